"""Model updates on a real loopback link (issue 17, part 2): fetched whatever goes wrong,
refused when bad, and never changing what was played.

Real parts throughout: the sender's control thread and update store (``updatesender``: the
real ``Responder`` on a real ``ControlServer``, packets of a real log, lp_d0.mp4 encoded with
its own model, each carrying the newest serial), the real receiver (``receiver.receiver``,
``receiver.updates.UpdateFetcher``), ZeroMQ on loopback, the lossy relay of ``lossy`` and the
real ``facewire relay``; the updates are real (``learned``: in-between states made of the
model's own layers, encoded by ``models.update.encode_update``) or real ones damaged.

- 30 % packet loss during two updates: every output frame is pixel-equal to its state
  rendered with the model version its packet named (or, while that update was on the way, an
  older one: ``clamped`` counts exactly those), and the first update shows within 3 s;
- a reply lost, a chunk corrupted, a whole that fails its hash: each is asked again, counted
  (``control_timeouts``, ``control_errors``, ``updates_refused``) and the update applied;
- malformed updates (sizes, NaN, a layer index out of range, a decompression bomb) are
  refused with one line naming the field, while the receiver keeps rendering at its version;
- a receiver stopped mid-session and started again, behind ``facewire relay``, catches up to
  the sender's version (late joiners get every update);
- fuzzed update requests never break the sender's control thread, and fuzzed update chunks
  never decode into anything invalid;
- the real ``facewire send``, learning, publishes what it learns and logs it, and its
  receiver reaches the same version.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from conftest import free_endpoint, start
from logsender import encoded_log, free_port_pair
from lossy import Faults, LossyRelay
from sessionlog import mouth_states, session_updates
from updatesender import UpdateSender

from facewire.models.modelfile import load_model, save_model
from facewire.protocol.control import (
    ControlError,
    Error,
    UpdateChunk,
    UpdateRequest,
    decode_message,
    encode_message,
)
from facewire.protocol.log import read_log
from facewire.protocol.relay import relay
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import control_endpoint
from facewire.receiver import updates as receiver_updates
from facewire.receiver.receiver import receive
from facewire.receiver.scene import StateRenderer
from facewire.receiver.updates import UpdateFetcher
from facewire.sender.responder import answer_request
from facewire.sender.sender import send
from facewire.sender.updates import UpdateStore

RATE_HZ = 30.0
SIZE = (64, 48)
FAST = (10**9, 1.1, (1e9, 1e9))  # a shaper that holds nothing, for tests not about rate
FIRST_APPLIED_S = 3.0


@pytest.fixture(scope="module")
def stream(person_model: Path, shared_data: Path) -> dict[str, Any]:
    model = load_model(person_model)
    log = encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    data, versions = session_updates(model, 2, regions=("mouth",))
    return {"path": person_model, "model": model, "log": log, "data": data,
            "versions": versions, "hello": dataclasses.replace(log.hello, rate_hz=RATE_HZ)}


def _sender(stream: dict[str, Any], count: int, issue: dict[int, bytes] | None = None,
            go: threading.Event | None = None, shaper: UpdateShaper | None = None
            ) -> tuple[UpdateSender, str]:
    port = free_port_pair()
    sender = UpdateSender(port, stream["hello"], stream["path"].read_bytes(),
                          stream["log"].packets, count, issue, go,
                          shaper or UpdateShaper(*FAST))
    return sender, f"tcp://127.0.0.1:{port}"


def _wait(condition: Any, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_updates_under_30_percent_loss_change_nothing_that_was_played(
        stream: dict[str, Any], tmp_path: Path) -> None:
    go = threading.Event()
    data = stream["data"]
    sender, inp = _sender(stream, 150, {20: data[0], 75: data[1]}, go, UpdateShaper())
    out = free_endpoint()
    lossy = LossyRelay(inp, out, seed=5, faults=(Faults(10, 10**6, loss=0.3),))
    frames: list[tuple[float, np.ndarray, Any]] = []
    issued: dict[int, float] = {}
    lines: list[tuple[float, str]] = []
    thread, stop, result = start(
        receive, connect=out, model_path=stream["path"], size=SIZE, cache_dir=tmp_path,
        ready=go, on_frame=lambda image, state: frames.append((time.monotonic(), image, state)),
        status=lambda line: lines.append((time.monotonic(), line)))
    try:
        assert go.wait(60), "the receiver did not get ready"
        _wait(lambda: sender.store.serial >= 1, 10, "update 1 was not issued")
        issued[1] = time.monotonic()
        _wait(lambda: sender.store.serial >= 2, 10, "update 2 was not issued")
        issued[2] = time.monotonic()
        assert sender.done.wait(20)
        _wait(lambda: not lossy.holding, 5, "the relay held packets")
        time.sleep(0.5)
    finally:
        stop.set()
        thread.join(30)
        sender.stop()
        lossy.stop()
    summary = result
    assert "error" not in summary, summary.get("error")
    assert summary["updates"] == 2 and summary["updates_refused"] == 0
    assert summary["model_serial"] == 2
    assert summary["lost"] > 20  # the loss was real
    versions = stream["versions"]
    renderers = [StateRenderer(v, *SIZE, stream["hello"].camera) for v in versions]
    version = 0  # the oldest version the receiver can have rendered with so far
    try:
        for _, image, state in frames:
            match = [v for v in range(version, state.serial + 1)
                     if np.array_equal(renderers[v].render(state), image)]
            assert match, (f"slot {state.seq}: not the render of a version in "
                           f"[{version}, {state.serial}]")
            version = match[0]  # versions are taken in order, never given back
    finally:
        for r in renderers:
            r.release()
    assert max(state.serial for _, _, state in frames) == 2
    fetched = next(t for t, line in lines if line.startswith("model update 1 fetched"))
    shown = next(t for t, _, state in frames if t >= fetched and state.serial >= 1)
    assert shown - issued[1] < FIRST_APPLIED_S, shown - issued[1]


def _fetch(stream: dict[str, Any], endpoint: str, target: int, seconds: float = 20
           ) -> tuple[UpdateFetcher, list[str]]:
    lines: list[str] = []
    fetcher = UpdateFetcher(endpoint, None, stream["model"], lines.append)
    fetcher.want(target)
    deadline = time.monotonic() + seconds
    while fetcher.fetched < target and time.monotonic() < deadline:
        time.sleep(0.02)
    fetcher.close()
    return fetcher, lines


def test_a_lost_a_corrupt_and_a_wrongly_hashed_chunk_are_each_fetched_again(
        stream: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(receiver_updates, "CHUNK_TIMEOUT_S", 0.5)
    sender, inp = _sender(stream, 0)
    sender.publish(stream["data"][0])
    seen: list[int] = []

    def damage(reply: list[bytes]) -> list[bytes] | None:
        body = msgpack.unpackb(reply[-1], raw=False)
        if body.get("type") != "update_chunk":
            return reply
        seen.append(body["index"])
        n = len(seen)
        if n == 1:
            return None  # lost
        if n == 2:
            body["data"] = bytes([body["data"][0] ^ 1]) + body["data"][1:]  # corrupt
        if n == 3:  # self-consistent, but not the update's: the whole fails its hash
            body["data"] = bytes(len(body["data"]))
            body["data_sha256"] = hashlib.sha256(body["data"]).hexdigest()
        return [*reply[:-1], msgpack.packb(body, use_bin_type=True)]

    out = free_endpoint()
    lossy = LossyRelay(inp, out, replies=damage)
    try:
        fetcher, lines = _fetch(stream, control_endpoint(out), 1)
    finally:
        lossy.stop()
        sender.stop()
    assert fetcher.fetched == 1, lines
    assert fetcher.control_counts == (1, 1)  # the lost reply, the corrupt chunk
    assert fetcher.counts["updates_refused"] == 1 and fetcher.counts["updates"] == 1
    assert any("do not hash" in line for line in lines)


def _damaged(data: bytes, field: str) -> bytes:
    body = msgpack.unpackb(data, raw=False)
    if field == "shape":
        body["areas"][0]["shape"] = [body["areas"][0]["shape"][0] + 1,
                                     body["areas"][0]["shape"][1]]
    elif field == "opacity":
        body["opacity"] = float("nan")
    elif field == "template":
        body["template"] = np.full(256, np.nan, "<f4").tobytes()
    elif field == "position":
        body["position"] = 99
    elif field == "diff":  # a decompression bomb: 64 MB of zeros in 64 kB
        body["areas"][0]["diff"] = zlib.compress(bytes(64 << 20), 9)
    return msgpack.packb(body, use_bin_type=True)


NAMED = {"shape": "areas[0]: shape", "opacity": "opacity", "template": "template",
         "position": "position", "diff": "areas[0]: diff"}


@pytest.mark.parametrize("field", list(NAMED))
def test_a_malformed_update_is_refused_naming_its_field(stream: dict[str, Any],
                                                        field: str) -> None:
    bad = _damaged(stream["data"][0], field)
    sender, inp = _sender(stream, 0)
    sender.publish(bad)
    try:
        fetcher, lines = _fetch(stream, control_endpoint(inp), 1, seconds=0.8)
    finally:
        sender.stop()
    assert fetcher.fetched == 0 and fetcher.counts["updates_refused"] >= 1
    refusal = next(line for line in lines if "refused" in line)
    assert "\n" not in refusal and refusal.startswith("update 1: ")
    assert NAMED[field] in refusal, refusal


def test_the_receiver_keeps_rendering_past_a_bad_update(stream: dict[str, Any],
                                                         tmp_path: Path) -> None:
    go = threading.Event()
    sender, inp = _sender(stream, 60, {10: _damaged(stream["data"][0], "diff")}, go)
    lines: list[str] = []
    thread, stop, result = start(receive, connect=inp, model_path=stream["path"], size=SIZE,
                                 cache_dir=tmp_path, ready=go, status=lines.append)
    try:
        assert go.wait(60)
        assert sender.done.wait(20)
        time.sleep(0.5)
    finally:
        stop.set()
        thread.join(30)
        sender.stop()
    assert "error" not in result, result.get("error")
    assert result["frames"] == 60 and result["model_serial"] == 0
    assert result["updates"] == 0 and result["updates_refused"] >= 1
    assert result["clamped"] >= 45  # the packets after the update named version 1
    assert any("update 1: areas[0]: diff" in line and "staying at model version 0" in line
               for line in lines), lines


def test_a_restarted_receiver_behind_a_relay_catches_up(stream: dict[str, Any],
                                                        tmp_path: Path) -> None:
    data = stream["data"]
    sender, inp = _sender(stream, 10**6)
    out = free_endpoint()
    relay_thread, relay_stop, _ = start(relay, inp=inp, out=out)
    try:
        sender.publish(data[0])
        first = receive(out, model_path=stream["path"], size=SIZE, cache_dir=tmp_path,
                        max_frames=45)
        sender.publish(data[1])  # while no receiver is there
        second = receive(out, model_path=stream["path"], size=SIZE, cache_dir=tmp_path,
                         max_frames=60)
    finally:
        sender.stop()
        relay_stop.set()
        relay_thread.join(10)
    assert first["updates"] == 1 and first["model_serial"] == 1
    assert second["updates"] == 2 and second["model_serial"] == 2


def test_fuzzed_update_messages_never_break_either_side(stream: dict[str, Any]) -> None:
    rng = np.random.default_rng(20261202)
    model = stream["model"]
    store = UpdateStore(model.sha256)
    store.publish_update(1, stream["data"][0])
    chunk = store.chunk(UpdateRequest(model.sha256, 1, 0))
    bodies = [encode_message(UpdateRequest(model.sha256, 1, 2)), encode_message(chunk)]
    answered = refused = decoded = 0
    for n in range(20_000):
        raw = bytearray(bodies[n % 2])
        for _ in range(int(rng.integers(1, 4))):
            raw[int(rng.integers(len(raw)))] = int(rng.integers(256))
        reply = answer_request(bytes(raw), stream["hello"], [], store)
        assert isinstance(reply, (Error, UpdateChunk)) or reply.TYPE == "hello"
        answered += 1
        try:
            message = decode_message(bytes(raw))
        except ControlError:
            refused += 1
            continue
        decoded += 1
        if isinstance(message, UpdateChunk):  # whatever decodes is a consistent chunk
            assert len(message.data) == min(1024, message.total - 1024 * message.index)
    assert answered == 20_000 and refused > 10_000 and decoded > 100


def test_a_restarted_sender_of_the_same_model_starts_the_updates_anew(
        stream: dict[str, Any], tmp_path: Path) -> None:
    data = stream["data"]
    other, _ = session_updates(stream["model"], 1, regions=("brow_furrow",))
    port = free_port_pair()
    go = threading.Event()
    first = UpdateSender(port, stream["hello"], stream["path"].read_bytes(),
                         stream["log"].packets, 90, {5: data[0], 10: data[1]}, go,
                         UpdateShaper(*FAST))
    lines: list[str] = []
    thread, stop, result = start(receive, connect=f"tcp://127.0.0.1:{port}",
                                 model_path=stream["path"], size=SIZE, cache_dir=tmp_path,
                                 ready=go, status=lines.append)
    try:
        assert go.wait(60) and first.done.wait(20)
        _wait(lambda: any("model v2" in line for line in lines), 10, "version 2 not shown")
        first.stop()
        second = UpdateSender(port, stream["hello"], stream["path"].read_bytes(),
                              stream["log"].packets, 90, {30: other[0]}, None,
                              UpdateShaper(*FAST))
        assert second.done.wait(20)
        time.sleep(0.5)
        second.stop()
    finally:
        first.stop()
        stop.set()
        thread.join(30)
    assert "error" not in result, result.get("error")
    assert any("a new session, its updates fetched anew" in line for line in lines), lines
    assert result["updates"] == 3 and result["model_serial"] == 1


def test_the_real_sender_learns_and_its_receiver_reaches_the_same_version(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """``facewire send`` itself (learning on), its model's mouth cut to one closed state
    (as tests/test_learn.py does), on lp_d0's first frames (the mouth opens): what it learns
    goes to the receiver and into its log."""
    path = tmp_path / "closed.fwm"
    save_model(mouth_states(load_model(person_model), 1), path)
    store = UpdateStore(load_model(path).sha256)
    endpoint, log = free_endpoint(), tmp_path / "session.fwlog"
    ready, lines = threading.Event(), []
    receiver, stop_receiver, received = start(
        receive, connect=endpoint, size=SIZE, cache_dir=tmp_path, ready=ready,
        status=lines.append)
    sender, stop_sender, sent = start(
        send, model_path=path, source=str(shared_data / "video" / "lp_d0.mp4"),
        bind=endpoint, frames=slice(0, 40), loop=True, start=ready, updates=store,
        record=log)
    try:
        _wait(lambda: store.serial >= 1 and any(
            line.startswith(f"model update {store.serial} fetched") for line in lines), 60,
            f"no update learned and fetched: {lines[-3:]}")
    finally:
        stop_sender.set()
        sender.join(30)
        time.sleep(0.5)
        stop_receiver.set()
        receiver.join(30)
    assert "error" not in sent and "error" not in received, (sent, received)
    assert received["updates_refused"] == 0 and received["updates"] >= 1
    assert received["model_serial"] == received["updates"] <= sent["updates"] == store.serial
    assert sent["control"]["update_bytes"] > sent["update_bytes_total"] > 0
    logged = read_log(log).updates
    assert [u.serial for u in logged] == list(range(1, store.serial + 1))
    assert sum(len(u.data) for u in logged) == store.bytes_total
