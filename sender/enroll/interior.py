"""The mouth's interior: what the cavity's texture shows when the lips part.

The cavity (``models.head.inserts.mouth_cavity``) has its texture on the disc at
``MOUTH_UV`` = (u_m, v_m), radius R = ``MOUTH_UV_RADIUS`` in u, 2R in v. A texel at (u, v)
has the polar coordinates

    rho = sqrt(((u - u_m) / R)^2 + ((v - v_m) / 2R)^2),
    alpha = atan2((v - v_m) / 2R, (u - u_m) / R),

rho = 1 on the rim (a copy of the inner lip line), rho = 0 at the back of the cavity; alpha
> 0 is the upper half (the upper lip's side), alpha < 0 the lower. The UV layout is the
generic head's for every model, so (rho, alpha) is a fixed map of the cavity. Seen from the
front through an open mouth (rendered with a disc coded by rho and alpha, on lp_d18's
yawns), the opening shows rho < 0.25: the back wall, stretched by the jaw's drop (its centre
rho = 0 in the middle of the opening, rho 0.2-0.23 right under the upper lip's middle,
0.24-0.29 toward the corners, 0.16-0.22 over the lower lip's middle). No camera sees the
cavity of a closed mouth, and without an occlusion test a frame paints its lips there
(``sender.enroll.layers``, step 4), which an opened mouth would show stretched. So every
cavity texel takes one of two colours:

1. Seen (``fuse_seen``). An enrollment frame whose mouth is open (inner-lip gap at least
   ``sender.enroll.coverage.OPEN_GAP`` outer-eye distances) saw the cavity texels whose
   projection falls inside its inner-lip polygon (landmarks 60..67, ``seen_weight``),
   shrunk by ``INSET`` of the gap |p66 - p62| (the polygon's edge is lip) and softened by a
   Gaussian of ``SOFT`` of the gap: the soft mask sampled at the texel's projection is the
   frame's weight w_f in [0, 1] (0 for a texel facing away, off the image, or under
   ``MIN_WEIGHT``). Several such frames are fused per texel and channel by the weighted
   median of their colours (weights w_f), which keeps the person's own teeth and tongue
   and drops a frame where a hand, a lip or a misplaced landmark crossed the opening. A
   frame with a hand on the face gives none (``sender.enroll.occluders``: the layers'
   occluded frames), and a texel that looks like the person's lit skin (``skin_like``: its
   chromaticity (r, g) / (r + g + b) within ``SKIN_CHROMA`` of the cheeks' and its grey at
   least ``SKIN_GREY`` of theirs: a finger the hand detector missed, a lip crossing the
   opening) is not seen by that frame: teeth are greyer, the tongue and the dark behind
   them darker. The texel's coverage is c = max_f w_f.
2. Made up, everywhere else. When at least ``MIN_SEEN`` cavity texels were seen, the seen
   interior is carried over the unseen ones (``continued``: the push-pull fill of
   ``sender.enroll.texture`` from the texels of coverage c >= 1/2): the person's own
   colours, and teeth only where they were seen (teeth made up beside a seen palate showed
   as fangs at the mouth's corners). Else (``synthetic``) a mouth in shadow, from the
   person's own lip colour L (``palette``; RGB), much darker toward the back,

       I = L (0.12 + 0.28 s(0, 0.25, rho)),     s the smoothstep,

   at most 0.4 of the lip's colour, with two teeth bands in the shadow of the lips. The
   teeth have the colour T = min(1.35 Y_skin, 235) (1.0, 0.95, 0.82) (Y_skin the skin's
   mean grey, so the teeth are lit like the face): the upper one over rho > 0.15 +
   ``TEETH_CORNER`` cos^2 alpha and 50 < alpha < 130 degrees, the lower one over rho > 0.14
   + ``TEETH_CORNER`` cos^2 alpha and -130 < alpha < -50 degrees (the opening shows rho up
   to 0.2 under the lips' middle and 0.29 toward the corners, so the bands' inner edge
   follows it out; bands from rho 0.2 over 40 to 140 degrees showed only at the corners, as
   fangs), each with smoothstep edges (0.03 in rho, 25 degrees in alpha) and shaded toward
   the mouth corners (0.55 + 0.45 |sin alpha|) and toward the back (0.75 at the band's
   inner edge, 1 from 0.05 further out): I <- I + m (T shade - I) with m the band's soft
   mask, at most ``UPPER_TEETH`` (0.55) above and ``LOWER_TEETH`` (0.2) below (the lower
   teeth lie deeper in shadow): a made-up mouth is a dark cavity, never a flat light plate.

The interior is then c * seen + (1 - c) * synthetic: soft where the seen part ends, never
the lips' or the skin's colour where nothing was seen.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.head.primitives import sstep
from facewire.models.head.uvlayout import MOUTH_UV, MOUTH_UV_RADIUS
from facewire.models.mesh import Mesh
from facewire.sender.appearance import bilinear
from facewire.sender.enroll.texture import fill_holes

INSET = 0.08  # the inner-lip polygon shrinks by this fraction of the gap
SOFT = 0.04  # and its edge softens over a Gaussian of this fraction of the gap
MIN_WEIGHT = 0.05  # a frame's weight below this: it did not see the texel
SKIN_CHROMA = 0.025  # chromaticity distance under which a colour is the skin's hue ...
SKIN_GREY = 0.75  # ... and, at least this bright against the cheeks, lit skin
MIN_SEEN = 200  # cavity texels seen: fewer, and the walls under the teeth stay the lip's
TEETH = np.array([1.0, 0.95, 0.82], np.float32)  # RGB of the teeth over the skin's grey
UPPER_TEETH = 0.55  # the made-up upper teeth's most opacity over the dark cavity
LOWER_TEETH = 0.2  # and the lower teeth's, deeper in shadow
TEETH_CORNER = 0.08  # the teeth bands' inner edge moves out by this toward the corners
_UPPER_LIP = ((50, 61), (51, 62), (52, 63))  # outer, inner landmark pairs across the lips
_LOWER_LIP = ((58, 67), (57, 66), (56, 65))
_CHEEKS = ((2, 31), (14, 35), (3, 48), (13, 54))  # pairs whose middle is cheek skin


def disc_polar(rows: slice, cols: slice, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(rho, alpha) of the texels of a block of an (H, W) texture (module docstring).

    Args:
        rows, cols: the block (texture rows top first, columns).
        shape: (H, W) of the texture.

    Returns:
        (h, w) float32 rho and (h, w) float32 alpha in radians.
    """
    v = 1.0 - (np.arange(rows.start, rows.stop) + 0.5) / shape[0]
    u = (np.arange(cols.start, cols.stop) + 0.5) / shape[1]
    du = (u[None, :] - MOUTH_UV[0]) / MOUTH_UV_RADIUS
    dv = (v[:, None] - MOUTH_UV[1]) / (2.0 * MOUTH_UV_RADIUS)
    du, dv = np.broadcast_arrays(du, dv)
    return np.hypot(du, dv).astype(np.float32), np.arctan2(dv, du).astype(np.float32)


