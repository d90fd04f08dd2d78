"""The packet log (``.fwlog``): a header, then records, append-only.

Layout, big-endian:

========  =======  ===============================================================
offset    size     content
========  =======  ===============================================================
0         8        magic ``b"\\x89FWLOG\\r\\n"``
8         2        log format version (3)
10        2        packet size P in bytes (``protocol.packet.PACKET_BYTES``)
12        4        Hello length L (at most 64 KiB)
16        L        the Hello, as its msgpack control message
16+L      4        CRC-32 of bytes 0 .. 16+L
20+L      ...      records, in the order they were written
========  =======  ===============================================================

A record is one of three kinds, told apart by the byte after its time:

- a packet record, 8 + P + 4 bytes: f64 time (s), the packet, CRC-32 of both. The packet's
  first byte holds its version in the top nibble and two flag bits under it (the reserved
  ones 0);
- an update record, 8 + 1 + 2 + 4 + U + 4 bytes: f64 time (s), the tag ``UPDATE_TAG``
  (``b"U"``, which no packet's first byte can be), u16 the update's serial (1 ..
  ``MAX_SERIAL``), u32 U (1 .. ``MAX_UPDATE_BYTES``), the update's U bytes (opaque here:
  ``models.update.encode_update``'s), CRC-32 of everything before it in the record;
- a voice record, 8 + 1 + 1 + V + 4 bytes: f64 time (s), the tag ``VOICE_TAG`` (``b"A"``),
  u8 V (``protocol.voice``'s smallest packet .. ``MAX_VOICE_BYTES``), the voice packet's V
  bytes (checked by its own CRC-16 when read), CRC-32 of everything before it in the record.
  Voice records are written as the voice packets were sent, between the face's packets.

An update record is written where the sender issued the update: after the packets sent
before it, before the first packet whose serial refers to it. Times are s since the Unix
epoch (``send --record``) or the source's presentation time (``encode``).

The writer writes the header and then every record straight to the file (no user-space
buffer), so a killed writer leaves every finished record readable. The reader recovers every
intact record of a truncated or partly corrupted log: a packet record is intact when its
CRC-32 matches, its time is finite and its packet decodes; an update record when its tag,
serial and length are in range, it fits in the file, its CRC-32 matches and its time is
finite (a CRC-32 that matches by chance at a wrong offset has odds of 1 in 2**32). After a
bad record it re-synchronises by searching forward byte by byte for the next intact one
(trying only the offsets whose byte after the time is a packet's first byte, the update
tag or the voice tag), so inserted or deleted bytes cost only the records they touch.
Reading is linear in the file's size whatever it holds: an update record's head can be
forged every few bytes, each declaring a body that reaches far ahead, so the bytes hashed to
check update records are at most ``CHECK_FACTOR`` times the file's size (plus one largest
update); past that budget an update head is taken for unusable bytes (no honest log comes
near it: each of its bytes is hashed once). It reports what was lost: a run of unusable
bytes that begins with an update record's head (tag, serial and length in range) holds one
lost update record of that length (or the rest of the run, whichever is shorter); the rest of
the run counts as its length in packet records, rounded, and at least one; a run that begins
with a voice record's head (tag and length in range) and is exactly that record's length
counts one lost voice record (a voice head is short enough to turn up by chance in garbage).
``PacketLog.missing_serials`` are the update serials between 1 and the highest any intact
record names (an update's own, or a packet's ``serial``) that no intact
update record holds: the updates a replay cannot apply, whose frames it plays clamped.

Format 1 (before model updates) is format 2 without update records, and format 2 (before the
voice) is format 3 without voice records; both are read as such while their packets are this
facewire's. A log written by another protocol version is refused
at its header with one line naming the version: its packet size says which (39 bytes:
version 1), and a log whose size matches but whose Hello announces another protocol is
refused by the Hello's check of its version.
"""

from __future__ import annotations

import math
import os
import struct
import threading
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np

