"""The person model and its file, ``.fwm``: one zip that both hosts read.

A person model holds what the sender and the receiver both need about one person: the fitted
head mesh (``models.mesh.Mesh``), the neutral texture, the enrollment camera
(``models.geometry.Intrinsics``), a little metadata and the texture regions of the
appearance work (their layer stacks, masks and classification templates). The receiver may
fetch a model from the network, so the reader treats every file as hostile: it never
extracts to disk, reads members by exact allow-listed names, bounds every size before it
inflates anything, and validates everything before it returns. Every failure is a
``ModelFileError`` (a ``ValueError``) whose message names the file and the member or field,
e.g. ``alice.fwm: arrays/vertices.npy: expected dtype float32, got float64``.

File layout, format version 1
-----------------------------
A zip archive holding exactly these members (no folders, no others, no duplicates):

==============================  ===============  ==============================================
member                          dtype, shape     content
==============================  ===============  ==============================================
``model.json``                  UTF-8 JSON       the manifest (below), at most 1 MiB
``arrays/vertices.npy``         float32 (N, 3)   vertex positions, model space, mm
``arrays/triangles.npy``        int32 (M, 3)     vertex indices, counter-clockwise from outside
``arrays/uv.npy``               float32 (N, 2)   texture coordinates in [0, 1], v up
``arrays/tags.npy``             uint8 (M,)       ``models.mesh.Tag`` of each triangle
``arrays/landmarks.npy``        int32 (68,)      vertex of each iBUG 300-W landmark, 0-based
``arrays/phantoms.npy``         int32 (13,)      vertices of the phantom points
``textures/neutral.png``        uint8 (H, W, 3)  neutral texture, 8-bit RGB PNG; row 0 is v = 1
``regions/R/layer_JJ.png``      uint8 (h, w, 3)  region R's appearance state JJ (00 .. k-1),
                                                 8-bit RGB PNG covering the region's
                                                 ``uv_rect``; row 0 is its top (v = v1)
``regions/R/mask.png``          uint8 (h, w)     8-bit grey PNG: the layers' alpha over the
                                                 neutral texture (255 = layer, 0 = neutral)
``regions/R/templates.npy``     float32 (k, 16,  region R's classification template of each
                                16)              state, in layer order
``regions/R/area_N/layer_JJ.png`` uint8 (h, w,   region R's state JJ over its further area N
                                3)               (1 .. A), covering ``areas[N - 1]``
``regions/R/area_N/mask.png``   uint8 (h, w)     the alpha of further area N's layers
==============================  ===============  ==============================================

N, M >= 1; 1 <= H, W, h, w <= 4096; 1 <= k <= 64. ``.npy`` members are numpy format 1.0 or
2.0, little-endian, never object arrays (read with ``allow_pickle=False``, and refused from
their header before that). Manifest ``model.json``, every key required and no others::

    {"format": "facewire-model", "format_version": 4,
     "camera":  {"fx", "fy": focal lengths, px; "cx", "cy": principal point, px
                 (image origin top-left); "width", "height": image size, px; within the
                 bounds of ``models.geometry.Intrinsics``},
     "info":    {"name": person, "source_video": enrollment video's name ("" if none),
                 "frames_used": strictly increasing frame indices, "neutral_frame": index,
                 "creator": software that built it, "created": a date given by the caller
                 or "", "source": the frames the model was built from, or null (below)},
     "members": {member name: {"dtype": numpy dtype name, "shape": [int, ...]}},
     "regions": [{"name": R, "uv_rect": [u0, v0, u1, v1], "template_rect": [u0, v0, u1, v1],
                  "layers": k, "opacity": [k numbers in [0, 1]], "rest": Q,
                  "areas": [[u0, v0, u1, v1], ...]}, ...]}

One key is optional: ``"coverage": {state: true or false}``, the expression states the
model's layers show (``sender.enroll.coverage``; at most 32, names as region names), absent
when they were not measured (models built before it). It leaves ``format_version`` at 3: a
reader that predates it refuses such a model by name ("unknown key 'coverage'").
Another is optional in the same way: ``"self_check": {"ssim": number or null, "render_nme":
number or null, "frames": int, "poor": bool, "causes": [text, ...]}``, the build's
self-check (``SelfCheck``; ``bench.selfcheck``): the model rendered at its own enrollment
frames, its mean face SSIM and render NME (percent of the outer-eye distance) over
``frames`` frames, whether that is poor and its likely causes (at most 8, each at most 64
characters), absent when it was not run (``model build --no-self-check``, older models).

``members`` lists every member but ``model.json``, with the dtype and shape its content must
have. ``regions`` is in packet order (the order of the Q values on the wire) and may be
empty; its names match ``[a-z][a-z0-9_]{0,31}``; rects are in UV, 0 <= u0 < u1 <= 1 and
0 <= v0 < v1 <= 1, and ``template_rect`` lies inside ``uv_rect``. ``opacity`` scales the
mask per layer (a layer's alpha is ``opacity[j] * mask``; the eyelids' open state is
transparent so the eyeball shows through it). ``rest`` is the region's Q on the neutral
face (what a receiver shows when the face is at rest or lost), in [0, k - 1]. ``areas`` are
the region's further layer areas (at most ``MAX_AREAS``; the eyelids' lid skin): each has k
layers and a mask of its own size, blended with the region's opacities and Q. The reader
checks each
member against a schema table (member-name pattern, kind, dtype, shape with named
dimensions, size limit) and against its ``members`` entry; the mesh arrays then go through
``Mesh``'s own checks (finiteness, index ranges). A later addition (e.g. per-landmark neutral
data) is a new row of that table and a new manifest key, with ``format_version`` raised: a
reader accepts only the versions it knows, and keeps reading the older ones. Version 1 had
no ``opacity`` and no ``rest`` (read as all ones and 0); nothing ever wrote a version-1
model with regions. Version 2 had no ``areas`` (read as none). Version 3 had no
``info.source`` (read as null: the build range is unknown).

``info.source`` (``SourceRange``) is the frame range the model was built from, so that a
benchmark can refuse to score a model on its own enrollment frames (``bench quality``):
``{"video": file name, "bytes": file size, "sha256": sha256 of the file's bytes (64
lowercase hex), "start": a, "stop": b}``, the frames [a, b) of that file (0 <= a < b; b is
one past the last frame decoded, never open-ended). Two videos are the same video when
their bytes are the same (size and sha256): a renamed copy is the same video, a re-encoded
one is not. null for a model made from no video (a still portrait).

The zip itself must be plain (``models.archive``, the container this module fills: it
ends with its end-of-archive record, no comment, nothing before or after the archive),
members are stored or deflated, never encrypted, and no name is absolute or holds ``..``, a
drive or a NUL (refused as unsafe, never used). Limits: file
256 MiB; uncompressed 64 MiB a member (1 MiB for ``model.json``, landmarks, phantoms and
templates) and 256 MiB in all, checked on the sizes the zip declares before anything is
inflated, and then by reading no more than the declared size (zipfile checks each member's
CRC-32 at its end); a member over 1 MiB may not inflate more than 100:1; 4096 members.
The arrays the members decode to (PNG images too: a flat 4096 x 4096 PNG is a few kB and
48 MiB decoded) may not hold more than 256 MiB in all, checked on the shapes ``model.json``
declares before any member is read (a real model holds about 11 MiB).

Determinism and identity: members are sorted by name, dated 1980-01-01 00:00, ``.npy`` and
JSON deflated at level 6, PNGs stored (already compressed), the JSON written with sorted
keys; there is no wall-clock time anywhere, so the same model always gives the same bytes
with the same numpy, zlib and OpenCV builds. A model's id is the sha256 of its file's bytes
(``model_sha256``); it is the hash of the bytes actually written, so a receiver checks the
file it fetched, never a rebuild.

Size: this module is over 600 lines because it is one concept, the person model as its
file defines it: the model types validate the same fields, with the same limits and field
checks (``_integer``, ``_number``, ``_rect``, ``_array``), that the manifest reader and the
schema table apply to a file, and both raise this module's ``ModelError``. The zip container
under it (bounded reading, ``.npy`` and PNG decoding, reproducible writing) is
``models.archive``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import stat
import zipfile
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from facewire.models.archive import (
    ZipRules,
    decode_npy,
    decode_png,
    npy_bytes,
    open_zip,
    png_bytes,
    read_member,
    zip_bytes,
)
from facewire.models.geometry import Intrinsics
from facewire.models.infra.atomic import write_atomically
from facewire.models.mesh import Mesh, MeshError
from facewire.protocol.errors import FacewireError

FORMAT = "facewire-model"
FORMAT_VERSION = 4
READ_VERSIONS = (1, 2, 3, 4)
MAX_FILE_BYTES = 256 * 1024**2
MAX_TOTAL_BYTES = 256 * 1024**2
MAX_MEMBER_BYTES = 64 * 1024**2
MAX_SMALL_BYTES = 1024**2
MAX_DECODED_BYTES = 256 * 1024**2
MAX_MEMBERS = 4096
MAX_RATIO = 100
RATIO_FLOOR = 1024**2
MAX_IMAGE_SIDE = 4096
MAX_LAYERS = 64
MAX_REGIONS = 32
MAX_AREAS = 4
TEMPLATE_SIZE = 16

MESH_FIELDS = ("vertices", "triangles", "uv", "tags", "landmarks", "phantoms")
TEXTURE_MEMBER = "textures/neutral.png"
MANIFEST_MEMBER = "model.json"
_REGION_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}", re.ASCII)
_HEX64 = re.compile(r"[0-9a-f]{64}", re.ASCII)


class ModelError(FacewireError, ValueError):
    """A person model's content is invalid; the message names the field."""


