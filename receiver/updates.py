"""The session's model updates at a receiver: fetched in the background, in order, verified.

A model's version is (model sha256, serial) (``models.update``); the receiver learns the
newest serial from the Hello (``model_serial``) and from every packet (``Frame.serial``: the
version its Q values refer to), and ``want`` raises the target. A thread of its own fetches
updates 1, 2, ... up to the target, one chunk at a time on a control socket of its own
(``receiver.acquire.ControlChannel``: each request with a timeout, the socket reopened after
a timeout or a bad reply), so the render loop never waits for it and the Hello's own requests
never queue behind it:

1. ``update_request(model sha256, n, index)`` -> ``update_chunk``, each chunk asked up to
   ``CHUNK_ATTEMPTS`` times (``CHUNK_TIMEOUT_S`` each: longer than the sender's shaping
   holds a chunk, ``protocol.shaper``); a chunk that fails its own hash never decodes
   (``protocol.control``), a chunk of another update or index is refused; both count as
   ``control_errors`` and are asked again;
2. the whole must hash to the sha256 its chunks name (``protocol.control.ChunkAssembler``),
   else it is refused (``updates_refused``) and fetched again;
3. the session's versions (``models.update.ModelVersions``, the one holder of versions that
   replay uses too) decode it against the version it applies to (the receiver's model
   n - 1; bounded sizes, shapes, finiteness, the region's layers, no decompression bomb),
   else refused with one line naming the field (``updates_refused``, ``stuck``); any other
   exception while decoding or applying it is refused the same way (counted, one line, the
   thread goes on: a bug met on a peer's bytes must not end the fetching). A refused
   update is fetched again after ``RETRY_S``, doubling with each refusal up to
   ``MAX_RETRY_S``; meanwhile the receiver stays at version n - 1 and says so (the renderer
   keeps rendering, its Q clamped to the layers it holds);
4. and apply it (``models.update.apply_update``): version n, held until the render loop
   takes it.

A sender that does not answer (a chunk timed out ``CHUNK_ATTEMPTS`` times) is asked again
after ``RETRY_S``.

The render loop (``receiver.receiver``) takes a version at the first packet that refers to it
(``take``): the newest version fetched that is no newer than the packet's serial, so a packet
is rendered with the layers its Q values index, or, while its update is still on the way,
with the newest ones held (``FaceRenderer`` clamps each Q to [0, k - 1]).

Counts (``counts``): ``updates`` (applied), ``update_bytes`` (their bytes), ``updates_refused``
(failed the hash or the decoding), ``update_chunks``; ``control_timeouts``,
``control_errors`` are the fetcher's channel's (``control_counts``), a control socket opened
at the first fetch (a stream without updates opens none).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from facewire.models.modelfile import PersonModel
from facewire.models.update import ModelVersions, UpdateError
from facewire.protocol.control import (
    MAX_UPDATE_BYTES,
    UPDATE_CHUNK_BYTES,
    ChunkAssembler,
    ControlError,
    UpdateChunk,
    UpdateRequest,
)
from facewire.protocol.keys import CurveClient
from facewire.receiver.acquire import ControlChannel

CHUNK_TIMEOUT_S = 5.0
CHUNK_ATTEMPTS = 5
RETRY_S = 1.0
MAX_RETRY_S = 30.0
_WAIT_S = 0.1

Status = Callable[[str], None]


class UpdateFetcher:
    """Fetches, verifies and applies one session's updates on a thread (module docstring).

    Args:
        endpoint: the sender's control endpoint.
        curve: CURVE client keys, or None.
        model: the session's model file (version 0).
        say: called with one line of text at each step (from the fetcher's thread).

    Attributes:
        base_sha256: the model file's sha256.
        target: the newest serial known to exist.
        fetched: the newest version fetched and applied (0: the model file).
        stuck: why the last update was refused ("" once one is applied).
        counts: module docstring.
    """

    def __init__(self, endpoint: str, curve: CurveClient | None, model: PersonModel,
                 say: Status) -> None:
        self.base_sha256 = model.sha256
        self.say = say
        self.target = 0
        self.fetched = 0
        self.stuck = ""
        self.counts = dict.fromkeys(("updates", "update_bytes", "updates_refused",
                                     "update_chunks"), 0)
        self._versions = ModelVersions(model)  # decodes, applies and holds them in order
        self._taken = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._endpoint, self._curve = endpoint, curve
        self._control: ControlChannel | None = None  # opened by the thread at its first fetch
        self._thread = threading.Thread(target=self._run, name="facewire updates",
                                        daemon=True)
        self._thread.start()

    def want(self, serial: int) -> None:
        """Version ``serial`` exists (a Hello or a packet says so): fetch up to it."""
        if serial > self.target:
            self.target = serial
            self._wake.set()

    def take(self, serial: int) -> tuple[PersonModel, int] | None:
        """The newest version fetched that is at most ``serial``, and its serial, if it is
        newer than the last one taken; None otherwise."""
        with self._lock:
            best = min(serial, self._versions.held)
            if best <= self._taken:
                return None
            self._taken = best
            return self._versions.model(best), best

    def version(self, serial: int) -> PersonModel | None:
        """Version ``serial`` (0: the model file) if fetched, else None: for a holder that
        needs each version in turn (``receiver.gateway``), where ``take`` skips to the
        newest."""
        with self._lock:
            return self._versions.model(serial) if 0 <= serial <= self._versions.held \
                else None

    def close(self) -> None:
        self._closing.set()
        self._wake.set()
        self._thread.join()
        if self._control is not None:
            self._control.close()

    @property
    def control_counts(self) -> tuple[int, int]:
        """The fetcher's control channel's timeouts and refused replies."""
        if self._control is None:
            return 0, 0
        return self._control.timeouts, self._control.errors

    # -- the fetcher's thread --------------------------------------------------------------

    def _run(self) -> None:
        failures = 0
        while not self._closing.is_set():
            if self.fetched >= self.target:
                self._wake.wait(_WAIT_S)
                self._wake.clear()
                continue
            serial = self.fetched + 1
            try:
                data = self._fetch(serial)
                if data is None:  # the sender did not answer, or we are closing
                    self._closing.wait(RETRY_S)
                    continue
                if not data:
                    raise UpdateError(f"update {serial}: its chunks do not hash to the "
                                      f"sha256 they name")
                with self._lock:
                    [update] = self._versions.add(serial, data, where=f"update {serial}")
            except Exception as exc:  # noqa: BLE001 - any failure on a peer's bytes: refused
                self.counts["updates_refused"] += 1
                failures += 1
                wait = min(RETRY_S * 2.0 ** min(failures - 1, 30), MAX_RETRY_S)
                self.stuck = str(exc) if isinstance(exc, UpdateError) else \
                    f"update {serial}: {type(exc).__name__}: {exc}"
                self.say(f"{self.stuck}: refused ({failures} times), fetching it again in "
                         f"{wait:.0f} s; staying at model version {serial - 1}")
                self._closing.wait(wait)
                continue
            failures, self.stuck = 0, ""
            self.fetched = serial
            self.counts["updates"] += 1
            self.counts["update_bytes"] += len(data)
            self.say(f"model update {serial} fetched: {len(data)} bytes, region "
                     f"{update.region}")

    def _fetch(self, serial: int) -> bytes | None:
        """Update ``serial``'s bytes, verified against the sha256 its chunks name; b"" when
        they do not hash to it (counted, to fetch again); None when the sender did not answer
        or the fetcher is closing."""
        assembler: ChunkAssembler | None = None
        index = 0
        while assembler is None or index < assembler.count:
            chunk = self._chunk(serial, index, assembler)
            if chunk is None:
                return None
            if assembler is None:
                assembler = ChunkAssembler(chunk.sha256, chunk.total, UPDATE_CHUNK_BYTES,
                                           f"update {serial}", MAX_UPDATE_BYTES)
            assembler.add(chunk)
            self.counts["update_chunks"] += 1
            index += 1
        try:
            return assembler.result()
        except ControlError:
            return b""

    def _chunk(self, serial: int, index: int, assembler: ChunkAssembler | None
               ) -> UpdateChunk | None:
        """Chunk ``index`` of update ``serial`` (of the same whole as ``assembler``'s);
        None after ``CHUNK_ATTEMPTS`` tries or when closing."""
        request = UpdateRequest(self.base_sha256, serial, index)
        if self._control is None:
            self._control = ControlChannel(self._endpoint, self._curve)
        control = self._control
        for _ in range(CHUNK_ATTEMPTS):
            if self._closing.is_set():
                return None
            chunk = control.ask(request, UpdateChunk, CHUNK_TIMEOUT_S)
            if chunk is None:
                continue
            whole = (assembler.sha256, assembler.total) if assembler is not None else \
                (chunk.sha256, chunk.total)
            if (chunk.model_sha256, chunk.serial, chunk.index, chunk.sha256, chunk.total) != \
                    (self.base_sha256, serial, index, *whole):
                control.reject(f"update_chunk {chunk.index} of update {chunk.serial} "
                                    f"for chunk {index} of update {serial}")
                continue
            return chunk
        self.say(f"update {serial}: chunk {index} failed {CHUNK_ATTEMPTS} times "
                 f"({control.last_error or 'no answer'}); asking again")
        return None