def palette(texture: np.ndarray, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The person's lip and skin colours, read from the base texture.

    Args:
        texture: (H, W, 3) uint8 RGB base texture.
        mesh: the model's mesh (its landmark vertices' UVs on the skin).

    Returns:
        (3,) float32 lip colour (the median over the middles of the lips: halfway between
        the outer and inner lip landmarks) and (3,) float32 skin colour (the same over the
        cheeks).
    """
    uv = mesh.uv[mesh.landmarks].astype(np.float64)
    h, w = texture.shape[:2]

    def median(pairs: tuple[tuple[int, int], ...]) -> np.ndarray:
        mid = np.array([0.5 * (uv[a] + uv[b]) for a, b in pairs])
        cols = np.clip((mid[:, 0] * w).astype(int), 1, w - 2)
        rows = np.clip(((1.0 - mid[:, 1]) * h).astype(int), 1, h - 2)
        patch = np.concatenate([texture[r - 1:r + 2, c - 1:c + 2].reshape(-1, 3)
                                for r, c in zip(rows, cols)])
        return np.median(patch.astype(np.float32), axis=0)

    return median(_UPPER_LIP + _LOWER_LIP), median(_CHEEKS)


def synthetic(rho: np.ndarray, alpha: np.ndarray, lip: np.ndarray, skin: np.ndarray
              ) -> np.ndarray:
    """The synthetic interior (module docstring, 2).

    Args:
        rho, alpha: (h, w) the texels' disc coordinates (``disc_polar``).
        lip, skin: (3,) RGB colours (``palette``).

    Returns:
        (h, w, 3) float32 RGB.
    """
    lip = np.asarray(lip, np.float32)
    out = lip * (0.12 + 0.28 * sstep(0.0, 0.25, rho))[..., None]
    teeth = min(1.35 * float(np.mean(skin)), 235.0) * TEETH
    degrees = np.degrees(alpha)
    for middle, a0, a1, most in ((0.15, 50.0, 130.0, UPPER_TEETH),
                                 (0.14, -130.0, -50.0, LOWER_TEETH)):
        lo = middle + TEETH_CORNER * np.cos(alpha) ** 2  # the opening reaches further out there
        band = sstep(lo - 0.03, lo, rho) * sstep(a0 - 25.0, a0, degrees) \
            * sstep(a1 + 25.0, a1, degrees)
        shade = (0.55 + 0.45 * np.abs(np.sin(alpha))) * (0.75 + 0.25 * sstep(lo, lo + 0.05, rho))
        mask = (most * band)[..., None]
        out = out + mask * (teeth * shade[..., None] - out)
    return out.astype(np.float32)


def continued(fused: np.ndarray, coverage: np.ndarray, cavity: np.ndarray
              ) -> np.ndarray | None:
    """The seen interior carried over the cavity's unseen texels (module docstring, 2).

    Args:
        fused, coverage: ``fuse_seen``'s results, (h, w, 3) and (h, w).
        cavity: (h, w) bool, the texels on the cavity.

    Returns:
        (h, w, 3) float32 RGB: the fused colour where the coverage is at least 1/2, the
        push-pull fill of it elsewhere (``sender.enroll.texture.fill_holes``); None when
        fewer than ``MIN_SEEN`` cavity texels were seen.
    """
    valid = (coverage >= 0.5) & cavity
    if int(valid.sum()) < MIN_SEEN:
        return None
    colour = np.clip(np.rint(fused), 0, 255).astype(np.uint8)
    return fill_holes(colour, valid).astype(np.float32)


def skin_like(colour: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """Where colours look like the person's lit skin (module docstring, 1).

    Args:
        colour: (..., 3) float32 RGB.
        skin: (3,) RGB, the cheeks' colour (``palette``).

    Returns:
        (...) bool.
    """
    skin = np.asarray(skin, np.float32)

    def chroma(c: np.ndarray) -> np.ndarray:
        return c[..., :2] / np.maximum(c.sum(axis=-1, keepdims=True), 1.0)

    grey = colour @ np.array([0.299, 0.587, 0.114], np.float32)
    near = np.linalg.norm(chroma(colour) - chroma(skin), axis=-1) < SKIN_CHROMA
    return near & (grey >= SKIN_GREY * float(skin @ np.array([0.299, 0.587, 0.114])))


def seen_weight(lips: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """How much one frame saw of each texel (module docstring, 1): its inner-lip polygon,
    shrunk and softened, sampled at the texels' projections.

    Args:
        lips: (8, 2) the inner-lip landmarks 60..67, px.
        x, y: (...) float32 the texels' projections, px.

    Returns:
        (...) float32 weights in [0, 1] (0 outside the polygon's box; whether a texel faces
        the camera and lies on the image is the caller's test).
    """
    gap = float(np.linalg.norm(lips[6] - lips[2]))
    sigma = max(SOFT * gap, 0.5)
    pad = int(np.ceil(3.0 * sigma)) + 2  # the blurred mask is 0 on the block's border
    x0, y0 = np.floor(lips.min(axis=0)).astype(int) - pad
    x1, y1 = np.ceil(lips.max(axis=0)).astype(int) + pad
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [np.rint(lips - (x0, y0)).astype(np.int32)], 255)
    inset = int(round(INSET * gap))
    if inset > 0:
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                         (2 * inset + 1, 2 * inset + 1)))
    soft = cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (0, 0), sigma)
    out = bilinear(soft, np.asarray(x, np.float32) - x0, np.asarray(y, np.float32) - y0)
    return np.clip(out, 0.0, 1.0)


def fuse_seen(colours: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted median of the frames that saw each texel (module docstring, 1).

    Args:
        colours: (F, h, w, 3) float32 the frames' colours at the texels.
        weights: (F, h, w) float32 their weights (``seen_weight``).

    Returns:
        (h, w, 3) float32 fused colour (0 where no frame saw the texel) and (h, w) float32
        coverage c = max_f w_f (0 below ``MIN_WEIGHT``).
    """
    w = np.where(weights >= MIN_WEIGHT, weights, 0.0).astype(np.float32)
    coverage = w.max(axis=0) if len(w) else np.zeros(colours.shape[1:3], np.float32)
    if len(w) == 0:
        return np.zeros(colours.shape[1:], np.float32), coverage
    order = np.argsort(colours, axis=0)  # per texel and channel
    ranked = np.take_along_axis(colours, order, axis=0)
    ranked_w = np.take_along_axis(np.broadcast_to(w[..., None], colours.shape), order, axis=0)
    cum = np.cumsum(ranked_w, axis=0)
    half = 0.5 * cum[-1:]
    pick = np.argmax(cum >= half, axis=0)[None]
    fused = np.take_along_axis(ranked, pick, axis=0)[0]
    return np.where(coverage[..., None] > 0, fused, 0.0).astype(np.float32), coverage


def interior(synth: np.ndarray, seen: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """c * seen + (1 - c) * synthetic, (h, w, 3) float32 (module docstring)."""
    c = np.clip(coverage, 0.0, 1.0)[..., None]
    return (c * seen + (1.0 - c) * synth).astype(np.float32)