class ModelFileError(FacewireError, ValueError):
    """A model file cannot be read or written; the message names the file and the field."""


@dataclass(frozen=True)
class SourceRange:
    """The frames of one video a model was built from (module docstring, ``info.source``).

    Attributes:
        video: the video's file name (no folder), 1 to 1024 printable characters.
        bytes: the video file's size, bytes, >= 1.
        sha256: lowercase hex sha256 of the video file's bytes (its identity).
        start: the first frame index used, >= 0.
        stop: one past the last frame index, > ``start``.
    """

    video: str
    bytes: int
    sha256: str
    start: int
    stop: int

    def __post_init__(self) -> None:
        _text(self.video, "info.source.video", 1, 1024)
        object.__setattr__(self, "bytes", _integer(self.bytes, "info.source.bytes", 1, 2**53))
        if not (isinstance(self.sha256, str) and _HEX64.fullmatch(self.sha256)):
            raise ModelError("info.source.sha256: expected 64 lowercase hex digits")
        start = _integer(self.start, "info.source.start", 0, 2**53)
        stop = _integer(self.stop, "info.source.stop", 1, 2**53)
        if stop <= start:
            raise ModelError(f"info.source.stop: {stop} not after start {start}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "stop", stop)

    @classmethod
    def of_file(cls, path: str | os.PathLike[str], start: int, stop: int) -> SourceRange:
        """The range [start, stop) of the video file ``path`` (hashes the file's bytes).

        Raises:
            ModelFileError: the file cannot be read (names it).
            ModelError: a bad range.
        """
        size, digest = file_identity(path)
        return cls(os.path.basename(os.fspath(path)), size, digest, start, stop)

    def same_video(self, path: str | os.PathLike[str]) -> bool:
        """Whether the file ``path`` is this video: the same size and sha256 of its bytes."""
        return file_identity(path) == (self.bytes, self.sha256)

    def overlap(self, start: int, stop: int | None) -> int:
        """How many frame indices of [start, stop) (``stop`` None: to the end of the video)
        also lie in this range."""
        end = self.stop if stop is None else min(stop, self.stop)
        return max(0, end - max(start, self.start))

    def text(self) -> str:
        """``NAME frames A:B``."""
        return f"{self.video} frames {self.start}:{self.stop}"

    def as_dict(self) -> dict[str, Any]:
        """The manifest's ``info.source`` object (also ``model build/info --json``'s
        ``source``): video, bytes, sha256, start, stop."""
        return {"video": self.video, "bytes": self.bytes, "sha256": self.sha256,
                "start": self.start, "stop": self.stop}


@dataclass(frozen=True)
class ModelInfo:
    """Who the model is and how it was made; nothing here depends on the clock.

    Attributes:
        name: the person's name, 1 to 256 printable characters.
        source_video: the enrollment video's file name, "" if none (at most 1024 characters).
        frames_used: strictly increasing, non-negative video frame indices used to build it.
        neutral_frame: the frame index the neutral texture comes from, >= 0.
        creator: the software that built it (e.g. "facewire 0.1.0"), at most 256 characters.
        created: a creation date given by the caller, "" for none (at most 64 characters).
        source: the video frames the model was built from; None when unknown (a model of
            format version 3 or older) or made from no video.
    """

    name: str
    source_video: str = ""
    frames_used: tuple[int, ...] = ()
    neutral_frame: int = 0
    creator: str = ""
    created: str = ""
    source: SourceRange | None = None

    def __post_init__(self) -> None:
        _text(self.name, "info.name", 1, 256)
        _text(self.source_video, "info.source_video", 0, 1024)
        _text(self.creator, "info.creator", 0, 256)
        _text(self.created, "info.created", 0, 64)
        neutral = _integer(self.neutral_frame, "info.neutral_frame", 0, 2**53)
        if not isinstance(self.frames_used, (tuple, list)):
            raise ModelError(f"info.frames_used: expected a list of frame indices, "
                             f"got {_kind(self.frames_used)}")
        frames = tuple(_integer(f, f"info.frames_used[{i}]", 0, 2**53)
                       for i, f in enumerate(self.frames_used))
        for i in range(1, len(frames)):
            if frames[i] <= frames[i - 1]:
                raise ModelError(f"info.frames_used[{i}]: not strictly increasing")
        object.__setattr__(self, "neutral_frame", neutral)
        object.__setattr__(self, "frames_used", frames)
        if self.source is not None and not isinstance(self.source, SourceRange):
            raise ModelError(f"info.source: expected a SourceRange or None, "
                             f"got {_kind(self.source)}")


@dataclass(frozen=True, eq=False)
class Area:
    """A texture area covered by a region's layers: its main one, or a further one.

    Attributes:
        uv_rect: (u0, v0, u1, v1), the texture area the layer images cover, UV, v up.
        layers: (k, h, w, 3) uint8 RGB, one image per state, row 0 at v = v1.
        mask: (h, w) uint8, the layers' alpha over the neutral texture (255 = layer).
    """

    uv_rect: tuple[float, float, float, float]
    layers: np.ndarray
    mask: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "uv_rect", _rect(self.uv_rect, "uv_rect"))
        _array(self.layers, "layers", np.uint8, 4)
        k, h, w, c = self.layers.shape
        if not 1 <= k <= MAX_LAYERS:
            raise ModelError(f"layers: {k} layers, expected 1 to {MAX_LAYERS}")
        if c != 3 or not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
            raise ModelError(f"layers: expected shape (k, h, w, 3) with h, w in "
                             f"[1, {MAX_IMAGE_SIDE}], got {self.layers.shape}")
        _array(self.mask, "mask", np.uint8, 2)
        if self.mask.shape != (h, w):
            raise ModelError(f"mask: expected shape {(h, w)} like the layers, "
                             f"got {self.mask.shape}")


