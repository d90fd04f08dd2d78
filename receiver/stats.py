"""The receive loop's statistics: its counts and measurements, the status line and the summary.

Summary keys (``ReceiveStats.summary``, with those the session adds: ``connect``, ``out``,
``width``, ``height`` and the model's, ``receiver.acquire``): ``frames`` (output frames:
``receiver.receiver``, "Output frames"), ``received``, ``lost`` (concealed slots written),
``late``, ``corrupt``, ``duplicates``, ``stray``, ``discarded``, ``skipped``, ``restarts`` (the
playouts' counts, ``receiver.playout``), ``ignored``, ``overflow``, ``streams`` (runs of output
frames), ``hellos`` (Hellos answered), ``control_timeouts``, ``control_errors``, ``fps``
(``(frames - 1) / (t_last - t_first)`` over the output frames' times), ``kbps`` (packet bytes
after the first, ``8 bytes / 1000 / (a_last - a_first)`` over the packets' arrival times),
``repeated`` (output frames that repeat the frame before, not drawn: ``keep_up``; their
latencies are the repeated frame's),
``latency_ms_median`` and ``latency_ms_p95`` (a played packet's arrival to its frame
rendered: the frame's own time, plus the wait behind a missing slot or a frame still
rendering, and any backlog of a loop that fell behind), ``glass_to_glass_ms_median`` and
``glass_to_glass_ms_p95`` (a played packet's capture at the sender to its frame out here,
clocks aligned: ``receiver.receiver``; None when the sender gives no clock),
``render_ms_median`` (morph, view and
render with readback), ``seconds`` and ``ended``: stop, max_frames or idle_timeout.

Model updates (``update_summary``, ``receiver.updates``): ``model_serial`` (the model version
rendered last), ``updates`` (applied), ``update_bytes`` (their bytes), ``updates_refused``
(failed their hash or their decoding), ``update_chunks``, ``update_control_timeouts`` and
``update_control_errors`` (the update fetcher's channel), ``clamped`` (slots rendered with an
older version than their packet's, its update still on the way: Q clamped to the layers held).
The status line says the version rendered and, while slots are clamped, the version they need.

Live statistics (``ReceiveStats.live``, keys ``LIVE_KEYS``: the second argument of a
receiver's ``view``, and the status line every ``STATUS_EVERY_S``) measure fps and kbit/s
over the last ``WINDOW_S``: ``fps = frames in the window / WINDOW_S``, ``kbps = 8 bytes in the
window / 1000 / WINDOW_S``, and the median latency and glass-to-glass latency of the
window's played frames (``latency_ms``, ``glass_ms``).

Each playout's counts are added to the totals when it is retired (a new Hello, the end);
what a retired playout still held, neither played nor otherwise dropped, is ``discarded``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Any

import numpy as np

from facewire.receiver.playout import FrameState, Playout
from facewire.receiver.scene import STATS_FRAMES
from facewire.receiver.updates import UpdateFetcher

STATUS_EVERY_S = 1.0
WINDOW_S = 1.0
LIVE_KEYS = ("state", "seq", "fps", "kbps", "frames", "received", "lost", "late", "corrupt",
             "duplicates", "latency_ms", "glass_ms")
UPDATE_KEYS = ("updates", "update_bytes", "updates_refused", "update_chunks",
               "update_control_timeouts", "update_control_errors")
PLAYOUT_KEYS = ("received", "corrupt", "duplicate", "late", "stray", "discarded", "skipped",
                "restarts")


class ReceiveStats:
    """A receive session's counts and measurements (module docstring); times are
    ``time.monotonic()`` seconds.

    Attributes:
        counts: ``frames``, ``lost``, ``ignored``, ``streams``, ``hellos``, ``clamped`` and
            ``repeated`` of the session.
        totals: the ``PLAYOUT_KEYS`` counts of the playouts already retired.
        last_packet: the last packet's arrival, or None.
    """

    def __init__(self) -> None:
        self.counts = dict.fromkeys(("frames", "lost", "ignored", "streams", "hellos",
                                     "clamped", "repeated"), 0)
        self.totals = dict.fromkeys(PLAYOUT_KEYS, 0)
        self.update_totals = dict.fromkeys(UPDATE_KEYS, 0)
        self.version = (0, 0)  # (the version rendered, the newest a packet needed)
        self.first_packet: tuple[float, int] | None = None  # arrival, bytes
        self.last_packet: float | None = None
        self.bytes_total = 0
        self.first_frame: float | None = None
        self.last_frame: float | None = None
        self.latencies: deque[float] = deque(maxlen=STATS_FRAMES)
        self.glass: deque[float] = deque(maxlen=STATS_FRAMES)
        self.recent_packets: deque[tuple[float, int]] = deque()  # arrival, bytes
        # time, latency, glass-to-glass
        self.recent_frames: deque[tuple[float, float | None, float | None]] = deque()
        self.next_status = 0.0

    def packet(self, size: int, arrival: float) -> None:
        """Count a packet of ``size`` bytes that arrived at ``arrival``."""
        if self.first_packet is None:
            self.first_packet = (arrival, size)
        self.last_packet = arrival
        self.bytes_total += size
        self.recent_packets.append((arrival, size))

    def frame(self, now: float, latency: float | None, glass: float | None = None) -> int:
        """Count an output frame made at ``now`` (``latency`` s for a played packet, None
        for a concealed slot; ``glass`` its glass-to-glass latency, s, when known); the
        number of output frames so far."""
        self.counts["frames"] += 1
        self.first_frame = self.first_frame or now
        self.last_frame = now
        if latency is not None:
            self.latencies.append(latency)
        if glass is not None:
            self.glass.append(glass)
        self.recent_frames.append((now, latency, glass))
        return self.counts["frames"]

    def clamped(self, needed: int, held: int) -> None:
        """Count a slot whose packet needs model version ``needed``, rendered with ``held``
        (older: its update is still on the way)."""
        self.counts["clamped"] += 1
        self.version = (held, needed)

    def retire_updates(self, fetcher: UpdateFetcher) -> None:
        """Add a finished session's update counts to the totals."""
        for key, value in _update_counts(fetcher).items():
            self.update_totals[key] += value

    def update_summary(self, fetcher: UpdateFetcher | None, version: int) -> dict[str, Any]:
        """The summary's model update keys (module docstring), ``version`` the model version
        rendered last."""
        counts = dict(self.update_totals)
        if fetcher is not None:
            for key, value in _update_counts(fetcher).items():
                counts[key] += value
        return {"model_serial": version, **counts, "clamped": self.counts["clamped"]}

    def retire(self, playout: Playout, played: int) -> None:
        """Add a playout's counts to the totals; of the ``received``, what it neither
        played (``played`` packets) nor dropped is ``discarded``."""
        stats = playout.stats
        for key in PLAYOUT_KEYS:
            self.totals[key] += stats[key]
        unplayed = stats["received"] - played - sum(
            stats[k] for k in ("duplicate", "late", "stray", "discarded"))
        self.totals["discarded"] += max(unplayed, 0)

    def playout_counts(self, playout: Playout | None) -> dict[str, int]:
        """The ``PLAYOUT_KEYS`` counts: the totals and the current playout's."""
        counts = dict(self.totals)
        if playout is not None:
            for key, value in playout.stats.items():
                if key in counts:
                    counts[key] += value
        return counts

    def live(self, now: float, state: FrameState | None, playout: Playout | None
             ) -> dict[str, Any]:
        """The live statistics (``LIVE_KEYS``) as of this slot (its playout status and wire
        sequence number), or between slots (None: "playing")."""
        while self.recent_packets and self.recent_packets[0][0] < now - WINDOW_S:
            self.recent_packets.popleft()
        while self.recent_frames and self.recent_frames[0][0] < now - WINDOW_S:
            self.recent_frames.popleft()
        counts = self.playout_counts(playout)
        latencies = [x for _, x, _ in self.recent_frames if x is not None]
        glass = [g for _, _, g in self.recent_frames if g is not None]
        return {"state": "playing" if state is None else state.status,
                "seq": None if state is None else state.seq,
                "fps": round(len(self.recent_frames) / WINDOW_S, 1),
                "kbps": round(sum(n for _, n in self.recent_packets) * 8 / 1000 / WINDOW_S, 2),
                "frames": self.counts["frames"], "received": counts["received"],
                "lost": self.counts["lost"], "late": counts["late"],
                "corrupt": counts["corrupt"], "duplicates": counts["duplicate"],
                "latency_ms": round(1000 * float(np.median(latencies)), 1) if latencies
                else None,
                "glass_ms": round(1000 * float(np.median(glass)), 1) if glass else None}

    def status_line(self, now: float, playout: Playout | None, connect: str,
                    last_arrival: float | None, playing_since: float,
                    version: int = 0, updates: UpdateFetcher | None = None) -> str | None:
        """The status line while playing, once every ``STATUS_EVERY_S``; None in between.

        Args:
            now: the time.
            playout: the current playout.
            connect: the sender's address.
            last_arrival: the last packet's arrival, None before any.
            playing_since: when the current playout was set up.
            version: the model version rendered.
            updates: the session's update fetcher, or None.
        """
        if now < self.next_status:
            return None
        self.next_status = now + STATUS_EVERY_S
        if last_arrival is None or now - last_arrival > STATUS_EVERY_S:
            quiet = now - max(last_arrival or 0.0, playing_since)
            return f"no packets from {connect} for {quiet:.0f} s: waiting for the sender"
        s = self.live(now, None, playout)
        latency = "-" if s["latency_ms"] is None else f"{s['latency_ms']:.0f} ms"
        glass = "-" if s["glass_ms"] is None else f"{s['glass_ms']:.0f} ms"
        line = (f"{s['fps']:.1f} fps, {s['kbps']:.1f} kbit/s; received {s['received']}, "
                f"lost {s['lost']}, late {s['late']}, corrupt {s['corrupt']}; latency "
                f"{latency}, glass-to-glass {glass}")
        if updates is None:
            return line
        line += f"; model v{version}, {updates.counts['updates']} updates " \
            f"({updates.counts['update_bytes'] / 1000:.1f} kB)"
        held, needed = self.version
        if needed > version:
            line += f", packets need v{needed}: Q clamped to v{held}'s layers"
        if updates.stuck:
            line += f"; {updates.stuck}"
        return line

    def summary(self, playout: Playout | None, ended: str, seconds: float, overflow: int,
                control_timeouts: int, control_errors: int,
                render_seconds: Iterable[float]) -> dict[str, Any]:
        """The summary's counts and measurements (module docstring).

        Args:
            playout: the current playout, or None.
            ended: why the session ended.
            seconds: the session's length, s.
            overflow: packets dropped by a full reader queue.
            control_timeouts, control_errors: the control channel's counts.
            render_seconds: the time of each recent render, s.
        """
        counts = self.playout_counts(playout)
        frames = self.counts["frames"]
        span = packet_span = 0.0
        if frames > 1 and self.first_frame is not None and self.last_frame is not None:
            span = self.last_frame - self.first_frame
        first_bytes = 0
        if self.first_packet is not None and self.last_packet is not None:
            packet_span = self.last_packet - self.first_packet[0]
            first_bytes = self.first_packet[1]
        latencies = np.asarray(self.latencies) * 1000
        glass = np.asarray(self.glass) * 1000
        renders = np.asarray(list(render_seconds)) * 1000

        def ms(values: np.ndarray, q: float) -> float | None:
            return round(float(np.percentile(values, q)), 1) if len(values) else None

        return {
            "ended": ended, "frames": frames,
            "received": counts["received"], "lost": self.counts["lost"],
            "late": counts["late"], "corrupt": counts["corrupt"],
            "duplicates": counts["duplicate"], "stray": counts["stray"],
            "discarded": counts["discarded"], "skipped": counts["skipped"],
            "restarts": counts["restarts"], "ignored": self.counts["ignored"],
            "overflow": overflow, "streams": self.counts["streams"],
            "repeated": self.counts["repeated"],
            "hellos": self.counts["hellos"], "control_timeouts": control_timeouts,
            "control_errors": control_errors,
            "fps": round((frames - 1) / span, 1) if span > 0 else None,
            "kbps": round((self.bytes_total - first_bytes) * 8 / 1000 / packet_span, 3)
            if packet_span > 0 else None,
            "latency_ms_median": ms(latencies, 50), "latency_ms_p95": ms(latencies, 95),
            "glass_to_glass_ms_median": ms(glass, 50), "glass_to_glass_ms_p95": ms(glass, 95),
            "render_ms_median": round(float(np.median(renders)), 2) if len(renders) else None,
            "seconds": round(seconds, 2),
        }


def _update_counts(fetcher: UpdateFetcher) -> dict[str, int]:
    """A fetcher's counts under the summary's ``UPDATE_KEYS``."""
    return {**{key: fetcher.counts[key] for key in UPDATE_KEYS if key in fetcher.counts},
            "update_control_timeouts": fetcher.control_counts[0],
            "update_control_errors": fetcher.control_counts[1]}
