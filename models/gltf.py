"""glTF 2.0 binary (.glb) meshes: read a textured triangle mesh, write one.

Container (glTF 2.0 spec, section "GLB File Format Specification"), all little-endian:

    header   magic b"glTF" | version uint32 = 2 | length uint32 = total file bytes
    chunk 0  length uint32 | type b"JSON" | UTF-8 JSON, padded with spaces to 4 bytes
    chunk 1  length uint32 | type b"BIN\\0" | binary buffer 0, padded with zeros to 4 bytes

The JSON describes meshes as primitives whose attributes (POSITION, NORMAL, TEXCOORD_0) and
indices are *accessors*: ``count`` elements of a ``type`` (SCALAR, VEC2, VEC3, ...) and a
``componentType`` (5121 uint8, 5123 uint16, 5125 uint32, 5126 float32, ...), read from a
*bufferView* (a byte range of a buffer, optionally with a ``byteStride`` between elements)
at the accessor's ``byteOffset``. Element ``i`` of an accessor starts at byte
``view.byteOffset + accessor.byteOffset + i * stride`` of the buffer.

Scene graph: each node carries a local transform, either a column-major 4x4 ``matrix`` or
``translation``, ``rotation`` (unit quaternion x, y, z, w) and ``scale`` composed as T R S;
a node's world transform is its parents' product times its own. Positions map by the world
matrix M, normals by the inverse transpose of its 3x3 part (then renormalised), and a
mirroring transform (det < 0) flips triangle winding so triangles stay counter-clockwise.

Units and conventions. glTF lengths are metres; facewire's are millimetres, so the writer
multiplies by 0.001 and the reader by ``mm_per_unit`` (1000 by default, as the spec says).
glTF puts the UV origin at the image's top-left with v down (texel row = v * H); facewire's
v is up (texel row = (1 - v) * H, ``models.mesh``), so both directions convert v -> 1 - v.
Files that ignore the spec need the caller's help: the shared Lee Perry-Smith scan is about
8.6 units wide (neither metres nor millimetres), and its ``Map-COL.jpg``, which is not
embedded, is stored for v up: with this reader's (spec) v, sample it flipped upside down
(``texture[::-1]``): rendered the spec way it is scrambled (``test_raster`` checks both).

The reader merges every triangle primitive of every mesh instance in the default scene into
one mesh; NORMAL and TEXCOORD_0 are returned only when every primitive has them. The texture
is the first primitive's material's base-colour image when it is embedded in the binary
chunk (external files and data URIs are not read). Not supported (refused with
``GltfError``): external buffers, sparse accessors, non-triangle primitives, and any
``extensionsRequired`` (e.g. Draco, mesh quantisation). Skins and morph targets are ignored.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facewire.models.arrays import check_array
from facewire.protocol.errors import FacewireError

MAX_FILE_BYTES = 512 * 1024 * 1024
MM_PER_M = 1000.0

_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<II")

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16,
               5125: np.uint32, 5126: np.float32}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT, _UINT8, _UINT16, _UINT32 = 5126, 5121, 5123, 5125
_TRIANGLES = 4
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071
_MAX_NODE_DEPTH = 64


class GltfError(FacewireError, ValueError):
    """A .glb file is malformed or uses what this reader does not support; names file and field."""


@dataclass(frozen=True, eq=False)
class GltfMesh:
    """One triangle mesh read from a .glb, in facewire's conventions.

    Attributes:
        positions: (N, 3) float32, scene (world) coordinates in mm (file units * mm_per_unit).
        normals: (N, 3) float32 unit normals in the same frame, or None.
        uv: (N, 2) float32 texture coordinates, v up (texel row = (1 - v) * H), or None.
        triangles: (M, 3) int32 vertex indices, counter-clockwise from outside.
        texture: (H, W, 3) uint8 RGB embedded base-colour image, top row first, or None.
    """

    positions: np.ndarray
    normals: np.ndarray | None
    uv: np.ndarray | None
    triangles: np.ndarray
    texture: np.ndarray | None


# ----------------------------------------------------------------------------------- reading

def read_glb(path: str | os.PathLike, mm_per_unit: float = MM_PER_M) -> GltfMesh:
    """Read the triangle mesh of a binary glTF 2.0 file.

    Args:
        path: the .glb file (at most 512 MiB).
        mm_per_unit: millimetres per file unit; glTF's unit is the metre, hence 1000.

    Returns:
        The merged mesh of the default scene, world transforms applied (see module docstring).

    Raises:
        GltfError: the file is not a valid, supported .glb; the message names file and field.
    """
    path = Path(path)
    if not np.isfinite(mm_per_unit) or mm_per_unit <= 0:
        raise GltfError(f"{path}: mm_per_unit must be a positive number, got {mm_per_unit}")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise GltfError(f"{path}: cannot read ({exc.strerror})") from exc
    if size > MAX_FILE_BYTES:
        raise GltfError(f"{path}: {size} bytes, more than the {MAX_FILE_BYTES}-byte limit")
    data = path.read_bytes()
    doc, binary = _split_chunks(path, data)
    return _Reader(path, doc, binary).mesh(mm_per_unit)


def _split_chunks(path: Path, data: bytes) -> tuple[dict, memoryview | None]:
    """Validate the GLB header and chunks; return the parsed JSON and the BIN chunk."""
    if len(data) < _HEADER.size:
        raise GltfError(f"{path}: header: file is {len(data)} bytes, shorter than 12")
    magic, version, length = _HEADER.unpack_from(data, 0)
    if magic != _MAGIC:
        raise GltfError(f"{path}: header magic: expected b'glTF', got {magic!r}")
    if version != 2:
        raise GltfError(f"{path}: header version: expected 2, got {version}")
    if length > len(data):
        raise GltfError(f"{path}: header length: {length} bytes declared but the file has "
                        f"{len(data)} (truncated)")
    chunks: list[tuple[int, memoryview]] = []
    offset = _HEADER.size
    view = memoryview(data)[:length]
    while offset < length:
        if offset + _CHUNK.size > length:
            raise GltfError(f"{path}: chunk {len(chunks)} header at byte {offset} runs past "
                            f"the end of the file ({length} bytes)")
        chunk_length, chunk_type = _CHUNK.unpack_from(data, offset)
        start = offset + _CHUNK.size
        if start + chunk_length > length:
            raise GltfError(f"{path}: chunk {len(chunks)} length: {chunk_length} bytes from "
                            f"byte {start} run past the end of the file ({length} bytes)")
        chunks.append((chunk_type, view[start:start + chunk_length]))
        offset = start + chunk_length + (-chunk_length) % 4
    if not chunks or chunks[0][0] != _CHUNK_JSON:
        raise GltfError(f"{path}: chunk 0: expected the JSON chunk first")
    try:
        doc = json.loads(bytes(chunks[0][1]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GltfError(f"{path}: JSON chunk: not valid UTF-8 JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise GltfError(f"{path}: JSON chunk: expected an object at the top level")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == _CHUNK_BIN else None
    return doc, binary


class _Reader:
    """Walks one parsed glTF document, validating every index and byte range it follows."""

    def __init__(self, path: Path, doc: dict, binary: memoryview | None) -> None:
        self.path, self.doc, self.binary = path, doc, binary
        version = self._get(doc, "asset", dict, "asset").get("version")
        if not isinstance(version, str) or not version.startswith("2."):
            raise self._error("asset.version", f"expected '2.x', got {version!r}")
        required = doc.get("extensionsRequired", [])
        if required:
            raise self._error("extensionsRequired", f"unsupported extensions {required}")

    def _error(self, field: str, message: str) -> GltfError:
        return GltfError(f"{self.path}: {field}: {message}")

    def _get(self, obj: dict, key: str, kind: type, field: str, default: object = None):
        """obj[key] checked to be of ``kind`` (bool is not an int); default when absent."""
        value = obj.get(key, default)
        if value is None:
            raise self._error(field, "missing")
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise self._error(field, f"expected {kind.__name__}, got {type(value).__name__}")
        return value

    def _item(self, array: str, index: object, field: str) -> dict:
        """doc[array][index], with the index checked."""
        items = self.doc.get(array, [])
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(items):
            raise self._error(field, f"index {index!r} outside {array}[0:{len(items)}]")
        item = items[index]
        if not isinstance(item, dict):
            raise self._error(f"{array}[{index}]", "expected an object")
        return item

    def _view_bytes(self, index: int, field: str) -> tuple[memoryview, int | None]:
        """The bytes of bufferView ``index`` and its byteStride (None when tightly packed)."""
        name = f"bufferViews[{index}]"
        view = self._item("bufferViews", index, field)
        buffer_index = self._get(view, "buffer", int, f"{name}.buffer")
        buffer = self._item("buffers", buffer_index, f"{name}.buffer")
        if "uri" in buffer:
            raise self._error(f"buffers[{buffer_index}].uri", "external buffers are not supported")
        if buffer_index != 0 or self.binary is None:
            raise self._error(f"{name}.buffer", "only buffer 0, the BIN chunk, is supported")
        offset = self._get(view, "byteOffset", int, f"{name}.byteOffset", 0)
        length = self._get(view, "byteLength", int, f"{name}.byteLength")
        declared = self._get(buffer, "byteLength", int, f"buffers[{buffer_index}].byteLength")
        end = min(declared, len(self.binary))
        if offset < 0 or length < 0 or offset + length > end:
            raise self._error(name, f"bytes [{offset}, {offset + length}) outside the "
                                    f"{end}-byte buffer")
        stride = view.get("byteStride")
        if stride is not None and (not isinstance(stride, int) or not 4 <= stride <= 252):
            raise self._error(f"{name}.byteStride", f"expected 4..252, got {stride!r}")
        return self.binary[offset:offset + length], stride

    def accessor(self, index: object, field: str, types: tuple[str, ...],
                 components: tuple[int, ...]) -> np.ndarray:
        """Accessor ``index`` as a (count, width) array of its component dtype (a copy)."""
        acc = self._item("accessors", index, field)
        name = f"accessors[{index}]"
        if "sparse" in acc:
            raise self._error(f"{name}.sparse", "sparse accessors are not supported")
        kind = self._get(acc, "type", str, f"{name}.type")
        component = self._get(acc, "componentType", int, f"{name}.componentType")
        if kind not in types:
            raise self._error(f"{name}.type", f"expected one of {types} for {field}, got {kind}")
        if component not in components:
            raise self._error(f"{name}.componentType",
                              f"expected one of {components} for {field}, got {component}")
        count = self._get(acc, "count", int, f"{name}.count")
        offset = self._get(acc, "byteOffset", int, f"{name}.byteOffset", 0)
        view_index = self._get(acc, "bufferView", int, f"{name}.bufferView")
        raw, stride = self._view_bytes(view_index, f"{name}.bufferView")
        dtype = np.dtype(_COMPONENTS[component]).newbyteorder("<")
        width = _WIDTHS[kind]
        element = dtype.itemsize * width
        stride = stride or element
        if count < 1 or offset < 0 or stride < element:
            raise self._error(name, f"count {count}, byteOffset {offset}, byteStride {stride} "
                                    f"for {element}-byte elements")
        if offset % dtype.itemsize:
            raise self._error(f"{name}.byteOffset", f"{offset} is not a multiple of "
                                                    f"{dtype.itemsize}")
        needed = offset + stride * (count - 1) + element
        if needed > len(raw):
            raise self._error(name, f"{count} elements need {needed} bytes of bufferView "
                                    f"{view_index}, which has {len(raw)} (out of bounds)")
        rows = np.ndarray((count, width), dtype=dtype, buffer=raw, offset=offset,
                          strides=(stride, dtype.itemsize))
        out = rows.astype(dtype.newbyteorder("="))
        if out.dtype.kind == "f" and not np.isfinite(out).all():
            raise self._error(name, "contains NaN or infinity")
        return out

    def mesh(self, mm_per_unit: float) -> GltfMesh:
        """Merge every triangle primitive of every mesh instance in the default scene."""
        parts: list[dict] = []
        for mesh_index, world in self._instances():
            mesh = self._item("meshes", mesh_index, "node.mesh")
            primitives = self._get(mesh, "primitives", list, f"meshes[{mesh_index}].primitives")
            parts.extend(self._primitive(prim, f"meshes[{mesh_index}].primitives[{p}]", world)
                         for p, prim in enumerate(primitives))
        if not parts:
            raise self._error("meshes", "the scene has no triangle mesh")
        offsets = np.cumsum([0] + [len(p["positions"]) for p in parts])
        positions = np.concatenate([p["positions"] for p in parts]) * mm_per_unit
        triangles = np.concatenate([p["triangles"] + o for p, o in zip(parts, offsets)])
        normals = uv = texture = None
        if all(p["normals"] is not None for p in parts):
            normals = np.concatenate([p["normals"] for p in parts]).astype(np.float32)
        if all(p["uv"] is not None for p in parts):
            uv = np.concatenate([p["uv"] for p in parts])
        for p in parts:
            texture = self._texture(p["material"], p["name"] + ".material")
            if texture is not None:
                break
        return GltfMesh(positions=positions.astype(np.float32), normals=normals, uv=uv,
                        triangles=triangles.astype(np.int32), texture=texture)

    def _instances(self) -> list[tuple[int, np.ndarray]]:
        """(mesh index, 4x4 float64 world matrix) of every mesh node in the default scene."""
        nodes = self.doc.get("nodes", [])
        if "scenes" in self.doc and self.doc["scenes"]:
            scene_index = self.doc.get("scene", 0)
            roots = self._get(self._item("scenes", scene_index, "scene"), "nodes", list,
                              f"scenes[{scene_index}].nodes", [])
        elif nodes:
            children = {c for n in nodes if isinstance(n, dict) for c in n.get("children", [])}
            roots = [i for i in range(len(nodes)) if i not in children]
        else:
            return [(i, np.eye(4)) for i in range(len(self.doc.get("meshes", [])))]
        found: list[tuple[int, np.ndarray]] = []
        stack = [(r, np.eye(4), 0) for r in reversed(roots)]
        while stack:
            index, parent, depth = stack.pop()
            if depth > _MAX_NODE_DEPTH:
                raise self._error("nodes", f"hierarchy deeper than {_MAX_NODE_DEPTH} (a cycle?)")
            node = self._item("nodes", index, "scene node")
            world = parent @ self._local_matrix(node, f"nodes[{index}]")
            if "mesh" in node:
                found.append((node["mesh"], world))
            children = self._get(node, "children", list, f"nodes[{index}].children", [])
            stack.extend((c, world, depth + 1) for c in reversed(children))
        return found

    def _local_matrix(self, node: dict, name: str) -> np.ndarray:
        """The node's local 4x4 transform (float64), from ``matrix`` or T * R * S."""
        if "matrix" in node:
            m = self._numbers(node["matrix"], 16, f"{name}.matrix")
            return m.reshape(4, 4).T  # stored column-major
        t = self._numbers(node.get("translation", [0, 0, 0]), 3, f"{name}.translation")
        x, y, z, w = self._numbers(node.get("rotation", [0, 0, 0, 1]), 4, f"{name}.rotation")
        s = self._numbers(node.get("scale", [1, 1, 1]), 3, f"{name}.scale")
        norm = np.sqrt(x * x + y * y + z * z + w * w)
        if norm < 1e-6:
            raise self._error(f"{name}.rotation", "not a unit quaternion")
        x, y, z, w = x / norm, y / norm, z / norm, w / norm
        rotation = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        m = np.eye(4)
        m[:3, :3] = rotation * s
        m[:3, 3] = t
        return m

    def _numbers(self, value: object, n: int, field: str) -> np.ndarray:
        if (not isinstance(value, list) or len(value) != n
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise self._error(field, f"expected {n} numbers")
        array = np.array(value, dtype=np.float64)
        if not np.isfinite(array).all():
            raise self._error(field, "contains NaN or infinity")
        return array

    def _primitive(self, prim: object, name: str, world: np.ndarray) -> dict:
        """One primitive's arrays (float64 geometry), world transform applied, uv v up."""
        if not isinstance(prim, dict):
            raise self._error(name, "expected an object")
        mode = prim.get("mode", _TRIANGLES)
        if mode != _TRIANGLES:
            raise self._error(f"{name}.mode", f"only triangles (4) are supported, got {mode}")
        attributes = self._get(prim, "attributes", dict, f"{name}.attributes")
        if "POSITION" not in attributes:
            raise self._error(f"{name}.attributes.POSITION", "missing")
        positions = self.accessor(attributes["POSITION"], f"{name}.attributes.POSITION",
                                  ("VEC3",), (_FLOAT,)).astype(np.float64)
        n = len(positions)
        normals = uv = None
        if "NORMAL" in attributes:
            normals = self.accessor(attributes["NORMAL"], f"{name}.attributes.NORMAL",
                                    ("VEC3",), (_FLOAT,)).astype(np.float64)
        if "TEXCOORD_0" in attributes:
            uv = self._texcoord(attributes["TEXCOORD_0"], f"{name}.attributes.TEXCOORD_0")
        for key, array in (("NORMAL", normals), ("TEXCOORD_0", uv)):
            if array is not None and len(array) != n:
                raise self._error(f"{name}.attributes.{key}",
                                  f"{len(array)} elements, POSITION has {n}")
        if "indices" in prim:
            indices = self.accessor(prim["indices"], f"{name}.indices", ("SCALAR",),
                                    (_UINT8, _UINT16, _UINT32)).ravel().astype(np.int64)
        else:
            indices = np.arange(n, dtype=np.int64)
        if len(indices) % 3:
            raise self._error(f"{name}.indices", f"{len(indices)} indices, not a multiple of 3")
        if indices.size and indices.max() >= n:
            raise self._error(f"{name}.indices", f"index {int(indices.max())} outside the "
                                                 f"{n} vertices")
        triangles = indices.reshape(-1, 3)
        linear = world[:3, :3]
        det = np.linalg.det(linear)
        if abs(det) < 1e-12:
            raise self._error(name, "its node transform is singular (a zero scale)")
        positions = positions @ linear.T + world[:3, 3]
        if normals is not None:
            normals = normals @ np.linalg.inv(linear)  # rows times the inverse transpose
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        if det < 0:
            triangles = triangles[:, ::-1]
        return {"name": name, "positions": positions, "normals": normals, "uv": uv,
                "triangles": triangles, "material": prim.get("material")}

    def _texcoord(self, index: object, field: str) -> np.ndarray:
        """TEXCOORD_0 as (N, 2) float32 with v up; normalised integer encodings allowed."""
        acc = self._item("accessors", index, field)
        raw = self.accessor(index, field, ("VEC2",), (_FLOAT, _UINT8, _UINT16))
        if raw.dtype != np.float32:
            if not acc.get("normalized", False):
                raise self._error(f"accessors[{index}].normalized",
                                  "integer texture coordinates must be normalized")
            raw = raw / np.float32(np.iinfo(raw.dtype).max)
        uv = raw.astype(np.float32)
        uv[:, 1] = 1.0 - uv[:, 1]
        return uv

    def _texture(self, material_index: object, field: str) -> np.ndarray | None:
        """The material's embedded base-colour image as (H, W, 3) uint8 RGB, or None."""
        if material_index is None:
            return None
        material = self._item("materials", material_index, field)
        base = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if not isinstance(base, dict) or "index" not in base:
            return None
        texture = self._item("textures", base["index"],
                             f"materials[{material_index}].baseColorTexture.index")
        if "source" not in texture:
            return None
        image = self._item("images", texture["source"], f"textures[{base['index']}].source")
        if "bufferView" not in image:
            return None
        raw, _ = self._view_bytes(image["bufferView"], f"images[{texture['source']}].bufferView")
        decoded = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise self._error(f"images[{texture['source']}]", "the embedded image cannot be "
                                                               "decoded")
        return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)


