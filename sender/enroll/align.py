"""Registration on the texture: the views warped onto their consensus before they are
fused, and each region's layers onto the base texture where they meet it.

Views (``register_views``). Every view is projected onto the texels through the fitted
mesh and its own head pose (``sender.enroll.texture``, 2). The mesh is the neutral face's
and the pose a fit to 68 points, so a view's features land a few texels off the others':
a pose a degree off, glasses that slid on the nose, a lid or brow a millimetre higher, a
frame of fast motion. Fused as they are, the views show such a feature twice (a doubled
glasses rim, two lash lines), or the consensus drops them where they disagree and the
texture is made of fewer views. So, before the fusion, every view but the first is warped
onto the views' consensus C (the weighted median of their luma,
``registration.weighted_median``: where most views put a feature), within the ``box`` of
texels where the first view sees the face frontally (weight at least ``FRONT_WEIGHT``).
The first view, the neutral frame, stays as it is: the mesh is fitted to its points, so
its features lie where the mesh's do (warped onto a consensus of talking frames, its lips
would move off the mesh's); where the others agree with it, as around still eyes and
glasses, C is its own picture:

1. Luma grids. C and the view's luma Y on the texel grid of the box, each filled with
   the other where it has nothing (so the edge of a view's coverage is no structure to
   follow), averaged over cells of ``SCALE`` x ``SCALE`` texels (4: at some 3-5 texels per
   image pixel, about one pixel of the image per cell).
2. Flow. Dense inverse-search optical flow (Kroeger et al. 2016, OpenCV's DIS, its
   medium preset) from C to Y gives f with C(x) ~ Y(x + f(x)), smoothed by a Gaussian of
   ``SMOOTH`` cells (a registration error varies slowly over the face; a flow that follows
   single texels follows noise), its length clipped to ``MAX_SHIFT`` cells (a larger
   offset is another expression, not a misregistration: the fusion's consensus handles
   that), faded to 0 where the view shares nothing with C (over ``SMOOTH`` cells) and
   scaled back to texels.
3. Warp. The view's colours and weights are resampled at x + f(x) (bilinear; the weight
   is 0 where the sample reaches a texel the view does not see).
4. Check. The warp is kept only when it raises the correlation of Y with C, over the
   texels both see where C is structured (its local standard deviation at least
   ``registration.STRUCTURE_STD``), by at least ``MIN_GAIN``: a flow on a view that shows
   another expression, or on a featureless face, must not make things worse.

With fewer than ``MIN_VIEWS`` views there is no consensus and nothing is moved.

Layers (``register_layer``). A region's layer is read from its own frame with the pose and
morph the sender found there (``sender.enroll.layers``, step 4), the base texture from the
fitted views: the two lay a brow or a lash line a few texels apart, and the layer, blended
in over its ramp (``models.regions.ramp_mask``), then shows the base's feature and its own
side by side along the region's edge: a crack, in every frame that draws the layer (the rest
state: every frame). So each layer is warped onto the base under it by the same flow (base
as C, layer as Y, every texel shared), applied in full within ``RAMP_TEXELS`` of the
layer's border and fading to nothing at twice that; the rest state's layer (the neutral
frame's expression, as the base's) is warped all over. Inside, the layer keeps its own
expression; at its border it meets the base. The warp is kept only when it raises the
layer's correlation with the base over the border band (within twice the ramp) by at
least ``MIN_GAIN``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.regions import RAMP_TEXELS, ramp_mask
from facewire.sender.enroll.registration import STRUCTURE_STD, weighted_median

SCALE = 4  # texels per flow cell
SMOOTH = 2.0  # cells: the Gaussian the flow is smoothed by
MAX_SHIFT = 3.0  # cells: the longest shift a registration may make
FRONT_WEIGHT = 0.3  # the reference's weight for a texel to be in the registered box
_MARGIN = 8  # cells around the box
_MIN_SHARED = 400  # texels a view must share with the consensus to be registered
MIN_GAIN = 0.01  # the least rise in correlation for a warp to be kept
MIN_VIEWS = 3  # views needed for a consensus to register them to


@dataclass(frozen=True)
class Registration:
    """What registering the views did.

    Attributes:
        shift: (V,) float64, the mean length of each view's kept flow over the texels it
            shares with the reference, texels (0 for the reference and views left as they were).
        gain: (V,) float64, the correlation with the reference after minus before over the
            shared structured texels (0 where the warp was not kept).
    """

    shift: np.ndarray
    gain: np.ndarray


def register_views(colours: list[np.ndarray], weights: list[np.ndarray], covered: np.ndarray
                   ) -> Registration:
    """Warp every view but the first onto the views' consensus, in place (module docstring).

    Args:
        colours: per view (K, 3) float32 BGR colours of the K covered texels (row-major);
            the first view is the neutral frame.
        weights: per view (K,) float32 weights (0: not seen), same order.
        covered: (H, W) bool, the covered texels.

    Returns:
        The ``Registration`` (each view's shift and correlation gain).
    """
    count = len(colours)
    shift, gain = np.zeros(count), np.zeros(count)
    box = _box(weights[0], covered)
    if box is None or count < MIN_VIEWS:
        return Registration(shift, gain)
    inside = covered[box]
    index = _index(covered, box)
    grids = [_grid(c, covered, box) for c in colours]
    seen = [_grid(w[:, None], covered, box)[..., 0] for w in weights]
    luma = np.stack([g @ _LUMA for g in grids])
    weight = np.stack(seen)
    any_seen = (weight > 0).any(axis=0)
    centre = np.zeros(inside.shape, np.float32)
    centre[any_seen] = weighted_median(luma[:, any_seen], weight[:, any_seen])
    for i in range(1, count):  # the first view stays: the mesh is fitted to its points
        y, w = luma[i], weight[i]
        shared = any_seen & (w > 0)
        if shared.sum() < _MIN_SHARED:
            continue
        flow = _flow(np.where(any_seen, centre, y), np.where(w > 0, y, centre), shared)
        map_x, map_y = _maps(flow)
        warped = cv2.remap(grids[i], map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        whole = cv2.remap((w > 0).astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        moved = cv2.remap(w, map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        moved = np.where(whole > 0.999, moved, 0.0).astype(np.float32)
        both = shared & (moved > 0)
        before = _structured_corr(y, centre, both)
        after = _structured_corr(warped @ _LUMA, centre, both)
        if before is None or after is None or after < before + MIN_GAIN:
            continue
        colours[i][index] = warped[inside]
        weights[i][index] = moved[inside]
        shift[i] = float(np.linalg.norm(flow, axis=2)[shared].mean())
        gain[i] = after - before
    return Registration(shift, gain)


_LUMA = np.array([0.114, 0.587, 0.299], np.float32)  # BGR


def _luma(colour: np.ndarray) -> np.ndarray:
    """(K, 1) float32 luma of (K, 3) BGR colours."""
    return (colour @ _LUMA)[:, None]


def _box(reference: np.ndarray, covered: np.ndarray) -> tuple[slice, slice] | None:
    """The texel rectangle where the reference sees the face frontally (weight at least
    ``FRONT_WEIGHT``), grown by ``_MARGIN`` cells and rounded out to whole cells; None when
    it sees no such texel."""
    grid = np.zeros(covered.shape, bool)
    grid[covered] = reference >= FRONT_WEIGHT
    rows, cols = np.nonzero(grid)
    if len(rows) == 0:
        return None
    pad = _MARGIN * SCALE
    height, width = covered.shape

    def span(lo: int, hi: int, size: int) -> slice:
        a = max(0, lo - pad) // SCALE * SCALE
        b = min(size, -(-(hi + 1 + pad) // SCALE) * SCALE)
        return slice(a, b - (b - a) % SCALE)

    return span(int(rows.min()), int(rows.max()), height), span(int(cols.min()),
                                                               int(cols.max()), width)


def _grid(values: np.ndarray, covered: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """(h, w, C) float32: the (K, C) values of the covered texels laid on the box's grid (0
    where uncovered)."""
    full = np.zeros((*covered.shape, values.shape[1]), np.float32)
    full[covered] = values
    return np.ascontiguousarray(full[box])


def _index(covered: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """(K,) bool: which of the K covered texels lie in the box."""
    inside = np.zeros(covered.shape, bool)
    inside[box] = True
    return inside[covered]


def _flow(reference: np.ndarray, view: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """(h, w, 2) float32 texel offsets (x, y) with reference(p) ~ view(p + f(p)) (module
    docstring, 2), of two (h, w) float32 luma images; 0 away from the ``shared`` texels."""
    h, w = reference.shape
    if h % SCALE or w % SCALE:  # pad to whole cells, then crop the flow back
        pad = ((0, -h % SCALE), (0, -w % SCALE))
        return _flow(np.pad(reference, pad, mode="edge"), np.pad(view, pad, mode="edge"),
                     np.pad(shared, pad))[:h, :w]

    def small(a: np.ndarray) -> np.ndarray:
        cells = a.reshape(h // SCALE, SCALE, w // SCALE, SCALE).mean(axis=(1, 3))
        return np.clip(np.rint(cells), 0, 255).astype(np.uint8)

    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    raw = np.asarray(dis.calc(small(reference), small(view), None),  # type: ignore[call-overload]
                     np.float32)
    flow = np.asarray(cv2.GaussianBlur(raw, (0, 0), SMOOTH), np.float32)
    length = np.linalg.norm(flow, axis=2, keepdims=True)
    flow = flow * np.minimum(1.0, MAX_SHIFT / np.maximum(length, 1e-6))
    share = shared.reshape(h // SCALE, SCALE, w // SCALE, SCALE).any(axis=(1, 3))
    near = cv2.GaussianBlur(np.asarray(share, np.float32), (0, 0), SMOOTH)
    flow = flow * np.clip(2.0 * near, 0.0, 1.0)[..., None]
    big = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
    return (big * SCALE).astype(np.float32)


def _maps(flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap's (h, w) float32 maps x + f_x, y + f_y."""
    h, w = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return xs + flow[..., 0], ys + flow[..., 1]


