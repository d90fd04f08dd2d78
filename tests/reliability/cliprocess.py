"""A ``facewire`` command run as a real process, its status lines read as they come.

``Facewire(*args, cache=...)`` starts ``python -m facewire.cli ARGS`` with the model cache at
``cache`` and one BLAS thread. A thread reads its stderr, where the command rewrites one
status line in place (``\\r``) and ends finished lines with ``\\n``: each line is kept with the
``time.monotonic()`` at which it was read, so a test can wait for a line (``wait_for``)
rather than sleep. ``summary()`` waits for the end and returns the JSON object that
``--json`` prints as the last line of stdout, after checking the exit status and that no
traceback was printed.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

WAIT_S = 120  # at most, for a process to end (a loaded 2-core machine starts them slowly)


class Facewire:
    """One ``facewire`` process (module docstring)."""

    def __init__(self, *args: str, cache: Path) -> None:
        env = {**os.environ, "FACEWIRE_CACHE": str(cache), "OPENBLAS_NUM_THREADS": "1"}
        self.args = args
        self.process = subprocess.Popen([sys.executable, "-m", "facewire.cli", *args],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        env=env)
        self.lines: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        pending = b""
        while chunk := os.read(self.process.stderr.fileno(), 65536):
            parts = re.split(rb"[\r\n]", pending + chunk)
            pending = parts.pop()
            now = time.monotonic()
            with self._lock:
                self.lines.extend((now, p.decode(errors="replace").strip()) for p in parts
                                  if p.strip())
        if pending.strip():
            with self._lock:
                self.lines.append((time.monotonic(), pending.decode(errors="replace").strip()))

    def text(self) -> str:
        with self._lock:
            return "\n".join(line for _, line in self.lines)

    def seen(self, pattern: str, after: float = -1.0) -> float | None:
        """The time of the first line read after ``after`` that contains ``pattern``."""
        with self._lock:
            return next((t for t, line in self.lines if t > after and pattern in line), None)

    def wait_for(self, pattern: str, after: float = -1.0, timeout: float = WAIT_S) -> float:
        """Wait for a line containing ``pattern`` read after ``after``; its time. Fails
        (with the process's stderr) on the timeout or if the process ends first."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            t = self.seen(pattern, after)
            if t is not None:
                return t
            if self.process.poll() is not None:
                self._reader.join(5)
                t = self.seen(pattern, after)
                if t is not None:
                    return t
                break
            time.sleep(0.02)
        raise AssertionError(f"facewire {self.args[0]}: no {pattern!r} (exit "
                             f"{self.process.poll()}):\n{self.text()[-3000:]}")

    def interrupt(self) -> None:
        """Ctrl-C: a clean stop, with the summary."""
        self.process.send_signal(signal.SIGINT)

    def kill(self) -> None:
        """SIGKILL: no clean-up of any kind."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(WAIT_S)
        self._reader.join(5)

    def summary(self, timeout: float = WAIT_S) -> dict[str, Any]:
        """The ``--json`` summary, once the process has ended with status 0."""
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"facewire {self.args[0]} did not end:\n"
                                 f"{self.text()[-3000:]}") from None
        self._reader.join(5)
        out = self.process.stdout.read().decode()
        err = self.text()
        assert self.process.returncode == 0, err[-3000:]
        assert "Traceback" not in err, err[-3000:]
        return json.loads(out.strip().splitlines()[-1])

    def close(self) -> None:
        """Kill the process if it still runs (a failed test), and close its pipes."""
        if self.process.poll() is None:
            self.kill()
        self._reader.join(5)
        self.process.stdout.close()
        self.process.stderr.close()
