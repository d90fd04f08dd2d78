"""Glare: texels where a frame shows a reflection (a spectacle lens, the cornea, wet skin)
instead of the surface, kept out of the base texture and the eye regions' layers.

A reflection is the light's colour, not the surface's: bright and grey. A texel of a frame
with colour c (RGB or BGR, 0-255) and luma y is glare when

    y >= ``SATURATED``                                 (clipped: the surface is lost), or
    y - y_ref >= ``RISE``  and  max(c) - min(c) <= ``GREY`` * y,

y_ref the luma the texel has elsewhere (the views' consensus, or the base texture for a
layer): much brighter than the surface and nearly colourless. Skin is saturated enough
(max - min some 0.25-0.45 of y) to fail the second test even where it shines a little;
the white of an eye is grey but is as bright in the reference, so its rise is small.
The mask is grown by ``GROW`` texels (a reflection's halo is brighter than the surface
too, and not grey enough to be caught).
"""

from __future__ import annotations

import cv2
import numpy as np

SATURATED = 245.0  # luma at or above which a texel is clipped
RISE = 45.0  # grey levels above the reference for a grey texel to be glare
GREY = 0.18  # at most this chroma (max - min over luma) for a texel to be grey
GROW = 2  # texels the glare mask is grown by
_LUMA_RGB = np.array([0.299, 0.587, 0.114], np.float32)


def glare_texels(colour: np.ndarray, reference_luma: np.ndarray, *, bgr: bool = False
                 ) -> np.ndarray:
    """Where a frame's texels show glare (module docstring), before growing.

    Args:
        colour: (..., 3) float32 colours, 0-255, RGB (BGR when ``bgr``).
        reference_luma: (...) float32 the texels' luma elsewhere.

    Returns:
        (...) bool.
    """
    weights = _LUMA_RGB[::-1] if bgr else _LUMA_RGB
    y = colour @ weights
    chroma = colour.max(axis=-1) - colour.min(axis=-1)
    return (y >= SATURATED) | ((y - reference_luma >= RISE) & (chroma <= GREY * y))


def grown(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: an (H, W) glare mask grown by ``GROW`` texels."""
    if not mask.any():
        return mask
    size = 2 * GROW + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def glare_free(colour: np.ndarray, seen: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """A layer read's seen texels without its glare.

    Args:
        colour: (h, w, 3) float32 RGB, the frame's colours at the area's texels.
        seen: (h, w) bool, the texels read from the frame.
        reference: (h, w, 3) RGB, the base texture there.

    Returns:
        (h, w) bool: ``seen`` less the grown glare.
    """
    ref = reference.astype(np.float32) @ _LUMA_RGB
    return seen & ~grown(seen & glare_texels(colour, ref))
