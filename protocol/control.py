"""Control messages: msgpack maps with an explicit, validated schema.

Every message is one msgpack map with a ``"type"`` key. Receivers ask, the sender answers:

============== ============================================================================
type           fields (msgpack types)
============== ============================================================================
hello_request  -
hello          protocol (int), model_sha256 (str, 64 hex), model_bytes (int), rate_hz
               (float), camera (map: fx, fy, cx, cy (float), width, height (int)), regions
               (array of <= 8 str), quantisers (array of maps, ``packet.quantiser_table()``),
               model_serial (int, 0 .. ``MAX_SERIAL``; optional, default 0), clock_origin_s
               (float; optional: absent until the stream's first frame, and from older
               senders), voice_bitrate (int, Opus's bit/s; optional: absent when the stream
               has no voice), voice_origin_s (float; optional: absent until the voice
               starts)
model_request  sha256 (str), index (int): ask for one chunk of the model file
model_chunk    sha256 (str), index, count, total (int), data (bin), data_sha256 (str)
update_request model_sha256 (str), serial, index (int): ask for one chunk of model update
               ``serial`` of the session that started from model ``model_sha256``
update_chunk   model_sha256 (str), serial, index, count, total (int), data (bin),
               data_sha256 (str), sha256 (str: the whole update's)
time_request   t1 (float): the receiver's clock when it asked (``protocol.clock``)
time_reply     t1 (float, the request's), t2, t3 (float): the sender's clock on receiving
               the request and on replying
error          message (str)
============== ============================================================================

The Hello's ``clock_origin_s`` is the capture time, on the sender's monotonic clock, of the
stream's slot 0: slot ``n`` (its packet's ``seq`` is ``n mod 65536``) was captured at
``clock_origin_s + n / rate_hz`` (``protocol.clock``); voice frame ``j`` (``protocol.voice``)
from ``voice_origin_s + j * 20 ms``. A time exchange (``time_request``,
``time_reply``) gives the offset between the two hosts' clocks. Every time is a finite
number of at most ``MAX_CLOCK_S`` in magnitude.

A model travels as ``count`` chunks of at most ``CHUNK_BYTES``; each chunk carries the sha256
of its own data, and the reassembled file must hash to the announced model sha256.

Model updates (``models.update``: one learned state of one region) make the model's version
the pair (model sha256, serial): serial 0 is the model file, update n turns version n - 1
into version n. The Hello's ``model_serial`` is the newest version the sender has issued, and
every packet names the version its Q values refer to (``packet.Frame.serial``): that is the
announcement, since the control channel only answers requests. Here an update is opaque bytes
(its format is ``models.update``'s): it travels as ``count`` chunks of at most
``UPDATE_CHUNK_BYTES`` (small, so that the sender can shape update traffic finely:
``protocol.shaper``), each carrying the sha256 of its own data and of the whole update; every
chunk of one transfer must name the same whole (``sha256``, ``total``), and the reassembled
bytes must hash to it (``ChunkAssembler``).

Decoding bounds every size before allocating (no message over ``MAX_MESSAGE_BYTES``, no
extension types, string map keys only), then checks each field's type and range. Anything
malformed or unknown raises ``ControlError``. A stream's rate is in [``MIN_RATE_HZ``,
``MAX_RATE_HZ``] (``protocol.rate``).

Text from a peer is shown to people (a receiver's status line quotes the sender's ``Error``
and what was wrong with a reply), so no text leaves this module raw: an ``Error`` message and
every ``ControlError`` message have their non-printable characters escaped (``printable``,
as in a Python string literal: a terminal escape sequence arrives as ``\\x1b[...``) and are
cut to ``MAX_TEXT_CHARS``.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import MISSING, asdict, dataclass, field, fields
from typing import Any, ClassVar

import msgpack

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import MAX_BITRATE, MIN_BITRATE
from facewire.protocol.packet import MAX_SERIAL, N_REGIONS, VERSION, quantiser_table
from facewire.protocol.rate import MAX_RATE_HZ, MIN_RATE_HZ

CHUNK_BYTES = 256 * 1024
MAX_MESSAGE_BYTES = CHUNK_BYTES + 4096
MAX_MODEL_BYTES = 256 * 1024 * 1024
UPDATE_CHUNK_BYTES = 1024
MAX_UPDATE_BYTES = 1024 * 1024  # an update's bytes, on the wire, in a log, in a model
MAX_TEXT_CHARS = 1000
# The camera's bounds, the one set (models.geometry.Intrinsics takes them from here).
MAX_FOCAL_PX = 1e6
MAX_PRINCIPAL_PX = 1e5
MAX_IMAGE_SIDE = 16384
MAX_CLOCK_S = 1e12
_HEX64 = re.compile(r"[0-9a-f]{64}")


def printable(text: str, limit: int = MAX_TEXT_CHARS) -> str:
    """``text`` safe to print: non-printable characters escaped as in a Python string literal
    (a newline as ``\\n``, ESC as ``\\x1b``), cut to ``limit`` characters ending in "...".
    """
    if text.isprintable() and len(text) <= limit:
        return text
    clean = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[:limit + 1])
    return clean if len(clean) <= limit else clean[:limit - 3] + "..."


class ControlError(FacewireError, ValueError):
    """A control message is malformed, unknown or inconsistent (the message ``printable``)."""

    def __init__(self, message: str) -> None:
        super().__init__(printable(message))


@dataclass(frozen=True)
class Camera:
    """The Hello's wire form of the sender camera's pinhole intrinsics, pixels, image origin
    top-left: ``models.geometry.Intrinsics`` (which this module may not import) on the wire,
    with the same bounds. The sender makes it in ``SenderPipeline.hello``; the receiver turns
    it back into intrinsics in ``receiver.views.sender_view`` (elsewhere only its image size
    is read)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            _require(0 < getattr(self, name) < MAX_FOCAL_PX,
                     f"camera.{name}: must be in (0, {MAX_FOCAL_PX:g})")
        for name in ("width", "height"):
            _require(0 < getattr(self, name) <= MAX_IMAGE_SIDE,
                     f"camera.{name}: must be in [1, {MAX_IMAGE_SIDE}]")
        _require(abs(self.cx) < MAX_PRINCIPAL_PX and abs(self.cy) < MAX_PRINCIPAL_PX,
                 "camera.cx/cy: out of range")


