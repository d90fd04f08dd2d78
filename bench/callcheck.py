"""``facewire bench call``: a call of some minutes on one machine, two ``facewire call``
processes each sending a clip looped, checked for loss, memory and sync.

Two processes, as a user starts them (``python -m facewire.cli call --loop --json``), side A
publishing at one free loopback port and side B at another, each the other's peer; no keys
(loopback), each fetching the other's model into a cache of the run's own. Every
``SAMPLE_S`` the run reads each process's resident memory (``bench.procfs.rss_mb``) and the
machine's 1-minute load average; after ``seconds`` it hangs both up (SIGINT, Ctrl-C's
hang-up) and reads each side's JSON summary (its last stdout line: ``{"send": ...,
"receive": ...}``).

Judged, per direction (A to B: what A sent, what B received):

- nothing lost on the way: the face's and the voice's packets sent less received
  (``face_missing``, ``voice_missing``; the first ones may leave before the other side
  listens, and the last ones be in flight at the hang-up: at most ``EDGE_FACE`` and
  ``EDGE_VOICE`` are let go), and no voice packet corrupt. What the receiver then could not
  play in time is apart: the playout's ``lost`` slots (a packet later than its slot's
  deadline), the voice's ``late``, ``dropped`` and ``concealed`` frames;
- memory flat: each process's resident memory at the end is within ``RSS_GROWTH_MB`` of the
  first sample taken after ``WARM_S`` (models fetched, renderer up), ``rss_mb_first``, ``_last``,
  ``_max`` and the samples given. Learning (the default) holds each model update learned, at
  the sender and at the other side's receiver, so memory grows until the clip's appearance is
  learned: ``learn=False`` leaves what is left;
- sync held: the receiver's skew over the whole call (``av_skew_ms_p5`` to ``_p95``, its
  ``receiver.voiceplayer`` window holding 10 minutes of frames) inside ITU-R BT.1359's
  -45 to +125 ms.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from facewire.bench.procfs import ProcessGone, rss_mb
from facewire.protocol.errors import FacewireError
from facewire.protocol.transport import free_loopback_endpoint
from facewire.receiver.modelcache import ENV_FOLDER

SAMPLE_S = 10.0
WARM_S = 60.0  # models fetched and renderers up: a loaded machine's call settles by then
RSS_GROWTH_MB = 50.0
EDGE_VOICE = 100  # 2 s of voice at the start and the end
EDGE_FACE = 60  # 2 s of face at 30 Hz
AHEAD_MS, BEHIND_MS = -45.0, 125.0  # ITU-R BT.1359
HANG_UP_S = 120.0  # a side that has not ended this long after its SIGINT is killed

Status = Callable[[str], None]


class CallCheckError(FacewireError, RuntimeError):
    """A side of the call ended early or gave no summary (the message holds its stderr)."""


def _endpoint_pair() -> tuple[str, str]:
    """Two free packet endpoints whose control ports (port + 1) are distinct from them."""
    while True:
        a, b = free_loopback_endpoint(), free_loopback_endpoint()
        pa, pb = (int(e.rsplit(":", 1)[1]) for e in (a, b))
        if abs(pa - pb) > 1:
            return a, b


def call_check(model_a: str | os.PathLike[str], source_a: str,
               model_b: str | os.PathLike[str], source_b: str, seconds: float,
               learn: bool = True, status: Status = lambda _: None
               ) -> tuple[dict[str, Any], list[str]]:
    """The module docstring's call and checks; the summary and its report lines. Without
    ``learn`` both sides run with ``--no-learn``.

    Raises:
        CallCheckError: a side exited before the hang-up or printed no summary.
    """
    bind_a, bind_b = _endpoint_pair()
    sides = {"a": (model_a, source_a, bind_a, bind_b), "b": (model_b, source_b, bind_b, bind_a)}
    samples: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="facewire-callcheck-") as scratch:
        folder = Path(scratch)
        procs: dict[str, subprocess.Popen[bytes]] = {}
        try:
            for name, (model, source, bind, peer) in sides.items():
                with open(folder / f"{name}.out", "wb") as out, \
                        open(folder / f"{name}.err", "wb") as err:
                    procs[name] = subprocess.Popen(
                        [sys.executable, "-m", "facewire.cli", "call", "--model",
                         os.fspath(model), "--source", source, "--bind", bind, "--peer", peer,
                         "--loop", "--json", *([] if learn else ["--no-learn"])],
                        stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                        env={**os.environ, ENV_FOLDER: str(folder / f"cache-{name}")})
            start = time.monotonic()
            while (elapsed := time.monotonic() - start) < seconds:
                for name, proc in procs.items():
                    if proc.poll() is not None:
                        raise CallCheckError(f"side {name} ended after {elapsed:.0f} s "
                                             f"({proc.returncode}): {_tail(folder, name)}")
                sample: dict[str, Any] = {"t_s": round(elapsed, 1),
                                          "load_average": round(os.getloadavg()[0], 1)}
                for name, proc in procs.items():
                    try:
                        sample[f"rss_mb_{name}"] = round(rss_mb(proc.pid), 1)
                    except ProcessGone:
                        sample[f"rss_mb_{name}"] = None
                samples.append(sample)
                status(f"{sample['t_s']:.0f} s: RSS A {sample['rss_mb_a']} MB, B "
                       f"{sample['rss_mb_b']} MB, load {sample['load_average']}")
                time.sleep(min(SAMPLE_S, max(0.0, seconds - elapsed)))
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
            for proc in procs.values():
                try:
                    proc.wait(HANG_UP_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        got = {name: _summary(folder, name) for name in procs}
    return _judge(got["a"], got["b"], samples, seconds, learn)


def _tail(folder: Path, name: str, lines: int = 5) -> str:
    text = (folder / f"{name}.err").read_text(errors="replace").strip().splitlines()
    return " | ".join(text[-lines:]) or "(nothing on stderr)"


def _summary(folder: Path, name: str) -> dict[str, Any]:
    """Side ``name``'s JSON summary: its stdout's last line."""
    lines = (folder / f"{name}.out").read_text(errors="replace").strip().splitlines()
    try:
        summary = json.loads(lines[-1])
    except (IndexError, json.JSONDecodeError):
        raise CallCheckError(f"side {name} printed no summary: {_tail(folder, name)}") from None
    if not isinstance(summary, dict):
        raise CallCheckError(f"side {name}'s summary is not an object: {lines[-1][:200]}")
    return summary


def _direction(sender: dict[str, Any], receiver: dict[str, Any]) -> dict[str, Any]:
    """One direction's counts and verdicts (module docstring)."""
    sent, got = sender.get("send", {}), receiver.get("receive", {})
    missing = sent.get("voice_packets", 0) - got.get("voice_received", 0)
    face_missing = sent.get("packets", 0) - got.get("received", 0)
    p5, p95 = got.get("av_skew_ms_p5"), got.get("av_skew_ms_p95")
    return {
        "frames_sent": sent.get("frames"), "packets_sent": sent.get("packets"),
        "updates_sent": sent.get("updates"), "model_serial": got.get("model_serial"),
        "received": got.get("received"), "face_missing": face_missing,
        "lost": got.get("lost"),
        "voice_sent": sent.get("voice_packets"), "voice_received": got.get("voice_received"),
        "voice_missing": missing, "voice_corrupt": got.get("voice_corrupt"),
        **{f"voice_{k}": got.get(f"voice_{k}") for k in
           ("played", "concealed", "late", "dropped", "stretched", "shrunk", "extra_ms",
            "glass_to_glass_ms_median", "glass_to_glass_ms_p95")},
        "glass_to_glass_ms_median": got.get("glass_to_glass_ms_median"),
        "av_skew_ms_median": got.get("av_skew_ms_median"), "av_skew_ms_p5": p5,
        "av_skew_ms_p95": p95, "ended": got.get("ended"),
        "nothing_lost": 0 <= face_missing <= EDGE_FACE and 0 <= missing <= EDGE_VOICE
        and not got.get("voice_corrupt"),
        "sync_held": p5 is not None and p95 is not None and AHEAD_MS <= p5 and p95 <= BEHIND_MS,
    }