# ----------------------------------------------------------------------------------- writing

def write_glb(path: str | os.PathLike, vertices: np.ndarray, triangles: np.ndarray,
              uv: np.ndarray, texture: np.ndarray | None = None,
              normals: np.ndarray | None = None) -> None:
    """Write a textured triangle mesh as a binary glTF 2.0 file.

    Positions are converted from mm to glTF's metres and v to glTF's v down; the texture is
    embedded as PNG and used as the base colour of an unlit material (KHR_materials_unlit,
    since the texture already carries the captured lighting; viewers without the extension
    fall back to a rough, non-metallic PBR material).

    Args:
        path: the .glb file to write.
        vertices: (N, 3) float32 positions in mm.
        triangles: (M, 3) int32 vertex indices, counter-clockwise from outside.
        uv: (N, 2) float32 texture coordinates, v up (texel row = (1 - v) * H).
        texture: (H, W, 3) uint8 RGB base-colour image, top row first, or None.
        normals: (N, 3) float32 normals (normalised on writing), or None.

    Raises:
        GltfError: an input has the wrong shape, dtype or values (the message names it).
    """
    path = Path(path)
    normals = _checked_inputs(path, vertices, triangles, uv, texture, normals)
    builder = BinBuilder()
    doc = mesh_document(builder, vertices, triangles, uv, normals)
    if texture is not None:
        _embed_texture(path, doc, builder, texture)
    data = glb_bytes(doc, builder)
    with open(path, "wb") as f:
        f.write(data)


