"""``facewire bench speed``'s live part: end-to-end latency and resident memory on loopback.

A real sender process (``facewire send --source VIDEO --loop --record LOG``, bound to free
ports on 127.0.0.1, BLAS pinned to one thread) and a real receiver
(``receiver.receiver.receive`` in this process, at ``size``, with a view callback, so that it
plays live as ``facewire receive --view`` does) run side by side for ``seconds`` of played
frames, through real ZeroMQ sockets; both share this machine's cores.

Latency. For each frame played from a packet (live status "received"), the time the view
callback gets it (rendered and read back) minus the time the sender published the packet
with that sequence number (its log's record, the latest one before the render: the log is
long enough for the 16-bit numbers to wrap only after 36 minutes). Both are ``time.time()``
on this machine. Frames of the first ``SETTLE_S`` are left out (the sender's first frames
come while it warms up). ``latency_ms_median`` and ``latency_ms_p95``; the target is a
median of 25 ms or less.

Glass-to-glass. ``glass_to_glass_ms_median`` and ``glass_to_glass_ms_p95`` are the
receiver's own (``receiver.receiver``: a frame's capture at the sender, from the Hello's
clock and the packet's seq, to its frame out, the clocks aligned over the control channel,
``protocol.clock``), over the receiver's last ``receiver.scene.STATS_FRAMES`` played frames;
``clock_offset_ms`` and ``clock_delay_ms`` are its estimate of the sender's clock (both
processes read this host's monotonic clock, so the offset is 0 give or take half the
delay).

Memory. The resident set size (``VmRSS`` of ``/proc/PID/status``) of the sender process and
of this process (the receiver's) every ``SAMPLE_S``. The growth is the median of the last
``WINDOW`` samples minus the median of the first ``WINDOW`` samples after ``warm-up =
min(WARMUP_S, seconds / 3)``; the target is under 10 MB. This process also holds what the
rest of the benchmark loaded, which does not change during the run.
"""

from __future__ import annotations

import bisect
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from facewire.bench.procfs import ProcessGone, rss_mb
from facewire.protocol.errors import FacewireError
from facewire.protocol.log import read_log
from facewire.protocol.transport import free_loopback_endpoint
from facewire.receiver.receiver import receive

SETTLE_S = 1.0
SAMPLE_S = 0.5
WARMUP_S = 10.0
WINDOW = 5
START_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 30.0
TARGET_LATENCY_MS = 25.0
TARGET_GROWTH_MB = 10.0


class LoopbackError(FacewireError, RuntimeError):
    """The loopback run could not be made: the sender or the receiver failed (says which)."""


