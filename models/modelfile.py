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
``model.json``                  UTF-8 JSON       the manifest (``models.manifest``), at most 1 MiB
``arrays/vertices.npy``         float32 (N, 3)   vertex positions, model space, mm
``arrays/triangles.npy``        int32 (M, 3)     vertex indices, counter-clockwise from outside
``arrays/uv.npy``               float32 (N, 2)   texture coordinates in [0, 1], v up
``arrays/tags.npy``             uint8 (M,)       ``models.mesh.Tag`` of each triangle
``arrays/landmarks.npy``        int32 (68,)      vertex of each iBUG 300-W landmark, 0-based
``arrays/phantoms.npy``         int32 (13,)      vertices of the phantom points
``arrays/descriptors.npy``      float32 (D,      optional: the person's face descriptors
                                128)             (``sender.identity``), 1 <= D <= 16, finite
``textures/neutral.png``        uint8 (H, W, 3)  neutral texture, 8-bit RGB PNG; row 0 is v = 1
``textures/confidence.png``     uint8 (H, W)     optional: how well the enrollment saw each
                                                 texel of the neutral texture, 0 (never) ..
                                                 255 (``sender.enroll.confidence``), 8-bit
                                                 grey PNG the texture's size
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

N, M >= 1; 1 <= H, W, h, w <= 4096; 1 <= k <= 64. ``arrays/descriptors.npy`` is optional:
present when the model was built with its person's descriptors (whom the sender follows:
``sender.identity``), absent in models built before them, which still load
(``PersonModel.descriptors`` None). ``textures/confidence.png`` is optional likewise (its
shape must be the texture's; ``PersonModel.confidence`` None without it). Neither raises
``format_version`` from 4: a reader that predates one refuses such a model by name ("not a
member of a facewire model").
``.npy`` members are numpy format 1.0 or 2.0, little-endian, never object arrays (read
with ``allow_pickle=False``, and refused from their header before that). The manifest
``model.json`` (its keys, the records it holds, the versions and what each added) and the
schema table every member is checked against are
``models.manifest``'s; the field checks and limits the model types share with it are
``models.fields``.

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
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
import zipfile
from dataclasses import dataclass
from typing import Any

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
from facewire.models.fields import (
    DESCRIPTOR_SIZE,
    HEX64,
    MAX_AREAS,
    MAX_DESCRIPTORS,
    MAX_IMAGE_SIDE,
    MAX_LAYERS,
    MAX_REGIONS,
    PATCH_REGION,
    TEMPLATE_SIZE,
    ModelError,
    ModelFileError,
    check_coverage,
    check_integer,
    check_ndarray,
    check_number,
    check_rect,
    check_region_name,
    type_name,
)
from facewire.models.geometry import Intrinsics
from facewire.models.infra.atomic import write_atomically
from facewire.models.manifest import (
    CONFIDENCE_MEMBER,
    DESCRIPTORS_MEMBER,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST_MEMBER,
    MESH_FIELDS,
    TEXTURE_MEMBER,
    Learned,
    Manifest,
    ModelInfo,
    RegionFrames,
    SelfCheck,
    Spec,
    area_folders,
    check_region_frames,
    expected_members,
    member_spec,
    parse_manifest,
)
from facewire.models.mesh import Mesh, MeshError

MAX_FILE_BYTES = 256 * 1024**2
MAX_TOTAL_BYTES = 256 * 1024**2
MAX_DECODED_BYTES = 256 * 1024**2
MAX_MEMBERS = 4096
MAX_RATIO = 100
RATIO_FLOOR = 1024**2


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
        object.__setattr__(self, "uv_rect", check_rect(self.uv_rect, "uv_rect"))
        check_ndarray(self.layers, "layers", np.uint8, 4)
        k, h, w, c = self.layers.shape
        if not 1 <= k <= MAX_LAYERS:
            raise ModelError(f"layers: {k} layers, expected 1 to {MAX_LAYERS}")
        if c != 3 or not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
            raise ModelError(f"layers: expected shape (k, h, w, 3) with h, w in "
                             f"[1, {MAX_IMAGE_SIDE}], got {self.layers.shape}")
        check_ndarray(self.mask, "mask", np.uint8, 2)
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
        check_region_name(self.name, "region")
        field = f"region {self.name!r}"
        try:
            main = Area(self.uv_rect, self.layers, self.mask)
        except ModelError as e:
            raise ModelError(f"{field}: {e}") from e
        inner = check_rect(self.template_rect, f"{field}: template_rect")
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
        check_ndarray(self.templates, f"{field}: templates", np.float32, 3)
        if self.templates.shape != (k, TEMPLATE_SIZE, TEMPLATE_SIZE):
            raise ModelError(f"{field}: templates: expected shape "
                             f"{(k, TEMPLATE_SIZE, TEMPLATE_SIZE)}, got {self.templates.shape}")
        if not np.isfinite(self.templates).all():
            raise ModelError(f"{field}: templates: contains NaN or infinity")
        opacity = (1.0,) * k if len(self.opacity) == 0 else self.opacity
        if not isinstance(opacity, (tuple, list)) or len(opacity) != k:
            raise ModelError(f"{field}: opacity: expected {k} numbers, one per layer")
        opacity = tuple(check_number(a, f"{field}: opacity[{j}]") for j, a in enumerate(opacity))
        if not all(0.0 <= a <= 1.0 for a in opacity):
            raise ModelError(f"{field}: opacity: expected numbers in [0, 1], got {opacity}")
        object.__setattr__(self, "opacity", opacity)
        rest = check_number(self.rest, f"{field}: rest")
        if not 0.0 <= rest <= k - 1:
            raise ModelError(f"{field}: rest: expected a number in [0, {k - 1}], got {rest}")
        object.__setattr__(self, "rest", rest)

    def parts(self) -> tuple[Area, ...]:
        """Every area the region's layers cover: its main area, then the further ones."""
        return (Area(self.uv_rect, self.layers, self.mask), *self.areas)


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
        region_frames: {region: how its layers spent the enrollment frames}
            (``sender.enroll.usage``), or None when not recorded (older models, models
            without regions). The manifest's optional ``region_frames`` key; every name is
            one of ``regions``.
        learned: the model updates of a session this model includes (``models.learned``),
            or None. The manifest's optional ``learned`` key; every region it names is one
            of ``regions``.
        descriptors: (D, 128) float32, finite, 1 <= D <= 16: the person's face descriptors
            (``sender.identity``: whom the sender follows), or None (older models). The
            optional member ``arrays/descriptors.npy``.
        confidence: (H, W) uint8, the texture's shape: how well the enrollment saw each
            texel (``sender.enroll.confidence``; 255 = fully), or None (older models). The
            optional member ``textures/confidence.png``.
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
    region_frames: dict[str, RegionFrames] | None = None
    learned: Learned | None = None
    descriptors: np.ndarray | None = None
    confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name, kind in (("mesh", Mesh), ("camera", Intrinsics), ("info", ModelInfo)):
            if not isinstance(getattr(self, name), kind):
                raise ModelError(f"{name}: expected a {kind.__name__}, "
                                 f"got {type_name(getattr(self, name))}")
        check_ndarray(self.texture, "texture", np.uint8, 3)
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
                                      and HEX64.fullmatch(self.sha256))):
            raise ModelError("sha256: expected '' or 64 lowercase hex digits")
        check_integer(self.file_bytes, "file_bytes", 0, MAX_FILE_BYTES)
        if self.coverage is not None:
            check_coverage(self.coverage)
        if self.self_check is not None and not isinstance(self.self_check, SelfCheck):
            raise ModelError(f"self_check: expected a SelfCheck or None, got "
                             f"{type_name(self.self_check)}")
        if self.region_frames is not None:
            frames = check_region_frames(self.region_frames)
            unknown = sorted(frames.keys() - set(names))
            if unknown:
                raise ModelError(f"region_frames.{unknown[0]}: not a region of the model")
            object.__setattr__(self, "region_frames", frames)
        if self.learned is not None:
            if not isinstance(self.learned, Learned):
                raise ModelError(f"learned: expected a Learned or None, got "
                                 f"{type_name(self.learned)}")
            strange = [u.region for u in self.learned.updates
                       if u.region not in names and u.region != PATCH_REGION]
            if strange:
                raise ModelError(f"learned.updates: {strange[0]!r} is not a region of the model")
        if self.descriptors is not None:
            check_descriptors(self.descriptors)
        if self.confidence is not None:
            check_confidence(self.confidence, (h, w))