def glb_bytes(doc: dict, builder: BinBuilder) -> bytes:
    """The .glb file of ``doc`` and the binary chunk ``builder`` holds (module docstring)."""
    binary = builder.finish(doc)
    json_bytes = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * (-len(json_bytes) % 4)
    total = _HEADER.size + 2 * _CHUNK.size + len(json_bytes) + len(binary)
    return b"".join([_HEADER.pack(_MAGIC, 2, total), _CHUNK.pack(len(json_bytes), _CHUNK_JSON),
                     json_bytes, _CHUNK.pack(len(binary), _CHUNK_BIN), binary])


def _checked_inputs(path: Path, vertices: np.ndarray, triangles: np.ndarray, uv: np.ndarray,
                    texture: np.ndarray | None, normals: np.ndarray | None
                    ) -> np.ndarray | None:
    """Validate the writer's inputs (``write_glb``'s Args); return the normals normalised."""
    n = check_array(f"{path}: vertices", vertices, np.float32, (None, 3), GltfError)
    m = check_array(f"{path}: triangles", triangles, np.int32, (None, 3), GltfError)
    check_array(f"{path}: uv", uv, np.float32, (n, 2), GltfError)
    if n == 0 or m == 0:
        raise GltfError(f"{path}: vertices/triangles: the mesh is empty")
    if triangles.min() < 0 or triangles.max() >= n:
        raise GltfError(f"{path}: triangles: vertex index outside [0, {n})")
    if texture is not None:
        check_array(f"{path}: texture", texture, np.uint8, (None, None, 3), GltfError)
    if normals is None:
        return None
    check_array(f"{path}: normals", normals, np.float32, (n, 3), GltfError)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if (length < 1e-12).any():
        raise GltfError(f"{path}: normals: contains a zero vector")
    return (normals / length).astype(np.float32)


