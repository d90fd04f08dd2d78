"""Whether a view's pixels line up with the others', texel by texel: sharp frames, local
correlation with the consensus, and the doubled-feature measure.

Issue 16's third reproduction (``bench.reproductions``: openface_multi_face, the man with
glasses talking and laughing, his head moving at some 220 mm/s, enrolled from 2.4 s) built
a texture with a doubled glasses rim and smeared lips: the neutral frame the fit chose
(frame 211) was motion-blurred (its sharpness b, ``sender.clean.sharpness``,
72 against the range's median of 138), and the base texture is that frame wherever it is
not an outlier. A blurred or slipped view is no outlier in colour: its skin is the skin
every view sees, only its edges are elsewhere. So two tests, both on structure:

1. Sharp frames (``sharp_frames``). A frame is sharp when b >= ``SHARP_RATIO`` (0.6) times
   the median b of the frames with a face. The build chooses the neutral frame among the
   sharp frames (``sender.enroll.fit.fit_person``'s ``neutral_among``), so the frame that
   makes most of the texture and every rest layer is not badly smeared. Measured
   (``bench.reproductions``, docs/DESIGN.md §8), on the fast motion: the fit's own choice
   is frame 211 (b 72, doubled glasses rims and lips); with a ratio of 1 (the sharper
   half) it became 201 (b 151: one rim, one mouth, but a less neutral face: held-out NME
   3.38 % against 2.80 %, face SSIM 0.765 against 0.815), with 0.8 241 (b 136, the lips
   apart), with 0.6 208 (b 88, still somewhat smeared; held-out NME 2.78 %, face SSIM
   0.789). A ratio of 1 also moved the neutral frame of ordinary clips: on openface_default
   0:90 the blinks then read worse against OpenFace (F1 0.67 against 0.80 with 0.6 or
   without the rule) and lp_d3 0:90 and 240:330 took other neutral frames; 0.6 keeps them.

2. Local alignment (``local_misfit``). Per covered texel seen by at least three views,
   the consensus m is the weighted median of the luma of the views that take part there
   (``sender.enroll.fusion``). For each view i, over the texels it shares with the
   consensus, the normalised cross-correlation in the ``WINDOW`` x ``WINDOW`` (31 x 31)
   texel square around each texel,

       ncc = cov(y_i, m) / sqrt(var(y_i) var(m)),

   box-filtered sums over the shared texels only (at least half the square), is judged
   where the consensus has structure there: its local standard deviation at least
   ``STRUCTURE_STD`` (8 grey levels; skin alone has 2-5 in these clips, an eye, a brow, a
   lip line or a glasses rim 15-40). Where ncc < ``MIN_NCC`` (0.5), the view does not
   line up with the others (a feature slipped, smeared or doubled in it; lips in another
   expression), and it takes no part in the square's texels (the square around each
   misfit centre: the misplaced copy of a feature may lie anywhere in the window). One
   view is judged against a median of all, so a single doubled view cannot pull the
   consensus to itself; the fusion then takes the texel from a view that lines up (its
   ``replace`` step), one view per patch, and no feature is shown twice. At 1024 x 2048
   texels a face of 70 px between the eyes spans some 5 texels per pixel, so the window
   is six pixels of the image: wide enough to hold a feature and its copy two or three
   pixels away.

3. The doubled-feature measure (``doubled_fraction``): the same correlation between a
   texture's luma and the consensus, over a part of the face (the eyes, the brows, the
   mouth), as the fraction of its structured texels where ncc < ``MIN_NCC``: a texture
   that blends two misaligned views, or shows a smeared one, has its features where the
   consensus has none and the other way round. The build reports it (``texture_evidence``
   ``doubled``) and the tests assert on it.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from facewire.sender.clean import SHARP_RATIO

WINDOW = 31  # texels: the square of the local correlation
MIN_NCC = 0.7  # a view (or a texture) correlating less with the consensus does not line up
STRUCTURE_STD = 8.0  # grey levels: the consensus's local deviation for a window to be judged
_MIN_SHARE = 0.5  # of the window's texels a view must share with the consensus there


def sharp_frames(sharpness: Sequence[float], present: Sequence[bool]) -> list[int]:
    """The frames whose sharpness is at least ``SHARP_RATIO`` times the median of the
    ``present`` frames' (module docstring, 1): indices into ``sharpness``; all present
    frames when their median is 0."""
    b = np.asarray(sharpness, np.float64)
    ok = np.asarray(present, bool)
    if not ok.any():
        return []
    ref = float(np.median(b[ok]))
    return [int(i) for i in np.flatnonzero(ok & (b >= SHARP_RATIO * ref))]


def local_ncc(y: np.ndarray, m: np.ndarray, shared: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """The windowed correlation of two (H, W) float32 images over their ``shared`` (H, W)
    bool texels (module docstring, 2): (H, W) float32 ncc, and (H, W) bool where it is
    judged (enough shared texels, and the consensus ``m`` structured there)."""
    size = (WINDOW, WINDOW)
    s = shared.astype(np.float32)
    ys, ms = y * s, m * s

    def box(a: np.ndarray) -> np.ndarray:
        return np.asarray(cv2.boxFilter(a, -1, size, normalize=False,
                                        borderType=cv2.BORDER_CONSTANT), np.float32)

    n = box(s)
    safe = np.maximum(n, 1.0)
    my, mm = box(ys) / safe, box(ms) / safe
    vy = box(ys * y) / safe - my * my
    vm = box(ms * m) / safe - mm * mm
    cov = box(ys * m) / safe - my * mm
    ncc = cov / np.sqrt(np.maximum(vy, 1e-6) * np.maximum(vm, 1e-6))
    judged = shared & (n >= _MIN_SHARE * WINDOW * WINDOW) & (vm >= STRUCTURE_STD ** 2)
    return ncc, judged


def local_misfit(luma: np.ndarray, seen: np.ndarray, centre: np.ndarray,
                 consensus: np.ndarray, covered: np.ndarray, features: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each view does not line up with the consensus (module docstring, 2).

    Args:
        luma: (V, K) float32 each view's luma at the covered texels.
        seen: (V, K) bool, the view sees the texel.
        centre: (K,) float32 the consensus's luma (any value where not ``consensus``).
        consensus: (K,) bool, the texels with a consensus (seen by at least three views).
        covered: (H, W) bool, the covered texels (the K columns, row-major).
        features: (H, W) bool, the texels judged (the parts of the face); all when None.

    Returns:
        (V, K) bool: the view takes no part at the texel; (H, W) bool, the windows where
        the consensus holds (most judged views line up with it); and (H, W) bool, the
        windows judged where it does not (a texel no view was judged at, skin without
        structure, is in neither).
    """
    m = np.zeros(covered.shape, np.float32)
    m[covered] = np.where(consensus, centre, 0.0)
    box = _around(features, covered.shape)  # the windows that can be judged
    good = np.zeros(covered.shape, np.int32)
    count = np.zeros(covered.shape, np.int32)
    bads = []
    for i in range(len(luma)):
        shared = np.zeros(covered.shape, bool)
        shared[covered] = seen[i] & consensus
        y = np.zeros(covered.shape, np.float32)
        y[covered] = luma[i]
        judged = np.zeros(covered.shape, bool)
        ncc = np.zeros(covered.shape, np.float32)
        ncc[box], judged[box] = local_ncc(y[box], m[box], shared[box])
        if features is not None:
            judged &= features
        bad = judged & (ncc < MIN_NCC)
        good += judged & ~bad
        count += judged
        bads.append(bad)
    holds = (count > 0) & (2 * good > count)
    out = np.zeros(seen.shape, bool)
    grow = np.ones((WINDOW, WINDOW), np.uint8)
    for i, bad in enumerate(bads):
        bad &= holds
        if bad.any():
            out[i] = cv2.dilate(bad.astype(np.uint8), grow)[covered].astype(bool) & seen[i]
    return out, holds, (count > 0) & ~holds


