"""The .fwm person-model file: round trip, determinism, and refusal of hostile files.

Over 600 lines because it tests, one by one, each way a hostile file can be wrong that
``models.modelfile`` (with its manifest, ``models.manifest``) promises to refuse, with the
zip-editing helpers those tests share.
"""

from __future__ import annotations

import hashlib
import io
import json
import struct
import tracemalloc
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import npy_bytes, write_zip, zip_members

from facewire.models import modelfile
from facewire.models.fields import ModelError
from facewire.models.geometry import Intrinsics
from facewire.models.manifest import MAX_MEMBER_BYTES, ModelInfo, SourceRange
from facewire.models.mesh import Mesh
from facewire.models.modelfile import (
    Area,
    ModelFileError,
    PersonModel,
    Region,
    load_model,
    load_model_bytes,
    model_sha256,
    model_summary,
    save_model,
)


def _grid_mesh(g: int = 12) -> Mesh:
    """A g x g dome of vertices, two CCW triangles per cell, valid landmark/phantom indices."""
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:g, 0:g].astype(np.float32)
    x, y = (x / (g - 1) - 0.5) * 120, (y / (g - 1) - 0.5) * 160
    z = 60 - (x**2 + y**2) / 200
    vertices = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    i, j = np.mgrid[0:g - 1, 0:g - 1]
    a, b, c, d = i * g + j, i * g + j + 1, (i + 1) * g + j + 1, (i + 1) * g + j
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                                np.stack([a, c, d], -1).reshape(-1, 3)]).astype(np.int32)
    uv = np.stack([(x / 120 + 0.5), (y / 160 + 0.5)], -1).reshape(-1, 2).astype(np.float32)
    tags = (rng.integers(0, 3, len(triangles))).astype(np.uint8)
    landmarks = rng.choice(g * g, 68, replace=False).astype(np.int32)
    phantoms = np.arange(13, dtype=np.int32) * g // 2
    return Mesh(vertices, triangles, uv, tags, landmarks, phantoms)


SOURCE = SourceRange("alice.mp4", 123456, "ab" * 32, 7, 43)


def _model(name: str = "alice", regions: bool = True) -> PersonModel:
    rng = np.random.default_rng(2)
    region = Region(
        "forehead", (0.2, 0.6, 0.8, 0.9), (0.4, 0.7, 0.6, 0.8),
        layers=rng.integers(0, 256, (3, 10, 20, 3), dtype=np.uint8),
        mask=rng.integers(0, 256, (10, 20), dtype=np.uint8),
        templates=rng.standard_normal((3, 16, 16)).astype(np.float32),
        opacity=(0.0, 1.0, 0.5), rest=1.25,
        areas=(Area((0.05, 0.1, 0.15, 0.3), rng.integers(0, 256, (3, 12, 6, 3), dtype=np.uint8),
                    rng.integers(0, 256, (12, 6), dtype=np.uint8)),))
    return PersonModel(
        mesh=_grid_mesh(),
        texture=rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
        camera=Intrinsics(fx=610.5, fy=612.25, cx=319.5, cy=241.0, width=640, height=480),
        info=ModelInfo(name=name, source_video="alice.mp4", frames_used=tuple(range(10, 40, 3)),
                       neutral_frame=13, creator="facewire test", source=SOURCE),
        regions=(region,) if regions else ())


@pytest.fixture()
def saved(tmp_path: Path) -> Path:
    path = tmp_path / "alice.fwm"
    save_model(_model(), path)
    return path


def _refused(path: Path, *fragments: str) -> str:
    """Load must fail with a ModelFileError naming the file and every fragment."""
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


def _edit(path: Path, out: Path, replace: dict[str, bytes | None] | None = None,
          manifest: dict | None = None) -> Path:
    """Copy the model at ``path`` with members replaced (None: removed) and/or a new manifest."""
    members = zip_members(path)
    for name, data in (replace or {}).items():
        if data is None:
            members.pop(name, None)
        else:
            members[name] = data
    if manifest is not None:
        members["model.json"] = json.dumps(manifest).encode()
    return write_zip(out, members)


def _no_areas(path: Path) -> dict[str, None]:
    """``_edit`` replacements that remove the further areas' members."""
    return {name: None for name in zip_members(path) if "/area_" in name}


