"""A texture patch: tiles of the base texture a session corrected (healing).

The enrollment fuses the base texture from a few seconds of video; what it saw badly (a hand
its detector missed, a side never turned to the camera) stays there. During a session the
sender may correct tiles of it (``sender.heal``) and ship them as a model update of their
own kind: update n (``models.update``'s serials and versions, applied to version n - 1) is
either a learned region state or a patch.

A patch holds at most ``MAX_TILES`` tiles. A tile is a texel rectangle of the base texture,
rows ``row .. row + s h - 1`` and columns ``col .. col + s w - 1``, s the patch's
``scale`` (1 .. ``MAX_SCALE``), and a difference image D (h, w, 3) uint8 at 1 / s of the
texture's resolution (the camera's: a face spans fewer pixels in a frame than texels in the
texture, so the finer texels would carry nothing it saw), stored as 8-bit RGB PNG. Applying
it (``apply_patch``):

    d = ``DIFF_STEP`` (D - 128)                          (signed, grey levels)
    d' = bilinear(d) to (s h, s w)                       (cv2.resize INTER_LINEAR: half-texel
                                                           centres, edges replicated)
    T'[tile] = clip(round(T[tile] + d'), 0, 255)         (the base texture)
    L'_j[tile ∩ area] = clip(L_j + (T' - T), 0, 255)      (every state j of every region area
                                                           the tile overlaps)

The regions' layers move with the texture under them, so a region's premultiplied volume
(``receiver.render``: a (L - B)) is unchanged and its rest layer stays the texture under it
(``sender.enroll.build.at_rest``): the correction shows in every state. A difference of zero
leaves a texel exactly as it was, so a tile need not be square with what changed.

The bytes, format 2 (``encode_patch``, ``decode_patch``): one msgpack map

=============  =====================================================================
key            value
=============  =====================================================================
format         2
base_sha256    str, 64 lowercase hex
serial         int, 1 .. ``MAX_SERIAL``
scale          int, 1 .. ``MAX_SCALE``
tiles          array of 1 .. ``MAX_TILES`` maps {row: int, col: int, shape: [h, w],
               png: bin}, h and w in 1 .. ``MAX_TILE_SIDE``, the rectangle inside the
               texture, the PNG's header (checked before it is decoded) (h, w) RGB 8-bit
=============  =====================================================================

Decoding treats the bytes as hostile: at most ``protocol.control.MAX_UPDATE_BYTES``, exact
keys and types, each tile's place checked against the texture it patches and its PNG's
header against its declared shape before anything is inflated; every failure is a
``PatchError`` naming the update and the field, and nothing of the model changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import cv2
import msgpack
import numpy as np

from facewire.models.archive import decode_png, png_bytes
from facewire.models.fields import HEX64, PATCH_REGION, ModelError, check_integer
from facewire.models.modelfile import Area, PersonModel
from facewire.models.texelgrid import texel_rect
from facewire.protocol.control import MAX_UPDATE_BYTES
from facewire.protocol.packet import MAX_SERIAL

FORMAT = 2
MAX_TILES = 64
MAX_TILE_SIDE = 64
MAX_SCALE = 16
DIFF_STEP = 4  # grey levels per step of a stored difference
_KEYS = {"format", "base_sha256", "serial", "scale", "tiles"}
_TILE_KEYS = {"row", "col", "shape", "png"}


class PatchError(ModelError):
    """A patch's bytes are malformed or do not fit the model they are applied to."""


@dataclass(frozen=True, eq=False)
class Tile:
    """One tile of a patch (module docstring).

    Attributes:
        row, col: its first texel (row 0 at v = 1).
        diff: (h, w, 3) uint8, the stored difference D (128: no change).
    """

    row: int
    col: int
    diff: np.ndarray


