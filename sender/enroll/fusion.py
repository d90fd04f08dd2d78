"""The base texture's fusion: the views projected onto the texture, made into one texture.

``sender.enroll.texture`` projects each view onto the texels (its docstring, 2: each view's
colour and angle-and-edge weight w per texel); this module fuses them (``fuse_views``).

Every texel is judged by a robust consensus of several views, and no frame's colour stays
where the consensus says it is wrong. A view may carry an occluder (a hand, hair) or a
passing expression over part of the face, or not line up with the fitted model (a tracking
slip: every feature lands a few pixels off), and a mean bakes both in: an occluder as a dark
patch, a slip as doubled features (ghosting).

Registration next (``sender.enroll.align``): after the exposure is matched (below), every
view is warped onto the views' consensus by a dense optical flow on the texture, so a
feature a few texels off in one view (a pose a degree off, glasses that slid, a frame of
fast motion) is moved onto the others' before anything below compares or blends them.

Exposure first: a camera's automatic exposure and white balance change between frames,
and a view a fifth darker leaves a soft but visible step where only it sees the skin. So
views are taken in order, the first (the neutral frame) as the reference, and each later
view's colours are scaled per channel by g = the m-weighted median of c_before / c_view
over the texels it shares with the views before it (c_before their weighted mean so far,
m the smaller of the two weights), when they share at least 200 texels; g is clipped to
[0.5, 2]. A median, not a ratio of sums: an occluder in the reference (up to half the
shared texels) must not set every other view's exposure.

Consensus. Per texel seen by at least ``MIN_VIEWS_FOR_CONSENSUS`` = 3 views (two views
that differ give no majority: both are kept), over the views i that see it, with y_i
the luma of view i's colour (0.299 R + 0.587 G + 0.114 B): the weighted median m = the
smallest y_j such that sum of w_i over y_i <= y_j reaches half of sum w_i, and the
robust spread s = max(1.4826 MAD_w, ``SPREAD_FLOOR``) with MAD_w the weighted median of
|y_i - m| (1.4826 makes it the standard deviation of Gaussian noise; the floor, 10 grey
levels, covers the noise of H.264 frames and the shading that changes as the head turns
under the room's light, so agreeing views do not reject each other over it: with 5,
lp_d3's views rejected each other in streaks over the cheeks). View i takes part at the
texel when |y_i - m| <= kappa s, kappa = ``OUTLIER_KAPPA`` = 3: a view whose colour
departs from the others' by more than three robust deviations (a dark occluder on skin
departs by 100 levels and more) gives that texel nothing. The median has a breakdown
point of one half. An occluder is a patch, not single texels, so the decision is
made coherent: view i takes part at a texel unless it was an outlier on at least half
of the texels it sees in the ``OUTLIER_WINDOW`` (17 x 17) square around it; isolated
outlying texels (noise, a pixel of registration at an edge) stay, and the texture shows
no speckle where views take turns. The median's estimate is right as long as the views
that see a texel cleanly carry more than half of its weight, which is why the views are
chosen clean first (``sender.enroll.evidence``) and spread in time (an occluder held
for a second is in consecutive frames).

Alignment. A view that does not line up with the model is dropped whole: over the texels
it shares with the consensus (seen by at least ``MIN_VIEWS_FOR_CONSENSUS`` = 3 views),
its disagreement is d_i = 1 - r_i, with r_i the Pearson correlation of y_i and m there.
Registration within a pixel and noise give every view a small d; a view with
d_i > ``ALIGN_RATIO`` (3) x median_j d_j + 0.02 is a misfit and takes no part anywhere,
and the consensus is computed again without it. (A single outlying view over a small part
of the face, an occluder, hardly moves r_i; that is the per-texel test's job.)

Local alignment. A view can line up as a whole and not over one feature: lips in another
expression, glasses or lids a few pixels off in a frame of fast motion. Its colours there
are the skin's and the feature's, as the others', so the per-texel test keeps them, and
blended or shown beside the others' they show the feature twice. So each view is also
judged by structure (``sender.enroll.registration``, 2): within the parts of the face
(``features``: the build's eyes, brows, nose and mouth boxes), where its windowed
correlation with the consensus m falls below ``MIN_NCC`` (0.7) while most views line up
with m there, it takes no part over that window, and a primary view's texels there are
replaced (below) as an occluded patch's are. Where most views do not line up with m (a
mouth that talks in every frame), m is no consensus and nobody is dropped: the primary
views make the texture, as they are.

Colour. The first P views are the *primary* ones (the build's: the neutral frame and
the side views beyond 15 degrees of yaw, ``sender.enroll.fit``); the rest only give
evidence. Where no primary view is an outlier, the texture is the primaries' weighted
mean, sum_{i<P} w_i c_i / sum_{i<P} w_i over those that line up, exactly as the views
are; where one is, it is
replaced by c_robust, the colour of the first view in the given order (the build's: the
primaries, then the others by their cost, cleanest first) that takes part at the texel
and sees it well (w >= ``REPLACE_MIN_WEIGHT`` = 0.3):

    c = (1 - r) c_primary + r c_robust,

r the indicator of the texels where a primary view that sees the texel well was an
outlier over a large patch (the coherence test above over a ``REPLACE_WINDOW`` = 33
texel square: an occluder over a mouth, an eye closed in a wink; not a mouth corner a
millimetre off, nor the jaw's silhouette, where the mesh is wider than the face and the
other views see the background), or where a primary view that sees it at all does not
line up locally or was dropped whole (a dropped primary makes no texel: it once still made
those it saw weakly, a ring of doubled features around the replaced middle), and some
view that sees it well took part, grown by ``REPLACE_GROW`` = 3 texels and feathered by
a Gaussian of ``REPLACE_FEATHER`` = 2 texels, so no seam shows where the replacement
stops (0 where no view that sees the texel well takes part: nothing to replace with; 1
wherever it is not 0 and no primary view that lines up sees the texel: nothing to blend
with). Why not
a mean of the views: the views are warped onto the neutral mesh, not onto each frame's
expression, so lips that moved a millimetre between frames double in a mean (measured
on lp_d14 0:178 with nine views blended everywhere: the viewer's mouth NME on the
held-out frames went from 1.13 % to 2.38 %, face SSIM from 0.898 to 0.889; with the
robust mean only where the neutral frame was an outlier, 1.41 % and 0.893). One clean
view per texel shows each feature once; the outlier decisions are coherent over
patches (above), so the view that replaces changes only between patches. Among the
primaries, the angle weight (k = 4: at 20 and 40 degrees the weights are 0.76 and 0.30)
makes the mean almost the best view where views differ, yet continuous across the
surface (a hard best-view choice would switch views along a curve and show every
difference of light or registration as a seam). A texel seen by one or two views keeps
them: nothing contradicts them. The summed weight of the views that made the texel is
returned (0: no view saw it). ``Fusion`` also keeps which view took part where, so the
caller can tell, per part of the face, which views were outliers there
(``Fusion.outlier_fraction``), and the consensus, so the texture's doubled features can be
measured against it (``Fusion.doubled_fraction``, ``sender.enroll.registration``, 3).

"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.infra.raster import Camera
from facewire.models.mesh import Mesh
from facewire.sender.enroll.align import Registration, register_views
from facewire.sender.enroll.registration import doubled_fraction, local_misfit, weighted_median
from facewire.sender.enroll.texture import (
    TextureError,
    UVSurface,
    check_views,
    sample_views,
)

_MIN_SHARED = 200  # texels two views must share to match their exposure
_GAIN_RANGE = (0.5, 2.0)  # the exposure gains we trust
SPREAD_FLOOR = 10.0  # grey levels: the least robust spread (module docstring)
OUTLIER_KAPPA = 3.0  # a view departing by more robust spreads takes no part at a texel
MIN_VIEWS_FOR_CONSENSUS = 3  # views that must see a texel for it to judge a view
ALIGN_RATIO = 3.0  # a view disagreeing this many times the median disagreement is dropped
ALIGN_SLACK = 0.02
OUTLIER_WINDOW = 17  # texels: the square over which a view's outliers must cohere
REPLACE_WINDOW = 33  # texels: a primary view is replaced only over patches this coherent
REPLACE_MIN_WEIGHT = 0.3  # angle-and-edge weight a view needs to replace or be replaced
REPLACE_GROW = 3  # texels a primary view's rejected patch is grown by ...
REPLACE_FEATHER = 2.0  # ... and feathered over (Gaussian sigma, texels)
_MIN_AREA_TEXELS = 50  # texels a view must share with the consensus to be judged
_LUMA_BGR = np.array([0.114, 0.587, 0.299], np.float32)


@dataclass(frozen=True, eq=False)
class Fusion:
    """The fused texture and which view took part where (module docstring).

    Attributes:
        texture: (H, W, 3) uint8 RGB, black where no kept view saw the texel.
        weight: (H, W) float32 summed weights of the views that took part (0: none).
        seen: (V, K) bool, view i sees covered texel k (K: the covered texels, row-major),
            as projected (before registration).
        kept: (V, K) bool, view i takes part at texel k as projected (seen, not an outlier,
            lined up locally): what ``outlier_fraction`` and so the build's occlusion
            evidence judge by (a view that differs from the others only by where its
            features lie, such as a frame whose lips or brows moved, stays an outlier
            there, as it was before registration).
        agreement: (V,) float64 r_i, the correlation of each view with the consensus (NaN
            when it shares too few texels with it).
        aligned: (V,) bool, the view lined up with the others (False: dropped whole).
        covered: (H, W) bool, the covered texels (the K columns of ``seen`` and ``kept``).
        consensus: (H, W) float32, the consensus's luma m (0 where fewer than
            ``MIN_VIEWS_FOR_CONSENSUS`` views that line up see the texel).
        judged: (H, W) bool, the texels that have a consensus.
        holds: (H, W) bool, where the consensus holds: most views judged there line up
            with it (``sender.enroll.registration.local_misfit``).
        fails: (H, W) bool, where it was judged and does not hold (neither where no view
            was judged: skin without structure).
        registration: how far each view was warped onto the first before the fusion
            (``sender.enroll.align``).
    """

    texture: np.ndarray
    weight: np.ndarray
    seen: np.ndarray
    kept: np.ndarray
    agreement: np.ndarray
    aligned: np.ndarray
    covered: np.ndarray
    consensus: np.ndarray
    judged: np.ndarray
    holds: np.ndarray
    fails: np.ndarray
    registration: Registration

    def doubled_fraction(self, area: np.ndarray) -> float:
        """The doubled-feature measure of the texture over ``area`` ((H, W) bool):
        ``sender.enroll.registration.doubled_fraction`` against the consensus, over the
        texels a view made and where the consensus holds."""
        luma = self.texture.astype(np.float32) @ _LUMA_BGR[::-1]
        return doubled_fraction(luma, self.consensus, self.judged & (self.weight > 0),
                                area & self.holds)

    def outlier_fraction(self, area: np.ndarray) -> np.ndarray:
        """(V,) float64: of the texels in ``area`` ((H, W) bool) that view i sees and that at
        least ``MIN_VIEWS_FOR_CONSENSUS`` views see, the fraction where it took no part (0
        where it sees fewer than ``_MIN_AREA_TEXELS`` of them)."""
        inside = area[self.covered]
        judged = inside & (self.seen.sum(axis=0) >= MIN_VIEWS_FOR_CONSENSUS)
        seen = self.seen[:, judged]
        out = (seen & ~self.kept[:, judged]).sum(axis=1).astype(np.float64)
        count = seen.sum(axis=1)
        return np.where(count >= _MIN_AREA_TEXELS, out / np.maximum(count, 1), 0.0)


def project_views(mesh: Mesh, surface: UVSurface, views: list[tuple[np.ndarray, Camera]], *,
                  sharpness: float = 4.0, cos_min: float = 0.1, feather_px: float = 8.0,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Project camera images onto the texture and fuse them (``fuse_views``): the texture
    and the summed weight of the views that took part."""
    fused = fuse_views(mesh, surface, views, sharpness=sharpness, cos_min=cos_min,
                       feather_px=feather_px)
    return fused.texture, fused.weight