@dataclass(frozen=True, eq=False)
class Region:
    """A texture region's stored appearance data (the appearance work computes it).

    Attributes:
        name: matches ``[a-z][a-z0-9_]{0,31}``; unique within a model.
        uv_rect: (u0, v0, u1, v1), the texture area the layer images cover, UV, v up.
        template_rect: (u0, v0, u1, v1), the area classification templates are taken from,
            inside ``uv_rect``.
        layers: (k, h, w, 3) uint8 RGB, the region's k appearance states in template order
            (the layers of its 3D texture), row 0 at v = v1; 1 <= k <= 64, 1 <= h, w <= 4096.
        mask: (h, w) uint8, the layers' alpha over the neutral texture (255 = layer).
        templates: (k, 16, 16) float32, finite, the classification template of each state.
        opacity: k numbers in [0, 1], each layer's alpha scale (``mask`` times it); all ones
            when not given.
        rest: the region's Q on the neutral face, in [0, k - 1].
        areas: further areas its layers cover (at most ``MAX_AREAS``), each with k layers.
    """

    name: str
    uv_rect: tuple[float, float, float, float]
    template_rect: tuple[float, float, float, float]
    layers: np.ndarray
    mask: np.ndarray
    templates: np.ndarray
    opacity: tuple[float, ...] = ()
    rest: float = 0.0
    areas: tuple[Area, ...] = ()

    def __post_init__(self) -> None:
        _region_name(self.name, "region")
        field = f"region {self.name!r}"
        try:
            main = Area(self.uv_rect, self.layers, self.mask)
        except ModelError as e:
            raise ModelError(f"{field}: {e}") from e
        inner = _rect(self.template_rect, f"{field}: template_rect")
        outer = main.uv_rect
        if not (outer[0] <= inner[0] and outer[1] <= inner[1]
                and inner[2] <= outer[2] and inner[3] <= outer[3]):
            raise ModelError(f"{field}: template_rect: not inside uv_rect")
        object.__setattr__(self, "uv_rect", outer)
        object.__setattr__(self, "template_rect", inner)
        k = self.layers.shape[0]
        if not isinstance(self.areas, (tuple, list)) or len(self.areas) > MAX_AREAS \
                or not all(isinstance(a, Area) for a in self.areas):
            raise ModelError(f"{field}: areas: expected at most {MAX_AREAS} Area values")
        for n, area in enumerate(self.areas, 1):
            if area.layers.shape[0] != k:
                raise ModelError(f"{field}: area {n}: {area.layers.shape[0]} layers, the "
                                 f"region has {k}")
        object.__setattr__(self, "areas", tuple(self.areas))
        _array(self.templates, f"{field}: templates", np.float32, 3)
        if self.templates.shape != (k, TEMPLATE_SIZE, TEMPLATE_SIZE):
            raise ModelError(f"{field}: templates: expected shape "
                             f"{(k, TEMPLATE_SIZE, TEMPLATE_SIZE)}, got {self.templates.shape}")
        if not np.isfinite(self.templates).all():
            raise ModelError(f"{field}: templates: contains NaN or infinity")
        opacity = (1.0,) * k if len(self.opacity) == 0 else self.opacity
        if not isinstance(opacity, (tuple, list)) or len(opacity) != k:
            raise ModelError(f"{field}: opacity: expected {k} numbers, one per layer")
        opacity = tuple(_number(a, f"{field}: opacity[{j}]") for j, a in enumerate(opacity))
        if not all(0.0 <= a <= 1.0 for a in opacity):
            raise ModelError(f"{field}: opacity: expected numbers in [0, 1], got {opacity}")
        object.__setattr__(self, "opacity", opacity)
        rest = _number(self.rest, f"{field}: rest")
        if not 0.0 <= rest <= k - 1:
            raise ModelError(f"{field}: rest: expected a number in [0, {k - 1}], got {rest}")
        object.__setattr__(self, "rest", rest)

    def parts(self) -> tuple[Area, ...]:
        """Every area the region's layers cover: its main area, then the further ones."""
        return (Area(self.uv_rect, self.layers, self.mask), *self.areas)


