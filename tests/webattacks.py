"""Attacks on the receiver's HTTP servers (``facewire web``, ``receive --view``) from raw
sockets, and what they cost the attacked process (``/proc``: resident memory, threads).

``measure(pid, attack, meanwhile)`` samples the process every ``SAMPLE_S`` while ``attack``
holds its connections and calls ``meanwhile`` (a normal client's check) before leaving, then
waits up to ``GIVE_BACK_S`` for the memory to come back; it returns a ``Cost``. The attacks
are functions of the port that open their connections, call ``meanwhile`` while they hold
them, and close them. Shared by ``tests/test_attacks_web.py``; the before/after figures of
docs/DESIGN.md §10 were taken with the same functions.
"""

from __future__ import annotations

import contextlib
import dataclasses
import socket
import struct
import subprocess
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

from facewire.bench.procfs import rss_mb, thread_count

SAMPLE_S = 0.05
GIVE_BACK_S = 5.0
KEPT_MB = 8.0  # what may stay resident once the attackers have left

Meanwhile = Callable[[], None]


@dataclasses.dataclass
class Cost:
    """What an attack cost: MB and threads before, at the peak and after leaving."""

    rss_before: float
    rss_peak: float
    rss_after: float
    threads_before: int
    threads_peak: int
    threads_after: int

    @property
    def rss_rise(self) -> float:
        return self.rss_peak - self.rss_before

    @property
    def thread_rise(self) -> int:
        return self.threads_peak - self.threads_before

    def line(self, name: str) -> str:
        return (f"{name}: RSS {self.rss_before:.0f} -> peak {self.rss_peak:.0f} (+"
                f"{self.rss_rise:.1f}) -> {self.rss_after:.0f} MB after; threads "
                f"{self.threads_before} -> {self.threads_peak} -> {self.threads_after}")


