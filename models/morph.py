"""RBF volume morph: move every mesh vertex by a smooth map fitted to a few moving centres.

The math
--------
Centres ``x_1 .. x_M`` (the neutral model's feature and phantom points, mm) move by
displacements ``d_i = target_i - x_i``. Any point ``p`` moves by the displacement field

    F(p) = sum_i c_i h_i(||p - x_i||) + q(p),        p' = p + F(p),

with coefficients ``c`` (M, 3) and a polynomial part ``q`` (below). We interpolate
displacements, not positions, so zero displacements give ``F = 0`` and the neutral points back
bit for bit.

Kernels (``r = ||p - x_i||``):

- ``"multiquadric"`` (default, the paper's): Hardy's ``h_i(r) = sqrt(r^2 + s_i^2)`` with Eck's
  per-centre stiffness ``s_i = min_{j != i} ||x_j - x_i||`` (mm), plus an affine part
  ``q(p) = B (p - x0) / ell + b``.
- ``"gaussian"``: ``h(r) = exp(-(r / w)^2)`` with one width for all centres,
  ``w = 2 * mean_i s_i``: each Gaussian still weighs 0.78 at the typical distance to the
  nearest centre, so the field spreads across the gaps between centres instead of leaving a
  bump at each. One shared width keeps the kernel strictly positive definite (per-centre widths
  would not). No polynomial part (``q = 0``): the Gaussian needs none to be well posed, and
  without one its field decays to zero away from the centres, which is what this option is
  for (with an affine part, fitted through a nearly flat face, the field would extrapolate its
  trend over the whole head: in the head-scan test, everything outside the ring of phantoms
  would move 4 mm on average, up to 9 mm at the shoulders, instead of 0.13 mm).

Fitting, with ``H[j, i] = h_i(||x_j - x_i||)`` (not symmetric for the multiquadric, because
``s_i`` depends on the column) and, for the multiquadric, ``P = alpha [(x_i - x0) / ell, 1]``
(M, 4), where ``x0`` is the centres' centroid, ``ell`` their RMS distance from it and ``alpha``
the largest entry of the regularised kernel block (balancing only: it keeps both blocks of the
system of one size for any ``lam`` and does not change the fitted field):

    multiquadric:  [ H - lambda I   P ] [ c ]   [ d ]        gaussian:  (H + lambda I) c = d.
                   [ P^T            0 ] [ a ] = [ 0 ],

Regularisation (Tikhonov). ``lambda = lam * mean_i H[i, i]``: ``lam`` is RELATIVE to the mean
diagonal of ``H``, i.e. ``lam * mean(s_i)`` mm for the multiquadric and ``lam`` (dimensionless)
for the Gaussian, whose diagonal is 1. Reason: the multiquadric's ``H`` is in mm, so an
absolute lambda would make the morph depend on the unit of length (the same face in metres
would be regularised a thousand times harder), and the paper's ``lambda = 0.01`` carries no
unit; read as relative it means "1 % of the kernel's self-weight", the same smoothing at any
scale. Read as 0.01 mm it would be about 1/2000 of a typical diagonal (s_i ~ 10-30 mm on a
face), i.e. no regularisation at all. With the default on a face, the fit misses the centres
by 3-4 % of their displacement (0.2 mm for a 6 mm move); ``lam -> 0`` interpolates exactly.

The sign of lambda: the paper writes ``c = (H + lambda I)^-1 d``. For the Gaussian (positive
definite) that is ridge regression. Hardy's multiquadric is conditionally NEGATIVE definite of
order 1 (on ``sum_i c_i = 0`` its quadratic form is negative; scipy's ``RBFInterpolator`` writes
it as ``-sqrt(1 + r^2)`` for this reason), so there ``+lambda`` pushes the eigenvalues of the
constrained system toward zero instead of away from it. On the 31 centres of the head-scan test
they lie in [-133, -1.1] mm (mean s_i 17.5 mm): the paper's sign makes the system singular at
``lam`` near 0.062, and at 0.01 it amplifies the mode nearest zero by about 20 % instead of
damping it. We use ``H - lambda I``: exactly Tikhonov for the kernel ``-h`` with coefficients
``-c`` (the fitted field is the same function of ``d`` either way); the residual at the centres
shrinks to zero as ``lam -> 0`` and, as ``lam`` grows, the field's departure from the
least-squares affine fit of the displacements shrinks steadily to zero.

The multiquadric's affine part (the standard polynomial augmentation of RBF interpolation):

- Affine, hence rigid, motions are reproduced EXACTLY for any ``lambda``: if ``d_i = A x_i + t``
  then ``c = 0`` with the matching ``a`` solves the system (first block row ``P a = d``, second
  ``P^T 0 = 0``), and the solution is unique; so ``p' = p + A p + t`` for every point. A small
  rigid error left in the displacements by the pose estimate therefore moves the head rigidly
  instead of distorting the face. The rigid-motion test checks this down to float32 rounding
  (its bound is derived there).
- The side conditions ``sum_i c_i = 0`` (which the multiquadric's conditional definiteness
  needs) and ``sum_i c_i x_i = 0`` make the Tikhonov term a penalty on the non-affine part only.
- It needs four centres that are not coplanar (checked).

Far field. The multiquadric grows with distance, so no variant of it (with or without a
polynomial part) leaves points far outside the centres still: on the head scan, with 13
phantoms around the face held fixed and a 6 mm expression, the rest of the head and the
shoulders move about 2 mm on average, up to 4 mm. Points that must stay rigid need centres of
their own (anchors with zero displacement) or should not be morphed; inside the ring of
phantoms the field decays.

Set-up and per-frame cost
-------------------------
At construction the system ``A`` ((M+4)-square, or M-square for the Gaussian) is LU-factored
once (``scipy.linalg.lu_factor``) and solved for the first M columns of its inverse,
``Z = A^-1 [:, :M]``. With the evaluation rows ``E = [h_i(||p_n - x_i||), (P rows of p_n)]`` of
the points to move, the whole map from centre displacements to point displacements is one
matrix,

    weights = E @ Z   (N, M),      F(p_n) = weights[n] @ d,

computed in float64 and stored in float32. Folding the back-substitution into the kernel
costs nothing per frame (an (N, M) @ (M, 3) product is no bigger than (N, M+4) @ (M+4, 3)),
keeps scipy (and its own OpenBLAS thread pool) entirely out of the per-frame path - each frame
is one numpy float32 GEMM plus one add - and is better conditioned in float32: ``weights``
holds the cardinal functions (values of order one), not large multiquadric coefficients that
cancel. Measured: about 0.12 ms a frame for 10,000 vertices and 31 centres on one core
(OPENBLAS_NUM_THREADS=1).
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import numpy as np
import scipy.linalg

KERNELS = ("multiquadric", "gaussian")

# A condition number above this means the centres are (nearly) degenerate for the system.
_MAX_CONDITION = 1e12


class RbfSolution(NamedTuple):
    """A fitted ``VolumeMorph`` as numbers, for evaluating it elsewhere (the browser's rig,
    ``models.webmodel``): the weights of a point p are ``rows(p) @ z`` with
    ``rows(p) = [h_i(||p - x_i||) for each centre i, then alpha [(p - x0) / ell, 1]]``
    (module docstring; no affine part for the Gaussian).

    Attributes:
        kernel: the kernel name.
        centres: (M, 3) float64 centre positions x_i, mm.
        shape: (M,) float64: the multiquadric's s_i, or the Gaussian's width w for each.
        origin: (3,) float64 x0, the centres' centroid.
        scale: ell, their RMS distance from it, mm.
        balance: alpha, the affine rows' scale.
        z: (M + 4, M) float64 (multiquadric) or (M, M) (Gaussian): the first M columns of the
            system's inverse.
    """

    kernel: str
    centres: np.ndarray
    shape: np.ndarray
    origin: np.ndarray
    scale: float
    balance: float
    z: np.ndarray


class VolumeMorph:
    """RBF volume morph of a fixed set of points driven by displacements of fixed centres.

    Args:
        centres: (M, 3) float32 (float64 accepted) neutral centre positions, mm; distinct and,
            for the multiquadric, not all in one plane.
        points: (N, 3) float32 (float64 accepted) neutral positions of the points to move
            (usually the mesh vertices), mm.
        kernel: ``"multiquadric"`` (Hardy, Eck's stiffness) or ``"gaussian"``.
        lam: Tikhonov weight relative to the mean diagonal of the kernel matrix (see the
            module docstring), >= 0.

    Attributes:
        centres: (M, 3) float32, read-only.
        points: (N, 3) float32, read-only.
        kernel: the kernel name.
        lam: the relative regularisation weight.
        weights: (N, M) float32, read-only: ``apply(d) == points + weights @ d``.

    Raises:
        ValueError: naming the argument, on a bad shape, dtype, non-finite value, repeated
            centres, coplanar centres, an unknown kernel or a bad ``lam``.
    """

    def __init__(
        self,
        centres: np.ndarray,
        points: np.ndarray,
        kernel: str = "multiquadric",
        lam: float = 0.01,
    ) -> None:
        x = _check_xyz("centres", centres)
        if kernel not in KERNELS:
            raise ValueError(f"kernel: expected one of {KERNELS}, got {kernel!r}")
        if isinstance(lam, bool) or not isinstance(lam, (int, float, np.floating, np.integer)):
            raise ValueError(f"lam: expected a real number, got {type(lam).__name__}")
        if not (np.isfinite(lam) and lam >= 0):
            raise ValueError(f"lam: expected a finite number >= 0, got {lam}")
        self.kernel = kernel
        self.lam = float(lam)
        self.centres = _frozen(x.astype(np.float32))
        self._fit(self.centres.astype(np.float64))
        self._bind(_check_xyz("points", points))

    def at(self, points: np.ndarray) -> VolumeMorph:
        """The same fitted morph, evaluated at other points (e.g. template pixel positions).

        Args:
            points: (P, 3) float32 (float64 accepted), mm.

        Returns:
            A ``VolumeMorph`` sharing this one's centres and factorisation, whose ``apply``
            moves ``points``.
        """
        other = copy.copy(self)
        other._bind(_check_xyz("points", points))
        return other

    def solution(self) -> RbfSolution:
        """The fitted system, from which ``weights`` at any point follow (``RbfSolution``)."""
        return RbfSolution(self.kernel, self.centres.astype(np.float64), self._shape.copy(),
                           self._origin.copy(), self._scale, self._balance, self._z.copy())

    def apply(self, displacements: np.ndarray) -> np.ndarray:
        """Move the points by the field fitted to the centres' displacements.

        Args:
            displacements: (M, 3) float32 (float64 accepted and rounded) per-centre
                displacements ``target - centre``, mm, in the centres' order.

        Returns:
            (N, 3) float32 moved points; exactly ``points`` when all displacements are zero.
        """
        d = displacements
        m = self.centres.shape[0]
        if not isinstance(d, np.ndarray):
            raise ValueError(f"displacements: expected a numpy array, got {type(d).__name__}")
        if d.shape != (m, 3):
            raise ValueError(f"displacements: expected shape ({m}, 3), got {d.shape}")
        if d.dtype not in (np.float32, np.float64):
            raise ValueError(f"displacements: expected float32 or float64, got {d.dtype.name}")
        if not np.isfinite(d).all():
            raise ValueError("displacements: contains NaN or infinity")
        out = self.weights @ d.astype(np.float32, copy=False)
        out += self.points
        return out

    def _fit(self, x: np.ndarray) -> None:
        """Factor the (augmented) system for centres ``x`` (M, 3) float64; set ``self._z``."""
        m = x.shape[0]
        if m < 2:
            raise ValueError(f"centres: need at least 2, got {m}")
        dist = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
        np.fill_diagonal(dist, np.inf)
        nearest = dist.min(axis=1)
        if not nearest.min() > 0:
            i = int(np.argmin(nearest))
            j = int(np.argmin(dist[i]))
            raise ValueError(f"centres: rows {i} and {j} are the same point")
        np.fill_diagonal(dist, 0.0)
        if self.kernel == "multiquadric":
            self._shape = nearest  # Eck's s_i, one per centre (column)
            sign = -1.0
        else:
            self._shape = np.full(m, 2.0 * nearest.mean())  # one Gaussian width w
            sign = 1.0
        h = self._kernel_of(dist)
        h += sign * self.lam * np.trace(h) / m * np.eye(m)
        self._origin = x.mean(axis=0)
        self._scale = float(np.sqrt(((x - self._origin) ** 2).sum(axis=1).mean()))
        self._balance = float(np.abs(h).max())
        poly = self._affine_rows(x)
        k = poly.shape[1]
        if k and np.linalg.matrix_rank(poly) < k:
            raise ValueError(
                "centres: all lie in one plane (or on a line); the multiquadric's affine term "
                "needs four centres that are not coplanar"
            )
        system = np.zeros((m + k, m + k))
        system[:m, :m] = h
        system[:m, m:] = poly
        system[m:, :m] = poly.T
        condition = np.linalg.cond(system)
        if not condition < _MAX_CONDITION:
            raise ValueError(
                f"centres: the RBF system is numerically singular (condition number "
                f"{condition:.3g}); are some centres nearly coincident (or, for the Gaussian, "
                f"is lam too small)?"
            )
        factor = scipy.linalg.lu_factor(system)
        self._z = scipy.linalg.lu_solve(factor, np.eye(m + k)[:, :m])

    def _bind(self, p: np.ndarray) -> None:
        """Precompute ``weights`` for points ``p`` (N, 3) float64 and set ``points``."""
        x = self.centres.astype(np.float64)
        dist = np.empty((p.shape[0], x.shape[0]))
        for i, centre in enumerate(x):  # column by column: no (N, M, 3) temporary
            dist[:, i] = np.sqrt(((p - centre) ** 2).sum(axis=1))
        rows = np.hstack([self._kernel_of(dist), self._affine_rows(p)])
        self.points = _frozen(p.astype(np.float32))
        self.weights = _frozen((rows @ self._z).astype(np.float32))

    def _kernel_of(self, dist: np.ndarray) -> np.ndarray:
        """Kernel values for distances ``dist`` (K, M) float64 to the M centres."""
        if self.kernel == "multiquadric":
            return np.sqrt(dist**2 + self._shape**2)
        return np.exp(-((dist / self._shape) ** 2))

    def _affine_rows(self, p: np.ndarray) -> np.ndarray:
        """(K, 4) float64 rows ``alpha [(p - x0) / ell, 1]`` of the affine part; (K, 0) if none."""
        if self.kernel == "gaussian":
            return np.zeros((p.shape[0], 0))
        rows = np.hstack([(p - self._origin) / self._scale, np.ones((p.shape[0], 1))])
        return self._balance * rows


def _check_xyz(name: str, a: np.ndarray) -> np.ndarray:
    """Validate a (K, 3) float32/float64 finite array; return it as float64."""
    if not isinstance(a, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(a).__name__}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (K, 3), got {a.shape}")
    if a.dtype not in (np.float32, np.float64):
        raise ValueError(f"{name}: expected float32 or float64, got {a.dtype.name}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinity")
    return a.astype(np.float64)


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` made read-only (the precomputation must not be edited behind our back)."""
    a.setflags(write=False)
    return a
