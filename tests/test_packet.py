"""The version-2 frame packet: layout, quantisers, clamping, CRC, and a decoder fuzz."""

from __future__ import annotations

import binascii

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facewire.protocol.packet import (
    FRAME_DTYPE,
    MAX_SERIAL,
    PACKET_BYTES,
    QUANTISERS,
    Flag,
    Frame,
    PacketError,
    crc16,
    decode,
    decode_frames,
    encode,
    encode_frames,
)

Q = {q.name: q for q in QUANTISERS}


def _in_range(name: str) -> st.SearchStrategy[float]:
    q = Q[name]
    return st.floats(q.lo, q.hi, allow_nan=False)


def _frames() -> st.SearchStrategy[Frame]:
    return st.builds(
        Frame,
        seq=st.integers(0, 65535),
        flags=st.sampled_from([Flag(0), Flag.FACE_PRESENT, Flag.FACE_PRESENT | Flag.HELD,
                               Flag.TRACKING_LOST | Flag.REACQUIRED | Flag.MIRRORED]),
        rotation=st.lists(_in_range("rotation"), min_size=3, max_size=3).map(
            lambda v: np.radians(np.array(v, np.float64)).astype(np.float32)),
        translation=st.tuples(_in_range("shift_xy"), _in_range("shift_xy"),
                              _in_range("shift_z")).map(lambda v: np.array(v, np.float32)),
        residuals=st.lists(_in_range("residuals"), min_size=18, max_size=18).map(
            lambda v: np.array(v, np.float32).reshape(9, 2)),
        q=st.lists(_in_range("q"), min_size=8, max_size=8).map(lambda v: np.array(v, np.float32)),
        serial=st.integers(0, MAX_SERIAL),
        shade=st.lists(_in_range("shade"), min_size=3, max_size=3).map(
            lambda v: np.array(v, np.float32)),
    )


def test_layout_is_43_bytes_under_12_kbps() -> None:
    assert PACKET_BYTES == 43
    bits = 4 + 8 + 16 + 11 + sum(q.count * q.bits for q in QUANTISERS) + 16
    assert bits == PACKET_BYTES * 8
    assert PACKET_BYTES * 8 * 30 < 12_000


def test_quantiser_targets() -> None:
    assert Q["residuals"].step <= 0.25 and Q["residuals"].lo <= -20 and Q["residuals"].hi >= 20
    assert Q["rotation"].step <= 0.1
    assert Q["q"].step <= 1 / 16 and Q["q"].hi >= 5  # six layers fit
    assert Q["shift_z"].hi < 0  # faces are in front of the camera (z < 0)
    # A face at the edge of a 53-degree view 2 m away is 1 m off the axis.
    assert Q["shift_xy"].lo <= -1000 and Q["shift_xy"].hi >= 1000


@settings(max_examples=300, deadline=None)
@given(_frames())
def test_round_trip_within_half_a_step(frame: Frame) -> None:
    out = decode(encode(frame))
    assert out.seq == frame.seq and out.serial == frame.serial
    assert out.flags == frame.flags  # in range: nothing clamped
    tol = 1e-4
    assert np.all(np.abs(np.degrees(out.rotation) - np.degrees(frame.rotation))
                  <= Q["rotation"].step / 2 + tol)
    assert np.all(np.abs(out.translation[:2] - frame.translation[:2])
                  <= Q["shift_xy"].step / 2 + tol)
    assert abs(out.translation[2] - frame.translation[2]) <= Q["shift_z"].step / 2 + tol
    assert np.all(np.abs(out.residuals - frame.residuals) <= Q["residuals"].step / 2 + tol)
    assert np.all(np.abs(out.q - frame.q) <= Q["q"].step / 2 + tol)
    assert np.all(np.abs(out.shade - frame.shade) <= Q["shade"].step / 2 + tol)


def test_serial_and_shade_round_trip_exactly() -> None:
    """The version-2 fields: the serial at its ends, each shade value on its own slot."""
    for serial in (0, 1, 1000, MAX_SERIAL):
        shade = np.array([-1.0, 0.5, 0.984375], np.float32)
        out = decode(encode(Frame(seq=9, serial=serial, shade=shade)))
        assert out.serial == serial and out.seq == 9
        np.testing.assert_array_equal(out.shade, shade)
        assert not out.flags & Flag.CLAMPED
    assert Q["shade"].lo == -1.0 and Q["shade"].hi == 0.984375 and Q["shade"].unit == "ln gain"
    with pytest.raises(ValueError, match="serial"):
        encode(Frame(serial=MAX_SERIAL + 1))  # a model version is never clamped