def measure(pid: int, attack: Callable[[Meanwhile], None], meanwhile: Meanwhile) -> Cost:
    """Run ``attack`` against process ``pid`` and measure it (module docstring)."""
    rss0, threads0 = rss_mb(pid), thread_count(pid)
    peak = [rss0, float(threads0)]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(SAMPLE_S):
            with contextlib.suppress(Exception):
                peak[0] = max(peak[0], rss_mb(pid))
                peak[1] = max(peak[1], thread_count(pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        attack(meanwhile)
        deadline = time.monotonic() + GIVE_BACK_S
        while rss_mb(pid) > rss0 + KEPT_MB and time.monotonic() < deadline:
            time.sleep(SAMPLE_S)
    finally:
        done.set()
        sampler.join()
    return Cost(rss0, peak[0], rss_mb(pid), threads0, int(peak[1]), thread_count(pid))


def settle(pid: int, timeout: float = 30.0) -> None:
    """Wait until a process's memory and threads hold still for a second (it has started:
    model fetched, renderer made), so that an attack's cost is the attack's."""
    deadline = time.monotonic() + timeout
    last = (rss_mb(pid), thread_count(pid))
    while time.monotonic() < deadline:
        time.sleep(1.0)
        now = (rss_mb(pid), thread_count(pid))
        if abs(now[0] - last[0]) < 1.0 and now[1] == last[1]:
            return
        last = now
    raise AssertionError(f"process {pid} does not settle: {last[0]:.0f} MB, {last[1]} threads")


def get(url: str, headers: dict[str, str] | None = None,
        timeout: float = 5.0) -> tuple[int, bytes]:
    """GET ``url``: (status, body)."""
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as answer:
            return answer.status, answer.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def raw_request(port: int, head: bytes, timeout: float = 5.0) -> bytes:
    """Send ``head`` on a new connection; what comes back until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(head)
        answer = b""
        with contextlib.suppress(OSError):
            while chunk := sock.recv(65536):
                answer += chunk
        return answer


def _connections(port: int, n: int) -> list[socket.socket]:
    socks = []
    for _ in range(n):
        with contextlib.suppress(OSError):
            socks.append(socket.create_connection(("127.0.0.1", port), timeout=2))
    return socks


def _send_quietly(sock: socket.socket, data: bytes) -> None:
    """Send what the server takes within the socket's timeout (it may close first)."""
    with contextlib.suppress(OSError):
        sock.sendall(data)


def _close(socks: list[socket.socket], reset: bool = False) -> None:
    for sock in socks:
        if reset:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()


def header_flood(port: int, path: str, n: int, headers: int, size: int,
                 hold_s: float) -> Callable[[Meanwhile], None]:
    """``n`` connections sending ``headers`` headers of ``size`` bytes and never the blank
    line that ends them, then trickling a byte each per second for ``hold_s``."""

    def attack(meanwhile: Meanwhile) -> None:
        socks = _connections(port, n)
        head = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n".encode()
        line = b"X-A: " + b"a" * (size - 7) + b"\r\n"
        for sock in socks:
            sock.settimeout(0.05)
            _send_quietly(sock, head + line * headers)
        end = time.monotonic() + hold_s
        while time.monotonic() < end:
            for sock in socks:
                _send_quietly(sock, b"a")
            time.sleep(min(1.0, max(0.0, end - time.monotonic())))
        meanwhile()
        _close(socks)

    return attack


def idle(port: int, n: int, hold_s: float) -> Callable[[Meanwhile], None]:
    """``n`` connections that send nothing, held ``hold_s``."""

    def attack(meanwhile: Meanwhile) -> None:
        socks = _connections(port, n)
        time.sleep(hold_s)
        meanwhile()
        _close(socks)

    return attack


def leave_early(port: int, path: str, n: int) -> Callable[[Meanwhile], None]:
    """``n`` clients that ask for ``path`` and go at once, half with a reset; measured
    2 s after the last."""

    def attack(meanwhile: Meanwhile) -> None:
        for i in range(n):
            with contextlib.suppress(OSError):
                sock = socket.create_connection(("127.0.0.1", port), timeout=2)
                sock.sendall(f"GET {path} HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
                _close([sock], reset=i % 2 == 1)
        time.sleep(2.0)
        meanwhile()

    return attack


def reset_mid_request(port: int, n: int) -> Callable[[Meanwhile], None]:
    """``n`` clients that send half a request and reset the connection."""

    def attack(meanwhile: Meanwhile) -> None:
        for _ in range(n):
            with contextlib.suppress(OSError):
                sock = socket.create_connection(("127.0.0.1", port), timeout=2)
                sock.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-A: a".encode())
                time.sleep(0.01)
                _close([sock], reset=True)
        time.sleep(0.5)
        meanwhile()

    return attack


def guess_tokens(url_without_token: str, seconds: float, workers: int = 8) -> int:
    """Wrong tokens tried for ``seconds`` by ``workers`` clients at once; the answers got."""
    answered = [0]
    end = time.monotonic() + seconds
    lock = threading.Lock()

    def guess(k: int) -> None:
        i = 0
        while time.monotonic() < end:
            i += 1
            with contextlib.suppress(OSError):
                status, _ = get(f"{url_without_token}?token=guess-{k}-{i:012d}",
                                timeout=max(0.1, end - time.monotonic()))
                if status == 403:
                    with lock:
                        answered[0] += 1

    threads = [threading.Thread(target=guess, args=(k,), daemon=True) for k in range(workers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return answered[0]


def tracebacks(err: Path) -> int:
    """How many tracebacks a process's stderr holds."""
    return err.read_text(errors="replace").count("Traceback")


def wait_serving(url: str, popen: subprocess.Popen[bytes], err: Path,
                 timeout: float = 60.0) -> None:
    """Wait until ``url`` answers 200 (the process must stay alive meanwhile)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert popen.poll() is None, err.read_text(errors="replace")
        with contextlib.suppress(OSError):
            if get(url, timeout=2)[0] == 200:
                return
        time.sleep(0.2)
    raise AssertionError(f"{url} does not answer: {err.read_text(errors='replace')}")
