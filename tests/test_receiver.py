"""The live receive loop over real ZeroMQ on 127.0.0.1, fed by a real log's packets.

The sender here is the real transport (``PacketPublisher`` and ``ControlServer``) answering
the real control messages, publishing the packets of lp_d0.mp4 encoded with its own model;
only the pacing and the scripted faults (junk, a restart) are the test's. Rendering is real
(EGL), at 160x120 to keep the tests short.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
import threading
import time
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from conftest import start
from logsender import LogSender
from logsender import free_port_pair as _free_port_pair
from logsender import hello_for as _hello_for
from logsender import ready as _ready

from facewire.models.infra.video import read_frames
from facewire.models.modelfile import ModelFileError
from facewire.protocol.keys import generate_keys, server_keys
from facewire.protocol.log import read_log
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.transport import TransportError
from facewire.receiver.modelcache import ModelCache, ModelCacheError, default_folder, verify_model
from facewire.receiver.playout import FrameState
from facewire.receiver.receiver import LIVE_SIZE, MAX_SIZE, ReceiveError, receive
from facewire.receiver.stats import LIVE_KEYS
from facewire.sender.pipeline import encode_video

SIZE = (160, 120)


@pytest.fixture(scope="module")
def log(person_model: Path, shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    """lp_d0.mp4 (78 frames, 25 Hz) encoded with its own model."""
    path = tmp_path_factory.mktemp("receiver") / "lp_d0.fwlog"
    encode_video(person_model, shared_data / "video" / "lp_d0.mp4", path)
    return read_log(path)


def _video_frames(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


# -- the model cache -------------------------------------------------------------------------

def test_model_is_fetched_by_hash_verified_cached_and_not_fetched_again(
        log, person_model: Path, tmp_path: Path) -> None:
    port = _free_port_pair()
    data = person_model.read_bytes()
    cache = tmp_path / "cache"
    go, lines = threading.Event(), []
    sender = LogSender(port, log.hello, data, log.packets, count=10**6, go=go)
    try:
        summary = receive(f"tcp://127.0.0.1:{port}", cache_dir=cache, size=SIZE,
                          status=_ready(go, lines), max_frames=10, idle_timeout_s=10)
        chunks = len(sender.chunks)
        assert chunks > 1  # a real multi-chunk transfer
        assert sender.requests["model_request"] == chunks
        assert summary["model_source"] == "fetched" and summary["frames"] == 10
        assert summary["model_sha256"] == log.hello.model_sha256
        cached = cache / f"{log.hello.model_sha256}.fwm"
        assert summary["cached"] == str(cached) and cached.read_bytes() == data
        assert not list(cache.glob(".*.tmp"))
        assert any("fetched" in line for line in lines)

        # a second receiver on this host finds it: no model request at all
        summary = receive(f"tcp://127.0.0.1:{port}", cache_dir=cache, size=SIZE, max_frames=5,
                          idle_timeout_s=10)
        assert sender.requests["model_request"] == chunks
        assert summary["model_source"] == "cache" and summary["frames"] == 5

        # a damaged cached file is refused and fetched again (and repaired)
        damaged = bytearray(data)
        damaged[len(damaged) // 2] ^= 0xFF
        cached.write_bytes(bytes(damaged))
        lines.clear()
        summary = receive(f"tcp://127.0.0.1:{port}", cache_dir=cache, size=SIZE,
                          status=lines.append, max_frames=5, idle_timeout_s=10)
        assert summary["model_source"] == "fetched"
        assert sender.requests["model_request"] == 2 * chunks
        assert cached.read_bytes() == data
        assert any("damaged" in line and "refused" in line for line in lines)
    finally:
        sender.stop()


def test_cache_refuses_bytes_that_are_not_the_announced_model(person_model: Path,
                                                               tmp_path: Path) -> None:
    data = person_model.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    with pytest.raises(ModelCacheError, match="hash to"):
        verify_model(data[:-1] + b"x", sha)
    junk = b"not a model at all"
    with pytest.raises(ModelFileError):  # hashes right, but is no model file
        verify_model(junk, hashlib.sha256(junk).hexdigest())
    cache = ModelCache(tmp_path)
    model = verify_model(data, sha)
    with pytest.raises(ModelCacheError, match="not those of model"):
        cache.put(data[:-1], model)
    with pytest.raises(ModelCacheError, match="64 lowercase hex"):
        cache.path("../" + sha[3:])
    assert cache.get(sha) is None and not list(tmp_path.iterdir())


def test_concurrent_writers_leave_one_whole_file(person_model: Path, tmp_path: Path) -> None:
    """Receivers that fetched the same model at once: each renames its own temporary file
    over the same name; the result is the whole file and no temporary is left behind."""
    data = person_model.read_bytes()
    model = verify_model(data, hashlib.sha256(data).hexdigest())
    cache = ModelCache(tmp_path / "models")
    seen: list[bool] = []
    writers = [threading.Thread(target=cache.put, args=(data, model)) for _ in range(6)]

    def reader() -> None:
        path = cache.path(model.sha256)
        while any(w.is_alive() for w in writers) or not seen:
            if path.exists():
                seen.append(hashlib.sha256(path.read_bytes()).hexdigest() == model.sha256)

    threads = [*writers, threading.Thread(target=reader)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert cache.get(model.sha256).sha256 == model.sha256
    assert (tmp_path / "models" / f"{model.sha256}.fwm").read_bytes() == data
    assert [p.name for p in (tmp_path / "models").iterdir()] == [f"{model.sha256}.fwm"]
    assert all(seen)  # a reader never saw a partial file (only none, or the whole one)
    assert os.stat(tmp_path / "models").st_mode & 0o077 == 0  # private: a person's face


def test_default_cache_folder(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("FACEWIRE_CACHE", str(tmp_path / "c"))
    assert default_folder() == tmp_path / "c"
    monkeypatch.delenv("FACEWIRE_CACHE")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_folder() == tmp_path / ".cache" / "facewire" / "models"


# -- the receive loop ------------------------------------------------------------------------

def test_a_model_that_is_not_the_senders_is_refused(log, generic_model: Path,
                                                     tmp_path: Path) -> None:
    port = _free_port_pair()
    sender = LogSender(port, log.hello, b"x", log.packets, count=0)
    try:
        with pytest.raises(ReceiveError, match="is not the sender's model"):
            receive(f"tcp://127.0.0.1:{port}", model_path=generic_model,
                    out=tmp_path / "x.mp4", idle_timeout_s=10)
        assert sender.requests["hello_request"] == 1 and not sender.requests["model_request"]
        assert not (tmp_path / "x.mp4").exists()
    finally:
        sender.stop()


def test_the_video_has_one_frame_per_packet_received(log, person_model: Path,
                                                     tmp_path: Path) -> None:
    """Junk between the packets is counted as corrupt and changes nothing else."""
    port = _free_port_pair()
    go, lines = threading.Event(), []
    sender = LogSender(port, log.hello, person_model.read_bytes(), log.packets, count=40,
                       go=go, junk_every=8)
    out = tmp_path / "live.mp4"
    packets: list[tuple[bytes, float]] = []
    ready = threading.Event()
    try:
        summary = receive(f"tcp://127.0.0.1:{port}", model_path=person_model, out=out,
                          size=SIZE, status=_ready(go, lines), idle_timeout_s=1.0,
                          on_packet=lambda *a: packets.append(a), ready=ready)
    finally:
        sender.stop()
    assert ready.is_set()
    assert sender.sent == 40 and sender.junk == 15
    # on_packet sees every message taken from the socket, junk too, in arrival order
    assert len(packets) == 55 and sum(len(d) == PACKET_BYTES for d, _ in packets) >= 40
    assert all(a <= b for (_, a), (_, b) in zip(packets, packets[1:]))
    assert summary["ended"] == "idle_timeout" and summary["model_source"] == "file"
    assert not sender.requests["model_request"]
    assert summary["received"] == 40 and summary["corrupt"] == 15
    assert summary["frames"] == 40 and summary["lost"] == 0
    frames = _video_frames(out)
    assert len(frames) == summary["frames"]
    assert frames[0].shape == (SIZE[1], SIZE[0], 3)
    assert all(f.mean() > 5 for f in frames)  # a face in every frame
    assert summary["fps"] == pytest.approx(25, rel=0.2)
    assert summary["kbps"] > 7  # 43-byte packets at 25 Hz, plus the junk
    assert 0 < summary["latency_ms_median"] < 400  # played on arrival (bench speed times it)


def _receive_fast(log, person_model: Path, keep_up: bool, out: Path | None = None
                  ) -> tuple[dict, list[bytes]]:
    """120 packets at 1000 Hz, far faster than any draw, received into ``on_frame`` (and
    ``out``) at 320x240; the summary and each output frame's sha256."""
    port = _free_port_pair()
    go, lines = threading.Event(), []
    hello = dataclasses.replace(log.hello, rate_hz=1000.0)
    sender = LogSender(port, hello, person_model.read_bytes(), log.packets, count=120, go=go)
    digests: list[bytes] = []
    try:
        summary = receive(f"tcp://127.0.0.1:{port}", person_model, out,
                          size=(320, 240), status=_ready(go, lines), idle_timeout_s=1.0,
                          audio=False, on_frame=lambda image, _: digests.append(
                              hashlib.sha256(image).digest()), keep_up=keep_up)
    finally:
        sender.stop()
    assert sender.sent == 120
    return summary, digests


