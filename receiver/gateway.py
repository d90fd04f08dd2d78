"""The browser gateway: ``facewire web --connect tcp://SENDER:5555 [--http 127.0.0.1:8080]``.

The gateway subscribes to a sender (or a relay) as a receiver does and serves browsers, on
one HTTP port, the page (``receiver/web/``), the person model as the browser loads it
(``models.webmodel``) and, over a WebSocket, the packets themselves: every browser renders
for itself, so a viewer costs the gateway 45 bytes a frame.

Upstream (what a receiver does, with the receiver's own parts)
--------------------------------------------------------------
- Packets: a SUB socket read on its own thread (``receiver.packetreader.PacketReader``: at
  most ``QUEUE_PACKETS`` queued, the socket opened anew after ``REOPEN_S`` of silence).
- The Hello, the model and its updates, on the *upstream thread*: the Hello asked over the
  control channel (``receiver.acquire.ControlChannel``); the model by its sha256 from the
  model cache or fetched in chunks and verified (``receiver.acquire.ModelAcquirer``); the
  session's updates fetched, verified and applied in order on the fetcher's own thread
  (``receiver.updates.UpdateFetcher``), up to the newest serial the Hello or the last packet
  names. CURVE with ``curve_dir`` (``protocol.keys.client_keys``) on every socket.
- The sender's presence (``receiver.link.SenderLink``, as ``receive`` has it). With no sender
  the Hello is asked again and again (``link.HELLO_TIMEOUT_S`` each); once one answers the
  sender is *connected*. The Hello is asked again every ``link.RECHECK_EVERY_S``, at once at
  a sign of the link (packets resuming after a silence, a seq far from the last one's, a
  Hello without the clock), and when no packet has come for ``SILENT_S``; a sender that does
  not answer while no packet has come for ``SILENT_S`` is *lost*, and the gateway waits
  again. The packets that came after a sign of a restart are held (at most ``MAX_DOUBT``)
  until the Hello answers: with the same model they go out; with another they are dropped
  (``held``), since the pages do not have that model yet; with no answer they go out
  (nothing tells). A Hello with another model sha256 brings that model (cache or fetch) and
  announces it; one whose ``model_serial`` is below the versions fetched is a new session of
  the same model: its updates are fetched anew and the model announced again (the page
  starts again from version 0).
- The sender's clock (``receiver.clocksync``, on its own thread): the pages get it in
  ``clock`` messages (below), so that a page can say how late its face is.

Each packet is checked with ``protocol.packet.decode`` (size, version, CRC, reserved bits):
a corrupt one is dropped and counted by its reason (``corrupt``), never forwarded. A packet
that decodes is forwarded exactly as received, one binary WebSocket message, to every
viewer, once the gateway has the model the current Hello names (before that, ``held``). A
voice packet (``protocol.voice``, told by its first nibble) is checked by its own decoder and
forwarded the same way (``voice``), never held in doubt: the page plays it against the
Hello's clock.

Downstream (``websockets``' asyncio server on the calling thread's event loop)
-----------------------------------------------------------------------------
One port, ``--http HOST:PORT``. Every request (page, model, WebSocket) must name in its
``Host`` header a loopback host, or with ``allow_remote`` a loopback host, an IP address or
one of the names the user gave (``hosts``; ``protocol.loopback``: DNS rebinding), and carry
``?token=T`` (compared in constant time); 403 otherwise, 400 for two ``Host`` or ``Origin``
headers. A gateway always has a token: the user's (16 to 256 URL-safe characters), or
``secrets.token_urlsafe(TOKEN_BYTES)`` (256 random bits). A wrong token earns
its address a delay (``serverguard.FailureThrottle``); the token is never in the summary
(``shown_url``). Plain GETs are answered in ``process_request``:

- ``/`` (``index.html``) and ``/NAME.js|.css|.html|.vert|.frag``: the page's files (the
  last two the GLSL shaders it shares with ``receiver.render``), read once at start from the
  installed package (``importlib.resources``, ``facewire.receiver/web``);
- ``/model/S.glb``, ``/model/S.rig``: ``models.webmodel.model_glb`` and ``rig_bin`` of the
  model with sha256 S (immutable: cached by the browser for ever); the last
  ``MODELS_KEPT`` models are held;
- ``/model/S/K.upd``: ``models.webmodel.update_bin`` from version K - 1 to K of the
  session of model S (``no-store``: a new session of the same model has other updates
  under the same serials);
- anything else 404. Each body is made once per model or version, on the upstream
  thread; gzip (``Content-Encoding``) is made once too, and served to a client that accepts
  it when it is smaller.

``/stream`` is the WebSocket (its ``Origin``, when a browser sends one, must be the page's
own host, so that another site's page cannot open it). On connecting a page gets, before any
packet, text messages (JSON objects with ``"type"``): ``status`` (``"sender"``: ``waiting`` or
``connected``, and a ``"text"``), then, once there is a model, ``hello`` (the Hello's fields
under their names), ``model`` (``sha256``, ``glb`` and ``rig`` URLs, ``bytes``: their
total) and one ``update`` per version held (``serial``, ``url``, ``bytes``), in order; then it
joins the stream. The same messages go to every page when they change. These first messages
and the joining happen in one step of the event loop, so no packet can come between them.
Every ``STATUS_S``, once the sender's clock is estimated, a ``clock`` message: ``origin_s``
and ``rate_hz`` (the Hello's clock: slot ``n`` captured at ``origin_s + n / rate_hz``) on the
gateway's monotonic clock (the offset applied), ``voice_origin_s`` when the stream has a
voice (voice frame ``j`` captured at ``voice_origin_s + j * 20 ms``, the same clock), and
``now_s``, the gateway's clock when sent; a page aligns its own clock to the gateway's from
these (``receiver/web/stats.js``).

Bounds. A page need send nothing: a message over ``MAX_MESSAGE_BYTES`` closes its connection
(1009, by ``websockets``' ``max_size``), more than ``MAX_MESSAGES_PER_S`` in a second closes
it (1008, policy violation). Packets go out with ``websockets.broadcast``, which writes to
each connection's buffer without waiting: a page that does not read fills its kernel send
buffer (fixed at ``SEND_BUFFER_BYTES`` per connection, which Linux doubles), then the
gateway's; every ``SWEEP_S`` a page with more than ``MAX_BUFFER_BYTES`` unsent is cut off
(``dropped_slow``). So a page that stalls costs at most those buffers and never holds up the
others; at 1.35 kB/s it is dropped once its own receive buffer and these are full (a minute
or more), unless ``websockets``' keepalive ping (20 s, then 20 s for the answer) closed it
first.
Before the token is checked, a connection costs at most its request: ``websockets``' parser
with at most ``MAX_HEADERS`` headers of ``MAX_LINE_BYTES`` each (set in ``websockets.http11``
for the process), ``OPEN_TIMEOUT_S`` for the whole handshake. Connections are admitted by
``serverguard.Admission``: at most ``MAX_PENDING`` in their request (the oldest evicted after
``EVICT_AFTER_S`` when more come), at most ``MAX_VIEWERS`` WebSockets (503 beyond), both caps
below the open-files limit (``serverguard.open_file_caps``); errors the event loop reports
(``accept`` failing with EMFILE...) are one line per ``ERROR_EVERY_S``
(``serverguard.QuietErrors``), never a traceback.

Threads: the event loop (the caller's thread: HTTP, WebSockets, forwarding, the status), the
packet reader, the upstream thread (Hello, model, the web bodies) and the update fetcher.
The reader wakes the loop for each packet (``call_soon_threadsafe``); the upstream thread
hands its results to the loop the same way; only the loop touches the viewers.

Stopping: ``stop`` set (Ctrl-C and SIGTERM in the CLI): the server closes every WebSocket
(1001, going away), the upstream thread and the reader end, the summary is returned.

Size: this module is some 900 lines, the docstring above about 125 of them; the server
(``Gateway``) and its upstream thread (``Upstream``) hand each other results at every step,
and the receiving parts they use already live apart (``receiver.packetreader``,
``receiver.acquire``, ``receiver.updates``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import email.utils
import gzip
import hmac
import ipaddress
import json
import logging
import os
import re
import secrets
import socket
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from http import HTTPStatus
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

import websockets.http11
from websockets.asyncio.server import ServerConnection, broadcast, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from facewire.models.modelfile import PersonModel
from facewire.models.webmodel import model_glb, rig_bin, update_bin
from facewire.protocol.control import Hello
from facewire.protocol.errors import FacewireError
from facewire.protocol.keys import CurveClient, client_keys
from facewire.protocol.loopback import host_header_is_loopback, is_loopback
from facewire.protocol.packet import PacketError, decode
from facewire.protocol.transport import PacketSubscriber, control_endpoint
from facewire.protocol.voice import VoiceError, is_voice
from facewire.protocol.voice import decode as decode_voice
from facewire.receiver.acquire import ModelAcquirer
from facewire.receiver.clocksync import ClockSync
from facewire.receiver.link import HELLO_TIMEOUT_S, RECHECK_EVERY_S, Change, SenderLink
from facewire.receiver.modelcache import ModelCache
from facewire.receiver.packetreader import PacketReader
from facewire.receiver.serverguard import Admission, FailureThrottle, QuietErrors, open_file_caps
from facewire.receiver.updates import UpdateFetcher

DEFAULT_HTTP = "127.0.0.1:8080"
MAX_DOUBT = 256  # packets held while the Hello is asked again; beyond, dropped (held)
SILENT_S = 1.0
QUEUE_PACKETS = 4096
REOPEN_S = 8.0
MAX_MESSAGE_BYTES = 256
MAX_MESSAGES_PER_S = 5
SEND_BUFFER_BYTES = 32 * 1024
RECEIVE_BUFFER_BYTES = 16 * 1024
MAX_BUFFER_BYTES = 16 * 1024
MAX_VIEWERS = 4096
MAX_PENDING = 32  # connections in their request (before the token is known)
EVICT_AFTER_S = 0.25
OPEN_TIMEOUT_S = 5.0
MAX_HEADERS = 32
MAX_LINE_BYTES = 8192
ERROR_EVERY_S = 10.0
TOKEN_BYTES = 32
TOKEN_ENV = "FACEWIRE_TOKEN"
SWEEP_S = 0.25
STATUS_S = 0.5
MODELS_KEPT = 4
GZIP_SAVES = 1.0  # serve gzip when it is smaller than the raw bytes at all
_WAKE_S = 0.1
_FILE = re.compile(r"/(?P<name>[A-Za-z0-9_-]+\.(?:js|css|html|vert|frag))")
_MODEL = re.compile(r"/model/(?P<sha>[0-9a-f]{64})\.(?P<kind>glb|rig)")
_UPDATE = re.compile(r"/model/(?P<sha>[0-9a-f]{64})/(?P<serial>[1-9][0-9]{0,3})\.upd")
_HTTP = re.compile(r"(?P<host>\[[^\]]+\]|[^:\[\]]*):(?P<port>[0-9]{1,5})")
_TOKEN = re.compile(r"[A-Za-z0-9._~-]{16,256}")
_NAME = re.compile(r"(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".vert": "text/plain; charset=utf-8",
          ".frag": "text/plain; charset=utf-8"}  # the GLSL shaders: receiver/render.py
_QUIET = logging.getLogger("facewire.gateway.websockets")  # websockets' own log: not shown
_QUIET.addHandler(logging.NullHandler())
_QUIET.propagate = False
# websockets reads these two at each request it parses: the gateway's bounds, process-wide.
websockets.http11.MAX_NUM_HEADERS = MAX_HEADERS
websockets.http11.MAX_LINE_LENGTH = MAX_LINE_BYTES

Say = Callable[[str], None]
Status = Callable[[dict[str, Any]], None]


class GatewayError(FacewireError, ValueError):
    """The gateway cannot serve: a bad option, or an address refused or in use."""


@dataclasses.dataclass(frozen=True)
class Body:
    """One HTTP body made once: its bytes, gzip's (None when it saves too little), its
    content type and cache policy."""

    raw: bytes
    gz: bytes | None
    kind: str
    cache: str

    @staticmethod
    def make(raw: bytes, kind: str, cache: str) -> Body:
        packed = gzip.compress(raw, compresslevel=6, mtime=0)
        return Body(raw, packed if len(packed) <= GZIP_SAVES * len(raw) else None, kind,
                    cache)


def parse_http(address: str, allow_remote: bool) -> tuple[str, int]:
    """``--http HOST:PORT`` as (host, port); an empty host is 0.0.0.0 (every interface).

    Raises:
        GatewayError: not HOST:PORT, a port over 65535, or a host that is not loopback
            without ``allow_remote``.
    """
    m = _HTTP.fullmatch(address)
    if m is None or int(m["port"]) > 65535:
        raise GatewayError(f"--http {address!r}: expected HOST:PORT, e.g. {DEFAULT_HTTP}")
    host = m["host"].strip("[]") or "0.0.0.0"
    if not allow_remote and not is_loopback(host):
        raise GatewayError(
            f"--http {address}: refusing to serve beyond this host: the page, the model and "
            f"the face stream go out unencrypted (plain HTTP); pass --allow-remote to serve "
            f"on {host} (and --host NAME for each name the page is opened by)")
    return host, int(m["port"])


def remote_warning(host: str) -> str | None:
    """The warning for serving on ``host`` (None on loopback), as ``send`` warns."""
    if is_loopback(host):
        return None
    return (f"warning: {host} is reachable from the network and the page, the model, the "
            f"face stream and the token in its URL go out unencrypted (plain HTTP)")


def check_token(token: str, where: str = "--token") -> None:
    """A token must be 16 to 256 characters that need no escaping in a URL.

    Raises:
        GatewayError: naming ``where`` the token came from.
    """
    if not _TOKEN.fullmatch(token):
        raise GatewayError(f"{where}: expected 16 to 256 of the characters A-Z a-z 0-9 . _ ~ "
                           f"- (got {len(token)} characters); leave the token out to have one "
                           f"of {8 * TOKEN_BYTES} random bits made")


def new_token() -> str:
    """A token of ``TOKEN_BYTES`` random bytes, URL-safe base64."""
    return secrets.token_urlsafe(TOKEN_BYTES)


def read_token_file(path: str) -> str:
    """The token in the first line of ``path``; a file that does not exist is made (0600)
    with a new token.

    Raises:
        GatewayError: the file cannot be read or made, or its token is not a valid one.
    """
    token = new_token()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        try:
            with open(path, encoding="utf-8") as file:
                token = file.readline().strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise GatewayError(f"--token-file {path}: cannot read it: {exc}") from None
        check_token(token, f"--token-file {path}")
        return token
    except OSError as exc:
        raise GatewayError(f"--token-file {path}: cannot make it: {exc.strerror}") from None
    with os.fdopen(fd, "w", encoding="utf-8") as file:
        file.write(token + "\n")
    return token


def check_hosts(hosts: tuple[str, ...], allow_remote: bool) -> None:
    """``--host NAME``: DNS names, and only with ``allow_remote``.

    Raises:
        GatewayError: a name that is not a DNS name, or names without ``allow_remote``.
    """
    if hosts and not allow_remote:
        raise GatewayError("--host: only with --allow-remote (on loopback the page is opened "
                           "by a loopback name)")
    for name in hosts:
        if not _NAME.fullmatch(name):
            raise GatewayError(f"--host {name!r}: expected a DNS name such as "
                               f"watch.example.org")


def shown_url(url: str) -> str:
    """``url`` with its token cut to its first 4 characters (for terminals and logs)."""
    base, sep, token = url.partition("?token=")
    return base + (f"?token={token[:4]}..." if sep else "")


def serve_gateway(connect: str, http: str = DEFAULT_HTTP,
                  curve_dir: str | None = None, token: str | None = None,
                  allow_remote: bool = False, cache_dir: str | None = None,
                  stop: threading.Event | None = None, say: Say | None = None,
                  status: Status | None = None,
                  ready: Callable[[str], None] | None = None,
                  hosts: tuple[str, ...] = ()) -> dict[str, Any]:
    """Serve browsers the stream of the sender at ``connect`` until ``stop`` is set.

    Args:
        connect: the sender's (or a relay's) packet address ``tcp://HOST:PORT``.
        http: where to serve, ``HOST:PORT`` (port 0: any free one).
        curve_dir: a CURVE key folder (``protocol.keys.client_keys``).
        token: every request must carry ``?token=`` it; None: one is made (``new_token``).
        allow_remote: serve on a host that is not loopback, and accept a ``Host`` header
            that is an IP address or one of ``hosts``.
        cache_dir: the model cache folder (``receiver.modelcache.default_folder`` if None).
        stop: set it (from another thread or a signal handler) to stop.
        say: called with a line of text at each event (sender found or lost, model...).
        status: called every ``STATUS_S`` with the live counts (``Gateway.status``).
        ready: called once serving, with the page's URL (the token included).
        hosts: with ``allow_remote``, the names (DNS) the page may be opened by.

    Returns:
        The summary (``Gateway.summary``).

    Raises:
        GatewayError: a bad option, or the address cannot be served.
        ReceiveError / TransportError / KeyFileError / PacketReaderError: the sender's model
            is not a valid model file or keeps failing its sha256; a bad ``connect``; a bad
            key folder; the packet socket failed.
    """
    host, port = parse_http(http, allow_remote)
    check_hosts(hosts, allow_remote)
    if token is None:
        token = new_token()
    check_token(token)
    control_endpoint(connect)  # checks the address (TransportError)
    curve = client_keys(curve_dir) if curve_dir is not None else None
    access = Access(token, allow_remote, frozenset(name.lower() for name in hosts))
    gateway = Gateway(connect, curve, ModelCache(cache_dir), access,
                      stop or threading.Event(), say, status)
    return asyncio.run(gateway.run(host, port, ready))


@dataclasses.dataclass(frozen=True)
class Access:
    """Who is answered: the token every request carries, and the ``Host`` names allowed."""

    token: str
    allow_remote: bool
    hosts: frozenset[str]

    def host_allowed(self, header: str) -> bool:
        """A ``Host`` header names loopback, or with ``allow_remote`` an IP address or one of
        ``hosts`` (module docstring)."""
        if host_header_is_loopback(header):
            return True
        if not self.allow_remote:
            return False
        try:
            name = urlsplit(f"//{header}").hostname
        except ValueError:
            return False
        if name is None:
            return False
        try:
            ipaddress.ip_address(name)
            return True
        except ValueError:
            return name in self.hosts


class Gateway:
    """One ``serve_gateway`` call: the viewers and what they are sent (module docstring).

    Only the event loop's thread touches the viewers and the bodies; the other threads hand
    their results over with ``post``.
    """

    def __init__(self, connect: str, curve: CurveClient | None, cache: ModelCache,
                 access: Access, stop: threading.Event, say: Say | None,
                 status: Status | None) -> None:
        self.connect, self.curve, self.cache = connect, curve, cache
        self.access, self.stop = access, stop
        self.throttle = FailureThrottle()
        total, self.backlog = open_file_caps(MAX_VIEWERS + MAX_PENDING)
        pending = min(MAX_PENDING, max(1, total // 2))
        self.max_viewers = max(1, total - pending)
        self.admission = Admission(total, pending, EVICT_AFTER_S)
        self._say_to, self._status_to = say, status
        self._say_lock = threading.Lock()
        self.viewers: set[ServerConnection] = set()
        self.files = _page_files()
        self.models: OrderedDict[str, dict[str, Body]] = OrderedDict()
        self.updates: dict[tuple[str, int], Body] = {}
        self.sender = "waiting"
        self.status_json = _status_json("waiting", "waiting for the sender")
        self.hello_json: str | None = None
        self.model_json: str | None = None
        self.update_json: list[str] = []
        self.sha256: str | None = None
        self.serial = 0  # the newest model version announced
        self.latest_serial = 0  # the serial of the last packet that decoded
        self.counts: Counter[str] = Counter()
        self.viewers_max = 0
        self.url = ""
        self.error: BaseException | None = None
        self._doubt: list[bytes] | None = None  # packets held until a Hello says whose
        self._doubt_since = 0.0
        self._scheduled = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self.reader: PacketReader | None = None
        self.upstream: Upstream | None = None
        self.started = time.monotonic()

    # -- the event loop ----------------------------------------------------------------------

    async def run(self, host: str, port: int, ready: Callable[[str], None] | None
                  ) -> dict[str, Any]:
        self._loop = asyncio.get_running_loop()
        self._loop.set_exception_handler(QuietErrors(self.say, "connections", ERROR_EVERY_S))
        try:
            server = await serve(self._viewer, host, port, process_request=self._http,
                                 compression=None, max_size=MAX_MESSAGE_BYTES, max_queue=4,
                                 logger=_QUIET, open_timeout=OPEN_TIMEOUT_S,
                                 backlog=self.backlog,
                                 create_connection=_guarded(self.admission))
        except OSError as exc:
            raise GatewayError(f"--http {host}:{port}: cannot serve there: "
                               f"{exc.strerror or exc}") from None
        bound = server.sockets[0].getsockname()
        shown = f"[{bound[0]}]" if ":" in bound[0] else bound[0]
        self.url = f"http://{shown}:{bound[1]}/?token={self.access.token}"
        try:
            self.reader = PacketReader(lambda: PacketSubscriber(self.connect, self.curve),
                                       QUEUE_PACKETS, REOPEN_S, self._wake)
            self.upstream = Upstream(self)
            if ready is not None:
                ready(self.url)
            next_status = 0.0
            while not self.stop.is_set() and self.error is None:
                await asyncio.sleep(SWEEP_S)
                self._forward()
                self._sweep()
                self.admission.tidy()
                if time.monotonic() >= next_status:
                    next_status = time.monotonic() + STATUS_S
                    if (clock := self._clock_json()) is not None:
                        self._send_all(clock)
                    if self._status_to is not None:
                        self._status_to(self.status())
        finally:
            server.close()
            await server.wait_closed()
            if self.upstream is not None:
                self.upstream.close()
            if self.reader is not None:
                self.reader.close()
        if self.error is not None:
            raise self.error
        return self.summary()

    def post(self, callback: Callable[..., None], *args: Any) -> None:
        """Run ``callback(*args)`` on the event loop's thread (from any thread)."""
        assert self._loop is not None
        try:
            self._loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # the loop has closed: the gateway is stopping
            pass

    def say(self, text: str) -> None:
        """A line of text to the caller (from any thread)."""
        if self._say_to is not None:
            with self._say_lock:
                self._say_to(text)

    def _wake(self) -> None:
        """The reader's thread: a packet is queued; forward it on the loop (once per
        burst)."""
        if not self._scheduled:
            self._scheduled = True
            self.post(self._forward)

    def _forward(self) -> None:
        """Check each queued packet and forward those that decode (module docstring)."""
        self._scheduled = False
        if self.reader is None:
            return
        try:
            while (item := self.reader.take()) is not None:
                data, arrival = item
                link = self.upstream.link if self.upstream is not None else None
                if is_voice(data):  # the voice: checked and forwarded as it is, never held
                    self._forward_voice(data)
                    continue
                try:
                    frame = decode(data)
                except PacketError as exc:
                    self.counts["corrupt"] += 1
                    self.counts[f"corrupt_{exc.reason}"] += 1
                    if link is not None:
                        link.note_packet(arrival)
                    continue
                clocked = self.upstream is None or self.upstream.clock is None or \
                    self.upstream.clock.answers is not False
                if link is not None and link.note_packet(arrival, frame.seq, clocked):
                    assert self.upstream is not None  # it holds the link
                    self.upstream.recheck.set()  # perhaps a restarted sender: ask its Hello
                    if self._doubt is None:
                        self._doubt, self._doubt_since = [], time.monotonic()
                self.latest_serial = frame.serial
                if self.model_json is None or self._doubt is not None and \
                        len(self._doubt) >= MAX_DOUBT:
                    self.counts["held"] += 1
                elif self._doubt is not None:
                    self._doubt.append(data)
                else:
                    self._send_packet(data)
        except FacewireError as exc:
            self.error = exc

    def _forward_voice(self, data: bytes) -> None:
        """A voice packet (``protocol.voice``): forwarded once the pages have the model the
        Hello names, counted ``voice``; one that does not decode is dropped and counted by
        its reason (``corrupt_voice_*``)."""
        try:
            decode_voice(data)
        except VoiceError as exc:
            self.counts["corrupt"] += 1
            self.counts[f"corrupt_voice_{exc.reason}"] += 1
            return
        if self.model_json is None:
            self.counts["held"] += 1
            return
        broadcast(self.viewers, data)
        self.counts["voice"] += 1
        self.counts["voice_bytes"] += len(data)

    def _send_packet(self, data: bytes) -> None:
        broadcast(self.viewers, data)
        self.counts["forwarded"] += 1
        self.counts["forwarded_bytes"] += len(data)

    def _sweep(self) -> None:
        """Cut off the viewers that do not read (module docstring)."""
        for viewer in list(self.viewers):
            if viewer.transport.get_write_buffer_size() > MAX_BUFFER_BYTES:
                self.viewers.discard(viewer)
                viewer.transport.abort()
                self.counts["dropped_slow"] += 1

    def _send_all(self, text: str) -> None:
        broadcast(self.viewers, text)

    def _clock_json(self) -> str | None:
        """The ``clock`` message (module docstring), or None before the Hello's clock and an
        offset estimate."""
        upstream = self.upstream
        best = upstream.clock.best() if upstream is not None and upstream.clock else None
        hello = upstream.link.hello if upstream is not None else None
        if best is None or hello is None or hello.clock_origin_s is None:
            return None
        voice = {} if hello.voice_origin_s is None else \
            {"voice_origin_s": hello.voice_origin_s - best.offset_s}
        return json.dumps({"type": "clock", "origin_s": hello.clock_origin_s - best.offset_s,
                           "rate_hz": hello.rate_hz, "now_s": time.monotonic(), **voice})

    # -- what the upstream thread hands over -------------------------------------------------

    def set_status(self, sender: str, text: str) -> None:
        if sender != self.sender:
            self.say(f"sender {sender}: {text}")
        self.sender = sender
        self.status_json = _status_json(sender, text)
        self._send_all(self.status_json)

    def adopt(self, hello: Hello, sha256: str, files: dict[str, Body]) -> None:
        """A model (new, or a new session of it) for this Hello: pages start from its file."""
        self.models[sha256] = files
        self.models.move_to_end(sha256)
        while len(self.models) > MODELS_KEPT:
            self.models.popitem(last=False)
        self.updates = {k: v for k, v in self.updates.items() if k[0] != sha256}
        self.sha256, self.serial, self.update_json = sha256, 0, []
        self.hello_json = _hello_json(hello)
        size = len(files["glb"].raw) + len(files["rig"].raw)
        self.model_json = json.dumps({"type": "model", "sha256": sha256,
                                      "glb": f"/model/{sha256}.glb",
                                      "rig": f"/model/{sha256}.rig", "bytes": size})
        self._send_all(self.hello_json)
        self._send_all(self.model_json)
        self.set_status("connected", "the sender is connected")

    def unready(self) -> None:
        """The sender names another model: no packet goes out until it is here (those in
        doubt were of that model: held)."""
        self.model_json = None
        self.counts["held"] += len(self._doubt or ())
        self._doubt = None

    def confirm(self, asked: float) -> None:
        """A Hello asked at ``asked`` (monotonic) was answered with the stream's model, or
        not answered: the packets in doubt since before it go out (module docstring)."""
        if self._doubt is not None and asked >= self._doubt_since:
            doubt, self._doubt = self._doubt, None
            for data in doubt:
                self._send_packet(data)

    def set_hello(self, hello: Hello) -> None:
        self.hello_json = _hello_json(hello)
        self._send_all(self.hello_json)

    def add_update(self, sha256: str, serial: int, body: Body) -> None:
        if sha256 != self.sha256 or serial != self.serial + 1:
            return  # of a session replaced meanwhile
        self.updates[(sha256, serial)] = body
        self.serial = serial
        message = json.dumps({"type": "update", "serial": serial,
                              "url": f"/model/{sha256}/{serial}.upd", "bytes": len(body.raw)})
        self.update_json.append(message)
        self._send_all(message)

    def fail(self, error: BaseException) -> None:
        self.error = error

    # -- WebSocket ---------------------------------------------------------------------------

    async def _viewer(self, viewer: ServerConnection) -> None:
        """One page: its first messages and the stream (module docstring); its messages
        counted, and the page closed when they are too many."""
        sock = viewer.transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
        first = [self.status_json]
        if self.model_json is not None and self.hello_json is not None:
            first += [self.hello_json, self.model_json, *self.update_json]
        for text in first:
            broadcast([viewer], text)
        self.admission.promote(viewer.transport)
        self.viewers.add(viewer)
        self.counts["viewers_total"] += 1
        self.viewers_max = max(self.viewers_max, len(self.viewers))
        recent: deque[float] = deque()
        try:
            async for _ in viewer:
                now = time.monotonic()
                recent.append(now)
                while recent[0] < now - 1.0:
                    recent.popleft()
                if len(recent) > MAX_MESSAGES_PER_S:
                    self.counts["dropped_junk"] += 1
                    self.viewers.discard(viewer)
                    closing = asyncio.create_task(
                        viewer.close(1008, "this stream takes no messages"))
                    with contextlib.suppress(ConnectionClosed):
                        async for _ in viewer:  # read what came before its answering close
                            pass
                    await closing
                    return
        except ConnectionClosed as closed:
            if closed.sent is not None and closed.sent.code == 1009:  # over max_size
                self.counts["dropped_junk"] += 1
        finally:
            self.viewers.discard(viewer)

    # -- HTTP --------------------------------------------------------------------------------

    async def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        """A plain GET answered, or None to open the WebSocket (module docstring)."""
        url = urlsplit(request.path)
        headers = request.headers
        hosts, origins = headers.get_all("Host"), headers.get_all("Origin")
        if len(hosts) > 1 or len(origins) > 1:
            return self._refuse(HTTPStatus.BAD_REQUEST, "one Host and at most one Origin "
                                "header, please")
        host = hosts[0] if hosts else ""
        if not self.access.host_allowed(host):
            return self._refuse(HTTPStatus.FORBIDDEN, "this gateway answers only requests "
                                "to a loopback host" + (", an IP address or a name given by "
                                                        "--host" if self.access.allow_remote
                                                        else ""))
        given = parse_qs(url.query).get("token", [""])[0]
        if not hmac.compare_digest(given.encode(), self.access.token.encode()):
            address = connection.remote_address[0] if connection.remote_address else None
            delay = self.throttle.delay(address)
            self.throttle.failed(address)
            if delay > 0:
                await asyncio.sleep(delay)
            return self._refuse(HTTPStatus.FORBIDDEN, "wrong or missing ?token=")
        upgrade = "websocket" in ",".join(headers.get_all("Upgrade")).lower()
        if url.path == "/stream" and upgrade:
            if origins and urlsplit(origins[0]).netloc != host:
                return self._refuse(HTTPStatus.FORBIDDEN, "the stream is for this "
                                    "gateway's own page (Origin)")
            if len(self.viewers) >= self.max_viewers:
                return self._refuse(HTTPStatus.SERVICE_UNAVAILABLE, "too many viewers")
            return None
        body = None if upgrade else self._body(url.path)
        if body is None:
            return self._refuse(HTTPStatus.NOT_FOUND, f"no {url.path[:100]} here")
        self.counts["http_served"] += 1
        gz = body.gz is not None and _accepts_gzip(",".join(headers.get_all("Accept-Encoding")))
        data = body.gz if gz and body.gz is not None else body.raw
        response = Headers([("Date", email.utils.formatdate(usegmt=True)),
                            ("Connection", "close"), ("Content-Type", body.kind),
                            ("Content-Length", str(len(data))),
                            ("Cache-Control", body.cache),
                            ("X-Content-Type-Options", "nosniff")])
        if body.gz is not None:
            response["Vary"] = "Accept-Encoding"
        if gz:
            response["Content-Encoding"] = "gzip"
        return Response(200, "OK", response, data)

    def _body(self, path: str) -> Body | None:
        if path == "/":
            path = "/index.html"
        if (m := _FILE.fullmatch(path)) is not None:
            return self.files.get(m["name"])
        if (m := _MODEL.fullmatch(path)) is not None:
            return self.models.get(m["sha"], {}).get(m["kind"])
        if (m := _UPDATE.fullmatch(path)) is not None:
            return self.updates.get((m["sha"], int(m["serial"])))
        return None

    def _refuse(self, status: HTTPStatus, text: str) -> Response:
        self.counts["http_refused"] += 1
        body = f"facewire web: {text}\n".encode()
        headers = Headers([("Date", email.utils.formatdate(usegmt=True)),
                           ("Connection", "close"),
                           ("Content-Type", "text/plain; charset=utf-8"),
                           ("Content-Length", str(len(body)))])
        return Response(status.value, status.phrase, headers, body)

    # -- reports -----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """The live counts: ``sender`` (waiting, connected), ``model`` (sha256 prefix or
        None), ``version``, ``viewers``, ``forwarded``, ``corrupt``, ``dropped`` (pages cut
        off: junk and slow), ``seconds``."""
        return {"sender": self.sender, "model": self.sha256[:12] if self.sha256 else None,
                "version": self.serial, "viewers": len(self.viewers),
                "forwarded": self.counts["forwarded"], "corrupt": self.counts["corrupt"],
                "dropped": self.counts["dropped_junk"] + self.counts["dropped_slow"],
                "seconds": round(time.monotonic() - self.started, 1)}

    def summary(self) -> dict[str, Any]:
        """``connect``, ``url`` (``shown_url``), ``seconds``; packets ``forwarded`` (and
        their bytes), ``voice`` packets forwarded (and ``voice_bytes``), ``held`` (before a
        model), ``corrupt`` (and ``corrupt_REASON``, ``corrupt_voice_REASON``), ``overflow``;
        viewers: ``viewers_total``, ``viewers_max``, ``dropped_junk``, ``dropped_slow``;
        ``http_served``, ``http_refused``; the model: ``model_sha256``, ``model_serial``,
        ``glb_bytes``, ``rig_bytes`` and as sent gzipped ``glb_bytes_gzip``,
        ``rig_bytes_gzip`` (None when sent as they are), ``model_file_bytes`` (the ``.fwm``);
        the sender's clock: ``receiver.clocksync.ClockSync.summary``'s keys."""
        files = self.models.get(self.sha256 or "", {})
        counts = {k: self.counts[k] for k in (
            "forwarded", "forwarded_bytes", "voice", "voice_bytes", "held", "corrupt",
            "viewers_total",
            "dropped_junk", "dropped_slow", "http_served", "http_refused")}
        reasons = {k: v for k, v in self.counts.items() if k.startswith("corrupt_")}
        upstream = self.upstream
        return {"connect": self.connect, "url": shown_url(self.url),
                "seconds": round(time.monotonic() - self.started, 3), **counts, **reasons,
                "overflow": self.reader.overflow if self.reader else 0,
                "viewers_max": self.viewers_max, "model_sha256": self.sha256,
                "model_serial": self.serial,
                "model_file_bytes": upstream.model_bytes if upstream else None,
                **(upstream.clock.summary() if upstream and upstream.clock
                   else ClockSync.EMPTY),
                **{f"{k}_bytes": len(b.raw) for k, b in files.items()},
                **{f"{k}_bytes_gzip": b.gz and len(b.gz) for k, b in files.items()}}


class Upstream:
    """The upstream thread: the Hello, the model, the updates and the web bodies (module
    docstring); hands each result to the gateway's loop.

    Attributes:
        link: the link to the sender (``receiver.link``); the loop notes packets in it.
        recheck: set to wake the thread at once (a sign of the link).
        clock: the sender's clock (``receiver.clocksync``), from the first Hello.
        model_bytes: the current model file's size.
    """

    def __init__(self, gateway: Gateway) -> None:
        self.gateway = gateway
        self.recheck = threading.Event()
        self.model_bytes: int | None = None
        self.clock: ClockSync | None = None
        self._closing = threading.Event()
        self.link = SenderLink(gateway.connect, gateway.curve)
        self._acquirer = ModelAcquirer(gateway.connect, self.link.control, gateway.cache,
                                       None, gateway.say, self._check_end, lambda: None)
        self._fetcher: UpdateFetcher | None = None
        self._thread = threading.Thread(target=self._run, name="facewire gateway upstream",
                                        daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._closing.set()
        self.recheck.set()
        self._thread.join()
        if self._fetcher is not None:
            self._fetcher.close()
        if self.clock is not None:
            self.clock.close()
        self.link.close()

    def _check_end(self) -> None:
        if self._closing.is_set() or self.gateway.stop.is_set():
            raise _Closing

    def _run(self) -> None:
        try:
            self._session()
        except _Closing:
            pass
        except Exception as exc:  # noqa: BLE001 - handed to the loop, which raises it
            self.gateway.post(self.gateway.fail, exc)

    def _session(self) -> None:
        gw = self.gateway
        link = self.link
        files: dict[str, Body] = {}
        connected, announced, next_ask = False, 0, 0.0
        gw.say(f"waiting for a sender at {gw.connect}")
        while True:
            self._check_end()
            now = time.monotonic()
            last = gw.reader.last_arrival if gw.reader is not None else None
            silent = last is None or now - last > SILENT_S
            if not connected or now >= next_ask or link.check_due(now) or silent:
                self.recheck.clear()
                asked = time.monotonic()
                fetched = self._fetcher.fetched if self._fetcher is not None else None
                answer = link.ask(HELLO_TIMEOUT_S, fetched)
                if answer is None:
                    if connected and silent:
                        connected = False
                        gw.post(gw.set_status, "waiting",
                                "the sender stopped answering: waiting for it")
                    next_ask = time.monotonic() + RECHECK_EVERY_S
                    gw.post(gw.confirm, asked)  # cannot tell: what was held goes out
                    continue
                got = answer.hello
                next_ask = time.monotonic() + (SILENT_S if silent else RECHECK_EVERY_S)
                if not connected:
                    connected = True
                    gw.post(gw.set_status, "connected", "the sender is connected")
                if self.clock is None:
                    self.clock = ClockSync(link.endpoint, gw.curve)
                if answer.change in (Change.FIRST, Change.MODEL):
                    gw.post(gw.set_status, "connected", "fetching the sender's model")
                    gw.post(gw.unready)
                    model = self._acquirer.obtain(got)
                    if model is None:  # the sender went away mid-fetch
                        continue
                    files = _model_files(model)
                    self._start_updates(model)
                    self.model_bytes = model.file_bytes
                    announced = 0
                    gw.post(gw.adopt, got, model.sha256, files)
                elif answer.new_session and self._fetcher is not None:
                    gw.say(f"the sender is at model version {got.model_serial}, the gateway "
                           f"at {self._fetcher.fetched}: a new session, its updates fetched "
                           f"anew")
                    self._start_updates(self._fetcher.version(0))
                    announced = 0
                    gw.post(gw.adopt, got, got.model_sha256, files)
                elif answer.change in (Change.DETAILS, Change.RATE):
                    gw.post(gw.set_hello, got)
                gw.post(gw.confirm, asked)
                link.take(got)
            announced = self._announce(announced)
            self.recheck.wait(_WAKE_S)

    def _announce(self, announced: int) -> int:
        """Hand the loop the bodies of the updates fetched beyond ``announced``; the newest
        announced."""
        gw, fetcher, hello = self.gateway, self._fetcher, self.link.hello
        if fetcher is None or hello is None:
            return announced
        fetcher.want(max(hello.model_serial, gw.latest_serial))
        while fetcher.fetched > announced:
            before, after = fetcher.version(announced), fetcher.version(announced + 1)
            assert before is not None and after is not None  # fetched, so held
            announced += 1
            body = Body.make(update_bin(before, after), "application/octet-stream",
                             "no-store")
            gw.post(gw.add_update, fetcher.base_sha256, announced, body)
        return announced

    def _start_updates(self, model: PersonModel | None) -> None:
        assert model is not None  # version 0 is always held
        if self._fetcher is not None:
            self._fetcher.close()
        self._fetcher = UpdateFetcher(control_endpoint(self.gateway.connect),
                                      self.gateway.curve, model, self.gateway.say)


class _Closing(Exception):
    """Unwinds the upstream thread when the gateway stops."""


def _guarded(admission: Admission) -> type[ServerConnection]:
    """``websockets``' connection class with each connection admitted by ``admission`` (and
    closed at once when refused)."""

    class Guarded(ServerConnection):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            sock = transport.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            transport.max_size = RECEIVE_BUFFER_BYTES  # type: ignore[attr-defined]
            super().connection_made(transport)
            assert isinstance(transport, asyncio.Transport)  # a TCP connection's
            if not admission.admit(transport):
                transport.abort()

        def connection_lost(self, exc: Exception | None) -> None:
            admission.release(self.transport)
            super().connection_lost(exc)

    return Guarded


def _model_files(model: PersonModel) -> dict[str, Body]:
    """A model's bodies as served: ``glb`` and ``rig`` (``models.webmodel``), immutable."""
    cache = "public, max-age=31536000, immutable"
    return {"glb": Body.make(model_glb(model), "model/gltf-binary", cache),
            "rig": Body.make(rig_bin(model), "application/octet-stream", cache)}