def fuse_views(mesh: Mesh, surface: UVSurface, views: list[tuple[np.ndarray, Camera]], *,
               sharpness: float = 4.0, cos_min: float = 0.1, feather_px: float = 8.0,
               primary: int | None = None, features: np.ndarray | None = None,
               silhouettes: list[np.ndarray] | None = None) -> Fusion:
    """Project camera images onto the texture (``sender.enroll.texture``, 2) and fuse them
    robustly (module docstring).

    Args:
        mesh: the mesh ``surface`` was made from, in the model space the cameras' poses use.
        surface: ``uv_surface(mesh, ...)``.
        views: one or more (image, camera): image (h, w, 3) uint8 BGR (OpenCV's order), top
            row first, with h, w the camera's height and width; camera with the view's
            intrinsics and head pose. The first view sets the exposure the others are
            matched to: put the neutral frontal frame first.
        sharpness: k, the exponent of the view-angle weight (>= 0).
        cos_min: a texel is not taken from a view that sees it at cos(angle) <= cos_min,
            in [0, 1).
        feather_px: pixels over which a view's weight fades before an edge (> 0).
        primary: how many of the first views make the texture where none of them is an
            outlier (module docstring); all of them when None. The others only judge
            and replace.
        features: (H, W) bool, the texels where views are judged for local alignment
            (``sender.enroll.registration``: the parts of the face); all when None.
        silhouettes: per view, (h, w) bool, the person's pixels
            (``sender.enroll.silhouette``): no texel takes a colour from outside them;
            None: the views are taken whole.

    Returns:
        The ``Fusion``: texture (H, W, 3) uint8 RGB, black where no view saw the texel, the
        summed weights of the views that took part, and which views took part where.

    Raises:
        TextureError: bad inputs, named.
        EGLUnavailable: headless OpenGL cannot be used.
    """
    check_views(mesh, surface, views, sharpness=sharpness, cos_min=cos_min,
                feather_px=feather_px, silhouettes=silhouettes)
    if primary is not None and not (isinstance(primary, int) and 1 <= primary <= len(views)):
        raise TextureError(f"primary: expected an int in [1, {len(views)}], got {primary!r}")
    colours, weights = sample_views(mesh, surface, views, sharpness=sharpness,
                                    cos_min=cos_min, feather_px=feather_px,
                                    silhouettes=silhouettes)
    _match_exposure(colours, weights)
    covered = surface.covered
    as_seen = _take_part(np.stack([c @ _LUMA_BGR for c in colours]), np.stack(weights),
                         covered, features)  # before registration: the evidence's judgement
    registration = register_views(colours, weights, covered)
    weight_v = np.stack(weights)
    luma = np.stack([c @ _LUMA_BGR for c in colours])
    seen = weight_v > 0
    kept, agreement, aligned = _judge(luma, weight_v)
    centre, judged = _consensus(luma, np.where(kept, weight_v, 0.0))
    misfit, holds, fails = local_misfit(luma, seen & aligned[:, None], centre, judged,
                                        covered, features)
    first = len(views) if primary is None else primary
    blend, total, _ = _colour(colours, weight_v, kept & ~misfit, seen & aligned[:, None],
                              covered, first, misfit)
    texture, weight = _to_texture(blend, total, covered)
    consensus = np.zeros(covered.shape, np.float32)
    consensus[covered] = np.where(judged, centre, 0.0)
    judged_grid = np.zeros(covered.shape, bool)
    judged_grid[covered] = judged
    return Fusion(texture, weight, as_seen[0], as_seen[1], agreement, aligned, covered,
                  consensus, judged_grid, holds, fails, registration)