def test_keep_up_repeats_the_overtaken_slots_and_bounds_the_latency(
        log, person_model: Path) -> None:
    """A renderer slower than the stream: by default every slot is drawn and the latency
    grows with the backlog; with ``keep_up`` every slot is still one output frame, but a slot
    already overtaken repeats the frame out before it (not drawn), so the latency stays
    within a few draws."""
    every, every_frames = _receive_fast(log, person_model, keep_up=False)
    kept, kept_frames = _receive_fast(log, person_model, keep_up=True)
    for summary, frames in ((every, every_frames), (kept, kept_frames)):
        # at 1 ms a slot, a stall of the machine can make a packet late: its slot concealed
        assert summary["frames"] == len(frames) >= 108 and summary["skipped"] == 0
    assert every["repeated"] == 0
    assert kept["repeated"] >= kept["frames"] // 2  # a draw takes well over a 1-ms slot
    same = sum(a == b for a, b in zip(kept_frames, kept_frames[1:]))
    assert same >= kept["repeated"]  # each repeat is its predecessor's image
    assert kept["latency_ms_p95"] < every["latency_ms_p95"] / 3


def test_keep_up_holds_in_the_file_what_it_repeats(log, person_model: Path,
                                                   tmp_path: Path) -> None:
    """With ``keep_up`` and a video file, a repeated slot is a hold (the frame before lasts,
    not encoded: receiver.output), so an encoder slower than the stream cannot hold the loop
    back: the file has the stream's timeline, one slot per output frame, and only the frames
    drawn in it."""
    out = tmp_path / "kept.mp4"
    summary, _ = _receive_fast(log, person_model, keep_up=True, out=out)
    decoded = list(read_frames(out))
    drawn = summary["frames"] - summary["repeated"]
    assert summary["repeated"] >= summary["frames"] // 2
    assert len(decoded) in (drawn, drawn + 1)  # + 1: the last frame again, after holds
    assert round(decoded[-1].time * 1000) == summary["frames"] - 1  # 1000 Hz: 1 ms a slot