@dataclass(frozen=True, eq=False)
class TexturePatch:
    """Tiles of the base texture corrected during a session: one model update.

    Attributes:
        base_sha256: the session's model file's sha256 (64 hex).
        serial: 1 .. ``MAX_SERIAL``: it makes model version ``serial``.
        scale: texels per stored difference pixel, 1 .. ``MAX_SCALE``.
        tiles: 1 .. ``MAX_TILES`` tiles.
    """

    base_sha256: str
    serial: int
    scale: int
    tiles: tuple[Tile, ...]
    region = PATCH_REGION  # what a model's ``learned`` record names as its region
    position = 0
    replaces = None

    def __post_init__(self) -> None:
        if not (isinstance(self.base_sha256, str) and HEX64.fullmatch(self.base_sha256)):
            raise ModelError("patch: base_sha256: expected 64 lowercase hex digits")
        check_integer(self.serial, "patch: serial", 1, MAX_SERIAL)
        check_integer(self.scale, "patch: scale", 1, MAX_SCALE)
        if not isinstance(self.tiles, (tuple, list)) or not 1 <= len(self.tiles) <= MAX_TILES:
            raise ModelError(f"patch: tiles: expected 1 to {MAX_TILES} tiles")
        for n, tile in enumerate(self.tiles):
            d = tile.diff
            if not (isinstance(d, np.ndarray) and d.dtype == np.uint8 and d.ndim == 3
                    and d.shape[2] == 3 and 1 <= d.shape[0] <= MAX_TILE_SIDE
                    and 1 <= d.shape[1] <= MAX_TILE_SIDE):
                raise ModelError(f"patch: tiles[{n}]: diff: expected (h, w, 3) uint8 with h, "
                                 f"w in [1, {MAX_TILE_SIDE}]")
            check_integer(tile.row, f"patch: tiles[{n}].row", 0, 2**16)
            check_integer(tile.col, f"patch: tiles[{n}].col", 0, 2**16)
        object.__setattr__(self, "tiles", tuple(self.tiles))

    def rects(self) -> list[tuple[slice, slice]]:
        """Each tile's texel rectangle (rows, columns) in the texture."""
        s = self.scale
        return [(slice(t.row, t.row + s * t.diff.shape[0]),
                 slice(t.col, t.col + s * t.diff.shape[1])) for t in self.tiles]


