"""The live sender over real ZeroMQ sockets on 127.0.0.1: Hello, model by chunks, packets, log."""

from __future__ import annotations

import hashlib
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
import zmq
from conftest import free_endpoint, start

from facewire.protocol.control import (
    ChunkAssembler,
    Error,
    Hello,
    HelloRequest,
    ModelChunk,
    ModelRequest,
    decode_message,
)
from facewire.protocol.keys import client_keys, generate_keys
from facewire.protocol.log import LogError, read_log
from facewire.protocol.packet import decode
from facewire.protocol.transport import (
    ControlClient,
    ControlServer,
    PacketPublisher,
    PacketSubscriber,
    control_endpoint,
)
from facewire.sender.capture import CaptureError, open_source
from facewire.sender.sender import MAX_LAG_S, _frames, send, unencrypted_warning
from facewire.sender.slots import SlotClock

TIMEOUT_MS = 30_000  # the first Hello waits for the sender to load the model and the tracker


def fetch_model(client: ControlClient, hello: Hello) -> tuple[bytes, int]:
    """The model announced by the Hello, chunk by chunk, verified; and the chunk count."""
    assembler = ChunkAssembler(hello.model_sha256, hello.model_bytes)
    for index in assembler.missing():
        chunk = client.request(ModelRequest(hello.model_sha256, index), 5000)
        assert isinstance(chunk, ModelChunk), chunk
        assembler.add(chunk)
    return assembler.result(), assembler.count


def raw_request(endpoint: str, body: bytes) -> object:
    """Send arbitrary bytes as a request on a plain DEALER; the decoded reply."""
    with zmq.Context.instance().socket(zmq.DEALER) as dealer:
        dealer.linger = 0
        dealer.connect(endpoint)
        dealer.send_multipart([b"", body])
        assert dealer.poll(5000, zmq.POLLIN)
        return decode_message(dealer.recv_multipart()[-1])