def _page_files() -> dict[str, Body]:
    """The page's files of the installed package, by name (read once)."""
    folder = resources.files("facewire.receiver") / "web"
    files: dict[str, Body] = {}
    if not folder.is_dir():
        return files
    for entry in folder.iterdir():
        if _FILE.fullmatch(f"/{entry.name}") and entry.is_file():
            kind = _TYPES[entry.name[entry.name.rindex("."):]]
            files[entry.name] = Body.make(entry.read_bytes(), kind, "no-cache")
    return files


def _status_json(sender: str, text: str) -> str:
    return json.dumps({"type": "status", "sender": sender, "text": text})


def _hello_json(hello: Hello) -> str:
    """The Hello as pages get it: its clock (the face's and the voice's origins) travels in
    ``clock`` messages instead, on the gateway's clock."""
    fields = dataclasses.asdict(hello)
    del fields["clock_origin_s"], fields["voice_origin_s"]
    return json.dumps({"type": "hello", **fields})


def _accepts_gzip(header: str) -> bool:
    """Whether an ``Accept-Encoding`` header accepts gzip (named, or ``*``, with q > 0)."""
    for item in header.lower().split(","):
        name, *params = (part.strip() for part in item.split(";"))
        if name in ("gzip", "*"):
            q = next((p[2:] for p in params if p.startswith("q=")), "1")
            try:
                return float(q) > 0
            except ValueError:
                return False
    return False
