"""The packet log (``.fwlog``): a header, then fixed-size records, append-only.

Layout, big-endian:

========  =======  ===============================================================
offset    size     content
========  =======  ===============================================================
0         8        magic ``b"\\x89FWLOG\\r\\n"``
8         2        log format version (1)
10        2        packet size in bytes (43 for protocol version 2)
12        4        Hello length L (at most 64 KiB)
16        L        the Hello, as its msgpack control message
16+L      4        CRC-32 of bytes 0 .. 16+L
20+L      55 each  records: f64 time (s, Unix epoch), the packet, CRC-32 of both
========  =======  ===============================================================

The writer writes the header and then every record straight to the file (no user-space
buffer), so a killed writer leaves every finished record readable. The reader recovers every
intact record of a truncated or partly corrupted log: a record is intact when its CRC-32
matches, its time is finite and its packet decodes (a CRC-32 that matches by chance at a
wrong offset has odds of 1 in 2**32). After a bad record it re-synchronises by
searching forward byte by byte for the next intact one (trying only the offsets whose
packet's first byte, version and reserved flag bits, fits), so inserted or deleted bytes
cost only the records they touch. It reports how many records were lost: each run of unusable
bytes counts as its length in records, rounded, and at least one.

A log written by another protocol version is refused at its header with one line naming the
version: its packet size says which (39 bytes: version 1), and a log whose size matches but
whose Hello announces another protocol is refused by the Hello's check of its version.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np

from facewire.protocol.control import ControlError, Hello, decode_message, encode_message
from facewire.protocol.errors import FacewireError
from facewire.protocol.packet import PACKET_BYTES, RESERVED_FLAGS, VERSION, decode_frames

MAGIC = b"\x89FWLOG\r\n"
FORMAT_VERSION = 1
MAX_HELLO_BYTES = 64 * 1024
MAX_LOG_BYTES = 2 * 1024**3
_HEAD = struct.Struct(">8sHHI")
_TIME = struct.Struct(">d")
RECORD_BYTES = _TIME.size + PACKET_BYTES + 4
# A packet's first byte holds its version, then the high half of its flags, whose reserved
# bits are 0: the re-synchronising search tries only the offsets where that byte fits.
_FIRST_MASK = 0xF0 | (RESERVED_FLAGS >> 4)
_FIRST_BYTE = VERSION << 4
_PACKET_VERSIONS = {39: 1, PACKET_BYTES: VERSION}  # packet size -> protocol version


class LogError(FacewireError, ValueError):
    """A packet log cannot be read; the message names the file and the field."""


@dataclass
class PacketLog:
    """What a log holds.

    Attributes:
        hello: the session's Hello.
        times: (N,) float64 record times, s.
        packets: (N, 43) uint8 intact packets, in file order.
        frames: (N,) ``FRAME_DTYPE``, the decoded packets.
        lost: records that could not be recovered (corrupt or cut off).
    """

    hello: Hello
    times: np.ndarray
    packets: np.ndarray
    frames: np.ndarray
    lost: int


class LogWriter:
    """Appends records to a new log. Use as a context manager, or call ``close``."""

    def __init__(self, path: str | os.PathLike[str], hello: Hello) -> None:
        self.path = Path(path)
        body = encode_message(hello)
        head = _HEAD.pack(MAGIC, FORMAT_VERSION, PACKET_BYTES, len(body)) + body
        self._file = open(self.path, "wb", buffering=0)
        self._file.write(head + struct.pack(">I", zlib.crc32(head)))
        self.records = 0

    def write(self, packet: bytes, time: float) -> None:
        """Append one packet with its time (s)."""
        if len(packet) != PACKET_BYTES:
            raise ValueError(f"packet has {len(packet)} bytes, expected {PACKET_BYTES}")
        record = _TIME.pack(time) + packet
        self._file.write(record + struct.pack(">I", zlib.crc32(record)))
        self.records += 1

    def close(self) -> None:
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
    hello, start = _read_header(path, data)
    offsets, lost = _intact_records(data, start)
    times = np.array([_TIME.unpack_from(data, o)[0] for o in offsets], np.float64)
    packets = np.array([np.frombuffer(data, np.uint8, PACKET_BYTES, o + _TIME.size)
                        for o in offsets], np.uint8).reshape(-1, PACKET_BYTES)
    frames, errors = decode_frames(packets)
    ok = errors == None  # noqa: E711 (elementwise on an object array)
    return PacketLog(hello, times[ok], packets[ok], frames[ok], lost + int((~ok).sum()))


def _read_header(path: Path, data: bytes) -> tuple[Hello, int]:
    if len(data) < _HEAD.size:
        raise LogError(f"{path}: header: file too short to be a packet log")
    magic, version, packet_bytes, hello_len = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise LogError(f"{path}: header.magic: not a facewire packet log")
    if version != FORMAT_VERSION:
        raise LogError(f"{path}: header.version: log format {version} is not supported "
                       f"(this facewire reads {FORMAT_VERSION})")
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
    if zlib.crc32(data[:end]) != struct.unpack_from(">I", data, end)[0]:
        raise LogError(f"{path}: header.crc: header is corrupt")
    try:
        hello = decode_message(data[_HEAD.size:end])
    except ControlError as exc:
        raise LogError(f"{path}: header.hello: {exc}") from None
    if not isinstance(hello, Hello):
        raise LogError(f"{path}: header.hello: holds a {hello.TYPE}, not a hello")
    return hello, end + 4


def _intact_records(data: bytes, start: int) -> tuple[list[int], int]:
    """Offsets of intact records, re-synchronising byte by byte after a bad one.

    Returns the offsets and the number of records lost: each run of unusable bytes counts as
    its length in records, rounded, and at least one.
    """
    offsets = []
    lost = 0
    offset = gap_start = start
    view = np.frombuffer(data, np.uint8)
    while offset + RECORD_BYTES <= len(data):
        if _intact(data, offset):
            lost += _records_in_gap(offset - gap_start)
            offsets.append(offset)
            offset += RECORD_BYTES
            gap_start = offset
        else:
            offset = _next_candidate(view, offset + 1)
    return offsets, lost + _records_in_gap(len(data) - gap_start)


def _next_candidate(view: np.ndarray, offset: int) -> int:
    """The first offset from ``offset`` whose packet's first byte fits, else the end.

    Searched with numpy in windows that double, so that megabytes of zeros (a crash's
    zero-filled blocks) or noise cost milliseconds, not a Python step per byte.
    """
    size = 64
    while offset + RECORD_BYTES <= len(view):
        window = view[offset + _TIME.size:offset + _TIME.size + size]
        hits = np.flatnonzero((window & _FIRST_MASK) == _FIRST_BYTE)
        if len(hits):
            return offset + int(hits[0])
        offset += len(window)
        size = min(2 * size, 1 << 20)
    return len(view)


def _records_in_gap(size: int) -> int:
    return max(1, round(size / RECORD_BYTES)) if size > 0 else 0


def _intact(data: bytes, offset: int) -> bool:
    """Whether the record at offset has a matching CRC-32 and a finite time.

    Its packet is validated afterwards, for all records at once.
    """
    body = data[offset:offset + RECORD_BYTES - 4]
    return (zlib.crc32(body) == struct.unpack_from(">I", data, offset + RECORD_BYTES - 4)[0]
            and math.isfinite(_TIME.unpack_from(body)[0]))
