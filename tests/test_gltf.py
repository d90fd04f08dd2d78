"""glTF 2.0 binary reading and writing: round trip, hand-built files, the real scan, bad input."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from facewire.models import gltf
from facewire.models.gltf import GltfError, read_glb, write_glb


def _pack(doc: dict, binary: bytes) -> bytes:
    """A .glb from a JSON document and a BIN chunk (the test's own minimal writer)."""
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text
    body += struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _unpack(data: bytes) -> tuple[dict, bytes]:
    (json_length,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20:20 + json_length])
    bin_start = 20 + json_length
    (bin_length,) = struct.unpack_from("<I", data, bin_start)
    return doc, data[bin_start + 8:bin_start + 8 + bin_length]


def _synthetic(n_side: int = 5):
    """A textured, bumpy grid in mm: vertices, triangles, uv (v up), texture, normals."""
    rng = np.random.default_rng(7)
    ys, xs = np.mgrid[0:n_side, 0:n_side].astype(np.float32)
    vertices = np.column_stack([xs.ravel() * 12.5 - 30, ys.ravel() * 9.0 + 4,
                                rng.normal(0, 3, n_side * n_side)]).astype(np.float32)
    uv = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float32) / (n_side - 1)
    quads = [(r * n_side + c, r * n_side + c + 1, (r + 1) * n_side + c + 1, (r + 1) * n_side + c)
             for r in range(n_side - 1) for c in range(n_side - 1)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    texture = rng.integers(0, 256, (6, 9, 3), dtype=np.uint8)
    normals = rng.normal(size=vertices.shape).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return vertices, triangles, uv, texture, normals


def test_round_trip_keeps_geometry_uv_texture_and_normals(tmp_path):
    vertices, triangles, uv, texture, normals = _synthetic()
    path = tmp_path / "grid.glb"
    write_glb(path, vertices, triangles, uv, texture, normals)
    mesh = read_glb(path)
    np.testing.assert_allclose(mesh.positions, vertices, atol=1e-4)
    np.testing.assert_array_equal(mesh.triangles, triangles)
    np.testing.assert_allclose(mesh.uv, uv, atol=1e-6)
    np.testing.assert_array_equal(mesh.texture, texture)
    np.testing.assert_allclose(mesh.normals, normals, atol=1e-6)
    assert mesh.positions.dtype == np.float32 and mesh.triangles.dtype == np.int32
    np.testing.assert_allclose(read_glb(path, mm_per_unit=1.0).positions, vertices / 1000,
                               atol=1e-7)


def test_written_file_follows_the_glb_layout(tmp_path):
    vertices, triangles, uv, texture, _ = _synthetic()
    path = tmp_path / "grid.glb"
    write_glb(path, vertices, triangles, uv, texture)
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    raw_json = data[20:20 + json_length]
    assert raw_json.rstrip(b" ").endswith(b"}")  # padded with spaces only
    doc, binary = _unpack(data)
    assert len(binary) % 4 == 0 and len(data) == 20 + json_length + 8 + len(binary)
    assert doc["asset"]["version"] == "2.0"
    prim = doc["meshes"][0]["primitives"][0]
    position = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(position["min"], vertices.min(axis=0) / 1000, rtol=1e-6)
    np.testing.assert_allclose(position["max"], vertices.max(axis=0) / 1000, rtol=1e-6)
    assert doc["accessors"][prim["indices"]]["componentType"] == 5123  # small mesh: uint16
    for view in doc["bufferViews"]:
        assert view["byteOffset"] % 4 == 0
    # glTF's v runs down: the stored v is 1 - ours.
    tex_acc = doc["accessors"][prim["attributes"]["TEXCOORD_0"]]
    view = doc["bufferViews"][tex_acc["bufferView"]]
    stored = np.frombuffer(binary, "<f4", tex_acc["count"] * 2, view["byteOffset"]).reshape(-1, 2)
    np.testing.assert_allclose(stored[:, 1], 1 - uv[:, 1], atol=1e-7)
    material = doc["materials"][prim["material"]]
    image = doc["images"][doc["textures"][material["pbrMetallicRoughness"]
                                          ["baseColorTexture"]["index"]]["source"]]
    assert image["mimeType"] == "image/png"
    png = doc["bufferViews"][image["bufferView"]]
    assert binary[png["byteOffset"]:png["byteOffset"] + 8] == b"\x89PNG\r\n\x1a\n"


def test_large_mesh_uses_uint32_indices_and_no_texture(tmp_path):
    n = 70_000
    vertices = np.random.default_rng(1).normal(size=(n, 3)).astype(np.float32)
    triangles = np.array([[0, 1, 2], [n - 3, n - 2, n - 1]], np.int32)
    uv = np.zeros((n, 2), np.float32)
    path = tmp_path / "big.glb"
    write_glb(path, vertices, triangles, uv)
    doc, _ = _unpack(path.read_bytes())
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] \
        == 5125
    mesh = read_glb(path)
    np.testing.assert_array_equal(mesh.triangles, triangles)
    assert mesh.texture is None and mesh.normals is None