@dataclass(frozen=True)
class SelfCheck:
    """The build's self-check (module docstring, ``self_check``; ``bench.selfcheck``).

    Attributes:
        ssim: mean face SSIM (grey) of the model rendered at its enrollment frames, in
            [-1, 1], or None when no frame was scored.
        render_nme: mean render NME, percent of the outer-eye distance, >= 0, or None.
        frames: frames scored, >= 0.
        poor: whether the scores are poor.
        causes: the likely causes named (at most 8, each 1 to 64 printable characters).
    """

    ssim: float | None
    render_nme: float | None
    frames: int
    poor: bool
    causes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.ssim is not None:
            ssim = _number(self.ssim, "self_check.ssim")
            if not -1.0 <= ssim <= 1.0:
                raise ModelError(f"self_check.ssim: {ssim} outside [-1, 1]")
            object.__setattr__(self, "ssim", ssim)
        if self.render_nme is not None:
            nme = _number(self.render_nme, "self_check.render_nme")
            if nme < 0:
                raise ModelError(f"self_check.render_nme: {nme} is negative")
            object.__setattr__(self, "render_nme", nme)
        object.__setattr__(self, "frames", _integer(self.frames, "self_check.frames", 0, 2**31))
        if not isinstance(self.poor, bool):
            raise ModelError(f"self_check.poor: expected true or false, got {_kind(self.poor)}")
        if not isinstance(self.causes, (tuple, list)) or len(self.causes) > 8:
            raise ModelError(f"self_check.causes: expected at most 8 texts, got "
                             f"{_kind(self.causes)}")
        for k, cause in enumerate(self.causes):
            _text(cause, f"self_check.causes[{k}]", 1, 64)
        object.__setattr__(self, "causes", tuple(self.causes))

    def as_dict(self) -> dict[str, Any]:
        """The manifest's ``self_check`` object."""
        return {"ssim": self.ssim, "render_nme": self.render_nme, "frames": self.frames,
                "poor": self.poor, "causes": list(self.causes)}


@dataclass(frozen=True, eq=False)
class PersonModel:
    """One person's model, as ``save_model`` writes it and ``load_model`` returns it.

    Attributes:
        mesh: the fitted head mesh (model space, mm).
        texture: (H, W, 3) uint8 RGB neutral texture, row 0 at v = 1; 1 <= H, W <= 4096.
        camera: the enrollment camera's intrinsics.
        info: name and provenance.
        regions: texture regions in packet order (may be empty), at most 32.
        sha256: the model id, lowercase hex sha256 of the file it was loaded from; "" for a
            model built in memory (``model_summary`` computes it then).
        file_bytes: size of that file, bytes; 0 for a model built in memory.
        coverage: {state: covered}, the expression states its layers show
            (``sender.enroll.coverage``; at most 32, names as region names), or None when
            not measured (older models). The manifest's optional ``coverage`` key.
        self_check: the build's self-check, or None when it was not run. The manifest's
            optional ``self_check`` key.
    """

    mesh: Mesh
    texture: np.ndarray
    camera: Intrinsics
    info: ModelInfo
    regions: tuple[Region, ...] = ()
    sha256: str = ""
    file_bytes: int = 0
    coverage: dict[str, bool] | None = None
    self_check: SelfCheck | None = None

    def __post_init__(self) -> None:
        for name, kind in (("mesh", Mesh), ("camera", Intrinsics), ("info", ModelInfo)):
            if not isinstance(getattr(self, name), kind):
                raise ModelError(f"{name}: expected a {kind.__name__}, "
                                 f"got {_kind(getattr(self, name))}")
        _array(self.texture, "texture", np.uint8, 3)
        h, w, c = self.texture.shape
        if c != 3 or not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
            raise ModelError(f"texture: expected shape (H, W, 3) with H, W in "
                             f"[1, {MAX_IMAGE_SIDE}], got {self.texture.shape}")
        if not isinstance(self.regions, (tuple, list)) or not all(
                isinstance(r, Region) for r in self.regions):
            raise ModelError("regions: expected a sequence of Region")
        if len(self.regions) > MAX_REGIONS:
            raise ModelError(f"regions: {len(self.regions)} regions, at most {MAX_REGIONS}")
        names = [r.name for r in self.regions]
        if len(set(names)) != len(names):
            raise ModelError("regions: region names are not unique")
        object.__setattr__(self, "regions", tuple(self.regions))
        if not (self.sha256 == "" or (isinstance(self.sha256, str)
                                      and _HEX64.fullmatch(self.sha256))):
            raise ModelError("sha256: expected '' or 64 lowercase hex digits")
        _integer(self.file_bytes, "file_bytes", 0, MAX_FILE_BYTES)
        if self.coverage is not None:
            _coverage(self.coverage)
        if self.self_check is not None and not isinstance(self.self_check, SelfCheck):
            raise ModelError(f"self_check: expected a SelfCheck or None, got "
                             f"{_kind(self.self_check)}")