@dataclass(frozen=True)
class HelloRequest:
    TYPE: ClassVar[str] = "hello_request"


@dataclass(frozen=True)
class Hello:
    """What a receiver needs before the first packet."""

    TYPE: ClassVar[str] = "hello"
    model_sha256: str
    model_bytes: int
    rate_hz: float
    camera: Camera
    regions: tuple[str, ...]
    protocol: int = VERSION
    quantisers: tuple[dict[str, Any], ...] = field(
        default_factory=lambda: tuple(quantiser_table()))
    model_serial: int = 0
    clock_origin_s: float | None = None
    voice_bitrate: int | None = None
    voice_origin_s: float | None = None

    def __post_init__(self) -> None:
        if self.clock_origin_s is not None:
            _check_time("hello.clock_origin_s", self.clock_origin_s)
        if self.voice_origin_s is not None:
            _check_time("hello.voice_origin_s", self.voice_origin_s)
        _require(self.voice_bitrate is None or MIN_BITRATE <= self.voice_bitrate <= MAX_BITRATE,
                 f"hello.voice_bitrate: must be in [{MIN_BITRATE}, {MAX_BITRATE}]")
        _require(self.protocol == VERSION, f"hello.protocol: the sender speaks protocol version "
                                           f"{self.protocol}, this facewire version {VERSION}")
        _require(bool(_HEX64.fullmatch(self.model_sha256)),
                 "hello.model_sha256: expected 64 lowercase hex digits")
        _require(0 < self.model_bytes <= MAX_MODEL_BYTES,
                 f"hello.model_bytes: must be in [1, {MAX_MODEL_BYTES}]")
        _require(MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ,
                 f"hello.rate_hz: must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}]")
        _require(len(self.regions) <= N_REGIONS, f"hello.regions: more than {N_REGIONS}")
        _require(all(0 < len(r) <= 64 and r.isprintable() for r in self.regions),
                 "hello.regions: names must have 1 to 64 printable characters")
        _require(list(self.quantisers) == quantiser_table(),
                 f"hello.quantisers: do not match this receiver's protocol version {VERSION} "
                 "table")
        _require(0 <= self.model_serial <= MAX_SERIAL,
                 f"hello.model_serial: must be in [0, {MAX_SERIAL}]")