def _hand_built(scale: list[float]) -> bytes:
    """Two primitives: interleaved (stride 32) with uint8 indices, and a non-indexed one.

    Node 0 (translation (1, 2, 3), ``scale``) holds node 1 (90 degrees about z) with mesh 0;
    node 2, outside the scene, must be ignored.
    """
    a_pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    a_nrm = np.tile(np.array([1, 1, 0], np.float32) / np.sqrt(2), (4, 1))
    a_uv = np.array([[0, 0.1], [1, 0.2], [1, 0.9], [0, 1.0]], np.float32)
    interleaved = np.concatenate([a_pos, a_nrm, a_uv], axis=1).astype(np.float32)  # 32 B
    a_idx = np.array([0, 1, 2, 0, 2, 3], np.uint8).tobytes() + b"\0\0"
    b_pos = np.array([[5, 0, 0], [6, 0, 0], [5, 1, 0]], np.float32)
    b_nrm = np.tile(np.array([0, 0, 1], np.float32), (3, 1))
    b_uv = np.array([[0.5, 0.25], [0.75, 0.25], [0.5, 0.75]], np.float32)
    chunks = [interleaved.tobytes(), a_idx, b_pos.tobytes(), b_nrm.tobytes(), b_uv.tobytes()]
    offsets = np.cumsum([0] + [len(c) for c in chunks])
    views = [{"buffer": 0, "byteOffset": int(o), "byteLength": len(c)}
             for o, c in zip(offsets, chunks)]
    views[0]["byteStride"] = 32
    accessors = [
        {"bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 0, "byteOffset": 24, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 1, "componentType": 5121, "count": 6, "type": "SCALAR"},
        {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 3, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 4, "componentType": 5126, "count": 3, "type": "VEC2"},
    ]
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"translation": [1, 2, 3], "scale": scale, "children": [1]},
                  {"rotation": [0, 0, s, c], "mesh": 0},
                  {"mesh": 0, "translation": [100, 0, 0]}],
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3},
            {"attributes": {"POSITION": 4, "NORMAL": 5, "TEXCOORD_0": 6}}]}],
        "accessors": accessors, "bufferViews": views,
        "buffers": [{"byteLength": int(offsets[-1])}],
    }
    return _pack(doc, b"".join(chunks))


def test_reader_merges_primitives_and_applies_node_transforms(tmp_path):
    path = tmp_path / "hand.glb"
    path.write_bytes(_hand_built([2.0, 1.0, 1.0]))
    mesh = read_glb(path, mm_per_unit=1.0)
    local = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                      [5, 0, 0], [6, 0, 0], [5, 1, 0]], np.float64)
    rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float64)
    linear = np.diag([2.0, 1.0, 1.0]) @ rz
    np.testing.assert_allclose(mesh.positions, local @ linear.T + [1, 2, 3], atol=1e-5)
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(mesh.uv[:4, 1], [0.9, 0.8, 0.1, 0.0], atol=1e-6)
    np.testing.assert_allclose(mesh.uv[4:], [[0.5, 0.75], [0.75, 0.75], [0.5, 0.25]])
    # Normals follow the inverse transpose: (1, 1, 0) -> R -> (-1, 1, 0) -> S^-1 -> (-1/2, 1, 0).
    expected = np.array([-0.5, 1.0, 0.0]) / np.linalg.norm([-0.5, 1.0, 0.0])
    np.testing.assert_allclose(mesh.normals[:4], np.tile(expected, (4, 1)), atol=1e-6)
    np.testing.assert_allclose(mesh.normals[4:], np.tile([0, 0, 1.0], (3, 1)), atol=1e-6)
    assert mesh.texture is None


def test_mirroring_node_flips_winding(tmp_path):
    path = tmp_path / "mirror.glb"
    path.write_bytes(_hand_built([-1.0, 1.0, 1.0]))
    mesh = read_glb(path, mm_per_unit=1.0)
    np.testing.assert_array_equal(mesh.triangles, [[2, 1, 0], [3, 2, 0], [6, 5, 4]])
    a, b, c = (mesh.positions[mesh.triangles[0, k]] for k in range(3))
    assert np.cross(b - a, c - a)[2] > 0  # still counter-clockwise seen from +z


