"""A process's measures from Linux's ``/proc``: CPU time, run-queue wait, resident memory.

- CPU time: user plus system clock ticks of all its threads, fields 14 and 15 of
  ``/proc/PID/stat`` (counted after the command name's closing parenthesis, which may hold
  spaces), divided by ``SC_CLK_TCK``.
- Run-queue wait: the time its threads were ready to run but waiting for a core, the second
  field of each ``/proc/PID/task/TID/schedstat``, ns.
- Resident memory: ``VmRSS`` of ``/proc/PID/status``, kB; its threads: ``Threads`` there.
"""

from __future__ import annotations

import os
from pathlib import Path

from facewire.protocol.errors import FacewireError


class ProcessGone(FacewireError, ProcessLookupError):
    """The measured process has exited (or holds no memory: a zombie)."""


def _read(pid: int, name: str) -> str:
    try:
        return Path(f"/proc/{pid}/{name}").read_text()
    except OSError:
        raise ProcessGone(f"process {pid} (measured) has gone") from None


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of a process (all its threads), s."""
    fields = _read(pid, "stat").rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_seconds(pid: int) -> float:
    """Time the threads of a process spent ready to run but waiting for a core, s."""
    total = 0
    for task in Path(f"/proc/{pid}/task").glob("*/schedstat"):
        try:
            total += int(task.read_text().split()[1])
        except (OSError, IndexError, ValueError):
            continue  # a thread that ended meanwhile
    return total / 1e9


def rss_mb(pid: int) -> float:
    """The resident set size of a process, MB."""
    return _status_field(pid, "VmRSS") / 1024


def thread_count(pid: int) -> int:
    """The threads of a process."""
    return _status_field(pid, "Threads")


def _status_field(pid: int, name: str) -> int:
    for line in _read(pid, "status").splitlines():
        if line.startswith(f"{name}:"):
            return int(line.split()[1])
    raise ProcessGone(f"/proc/{pid}/status: no {name}")