def save_model(model: PersonModel, path: str | os.PathLike[str]) -> str:
    """Write ``model`` to ``path`` atomically; return the file's sha256 (the model id).

    The bytes go to a temporary file in the same folder, are flushed to disk, and only then
    renamed over ``path``: a crash leaves either the old file or the new one, never half of
    one. Raises ``ModelFileError`` naming the file if it cannot be written.
    """
    if not isinstance(model, PersonModel):
        raise TypeError(f"save_model: expected a PersonModel, got {_kind(model)}")
    data = _encode(model)
    try:
        write_atomically(path, data)
    except OSError as e:
        raise ModelFileError(f"{os.fspath(path)}: cannot write ({e})") from e
    return hashlib.sha256(data).hexdigest()


def file_identity(path: str | os.PathLike[str]) -> tuple[int, str]:
    """A file's size in bytes and the lowercase hex sha256 of its bytes (read in chunks).

    Raises ``ModelFileError`` naming the file if it cannot be read.
    """
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            return size, hashlib.file_digest(f, "sha256").hexdigest()
    except OSError as e:
        raise ModelFileError(f"{os.fspath(path)}: cannot read ({e})") from e


def model_sha256(path: str | os.PathLike[str]) -> str:
    """The model id: lowercase hex sha256 of the file's bytes."""
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError as e:
        raise ModelFileError(f"{os.fspath(path)}: cannot read ({e})") from e