@pytest.mark.parametrize("name", [q.name for q in QUANTISERS])
def test_range_edges_are_exact(name: str) -> None:
    """The lowest and highest codes decode to exactly lo and hi, unflagged."""
    q = Q[name]
    for edge in (q.lo, q.hi):
        frame = Frame()
        value = np.float32(edge)
        if name == "rotation":
            frame.rotation[:] = np.radians(edge)
        elif name == "shift_xy":
            frame.translation[:2] = value
        elif name == "shift_z":
            frame.translation[2] = value
        elif name == "residuals":
            frame.residuals[:] = value
        elif name == "q":
            frame.q[:] = value
        else:
            frame.shade[:] = value
        out = decode(encode(frame))
        assert not out.flags & Flag.CLAMPED, (name, edge)
        got = {"rotation": np.degrees(out.rotation), "shift_xy": out.translation[:2],
               "shift_z": out.translation[2:], "residuals": out.residuals, "q": out.q,
               "shade": out.shade}[name]
        np.testing.assert_allclose(got, edge, atol=1e-4)


@pytest.mark.parametrize("name,beyond", [("residuals", 40.0), ("residuals", -40.0),
                                         ("q", 9.0), ("q", -1.0), ("shift_z", 10.0),
                                         ("shift_z", -5000.0), ("rotation", 170.0),
                                         ("shade", 1.5), ("shade", -2.0)])
def test_out_of_range_is_clamped_and_flagged(name: str, beyond: float) -> None:
    frame = Frame(flags=Flag.FACE_PRESENT)
    if name == "residuals":
        frame.residuals[3, 1] = beyond
    elif name == "q":
        frame.q[2] = beyond
    elif name == "shift_z":
        frame.translation[2] = beyond
    elif name == "shade":
        frame.shade[1] = beyond
    else:
        frame.rotation[1] = np.radians(beyond)
    packets, clamped = encode_frames(frame.to_record().reshape(1))
    assert clamped.tolist() == [1]
    out = decode(packets[0].tobytes())
    assert out.flags == Flag.FACE_PRESENT | Flag.CLAMPED
    q = Q[name]
    edge = q.hi if beyond > 0 else q.lo
    got = {"residuals": out.residuals[3, 1], "q": out.q[2], "shift_z": out.translation[2],
           "rotation": np.degrees(out.rotation[1]), "shade": out.shade[1]}[name]
    assert got == pytest.approx(edge, abs=1e-4)  # clamped to the edge, never wrapped


def test_nan_cannot_be_encoded() -> None:
    frame = Frame()
    frame.residuals[0, 0] = np.nan
    with pytest.raises(ValueError, match="residuals"):
        encode(frame)


def test_sequence_wraps() -> None:
    assert decode(encode(Frame(seq=65535))).seq == 65535
    assert decode(encode(Frame(seq=65536 + 7))).seq == 7


def test_vectorised_matches_single() -> None:
    rng = np.random.default_rng(1)
    frames = np.zeros(500, FRAME_DTYPE)
    frames["seq"] = rng.integers(0, 65536, 500)
    frames["flags"] = rng.integers(0, 64, 500)
    frames["rotation"] = rng.uniform(-1.5, 1.5, (500, 3))
    frames["translation"] = rng.uniform([-300, -300, -2500], [300, 300, 50], (500, 3))
    frames["residuals"] = rng.uniform(-40, 40, (500, 9, 2))
    frames["q"] = rng.uniform(-1, 9, (500, 8))
    frames["serial"] = rng.integers(0, 2048, 500)
    frames["shade"] = rng.uniform(-1.2, 1.2, (500, 3))
    packets, _ = encode_frames(frames)
    decoded, errors = decode_frames(packets)
    assert all(e is None for e in errors)
    for i in range(0, 500, 37):
        single = encode(Frame.from_record(frames[i]))
        assert single == packets[i].tobytes()
        one = decode(single)
        assert one.seq == decoded[i]["seq"] and one.flags == decoded[i]["flags"]
        assert one.serial == decoded[i]["serial"] == frames[i]["serial"]
        np.testing.assert_array_equal(one.residuals, decoded[i]["residuals"])
        np.testing.assert_array_equal(one.shade, decoded[i]["shade"])


