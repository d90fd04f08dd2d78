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

An update's bytes, format 1 (``encode_update``, ``decode_update``): one msgpack map

=============  =====================================================================
key            value
=============  =====================================================================
format         1
base_sha256    str, 64 lowercase hex
serial         int, 1 .. ``MAX_SERIAL``
region         str, the region's name
position       int
replaces       int or nil
opacity        float in [0, 1]
template       bin, 1024 bytes: the (16, 16) float32 template, little-endian
areas          array, one per area of the region, main first: maps {shape: [h, w],
               diff: bin}, ``diff`` the zlib stream of the (h, w, 3) uint8 array
               (layer - reference) mod 256
=============  =====================================================================

The reference of every area is its state that the new one will sit just before (the state
at index ``position`` of the kept states, or the last one when it goes at the end), in the
model version the update applies to. Texels the update does not change are zero in the
difference and cost almost nothing once compressed: the capture copies the reference's
texels wherever it saw no change, so an update carries only the texels that changed. The
coding is lossless, so the sender's model and every receiver's stay identical.

An update's bytes of format 2 are a texture patch instead (``models.patch``: tiles of the
base texture corrected during the session); ``Update`` is either kind, and
``decode_update``, ``apply_update``, ``update_head`` and ``ModelVersions`` take both.

Decoding treats the bytes as hostile, like a model file: at most ``MAX_UPDATE_BYTES``, a
map with exactly these keys and types, every size checked against the region it names
before anything is inflated, and no zlib stream inflated past the one size it must have (a
decompression bomb is refused after reading that many bytes). Every failure is an
``UpdateError`` naming the update and the field.
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass
from typing import Any, NamedTuple

import msgpack
import numpy as np

from facewire.models.fields import (
    HEX64,
    PATCH_REGION,
    TEMPLATE_SIZE,
    check_integer,
    check_number,
    check_region_name,
)
from facewire.models.modelfile import Area, ModelError, PersonModel, Region
from facewire.models.patch import (
    TexturePatch,
    apply_patch,
    decode_patch,
    is_patch,
    patch_shell,
)
from facewire.protocol.control import MAX_UPDATE_BYTES
from facewire.protocol.packet import MAX_SERIAL

MAX_LEARNED_LAYERS = 8
FORMAT = 1
_KEYS = {"format", "base_sha256", "serial", "region", "position", "replaces", "opacity",
         "template", "areas"}


class UpdateError(ModelError):
    """An update's bytes are malformed or do not fit the model they are applied to."""


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


Update = ModelUpdate | TexturePatch


def apply_update(model: PersonModel, update: Update) -> PersonModel:
    """The model with ``update``'s state in its region (the module docstring's rules), or
    with its texture patch (``models.patch.apply_patch``), held in memory (its ``sha256``
    is "": its version is the base sha256 and the serial).

    Raises ``ModelError`` naming the field when the update does not fit the model: an
    unknown region, a position or replaced index out of range, the rest state replaced, a
    region already at ``MAX_LEARNED_LAYERS`` states, or layer images of the wrong shape.
    """
    if isinstance(update, TexturePatch):
        return apply_patch(model, update)
    old, keep = _neighbours(model, update)
    k = old.layers.shape[0]
    rest = old.rest
    if update.replaces is not None:
        rest -= update.replaces < rest
    elif k >= MAX_LEARNED_LAYERS:
        raise ModelError(f"update {update.serial}: region {update.region!r} already has "
                         f"{k} states, at most {MAX_LEARNED_LAYERS}")
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
    regions = [region if r.name == update.region else r for r in model.regions]
    return dataclasses.replace(model, regions=tuple(regions), sha256="", file_bytes=0)


def _neighbours(model: PersonModel, update: ModelUpdate) -> tuple[Region, list[int]]:
    """The update's region in ``model`` and the indices of the states it keeps (never none:
    the rest state is kept).

    Raises ``ModelError`` naming the field: an unknown region, a replaced state that is past
    the region's or is its rest state, a position past the kept states.
    """
    names = [r.name for r in model.regions]
    if update.region not in names:
        raise ModelError(f"update {update.serial}: region: {update.region!r} is not a region "
                         f"of the model")
    region = model.regions[names.index(update.region)]
    k = region.layers.shape[0]
    if update.replaces is not None:
        if update.replaces >= k:
            raise ModelError(f"update {update.serial}: replaces: {update.replaces} is past the "
                             f"region's {k} states")
        if update.replaces == round(region.rest):
            raise ModelError(f"update {update.serial}: replaces: state {update.replaces} is "
                             f"the rest state")
    keep = [j for j in range(k) if j != update.replaces]
    if update.position > len(keep):
        raise ModelError(f"update {update.serial}: position: {update.position} is past the "
                         f"region's {len(keep)} kept states")
    return region, keep


