"""A raw ZMTP 3.0 peer of test code over a plain TCP socket (RFC 23/ZMTP, NULL mechanism),
to send what libzmq's own sockets never would: a frame header declaring a gigabyte.

    greeting  0xFF | 8 bytes padding | 0x7F | version 3, 0 | b"NULL" padded to 20 bytes
              | as-server (1 byte) | 31 bytes filler                              (64 bytes)
    READY     flags 0x04 | size (1 byte) | b"\\x05READY" | b"\\x0bSocket-Type"
              | value length (4 bytes, big-endian) | value
    a long frame's header: flags 0x02 | size (8 bytes, big-endian)
    a short frame:         flags (0x01: more frames follow) | size (1 byte) | body

A peer sends its greeting and its READY and reads the other side's. Reads take exactly the
bytes expected: ``recv`` on a socket with a timeout may return fewer, and libzmq sends its
greeting in two parts. A CURVE greeting (``greeting(mechanism=b"CURVE")``) starts a handshake
that the raw peer never finishes: what it sends then is what an unauthenticated peer can send.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time

GIGABYTE = 1 << 30


def greeting(as_server: bool, mechanism: bytes = b"NULL") -> bytes:
    return (b"\xff" + bytes(8) + b"\x7f\x03\x00" + mechanism.ljust(20, b"\x00")
            + bytes([as_server]) + bytes(31))


def ready(socket_type: bytes) -> bytes:
    body = b"\x05READY\x0bSocket-Type" + struct.pack(">I", len(socket_type)) + socket_type
    return bytes([0x04, len(body)]) + body


def read_exactly(conn: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        part = conn.recv(size - len(data))
        assert part, f"the connection closed after {len(data)} of {size} bytes"
        data += part
    return data


def handshake(conn: socket.socket, socket_type: bytes, as_server: bool) -> None:
    """Greet the libzmq peer on ``conn`` and exchange READY commands, posing as
    ``socket_type``."""
    conn.sendall(greeting(as_server))
    assert read_exactly(conn, 64)[:1] == b"\xff"
    conn.sendall(ready(socket_type))
    header = read_exactly(conn, 2)
    assert header[:1] == b"\x04", header
    assert read_exactly(conn, header[1]).startswith(b"\x05READY")


def accept_as_pub(server: socket.socket) -> socket.socket:
    """The next connection to ``server`` (a listening TCP socket), after a handshake as the
    server side of a PUB socket."""
    conn, _ = server.accept()
    conn.settimeout(10)
    handshake(conn, b"PUB", as_server=True)
    return conn


def connect_as_dealer(port: int) -> socket.socket:
    """A connection to 127.0.0.1:``port`` after a handshake as the client side of a DEALER."""
    conn = socket.create_connection(("127.0.0.1", port), timeout=10)
    handshake(conn, b"DEALER", as_server=False)
    return conn


def declare_a_gigabyte(conn: socket.socket) -> float:
    """Send the header of a frame of 1 GiB, then read (and drop) what comes until the peer
    closes the connection; return the seconds until it did."""
    conn.sendall(b"\x02" + struct.pack(">Q", GIGABYTE))
    tick = time.monotonic()
    with contextlib.suppress(ConnectionResetError):  # closed, by FIN or RST
        while conn.recv(4096):
            pass
    return time.monotonic() - tick


def frame(body: bytes, more: bool = False) -> bytes:
    """One ZMTP frame carrying ``body`` (short or long form), with MORE set if asked."""
    if len(body) < 256:
        return bytes([int(more), len(body)]) + body
    return bytes([0x02 | int(more)]) + struct.pack(">Q", len(body)) + body


def connect_raw(port: int, mechanism: bytes = b"NULL") -> socket.socket:
    """A connection to 127.0.0.1:``port`` that has sent its greeting only (and read the
    other side's): a CURVE peer stops here, before its HELLO."""
    conn = socket.create_connection(("127.0.0.1", port), timeout=10)
    conn.sendall(greeting(False, mechanism))
    assert read_exactly(conn, 64)[:1] == b"\xff"
    return conn


def stream(conn: socket.socket, data: bytes, total: int, seconds: float) -> int:
    """Send ``data`` over and over until ``total`` bytes or ``seconds`` have gone, or the peer
    closed the connection; the bytes sent."""
    sent, deadline = 0, time.monotonic() + seconds
    conn.settimeout(0.5)
    while sent < total and time.monotonic() < deadline:
        try:
            sent += conn.send(data)
        except TimeoutError:
            continue
        except OSError:  # reset or closed by the peer
            break
    return sent
