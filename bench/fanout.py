"""``facewire bench fanout``: one sender's stream fanned out to N viewers, measured.

The chain, all real and on 127.0.0.1:

```
log sender ──> facewire relay ──> facewire web ──> N WebSocket viewers  (websocket runs)
 (this process)  (a process)   └─> N ZeroMQ SUB viewers                 (zmq runs)
```

- The sender (``LogSender``, a thread of this process): the packets of a real packet log
  (``--log``, or ``--source`` encoded first with the model by ``sender.pipeline.
  encode_video``, as ``facewire encode`` does), in order and cycling, renumbered 0, 1, ...
  (``seq`` modulo 2^16) and published at the log's rate on the real ``PacketPublisher``;
  the real control side (``sender.responder.Responder``) answers the Hello and the model's
  and the log's updates' chunks (an update is issued when the stream first passes its place
  in the log). The sender stamps each packet's send time (``time.monotonic()``) by its
  running number.
- ``facewire relay --in SENDER --out RELAY`` and ``facewire web --connect RELAY --http
  127.0.0.1:PORT``, each its own process (so that their CPU time is theirs alone).
- The viewers (``bench.viewers``), in processes of their own, at most ``PER_PROCESS`` each:
  N WebSocket clients of the gateway's ``/stream``, or N ZeroMQ SUB sockets connected to the
  relay's out, each recording every packet's arrival time.

One run (kind, N): start the viewers; once every one has a packet, wait ``SETTLE_S``, then
measure a window of ``seconds``: the packets sent in it (numbers k0 .. k1 - 1, ``expected``
= k1 - k0) and the measured process's CPU time (utime + stime of ``/proc/PID/stat``: the
gateway for WebSocket, the relay for ZeroMQ) and, at its end, its resident set (``VmRSS``);
then the viewers stop once each has the window's last packet, or after ``DRAIN_S`` (a packet
not there by then is lost). For each viewer, ``delivered``
is the number of distinct window packets it received (a packet's number is known from its
16-bit seq and k0: the window is far shorter than the 36 min it takes to wrap); ``lost`` =
N * expected - delivered, summed over the viewers. Added latency: arrival minus send time of
every window packet delivered, all viewers pooled, median and 95th percentile, in ms; it
includes the relay's hop, the gateway's (WebSocket) and the viewer process's own scheduling,
on a machine whose cores the viewers share with the relay and the gateway. ``cpu_percent``
is CPU seconds per wall second of the window, in percent of one core.

Then, unless ``page`` is false, the page run (``bench.pageview``): no viewer but one headless
Chromium showing the gateway's own page (``http://127.0.0.1:PORT/``) for ``PAGE_SECONDS``
(or ``seconds`` if shorter), so that its frame rate is the page's rather than that of a
machine busy with a thousand viewer clients; its ``page`` object holds the frames drawn per
second, the page's own frame time, latency and loss, the canvas size. Without Chromium on
PATH ``page`` is null and the reason is given (a status line and a report line): the
fan-out runs do not need it, and CI installs it.

Targets (issue 18), judged at the largest N: WebSocket, nothing lost, p95 <= 50 ms, the
gateway below one core; ZeroMQ, nothing lost, p95 <= 20 ms. They inform: a miss is reported,
not an error (the machine is shared). The page: >= 30 fps at 640 x 480, judged on its frame
time (``bench.pageview``).
"""

from __future__ import annotations

import hashlib
import math
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import IO, Any

import numpy as np

from facewire.bench.chromium import ChromiumMissing
from facewire.bench.pageview import measure_page
from facewire.bench.procfs import cpu_seconds, rss_mb, wait_seconds
from facewire.bench.viewers import raise_fd_limit
from facewire.protocol.control import model_chunks
from facewire.protocol.errors import FacewireError
from facewire.protocol.log import PacketLog, read_log
from facewire.protocol.packet import SEQ_MODULO, encode_frames
from facewire.protocol.transport import (
    ControlServer,
    PacketPublisher,
    control_endpoint,
    free_loopback_endpoint,
)
from facewire.receiver.gateway import TOKEN_ENV, new_token
from facewire.sender.responder import Responder
from facewire.sender.updates import UpdateStore