def test_lost_packets_become_concealed_frames_and_bad_control_replies_are_retried(
        log, person_model: Path, tmp_path: Path) -> None:
    """Every 7th packet is lost on the way: its slot is concealed and still one frame (frames
    == received + lost). The first Hello and the first chunk get wrong answers: counted,
    asked again, and the model still arrives whole."""
    port = _free_port_pair()
    go, lines = threading.Event(), []
    sender = LogSender(port, log.hello, person_model.read_bytes(), log.packets, count=40,
                       go=go, drop_every=7, faulty=(1, 3))
    out = tmp_path / "frames"
    shown: list[tuple[np.ndarray, FrameState]] = []
    try:
        summary = receive(f"tcp://127.0.0.1:{port}", frames_dir=out, size=SIZE,
                          cache_dir=tmp_path / "cache", status=_ready(go, lines),
                          idle_timeout_s=1.0, on_frame=lambda *a: shown.append(a))
    finally:
        sender.stop()
    assert summary["control_errors"] == 2 and summary["model_source"] == "fetched"
    assert sender.requests["hello_request"] == 2
    assert sender.requests["model_request"] == len(sender.chunks) + 1
    assert sender.dropped == 5 and summary["received"] == 35
    assert summary["lost"] == 5 and summary["frames"] == 40
    assert len(list(out.glob("frame_*.png"))) == 40
    # on_frame sees the same 40 output frames, the concealed slots rendered too, in order
    assert len(shown) == 40 and sum(s.arrival_s is None for _, s in shown) == 5
    assert all(i.shape == (SIZE[1], SIZE[0], 3) and i.mean() > 5 for i, _ in shown)
    seqs = [s.seq for _, s in shown]
    assert all((b - a) % 65536 == 1 for a, b in zip(seqs, seqs[1:]))