def check_confidence(confidence: object, shape: tuple[int, int]) -> None:
    """A model's ``confidence``: (H, W) uint8, the texture's (H, W); ``ModelError`` names
    the field."""
    field = f"confidence ({CONFIDENCE_MEMBER})"
    check_ndarray(confidence, field, np.uint8, 2)
    assert isinstance(confidence, np.ndarray)
    if confidence.shape != shape:
        raise ModelError(f"{field}: expected the texture's shape {shape}, got "
                         f"{confidence.shape}")


def check_descriptors(descriptors: object) -> None:
    """A model's ``descriptors``: (D, 128) float32, 1 <= D <= 16, finite; ``ModelError``
    names the field."""
    field = f"descriptors ({DESCRIPTORS_MEMBER})"
    check_ndarray(descriptors, field, np.float32, 2)
    assert isinstance(descriptors, np.ndarray)
    d, size = descriptors.shape
    if size != DESCRIPTOR_SIZE or not 1 <= d <= MAX_DESCRIPTORS:
        raise ModelError(f"{field}: expected shape (D, {DESCRIPTOR_SIZE}) with D in "
                         f"[1, {MAX_DESCRIPTORS}], got {descriptors.shape}")
    if not np.isfinite(descriptors).all():
        raise ModelError(f"{field}: contains NaN or infinity")


