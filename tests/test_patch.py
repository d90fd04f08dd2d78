"""Texture patches and the texture's confidence map (issue 24, parts 1 and 2).

- a confidence map rides in the model file and comes back; one of another shape, or
  declared as another dtype, is refused naming its member;
- a patch's bytes decode to the patch that was encoded, apply only inside its tiles, and
  move the layers of a region over them by the texture's change (so the region's volume
  a (L - B) does not change);
- a session's versions hold three models' textures however many patches it has, and give
  each version exactly as its updates make it;
- a patch out of the texture, of a wrong size, with a broken PNG or another model's sha256
  is refused naming the field, and changes nothing;
- a log holding a patch is replayed with it and ``model build --from-log`` keeps it.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import tracemalloc
from pathlib import Path

import msgpack
import numpy as np
import pytest
from conftest import write_zip, zip_members

from facewire.models.learned import learned_model
from facewire.models.modelfile import ModelFileError, Region, load_model, save_model
from facewire.models.patch import (
    DIFF_STEP,
    TexturePatch,
    Tile,
    apply_patch,
    changed_rect,
    encode_patch,
    tile_diff,
)
from facewire.models.update import ModelVersions, UpdateError, decode_update, update_head
from facewire.protocol.log import LogWriter, read_log


@pytest.fixture
def confident(generic_model: Path, tmp_path: Path) -> Path:
    """The generic model with a region over texels 8..24 x 16..48 and a confidence map."""
    model = load_model(generic_model)
    h, w = model.texture.shape[:2]
    layers = np.stack([np.full((16, 32, 3), 170, np.uint8), np.full((16, 32, 3), 60, np.uint8)])
    rect = (16 / w, 1 - 24 / h, 48 / w, 1 - 8 / h)
    region = Region("mouth", rect, rect, layers, np.full((16, 32), 255, np.uint8),
                    np.zeros((2, 16, 16), np.float32))
    confidence = np.tile(np.arange(w, dtype=np.uint8)[None] * 2, (h, 1))
    path = tmp_path / "confident.fwm"
    save_model(dataclasses.replace(model, regions=(region,), confidence=confidence), path)
    return path


def test_the_confidence_map_is_kept_in_the_model_file(confident: Path) -> None:
    model = load_model(confident)
    assert model.confidence is not None and model.confidence.shape == model.texture.shape[:2]
    assert model.confidence[5, 10] == 20


def _rewrite(path: Path, out: Path, confidence: np.ndarray, declared: dict) -> Path:
    from facewire.models.archive import png_bytes

    members = zip_members(path)
    members["textures/confidence.png"] = png_bytes(confidence)
    manifest = json.loads(members["model.json"])
    manifest["members"]["textures/confidence.png"] = declared
    members["model.json"] = json.dumps(manifest).encode()
    return write_zip(out, members)


def test_a_confidence_map_of_another_shape_is_refused_naming_it(confident: Path,
                                                                tmp_path: Path) -> None:
    small = np.zeros((8, 8), np.uint8)
    bad = _rewrite(confident, tmp_path / "bad.fwm", small,
                   {"dtype": "uint8", "shape": [8, 8]})
    with pytest.raises(ModelFileError, match=r"confidence \(textures/confidence.png\): "
                                             r"expected the texture's shape"):
        load_model(bad)
    lying = _rewrite(confident, tmp_path / "lying.fwm", small,
                     {"dtype": "uint8", "shape": [64, 128]})
    with pytest.raises(ModelFileError, match=r"textures/confidence.png: expected a 128x64"):
        load_model(lying)
    wrong = _rewrite(confident, tmp_path / "wrong.fwm", small,
                     {"dtype": "float32", "shape": [8, 8]})
    with pytest.raises(ModelFileError, match=r"textures/confidence.png: expected dtype uint8"):
        load_model(wrong)


def _patch(sha: str, serial: int = 1, row: int = 4, col: int = 8) -> TexturePatch:
    """Texels rows row..row+16, cols col..col+16 darkened by 80 levels."""
    diff = tile_diff(np.full((4, 4, 3), 90.0, np.float32), np.full((4, 4, 3), 170, np.float32))
    return TexturePatch(sha, serial, 4, (Tile(row, col, diff),))


def test_a_patch_applies_inside_its_tiles_and_moves_the_layers_over_them(confident: Path
                                                                          ) -> None:
    model = load_model(confident)
    patch = _patch(model.sha256)
    data = encode_patch(patch)
    decoded = decode_update(data, model, model.sha256)
    assert isinstance(decoded, TexturePatch)
    assert decoded.rects() == patch.rects() == [(slice(4, 20), slice(8, 24))]
    head = update_head(data)
    assert (head.serial, head.region) == (1, "texture")
    patched = apply_patch(model, decoded)
    assert changed_rect(model.texture, patched.texture) == (slice(4, 20), slice(8, 24))
    assert abs(int(patched.texture[10, 12, 0]) - 90) <= DIFF_STEP
    # the region over texels 8..24 x 16..48 moved by the texture's change where they meet
    old, new = model.regions[0], patched.regions[0]
    change = patched.texture[8:24, 16:48].astype(int) - model.texture[8:24, 16:48].astype(int)
    moved = new.layers.astype(int) - old.layers.astype(int)
    assert np.array_equal(moved[0], change) and np.array_equal(
        moved[1], np.clip(old.layers[1].astype(int) + change, 0, 255) - old.layers[1])
    assert change[:12, :8].any() and not change[:, 8:].any()


def _field(data: bytes, **changes: object) -> bytes:
    body = msgpack.unpackb(data, raw=False)
    tile = body["tiles"][0]
    for key, value in changes.items():
        if key in tile:
            tile[key] = value
        else:
            body[key] = value
    return msgpack.packb(body, use_bin_type=True)


BAD = {
    "out of bounds": ({"row": 60}, r"tiles\[0\]: texels \[60:76"),
    "wrong size": ({"shape": [5, 4]}, r"tiles\[0\]: png: expected a 4x5 image"),
    "too large": ({"shape": [65, 4]}, r"tiles\[0\].shape\[0\]"),
    "bad compression": ({"png": b"\x89PNG\r\n\x1a\n" + bytes(40)}, r"tiles\[0\]: png"),
    "scale": ({"scale": 0}, r"scale"),
    "another model": ({"base_sha256": "0" * 64}, r"base_sha256"),
    "extra key": ({"extra": 1}, r"expected a map with the keys"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_corrupt_patch_is_refused_naming_its_field(confident: Path, case: str) -> None:
    model = load_model(confident)
    changes, named = BAD[case]
    data = _field(encode_patch(_patch(model.sha256)), **changes)
    versions = ModelVersions(model)
    with pytest.raises(UpdateError, match=r"^update 1: " + named):
        versions.add(1, data, "update 1")
    assert versions.held == 0 and versions.model(1) is model


def test_a_sessions_versions_hold_three_textures_whatever_the_patches(confident: Path
                                                                     ) -> None:
    """Twelve patches held (a gateway's session): the versions' memory stays that of the
    base, the newest and one other, and every version, asked for in any order, is the one
    its updates make."""
    small = load_model(confident)
    texture = np.repeat(np.repeat(small.texture, 8, axis=0), 8, axis=1)  # 512 x 1024: the
    model = dataclasses.replace(small, texture=texture, confidence=None)  # textures weigh
    patches = [_patch(model.sha256, n, row=4 + 12 * (n % 4), col=8 + 8 * n)
               for n in range(1, 13)]
    versions = ModelVersions(model)
    tracemalloc.start()
    try:
        for patch in patches:
            versions.add(patch.serial, encode_patch(patch))
        gc.collect()
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert versions.held == 12
    assert held < 3 * model.texture.nbytes, held
    made = [model]
    for patch in patches:
        made.append(apply_patch(made[-1], patch))
    for serial in (7, 3, 12, 0, 11, 5, 6, 6, 2):
        version = versions.model(serial)
        assert np.array_equal(version.texture, made[serial].texture), serial
        assert np.array_equal(version.regions[0].layers, made[serial].regions[0].layers)


def test_a_log_keeps_its_patches_for_replay_and_build_from_log(confident: Path,
                                                               tmp_path: Path) -> None:
    from facewire.protocol.control import Camera, Hello
    from facewire.protocol.packet import Frame, encode

    model = load_model(confident)
    data = encode_patch(_patch(model.sha256))
    log = tmp_path / "session.fwlog"
    hello = Hello(model_sha256=model.sha256, model_bytes=model.file_bytes, rate_hz=25.0,
                  camera=Camera(640.0, 640.0, 319.5, 239.5, 640, 480), regions=("mouth",))
    writer = LogWriter(log, hello)
    writer.write(encode(Frame(seq=0)), 0.0)
    writer.write_update(0.04, 1, data)
    writer.write(encode(Frame(seq=1, serial=1)), 0.04)
    writer.close()
    read = read_log(log)
    assert [(u.serial, u.data) for u in read.updates] == [(1, data)]
    learned, _ = learned_model(log, confident)
    assert learned.learned is not None and learned.learned.updates[0].region == "texture"
    out = tmp_path / "learned.fwm"
    save_model(learned, out)
    again = load_model(out)
    assert np.array_equal(again.texture, apply_patch(model, _patch(model.sha256)).texture)


def test_a_renderer_takes_a_patch_as_a_new_renderer_draws_it(confident: Path) -> None:
    from facewire.receiver.render import FaceRenderer
    from facewire.receiver.views import virtual_view

    model = load_model(confident)
    patched = apply_patch(model, _patch(model.sha256, row=8, col=56))
    camera = virtual_view("front", model.mesh, np.zeros(3), 160, 160)
    q = np.zeros(1, np.float32)
    with FaceRenderer(patched, 160, 160, samples=0) as fresh:
        want = fresh.render(model.mesh.vertices, q, camera)
    with FaceRenderer(model, 160, 160, samples=0) as renderer:
        before = renderer.render(model.mesh.vertices, q, camera)
        assert renderer.can_update(patched)
        renderer.update_regions(patched)
        after = renderer.render(model.mesh.vertices, q, camera)
    assert np.array_equal(after, want)
    assert not np.array_equal(before, after)
