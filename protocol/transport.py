"""ZeroMQ transport: frame packets over PUB/SUB, control over ROUTER/DEALER, optional CURVE.

The sender binds both sockets and receivers connect, so any number of receivers can join
and leave. Packets go out on the PUB socket; a receiver's SUB socket keeps at most
``PACKET_HWM`` unread packets (about 3 s at 30 Hz) and the PUB side drops rather than
blocks when a slow receiver's queue is full: for live video a stale frame is worth nothing.
Control requests (the Hello, model chunks) go to the sender's ROUTER socket, one reply per
request; a request may come through relays (``protocol.relay``), each adding one routing
identity to its envelope, and the reply goes back the same way. ``PeerCounter`` counts the
peers connected to a bound socket (the sender's receiver count).

The control endpoint is the packet endpoint's port plus one (``control_endpoint``), so one
address names a sender.

Bounds before authentication (docs/DESIGN.md, the threat model). A peer is anyone who can
open a TCP connection; before its CURVE handshake is done it can still send a greeting and
frames, and without CURVE it can send anything. So every socket that reads from the network:

- refuses a frame larger than its protocol allows, at the frame's header and before
  allocating it (libzmq's ``MAXMSGSIZE``, a limit per frame, handshake commands included):
  ``MAX_PACKET_FRAME`` bytes on the packet sockets (a packet is 43 bytes; the sender's packet
  socket reads only subscriptions), ``MAX_REQUEST_FRAME`` on the sender's control socket (a
  request is under 200 bytes), ``MAX_CONTROL_FRAME`` on the sockets that read replies (a
  reply is at most ``protocol.control.MAX_MESSAGE_BYTES``); all leave room for CURVE's 33
  bytes of per-message overhead and its handshake commands (the largest, INITIATE, is about
  300 bytes). A peer that sends a larger frame, or only declares one in a frame header, is
  disconnected at that header. libzmq takes the oversized frame for a protocol error, after
  which the socket that *connected* does not connect to that address again (libzmq issue
  4196): a bound socket (the sender's) just loses that peer, which is free to connect again;
  a receiver's control socket is opened anew after the timeout
  (``receiver.acquire.ControlChannel``); a receiver's packet socket stays silent until it is
  opened anew;
- holds at most ``CONTROL_HWM`` messages per peer each way on the sender's control socket,
  and the model chunks among its replies go out zero-copy (``ControlServer.reply``), so a
  peer that asks for chunks and never reads holds replies that share the model's bytes (a few
  hundred bytes of bookkeeping each) rather than a copy of 256 KiB each.

What libzmq cannot bound, only authentication can: the number of frames of one message (a
message is delivered whole, and until its last frame its frames pile up unseen), and the
subscriptions a PUB or XPUB socket keeps (a trie of every distinct topic each peer sent, up
to its frame limit each: libzmq 4.3 keeps that trie even with ``XPUB_MANUAL``). Before its
CURVE handshake is done a peer can send neither, so a socket without CURVE is bound only to
loopback unless the user says otherwise (``check_plaintext``; ``unencrypted_warning`` is the
loud warning then).

With CURVE (``protocol.keys``) every socket is encrypted; the sender's authenticator (pyzmq's
own ``ThreadAuthenticator``) admits only clients whose public keys are in its authorised
folder, and a client with an unknown key, or one that expects another server key, never
completes the handshake and so receives nothing.

Contexts: each bound socket runs in a ``zmq.Context`` of its own, made with it and ended when it
closes; connected sockets share the process's context. libzmq closes a socket later, on its
reaper thread, and ending the context waits for that, so a closed server has released its port
(a sender started again on the same address binds at once) and, under CURVE, its authenticator's
fixed address ``inproc://zeromq.zap.01`` (libzmq allows one authenticator per context).

Bytes on the wire per packet (ZMTP 3): a 2-byte frame header; under CURVE each message is a
MESSAGE command (2-byte header, 8-byte name, 8-byte nonce, 16-byte MAC, 1 flags byte), so
35 bytes in all. ``WIRE_OVERHEAD`` holds these, and the tests measure them on a socket.
"""

from __future__ import annotations

import os
import random
import re
import socket
import threading
import time
from pathlib import Path

import zmq
import zmq.auth.thread
import zmq.utils.monitor

from facewire.protocol.control import MAX_MESSAGE_BYTES, Message, decode_message, encode_message
from facewire.protocol.errors import FacewireError
from facewire.protocol.keys import CurveClient, CurveServer
from facewire.protocol.loopback import is_loopback

