"""Appearance classification: Haar-wavelet template matching, one continuous Q per region.

Each texture region of a person model has k templates T_0 .. T_{k-1} (1 <= k <= 64), 16 x 16
raw grey levels (0..255, float32) ordered along the region's axis (eye open -> closed, gaze
left -> right, ...). Each frame the sender samples every region at m offsets (m = 5, see
``models.regions.OFFSETS``); this module turns those samples into Q in [0, k-1] per region:
Q = j means "looks like template j", fractional values lie between two adjacent templates.

Transform. ``haar_pyramid`` is the orthonormal 2D Haar wavelet decomposition of a 16 x 16
sample, Mallat's pyramid (the non-standard decomposition): at each of the 4 levels one 1D
Haar step (a, d) = ((x[2i] + x[2i+1]) / sqrt 2, (x[2i] - x[2i+1]) / sqrt 2) runs down the
columns and then along the rows of the current approximation block, which then recurses.
The 256 coefficients are laid out like ``pywt.coeffs_to_array(pywt.wavedec2(x, 'haar',
mode='periodization', level=4))[0].ravel()``: the (16, 16) array holds the 1 x 1
approximation at (0, 0), and for the detail blocks of size s (1, 2, 4, 8) the detail along
the rows ("da") at [s:2s, :s], along the columns ("ad") at [:s, s:2s] and the diagonal at
[s:2s, s:2s]. It is one precomputed 256 x 256 matrix ``HAAR_MATRIX`` (built from the 1D
steps; coefficients = flat sample @ HAAR_MATRIX) and one float32 matmul for a whole batch.
Its entries are 0 or +-2^-p (p = 1..4).

Scales and weights. ``SCALE_INDEX`` gives each coefficient's scale, coarse to fine: 0 = the
1 x 1 approximation (1 coefficient), 1 = the coarsest details, 1 x 1 blocks (3), 2 = the
2 x 2 detail blocks (12), 3 = the 4 x 4 blocks (48), 4 = the finest, 8 x 8 blocks (192).
The paper's weights from the coarse top of the pyramid to the finest level are
``ETA`` = (2, 4, 2, 1, 0): the 192 finest details (pixel noise, aliasing) never count.

Normalisation (brightness and contrast). A sample a is replaced by
a' = (a - mean(a)) / max(std(a), floor): its approximation (16 mean(a)) becomes 0 and its
details are divided by max(std, floor), std over the 256 pixels. The floor is per region,
floor = max(MIN_FLOOR, FLOOR_FRACTION * min_j std(T_j)) = max(2, half the smallest template
std) grey levels. Above the floor the normalisation is exact: a' and Q do not change under
a -> g a + o for any gain g > 0 and offset o. Unless the region is flatter than 4 grey
levels, every template has at least twice the floor's std, so templates, and samples like
them, stay exactly invariant down to half their contrast; a sample flatter than that
(occluded, saturated, blurred, a featureless patch with sensor noise) is divided by the
floor instead of being blown up to unit contrast, so its features stay small instead of
becoming amplified noise that matches whichever template the noise happens to resemble.
Why a relative floor: on 5 shared clips (16 x 16 boxes around the tracked eyes; lp_d14,
lp_d3, openface_gaze, openface_default, hdtf_katiehill) eye patches have std 14-54 grey
levels and closed eyes are no flatter than open ones (5th percentile over closed frames
14-44, median closed / open 0.7-1.1), while the finest-scale detail (median |d| / 0.6745,
noise plus fine texture) is 3-12: half the flattest template is then 7-22, above the noise,
and an absolute floor low enough for the flattest region would be far below the contrast
of the others. Documented range (checked by tests/test_classify.py on templates and blends
of adjacent templates of synthetic eye, gaze and mouth families): gain 0.6 .. 1.6 about
mid-grey and offset -40 .. +40 grey levels, on samples that stay within 0..255 (clipping
cannot be undone), move Q by at most 0.1 (measured: at most 0.013; gain 0.5 moved it by up
to 0.075, gain 0.4 by up to 1.0).

Exact arithmetic. Samples are rounded to 1/64 grey level first (an error of at most 1/128
grey level, far below that of 8-bit pixels). The matrix entries being 0 or +-2^-p, every
product and partial sum of the matmul is then exact in float32 for |a| < 1024, and the mean
and variance come from sums of integers, exact in float64 for the same range.
So a sample's features do not depend on BLAS blocking or on the sample's place in the batch
(measured: OpenBLAS sgemm gives the same row different last bits in batches of different
sizes), and a sample equal to a template scores exactly 0 in any batch.

Template features. For each normalised, transformed template j the ``n_keep`` = 50
largest-magnitude coefficients among the 63 details with non-zero weight (scales 1-3) are
kept (indices K_j; ties in magnitude go to the coarser scale, then to the lower layout
index). The approximation also has weight 2 but is 0 after normalisation in every template
and sample, so it would add 0 to every score: it is left out. The score of a sample a
against template j is the weighted L1 distance on those indices, on actual coefficient
values (not sign-quantised):

    phi_j(a) = sum over i in K_j of eta(i) |c_j,i - a'_i|

Interpolation. gamma is the template with the smallest score. The side s = +-1 toward which
the sample lies is the neighbour whose score fell furthest relative to its score of template
gamma itself: rho_s = phi_{gamma+s}(a) / phi_{gamma+s}(T_gamma), s = +1 when rho_+ <= rho_-
(a missing neighbour has rho = inf). With lo = min(gamma, gamma + s), hi = lo + 1:

    u = phi_lo(a) / phi_lo(T_hi),   v = phi_hi(a) / phi_hi(T_lo),   Q = lo + u / (u + v)

Why: if a's normalised coefficients are the blend (1 - t) c_lo + t c_hi, then on every index
c_lo - a' = t (c_lo - c_hi) and c_hi - a' = (1 - t) (c_hi - c_lo), so phi_lo(a) =
t phi_lo(T_hi) and phi_hi(a) = (1 - t) phi_hi(T_lo) exactly (L1 is homogeneous): u = t,
v = 1 - t and Q = lo + t, linear in t and exactly lo and hi at the templates. Any sample
gets Q in [lo, hi] of the pair chosen. A blend of the raw templates differs from the above
by the normalisation only (its std is below the blend of the stds, so its normalised
coefficients are the chord point scaled up): Q(t) bends but, on the test families, stays
monotonic, exact at both ends and near linear (t = 0.5 gave Q between lo + 0.42 and
lo + 0.59). Q depends only on the pair, not on which of lo and hi is gamma, so it is
continuous where gamma changes (the pair is always evaluated as lo + u / (u + v): the same
bits on both sides). The paper's "interpolate the peak of the three scores" read as a
parabola fit is not exact at the templates (phi has a V-shaped minimum, not a parabolic
one). k = 1 gives Q = 0; at the ends of the axis (so for k = 2) only one neighbour exists.
Adjacent templates that are identical after normalisation (a region the enrollment video
never varied, or one that was flat) cannot be told apart: the lower index wins ties, and
their pair interpolates with the plain ratio phi_lo / (phi_lo + phi_hi) (1/2 between two
identical templates), so Q stays defined and within [0, k-1].

Offsets. Of the m samples of a region, the one whose best score is smallest wins (ties: the
lower offset index); the others are discarded. ``RegionClassifiers.classify`` takes all
regions' samples of a frame, (R, m, 16, 16): one float32 matmul of the R m samples with
the 63 eligible columns of ``HAAR_MATRIX`` (the finest details are only needed for the std,
which comes from the pixels), then vectorised scoring over all regions, padded to the
largest k. 7 regions x 5 offsets with k = 3..6 take 0.2-0.3 ms (median, one core).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from facewire.models.fields import MAX_LAYERS, TEMPLATE_SIZE

LEVELS = 4
N_COEFFS = TEMPLATE_SIZE * TEMPLATE_SIZE
ETA = (2.0, 4.0, 2.0, 1.0, 0.0)
N_KEEP = 50
FLOOR_FRACTION = 0.5
MIN_FLOOR = 2.0
QUANTUM_STEPS = 64  # samples are rounded to 1 / QUANTUM_STEPS grey level before the matmul

assert 2**LEVELS == TEMPLATE_SIZE


def _haar_step(x: np.ndarray, axis: int) -> np.ndarray:
    """One orthonormal 1D Haar step along ``axis``: approximations first, then details."""
    even = np.take(x, np.arange(0, x.shape[axis], 2), axis=axis)
    odd = np.take(x, np.arange(1, x.shape[axis], 2), axis=axis)
    return np.concatenate([(even + odd) / math.sqrt(2), (even - odd) / math.sqrt(2)], axis=axis)


def _pyramid_matrix() -> np.ndarray:
    """(256, 256) float32: row p is the pyramid of the unit image with a 1 at flat pixel p."""
    out = np.eye(N_COEFFS).reshape(N_COEFFS, TEMPLATE_SIZE, TEMPLATE_SIZE)
    size = TEMPLATE_SIZE
    for _ in range(LEVELS):
        block = out[:, :size, :size]
        out[:, :size, :size] = _haar_step(_haar_step(block, 1), 2)
        size //= 2
    matrix = out.reshape(N_COEFFS, N_COEFFS).astype(np.float32)  # entries round to +-2^-p
    matrix.flags.writeable = False
    return matrix


def _scale_index() -> np.ndarray:
    """(256,) int8: 0 for the approximation, 1 + log2 of the block size for the details."""
    rows, cols = np.indices((TEMPLATE_SIZE, TEMPLATE_SIZE))
    reach = np.maximum(rows, cols).ravel()
    index = np.zeros(N_COEFFS, np.int8)
    index[reach > 0] = np.floor(np.log2(reach[reach > 0])).astype(np.int8) + 1
    index.flags.writeable = False
    return index


HAAR_MATRIX = _pyramid_matrix()
SCALE_INDEX = _scale_index()
_WEIGHT = np.asarray(ETA, np.float32)[SCALE_INDEX]  # (256,) eta of each coefficient
# The 63 details that can count (the approximation is 0 once the mean is removed).
_ELIGIBLE = np.flatnonzero((_WEIGHT > 0) & (SCALE_INDEX > 0))
_ELIGIBLE_MATRIX = np.ascontiguousarray(HAAR_MATRIX[:, _ELIGIBLE] / np.float32(QUANTUM_STEPS))


def haar_pyramid(samples: np.ndarray) -> np.ndarray:
    """The orthonormal 4-level 2D Haar pyramid of each sample (layout: module docstring).

    Args:
        samples: (n, 16, 16) float32, finite.

    Returns:
        (n, 256) float32 coefficients, ``samples.reshape(n, 256) @ HAAR_MATRIX``.
    """
    _check_samples(samples, "samples", "n")
    return samples.reshape(len(samples), N_COEFFS) @ HAAR_MATRIX


@dataclass(frozen=True)
class Classification:
    """One region's result.

    Attributes:
        q: continuous template index in [0, k-1].
        offset: index of the winning sample among the m offsets.
        score: its best (smallest) score phi_gamma, in normalised coefficient units.
    """

    q: float
    offset: int
    score: float


@dataclass(frozen=True, eq=False)
class FrameClassification:
    """All regions' results for one frame.

    Attributes:
        q: (R,) float32, each region's Q in [0, k_r - 1].
        offset: (R,) int64, the winning offset of each region.
        score: (R,) float32, the winning sample's best score.
    """

    q: np.ndarray
    offset: np.ndarray
    score: np.ndarray


class TemplateClassifier:
    """One region's k templates, precomputed for scoring (see the module docstring).

    Attributes:
        k: number of templates.
        floor: the region's std floor, grey levels.
        kept: (k, n_keep) int64, each template's kept coefficient indices (layout order).
        values: (k, n_keep) float32, the normalised template coefficients at ``kept``.
        weights: (k, n_keep) float32, eta at ``kept``.
        cross: (k, k) float32, cross[a, b] = phi_b(T_a), template a scored against b.
    """

    def __init__(self, templates: np.ndarray, n_keep: int = N_KEEP) -> None:
        """Args:
            templates: (k, 16, 16) float32 raw grey levels, finite, 1 <= k <= 64, in axis
                order.
            n_keep: coefficients kept per template, 1 .. 63 (the paper: 50).
        """
        _check_samples(templates, "templates", "k")
        k = len(templates)
        if not 1 <= k <= MAX_LAYERS:
            raise ValueError(f"templates: {k} templates, expected 1 to {MAX_LAYERS}")
        if isinstance(n_keep, bool) or not isinstance(n_keep, (int, np.integer)) \
                or not 1 <= n_keep <= len(_ELIGIBLE):
            raise ValueError(f"n_keep: expected an integer in [1, {len(_ELIGIBLE)}], "
                             f"got {n_keep!r}")
        coeffs, energy = _coefficients(templates.reshape(k, N_COEFFS))
        std = np.sqrt(energy / N_COEFFS)
        self.k = k
        self.floor = max(MIN_FLOOR, FLOOR_FRACTION * float(std.min()))
        features = coeffs * _scales(energy, np.full(k, self.floor))[:, None]  # (k, 63)
        order = np.lexsort((np.broadcast_to(_ELIGIBLE, features.shape),
                            np.broadcast_to(SCALE_INDEX[_ELIGIBLE], features.shape),
                            -np.abs(features)), axis=-1)
        self._positions = order[:, :n_keep]  # columns of the 63 eligible coefficients
        self.kept = _ELIGIBLE[self._positions]
        self.values = np.take_along_axis(features, self._positions, axis=1)
        self.weights = _WEIGHT[self.kept]
        diff = np.abs(self.values[None] - features[:, self._positions])  # (a, b, n_keep)
        self.cross = (diff * self.weights[None]).sum(axis=-1, dtype=np.float32)
        for array in (self.kept, self.values, self.weights, self.cross):
            array.flags.writeable = False
        self._frame = RegionClassifiers([self])

    def scores(self, samples: np.ndarray) -> np.ndarray:
        """Scores phi_j of each sample against each template.

        Args:
            samples: (m, 16, 16) float32 raw grey levels, finite, m >= 1.

        Returns:
            (m, k) float32.
        """
        _check_samples(samples, "samples", "m")
        return self._frame.scores(samples[None])[0, :self.k].T

    def classify(self, samples: np.ndarray) -> Classification:
        """Q of the best of m offset samples.

        Args:
            samples: (m, 16, 16) float32 raw grey levels, finite, m >= 1.
        """
        _check_samples(samples, "samples", "m")
        frame = self._frame.classify(samples[None])
        return Classification(float(frame.q[0]), int(frame.offset[0]), float(frame.score[0]))


class RegionClassifiers:
    """All regions of a model, classified together from one frame's samples.

    Attributes:
        regions: the regions' ``TemplateClassifier`` in the caller's (packet) order.
    """

    def __init__(self, regions: Sequence[np.ndarray | TemplateClassifier],
                 n_keep: int = N_KEEP) -> None:
        """Args:
            regions: per region, its (k, 16, 16) float32 templates (see ``TemplateClassifier``)
                or a ready ``TemplateClassifier``; at least one region.
            n_keep: coefficients kept per template for regions given as arrays.
        """
        if (isinstance(regions, np.ndarray)  # type: ignore[unreachable]  # untyped callers
                or not isinstance(regions, Sequence) or len(regions) == 0):
            raise ValueError("regions: expected a non-empty sequence of template arrays")
        built = []
        for r, region in enumerate(regions):
            if isinstance(region, TemplateClassifier):
                built.append(region)
                continue
            try:
                built.append(TemplateClassifier(region, n_keep))
            except ValueError as error:
                raise ValueError(f"regions[{r}]: {error}") from None
        self.regions = tuple(built)
        count, kmax = len(built), max(c.k for c in built)
        n_keep_max = max(c.kept.shape[1] for c in built)
        self._floor = np.array([c.floor for c in built])
        self._kept = np.zeros((count, kmax, n_keep_max), np.int64)  # eligible columns
        self._values = np.zeros((count, kmax, n_keep_max), np.float32)
        self._weights = np.zeros((count, kmax, n_keep_max), np.float32)  # padding counts 0
        self._absent = np.zeros((count, kmax), np.float32)  # +inf for padding templates
        # phi_{j+1}(T_j) and phi_{j-1}(T_j); 1 where the neighbour does not exist.
        self._up = np.ones((count, kmax + 1), np.float32)
        self._down = np.ones((count, kmax + 1), np.float32)
        for r, c in enumerate(built):
            n = c.kept.shape[1]
            self._kept[r, :c.k, :n] = c._positions
            self._values[r, :c.k, :n] = c.values
            self._weights[r, :c.k, :n] = c.weights
            self._absent[r, c.k:] = np.inf
            j = np.arange(c.k - 1)
            up, down = c.cross[j, j + 1], c.cross[j + 1, j]
            alike = (up == 0) | (down == 0)  # identical templates: plain score ratio
            self._up[r, j] = np.where(alike, 1, up)
            self._down[r, j + 1] = np.where(alike, 1, down)
        self._rows = np.arange(count)
        self._gather: dict[int, np.ndarray] = {}

    def scores(self, samples: np.ndarray) -> np.ndarray:
        """Every sample's score against every template of its region.

        Args:
            samples: (R, m, 16, 16) float32 raw grey levels, finite, m >= 1.

        Returns:
            (R, kmax, m) float32 phi; +inf for the padding templates of regions with
            k < kmax (kmax = the largest k).
        """
        count, m = self._check_frame(samples)
        coeffs, energy = _coefficients(samples.reshape(count * m, N_COEFFS))
        scale = _scales(energy, np.repeat(self._floor, m)).reshape(count, 1, m, 1)
        index = self._gather.get(m)
        if index is None:  # flat indices of each template's kept coefficients in each sample
            base = (self._rows[:, None, None, None] * m + np.arange(m)[None, None, :, None])
            index = base * len(_ELIGIBLE) + self._kept[:, :, None, :]
            self._gather[m] = index
        diff = coeffs.ravel()[index]  # (R, kmax, m, n_keep)
        diff *= scale
        diff -= self._values[:, :, None, :]
        np.abs(diff, out=diff)
        diff *= self._weights[:, :, None, :]
        return np.add.reduce(diff, axis=-1) + self._absent[:, :, None]

    def classify(self, samples: np.ndarray) -> FrameClassification:
        """Q, winning offset and score of every region (module docstring).

        Args:
            samples: (R, m, 16, 16) float32 raw grey levels, finite, m >= 1 samples (offsets)
                per region, regions in ``self.regions`` order.
        """
        phi = self.scores(samples)  # (R, kmax, m)
        best = np.minimum.reduce(phi, axis=1)  # (R, m)
        offset = best.argmin(axis=1)
        rows = self._rows
        phis = phi[rows, :, offset]  # (R, kmax): the winning sample's scores
        gamma = phis.argmin(axis=1)
        score = phis[rows, gamma]
        padded = np.full((len(rows), phis.shape[1] + 2), np.inf, np.float32)
        padded[:, 1:-1] = phis  # padded[:, j + 1] = phi_j; inf beyond the templates
        rho_up = padded[rows, gamma + 2] / self._up[rows, gamma]
        rho_down = padded[rows, gamma] / self._down[rows, gamma]
        lo = np.where(rho_up <= rho_down, gamma, gamma - 1)  # k = 1: both inf, lo = 0
        u = padded[rows, lo + 1] / self._down[rows, lo + 1]
        v = padded[rows, lo + 2] / self._up[rows, lo]
        with np.errstate(invalid="ignore"):  # u = v = 0 takes the other branch
            t = np.where(u > 0, u / (u + v), np.float32(0))  # k = 1: v = inf, t = 0
        q = (lo + t).astype(np.float32)
        return FrameClassification(q, offset.astype(np.int64), score.astype(np.float32))

    def _check_frame(self, samples: np.ndarray) -> tuple[int, int]:
        _check_samples(samples, "samples", "R, m")
        if samples.shape[0] != len(self.regions) or samples.shape[1] < 1:
            raise ValueError(f"samples: expected shape (R={len(self.regions)}, m >= 1, "
                             f"{TEMPLATE_SIZE}, {TEMPLATE_SIZE}), got {samples.shape}")
        return samples.shape[0], samples.shape[1]


def _check_samples(x: object, name: str, lead: str) -> None:
    """Raise ValueError naming ``name`` unless x is a finite float32 (lead..., 16, 16) array.

    ``lead`` names the leading axes, e.g. "k" or "R, m".
    """
    if not isinstance(x, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(x).__name__}")
    if x.dtype != np.float32:
        raise ValueError(f"{name}: expected float32, got {x.dtype}")
    if x.ndim != lead.count(",") + 3 or x.shape[-2:] != (TEMPLATE_SIZE, TEMPLATE_SIZE):
        raise ValueError(f"{name}: expected shape ({lead}, {TEMPLATE_SIZE}, {TEMPLATE_SIZE}), "
                         f"got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{name}: contains NaN or infinity")


def _coefficients(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact eligible coefficients and detail energy of samples rounded to 1/64 grey level.

    Args:
        flat: (n, 256) float32 raw grey levels.

    Returns:
        (n, 63) float32 coefficients at ``_ELIGIBLE``, and (n,) float64 detail energy,
        256 var of the rounded sample (sums of integers, exact in float64).
    """
    steps = np.rint(flat * np.float32(QUANTUM_STEPS))  # integers: sample * 64
    coeffs = steps @ _ELIGIBLE_MATRIX
    wide = steps.astype(np.float64)
    total = np.add.reduce(wide, axis=1)
    energy = (np.einsum("ij,ij->i", wide, wide) - total * total / N_COEFFS) \
        / QUANTUM_STEPS**2
    return coeffs, energy


def _scales(energy: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(n,) float32 1 / max(std, floor) from the detail energy (n,) and floors (n,)."""
    return (1.0 / np.maximum(np.sqrt(energy / N_COEFFS), floor)).astype(np.float32)
