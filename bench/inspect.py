"""``facewire inspect``: summarise a packet log, and dump its decoded frames as CSV.

CSV columns: ``seq, time, flags, face_present, rot_x_deg, rot_y_deg, rot_z_deg, tx_mm,
ty_mm, tz_mm``, the residuals ``res<k>_u, res<k>_v`` (k = 0..8 in the protocol's point
order), then ``q_<region>`` for each region named in the log's Hello, then ``serial`` (the
model version the Q values refer to) and the light's log-gain field ``shade_centre, shade_x,
shade_y`` (``protocol.packet``).

Model updates: the summary's ``updates`` lists the log's intact update records in file
order, each ``serial``, ``region`` (read from the update's own bytes,
``models.update.update_head``, without the model: None with an ``error`` when they do not
parse), ``position``, ``replaces``, ``bytes``, ``time`` (s) and ``before`` (the intact packets
before it); ``update_bytes`` their total, ``lost_updates`` the damaged update records and
``missing_serials`` the serials the frames or updates name that no intact record holds
(``protocol.log``). One report line per update.

Voice: ``voice_packets`` (intact voice records), ``voice_s`` (their sound, 20 ms each),
``voice_kbps`` (their bytes over the log's duration), ``voice_gaps`` (voice frames missing
from their sequence), ``lost_voice`` (damaged voice records); one report line when the log
holds any.
"""

from __future__ import annotations

import csv
import os
from typing import Any

import numpy as np

from facewire.models.update import UpdateError, update_head
from facewire.protocol.log import LoggedUpdate, LoggedVoice, read_log
from facewire.protocol.opus import FRAME_S
from facewire.protocol.packet import N_RESIDUAL_POINTS, SEQ_MODULO, Flag
from facewire.protocol.voice import SEQ_MODULO as VOICE_SEQ_MODULO
from facewire.protocol.voice import decode


def inspect_log(log: str | os.PathLike[str], csv_path: str | os.PathLike[str] | None = None
                ) -> tuple[dict[str, Any], list[str]]:
    """A log's summary and report lines; optionally write its frames as CSV."""
    data = read_log(log)
    f = data.frames
    n = len(f)
    span = float(data.times[-1] - data.times[0]) if n > 1 else 0.0
    steps = np.mod(np.diff(f["seq"].astype(np.int64)), SEQ_MODULO)  # numpy's stub lacks % int
    summary = {
        "log": str(log),
        "frames": n,
        "duration_s": round(span, 3),
        "rate_hz": round((n - 1) / span, 3) if span > 0 else data.hello.rate_hz,
        "lost_records": data.lost,
        "sequence_gaps": int(np.clip(steps - 1, 0, None).sum()) if n > 1 else 0,
        "face_frames": int(np.count_nonzero(f["flags"] & Flag.FACE_PRESENT)),
        "clamped_frames": int(np.count_nonzero(f["flags"] & Flag.CLAMPED)),
        "model_sha256": data.hello.model_sha256,
        "regions": list(data.hello.regions),
        "updates": [_update(u) for u in data.updates],
        "update_bytes": sum(len(u.data) for u in data.updates),
        "lost_updates": data.lost_updates,
        "missing_serials": list(data.missing_serials),
        **_voice(data.voice, data.lost_voice, span),
    }
    lines = [
        f"{log}: {n} frames over {span:.2f} s ({summary['rate_hz']} Hz)",
        f"lost or corrupt records: {data.lost}; packets missing from the sequence: "
        f"{summary['sequence_gaps']}",
        f"face present in {summary['face_frames']} frames; clamped in "
        f"{summary['clamped_frames']}",
        f"model {data.hello.model_sha256[:16]}…, regions: {', '.join(data.hello.regions)}",
        *_update_lines(summary),
        *([f"voice: {summary['voice_packets']} packets, {summary['voice_s']} s of sound at "
           f"{summary['voice_kbps']} kbit/s; missing from the sequence: "
           f"{summary['voice_gaps']}; damaged records: {summary['lost_voice']}"]
          if summary["voice_packets"] or summary["lost_voice"] else []),
    ]
    if csv_path is not None:
        _write_csv(csv_path, data.times, f, data.hello.regions)
        lines.append(f"csv: {csv_path}")
    return summary, lines


def _voice(records: tuple[LoggedVoice, ...], lost: int, span: float) -> dict[str, Any]:
    """The summary's voice keys (module docstring)."""
    seqs = np.array([decode(r.data).seq for r in records], np.int64)
    steps = np.mod(np.diff(seqs), VOICE_SEQ_MODULO)
    size = sum(len(r.data) for r in records)
    return {"voice_packets": len(records), "voice_s": round(len(records) * FRAME_S, 3),
            "voice_kbps": round(size * 8 / span / 1000, 3) if span > 0 else 0.0,
            "voice_gaps": int(np.clip(steps - 1, 0, None).sum()), "lost_voice": lost}


def _update(record: LoggedUpdate) -> dict[str, Any]:
    """One update record as the summary lists it (module docstring)."""
    entry: dict[str, Any] = {"serial": record.serial, "bytes": len(record.data),
                             "time": round(record.time, 6), "before": record.before}
    try:
        head = update_head(record.data, f"update record {record.serial}")
    except UpdateError as e:
        return {**entry, "region": None, "position": None, "replaces": None, "error": str(e)}
    return {**entry, "region": head.region, "position": head.position,
            "replaces": head.replaces}


def _update_lines(summary: dict[str, Any]) -> list[str]:
    """The report's lines on the model updates: a count, then one per update."""
    updates = summary["updates"]
    if not (updates or summary["lost_updates"] or summary["missing_serials"]):
        return ["model updates: none"]
    lines = [f"model updates: {len(updates)} ({summary['update_bytes']:,} bytes), "
             f"{summary['lost_updates']} damaged"
             + (f"; lacking serials {', '.join(map(str, summary['missing_serials']))}"
                if summary["missing_serials"] else "")]
    for u in updates:
        what = (f"{u['region']}, state {u['position']}"
                + ("" if u["replaces"] is None else f" replacing {u['replaces']}")
                if u["region"] is not None else f"unreadable: {u['error']}")
        lines.append(f"  update {u['serial']}: {what}, {u['bytes']:,} bytes, at "
                     f"{u['time']:.3f} s (after {u['before']} packets)")
    return lines


def _write_csv(path: str | os.PathLike[str], times: np.ndarray, f: np.ndarray,
               regions: tuple[str, ...]) -> None:
    header = ["seq", "time", "flags", "face_present", "rot_x_deg", "rot_y_deg", "rot_z_deg",
              "tx_mm", "ty_mm", "tz_mm"]
    header += [f"res{k}_{axis}" for k in range(N_RESIDUAL_POINTS) for axis in "uv"]
    header += [f"q_{name}" for name in regions]
    header += ["serial", "shade_centre", "shade_x", "shade_y"]
    columns = [f["seq"], times, f["flags"], (f["flags"] & Flag.FACE_PRESENT) > 0,
               *np.degrees(f["rotation"]).T, *f["translation"].T,
               *f["residuals"].reshape(len(f), -1).T, *f["q"][:, :len(regions)].T,
               f["serial"], *f["shade"].T]
    with open(path, "w", newline="") as out:
        writer = csv.writer(out)
        writer.writerow(header)
        for row in zip(*columns):
            writer.writerow([_cell(v) for v in row])


def _cell(v: object) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (np.floating, float)):
        return f"{float(v):.6g}"
    return str(v)
