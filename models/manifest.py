"""The ``.fwm`` file's manifest, ``model.json``: its keys, the records it holds, its versions.

``models.modelfile`` reads a model file through this module: the manifest is decoded and
type-checked here (``parse_manifest``) before any other member is read, and the schema
table of the members it declares (``SPECS``) is defined here, so that the sizes the file
declares can be bounded before anything is inflated. The manifest's records of how a model
was made (``ModelInfo``, ``SourceRange``, ``SelfCheck``) are its types. ``models.modelfile``
writes the manifest (``_encode``); the field checks and limits both use are
``models.fields``.

Manifest ``model.json``, every key required and no others::

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

A third is optional in the same way: ``"region_frames": {region: {"candidates": int, "used":
[frame, ...], "rejected": {reason: int, ...}}}``, per region how the enrollment frames were
spent (``RegionFrames``; ``sender.enroll.usage``): of the ``candidates`` frames of the build's
range, the frames its layers were taken from (strictly increasing; empty when no frame was
clean for it: its layers then draw the base texture), and per reason (a name as a region's,
at most 16 of them) how many were rejected; the remaining ``candidates - len(used) - sum of
rejected`` were clean but not chosen (never below 0). At most ``MAX_REGIONS`` regions; absent
in models built before it, and for a model without regions.

A fourth is optional in the same way: ``"learned": {"base_sha256": 64 lowercase hex, "log":
file name, "updates": [{"serial": n, "region": name, "position": p, "replaces": r or null},
...]}``, the model updates of one session this model includes (``Learned``;
``models.learned``, ``model build --from-log``): the model file the session started from, the
session's log, and per update, in serial order 1, 2, ... (at most ``MAX_LEARNED_UPDATES``),
the region it taught a state to and where (``models.update.ModelUpdate``). Absent in a model
that no session taught. A model learned from a session whose base had itself learned keeps
only its own session's record; the base's sha256 leads to the one before.

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
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from typing import Any, NamedTuple

from facewire.models.fields import (
    DESCRIPTOR_SIZE,
    HEX64,
    MAX_AREAS,
    MAX_IMAGE_SIDE,
    MAX_LAYERS,
    MAX_REGIONS,
    REGION_NAME,
    TEMPLATE_SIZE,
    ModelError,
    ModelFileError,
    check_coverage,
    check_integer,
    check_keys,
    check_number,
    check_region_name,
    check_text,
    type_name,
)
from facewire.models.geometry import Intrinsics

FORMAT = "facewire-model"
FORMAT_VERSION = 4
READ_VERSIONS = (1, 2, 3, 4)
MAX_MEMBER_BYTES = 64 * 1024**2
MAX_SMALL_BYTES = 1024**2
MAX_REASONS = 16
MAX_LEARNED_UPDATES = 2047  # a session's serials (protocol.packet.MAX_SERIAL)

MESH_FIELDS = ("vertices", "triangles", "uv", "tags", "landmarks", "phantoms")
TEXTURE_MEMBER = "textures/neutral.png"
DESCRIPTORS_MEMBER = "arrays/descriptors.npy"
CONFIDENCE_MEMBER = "textures/confidence.png"
MANIFEST_MEMBER = "model.json"


# ---- the manifest's records --------------------------------------------------------------

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
        check_text(self.video, "info.source.video", 1, 1024)
        object.__setattr__(self, "bytes", check_integer(self.bytes, "info.source.bytes", 1, 2**53))
        if not (isinstance(self.sha256, str) and HEX64.fullmatch(self.sha256)):
            raise ModelError("info.source.sha256: expected 64 lowercase hex digits")
        start = check_integer(self.start, "info.source.start", 0, 2**53)
        stop = check_integer(self.stop, "info.source.stop", 1, 2**53)
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
        check_text(self.name, "info.name", 1, 256)
        check_text(self.source_video, "info.source_video", 0, 1024)
        check_text(self.creator, "info.creator", 0, 256)
        check_text(self.created, "info.created", 0, 64)
        neutral = check_integer(self.neutral_frame, "info.neutral_frame", 0, 2**53)
        if not isinstance(self.frames_used, (tuple, list)):
            raise ModelError(f"info.frames_used: expected a list of frame indices, "
                             f"got {type_name(self.frames_used)}")
        frames = tuple(check_integer(f, f"info.frames_used[{i}]", 0, 2**53)
                       for i, f in enumerate(self.frames_used))
        for i in range(1, len(frames)):
            if frames[i] <= frames[i - 1]:
                raise ModelError(f"info.frames_used[{i}]: not strictly increasing")
        object.__setattr__(self, "neutral_frame", neutral)
        object.__setattr__(self, "frames_used", frames)
        if self.source is not None and not isinstance(self.source, SourceRange):
            raise ModelError(f"info.source: expected a SourceRange or None, "
                             f"got {type_name(self.source)}")



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
            ssim = check_number(self.ssim, "self_check.ssim")
            if not -1.0 <= ssim <= 1.0:
                raise ModelError(f"self_check.ssim: {ssim} outside [-1, 1]")
            object.__setattr__(self, "ssim", ssim)
        if self.render_nme is not None:
            nme = check_number(self.render_nme, "self_check.render_nme")
            if nme < 0:
                raise ModelError(f"self_check.render_nme: {nme} is negative")
            object.__setattr__(self, "render_nme", nme)
        frames = check_integer(self.frames, "self_check.frames", 0, 2**31)
        object.__setattr__(self, "frames", frames)
        if not isinstance(self.poor, bool):
            raise ModelError(f"self_check.poor: expected true or false, got {type_name(self.poor)}")
        if not isinstance(self.causes, (tuple, list)) or len(self.causes) > 8:
            raise ModelError(f"self_check.causes: expected at most 8 texts, got "
                             f"{type_name(self.causes)}")
        for k, cause in enumerate(self.causes):
            check_text(cause, f"self_check.causes[{k}]", 1, 64)
        object.__setattr__(self, "causes", tuple(self.causes))

    def as_dict(self) -> dict[str, Any]:
        """The manifest's ``self_check`` object."""
        return {"ssim": self.ssim, "render_nme": self.render_nme, "frames": self.frames,
                "poor": self.poor, "causes": list(self.causes)}