DEFAULT_VIEWERS = (10, 100, 1000)
DEFAULT_SECONDS = 10.0
MAX_SECONDS = 600.0  # a window far shorter than the seq's wrap (65536 / 30 Hz = 36 min)
MAX_VIEWERS = 5000
PER_PROCESS = 500  # viewers per viewer process
SETTLE_S = 1.0
DRAIN_S = 10.0  # at most, after the window, for the last arrivals
JOIN_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 30.0
GATEWAY_TIMEOUT_S = 60.0
PAUSE_S = 3.0  # between runs: the server lets the last run's connections go
PAGE_SECONDS = 5.0  # the page run's window, at most
KINDS = ("websocket", "zmq")
TARGETS = {"websocket": {"lost": 0, "latency_ms_p95": 50.0, "cpu_percent": 100.0},
           "zmq": {"lost": 0, "latency_ms_p95": 20.0}}
RESULT_KEYS = ("viewers", "delivered", "lost", "latency_ms_median", "latency_ms_p95",
               "cpu_percent", "rss_mb")

Status = Callable[[str], None]


class FanoutError(FacewireError, RuntimeError):
    """The fan-out run could not be made: a bad argument, a log of another model, or a part
    (relay, gateway, viewers) that failed (the message says which, with its stderr)."""


class LogSender(threading.Thread):
    """A real log's packets published at its rate, with the real control side (module
    docstring); ``stop()`` ends it and closes its sockets.

    Attributes:
        endpoint: the packet endpoint (control on the next port).
        times: send time (``time.monotonic()``) of packet k, in order; ``len`` is the count.
    """

    def __init__(self, log: PacketLog, model: bytes) -> None:
        super().__init__(name="facewire-fanout-sender", daemon=True)
        hello = log.hello
        frames = log.frames[np.arange(SEQ_MODULO) % len(log.frames)]
        frames["seq"] = np.arange(SEQ_MODULO)
        self.packets, _ = encode_frames(frames)
        self.period = 1.0 / hello.rate_hz
        self.updates = sorted(log.updates, key=lambda u: u.serial)
        self.times: list[float] = []
        self._halt = threading.Event()
        self.endpoint = free_loopback_endpoint()
        self._pub = PacketPublisher(self.endpoint)
        self._control = ControlServer(control_endpoint(self.endpoint))
        self._store = UpdateStore(hello.model_sha256)
        self._responder = Responder(self._control, hello,
                                    model_chunks(model, hello.model_sha256), self._store)

    def run(self) -> None:
        self._responder.start()
        next_t = time.monotonic()
        k = 0
        while not self._halt.is_set():
            while self.updates and self.updates[0].before <= k:
                update = self.updates.pop(0)
                self._store.publish_update(update.serial, update.data)
            wait = next_t - time.monotonic()
            if wait > 0 and self._halt.wait(wait):
                break
            self.times.append(time.monotonic())
            self._pub.send(self.packets[k % SEQ_MODULO].tobytes())
            k += 1
            next_t += self.period

    def stop(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join()
        self._responder.stop()
        self._pub.close()
        self._control.close()


class _Process:
    """A child process with its stderr in a file, stopped by SIGINT (killed if stuck)."""

    def __init__(self, args: list[str], name: str, folder: Path,
                 stdio: bool = False, env: dict[str, str] | None = None) -> None:
        self.name = name
        self.err_path = folder / f"{name}.err"
        with open(self.err_path, "w") as err:
            self.popen = subprocess.Popen(
                [sys.executable, *args], stderr=err,
                stdin=subprocess.PIPE if stdio else subprocess.DEVNULL,
                stdout=subprocess.PIPE if stdio else subprocess.DEVNULL,
                text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})})

    def check(self) -> None:
        """Raise ``FanoutError`` if the process has exited."""
        if self.popen.poll() is not None:
            raise FanoutError(f"{self.name} exited ({self.popen.returncode}): {self.tail()}")

    def tail(self, lines: int = 5) -> str:
        text = self.err_path.read_text(errors="replace").strip().splitlines()
        return " | ".join(text[-lines:]) or "(nothing on stderr)"

    def line(self, deadline: float) -> str:
        """The next line on its stdout, waiting until ``deadline`` (monotonic)."""
        out: IO[str] = self.popen.stdout  # type: ignore[assignment]
        while time.monotonic() < deadline:
            if select.select([out], [], [], 0.2)[0]:
                line = out.readline()
                if line:
                    return line.strip()
                self.popen.wait()
                raise FanoutError(f"{self.name} exited ({self.popen.returncode}): "
                                  f"{self.tail()}")
        raise FanoutError(f"{self.name}: no answer in time; it says: {self.tail()}")

    def tell(self, line: str) -> None:
        stdin: IO[str] = self.popen.stdin  # type: ignore[assignment]
        stdin.write(line + "\n")
        stdin.flush()

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()


def _free_port() -> int:
    return int(free_loopback_endpoint().rsplit(":", 1)[1])


