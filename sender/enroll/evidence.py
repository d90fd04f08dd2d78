"""Clean evidence for the base texture: which enrollment frames it is fused from.

The base texture (``sender.enroll.fusion.fuse_views``) is a robust estimate across views,
and a median is only right when the clean views carry more than half of the weight. So the
views are chosen clean, and spread in time, before they are fused; after the fusion, the
views that were outliers over a part of the face tell which frames were occluded there.

1. Score (``frame_scores``). Every frame with a pose against the fitted mesh gets

       cost = expression + pose + blur,

   with expression and pose the fit's neutral costs (``sender.enroll.fit.frame_costs``:
   eyes open, lips closed, mouth at its usual width, the landmarks' residual against the
   fitted model, the head frontal and at its usual pitch), and

       blur = (max(0, 1 - b / median b) / 0.25)^2,

   b the sharpness of the face box (``sender.clean.sharpness``: the variance of the
   Laplacian of the grey landmarks' box at ``BLUR_BOX_PX`` wide). A frame whose landmarks
   do not line up with the fitted model, an RMS residual over the stable points (17-67)
   above ``MISFIT_RATIO`` (2) times the video's median, is not a candidate at all: a tracking
   slip puts every feature a few pixels off, and its texture would ghost.

2. Choose (``texture_views``): the neutral frame first (it sets the exposure), then the
   fit's side views (for the texture beyond the front) when they are candidates (these are
   the fusion's primary views: they make the texture wherever none of them is an outlier),
   then the lowest-cost candidates, each at least ``gap`` frames from every view taken (an occluder
   or an expression held for a second is in consecutive frames: spaced views are
   independent evidence), up to ``TEXTURE_VIEWS`` views; ``gap`` is the range's length over
   twice that count, at least 1.

3. Judge (``occluded_parts``). After the fusion, each part of the face (``PARTS``: the
   mouth, each eye, the nose, the brows; in texture space the UV bounding box of the
   part's landmark vertices, grown by ``PART_MARGIN`` of its size on every side) is judged
   per view: a view that was an outlier (``Fusion.outlier_fraction``) on more than
   ``OCCLUDED_FRACTION`` of the part's texels it sees was occluded there (or showed an
   expression the others did not). ``sender.enroll.build`` takes the neutral frame again
   from the clean views (``clean_views``: aligned, and occluded over none of
   ``NEUTRAL_PARTS``, the mouth and the nose) when the first neutral was not clean: the
   neutral frame also gives the regions' rest layers, which are painted over the base
   texture. The eyes and brows do not count there: a neutral frame looking up while most
   views look ahead is an outlier over its eyes, and on lp_d3 (a skin patch over the mouth
   in frames 20-59 of 0:140) taking the neutral again for that replaced an open-eyed
   frame by one looking down; the fusion still replaces such a patch of the texture.

4. Every frame, for the regions' layers (``ring_occluded``, called by
   ``sender.enroll.layers``): the layers take one frame per state, chosen by a landmark cue,
   and a dark occluder over the mouth reads as an open mouth to the tracker, so the mouth's
   open states would show the occluder. Each region's part (``REGION_PARTS``) is judged on
   each frame on the skin *around* it, which the part's own expressions barely change (a
   blink moves the lids, not the skin beside the eye; a jaw drop is followed by the morph):
   the ring between the part's box grown by ``RING_INNER`` and by ``RING_OUTER`` of its
   size, read from the frame on the morphed, posed mesh like a layer, its colours scaled per
   channel by the ratio of medians to the base texture's (exposure), and compared with the
   base texture in luma. When more than ``RING_OCCLUDED_FRACTION`` (15 %) of the ring's seen
   texels depart by more than ``RING_DEPART_LEVELS`` grey levels, the part is occluded in
   that frame and the region takes nothing from it: neither a layer nor its cue's
   percentiles (the check is ``sender.clean``'s, shared with the sender's learning). The
   parts judged (``REGION_PARTS``) are the mouth, for the mouth region,
   and each eye, for its eyelid and its eyeball, with the same ring and bound. Measured on
   the reproduction (``bench.occluded``; the model of the clean frames gives the base
   texture; "over": the ring's texels departing on more than 15 %):

   ==========================================  ========================================
   lp_d3 0:140, dark patch over the mouth      clean frames 0-1 %, occluded 24-81 %
   lp_d3 0:140, dark patch over the right eye  60 of 61 occluded frames over (one at 15 %);
                                               clean frames of that eye 1 of 79 over
   lp_d3 0:140, skin patch over the right eye  61 of 61 occluded frames over
   lp_d14 0:200, dark patch over the left eye  95 of 95 occluded frames over (36 % at least)
   lp_d14 0:200, clean (winks and blinks)      at most 11 % (right eye), 14 % (left): none
   lp_d3 0:140, clean (eyes shut, frown)       up to 21 %: 4 frames of 140 per eye over
                                               (the eye open where the base texture's is
                                               half shut); the closed states remain
   lp_d3 0:90, dark patch over the right eye,  patched 5-17 %, clean 0-7 %: 4-7 of 38
   on a model whose neutral looks wide-eyed    patched frames over; the rows above were
   (frame 4, as with the neutral among the     measured on a base texture whose eye was
   sharper half of the frames)                 half shut (frame 33). Not solved
   ==========================================  ========================================

   A wink or a blink moves the lids, which the ring (outside the eye's box grown by 10 %)
   leaves out; what it takes is the skin beside and below the eye, which a hand or hair
   covers. The brows are not judged: their ring reaches the hairline, and on clean frames
   of lp_d3 it departs on up to 34 % of its texels (the brows raised, the frown), so no
   bound keeps raised brows in the forehead's layers and an occluder out. The test is
   relative to the base texture, so it holds only where the base texture is clean: when
   the neutral frame's eye is occluded, the fusion kept the patch (lp_d3 0:140 with the
   patch over the right eye in 32 of the first 42 frames: the neutral frame 33 and two
   more of the 9 views carry it, and the fusion flagged no view over the right eye; with
   61 frames of the first 84, 6 of the 9 views), the occluded frames match it, the clean
   ones depart, and the eye's layers take patched frames (the neutral taken again for the
   mouth and the nose only, 3). A consensus of the frames' own rings instead of the base
   texture (per texel, the median over the frames, exposure matched) kept winks and
   blinks (at most 14 % departed, lp_d3 and lp_d14 clean) but found 7-22 % on the
   patched frames of the first case: no bound between them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from facewire.models.geometry import Intrinsics
from facewire.models.mesh import Mesh
from facewire.models.texelgrid import texel_rect
from facewire.sender.clean import PARTS, part_rect
from facewire.sender.enroll.fit import Fit, frame_costs
from facewire.sender.enroll.fusion import Fusion

TEXTURE_VIEWS = 9
MISFIT_RATIO = 2.0
BLUR_SCALE = 0.25
OCCLUDED_FRACTION = 0.3
PART_MARGIN = 0.25
NEUTRAL_PARTS = ("mouth", "nose")  # the parts whose occlusion makes the neutral taken again


def frame_scores(points: Sequence[np.ndarray | None], fit: Fit, camera: Intrinsics,
                 blur: Sequence[float]) -> dict[int, float]:
    """Each candidate frame's cost (module docstring, 1), by its index in ``points``.

    Args:
        points: per frame, (68, 2) landmarks or None.
        fit: the fit (its poses and mesh).
        camera: the intrinsics the fit used.
        blur: per frame, ``sharpness`` (any value where there are no points).

    Returns:
        {frame: cost} over the posed frames that are not misfits.
    """
    posed = [i for i, (p, q) in enumerate(zip(points, fit.poses))
             if p is not None and q is not None]
    if not posed:
        return {}
    costs = frame_costs(points, fit.poses, posed, fit.landmarks3d, camera)
    b = np.array([blur[i] for i in posed], np.float64)
    ref = max(float(np.median(b)), 1e-9)
    blur_cost = (np.maximum(0.0, 1.0 - b / ref) / BLUR_SCALE) ** 2
    residual = costs["residual"]
    clean = residual <= MISFIT_RATIO * float(np.median(residual))
    total = costs["total"] + blur_cost
    return {f: float(c) for f, c, ok in zip(posed, total, clean) if ok}


def texture_views(fit: Fit, scores: dict[int, float], count: int = TEXTURE_VIEWS
                  ) -> tuple[tuple[int, ...], int]:
    """The frames to fuse, the neutral first, and how many of them are primary (the neutral
    and the fit's side views: ``sender.enroll.fusion``, colour) (module docstring, 2)."""
    frames = len(fit.poses)
    gap = max(1, frames // (2 * count))
    views = [fit.neutral]
    for v in fit.views[1:]:
        if v in scores and len(views) < count:
            views.append(v)
    primary = len(views)
    for f in sorted(scores, key=lambda f: (scores[f], f)):
        if len(views) >= count:
            break
        if all(abs(f - v) >= gap for v in views):
            views.append(f)
    return tuple(views), primary


def part_masks(mesh: Mesh, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """Each part's (H, W) bool texel mask (module docstring, 3) in a texture of ``shape``."""
    out = {}
    for name in PARTS:
        mask = np.zeros(shape, bool)
        mask[texel_rect(part_rect(mesh, name, PART_MARGIN), shape)[1]] = True
        out[name] = mask
    return out


def occluded_parts(fusion: Fusion, masks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per part, (V,) bool: the view was an outlier over the part (module docstring, 3)."""
    return {name: fusion.outlier_fraction(mask) > OCCLUDED_FRACTION
            for name, mask in masks.items()}


def clean_views(fusion: Fusion, occluded: dict[str, np.ndarray]) -> np.ndarray:
    """(V,) bool: the view lined up with the others and was occluded in none of the
    ``NEUTRAL_PARTS`` (module docstring, 3)."""
    ok = fusion.aligned.copy()
    for part in NEUTRAL_PARTS:
        ok &= ~occluded[part]
    return ok