def references(model: PersonModel, update: ModelUpdate) -> list[np.ndarray]:
    """(h, w, 3) uint8 per area of the update's region, main first: the state the new one
    will sit just before in ``model`` (the module docstring), its bytes' reference; the
    sender's capture copies its texels where the new state shows no change."""
    region, keep = _neighbours(model, update)
    j = keep[min(update.position, len(keep) - 1)]
    return [part.layers[j] for part in region.parts()]


def encode_update(update: ModelUpdate, model: PersonModel) -> bytes:
    """The update's bytes (format 1, the module docstring), against ``model``, the version
    it applies to (its layers are the references of the differences).

    Raises ``ModelError`` when the update does not fit the model (``apply_update``'s checks).
    """
    apply_update(model, update)
    areas = []
    for image, reference in zip(update.layers, references(model, update), strict=True):
        diff = ((image.astype(np.int16) - reference) & 0xFF).astype(np.uint8)
        areas.append({"shape": list(image.shape[:2]), "diff": zlib.compress(diff.tobytes(), 9)})
    data = msgpack.packb({
        "format": FORMAT, "base_sha256": update.base_sha256, "serial": update.serial,
        "region": update.region, "position": update.position, "replaces": update.replaces,
        "opacity": update.opacity, "template": update.template.astype("<f4").tobytes(),
        "areas": areas}, use_bin_type=True)
    if len(data) > MAX_UPDATE_BYTES:
        raise UpdateError(f"update {update.serial}: {len(data)} bytes, at most "
                          f"{MAX_UPDATE_BYTES}")
    return data


def decode_update(data: bytes, model: PersonModel, base_sha256: str,
                  where: str = "update") -> Update:
    """The update held in ``data``, checked against ``model`` (the version it applies to,
    which comes from the model file ``base_sha256``).

    Args:
        data: the update's bytes.
        model: the model version the update applies to.
        base_sha256: the sha256 of the session's model file.
        where: how messages name the update (a log record, a chunk set).

    Raises:
        UpdateError: the bytes are malformed, or the update does not fit ``model``; the
            message names ``where`` and the field.
    """
    try:
        fields = _map(data)
        if is_patch(fields):
            return decode_patch(fields, model, base_sha256)
        return _decode(_checked(fields), model, base_sha256)
    except ModelError as e:
        raise UpdateError(f"{where}: {e}") from e


class UpdateHead(NamedTuple):
    """What an update's bytes say of it without the model (``update_head``)."""

    base_sha256: str
    serial: int
    region: str
    position: int
    replaces: int | None


def update_head(data: bytes, where: str = "update") -> UpdateHead:
    """The scalar fields of an update's bytes, checked, without the model its layers need
    (``facewire inspect`` lists a log's updates with it).

    Raises:
        UpdateError: the bytes are malformed; the message names ``where`` and the field.
    """
    try:
        fields = _map(data)
        if is_patch(fields):
            patch = patch_shell(fields)
            return UpdateHead(patch.base_sha256, patch.serial, PATCH_REGION, 0, None)
        shell = _shell(_checked(fields))
    except ModelError as e:
        raise UpdateError(f"{where}: {e}") from e
    return UpdateHead(shell.base_sha256, shell.serial, shell.region, shell.position,
                      shell.replaces)


def _map(data: bytes) -> dict[str, Any]:
    """The update's msgpack map (of either format), its sizes bounded."""
    if not isinstance(data, (bytes, bytearray)) or len(data) > MAX_UPDATE_BYTES:
        raise UpdateError(f"expected at most {MAX_UPDATE_BYTES} bytes")
    try:
        fields = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True,
                                 max_bin_len=MAX_UPDATE_BYTES, max_str_len=1024,
                                 max_array_len=64, max_map_len=16, max_ext_len=0)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as e:
        raise UpdateError(f"not a msgpack map: {e}") from e
    if not isinstance(fields, dict):
        raise UpdateError("expected a msgpack map")
    return fields


def _checked(fields: dict[str, Any]) -> dict[str, Any]:
    """A state update's map, its keys, format, template and areas' types checked."""
    if set(fields) != _KEYS:
        raise UpdateError(f"expected a map with the keys {sorted(_KEYS)}")
    if fields["format"] != FORMAT:
        raise UpdateError(f"format: {fields['format']!r}, expected {FORMAT}")
    template = fields["template"]
    if not isinstance(template, bytes) or len(template) != 4 * TEMPLATE_SIZE ** 2:
        raise UpdateError(f"template: expected {4 * TEMPLATE_SIZE ** 2} bytes")
    areas = fields["areas"]
    if not isinstance(areas, list) or not all(isinstance(a, dict) and set(a) == {"shape", "diff"}
                                              for a in areas):
        raise UpdateError("areas: expected an array of maps {shape, diff}")
    return fields


def _shell(fields: dict[str, Any]) -> ModelUpdate:
    """The update of ``_checked``'s fields, every scalar checked; its layers are stand-ins
    until inflated."""
    return ModelUpdate(
        base_sha256=fields["base_sha256"], serial=fields["serial"], region=fields["region"],
        position=fields["position"], replaces=fields["replaces"], opacity=fields["opacity"],
        template=np.frombuffer(fields["template"], "<f4").reshape(TEMPLATE_SIZE, TEMPLATE_SIZE)
        .astype(np.float32), layers=(np.zeros((1, 1, 3), np.uint8),))


