"""The frame packet, protocol version 2: 43 bytes per frame, 10.32 kbit/s at 30 Hz.

One fixed-size packet carries everything the receiver needs for one frame. The fields are
quantised to unsigned integer codes and packed most-significant bit first into one bit
stream, followed by a CRC:

=========  =====  ==========  ==================================  ========  =====================
field      count  bits each   range (decoded value)               step      unit
=========  =====  ==========  ==================================  ========  =====================
version    1      4           2                                   -         -
flags      1      8           bit set, see ``Flag``               -         -
seq        1      16          0 .. 65535, wraps                   1         -
serial     1      11          0 .. 2047                           1         -
rotation   3      11          -102.4 .. +102.3                    0.1       degree (rotation vector)
shift_xy   2      12          -1024.0 .. +1023.5                  0.5       mm
shift_z    1      11          -2147 .. -100                       1         mm
residuals  18     8           -32.0 .. +31.75                     0.25      mm
q          8      7           0 .. 7.9375                         1/16      layer
shade      3      7           -1.0 .. +0.984375                   1/64      ln gain
crc        1      16          CRC-16/CCITT-FALSE of bytes 0..40   -         -
=========  =====  ==========  ==================================  ========  =====================

Total 344 bits = 43 bytes. Worst-case quantisation error is half a step: 0.05 degree per
rotation-vector component (at most 0.087 degree of rotation), 0.25 mm in x and y, 0.5 mm in
depth, 0.125 mm per residual coordinate, 1/32 layer in Q, 1/128 in a shade coefficient (a
gain error of 0.8 %, below what a viewer sees in a face's brightness). The tracker's own noise
is about a pixel, roughly 1 mm at a typical webcam distance, so quantisation stays well below
it.

Meaning of the values (frames as in docs/DESIGN.md §2):

- ``rotation`` (3,): the head's rotation as a rotation vector (axis times angle, radians in
  the API, quantised in degrees) that maps model space into the camera frame. The camera
  frame is x right, y up, z toward the viewer (the camera looks along -z), so a frontal face
  has rotation (0, 0, 0).
- ``translation`` (3,): the model origin in that camera frame, mm; z < 0 in front of it.
- ``residuals`` (9, 2): the expression of the 9 non-rigid feature points (docs/DESIGN.md §2 order:
  19, 21, 22, 24, 48, 54, 51, 57, 8) as displacements on the model surface, mm, in each
  point's tangent frame (t1, t2) defined by the person model. A 2D image residual lifted onto
  the surface has two degrees of freedom; a third coordinate would carry no information.
- ``serial``: the version of the person model the frame's Q values refer to: 0 is the model
  file the Hello names, n the model after its first n updates (``models.update``).
- ``q`` (8,): the classified appearance of each region, in layers of its 3D texture; the
  region names travel in the Hello.
- ``shade`` (3,): the face's light relative to the model's texture as a natural-log gain
  field ``s0 + s1 x / 100 mm + s2 y / 100 mm`` over model space (x, y in mm): s0 at the
  face centre (the model origin's x and y), s1 per 100 mm to the model's +x, s2 per 100 mm to
  the model's +y. Zeros: the model's own light.

A value outside its range is clamped to the range and the packet gets ``Flag.CLAMPED``; it is
never wrapped. Decoding any byte string either returns a frame or raises ``PacketError``.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np

from facewire.protocol.errors import FacewireError

VERSION = 2
PACKET_BYTES = 43
N_RESIDUAL_POINTS = 9
N_REGIONS = 8
N_SHADE = 3
SEQ_MODULO = 1 << 16
SERIAL_BITS = 11
MAX_SERIAL = (1 << SERIAL_BITS) - 1


class Flag(IntFlag):
    """Per-frame state bits."""

    FACE_PRESENT = 1 << 0  # the tracker saw a face this frame
    TRACKING_LOST = 1 << 1  # the face was lost; pose and residuals are the last good ones
    CLAMPED = 1 << 2  # at least one value was outside its quantiser's range
    HELD = 1 << 3  # a heuristic held or decayed at least one feature point
    MIRRORED = 1 << 4  # at least one feature point was completed from its partner
    REACQUIRED = 1 << 5  # first frame after the face was found again


RESERVED_FLAGS = 0xFF & ~int(sum(Flag))


class PacketError(FacewireError, ValueError):
    """A byte string is not a valid packet of this protocol version.

    Attributes:
        reason: one of ``"size"``, ``"version"``, ``"crc"``, ``"reserved"``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Quantiser:
    """A uniform quantiser: code k in [0, 2**bits) decodes to ``lo + k * step``."""

    name: str
    count: int
    bits: int
    lo: float
    step: float
    unit: str

    @property
    def hi(self) -> float:
        """The largest decodable value."""
        return self.lo + ((1 << self.bits) - 1) * self.step