def test_a_restarted_sender_with_a_new_model_is_followed(log, person_model: Path,
                                                         generic_model: Path,
                                                         tmp_path: Path) -> None:
    """The sender stops after 30 packets and a new one (another model) takes its address,
    numbering from 0 again: the receiver fetches the new Hello and model and renders it."""
    port = _free_port_pair()
    go, lines = threading.Event(), []
    first = LogSender(port, log.hello, person_model.read_bytes(), log.packets, count=30,
                      go=go, first_seq=1000)
    out = tmp_path / "restart.mp4"
    thread, _, result = start(receive, connect=f"tcp://127.0.0.1:{port}", out=out,
                              cache_dir=tmp_path / "cache", size=SIZE,
                              status=_ready(go, lines), idle_timeout_s=1.5)
    try:
        assert first.done.wait(20)
        time.sleep(0.3)
        first.stop()
        hello = _hello_for(generic_model, log.hello)
        second = LogSender(port, hello, generic_model.read_bytes(), log.packets, count=60)
        assert second.done.wait(20)
        thread.join(30)
        second.stop()
    finally:
        first.stop()
    assert not thread.is_alive() and result, "receive did not end"
    assert result["ended"] == "idle_timeout"
    assert second.requests["hello_request"] >= 1 and second.requests["model_request"] >= 1
    assert result["model_sha256"] == hello.model_sha256 and result["streams"] == 2
    assert result["received"] >= 60  # (the new sender's first packets may go before the
    # receiver has reconnected, and those that come while the model is fetched are ignored)
    frames = _video_frames(out)
    assert len(frames) == result["frames"] >= 30 + 20
    person, generic = frames[5].astype(float), frames[-1].astype(float)
    face = generic.max(axis=2) > 20
    assert face.mean() > 0.05  # the new stream renders a face...
    grey = np.abs(generic[face] - generic[face].mean(axis=1, keepdims=True)).mean()
    skin = np.abs(person[person.max(axis=2) > 20]
                  - person[person.max(axis=2) > 20].mean(axis=1, keepdims=True)).mean()
    assert grey < 8 < skin  # ...with the new model's flat grey texture, not the person's


