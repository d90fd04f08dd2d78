"""What a receiver asks its sender for over the control channel: answers, and the person model.

Control requests (ZeroMQ's "lazy pirate" pattern, ``ControlChannel``)
---------------------------------------------------------------------
One request at a time, each with a timeout, on a DEALER socket at
``protocol.transport.control_endpoint(connect)`` (the packet port + 1), under CURVE when keys
are given. A DEALER queues a request even when no sender is there yet and delivers it when one
appears, so a reply may come after its request timed out. After a timeout or a bad reply
(malformed, an ``Error``, or not the answer asked for) the socket is closed and opened again,
so a late reply can never be taken for the answer to the next request. Both are counted
(``timeouts``, ``errors``), neither is fatal.

The model (``ModelAcquirer.obtain``, for each Hello whose model is new)
-----------------------------------------------------------------------
1. With a model file (``--model``), its sha256 must be the Hello's, or ``ReceiveError``.
2. Else the model cache (``receiver.modelcache``) by the Hello's sha256; a cached file that is
   refused (damaged) is fetched again.
3. Else the sender's file in chunks (``ModelRequest(sha256, index)`` -> ``ModelChunk``,
   reassembled by ``protocol.control.ChunkAssembler``), each chunk asked up to
   ``CHUNK_ATTEMPTS`` times (``CHUNK_TIMEOUT_S`` each); the whole is verified (sha256, then
   decoded: ``receiver.modelcache.verify_model``) before it is cached and used.

A sender that stops answering mid-transfer (a chunk request times out) gives None: the
receiver asks for the Hello again. A transfer whose whole fails the sha256, or in which a
chunk was answered ``CHUNK_ATTEMPTS`` times with something else (another chunk, an error), is
a failed attempt, and ``MODEL_ATTEMPTS`` of them raise ``ReceiveError``; so does a model that
hashes right but is not a valid model file.

``ModelAcquirer.info`` holds the summary's model keys: ``model_sha256``, ``model_source``
(file, cache or fetched), ``model_bytes``, ``model_fetch_s`` (fetch and verification, None
unless fetched) and ``cached`` (the cache file, or None).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from facewire.models.modelfile import ModelFileError, PersonModel
from facewire.protocol import control as ctl
from facewire.protocol.control import ChunkAssembler, ControlError, Hello, ModelChunk, ModelRequest
from facewire.protocol.errors import FacewireError
from facewire.protocol.keys import CurveClient
from facewire.protocol.transport import ControlClient
from facewire.receiver.modelcache import ModelCache, ModelCacheError, verify_model

CHUNK_TIMEOUT_S = 5.0
CHUNK_ATTEMPTS = 5
MODEL_ATTEMPTS = 3

Status = Callable[[str], None]


class ReceiveError(FacewireError, ValueError):
    """The receive cannot go on: a bad option, or a model that is not the sender's."""


class ControlChannel:
    """The control socket, reopened after any timeout or bad reply (module docstring).

    Args:
        endpoint: the sender's control endpoint, ``tcp://HOST:PORT``.
        curve: CURVE client keys, or None for plain TCP.

    Attributes:
        timeouts, errors: requests that timed out, replies refused.
        last_error: why the last reply was refused ("" if none was).
    """

    def __init__(self, endpoint: str, curve: CurveClient | None) -> None:
        self.endpoint = endpoint
        self._curve = curve
        self._client = ControlClient(endpoint, curve)
        self.timeouts = 0
        self.errors = 0
        self.last_error = ""

    def ask(self, message: ctl.Message, expect: type | tuple[type, ...], timeout_s: float
            ) -> Any:
        """The reply if it is an ``expect``; None (counted, socket reopened) otherwise."""
        try:
            reply = self._client.request(message, max(1, round(timeout_s * 1000)))
        except ControlError as exc:
            return self.reject(f"malformed reply: {exc}")
        if reply is None:
            self.timeouts += 1
            self._reopen()
            return None
        if isinstance(reply, expect):
            return reply
        if isinstance(reply, ctl.Error):
            return self.reject(f"the sender says: {reply.message}")
        return self.reject(f"a {reply.TYPE} reply to a {message.TYPE}")

    def reject(self, why: str) -> None:
        """Count a reply that is not the answer asked for, and reopen the socket."""
        self.errors += 1
        self.last_error = why
        self._reopen()

    def _reopen(self) -> None:
        self._client.close()
        self._client = ControlClient(self.endpoint, self._curve)

    def close(self) -> None:
        self._client.close()