def _wait_listening(port: int, process: _Process) -> None:
    """Wait until something accepts TCP connections on 127.0.0.1:port."""
    deadline = time.monotonic() + GATEWAY_TIMEOUT_S
    while time.monotonic() < deadline:
        process.check()
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise FanoutError(f"{process.name}: not listening on port {port} after "
                      f"{GATEWAY_TIMEOUT_S:g} s; it says: {process.tail()}")


def measure_run(kind: str, n: int, target: str, pid: int, sender: LogSender,
                seconds: float, folder: Path) -> dict[str, Any]:
    """One run: N viewers of ``kind`` on ``target``, the CPU and memory of process ``pid``
    measured (module docstring).

    Returns:
        ``kind``, ``viewers``, ``processes`` (viewer processes), ``expected`` (packets sent
        in the window), ``delivered``, ``lost``, ``closed`` (viewers whose connection ended
        early), ``retries`` (WebSocket handshakes made again while joining),
        ``latency_ms_median``, ``latency_ms_p95``, ``cpu_percent``, ``rss_mb`` (of
        process ``pid``), ``viewers_cpu_percent`` (the viewer processes' CPU, summed),
        ``wait_percent`` and ``viewers_wait_percent`` (their threads' time ready to run but
        waiting for a core: how much the machine's other load held them up), ``seconds``
        (the window).
    """
    sizes = [len(part) for part in np.array_split(np.arange(n), math.ceil(n / PER_PROCESS))]
    outs = [folder / f"{kind}-{n}-{i}.npz" for i in range(len(sizes))]
    with ExitStack() as stack:
        viewers = []
        for i, (size, out) in enumerate(zip(sizes, outs)):
            v = _Process(["-m", "facewire.bench.viewers", kind, target, str(size), str(out)],
                         f"{kind} viewers {i + 1}", folder, stdio=True)
            stack.callback(v.stop)
            viewers.append(v)
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        for v in viewers:
            if (line := v.line(deadline)) != "ready":
                raise FanoutError(f"{v.name}: {line}")
        time.sleep(SETTLE_S)
        pids = [pid, *(v.popen.pid for v in viewers)]
        k0, t0 = len(sender.times), time.monotonic()
        cpu0, wait0 = [cpu_seconds(p) for p in pids], [wait_seconds(p) for p in pids]
        time.sleep(seconds)
        k1, t1 = len(sender.times), time.monotonic()
        cpu1, wait1 = [cpu_seconds(p) for p in pids], [wait_seconds(p) for p in pids]
        rss = rss_mb(pid)
        for v in viewers:
            v.tell(f"stop {(k1 - 1) % SEQ_MODULO} {DRAIN_S}")
        for v in viewers:
            if (line := v.line(time.monotonic() + DRAIN_S + STOP_TIMEOUT_S)) != "done":
                raise FanoutError(f"{v.name}: {line}")
    sent = np.asarray(sender.times[k0:k1])
    expected = k1 - k0
    delivered, closed, retries, latencies = 0, 0, 0, []
    for out in outs:
        with np.load(out, allow_pickle=False) as data:
            viewer, seq, arrival = data["viewer"], data["seq"], data["arrival"]
            closed += int(data["closed"].sum())
            retries += int(data["retries"].sum())
        offset = (seq - k0) % SEQ_MODULO
        keep = (seq >= 0) & (offset < expected)
        key = viewer[keep].astype(np.int64) * SEQ_MODULO + offset[keep]
        _, first = np.unique(key, return_index=True)
        delivered += len(first)
        latencies.append((arrival[keep][first] - sent[offset[keep][first]]) * 1000)
    lat = np.concatenate(latencies)
    return {"kind": kind, "viewers": n, "processes": len(sizes), "expected": expected,
            "delivered": delivered, "lost": n * expected - delivered, "closed": closed,
            "retries": retries,
            "latency_ms_median": round(float(np.median(lat)), 2) if len(lat) else None,
            "latency_ms_p95": round(float(np.percentile(lat, 95)), 2) if len(lat) else None,
            "cpu_percent": round(100 * (cpu1[0] - cpu0[0]) / (t1 - t0), 1),
            "viewers_cpu_percent": round(100 * (sum(cpu1[1:]) - sum(cpu0[1:])) / (t1 - t0), 1),
            "wait_percent": round(100 * (wait1[0] - wait0[0]) / (t1 - t0), 1),
            "viewers_wait_percent": round(100 * (sum(wait1[1:]) - sum(wait0[1:])) / (t1 - t0),
                                          1),
            "rss_mb": round(rss, 1), "seconds": round(t1 - t0, 2)}


