"""A plain zip archive of ``.npy`` and PNG members, read under bounds and written reproducibly.

This is the container of a model file (``models.modelfile``, which knows which members a
model has, their dtypes and shapes, and the limits); this module knows zips, ``.npy`` and
PNG, and treats the bytes as hostile.

Reading (``open_zip``, ``read_member``, ``decode_npy``, ``decode_png``). Before zipfile
parses anything, the archive must be plain: it ends with its end-of-archive record (no
comment, nothing before or after it, one disk) and its central directory sits where that
record says. Then every entry, before any is read: a safe name (not absolute, no ``..``, no
drive, no NUL), allowed by the caller's rules (``ZipRules.limit``), not repeated, not
encrypted, stored or deflated, within its uncompressed size limit, no more than
``max_ratio``:1 compressed when over ``ratio_floor`` bytes, and within ``max_total`` bytes
in all. A member is read to no more than its declared size (zipfile checks its CRC-32 at the
end). ``.npy`` members are numpy format 1.0 or 2.0, little-endian, never object arrays
(refused from the header, then read with ``allow_pickle=False``); PNGs are 8-bit RGB or grey;
both must have the caller's declared dtype and shape, checked from the header before the
data is decoded (a flat 4096 x 4096 PNG is a few kB and 48 MiB decoded).

Writing (``zip_bytes``, ``npy_bytes``, ``png_bytes``): members sorted by name, dated
1980-01-01 00:00, PNGs stored (already compressed), the rest deflated at level 6; so the same
members always give the same bytes with the same numpy, zlib and OpenCV builds.

Every failure is a ``ValueError`` whose message names the source (``where``) and the member
(the model file reader raises them as its own ``ModelFileError``).
"""

from __future__ import annotations

import io
import math
import struct
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, RuntimeError,
              EOFError, OSError, ValueError, zlib.error, struct.error, KeyError, IndexError,
              OverflowError)
_NPY_ERRORS = (ValueError, SyntaxError, TypeError, RecursionError, EOFError)
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
_DEFLATE_LEVEL = 6
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR_TYPES = {2: 3, 0: 2}  # PNG colour type -> array rank (RGB, grey)
_EOCD = struct.Struct("<4sHHHHIIH")


@dataclass(frozen=True)
class ZipRules:
    """What an archive may hold.

    Attributes:
        kind: what the archive is, for messages (e.g. "a facewire model").
        limit: a member name's uncompressed size limit in bytes, None for a name not allowed.
        max_members: most entries in the archive.
        max_total: most uncompressed bytes the entries may declare in all.
        max_ratio: highest compression ratio of a member over ``ratio_floor`` bytes.
        ratio_floor: bytes below which any ratio is allowed.
    """

    kind: str
    limit: Callable[[str], int | None]
    max_members: int
    max_total: int
    max_ratio: int
    ratio_floor: int


def open_zip(data: bytes, where: str, rules: ZipRules
             ) -> tuple[zipfile.ZipFile, dict[str, zipfile.ZipInfo]]:
    """The archive in ``data`` and its entries by name, every one checked (module docstring).

    Raises:
        ValueError: the archive breaks a rule; the message names ``where`` and the member.
    """
    _check_layout(data, where, rules)
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
    except ZIP_ERRORS as e:
        raise ValueError(f"{where}: not a readable zip file ({e})") from e
    try:
        return archive, _check_entries(archive, where, rules)
    except ValueError:
        archive.close()
        raise


def read_member(archive: zipfile.ZipFile, entry: zipfile.ZipInfo, where: str) -> bytes:
    """The member's bytes, reading no more than its (already bounded) declared size.

    zipfile verifies the CRC-32 once the declared size has been read.
    """
    out = bytearray()
    try:
        with archive.open(entry) as f:
            while len(out) < entry.file_size:
                chunk = f.read(min(1 << 20, entry.file_size - len(out)))
                if not chunk:
                    break
                out += chunk
    except ZIP_ERRORS as e:
        raise ValueError(f"{where}: {entry.filename}: corrupt ({e})") from e
    if len(out) != entry.file_size:
        raise ValueError(f"{where}: {entry.filename}: truncated ({len(out)} of "
                         f"{entry.file_size} bytes)")
    return bytes(out)


def decode_npy(raw: bytes, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """An ``.npy`` member's array of ``dtype`` and ``shape``; the header is checked first.

    Raises:
        ValueError: object arrays, another dtype, shape or size, or a malformed file.
    """
    f = io.BytesIO(raw)
    try:
        version = np.lib.format.read_magic(f)
    except _NPY_ERRORS as e:
        raise ValueError(f"not a valid .npy array ({e})") from e
    read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                   (2, 0): np.lib.format.read_array_header_2_0}.get(version)
    if read_header is None:
        raise ValueError(f"npy format version {version} not supported (1.0 or 2.0)")
    try:
        header = read_header(f)
    except _NPY_ERRORS as e:
        raise ValueError(f"not a valid .npy array ({e})") from e
    got_shape, _, got_dtype = header
    if got_dtype.hasobject:
        raise ValueError("object arrays (pickle) are not allowed")
    want = dtype.newbyteorder("<")
    if got_dtype != want:
        shown = got_dtype.name if got_dtype.isnative else got_dtype.str
        raise ValueError(f"expected dtype {dtype.name}, got {shown}")
    if tuple(got_shape) != shape:
        raise ValueError(f"expected shape {shape} (as declared), got {tuple(got_shape)}")
    size = math.prod(shape) * want.itemsize
    if len(raw) - f.tell() != size:
        raise ValueError(f"array data is {len(raw) - f.tell()} bytes, expected {size}")
    try:
        array = np.load(io.BytesIO(raw), allow_pickle=False)
    except (ValueError, EOFError, OSError) as e:
        raise ValueError(f"not a valid .npy array ({e})") from e
    return np.ascontiguousarray(array, dtype=dtype)