def _manifest(path: Path) -> dict:
    return json.loads(zip_members(path)["model.json"])


def _entry_data_offset(data: bytes, name: str) -> int:
    """Offset of a member's (compressed) data in a zip's bytes."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        offset = archive.getinfo(name).header_offset
    name_len, extra_len = struct.unpack("<HH", data[offset + 26:offset + 30])
    return offset + 30 + name_len + extra_len


def _set_declared_size(data: bytes, name: str, size: int) -> bytes:
    """Patch a member's uncompressed size in its local header and its directory entry."""
    out = bytearray(data)
    encoded = name.encode()
    local = data.index(b"PK\x03\x04")
    while data[local + 30:local + 30 + len(encoded)] != encoded:
        local = data.index(b"PK\x03\x04", local + 1)
    struct.pack_into("<I", out, local + 22, size)
    central = data.index(b"PK\x01\x02")
    while data[central + 46:central + 46 + len(encoded)] != encoded:
        central = data.index(b"PK\x01\x02", central + 1)
    struct.pack_into("<I", out, central + 24, size)
    return bytes(out)


# ---- round trip and identity --------------------------------------------------------------

def test_round_trip_keeps_everything(saved: Path) -> None:
    model, loaded = _model(), load_model(saved)
    for field in ("vertices", "triangles", "uv", "tags", "landmarks", "phantoms"):
        got, want = getattr(loaded.mesh, field), getattr(model.mesh, field)
        assert got.dtype == want.dtype and np.array_equal(got, want), field
    np.testing.assert_array_equal(loaded.texture, model.texture)
    assert loaded.camera == model.camera and loaded.info == model.info
    (got,), (want,) = loaded.regions, model.regions
    assert (got.name, got.uv_rect, got.template_rect) == (want.name, want.uv_rect,
                                                          want.template_rect)
    for field in ("layers", "mask", "templates"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    (got_area,), (want_area,) = got.areas, want.areas
    assert got_area.uv_rect == want_area.uv_rect
    np.testing.assert_array_equal(got_area.layers, want_area.layers)
    np.testing.assert_array_equal(got_area.mask, want_area.mask)
    assert [p.uv_rect for p in got.parts()] == [want.uv_rect, want_area.uv_rect]
    data = saved.read_bytes()
    assert loaded.sha256 == model_sha256(saved) == hashlib.sha256(data).hexdigest()
    assert loaded.file_bytes == len(data)


def test_texture_is_stored_as_rgb_png(saved: Path) -> None:
    import cv2
    png = zip_members(saved)["textures/neutral.png"]
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr[..., ::-1], _model().texture)