def load_model(path: str | os.PathLike[str]) -> PersonModel:
    """Read and validate a ``.fwm`` file; the result carries its ``sha256`` and ``file_bytes``.

    Raises ``ModelFileError`` naming the file and the member or field on any problem.
    """
    where = os.fspath(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise ModelFileError(f"{where}: not a regular file")
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > MAX_FILE_BYTES:
                raise ModelFileError(f"{where}: {size} bytes, more than the "
                                     f"{MAX_FILE_BYTES} a model may have")
            data = f.read(size + 1)
    except OSError as e:
        raise ModelFileError(f"{where}: cannot read ({e})") from e
    return load_model_bytes(data, where)


def load_model_bytes(data: bytes, where: str = "<model>") -> PersonModel:
    """Validate and decode the bytes of a ``.fwm`` file (e.g. as fetched from the network).

    ``where`` names the source in error messages. Raises ``ModelFileError``.
    """
    if len(data) > MAX_FILE_BYTES:
        raise ModelFileError(f"{where}: more than the {MAX_FILE_BYTES} bytes a model may have")
    try:
        archive, entries = open_zip(data, where, _RULES)
    except ValueError as e:
        raise ModelFileError(str(e)) from e
    with archive:
        if MANIFEST_MEMBER not in entries:
            raise ModelFileError(f"{where}: {MANIFEST_MEMBER}: missing")
        raw = _member_bytes(archive, entries[MANIFEST_MEMBER], where)
        try:
            manifest = _parse_manifest(raw)
        except ModelError as e:
            raise ModelFileError(f"{where}: {MANIFEST_MEMBER}: {e}") from e
        expected = _check_members(manifest, entries, where)
        arrays = {name: _read_array(archive, entries[name], manifest, where)
                  for name in sorted(expected)}
    try:
        mesh = Mesh(**{f: arrays[f"arrays/{f}.npy"] for f in MESH_FIELDS})
    except MeshError as e:
        raise ModelFileError(f"{where}: mesh: {e}") from e
    def layers(folder: str, k: int) -> np.ndarray:
        return np.stack([arrays[f"{folder}/layer_{j:02d}.png"] for j in range(k)])

    try:
        regions = []
        for r in manifest.regions:
            main, *further = _area_folders(r)
            areas = []
            for n, (rect, folder) in enumerate(zip(r.areas, further), 1):
                try:
                    areas.append(Area(rect, layers(folder, r.layers), arrays[f"{folder}/mask.png"]))
                except ModelError as e:
                    raise ModelError(f"region {r.name!r}: area {n}: {e}") from e
            regions.append(Region(r.name, r.uv_rect, r.template_rect, layers(main, r.layers),
                                  arrays[f"{main}/mask.png"], arrays[f"{main}/templates.npy"],
                                  r.opacity, r.rest, tuple(areas)))
        return PersonModel(mesh, arrays[TEXTURE_MEMBER], manifest.camera, manifest.info,
                           tuple(regions), hashlib.sha256(data).hexdigest(), len(data),
                           manifest.coverage, manifest.self_check)
    except ModelError as e:
        raise ModelFileError(f"{where}: {e}") from e


def model_summary(model: PersonModel) -> dict[str, Any]:
    """The ``model build/info --json`` keys: vertices, triangles, regions, layers, bytes, sha256.

    ``bytes`` and ``sha256`` are the loaded file's; for a model built in memory they are those
    of the file ``save_model`` would write.
    """
    if model.sha256:
        digest, size = model.sha256, model.file_bytes
    else:
        data = _encode(model)
        digest, size = hashlib.sha256(data).hexdigest(), len(data)
    return {
        "vertices": int(model.mesh.vertices.shape[0]),
        "triangles": int(model.mesh.triangles.shape[0]),
        "regions": len(model.regions),
        "layers": sum(int(r.layers.shape[0]) for r in model.regions),
        "bytes": size,
        "sha256": digest,
    }


# ---- the schema table -------------------------------------------------------------------

class _Spec(NamedTuple):
    """One kind of member: name pattern, storage, dtype, shape (str = named size), limit."""

    pattern: re.Pattern[str]
    kind: str
    dtype: str
    shape: tuple[int | str, ...]
    limit: int


_R = r"[a-z][a-z0-9_]{0,31}"
_SPECS = (
    _Spec(re.compile(r"model\.json"), "json", "", (), MAX_SMALL_BYTES),
    _Spec(re.compile(r"arrays/vertices\.npy"), "npy", "float32", ("N", 3), MAX_MEMBER_BYTES),
    _Spec(re.compile(r"arrays/triangles\.npy"), "npy", "int32", ("M", 3), MAX_MEMBER_BYTES),
    _Spec(re.compile(r"arrays/uv\.npy"), "npy", "float32", ("N", 2), MAX_MEMBER_BYTES),
    _Spec(re.compile(r"arrays/tags\.npy"), "npy", "uint8", ("M",), MAX_MEMBER_BYTES),
    _Spec(re.compile(r"arrays/landmarks\.npy"), "npy", "int32", (68,), MAX_SMALL_BYTES),
    _Spec(re.compile(r"arrays/phantoms\.npy"), "npy", "int32", (13,), MAX_SMALL_BYTES),
    _Spec(re.compile(r"textures/neutral\.png"), "png", "uint8", ("H", "W", 3), MAX_MEMBER_BYTES),
    _Spec(re.compile(rf"regions/{_R}/(area_[1-9]/)?layer_[0-9]{{2}}\.png", re.ASCII), "png",
          "uint8", ("h", "w", 3), MAX_MEMBER_BYTES),
    _Spec(re.compile(rf"regions/{_R}/(area_[1-9]/)?mask\.png", re.ASCII), "png", "uint8",
          ("h", "w"), MAX_MEMBER_BYTES),
    _Spec(re.compile(rf"regions/{_R}/templates\.npy", re.ASCII), "npy", "float32",
          ("k", TEMPLATE_SIZE, TEMPLATE_SIZE), MAX_SMALL_BYTES),
)


def _spec(name: str) -> _Spec | None:
    return next((s for s in _SPECS if s.pattern.fullmatch(name)), None)


def _limit(name: str) -> int | None:
    spec = _spec(name)
    return None if spec is None else spec.limit


_RULES = ZipRules("a facewire model", _limit, MAX_MEMBERS, MAX_TOTAL_BYTES, MAX_RATIO,
                  RATIO_FLOOR)


def _expected_members(regions: list[_RegionEntry]) -> set[str]:
    names = {f"arrays/{f}.npy" for f in MESH_FIELDS} | {TEXTURE_MEMBER}
    for r in regions:
        for folder in _area_folders(r):
            names |= {f"{folder}/layer_{j:02d}.png" for j in range(r.layers)}
            names.add(f"{folder}/mask.png")
        names.add(f"regions/{r.name}/templates.npy")
    return names


def _area_folders(region: _RegionEntry) -> list[str]:
    """The member folders of a region's areas: its main one, then area_1 .. area_A."""
    return [f"regions/{region.name}"] + [f"regions/{region.name}/area_{n}"
                                         for n in range(1, len(region.areas) + 1)]


# ---- writing -----------------------------------------------------------------------------

def _encode(model: PersonModel) -> bytes:
    """The file's bytes: deterministic for a given model (see the module docstring)."""
    members: dict[str, bytes] = {}
    declared: dict[str, dict[str, Any]] = {}

    def put(name: str, array: np.ndarray, data: bytes) -> None:
        members[name] = data
        declared[name] = {"dtype": array.dtype.name, "shape": list(array.shape)}

    for f in MESH_FIELDS:
        array = getattr(model.mesh, f)
        put(f"arrays/{f}.npy", array, npy_bytes(array))
    put(TEXTURE_MEMBER, model.texture, png_bytes(model.texture))
    for r in model.regions:
        for n, area in enumerate(r.parts()):
            folder = f"regions/{r.name}" + (f"/area_{n}" if n else "")
            for j, layer in enumerate(area.layers):
                put(f"{folder}/layer_{j:02d}.png", layer, png_bytes(layer))
            put(f"{folder}/mask.png", area.mask, png_bytes(area.mask))
        put(f"regions/{r.name}/templates.npy", r.templates, npy_bytes(r.templates))
    c, i = model.camera, model.info
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                   "width": c.width, "height": c.height},
        "info": {"name": i.name, "source_video": i.source_video,
                 "frames_used": list(i.frames_used), "neutral_frame": i.neutral_frame,
                 "creator": i.creator, "created": i.created,
                 "source": None if i.source is None else i.source.as_dict()},
        "members": declared,
        "regions": [{"name": r.name, "uv_rect": list(r.uv_rect),
                     "template_rect": list(r.template_rect), "layers": int(r.layers.shape[0]),
                     "opacity": list(r.opacity), "rest": r.rest,
                     "areas": [list(a.uv_rect) for a in r.areas]}
                    for r in model.regions],
    }
    if model.coverage is not None:
        manifest["coverage"] = dict(model.coverage)
    if model.self_check is not None:
        manifest["self_check"] = model.self_check.as_dict()
    members[MANIFEST_MEMBER] = (json.dumps(manifest, sort_keys=True, indent=1, ensure_ascii=True,
                                           allow_nan=False) + "\n").encode("ascii")
    return zip_bytes(members)