from facewire.protocol.control import (
    MAX_UPDATE_BYTES,
    ControlError,
    Hello,
    decode_message,
    encode_message,
)
from facewire.protocol.errors import FacewireError
from facewire.protocol.packet import (
    MAX_SERIAL,
    PACKET_BYTES,
    RESERVED_FLAGS,
    VERSION,
    decode_frames,
)
from facewire.protocol.voice import CRC_BYTES, HEADER_BYTES, MAX_VOICE_BYTES, VoiceError, decode

MAGIC = b"\x89FWLOG\r\n"
FORMAT_VERSION = 3
READ_VERSIONS = (1, 2, 3)
MAX_HELLO_BYTES = 64 * 1024
MAX_LOG_BYTES = 2 * 1024**3
CHECK_FACTOR = 4
UPDATE_TAG = ord("U")
VOICE_TAG = ord("A")
_HEAD = struct.Struct(">8sHHI")
_TIME = struct.Struct(">d")
_CRC = struct.Struct(">I")
_UPDATE_HEAD = struct.Struct(">dBHI")  # time, tag, serial, length
_VOICE_HEAD = struct.Struct(">dBB")  # time, tag, length
_MIN_VOICE_BYTES = HEADER_BYTES + 1 + CRC_BYTES
RECORD_BYTES = _TIME.size + PACKET_BYTES + _CRC.size  # a packet record
# A packet's first byte holds its version, then the high half of its flags, whose reserved
# bits are 0: the re-synchronising search tries only the offsets where that byte fits, or
# where the update tag is.
_FIRST_MASK = 0xF0 | (RESERVED_FLAGS >> 4)
_FIRST_BYTE = VERSION << 4
_PACKET_VERSIONS = {39: 1, PACKET_BYTES: VERSION}  # packet size -> protocol version


class LogError(FacewireError, ValueError):
    """A packet log cannot be read; the message names the file and the field."""


@dataclass(frozen=True)
class LoggedUpdate:
    """One intact update record.

    Attributes:
        time: the record's time, s.
        serial: the update's serial, 1 .. ``MAX_SERIAL``.
        data: the update's bytes (``models.update.decode_update`` reads them).
        before: the number of intact packets that precede it in the log (its place among
            ``PacketLog.packets``: it was issued before packet ``before``).
    """

    time: float
    serial: int
    data: bytes
    before: int


@dataclass(frozen=True)
class LoggedVoice:
    """One intact voice record: ``time`` (s), ``data`` (the voice packet's bytes, which
    ``protocol.voice.decode`` accepts) and ``before`` (intact packets before it in the log)."""

    time: float
    data: bytes
    before: int


@dataclass
class PacketLog:
    """What a log holds.

    Attributes:
        hello: the session's Hello.
        times: (N,) float64 packet record times, s.
        packets: (N, 43) uint8 intact packets, in file order.
        frames: (N,) ``FRAME_DTYPE``, the decoded packets.
        lost: packet records that could not be recovered (corrupt or cut off).
        updates: the intact update records, in file order.
        lost_updates: update records that were found damaged (their head intact).
        missing_serials: the serials from 1 to the highest any intact record names that no
            intact update record holds, ascending (module docstring).
        voice: the intact voice records, in file order.
        lost_voice: voice records found damaged (their head intact).
    """

    hello: Hello
    times: np.ndarray
    packets: np.ndarray
    frames: np.ndarray
    lost: int
    updates: tuple[LoggedUpdate, ...] = ()
    lost_updates: int = 0
    missing_serials: tuple[int, ...] = ()
    voice: tuple[LoggedVoice, ...] = ()
    lost_voice: int = 0