def test_same_model_gives_same_bytes(tmp_path: Path) -> None:
    first = save_model(_model(), tmp_path / "a.fwm")
    second = save_model(_model(), tmp_path / "b.fwm")
    again = save_model(load_model(tmp_path / "a.fwm"), tmp_path / "c.fwm")
    assert first == second == again
    assert (tmp_path / "a.fwm").read_bytes() == (tmp_path / "b.fwm").read_bytes() \
        == (tmp_path / "c.fwm").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.fwm") as archive:
        names = archive.namelist()
        assert names == sorted(names)
        assert {i.date_time for i in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_different_content_gives_different_id(tmp_path: Path) -> None:
    base = save_model(_model(), tmp_path / "a.fwm")
    assert save_model(_model(name="bob"), tmp_path / "b.fwm") != base
    model = _model()
    vertices = model.mesh.vertices.copy()
    vertices[5, 2] += 1.0
    mesh = Mesh(vertices, model.mesh.triangles, model.mesh.uv, model.mesh.tags,
                model.mesh.landmarks, model.mesh.phantoms)
    moved = PersonModel(mesh, model.texture, model.camera, model.info, model.regions)
    assert save_model(moved, tmp_path / "c.fwm") != base


def test_summary_of_loaded_and_in_memory_model_agree(saved: Path) -> None:
    loaded = load_model(saved)
    summary = model_summary(loaded)
    assert summary == {"vertices": 144, "triangles": 242, "regions": 1, "layers": 3,
                       "descriptors": 0, "bytes": saved.stat().st_size,
                       "sha256": model_sha256(saved)}
    assert model_summary(_model()) == summary
    empty = model_summary(_model(regions=False))
    assert (empty["regions"], empty["layers"]) == (0, 0)
    assert empty["sha256"] != summary["sha256"]


def test_model_without_regions_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "plain.fwm"
    save_model(_model(regions=False), path)
    assert load_model(path).regions == ()
    assert _manifest(path)["regions"] == []


def test_load_from_bytes_matches_load_from_file(saved: Path) -> None:
    loaded = load_model_bytes(saved.read_bytes(), "peer")
    assert loaded.sha256 == model_sha256(saved)
    with pytest.raises(ModelFileError, match=r"^peer: "):
        load_model_bytes(saved.read_bytes()[:-1], "peer")


def test_failed_save_leaves_old_file_and_no_temporary(saved: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    before = saved.read_bytes()

    def crash(*_: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(modelfile.os, "replace", crash)
    with pytest.raises(ModelFileError, match="alice.fwm: cannot write"):
        save_model(_model(name="bob"), saved)
    assert saved.read_bytes() == before
    assert sorted(p.name for p in saved.parent.iterdir()) == ["alice.fwm"]


# ---- damaged files --------------------------------------------------------------------------

def test_truncated_files_are_refused(saved: Path, tmp_path: Path) -> None:
    data = saved.read_bytes()
    cut = tmp_path / "cut.fwm"
    for n in sorted({0, 1, 4, 29, 100, len(data) // 3, len(data) // 2, len(data) - 23,
                     len(data) - 22, len(data) - 1, *range(7, len(data), 997)}):
        cut.write_bytes(data[:n])
        _refused(cut)


def test_flipped_bit_in_member_data_fails_the_crc(saved: Path, tmp_path: Path) -> None:
    data = saved.read_bytes()
    for name in ("textures/neutral.png", "arrays/vertices.npy"):
        at = _entry_data_offset(data, name) + 40
        flipped = bytearray(data)
        flipped[at] ^= 0x10
        path = tmp_path / "flipped.fwm"
        path.write_bytes(flipped)
        _refused(path, name)


def test_no_bit_flip_escapes_as_a_raw_error_or_a_changed_model(saved: Path,
                                                                tmp_path: Path) -> None:
    """Anywhere in the file: a ModelFileError, or (an unchecked zip field) the same model."""
    data = saved.read_bytes()
    original = load_model(saved)
    path = tmp_path / "flipped.fwm"
    refused = 0
    for at in range(3, len(data), 53):
        flipped = bytearray(data)
        flipped[at] ^= 1 << (at % 8)
        path.write_bytes(flipped)
        try:
            model = load_model(path)
        except ModelFileError as e:
            assert str(e).startswith(f"{path}: ")
            refused += 1
            continue
        for field in ("vertices", "triangles", "uv", "tags", "landmarks", "phantoms"):
            assert np.array_equal(getattr(model.mesh, field), getattr(original.mesh, field))
        assert np.array_equal(model.texture, original.texture)
        assert model.info == original.info and model.camera == original.camera
    assert refused > 0.8 * len(range(3, len(data), 53))


def test_non_zip_empty_and_missing_files_are_refused(tmp_path: Path) -> None:
    text = tmp_path / "notes.fwm"
    text.write_text("hello, I am not a model\n" * 20)
    _refused(text, "not a facewire model")
    empty = tmp_path / "empty.fwm"
    empty.write_bytes(b"")
    _refused(empty)
    _refused(tmp_path / "absent.fwm", "cannot read")
    _refused(tmp_path, "not a regular file")


def test_file_over_the_size_limit_is_refused(saved: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(modelfile, "MAX_FILE_BYTES", saved.stat().st_size - 1)
    _refused(saved, "bytes, more than")


def test_trailing_or_prefixed_data_is_refused(saved: Path, tmp_path: Path) -> None:
    data = saved.read_bytes()
    (tmp_path / "tail.fwm").write_bytes(data + b"junk")
    _refused(tmp_path / "tail.fwm")
    (tmp_path / "head.fwm").write_bytes(b"junk" + data)
    _refused(tmp_path / "head.fwm", "zip directory")


# ---- zip bombs -------------------------------------------------------------------------------

def _bomb(path: Path, source: Path, member: str, inflated: int) -> bytes:
    """The model at ``source`` with ``member`` replaced by ``inflated`` zero bytes, deflated."""
    members = zip_members(source)
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            if name != member:
                archive.writestr(name, data, zipfile.ZIP_DEFLATED)
        entry = zipfile.ZipInfo(member)
        entry.compress_type = zipfile.ZIP_DEFLATED
        with archive.open(entry, "w") as f:
            chunk = bytes(1 << 20)
            for _ in range(inflated >> 20):
                f.write(chunk)
            f.write(bytes(inflated % (1 << 20)))
    return path.read_bytes()


def test_member_declaring_more_than_allowed_is_refused(saved: Path, tmp_path: Path) -> None:
    path = tmp_path / "bomb.fwm"
    _bomb(path, saved, "arrays/vertices.npy", MAX_MEMBER_BYTES + 1)
    _refused(path, "arrays/vertices.npy", "declares")


def test_extreme_compression_ratio_is_refused(saved: Path, tmp_path: Path) -> None:
    path = tmp_path / "bomb.fwm"
    _bomb(path, saved, "arrays/uv.npy", 8 << 20)
    _refused(path, "arrays/uv.npy", "compression ratio")


def test_member_inflating_past_its_declared_size_is_not_inflated(saved: Path,
                                                                 tmp_path: Path) -> None:
    path = tmp_path / "bomb.fwm"
    data = _bomb(path, saved, "arrays/vertices.npy", 80 << 20)
    path.write_bytes(_set_declared_size(data, "arrays/vertices.npy", 4096))
    tracemalloc.start()
    try:
        _refused(path, "arrays/vertices.npy")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, peak


# ---- hostile names and members --------------------------------------------------------------

@pytest.mark.parametrize("evil", ["../evil.npy", "/etc/x", "arrays/../../evil.npy",
                                  "..\\evil.npy", "C:/evil.npy"])
def test_path_traversal_names_are_refused_and_nothing_is_written(
        saved: Path, tmp_path: Path, evil: str, monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    members = zip_members(saved)
    manifest = json.loads(members["model.json"])
    manifest["members"][evil] = {"dtype": "float32", "shape": [1]}
    members["model.json"] = json.dumps(manifest).encode()
    members[evil] = npy_bytes(np.zeros(1, np.float32))
    path = write_zip(tmp_path / "evil.fwm", members)
    before = sorted(tmp_path.rglob("*")), sorted(tmp_path.parent.iterdir())
    message = _refused(path, "unsafe name")
    assert repr(evil) in message
    assert (sorted(tmp_path.rglob("*")), sorted(tmp_path.parent.iterdir())) == before


def test_unknown_and_duplicate_members_are_refused(saved: Path, tmp_path: Path) -> None:
    members = zip_members(saved)
    _refused(write_zip(tmp_path / "extra.fwm", {**members, "notes.txt": b"hi"}),
             "'notes.txt'", "not a member")
    orphan = {**members, "regions/cheeks/mask.png": members["regions/forehead/mask.png"]}
    _refused(write_zip(tmp_path / "orphan.fwm", orphan), "regions/cheeks/mask.png")
    path = tmp_path / "twice.fwm"
    with pytest.warns(UserWarning, match="Duplicate name"):
        with zipfile.ZipFile(path, "w") as archive:
            for name, data in members.items():
                archive.writestr(name, data)
            archive.writestr("arrays/uv.npy", members["arrays/uv.npy"])
    _refused(path, "arrays/uv.npy", "twice")


def _hostile_npy(target: Path) -> bytes:
    """An object-dtype .npy whose payload, if unpickled, would create ``target``.

    Written by hand (header, then protocol-0 pickle opcodes calling ``open(target, "w")``),
    so the test itself never pickles anything.
    """
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        out, {"descr": "|O", "fortran_order": False, "shape": (1,)})
    out.write(b"cbuiltins\nopen\n(V" + str(target).encode() + b"\nVw\ntR.")
    return out.getvalue()


def test_pickled_npy_is_refused_without_unpickling(saved: Path, tmp_path: Path) -> None:
    sentinel = tmp_path / "pwned"
    path = _edit(saved, tmp_path / "pickle.fwm", {"arrays/vertices.npy": _hostile_npy(sentinel)})
    _refused(path, "arrays/vertices.npy", "pickle")
    assert not sentinel.exists()


def test_missing_member_is_refused(saved: Path, tmp_path: Path) -> None:
    path = _edit(saved, tmp_path / "a.fwm", {"arrays/uv.npy": None})
    _refused(path, "arrays/uv.npy: missing")
    manifest = _manifest(saved)
    del manifest["members"]["arrays/uv.npy"]
    path = _edit(saved, tmp_path / "b.fwm", {"arrays/uv.npy": None}, manifest)
    _refused(path, "arrays/uv.npy: missing")
    path = _edit(saved, tmp_path / "c.fwm", {"regions/forehead/layer_02.png": None})
    _refused(path, "regions/forehead/layer_02.png: missing")
    _refused(_edit(saved, tmp_path / "d.fwm", {"model.json": None}), "model.json: missing")


def test_region_layers_of_different_sizes_are_refused(saved: Path, tmp_path: Path) -> None:
    import cv2
    manifest = _manifest(saved)
    manifest["members"]["regions/forehead/layer_01.png"]["shape"] = [12, 20, 3]
    small = cv2.imencode(".png", np.zeros((12, 20, 3), np.uint8))[1].tobytes()
    path = _edit(saved, tmp_path / "a.fwm", {"regions/forehead/layer_01.png": small}, manifest)
    _refused(path, "regions/forehead/layer_01.png: shape (12, 20, 3) does not match")
    manifest = _manifest(saved)
    manifest["regions"][0]["layers"] = 2
    _refused(_edit(saved, tmp_path / "b.fwm", manifest=manifest),
             "regions/forehead/area_1/layer_02.png: not a member of this model")


def test_member_not_listed_in_the_manifest_is_refused(saved: Path, tmp_path: Path) -> None:
    manifest = _manifest(saved)
    del manifest["members"]["arrays/tags.npy"]
    _refused(_edit(saved, tmp_path / "a.fwm", manifest=manifest),
             "arrays/tags.npy: not listed")


# ---- validation of content -------------------------------------------------------------------

def test_wrong_dtype_is_refused(saved: Path, tmp_path: Path) -> None:
    vertices = load_model(saved).mesh.vertices.astype(np.float64)
    path = _edit(saved, tmp_path / "a.fwm", {"arrays/vertices.npy": npy_bytes(vertices)})
    _refused(path, "arrays/vertices.npy: expected dtype float32, got float64")
    manifest = _manifest(saved)
    manifest["members"]["arrays/vertices.npy"]["dtype"] = "float64"
    path = _edit(saved, tmp_path / "b.fwm", {"arrays/vertices.npy": npy_bytes(vertices)}, manifest)
    _refused(path, "arrays/vertices.npy: expected dtype float32, got 'float64'")
    swapped = load_model(saved).mesh.vertices.astype(">f4")
    path = _edit(saved, tmp_path / "c.fwm", {"arrays/vertices.npy": npy_bytes(swapped)})
    _refused(path, "arrays/vertices.npy: expected dtype float32, got >f4")


def test_wrong_shape_is_refused(saved: Path, tmp_path: Path) -> None:
    wide = np.zeros((144, 4), np.float32)
    path = _edit(saved, tmp_path / "a.fwm", {"arrays/vertices.npy": npy_bytes(wide)})
    _refused(path, "arrays/vertices.npy: expected shape (144, 3)")
    manifest = _manifest(saved)
    manifest["members"]["arrays/vertices.npy"]["shape"] = [144, 4]
    path = _edit(saved, tmp_path / "b.fwm", {"arrays/vertices.npy": npy_bytes(wide)}, manifest)
    _refused(path, "arrays/vertices.npy: expected shape (N, 3)")
    manifest = _manifest(saved)
    manifest["members"]["arrays/uv.npy"]["shape"] = [100, 2]
    path = _edit(saved, tmp_path / "c.fwm", {"arrays/uv.npy": npy_bytes(np.zeros((100, 2),
                                                                          np.float32))}, manifest)
    _refused(path, "mesh: uv: expected shape (144, 2)")


def test_npy_data_shorter_than_its_header_says_is_refused(saved: Path, tmp_path: Path) -> None:
    data = npy_bytes(np.zeros((144, 3), np.float32))[:-4]
    _refused(_edit(saved, tmp_path / "a.fwm", {"arrays/vertices.npy": data}),
             "arrays/vertices.npy", "bytes, expected")


def test_non_finite_vertices_are_refused(saved: Path, tmp_path: Path) -> None:
    for bad in (np.nan, np.inf):
        vertices = load_model(saved).mesh.vertices.copy()
        vertices[7, 1] = bad
        path = _edit(saved, tmp_path / "a.fwm", {"arrays/vertices.npy": npy_bytes(vertices)})
        _refused(path, "vertices", "NaN or infinity")


def test_index_outside_the_mesh_is_refused(saved: Path, tmp_path: Path) -> None:
    mesh = load_model(saved).mesh
    for field, array in (("triangles", mesh.triangles), ("landmarks", mesh.landmarks),
                         ("phantoms", mesh.phantoms)):
        bad = array.copy()
        bad.flat[3] = 144
        path = _edit(saved, tmp_path / f"{field}.fwm", {f"arrays/{field}.npy": npy_bytes(bad)})
        _refused(path, field, "vertex index outside [0, 144)")


def test_unknown_format_version_is_refused(saved: Path, tmp_path: Path) -> None:
    manifest = _manifest(saved)
    manifest["format_version"] = 5
    _refused(_edit(saved, tmp_path / "a.fwm", manifest=manifest),
             "model.json: format_version: unsupported version 5")
    manifest["format_version"] = "1"
    _refused(_edit(saved, tmp_path / "b.fwm", manifest=manifest),
             "model.json: format_version: expected an integer")
    manifest = _manifest(saved)
    manifest["format"] = "something-else"
    _refused(_edit(saved, tmp_path / "c.fwm", manifest=manifest), "model.json: format:")


@pytest.mark.parametrize(("edit", "fragment"), [
    (lambda m: m["camera"].update(fx="600"), "camera.fx: expected a number, got str"),
    (lambda m: m["camera"].update(fy=-1.0), "camera.fy: must be in"),
    (lambda m: m["camera"].update(width=65535), "camera.width: must be in"),
    (lambda m: m["camera"].update(width=True), "camera.width: expected an integer"),
    (lambda m: m["camera"].pop("cx"), "camera: missing key 'cx'"),
    (lambda m: m["info"].update(extra=1), "info: unknown key 'extra'"),
    (lambda m: m["info"].update(frames_used=[3, 2]), "info.frames_used[1]: not strictly"),
    (lambda m: m["info"].update(name=""), "info.name"),
    (lambda m: m["info"].pop("source"), "info: missing key 'source'"),
    (lambda m: m["info"].update(source=[0, 10]), "info.source: expected an object, got list"),
    (lambda m: m["info"]["source"].pop("sha256"), "info.source: missing key 'sha256'"),
    (lambda m: m["info"]["source"].update(frames=9), "info.source: unknown key 'frames'"),
    (lambda m: m["info"]["source"].update(start=-1), "info.source.start: -1 outside"),
    (lambda m: m["info"]["source"].update(start=1.5), "info.source.start: expected an integer"),
    (lambda m: m["info"]["source"].update(stop=7), "info.source.stop: 7 not after start 7"),
    (lambda m: m["info"]["source"].update(bytes=0), "info.source.bytes: 0 outside"),
    (lambda m: m["info"]["source"].update(sha256="AB" * 32),
     "info.source.sha256: expected 64 lowercase hex"),
    (lambda m: m["info"]["source"].update(video=""), "info.source.video: expected 1 to 1024"),
    (lambda m: m.update(regions={}), "regions: expected a list"),
    (lambda m: m["regions"][0].update(name="../x"), "regions[0].name"),
    (lambda m: m["regions"][0].update(layers=0), "regions[0].layers"),
    (lambda m: m["regions"][0].update(opacity=[0.0, 1.0]), "opacity: expected 3 numbers"),
    (lambda m: m["regions"][0].update(opacity=[0.0, 1.0, 1.5]), "opacity: expected numbers in"),
    (lambda m: m["regions"][0].update(opacity="1"), "regions[0].opacity: expected a list"),
    (lambda m: m["regions"][0].pop("opacity"), "regions[0]: missing key 'opacity'"),
    (lambda m: m["regions"][0].update(rest=2.5), "rest: expected a number in [0, 2]"),
    (lambda m: m["regions"][0].update(rest="1"), "rest: expected a number"),
    (lambda m: m["regions"][0].update(uv_rect=[0.5, 0.5, 0.4, 0.9]), "uv_rect"),
    (lambda m: m["regions"][0].update(areas={}), "regions[0].areas: expected a list"),
    (lambda m: m["regions"][0].update(areas=[[0, 0, 1, 1]] * 5), "at most 4 rectangles"),
    (lambda m: m["regions"][0].update(areas=[[0.3, 0.1, 0.2, 0.3]]),
     "region 'forehead': area 1: uv_rect"),
    (lambda m: m["regions"][0].update(areas=[]), "regions/forehead/area_1/layer_00.png: not a "
                                                 "member of this model"),
    (lambda m: m["regions"][0].update(template_rect=[0.0, 0.0, 1.0, 1.0]),
     "template_rect: not inside uv_rect"),
    (lambda m: m["members"]["textures/neutral.png"].update(shape=[5000, 5000, 3]),
     "textures/neutral.png: image side 5000 exceeds 4096"),
    (lambda m: m["members"]["textures/neutral.png"].update(shape=[24, 33, 3]),
     "textures/neutral.png: expected a 33x24 image"),
])
def test_manifest_schema_is_enforced(saved: Path, tmp_path: Path, edit, fragment: str) -> None:
    manifest = _manifest(saved)
    edit(manifest)
    _refused(_edit(saved, tmp_path / "a.fwm", manifest=manifest), fragment)


def test_build_range_round_trips(saved: Path, tmp_path: Path) -> None:
    """info.source: written as the manifest's object, read back equal; None round-trips as
    null; the range's overlap arithmetic."""
    loaded = load_model(saved).info.source
    assert loaded == SOURCE
    assert _manifest(saved)["info"]["source"] == {"video": "alice.mp4", "bytes": 123456,
                                                  "sha256": "ab" * 32, "start": 7, "stop": 43}
    none = replace(_model(), info=replace(_model().info, source=None))
    save_model(none, tmp_path / "none.fwm")
    assert _manifest(tmp_path / "none.fwm")["info"]["source"] is None
    assert load_model(tmp_path / "none.fwm").info.source is None
    assert [SOURCE.overlap(a, b) for a, b in ((43, None), (0, 7), (0, None), (40, 50),
                                              (10, 20), (0, 8))] == [0, 0, 36, 3, 10, 1]
    with pytest.raises(ModelError, match="info.source.stop"):
        SourceRange("a.mp4", 1, "ab" * 32, 5, 5)
    with pytest.raises(ModelError, match="info.source: expected a SourceRange"):
        ModelInfo("alice", source=(0, 10))  # type: ignore[arg-type]


def test_build_range_identifies_the_video_by_its_bytes(tmp_path: Path) -> None:
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"frames" * 1000)
    built = SourceRange.of_file(video, 0, 30)
    assert (built.video, built.bytes) == ("clip.mp4", 6000)
    assert built.sha256 == hashlib.sha256(video.read_bytes()).hexdigest()
    copy = tmp_path / "renamed.mkv"
    copy.write_bytes(video.read_bytes())
    assert built.same_video(video) and built.same_video(copy)  # the bytes, not the name
    other = tmp_path / "other" / "clip.mp4"
    other.parent.mkdir()
    other.write_bytes(b"frameS" * 1000)  # same name, same size, other bytes
    assert not built.same_video(other)
    with pytest.raises(ModelFileError, match="absent.mp4"):
        SourceRange.of_file(tmp_path / "absent.mp4", 0, 1)


def test_version_3_is_read_without_a_build_range(saved: Path, tmp_path: Path) -> None:
    manifest = _manifest(saved)
    manifest["format_version"] = 3
    manifest["info"].pop("source")
    assert load_model(_edit(saved, tmp_path / "v3.fwm", manifest=manifest)).info.source is None
    manifest["info"]["source"] = None
    _refused(_edit(saved, tmp_path / "v3b.fwm", manifest=manifest),
             "info: unknown key 'source'")


def test_version_2_is_read_without_further_areas(saved: Path, tmp_path: Path) -> None:
    manifest = _manifest(saved)
    manifest["format_version"] = 2
    manifest["info"].pop("source")
    manifest["regions"][0].pop("areas")
    for name in [n for n in manifest["members"] if "/area_" in n]:
        manifest["members"].pop(name)
    path = _edit(saved, tmp_path / "v2.fwm", _no_areas(saved), manifest)
    assert load_model(path).regions[0].areas == ()
    manifest["regions"][0]["areas"] = []
    _refused(_edit(saved, tmp_path / "v2b.fwm", _no_areas(saved), manifest),
             "regions[0]: unknown key 'areas'")


def test_version_1_is_read_with_opaque_layers(saved: Path, tmp_path: Path) -> None:
    manifest = _manifest(saved)
    manifest["format_version"] = 1
    manifest["info"].pop("source")
    manifest["regions"][0].pop("opacity")
    manifest["regions"][0].pop("rest")
    manifest["regions"][0].pop("areas")
    for name in [n for n in manifest["members"] if "/area_" in n]:
        manifest["members"].pop(name)
    model = load_model(_edit(saved, tmp_path / "v1.fwm", _no_areas(saved), manifest))
    assert model.regions[0].opacity == (1.0, 1.0, 1.0) and model.regions[0].rest == 0.0
    saved_region = load_model(saved).regions[0]
    assert saved_region.opacity == (0.0, 1.0, 0.5) and saved_region.rest == 1.25
    manifest["regions"][0]["opacity"] = [1.0, 1.0, 1.0]
    _refused(_edit(saved, tmp_path / "v1b.fwm", _no_areas(saved), manifest),
             "regions[0]: unknown key 'opacity'")


def test_invalid_json_is_refused(saved: Path, tmp_path: Path) -> None:
    for raw in (b"{", b"[]", b'{"format": NaN}', b"\xff\xfe", b"[" * 100000,
                b'{"format": 1, "format": 2}'):
        _refused(_edit(saved, tmp_path / "a.fwm", {"model.json": raw}), "model.json")


def test_wrong_png_kind_is_refused(saved: Path, tmp_path: Path) -> None:
    import cv2
    grey = cv2.imencode(".png", np.zeros((24, 32), np.uint8))[1].tobytes()
    _refused(_edit(saved, tmp_path / "a.fwm", {"textures/neutral.png": grey}),
             "textures/neutral.png: expected an 8-bit RGB PNG")
    _refused(_edit(saved, tmp_path / "b.fwm", {"textures/neutral.png": b"GIF89a" + bytes(40)}),
             "textures/neutral.png: not a PNG image")


# ---- in-memory validation --------------------------------------------------------------------

def test_invalid_models_cannot_be_built() -> None:
    model = _model()
    with pytest.raises(ModelError, match="texture: expected dtype uint8"):
        PersonModel(model.mesh, model.texture.astype(np.float32), model.camera, model.info)
    with pytest.raises(ModelError, match="texture: expected shape"):
        PersonModel(model.mesh, np.zeros((8, 8, 4), np.uint8), model.camera, model.info)
    region = model.regions[0]
    with pytest.raises(ModelError, match="regions: region names are not unique"):
        PersonModel(model.mesh, model.texture, model.camera, model.info, (region, region))
    with pytest.raises(ModelError, match="mask: expected shape"):
        Region("eye", region.uv_rect, region.template_rect, region.layers,
               np.zeros((3, 3), np.uint8), region.templates)
    with pytest.raises(ModelError, match="area 1: 2 layers, the region has 3"):
        Region("eye", region.uv_rect, region.template_rect, region.layers, region.mask,
               region.templates, areas=(Area((0.1, 0.1, 0.2, 0.2), region.layers[:2],
                                             region.mask),))
    with pytest.raises(ModelError, match="templates: expected shape"):
        Region("eye", region.uv_rect, region.template_rect, region.layers, region.mask,
               region.templates[:2])
    with pytest.raises(ModelError, match="camera: expected a Intrinsics"):
        PersonModel(model.mesh, model.texture, (600.0, 600.0, 320.0, 240.0, 640, 480),
                    model.info)
    with pytest.raises(ModelError, match="info.frames_used"):
        ModelInfo("alice", frames_used=(1, 1))
    assert ModelInfo("alice", frames_used=list(np.arange(3))).frames_used == (0, 1, 2)
