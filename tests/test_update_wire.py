"""Model updates between the sender's store and the receiver's renderer, on real sockets.

The sender's store serves exactly what was published, in serial order, and refuses what was
not (naming the field); its control thread holds update chunks to the shaper's schedule on a
real socket (a greedy client's update bytes stay under 32 kbit/s in every second); the
receiver's fetcher gets every update in order, verifies, decodes and applies it; and the
renderer, given a new version, draws exactly what a renderer made for that version draws.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_endpoint
from sessionlog import session_updates

from facewire.models.modelfile import PersonModel, load_model
from facewire.protocol.control import (
    Camera,
    ControlError,
    Error,
    Hello,
    HelloRequest,
    UpdateChunk,
    UpdateRequest,
    decode_message,
    encode_message,
)
from facewire.protocol.packet import Flag
from facewire.protocol.shaper import LIMIT_KBPS_1S, WINDOW_BYTES, UpdateShaper, window_kbps
from facewire.protocol.transport import ControlClient, ControlServer, control_endpoint
from facewire.receiver.playout import FrameState
from facewire.receiver.scene import StateRenderer
from facewire.receiver.updates import UpdateFetcher
from facewire.sender.responder import (
    MAX_HELD_PER_PEER,
    MAX_RECEIVERS_PER_CONNECTION,
    Responder,
    answer_request,
)
from facewire.sender.updates import UpdateStore

SIZE = (160, 120)
CAMERA = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
FAST = (10**9, 1.1, (1e9, 1e9))  # a shaper that holds nothing, for tests not about rate


@pytest.fixture(scope="module")
def session(person_model: Path):
    model = load_model(person_model)
    data, versions = session_updates(model, 3, regions=("mouth",))
    return model, data, versions


def _state(q: np.ndarray, serial: int = 0) -> FrameState:
    return FrameState(0, np.eye(3), np.array([0.0, 0.0, -600.0]),
                      np.zeros((9, 2), np.float32), q, Flag.FACE_PRESENT, "received", 1.0,
                      0.0, serial)


def test_a_new_version_renders_as_a_renderer_made_for_it(session) -> None:
    model = session[0]
    _, versions = session_updates(model, 2, regions=("forehead", "eyelid_left"))
    q = np.array([r.rest for r in versions[2].regions] + [0.0], np.float32)
    forehead = [r.name for r in model.regions].index("forehead")
    q[forehead] = 3  # the learned state (the base model has its last one there)
    with StateRenderer(model, *SIZE, CAMERA, view="front") as live, \
            StateRenderer(versions[2], *SIZE, CAMERA, view="front") as fresh:
        before = live.render(_state(q))
        live.set_model(versions[1])
        live.set_model(versions[2])
        after = live.render(_state(q))
        assert np.array_equal(after, fresh.render(_state(q)))
    assert (np.abs(after.astype(int) - before).sum(-1) > 0).sum() > 100  # the update shows


def test_the_store_serves_what_was_published_and_names_what_it_refuses(session) -> None:
    model, data, _ = session
    store = UpdateStore(model.sha256)
    with pytest.raises(ControlError, match="next update's serial is 1"):
        store.publish_update(2, data[1])
    store.publish_update(1, data[0])
    hello = _hello(model)
    assert answer_request(encode_message(HelloRequest()), hello, [], store).model_serial == 1
    chunk = answer_request(encode_message(UpdateRequest(model.sha256, 1, 0)), hello, [], store)
    assert isinstance(chunk, UpdateChunk)
    assert chunk.sha256 == hashlib.sha256(data[0]).hexdigest()
    for request, field in ((UpdateRequest(model.sha256, 2, 0), "update_request.serial"),
                           (UpdateRequest(model.sha256, 1, 99), "update_request.index"),
                           (UpdateRequest("cd" * 32, 1, 0), "update_request.model_sha256")):
        reply = answer_request(encode_message(request), hello, [], store)
        assert isinstance(reply, Error) and reply.message.startswith(field)


def _hello(model: PersonModel) -> Hello:
    return Hello(model_sha256=model.sha256, model_bytes=model.file_bytes, rate_hz=30.0,
                 camera=CAMERA, regions=tuple(r.name for r in model.regions))


class _Server:
    """The sender's real control thread on loopback, with a store of ``updates``."""

    def __init__(self, endpoint: str, model, updates: list[bytes], shaper=None) -> None:
        self.store = UpdateStore(model.sha256)
        for serial, data in enumerate(updates, 1):
            self.store.publish_update(serial, data)
        self.server = ControlServer(control_endpoint(endpoint))
        self.responder = Responder(self.server, _hello(model), [], self.store,
                                   shaper or UpdateShaper(*FAST))
        self.responder.start()

    def close(self) -> None:
        self.responder.stop()
        self.server.close()


