"""The relay (``facewire relay --in tcp://SENDER:P --out tcp://*:Q``): packets and control.

Two loops, each on its own thread:

- packets (``_packets``): an XSUB socket connected to the sender's packet endpoint ``inp``,
  subscribed to everything once, and an XPUB socket bound at ``out`` with manual
  subscriptions (``XPUB_MANUAL``, ``_admit``: a receiver's subscription to everything is
  taken, any other dropped), so what receivers subscribe to never travels upstream: the
  sender sees the relay's one subscription. (libzmq still keeps each peer's subscriptions
  here, ``protocol.transport``.) Every packet from the sender is fanned out to every receiver (one
  stream upstream however many receivers there are). Several senders can be relayed by
  several relays into one hub the same way.
- control (``zmq.proxy_steerable``): a ROUTER socket bound at ``control_endpoint(out)``
  (port + 1), a DEALER socket
  connected to ``control_endpoint(inp)``. A receiver's request gains the ROUTER's routing
  identity on the way in, the sender's ``ControlServer`` replies along that envelope, and
  the ROUTER returns the reply to the receiver: receivers behind a relay fetch the Hello
  and the model as if they were connected directly.

Queues are bounded like the sender's (``protocol.transport``): the XPUB drops packets for a
receiver whose queue is full rather than stall the others.

Keys: ``curve_in`` is a client key folder (the relay's pair, and the sender's public key in
``authorized/``: ``protocol.keys.client_keys``) for the upstream link; ``curve_out`` a server
key folder (the relay's pair, and the receivers it admits in ``authorized/``) for the
downstream side. The relay decrypts and re-encrypts, so it must be trusted with the stream.

Every socket has the transport's bounds (``protocol.transport``): frames over
``MAX_PACKET_FRAME`` on the packet sockets, over ``MAX_REQUEST_FRAME`` on the ROUTER (it reads
requests) and over ``MAX_CONTROL_FRAME`` on the DEALER (it reads replies) are refused at their
header, and the ROUTER holds at most ``REPLY_HWM`` messages per receiver each way, so a
receiver that never reads holds at most that many replies here (each a copy of what the
sender sent; a receiver asks one at a time). Without ``curve_out``, ``out``
must be a loopback address unless ``insecure`` (``protocol.transport.check_plaintext``).

Stopping (``stop`` set, or Ctrl-C): each loop is asked for its statistics and then to
terminate over its inproc control socket (``STATISTICS``, ``TERMINATE``), the threads are
joined and the sockets closed.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from contextlib import ExitStack
from typing import Any

import zmq
import zmq.auth.thread

from facewire.protocol.keys import CurveClient, CurveServer, client_keys, server_keys
from facewire.protocol.transport import (
    CONTROL_HWM,
    MAX_CONTROL_FRAME,
    MAX_PACKET_FRAME,
    MAX_REQUEST_FRAME,
    PACKET_HWM,
    TransportError,
    check_plaintext,
    control_endpoint,
)

WAIT_S = 0.1
STATISTICS_TIMEOUT_MS = 2000
_COUNTER = struct.Struct("=Q")  # libzmq sends its counters as native uint64
REPLY_HWM = 8  # replies held per receiver: copies, 256 KiB each at most
SUBSCRIBE_ALL = b"\x01"  # a subscription message (ZMTP 3.0) to every topic


class _Proxy:
    """``loop(frontend, backend, None, steered)`` on a thread (``zmq.proxy_steerable`` or
    ``_packets``), steered over inproc PAIRs."""

    def __init__(self, context: zmq.Context, name: str, frontend: zmq.Socket,
                 backend: zmq.Socket, loop: Any = zmq.proxy_steerable) -> None:
        address = f"inproc://facewire-relay-{name}-{id(self)}"
        self._steer = context.socket(zmq.PAIR)
        self._steer.bind(address)
        self._steered = context.socket(zmq.PAIR)
        self._steered.connect(address)
        self._thread = threading.Thread(target=loop, name=f"relay-{name}",
                                        args=(frontend, backend, None, self._steered),
                                        daemon=True)
        self._thread.start()

    def stop(self) -> list[int]:
        """Terminate the proxy; its 8 counters: frontend messages in, bytes in, messages out,
        bytes out, then the same for the backend (zeros if it did not answer)."""
        self._steer.send(b"STATISTICS")
        stats = [0] * 8
        if self._steer.poll(STATISTICS_TIMEOUT_MS, zmq.POLLIN):
            stats = [_COUNTER.unpack(part)[0] for part in self._steer.recv_multipart()]
        self._steer.send(b"TERMINATE")
        self._thread.join()
        self._steer.close(linger=0)
        self._steered.close(linger=0)
        return stats


def _admit(xpub: zmq.Socket) -> int:
    """Take the subscriptions waiting on the XPUB (never blocks): a receiver that subscribes
    to every topic (``SUBSCRIBE_ALL``) gets the packets from now on; any other subscription
    message is dropped. Returns the messages taken."""
    taken = 0
    while True:
        try:
            message = xpub.recv(zmq.NOBLOCK)
        except zmq.Again:
            return taken
        taken += 1
        if message == SUBSCRIBE_ALL:
            xpub.subscribe(b"")  # for the receiver that sent it


def _packets(xsub: zmq.Socket, xpub: zmq.Socket, _: None, steered: zmq.Socket) -> None:
    """The packet loop: packets from ``xsub`` out on ``xpub``, subscriptions at ``xpub``
    admitted (``_admit``), until ``TERMINATE`` on ``steered``; ``STATISTICS``
    answers with ``_Proxy.stop``'s 8 counters (packets in the frontend's, subscription
    messages in the backend's)."""
    counts = [0] * 8
    xsub.send(SUBSCRIBE_ALL)
    poller = zmq.Poller()
    for socket in (xsub, xpub, steered):
        poller.register(socket, zmq.POLLIN)
    while True:
        ready = dict(poller.poll())
        if xpub in ready:
            counts[4] += _admit(xpub)
        if xsub in ready:
            while True:
                try:
                    packet = xsub.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                counts[0] += 1
                try:
                    xpub.send(packet, zmq.NOBLOCK)
                except zmq.Again:
                    pass
        if steered in ready:
            command = steered.recv()
            if command == b"TERMINATE":
                return
            if command == b"STATISTICS":
                steered.send_multipart([_COUNTER.pack(n) for n in counts])