@dataclass(frozen=True)
class ModelRequest:
    TYPE: ClassVar[str] = "model_request"
    sha256: str
    index: int

    def __post_init__(self) -> None:
        _require(bool(_HEX64.fullmatch(self.sha256)), "model_request.sha256: not 64 hex digits")
        _require(0 <= self.index < MAX_MODEL_BYTES // CHUNK_BYTES + 1,
                 "model_request.index: out of range")


@dataclass(frozen=True)
class ModelChunk:
    TYPE: ClassVar[str] = "model_chunk"
    sha256: str
    index: int
    count: int
    total: int
    data: bytes
    data_sha256: str

    def __post_init__(self) -> None:
        _require(bool(_HEX64.fullmatch(self.sha256)), "model_chunk.sha256: not 64 hex digits")
        _check_chunk(self, CHUNK_BYTES, MAX_MODEL_BYTES)


@dataclass(frozen=True)
class UpdateRequest:
    """Ask for chunk ``index`` of update ``serial`` of the session of model ``model_sha256``."""

    TYPE: ClassVar[str] = "update_request"
    model_sha256: str
    serial: int
    index: int

    def __post_init__(self) -> None:
        _require(bool(_HEX64.fullmatch(self.model_sha256)),
                 "update_request.model_sha256: not 64 hex digits")
        _require(1 <= self.serial <= MAX_SERIAL,
                 f"update_request.serial: must be in [1, {MAX_SERIAL}]")
        _require(0 <= self.index < MAX_UPDATE_BYTES // UPDATE_CHUNK_BYTES,
                 "update_request.index: out of range")


@dataclass(frozen=True)
class UpdateChunk:
    """Chunk ``index`` of ``count`` of update ``serial`` (``total`` bytes, hashing to
    ``sha256``); its ``data`` hash to ``data_sha256``."""

    TYPE: ClassVar[str] = "update_chunk"
    model_sha256: str
    serial: int
    index: int
    count: int
    total: int
    data: bytes
    data_sha256: str
    sha256: str

    def __post_init__(self) -> None:
        for name in ("model_sha256", "sha256"):
            _require(bool(_HEX64.fullmatch(getattr(self, name))),
                     f"update_chunk.{name}: not 64 hex digits")
        _require(1 <= self.serial <= MAX_SERIAL,
                 f"update_chunk.serial: must be in [1, {MAX_SERIAL}]")
        _check_chunk(self, UPDATE_CHUNK_BYTES, MAX_UPDATE_BYTES)


def _check_chunk(chunk: ModelChunk | UpdateChunk, size: int, most: int) -> None:
    """A chunk's place and data: chunk ``index`` of ``count`` chunks of at most ``size``
    bytes that hold ``total`` (at most ``most``) bytes, its data hashing to ``data_sha256``."""
    kind = chunk.TYPE
    _require(0 < chunk.total <= most, f"{kind}.total: must be in [1, {most}]")
    _require(chunk.count == math.ceil(chunk.total / size), f"{kind}.count: does not match total")
    _require(0 <= chunk.index < chunk.count, f"{kind}.index: out of range")
    want = min(size, chunk.total - chunk.index * size)
    _require(len(chunk.data) == want, f"{kind}.data: {len(chunk.data)} bytes, expected {want}")
    _require(hashlib.sha256(chunk.data).hexdigest() == chunk.data_sha256,
             f"{kind}.data_sha256: does not match the data")


@dataclass(frozen=True)
class TimeRequest:
    """Ask the sender's clock; ``t1`` is the receiver's when asking (``protocol.clock``)."""

    TYPE: ClassVar[str] = "time_request"
    t1: float

    def __post_init__(self) -> None:
        _check_time("time_request.t1", self.t1)