def _around(features: np.ndarray | None, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The rectangle of an (H, W) texture holding the ``features`` (H, W) bool texels and
    every texel within ``WINDOW`` of them (all of it when None): outside it no window is
    judged, and the windows inside it see the same texels as on the whole texture."""
    if features is None or not features.any():
        return slice(0, shape[0]), slice(0, shape[1])
    rows, cols = np.nonzero(features)
    return (slice(max(int(rows.min()) - WINDOW, 0), min(int(rows.max()) + WINDOW + 1, shape[0])),
            slice(max(int(cols.min()) - WINDOW, 0), min(int(cols.max()) + WINDOW + 1, shape[1])))


def doubled_fraction(texture_luma: np.ndarray, consensus: np.ndarray, judged: np.ndarray,
                     area: np.ndarray) -> float:
    """The doubled-feature measure (module docstring, 3): of the texels in ``area`` where
    the (H, W) float32 ``consensus`` is judged and structured, the fraction where the (H, W)
    float32 ``texture_luma`` correlates with it below ``MIN_NCC``; 0 when none is judged.
    ``judged``: (H, W) bool, the texels that have a consensus; ``area`` (H, W) bool, best
    restricted to where it holds (``local_misfit``)."""
    ncc, ok = local_ncc(texture_luma, consensus, judged)
    ok &= area
    if not ok.any():
        return 0.0
    return float((ncc[ok] < MIN_NCC).mean())


def weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K,) the weighted median over axis 0 of (V, K) values with (V, K) weights >= 0: the
    smallest value whose cumulative weight reaches half the total (NaN where it is 0)."""
    order = np.argsort(np.where(weights > 0, values, np.inf), axis=0)
    v = np.take_along_axis(values, order, axis=0)
    w = np.take_along_axis(weights, order, axis=0)
    cum = np.cumsum(w, axis=0)
    half = 0.5 * cum[-1]
    pick = np.argmax(cum >= half[None] - 1e-9 * np.maximum(half[None], 1.0), axis=0)
    out = v[pick, np.arange(values.shape[1])]
    return np.where(cum[-1] > 0, out, np.nan)