# ---- reading -----------------------------------------------------------------------------

class _RegionEntry(NamedTuple):
    """One ``regions`` entry of the manifest, its values not yet checked by ``Region``."""

    name: str
    uv_rect: Any
    template_rect: Any
    layers: int
    opacity: tuple[Any, ...]
    rest: Any
    areas: list[Any]


class _Manifest(NamedTuple):
    camera: Intrinsics
    info: ModelInfo
    members: dict[str, tuple[int, ...]]  # member name -> declared shape
    regions: list[_RegionEntry]
    coverage: dict[str, bool] | None
    self_check: SelfCheck | None


def _parse_manifest(raw: bytes) -> _Manifest:
    """Decode and type-check ``model.json``; raises ``ModelError`` naming the field."""
    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in pairs]
        if len(set(keys)) != len(keys):
            raise ValueError(f"duplicate key {next(k for k in keys if keys.count(k) > 1)!r}")
        return dict(pairs)

    def no_constant(token: str) -> None:
        raise ValueError(f"{token} is not allowed")

    try:
        doc = json.loads(raw.decode("utf-8"), object_pairs_hook=unique, parse_constant=no_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise ModelError(f"not valid JSON ({e})") from e
    optional = {"coverage", "self_check"} & (doc.keys() if isinstance(doc, dict) else set())
    _keys(doc, "manifest", {"format", "format_version", "camera", "info", "members",
                            "regions"} | optional)
    if doc["format"] != FORMAT:
        raise ModelError(f"format: expected {FORMAT!r}, got {doc['format']!r:.80}")
    version = _integer(doc["format_version"], "format_version", 0, 2**31)
    if version not in READ_VERSIONS:
        raise ModelError(f"format_version: unsupported version {version} "
                         f"(this reader knows {', '.join(map(str, READ_VERSIONS))})")
    fields = _keys(doc["camera"], "camera", {"fx", "fy", "cx", "cy", "width", "height"})
    try:
        camera = Intrinsics(**fields)
    except ValueError as e:
        raise ModelError(f"camera.{e}") from e
    info_keys = {"name", "source_video", "frames_used", "neutral_frame", "creator", "created"}
    info_fields = dict(_keys(doc["info"], "info", info_keys | ({"source"} if version >= 4
                                                                 else set())))
    source = info_fields.pop("source", None)
    if source is not None:
        source = SourceRange(**_keys(source, "info.source",
                                     {"video", "bytes", "sha256", "start", "stop"}))
    info = ModelInfo(**info_fields, source=source)
    members: dict[str, tuple[int, ...]] = {}
    if not isinstance(doc["members"], dict):
        raise ModelError(f"members: expected an object, got {_kind(doc['members'])}")
    for name, entry in doc["members"].items():
        field = f"members[{name!r:.80}]"
        spec = _spec(name)
        if spec is None or spec.kind == "json":
            raise ModelError(f"{field}: not a member of a facewire model")
        _keys(entry, field, {"dtype", "shape"})
        if entry["dtype"] != spec.dtype:
            raise ModelError(f"{name}: expected dtype {spec.dtype}, got {entry['dtype']!r:.40}")
        shape = entry["shape"]
        if not isinstance(shape, list) or len(shape) != len(spec.shape):
            raise ModelError(f"{name}: expected shape {_shape_text(spec.shape)}, "
                             f"got {shape!r:.80}")
        for axis, (size, want) in enumerate(zip(shape, spec.shape)):
            _integer(size, f"{field}.shape[{axis}]", 1, 2**53)
            if isinstance(want, int) and size != want:
                raise ModelError(f"{name}: expected shape {_shape_text(spec.shape)}, "
                                 f"got {tuple(shape)}")
            if spec.kind == "png" and axis < 2 and size > MAX_IMAGE_SIDE:
                raise ModelError(f"{name}: image side {size} exceeds {MAX_IMAGE_SIDE}")
        members[name] = tuple(shape)
    if not isinstance(doc["regions"], list):
        raise ModelError(f"regions: expected a list, got {_kind(doc['regions'])}")
    if len(doc["regions"]) > MAX_REGIONS:
        raise ModelError(f"regions: {len(doc['regions'])} regions, at most {MAX_REGIONS}")
    regions: list[_RegionEntry] = []
    for i, entry in enumerate(doc["regions"]):
        field = f"regions[{i}]"
        keys = {"name", "uv_rect", "template_rect", "layers"}
        keys |= {"opacity", "rest"} if version >= 2 else set()
        _keys(entry, field, keys | {"areas"} if version >= 3 else keys)
        name = _region_name(entry["name"], f"{field}.name")
        if any(name == r[0] for r in regions):
            raise ModelError(f"{field}.name: {name!r} appears twice")
        k = _integer(entry["layers"], f"{field}.layers", 1, MAX_LAYERS)
        opacity = entry.get("opacity", [1.0] * k)
        if not isinstance(opacity, list):
            raise ModelError(f"{field}.opacity: expected a list, got {_kind(opacity)}")
        areas = entry.get("areas", [])
        if not isinstance(areas, list) or len(areas) > MAX_AREAS:
            raise ModelError(f"{field}.areas: expected a list of at most {MAX_AREAS} "
                             f"rectangles, got {_kind(areas)}")
        regions.append(_RegionEntry(name, entry["uv_rect"], entry["template_rect"], k,
                                    tuple(opacity), entry.get("rest", 0.0), areas))
    coverage = _coverage(doc["coverage"]) if "coverage" in optional else None
    check = None
    if "self_check" in optional:
        entry = _keys(doc["self_check"], "self_check",
                      {"ssim", "render_nme", "frames", "poor", "causes"})
        check = SelfCheck(entry["ssim"], entry["render_nme"], entry["frames"], entry["poor"],
                          entry["causes"])
    return _Manifest(camera, info, members, regions, coverage, check)


def _check_members(manifest: _Manifest, entries: dict[str, zipfile.ZipInfo],
                   where: str) -> set[str]:
    """The members the manifest requires: each in the zip and declared, region sizes agreeing."""
    expected = _expected_members(manifest.regions)
    for name in sorted(expected | entries.keys() | manifest.members.keys()):
        if name == MANIFEST_MEMBER:
            continue
        if name not in expected:
            raise ModelFileError(f"{where}: {name}: not a member of this model "
                                 f"(not required by model.json's regions)")
        if name not in entries:
            raise ModelFileError(f"{where}: {name}: missing")
        if name not in manifest.members:
            raise ModelFileError(f"{where}: {name}: not listed in model.json's members")
    decoded = 0
    for name, shape in manifest.members.items():
        spec = _spec(name)
        assert spec is not None  # _parse_manifest refuses a member without one
        decoded += math.prod(shape) * np.dtype(spec.dtype).itemsize
    if decoded > MAX_DECODED_BYTES:
        raise ModelFileError(f"{where}: {MANIFEST_MEMBER}: members: declare arrays of "
                             f"{decoded} bytes in all, more than the {MAX_DECODED_BYTES} a "
                             f"model may decode to (an image bomb?)")
    for region in manifest.regions:
        for folder in _area_folders(region):
            size = manifest.members[f"{folder}/mask.png"]
            for j in range(region.layers):
                name = f"{folder}/layer_{j:02d}.png"
                if manifest.members[name][:2] != size:
                    raise ModelFileError(f"{where}: {name}: shape {manifest.members[name]} does "
                                         f"not match its mask {size}")
    return expected


def _decode(raw: bytes, spec: _Spec, shape: tuple[int, ...]) -> np.ndarray:
    """One member's array, checked against its declared shape; raises ``ValueError``."""
    if spec.kind == "png":
        return decode_png(raw, shape)
    return decode_npy(raw, np.dtype(spec.dtype), shape)


def _read_array(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, manifest: _Manifest,
                where: str) -> np.ndarray:
    """One member read and decoded to its declared array; raises ``ModelFileError``."""
    raw = _member_bytes(archive, entry, where)
    spec = _spec(entry.filename)
    assert spec is not None  # _parse_manifest refuses a member without one
    try:
        return _decode(raw, spec, manifest.members[entry.filename])
    except ValueError as e:
        raise ModelFileError(f"{where}: {entry.filename}: {e}") from e


def _member_bytes(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, where: str) -> bytes:
    try:
        return read_member(archive, entry, where)
    except ValueError as e:
        raise ModelFileError(str(e)) from e


# ---- field checks ------------------------------------------------------------------------

def _kind(value: object) -> str:
    return type(value).__name__


def _shape_text(shape: tuple[int | str, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _coverage(value: object) -> dict[str, bool]:
    """The ``coverage`` field: at most ``MAX_REGIONS`` states, names as region names, each
    true or false; raises ``ModelError`` otherwise."""
    if not isinstance(value, dict) or len(value) > MAX_REGIONS:
        raise ModelError(f"coverage: expected an object of at most {MAX_REGIONS} states, "
                         f"got {_kind(value)}")
    for name, covered in value.items():
        if not isinstance(name, str) or not _REGION_NAME.fullmatch(name):
            raise ModelError(f"coverage: bad state name {name!r:.40}")
        if not isinstance(covered, bool):
            raise ModelError(f"coverage[{name!r}]: expected true or false, got {_kind(covered)}")
    return dict(value)


def _keys(value: object, field: str, keys: set[str]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ModelError(f"{field}: expected an object, got {_kind(value)}")
    missing, unknown = sorted(keys - value.keys()), sorted(value.keys() - keys)
    if missing:
        raise ModelError(f"{field}: missing key {missing[0]!r}")
    if unknown:
        raise ModelError(f"{field}: unknown key {unknown[0]!r:.80}")
    return value


def _integer(value: object, field: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ModelError(f"{field}: expected an integer, got {_kind(value)}")
    if not low <= value <= high:
        raise ModelError(f"{field}: {value} outside [{low}, {high}]")
    return int(value)


def _number(value: object, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ModelError(f"{field}: expected a number, got {_kind(value)}")
    number = float(value)
    if not math.isfinite(number):
        raise ModelError(f"{field}: must be finite, got {number}")
    return number


def _text(value: object, field: str, low: int, high: int) -> str:
    if not isinstance(value, str):
        raise ModelError(f"{field}: expected a string, got {_kind(value)}")
    if not low <= len(value) <= high or not value.isprintable():
        raise ModelError(f"{field}: expected {low} to {high} printable characters")
    return value


def _region_name(value: object, field: str) -> str:
    if not isinstance(value, str) or not _REGION_NAME.fullmatch(value):
        raise ModelError(f"{field}: expected a name matching [a-z][a-z0-9_]{{0,31}}, "
                         f"got {value!r:.40}")
    return value


def _rect(value: object, field: str) -> tuple[float, float, float, float]:
    if not isinstance(value, (tuple, list)) or len(value) != 4:
        raise ModelError(f"{field}: expected [u0, v0, u1, v1]")
    u0, v0, u1, v1 = (_number(x, field) for x in value)
    if not (0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1):
        raise ModelError(f"{field}: expected 0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1")
    return (u0, v0, u1, v1)


def _array(value: object, field: str, dtype: type, ndim: int) -> None:
    if not isinstance(value, np.ndarray):
        raise ModelError(f"{field}: expected a numpy array, got {_kind(value)}")
    if value.dtype != dtype:
        raise ModelError(f"{field}: expected dtype {np.dtype(dtype).name}, got {value.dtype}")
    if value.ndim != ndim:
        raise ModelError(f"{field}: expected {ndim} dimensions, got shape {value.shape}")

