"""``facewire bench bandwidth``: the bit rates a packet log actually carried, judged.

A log holds one record per packet sent, stamped with the sender's clock (``protocol.log``);
every packet has ``PACKET_BYTES`` bytes. Over the log's span ``T`` = last time - first time,
its N records give the mean rate ``rate_hz`` = (N - 1) / T, and at a rate ``r`` the bit
rates of one packet per slot are (``protocol.rate.kbps``):

    payload_kbps    = PACKET_BYTES * 8 * r / 1000                 the packets' own bytes
    wire_kbps       = (PACKET_BYTES + 2) * 8 * r / 1000           ZeroMQ (ZMTP 3) frame header
    wire_kbps_curve = (PACKET_BYTES + 35) * 8 * r / 1000          under CURVE
    ip_kbps         = (PACKET_BYTES + 2 + IP_TCP_OVERHEAD) * 8 * r / 1000

(``protocol.transport.WIRE_OVERHEAD``). ``ip_kbps`` is an estimate: one TCP segment per
message, each with a 20-byte IPv4 header and a 32-byte TCP header (20 bytes and the 12-byte
timestamps option Linux sends), so 52 bytes; ZeroMQ may batch messages that queue together
into one segment (then less), and the link layer, the receiver's ACKs and retransmissions
are not counted.

The judgement is on the worst second: for each record i, the records in the second ending at
it, ``n_i`` = #{j : t_i - 1 s + eps <= t_j <= t_i} (times sorted; eps = ``WINDOW_EPS_S``
absorbs the rounding of Unix times, so a regular 30 Hz log counts 30, not 31), and the ``*_max_1s``
figures are the rates above at ``max_i n_i`` packets per second. A log that spans less than a
second has no full window and is judged at its mean rate (with fewer than 2 records, at the
rate its Hello announces). The 12 kbit/s budget
(``protocol.rate.PAYLOAD_LIMIT_KBPS``) applies to the payload, as in the paper:
``payload_kbps_max_1s`` >= 12 exits 1. A 30 Hz stream is 10.32 kbit/s; 35 packets in one
second are 12.04 kbit/s and fail.

The voice (``protocol.voice``) travels on the packet socket beside the face, in packets of
its own, one per 20 ms; a log keeps them as voice records. ``audio_kbps`` is their bytes
over the log's span, ``audio_kbps_max_1s`` over its worst second (the bytes of the voice
records in the second ending at each of them), and ``total_kbps``, ``total_kbps_max_1s`` add
the face's payload: the call's budget is 12 kbit/s each, 24 in all. A log without voice has
zeros. The exit code judges the face's payload alone, as before.

Model updates travel beside the packets, on the control channel. Their traffic is measured on
real loopback sockets by ``bench.updatetraffic`` (the sender's control thread serving them at
their issue times, one receiver fetching them): ``update_bytes_total``, ``update_kbps_max_1s``,
``update_kbps_max_60s`` (limits 32 and 8 kbit/s, ``protocol.shaper``), ``update_first_s``; a
session without updates has none (zeros). The updates are the log's (``protocol.log``), in
serial order up to the first the log lacks.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facewire.bench.updatetraffic import update_traffic
from facewire.protocol.log import LoggedUpdate, read_log
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.rate import PAYLOAD_LIMIT_KBPS, kbps
from facewire.protocol.transport import WIRE_OVERHEAD

WINDOW_S = 1.0
WINDOW_EPS_S = 1e-6  # Unix times near 1.7e9 s are doubles with a 2.4e-7 s step
IP_TCP_OVERHEAD = 20 + 32  # IPv4 header + TCP header with the timestamps option, per segment
LIMIT_APPLIES_TO = "payload_kbps_max_1s"


def packets_in_last_second(times: np.ndarray) -> np.ndarray:
    """For each record, how many records fell in the second that ends with it.

    Args:
        times: (N,) float64, record times in seconds, in any order.

    Returns:
        (N,) int64, ``n_i`` of the module docstring, in the order of ``np.sort(times)``.
    """
    t = np.sort(np.asarray(times, np.float64))
    first = np.searchsorted(t, t - WINDOW_S + WINDOW_EPS_S, side="left")
    return np.arange(1, len(t) + 1) - first


def rates(rate_hz: float) -> dict[str, float]:
    """The payload, wire and IP bit rates (kbit/s) of one packet per slot at ``rate_hz``."""
    plain = PACKET_BYTES + WIRE_OVERHEAD["plain"]
    return {"payload_kbps": kbps(PACKET_BYTES, rate_hz), "wire_kbps": kbps(plain, rate_hz),
            "wire_kbps_curve": kbps(PACKET_BYTES + WIRE_OVERHEAD["curve"], rate_hz),
            "ip_kbps": kbps(plain + IP_TCP_OVERHEAD, rate_hz)}


def bandwidth(log: str | os.PathLike[str], plot: str | os.PathLike[str] | None = None
              ) -> tuple[dict[str, Any], list[str]]:
    """Measure and judge a packet log (module docstring).

    Returns:
        The summary (``frames``, ``rate_hz``, ``packet_bytes``, ``payload_kbps``,
        ``wire_kbps``, ``wire_kbps_curve``, ``ip_kbps``, the same four with ``_max_1s``,
        ``packets_max_1s``, ``limit_kbps``, ``limit_applies_to``, ``under_limit``, the update
        traffic's keys (``bench.updatetraffic.update_traffic``), ...) and the report's lines.

    Raises:
        LogError: the log cannot be read (names the file and field).
    """
    data = read_log(log)
    n = len(data.times)
    span = float(np.ptp(data.times)) if n > 1 else 0.0
    rate = (n - 1) / span if span > 0 else data.hello.rate_hz
    full_window = span >= WINDOW_S
    worst = int(packets_in_last_second(data.times).max()) if full_window else None
    mean = rates(rate)
    peak = rates(worst if worst is not None else rate)
    under = peak["payload_kbps"] < PAYLOAD_LIMIT_KBPS
    summary: dict[str, Any] = {
        "log": str(log), "frames": n, "lost_records": data.lost, "duration_s": round(span, 3),
        "rate_hz": round(rate, 3), "hello_rate_hz": data.hello.rate_hz,
        "packet_bytes": PACKET_BYTES, "ip_tcp_overhead_bytes": IP_TCP_OVERHEAD,
        **{key: round(value, 3) for key, value in mean.items()},
        **{f"{key}_max_1s": round(value, 3) for key, value in peak.items()},
        "packets_max_1s": worst, "limit_kbps": PAYLOAD_LIMIT_KBPS,
        "limit_applies_to": LIMIT_APPLIES_TO, "under_limit": under,
    }
    judged = (f"worst 1-s window: {worst} packets" if full_window
              else "under 1 s of records: judged at the mean rate" if span > 0
              else "fewer than 2 records: judged at the Hello's rate")
    lines = [
        f"{log}: {n} frames over {span:.2f} s ({rate:.2f} Hz; the Hello says "
        f"{data.hello.rate_hz:g} Hz), {data.lost} records lost",
        f"packet: {PACKET_BYTES} bytes = {PACKET_BYTES * 8} bits per frame",
        f"                   mean      worst 1 s   ({judged})",
        *(f"{label:<18} {mean[key]:6.2f}      {peak[key]:6.2f}   kbit/s"
          for label, key in (("payload:", "payload_kbps"), ("wire (ZeroMQ):", "wire_kbps"),
                             ("wire (CURVE):", "wire_kbps_curve"),
                             ("IP/TCP estimate:", "ip_kbps"))),
        f"IP/TCP assumes one segment per message with {IP_TCP_OVERHEAD} bytes of headers (IPv4 "
        f"20 + TCP 32 with timestamps); ZeroMQ may batch messages, so it can be less",
        f"{'OK' if under else 'OVER'}: the {PAYLOAD_LIMIT_KBPS:g} kbit/s budget applies to the "
        f"payload (as in the paper); worst 1-s payload {peak['payload_kbps']:.2f} kbit/s is "
        f"{'under' if under else 'at or over'} it",
    ]
    voice_times = np.array([r.time for r in data.voice], np.float64)
    voice_bytes = np.array([len(r.data) for r in data.voice], np.int64)
    audio = {"audio_kbps": round(voice_bytes.sum() * 8 / span / 1000, 3) if span > 0 else 0.0,
             "audio_kbps_max_1s": round(_worst_second_bits(voice_times, voice_bytes) / 1000, 3)
             if full_window else None}
    summary.update(audio, total_kbps=round(summary["payload_kbps"] + audio["audio_kbps"], 3),
                   total_kbps_max_1s=None if audio["audio_kbps_max_1s"] is None else
                   round(summary["payload_kbps_max_1s"] + audio["audio_kbps_max_1s"], 3))
    if len(voice_times):
        lines.insert(-1, f"voice: {len(voice_times)} packets, {audio['audio_kbps']:.2f} kbit/s "
                     f"mean, worst 1 s {audio['audio_kbps_max_1s']}; face and voice "
                     f"{summary['total_kbps']:.2f} kbit/s mean, worst 1 s "
                     f"{summary['total_kbps_max_1s']}")
    traffic = update_traffic(_served(data.updates), data.hello)
    summary.update(traffic)
    lines.insert(-1, f"model updates: {traffic['updates']} ({traffic['update_bytes_total']} "
                 f"bytes), measured on loopback: worst 1 s "
                 f"{traffic['update_kbps_max_1s']:.2f} kbit/s (limit "
                 f"{traffic['update_limit_kbps_1s']:g}), worst 60 s "
                 f"{traffic['update_kbps_max_60s']:.2f} kbit/s (limit "
                 f"{traffic['update_limit_kbps_60s']:g})")
    if plot is not None:
        _plot(data.times, Path(plot))
        lines.append(f"plot: {plot}")
    return summary, lines


def _worst_second_bits(times: np.ndarray, sizes: np.ndarray) -> float:
    """The most bits of records in one second ending at a record (module docstring)."""
    if not len(times):
        return 0.0
    order = np.argsort(times, kind="stable")
    t, cum = times[order], np.concatenate([[0], np.cumsum(sizes[order])])
    first = np.searchsorted(t, t - WINDOW_S + WINDOW_EPS_S, side="left")
    return float((cum[1:] - cum[first]).max() * 8)


def _served(updates: Sequence[LoggedUpdate]) -> list[tuple[float, bytes]]:
    """(time, bytes) of the log's updates 1, 2, ... up to the first it lacks: what a sender
    serves in order (a receiver cannot apply an update past a missing one)."""
    by_serial = {u.serial: u for u in updates}
    served: list[tuple[float, bytes]] = []
    while (update := by_serial.get(len(served) + 1)) is not None:
        served.append((update.time, update.data))
    return served


def _plot(times: np.ndarray, path: Path) -> None:
    """Bits per frame, and the payload kbit/s carried over the trailing second, against
    time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.sort(times)
    t = t - t[0] if len(t) else t
    per_second = packets_in_last_second(t)
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(8, 5))
    top.plot(t, np.full(len(t), PACKET_BYTES * 8), ".", ms=2)
    top.set_ylabel("bits per frame")
    top.set_ylim(0, PACKET_BYTES * 8 * 1.5)
    payload = np.array([kbps(PACKET_BYTES, n) for n in per_second], np.float64)
    bottom.plot(t, payload, lw=1, label="payload, 1 s window")
    bottom.axhline(PAYLOAD_LIMIT_KBPS, color="red", ls="--",
                   label=f"{PAYLOAD_LIMIT_KBPS:g} kbit/s budget")
    bottom.set_ylabel("kbit/s")
    bottom.set_xlabel("time (s)")
    bottom.set_ylim(0, max(PAYLOAD_LIMIT_KBPS, float(payload.max(initial=0))) * 1.25)
    bottom.legend(loc="lower right")
    fig.suptitle("facewire packet log bandwidth")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