def test_live_sender_serves_the_hello_the_model_and_every_packet(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """lp_d0.mp4 (78 frames, 25 Hz) sent in real time to two subscribers, one of which leaves."""
    endpoint, log_path = free_endpoint(), tmp_path / "live.fwlog"
    statuses: list[dict[str, Any]] = []
    with PacketSubscriber(endpoint) as sub, PacketSubscriber(endpoint) as leaver, \
            ControlClient(control_endpoint(endpoint)) as client:
        thread, _, result = start(
            send, model_path=person_model, source=str(shared_data / "video" / "lp_d0.mp4"),
            bind=endpoint, record=log_path, status=statuses.append)
        hello = client.request(HelloRequest(), TIMEOUT_MS)
        assert isinstance(hello, Hello), result
        file_bytes = person_model.read_bytes()
        assert hello.model_sha256 == hashlib.sha256(file_bytes).hexdigest()
        assert hello.rate_hz == 25.0  # the file's rate, below the 30 Hz target
        data, count = fetch_model(client, hello)
        assert data == file_bytes and count == -(-len(file_bytes) // (256 * 1024))

        # bad requests get an Error each, and the sender keeps serving
        control = control_endpoint(endpoint)
        assert "bad request" in raw_request(control, b"\xc1 not msgpack").message
        reply = client.request(ModelRequest("0" * 64, 0), 5000)
        assert isinstance(reply, Error) and hello.model_sha256 in reply.message
        reply = client.request(ModelRequest(hello.model_sha256, count), 5000)
        assert isinstance(reply, Error) and "out of range" in reply.message
        reply = client.request(hello, 5000)
        assert isinstance(reply, Error) and "not a request" in reply.message
        again = client.request(HelloRequest(), 5000)  # the clock: announced from frame 1 on
        assert isinstance(again, Hello) and replace(again, clock_origin_s=None) == \
            replace(hello, clock_origin_s=None)

        received: list[bytes] = []
        left_at = None
        while thread.is_alive():
            packet = sub.recv(20)
            if packet is not None:
                received.append(packet)
            if left_at is None and len(received) >= 10:
                leaver.close()  # a receiver goes away mid-stream
                left_at = len(received)
        while (packet := sub.recv(300)) is not None:
            received.append(packet)
        thread.join()

    assert "error" not in result, result.get("error")
    assert result["stopped"] == "end" and result["frames"] == result["packets"] == 78
    assert result["face_frames"] >= 70
    # paced to real time: never faster (a loaded machine may make it slower, never by much)
    assert 0.95 * 77 / 25 <= result["seconds"] < 3 * 77 / 25
    assert result["control"] == {"hello_requests": 2, "chunk_requests": count,
                                 "update_requests": 0, "update_bytes": 0, "time_requests": 0,
                                 "errors": 4}
    assert result["receivers_max"] == 2 and statuses and statuses[-1]["receivers"] == 1
    assert {"fps", "payload_kbps", "face", "receivers"} <= statuses[-1].keys()
    assert left_at is not None and len(received) > left_at + 30  # the sender went on

    log = read_log(log_path)
    assert log.lost == 0 and log.hello == replace(hello, clock_origin_s=None)
    assert len(log.packets) == 78
    assert np.all(np.diff(log.times) > 0)
    published = [p.tobytes() for p in log.packets]
    assert len(received) >= 60 and received == published[-len(received):]
    seqs = np.array([decode(p).seq for p in received])
    assert np.all(np.diff(seqs) > 0)  # consecutive but where the sender was late (slots)


@pytest.fixture()
def grey_clip(grey_video: Callable[..., Path]) -> Path:
    """A real H.264 clip of 6 flat grey frames (no face) at 25 Hz: 0.24 s."""
    return grey_video("grey.mp4", frames=6)


def test_stop_event_ends_a_looping_send_cleanly(generic_model: Path, grey_clip: Path,
                                                 tmp_path: Path) -> None:
    endpoint, log_path = free_endpoint(), tmp_path / "loop.fwlog"
    with ControlClient(control_endpoint(endpoint)) as client:
        thread, stop, result = start(send, model_path=generic_model, source=str(grey_clip),
                                            bind=endpoint, record=log_path, loop=True)
        assert isinstance(client.request(HelloRequest(), TIMEOUT_MS), Hello), result
        time.sleep(1.0)
        stop.set()
        thread.join(10)
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert result["stopped"] == "stop" and result["frames"] > 12  # looped the 6 frames
    assert result["face_frames"] == 0
    log = read_log(log_path)
    assert log.lost == 0 and len(log.packets) == result["packets"]
    seqs = log.frames["seq"].astype(np.int64)
    assert seqs[0] == 0 and np.all(np.diff(seqs) > 0)  # one stream across the loops
    # the sockets are closed: both ports can be bound again
    with PacketPublisher(endpoint), ControlServer(control_endpoint(endpoint)):
        pass


def test_start_holds_the_first_frame_and_frames_picks_the_file_s_range(
        generic_model: Path, grey_video: Callable[..., Path], tmp_path: Path) -> None:
    """Frames 4:10 of a 12-frame clip, held until ``start`` is set while the Hello is served;
    a send stopped while held sends nothing."""
    clip = grey_video("grey12.mp4", frames=12)
    endpoint, log_path = free_endpoint(), tmp_path / "range.fwlog"
    go = threading.Event()
    with PacketSubscriber(endpoint) as sub, ControlClient(control_endpoint(endpoint)) as client:
        thread, _, result = start(send, model_path=generic_model, source=str(clip),
                                  bind=endpoint, record=log_path, frames=slice(4, 10), start=go)
        assert isinstance(client.request(HelloRequest(), TIMEOUT_MS), Hello), result
        assert sub.recv(1000) is None and thread.is_alive()  # held
        go.set()
        received = []
        while (packet := sub.recv(3000)) is not None:
            received.append(packet)
        thread.join(10)
    assert "error" not in result, result.get("error")
    assert result["stopped"] == "end" and result["frames"] == result["packets"] == 6
    seqs = [decode(p).seq for p in received]
    assert seqs[0] == 0 and len(seqs) == 6 and np.all(np.diff(seqs) > 0)
    assert len(read_log(log_path).packets) == 6

    endpoint = free_endpoint()
    with ControlClient(control_endpoint(endpoint)) as client:
        thread, stop, result = start(send, model_path=generic_model, source=str(clip),
                                     bind=endpoint, start=threading.Event())
        assert isinstance(client.request(HelloRequest(), TIMEOUT_MS), Hello), result
        stop.set()
        thread.join(10)
    assert not thread.is_alive() and result["stopped"] == "stop" and result["packets"] == 0


@pytest.fixture()
def keys(tmp_path: Path) -> Path:
    """Sender keys trusting 'good'; 'good' and 'stranger' both trust the sender."""
    for name in ("sender", "good", "stranger"):
        generate_keys(tmp_path / name)
    shutil.copy(tmp_path / "good/id.key", tmp_path / "sender/authorized/good.key")
    for name in ("good", "stranger"):
        shutil.copy(tmp_path / "sender/id.key", tmp_path / f"{name}/authorized/sender.key")
    return tmp_path


def test_curve_sender_serves_only_authorised_receivers(generic_model: Path, grey_clip: Path,
                                                       keys: Path) -> None:
    endpoint = free_endpoint()
    control = control_endpoint(endpoint)
    good, stranger = client_keys(keys / "good"), client_keys(keys / "stranger")
    with PacketSubscriber(endpoint, good) as sub, ControlClient(control, good) as client, \
            PacketSubscriber(endpoint, stranger) as intruder, \
            ControlClient(control, stranger) as intruder_client:
        thread, stop, result = start(send, model_path=generic_model, source=str(grey_clip),
                                            bind=endpoint, curve_dir=keys / "sender",
                                            loop=True)
        hello = client.request(HelloRequest(), TIMEOUT_MS)
        assert isinstance(hello, Hello), result
        data, _ = fetch_model(client, hello)
        assert data == generic_model.read_bytes()
        assert sub.recv(5000) is not None
        assert intruder.recv(500) is None
        assert intruder_client.request(HelloRequest(), 500) is None
        stop.set()
        thread.join(10)
    assert result["encrypted"] and result["warning"] is None


def test_missing_or_empty_sources_are_clear_errors(generic_model: Path, tmp_path: Path) -> None:
    log_path = tmp_path / "never.fwlog"
    with pytest.raises(CaptureError, match="camera:9: no camera"):
        send(generic_model, "camera:9", bind=free_endpoint(), record=log_path)
    empty = tmp_path / "empty.mkv"  # a container with a video stream and no frame
    with av.open(str(empty), "w") as container:
        stream = container.add_stream("ffv1", rate=25)
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
    with pytest.raises(CaptureError, match="empty.mkv"):
        send(generic_model, str(empty), bind=free_endpoint(), record=log_path)
    with pytest.raises(CaptureError, match="no such file"):
        send(generic_model, str(tmp_path / "missing.mp4"), bind=free_endpoint())
    assert not log_path.exists()


def test_an_unwritable_log_is_a_clear_error(generic_model: Path, grey_clip: Path,
                                            tmp_path: Path) -> None:
    endpoint = free_endpoint()
    with pytest.raises(LogError, match="no/such/folder/x.fwlog: cannot write"):
        send(generic_model, str(grey_clip), bind=endpoint,
             record=tmp_path / "no/such/folder/x.fwlog")
    with PacketPublisher(endpoint), ControlServer(control_endpoint(endpoint)):
        pass  # the sockets it had bound were closed


def test_unencrypted_warning_only_off_loopback() -> None:
    for bind in ("tcp://127.0.0.1:5555", "tcp://localhost:5555", "tcp://[::1]:5555",
                 "tcp://lo:5555", "tcp://127.1.2.3:80"):
        assert unencrypted_warning(bind, None) is None, bind
    for bind in ("tcp://*:5555", "tcp://0.0.0.0:5555", "tcp://192.168.1.20:5555",
                 "tcp://[::]:5555", "tcp://eth0:5555", "tcp://camera-host:5555"):
        warning = unencrypted_warning(bind, None)
        assert warning is not None and "unencrypted" in warning and bind in warning, bind
        assert unencrypted_warning(bind, "keys") is None


def test_a_variable_rate_file_is_resampled_to_the_rate_s_slots(tmp_path: Path) -> None:
    """15 Hz, then 12.5 Hz: every slot of 1/15 s gets the latest frame by its quarter-period
    tolerance, repeated where the file has none; the stamps are the slots' own times."""
    times_ms = [0, 67, 133, 200, 267, 333, 413, 493, 573, 653, 733, 813]
    path = tmp_path / "vfr.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=15)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.codec_context.time_base = Fraction(1, 1000)
        for i, t in enumerate(times_ms):
            frame = av.VideoFrame.from_ndarray(np.full((48, 64, 3), 10 + 20 * i, np.uint8),
                                               format="bgr24")
            frame.pts, frame.time_base = t, Fraction(1, 1000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    with open_source(str(path)) as source:
        sent = list(_frames(source, SlotClock(15.0, MAX_LAG_S), False, threading.Event()))
    slots = np.arange(len(sent)) / 15.0
    np.testing.assert_allclose([t for _, t, _ in sent], slots, atol=1e-9)
    assert len(sent) == 13  # 0.813 s of frames: slots 0 .. 12
    numbers = [n for _, _, n in sent]  # the slots' numbers: late ones skip ahead (slots.py)
    assert numbers[0] == 0 and np.all(np.diff(numbers) > 0)
    expected = [max(j for j, t in enumerate(times_ms) if t / 1000 <= s + 0.25 / 15)
                for s in slots]
    got = [round((image.mean() - 10) / 20) for image, _, _ in sent]
    assert got == expected
    assert sorted(set(got)) == list(range(12))  # every frame sent, one of them twice