def measure_loopback(model_path: str | os.PathLike[str], source: str | os.PathLike[str],
                     seconds: float, size: tuple[int, int] = (640, 480)) -> dict[str, Any]:
    """Run a real sender process and a receiver for ``seconds`` (module docstring).

    Args:
        model_path: the person model (``.fwm``) for both sides.
        source: the sender's video, looped.
        seconds: how long to play, s, counted from the first frame rendered; > 0.
        size: the receiver's rendering size, (width, height).

    Returns:
        ``latency_ms_median``, ``latency_ms_p95``, ``latency_frames`` (frames timed),
        ``glass_to_glass_ms_median``, ``glass_to_glass_ms_p95``, ``clock_offset_ms``,
        ``clock_delay_ms``,
        ``loopback_s``, ``sender_rss_mb``, ``sender_rss_growth_mb``, ``receiver_rss_mb``,
        ``receiver_rss_growth_mb`` (None when the run was too short for two windows), and
        ``loopback`` (the receiver's counts: received, lost, late, skipped, restarts).

    Raises:
        ValueError: ``seconds`` is not > 0.
        LoopbackError: the sender exited early, nothing was played within
            ``START_TIMEOUT_S``, or the receiver failed.
    """
    if not seconds > 0:
        raise ValueError(f"seconds: expected a number > 0, got {seconds!r}")
    endpoint = free_loopback_endpoint()
    with tempfile.TemporaryDirectory(prefix="facewire-loopback-") as tmp:
        log_path, err_path = Path(tmp) / "sent.fwlog", Path(tmp) / "sender.err"
        with open(err_path, "w") as err:
            sender = subprocess.Popen(
                [sys.executable, "-m", "facewire.cli", "send", "--model", str(model_path),
                 "--source", str(source), "--bind", endpoint, "--record", str(log_path),
                 "--loop"], stdout=subprocess.DEVNULL, stderr=err,
                env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        try:
            shown, samples, summary = _play(endpoint, model_path, sender, seconds, size,
                                            err_path)
        finally:
            _stop(sender)
        sent = read_log(log_path)
    published: dict[int, list[float]] = {}
    for seq, t in zip(sent.frames["seq"].tolist(), sent.times.tolist()):
        published.setdefault(int(seq), []).append(float(t))
    first = shown[0][1] if shown else 0.0
    latencies = []
    for seq, t in shown:
        times = published.get(seq, [])
        i = bisect.bisect_right(times, t)
        if i and t - first >= SETTLE_S:
            latencies.append((t - times[i - 1]) * 1000)
    lat = np.asarray(latencies)
    warm = min(WARMUP_S, seconds / 3)
    return {
        "latency_ms_median": round(float(np.median(lat)), 2) if len(lat) else None,
        "latency_ms_p95": round(float(np.percentile(lat, 95)), 2) if len(lat) else None,
        "latency_frames": len(lat),
        **{k: summary.get(k) for k in ("glass_to_glass_ms_median", "glass_to_glass_ms_p95",
                                       "clock_offset_ms", "clock_delay_ms")},
        "loopback_s": round(seconds, 1),
        **_memory("sender", [(t, s) for t, s, _ in samples], warm),
        **_memory("receiver", [(t, r) for t, _, r in samples], warm),
        "loopback": {k: summary.get(k) for k in ("received", "lost", "late", "skipped",
                                                 "restarts", "corrupt")},
    }


def _play(endpoint: str, model_path: str | os.PathLike[str], sender: subprocess.Popen,
          seconds: float, size: tuple[int, int], err_path: Path
          ) -> tuple[list[tuple[int, float]], list[tuple[float, float, float]], dict]:
    """The receiver on a thread, sampled from this one: the frames shown (seq, time), the
    memory samples (time since the first frame, sender MB, receiver MB) and the summary."""
    shown: list[tuple[int, float]] = []
    stop = threading.Event()
    result: dict[str, Any] = {}

    def view(frame: np.ndarray, stats: dict[str, Any]) -> None:
        if stats["state"] == "received":
            shown.append((stats["seq"], time.time()))

    def run() -> None:
        try:
            result.update(receive(endpoint, model_path, view=view, size=size, stop=stop))
        except Exception as exc:  # noqa: BLE001 - reported below, with the sender's stderr
            result["error"] = exc

    thread = threading.Thread(target=run, name="facewire loopback receiver", daemon=True)
    thread.start()
    samples: list[tuple[float, float, float]] = []
    start = time.monotonic()
    began: float | None = None
    try:
        while True:
            time.sleep(SAMPLE_S)
            if "error" in result or not thread.is_alive():
                raise LoopbackError(f"the receiver failed: {result.get('error')}")
            if sender.poll() is not None:
                raise LoopbackError(f"the sender exited ({sender.returncode}): "
                                    f"{_tail(err_path)}")
            if began is None:
                if shown:
                    began = time.monotonic()
                elif time.monotonic() - start > START_TIMEOUT_S:
                    raise LoopbackError(f"no frame played within {START_TIMEOUT_S:g} s; "
                                        f"the sender says: {_tail(err_path)}")
                continue
            now = time.monotonic() - began
            samples.append((now, _rss_mb(sender.pid), _rss_mb(os.getpid())))
            if now >= seconds:
                break
    finally:
        stop.set()
        thread.join()
    if "error" in result:
        raise LoopbackError(f"the receiver failed: {result['error']}")
    return shown, samples, result


def _memory(name: str, samples: list[tuple[float, float]], warm: float) -> dict[str, Any]:
    after = [mb for t, mb in samples if t >= warm]
    growth = None
    if len(after) >= 2 * WINDOW:
        growth = round(float(np.median(after[-WINDOW:]) - np.median(after[:WINDOW])), 2)
    return {f"{name}_rss_mb": round(samples[-1][1], 1) if samples else None,
            f"{name}_rss_growth_mb": growth}


def _rss_mb(pid: int) -> float:
    """The resident set size of a process, MB; nan when it has gone."""
    try:
        return rss_mb(pid)
    except ProcessGone:
        return float("nan")


def _stop(sender: subprocess.Popen) -> None:
    """Ctrl-C the sender (its log is then complete), killed if it does not end in time."""
    if sender.poll() is None:
        sender.send_signal(signal.SIGINT)
        try:
            sender.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            sender.kill()
            sender.wait()


def _tail(path: Path, lines: int = 5) -> str:
    text = path.read_text(errors="replace").strip().splitlines() if path.exists() else []
    return " | ".join(text[-lines:]) or "(nothing on stderr)"
