"""The voice's parts on real speech: the Opus codec, the voice packet, a file's sound track,
the jitter buffer under loss, reordering and jitter, and the sender's voice thread on real
ZeroMQ sockets."""

from __future__ import annotations

import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import free_endpoint, start

from facewire.bench.bandwidth import bandwidth
from facewire.bench.inspect import inspect_log
from facewire.bench.speech import SpeechError, speech_quality, speech_table
from facewire.bench.sync import shown_per_slot
from facewire.models.infra.sound import SoundError, read_sound
from facewire.protocol import opus, voice
from facewire.protocol.control import Camera, Hello, HelloRequest
from facewire.protocol.log import RECORD_BYTES, VOICE_TAG, LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, encode_frames
from facewire.protocol.transport import (
    ControlClient,
    PacketPublisher,
    PacketSubscriber,
    control_endpoint,
    free_loopback_endpoint,
)
from facewire.receiver.jitterbuffer import MAX_DEPTH, MAX_EXTRA, JitterBuffer
from facewire.receiver.output import VideoWriter
from facewire.receiver.receiver import receive
from facewire.receiver.replay import replay_log
from facewire.receiver.speaker import SoundClock, Speaker, SpeakerError
from facewire.receiver.voiceplayer import AHEAD_S, BEHIND_S, VoicePlayer, voice_capture
from facewire.sender.pipeline import encode_video
from facewire.sender.sender import send
from facewire.sender.voice import FileVoice, MicVoice, VoiceSourceError, VoiceThread

SPEECH = "hdtf_edmarkey.mp4"
LOG_HELLO = Hello("0f" * 32, 4096, 30.0, Camera(500.0, 500.0, 320.0, 240.0, 640, 480),
                  ("forehead", "mouth"))


@pytest.fixture(scope="module")
def speech(shared_data: Path) -> np.ndarray:
    """(F, 960) int16: the clip's sound in 20-ms frames."""
    sound = read_sound(shared_data / "video" / SPEECH)
    assert sound is not None
    n = len(sound.pcm) // opus.FRAME_SAMPLES
    return sound.pcm[:n * opus.FRAME_SAMPLES].reshape(n, opus.FRAME_SAMPLES)


def _envelope(frames: np.ndarray) -> np.ndarray:
    """(F,) dB level per 20-ms frame."""
    rms = np.sqrt(np.mean(frames.astype(np.float64) ** 2, axis=1))
    return 20 * np.log10(rms + 1.0)


def _packets(frames: np.ndarray, bitrate: int = opus.DEFAULT_BITRATE) -> list[bytes]:
    encoder = opus.Encoder(bitrate)
    return [encoder.encode(frame) for frame in frames]


def test_a_held_frame_is_on_screen_for_every_slot_it_lasts() -> None:
    """bench sync reads a live receiver's file (frames held over slots, receiver.output) on
    the stream's grid: each slot has the last frame at or before it."""
    times = np.array([0.0, 0.04, 0.16, 0.2, 0.36]) + 1.0  # 25 Hz slots 0, 1, 4, 5, 9
    assert shown_per_slot(times, 25.0).tolist() == [0, 1, 1, 1, 2, 3, 3, 3, 3, 4]
    assert shown_per_slot(times[:1], 25.0).tolist() == [0]


