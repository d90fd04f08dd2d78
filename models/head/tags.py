"""The generic head's skin tags: SKIN (face, neck, sockets), SCALP (above a hairline that
comes down in front of the ears and behind them to the nape) and EAR (near the ear's field).

The hairline is a height against the azimuth about the vertical axis x = 0, z = -5 (0 at the
front), linear between designed points; a triangle is SCALP when its centroid is above it,
EAR when the ear's field is below 2 mm at the centroid (EAR wins). MOUTH_INTERIOR and the
eyeballs are tagged where they are made (``assembly``).
"""

from __future__ import annotations

import numpy as np

from facewire.models.head.rays import RAY_AXIS_Z
from facewire.models.head.skin import ear_field
from facewire.models.mesh import Tag

# Hairline: height (mm) against the azimuth about the vertical axis x = 0, z = -5 (0 at the
# front): the forehead, the temples, the sideburns in front of the ears, down behind them.
_HAIRLINE_AZ = np.radians([0.0, 30.0, 50.0, 65.0, 78.0, 90.0, 100.0, 180.0])
_HAIRLINE_Y = np.array([72.0, 68.0, 55.0, 35.0, 8.0, 5.0, -55.0, -55.0])


def skin_tags(centroids: np.ndarray) -> np.ndarray:
    """SKIN, SCALP (above the hairline) or EAR for skin triangles with centroids (M, 3)."""
    q = np.column_stack([np.abs(centroids[:, 0]), centroids[:, 1], centroids[:, 2]])
    az = np.arctan2(q[:, 0], q[:, 2] - RAY_AXIS_Z)
    tags = np.full(len(q), Tag.SKIN, dtype=np.uint8)
    tags[q[:, 1] > np.interp(az, _HAIRLINE_AZ, _HAIRLINE_Y)] = Tag.SCALP
    tags[ear_field(q) < 2.0] = Tag.EAR
    return tags
