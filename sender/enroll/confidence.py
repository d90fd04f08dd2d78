"""How well the enrollment saw each texel of the base texture: the model's confidence map.

The fusion (``sender.enroll.fusion``) knows, per texel, the summed weight W of the views
that took part there (each view's weight is its view angle's, so a foreshortened view
counts less, times its edge feather) and which views took part (``Fusion.kept``). The
confidence of a texel is

    c = (1 - exp(-W f / W0)) * g,    W0 = ``VIEW_WEIGHT``

- f, occlusion and blur: the mean over the views that took part of each view's factor, 0
  for a view with a hand on the face (``handed``) or an outlier over the part of the face
  the texel lies in (``occluded``: ``sender.enroll.evidence``), else its sharpness relative
  to the sharpest of the views, clipped to [``BLUR_FLOOR``, 1];
- 1 - exp(-W f / W0): W0 is the weight of one view that sees the texel 45 degrees from
  frontal (``sender.enroll.texture``'s angle weight, ((cos a - 0.1) / 0.9)^4 = 0.21), so
  one such view, sharp and clean, gives 0.63, two 0.86, one frontal view 0.99;
- g, registration: ``MISFIT_FACTOR`` where the views' consensus was judged and does not
  hold (``Fusion.fails``: most of the views judged there do not line up with it), else 1.
  Only structure is judged (an eye, a brow, a lip line); skin, which has none, is not
  doubled by a misregistration and keeps 1 (with 1 only where the consensus holds, 94 % of
  the texels lp_d0's clean enrollment saw had g = 1/2, and 58 % a confidence under 40).

Texels no view saw (filled by the hole filling) have c = 0. The map is stored as 8-bit
grey, 255 c (``models.modelfile``: ``textures/confidence.png``); the sender's healing
(``sender.heal``) corrects low-confidence texels first.
"""

from __future__ import annotations

import numpy as np

from facewire.sender.enroll.fusion import Fusion

VIEW_WEIGHT = 0.21  # W0: the fusion's weight of one view 45 degrees from frontal
BLUR_FLOOR = 0.3  # a view's sharpness factor, at least
MISFIT_FACTOR = 0.5  # confidence kept where the views' consensus does not hold


def texture_confidence(fusion: Fusion, sharpness: np.ndarray, handed: np.ndarray,
                       occluded: dict[str, np.ndarray], parts: dict[str, np.ndarray]
                       ) -> np.ndarray:
    """The confidence map of a fused texture (module docstring).

    Args:
        fusion: the views' fusion, V views.
        sharpness: (V,) float, each view's sharpness (``sender.clean.sharpness``).
        handed: (V,) bool, a hand was found on the face in the view.
        occluded: per part of the face, (V,) bool: the view was an outlier over it.
        parts: per part, (H, W) bool its texels (``sender.enroll.evidence.part_masks``).

    Returns:
        (H, W) uint8, 255 c.
    """
    sharp = np.asarray(sharpness, np.float64)
    factor = np.clip(sharp / max(float(sharp.max()), 1e-9), BLUR_FLOOR, 1.0)
    factor = np.where(np.asarray(handed, bool), 0.0, factor)
    covered = fusion.covered
    per_view = np.repeat(factor[:, None], int(covered.sum()), axis=1)  # (V, K)
    for name, flags in occluded.items():
        inside = parts[name][covered]
        per_view[np.ix_(np.asarray(flags, bool), inside)] = 0.0
    kept = fusion.kept
    count = kept.sum(axis=0)
    mean = np.where(count > 0, (per_view * kept).sum(axis=0) / np.maximum(count, 1), 0.0)
    f = np.zeros(covered.shape)
    f[covered] = mean
    c = (1.0 - np.exp(-fusion.weight.astype(np.float64) * f / VIEW_WEIGHT))
    c *= np.where(fusion.fails, MISFIT_FACTOR, 1.0)
    return np.clip(np.rint(255.0 * c), 0, 255).astype(np.uint8)
