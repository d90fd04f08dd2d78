"""``facewire bench speed``: per-frame cost of the pipeline's stages, one core where possible.

Every key of the contract (docs/DESIGN.md §7) is measured; the end-to-end latency and the memory
growth come from a live run of a real sender and receiver over loopback
(``bench.loopback``, ``loopback_s`` seconds; 0 leaves them out, listed under
``not_measured``, never estimated).

The sender stages are timed by running the whole ``sender.pipeline.SenderPipeline`` (the
model, the intrinsics guess of ``sender.capture.estimate_intrinsics`` for the video's size)
over the video's frames, BLAS pinned to one thread; each frame's stages come from
``SenderOutput.timings``. Decoding is not timed.

- ``track_ms``: median wall time of ``LandmarkTracker.track`` on the source video's frames
  once the face is acquired, i.e. on frames whose ``TrackResult`` says the full-frame detector
  did not run (``detected`` false) and a face was found. These include the tracker's periodic
  neighbourhood checks (``verified``, every 5th frame, about +1.4 ms), so the median is the
  plain tracked frame. Frames where the full-frame detector ran (acquisition, re-acquisition,
  the periodic search for a larger face) give ``track_detect_ms``.
- ``pose_ms`` (pose fit alternated with the lift, and the One-Euro filter), ``lift_ms`` (the
  lift with the filtered pose), ``heuristics_ms`` (``ResidualFilter`` and the tangent
  projection), ``sample_ms`` (``AppearanceSampler``: every region's five offset samples,
  grey conversion included), ``classify_ms`` (``RegionClassifiers``: all regions, five
  offsets each), ``learn_ms`` (``sender.learn``: noticing, holding, capturing; the
  pipeline learns by default) and ``shade_ms`` (``sender.shading.ShadingEstimator``: the
  light's fit and its smoothing): medians over the frames with a face (a model without
  regions gives None for sample, classify and learn); ``pack_ms``: median over all frames.
- ``learn_ms_per_frame``: the learning's mean per frame over the frames with a face, its
  rare captures (tens to hundreds of ms each, the first of a region building that region's
  texels) included, and ``learn_updates``, the model updates it made on the video; the
  target is <= 0.5 ms per frame on average.
- ``sender_ms_median``: median over all frames of the sum of the stages (track, pose,
  lift, heuristics, sample, classify, learn, shade, pack); ``sender_fps`` = 1000 /
  ``sender_ms_median``. ``sender_ms_mean``: the mean of the same sums, which the rare
  costly frames (detections, the tracker's identity checks) move and the median does not;
  ``identify_frames``: the frames on which the tracker asked for an identity check
  (``sender.identity``; none with a model without descriptors), and ``identify_ms`` the
  median track time of those frames. The pipeline computes the checks' descriptors in a
  process of its own, as ``send`` does (``SenderPipeline(identify_apart=True)``): the frame
  path cuts the face's chip and goes on, and the tracker takes the answer frames later.
- The receiver, on the packets the sender made (``_time_receiver``), as ``receive`` and
  ``replay`` render: in a process of its own (``receiver.renderprocess.RenderProcess``,
  two frames in flight), after ``RECEIVER_WARMUP`` frames: ``decode_ms``
  (``protocol.packet.decode``, in this process), ``render_ms`` (the child's time for one
  frame: ``Rig.from_tangent`` and ``Rig.morph``, the view camera,
  ``receiver.render.FaceRenderer.render``'s vertex upload, draw with the base texture and
  the region volumes, and readback into shared memory), and ``receiver_ms_median`` (the
  median time between two frames handed back to this process, copied out of shared
  memory: the receiver's throughput) with ``receiver_fps`` = 1000 / it, at 640 x 480; the
  same at 1280 x 720 as ``receiver_fps_1280x720`` and ``render_ms_1280x720``. Then the first
  ``ENCODE_FRAMES`` frames rendered at 640 x 480 go to a ``receiver.output.VideoWriter`` as
  ``facewire receive --out`` writes them: ``encode_ms`` is the median time its thread takes
  to encode one (H.264). Live, it runs on its own thread beside the rendering, so it is not
  part of ``receiver_ms_median``; timed apart, neither slows the other down here.
- ``latency_ms_median``, ``latency_ms_p95``, ``glass_to_glass_ms_median``,
  ``glass_to_glass_ms_p95`` (capture to frame out, clocks aligned), ``sender_rss_growth_mb``,
  ``receiver_rss_growth_mb`` and the rest of ``bench.loopback.measure_loopback``: a real
  ``facewire send`` process on the video (looped) and a live receiver in this process for
  ``loopback_s`` seconds.
- ``morph_ms``: median wall time of one ``Rig.morph`` call (``models/rig.py``: an
  (N, 9) @ (9, 3) float32 product and an add) on the model's mesh, over ``MORPH_CALLS`` calls
  cycling through residuals drawn uniformly from +-``RESIDUAL_MM`` mm, after a warm-up.

BLAS threads. The morph's product is a numpy float32 GEMM, run by the OpenBLAS that numpy
bundles (scipy bundles another). OpenBLAS splits a GEMM over threads once m*n*k exceeds a
build-time threshold (262,144 with the defaults; the generic head's 11,188 x 9 x 3 is just
over it), and on a shared 2-core machine the split can cost more than it saves.
``OPENBLAS_NUM_THREADS`` only acts when the library loads, so in-process we call each loaded
OpenBLAS's own ``*_set_num_threads`` (found through ``/proc/self/maps`` and ``ctypes``; the
``get`` twin gives the value restored afterwards). ``morph_ms`` is timed pinned to one thread;
``morph_ms_default_threads`` is the same timing with the libraries' own setting, for
comparison. Where no OpenBLAS can be found (another BLAS, another OS) nothing is pinned and
``threads`` says so. dlib (tracking) is single-threaded and uses no BLAS.

Targets (printed, informative): morph <= 0.2 ms per 10,000 vertices on one core (the time is
linear in the vertex count, so a mesh of N vertices is judged by ``morph_ms * 10000 / N``),
tracking <= 2 ms per acquired frame on 640x480, the sender >= 150 fps on 640x480,
classification of all regions <= 1 ms per frame, learning <= 0.5 ms per frame on average,
the receiver >= 60 fps at 640x480 and >= 30 fps at 1280x720 (CPU rendering here: Mesa
llvmpipe), the loopback latency median <= 25 ms and each side's resident memory growing
by under 10 MB. A miss
does not fail the command (exit 0): wall times on a shared machine vary by +-20 % from run
to run, so a hard threshold on them would fail at random; the report states whether each
target was met in this run.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from facewire.bench.loopback import TARGET_GROWTH_MB, TARGET_LATENCY_MS, measure_loopback
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import (
    VideoError,
    frames_in_range,
    range_text,
    read_frames,
    video_info,
)
from facewire.models.modelfile import load_model
from facewire.models.rig import N_RESIDUALS, Rig
from facewire.protocol.packet import decode as decode_packet
from facewire.protocol.rate import stream_rate
from facewire.receiver.output import VideoWriter
from facewire.receiver.playout import FrameState
from facewire.receiver.renderprocess import RenderProcess
from facewire.sender.capture import estimate_intrinsics
from facewire.sender.pipeline import SenderPipeline

MORPH_CALLS = 300
MORPH_WARMUP = 30
RESIDUAL_MM = 5.0
TARGET_MORPH_MS_PER_10K = 0.2
TARGET_TRACK_MS = 2.0
TARGET_SENDER_FPS = 150.0
TARGET_CLASSIFY_MS = 1.0
TARGET_RECEIVER_FPS = 60.0
TARGET_RECEIVER_FPS_HD = 30.0
RECEIVER_SIZES = ((640, 480), (1280, 720))
RECEIVER_WARMUP = 3  # frames rendered before timing (shader compilation, first uploads)
ENCODE_FRAMES = 60  # rendered frames kept for timing the encoder (55 MB at 640x480)
LOOPBACK_S = 30.0
TARGET_SIZE = (640, 480)
SENDER_STAGES = ("track", "pose", "lift", "heuristics", "sample", "classify", "learn", "shade",
                 "pack")
_FACE_STAGES = ("pose", "lift", "heuristics", "sample", "classify", "learn", "shade")
TARGET_LEARN_MS = 0.5

TARGETS = {"morph_ms_per_10k_vertices": TARGET_MORPH_MS_PER_10K, "track_ms": TARGET_TRACK_MS,
           "sender_fps": TARGET_SENDER_FPS, "classify_ms": TARGET_CLASSIFY_MS,
           "learn_ms_per_frame": TARGET_LEARN_MS,
           "receiver_fps": TARGET_RECEIVER_FPS, "receiver_fps_1280x720": TARGET_RECEIVER_FPS_HD,
           "latency_ms_median": TARGET_LATENCY_MS, "rss_growth_mb": TARGET_GROWTH_MB}

# The keys that only the loopback run measures.
LOOPBACK_KEYS = ("latency_ms_median", "latency_ms_p95", "glass_to_glass_ms_median",
                 "glass_to_glass_ms_p95", "sender_rss_growth_mb", "receiver_rss_growth_mb")

# get/set symbol pairs of OpenBLAS builds: plain, numpy's (64-bit ints) and scipy's bundles.
_BLAS_SYMBOLS = (
    ("openblas_get_num_threads", "openblas_set_num_threads"),
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
)


class NoFaceError(VideoError):
    """The video holds no face the tracker can find; the message names the file."""


def measure_speed(model_path: str | os.PathLike[str], source: str | os.PathLike[str],
                  frames: slice | None = None, progress: Progress = no_progress,
                  loopback_s: float = LOOPBACK_S) -> dict[str, Any]:
    """Time tracking on a video and the morph on a model (module docstring).

    Args:
        model_path: the person model (``.fwm``).
        source: a video file.
        frames: the frame range to track (``models.infra.video.frame_range``); all by default.
        progress: wraps an iterable to show progress: ``progress(items, label, total)``.
        loopback_s: seconds of the live loopback run (``bench.loopback``); 0 skips it.

    Returns:
        A dict: ``frames`` (frames tracked), ``tracked_frames``, ``detect_frames``,
        ``no_face_frames``, ``track_ms`` (None if no frame was tracked after acquisition),
        ``track_detect_ms``, ``pose_ms``, ``lift_ms``, ``heuristics_ms``, ``sample_ms``,
        ``classify_ms``, ``shade_ms``, ``pack_ms``, ``regions``, ``sender_ms_median``,
        ``sender_fps``, ``width``, ``height``, ``vertices``, ``morph_ms``,
        ``morph_ms_default_threads``, ``morph_calls``, ``threads`` (what was pinned),
        ``encode_ms``, the keys of ``bench.loopback.measure_loopback`` (None when skipped),
        ``targets`` and ``met`` (per target), ``not_measured`` (the loopback keys when it was
        skipped); times in milliseconds.

    Raises:
        ModelFileError: the model is missing or corrupt (names the file).
        LoopbackError: the loopback run failed (says which side).
        VideoError: the video is missing or unreadable, or the range holds no frame;
            ``NoFaceError`` when no frame holds a face (names the file).
    """
    frames = slice(0, None) if frames is None else frames
    model = load_model(model_path)
    source = Path(source)
    info = video_info(source)
    tracking, packets, hello = _time_sender(model, source, frames, info, progress)
    rig = Rig(model.mesh)
    with _one_blas_thread():
        receiver, images = _time_receiver(model, packets, hello.camera, RECEIVER_SIZES[0],
                                          keep=ENCODE_FRAMES)
        receiver_hd, _ = _time_receiver(model, packets, hello.camera, RECEIVER_SIZES[1])
    encode_ms = _time_encode(images, hello.rate_hz)
    n = len(model.mesh.vertices)
    pinned, threads = _time_morph_pinned(rig)
    default = _time_morph(rig)
    morph_per_10k = pinned * 10_000 / n
    if loopback_s > 0:
        loopback = measure_loopback(model_path, source, loopback_s)
    else:
        loopback = dict.fromkeys(LOOPBACK_KEYS)
    result: dict[str, Any] = {
        "model": str(model_path),
        "source": str(source),
        **tracking,
        **receiver,
        "encode_ms": encode_ms,
        "receiver_fps_1280x720": receiver_hd["receiver_fps"],
        "render_ms_1280x720": receiver_hd["render_ms"],
        "vertices": n,
        "morph_ms": round(pinned, 4),
        "morph_ms_per_10k_vertices": round(morph_per_10k, 4),
        "morph_ms_default_threads": round(default, 4),
        "morph_calls": MORPH_CALLS,
        "threads": threads,
        **loopback,
        "not_measured": [k for k in LOOPBACK_KEYS if loopback[k] is None],
    }
    return {**result, "targets": TARGETS, "met": _met(result)}


def _met(r: dict[str, Any]) -> dict[str, bool]:
    """Per target of ``TARGETS``, whether the measured ``measure_speed`` result ``r`` met it
    (a figure not measured misses)."""
    growth = (r["sender_rss_growth_mb"], r["receiver_rss_growth_mb"])
    return {"morph": r["morph_ms_per_10k_vertices"] <= TARGET_MORPH_MS_PER_10K,
            "track": r["track_ms"] is not None and r["track_ms"] <= TARGET_TRACK_MS,
            "sender": r["sender_fps"] >= TARGET_SENDER_FPS,
            "classify": r["classify_ms"] is not None and r["classify_ms"] <= TARGET_CLASSIFY_MS,
            "learn": (r["learn_ms_per_frame"] is not None
                      and r["learn_ms_per_frame"] <= TARGET_LEARN_MS),
            "receiver": r["receiver_fps"] >= TARGET_RECEIVER_FPS,
            "receiver_1280x720": r["receiver_fps_1280x720"] >= TARGET_RECEIVER_FPS_HD,
            "latency": (r["latency_ms_median"] is not None
                        and r["latency_ms_median"] <= TARGET_LATENCY_MS),
            "memory": all(g is not None and g < TARGET_GROWTH_MB for g in growth)}


def format_speed(result: dict[str, Any]) -> str:
    """Human-readable lines of a ``measure_speed`` result (no trailing newline)."""
    r = result
    size = f"{r['width']}x{r['height']}"
    lines = [f"{r['source']}: {r['frames']} frames ({size}): {r['tracked_frames']} tracked, "
             f"{r['detect_frames']} with a full-frame detection, {r['no_face_frames']} without "
             f"a face"]
    if r["track_ms"] is None:
        lines.append("track:  not measured (no frame was tracked after acquisition)")
    else:
        note = "" if (r["width"], r["height"]) == TARGET_SIZE else \
            f" (target stated for {TARGET_SIZE[0]}x{TARGET_SIZE[1]})"
        lines.append(f"track:  {r['track_ms']:.3f} ms median per tracked frame; "
                     f"{_verdict(r['met']['track'])} <= {TARGET_TRACK_MS:g} ms{note}")
    if r["track_detect_ms"] is not None:
        lines.append(f"        {r['track_detect_ms']:.3f} ms median with a full-frame detection")
    stages = ", ".join(f"{k} {r[k + '_ms']:.3f} ms" for k in SENDER_STAGES[1:]
                       if r[k + "_ms"] is not None)
    lines += [f"sender: {r['sender_ms_median']:.3f} ms median per frame = "
              f"{r['sender_fps']:.1f} fps; {_verdict(r['met']['sender'])} >= "
              f"{TARGET_SENDER_FPS:g} fps",
              f"        {r['sender_ms_mean']:.3f} ms mean per frame; identity checks asked on "
              f"{r['identify_frames']} frames"
              + ("" if r["identify_ms"] is None else
                 f" ({r['identify_ms']:.1f} ms median track time there)"),
              f"        per stage (medians): {stages or 'no frame with a face'}"]
    if r["classify_ms"] is not None:
        lines.append(f"classify: {r['classify_ms']:.3f} ms median per frame, "
                     f"{r['regions']} regions x 5 offsets; "
                     f"{_verdict(r['met']['classify'])} <= {TARGET_CLASSIFY_MS:g} ms")
    else:
        lines.append("classify: not measured (the model has no regions, or no face was seen)")
    if r["learn_ms_per_frame"] is not None:
        lines.append(f"learn:  {r['learn_ms_per_frame']:.3f} ms mean per frame, "
                     f"{r['learn_updates']} model updates; "
                     f"{_verdict(r['met']['learn'])} <= {TARGET_LEARN_MS:g} ms")
    lines += [
        f"receiver: {r['receiver_ms_median']:.3f} ms median per frame = "
        f"{r['receiver_fps']:.1f} fps at 640x480 (decode {r['decode_ms']:.3f} ms, render and "
        f"read back {r['render_ms']:.3f} ms); {_verdict(r['met']['receiver'])} >= "
        f"{TARGET_RECEIVER_FPS:g} fps",
        f"          {r['receiver_fps_1280x720']:.1f} fps at 1280x720 (render "
        f"{r['render_ms_1280x720']:.3f} ms); {_verdict(r['met']['receiver_1280x720'])} >= "
        f"{TARGET_RECEIVER_FPS_HD:g} fps",
        f"morph:  {r['morph_ms']:.4f} ms median per frame, {r['vertices']:,} vertices "
        f"({r['morph_ms_per_10k_vertices']:.4f} ms per 10k); "
        f"{_verdict(r['met']['morph'])} <= {TARGET_MORPH_MS_PER_10K:g} ms per 10k vertices",
        f"        {r['morph_ms_default_threads']:.4f} ms with the default BLAS threads",
        f"encode: {r['encode_ms']:.3f} ms median per 640x480 frame (H.264, its own thread)",
        f"threads: {r['threads']}",
    ]
    if r["latency_ms_median"] is not None:
        lines.append(f"latency: {r['latency_ms_median']:.1f} ms median, "
                     f"{r['latency_ms_p95']:.1f} ms p95 from a packet sent to its frame "
                     f"rendered ({r['latency_frames']} frames, {r['loopback_s']:g} s live on "
                     f"loopback); {_verdict(r['met']['latency'])} <= {TARGET_LATENCY_MS:g} ms")
    if r["glass_to_glass_ms_median"] is not None:
        lines.append(f"glass-to-glass: {r['glass_to_glass_ms_median']:.1f} ms median, "
                     f"{r['glass_to_glass_ms_p95']:.1f} ms p95 from a frame's capture at the "
                     f"sender to its frame out (clock offset {r['clock_offset_ms']:.3f} ms, "
                     f"delay {r['clock_delay_ms']:.3f} ms)")
    grow = [f"{side} {r[side + '_rss_mb']:.0f} MB, grew {r[side + '_rss_growth_mb']:+.1f} MB"
            for side in ("sender", "receiver") if r[side + "_rss_growth_mb"] is not None]
    if grow:
        lines.append(f"memory: {'; '.join(grow)} after warm-up; "
                     f"{_verdict(r['met']['memory'])} < {TARGET_GROWTH_MB:g} MB")
    if r["not_measured"]:
        lines.append(f"not measured: {', '.join(r['not_measured'])} (a longer loopback run "
                     f"gives them)")
    return "\n".join(lines)


def speed(model_path: str | os.PathLike[str], source: str | os.PathLike[str],
          frames: slice | None = None, progress: Progress = no_progress,
          loopback_s: float = LOOPBACK_S) -> tuple[dict[str, Any], list[str]]:
    """Run ``measure_speed``: its result and the report's lines (targets inform: a miss is
    no failure)."""
    result = measure_speed(model_path, source, frames, progress, loopback_s)
    return result, format_speed(result).splitlines()


def _verdict(met: bool) -> str:
    return "met" if met else "MISSED"


def _time_sender(model: Any, source: Path, frames: slice, info: Any, progress: Progress
                 ) -> tuple[dict[str, Any], list[bytes], Any]:
    """Run the sender pipeline over the range: median stage times (module docstring), the
    packets it made and its Hello."""
    total = frames_in_range(frames, info.frames)
    pipeline = SenderPipeline(model, estimate_intrinsics(info.width, info.height),
                              rate_hz=stream_rate(info.rate_hz), identify_apart=True)
    tracked: list[float] = []
    detect: list[float] = []
    identify: list[float] = []
    stages: dict[str, list[float]] = {k: [] for k in SENDER_STAGES}
    totals: list[float] = []
    missing = 0
    n = 0
    updates = 0
    packets: list[bytes] = []
    shape: tuple[int, ...] = ()
    with _one_blas_thread(), contextlib.closing(pipeline):
        for frame in progress(read_frames(source, frames), "sender", total):
            n += 1
            shape = frame.image.shape
            out = pipeline.process(frame.image, frame.time)
            packets.append(out.packet)
            updates += out.update is not None
            ms = {k: v * 1000 for k, v in out.timings.items()}
            totals.append(sum(ms[k] for k in SENDER_STAGES))
            stages["pack"].append(ms["pack"])
            if out.identified:
                identify.append(ms["track"])
            if out.points is None:
                missing += 1
                continue
            for k in _FACE_STAGES:
                if k in ("sample", "classify", "learn") and out.offsets is None:
                    continue
                stages[k].append(ms[k])
            (detect if out.detected else tracked).append(ms["track"])
    if n == 0:
        raise VideoError(f"{source}: no frames in range {range_text(frames)}")
    if missing == n:
        raise NoFaceError(f"{source}: no face found in any of its {n} frames "
                          f"(range {range_text(frames)})")
    sender_ms = float(np.median(totals))
    timings = {
        "frames": n,
        "tracked_frames": len(tracked),
        "detect_frames": len(detect),
        "no_face_frames": missing,
        "width": int(shape[1]),
        "height": int(shape[0]),
        "track_ms": _median(tracked),
        "track_detect_ms": _median(detect),
        **{f"{k}_ms": _median(stages[k]) for k in SENDER_STAGES[1:]},
        "learn_ms_per_frame": None if not stages["learn"] else round(
            float(np.mean(stages["learn"])), 4),
        "learn_updates": updates,
        "regions": len(pipeline.sampler.names),
        "sender_ms_median": round(sender_ms, 4),
        "sender_ms_mean": round(float(np.mean(totals)), 4),
        "identify_frames": len(identify),
        "identify_ms": _median(identify),
        "sender_fps": round(1000.0 / sender_ms, 2),
    }
    return timings, packets, pipeline.hello()


def _time_receiver(model: Any, packets: list[bytes], camera: Any, size: tuple[int, int],
                   keep: int = 0) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The receiver's per-frame work on the sender's packets (module docstring): decode here,
    morph, render and read back in the render process at ``size``, medians in ms; and the
    first ``keep`` frames rendered, (H, W, 3) uint8 RGB."""
    width, height = size
    decode, total = [], []
    images: list[np.ndarray] = []
    with RenderProcess(model, width, height, camera) as renderer:
        last = time.perf_counter()

        def collect() -> None:
            nonlocal last
            image = renderer.collect()
            now = time.perf_counter()
            if len(renderer.render_seconds) > RECEIVER_WARMUP:
                total.append((now - last) * 1000)
            last = now
            if len(images) < keep:
                images.append(image)

        for k, packet in enumerate(packets):
            t0 = time.perf_counter()
            frame = decode_packet(packet)
            t1 = time.perf_counter()
            if k >= RECEIVER_WARMUP:
                decode.append((t1 - t0) * 1000)
            if renderer.in_flight == renderer.depth:
                collect()
            renderer.submit(FrameState(frame.seq, frame.rotation, frame.translation,
                                       frame.residuals, frame.q, frame.flags, "received", 1.0,
                                       shade=frame.shade))
        while renderer.in_flight:
            collect()
        render = [t * 1000 for t in list(renderer.render_seconds)[RECEIVER_WARMUP:]]
    receiver_ms = float(np.median(total)) if total else float("nan")
    return {"decode_ms": _median(decode), "render_ms": _median(render),
            "receiver_ms_median": round(receiver_ms, 4),
            "receiver_fps": round(1000.0 / receiver_ms, 2) if total else 0.0,
            "receiver_size": f"{width}x{height}"}, images


