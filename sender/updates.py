"""The session's model updates as the sender holds them: in serial order, split into chunks.

A model update (``models.update``) is issued once, with serial n = the previous one + 1
(starting at 1: serial 0 is the model file), and kept for the whole session, so that a
receiver joining late, or restarted, fetches every one of them in order
(``protocol.control``: ``update_request`` -> ``update_chunk``). Its bytes are opaque here
(``models.update``'s format); they are split once into ``protocol.control.update_chunks``.
At most ``protocol.packet.MAX_SERIAL`` updates a session (the packet's serial field).

``publish_update`` may be called from any thread (the frame loop issues updates while the
control thread serves them); the newest serial is what the Hello's ``model_serial`` says.
"""

from __future__ import annotations

import threading

from facewire.protocol.control import (
    ControlError,
    UpdateChunk,
    UpdateRequest,
    update_chunks,
)
from facewire.protocol.packet import MAX_SERIAL


class UpdateStore:
    """The updates of one session of model ``model_sha256`` (module docstring).

    Attributes:
        model_sha256: the model file's sha256, the session's base.
        bytes_total: the bytes of every update published.
    """

    def __init__(self, model_sha256: str) -> None:
        self.model_sha256 = model_sha256
        self.bytes_total = 0
        self._chunks: list[list[UpdateChunk]] = []  # [n - 1]: update n's chunks
        self._lock = threading.Lock()

    @property
    def serial(self) -> int:
        """The newest update's serial (0: none yet)."""
        return len(self._chunks)

    def publish_update(self, serial: int, data: bytes) -> None:
        """Hold update ``serial`` (its bytes, ``models.update.encode_update``) to serve.

        Raises:
            ControlError: ``serial`` is not the next one, past ``MAX_SERIAL``, or the
                bytes are empty or over ``protocol.control.MAX_UPDATE_BYTES``.
        """
        with self._lock:
            if serial != len(self._chunks) + 1:
                raise ControlError(f"update {serial}: the next update's serial is "
                                   f"{len(self._chunks) + 1}")
            if serial > MAX_SERIAL:
                raise ControlError(f"update {serial}: a session holds at most "
                                   f"{MAX_SERIAL} updates")
            self._chunks.append(update_chunks(bytes(data), self.model_sha256, serial))
            self.bytes_total += len(data)

    def chunk(self, request: UpdateRequest) -> UpdateChunk:
        """The chunk a request asks for.

        Raises:
            ControlError: another model, an update not issued, or an index out of range
                (the message names the field).
        """
        if request.model_sha256 != self.model_sha256:
            raise ControlError(f"update_request.model_sha256: this sender's session is of "
                               f"model {self.model_sha256}, not {request.model_sha256}")
        with self._lock:
            if request.serial > len(self._chunks):
                raise ControlError(f"update_request.serial: update {request.serial} has not "
                                   f"been issued (the newest is {len(self._chunks)})")
            chunks = self._chunks[request.serial - 1]
        if request.index >= len(chunks):
            raise ControlError(f"update_request.index: {request.index} is out of range "
                               f"(update {request.serial} has {len(chunks)} chunks)")
        return chunks[request.index]