@dataclass(frozen=True)
class RegionFrames:
    """How a region's layers spent the enrollment frames (module docstring,
    ``region_frames``; ``sender.enroll.usage``).

    Attributes:
        candidates: the frames of the build's range, >= 0.
        used: the video frame indices its layers were taken from, strictly increasing; ()
            when none was clean (its layers draw the base texture).
        rejected: {reason: frames rejected for it}, at most ``MAX_REASONS`` reasons named as
            regions, each count >= 1.

    Checked where it enters a model (``check_region_frames``: ``PersonModel`` and the
    manifest reader), where its region's name is known for the messages.
    """

    candidates: int
    used: tuple[int, ...]
    rejected: dict[str, int]

    def check(self, field: str) -> RegionFrames:
        """The record with its fields validated and normalised; ``ModelError`` names
        ``field``."""
        candidates = check_integer(self.candidates, f"{field}.candidates", 0, 2**31)
        if not isinstance(self.used, (tuple, list)) or len(self.used) > MAX_LAYERS * 2:
            raise ModelError(f"{field}.used: expected a list of at most {MAX_LAYERS * 2} frame "
                             f"indices, got {type_name(self.used)}")
        used = tuple(check_integer(f, f"{field}.used[{i}]", 0, 2**53)
                     for i, f in enumerate(self.used))
        if any(b <= a for a, b in zip(used, used[1:])):
            raise ModelError(f"{field}.used: not strictly increasing")
        if not isinstance(self.rejected, dict) or len(self.rejected) > MAX_REASONS:
            raise ModelError(f"{field}.rejected: expected an object of at most {MAX_REASONS} "
                             f"reasons, got {type_name(self.rejected)}")
        rejected = {}
        for reason, count in self.rejected.items():
            if not isinstance(reason, str) or not REGION_NAME.fullmatch(reason):
                raise ModelError(f"{field}.rejected: bad reason {reason!r:.40}")
            rejected[reason] = check_integer(count, f"{field}.rejected.{reason}", 1, 2**31)
        if len(used) + sum(rejected.values()) > candidates:
            raise ModelError(f"{field}: {len(used)} used and {sum(rejected.values())} rejected "
                             f"of {candidates} candidates")
        return RegionFrames(candidates, used, rejected)

    @property
    def clean(self) -> int:
        """The frames neither used nor rejected: clean, but not chosen."""
        return self.candidates - len(self.used) - sum(self.rejected.values())

    def as_dict(self) -> dict[str, Any]:
        """The manifest's entry (also ``model build/info --json``'s ``region_frames``)."""
        return {"candidates": self.candidates, "used": list(self.used),
                "rejected": dict(self.rejected)}