def test_the_sound_track_is_read_on_the_files_timeline(shared_data: Path) -> None:
    sound = read_sound(shared_data / "video" / SPEECH)
    assert sound is not None
    assert sound.seconds == pytest.approx(8.0, abs=0.05)
    assert np.abs(sound.pcm).max() > 1000  # speech, not silence
    cut = sound.between(sound.start - 0.5, sound.start + 0.5)
    assert len(cut) == opus.SAMPLE_RATE
    assert not cut[:opus.SAMPLE_RATE // 2].any()  # before the track: silence
    assert np.array_equal(cut[opus.SAMPLE_RATE // 2:], sound.pcm[:opus.SAMPLE_RATE // 2])
    assert read_sound(shared_data / "video" / "openface_gaze.avi") is None  # no sound track


def test_a_file_that_is_not_media_is_refused_naming_it(tmp_path: Path) -> None:
    bad = tmp_path / "noise.mp4"
    bad.write_bytes(b"not a video" * 100)
    with pytest.raises(SoundError, match="noise.mp4"):
        read_sound(bad)


def test_opus_packets_have_the_constant_size_and_follow_the_speech(speech: np.ndarray) -> None:
    packets = _packets(speech)
    assert {len(p) for p in packets} == {opus.packet_bytes(opus.DEFAULT_BITRATE)}
    decoder = opus.Decoder()
    out = np.stack([decoder.decode(p) for p in packets])
    # Opus keeps the speech's level per frame, after its look-ahead (6.5 ms: one frame).
    r = np.corrcoef(_envelope(speech[:-1]), _envelope(out[1:]))[0, 1]
    assert r > 0.9


def test_fec_recovers_a_lost_frame_better_than_concealment(speech: np.ndarray) -> None:
    packets = _packets(speech, 20_000)  # libopus adds FEC from about 20 kbit/s (protocol.opus)
    lost = np.arange(20, len(packets) - 1, 7)  # one frame in seven, never two in a row
    outs = {}
    for mode in ("recover", "conceal"):
        decoder, frames = opus.Decoder(), []
        for k, packet in enumerate(packets):
            if k in lost:
                frames.append(decoder.recover(packets[k + 1]) if mode == "recover"
                              else decoder.conceal())
            else:
                frames.append(decoder.decode(packet))
        outs[mode] = np.stack(frames)
    reference = opus.Decoder()
    clean = np.stack([reference.decode(p) for p in packets])
    err = {mode: np.mean([np.abs(_envelope(out[k:k + 1]) - _envelope(clean[k:k + 1]))
                          for k in lost]) for mode, out in outs.items()}
    assert err["recover"] < err["conceal"]


def test_a_voice_packet_round_trips_and_any_bytes_decode_or_raise() -> None:
    packet = voice.VoicePacket(65535, bytes(range(24)))
    data = voice.encode(packet)
    assert len(data) == voice.HEADER_BYTES + 24 + voice.CRC_BYTES
    assert voice.is_voice(data) and voice.decode(data) == packet
    # every single-bit error is caught by the CRC (or the kind and reserved checks)
    for bit in range(len(data) * 8):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 0x80 >> (bit % 8)
        with pytest.raises(voice.VoiceError):
            voice.decode(bytes(flipped))
    rng = np.random.default_rng(7)
    decoded = 0
    for _ in range(5000):
        junk = rng.integers(0, 256, rng.integers(0, 80), dtype=np.uint8).tobytes()
        try:
            voice.decode(junk)
            decoded += 1
        except voice.VoiceError:
            pass
    assert decoded == 0
    with pytest.raises(voice.VoiceError, match="bytes"):
        voice.encode(voice.VoicePacket(0, bytes(voice.MAX_OPUS_BYTES + 1)))


def test_unwrap_follows_the_wrap() -> None:
    assert voice.unwrap(3, 65534) == 65539
    assert voice.unwrap(65534, 65539) == 65534
    assert voice.unwrap(10, None) == 10


def _play(packets: list[bytes], arrivals: np.ndarray, buffer: JitterBuffer,
          start_seq: int = 0) -> np.ndarray:
    """Deliver each packet whose arrival is finite at that time and pull every 20 ms until
    0.1 s after the last arrival; (pulls, 960) int16."""
    order = [int(i) for i in np.argsort(arrivals, kind="stable") if np.isfinite(arrivals[i])]
    out, k = [], 0
    for tick in np.arange(0.0, arrivals[order[-1]] + 0.1, opus.FRAME_S):
        while k < len(order) and arrivals[order[k]] <= tick + 1e-9:
            i = order[k]
            buffer.push(voice.VoicePacket((start_seq + i) % voice.SEQ_MODULO, packets[i]),
                        float(arrivals[i]))
            k += 1
        out.append(buffer.pull())
    return np.stack(out)


def _aligned_r(source: np.ndarray, played: np.ndarray) -> float:
    """The best envelope correlation of the played sound with the source over small lags."""
    a = _envelope(source)
    b = _envelope(played)
    best = -1.0
    for lag in range(0, len(b) - len(a) + 1):
        best = max(best, float(np.corrcoef(a, b[lag:lag + len(a)])[0, 1]))
    return best


def test_the_buffer_plays_through_jitter_reordering_loss_and_a_wrap(
        speech: np.ndarray) -> None:
    frames = speech[:300]
    packets = _packets(frames)
    rng = np.random.default_rng(3)
    # 50 ms of transit and up to 60 ms of jitter (so packets overtake each other), 10 % lost
    arrivals = np.arange(len(packets)) * opus.FRAME_S + 0.05 + rng.uniform(0, 0.06, len(packets))
    lost = rng.random(len(packets)) < 0.1
    buffer = JitterBuffer()
    played = _play(packets, np.where(lost, np.inf, arrivals), buffer, start_seq=65500)
    stats = buffer.stats
    assert stats["received"] == int((~lost).sum())
    assert stats["resets"] == 0 and stats["duplicate"] == 0
    assert stats["late"] <= 0.02 * len(packets)  # the depth followed the jitter
    assert 3 <= buffer.target <= MAX_DEPTH
    assert stats["played"] >= int((~lost).sum()) - stats["late"] - stats["dropped"]
    assert _aligned_r(frames, played) > 0.85


def test_a_stretch_plays_the_rest_a_frame_later_and_a_shrink_undoes_it(
        speech: np.ndarray) -> None:
    """Five stretches at frame 30: five pulls of concealment, then every frame on in order,
    none dropped (the deeper target keeps the depth won); five shrinks at frame 60 skip five
    frames; a stretch past ``MAX_EXTRA`` is refused."""
    packets = _packets(speech[:100])
    buffer = JitterBuffer()
    pulled: list[int | None] = []
    for tick in range(140):
        if tick < len(packets):
            buffer.push(voice.VoicePacket(tick, packets[tick]), tick * opus.FRAME_S + 0.005)
        if pulled and pulled[-1] == 30:
            assert all(buffer.stretch() for _ in range(5))
        if pulled and pulled[-1] == 60:
            assert all(buffer.shrink() for _ in range(5))
        buffer.pull()
        pulled.append(buffer.pulled)
    frames = [n for n in pulled if n is not None]
    at = pulled.index(30)
    assert pulled[at + 1:at + 6] == [None] * 5 and pulled[at + 6] == 31
    assert frames[:61] == list(range(61)) and frames[61] == 66  # 61-65 skipped
    assert frames[61:95] == list(range(66, 100))  # then concealment past the last
    stats = buffer.stats
    assert (stats["stretched"], stats["shrunk"], stats["dropped"], buffer.extra) == (5, 5, 0, 0)
    assert not buffer.shrink()  # nothing left to undo
    buffer.extra = MAX_EXTRA
    assert not buffer.stretch()


@pytest.mark.parametrize("face_s", [0.3, 0.1])
def test_the_player_holds_the_sound_back_to_the_faces_latency(speech: np.ndarray,
                                                              face_s: float) -> None:
    """The clip's voice in real packets, 5 ms of transit, pulled every 20 ms on the test's
    clock beside a face shown ``face_s`` after its capture (a receiver that renders), then
    0.1 s after: the sound walks to the face's latency and stays within -AHEAD_S..BEHIND_S
    of it, and back when the face speeds up."""
    packets = _packets(speech[:400])
    origin = 1000.0
    player = VoicePlayer(None, None, lambda _: None,
                         lambda seq, near: voice_capture(seq, origin, near))
    player.close()  # the test's clock pulls, not the player's own
    latency = face_s
    for tick in range(len(packets) + 60):
        t = origin + tick * opus.FRAME_S
        if tick == 200:
            latency = 0.1  # the face speeds up
        if 1 <= tick <= len(packets):  # frame j released at origin + (j + 1) 20 ms
            player.push(voice.encode(voice.VoicePacket(tick - 1, packets[tick - 1])),
                        t + 0.005)
        player.face(t - latency, t)
        player._heard(player._pull(), t)
        if tick in (190, len(packets) - 10):  # settled: the last second within the window
            recent = np.array(player.skews)[-50:]
            assert -AHEAD_S - 1e-9 <= recent.min() and recent.max() <= BEHIND_S + 1e-9, \
                (tick, recent)
    got = player.summary()
    assert got["voice_stretched"] >= round((face_s - 0.1) / opus.FRAME_S)
    # every frame played but those a shrink skipped, when the face sped up
    assert got["voice_played"] + got["voice_shrunk"] == len(packets)
    assert got["voice_dropped"] == got["voice_late"] == 0
    assert (got["voice_shrunk"] > 0) == (face_s > 0.1)
    assert got["voice_extra_ms"] <= 100


def test_packets_carry_fec_only_at_rates_over_the_voices_budget(speech: np.ndarray) -> None:
    """libopus spends bits on in-band FEC from about 17-20 kbit/s (protocol.opus): none at the
    default rate, most packets (all but those without voice) at 20 kbit/s."""
    assert not any(map(opus.has_fec, _packets(speech)))
    assert not any(map(opus.has_fec, _packets(speech, 16_000)))
    assert sum(map(opus.has_fec, _packets(speech, 20_000))) >= 0.7 * len(speech)
    assert not opus.has_fec(b"") and not opus.has_fec(bytes(opus.MAX_PACKET_BYTES + 1))


@pytest.mark.parametrize("bitrate", [opus.DEFAULT_BITRATE, 20_000])
def test_lost_packets_are_recovered_from_fec_or_concealed_and_the_sound_goes_on(
        speech: np.ndarray, bitrate: int) -> None:
    frames = speech[:300]
    packets = _packets(frames, bitrate)
    arrivals = np.arange(len(packets)) * opus.FRAME_S + 0.03
    lost = set(range(40, len(packets), 10)) | {100, 101, 102}
    buffer = JitterBuffer()
    played = _play(packets, np.where(np.isin(np.arange(len(packets)), list(lost)), np.inf,
                                     arrivals), buffer)
    stats = buffer.stats
    # a lost frame is rebuilt exactly when the next packet arrived and carries FEC
    rebuilt = sum(k + 1 not in lost and opus.has_fec(packets[k + 1]) for k in lost)
    assert stats["recovered"] == rebuilt
    # the rest concealed, and past the last packet a frame or two before the pulls stop
    assert 0 <= stats["concealed"] - (len(lost) - rebuilt) <= 3
    assert (rebuilt == 0) == (bitrate == opus.DEFAULT_BITRATE)
    assert rebuilt >= len(lost) // 2 or bitrate == opus.DEFAULT_BITRATE
    assert stats["played"] == len(packets) - len(lost) and stats["resets"] == 0
    assert _aligned_r(frames, played) > 0.85


def test_ten_lost_frames_in_a_row_before_packets_come_again_do_not_reset(
        speech: np.ndarray) -> None:
    """The tenth concealment in a row resets the buffer only when no packet follows: here
    packet 50 is buffered when frame 49's turn comes (its packet, without FEC, is no
    recovery)."""
    packets = _packets(speech[:100])
    arrivals = np.arange(len(packets)) * opus.FRAME_S + 0.03
    arrivals[40:50] = np.inf
    buffer = JitterBuffer()
    _play(packets, arrivals, buffer)
    assert buffer.stats["resets"] == 0
    assert 10 <= buffer.stats["concealed"] <= 13  # and past the last packet, as above
    assert buffer.stats["played"] == 90


def test_a_stopped_stream_turns_to_silence_and_a_new_one_primes_again(
        speech: np.ndarray) -> None:
    packets = _packets(speech[:100])
    buffer = JitterBuffer()
    for i in range(50):
        buffer.push(voice.VoicePacket(i, packets[i]), i * opus.FRAME_S)
    outs = [buffer.pull() for _ in range(80)]
    assert buffer.stats["resets"] == 1
    assert not np.concatenate(outs[-10:]).any()  # silence, not a fading concealment
    # the sender comes back at another number: a new stream, in real time
    played = _play(packets[50:], np.arange(50) * opus.FRAME_S, buffer, start_seq=5000)
    assert buffer.stats["resets"] == 1
    assert buffer.stats["played"] == 100 - buffer.stats["dropped"]
    assert np.abs(played[-30:]).max() > 1000


def test_a_files_voice_goes_out_paced_on_real_sockets_and_plays_back(
        shared_data: Path, speech: np.ndarray) -> None:
    sound = read_sound(shared_data / "video" / SPEECH)
    assert sound is not None
    source = FileVoice(sound, sound.start)
    assert np.array_equal(source.frame(7), speech[7])
    with PacketPublisher(free_loopback_endpoint()) as publisher, \
            PacketSubscriber(publisher.endpoint) as subscriber:
        time.sleep(0.3)  # the subscription reaches the publisher
        origin = time.monotonic() + 0.1
        thread = VoiceThread(source, opus.Encoder(), origin, publisher.send)
        thread.start()
        got: list[tuple[float, voice.VoicePacket]] = []
        while time.monotonic() < origin + 2.0:
            data = subscriber.recv(100)
            if data is not None:
                got.append((time.monotonic(), voice.decode(data)))
        thread.stop()
    seqs = [p.seq for _, p in got]
    assert seqs[:80] == list(range(80))  # numbered from the origin, none lost on loopback
    # frame j leaves once its 20 ms have passed, never before (a generous bound after)
    assert all(t >= origin + (p.seq + 1) * opus.FRAME_S - 0.002 for t, p in got)
    assert thread.packets >= 80 and thread.bytes == sum(len(voice.encode(p)) for _, p in got)
    decoder = opus.Decoder()
    out = np.stack([decoder.decode(p.opus) for _, p in got[:80]])
    r = np.corrcoef(_envelope(speech[:79]), _envelope(out[1:80]))[0, 1]
    assert r > 0.9


def test_a_missing_microphone_is_one_clear_line() -> None:
    with pytest.raises(VoiceSourceError, match="microphone mic:9"):
        MicVoice("mic:9")


def _voice_log(path: Path, speech: np.ndarray, n: int = 60) -> list[bytes]:
    """A log of n face packets with a voice packet after each (real Opus of the speech)."""
    frames = np.zeros(n, FRAME_DTYPE)
    frames["seq"] = np.arange(n)
    frames["translation"][:, 2] = -600
    packets, _ = encode_frames(frames)
    encoder = opus.Encoder()
    sent = []
    with LogWriter(path, LOG_HELLO) as log:
        for i, packet in enumerate(packets):
            log.write(packet.tobytes(), 100.0 + i / 30)
            sent.append(voice.encode(voice.VoicePacket(i, encoder.encode(speech[i]))))
            log.write_voice(sent[-1], 100.0 + i / 30 + 0.001)
        assert (log.records, log.voice) == (n, n)
    return sent


def test_a_log_keeps_the_voice_and_recovers_around_a_damaged_record(
        tmp_path: Path, speech: np.ndarray) -> None:
    path = tmp_path / "v.fwlog"
    sent = _voice_log(path, speech)
    log = read_log(path)
    assert [v.data for v in log.voice] == sent
    assert [v.before for v in log.voice] == list(range(1, 61))
    assert (len(log.packets), log.lost, log.lost_voice) == (60, 0, 0)
    data = bytearray(path.read_bytes())
    start = len(data) - 30 * (len(sent[0]) + 14 + RECORD_BYTES)  # a voice record's middle
    offset = data.index(bytes([VOICE_TAG]), start) - 8
    data[offset + 15] ^= 0xFF
    path.write_bytes(bytes(data))
    damaged = read_log(path)
    assert (len(damaged.packets), len(damaged.voice), damaged.lost_voice) == (60, 59, 1)


def test_a_log_written_before_the_voice_still_reads(tmp_path: Path, speech: np.ndarray) -> None:
    path = tmp_path / "old.fwlog"
    frames = np.zeros(10, FRAME_DTYPE)
    frames["seq"] = np.arange(10)
    frames["translation"][:, 2] = -600
    packets, _ = encode_frames(frames)
    with LogWriter(path, LOG_HELLO) as log:
        for i, packet in enumerate(packets):
            log.write(packet.tobytes(), float(i))
    data = bytearray(path.read_bytes())
    data[8:10] = (2).to_bytes(2, "big")  # format 2: the same bytes without voice records
    end = 16 + int.from_bytes(data[12:16], "big")
    data[end:end + 4] = zlib.crc32(data[:end]).to_bytes(4, "big")
    path.write_bytes(bytes(data))
    old = read_log(path)
    assert (len(old.packets), old.voice, old.lost) == (10, (), 0)


def test_inspect_lists_the_voice(tmp_path: Path, speech: np.ndarray) -> None:
    path = tmp_path / "v.fwlog"
    sent = _voice_log(path, speech)
    summary, lines = inspect_log(path)
    assert (summary["voice_packets"], summary["voice_gaps"], summary["lost_voice"]) == (60, 0, 0)
    assert summary["voice_s"] == pytest.approx(1.2)
    span = 59 / 30 + 0.0  # the face packets' times
    assert summary["voice_kbps"] == pytest.approx(sum(map(len, sent)) * 8 / span / 1000,
                                                  rel=1e-3)
    assert any(line.startswith("voice: 60 packets") for line in lines)


def test_a_missing_speaker_is_one_clear_line() -> None:
    with pytest.raises(SpeakerError, match="speaker 7"):
        Speaker(lambda: np.zeros(opus.FRAME_SAMPLES, np.int16), "7")


def test_the_sound_clock_pulls_every_frame_in_order() -> None:
    pulled: list[float] = []
    heard: list[float] = []
    clock = SoundClock(lambda: pulled.append(time.monotonic()) or
                       np.zeros(opus.FRAME_SAMPLES, np.int16),
                       lambda pcm, t: heard.append(t))
    clock.start()
    time.sleep(0.5)
    clock.stop()
    assert 15 <= clock.frames == len(pulled) == len(heard)
    assert np.allclose(np.diff(heard), opus.FRAME_S)  # due times, one frame apart
    assert all(p >= t - 1e-3 for p, t in zip(pulled, heard))  # never before its time


def test_a_video_file_gets_the_sound_where_it_was_placed(tmp_path: Path,
                                                         speech: np.ndarray) -> None:
    path = tmp_path / "out.mp4"
    with VideoWriter(path, 64, 48, 25.0, sound=True) as writer:
        for i in range(50):
            writer.write(np.full((48, 64, 3), i * 4, np.uint8))
            writer.write_sound(speech[i].reshape(-1) if i else speech[0], 0.4 if i == 0
                               else None)
    sound = read_sound(path)
    assert sound is not None
    assert sound.start == pytest.approx(0.4, abs=0.002)
    assert sound.seconds == pytest.approx(50 * opus.FRAME_S, abs=0.03)
    # the file's sound is the speech (Opus at 64 kbit/s): same level per frame
    n = len(sound.pcm) // opus.FRAME_SAMPLES
    got = sound.pcm[:n * opus.FRAME_SAMPLES].reshape(n, -1)
    assert np.corrcoef(_envelope(speech[:n - 1]), _envelope(got[:n - 1]))[0, 1] > 0.9
    with VideoWriter(tmp_path / "silent.mp4", 64, 48, 25.0) as silent:
        silent.write(np.zeros((48, 64, 3), np.uint8))
        with pytest.raises(ValueError, match="without a sound track"):
            silent.write_sound(speech[0])


def test_speech_quality_falls_with_loss_and_the_codec_alone_holds_speech(
        shared_data: Path) -> None:
    summary, lines = speech_quality(shared_data / "video" / "retalk_2.mp4", losses=(0, 30))
    assert summary["pesq_wb_source"] == pytest.approx(4.64, abs=0.01)  # PESQ-WB's ceiling
    assert 3.0 <= summary["pesq_wb_opus"] < summary["pesq_wb_source"]
    assert summary["pesq_wb"]["30"] < summary["pesq_wb"]["0"] - 0.5
    assert summary["audio_kbps"] == pytest.approx(
        (opus.packet_bytes(opus.DEFAULT_BITRATE) + voice.HEADER_BYTES + voice.CRC_BYTES)
        * 8 / opus.FRAME_S / 1000, rel=0.01)
    # at the default rate no packet carries FEC: every lost frame is concealed
    assert summary["fec_packets"] == 0 and summary["recovered"] == {"0": None, "30": 0.0}
    assert "30 % loss" in lines[-1]
    with pytest.raises(SpeechError, match="no sound track"):
        speech_quality(shared_data / "video" / "openface_gaze.avi")


def test_bench_speech_scores_clips_in_one_run_and_fec_lifts_the_speech_under_loss(
        shared_data: Path) -> None:
    """At 20 kbit/s libopus carries FEC: lost frames with voice are rebuilt and the speech at 10 %
    loss scores well above the default rate's, whose lost frames are all concealed."""
    clips = [str(shared_data / "video" / name) for name in ("retalk_2.mp4", "retalk_1.mp4")]
    low, lines = speech_table(clips, losses=(10,))
    high, _ = speech_table(clips, 20_000, losses=(10,))
    assert [c["source"] for c in low["clips"]] == clips and len(lines) == 2 * 2 + 1
    assert low["pesq_wb_min"]["10"] == min(c["pesq_wb"]["10"] for c in low["clips"])
    for slow, fast in zip(low["clips"], high["clips"]):
        assert slow["recovered"]["10"] == 0 and fast["recovered"]["10"] >= 0.4
        assert fast["fec_packets"] >= 0.4  # pauses carry none
        assert fast["pesq_wb"]["10"] > slow["pesq_wb"]["10"] + 0.3
        assert fast["audio_kbps"] == pytest.approx(22.0, rel=0.01)


def test_send_streams_the_files_voice_beside_the_face_and_logs_it(
        generic_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """hdtf_edmarkey's frames 0:75 (3 s at 25 Hz) sent live: the voice packets go out on the
    face's socket, numbered from the face's origin, and the log keeps them."""
    clip = shared_data / "video" / SPEECH
    endpoint, log_path = free_endpoint(), tmp_path / "voice.fwlog"
    warnings: list[str] = []
    with PacketSubscriber(endpoint) as sub, ControlClient(control_endpoint(endpoint)) as client:
        thread, _, result = start(send, model_path=generic_model, source=str(clip),
                                  bind=endpoint, record=log_path, frames=slice(0, 75),
                                  learn=False, warn=warnings.append)
        got: list[bytes] = []
        hello = None
        while thread.is_alive():
            data = sub.recv(20)
            if data is not None:
                got.append(data)
            if hello is None and sum(map(voice.is_voice, got)) >= 10:  # the voice has begun
                hello = client.request(HelloRequest(), 5000)
        while (data := sub.recv(300)) is not None:
            got.append(data)
        thread.join()
    assert "error" not in result, result.get("error")
    assert isinstance(hello, Hello) and hello.voice_bitrate == opus.DEFAULT_BITRATE
    assert hello.voice_origin_s == hello.clock_origin_s  # a file's voice starts with its face
    voices = [voice.decode(d) for d in got if voice.is_voice(d)]
    seconds = 75 / 25
    assert result["voice"] == "file" and result["voice_packets"] >= 0.9 * seconds / opus.FRAME_S
    assert result["audio_kbps"] == pytest.approx(11.6, rel=0.15)
    assert [p.seq for p in voices] == list(range(voices[0].seq, voices[0].seq + len(voices)))
    log = read_log(log_path)
    assert len(log.voice) == result["voice_packets"] and len(log.packets) == result["packets"]
    decoder = opus.Decoder()
    played = np.stack([decoder.decode(voice.decode(r.data).opus) for r in log.voice])
    sound = read_sound(clip)
    assert sound is not None
    source = sound.pcm[:len(played) * opus.FRAME_SAMPLES].reshape(len(played), -1)
    r = np.corrcoef(_envelope(source[:-1]), _envelope(played[1:]))[0, 1]
    assert r > 0.9  # the file's sound from its first frame on, in order


def test_a_silent_source_sends_the_face_alone_and_says_so(
        generic_model: Path, shared_data: Path) -> None:
    warnings: list[str] = []
    result = send(generic_model, str(shared_data / "video" / "openface_gaze.avi"),
                  bind=free_endpoint(), frames=slice(0, 10), learn=False, warn=warnings.append)
    assert result["voice"] is None and result["voice_packets"] == 0
    assert any("no sound track" in w for w in warnings)


def test_encode_keeps_the_sound_and_replay_writes_it_in_sync(
        generic_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """hdtf_edmarkey's frames 25:75 encoded (the sound from 1 s on) and replayed: the file's
    sound track is the source's sound from the first frame's time, starting with frame 0."""
    clip = shared_data / "video" / SPEECH
    log_path, out = tmp_path / "e.fwlog", tmp_path / "e.mp4"
    summary = encode_video(generic_model, clip, log_path, slice(25, 75), learn=False)
    assert summary["voice_packets"] == 100  # 50 frames at 25 Hz: 2 s of 20-ms frames
    log = read_log(log_path)
    assert log.hello.voice_bitrate == opus.DEFAULT_BITRATE
    assert log.voice[0].time == pytest.approx(1.0 + opus.FRAME_S)  # logged once captured
    assert np.all(np.diff([r.time for r in log.voice]) > 0)
    replayed = replay_log(log_path, generic_model, out)
    assert replayed["voice_frames"] == 100 and replayed["sound_s"] == pytest.approx(2.0)
    sound, source = read_sound(out), read_sound(clip)
    assert sound is not None and source is not None
    assert sound.start == pytest.approx(0.0, abs=0.002)
    n = len(sound.pcm) // opus.FRAME_SAMPLES - 2
    got = sound.pcm[:n * opus.FRAME_SAMPLES].reshape(n, -1)
    want = source.between(1.0, 1.0 + n * opus.FRAME_S).reshape(n, -1)
    lags = {lag: np.corrcoef(_envelope(want[:n - 3]), _envelope(got[lag:n - 3 + lag]))[0, 1]
            for lag in range(3)}
    assert max(lags, key=lambda lag: lags[lag]) <= 1  # in sync, to Opus's look-ahead
    assert max(lags.values()) > 0.9
    silent = encode_video(generic_model, clip, tmp_path / "s.fwlog", slice(0, 5),
                          learn=False, audio=False)
    assert silent["voice_packets"] == 0 and read_log(tmp_path / "s.fwlog").voice == ()


def test_receive_plays_the_voice_into_the_file_and_measures_the_sync(
        generic_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """A live send of hdtf_edmarkey 0:100 (4 s) to a receiver writing a video: the voice is
    received whole, played, written as the file's sound track and its sync measured."""
    endpoint, out = free_endpoint(), tmp_path / "live.mp4"
    ready = threading.Event()
    thread, _, got = start(receive, connect=endpoint, model_path=generic_model, out=out,
                           idle_timeout_s=30.0, ready=ready, audio=True, speaker=None)
    sent = send(generic_model, str(shared_data / "video" / SPEECH), bind=endpoint,
                frames=slice(0, 100), learn=False, start=ready)
    thread.join()
    assert "error" not in got, got.get("error")
    assert sent["voice_packets"] >= 190
    assert got["voice_received"] == sent["voice_packets"] and got["voice_corrupt"] == 0
    # most of it played: the rest concealed or late, on a busy machine (87 % played under a
    # load of 30 on 2 cores)
    assert got["voice_played"] >= 0.5 * got["voice_received"]
    assert got["speaker"] == "none"
    assert got["av_skew_ms_median"] is not None  # measured (its size: bench sync)
    sound = read_sound(out)
    assert sound is not None
    heard = (got["voice_played"] + got["voice_recovered"] + got["voice_concealed"]
             + got["voice_stretched"]) * opus.FRAME_S
    assert sound.seconds == pytest.approx(heard, abs=0.5)


def test_bandwidth_reports_the_voice_beside_the_face(tmp_path: Path,
                                                      speech: np.ndarray) -> None:
    path = tmp_path / "b.fwlog"
    frames = np.zeros(90, FRAME_DTYPE)
    frames["seq"] = np.arange(90)
    frames["translation"][:, 2] = -600
    packets, _ = encode_frames(frames)
    encoder = opus.Encoder()
    with LogWriter(path, LOG_HELLO) as log:  # 3 s: a face packet per 1/30 s, voice per 20 ms
        for j in range(150):
            if j % 5 < 3:
                k = j // 5 * 3 + j % 5
                log.write(packets[k].tobytes(), 100.0 + k / 30)
            log.write_voice(voice.encode(voice.VoicePacket(j, encoder.encode(speech[j]))),
                            100.0 + (j + 1) * opus.FRAME_S)
    summary, lines = bandwidth(path)
    per_packet = opus.packet_bytes(opus.DEFAULT_BITRATE) + voice.HEADER_BYTES + voice.CRC_BYTES
    assert summary["audio_kbps_max_1s"] == pytest.approx(per_packet * 8 * 50 / 1000)  # 11.6
    assert summary["total_kbps_max_1s"] == pytest.approx(
        summary["payload_kbps_max_1s"] + summary["audio_kbps_max_1s"])
    assert summary["total_kbps_max_1s"] < 24  # the call's budget, each way
    assert any(line.startswith("voice: 150 packets") for line in lines)