def _decode(fields: dict[str, Any], model: PersonModel, base_sha256: str) -> ModelUpdate:
    if fields["base_sha256"] != base_sha256:
        raise UpdateError("base_sha256: made for another model file")
    shell = _shell(fields)
    areas = fields["areas"]
    refs = references(model, shell)
    if len(areas) != len(refs):
        raise UpdateError(f"areas: {len(areas)} areas, the region has {len(refs)}")
    layers = tuple(_inflate(area, reference, n)
                   for n, (area, reference) in enumerate(zip(areas, refs, strict=True)))
    update = dataclasses.replace(shell, layers=layers)
    apply_update(model, update)
    return update


def _inflate(area: dict[str, Any], reference: np.ndarray, n: int) -> np.ndarray:
    """One area's layer image: its difference inflated (to exactly the reference's size, never
    past it) and added to the reference."""
    if area["shape"] != list(reference.shape[:2]):
        raise UpdateError(f"areas[{n}]: shape: expected {list(reference.shape[:2])}, the "
                          f"area's layers")
    if not isinstance(area["diff"], bytes):
        raise UpdateError(f"areas[{n}]: diff: expected bin")
    size = reference.size
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(area["diff"], size + 1)
    except zlib.error as e:
        raise UpdateError(f"areas[{n}]: diff: not a zlib stream: {e}") from e
    if len(raw) != size or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise UpdateError(f"areas[{n}]: diff: expected a zlib stream of exactly {size} bytes")
    diff = np.frombuffer(raw, np.uint8).reshape(reference.shape)
    return ((reference.astype(np.int16) + diff) & 0xFF).astype(np.uint8)


class ModelVersions:
    """A session's model versions as a receiver holds them: version 0 is the model file,
    version n the model with updates 1 .. n applied in order (module docstring).

    An update can be decoded only against the version it applies to, so update n is held
    once updates 1 .. n - 1 are; one that comes early waits (``pending``). A frame whose Q
    values refer to version s is shown with ``model(s)``: version s when held, else the
    newest held, whose regions clamp Q to the layers they have (``receiver.render``).

    Held in memory are the base, the newest version and one other (the one before the
    newest, or the one ``model`` gave last); any other is made again when asked for, from
    the nearest of those below it, by applying its updates once more (``apply_update`` is
    exact: the same version, array for array). So a session's versions cost at most three
    models whatever their number: a texture patch's version has a texture of its own
    (``models.patch``), which every version held would otherwise keep for the session.

    Attributes:
        base: the model file (version 0); its ``sha256`` is the session's base sha256.
        updates: the updates applied, in serial order (``updates[n - 1]`` made version n).
        pending: {serial: bytes} received but not yet applicable.
    """

    def __init__(self, base: PersonModel) -> None:
        if not (isinstance(base, PersonModel) and HEX64.fullmatch(base.sha256)):
            raise ModelError("versions: the base must be a model read from its file (its "
                             "sha256 known)")
        self.base = base
        self.updates: list[Update] = []
        self.pending: dict[int, bytes] = {}
        self._newest = base
        self._last = (0, base)  # the other version held, and its serial

    @property
    def held(self) -> int:
        """The newest version held: every update up to it is applied."""
        return len(self.updates)

    def add(self, serial: int, data: bytes, where: str = "update") -> list[Update]:
        """Take update ``serial``'s bytes; returns the updates this made applicable, in order
        (none when it waits for an earlier one, or was held already).

        Raises:
            UpdateError: the bytes (of this update or of one it unblocked) are malformed or
                do not fit the version they apply to; the message names ``where``.
        """
        check_integer(serial, f"{where}: serial", 1, MAX_SERIAL)
        if serial > self.held:
            self.pending.setdefault(serial, bytes(data))
        applied = []
        while self.held + 1 in self.pending:
            n = self.held + 1
            update = decode_update(self.pending.pop(n), self._newest, self.base.sha256,
                                   where if n == serial else f"update {n}")
            if update.serial != n:
                raise UpdateError(f"{where}: serial: the bytes say {update.serial}, the "
                                  f"record {n}")
            self._last = (self.held, self._newest)
            self._newest = apply_update(self._newest, update)
            self.updates.append(update)
            applied.append(update)
        return applied

    def model(self, serial: int) -> PersonModel:
        """The version to show a frame whose Q values refer to version ``serial`` with:
        ``serial`` itself when held, else the newest held."""
        n = min(max(int(serial), 0), self.held)
        if n == self.held:
            return self._newest
        start, model = self._last if self._last[0] <= n else (0, self.base)
        for update in self.updates[start:n]:
            model = apply_update(model, update)
        self._last = (n, model)
        return model
