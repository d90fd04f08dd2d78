"""Real model updates for the tests: states made of a real model's own layers.

``blend_update(model, region, serial)`` is the state halfway between a region's last two
states (each area's layers and the template averaged), inserted between them, with the
opacity of the later one: an appearance the model's enrollment did not hold but that lies
where the capture of an in-between expression would put it. ``session_updates`` chains such
updates over several regions, each made against the version before it, and encodes them
(``models.update.encode_update``), as a sender would issue them.
"""

from __future__ import annotations

import numpy as np

from facewire.models.modelfile import PersonModel
from facewire.models.update import ModelUpdate, apply_update, encode_update

REGIONS = ("mouth", "forehead", "brow_furrow", "eyeball_left")


def blend_update(model: PersonModel, base_sha256: str, region: str, serial: int
                 ) -> ModelUpdate:
    """The halfway state between ``region``'s last two states, inserted between them."""
    r = next(r for r in model.regions if r.name == region)
    k = r.layers.shape[0]
    layers = tuple(((p.layers[k - 2].astype(np.uint16) + p.layers[k - 1]) // 2).astype(np.uint8)
                   for p in r.parts())
    template = ((r.templates[k - 2] + r.templates[k - 1]) / 2).astype(np.float32)
    return ModelUpdate(base_sha256=base_sha256, serial=serial, region=region,
                       position=k - 1, replaces=None, layers=layers, template=template,
                       opacity=r.opacity[k - 1])


def session_updates(model: PersonModel, count: int, regions: tuple[str, ...] = REGIONS
                    ) -> tuple[list[bytes], list[PersonModel]]:
    """``count`` updates (serials 1 .. count, regions in turn) of the session of ``model``
    (a model file: its ``sha256``): their bytes, and the versions 0 .. count."""
    versions, data = [model], []
    for serial in range(1, count + 1):
        update = blend_update(versions[-1], model.sha256, regions[(serial - 1) % len(regions)],
                              serial)
        data.append(encode_update(update, versions[-1]))
        versions.append(apply_update(versions[-1], update))
    return data, versions
