"""A sideways phone video through the commands: tracked, built, encoded and replayed side by
side as its upright original, and a rotation that is not a quarter turn refused by them.

The clip is obama_speaking.mp4 (512x388, not square, so a quarter turn shows in every size),
re-encoded upright and turned with a display matrix (``conftest.write_video``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import write_video

from facewire.cli import main
from facewire.models.infra.video import read_frames, video_info
from facewire.models.modelfile import load_model
from facewire.protocol.log import read_log
from facewire.sender.capture import CaptureError, open_source
from facewire.sender.pipeline import encode_video
from facewire.sender.tracker import LandmarkTracker

FRAMES = 40  # enough for a model build with its appearance step
SIZE = (512, 388)  # the clip's upright width, height


@pytest.fixture(scope="module")
def clip(shared_data: Path) -> list[np.ndarray]:
    return [f.image.copy() for f in read_frames(shared_data / "video" / "obama_speaking.mp4",
                                                slice(0, FRAMES))]


@pytest.fixture(scope="module")
def copies(clip: list[np.ndarray], tmp_path_factory: pytest.TempPathFactory
           ) -> dict[int, Path]:
    """The clip encoded upright (0) and turned by 90, 180 and 270 degrees, by rotation."""
    folder = tmp_path_factory.mktemp("rotated")
    return {r: write_video(folder / f"r{r}.mp4", clip, rotation=r) for r in (0, 90, 180, 270)}


def test_tracking_sees_the_upright_face(copies: dict[int, Path]) -> None:
    """The tracker's landmarks on each turned copy are the upright copy's, up to codec noise
    (each copy is its own encoding)."""
    def landmarks(path: Path) -> np.ndarray:
        tracker = LandmarkTracker()
        points = [tracker.track(f.image).points for f in read_frames(path, slice(0, 12))]
        assert all(p is not None for p in points)
        return np.array(points)

    upright = landmarks(copies[0])
    for rotation in (90, 180, 270):
        error = np.linalg.norm(landmarks(copies[rotation]) - upright, axis=-1)
        assert np.median(error) <= 1.0 and np.percentile(error, 99) <= 3.0 \
            and error.max() < 6.0, rotation


def test_the_sender_source_is_upright(copies: dict[int, Path]) -> None:
    with open_source(str(copies[270])) as source:
        assert (source.width, source.height) == SIZE
        first = next(iter(source))
    assert first.image.shape == (SIZE[1], SIZE[0], 3)


def test_a_sideways_video_builds_encodes_and_replays_upright(
        copies: dict[int, Path], clip: list[np.ndarray], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The copy a phone would write (-90: stored a quarter turn counter-clockwise of
    upright) through ``model build``, the sender and ``replay --side-by-side``."""
    model_path = tmp_path / "sideways.fwm"
    assert main(["model", "build", str(copies[270]), "--frames", f"0:{FRAMES}",
                 "--no-self-check", "-o", str(model_path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["face_frames"] == FRAMES
    model = load_model(model_path)
    assert (model.camera.width, model.camera.height) == SIZE
    log = tmp_path / "sideways.fwlog"
    sent = encode_video(model_path, copies[270], log, learn=False)
    assert sent["face_frames"] == FRAMES
    hello = read_log(log).hello
    assert (hello.camera.width, hello.camera.height) == SIZE
    out = tmp_path / "side.mp4"
    assert main(["replay", str(log), "--model", str(model_path), "--out", str(out),
                 "--side-by-side", str(copies[270]), "--json"]) == 0
    capsys.readouterr()
    info = video_info(out)
    assert (info.width, info.height, info.rotation) == (2 * SIZE[0], SIZE[1], 0)
    written = next(read_frames(out)).image
    # the left half is the source, upright (the writer's own encoding adds its noise)
    assert np.abs(written[:, :SIZE[0]].astype(int) - clip[0]).mean() < 6


def test_a_tilted_video_is_refused_in_one_line(clip: list[np.ndarray], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    tilted = write_video(tmp_path / "tilted.mp4", clip[:3], rotation=45)
    assert main(["model", "build", str(tilted), "-o", str(tmp_path / "m.fwm")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(tilted) in err and "45 degrees" in err and "multiple of 90" in err
    with pytest.raises(CaptureError, match="45 degrees"):
        open_source(str(tilted))
