"""Tests for bench.speed: per-stage timings, the live loopback run, the report and errors."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from facewire.bench.speed import (
    LOOPBACK_KEYS,
    NoFaceError,
    _one_blas_thread,
    format_speed,
    measure_speed,
    speed,
)
from facewire.models.head import generic_head
from facewire.models.infra.video import VideoError, frame_range
from facewire.models.modelfile import ModelFileError


@pytest.fixture(scope="module")
def result(generic_model: Path, shared_data: Path) -> dict:
    return measure_speed(generic_model, shared_data / "video" / "lp_d0.mp4", frame_range("0:60"),
                         loopback_s=0)


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
    assert set(result["not_measured"]) == set(LOOPBACK_KEYS)  # the loopback run was skipped
    assert all(result[key] is None for key in LOOPBACK_KEYS)  # never faked
    assert set(result["met"]) == {"morph", "track", "sender", "classify", "learn", "receiver",
                                  "receiver_1280x720", "latency", "memory"}
    assert result["met"]["latency"] is False and result["met"]["memory"] is False
    # the receiver renders the sender's packets for real, at two sizes
    for key in ("decode_ms", "render_ms", "receiver_ms_median", "render_ms_1280x720",
                "encode_ms"):
        assert isinstance(result[key], float) and result[key] > 0, key
    assert result["receiver_ms_median"] > result["render_ms"] > result["decode_ms"]
    assert result["receiver_fps"] == pytest.approx(1000 / result["receiver_ms_median"], rel=1e-3)
    assert result["render_ms_1280x720"] > result["render_ms"] * 0.8
    assert result["met"]["morph"] == (result["morph_ms_per_10k_vertices"] <= 0.2)
    assert result["threads"]
    # the generic model has no regions: nothing is sampled or classified, nothing is faked
    assert result["regions"] == 0
    assert result["classify_ms"] is None and result["sample_ms"] is None
    assert result["met"]["classify"] is False
    assert result["learn_ms_per_frame"] is None and result["learn_updates"] == 0


def test_classification_is_timed_on_a_model_with_regions(person_model: Path,
                                                         shared_data: Path) -> None:
    result = measure_speed(person_model, shared_data / "video" / "lp_d0.mp4",
                           frame_range("0:30"), loopback_s=0)
    assert result["regions"] == 7
    for key in ("sample_ms", "classify_ms", "learn_ms", "shade_ms"):  # medians: a frame's part
        assert isinstance(result[key], float) and 0 < result[key] < result["sender_ms_median"]
    # a mean, with the healing's hand checks inline (bench runs have no worker): any size
    assert isinstance(result["learn_ms_per_frame"], float) and result["learn_ms_per_frame"] > 0
    assert result["met"]["classify"] == (result["classify_ms"] <= 1.0)
    assert result["met"]["learn"] == (result["learn_ms_per_frame"] <= 0.5)
    assert "classify: " in format_speed(result) and "learn: " in format_speed(result)


def test_report_lines_with_a_live_loopback_run(result: dict, generic_model: Path,
                                               shared_data: Path) -> None:
    text = format_speed(result)
    assert "track:" in text and "morph:" in text and "not measured: latency_ms" in text
    assert "receiver: " in text and "at 1280x720" in text and "encode: " in text
    assert "classify: not measured (the model has no regions" in text
    assert f"{result['morph_ms']:.4f} ms" in text
    # a real `facewire send` process and a live receiver, 8 s of played frames
    summary, out = speed(generic_model, shared_data / "video" / "lp_d0.mp4",
                         frames=frame_range("0:12"), loopback_s=8)
    assert summary["frames"] == 12 and summary["morph_ms"] > 0
    assert out[0].startswith(str(shared_data / "video" / "lp_d0.mp4"))
    assert summary["not_measured"] == []
    assert summary["latency_frames"] > 100  # 25 Hz for 8 s, less the first second
    assert 0 < summary["latency_ms_median"] <= summary["latency_ms_p95"]
    assert summary["loopback"]["received"] >= summary["latency_frames"]
    for side in ("sender", "receiver"):
        assert summary[f"{side}_rss_mb"] > 50 and math.isfinite(summary[f"{side}_rss_growth_mb"])
    assert any(line.startswith("latency: ") for line in out)
    assert any(line.startswith("memory: sender ") for line in out)


def test_blas_pinning_is_restored() -> None:
    with _one_blas_thread() as pinned:
        inside = list(pinned)
    with _one_blas_thread() as again:
        assert [before for _, before in again] == [before for _, before in inside]
    if inside:  # numpy's OpenBLAS is found on Linux wheels
        assert any("openblas" in name.lower() for name, _ in inside)


def test_video_without_a_face(generic_model: Path, grey_video) -> None:
    video = grey_video()
    with pytest.raises(NoFaceError, match="no face") as err:
        measure_speed(generic_model, video)
    assert str(video) in str(err.value)
    assert isinstance(err.value, VideoError)


def test_unreadable_inputs(generic_model: Path, grey_video, tmp_path: Path) -> None:
    text = tmp_path / "clip.mp4"
    text.write_text("not a video")
    with pytest.raises(VideoError, match="not a readable video") as err:
        measure_speed(generic_model, text, loopback_s=0)
    assert str(text) in str(err.value)
    with pytest.raises(VideoError, match="no such video file"):
        measure_speed(generic_model, tmp_path / "missing.mp4")
    video = grey_video(frames=3)
    with pytest.raises(VideoError, match="no frames in range"):
        measure_speed(generic_model, video, frame_range("10:20"))
    bad_model = tmp_path / "broken.fwm"
    bad_model.write_bytes(b"PK\x03\x04 not really a zip")
    for path in (bad_model, tmp_path / "absent.fwm"):
        with pytest.raises(ModelFileError) as err:
            measure_speed(path, video)
        assert str(path) in str(err.value)
