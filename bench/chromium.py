"""Headless Chromium, found on PATH and driven over DevTools: the bench's page viewer and the
browser tests use it.

Chromium is driven through the DevTools protocol over ``--remote-debugging-pipe`` (JSON
messages ending in a NUL byte on the browser's file descriptors 3 and 4): no websocket client
and no new dependency. ``WEBGL_FLAGS`` give a page WebGL2 through Chromium's software
renderer (SwiftShader, through ANGLE), as on a machine with no GPU.

Chromium is found as ``chromium`` or ``chromium-browser`` on PATH (``install.sh`` installs it
when apt has it, and says how to get one when not); without it ``chromium_binary`` raises
``ChromiumMissing`` saying so.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import shutil
import signal
import time
from pathlib import Path
from typing import Any

from facewire.protocol.errors import FacewireError

CHROMIUM_NAMES = ("chromium", "chromium-browser")
WEBGL_FLAGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")


class ChromiumMissing(FacewireError, FileNotFoundError):
    """No Chromium binary on PATH (the message says how to get one)."""


def chromium_binary() -> str:
    """The path of the Chromium binary on PATH.

    Raises:
        ChromiumMissing: there is none.
    """
    for name in CHROMIUM_NAMES:
        if path := shutil.which(name):
            return path
    raise ChromiumMissing(
        f"headless Chromium not found (looked for {' and '.join(CHROMIUM_NAMES)} on PATH): "
        f"./install.sh installs it where apt has it (Debian: apt-get install -y chromium); on "
        f"Ubuntu chromium is a snap, which a container cannot run: put a Chromium or Chrome on "
        f"PATH under one of those names")


class DevTools:
    """Headless Chromium driven over ``--remote-debugging-pipe``: the browser reads commands
    on its fd 3 and writes replies and events on its fd 4, each a JSON text ending in NUL."""

    def __init__(self, binary: str, profile: Path, log: Path,
                 extra_flags: tuple[str, ...] = ()) -> None:
        commands_r, self._commands = os.pipe()
        self._replies, replies_w = os.pipe()
        # above 9, so that placing them at 3 and 4 cannot overwrite each other
        child = [fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (commands_r, replies_w)]
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--remote-debugging-pipe", f"--user-data-dir={profile}", "--no-first-run",
                 "--no-default-browser-check", "--disable-extensions", "--mute-audio",
                 "--autoplay-policy=no-user-gesture-required",
                 *extra_flags, "about:blank"]
        self.pid = os.posix_spawn(binary, [binary, *flags], os.environ, setsid=True,
                                  file_actions=[
                                      (os.POSIX_SPAWN_DUP2, child[0], 3),
                                      (os.POSIX_SPAWN_DUP2, child[1], 4),
                                      (os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0),
                                      (os.POSIX_SPAWN_OPEN, 2, str(log),
                                       os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)])
        for fd in (commands_r, replies_w, *child):
            os.close(fd)
        self._next_id = 0
        self._pending = b""
        self.log = log

    def call(self, method: str, params: dict[str, Any] | None = None,
             session: str | None = None, timeout: float = 10.0) -> dict[str, Any]:
        """Send one command and wait for its reply (events in between are dropped)."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        os.write(self._commands, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self._pending:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self._replies], [], [], left)[0]:
                    raise TimeoutError(f"Chromium did not answer {method} within {timeout} s "
                                       f"(its log: {self.log})")
                chunk = os.read(self._replies, 1 << 20)
                if not chunk:
                    raise EOFError(f"Chromium exited (its log: {self.log})")
                self._pending += chunk
            text, self._pending = self._pending.split(b"\0", 1)
            reply = json.loads(text)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def evaluate(self, session: str, expression: str) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                "awaitPromise": True}, session)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=5)
        except (OSError, TimeoutError, RuntimeError):
            pass  # it is killed below
        deadline = time.monotonic() + 5
        while os.waitpid(self.pid, os.WNOHANG) == (0, 0) and time.monotonic() < deadline:
            time.sleep(0.05)
        try:
            os.killpg(self.pid, signal.SIGKILL)  # the group started for this browser only
            os.waitpid(self.pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass  # it exited and was reaped
        os.close(self._commands)
        os.close(self._replies)


def open_tab(browser: DevTools, url: str, ready: str = "true", timeout: float = 30.0) -> str:
    """Open ``url`` in a new tab of ``browser``; its DevTools session id once the expression
    ``ready`` evaluates true there (``TimeoutError`` naming the last value otherwise)."""
    target = browser.call("Target.createTarget", {"url": url})["targetId"]
    session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})[
        "sessionId"]
    deadline = time.monotonic() + timeout
    value: Any = None
    while time.monotonic() < deadline:
        try:
            value = browser.evaluate(session, ready)
        except RuntimeError as error:  # the page's scripts are still loading
            value = error
        if value is True:
            return session
        time.sleep(0.1)
    raise TimeoutError(f"{url}: {ready} still not true after {timeout} s (last: {value!r})")