def _judge(a: dict[str, Any], b: dict[str, Any], samples: list[dict[str, Any]],
           seconds: float, learn: bool) -> tuple[dict[str, Any], list[str]]:
    directions = {"a_to_b": _direction(a, b), "b_to_a": _direction(b, a)}
    memory: dict[str, Any] = {}
    for name in ("a", "b"):
        series = [(s["t_s"], s[f"rss_mb_{name}"]) for s in samples
                  if s[f"rss_mb_{name}"] is not None]
        warm = [v for t, v in series if t >= WARM_S] or [v for _, v in series]
        memory[name] = {"rss_mb_first": warm[0] if warm else None,
                        "rss_mb_last": warm[-1] if warm else None,
                        "rss_mb_max": max(warm) if warm else None,
                        "flat": bool(warm) and warm[-1] - warm[0] <= RSS_GROWTH_MB}
    loads = [s["load_average"] for s in samples]
    summary = {"seconds": seconds, "learn": learn, **directions, "memory": memory,
               "samples": samples,
               "load_average_min": min(loads, default=None),
               "load_average_max": max(loads, default=None),
               "passed": all(d["nothing_lost"] and d["sync_held"] for d in directions.values())
               and all(m["flat"] for m in memory.values())}
    lines = [f"{seconds:g} s call, load average {summary['load_average_min']} to "
             f"{summary['load_average_max']}"]
    for key, d in directions.items():
        lines.append(f"{key}: face {d['packets_sent']} sent, {d['received']} received, "
                     f"{d['lost']} slots lost at the playout; voice {d['voice_sent']} sent, "
                     f"{d['voice_received']} received, {d['voice_corrupt']} corrupt, "
                     f"{d['voice_concealed']} concealed; "
                     f"skew {d['av_skew_ms_p5']} to {d['av_skew_ms_p95']} ms (5-95 %), "
                     f"{d['av_skew_ms_median']} median; voice glass-to-glass "
                     f"{d['voice_glass_to_glass_ms_median']} ms median")
    for name, m in memory.items():
        lines.append(f"side {name} RSS: {m['rss_mb_first']} MB after {WARM_S:g} s, "
                     f"{m['rss_mb_last']} MB at the end, {m['rss_mb_max']} MB at most")
    lines.append("passed" if summary["passed"] else "not passed")
    return summary, lines
