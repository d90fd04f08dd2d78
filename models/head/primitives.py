"""Smooth field primitives of the generic head's skin field (float64 arrays throughout).

- smooth minimum of two fields with blend width k (polynomial):
  ``smin(a, b) = b + (a - b) h - k h (1 - h)``, ``h = clamp(1/2 + (b - a) / (2 k), 0, 1)``;
  ``smax(a, b) = -smin(-a, -b)``;
- smoothstep ``3 t^2 - 2 t^3``, ``t = clamp((x - e0) / (e1 - e0), 0, 1)``;
- bump ``(1 - u^2)^3`` for ``|u| < 1``, else 0;
- ellipsoid (centre c, radii r): the approximate signed distance ``k0 (k0 - 1) / k1``,
  ``k0 = |(q - c) / r|``, ``k1 = |(q - c) / r^2|``, exact on its surface;
- the rotation about y, and unit vectors.
"""

from __future__ import annotations

import numpy as np


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two fields with blend width k (mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum of two fields with blend width k (mm)."""
    return -smin(-a, -b, k)


def sstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Smoothstep from 0 at e0 to 1 at e1 (e1 < e0 gives a falling step)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def bump(u: np.ndarray) -> np.ndarray:
    """(1 - u^2)^3 for |u| < 1, else 0: a smooth bump of height 1 and half-width 1."""
    t = np.clip(1.0 - u * u, 0.0, 1.0)
    return t * t * t


def ellipsoid(q: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (exact on its surface)."""
    r = np.asarray(radii, dtype=np.float64)
    d = (q - np.asarray(centre, dtype=np.float64)) / r
    k0 = np.linalg.norm(d, axis=-1)
    k1 = np.linalg.norm(d / r, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def rot_y(angle_deg: float) -> np.ndarray:
    """(3, 3) rotation by angle_deg about +y (z turns toward x)."""
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def unit(v: np.ndarray) -> np.ndarray:
    """v (..., 3) scaled to unit length along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