def _socket(context: zmq.Context, kind: int, hwm: int, max_frame: int) -> zmq.Socket:
    socket = context.socket(kind)
    socket.maxmsgsize = max_frame
    socket.linger = 0
    socket.sndhwm = hwm
    socket.rcvhwm = hwm
    return socket


def _bind(socket: zmq.Socket, endpoint: str, curve: CurveServer | None) -> None:
    if curve is not None:
        socket.curve_secretkey = curve.secret
        socket.curve_publickey = curve.public
        socket.curve_server = True
    try:
        socket.bind(endpoint)
    except zmq.ZMQError as exc:
        raise TransportError(f"cannot bind {endpoint}: {exc}") from None


def _connect(socket: zmq.Socket, endpoint: str, curve: CurveClient | None) -> None:
    if curve is not None:
        socket.curve_secretkey = curve.secret
        socket.curve_publickey = curve.public
        socket.curve_serverkey = curve.server_public
    try:
        socket.connect(endpoint)
    except zmq.ZMQError as exc:
        raise TransportError(f"cannot connect to {endpoint}: {exc}") from None


def relay(inp: str, out: str, stop: threading.Event | None = None,
          curve_in: str | os.PathLike[str] | None = None,
          curve_out: str | os.PathLike[str] | None = None, insecure: bool = False
          ) -> dict[str, Any]:
    """Relay one sender's packets and control requests until ``stop`` is set or Ctrl-C.

    Args:
        inp: the sender's packet endpoint ``tcp://HOST:PORT`` (control on PORT + 1).
        out: where receivers connect, ``tcp://HOST:PORT`` (control on PORT + 1).
        stop: set it (from another thread) to stop.
        curve_in: client key folder for the link to the sender, or None (plain).
        curve_out: server key folder for the receivers' side, or None (plain).
        insecure: listen at ``out`` without ``curve_out`` beyond loopback all the same.

    Returns:
        the loops' counters: ``packets`` (from the sender), ``subscriptions`` (subscribe
        and unsubscribe messages from receivers), ``request_parts`` and ``reply_parts``
        (control message parts from receivers and from the sender: a request or reply is 3,
        routing identity, empty delimiter and body), ``reply_bytes`` (their size: the Hellos
        and model chunks that went through); and ``seconds``, ``stopped`` (``stop`` or
        ``interrupt``).

    Raises:
        TransportError: a bad endpoint, a port in use, or ``out`` beyond loopback without
            ``curve_out`` or ``insecure``.
        KeyFileError: a missing or malformed key folder.
    """
    control_in, control_out = control_endpoint(inp), control_endpoint(out)
    check_plaintext(out, curve_out, insecure)
    client = client_keys(curve_in) if curve_in is not None else None
    server = server_keys(curve_out) if curve_out is not None else None
    stop = stop if stop is not None else threading.Event()
    start = time.monotonic()
    context = zmq.Context()
    with ExitStack() as stack:
        stack.callback(context.term)
        if server is not None:
            auth = zmq.auth.thread.ThreadAuthenticator(context)
            auth.start()
            stack.callback(auth.stop)
            auth.configure_curve(domain="*", location=str(server.authorized))
        sockets = [_socket(context, kind, hwm, limit) for kind, hwm, limit in (
            (zmq.XSUB, PACKET_HWM, MAX_PACKET_FRAME), (zmq.XPUB, PACKET_HWM, MAX_PACKET_FRAME),
            (zmq.ROUTER, REPLY_HWM, MAX_REQUEST_FRAME),
            (zmq.DEALER, CONTROL_HWM, MAX_CONTROL_FRAME))]
        for socket in sockets:
            stack.callback(socket.close, linger=0)
        xsub, xpub, router, dealer = sockets
        xpub.setsockopt(zmq.XPUB_MANUAL, 1)
        _bind(xpub, out, server)
        _bind(router, control_out, server)
        _connect(xsub, inp, client)
        _connect(dealer, control_in, client)
        packets = _Proxy(context, "packets", xsub, xpub, _packets)
        control = _Proxy(context, "control", router, dealer)
        stopped = "stop"
        try:
            while not stop.wait(WAIT_S):
                pass
        except KeyboardInterrupt:
            stopped = "interrupt"
        packet_stats, control_stats = packets.stop(), control.stop()
    return {"packets": packet_stats[0], "subscriptions": packet_stats[4],
            "request_parts": control_stats[0], "reply_parts": control_stats[4],
            "reply_bytes": control_stats[5],
            "seconds": round(time.monotonic() - start, 3), "stopped": stopped}
