"""Tests for receiver.playout: the playout buffer plays every slot once, in order, conceals
lost ones (hold, then a smooth ease to neutral), eases on face loss, drops duplicates, late
and corrupt packets with exact counts, plays through the 16-bit wrap and resyncs on a sender
restart. Packets are real ``protocol.packet.encode`` output; the clock is driven by hand:
at tick k the packets scheduled for k arrive (time k / RATE), then ``pop`` is called once."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facewire.models.geometry import rotation_matrix
from facewire.protocol.packet import (
    PACKET_BYTES,
    QUANTISERS,
    SEQ_MODULO,
    Flag,
    Frame,
    PacketError,
    decode,
    encode,
)
from facewire.receiver.playout import (
    MIN_JITTER_PACKETS,
    STATUSES,
    FrameState,
    Playout,
    replay_states,
)

RATE = 30.0
DEPTH = 3
# Half steps of the quantisers: rotation (degree), shift_xy, shift_z, residuals (mm), q (layer).
ROT_DEG, SHIFT_XY, SHIFT_Z, RESIDUAL, Q_STEP, _ = (q.step / 2 for q in QUANTISERS)
FACE = Flag.FACE_PRESENT
HELD = ("held", "easing", "neutral")
PLAYED = ("received", "face_lost")


def make_frame(seq: int, rng: np.random.Generator, flags: Flag = FACE,
               q: float | None = None) -> Frame:
    """A frame with random in-range content; ``q`` fills all Q slots when given (a stream mark)."""
    return Frame(
        seq=seq % SEQ_MODULO, flags=flags,
        rotation=rng.uniform(-0.5, 0.5, 3).astype(np.float32),
        translation=np.array([rng.uniform(-100, 100), rng.uniform(-100, 100),
                              rng.uniform(-1500, -300)], np.float32),
        residuals=rng.uniform(-20, 20, (9, 2)).astype(np.float32),
        q=(rng.uniform(0.5, 7, 8) if q is None else np.full(8, q)).astype(np.float32),
        serial=int(rng.integers(0, 2048)), shade=rng.uniform(-1, 0.98, 3).astype(np.float32))


def drive(playout: Playout, schedule: dict[int, list[bytes]], ticks: int) -> list[FrameState]:
    """Tick k = 0 .. ticks-1: push ``schedule[k]`` at time k / RATE, then pop once."""
    states = []
    for k in range(ticks):
        for data in schedule.get(k, []):
            playout.push(data, k / RATE)
        states.append(playout.pop())
    return states


def assert_plays(state: FrameState, data: bytes) -> None:
    """The state is exactly the decoded packet (rotation as OpenCV's Rodrigues of it)."""
    frame = decode(data)
    assert state.seq == frame.seq and state.flags == frame.flags
    np.testing.assert_allclose(state.rotation,
                               cv2.Rodrigues(frame.rotation.astype(np.float64))[0], atol=1e-12)
    np.testing.assert_array_equal(state.translation, frame.translation.astype(np.float64))
    np.testing.assert_array_equal(state.residuals, frame.residuals)
    np.testing.assert_array_equal(state.q, frame.q)
    assert state.serial == frame.serial
    np.testing.assert_array_equal(state.shade, frame.shade)


def ledger(playout: Playout, states: list[FrameState]) -> None:
    """Every valid packet is accounted for exactly once (none pending at the end)."""
    assert {st.status for st in states} <= set(STATUSES)
    s = playout.stats
    played = sum(st.status in PLAYED for st in states)
    assert s["received"] == played + s["duplicate"] + s["late"] + s["stray"] + s["discarded"]
    assert s["concealed"] == sum(st.status in HELD and st.seq is not None for st in states)


def test_in_order_stream_plays_every_packet_after_depth_pops() -> None:
    rng = np.random.default_rng(1)
    frames = [make_frame(s, rng) for s in range(100)]
    packets = [encode(f) for f in frames]
    playout = Playout(RATE, depth=DEPTH)
    assert playout.latency_s == pytest.approx(DEPTH / RATE)
    states = drive(playout, {k: [p] for k, p in enumerate(packets)}, 100 + DEPTH)
    # the first DEPTH pops play no slot; packet k (pushed at tick k) plays at tick k + DEPTH
    assert [st.seq for st in states[:DEPTH]] == [None] * DEPTH
    assert all(st.status == "neutral" for st in states[:DEPTH])
    for k, (frame, data) in enumerate(zip(frames, packets)):
        st = states[k + DEPTH]
        assert st.status == "received" and st.weight == 1.0 and st.arrival_s == k / RATE
        assert_plays(st, data)
        # and equals the sent frame to quantisation
        err = cv2.Rodrigues(st.rotation)[0].ravel() - frame.rotation
        assert np.degrees(np.abs(err)).max() <= ROT_DEG + 1e-3
        assert np.abs(st.translation - frame.translation)[:2].max() <= SHIFT_XY + 1e-4
        assert abs(st.translation[2] - frame.translation[2]) <= SHIFT_Z + 1e-4
        assert np.abs(st.residuals - frame.residuals).max() <= RESIDUAL + 1e-5
        assert np.abs(st.q - frame.q).max() <= Q_STEP + 1e-5
    assert playout.stats == dict(received=100, corrupt=0, duplicate=0, late=0, stray=0,
                                 discarded=0, concealed=0, skipped=0, restarts=0)


def test_before_any_packet_the_state_is_neutral_at_the_default_pose() -> None:
    playout = Playout(RATE)
    st = playout.pop()
    default = Frame()
    assert st.seq is None and st.status == "neutral" and st.weight == 0.0
    np.testing.assert_array_equal(st.rotation, np.eye(3))
    np.testing.assert_array_equal(st.translation, default.translation)
    assert not st.residuals.any() and not st.q.any() and st.flags == Flag(0)
    with pytest.raises(ValueError):  # the arrays are read-only
        st.residuals[0, 0] = 1.0


def test_serial_and_shade_are_the_last_face_present_packets() -> None:
    """A received packet's serial and shade play as they are; a lost slot and a packet with
    the face lost keep those of the last face-present packet (never eased)."""
    shades = [np.array([0.25, -0.5, 0.125], np.float32), np.array([-1, 0, 0.5], np.float32)]
    frames = [Frame(seq=0, flags=FACE, serial=3, shade=shades[0]),
              Frame(seq=1, flags=FACE, serial=4, shade=shades[1]),
              Frame(seq=3, flags=Flag.TRACKING_LOST, serial=5, shade=-shades[1])]
    playout = Playout(RATE, depth=1, hold_s=0.0, ease_s=0.0)
    states = drive(playout, {k: [encode(f)] for k, f in zip((0, 1, 3), frames)}, 5)
    assert [st.status for st in states] == ["neutral", "received", "received", "neutral",
                                           "face_lost"]
    assert [st.serial for st in states] == [0, 3, 4, 4, 4]
    for st, want in zip(states, [np.zeros(3), shades[0], *shades[1:] * 3]):
        np.testing.assert_array_equal(st.shade, want)


def test_replay_with_loss_and_reordering_yields_every_slot_once() -> None:
    rng = np.random.default_rng(2)
    n, first = 600, 65300  # crosses the 16-bit wrap
    packets = [encode(make_frame(first + k, rng)) for k in range(n)]
    interior = np.arange(1, n - 1)
    removed = set(rng.choice(interior, int(0.3 * n), replace=False).tolist())
    kept = [k for k in range(n) if k not in removed]
    times = {k: k / RATE for k in kept}
    reordered = rng.choice(kept[1:-1], int(0.05 * len(kept)), replace=False)
    for k in reordered:  # arrives after its successor, within the buffer's depth
        times[k] += 1.5 / RATE
    playout = Playout(RATE, depth=DEPTH)
    states = list(replay_states([packets[k] for k in kept], [times[k] for k in kept], RATE,
                                playout=playout))
    assert [st.seq for st in states] == [(first + k) % SEQ_MODULO for k in range(n)]
    for k, st in enumerate(states):
        if k in removed:
            assert st.status in HELD and st.flags == Flag(0) and st.arrival_s is None
        else:
            assert st.status == "received"
            assert_plays(st, packets[k])
    assert playout.stats == dict(received=len(kept), corrupt=0, duplicate=0, late=0, stray=0,
                                 discarded=0, concealed=len(removed), skipped=0, restarts=0)
    # the same log as an (N, 39) array, as protocol.log reads it, plays the same
    again = list(replay_states(np.array([np.frombuffer(packets[k], np.uint8) for k in kept]),
                               np.array([times[k] for k in kept]), RATE))
    assert [(a.seq, a.status) for a in again] == [(b.seq, b.status) for b in states]


def assert_eases_in_and_out(weights: np.ndarray) -> None:
    """A smooth ease: the weight leaves 1 and reaches 0 gently (first and last steps small
    against the largest), not with a linear ramp's constant steps."""
    drops = -np.diff(weights)
    drops = drops[drops > 0]
    assert len(drops) >= 5
    assert drops[0] < 0.3 * drops.max() and drops[-1] < 0.3 * drops.max()


def test_hold_then_ease_to_neutral() -> None:
    rng = np.random.default_rng(3)
    hold_s, ease_s, gap = 0.2, 0.5, 40
    assert gap / RATE > hold_s + ease_s
    seqs = [*range(30), *range(30 + gap, 30 + gap + 10)]
    packets = {s: encode(make_frame(s, rng)) for s in seqs}
    playout = Playout(RATE, depth=DEPTH, hold_s=hold_s, ease_s=ease_s)
    states = drive(playout, {s: [packets[s]] for s in seqs}, seqs[-1] + 1 + DEPTH)
    by_seq = {st.seq: st for st in states if st.seq is not None}
    last = decode(packets[29])
    gap_states = [by_seq[30 + j] for j in range(gap)]  # j + 1 slots after the last received
    weights = np.array([st.weight for st in gap_states])
    for j, st in enumerate(gap_states):
        elapsed = (j + 1) / RATE
        assert st.status in HELD and st.flags == Flag(0)
        # the pose is held, never eased
        np.testing.assert_allclose(st.rotation, rotation_matrix(last.rotation), atol=1e-12)
        np.testing.assert_array_equal(st.translation, last.translation.astype(np.float64))
        # the expression is weight x the last one
        np.testing.assert_allclose(st.residuals, st.weight * last.residuals, atol=1e-5)
        np.testing.assert_allclose(st.q, st.weight * last.q, atol=1e-5)
        if elapsed <= hold_s + 1e-9:
            assert st.status == "held" and st.weight == 1.0
            np.testing.assert_array_equal(st.residuals, last.residuals)
        else:
            assert st.weight < 1.0
        if elapsed >= hold_s + ease_s - 1e-9:
            assert st.status == "neutral" and st.weight == 0.0
            assert not st.residuals.any() and not st.q.any()
        elif elapsed > hold_s:
            assert st.status == "easing" and 0.0 < st.weight < 1.0
    easing = (np.arange(1, gap + 1) / RATE > hold_s) & (weights > 0)
    assert easing.sum() >= ease_s * RATE - 1  # the ease takes ease_s, not one jump
    steps = np.diff(weights)
    assert (steps <= 0).all()  # monotonic ...
    assert (np.diff(weights[easing]) < 0).all()  # ... strictly while easing ...
    assert -steps.min() <= 1.5 / (ease_s * RATE) + 1e-9  # ... and smooth (smoothstep slope)
    assert_eases_in_and_out(weights)
    norms = [np.linalg.norm(st.residuals) + np.linalg.norm(st.q) for st in gap_states]
    assert (np.diff(norms) <= 1e-6).all()
    # the stream comes back at full weight
    back = by_seq[30 + gap]
    assert back.status == "received" and back.weight == 1.0
    assert_plays(back, packets[30 + gap])
    assert playout.stats["concealed"] == gap
    ledger(playout, states)


def test_q_eases_to_the_models_rest_values() -> None:
    rng = np.random.default_rng(11)
    rest = np.array([0.5, 1.0, 2.0, 0.0, 3.5, 1.25, 2.5, 0.0], np.float32)
    seqs = [*range(20), *range(60, 70)]
    packets = {s: encode(make_frame(s, rng)) for s in seqs}
    playout = Playout(RATE, depth=DEPTH, hold_s=0.1, ease_s=0.3, rest_q=rest)
    assert np.array_equal(playout.pop().q, rest)  # before any packet: the face at rest
    states = drive(playout, {s: [packets[s]] for s in seqs}, seqs[-1] + 1 + DEPTH)
    by_seq = {st.seq: st for st in states if st.seq is not None}
    last = decode(packets[19])
    for s in range(20, 60):
        st = by_seq[s]
        np.testing.assert_allclose(st.q, rest + st.weight * (last.q - rest), atol=1e-5)
    assert by_seq[59].status == "neutral" and np.array_equal(by_seq[59].q, rest)
    np.testing.assert_allclose(by_seq[60].q, decode(packets[60]).q, atol=1e-6)
    with pytest.raises(ValueError, match="rest_q"):
        Playout(RATE, rest_q=np.zeros(7))


@pytest.mark.parametrize("lost_flags", [Flag(0), Flag.FACE_PRESENT | Flag.TRACKING_LOST,
                                        Flag.TRACKING_LOST | Flag.HELD],
                         ids=["no_face", "face_but_tracking_lost", "tracking_lost_held"])
def test_face_lost_packets_ease_to_neutral_and_keep_their_pose(lost_flags: Flag) -> None:
    rng = np.random.default_rng(4)
    ease_s = 0.4
    flags = {s: FACE if s < 20 or s >= 50 else lost_flags for s in range(60)}
    packets = {s: encode(make_frame(s, rng, flags[s])) for s in range(60)}
    playout = Playout(RATE, depth=DEPTH, hold_s=0.2, ease_s=ease_s)
    states = drive(playout, {s: [packets[s]] for s in range(60)}, 60 + DEPTH)
    by_seq = {st.seq: st for st in states if st.seq is not None}
    face = decode(packets[19])
    weights = []
    for s in range(20, 50):
        st, sent = by_seq[s], decode(packets[s])
        assert st.status == "face_lost" and st.flags == sent.flags
        # the face-lost packet's pose is used, its expression is not
        np.testing.assert_allclose(st.rotation, rotation_matrix(sent.rotation), atol=1e-12)
        np.testing.assert_array_equal(st.translation, sent.translation.astype(np.float64))
        np.testing.assert_allclose(st.residuals, st.weight * face.residuals, atol=1e-5)
        np.testing.assert_allclose(st.q, st.weight * face.q, atol=1e-5)
        weights.append(st.weight)
        if (s - 19) / RATE >= ease_s - 1e-9:
            assert st.weight == 0.0 and not st.residuals.any() and not st.q.any()
    weights = np.array(weights)
    assert weights[0] < 1.0  # no hold on face loss
    positive = weights > 0
    assert positive.sum() >= ease_s * RATE - 1 and (np.diff(weights[positive]) < 0).all()
    assert (np.diff(weights) <= 0).all()
    assert_eases_in_and_out(np.concatenate([[1.0], weights]))
    assert by_seq[50].status == "received" and by_seq[50].weight == 1.0
    assert_plays(by_seq[50], packets[50])
    assert playout.stats["concealed"] == 0


def test_duplicates_and_late_packets_are_counted_and_dropped() -> None:
    rng = np.random.default_rng(5)
    packets = {s: encode(make_frame(s, rng)) for s in range(60)}
    schedule = {k: [packets[k]] for k in range(60) if k not in (20, 40)}
    # a duplicate while buffered, with other content: the first copy wins
    rogue = decode(packets[10])
    rogue.q = np.zeros(8, np.float32)
    schedule[10] = [packets[10], encode(rogue), packets[10]]
    schedule[30] += [packets[5]]  # a duplicate of a slot played long ago
    # 20 and 40 arrive after their slots (played at tick seq + DEPTH) were concealed
    schedule[20 + DEPTH + 2] += [packets[20]]
    schedule[40 + DEPTH + 1] += [packets[40], packets[40]]  # late, then a duplicate of it
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 60 + DEPTH)
    by_seq = {st.seq: st for st in states if st.seq is not None}
    assert sorted(by_seq) == list(range(60))
    for s in range(60):
        if s in (20, 40):
            assert by_seq[s].status == "held"
        else:
            assert_plays(by_seq[s], packets[s])
    assert playout.stats == dict(received=60 + 2 + 1 + 1, corrupt=0, duplicate=2 + 1 + 1,
                                 late=2, stray=0, discarded=0, concealed=2, skipped=0,
                                 restarts=0)
    ledger(playout, states)


