"""Corrupt texture patches at a real receiver (issue 24, part 2): dropped, counted, never drawn.

Real parts: the sender's control thread and update store (``updatesender``: the real
``Responder`` on a real ``ControlServer``), the receiver's real ``UpdateFetcher`` (what the
render loop takes its model versions from), ZeroMQ on loopback, and between them the lossy
relay of ``lossy``, whose reply hook puts a corrupt patch in every update chunk that passes,
with the chunk's hashes made to agree with it (so each reaches the patch's decoder, as from a
sender that meant it). 5000 corrupt patches, each checked corrupt against the model first
(``models.update.decode_update``): random byte flips of a real patch's bytes, a tile out of
the texture, a PNG of the wrong size or broken, a bad scale, too many tiles. The fetcher
must refuse every one (``updates_refused``), stay at the model file (version 0), and the
model it hands the renderer must be the file's, texel for texel.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from conftest import free_endpoint
from lossy import LossyRelay
from updatesender import UpdateSender

from facewire.models.modelfile import load_model
from facewire.models.patch import MAX_SCALE, TexturePatch, Tile, encode_patch
from facewire.models.update import UpdateError, decode_update
from facewire.protocol.control import Camera, Hello
from facewire.protocol.packet import Frame, encode
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import control_endpoint
from facewire.receiver import updates as receiver_updates
from facewire.receiver.updates import UpdateFetcher

MESSAGES = 5000
FAST = (10**9, 1.1, (1e9, 1e9))  # a shaper that holds nothing


def _corrupt(valid: bytes, rng: np.random.Generator) -> bytes:
    """One corrupt variant of a valid patch's bytes (module docstring)."""
    kind = int(rng.integers(6))
    if kind == 0:
        raw = bytearray(valid)
        for _ in range(int(rng.integers(1, 5))):
            raw[int(rng.integers(len(raw)))] = int(rng.integers(256))
        return bytes(raw)
    body = msgpack.unpackb(valid, raw=False)
    tile = body["tiles"][0]
    if kind == 1:
        tile["row"] = int(rng.integers(40, 1 << 16))
    elif kind == 2:
        tile["shape"] = [int(rng.integers(1, 70)), int(rng.integers(1, 70))]
    elif kind == 3:
        png = bytearray(tile["png"])
        cut = int(rng.integers(8, len(png)))
        tile["png"] = bytes(png[:cut]) + bytes(rng.integers(0, 256, int(rng.integers(0, 40)),
                                                             np.uint8))
    elif kind == 4:
        body["scale"] = int(rng.choice([0, MAX_SCALE + 1, -1, 1 << 20]))
    else:
        body["tiles"] = [tile] * int(rng.integers(65, 80))
    return msgpack.packb(body, use_bin_type=True)


def test_5000_corrupt_patches_are_refused_and_nothing_is_drawn(
        generic_model: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(receiver_updates, "RETRY_S", 0.0)
    monkeypatch.setattr(receiver_updates, "MAX_RETRY_S", 0.0)
    monkeypatch.setattr(receiver_updates, "CHUNK_TIMEOUT_S", 0.5)
    model = load_model(generic_model)
    rng = np.random.default_rng(20261206)
    diff = rng.integers(100, 156, (4, 4, 3), np.uint8)
    valid = encode_patch(TexturePatch(model.sha256, 1, 4, (Tile(8, 16, diff),)))
    served: list[bytes] = []

    def next_corrupt() -> bytes:
        while True:
            data = _corrupt(valid, rng)
            if len(data) > 1024:
                continue
            try:
                decode_update(data, model, model.sha256)
            except UpdateError:
                return data

    def damage(reply: list[bytes]) -> list[bytes] | None:
        body = msgpack.unpackb(reply[-1], raw=False)
        if body.get("type") != "update_chunk":
            return reply
        if len(served) >= MESSAGES:
            return None  # lost: the valid patch never gets through
        data = next_corrupt()
        served.append(data)
        digest = hashlib.sha256(data).hexdigest()
        body.update(data=data, index=0, count=1, total=len(data), data_sha256=digest,
                    sha256=digest)
        return [*reply[:-1], msgpack.packb(body, use_bin_type=True)]

    hello = Hello(model_sha256=model.sha256, model_bytes=model.file_bytes, rate_hz=30.0,
                  camera=Camera(640.0, 640.0, 319.5, 239.5, 640, 480), regions=())
    packets = np.frombuffer(encode(Frame()), np.uint8)[None]
    port = int(free_endpoint().rsplit(":", 1)[1])
    sender = UpdateSender(port, hello, generic_model.read_bytes(), packets, 0,
                          shaper=UpdateShaper(*FAST))
    sender.publish(valid)
    out = free_endpoint()
    lossy = LossyRelay(f"tcp://127.0.0.1:{port}", out, replies=damage)
    lines: list[str] = []
    fetcher = UpdateFetcher(control_endpoint(out), None, model, lines.append)
    try:
        fetcher.want(1)
        deadline = time.monotonic() + 240
        while len(served) < MESSAGES and time.monotonic() < deadline:
            time.sleep(0.05)
            assert fetcher.fetched == 0, lines[-3:]
        time.sleep(0.3)  # the last one decoded and refused
    finally:
        fetcher.close()
        lossy.stop()
        sender.stop()
    assert len(served) == MESSAGES
    assert fetcher.counts["updates_refused"] >= MESSAGES, fetcher.counts
    assert fetcher.counts["updates"] == 0 and fetcher.fetched == 0
    assert fetcher.take(1) is None
    shown = fetcher.version(0)
    assert shown is model and np.array_equal(shown.texture, load_model(generic_model).texture)
    assert all("\n" not in line and line.startswith("update 1: ") for line in lines[:50])
