"""The packet log: writing, reading, recovery from truncation and corruption, killed writers."""

from __future__ import annotations

import math
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest

from facewire.protocol import log as log_module
from facewire.protocol.control import Camera, Hello, encode_message
from facewire.protocol.log import CHECK_FACTOR, RECORD_BYTES, LogError, LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames

HELLO = Hello("0f" * 32, 4096, 30.0, Camera(500.0, 500.0, 320.0, 240.0, 640, 480),
              ("forehead", "mouth"))


def _write(path: Path, n: int) -> np.ndarray:
    frames = np.zeros(n, FRAME_DTYPE)
    frames["seq"] = np.arange(n)
    frames["flags"] = Flag.FACE_PRESENT
    frames["translation"][:, 2] = -600
    frames["residuals"] = np.linspace(-5, 5, 18).reshape(9, 2)
    packets, _ = encode_frames(frames)
    with LogWriter(path, HELLO) as log:
        for i, p in enumerate(packets):
            log.write(p.tobytes(), 100.0 + i / 30)
    return packets


def test_round_trip(tmp_path: Path) -> None:
    packets = _write(tmp_path / "a.fwlog", 90)
    log = read_log(tmp_path / "a.fwlog")
    assert log.hello == HELLO and log.lost == 0
    np.testing.assert_array_equal(log.packets, packets)
    assert log.frames["seq"].tolist() == list(range(90))
    np.testing.assert_allclose(np.diff(log.times), 1 / 30, rtol=1e-9)


def test_empty_log(tmp_path: Path) -> None:
    _write(tmp_path / "e.fwlog", 0)
    log = read_log(tmp_path / "e.fwlog")
    assert len(log.frames) == 0 and log.lost == 0


def test_truncated_at_every_byte_offset(tmp_path: Path) -> None:
    src = tmp_path / "full.fwlog"
    _write(src, 5)
    data = src.read_bytes()
    header = len(data) - 5 * RECORD_BYTES
    cut = tmp_path / "cut.fwlog"
    for end in range(len(data) + 1):
        cut.write_bytes(data[:end])
        if end < header:
            with pytest.raises(LogError, match="header"):
                read_log(cut)
            continue
        log = read_log(cut)
        whole, partial = divmod(end - header, RECORD_BYTES)
        assert len(log.frames) == whole, end
        assert log.lost == (1 if partial else 0), end
        assert log.frames["seq"].tolist() == list(range(whole))


def test_corruption_loses_only_the_records_it_touches(tmp_path: Path) -> None:
    src = tmp_path / "c.fwlog"
    _write(src, 60)
    data = bytearray(src.read_bytes())
    header = len(data) - 60 * RECORD_BYTES
    at = header + 44 * RECORD_BYTES + 9  # from the end, so earlier offsets stay put
    data[at:at] = b"junk"  # bytes inserted into record 44
    del data[header + 30 * RECORD_BYTES + 5: header + 30 * RECORD_BYTES + 8]  # record 30 shortened
    data[header + 20 * RECORD_BYTES + 2] ^= 0xFF  # record 20: time corrupted
    data[header + 10 * RECORD_BYTES + 20] ^= 0x10  # record 10: packet bit flip
    src.write_bytes(bytes(data))
    log = read_log(src)
    seqs = log.frames["seq"].tolist()
    assert 10 not in seqs and 20 not in seqs and 30 not in seqs and 44 not in seqs
    assert len(seqs) == 56 and seqs == sorted(seqs)
    assert log.lost == 4


@pytest.mark.parametrize("mutate,field", [
    (lambda d: b"NOTALOG!" + d[8:], "header.magic"),
    (lambda d: d[:8] + b"\x00\x09" + d[10:], "header.version"),
    (lambda d: d[:10] + b"\x00\x28" + d[12:], "header.packet_bytes"),
    (lambda d: d[:12] + b"\x7f\xff\xff\xff" + d[16:], "header.hello_length"),
    (lambda d: d[:20] + bytes([d[20] ^ 1]) + d[21:], "header.crc"),
    (lambda d: d[:5], "header"),
])
def test_bad_headers_name_the_field(tmp_path: Path, mutate, field: str) -> None:
    src = tmp_path / "h.fwlog"
    _write(src, 3)
    src.write_bytes(mutate(src.read_bytes()))
    with pytest.raises(LogError, match=field) as err:
        read_log(src)
    assert str(src) in str(err.value)