def _time_encode(images: list[np.ndarray], rate_hz: float) -> float | None:
    """Median ms the ``VideoWriter`` thread takes to encode one of ``images`` (K, H, W, 3
    uint8 RGB), after ``RECEIVER_WARMUP``; None with too few frames."""
    if not images:
        return None
    height, width = images[0].shape[:2]
    with tempfile.TemporaryDirectory(prefix="facewire-speed-") as tmp, \
            VideoWriter(Path(tmp) / "out.mp4", width, height, rate_hz) as writer:
        for image in images:
            writer.write(image)
    return _median([t * 1000 for t in list(writer.consume_seconds)[RECEIVER_WARMUP:]])


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 4) if values else None


def _time_morph(rig: Rig) -> float:
    """Median ms of ``rig.morph`` over ``MORPH_CALLS`` calls with residuals in +-RESIDUAL_MM."""
    rng = np.random.default_rng(0)
    pool = rng.uniform(-RESIDUAL_MM, RESIDUAL_MM, (64, N_RESIDUALS, 3)).astype(np.float32)
    for k in range(MORPH_WARMUP):
        rig.morph(pool[k % len(pool)])
    times = np.empty(MORPH_CALLS)
    for k in range(MORPH_CALLS):
        r = pool[k % len(pool)]
        start = time.perf_counter()
        rig.morph(r)
        times[k] = time.perf_counter() - start
    return float(np.median(times)) * 1000