def test_a_restarted_sender_with_the_same_model_resumes(log, person_model: Path,
                                                        tmp_path: Path) -> None:
    port = _free_port_pair()
    go, lines = threading.Event(), []
    data = person_model.read_bytes()
    first = LogSender(port, log.hello, data, log.packets, count=30, go=go, first_seq=500)
    shown: list[tuple[tuple[int, ...], dict]] = []
    thread, _, result = start(receive, connect=f"tcp://127.0.0.1:{port}",
                              model_path=person_model, size=SIZE,
                              view=lambda rgb, stats: shown.append((rgb.shape, stats)),
                              status=_ready(go, lines), idle_timeout_s=1.5)
    try:
        assert first.done.wait(20)
        time.sleep(0.3)
        first.stop()
        later = threading.Event()  # a restarting sender takes a moment (model, camera), in
        threading.Timer(0.5, later.set).start()  # which the receiver reconnects
        second = LogSender(port, log.hello, data, log.packets, count=30, go=later)
        assert second.done.wait(20)
        thread.join(30)
        second.stop()
    finally:
        first.stop()
    assert not thread.is_alive() and result
    assert result["streams"] == 2 and result["restarts"] >= 1
    assert second.requests["hello_request"] >= 1  # the Hello was asked again
    assert result["received"] == 60
    # the new stream plays from its first packets: at most the two the resync needs are lost
    assert result["frames"] >= 58 and result["frames"] == result["received"] - \
        result["late"] - result["discarded"] - result["duplicates"] - result["stray"]
    assert any("restarted" in line for line in lines)
    # the live view saw every frame, and the concealed slots between the streams too
    assert len(shown) > result["frames"]
    assert all(shape == (SIZE[1], SIZE[0], 3) for shape, _ in shown)
    assert all(tuple(stats) == LIVE_KEYS for _, stats in shown)
    assert shown[-1][1]["received"] == result["received"]


def test_with_keys_the_stream_and_the_model_come_only_to_an_authorised_receiver(
        log, person_model: Path, tmp_path: Path) -> None:
    for name in ("sender", "good", "stranger"):
        generate_keys(tmp_path / name)
    shutil.copy(tmp_path / "good/id.key", tmp_path / "sender/authorized/good.key")
    for name in ("good", "stranger"):
        shutil.copy(tmp_path / "sender/id.key", tmp_path / f"{name}/authorized/sender.key")
    port = _free_port_pair()
    sender = LogSender(port, log.hello, person_model.read_bytes(), log.packets,
                       count=10**6, curve=server_keys(tmp_path / "sender"))
    try:
        good = receive(f"tcp://127.0.0.1:{port}", curve_dir=tmp_path / "good",
                       cache_dir=tmp_path / "cache", size=SIZE, max_frames=3,
                       idle_timeout_s=10)
        assert good["frames"] == 3 and good["model_source"] == "fetched"
        requests = sender.requests.total()
        lines: list[str] = []
        stranger = receive(f"tcp://127.0.0.1:{port}", curve_dir=tmp_path / "stranger",
                           cache_dir=tmp_path / "cache2", status=lines.append,
                           idle_timeout_s=1.5)
        assert stranger["received"] == 0 and stranger["model_sha256"] is None
        assert sender.requests.total() == requests  # not one request got through
        assert lines and all("waiting for a sender" in line for line in lines)
    finally:
        sender.stop()


def test_without_a_sender_it_waits_with_a_status_then_ends_on_the_idle_timeout(
        tmp_path: Path) -> None:
    port = _free_port_pair()
    lines: list[str] = []
    tick = time.monotonic()
    summary = receive(f"tcp://127.0.0.1:{port}", out=tmp_path / "none.mp4",
                      status=lines.append, idle_timeout_s=1.5)
    assert 1.4 < time.monotonic() - tick < 4
    assert summary["ended"] == "idle_timeout" and summary["frames"] == 0
    assert summary["model_sha256"] is None and summary["control_timeouts"] >= 1
    assert lines and all("waiting for a sender" in line for line in lines)
    assert f"127.0.0.1:{port}" in lines[0]
    assert not (tmp_path / "none.mp4").exists()


def test_stop_event_ends_a_waiting_receiver(tmp_path: Path) -> None:
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    summary = receive(f"tcp://127.0.0.1:{_free_port_pair()}", stop=stop)
    assert summary["ended"] == "stop"