class LogWriter:
    """Appends records to a new log. Use as a context manager, or call ``close``. Records may
    be written from several threads (the send loop's face, its voice thread): each is one
    ``write`` under a lock, so records never interleave.

    Attributes:
        records: packet records written.
        updates: update records written.
        voice: voice records written.
    """

    def __init__(self, path: str | os.PathLike[str], hello: Hello) -> None:
        self.path = Path(path)
        body = encode_message(hello)
        head = _HEAD.pack(MAGIC, FORMAT_VERSION, PACKET_BYTES, len(body)) + body
        self._file = open(self.path, "wb", buffering=0)
        self._lock = threading.Lock()
        self._file.write(head + _CRC.pack(zlib.crc32(head)))
        self.records = 0
        self.updates = 0
        self.voice = 0

    def write(self, packet: bytes, time: float) -> None:
        """Append one packet with its time (s)."""
        if len(packet) != PACKET_BYTES:
            raise ValueError(f"packet has {len(packet)} bytes, expected {PACKET_BYTES}")
        record = _TIME.pack(time) + packet
        self._append(record)
        self.records += 1

    def write_update(self, time: float, serial: int, data: bytes) -> None:
        """Append one model update, where it was issued: after the packets sent before it,
        before the first packet that refers to it.

        Args:
            time: the time it was issued, s (the clock of the packet records).
            serial: its serial, 1 .. ``MAX_SERIAL``.
            data: its bytes (``models.update.encode_update``), 1 .. ``MAX_UPDATE_BYTES``.
        """
        if not (isinstance(serial, int) and 1 <= serial <= MAX_SERIAL):
            raise ValueError(f"serial: expected an integer in [1, {MAX_SERIAL}], got {serial!r}")
        if not 1 <= len(data) <= MAX_UPDATE_BYTES:
            raise ValueError(f"update {serial} has {len(data)} bytes, expected 1 .. "
                             f"{MAX_UPDATE_BYTES}")
        record = _UPDATE_HEAD.pack(time, UPDATE_TAG, serial, len(data)) + bytes(data)
        self._append(record)
        self.updates += 1

    def write_voice(self, packet: bytes, time: float) -> None:
        """Append one voice packet (``protocol.voice``'s bytes) with its time (s)."""
        if not _MIN_VOICE_BYTES <= len(packet) <= MAX_VOICE_BYTES:
            raise ValueError(f"voice packet has {len(packet)} bytes, expected "
                             f"{_MIN_VOICE_BYTES} .. {MAX_VOICE_BYTES}")
        record = _VOICE_HEAD.pack(time, VOICE_TAG, len(packet)) + bytes(packet)
        self._append(record)
        self.voice += 1

    def _append(self, record: bytes) -> None:
        with self._lock:
            self._file.write(record + _CRC.pack(zlib.crc32(record)))

    def close(self) -> None:
        with self._lock:
            self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def read_log(path: str | os.PathLike[str]) -> PacketLog:
    """Read a log, recovering every intact record.

    Raises:
        LogError: missing or unreadable file, or a bad header (the records cannot be
            interpreted without it); the message names the file and the field.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_LOG_BYTES:
            raise LogError(f"{path}: {size} bytes is larger than the {MAX_LOG_BYTES} allowed")
        data = path.read_bytes()
    except OSError as exc:
        raise LogError(f"{path}: cannot read: {exc.strerror or exc}") from None
    hello, start, version = _read_header(path, data)
    found = _Records(data, updates=version >= 2, voice=version >= 3)
    found.scan(start)
    offsets = found.packets
    times = np.array([_TIME.unpack_from(data, o)[0] for o in offsets], np.float64)
    packets = np.array([np.frombuffer(data, np.uint8, PACKET_BYTES, o + _TIME.size)
                        for o in offsets], np.uint8).reshape(-1, PACKET_BYTES)
    frames, errors = decode_frames(packets)
    ok = errors == None  # noqa: E711 (elementwise on an object array)
    kept = np.concatenate([[0], np.cumsum(ok)])  # intact packets before each packet record
    updates = tuple(LoggedUpdate(time, serial, payload, int(kept[before]))
                    for time, serial, payload, before in found.updates)
    voice = tuple(LoggedVoice(time, payload, int(kept[before]))
                  for time, payload, before in found.voice)
    frames = frames[ok]
    return PacketLog(hello, times[ok], packets[ok], frames, found.lost + int((~ok).sum()),
                     updates, found.lost_updates, _missing_serials(updates, frames), voice,
                     found.lost_voice)


def _missing_serials(updates: tuple[LoggedUpdate, ...], frames: np.ndarray) -> tuple[int, ...]:
    """The serials from 1 to the highest named (by an update or a frame) that no update
    holds."""
    named = [u.serial for u in updates] + ([int(frames["serial"].max())] if len(frames) else [])
    held = {u.serial for u in updates}
    return tuple(s for s in range(1, max(named, default=0) + 1) if s not in held)


def _read_header(path: Path, data: bytes) -> tuple[Hello, int, int]:
    """The Hello, the offset of the first record and the format version."""
    if len(data) < _HEAD.size:
        raise LogError(f"{path}: header: file too short to be a packet log")
    magic, version, packet_bytes, hello_len = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise LogError(f"{path}: header.magic: not a facewire packet log")
    if version not in READ_VERSIONS:
        raise LogError(f"{path}: header.version: log format {version} is not supported "
                       f"(this facewire reads {', '.join(map(str, READ_VERSIONS))})")
    if packet_bytes != PACKET_BYTES:
        known = _PACKET_VERSIONS.get(packet_bytes)
        what = f"protocol version {known}" if known else "an unknown protocol version"
        raise LogError(f"{path}: header.packet_bytes: {packet_bytes}-byte packets are {what}; "
                       f"this facewire reads version {VERSION} ({PACKET_BYTES}-byte packets)")
    if hello_len > MAX_HELLO_BYTES:
        raise LogError(f"{path}: header.hello_length: {hello_len} exceeds {MAX_HELLO_BYTES}")
    end = _HEAD.size + hello_len
    if len(data) < end + 4:
        raise LogError(f"{path}: header: truncated")
    if zlib.crc32(data[:end]) != _CRC.unpack_from(data, end)[0]:
        raise LogError(f"{path}: header.crc: header is corrupt")
    try:
        hello = decode_message(data[_HEAD.size:end])
    except ControlError as exc:
        raise LogError(f"{path}: header.hello: {exc}") from None
    if not isinstance(hello, Hello):
        raise LogError(f"{path}: header.hello: holds a {hello.TYPE}, not a hello")
    return hello, end + 4, version


class _Records:
    """The intact records of a log's body, re-synchronising byte by byte after a bad one.

    After ``scan``: ``packets``, the offsets of the packet records that pass their CRC-32
    and time checks (their packets are decoded afterwards, all at once); ``updates``, the
    intact update records as (time, serial, data, packet records before it); ``voice``, the
    intact voice records as (time, data, packet records before it); ``lost``,
    ``lost_updates``, ``lost_voice``: the module docstring's count of each run of unusable
    bytes.
    """

    def __init__(self, data: bytes, updates: bool, voice: bool) -> None:
        self.data = data
        self.view = np.frombuffer(data, np.uint8)
        self.with_updates = updates
        self.with_voice = voice
        self.packets: list[int] = []
        self.updates: list[tuple[float, int, bytes, int]] = []
        self.voice: list[tuple[float, bytes, int]] = []
        self.lost = 0
        self.lost_updates = 0
        self.lost_voice = 0
        self._budget = CHECK_FACTOR * len(data) + MAX_UPDATE_BYTES  # bytes hashed (docstring)

    def scan(self, start: int) -> None:
        offset = gap_start = start
        end = len(self.data)
        while offset + min(RECORD_BYTES, _UPDATE_HEAD.size) <= end:
            size = self._intact(offset)
            if size:
                self._gap(gap_start, offset)
                offset += size
                gap_start = offset
            else:
                offset = self._next_candidate(offset + 1)
        self._gap(gap_start, end)

    def _intact(self, offset: int) -> int:
        """The size of the intact record at ``offset`` (kept), else 0."""
        data = self.data
        if offset + _TIME.size < len(data) and data[offset + _TIME.size] == VOICE_TAG \
                and self.with_voice:
            return self._intact_voice(offset)
        if offset + _TIME.size < len(data) and data[offset + _TIME.size] == UPDATE_TAG \
                and self.with_updates:
            head = self._update_head(offset)
            if head is None:
                return 0
            time, serial, length = head
            body_end = offset + _UPDATE_HEAD.size + length
            if body_end + _CRC.size > len(data) or not math.isfinite(time) \
                    or body_end - offset > self._budget:
                return 0
            self._budget -= body_end - offset
            if zlib.crc32(data[offset:body_end]) != _CRC.unpack_from(data, body_end)[0]:
                return 0
            self.updates.append((time, serial, data[offset + _UPDATE_HEAD.size:body_end],
                                 len(self.packets)))
            return body_end + _CRC.size - offset
        if offset + RECORD_BYTES > len(data):
            return 0
        body = data[offset:offset + RECORD_BYTES - _CRC.size]
        if zlib.crc32(body) != _CRC.unpack_from(data, offset + RECORD_BYTES - _CRC.size)[0] \
                or not math.isfinite(_TIME.unpack_from(body)[0]):
            return 0
        self.packets.append(offset)
        return RECORD_BYTES

    def _intact_voice(self, offset: int) -> int:
        """The size of the intact voice record at ``offset`` (kept), else 0."""
        length = self._voice_head(offset)
        end = offset + _VOICE_HEAD.size + (length or 0)
        if length is None or end + _CRC.size > len(self.data) \
                or not math.isfinite(_VOICE_HEAD.unpack_from(self.data, offset)[0]) \
                or zlib.crc32(self.data[offset:end]) != _CRC.unpack_from(self.data, end)[0]:
            return 0
        payload = self.data[offset + _VOICE_HEAD.size:end]
        try:
            decode(payload)
        except VoiceError:
            return 0
        self.voice.append((_VOICE_HEAD.unpack_from(self.data, offset)[0], payload,
                           len(self.packets)))
        return end + _CRC.size - offset

    def _voice_head(self, offset: int) -> int | None:
        """The length of a voice record's packet at ``offset`` when its tag and length are in
        range, else None."""
        if offset + _VOICE_HEAD.size > len(self.data):
            return None
        _, tag, length = _VOICE_HEAD.unpack_from(self.data, offset)
        if tag != VOICE_TAG or not _MIN_VOICE_BYTES <= length <= MAX_VOICE_BYTES:
            return None
        return int(length)

    def _update_head(self, offset: int) -> tuple[float, int, int] | None:
        """(time, serial, length) of an update record's head at ``offset`` when its tag,
        serial and length are in range, else None."""
        if offset + _UPDATE_HEAD.size > len(self.data):
            return None
        time, tag, serial, length = _UPDATE_HEAD.unpack_from(self.data, offset)
        if tag != UPDATE_TAG or not 1 <= serial <= MAX_SERIAL \
                or not 1 <= length <= MAX_UPDATE_BYTES:
            return None
        return time, serial, length

    def _gap(self, start: int, stop: int) -> None:
        """Count the unusable bytes [start, stop) (module docstring)."""
        size = stop - start
        if size <= 0:
            return
        head = self._update_head(start) if self.with_updates else None
        voice = self._voice_head(start) if self.with_voice else None
        if head is not None:
            self.lost_updates += 1
            size -= min(size, _UPDATE_HEAD.size + head[2] + _CRC.size)
        elif voice is not None and size == _VOICE_HEAD.size + voice + _CRC.size:
            self.lost_voice += 1
            size = 0
        if size > 0:
            self.lost += max(1, round(size / RECORD_BYTES))

    def _next_candidate(self, offset: int) -> int:
        """The first offset from ``offset`` whose byte after the time is a packet's first
        byte, the update tag or the voice tag, else the end.

        Searched with numpy in windows that double, so that megabytes of zeros (a crash's
        zero-filled blocks) or noise cost milliseconds, not a Python step per byte.
        """
        view = self.view
        size = 64
        while offset + _TIME.size < len(view):
            window = view[offset + _TIME.size:offset + _TIME.size + size]
            fits = (window & _FIRST_MASK) == _FIRST_BYTE
            if self.with_updates:
                fits |= window == UPDATE_TAG
            if self.with_voice:
                fits |= window == VOICE_TAG
            hits = np.flatnonzero(fits)
            if len(hits):
                return offset + int(hits[0])
            offset += len(window)
            size = min(2 * size, 1 << 20)
        return len(view)