@dataclass(frozen=True)
class TimeReply:
    """The sender's clock: ``t2`` when the request came, ``t3`` when replying; ``t1`` the
    request's, echoed."""

    TYPE: ClassVar[str] = "time_reply"
    t1: float
    t2: float
    t3: float

    def __post_init__(self) -> None:
        for name in ("t1", "t2", "t3"):
            _check_time(f"time_reply.{name}", getattr(self, name))


@dataclass(frozen=True)
class Error:
    """A refusal; ``message`` is kept ``printable`` (escaped and cut, never refused)."""

    TYPE: ClassVar[str] = "error"
    message: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "message", printable(self.message))


Message = (HelloRequest | Hello | ModelRequest | ModelChunk | UpdateRequest | UpdateChunk
           | TimeRequest | TimeReply | Error)
_TYPES: dict[str, type] = {t.TYPE: t for t in (HelloRequest, Hello, ModelRequest, ModelChunk,
                                                 UpdateRequest, UpdateChunk, TimeRequest,
                                                 TimeReply, Error)}
_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "model_sha256": (str,), "sha256": (str,), "data_sha256": (str,), "message": (str,),
    "model_bytes": (int,), "index": (int,), "count": (int,), "total": (int,),
    "protocol": (int,), "rate_hz": (float, int), "camera": (dict,), "regions": (list,),
    "quantisers": (list,), "data": (bytes,), "model_serial": (int,), "serial": (int,),
    "clock_origin_s": (float, int), "voice_origin_s": (float, int), "voice_bitrate": (int,),
    "t1": (float, int), "t2": (float, int), "t3": (float, int),
}


def encode_message(message: Message) -> bytes:
    """Serialise a message to msgpack bytes."""
    body = {"type": message.TYPE, **asdict(message)}
    for optional in ("clock_origin_s", "voice_bitrate", "voice_origin_s"):
        if body.get(optional, 0) is None:  # absent, as from older senders
            del body[optional]
    return msgpack.packb(body, use_bin_type=True)