def _time_morph_pinned(rig: Rig) -> tuple[float, str]:
    """``_time_morph`` with every loaded OpenBLAS pinned to one thread; and what was pinned."""
    with _one_blas_thread() as pinned:
        ms = _time_morph(rig)
    if not pinned:
        return ms, "no OpenBLAS found to pin: morph timed with the default BLAS threads"
    libs = ", ".join(f"{name} ({before} -> 1)" for name, before in pinned)
    return ms, f"morph timed with BLAS pinned to 1 thread: {libs}; tracking: dlib, 1 thread"


@contextlib.contextmanager
def _one_blas_thread() -> Iterator[list[tuple[str, int]]]:
    """Set every loaded OpenBLAS to one thread; yield [(library name, previous count)]."""
    controls = []
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in _BLAS_SYMBOLS:
            if hasattr(lib, get_name) and hasattr(lib, set_name):
                get, put = getattr(lib, get_name), getattr(lib, set_name)
                get.restype, get.argtypes = ctypes.c_int, []
                put.restype, put.argtypes = None, [ctypes.c_int]
                controls.append((Path(path).name, get, put))
                break
    pinned = []
    try:
        for name, get, put in controls:
            before = int(get())
            put(1)
            pinned.append((name, before, put))
        yield [(name, before) for name, before, _ in pinned]
    finally:
        for _, before, put in pinned:
            put(before)


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries mapped into this process (Linux); [] elsewhere."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return []
    paths = []
    for line in maps.splitlines():
        path = line.split(maxsplit=5)[-1] if line.count(" ") >= 5 else ""
        if "openblas" in Path(path).name.lower() and path not in paths:
            paths.append(path)
    return paths
