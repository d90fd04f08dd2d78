"""ZeroMQ transport: frame packets over PUB/SUB, control over ROUTER/DEALER, optional CURVE.

The sender binds both sockets and receivers connect, so any number of receivers can join
and leave. Packets go out on the PUB socket; a receiver's SUB socket keeps at most
``PACKET_HWM`` unread packets (about 3 s at 30 Hz) and the PUB side drops rather than
blocks when a slow receiver's queue is full: for live video a stale frame is worth nothing.
Control requests (the Hello, model chunks) go to the sender's ROUTER socket, one reply per
request.

The control endpoint is the packet endpoint's port plus one (``control_endpoint``), so one
address names a sender.

With CURVE (``protocol.keys``) every socket is encrypted; the sender's authenticator (pyzmq's
own ``ThreadAuthenticator``) admits only clients whose public keys are in its authorised
folder, and a client with an unknown key, or one that expects another server key, never
completes the handshake and so receives nothing.

Bytes on the wire per packet (ZMTP 3): a 2-byte frame header; under CURVE each message is a
MESSAGE command (2-byte header, 8-byte name, 8-byte nonce, 16-byte MAC, 1 flags byte), so
35 bytes in all. ``WIRE_OVERHEAD`` holds these, and the tests measure them on a socket.
"""

from __future__ import annotations

import re
import time

import zmq
import zmq.auth.thread

from protocol.control import Message, decode_message, encode_message
from protocol.keys import CurveClient, CurveServer

PACKET_HWM = 100
CONTROL_HWM = 1000
WIRE_OVERHEAD = {"plain": 2, "curve": 35}
_ENDPOINT = re.compile(r"tcp://(?P<host>[^:]+|\[[^\]]+\]):(?P<port>\d+)")


class TransportError(RuntimeError):
    """A socket could not be set up: bad address, port in use, keys rejected."""


def control_endpoint(endpoint: str) -> str:
    """The control address that goes with a packet address: same host, port + 1."""
    m = _ENDPOINT.fullmatch(endpoint)
    if m is None:
        raise TransportError(f"{endpoint!r}: expected tcp://HOST:PORT")
    port = int(m["port"])
    if not 0 < port < 65535:
        raise TransportError(f"{endpoint!r}: port must be in 1..65534")
    return f"tcp://{m['host']}:{port + 1}"


class _Socket:
    """One ZeroMQ socket with our options, CURVE set up, and clean closing."""

    def __init__(self, kind: int, context: zmq.Context | None, hwm: int) -> None:
        self.context = context or zmq.Context.instance()
        self.socket = self.context.socket(kind)
        self.socket.linger = 0
        self.socket.sndhwm = hwm
        self.socket.rcvhwm = hwm
        self._auth: zmq.auth.thread.ThreadAuthenticator | None = None

    def _serve(self, endpoint: str, curve: CurveServer | None) -> str:
        if curve is not None:
            self._auth = zmq.auth.thread.ThreadAuthenticator(self.context)
            self._auth.start()
            self._auth.configure_curve(domain="*", location=str(curve.authorized))
            self.socket.curve_secretkey = curve.secret
            self.socket.curve_publickey = curve.public
            self.socket.curve_server = True
        try:
            self.socket.bind(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise TransportError(f"cannot bind {endpoint}: {exc}") from None
        return self.socket.last_endpoint.decode()

    def _connect(self, endpoint: str, curve: CurveClient | None) -> None:
        if curve is not None:
            self.socket.curve_secretkey = curve.secret
            self.socket.curve_publickey = curve.public
            self.socket.curve_serverkey = curve.server_public
        try:
            self.socket.connect(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise TransportError(f"cannot connect to {endpoint}: {exc}") from None

    def close(self) -> None:
        self.socket.close(linger=0)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None

    def __enter__(self):  # noqa: ANN204 (returns the subclass)
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class PacketPublisher(_Socket):
    """The sender's packet socket (PUB, bound)."""

    def __init__(self, endpoint: str, curve: CurveServer | None = None,
                 context: zmq.Context | None = None) -> None:
        super().__init__(zmq.PUB, context, PACKET_HWM)
        self.endpoint = self._serve(endpoint, curve)

    def send(self, packet: bytes) -> None:
        """Publish one packet; never blocks (a full receiver queue drops it)."""
        try:
            self.socket.send(packet, zmq.NOBLOCK)
        except zmq.Again:
            pass


class PacketSubscriber(_Socket):
    """A receiver's packet socket (SUB, connected, subscribed to everything)."""

    def __init__(self, endpoint: str, curve: CurveClient | None = None,
                 context: zmq.Context | None = None) -> None:
        super().__init__(zmq.SUB, context, PACKET_HWM)
        self.socket.subscribe(b"")
        self._connect(endpoint, curve)

    def recv(self, timeout_ms: int) -> bytes | None:
        """The next packet, or None when none arrives within the timeout."""
        if self.socket.poll(timeout_ms, zmq.POLLIN):
            return self.socket.recv(zmq.NOBLOCK)
        return None


class ControlServer(_Socket):
    """The sender's control socket (ROUTER, bound): requests in, one reply each."""

    def __init__(self, endpoint: str, curve: CurveServer | None = None,
                 context: zmq.Context | None = None) -> None:
        super().__init__(zmq.ROUTER, context, CONTROL_HWM)
        self.endpoint = self._serve(endpoint, curve)

    def recv(self, timeout_ms: int) -> tuple[bytes, bytes] | None:
        """(peer identity, raw request), or None on timeout. Malformed framing is dropped."""
        if not self.socket.poll(timeout_ms, zmq.POLLIN):
            return None
        parts = self.socket.recv_multipart(zmq.NOBLOCK)
        if len(parts) != 3 or parts[1] != b"":
            return None
        return parts[0], parts[2]

    def reply(self, peer: bytes, message: Message) -> None:
        try:
            self.socket.send_multipart([peer, b"", encode_message(message)], zmq.NOBLOCK)
        except zmq.Again:
            pass


class ControlClient(_Socket):
    """A receiver's control socket (DEALER, connected)."""

    def __init__(self, endpoint: str, curve: CurveClient | None = None,
                 context: zmq.Context | None = None) -> None:
        super().__init__(zmq.DEALER, context, CONTROL_HWM)
        self._connect(endpoint, curve)

    def request(self, message: Message, timeout_ms: int) -> Message | None:
        """Send a request and wait for its reply; None on timeout.

        The timeout covers the send too: a DEALER with no connected peer (the server is down,
        or refused our CURVE handshake) cannot take the message and would block forever.

        Raises:
            ControlError: the reply is malformed.
        """
        deadline = time.monotonic() + timeout_ms / 1000
        if not self.socket.poll(timeout_ms, zmq.POLLOUT):
            return None
        try:
            self.socket.send_multipart([b"", encode_message(message)], zmq.NOBLOCK)
        except zmq.Again:
            return None
        left = max(0, round((deadline - time.monotonic()) * 1000))
        if not self.socket.poll(left, zmq.POLLIN):
            return None
        parts = self.socket.recv_multipart(zmq.NOBLOCK)
        return decode_message(parts[-1])