QUANTISERS: tuple[Quantiser, ...] = (
    Quantiser("rotation", 3, 11, -102.4, 0.1, "degree"),
    Quantiser("shift_xy", 2, 12, -1024.0, 0.5, "mm"),
    Quantiser("shift_z", 1, 11, -2147.0, 1.0, "mm"),
    Quantiser("residuals", 2 * N_RESIDUAL_POINTS, 8, -32.0, 0.25, "mm"),
    Quantiser("q", N_REGIONS, 7, 0.0, 1.0 / 16.0, "layer"),
    Quantiser("shade", N_SHADE, 7, -1.0, 1.0 / 64.0, "ln gain"),
)

# The bit layout: (name, count, bits) in stream order, CRC excluded, flattened into slots.
_LAYOUT: tuple[tuple[str, int, int], ...] = (
    ("version", 1, 4), ("flags", 1, 8), ("seq", 1, 16), ("serial", 1, SERIAL_BITS),
    *((q.name, q.count, q.bits) for q in QUANTISERS),
)
_WIDTHS = np.array([bits for _, count, bits in _LAYOUT for _ in range(count)])
_SLOT: dict[str, slice] = {}  # name -> slice of slots
for _name, _count, _ in _LAYOUT:
    _start = sum(s.stop - s.start for s in _SLOT.values())
    _SLOT[_name] = slice(_start, _start + _count)
# A slot of at most 16 bits starting at bit offset o (0..7) of byte b lies in bytes b..b+2:
# read as one 24-bit big-endian word w, the slot is (w >> (24 - o - width)) & (2**width - 1).
_STARTS = np.concatenate([[0], np.cumsum(_WIDTHS)[:-1]])
_BYTES3 = _STARTS[:, None] // 8 + np.arange(3)  # (slots, 3) byte indices, at most 42
_SHIFT24 = 24 - _STARTS % 8 - _WIDTHS
_MASK = (1 << _WIDTHS) - 1
# Packing sums each slot's three byte contributions into their bytes (the slots' bits are
# disjoint, so the sum is their OR): the contributions sorted by byte, summed per byte.
_BY_BYTE = np.argsort(_BYTES3.ravel(), kind="stable")
_BYTE_STARTS = np.flatnonzero(np.diff(_BYTES3.ravel()[_BY_BYTE], prepend=-1))
_BLOCK = 1 << 14  # rows per step of the vectorised coders: bounded temporary memory
_BODY_BYTES = PACKET_BYTES - 2
# The same slots for ``decode``: (shift from the least significant bit of the body, mask).
_FROM_LSB = [(int(8 * _BODY_BYTES - start - width), (1 << int(width)) - 1)
             for start, width in zip(_STARTS, _WIDTHS)]
assert int(_WIDTHS.sum()) == 8 * _BODY_BYTES and int(_WIDTHS.max()) <= 16
assert np.array_equal(_BYTES3.ravel()[_BY_BYTE][_BYTE_STARTS],
                      np.arange(PACKET_BYTES))  # every byte is summed, in order

