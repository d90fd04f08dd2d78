"""A model update: one appearance state a region learned during a session.

The enrollment cannot show every face a person makes. During a session the sender may
capture a new state of one region (a layer image for each of the region's areas and a
classification template) and ship it to every receiver as a model update. A model's version
is the pair (base model sha256, update serial): serial 0 is the model file itself, and
update n applies to version n - 1 and makes version n.

Applying an update to a region with k states (``apply_update``):

- ``replaces`` is None: the new state is inserted, so the region has k + 1 states (at most
  ``MAX_LEARNED_LAYERS``); it takes index ``position`` in 0 .. k and every state at or past
  ``position`` moves up one.
- ``replaces`` is r in 0 .. k - 1: state r is removed first, then the new state is inserted
  at ``position`` in 0 .. k - 1; the region keeps k states. The rest state (the neutral) is
  never replaced.

Q stays a scalar along the region's axis because the new state is inserted where it belongs
in the ordering; the region's rest Q moves with the state it names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from facewire.models.fields import (
    HEX64,
    TEMPLATE_SIZE,
    check_integer,
    check_number,
    check_region_name,
)
from facewire.models.modelfile import Area, ModelError, PersonModel, Region

MAX_LEARNED_LAYERS = 8
MAX_SERIAL = 2047


@dataclass(frozen=True, eq=False)
class ModelUpdate:
    """One learned state of one region.

    Attributes:
        base_sha256: the sha256 of the model file the session started from (64 hex).
        serial: this update's serial, 1 .. ``MAX_SERIAL``; it makes model version ``serial``.
        region: the region's name.
        position: the new state's index in the region's ordering after the update.
        replaces: the index of the state it replaces (before the update), or None to insert.
        layers: one (h, w, 3) uint8 RGB image per area of the region, main area first, each
            the shape of that area's layers.
        template: (16, 16) float32, finite, the new state's classification template.
        opacity: the new layer's alpha scale, in [0, 1].
    """

    base_sha256: str
    serial: int
    region: str
    position: int
    replaces: int | None
    layers: tuple[np.ndarray, ...]
    template: np.ndarray
    opacity: float = 1.0

    def __post_init__(self) -> None:
        if not (isinstance(self.base_sha256, str) and HEX64.fullmatch(self.base_sha256)):
            raise ModelError("update: base_sha256: expected 64 lowercase hex digits")
        check_integer(self.serial, "update: serial", 1, MAX_SERIAL)
        check_region_name(self.region, "update: region")
        check_integer(self.position, "update: position", 0, MAX_LEARNED_LAYERS)
        if self.replaces is not None:
            check_integer(self.replaces, "update: replaces", 0, MAX_LEARNED_LAYERS - 1)
        if not isinstance(self.layers, (tuple, list)) or not self.layers:
            raise ModelError("update: layers: expected one image per area")
        for n, image in enumerate(self.layers):
            if not (isinstance(image, np.ndarray) and image.dtype == np.uint8
                    and image.ndim == 3 and image.shape[2] == 3):
                raise ModelError(f"update: layers[{n}]: expected a (h, w, 3) uint8 image")
        object.__setattr__(self, "layers", tuple(self.layers))
        t = self.template
        if not (isinstance(t, np.ndarray) and t.dtype == np.float32
                and t.shape == (TEMPLATE_SIZE, TEMPLATE_SIZE) and np.isfinite(t).all()):
            raise ModelError(f"update: template: expected a finite ({TEMPLATE_SIZE}, "
                             f"{TEMPLATE_SIZE}) float32 array")
        opacity = check_number(self.opacity, "update: opacity")
        if not 0.0 <= opacity <= 1.0:
            raise ModelError(f"update: opacity: expected a number in [0, 1], got {opacity}")
        object.__setattr__(self, "opacity", opacity)


def apply_update(model: PersonModel, update: ModelUpdate) -> PersonModel:
    """The model with ``update``'s state in its region (the module docstring's rules), held
    in memory (its ``sha256`` is "": its version is the base sha256 and the serial).

    Raises ``ModelError`` naming the field when the update does not fit the model: an
    unknown region, a position or replaced index out of range, the rest state replaced, a
    region already at ``MAX_LEARNED_LAYERS`` states, or layer images of the wrong shape.
    """
    names = [r.name for r in model.regions]
    if update.region not in names:
        raise ModelError(f"update {update.serial}: region: {update.region!r} is not a region "
                         f"of the model")
    index = names.index(update.region)
    old = model.regions[index]
    k = old.layers.shape[0]
    keep = list(range(k))
    rest = old.rest
    if update.replaces is not None:
        if update.replaces >= k:
            raise ModelError(f"update {update.serial}: replaces: {update.replaces} is past the "
                             f"region's {k} states")
        if update.replaces == round(old.rest):
            raise ModelError(f"update {update.serial}: replaces: state {update.replaces} is "
                             f"the rest state")
        keep.remove(update.replaces)
        rest -= update.replaces < rest
    elif k >= MAX_LEARNED_LAYERS:
        raise ModelError(f"update {update.serial}: region {update.region!r} already has "
                         f"{k} states, at most {MAX_LEARNED_LAYERS}")
    if update.position > len(keep):
        raise ModelError(f"update {update.serial}: position: {update.position} is past the "
                         f"region's {len(keep)} kept states")
    rest += update.position <= rest
    parts = old.parts()
    if len(update.layers) != len(parts):
        raise ModelError(f"update {update.serial}: layers: {len(update.layers)} images, the "
                         f"region has {len(parts)} areas")
    stacks = []
    for n, (part, image) in enumerate(zip(parts, update.layers, strict=True)):
        if image.shape != part.layers.shape[1:]:
            raise ModelError(f"update {update.serial}: layers[{n}]: shape {image.shape}, the "
                             f"area's layers are {part.layers.shape[1:]}")
        stacks.append(np.insert(part.layers[keep], update.position, image, axis=0))
    templates = np.insert(old.templates[keep], update.position, update.template, axis=0)
    opacity = [old.opacity[j] for j in keep]
    opacity.insert(update.position, update.opacity)
    region = Region(
        name=old.name, uv_rect=old.uv_rect, template_rect=old.template_rect,
        layers=stacks[0], mask=old.mask, templates=templates, opacity=tuple(opacity),
        rest=float(min(max(rest, 0.0), len(opacity) - 1)),
        areas=tuple(Area(a.uv_rect, s, a.mask) for a, s in zip(old.areas, stacks[1:],
                                                                strict=True)))
    regions = list(model.regions)
    regions[index] = region
    return dataclasses.replace(model, regions=tuple(regions), sha256="", file_bytes=0)