def check_region_frames(value: object) -> dict[str, RegionFrames]:
    """The ``region_frames`` field, from the manifest (objects) or in memory (records)."""
    if not isinstance(value, dict) or len(value) > MAX_REGIONS:
        raise ModelError(f"region_frames: expected an object of at most {MAX_REGIONS} regions, "
                         f"got {type_name(value)}")
    out = {}
    for name, entry in value.items():
        check_region_name(name, "region_frames")
        field = f"region_frames.{name}"
        if not isinstance(entry, RegionFrames):
            entry = RegionFrames(**check_keys(entry, field, {"candidates", "used", "rejected"}))
        out[name] = entry.check(field)
    return out


class LearnedState(NamedTuple):
    """One update a model includes (``Learned.updates``): its serial, the region it taught a
    state to, that state's index after it, and the index it replaced (None: inserted)."""

    serial: int
    region: str
    position: int
    replaces: int | None


@dataclass(frozen=True)
class Learned:
    """The model updates of one session a model includes (module docstring, ``learned``).

    Attributes:
        base_sha256: the sha256 of the model file the session started from (64 hex).
        log: the session's log file name (no folder), 1 to 1024 printable characters.
        updates: the updates applied, serials 1, 2, ... in order, at least one.
    """

    base_sha256: str
    log: str
    updates: tuple[LearnedState, ...]

    def __post_init__(self) -> None:
        if not (isinstance(self.base_sha256, str) and HEX64.fullmatch(self.base_sha256)):
            raise ModelError("learned.base_sha256: expected 64 lowercase hex digits")
        check_text(self.log, "learned.log", 1, 1024)
        if not isinstance(self.updates, (tuple, list)) \
                or not 1 <= len(self.updates) <= MAX_LEARNED_UPDATES:
            raise ModelError(f"learned.updates: expected 1 to {MAX_LEARNED_UPDATES} updates, "
                             f"got {type_name(self.updates)}")
        states = []
        items: list[object] = list(self.updates)  # from the manifest: objects, not yet records
        for n, item in enumerate(items, 1):
            field = f"learned.updates[{n - 1}]"
            entry = item if isinstance(item, LearnedState) else LearnedState(
                **check_keys(item, field, set(LearnedState._fields)))
            if check_integer(entry.serial, f"{field}.serial", n, n) != n:
                raise ModelError(f"{field}.serial: expected {n}")
            check_region_name(entry.region, f"{field}.region")
            check_integer(entry.position, f"{field}.position", 0, MAX_LAYERS)
            if entry.replaces is not None:
                check_integer(entry.replaces, f"{field}.replaces", 0, MAX_LAYERS)
            states.append(LearnedState(int(entry.serial), entry.region, int(entry.position),
                                       None if entry.replaces is None else int(entry.replaces)))
        object.__setattr__(self, "updates", tuple(states))

    def as_dict(self) -> dict[str, Any]:
        """The manifest's ``learned`` object (also ``model info --json``'s)."""
        return {"base_sha256": self.base_sha256, "log": self.log,
                "updates": [u._asdict() for u in self.updates]}