def _read_inputs(model_path: str | os.PathLike[str], source: str | os.PathLike[str] | None,
                 log_path: str | os.PathLike[str] | None, folder: Path,
                 status: Status) -> tuple[PacketLog, bytes]:
    """The packet log (read, or ``source`` encoded with the model) and the model's bytes."""
    from facewire.models.modelfile import load_model
    from facewire.sender.pipeline import encode_video

    load_model(model_path)  # validates the file, names it when it is bad
    model = Path(model_path).read_bytes()
    if log_path is None:
        if source is None:
            raise FanoutError("fanout: give a source video or a packet log")
        log_path = folder / "source.fwlog"
        status(f"encoding {os.fspath(source)} with {os.fspath(model_path)}")
        encode_video(model_path, source, log_path)
    log = read_log(log_path)
    if not len(log.frames):
        raise FanoutError(f"{os.fspath(log_path)}: the log holds no packet")
    if log.hello.model_sha256 != hashlib.sha256(model).hexdigest():
        raise FanoutError(f"{os.fspath(log_path)}: hello.model_sha256 is "
                          f"{log.hello.model_sha256}, not the sha256 of "
                          f"{os.fspath(model_path)}")
    return log, model


def measure_fanout(model_path: str | os.PathLike[str], source: str | os.PathLike[str] | None = None,
                   viewers: Sequence[int] = DEFAULT_VIEWERS, seconds: float = DEFAULT_SECONDS,
                   log_path: str | os.PathLike[str] | None = None,
                   status: Status = lambda _: None, page: bool = True) -> dict[str, Any]:
    """Fan one sender out to each N of ``viewers`` over WebSocket and over ZeroMQ (module
    docstring).

    Args:
        model_path: the person model (``.fwm``) the stream is of.
        source: a video to encode with the model into the log (unless ``log_path``).
        viewers: the N to run, each > 0.
        seconds: each run's measured window, s, in (0, ``MAX_SECONDS``].
        log_path: a packet log of the model to send instead of encoding ``source``.
        status: called with a line of progress.
        page: whether to make the page run (module docstring).

    Returns:
        ``runs``: every run (``measure_run``), in order; ``websocket`` and ``zmq``: the
        ``RESULT_KEYS`` of the largest N's runs; ``targets``: per kind, ``met`` and the
        thresholds; ``rate_hz``, ``seconds``, ``log_packets``; ``page``: the page run's
        ``bench.pageview.measure_page`` result, or None (not asked for, or no Chromium:
        ``page_skipped`` says why).

    Raises:
        FanoutError: a bad argument, a log of another model, or a part that failed.
        ModelFileError, LogError, CaptureError: a bad model, log or video (names it).
    """
    if not viewers or any(not 0 < n <= MAX_VIEWERS for n in viewers):
        raise FanoutError(f"--viewers: each must be in 1..{MAX_VIEWERS}, got {list(viewers)}")
    if not 0 < seconds <= MAX_SECONDS:
        raise FanoutError(f"--seconds: must be in (0, {MAX_SECONDS:g}], got {seconds:g}")
    limit = raise_fd_limit()
    if 3 * max(viewers) + 256 > limit:
        raise FanoutError(f"--viewers: {max(viewers)} viewers need about "
                          f"{3 * max(viewers) + 256} open files; the limit is {limit}")
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="facewire-fanout-") as tmp, ExitStack() as stack:
        folder = Path(tmp)
        log, model = _read_inputs(model_path, source, log_path, folder, status)
        sender = LogSender(log, model)
        stack.callback(sender.stop)
        sender.start()
        relay_out, port = free_loopback_endpoint(), _free_port()
        relay = _Process(["-m", "facewire.cli", "relay", "--in", sender.endpoint, "--out",
                          relay_out], "relay", folder)
        stack.callback(relay.stop)
        token = new_token()
        gateway = _Process(["-m", "facewire.cli", "web", "--connect", relay_out, "--http",
                            f"127.0.0.1:{port}"], "gateway", folder, env={TOKEN_ENV: token})
        stack.callback(gateway.stop)
        _wait_listening(port, gateway)
        targets = {"websocket": (f"ws://127.0.0.1:{port}/stream?token={token}", gateway),
                   "zmq": (relay_out, relay)}
        for n, kind in ((n, kind) for n in viewers for kind in KINDS):
            if runs:
                time.sleep(PAUSE_S)
            status(f"{kind}: {n} viewers, {seconds:g} s")
            target, measured = targets[kind]
            measured.check()
            runs.append(measure_run(kind, n, target, measured.popen.pid, sender, seconds,
                                    folder))
            status(format_run(runs[-1]))
        page_result: dict[str, Any] | None = None
        skipped = None if page else "not asked for (--no-page)"
        if page:
            time.sleep(PAUSE_S)
            page_seconds = min(seconds, PAGE_SECONDS)
            status(f"page: the gateway's page in headless Chromium, {page_seconds:g} s")
            gateway.check()
            try:
                page_result = measure_page(f"http://127.0.0.1:{port}/?token={token}",
                                           page_seconds, folder)
                status(format_page(page_result))
            except ChromiumMissing as missing:
                skipped = str(missing)
                status(f"page: skipped: {skipped}")
    largest = {kind: next(r for r in reversed(runs) if r["kind"] == kind) for kind in KINDS}
    return {"runs": runs, "rate_hz": log.hello.rate_hz, "seconds": seconds,
            "log_packets": len(log.frames), "page": page_result, "page_skipped": skipped,
            **{kind: {k: largest[kind][k] for k in RESULT_KEYS} for kind in KINDS},
            "targets": {kind: {"viewers": largest[kind]["viewers"], **TARGETS[kind],
                               "met": _met(largest[kind])} for kind in KINDS}}