def test_update_chunks_are_shaped_on_the_socket(session) -> None:
    model, data, _ = session
    endpoint = free_endpoint()
    server = _Server(endpoint, model, data[:2], UpdateShaper())
    client = ControlClient(control_endpoint(endpoint))
    times, sizes = [], []
    try:
        for serial, whole in enumerate(data[:2], 1):
            for index in range(-(-len(whole) // 1024)):
                reply = client.request(UpdateRequest(model.sha256, serial, index), 5000)
                assert isinstance(reply, UpdateChunk), reply
                times.append(time.monotonic())
                sizes.append(len(encode_message(reply)))
    finally:
        client.close()
        server.close()
    kbps = window_kbps(times, sizes, 1.0)
    assert 0.7 * LIMIT_KBPS_1S < kbps <= LIMIT_KBPS_1S, kbps
    assert server.responder.counts["update_bytes"] == sum(sizes)


def test_the_fetcher_gets_every_update_in_order(session) -> None:
    model, data, versions = session
    endpoint = free_endpoint()
    server = _Server(endpoint, model, data)
    lines: list[str] = []
    fetcher = UpdateFetcher(control_endpoint(endpoint), None, model, lines.append)
    try:
        fetcher.want(3)
        deadline = time.monotonic() + 10
        while fetcher.fetched < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        taken = fetcher.take(2)
        assert taken is not None and taken[1] == 2
        final = fetcher.take(5)
    finally:
        fetcher.close()
        server.close()
    assert final is not None and final[1] == 3
    mouth = [r.name for r in model.regions].index("mouth")
    assert np.array_equal(final[0].regions[mouth].layers, versions[3].regions[mouth].layers)
    assert fetcher.counts["updates"] == 3 and fetcher.counts["updates_refused"] == 0
    assert fetcher.counts["update_bytes"] == sum(map(len, data))
    assert sum("fetched" in line for line in lines) == 3


def test_a_receiver_asking_too_many_chunks_at_once_is_told_to_ask_one_at_a_time(session
                                                                                ) -> None:
    model, data, _ = session
    endpoint = free_endpoint()
    server = _Server(endpoint, model, data[:1], UpdateShaper())
    client = ControlClient(control_endpoint(endpoint))
    try:
        # all at once, without waiting: as many as the shaper's window holds go out at once,
        # the next MAX_HELD_PER_PEER are held, the last is refused
        size = len(encode_message(server.store.chunk(UpdateRequest(model.sha256, 1, 0))))
        count = WINDOW_BYTES // size + MAX_HELD_PER_PEER + 1
        for index in range(count):
            client.socket.send_multipart(
                [b"", encode_message(UpdateRequest(model.sha256, 1, index % 4))])
        replies = [decode_message(client.socket.recv_multipart()[-1])
                   for _ in range(count) if client.socket.poll(5000)]
    finally:
        client.close()
        server.close()
    errors = [r for r in replies if isinstance(r, Error)]
    assert len(errors) == 1 and "ask one at a time" in errors[0].message
    assert [r.index for r in replies if isinstance(r, UpdateChunk)] == \
        [index % 4 for index in range(count - 1)]
    assert server.responder.counts["errors"] == 1


def test_forged_relay_hops_are_shaped_per_connection(session) -> None:
    """One connection forging 300 relay hops with 7 update requests each (issue 26 item 5: it
    got 1792 chunks in 3 s and filled every held reply): at most
    ``MAX_RECEIVERS_PER_CONNECTION`` of its receivers are shaped at once, the rest are
    refused at once, and a receiver on a connection of its own still gets its chunk."""
    model, data, _ = session
    endpoint = free_endpoint()
    server = _Server(endpoint, model, data[:1], UpdateShaper())
    attacker = ControlClient(control_endpoint(endpoint))
    honest = ControlClient(control_endpoint(endpoint))
    count = -(-len(data[0]) // 1024)
    replies: list = []
    try:
        for hop in range(300):
            for index in range(7):
                attacker.socket.send_multipart([b"hop%d" % hop, b"", encode_message(
                    UpdateRequest(model.sha256, 1, index % count))])
        deadline = time.monotonic() + 3.0
        while (left := deadline - time.monotonic()) > 0:
            if attacker.socket.poll(round(left * 1000)):
                replies.append(decode_message(attacker.socket.recv_multipart()[-1]))
        mine = honest.request(UpdateRequest(model.sha256, 1, 0), 5000)
    finally:
        attacker.close()
        honest.close()
        server.close()
    chunks = sum(isinstance(r, UpdateChunk) for r in replies)
    # a shaped receiver gets at most 3 chunks per 1.1 s window: 9 in 3 s
    assert 0 < chunks <= MAX_RECEIVERS_PER_CONNECTION * 9, chunks
    assert any(isinstance(r, Error) and "of this connection" in r.message for r in replies)
    assert isinstance(mine, UpdateChunk), mine