def decode_png(raw: bytes, shape: tuple[int, ...]) -> np.ndarray:
    """A PNG member as (h, w, 3) RGB or (h, w) grey uint8 of ``shape``; header checked first.

    Raises:
        ValueError: not an 8-bit PNG of that kind and size, or it does not decode.
    """
    if len(raw) < 33 or raw[:8] != _PNG_SIGNATURE or raw[8:16] != b"\x00\x00\x00\x0dIHDR":
        raise ValueError("not a PNG image")
    width, height = struct.unpack(">II", raw[16:24])
    depth, colour = raw[24], raw[25]
    if depth != 8 or _PNG_COLOUR_TYPES.get(colour) != len(shape):
        want = "RGB" if len(shape) == 3 else "grey"
        raise ValueError(f"expected an 8-bit {want} PNG, got bit depth {depth}, "
                         f"colour type {colour}")
    if (height, width) != shape[:2]:
        raise ValueError(f"expected a {shape[1]}x{shape[0]} image (as declared), "
                         f"got {width}x{height}")
    try:
        image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise ValueError(f"PNG does not decode ({e})") from e
    if image is None or image.dtype != np.uint8 or image.shape != shape:
        raise ValueError("PNG does not decode to the declared image")
    return np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)


def zip_bytes(members: dict[str, bytes]) -> bytes:
    """The archive of ``members`` (name -> bytes), reproducibly (module docstring)."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        for name in sorted(members):
            entry = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
            entry.create_system = 3
            entry.external_attr = 0o644 << 16
            entry.compress_type = zipfile.ZIP_STORED if name.endswith(".png") \
                else zipfile.ZIP_DEFLATED
            archive.writestr(entry, members[name], compresslevel=_DEFLATE_LEVEL)
    return out.getvalue()


def npy_bytes(array: np.ndarray) -> bytes:
    """``.npy`` format 1.0 of ``array``, little-endian."""
    out = io.BytesIO()
    little = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    np.lib.format.write_array(out, little, version=(1, 0), allow_pickle=False)
    return out.getvalue()


def png_bytes(image: np.ndarray) -> bytes:
    """8-bit PNG of an (h, w, 3) RGB or (h, w) grey uint8 image."""
    bgr = np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)
    ok, data = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape}")
    return data.tobytes()


def _check_layout(data: bytes, where: str, rules: ZipRules) -> None:
    """Refuse anything but a plain zip ending in its end record, before zipfile parses it."""
    if len(data) < _EOCD.size or data[-_EOCD.size:-_EOCD.size + 4] != b"PK\x05\x06":
        raise ValueError(f"{where}: not {rules.kind} (not a zip file, or truncated, "
                         f"or followed by a comment or other data)")
    _, disk, cd_disk, n_disk, n_total, cd_size, cd_offset, comment = _EOCD.unpack(
        data[-_EOCD.size:])
    if disk or cd_disk or n_disk != n_total or comment:
        raise ValueError(f"{where}: not a plain zip file (multi-part or commented)")
    if n_total > rules.max_members:
        raise ValueError(f"{where}: {n_total} members, at most {rules.max_members}")
    if cd_offset + cd_size != len(data) - _EOCD.size:
        raise ValueError(f"{where}: zip directory is not where the end record says "
                         f"(truncated, prefixed or corrupt file)")


def _check_entries(archive: zipfile.ZipFile, where: str,
                   rules: ZipRules) -> dict[str, zipfile.ZipInfo]:
    """Name, size and compression checks on every entry, before any is read."""
    entries: dict[str, zipfile.ZipInfo] = {}
    total = 0
    for entry in archive.infolist():
        name = entry.filename
        parts = entry.orig_filename.replace("\\", "/").split("/")
        if (entry.orig_filename != name or name.startswith("/") or ":" in name
                or ".." in parts):
            raise ValueError(f"{where}: zip member {entry.orig_filename!r}: unsafe name "
                             f"(absolute, '..', drive or NUL); refused")
        limit = rules.limit(name)
        if limit is None:
            raise ValueError(f"{where}: zip member {name!r}: not a member of {rules.kind}; "
                             f"refused")
        if name in entries:
            raise ValueError(f"{where}: {name}: appears twice in the zip")
        if entry.flag_bits & 0x1:
            raise ValueError(f"{where}: {name}: encrypted members are not allowed")
        if entry.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise ValueError(f"{where}: {name}: compression method {entry.compress_type} "
                             f"not allowed (stored or deflated only)")
        if entry.file_size > limit:
            raise ValueError(f"{where}: {name}: declares {entry.file_size} bytes "
                             f"uncompressed, limit {limit}")
        if entry.file_size > rules.ratio_floor \
                and entry.file_size > rules.max_ratio * entry.compress_size:
            raise ValueError(f"{where}: {name}: compression ratio "
                             f"{entry.file_size / max(entry.compress_size, 1):.0f}:1 "
                             f"exceeds {rules.max_ratio}:1 (zip bomb?)")
        total += entry.file_size
        if total > rules.max_total:
            raise ValueError(f"{where}: {name}: members declare more than "
                             f"{rules.max_total} bytes uncompressed in all")
        entries[name] = entry
    return entries