def _structured_corr(y: np.ndarray, ref: np.ndarray, shared: np.ndarray) -> float | None:
    """The Pearson correlation of ``y`` and ``ref`` over the ``shared`` texels where ``ref``
    varies locally (module docstring, 4); None when fewer than ``_MIN_SHARED`` such
    texels."""
    k = (9, 9)
    mean = cv2.blur(ref, k)
    var = cv2.blur(ref * ref, k) - mean * mean
    use = shared & (var >= STRUCTURE_STD ** 2)
    if use.sum() < _MIN_SHARED:
        return None
    a, b = y[use].astype(np.float64), ref[use].astype(np.float64)
    if a.std() < 1e-6 or b.std() < 1e-6:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def register_layer(layer: np.ndarray, base: np.ndarray, rest: bool) -> np.ndarray:
    """A region's layer warped onto the base texture under it where it meets it (module
    docstring, layers).

    Args:
        layer: (h, w, 3) uint8 RGB, one state's layer image over an area.
        base: (h, w, 3) uint8 RGB, the base texture over the same area.
        rest: the layer is the rest state's (the neutral frame's expression): warped
            everywhere, not only along its border.

    Returns:
        (h, w, 3) uint8 RGB: the warped layer, or ``layer`` itself when the warp does not
        raise its correlation with the base over the border band.
    """
    y_layer = layer.astype(np.float32) @ _LUMA[::-1]
    y_base = base.astype(np.float32) @ _LUMA[::-1]
    flow = _flow(y_base, y_layer, np.ones(y_base.shape, bool))
    band = ramp_mask(y_base.shape, 2 * RAMP_TEXELS) < 1.0
    if not rest:  # full along the border band, none deeper than twice the ramp
        reach = 1.0 - np.clip(2.0 * ramp_mask(y_base.shape, 2 * RAMP_TEXELS) - 1.0, 0.0, 1.0)
        flow = flow * reach[..., None]
    map_x, map_y = _maps(flow)
    warped = cv2.remap(layer, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    before = _structured_corr(y_layer, y_base, band)
    after = _structured_corr(warped.astype(np.float32) @ _LUMA[::-1], y_base, band)
    if before is None or after is None or after < before + MIN_GAIN:
        return layer
    return np.asarray(warped, np.uint8)
