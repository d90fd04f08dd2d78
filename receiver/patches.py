"""A model version's texture patch as a renderer takes it: the texels that changed.

A texture patch (``models.patch``) changes the base texture in a few tiles and moves the
layers of the regions over them by the same amount, so a region's premultiplied volume
a (L - B) is unchanged but for the rounding at 0 and 255. A renderer holding the previous
version writes again only the bounding rectangle of the texels that differ
(``models.patch.changed_rect``, then ``upload_rect``) and rebuilds the texture's mipmaps
(``receiver.render.FaceRenderer.update_regions``), and the volumes of the regions whose
layers changed, as for any update. Whatever process renders (the receiver's, a child of it)
calls these with the two versions.
"""

from __future__ import annotations

import numpy as np


def upload_rect(texture: np.ndarray, rect: tuple[slice, slice]
                ) -> tuple[tuple[int, int, int, int], bytes]:
    """The OpenGL viewport (x, y, width, height; y from the bottom row) and the bytes
    (rows bottom first, RGB, unpadded) that write ``rect`` of ``texture`` (H, W, 3) into a
    texture uploaded whole with its rows flipped (``FaceRenderer``'s)."""
    rows, cols = rect
    height = texture.shape[0]
    data = np.ascontiguousarray(texture[rows, cols][::-1])
    return ((cols.start, height - rows.stop, cols.stop - cols.start, rows.stop - rows.start),
            data.tobytes())