PACKET_HWM = 100
CONTROL_HWM = 1000
MAX_PACKET_FRAME = 1024
MAX_REQUEST_FRAME = 1024
MAX_CONTROL_FRAME = MAX_MESSAGE_BYTES + 64
MAX_HOPS = 8
WIRE_OVERHEAD = {"plain": 2, "curve": 35}
_ENDPOINT = re.compile(r"tcp://(?P<host>[^:]+|\[[^\]]+\]):(?P<port>\d+)")


class TransportError(FacewireError, RuntimeError):
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


def endpoint_is_loopback(endpoint: str) -> bool:
    """True when a bind address stays on this host: a loopback host (``protocol.loopback``) or
    the interface ``lo``; anything else (``*``, ``0.0.0.0``, an address, a host or interface
    name) can be reached from the network."""
    match = re.fullmatch(r"tcp://(\[?)(?P<host>[^\]]*)\]?:\S+", endpoint)
    host = match["host"] if match else endpoint
    return host == "lo" or is_loopback(host)  # lo: the loopback interface, as ZeroMQ allows


def unencrypted_warning(bind: str, curve_dir: str | os.PathLike[str] | None) -> str | None:
    """The warning to show when ``bind`` reaches beyond this host without CURVE, else None."""
    if curve_dir is not None or endpoint_is_loopback(bind):
        return None
    return (f"WARNING: {bind} is reachable from the network and unencrypted: anyone who "
            f"can reach it reads the face stream and the model, and can make this process "
            f"allocate memory without bound (one ZeroMQ message of endless frames); use "
            f"--curve-dir DIR (facewire keys generate DIR)")


def check_plaintext(bind: str, curve_dir: str | os.PathLike[str] | None, insecure: bool
                    ) -> None:
    """Refuse to listen without CURVE beyond loopback unless ``insecure`` (module docstring).

    Raises:
        TransportError: ``bind`` reaches the network, without keys and without ``insecure``.
    """
    if not insecure and unencrypted_warning(bind, curve_dir) is not None:
        raise TransportError(f"{bind}: refusing to listen beyond loopback without encryption "
                             f"(any peer could make this process grow without bound); use "
                             f"--curve-dir DIR, or --insecure to accept that")


def free_loopback_endpoint() -> str:
    """``tcp://127.0.0.1:P`` with ports P (packets) and P + 1 (control) both free now.

    The ports lie below the kernel's ephemeral range: a client that connects before the server
    has bound retries every 100 ms from an ephemeral port, and on loopback one of those tries
    can connect to itself (TCP simultaneous open) when the target port is in that range,
    taking the port the server is about to bind.

    Raises:
        TransportError: no two adjacent free ports were found in 200 tries.
    """
    ranges = Path("/proc/sys/net/ipv4/ip_local_port_range")
    low = int(ranges.read_text().split()[0]) if ranges.is_file() else 32768
    for _ in range(200):
        port = random.randrange(10_000, low - 1)
        try:
            with socket.socket() as first, socket.socket() as second:
                first.bind(("127.0.0.1", port))
                second.bind(("127.0.0.1", port + 1))
        except OSError:
            continue
        return f"tcp://127.0.0.1:{port}"
    raise TransportError("no two adjacent free ports on 127.0.0.1")


class _Socket:
    """One ZeroMQ socket with our options, CURVE set up, and clean closing."""

    def __init__(self, kind: int, hwm: int, max_frame: int = -1, bound: bool = False) -> None:
        self._bound = bound
        self.context = zmq.Context() if bound else zmq.Context.instance()
        self.socket = self.context.socket(kind)
        self.socket.linger = 0
        self.socket.sndhwm = hwm
        self.socket.rcvhwm = hwm
        self.socket.maxmsgsize = max_frame  # -1: no limit (a socket that only sends)
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
        return self.socket.getsockopt_string(zmq.LAST_ENDPOINT)

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
        if self._bound and not self.context.closed:
            self.context.destroy(linger=0)  # waits until libzmq has closed the socket

    def __enter__(self):  # noqa: ANN204 (returns the subclass)
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class PacketPublisher(_Socket):
    """The sender's packet socket (PUB, bound). Its ``send`` may be called from several
    threads (the face's frame loop and the voice's thread): a lock serialises them, as a
    ZeroMQ socket must only be used by one thread at a time."""

    def __init__(self, endpoint: str, curve: CurveServer | None = None) -> None:
        super().__init__(zmq.PUB, PACKET_HWM, MAX_PACKET_FRAME, bound=True)
        self.endpoint = self._serve(endpoint, curve)
        self._lock = threading.Lock()

    def send(self, packet: bytes) -> None:
        """Publish one packet; never blocks (a full receiver queue drops it)."""
        with self._lock:
            try:
                self.socket.send(packet, zmq.NOBLOCK)
            except zmq.Again:
                pass