def mesh_document(builder: BinBuilder, vertices: np.ndarray, triangles: np.ndarray,
                  uv: np.ndarray, normals: np.ndarray | None, in_mm: bool = False) -> dict:
    """The JSON chunk of one node with one triangle primitive and its unlit material, its
    attributes and indices appended to ``builder`` (positions in metres, v down; with
    ``in_mm``, the positions stay the float32 mm given and the node scales them to metres)."""
    positions = vertices if in_mm else (vertices.astype(np.float64) / MM_PER_M).astype(np.float32)
    attributes = {"POSITION": builder.accessor(positions, _FLOAT, "VEC3", _ARRAY_BUFFER,
                                               bounds=True)}
    if normals is not None:
        attributes["NORMAL"] = builder.accessor(normals, _FLOAT, "VEC3", _ARRAY_BUFFER)
    gltf_uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)
    attributes["TEXCOORD_0"] = builder.accessor(gltf_uv, _FLOAT, "VEC2", _ARRAY_BUFFER)
    n = len(vertices)
    index_type, index_dtype = ((_UINT16, np.uint16) if n <= 0xFFFF else (_UINT32, np.uint32))
    indices = builder.accessor(triangles.astype(index_dtype).reshape(-1, 1), index_type,
                               "SCALAR", _ELEMENT_ARRAY_BUFFER, bounds=True)

    material: dict = {"name": "facewire",
                      "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0},
                      "extensions": {"KHR_materials_unlit": {}}}
    return {
        "asset": {"version": "2.0", "generator": "facewire models.gltf"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "facewire", **({"scale": [1 / MM_PER_M] * 3} if in_mm
                                                        else {})}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices,
                                    "material": 0, "mode": _TRIANGLES}]}],
        "materials": [material],
    }