class ModelAcquirer:
    """The model of each Hello: the local file, the cache, or fetched (module docstring).

    Args:
        connect: the sender's packet address (names it in messages).
        control: the control channel to fetch over.
        cache: the model cache.
        local: the model given with ``--model``, or None to look up and fetch.
        say: called with one line of text at each step.
        check_end: called before each chunk request; raises to end the session (stop, idle).
        touch: called on each chunk received (the sender is alive).

    Attributes:
        info: the summary's model keys (module docstring); all None before a model.
    """

    def __init__(self, connect: str, control: ControlChannel, cache: ModelCache,
                 local: PersonModel | None, say: Status, check_end: Callable[[], None],
                 touch: Callable[[], None]) -> None:
        self.connect, self.control, self.cache, self.local = connect, control, cache, local
        self.say, self.check_end, self.touch = say, check_end, touch
        self.info: dict[str, Any] = dict.fromkeys(
            ("model_sha256", "model_source", "model_bytes", "model_fetch_s", "cached"))

    def obtain(self, hello: Hello) -> PersonModel | None:
        """The Hello's model: the local file, the cache, or fetched; None: the sender is gone.

        Raises:
            ReceiveError: the local model is not the sender's; the sender's model is not a
                valid model file, or failed its sha256 ``MODEL_ATTEMPTS`` times.
        """
        sha = hello.model_sha256
        if self.local is not None:
            if self.local.sha256 != sha:
                raise ReceiveError(
                    f"--model: {self.local.sha256[:16]}... is not the sender's model "
                    f"({sha[:16]}..., announced by {self.connect}); omit --model to fetch it")
            self._note(self.local, "file")
            return self.local
        try:
            model = self.cache.get(sha)
        except ModelCacheError as exc:
            self.say(f"{exc}: fetching it again")
            model = None
        if model is not None:
            self._note(model, "cache", cached=self.cache.path(sha))
            self.say(f"model {sha[:12]} from the cache ({self.cache.path(sha)})")
            return model
        for _ in range(MODEL_ATTEMPTS):
            tick = time.monotonic()
            data = self._fetch(hello)
            if data is None:
                return None
            if not data:  # the chunks did not hash to the announced sha256
                continue
            try:
                model = verify_model(data, sha, f"model {sha[:12]} from {self.connect}")
            except ModelFileError as exc:
                raise ReceiveError(f"the sender's model is not a valid model file: {exc}") \
                    from None
            seconds = time.monotonic() - tick
            try:
                path = self.cache.put(data, model)
            except ModelCacheError as exc:
                path = None
                self.say(f"model not cached: {exc}")
            self._note(model, "fetched", cached=path, seconds=seconds)
            self.say(f"model {sha[:12]} fetched: {len(data)} bytes in {seconds:.2f} s"
                     + (f", cached as {path}" if path else ""))
            return model
        raise ReceiveError(f"the model announced by {self.connect} ({sha[:16]}...) failed "
                           f"its sha256 {MODEL_ATTEMPTS} times (its chunks did not hash to "
                           f"it, or were not the ones asked for)")

    def _fetch(self, hello: Hello) -> bytes | None:
        """The model file's bytes; None when the sender stopped answering (a chunk timed
        out), b"" when the whole does not hash to the announced sha256 or every answer for
        a chunk was another chunk or an error (a failed attempt, bounded by
        ``MODEL_ATTEMPTS``)."""
        sha, total = hello.model_sha256, hello.model_bytes
        assembler = ChunkAssembler(sha, total)
        for index in assembler.missing():
            timeouts = self.control.timeouts
            for _ in range(CHUNK_ATTEMPTS):
                self.check_end()
                chunk = self.control.ask(ModelRequest(sha, index), ModelChunk, CHUNK_TIMEOUT_S)
                if chunk is None:
                    continue
                if (chunk.sha256, chunk.index, chunk.total) != (sha, index, total):
                    self.control.reject(f"chunk {chunk.index} of {chunk.sha256[:12]} "
                                        f"({chunk.total} bytes) for chunk {index} of "
                                        f"{sha[:12]} ({total} bytes)")
                    continue
                self.touch()
                assembler.add(chunk)
                self.say(f"fetching model {sha[:12]}: chunk {index + 1}/{assembler.count} "
                         f"({min((index + 1) * ctl.CHUNK_BYTES, total) // 1024} of "
                         f"{total // 1024} KiB)")
                break
            else:
                gone = self.control.timeouts > timeouts
                self.say(f"model {sha[:12]}: chunk {index} failed {CHUNK_ATTEMPTS} times "
                         f"({self.control.last_error or 'no answer'}); "
                         + ("asking the sender again" if gone else "fetching it again"))
                return None if gone else b""
        try:
            return assembler.result()
        except ControlError as exc:
            self.say(f"model {sha[:12]}: {exc}; fetching it again")
            return b""

    def _note(self, model: PersonModel, source: str, cached: Path | None = None,
              seconds: float | None = None) -> None:
        self.info = {"model_sha256": model.sha256, "model_source": source,
                     "model_bytes": model.file_bytes,
                     "model_fetch_s": None if seconds is None else round(seconds, 3),
                     "cached": None if cached is None else str(cached)}
