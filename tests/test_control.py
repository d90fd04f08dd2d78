"""Control messages: schema, validation, and chunked, hashed model transfer."""

from __future__ import annotations

import hashlib

import msgpack
import numpy as np
import pytest

from facewire.protocol.control import (
    CHUNK_BYTES,
    MAX_MESSAGE_BYTES,
    Camera,
    ControlError,
    Error,
    Hello,
    HelloRequest,
    ModelAssembler,
    ModelChunk,
    ModelRequest,
    decode_message,
    encode_message,
    model_chunks,
)

SHA = "ab" * 32


def _hello(**over: object) -> Hello:
    kw: dict = dict(model_sha256=SHA, model_bytes=1234, rate_hz=30.0,
                    camera=Camera(600.0, 600.0, 320.0, 240.0, 640, 480),
                    regions=("forehead", "brow_furrow", "eyelid_right", "eyelid_left",
                             "eyeball_right", "eyeball_left", "mouth"))
    kw.update(over)
    return Hello(**kw)


@pytest.mark.parametrize("message", [
    HelloRequest(), _hello(), ModelRequest(SHA, 3), Error("no such model"),
    model_chunks(b"x" * 1000, SHA)[0],
])
def test_round_trip(message: object) -> None:
    assert decode_message(encode_message(message)) == message


def test_hello_is_small() -> None:
    assert len(encode_message(_hello())) < 1024


@pytest.mark.parametrize("body,match", [
    ([1, 2], "not a map"),
    ({"type": "launch"}, "unknown control message type"),
    ({"type": 7}, "unknown control message type"),
    ({}, "unknown control message type"),
    ({"type": "model_request", "sha256": SHA}, "missing index"),
    ({"type": "model_request", "sha256": SHA, "index": 1, "extra": 1}, "unknown field"),
    ({"type": "model_request", "sha256": SHA, "index": "1"}, "wrong type"),
    ({"type": "model_request", "sha256": SHA, "index": True}, "wrong type"),
    ({"type": "model_request", "sha256": "XYZ", "index": 1}, "sha256"),
    ({"type": "model_request", "sha256": SHA, "index": 2**40}, "index"),
    ({"type": "error", "message": b"bytes"}, "wrong type"),
])
def test_malformed_messages_are_refused(body: object, match: str) -> None:
    with pytest.raises(ControlError, match=match):
        decode_message(msgpack.packb(body, use_bin_type=True))


def _hello_body(**over: object) -> dict:
    body = msgpack.unpackb(encode_message(_hello()), raw=False)
    body.update(over)
    return body


@pytest.mark.parametrize("over,match", [
    ({"protocol": 1}, "protocol version 1, this facewire version 2"),
    ({"protocol": 3}, "protocol"),
    ({"rate_hz": float("nan")}, "rate_hz"),
    ({"rate_hz": -5.0}, "rate_hz"),
    ({"model_bytes": 0}, "model_bytes"),
    ({"camera": {"fx": 1.0}}, "camera"),
    ({"camera": {"fx": float("inf"), "fy": 1.0, "cx": 1.0, "cy": 1.0, "width": 1,
                 "height": 1}}, "camera.fx"),
    ({"camera": {"fx": 500.0, "fy": 500.0, "cx": 1.0, "cy": 1.0, "width": 0,
                 "height": 1}}, "camera.width"),
    ({"regions": ["a"] * 9}, "regions"),
    ({"regions": [1, 2]}, "regions"),
    ({"quantisers": []}, "quantisers"),
])
def test_bad_hello_fields(over: dict, match: str) -> None:
    with pytest.raises(ControlError, match=match):
        decode_message(msgpack.packb(_hello_body(**over), use_bin_type=True))


def test_size_limits_and_garbage() -> None:
    with pytest.raises(ControlError, match="exceeds"):
        decode_message(b"\x00" * (MAX_MESSAGE_BYTES + 1))
    # A header declaring a huge array or string must not allocate it.
    for data in (b"\xdd\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff",
                 b"\xc7\x01\x05x", b"\xc1"):
        with pytest.raises(ControlError):
            decode_message(data)
    rng = np.random.default_rng(5)
    for _ in range(5000):
        try:
            decode_message(rng.bytes(int(rng.integers(0, 64))))
        except ControlError:
            pass


def test_model_transfer_in_chunks() -> None:
    data = np.random.default_rng(0).bytes(2 * CHUNK_BYTES + 777)
    sha = hashlib.sha256(data).hexdigest()
    chunks = model_chunks(data, sha)
    assert [c.index for c in chunks] == [0, 1, 2] and chunks[0].count == 3
    assembler = ModelAssembler(sha, len(data))
    for chunk in reversed(chunks):  # any order
        assembler.add(decode_message(encode_message(chunk)))
    assert assembler.missing() == [] and assembler.result() == data


def test_tampered_chunk_refused() -> None:
    data = b"model bytes" * 100
    chunk = model_chunks(data, hashlib.sha256(data).hexdigest())[0]
    body = msgpack.unpackb(encode_message(chunk), raw=False)
    body["data"] = b"X" + body["data"][1:]
    with pytest.raises(ControlError, match="data_sha256"):
        decode_message(msgpack.packb(body, use_bin_type=True))


def test_chunks_that_do_not_hash_to_the_model_are_refused() -> None:
    data = b"the real model" * 50
    wrong = hashlib.sha256(b"another model").hexdigest()
    assembler = ModelAssembler(wrong, len(data))
    for chunk in model_chunks(data, wrong):  # self-consistent chunks, wrong announced hash
        assembler.add(chunk)
    with pytest.raises(ControlError, match="announced sha256"):
        assembler.result()
    incomplete = ModelAssembler(SHA, 3 * CHUNK_BYTES)
    with pytest.raises(ControlError, match="incomplete"):
        incomplete.result()
    other = model_chunks(b"y" * 10, "cd" * 32)[0]
    with pytest.raises(ControlError, match="another model"):
        ModelAssembler(SHA, 10).add(other)


def test_chunk_size_consistency() -> None:
    with pytest.raises(ControlError, match="data"):
        ModelChunk(SHA, 0, 1, 10, b"short", hashlib.sha256(b"short").hexdigest())
    with pytest.raises(ControlError, match="count"):
        ModelChunk(SHA, 0, 5, 10, b"x" * 10, hashlib.sha256(b"x" * 10).hexdigest())
