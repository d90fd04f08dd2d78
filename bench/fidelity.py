"""Appearance fidelity: the face box, grayscale SSIM, PSNR, and an x264 reference encode.

Face box (``face_box``). From the 68 tracked landmarks (pixels, x right, y down), with
``(xa, ya)``-``(xb, yb)`` their bounding box, ``w = xb - xa`` and ``h = yb - ya`` (brow top
to chin):

    x0 = xa - margin * w               x1 = xb + margin * w
    y0 = ya - (margin + forehead) * h  y1 = yb + margin * h

``margin = 0.1`` on every side; ``forehead = 0.3`` more above the brows, because the 68
points stop at the brows while the face goes on to the hairline (about half the brow-chin
height on an average face; 0.4 h above the brows reaches near the hairline on the shared
clips without taking in much hair). The corners are rounded outward to whole pixels and
clipped to the image; the box is returned as ``(x0, y0, x1, y1)`` with ``x1``, ``y1``
exclusive: the crop is ``image[y0:y1, x0:x1]``.

SSIM (``gray_ssim``), Wang, Bovik, Sheikh and Simoncelli 2004, on the grey levels
(``cv2.COLOR_BGR2GRAY`` of a 3-channel BGR image; a 2-D image is taken as grey):

    mu_x = G * x,   sigma_x^2 = G * x^2 - mu_x^2,   sigma_xy = G * (x y) - mu_x mu_y
    SSIM(x, y) = mean over the window centres of
                 (2 mu_x mu_y + C1) (2 sigma_xy + C2)
                 -----------------------------------------------------
                 (mu_x^2 + mu_y^2 + C1) (sigma_x^2 + sigma_y^2 + C2)

with ``G`` the 11x11 Gaussian window of sigma 1.5 (normalised to sum 1), ``C1 = (K1 L)^2``,
``C2 = (K2 L)^2``, ``K1 = 0.01``, ``K2 = 0.03``, ``L = 255``. The filtering is
``cv2.GaussianBlur`` in float64; only centres whose whole window lies inside the image are
averaged (the 5-pixel border is dropped, as the paper's "valid" filtering and
``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=255)`` do). The images are not downsampled first
(the authors' later ``ssim.m`` downsamples images larger than 256 px; the paper does not).

PSNR (``psnr``): ``10 log10(255^2 / MSE)`` dB over every value of the two arrays as given
(pass grey images for a grayscale PSNR); ``inf`` when they are identical.

x264 reference (``x264_reference``): what a conventional codec does at a comparable rate.
The clip is encoded with PyAV's libx264, preset veryslow, tune ssim, yuv420p, x264's own
GOP (a keyframe at most every 250 frames, and at scene cuts), B-frames and lookahead, and
x264's frame threading (PyAV otherwise asks for slice threads, which on openface_default.wmv
cost x264 a fifth to a quarter more bits at equal SSIM). Rate control is x264's two-pass
ABR, its way to hit a file size: pass 1 (no file) writes statistics at the rate asked, pass
2 spends the bits by them (``b`` = the rate asked, whole kbit/s, x264's unit, at least 1).
The stream's rate, ``kbps = packet bytes * 8 / (frames / rate_hz) / 1000`` (the sizes of
the H.264 packets x264 put out, summed as they are muxed: what a conventional stream would
carry, without the MP4 container's index and headers, ``file_kbps``), is then compared with
the target: more than ``RATE_TOLERANCE`` (5 %) off, both passes run
again with the rate asked scaled by target / actual (at most ``CORRECTIONS`` = 2 times;
stopping early when a run comes no nearer or its rate moved by no more than the tolerance),
and the file nearest the target is kept. Pass 1 always runs at pass 2's rate: statistics
gathered at another rate spend the bits worse (openface_default.wmv, pass 1 at 15 and pass
2 at 10 kbit/s: face SSIM 0.66; both at 10: 0.70).

Below what x264 can do, it either refuses to open pass 2 ("estimated minimum is N kbps":
the rate asked is raised to N + 1, N being printed rounded, and both passes run again) or
codes every frame at QP 51, the coarsest H.264 allows: the result is then the lowest rate
x264 reaches on the clip, and that rate is what is reported, not the target. On
openface_default.wmv (640x480, 15 Hz, 288 frames) the floor is 17-18 kbit/s for the file
(16-16.5 for the stream), with face-box grey SSIM 0.70 and grey PSNR 21.2-21.3 dB (issue 6
report); until issue 16 the rate reported and aimed at was the file's. The file is decoded back with
``models.infra.video.read_frames`` to BGR frames, as many as went in. PyAV's log level is
process-wide: while a pass runs it is raised to WARNING (if lower) and x264's messages, from
every thread, are captured rather than printed.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import av.logging
import cv2
import numpy as np

from facewire.models.infra.video import read_frames
from facewire.models.landmarks import N_LANDMARKS

MARGIN = 0.1
FOREHEAD = 0.3

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2, SSIM_L = 0.01, 0.03, 255.0

X264_PRESET = "veryslow"
X264_TUNE = "ssim"
MAX_RAISES = 5
CORRECTIONS = 2
RATE_TOLERANCE = 0.05


def face_box(points: np.ndarray, width: int, height: int, margin: float = MARGIN,
             forehead: float = FOREHEAD) -> tuple[int, int, int, int]:
    """The face box of a frame from its tracked landmarks (see the module docstring).

    Args:
        points: (68, 2) landmarks, pixels (x right, y down).
        width, height: the image size, pixels.
        margin: growth of the landmarks' box on every side, fraction of its width/height.
        forehead: further growth above, fraction of the box's height.

    Returns:
        ``(x0, y0, x1, y1)`` ints, ``0 <= x0 < x1 <= width``, ``0 <= y0 < y1 <= height``.

    Raises:
        ValueError: bad points, size or margins, or a box entirely outside the image.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (N_LANDMARKS, 2) or not np.isfinite(points).all():
        raise ValueError(f"points: expected finite ({N_LANDMARKS}, 2), got {points.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"image size: expected positive, got {width}x{height}")
    if margin < 0 or forehead < 0:
        raise ValueError(f"margin {margin}, forehead {forehead}: expected >= 0")
    (xa, ya), (xb, yb) = points.min(axis=0), points.max(axis=0)
    w, h = xb - xa, yb - ya
    x0 = max(math.floor(xa - margin * w), 0)
    y0 = max(math.floor(ya - (margin + forehead) * h), 0)
    x1 = min(math.ceil(xb + margin * w) + 1, width)
    y1 = min(math.ceil(yb + margin * h) + 1, height)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"face box ({x0}, {y0}, {x1}, {y1}) lies outside the "
                         f"{width}x{height} image")
    return x0, y0, x1, y1