def tile_diff(target: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 the stored difference D of a tile whose texels should become
    ``target`` ((h, w, 3) float, at the patch's scale) where they are ``texture``'s
    (the same shape, the texture there resized to the scale): 128 + round(diff / step)."""
    step = np.rint((np.asarray(target, np.float32) - texture) / DIFF_STEP)
    return np.clip(step + 128, 0, 255).astype(np.uint8)


def apply_patch(model: PersonModel, patch: TexturePatch) -> PersonModel:
    """The model with ``patch``'s tiles applied (module docstring), held in memory (its
    ``sha256`` is "").

    Raises ``ModelError`` naming the tile when one lies outside the texture.
    """
    texture = model.texture.copy()
    height, width = texture.shape[:2]
    for n, (tile, (rows, cols)) in enumerate(zip(patch.tiles, patch.rects(), strict=True)):
        if rows.stop > height or cols.stop > width:
            raise PatchError(f"patch {patch.serial}: tiles[{n}]: texels [{rows.start}:"
                             f"{rows.stop}, {cols.start}:{cols.stop}] lie outside the "
                             f"{height} x {width} texture")
        stored = DIFF_STEP * (tile.diff.astype(np.float32) - 128.0)
        d = cv2.resize(stored, (cols.stop - cols.start, rows.stop - rows.start),
                       interpolation=cv2.INTER_LINEAR)
        old = texture[rows, cols].astype(np.int16)
        new = np.clip(np.rint(old + d), 0, 255).astype(np.int16)
        texture[rows, cols] = new.astype(np.uint8)
    regions = []
    for region in model.regions:
        parts = [_moved(part, model.texture, texture) for part in region.parts()]
        if all(p is q for p, q in zip(parts, region.parts(), strict=True)):
            regions.append(region)
            continue
        regions.append(dataclasses.replace(region, layers=parts[0].layers,
                                           areas=tuple(parts[1:])))
    return dataclasses.replace(model, texture=texture, regions=tuple(regions), sha256="",
                               file_bytes=0)


def _moved(area: Area, old: np.ndarray, new: np.ndarray) -> Area:
    """The area with the texture's change under it (``new - old``, (H, W, 3) uint8 each)
    added to each of its layers (itself when nothing under it changed)."""
    rows, cols = texel_rect(area.uv_rect, old.shape[:2])[1]
    if (new[rows, cols].shape != area.layers.shape[1:]
            or np.array_equal(new[rows, cols], old[rows, cols])):
        return area
    under = new[rows, cols].astype(np.int16) - old[rows, cols]
    layers = np.clip(area.layers.astype(np.int16) + under, 0, 255).astype(np.uint8)
    return Area(area.uv_rect, layers, area.mask)


def changed_rect(old: np.ndarray, new: np.ndarray) -> tuple[slice, slice] | None:
    """The smallest rectangle (rows, columns) holding every texel where two textures of
    the same shape differ ((H, W, 3) uint8 each, row 0 at v = 1); None when none does."""
    differ = np.any(old != new, axis=2)
    rows = np.flatnonzero(differ.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(differ.any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def encode_patch(patch: TexturePatch) -> bytes:
    """The patch's bytes (format 2, the module docstring).

    Raises ``PatchError`` when they would exceed ``MAX_UPDATE_BYTES``.
    """
    data = msgpack.packb({
        "format": FORMAT, "base_sha256": patch.base_sha256, "serial": patch.serial,
        "scale": patch.scale,
        "tiles": [{"row": t.row, "col": t.col, "shape": list(t.diff.shape[:2]),
                   "png": png_bytes(t.diff)} for t in patch.tiles]}, use_bin_type=True)
    if len(data) > MAX_UPDATE_BYTES:
        raise PatchError(f"patch {patch.serial}: {len(data)} bytes, at most {MAX_UPDATE_BYTES}")
    return data


def is_patch(fields: dict[str, Any]) -> bool:
    """Whether an update's unpacked msgpack map is a patch's (its ``format``)."""
    return fields.get("format") == FORMAT


def decode_patch(fields: dict[str, Any], model: PersonModel, base_sha256: str) -> TexturePatch:
    """The patch of an update's unpacked msgpack map, checked against ``model`` (the version
    it applies to) without changing it.

    Raises:
        PatchError: a key, type, size or place is wrong, or a PNG is malformed (named).
    """
    shell = patch_shell(fields)
    if shell.base_sha256 != base_sha256:
        raise PatchError("base_sha256: made for another model file")
    height, width = model.texture.shape[:2]
    tiles = []
    for n, entry in enumerate(fields["tiles"]):
        h, w = entry["shape"]
        s = shell.scale
        if entry["row"] + s * h > height or entry["col"] + s * w > width:
            raise PatchError(f"tiles[{n}]: texels [{entry['row']}:{entry['row'] + s * h}, "
                             f"{entry['col']}:{entry['col'] + s * w}] lie outside the "
                             f"{height} x {width} texture")
        try:
            diff = decode_png(entry["png"], (h, w, 3))
        except ValueError as e:
            raise PatchError(f"tiles[{n}]: png: {e}") from e
        tiles.append(Tile(entry["row"], entry["col"], diff))
    return dataclasses.replace(shell, tiles=tuple(tiles))


def patch_shell(fields: dict[str, Any]) -> TexturePatch:
    """The patch of an update's unpacked map with every field but the PNGs checked (its
    tiles' differences are stand-ins of their declared shapes).

    Raises:
        PatchError: a key, type or size is wrong (named).
    """
    if set(fields) != _KEYS:
        raise PatchError(f"expected a map with the keys {sorted(_KEYS)}")
    tiles = fields["tiles"]
    if not isinstance(tiles, list) or not 1 <= len(tiles) <= MAX_TILES:
        raise PatchError(f"tiles: expected an array of 1 to {MAX_TILES} tiles")
    stand_ins = []
    for n, entry in enumerate(tiles):
        if not isinstance(entry, dict) or set(entry) != _TILE_KEYS:
            raise PatchError(f"tiles[{n}]: expected a map with the keys {sorted(_TILE_KEYS)}")
        shape = entry["shape"]
        if not (isinstance(shape, list) and len(shape) == 2):
            raise PatchError(f"tiles[{n}].shape: expected [h, w]")
        for axis, size in enumerate(shape):
            check_integer(size, f"tiles[{n}].shape[{axis}]", 1, MAX_TILE_SIDE)
        if not isinstance(entry["png"], bytes):
            raise PatchError(f"tiles[{n}].png: expected bin")
        stand_ins.append(Tile(entry["row"], entry["col"], np.zeros((*shape, 3), np.uint8)))
    try:
        return TexturePatch(fields["base_sha256"], fields["serial"], fields["scale"],
                            tuple(stand_ins))
    except PatchError:
        raise
    except ModelError as e:
        raise PatchError(str(e).removeprefix("patch: ")) from e