# ---- the schema table -------------------------------------------------------------------

class Spec(NamedTuple):
    """One kind of member: name pattern, storage, dtype, shape (str = named size), limit."""

    pattern: re.Pattern[str]
    kind: str
    dtype: str
    shape: tuple[int | str, ...]
    limit: int


_R = r"[a-z][a-z0-9_]{0,31}"
SPECS = (
    Spec(re.compile(r"model\.json"), "json", "", (), MAX_SMALL_BYTES),
    Spec(re.compile(r"arrays/vertices\.npy"), "npy", "float32", ("N", 3), MAX_MEMBER_BYTES),
    Spec(re.compile(r"arrays/triangles\.npy"), "npy", "int32", ("M", 3), MAX_MEMBER_BYTES),
    Spec(re.compile(r"arrays/uv\.npy"), "npy", "float32", ("N", 2), MAX_MEMBER_BYTES),
    Spec(re.compile(r"arrays/tags\.npy"), "npy", "uint8", ("M",), MAX_MEMBER_BYTES),
    Spec(re.compile(r"arrays/landmarks\.npy"), "npy", "int32", (68,), MAX_SMALL_BYTES),
    Spec(re.compile(r"arrays/phantoms\.npy"), "npy", "int32", (13,), MAX_SMALL_BYTES),
    Spec(re.compile(r"arrays/descriptors\.npy"), "npy", "float32", ("D", DESCRIPTOR_SIZE),
         MAX_SMALL_BYTES),
    Spec(re.compile(r"textures/neutral\.png"), "png", "uint8", ("H", "W", 3), MAX_MEMBER_BYTES),
    Spec(re.compile(r"textures/confidence\.png"), "png", "uint8", ("H", "W"), MAX_MEMBER_BYTES),
    Spec(re.compile(rf"regions/{_R}/(area_[1-9]/)?layer_[0-9]{{2}}\.png", re.ASCII), "png",
          "uint8", ("h", "w", 3), MAX_MEMBER_BYTES),
    Spec(re.compile(rf"regions/{_R}/(area_[1-9]/)?mask\.png", re.ASCII), "png", "uint8",
          ("h", "w"), MAX_MEMBER_BYTES),
    Spec(re.compile(rf"regions/{_R}/templates\.npy", re.ASCII), "npy", "float32",
          ("k", TEMPLATE_SIZE, TEMPLATE_SIZE), MAX_SMALL_BYTES),
)


def member_spec(name: str) -> Spec | None:
    return next((s for s in SPECS if s.pattern.fullmatch(name)), None)



def expected_members(regions: list[RegionEntry], descriptors: bool = False,
                     confidence: bool = False) -> set[str]:
    """The members a model of these regions holds; ``descriptors``, ``confidence``: with the
    optional ``arrays/descriptors.npy``, ``textures/confidence.png`` (the model file lists
    each in ``members`` when it has it)."""
    names = {f"arrays/{f}.npy" for f in MESH_FIELDS} | {TEXTURE_MEMBER}
    if descriptors:
        names.add(DESCRIPTORS_MEMBER)
    if confidence:
        names.add(CONFIDENCE_MEMBER)
    for r in regions:
        for folder in area_folders(r):
            names |= {f"{folder}/layer_{j:02d}.png" for j in range(r.layers)}
            names.add(f"{folder}/mask.png")
        names.add(f"regions/{r.name}/templates.npy")
    return names


def area_folders(region: RegionEntry) -> list[str]:
    """The member folders of a region's areas: its main one, then area_1 .. area_A."""
    return [f"regions/{region.name}"] + [f"regions/{region.name}/area_{n}"
                                         for n in range(1, len(region.areas) + 1)]