def test_crc16_matches_binascii() -> None:
    rng = np.random.default_rng(2)
    rows = rng.integers(0, 256, (200, 41), dtype=np.uint8)  # > 16 rows: the table path
    expected = [binascii.crc_hqx(r.tobytes(), 0xFFFF) for r in rows]
    assert crc16(rows).tolist() == expected
    assert crc16(rows[:3]).tolist() == expected[:3]


@pytest.mark.parametrize("data,reason", [
    (b"", "size"), (b"\x20" * 42, "size"), (b"\x20" * 44, "size"), (b"\x10" * 39, "size"),
])
def test_wrong_size(data: bytes, reason: str) -> None:
    with pytest.raises(PacketError) as err:
        decode(data)
    assert err.value.reason == reason


def test_unknown_version_and_bad_crc() -> None:
    good = bytearray(encode(Frame(seq=3)))
    other = bytearray(good)
    other[0] = (1 << 4) | (other[0] & 0x0F)
    with pytest.raises(PacketError, match="packet version 1, expected 2") as err:
        decode(bytes(other))
    assert err.value.reason == "version"
    good[20] ^= 0x04
    with pytest.raises(PacketError) as err:
        decode(bytes(good))
    assert err.value.reason == "crc"


def test_reserved_bits_refused_even_with_valid_crc() -> None:
    raw = np.frombuffer(encode(Frame()), np.uint8).copy()
    raw[0] |= 0x08  # flag bit 7, reserved: flags are stream bits 4..11, MSB first
    body = raw[:41].reshape(1, -1)
    crc = int(crc16(body)[0])
    raw[41], raw[42] = crc >> 8, crc & 0xFF
    with pytest.raises(PacketError) as err:
        decode(raw.tobytes())
    assert err.value.reason == "reserved"


def _check_decodes_or_typed_error(data: bytes) -> None:
    try:
        frame = decode(data)
    except PacketError:
        return
    for a in (frame.rotation, frame.translation, frame.residuals, frame.q):
        assert np.isfinite(a).all()


def test_fuzz_random_and_mutated_inputs() -> None:
    """100k random and mutated byte strings: a frame or a PacketError, nothing else."""
    rng = np.random.default_rng(1234)
    valid = [encode(Frame(seq=i, flags=Flag.FACE_PRESENT,
                          residuals=rng.uniform(-30, 30, (9, 2)).astype(np.float32),
                          q=rng.uniform(0, 7, 8).astype(np.float32))) for i in range(64)]
    count = 0
    # Random strings of random length (mostly the right length, so they reach the CRC).
    lengths = np.where(rng.random(40_000) < 0.8, PACKET_BYTES, rng.integers(0, 80, 40_000))
    for n in lengths:
        _check_decodes_or_typed_error(rng.bytes(int(n)))
        count += 1
    # Mutations of valid packets: bit flips, byte overwrites, truncations, extensions.
    accepted_mutants = 0
    for i in range(60_000):
        data = bytearray(valid[i % len(valid)])
        kind = i % 4
        if kind == 0:
            for bit in rng.integers(0, PACKET_BYTES * 8, rng.integers(1, 4)):
                data[bit // 8] ^= 1 << (bit % 8)
        elif kind == 1:
            data[rng.integers(0, PACKET_BYTES)] = rng.integers(0, 256)
        elif kind == 2:
            del data[rng.integers(0, PACKET_BYTES):]
        else:
            data += rng.bytes(int(rng.integers(1, 5)))
        try:
            decode(bytes(data))
            accepted_mutants += bytes(data) not in valid
        except PacketError:
            pass
        count += 1
    assert count >= 100_000
    # CRC-16 catches all 1-3 bit errors and most byte overwrites; none should slip through.
    assert accepted_mutants == 0


def test_vectorised_decoder_fuzz() -> None:
    rng = np.random.default_rng(99)
    packets = rng.integers(0, 256, (100_000, PACKET_BYTES), dtype=np.uint8)
    frames, errors = decode_frames(packets)
    ok = np.array([e is None for e in errors])
    assert set(errors[~ok]) <= {"version", "crc", "reserved"}
    for name in ("rotation", "translation", "residuals", "q"):
        assert np.isfinite(frames[name]).all()
    assert not frames[~ok]["seq"].any()
