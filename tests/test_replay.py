"""`facewire replay`: a recorded log rendered for real (EGL, H.264 through PyAV), with loss."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from facewire.cli import main
from facewire.models.infra.video import read_frames, video_info
from facewire.models.modelfile import load_model
from facewire.protocol.log import LogWriter, read_log
from facewire.receiver.replay import ReplayError, replay_log
from facewire.sender.pipeline import encode_video


@pytest.fixture(scope="module")
def log(person_model: Path, shared_data: Path, tmp_path_factory: pytest.TempPathFactory
        ) -> Path:
    """lp_d0.mp4 (78 frames) encoded with its own model."""
    path = tmp_path_factory.mktemp("replay") / "lp_d0.fwlog"
    encode_video(person_model, shared_data / "video" / "lp_d0.mp4", path)
    return path


def _damaged(log: Path, out: Path, seed: int = 5) -> tuple[Path, int]:
    """The log with 30 % of its packets removed (never the first or the last) and 5 % of
    the rest moved one place later; returns the path and how many were removed."""
    original = read_log(log)
    n = len(original.packets)
    rng = np.random.default_rng(seed)
    removed = rng.choice(np.arange(1, n - 1), size=int(0.3 * n), replace=False)
    kept = [i for i in range(n) if i not in set(removed)]
    for k in rng.choice(len(kept) - 2, size=max(1, int(0.05 * len(kept))), replace=False):
        kept[k], kept[k + 1] = kept[k + 1], kept[k]
    with LogWriter(out, original.hello) as writer:
        for i in kept:
            writer.write(original.packets[i].tobytes(), float(original.times[i]))
    return out, len(removed)


def test_every_frame_slot_is_rendered_despite_loss_and_reordering(
        log: Path, person_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
        ) -> None:
    damaged, removed = _damaged(log, tmp_path / "damaged.fwlog")
    out = tmp_path / "replay.mp4"
    assert main(["replay", str(damaged), "--model", str(person_model), "--out", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 78  # every slot from the first sequence number to the last
    assert summary["concealed"] == removed and summary["received"] == 78 - removed
    info = video_info(out)
    assert (info.width, info.height) == (512, 512)  # the sender camera's size
    frames = [f.image for f in read_frames(out)]
    assert len(frames) == 78
    assert all(f.mean() > 5 for f in frames)  # a face in every frame, none left black


def test_the_reconstruction_lines_up_with_the_input(log: Path, person_model: Path,
                                                    shared_data: Path, tmp_path: Path) -> None:
    """Side by side with its source; the rendered face covers the input's face."""
    source = shared_data / "video" / "lp_d0.mp4"
    out = tmp_path / "frames"
    summary = replay_log(log, person_model, out, source=source)
    assert summary["frames"] == 78 and summary["concealed"] == 0
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 78
    import cv2
    image = cv2.imread(str(pngs[40]))
    assert image.shape == (512, 1024, 3)
    left, right = image[:, :512], image[:, 512:]
    face = right.max(axis=2) > 0  # the rendering's face pixels (black background)
    assert 0.05 < face.mean() < 0.6
    # where the rendering is the face, the input is the face too: similar colour
    diff = np.abs(left[face].astype(float) - right[face].astype(float)).mean()
    assert diff < 40


def test_virtual_views_frame_the_head(log: Path, person_model: Path, tmp_path: Path) -> None:
    for view in ("front", "three-quarter"):
        out = tmp_path / view
        summary = replay_log(log, person_model, out, view=view, size=(320, 240))
        assert (summary["width"], summary["height"]) == (320, 240)
        import cv2
        image = cv2.imread(str(sorted(out.glob("*.png"))[10]))
        rows, cols = np.nonzero(image.max(axis=2) > 0)
        assert abs(cols.mean() - 160) < 40 and abs(rows.mean() - 120) < 40


def test_a_model_that_is_not_the_logs_is_refused(log: Path, generic_model: Path,
                                                  tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ReplayError, match="generic.fwm: sha256"):
        replay_log(log, generic_model, tmp_path / "x.mp4")
    assert main(["replay", str(log), "--model", str(generic_model), "--out",
                 str(tmp_path / "x.mp4")]) == 2
    assert "is not the model of" in capsys.readouterr().err
    assert main(["replay", str(log), "--model", str(generic_model), "--out",
                 str(tmp_path / "x.mp4"), "--size", "big"]) == 2
    assert not (tmp_path / "x.mp4").exists()
    assert load_model(generic_model).sha256 != read_log(log).hello.model_sha256


def test_inspect_names_the_q_columns_by_region(log: Path, person_model: Path,
                                               tmp_path: Path) -> None:
    import csv

    out = tmp_path / "log.csv"
    assert main(["inspect", str(log), "--csv", str(out)]) == 0
    with out.open() as f:
        rows = list(csv.DictReader(f))
    regions = load_model(person_model).regions
    assert len(rows) == 78
    for region in regions:
        values = np.array([float(row[f"q_{region.name}"]) for row in rows])
        assert values.min() >= 0 and values.max() <= len(region.layers) - 1
        assert np.ptp(values) > 0  # the packets carry the classified Q, not a constant


def test_a_neutral_packet_renders_the_models_own_preview(person_model: Path) -> None:
    """Neutral geometry and every region at its rest state (what the playout gives for a
    face at rest or lost) render pixel-identical to the preview's model panels."""
    from facewire.protocol.packet import N_REGIONS
    from facewire.receiver.playout import Playout
    from facewire.receiver.render import FaceRenderer
    from facewire.sender.enroll.build import (
        PREVIEW_BACKGROUND,
        PREVIEW_HEIGHT,
        PREVIEW_SAMPLES,
        preview_cameras,
        render_preview,
    )

    model = load_model(person_model)
    rest = np.zeros(N_REGIONS, np.float32)
    rest[:len(model.regions)] = [r.rest for r in model.regions]
    state = Playout(30.0, rest_q=rest).pop()  # before any packet: the face at rest
    assert not state.residuals.any() and np.array_equal(state.q, rest)
    preview = render_preview(model)
    with FaceRenderer(model, PREVIEW_HEIGHT, PREVIEW_HEIGHT, samples=PREVIEW_SAMPLES,
                      background=PREVIEW_BACKGROUND) as renderer:
        for k, camera in enumerate(preview_cameras(model.mesh)):
            image = renderer.render(model.mesh.vertices, state.q, camera)[..., ::-1]
            panel = preview[:PREVIEW_HEIGHT, k * PREVIEW_HEIGHT:(k + 1) * PREVIEW_HEIGHT]
            assert np.array_equal(image, panel), f"panel {k}"
            # and any other state of the regions shows: the layers are really drawn
            other = renderer.render(model.mesh.vertices, np.where(rest > 0, 0.0, 1.0)
                                    .astype(np.float32), camera)[..., ::-1]
            assert (np.abs(other.astype(int) - panel).max(axis=2) > 8).sum() > 100