def mutants(valid: list[bytes], count: int, rng: np.random.Generator) -> list[object]:
    """``count`` damaged packets: random bytes (any length), truncated or extended valid ones,
    and 1-3 bit flips of valid ones (a CRC-16 with Hamming distance 4 catches all of those)."""
    out: list[object] = []
    for k in range(count):
        base = np.frombuffer(valid[rng.integers(len(valid))], np.uint8)
        kind = k % 3
        if kind == 0:
            size = int(rng.choice([0, 1, PACKET_BYTES, PACKET_BYTES, 40, 200]))
            out.append(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
        elif kind == 1:
            cut = int(rng.integers(0, 2 * PACKET_BYTES))
            cut += cut == PACKET_BYTES
            tail = rng.integers(0, 256, max(0, cut - PACKET_BYTES), dtype=np.uint8)
            out.append(np.concatenate([base[:cut], tail]).tobytes())
        else:
            bits = np.unpackbits(base)
            flip = rng.choice(8 * PACKET_BYTES, int(rng.integers(1, 4)), replace=False)
            bits[flip] ^= 1
            out.append(np.packbits(bits).tobytes())
    return out


def test_corrupt_packets_are_counted_and_never_disturb_the_stream() -> None:
    rng = np.random.default_rng(6)
    packets = [encode(make_frame(s, rng)) for s in range(100)]
    bad = mutants(packets, 10_000, rng)
    bad += [None, "not bytes", 12345, 1.5, b"", bytes(100_000), [1, 2, 3],
            np.frombuffer(packets[0], np.uint8)]  # an array is not bytes either

    def rejected(data: object) -> bool:
        """What the protocol rejects, and anything that is not bytes-like."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            return True
        try:
            decode(data)
        except PacketError:
            return True
        return False

    expected_corrupt = sum(rejected(b) for b in bad)
    assert expected_corrupt == len(bad)  # this seed's random bytes never pass validation
    clean = drive(Playout(RATE), {k: [p] for k, p in enumerate(packets)}, 100 + DEPTH)
    playout = Playout(RATE)
    chunks = np.array_split(np.arange(len(bad)), 100)
    schedule = {k: [bad[i] for i in chunks[k][:50]] + [p] + [bad[i] for i in chunks[k][50:]]
                for k, p in enumerate(packets)}
    states = drive(playout, schedule, 100 + DEPTH)
    assert playout.stats["corrupt"] == expected_corrupt
    assert playout.stats["received"] == 100
    assert [(s.seq, s.status) for s in states] == [(s.seq, s.status) for s in clean]
    for st, data in zip(states[DEPTH:], packets):
        assert_plays(st, data)
    # bytes-like containers of a valid packet are accepted
    playout = Playout(RATE)
    playout.push(bytearray(packets[0]), 0.0)
    playout.push(memoryview(packets[1]), 0.0)
    assert playout.stats["received"] == 2 and playout.stats["corrupt"] == 0


def test_bad_arguments_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        Playout(0.0)
    with pytest.raises(ValueError, match="depth"):
        Playout(RATE, depth=0)
    with pytest.raises(ValueError, match="ease_s"):
        Playout(RATE, ease_s=float("nan"))
    with pytest.raises(ValueError, match="arrival_s"):
        Playout(RATE).push(b"", float("inf"))
    with pytest.raises(ValueError, match="times"):
        replay_states([b"", b""], [0.0], RATE)


def test_a_stream_whose_first_packet_arrives_second_starts_at_it() -> None:
    rng = np.random.default_rng(14)
    packets = {s: encode(make_frame(s, rng)) for s in range(500, 520)}
    schedule = {k: [packets[500 + k]] for k in range(20)}
    schedule[0], schedule[1] = schedule[1], schedule[0]  # 501 arrives, then 500
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 20 + DEPTH)
    assert [st.seq for st in states[DEPTH:]] == list(range(500, 520))
    for st in states[DEPTH:]:
        assert_plays(st, packets[st.seq])
    assert playout.stats["late"] == 0 and playout.stats["concealed"] == 0


@pytest.mark.parametrize("swap", [False, True])
def test_sequence_wraps_without_a_gap(swap: bool) -> None:
    rng = np.random.default_rng(7)
    seqs = [(65520 + k) % SEQ_MODULO for k in range(40)]
    packets = [encode(make_frame(s, rng)) for s in seqs]
    schedule = {k: [p] for k, p in enumerate(packets)}
    if swap:  # 0 arrives before 65535
        schedule[15], schedule[16] = schedule[16], schedule[15]
        assert seqs[15:17] == [65535, 0]
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 40 + DEPTH)
    played = [st for st in states if st.seq is not None]
    assert [st.seq for st in played] == seqs
    for st, data in zip(played, packets):
        assert st.status == "received"
        assert_plays(st, data)
    assert playout.stats["concealed"] == playout.stats["restarts"] == playout.stats["late"] == 0


@pytest.mark.parametrize("new_first", [0, 40000])
def test_sender_restart_far_away_resyncs(new_first: int) -> None:
    """A sender that restarts at 0 after 300 frames (or at a far number) is a new stream."""
    rng = np.random.default_rng(8)
    old = [encode(make_frame(s, rng, q=1.0)) for s in range(300)]
    new = [encode(make_frame(new_first + s, rng, q=2.0)) for s in range(100)]
    schedule = {k: [p] for k, p in enumerate(old + new)}
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 400 + 2 * DEPTH)
    s = playout.stats
    assert s["restarts"] == 1 and s["late"] == 0 and s["stray"] == 0
    marks = [float(st.q[0]) for st in states if st.status == "received"]
    switch = marks.index(2.0)
    assert set(marks[:switch]) == {1.0} and set(marks[switch:]) == {2.0}
    new_states = [st for st in states if st.status == "received" and st.q[0] == 2.0]
    # every packet of the new stream plays, from its first, in order
    assert [st.seq for st in new_states] == [new_first + k for k in range(100)]
    for st, data in zip(new_states, new):
        assert_plays(st, data)
    # between the streams: the last state held (no slot during the new stream's countdown)
    gap = states[states.index(new_states[0]) - DEPTH: states.index(new_states[0])]
    assert all(st.seq is None and st.status == "held" for st in gap)
    ledger(playout, states)


def test_sender_restart_a_few_frames_back_resyncs() -> None:
    """A restart at 0 after 40 frames sits inside the window: the fallen-behind rule."""
    rng = np.random.default_rng(9)
    old = [encode(make_frame(s, rng, q=1.0)) for s in range(40)]
    new = [encode(make_frame(s, rng, q=2.0)) for s in range(100)]
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, {k: [p] for k, p in enumerate(old + new)}, 140 + DEPTH)
    s = playout.stats
    # a run of late packets spanning more than DEPTH slot periods: DEPTH + 2 packets, the
    # last of which restarts the stream
    assert s["restarts"] == 1 and s["late"] == DEPTH + 1
    new_states = [st for st in states if st.status == "received" and st.q[0] == 2.0]
    assert [st.seq for st in new_states] == list(range(DEPTH + 1, 100))
    assert states[-1].status == "received" and states[-1].seq == 99
    ledger(playout, states)


def test_stragglers_after_a_stall_are_late_but_do_not_resync() -> None:
    rng = np.random.default_rng(10)
    packets = [encode(make_frame(s, rng)) for s in range(100)]
    schedule = {k: [packets[k]] for k in range(100) if not 40 <= k < 60}
    schedule[60] = packets[40:61]  # the network delivers the stalled packets in a burst
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 100 + DEPTH)
    late = 60 - DEPTH - 40  # slots 40 .. 56 were played (concealed) before tick 60's pop
    s = playout.stats
    assert s["restarts"] == 0 and s["late"] == late and s["concealed"] == late
    by_seq = {st.seq: st for st in states if st.seq is not None}
    assert sorted(by_seq) == list(range(100))
    assert all(by_seq[k].status in HELD for k in range(40, 40 + late))
    for k in [*range(40), *range(40 + late, 100)]:
        assert_plays(by_seq[k], packets[k])
    ledger(playout, states)


def test_a_forward_jump_skips_the_missing_slots_and_keeps_the_latency() -> None:
    rng = np.random.default_rng(11)
    jump = 10  # the sender skipped ten numbers: 50 .. 59 never exist
    seqs = [*range(50), *range(50 + jump, 100 + jump)]
    packets = {s: encode(make_frame(s, rng)) for s in seqs}
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, {k: [packets[s]] for k, s in enumerate(seqs)}, 100 + DEPTH)
    played = [st for st in states if st.seq is not None]
    assert [st.seq for st in played] == seqs  # every packet plays, no slot is concealed
    s = playout.stats
    assert s["skipped"] == jump and s["concealed"] == 0 and s["discarded"] == 0
    assert s["restarts"] == 0
    # each packet still plays DEPTH pops after it arrived
    assert all(st.arrival_s == pytest.approx(k / RATE) for k, st in enumerate(played))
    assert all(states[k + DEPTH] is st for k, st in enumerate(played))


def test_a_faster_sender_clock_does_not_grow_the_latency() -> None:
    rng = np.random.default_rng(12)
    n = 300
    packets = [encode(make_frame(s, rng)) for s in range(n)]
    # 6 packets every 5 ticks: the sender's clock runs 20 % fast
    schedule: dict[int, list[bytes]] = {}
    for s in range(n):
        schedule.setdefault(s * 5 // 6, []).append(packets[s])
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, n * 5 // 6 + 2 * DEPTH)
    played = [st for st in states if st.status == "received"]
    lags = [states.index(st) - st.arrival_s * RATE for st in played]
    assert max(lags) <= 2 * DEPTH  # without the skip rule it would reach about 50
    assert played[-1].seq == n - 1
    s = playout.stats
    assert s["skipped"] > 0 and s["discarded"] == s["skipped"]
    # only the skipped slots go: every other slot up to the last packet plays its packet
    assert len(played) + s["skipped"] == n
    assert all(st.seq >= n for st in states if st.status in HELD and st.seq is not None)
    ledger(playout, states)


def test_a_stray_far_packet_moves_nothing() -> None:
    rng = np.random.default_rng(13)
    packets = [encode(make_frame(s, rng)) for s in range(60)]
    schedule = {k: [p] for k, p in enumerate(packets)}
    schedule[30] = [encode(make_frame(30000, rng)), packets[30]]
    playout = Playout(RATE, depth=DEPTH)
    states = drive(playout, schedule, 60 + DEPTH)
    assert [st.seq for st in states[DEPTH:]] == list(range(60))
    assert all(st.status == "received" for st in states[DEPTH:])
    s = playout.stats
    assert s["stray"] == 1 and s["restarts"] == 0 and s["received"] == 61
    ledger(playout, states)


def test_playing_on_arrival_waits_for_a_missing_slot_until_its_adaptive_deadline() -> None:
    rng = np.random.default_rng(7)
    n = MIN_JITTER_PACKETS  # the first slot played once the margin is judged from the jitter
    packets = [encode(make_frame(s, rng)) for s in range(n + 10)]
    playout = Playout(RATE, depth=DEPTH)
    period = 1 / RATE
    assert not playout.ready and playout.due() is None and playout.ahead == 0
    playout.push(packets[0], 0.0)
    assert playout.ready and playout.ahead == 1
    states = []
    while playout.ready:  # the countdown costs nothing: slot 0 plays at once
        states.append(playout.pop())
    assert [s.seq for s in states] == [None] * DEPTH + [0]
    assert playout.margin_s == pytest.approx(DEPTH * period)  # too few packets to judge
    for s in range(1, n):  # steady arrivals, each played on arrival
        assert playout.margin_s == pytest.approx(DEPTH * period)
        playout.push(packets[s], s * period)
        assert playout.ready and playout.pop().seq == s
    # no jitter: the margin is one period and the guard
    assert playout.margin_s == pytest.approx(period + 0.005)
    assert playout.due() == pytest.approx(n * period + period + 0.005)
    # slot n + 1 overtakes slot n by a few ms: slot n is waited for, then both play
    playout.push(packets[n + 1], (n + 1) * period)
    assert not playout.ready and playout.ahead == 2
    playout.push(packets[n], (n + 1) * period + 0.004)
    assert playout.ready
    assert [playout.pop().seq, playout.pop().seq] == [n, n + 1]
    assert playout.stats["late"] == 0
    # slot n + 2 is lost: nothing is ready until its deadline; slot n + 3 plays after it
    playout.push(packets[n + 3], (n + 3) * period)
    assert not playout.ready
    due = playout.due()
    # the jitter so far: slot n came one period and 4 ms after its earliest time
    assert due == pytest.approx((n + 2) * period + period + (period + 0.004) + 0.005)
    state = playout.pop()  # the caller pops at the deadline
    assert state.seq == n + 2 and state.status == "held"
    assert playout.ready and playout.pop().seq == n + 3
    assert playout.stats["concealed"] == 1


@pytest.mark.parametrize("sender_hz", [24.0, 27.0, 30.0])
def test_a_sender_slower_than_its_rate_is_followed_not_concealed(sender_hz: float) -> None:
    """A busy machine's sender numbers 30 Hz slots but sends at ``sender_hz``: each packet
    later than the last by a share of a period. Popped on arrival, and at each deadline
    passed before the next arrival, every slot plays its packet; none is concealed or late
    (with the deadline's base over all 64 offsets, 24 and 27 Hz concealed slots)."""
    rng = np.random.default_rng(10)
    playout = Playout(RATE, depth=DEPTH)
    played = []
    for s in range(300):
        arrival = s / sender_hz
        while (due := playout.due()) is not None and due <= arrival:
            playout.pop()  # the deadline passed before this packet came: concealed
        playout.push(encode(make_frame(s, rng)), arrival)
        while playout.ready:
            state = playout.pop()
            if state.seq is not None:
                played.append(state.seq)
    assert played == list(range(300))
    assert playout.stats["concealed"] == 0 and playout.stats["late"] == 0
    assert playout.stats["restarts"] == 0


def test_the_margin_follows_the_jitter_up_to_the_depth() -> None:
    rng = np.random.default_rng(8)
    playout = Playout(RATE, depth=DEPTH)
    period = 1 / RATE
    n = MIN_JITTER_PACKETS + 12
    for s in range(n):  # every other packet 50 ms late
        playout.push(encode(make_frame(s, rng)), s * period + (0.05 if s % 2 else 0.0))
        while playout.ready:
            playout.pop()
    assert playout.margin_s == pytest.approx(period + 0.05 + 0.005)
    for s in range(n, n + 20):  # jitter beyond the depth: capped
        playout.push(encode(make_frame(s, rng)), s * period + (0.3 if s % 2 else 0.0))
    assert playout.margin_s == pytest.approx(DEPTH * period)


def test_without_skip_every_slot_plays_however_far_behind() -> None:
    """A file-writing receiver that fell behind: packets pile up past a lost slot, and
    every slot is still played (with ``skip`` the skip rule gives up the lost one and
    discards the ones before the target)."""
    rng = np.random.default_rng(9)
    packets = {s: encode(make_frame(s, rng)) for s in range(20) if s != 3}
    for skip, expected in ((False, list(range(20))), (True, None)):
        playout = Playout(RATE, depth=DEPTH, skip=skip)
        for data in packets.values():
            playout.push(data, 0.0)
        seqs = [state.seq for state in (playout.pop() for _ in range(DEPTH + 20))
                if state.seq is not None]
        if expected is not None:
            assert seqs == expected
            assert playout.stats["skipped"] == 0 and playout.stats["discarded"] == 0
            assert playout.stats["concealed"] == 1
        else:
            assert playout.stats["skipped"] > 0 and playout.stats["discarded"] > 0