def _met(run: dict[str, Any]) -> bool:
    target = TARGETS[run["kind"]]
    p95 = run["latency_ms_p95"]
    return (run["lost"] <= target["lost"] and p95 is not None
            and p95 <= target["latency_ms_p95"]
            and run["cpu_percent"] < target.get("cpu_percent", math.inf))


def format_page(page: dict[str, Any]) -> str:
    """The page run in one line."""
    return (f"page {page['width']} x {page['height']}: {page['fps']} fps drawn, frame time "
            f"{page['frame_ms_median']} ms (median), latency {page['latency_ms']} ms, loss "
            f"{page['loss_pct']} % over {page['seconds']} s")


def format_run(run: dict[str, Any]) -> str:
    """One run as a row of the table."""
    return (f"{run['kind']:<9} {run['viewers']:>6} {run['expected']:>8} {run['delivered']:>10} "
            f"{run['lost']:>6} {run['closed']:>6} {run['latency_ms_median']!s:>8} "
            f"{run['latency_ms_p95']!s:>8} {run['cpu_percent']:>6} {run['rss_mb']:>7} "
            f"{run['viewers_cpu_percent']:>9} {run['wait_percent']:>6} "
            f"{run['viewers_wait_percent']:>8}")


HEADER = (f"{'kind':<9} {'N':>6} {'expected':>8} {'delivered':>10} {'lost':>6} {'closed':>6} "
          f"{'med ms':>8} {'p95 ms':>8} {'cpu %':>6} {'rss MB':>7} {'viewers %':>9} "
          f"{'wait %':>6} {'v wait %':>8}")


def fanout(model_path: str | os.PathLike[str], source: str | os.PathLike[str] | None = None,
           viewers: Sequence[int] = DEFAULT_VIEWERS, seconds: float = DEFAULT_SECONDS,
           log_path: str | os.PathLike[str] | None = None,
           status: Status = lambda _: None, page: bool = True
           ) -> tuple[dict[str, Any], list[str]]:
    """Run ``measure_fanout``: its result and the report's lines (the table, the page run,
    then the targets: a miss informs, it is no failure)."""
    result = measure_fanout(model_path, source, viewers, seconds, log_path, status, page)
    lines = [f"{result['rate_hz']:g} Hz; each run {seconds:g} s; expected is per viewer; "
             f"cpu, rss and wait (ready to run, waiting for a core): the gateway (websocket), "
             f"the relay (zmq); viewers %, v wait %: the viewer processes'", HEADER,
             *(format_run(r) for r in result["runs"])]
    for kind, t in result["targets"].items():
        limits = f"nothing lost, p95 <= {t['latency_ms_p95']:g} ms" + (
            f", below {t['cpu_percent']:g} % of a core" if "cpu_percent" in t else "")
        lines.append(f"target {kind} at N={t['viewers']} ({limits}): "
                     f"{'met' if t['met'] else 'MISSED'}")
    if (shown := result["page"]) is None:
        lines.append(f"page: none ({result['page_skipped']})")
    else:
        lines.insert(-len(result["targets"]), format_page(shown))
        lines.append(f"target page at {shown['width']}x{shown['height']} >= "
                     f"{shown['target_fps']:g} fps (1000 / its frame time): "
                     f"{'met' if shown['met'] else 'MISSED'}")
    return result, lines
