"""The texture's texel grid: a UV rectangle snapped outward to texel edges.

A texture of (H, W) texels covers UV [0, 1]^2 with v up: texel row r spans
v in [1 - (r + 1) / H, 1 - r / H] (row 0 at v = 1) and column c spans u in [c / W, (c + 1) / W].
A rectangle (u0, v0, u1, v1) covers the columns floor(u0 W) .. ceil(u1 W) - 1 and the rows
floor((1 - v1) H) .. ceil((1 - v0) H) - 1, clipped to the texture (a 1e-9 tolerance keeps a
rectangle already on texel edges where it is). The region layers (``models.regions``), the
texture patches (``models.patch``) and the sender's texel samplers all place their pixels
with it, so that a layer's pixel is a texel of the texture.
"""

from __future__ import annotations

import numpy as np


def texel_rect(rect: tuple[float, float, float, float], texture_shape: tuple[int, int]
               ) -> tuple[tuple[float, float, float, float], tuple[slice, slice]]:
    """A UV rectangle grown to texel edges and clipped to [0, 1], and its texel slices.

    Args:
        rect: (u0, v0, u1, v1), UV, v up.
        texture_shape: (H, W) texels; texel row r spans v in [1 - (r+1)/H, 1 - r/H].

    Returns:
        The snapped rectangle, and (rows, columns) slices of the texture it covers (row 0 at
        its top, v = v1).
    """
    h, w = texture_shape
    c0 = max(0, int(np.floor(rect[0] * w + 1e-9)))
    c1 = min(w, int(np.ceil(rect[2] * w - 1e-9)))
    r0 = max(0, int(np.floor((1.0 - rect[3]) * h + 1e-9)))
    r1 = min(h, int(np.ceil((1.0 - rect[1]) * h - 1e-9)))
    snapped = (c0 / w, 1.0 - r1 / h, c1 / w, 1.0 - r0 / h)
    return snapped, (slice(r0, r1), slice(c0, c1))