def decode_message(data: bytes) -> Message:
    """Parse and validate one control message.

    Raises:
        ControlError: too large, not msgpack, unknown type, missing/extra/mistyped fields,
            or a value out of range.
    """
    if len(data) > MAX_MESSAGE_BYTES:
        raise ControlError(f"control message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True, ext_hook=_no_ext)
    except ControlError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types on malformed input
        raise ControlError(f"control message is not valid msgpack: {exc}") from None
    if not isinstance(body, dict):
        raise ControlError("control message is not a map")
    kind = body.pop("type", None)
    cls = _TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ControlError(f"unknown control message type {kind!r}")
    names = {f.name for f in fields(cls)}
    required = {f.name for f in fields(cls) if f.default is f.default_factory is MISSING}
    if missing := required - body.keys():
        raise ControlError(f"{kind}: missing {', '.join(sorted(missing))}")
    if extra := body.keys() - names:
        raise ControlError(f"{kind}: unknown field {', '.join(sorted(map(repr, extra)))}")
    for name, value in body.items():
        if not isinstance(value, _FIELD_TYPES[name]) or isinstance(value, bool):
            raise ControlError(f"{kind}.{name}: wrong type {type(value).__name__}")
    try:
        if kind == "hello":
            body["camera"] = Camera(**_camera_fields(body["camera"]))
            body["regions"] = tuple(body["regions"])
            body["quantisers"] = tuple(body.get("quantisers", ()))
            if not all(isinstance(r, str) for r in body["regions"]):
                raise ControlError("hello.regions: names must be strings")
        return cls(**body)
    except TypeError as exc:
        raise ControlError(f"{kind}: {exc}") from None


def model_chunks(data: bytes, sha256: str) -> list[ModelChunk]:
    """Split a model file into hashed chunks of at most ``CHUNK_BYTES``."""
    count = math.ceil(len(data) / CHUNK_BYTES)
    return [ModelChunk(sha256, i, count, len(data), part, hashlib.sha256(part).hexdigest())
            for i in range(count)
            for part in [data[i * CHUNK_BYTES:(i + 1) * CHUNK_BYTES]]]


def update_chunks(data: bytes, model_sha256: str, serial: int) -> list[UpdateChunk]:
    """Split update ``serial``'s bytes into hashed chunks of at most ``UPDATE_CHUNK_BYTES``.

    Raises:
        ControlError: no bytes, more than ``MAX_UPDATE_BYTES``, or a serial out of range.
    """
    _require(0 < len(data) <= MAX_UPDATE_BYTES,
             f"update {serial}: {len(data)} bytes, expected 1 to {MAX_UPDATE_BYTES}")
    count = math.ceil(len(data) / UPDATE_CHUNK_BYTES)
    whole = hashlib.sha256(data).hexdigest()
    return [UpdateChunk(model_sha256, serial, i, count, len(data), part,
                        hashlib.sha256(part).hexdigest(), whole)
            for i in range(count)
            for part in [data[i * UPDATE_CHUNK_BYTES:(i + 1) * UPDATE_CHUNK_BYTES]]]


class ChunkAssembler:
    """Collects the chunks of one transfer (a model file, or an update) and verifies the
    whole against its sha256.

    Args:
        sha256: the whole's sha256 (64 hex).
        total: its size in bytes, in [1, ``limit``].
        chunk_bytes: the chunk size (``CHUNK_BYTES``, ``UPDATE_CHUNK_BYTES``).
        what: names the transfer in messages ("model", "update 3").
        limit: the largest whole allowed.
    """

    def __init__(self, sha256: str, total: int, chunk_bytes: int = CHUNK_BYTES,
                 what: str = "model", limit: int = MAX_MODEL_BYTES) -> None:
        _require(bool(_HEX64.fullmatch(sha256)), f"{what} sha256: not 64 hex digits")
        _require(0 < total <= limit, f"{what} size {total}: out of range")
        self.sha256, self.total, self.what = sha256, total, what
        self.count = math.ceil(total / chunk_bytes)
        self._parts: dict[int, bytes] = {}

    def missing(self) -> list[int]:
        """Indices of the chunks still to fetch."""
        return [i for i in range(self.count) if i not in self._parts]

    def add(self, chunk: ModelChunk | UpdateChunk) -> None:
        """Accept one chunk (already validated on decode) of this transfer."""
        if chunk.sha256 != self.sha256 or chunk.total != self.total:
            raise ControlError(f"{chunk.TYPE}: belongs to another {self.what.split()[0]}")
        self._parts[chunk.index] = chunk.data

    def result(self) -> bytes:
        """The whole, once every chunk is in and the sha256 matches."""
        if missing := self.missing():
            raise ControlError(f"{self.what} transfer incomplete: {len(missing)} chunks "
                               f"missing")
        data = b"".join(self._parts[i] for i in range(self.count))
        if hashlib.sha256(data).hexdigest() != self.sha256:
            raise ControlError(f"{self.what} transfer: the chunks do not hash to the "
                               f"announced sha256")
        return data




def _camera_fields(camera: dict[Any, Any]) -> dict[str, Any]:
    want = {"fx": (float, int), "fy": (float, int), "cx": (float, int), "cy": (float, int),
            "width": (int,), "height": (int,)}
    if camera.keys() != want.keys():
        raise ControlError("hello.camera: expected exactly fx, fy, cx, cy, width, height")
    for key, types in want.items():
        if not isinstance(camera[key], types) or isinstance(camera[key], bool):
            raise ControlError(f"hello.camera.{key}: wrong type")
        if isinstance(camera[key], float) and not math.isfinite(camera[key]):
            raise ControlError(f"hello.camera.{key}: not finite")
    return camera


def _check_time(name: str, value: float) -> None:
    _require(isinstance(value, (int, float)) and not isinstance(value, bool)
             and math.isfinite(value) and abs(value) <= MAX_CLOCK_S,
             f"{name}: expected a finite time of at most {MAX_CLOCK_S:g} s")


def _no_ext(code: int, data: bytes) -> None:
    raise ControlError(f"msgpack extension type {code} is not allowed")


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ControlError(message)