class PacketSubscriber(_Socket):
    """A receiver's packet socket (SUB, connected, subscribed to everything)."""

    def __init__(self, endpoint: str, curve: CurveClient | None = None) -> None:
        super().__init__(zmq.SUB, PACKET_HWM, MAX_PACKET_FRAME)
        self.socket.subscribe(b"")
        self._connect(endpoint, curve)

    def recv(self, timeout_ms: int) -> bytes | None:
        """The next packet, or None when none arrives within the timeout."""
        if self.socket.poll(timeout_ms, zmq.POLLIN):
            return self.socket.recv(zmq.NOBLOCK)
        return None


class ControlServer(_Socket):
    """The sender's control socket (ROUTER, bound): requests in, one reply each."""

    def __init__(self, endpoint: str, curve: CurveServer | None = None) -> None:
        super().__init__(zmq.ROUTER, CONTROL_HWM, MAX_REQUEST_FRAME, bound=True)
        self.endpoint = self._serve(endpoint, curve)

    def recv(self, timeout_ms: int) -> tuple[tuple[bytes, ...], bytes] | None:
        """(peer envelope, raw request), or None on timeout. Malformed framing is dropped.

        A request arrives as ``[identity, ..., b"", request]``: one identity from a client
        connected directly, one more per relay (``protocol.relay``) it passed through, at
        most ``MAX_HOPS``. ``reply`` sends the answer back along the same envelope.
        """
        if not self.socket.poll(timeout_ms, zmq.POLLIN):
            return None
        parts = self.socket.recv_multipart(zmq.NOBLOCK)
        if b"" not in parts[1:]:
            return None
        hops = parts.index(b"", 1)
        if hops > MAX_HOPS or len(parts) != hops + 2:
            return None
        return tuple(parts[:hops]), parts[-1]

    def reply(self, peer: tuple[bytes, ...], message: Message | bytes) -> None:
        """Send a reply (or its bytes, ``encode_message``'s) along ``peer``'s envelope, without
        copying them: a reply held for a peer that does not read shares its bytes. Dropped
        when the peer already has ``CONTROL_HWM`` replies waiting, or has gone."""
        data = message if isinstance(message, bytes) else encode_message(message)
        try:
            self.socket.send_multipart([*peer, b"", data], zmq.NOBLOCK, copy=False)
        except zmq.Again:
            pass


class PeerCounter:
    """How many peers are connected to a bound socket, from libzmq's socket monitor.

    A peer counts from the moment its TCP connection is accepted until it disconnects
    (``EVENT_ACCEPTED`` minus ``EVENT_DISCONNECTED``, matched by file descriptor). This counts
    connections, not people: a relay counts as one peer however many receivers it serves,
    and a peer still in its handshake counts too (under CURVE a refused client is counted
    for the moment of its attempt; libzmq's handshake events carry no descriptor to match).
    Close it before the socket it watches.
    """

    def __init__(self, socket: _Socket) -> None:
        self._socket = socket.socket
        self._monitor = self._socket.get_monitor_socket(
            zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)
        self._peers: set[int] = set()
        self.most = 0  # the most peers connected at once, up to the last ``count``

    def count(self) -> int:
        """Peers connected now (reads the monitor's pending events; never blocks)."""
        while self._monitor.poll(0, zmq.POLLIN):
            event = zmq.utils.monitor.recv_monitor_message(self._monitor, zmq.NOBLOCK)
            if event["event"] == zmq.EVENT_ACCEPTED:
                self._peers.add(event["value"])
                self.most = max(self.most, len(self._peers))
            elif event["event"] == zmq.EVENT_DISCONNECTED:
                self._peers.discard(event["value"])
        return len(self._peers)

    def close(self) -> None:
        if not self._monitor.closed:
            self._socket.disable_monitor()
            self._monitor.close(linger=0)

    def __enter__(self) -> PeerCounter:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class ControlClient(_Socket):
    """A receiver's control socket (DEALER, connected)."""

    def __init__(self, endpoint: str, curve: CurveClient | None = None) -> None:
        super().__init__(zmq.DEALER, CONTROL_HWM, MAX_CONTROL_FRAME)
        self._connect(endpoint, curve)

    def request(self, message: Message, timeout_ms: int) -> Message | None:
        """Send a request and wait for its reply; None on timeout.

        The timeout covers the send too (a full queue). A DEALER with no peer yet queues the
        request and delivers it when a server appears, so a reply can come after its request
        timed out: a caller that asks again after a timeout must use a new socket, or it may
        take that late reply for the answer to its next request
        (``receiver.acquire.ControlChannel`` does).

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
