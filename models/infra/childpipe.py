"""A spawned child's next word on a pipe, without waiting forever on a child that died.

``Connection.recv`` blocks until something arrives; a child killed by a signal or the
out-of-memory killer sends nothing, and if the parent still holds an end of the pipe the
read never ends. So the parent polls the pipe every ``POLL_S`` seconds and checks between
polls that the child still lives; a child that exited with nothing left on the pipe is
``EOFError``, the same as a pipe whose far end was closed. A reply sent just before the
child exited is still read. With a ``timeout_s``, a child that lives but says nothing for
that long is ``TimeoutError`` (checked between polls).
"""

from __future__ import annotations

import time
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

POLL_S = 0.5  # how often the child's liveness is checked while waiting


def receive_from(process: BaseProcess, conn: Connection, timeout_s: float | None = None
                 ) -> Any:
    """The next object ``process`` sends on ``conn`` (module docstring).

    Raises:
        EOFError: the child exited, or closed its end, before sending one.
        TimeoutError: none came within ``timeout_s`` seconds.
        OSError: the pipe broke (``ConnectionResetError``, ...).
    """
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while not conn.poll(POLL_S):
        if not process.is_alive() and not conn.poll(0):
            raise EOFError(f"{process.name} (pid {process.pid}) exited without a reply")
        if deadline is not None and time.monotonic() > deadline:
            raise TimeoutError(f"{process.name} (pid {process.pid}) sent nothing within "
                               f"{timeout_s:g} s")
    return conn.recv()