# ---- reading -----------------------------------------------------------------------------

class RegionEntry(NamedTuple):
    """One ``regions`` entry of the manifest, its values not yet checked by ``Region``."""

    name: str
    uv_rect: Any
    template_rect: Any
    layers: int
    opacity: tuple[Any, ...]
    rest: Any
    areas: list[Any]


class Manifest(NamedTuple):
    camera: Intrinsics
    info: ModelInfo
    members: dict[str, tuple[int, ...]]  # member name -> declared shape
    regions: list[RegionEntry]
    coverage: dict[str, bool] | None
    self_check: SelfCheck | None
    region_frames: dict[str, RegionFrames] | None
    learned: Learned | None


def parse_manifest(raw: bytes) -> Manifest:
    """Decode and type-check ``model.json``; raises ``ModelError`` naming the field.

    The fields are checked in the order they are listed here: the keys, ``format``,
    ``format_version``, ``camera``, ``info``, ``members``, ``regions``, then the optional
    ``coverage``, ``self_check``, ``region_frames`` and ``learned``.
    """
    doc = _decode_json(raw)
    optional = {"coverage", "self_check", "region_frames", "learned"} & (
        doc.keys() if isinstance(doc, dict) else set())
    check_keys(doc, "manifest", {"format", "format_version", "camera", "info", "members",
                                 "regions"} | optional)
    version = _version(doc)
    camera = _camera(doc["camera"])
    info = _info(doc["info"], version)
    members = _members(doc["members"])
    regions = _regions(doc["regions"], version)
    coverage = check_coverage(doc["coverage"]) if "coverage" in optional else None
    check = _self_check(doc["self_check"]) if "self_check" in optional else None
    frames = check_region_frames(doc["region_frames"]) if "region_frames" in optional else None
    learned = _learned(doc["learned"]) if "learned" in optional else None
    return Manifest(camera, info, members, regions, coverage, check, frames, learned)