FRAME_DTYPE = np.dtype([
    ("seq", np.uint16),
    ("flags", np.uint8),
    ("serial", np.uint16),
    ("rotation", np.float32, (3,)),
    ("translation", np.float32, (3,)),
    ("residuals", np.float32, (N_RESIDUAL_POINTS, 2)),
    ("q", np.float32, (N_REGIONS,)),
    ("shade", np.float32, (N_SHADE,)),
])
"""One frame as a numpy record; arrays of these are what logs and benchmarks work on."""


@dataclass
class Frame:
    """One frame's content, decoded (or to be encoded).

    Attributes:
        seq: sequence number, 0..65535 (wraps).
        flags: ``Flag`` bits.
        rotation: (3,) float32 rotation vector, radians, model -> camera.
        translation: (3,) float32 model origin in the camera frame, mm.
        residuals: (9, 2) float32 tangent-frame displacements of the non-rigid points, mm.
        q: (8,) float32 region appearance values, layers.
        serial: the model version the q values refer to, 0..2047 (0: the model file).
        shade: (3,) float32 log-gain field of the face's light (s0, s1, s2), ln gain at the
            face centre, per 100 mm to the model's +x, per 100 mm to its +y.
    """

    seq: int = 0
    flags: Flag = Flag(0)
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    translation: np.ndarray = field(
        default_factory=lambda: np.array([0.0, 0.0, -600.0], np.float32))
    residuals: np.ndarray = field(
        default_factory=lambda: np.zeros((N_RESIDUAL_POINTS, 2), np.float32))
    q: np.ndarray = field(default_factory=lambda: np.zeros(N_REGIONS, np.float32))
    serial: int = 0
    shade: np.ndarray = field(default_factory=lambda: np.zeros(N_SHADE, np.float32))

    def to_record(self) -> np.ndarray:
        """This frame as a shape-() record of ``FRAME_DTYPE``."""
        rec = np.zeros((), FRAME_DTYPE)
        rec["seq"] = self.seq % SEQ_MODULO
        rec["flags"] = int(self.flags)
        rec["rotation"] = self.rotation
        rec["translation"] = self.translation
        rec["residuals"] = self.residuals
        rec["q"] = self.q
        rec["serial"] = self.serial
        rec["shade"] = self.shade
        return rec

    @classmethod
    def from_record(cls, rec: np.ndarray) -> Frame:
        """The frame held in one ``FRAME_DTYPE`` record."""
        return cls(int(rec["seq"]), Flag(int(rec["flags"])), rec["rotation"].copy(),
                   rec["translation"].copy(), rec["residuals"].copy(), rec["q"].copy(),
                   int(rec["serial"]), rec["shade"].copy())


_QUANTISED = slice(_SLOT[QUANTISERS[0].name].start, _SLOT[QUANTISERS[-1].name].stop)
_LO = np.concatenate([np.full(q.count, q.lo) for q in QUANTISERS])
_STEP = np.concatenate([np.full(q.count, q.step) for q in QUANTISERS])
_TOP = np.concatenate([np.full(q.count, (1 << q.bits) - 1) for q in QUANTISERS])
_NAME = np.concatenate([[q.name] * q.count for q in QUANTISERS])
# The quantised values' columns (``_values``' order) of the fields after the pose.
_RESIDUALS = slice(6, 6 + 2 * N_RESIDUAL_POINTS)
_Q = slice(_RESIDUALS.stop, _RESIDUALS.stop + N_REGIONS)
_SHADE = slice(_Q.stop, _Q.stop + N_SHADE)


def _values(frames: np.ndarray) -> np.ndarray:
    """(N, 36) float64 values in quantiser units, in slot order."""
    n = len(frames)
    return np.concatenate([
        np.degrees(frames["rotation"].astype(np.float64)),
        frames["translation"].astype(np.float64),
        frames["residuals"].astype(np.float64).reshape(n, 2 * N_RESIDUAL_POINTS),
        frames["q"].astype(np.float64),
        frames["shade"].astype(np.float64),
    ], axis=1)