def test_bad_arguments_are_refused_before_connecting(tmp_path: Path) -> None:
    with pytest.raises(ReceiveError, match="one or the other"):
        receive("tcp://127.0.0.1:5555", out=tmp_path / "a.mp4", frames_dir=tmp_path / "f")
    with pytest.raises(ReceiveError, match="size"):
        receive("tcp://127.0.0.1:5555", size=(0, 10))
    with pytest.raises(ReceiveError, match="callable"):
        receive("tcp://127.0.0.1:5555", view=5)
    with pytest.raises(ReceiveError, match="on_frame"):
        receive("tcp://127.0.0.1:5555", on_frame=5)
    with pytest.raises(ReceiveError, match="ready"):
        receive("tcp://127.0.0.1:5555", ready=True)
    with pytest.raises(TransportError):
        receive("udp://nowhere", idle_timeout_s=1)


def test_a_live_picture_of_a_phone_camera_is_rendered_at_most_live_size(
        log, person_model: Path, tmp_path: Path) -> None:
    """A phone's 1080x1920 camera: with ``keep_up`` (a live picture) and no --size, the
    output is scaled to LIVE_SIZE on its longer side (540x960), which this machine draws at
    the stream's rate; a recording keeps the camera's size."""
    cam = log.hello.camera
    sx, sy = 1080 / cam.width, 1920 / cam.height
    phone = dataclasses.replace(cam, fx=cam.fx * sx, fy=cam.fy * sy, cx=cam.cx * sx,
                                cy=cam.cy * sy, width=1080, height=1920)
    hello = _hello_for(person_model, dataclasses.replace(log.hello, camera=phone))
    sizes = {}
    for keep_up in (True, False):
        port = _free_port_pair()
        go, lines = threading.Event(), []
        sender = LogSender(port, hello, person_model.read_bytes(), log.packets, count=10,
                           go=go)
        try:
            sizes[keep_up] = receive(
                f"tcp://127.0.0.1:{port}", model_path=person_model, max_frames=2,
                frames_dir=tmp_path / f"frames_{keep_up}", idle_timeout_s=20, audio=False,
                status=_ready(go, lines), keep_up=keep_up)
        finally:
            sender.stop()
    assert LIVE_SIZE == 960
    assert (sizes[True]["width"], sizes[True]["height"]) == (540, 960)
    assert (sizes[False]["width"], sizes[False]["height"]) == (1080, 1920)


def test_an_oversized_sender_camera_is_rendered_at_most_max_size(log, person_model: Path,
                                                                   tmp_path: Path) -> None:
    """A Hello may announce a 16384-pixel camera; without --size the output is scaled down
    to MAX_SIZE on its longer side, keeping the aspect (8192 x 1024 -> 4096 x 512)."""
    cam = log.hello.camera
    wide = dataclasses.replace(cam, fx=cam.fx * 16, fy=cam.fy * 2, cx=cam.cx * 16,
                               cy=cam.cy * 2, width=8192, height=1024)
    hello = _hello_for(person_model, dataclasses.replace(log.hello, camera=wide))
    port = _free_port_pair()
    # sent once the receiver plays: PUB drops what is sent before the receiver subscribed,
    # and on a loaded machine its model load alone outlasts the ten packets
    go, lines = threading.Event(), []
    sender = LogSender(port, hello, person_model.read_bytes(), log.packets, count=10, go=go)
    try:
        summary = receive(f"tcp://127.0.0.1:{port}", model_path=person_model,
                          frames_dir=tmp_path / "frames", max_frames=2, idle_timeout_s=20,
                          status=_ready(go, lines))
    finally:
        sender.stop()
    assert (summary["width"], summary["height"]) == (MAX_SIZE, MAX_SIZE // 8)
    frames = sorted((tmp_path / "frames").glob("*.png"))
    assert len(frames) == 2
    assert cv2.imread(str(frames[0])).shape[:2] == (MAX_SIZE // 8, MAX_SIZE)
