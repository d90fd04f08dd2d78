"""The generic head's texture layout (u to the right, v up; 1024 x 512 in the paper).

- Skin, ``u in [0, 0.8]``: a warped cylindrical map of the ray direction,
  ``u = 0.4 +- 0.4 F(az)``, ``v = G(el)``, ``az = atan2(|d_x|, d_z)``, ``el = asin(d_y)``,
  ``+`` for x >= 0 (the image right of a frontal face). F and G are normalised integrals of a
  density that is 1 over the face (az < 70 deg, el from -45 to 52 deg), falling smoothly over
  15 deg to 0.12 (u) or 0.15 (v) elsewhere: the face, between the ears and from hairline to
  chin, takes about half of the texture (62 % of the skin's share). The only seam runs down
  the back of the head (u = 0 and u = 0.8 are the same points); the map's pole turns over a
  few scalp triangles at the very top. Socket cups map into the eye openings of this map,
  which no skin triangle covers.
- Eyeballs: discs of radius ``EYE_UV_RADIUS`` in u (twice that in v: round in texels) centred
  at ``EYE_UV[side]``; the back halves, never seen, have small discs of their own at
  ``EYE_BACK_UV`` (``inserts`` gives the mapping).
- Mouth cavity: a disc at ``MOUTH_UV``, radius ``MOUTH_UV_RADIUS`` in u.
"""

from __future__ import annotations

import numpy as np

from facewire.models.head.primitives import sstep
from facewire.models.head.rays import az_el

SKIN_U_MAX = 0.8
EYE_UV = {"left": (0.95, 0.9), "right": (0.85, 0.9)}
EYE_UV_RADIUS = 0.047  # in u; the v radius is twice as large (square texels on a 2:1 image)
EYE_BACK_UV = {"left": (0.95, 0.2), "right": (0.85, 0.2)}  # the hidden back halves
EYE_BACK_UV_RADIUS = 0.03
MOUTH_UV = (0.9, 0.55)
MOUTH_UV_RADIUS = 0.09


def _warp(values: np.ndarray, lo: float, hi: float, inner: float, outer: float,
          rest: float) -> np.ndarray:
    """Normalised integral over [lo, hi] of a density that is 1 inside [inner, outer] and
    falls smoothly (over 15 degrees) to ``rest`` outside, evaluated at ``values``."""
    grid = np.linspace(lo, hi, 2001)
    ramp = np.radians(15.0)
    inside = sstep(inner - ramp, inner, grid) * sstep(outer + ramp, outer, grid)
    dens = rest + (1.0 - rest) * inside
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return np.interp(values, grid, cum / cum[-1])


def skin_uv(dirs: np.ndarray) -> np.ndarray:
    """Texture coordinates of skin directions (N, 3) with x >= 0 (module docstring)."""
    az, el = az_el(dirs)
    u = 0.5 * SKIN_U_MAX * (1.0 + _warp(az, 0.0, np.pi, -1.0, np.radians(70.0), 0.12))
    v = _warp(el, -np.pi / 2, np.pi / 2, np.radians(-45.0), np.radians(52.0), 0.15)
    return np.column_stack([u, v])