def face_mask(points: np.ndarray, box: tuple[int, int, int, int],
              forehead: float = FOREHEAD) -> np.ndarray:
    """The face itself inside a face box: the convex hull of the jaw line (iBUG 0-16) and the
    brows (17-26) raised by ``forehead`` times the landmarks' height, so that neither the
    background nor the hair around the face is measured.

    Args:
        points: (68, 2) landmarks, pixels.
        box: ``face_box`` of the same points.
        forehead: how far the brows are raised, fraction of the landmarks' height.

    Returns:
        (y1 - y0, x1 - x0) bool mask, True on the face.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (N_LANDMARKS, 2) or not np.isfinite(points).all():
        raise ValueError(f"points: expected finite ({N_LANDMARKS}, 2), got {points.shape}")
    x0, y0, x1, y1 = box
    height = float(np.ptp(points[:, 1]))
    brows = points[17:27] - [0.0, forehead * height]
    outline = np.vstack([points[:17], brows]) - [x0, y0]
    hull = cv2.convexHull(np.rint(outline).astype(np.int32))
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask > 0


def gray_ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM of the grey levels of two images (see the module docstring).

    Args:
        a, b: (H, W) uint8 grey or (H, W, 3) uint8 BGR images of the same shape, H and W
            at least 11 (the window).
        mask: (H, W) bool, the pixels whose SSIM is averaged (with the window inside the
            image); all when None.

    Returns:
        SSIM in [-1, 1]; 1 for identical images.
    """
    x, y = _gray(a, "a"), _gray(b, "b")
    if x.shape != y.shape:
        raise ValueError(f"images differ in size: {x.shape} vs {y.shape}")
    if min(x.shape) < SSIM_WINDOW:
        raise ValueError(f"image {x.shape}: SSIM needs at least {SSIM_WINDOW}x{SSIM_WINDOW}")
    c1, c2 = (SSIM_K1 * SSIM_L) ** 2, (SSIM_K2 * SSIM_L) ** 2

    def blur(image: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(image, (SSIM_WINDOW, SSIM_WINDOW), SSIM_SIGMA,
                                sigmaY=SSIM_SIGMA, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    ssim = ((2 * mx * my + c1) * (2 * sxy + c2)
            / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    r = SSIM_WINDOW // 2
    inside = np.zeros(x.shape, bool)
    inside[r:-r, r:-r] = True
    if mask is not None:
        if np.shape(mask) != x.shape:
            raise ValueError(f"mask: expected shape {x.shape}, got {np.shape(mask)}")
        inside &= np.asarray(mask, bool)
    if not inside.any():
        raise ValueError("mask: no pixel with its SSIM window inside the image")
    return float(ssim[inside].mean())


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for 8-bit data: ``10 log10(255^2 / MSE)``.

    Args:
        a, b: uint8 arrays of the same shape (every value counts).

    Returns:
        dB; ``inf`` when the arrays are equal.
    """
    for name, image in (("a", a), ("b", b)):
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.size == 0:
            raise ValueError(f"{name}: expected a non-empty uint8 array")
    if a.shape != b.shape:
        raise ValueError(f"arrays differ in shape: {a.shape} vs {b.shape}")
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    """(H, W) float64 grey levels of a uint8 grey or BGR image."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"{name}: expected a uint8 image")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"{name}: expected (H, W) or (H, W, 3), got {image.shape}")
    return image.astype(np.float64)


@dataclass(frozen=True, eq=False)
class X264Result:
    """An x264 reference encode.

    Attributes:
        frames: the decoded frames, (H, W, 3) uint8 BGR, as many as were encoded.
        kbps: actual rate, kbit/s, of the H.264 stream: the encoded packets' bytes, no
            container (what ``bench quality`` reports as ``h264_kbps``).
        file_kbps: actual rate of the whole ``.mp4`` file, container included, kbit/s.
        asked_kbps: the bit rate given to x264's second pass for this file (whole kbit/s:
            the unit of x264's ``bitrate``).
        path: the ``.mp4`` file.
    """

    frames: list[np.ndarray]
    kbps: float
    file_kbps: float
    asked_kbps: int
    path: Path


def x264_reference(frames: list[np.ndarray], rate_hz: float, target_kbps: float,
                   workdir: str | os.PathLike[str]) -> X264Result:
    """Encode frames with two-pass x264 (veryslow, tune ssim) near a target rate, decode back.

    Args:
        frames: (H, W, 3) uint8 BGR images, all the same size, H and W even.
        rate_hz: the clip's frame rate, > 0.
        target_kbps: the stream rate to aim at (packet bytes, no container), kbit/s, > 0.
        workdir: an existing folder; ``x264_<target>kbps.mp4`` is written there (the pass-1
            statistics and the discarded pass-2 files go there too and are removed).

    Returns:
        The decoded frames, the actual rates and the file (see ``X264Result``).

    Raises:
        ValueError: bad frames, rate, target or folder; x264 failing (names the file).
    """
    if not frames:
        raise ValueError("frames: empty")
    shape = frames[0].shape
    if len(shape) != 3 or shape[2] != 3 or shape[0] % 2 or shape[1] % 2:
        raise ValueError(f"frames: expected (H, W, 3) with H and W even (4:2:0), got {shape}")
    for i, image in enumerate(frames):
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != shape:
            raise ValueError(f"frames[{i}]: expected a {shape} uint8 array")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz: expected > 0, got {rate_hz}")
    if not (math.isfinite(target_kbps) and target_kbps > 0):
        raise ValueError(f"target_kbps: expected > 0, got {target_kbps}")
    workdir = Path(workdir)
    if not workdir.is_dir():
        raise ValueError(f"{workdir}: not a folder")
    path = workdir / f"x264_{target_kbps:g}kbps.mp4"
    stats = workdir / f"x264_{target_kbps:g}kbps.stats"
    rate = Fraction(rate_hz).limit_denominator(1001)
    seconds = len(frames) / rate_hz
    tries: list[tuple[float, float, int, Path]] = []  # (kbps, stream kbps, asked, file)
    try:
        asked, lowest = max(round(target_kbps), 1), 1
        for k in range(CORRECTIONS + 1):
            attempt = path.with_name(f"{path.stem}.try{k}.mp4")
            used, stream_bytes = _two_pass(frames, rate, asked, stats, attempt)
            if used > asked:
                lowest = used
            tries.append((stream_bytes * 8 / seconds / 1000,
                          attempt.stat().st_size * 8 / seconds / 1000, used, attempt))
            miss = tries[-1][0] / target_kbps
            if abs(miss - 1) <= RATE_TOLERANCE:
                break
            if k > 0 and (abs(tries[-1][0] - target_kbps) >= abs(tries[-2][0] - target_kbps)
                          or abs(tries[-1][0] / tries[-2][0] - 1) <= RATE_TOLERANCE):
                break  # no nearer, or the rate no longer follows the request: x264's floor
            asked = max(round(used / miss), lowest)
            if asked in (t[2] for t in tries):
                break
        kbps, file_kbps, asked, best = min(tries, key=lambda t: abs(t[0] - target_kbps))
        best.replace(path)
    finally:
        for leftover in [*workdir.glob(stats.name + "*"), *workdir.glob(f"{path.stem}.try*")]:
            leftover.unlink(missing_ok=True)
    decoded = [f.image for f in read_frames(path)]
    if len(decoded) != len(frames):
        raise ValueError(f"{path}: decoded {len(decoded)} frames of {len(frames)} encoded")
    return X264Result(decoded, kbps, file_kbps, asked, path)


def _two_pass(frames: list[np.ndarray], rate: Fraction, kbps: int, stats: Path, path: Path
              ) -> tuple[int, int]:
    """Passes 1 and 2 at ``kbps`` into ``path``. While x264 refuses pass 2, the rate is
    raised to its estimated minimum plus 1 kbit/s (it prints the estimate rounded) and both
    passes run again at that rate. Returns the rate used and the packet bytes of pass 2."""
    for _ in range(MAX_RAISES):
        _encode(frames, rate, kbps, stats, None)
        try:
            return kbps, _encode(frames, rate, kbps, stats, path)
        except _X264Refused as refusal:
            if refusal.minimum is None:
                raise ValueError(f"{path}: x264 failed: {refusal}") from None
            kbps = max(math.ceil(refusal.minimum), kbps) + 1
    raise ValueError(f"{path}: x264 refused {MAX_RAISES} pass-2 rates up to {kbps} kbit/s")


class _X264Refused(Exception):
    """x264 would not open a pass; ``minimum`` is its estimated minimum rate if it gave one."""

    def __init__(self, message: str, minimum: float | None) -> None:
        super().__init__(message)
        self.minimum = minimum


def _encode(frames: list[np.ndarray], rate: Fraction, kbps: int, stats: Path,
            path: Path | None) -> int:
    """One x264 pass at ``kbps``: pass 1 when ``path`` is None (statistics only, no file),
    else pass 2 into ``path``. x264's messages are captured, not printed (PyAV's log level
    is raised to WARNING for the pass, so that its refusals carry x264's reason).

    Returns:
        The bytes of H.264 packets produced.

    Raises:
        _X264Refused: pass 2 did not open (e.g. a rate below x264's estimated minimum).
        ValueError: any other encoding or writing failure, naming the file.
    """
    h, w = frames[0].shape[:2]
    options = {"preset": X264_PRESET, "tune": X264_TUNE, "b": str(kbps * 1000),
               "stats": str(stats)}
    flag = av.codec.context.Flags.pass1 if path is None else av.codec.context.Flags.pass2
    name = "x264 pass 1" if path is None else str(path)
    total = 0
    level = av.logging.get_level()
    if level is None or level < av.logging.WARNING:
        av.logging.set_level(av.logging.WARNING)
    try:
        with av.logging.Capture(local=False) as captured:
            try:
                with av.open(os.devnull if path is None else str(path), "w",
                             format="null" if path is None else "mp4") as container:
                    stream = container.add_stream("libx264", rate=rate, options=options,
                                                  time_base=1 / rate)
                    stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
                    stream.codec_context.thread_type = "FRAME"
                    stream.codec_context.flags = int(stream.codec_context.flags) | int(flag)
                    try:
                        stream.codec_context.open()
                    except av.FFmpegError as exc:
                        text = " ".join([str(exc)] + [m.strip() for _, _, m in captured])
                        if path is None:
                            raise ValueError(f"{name}: x264 failed: {text}") from None
                        raise _X264Refused(text, _estimated_minimum(text)) from None
                    for i, image in enumerate(frames):
                        frame = av.VideoFrame.from_ndarray(image, format="bgr24")
                        frame.pts, frame.time_base = i, 1 / rate
                        for packet in stream.encode(frame):
                            total += packet.size
                            container.mux(packet)
                    for packet in stream.encode():
                        total += packet.size
                        container.mux(packet)
            except av.FFmpegError as exc:
                raise ValueError(f"{name}: x264 failed: {exc}") from None
    finally:
        av.logging.set_level(level)
    return total


def _estimated_minimum(message: str) -> float | None:
    """x264's "estimated minimum is N kbps" from its refusal to open pass 2, if present."""
    match = re.search(r"estimated minimum is (\d+(?:\.\d+)?) kbps", message)
    return float(match.group(1)) if match else None