def save_model(model: PersonModel, path: str | os.PathLike[str]) -> str:
    """Write ``model`` to ``path`` atomically; return the file's sha256 (the model id).

    The bytes go to a temporary file in the same folder, are flushed to disk, and only then
    renamed over ``path``: a crash leaves either the old file or the new one, never half of
    one. The file is created readable by its owner only (0600: it holds a person's face).
    Raises ``ModelFileError`` naming the file if it cannot be written.
    """
    if not isinstance(model, PersonModel):
        raise TypeError(f"save_model: expected a PersonModel, got {type_name(model)}")
    data = _encode(model)
    try:
        write_atomically(path, data, 0o600)
    except OSError as e:
        raise ModelFileError(f"{os.fspath(path)}: cannot write ({e})") from e
    return hashlib.sha256(data).hexdigest()


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
            manifest = parse_manifest(raw)
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
            main, *further = area_folders(r)
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
                           manifest.coverage, manifest.self_check, manifest.region_frames,
                           manifest.learned, arrays.get(DESCRIPTORS_MEMBER),
                           arrays.get(CONFIDENCE_MEMBER))
    except ModelError as e:
        raise ModelFileError(f"{where}: {e}") from e


def model_summary(model: PersonModel) -> dict[str, Any]:
    """The ``model build/info --json`` keys: vertices, triangles, regions, layers,
    descriptors (how many the model stores, 0 for none), bytes, sha256.

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
        "descriptors": 0 if model.descriptors is None else int(model.descriptors.shape[0]),
        "bytes": size,
        "sha256": digest,
    }


# ---- the zip's rules ---------------------------------------------------------------------

def _limit(name: str) -> int | None:
    spec = member_spec(name)
    return None if spec is None else spec.limit


_RULES = ZipRules("a facewire model", _limit, MAX_MEMBERS, MAX_TOTAL_BYTES, MAX_RATIO,
                  RATIO_FLOOR)


# ---- writing -----------------------------------------------------------------------------

def png_members(model: PersonModel) -> dict[str, tuple[np.ndarray, bytes]]:
    """The model's images as its file holds them: {member name: (array, PNG bytes)}.

    The neutral texture, then each region's areas (main first), each area's layers in order
    and its mask. The bytes are ``png_bytes`` of the arrays, deterministic (module docstring),
    so for a model read from a file written by this module they are that file's members, byte
    for byte; the browser's model (``models.webmodel``) carries them as they are.
    """
    out = {TEXTURE_MEMBER: (model.texture, png_bytes(model.texture))}
    for r in model.regions:
        for n, area in enumerate(r.parts()):
            folder = f"regions/{r.name}" + (f"/area_{n}" if n else "")
            for j, layer in enumerate(area.layers):
                out[f"{folder}/layer_{j:02d}.png"] = (layer, png_bytes(layer))
            out[f"{folder}/mask.png"] = (area.mask, png_bytes(area.mask))
    return out


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
    for name, (array, data) in png_members(model).items():
        put(name, array, data)
    for r in model.regions:
        put(f"regions/{r.name}/templates.npy", r.templates, npy_bytes(r.templates))
    if model.descriptors is not None:
        put(DESCRIPTORS_MEMBER, model.descriptors, npy_bytes(model.descriptors))
    if model.confidence is not None:
        put(CONFIDENCE_MEMBER, model.confidence, png_bytes(model.confidence))
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
    if model.region_frames is not None:
        manifest["region_frames"] = {name: frames.as_dict()
                                     for name, frames in model.region_frames.items()}
    if model.learned is not None:
        manifest["learned"] = model.learned.as_dict()
    members[MANIFEST_MEMBER] = (json.dumps(manifest, sort_keys=True, indent=1, ensure_ascii=True,
                                           allow_nan=False) + "\n").encode("ascii")
    return zip_bytes(members)


# ---- reading -----------------------------------------------------------------------------

def _check_members(manifest: Manifest, entries: dict[str, zipfile.ZipInfo],
                   where: str) -> set[str]:
    """The members the manifest requires: each in the zip and declared, region sizes agreeing."""
    expected = expected_members(manifest.regions, DESCRIPTORS_MEMBER in manifest.members,
                                CONFIDENCE_MEMBER in manifest.members)
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
        spec = member_spec(name)
        assert spec is not None  # parse_manifest refuses a member without one
        decoded += math.prod(shape) * np.dtype(spec.dtype).itemsize
    if decoded > MAX_DECODED_BYTES:
        raise ModelFileError(f"{where}: {MANIFEST_MEMBER}: members: declare arrays of "
                             f"{decoded} bytes in all, more than the {MAX_DECODED_BYTES} a "
                             f"model may decode to (an image bomb?)")
    for region in manifest.regions:
        for folder in area_folders(region):
            size = manifest.members[f"{folder}/mask.png"]
            for j in range(region.layers):
                name = f"{folder}/layer_{j:02d}.png"
                if manifest.members[name][:2] != size:
                    raise ModelFileError(f"{where}: {name}: shape {manifest.members[name]} does "
                                         f"not match its mask {size}")
    return expected


def _decode(raw: bytes, spec: Spec, shape: tuple[int, ...]) -> np.ndarray:
    """One member's array, checked against its declared shape; raises ``ValueError``."""
    if spec.kind == "png":
        return decode_png(raw, shape)
    return decode_npy(raw, np.dtype(spec.dtype), shape)


def _read_array(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, manifest: Manifest,
                where: str) -> np.ndarray:
    """One member read and decoded to its declared array; raises ``ModelFileError``."""
    raw = _member_bytes(archive, entry, where)
    spec = member_spec(entry.filename)
    assert spec is not None  # parse_manifest refuses a member without one
    try:
        return _decode(raw, spec, manifest.members[entry.filename])
    except ValueError as e:
        raise ModelFileError(f"{where}: {entry.filename}: {e}") from e


def _member_bytes(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, where: str) -> bytes:
    try:
        return read_member(archive, entry, where)
    except ValueError as e:
        raise ModelFileError(str(e)) from e


