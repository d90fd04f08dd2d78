"""``facewire bench bandwidth``: payload and wire bit rates of a packet log.

payload kbit/s = packet bytes * 8 * rate / 1000, reported at the log's own rate and
normalised to 30 Hz (the contract's ``payload_kbps``). Wire kbit/s adds ZeroMQ's framing per
message (``protocol.transport.WIRE_OVERHEAD``: 2 bytes, 35 under CURVE); TCP/IP headers are
not counted. Every packet has the same size, so the 30 Hz payload rate holds by
construction; the plot shows what the log actually carried, second by second.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facewire.bench.report import report
from facewire.protocol.log import read_log
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.transport import WIRE_OVERHEAD

LIMIT_KBPS = 12.0
NOMINAL_HZ = 30.0


def kbps(message_bytes: float, rate_hz: float) -> float:
    """Bit rate in kbit/s of messages of a given size at a given rate."""
    return message_bytes * 8 * rate_hz / 1000


def bandwidth(log: str | os.PathLike[str], as_json: bool = False,
              plot: str | os.PathLike[str] | None = None) -> int:
    """Measure a log; returns the exit status: 1 when payload >= 12 kbit/s at 30 Hz."""
    data = read_log(log)
    n = len(data.times)
    span = float(data.times[-1] - data.times[0]) if n > 1 else 0.0
    rate = (n - 1) / span if span > 0 else data.hello.rate_hz
    summary = {
        "log": str(log),
        "frames": n,
        "lost_records": data.lost,
        "duration_s": round(span, 3),
        "rate_hz": round(rate, 3),
        "packet_bytes": PACKET_BYTES,
        "payload_kbps": round(kbps(PACKET_BYTES, NOMINAL_HZ), 3),
        "payload_kbps_at_log_rate": round(kbps(PACKET_BYTES, rate), 3),
        "wire_kbps": round(kbps(PACKET_BYTES + WIRE_OVERHEAD["plain"], NOMINAL_HZ), 3),
        "wire_kbps_curve": round(kbps(PACKET_BYTES + WIRE_OVERHEAD["curve"], NOMINAL_HZ), 3),
        "wire_kbps_at_log_rate": round(kbps(PACKET_BYTES + WIRE_OVERHEAD["plain"], rate), 3),
    }
    ok = summary["payload_kbps"] < LIMIT_KBPS
    lines = [
        f"{log}: {n} frames over {span:.2f} s ({rate:.2f} Hz), {data.lost} records lost",
        f"packet: {PACKET_BYTES} bytes = {PACKET_BYTES * 8} bits per frame",
        f"payload: {summary['payload_kbps']:.2f} kbit/s at 30 Hz "
        f"({summary['payload_kbps_at_log_rate']:.2f} kbit/s at the log's rate)",
        f"wire (ZeroMQ): {summary['wire_kbps']:.2f} kbit/s at 30 Hz, "
        f"{summary['wire_kbps_curve']:.2f} kbit/s with CURVE",
        f"{'OK' if ok else 'OVER'}: payload {'under' if ok else 'at or over'} "
        f"{LIMIT_KBPS:g} kbit/s at 30 Hz",
    ]
    if plot is not None:
        _plot(data.times, Path(plot))
        lines.append(f"plot: {plot}")
    report(summary, lines, as_json)
    return 0 if ok else 1


def _plot(times: np.ndarray, path: Path) -> None:
    """Bits per frame, and the kbit/s carried over the trailing second, against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = times - times[0] if len(times) else times
    in_last_second = np.searchsorted(t, t, side="right") - np.searchsorted(t, t - 1.0,
                                                                            side="right")
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(8, 5))
    top.plot(t, np.full(len(t), PACKET_BYTES * 8), ".", ms=2)
    top.set_ylabel("bits per frame")
    top.set_ylim(0, PACKET_BYTES * 8 * 1.5)
    bottom.plot(t, in_last_second * PACKET_BYTES * 8 / 1000, lw=1, label="payload, 1 s window")
    bottom.axhline(LIMIT_KBPS, color="red", ls="--", label=f"{LIMIT_KBPS:g} kbit/s limit")
    bottom.set_ylabel("kbit/s")
    bottom.set_xlabel("time (s)")
    bottom.set_ylim(0, LIMIT_KBPS * 1.25)
    bottom.legend(loc="lower right")
    fig.suptitle("facewire packet log bandwidth")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
