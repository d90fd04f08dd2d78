"""The texture heals during the session (issue 24, part 2): a blotch the enrollment never saw
is corrected by patches the sender ships, and the session's patches are what a receiver
applies; a patch's neighbouring tiles travel as one stored tile and carry the correction.

Real parts: the model lp_d0.mp4 builds (``person_model``), given a dark blotch on the cheek
that the enrollment believed (confidence 255 there), and the real sender pipeline, learning,
over lp_d0.mp4's own frames, which show that cheek clean.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from facewire.models.modelfile import load_model, save_model
from facewire.models.patch import TexturePatch, Tile, apply_patch
from facewire.models.update import ModelVersions
from facewire.sender.capture import open_source
from facewire.sender.enroll.silhouette import SilhouetteFinder
from facewire.sender.heal import SCALE, STORE, TILE, VIEWS, Healer, _Read
from facewire.sender.pipeline import SenderPipeline, sender_camera


def _blotched(person_model: Path, out: Path) -> tuple[Path, tuple[slice, slice]]:
    """The model with a dark 128 x 128-texel blotch on its right cheek, and its texels."""
    model = load_model(person_model)
    h, w = model.texture.shape[:2]
    uv = model.mesh.uv[model.mesh.landmarks].astype(np.float64)
    u, v = uv[31] + 0.35 * (uv[3] - uv[31])  # the cheek beside the nose
    row, col = int((1 - v) * h) - 64, int(u * w) - 64
    dark = np.full((16, 16, 3), 128 - 20, np.uint8)  # -80 levels (models.patch.DIFF_STEP 4)
    blotch = apply_patch(model, TexturePatch(model.sha256, 1, 8, (Tile(row, col, dark),)))
    confidence = np.full((h, w), 255, np.uint8)
    save_model(dataclasses.replace(blotch, confidence=confidence), out)
    return out, (slice(row + 16, row + 112), slice(col + 16, col + 112))


def test_a_blotch_seen_clean_is_healed_by_patches(person_model: Path, shared_data: Path,
                                                 tmp_path: Path) -> None:
    path, inner = _blotched(person_model, tmp_path / "blotched.fwm")
    model = load_model(path)
    truth = load_model(person_model).texture[inner].astype(np.float64)
    src = open_source(str(shared_data / "video" / "lp_d0.mp4"), pace=False)
    pipeline = SenderPipeline(model, sender_camera(src.width, src.height), learn=True)
    issued: list[tuple[float, bytes]] = []
    with src:
        for frame in src:
            out = pipeline.process(frame.image, frame.time)
            if out.update_bytes is not None:
                issued.append((frame.time, out.update_bytes))
    patches = [u for u in pipeline.updates if isinstance(u, TexturePatch)]
    assert patches, "no patch was issued"
    before = np.abs(model.texture[inner] - truth).mean()
    after = np.abs(pipeline.model.texture[inner] - truth).mean()
    assert before > 60 and after < 0.4 * before, (before, after)
    # a receiver applying the session's bytes holds the sender's texture, texel for texel
    versions = ModelVersions(model)
    for serial, (_, data) in enumerate(issued, 1):
        versions.add(serial, data)
    assert np.array_equal(versions.model(len(issued)).texture, pipeline.model.texture)


def test_neighbouring_tiles_are_stored_as_one_and_carry_the_correction(
        person_model: Path) -> None:
    model = load_model(person_model)
    pipeline = SenderPipeline(model, sender_camera(640, 480), learn=False)
    healer = Healer(model, pipeline.camera, pipeline.rig)
    d = np.full(healer.base.shape, 20.0, np.float32)  # +20 levels over the whole box
    picked = [(0, 0), (0, TILE), (0, 2 * TILE), (TILE, 0)]  # a row of three, and one below
    tiles = healer._tiles(d, picked)
    assert len(tiles) == 2
    patch = TexturePatch(model.sha256, 1, SCALE * STORE, tuple(tiles))
    changed = apply_patch(model, patch).texture.astype(np.int16) - model.texture
    row, col = SCALE * healer.rows.start, SCALE * healer.cols.start
    side = SCALE * TILE
    inside = np.zeros(model.texture.shape[:2], bool)
    inside[row:row + side, col:col + 3 * side] = True
    inside[row + side:row + 2 * side, col:col + side] = True
    unclipped = inside & (model.texture.max(axis=2) < 200)
    assert np.abs(changed[unclipped] - 20).max() <= 2
    assert not changed[~inside].any()


def test_a_correction_has_no_edge(person_model: Path) -> None:
    # Five agreeing reads, +40 levels over a block of cells and unseen around it: the
    # correction heals the block's middle and fades out smoothly, with no step a viewer sees
    # as an edge (the fade over 3 cells and the cut where the seen cells ended left a tile's
    # rectangle on lp_d9's cheek: steps of 40 levels a cell here)
    model = load_model(person_model)
    pipeline = SenderPipeline(model, sender_camera(640, 480), learn=False)
    healer = Healer(model, pipeline.camera, pipeline.rig)
    h, w = healer.base.shape[:2]
    diff = np.full((h, w, 3), np.nan, np.float32)
    block = (slice(h // 2 - 20, h // 2 + 20), slice(w // 2 - 20, w // 2 + 20))
    diff[block] = 40.0
    nowhere = np.zeros((h, w), np.float32)
    reads = [_Read(np.zeros((8, 8, 3), np.uint8), np.zeros((68, 2)), nowhere, nowhere,
                   diff.copy()) for _ in range(VIEWS)]
    found = healer.correction(reads)
    assert found is not None
    d, tiles = found
    luma = d @ np.array([0.299, 0.587, 0.114], np.float32)
    assert luma[h // 2, w // 2] > 36  # the middle healed
    steps = max(np.abs(np.diff(luma, axis=0)).max(), np.abs(np.diff(luma, axis=1)).max())
    assert steps < 0.25 * 40 + 1, steps  # a smoothstep over TAPER = 6 cells at most
    inside = np.zeros((h, w), bool)
    for r, c in tiles:
        inside[r:r + TILE, c:c + TILE] = True
    assert not luma[~inside].any()  # nothing outside the tiles patched


@pytest.fixture(scope="module")
def own_frames(person_model: Path, shared_data: Path) -> SenderPipeline:
    """The real sender pipeline, learning, after lp_d0.mp4's own frames (its model's)."""
    model = load_model(person_model)
    src = open_source(str(shared_data / "video" / "lp_d0.mp4"), pace=False)
    pipeline = SenderPipeline(model, sender_camera(src.width, src.height), learn=True)
    with src:
        for frame in src:
            pipeline.process(frame.image, frame.time)
    assert pipeline.learner is not None and pipeline.learner.healer is not None
    return pipeline


def test_a_clean_enrollment_seen_again_is_not_patched(own_frames: SenderPipeline) -> None:
    # the model's own frames, which it was built from, hold nothing to heal: no patch (before
    # the confidence map counted unjudged skin as misregistered and the reads took the chin
    # for the neck behind it, three patches on lp_d0's first 40 frames)
    assert own_frames.learner is not None and own_frames.learner.healer is not None
    assert own_frames.learner.healer.read_count >= 10  # it did look
    patches = [u for u in own_frames.updates if isinstance(u, TexturePatch)]
    assert not patches, [[(t.row, t.col) for t in p.tiles] for p in patches]


def test_cells_that_read_the_room_take_no_part(own_frames: SenderPipeline) -> None:
    # The healing box reaches above the brows and beside the cheeks, where the fitted head
    # can be larger than the real one: a read sees the room there, clean and agreeing, and
    # would paint it onto the head (mediapipe_selfie's sky on its crown, before). The held
    # reads' cells within ROOM_PX of a pixel outside the person are taken out; the rest stay.
    assert own_frames.learner is not None and own_frames.learner.healer is not None
    healer = own_frames.learner.healer
    reads = [r for r in healer.reads if not r.outlined]
    assert len(reads) >= 3
    before = [r.diff.copy() for r in reads]
    assert healer._room(reads)  # some cell saw the room (26 over lp_d0's last five reads)
    assert not healer._room(reads)  # each read is asked once
    with SilhouetteFinder() as finder:
        for r, diff in zip(reads, before):
            person = finder.find(r.image, r.points)
            h, w = person.shape
            inside = person[np.clip(np.rint(r.y), 0, h - 1).astype(int),
                            np.clip(np.rint(r.x), 0, w - 1).astype(int)]
            seen = np.isfinite(diff[..., 0])
            kept = np.isfinite(r.diff[..., 0])
            assert not (kept & ~inside).any()  # no cell on a room pixel
            assert (kept <= seen).all()
            np.testing.assert_array_equal(r.diff[kept], diff[kept])
            assert (seen & inside & ~kept).sum() <= 0.2 * (seen & inside).sum()