def encode_frames(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Encode frames into packets (vectorised, in blocks of ``_BLOCK`` rows so that the
    temporary memory stays bounded for any N), clamping out-of-range values.

    Args:
        frames: (N,) array of ``FRAME_DTYPE``; all values finite; ``serial`` at most
            ``MAX_SERIAL``.

    Returns:
        packets: (N, 43) uint8, one packet per row; ``Flag.CLAMPED`` set where clamped.
        clamped: (N,) int64, the number of clamped values per frame (never silent).

    Raises:
        ValueError: a value is NaN or infinite, or a serial is beyond ``MAX_SERIAL`` (naming
            the field): a serial is a model version, never clamped into another one.
    """
    frames = np.asarray(frames, FRAME_DTYPE).reshape(-1)
    if len(frames) and int(frames["serial"].max()) > MAX_SERIAL:
        raise ValueError(f"serial: {int(frames['serial'].max())} is beyond {MAX_SERIAL}")
    n = len(frames)
    packets = np.empty((n, PACKET_BYTES), np.uint8)
    clamped = np.empty(n, np.int64)
    for lo in range(0, n, _BLOCK):
        packets[lo:lo + _BLOCK], clamped[lo:lo + _BLOCK] = _encode_block(frames[lo:lo + _BLOCK])
    return packets, clamped


def _encode_block(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    values = _values(frames)
    finite = np.isfinite(values)
    if not finite.all():
        raise ValueError(f"{_NAME[np.argmin(finite.all(axis=0))]}: cannot encode NaN or infinity")
    k = np.rint((values - _LO) / _STEP)
    outside = (k < 0) | (k > _TOP)
    clamped = outside.sum(axis=1)
    n = len(frames)
    flags = frames["flags"].astype(np.int64) & ~RESERVED_FLAGS
    flags[clamped > 0] |= Flag.CLAMPED
    slots = np.zeros((n, len(_WIDTHS)), np.int64)
    slots[:, _SLOT["version"]] = VERSION
    slots[:, _SLOT["flags"]] = flags[:, None]
    slots[:, _SLOT["seq"]] = frames["seq"][:, None]
    slots[:, _SLOT["serial"]] = frames["serial"][:, None]
    slots[:, _QUANTISED] = np.clip(k, 0, _TOP)
    word = slots << _SHIFT24
    parts = np.stack([word >> 16, word >> 8, word], axis=2).reshape(n, -1) & 0xFF
    body = np.add.reduceat(parts[:, _BY_BYTE], _BYTE_STARTS, axis=1)[:, :_BODY_BYTES]
    crc = crc16(body.astype(np.uint8))
    packets = np.concatenate([body, (crc >> 8)[:, None], (crc & 0xFF)[:, None]], axis=1)
    return packets.astype(np.uint8), clamped


def decode_frames(packets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decode packets (vectorised, in blocks of ``_BLOCK`` rows: bounded temporary memory for
    a log of any length), validating each.

    Args:
        packets: (N, 43) uint8.

    Returns:
        frames: (N,) ``FRAME_DTYPE``; rows that failed validation are zero.
        errors: (N,) object array, None for a valid packet, else the ``PacketError`` reason.
    """
    packets = np.asarray(packets)
    if packets.ndim != 2 or packets.shape[1] != PACKET_BYTES or packets.dtype != np.uint8:
        raise ValueError(f"packets: expected (N, {PACKET_BYTES}) uint8, "
                         f"got {packets.shape} {packets.dtype}")
    n = len(packets)
    frames = np.zeros(n, FRAME_DTYPE)
    errors = np.full(n, None, object)
    for lo in range(0, n, _BLOCK):
        _decode_block(packets[lo:lo + _BLOCK], frames[lo:lo + _BLOCK], errors[lo:lo + _BLOCK])
    return frames, errors


def _decode_block(packets: np.ndarray, frames: np.ndarray, errors: np.ndarray) -> None:
    """Decode rows of packets into the views ``frames`` and ``errors`` (zeros and None)."""
    b = packets[:, _BYTES3].astype(np.int32)
    slots = (((b[..., 0] << 16) | (b[..., 1] << 8) | b[..., 2]) >> _SHIFT24) & _MASK
    crc = packets[:, -2].astype(np.int64) << 8 | packets[:, -1]
    reserved = slots[:, _SLOT["flags"].start] & RESERVED_FLAGS
    errors[reserved != 0] = "reserved"
    errors[crc != crc16(packets[:, :_BODY_BYTES])] = "crc"
    errors[slots[:, _SLOT["version"].start] != VERSION] = "version"
    ok = errors == None  # noqa: E711 (elementwise on an object array)
    n = int(ok.sum())
    slots = slots[ok]
    value = _LO + slots[:, _QUANTISED] * _STEP
    good = frames[ok]
    good["seq"] = slots[:, _SLOT["seq"].start]
    good["flags"] = slots[:, _SLOT["flags"].start]
    good["serial"] = slots[:, _SLOT["serial"].start]
    good["rotation"] = np.radians(value[:, 0:3])
    good["translation"] = value[:, 3:6]
    good["residuals"] = value[:, _RESIDUALS].reshape(n, N_RESIDUAL_POINTS, 2)
    good["q"] = value[:, _Q]
    good["shade"] = value[:, _SHADE]
    frames[ok] = good


def encode(frame: Frame) -> bytes:
    """Encode one frame into a 43-byte packet (values out of range are clamped and flagged)."""
    packets, _ = encode_frames(frame.to_record().reshape(1))
    return packets[0].tobytes()


def decode(data: bytes) -> Frame:
    """Decode one packet: the values ``decode_frames`` gives, read from the body as one
    328-bit integer (about a quarter of the vectorised path's time for a single packet,
    which is mostly numpy's per-call overhead).

    Raises:
        PacketError: wrong size, unknown version, bad CRC or reserved bits set.
    """
    if len(data) != PACKET_BYTES:
        raise PacketError("size", f"packet has {len(data)} bytes, expected {PACKET_BYTES}")
    if data[0] >> 4 != VERSION:
        raise PacketError("version", f"packet version {data[0] >> 4}, expected {VERSION}")
    if binascii.crc_hqx(data[:_BODY_BYTES], 0xFFFF) != int.from_bytes(data[-2:], "big"):
        raise PacketError("crc", "packet CRC mismatch")
    body = int.from_bytes(data[:_BODY_BYTES], "big")
    slots = [(body >> shift) & mask for shift, mask in _FROM_LSB]
    flags = slots[_SLOT["flags"].start]
    if flags & RESERVED_FLAGS:
        raise PacketError("reserved", "packet rejected: reserved bits set")
    value = _LO + np.array(slots[_QUANTISED], np.int64) * _STEP
    return Frame(slots[_SLOT["seq"].start], Flag(flags),
                 np.radians(value[0:3]).astype(np.float32), value[3:6].astype(np.float32),
                 value[_RESIDUALS].astype(np.float32).reshape(N_RESIDUAL_POINTS, 2),
                 value[_Q].astype(np.float32), slots[_SLOT["serial"].start],
                 value[_SHADE].astype(np.float32))


def quantiser_table() -> list[dict[str, object]]:
    """The quantisers as plain data, for the Hello."""
    return [{"name": q.name, "count": q.count, "bits": q.bits, "lo": q.lo, "step": q.step,
             "unit": q.unit} for q in QUANTISERS]


def _crc_table() -> np.ndarray:
    table = np.zeros(256, np.int64)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = (crc << 1) ^ 0x1021 if crc & 0x8000 else crc << 1
        table[byte] = crc & 0xFFFF
    return table


_CRC_TABLE = _crc_table()


def crc16(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of each row.

    Args:
        rows: (N, L) uint8.

    Returns:
        (N,) int64 CRCs, equal to ``binascii.crc_hqx(row, 0xFFFF)``.
    """
    if len(rows) <= 16:  # the per-row C routine wins for a handful of rows
        return np.array([binascii.crc_hqx(r.tobytes(), 0xFFFF) for r in rows], np.int64)
    crc = np.full(len(rows), 0xFFFF, np.int64)
    for col in rows.T.astype(np.int64):
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[((crc >> 8) ^ col) & 0xFF]
    return crc