def _embed_texture(path: Path, doc: dict, builder: BinBuilder, texture: np.ndarray) -> None:
    """Embed the (H, W, 3) uint8 RGB texture as PNG, the base colour of ``doc``'s material."""
    ok, png = cv2.imencode(".png", cv2.cvtColor(texture, cv2.COLOR_RGB2BGR))
    if not ok:
        raise GltfError(f"{path}: texture: PNG encoding failed")
    embed_base_colour(doc, builder, png.tobytes())


def embed_base_colour(doc: dict, builder: BinBuilder, png: bytes) -> None:
    """Embed ``png`` (a PNG file's bytes, as they are) as image 0, the base colour of
    ``doc``'s material (``mesh_document``), mipmapped, clamped to the edge."""
    doc["images"] = [{"bufferView": builder.view(png), "mimeType": "image/png"}]
    doc["samplers"] = [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR,
                        "wrapS": _CLAMP_TO_EDGE, "wrapT": _CLAMP_TO_EDGE}]
    doc["textures"] = [{"source": 0, "sampler": 0}]
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}


class BinBuilder:
    """Accumulates the BIN chunk: 4-byte aligned bufferViews and their accessors."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, payload: bytes, target: int | None = None) -> int:
        """Append a bufferView (zero-padded to 4 bytes); return its index."""
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(payload)}
        if target is not None:
            view["target"] = target
        padded = payload + b"\0" * (-len(payload) % 4)
        self.parts.append(padded)
        self.size += len(padded)
        self.views.append(view)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, component: int, kind: str, target: int,
                 bounds: bool = False) -> int:
        """Append (count, width) ``array`` as a tightly packed accessor; return its index."""
        payload = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<")).tobytes()
        accessor = {"bufferView": self.view(payload, target), "componentType": component,
                    "count": len(array), "type": kind}
        if bounds:
            cast = float if array.dtype.kind == "f" else int
            accessor["min"] = [cast(v) for v in array.min(axis=0)]
            accessor["max"] = [cast(v) for v in array.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def finish(self, doc: dict) -> bytes:
        """Put the views, accessors and buffer into ``doc``; return the BIN chunk bytes."""
        doc["bufferViews"] = self.views
        doc["accessors"] = self.accessors
        doc["buffers"] = [{"byteLength": self.size}]
        return b"".join(self.parts)
