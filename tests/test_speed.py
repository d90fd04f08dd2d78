"""Tests for bench.speed: per-frame tracking and morph timings, their report and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import av
import numpy as np
import pytest

from bench.speed import (NOT_MEASURED, NoFaceError, _one_blas_thread, format_speed,
                         measure_speed, speed)
from models.head import generic_head
from models.modelfile import Camera, ModelFileError, ModelInfo, PersonModel, save_model
from models.video import VideoError, frame_range


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generic head with a flat grey texture, saved as a model file."""
    model = PersonModel(mesh=generic_head(), texture=np.full((64, 128, 3), 170, np.uint8),
                        camera=Camera(500.0, 500.0, 320.0, 240.0, 640, 480),
                        info=ModelInfo(name="generic"))
    path = tmp_path_factory.mktemp("model") / "generic.fwm"
    save_model(model, path)
    return path


@pytest.fixture(scope="module")
def result(model_path: Path, shared_data: Path) -> dict:
    return measure_speed(model_path, shared_data / "video" / "lp_d0.mp4", frame_range("0:60"))


def _grey_video(path: Path, frames: int = 8) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
        for _ in range(frames):
            image = av.VideoFrame.from_ndarray(np.full((120, 160, 3), 128, np.uint8),
                                               format="bgr24")
            for packet in stream.encode(image):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_keys_and_values(result: dict) -> None:
    assert result["frames"] == 60
    assert result["tracked_frames"] + result["detect_frames"] == 60
    assert result["detect_frames"] >= 1  # the first frame acquires the face
    assert result["tracked_frames"] >= 50
    assert result["no_face_frames"] == 0
    assert result["vertices"] == len(generic_head().vertices)
    for key in ("track_ms", "track_detect_ms", "morph_ms", "morph_ms_default_threads",
                "morph_ms_per_10k_vertices"):
        assert isinstance(result[key], float) and math.isfinite(result[key])
        assert result[key] > 0, key
    assert result["track_ms"] < result["track_detect_ms"]  # detection is the expensive path
    assert result["morph_ms"] < result["track_ms"]
    assert result["morph_calls"] >= 300
    assert set(result["not_measured"]) == set(NOT_MEASURED)
    assert not {"track_ms", "morph_ms"} & set(result["not_measured"])
    assert not set(NOT_MEASURED) & set(result)  # never faked
    assert set(result["met"]) == {"morph", "track", "sender"}
    assert result["met"]["morph"] == (result["morph_ms_per_10k_vertices"] <= 0.2)
    assert result["threads"]


def test_report_lines_and_json(result: dict, model_path: Path, shared_data: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    text = format_speed(result)
    assert "track:" in text and "morph:" in text and "not measured yet: classify_ms" in text
    assert f"{result['morph_ms']:.4f} ms" in text
    status = speed(model_path, shared_data / "video" / "lp_d0.mp4", as_json=True,
                   frames=frame_range("0:12"))
    assert status == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(out[-1])
    assert summary["frames"] == 12 and summary["morph_ms"] > 0
    assert out[0].startswith(str(shared_data / "video" / "lp_d0.mp4"))


def test_blas_pinning_is_restored() -> None:
    with _one_blas_thread() as pinned:
        inside = list(pinned)
    with _one_blas_thread() as again:
        assert [before for _, before in again] == [before for _, before in inside]
    if inside:  # numpy's OpenBLAS is found on Linux wheels
        assert any("openblas" in name.lower() for name, _ in inside)


def test_video_without_a_face(model_path: Path, tmp_path: Path) -> None:
    video = tmp_path / "grey.mp4"
    _grey_video(video)
    with pytest.raises(NoFaceError, match="no face") as err:
        measure_speed(model_path, video)
    assert str(video) in str(err.value)
    assert isinstance(err.value, VideoError)


def test_unreadable_inputs(model_path: Path, tmp_path: Path) -> None:
    text = tmp_path / "clip.mp4"
    text.write_text("not a video")
    with pytest.raises(VideoError, match="not a readable video") as err:
        measure_speed(model_path, text)
    assert str(text) in str(err.value)
    with pytest.raises(VideoError, match="no such video file"):
        measure_speed(model_path, tmp_path / "missing.mp4")
    video = tmp_path / "grey.mp4"
    _grey_video(video, frames=3)
    with pytest.raises(VideoError, match="no frames in range"):
        measure_speed(model_path, video, frame_range("10:20"))
    bad_model = tmp_path / "broken.fwm"
    bad_model.write_bytes(b"PK\x03\x04 not really a zip")
    for path in (bad_model, tmp_path / "absent.fwm"):
        with pytest.raises(ModelFileError) as err:
            measure_speed(path, video)
        assert str(path) in str(err.value)