def _take_part(luma: np.ndarray, weight_v: np.ndarray, covered: np.ndarray,
               features: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Which views see each covered texel (V, K) bool, and which take part there (V, K)
    bool: not outliers, lined up locally, coherent over ``OUTLIER_WINDOW`` (module
    docstring), judged on the (V, K) luma and weights given."""
    seen = weight_v > 0
    kept, _, aligned = _judge(luma, weight_v)
    centre, judged = _consensus(luma, np.where(kept, weight_v, 0.0))
    lined_up = seen & aligned[:, None]
    misfit, _, _ = local_misfit(luma, lined_up, centre, judged, covered, features)
    return seen, _coherent(kept & ~misfit, lined_up, covered, OUTLIER_WINDOW)


def _match_exposure(colours: list[np.ndarray], weights: list[np.ndarray]) -> None:
    """Scale each view's colours, in place and in order, by its exposure gain against the
    views before it (module docstring, exposure)."""
    colour_sum = np.zeros((len(weights[0]), 3), np.float32)
    weight_sum = np.zeros(len(weights[0]), np.float32)
    for colour, weight in zip(colours, weights):
        colour *= _exposure_gain(colour, weight, colour_sum, weight_sum)
        colour_sum += weight[:, None] * colour
        weight_sum += weight


def _judge(luma: np.ndarray, weight_v: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which views take part at each texel (V, K) bool, before the coherence test, each
    view's agreement r_i (V,) and which views line up (V,) bool (module docstring,
    consensus and alignment)."""
    aligned = np.ones(len(weight_v), bool)
    kept, agreement = _robust_keep(luma, weight_v, aligned)
    disagreement = 1.0 - agreement
    finite = np.isfinite(disagreement)
    if finite.sum() >= 3:
        bound = ALIGN_RATIO * float(np.median(disagreement[finite])) + ALIGN_SLACK
        aligned = ~(finite & (disagreement > bound))
        if not aligned.all():
            kept, _ = _robust_keep(luma, weight_v, aligned)
    return kept, agreement, aligned


def _consensus(luma: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) float32 the consensus m (the weighted median luma of the views taking part, with
    their (V, K) weights ``use``), and (K,) bool where at least ``MIN_VIEWS_FOR_CONSENSUS``
    views take part (m is 0 elsewhere)."""
    judged = (use > 0).sum(axis=0) >= MIN_VIEWS_FOR_CONSENSUS
    centre = np.zeros(luma.shape[1], np.float32)
    if judged.any():
        centre[judged] = weighted_median(luma[:, judged], use[:, judged])
    return centre, judged


def _colour(colours: list[np.ndarray], weight_v: np.ndarray, kept: np.ndarray,
            judged: np.ndarray, covered: np.ndarray, first: int, misfit: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each texel's colour (K, 3) float32 BGR, its summed weight (K,) and which views took
    part there after the coherence test (V, K) bool (module docstring, colour); ``judged``:
    seen by a view that lines up, ``first``: the number of primary views, ``misfit``: (V, K)
    where a view does not line up locally (``sender.enroll.registration``)."""
    seen = weight_v > 0
    strong = weight_v >= REPLACE_MIN_WEIGHT
    patches = _coherent(kept, judged, covered, REPLACE_WINDOW)
    kept = _coherent(kept, judged, covered, OUTLIER_WINDOW)
    use = np.where(kept, weight_v, 0.0).astype(np.float32)
    plain_w = np.where(judged[:first], weight_v[:first], 0.0)
    plain = _mean(colours[:first], plain_w)  # the primary views that line up, as they are
    robust = _first_kept(colours, kept & strong)  # the best view that takes part, seen well
    replaceable = (kept & strong).any(axis=0)
    rejected = (seen[:first] & ((strong[:first] & ~patches[:first]) | misfit[:first]
                                | ~judged[:first])).any(axis=0) & replaceable
    r = _replaced(rejected, covered) * replaceable
    r = np.where(plain_w.sum(axis=0) > 0, r, np.ceil(r))[:, None]  # no primary: all robust
    blend = (1.0 - r) * plain + r * robust
    total = np.where(r[:, 0] > 0, use.sum(axis=0), plain_w.sum(axis=0))
    return blend, total, kept


def _to_texture(blend: np.ndarray, total: np.ndarray, covered: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W, 3) uint8 RGB texture (black where no view took part) and the (H, W)
    float32 weight from the covered texels' BGR colours and summed weights."""
    height, width = covered.shape
    texture = np.zeros((height, width, 3), np.uint8)
    ok = total > 0
    mean = blend[ok]
    rows, cols = np.nonzero(covered)
    texture[rows[ok], cols[ok]] = np.clip(np.rint(mean[:, ::-1]), 0, 255)  # BGR -> RGB
    weight = np.zeros((height, width), np.float32)
    weight[covered] = total
    return texture, weight

def _mean(colours: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """(K, 3) float32 weighted mean of (K, 3) colours with (V, K) weights (0 where none)."""
    total = np.zeros(weights.shape[1], np.float32)
    out = np.zeros((weights.shape[1], 3), np.float32)
    for c, w in zip(colours, weights):
        out += w[:, None] * c
        total += w
    return out / np.where(total > 0, total, 1.0)[:, None]


def _first_kept(colours: list[np.ndarray], kept: np.ndarray) -> np.ndarray:
    """(K, 3) float32: at each texel the colour of the first view (in the given order) that
    takes part there; 0 where none does."""
    out = np.zeros((kept.shape[1], 3), np.float32)
    todo = np.ones(kept.shape[1], bool)
    for c, k in zip(colours, kept):
        take = todo & k
        out[take] = c[take]
        todo &= ~k
    return out


def _replaced(rejected: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """(K,) float32 r in [0, 1] (module docstring): the texels where a primary view was
    rejected, grown by ``REPLACE_GROW`` texels and feathered by a Gaussian of
    ``REPLACE_FEATHER`` texels."""
    if not rejected.any():
        return np.zeros(len(rejected), np.float32)
    marks = np.zeros(covered.shape, np.uint8)
    marks[covered] = rejected
    size = 2 * REPLACE_GROW + 1
    grown = np.asarray(cv2.dilate(marks, np.ones((size, size), np.uint8)), np.float32)
    smooth = np.asarray(cv2.GaussianBlur(grown, (0, 0), REPLACE_FEATHER), np.float32)
    return np.clip(smooth[covered], 0.0, 1.0)


def _coherent(kept: np.ndarray, seen: np.ndarray, covered: np.ndarray, window: int
              ) -> np.ndarray:
    """(V, K) bool: a view takes part at a texel unless it was an outlier on at least half of
    the texels it sees in the ``window`` square around it (module docstring)."""
    out = kept.copy()
    size = (window, window)
    for i in range(len(kept)):
        outlier = seen[i] & ~kept[i]
        if not outlier.any():
            continue
        o = np.zeros(covered.shape, np.float32)
        n = np.zeros(covered.shape, np.float32)
        o[covered] = outlier
        n[covered] = seen[i]
        o_sum = np.asarray(cv2.boxFilter(o, -1, size, normalize=False,
                                         borderType=cv2.BORDER_CONSTANT), np.float32)
        n_sum = np.asarray(cv2.boxFilter(n, -1, size, normalize=False,
                                         borderType=cv2.BORDER_CONSTANT), np.float32)
        out[i] = seen[i] & (o_sum[covered] < 0.5 * np.maximum(n_sum[covered], 1.0))
    return out


def _robust_keep(luma: np.ndarray, weight: np.ndarray, aligned: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per texel, which views take part (module docstring): (V, K) bool, and each view's
    correlation with the consensus (V,) (NaN: too few shared texels). Views not ``aligned``
    take part nowhere."""
    w = np.where(aligned[:, None], weight, 0.0)
    many = (w > 0).sum(axis=0) >= MIN_VIEWS_FOR_CONSENSUS
    kept = w > 0
    agreement = np.full(len(luma), np.nan)
    if not many.any():
        return kept, agreement
    y, ww = luma[:, many], w[:, many]
    centre = weighted_median(y, ww)
    spread = np.maximum(1.4826 * weighted_median(np.abs(y - centre), ww), SPREAD_FLOOR)
    kept[:, many] = (ww > 0) & (np.abs(y - centre) <= OUTLIER_KAPPA * spread)
    for i in range(len(luma)):
        shared = ww[i] > 0
        if shared.sum() >= _MIN_AREA_TEXELS:
            a, b = y[i, shared], centre[shared]
            if a.std() > 1e-6 and b.std() > 1e-6:
                agreement[i] = float(np.corrcoef(a, b)[0, 1])
    return kept, agreement


def _exposure_gain(colour: np.ndarray, weight: np.ndarray, colour_sum: np.ndarray,
                   weight_sum: np.ndarray) -> np.ndarray:
    """(3,) float32 per-channel gain matching a view's colours to the views before it.

    Over the texels both see, with m = min(w_view, w_before), the gain is the m-weighted
    median of c_before / c_view per channel (module docstring); 1 where they share fewer
    than ``_MIN_SHARED`` texels.
    """
    before = weight_sum > 0
    m = np.where(before, np.minimum(weight, weight_sum), 0.0)
    shared = m > 0
    if np.count_nonzero(shared) < _MIN_SHARED:
        return np.ones(3, np.float32)
    mean_before = colour_sum[shared] / weight_sum[shared, None]
    ratio = mean_before / np.maximum(colour[shared], 1.0)  # (S, 3)
    weights = np.repeat(m[shared, None], 3, axis=1)
    gain = weighted_median(ratio, weights)
    gain = np.where(np.isfinite(gain), gain, 1.0)
    return np.clip(gain, *_GAIN_RANGE).astype(np.float32)