def _version_1_log(path: Path, packet_bytes: int) -> None:
    """A log as protocol version 1 wrote it: its Hello says protocol 1 and has no serial or
    shade, its header's packet size is ``packet_bytes`` (39 then), three records."""
    hello = msgpack.unpackb(encode_message(HELLO))
    hello["protocol"] = 1
    hello["quantisers"] = [q for q in hello["quantisers"] if q["name"] != "shade"]
    body = msgpack.packb(hello)
    head = struct.pack(">8sHHI", b"\x89FWLOG\r\n", 1, packet_bytes, len(body)) + body
    records = b""
    for seq in range(3):
        record = struct.pack(">d", 100.0 + seq / 30) + bytes([0x10, 0x00, seq]) + bytes(
            packet_bytes - 3)
        records += record + struct.pack(">I", zlib.crc32(record))
    path.write_bytes(head + struct.pack(">I", zlib.crc32(head)) + records)


@pytest.mark.parametrize(("packet_bytes", "message"), [
    (39, r"header.packet_bytes: 39-byte packets are protocol version 1; this facewire reads "
         r"version 2 \(43-byte packets\)"),
    (43, r"header.hello: hello.protocol: the sender speaks protocol version 1, this facewire "
         r"version 2"),
])
def test_a_version_1_log_is_refused_naming_the_version(tmp_path: Path, packet_bytes: int,
                                                       message: str) -> None:
    """By its packet size when it has version 1's (the real case), else by its Hello."""
    path = tmp_path / "v1.fwlog"
    _version_1_log(path, packet_bytes)
    with pytest.raises(LogError, match=message) as err:
        read_log(path)
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)


def test_forged_update_heads_cost_a_bounded_number_of_bytes_hashed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """4000 forged update heads in 1 MiB (issue 26 item 12), each declaring a body that
    reaches almost to the end of that MiB, then 30 packet records: at most ``CHECK_FACTOR``
    times the file is hashed (each head hashing its body would be about 2000 times), and the
    packets after the heads are read."""
    region = 1 << 20
    heads = b"".join(struct.pack(">dBHI", 1.0, ord("U"), 1, region - 15 * i - 15 - 4 - 64)
                     for i in range(4000))
    path = tmp_path / "forged.fwlog"
    _write(path, 0)
    header = path.stat().st_size
    _write(tmp_path / "tail.fwlog", 30)
    with path.open("ab") as f:
        f.write(heads + bytes(region - len(heads)))
        f.write((tmp_path / "tail.fwlog").read_bytes()[header:])
    hashed = [0]
    crc32 = zlib.crc32

    def counting(data: bytes, value: int = 0) -> int:
        hashed[0] += len(data)
        return crc32(data, value)

    monkeypatch.setattr(log_module.zlib, "crc32", counting)
    log = read_log(path)
    assert len(log.times) == 30
    assert CHECK_FACTOR <= 8  # the bound below: linear, with a small factor
    assert hashed[0] <= 8 * path.stat().st_size + 2 * region, hashed[0]


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(LogError, match="cannot read"):
        read_log(tmp_path / "nope.fwlog")


def test_killed_writer_leaves_a_readable_log(tmp_path: Path) -> None:
    path = tmp_path / "killed.fwlog"
    script = f"""
import sys, time, numpy as np
sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})
from tests.test_log import HELLO
from facewire.protocol.log import LogWriter
from facewire.protocol.packet import Frame, encode
w = LogWriter({str(path)!r}, HELLO)
i = 0
while True:
    w.write(encode(Frame(seq=i)), time.time())
    i += 1
    if i == 50:
        print("ready", flush=True)
    time.sleep(0.001)
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
    time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    log = read_log(path)
    assert len(log.frames) >= 50
    assert log.lost <= 1
    assert log.frames["seq"].tolist() == list(range(len(log.frames)))
    assert math.isfinite(log.times[-1])