def _decode_json(raw: bytes) -> Any:
    """The manifest's JSON: UTF-8, no duplicate keys, no NaN or infinity."""
    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in pairs]
        if len(set(keys)) != len(keys):
            raise ValueError(f"duplicate key {next(k for k in keys if keys.count(k) > 1)!r}")
        return dict(pairs)

    def no_constant(token: str) -> None:
        raise ValueError(f"{token} is not allowed")

    try:
        return json.loads(raw.decode("utf-8"), object_pairs_hook=unique,
                          parse_constant=no_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise ModelError(f"not valid JSON ({e})") from e


def _version(doc: dict[str, Any]) -> int:
    """``format`` and ``format_version``: this format, a version this reader knows."""
    if doc["format"] != FORMAT:
        raise ModelError(f"format: expected {FORMAT!r}, got {doc['format']!r:.80}")
    version = check_integer(doc["format_version"], "format_version", 0, 2**31)
    if version not in READ_VERSIONS:
        raise ModelError(f"format_version: unsupported version {version} "
                         f"(this reader knows {', '.join(map(str, READ_VERSIONS))})")
    return version


def _camera(value: object) -> Intrinsics:
    """The ``camera`` object: the enrollment camera's intrinsics."""
    fields = check_keys(value, "camera", {"fx", "fy", "cx", "cy", "width", "height"})
    try:
        return Intrinsics(**fields)
    except ValueError as e:
        raise ModelError(f"camera.{e}") from e


def _info(value: object, version: int) -> ModelInfo:
    """The ``info`` object; ``info.source`` from version 4 on (null or a ``SourceRange``)."""
    info_keys = {"name", "source_video", "frames_used", "neutral_frame", "creator", "created"}
    info_fields = dict(check_keys(value, "info", info_keys | ({"source"} if version >= 4
                                                              else set())))
    source = info_fields.pop("source", None)
    if source is not None:
        source = SourceRange(**check_keys(source, "info.source",
                                          {"video", "bytes", "sha256", "start", "stop"}))
    return ModelInfo(**info_fields, source=source)


def _members(value: object) -> dict[str, tuple[int, ...]]:
    """The ``members`` object: each a member of the schema table, its dtype and shape."""
    members: dict[str, tuple[int, ...]] = {}
    if not isinstance(value, dict):
        raise ModelError(f"members: expected an object, got {type_name(value)}")
    for name, entry in value.items():
        field = f"members[{name!r:.80}]"
        spec = member_spec(name)
        if spec is None or spec.kind == "json":
            raise ModelError(f"{field}: not a member of a facewire model")
        check_keys(entry, field, {"dtype", "shape"})
        if entry["dtype"] != spec.dtype:
            raise ModelError(f"{name}: expected dtype {spec.dtype}, got {entry['dtype']!r:.40}")
        shape = entry["shape"]
        if not isinstance(shape, list) or len(shape) != len(spec.shape):
            raise ModelError(f"{name}: expected shape {_shape_text(spec.shape)}, "
                             f"got {shape!r:.80}")
        for axis, (size, want) in enumerate(zip(shape, spec.shape)):
            check_integer(size, f"{field}.shape[{axis}]", 1, 2**53)
            if isinstance(want, int) and size != want:
                raise ModelError(f"{name}: expected shape {_shape_text(spec.shape)}, "
                                 f"got {tuple(shape)}")
            if spec.kind == "png" and axis < 2 and size > MAX_IMAGE_SIDE:
                raise ModelError(f"{name}: image side {size} exceeds {MAX_IMAGE_SIDE}")
        members[name] = tuple(shape)
    return members


def _regions(value: object, version: int) -> list[RegionEntry]:
    """The ``regions`` list: version 1 has no ``opacity`` and ``rest``, 2 no ``areas``."""
    if not isinstance(value, list):
        raise ModelError(f"regions: expected a list, got {type_name(value)}")
    if len(value) > MAX_REGIONS:
        raise ModelError(f"regions: {len(value)} regions, at most {MAX_REGIONS}")
    regions: list[RegionEntry] = []
    for i, entry in enumerate(value):
        field = f"regions[{i}]"
        keys = {"name", "uv_rect", "template_rect", "layers"}
        keys |= {"opacity", "rest"} if version >= 2 else set()
        check_keys(entry, field, keys | {"areas"} if version >= 3 else keys)
        name = check_region_name(entry["name"], f"{field}.name")
        if any(name == r[0] for r in regions):
            raise ModelError(f"{field}.name: {name!r} appears twice")
        k = check_integer(entry["layers"], f"{field}.layers", 1, MAX_LAYERS)
        opacity = entry.get("opacity", [1.0] * k)
        if not isinstance(opacity, list):
            raise ModelError(f"{field}.opacity: expected a list, got {type_name(opacity)}")
        areas = entry.get("areas", [])
        if not isinstance(areas, list) or len(areas) > MAX_AREAS:
            raise ModelError(f"{field}.areas: expected a list of at most {MAX_AREAS} "
                             f"rectangles, got {type_name(areas)}")
        regions.append(RegionEntry(name, entry["uv_rect"], entry["template_rect"], k,
                                   tuple(opacity), entry.get("rest", 0.0), areas))
    return regions


def _self_check(value: object) -> SelfCheck:
    """The optional ``self_check`` object."""
    entry = check_keys(value, "self_check", {"ssim", "render_nme", "frames", "poor", "causes"})
    return SelfCheck(entry["ssim"], entry["render_nme"], entry["frames"], entry["poor"],
                     entry["causes"])


def _learned(value: object) -> Learned:
    """The optional ``learned`` object."""
    entry = check_keys(value, "learned", {"base_sha256", "log", "updates"})
    return Learned(entry["base_sha256"], entry["log"], entry["updates"])


def _shape_text(shape: tuple[int | str, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
