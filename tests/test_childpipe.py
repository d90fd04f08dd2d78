"""A child's reply on a pipe: read when it came before the child exited, EOFError when the
child exited without one (``models.infra.childpipe``), on real processes and pipes."""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

import pytest

from facewire.models.infra.childpipe import POLL_S, receive_from

_FORK = multiprocessing.get_context("fork")


def _reply_and_exit(conn: Connection) -> None:
    conn.send(("done", 42))
    os._exit(0)  # at once, as a crash would: no cleanup


def _exit_silently(conn: Connection) -> None:
    os._exit(3)


def _run(target: Callable[[Connection], None]) -> tuple[BaseProcess, Connection, Connection]:
    """The child started on ``target`` with the pipe's sending end, and that end, which the
    parent keeps open too: so the pipe never says EOF, and a plain ``recv`` would wait
    forever on a silent child."""
    receiving, sending = _FORK.Pipe(duplex=False)
    child = _FORK.Process(target=target, args=(sending,))
    child.start()
    child.join()  # it has exited before the parent reads
    return child, receiving, sending


def test_a_reply_sent_before_the_child_exited_is_read() -> None:
    child, conn, _ = _run(_reply_and_exit)
    assert receive_from(child, conn) == ("done", 42)


def test_a_child_that_exited_without_a_reply_is_eof_within_a_poll() -> None:
    child, conn, sending = _run(_exit_silently)
    start = time.monotonic()
    with pytest.raises(EOFError, match=rf"\(pid {child.pid}\) exited without a reply"):
        receive_from(child, conn)
    assert time.monotonic() - start < 2 * POLL_S + 1.0
    sending.close()


def _wait_silently(conn: Connection) -> None:
    time.sleep(30)  # alive, and saying nothing


def test_a_live_child_that_says_nothing_is_a_timeout_when_one_is_given() -> None:
    receiving, sending = _FORK.Pipe(duplex=False)
    child = _FORK.Process(target=_wait_silently, args=(sending,), daemon=True)
    child.start()
    try:
        start = time.monotonic()
        with pytest.raises(TimeoutError, match=rf"\(pid {child.pid}\) sent nothing within 1 s"):
            receive_from(child, receiving, timeout_s=1.0)
        assert 1.0 <= time.monotonic() - start < 1.0 + 2 * POLL_S + 1.0
    finally:
        child.kill()
        child.join()
        sending.close()
