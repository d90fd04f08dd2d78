"""The browser's model (models.webmodel) and its WebGL2 renderer (receiver/web/) against Python.

The model's bytes are read back here the way the page reads them (the glb with models.gltf's
reader, the rig's weights rebuilt from the rig file alone, an update applied from its file
alone) and compared with the Python model, rig and versions.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import zip_members

from facewire.models.gltf import read_glb
from facewire.models.modelfile import PersonModel, load_model
from facewire.models.rig import Rig
from facewire.models.update import ModelUpdate, apply_update
from facewire.models.webmodel import model_glb, rig_bin, update_bin


def _glb_json(data: bytes) -> dict:
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def _glb_image(data: bytes, doc: dict, index: int) -> bytes:
    view = doc["bufferViews"][doc["images"][index]["bufferView"]]
    start = 28 + struct.unpack_from("<I", data, 12)[0] + view["byteOffset"]
    return data[start:start + view["byteLength"]]


def _container(data: bytes, magic: bytes) -> tuple[dict, dict[str, np.ndarray], memoryview]:
    """The JSON, arrays and body of a rig or update file (models.webmodel's container)."""
    head, version, length = struct.unpack_from("<4sII", data)
    assert (head, version) == (magic, 1) and (12 + length) % 8 == 0
    header = json.loads(data[12:12 + length])
    body = memoryview(data)[12 + length:]
    arrays = {}
    for name, spec in header.get("arrays", {}).items():
        dtype = np.dtype("<" + spec["dtype"])
        assert spec["offset"] % 8 == 0
        count = int(np.prod(spec["shape"]))
        arrays[name] = np.frombuffer(body, dtype, count, spec["offset"]).reshape(spec["shape"])
    return header, arrays, body


@pytest.fixture(scope="module")
def model(person_model: Path) -> PersonModel:
    return load_model(person_model)


@pytest.fixture(scope="module")
def glb(model: PersonModel) -> bytes:
    return model_glb(model)


def test_the_glb_holds_the_mesh_and_the_model_files_own_pngs(
        model: PersonModel, glb: bytes, person_model: Path, tmp_path: Path) -> None:
    (tmp_path / "m.glb").write_bytes(glb)
    mesh = read_glb(tmp_path / "m.glb")
    assert np.array_equal(mesh.positions, model.mesh.vertices)  # mm, exactly
    assert np.abs(mesh.uv - model.mesh.uv).max() < 1e-7
    assert np.array_equal(mesh.triangles, model.mesh.triangles)
    assert np.array_equal(mesh.texture, model.texture)
    doc = _glb_json(glb)
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] \
        == 5123  # uint16: N < 65536
    members = zip_members(person_model)
    for image in doc["images"]:
        assert _glb_image(glb, doc, doc["images"].index(image)) == members[image["name"]]
    regions = doc["extras"]["facewire"]["regions"]
    assert [r["name"] for r in regions] == [r.name for r in model.regions]
    for meta, region in zip(regions, model.regions, strict=True):
        assert meta["opacity"] == list(region.opacity) and meta["rest"] == region.rest
        for area_meta, area in zip(meta["areas"], region.parts(), strict=True):
            assert tuple(area_meta["uv_rect"]) == area.uv_rect
            mask = cv2.imdecode(np.frombuffer(_glb_image(glb, doc, area_meta["mask"]),
                                              np.uint8), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(mask, area.mask)
    size = len(glb) + len(rig_bin(model))
    assert size <= 1.10 * model.file_bytes, (size, model.file_bytes)


def weights_from_rig_file(data: bytes, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 9) morph weights and (9, 2, 3) tangents from the rig file and the glb's positions
    alone: the page's computation (models.webmodel, "Rig"), in numpy."""
    header, a, _ = _container(data, b"FWRG")
    p = positions.astype(np.float64)
    p[a["lip_vertices"], 1] -= a["lip_drop"]
    r = np.linalg.norm(p[:, None, :] - a["centres"][None], axis=2)
    if header["kernel"] == "multiquadric":
        rows = np.hstack([np.sqrt(r ** 2 + a["shape"] ** 2),
                          header["balance"] * np.hstack([(p - a["origin"]) / header["scale"],
                                                         np.ones((len(p), 1))])])
    else:
        rows = np.exp(-(r / a["shape"]) ** 2)
    weights = rows @ a["z"]
    weights[a["frozen"]] = 0.0
    return weights, a["tangents"]


def test_the_rig_file_gives_the_rigs_weights(model: PersonModel) -> None:
    rig = Rig(model.mesh)
    data = rig_bin(model, rig)
    assert len(data) < 40_000
    weights, tangents = weights_from_rig_file(data, model.mesh.vertices)
    assert np.abs(weights - rig.weights).max() < 1e-4
    assert np.array_equal(tangents, rig.tangents)
    uv = np.random.default_rng(1).normal(0.0, 3.0, (9, 2)).astype(np.float32)
    d = np.einsum("kc,kcj->kj", uv, tangents)
    assert np.abs(model.mesh.vertices + weights @ d - rig.morph(rig.from_tangent(uv))).max() \
        < 1e-3


def apply_update_file(data: bytes, previous: PersonModel) -> list[tuple[int, list[np.ndarray],
                                                                         tuple, float]]:
    """Per changed region: (index, its new layer stacks per area, opacity, rest), from the
    update file and the previous version alone."""
    header, _, body = _container(data, b"FWUP")
    out = []
    for change in header["regions"]:
        parts = previous.regions[change["index"]].parts()
        stacks = []
        for n, part in enumerate(parts):
            layers = []
            for state in change["states"]:
                if "from" in state:
                    layers.append(part.layers[state["from"]])
                else:
                    at, length = header["blobs"][state["images"][n]]
                    png = np.frombuffer(body[at:at + length], np.uint8)
                    layers.append(cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR),
                                               cv2.COLOR_BGR2RGB))
            stacks.append(np.stack(layers))
        out.append((change["index"], stacks, tuple(change["opacity"]), change["rest"]))
    return out


def learned_version(model: PersonModel) -> PersonModel:
    """The model with a new mouth state inserted at its rest (an update's version 1)."""
    region = next(r for r in model.regions if r.name == "mouth")
    rng = np.random.default_rng(3)
    return apply_update(model, ModelUpdate(
        base_sha256=model.sha256, serial=1, region="mouth", position=round(region.rest),
        replaces=None, template=np.zeros((16, 16), np.float32), opacity=0.8,
        layers=tuple(rng.integers(0, 256, p.layers.shape[1:], dtype=np.uint8)
                     for p in region.parts())))


def test_the_update_file_makes_the_next_version(model: PersonModel) -> None:
    version = learned_version(model)
    data = update_bin(model, version)
    changes = apply_update_file(data, model)
    assert [c[0] for c in changes] == [[r.name for r in model.regions].index("mouth")]
    index, stacks, opacity, rest = changes[0]
    new = version.regions[index]
    assert opacity == new.opacity and rest == new.rest
    for stack, part in zip(stacks, new.parts(), strict=True):
        assert np.array_equal(stack, part.layers)
    header = _container(data, b"FWUP")[0]  # only the new state's images travel
    assert len(header["blobs"]) == len(new.parts())
    assert _container(update_bin(version, version), b"FWUP")[0]["regions"] == []