def test_lee_perry_smith_scan(shared_data):
    mesh = read_glb(shared_data / "meshes/lee-perry-smith/LeePerrySmith.glb")
    assert mesh.positions.shape == (9279, 3) and mesh.triangles.shape == (17684, 3)
    assert mesh.normals.shape == (9279, 3) and mesh.uv.shape == (9279, 2)
    for array in (mesh.positions, mesh.normals, mesh.uv):
        assert array.dtype == np.float32 and np.isfinite(array).all()
    assert mesh.triangles.min() >= 0 and mesh.triangles.max() < 9279
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1, atol=1e-3)
    assert mesh.uv.min() >= 0 and mesh.uv.max() <= 1
    assert mesh.texture is None  # Map-COL.jpg is a separate file
    # The bust faces +z, y up: the nose tip (front-most vertex) is in the upper half.
    nose = mesh.positions[np.argmax(mesh.positions[:, 2])]
    assert abs(nose[0]) < 200 and nose[1] > 0


@pytest.fixture
def good_file(tmp_path):
    vertices, triangles, uv, texture, _ = _synthetic(3)
    path = tmp_path / "good.glb"
    write_glb(path, vertices, triangles, uv, texture)
    return path


def _rewrite(path, edit) -> None:
    doc, binary = _unpack(path.read_bytes())
    edit(doc)
    path.write_bytes(_pack(doc, binary))


def test_truncated_file_is_refused(good_file):
    data = good_file.read_bytes()
    good_file.write_bytes(data[:len(data) // 2])
    with pytest.raises(GltfError, match="truncated"):
        read_glb(good_file)
    good_file.write_bytes(data[:7])
    with pytest.raises(GltfError, match="header"):
        read_glb(good_file)


def test_bad_magic_and_version_are_refused(good_file):
    data = good_file.read_bytes()
    good_file.write_bytes(b"GLTF" + data[4:])
    with pytest.raises(GltfError, match="magic") as info:
        read_glb(good_file)
    assert str(good_file) in str(info.value)
    good_file.write_bytes(data[:4] + struct.pack("<I", 1) + data[8:])
    with pytest.raises(GltfError, match="version"):
        read_glb(good_file)


def test_accessor_out_of_bounds_is_refused(good_file):
    def grow_positions(doc):
        doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]][
            "count"] += 1
    _rewrite(good_file, grow_positions)
    with pytest.raises(GltfError, match=r"accessors\[0\].*out of bounds"):
        read_glb(good_file)


def test_buffer_view_outside_buffer_is_refused(good_file):
    def stretch(doc):
        doc["bufferViews"][0]["byteLength"] += 10_000
    _rewrite(good_file, stretch)
    with pytest.raises(GltfError, match=r"bufferViews\[0\].*outside"):
        read_glb(good_file)


def test_index_out_of_range_is_refused(good_file):
    def shrink_positions(doc):
        prim = doc["meshes"][0]["primitives"][0]
        for key in ("POSITION", "TEXCOORD_0"):
            doc["accessors"][prim["attributes"][key]]["count"] = 4
    _rewrite(good_file, shrink_positions)
    with pytest.raises(GltfError, match=r"indices: index \d+ outside the 4 vertices"):
        read_glb(good_file)


def test_unsupported_features_are_named(good_file):
    _rewrite(good_file, lambda doc: doc.update(extensionsRequired=["KHR_draco_mesh_compression"]))
    with pytest.raises(GltfError, match="extensionsRequired.*draco"):
        read_glb(good_file)
    _rewrite(good_file, lambda doc: (doc.pop("extensionsRequired"),
                                     doc["meshes"][0]["primitives"][0].update(mode=1)))
    with pytest.raises(GltfError, match=r"primitives\[0\]\.mode"):
        read_glb(good_file)


def test_size_limit(good_file, monkeypatch):
    monkeypatch.setattr(gltf, "MAX_FILE_BYTES", 100)
    with pytest.raises(GltfError, match="limit"):
        read_glb(good_file)


def test_writer_validates_inputs(tmp_path):
    vertices, triangles, uv, texture, _ = _synthetic(3)
    path = tmp_path / "bad.glb"
    with pytest.raises(GltfError, match="vertices: expected dtype float32"):
        write_glb(path, vertices.astype(np.float64), triangles, uv)
    with pytest.raises(GltfError, match="triangles: vertex index"):
        write_glb(path, vertices, triangles + 100, uv)
    with pytest.raises(GltfError, match="uv: expected shape"):
        write_glb(path, vertices, triangles, uv[:-1])
    with pytest.raises(GltfError, match="texture: expected shape"):
        write_glb(path, vertices, triangles, uv, texture[..., 0])
