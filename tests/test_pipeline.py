"""Tests for sender.pipeline: the whole sender on real video (one packet per frame, flags
following the tracker, decoded geometry within the quantisation bounds), and its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facewire.models.geometry import rotation_vector
from facewire.models.infra.video import frame_range, read_frames
from facewire.models.landmarks import eye_aspect_ratio
from facewire.models.modelfile import ModelFileError
from facewire.protocol.control import Camera, decode_message, encode_message
from facewire.protocol.log import read_log
from facewire.protocol.packet import QUANTISERS, Flag
from facewire.sender.capture import CaptureError, estimate_intrinsics
from facewire.sender.pack import unpack_geometry
from facewire.sender.pipeline import SenderPipeline, encode_video
from facewire.sender.tracker import LandmarkTracker

ROT_DEG, SHIFT_XY, SHIFT_Z, RESIDUAL = (q.step / 2 for q in QUANTISERS[:4])


@pytest.fixture(scope="module")
def video(shared_data: Path) -> Path:
    return shared_data / "video" / "lp_d0.mp4"


def test_encode_real_video(generic_model: Path, video: Path, tmp_path: Path) -> None:
    log_path = tmp_path / "lp_d0.fwlog"
    seen: list[tuple[str, int | None]] = []

    def progress(items, label, total):
        seen.append((label, total))
        return items

    summary = encode_video(generic_model, video, log_path, progress=progress)
    assert seen == [("encoding", 78)]
    assert summary["frames"] == summary["packets"] == 78
    log = read_log(log_path)
    assert log.lost == 0 and len(log.packets) == 78  # exactly one packet per frame
    assert list(log.frames["seq"]) == list(range(78))
    assert np.all(np.diff(log.times) > 0)
    # the face-present flag follows the tracker, frame by frame
    tracker = LandmarkTracker()
    present = [tracker.track(f.image).points is not None for f in read_frames(video)]
    flags = log.frames["flags"].astype(int)
    assert [bool(f & Flag.FACE_PRESENT) for f in flags] == present
    assert summary["face_frames"] == sum(present) >= 70
    assert summary["tracking_lost"] == sum(bool(f & Flag.TRACKING_LOST) for f in flags)
    assert summary["clamped"] == sum(bool(f & Flag.CLAMPED) for f in flags)
    assert summary["payload_kbps"] == pytest.approx(10.32)
    # the Hello: camera guess and the model's id; no regions yet
    c = estimate_intrinsics(512, 512)
    assert log.hello.camera == Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
    assert log.hello.model_sha256 == summary["model_sha256"]
    assert log.hello.regions == ()
    assert log.hello.rate_hz == pytest.approx(25.0)


def test_decoded_geometry_matches_the_senders(generic_model: Path, video: Path) -> None:
    from facewire.models.modelfile import load_model
    model = load_model(generic_model)
    pipeline = SenderPipeline(model, estimate_intrinsics(512, 512), rate_hz=25.0)
    hello = decode_message(encode_message(pipeline.hello()))
    assert hello == pipeline.hello()
    posed = 0
    last = None
    for f in read_frames(video, frame_range("0:40")):
        out = pipeline.process(f.image, f.time)
        assert set(out.timings) == {"track", "pose", "lift", "heuristics", "sample",
                                    "classify", "learn", "shade", "pack"}
        frame, pose, residuals = unpack_geometry(pipeline.rig, out.packet)
        assert out.q.shape == (0,) and not frame.q.any()  # no regions: Q slots stay 0
        assert frame.seq == f.index
        if out.rotation is None:  # no pose: the last one is repeated
            assert last is not None and np.array_equal(frame.rotation, last.rotation)
            continue
        posed += 1
        assert out.residuals.shape == (9, 3) and out.residuals.dtype == np.float32
        assert np.abs(np.degrees(rotation_vector(pose.rotation)
                                 - rotation_vector(out.rotation))).max() <= ROT_DEG + 1e-4
        err_t = np.abs(pose.translation - out.translation)
        assert err_t[:2].max() <= SHIFT_XY + 1e-4 and err_t[2] <= SHIFT_Z + 1e-3
        uv = pipeline.rig.to_tangent(out.residuals)
        assert np.abs(frame.residuals - uv).max() <= RESIDUAL + 1e-4
        assert np.linalg.norm(residuals - out.residuals, axis=1).max() <= RESIDUAL * 1.5
        last = frame
    assert posed >= 35
    pipeline.reset()
    first = pipeline.process(next(iter(read_frames(video))).image, 0.0)
    assert first.frame.seq == 0


def test_packets_carry_each_regions_q(person_model: Path, video: Path, tmp_path: Path) -> None:
    from facewire.models.modelfile import load_model
    model = load_model(person_model)
    pipeline = SenderPipeline(model, estimate_intrinsics(512, 512), rate_hz=25.0)
    names = tuple(r.name for r in model.regions)
    assert pipeline.hello().regions == names
    layers = np.array([len(r.layers) for r in model.regions])
    step = next(q.step for q in QUANTISERS if q.name == "q")
    qs, ratios = [], []
    for f in read_frames(video):
        out = pipeline.process(f.image, f.time)
        ratios.append(eye_aspect_ratio(out.points).mean() if out.points is not None else np.nan)
        frame, _, _ = unpack_geometry(pipeline.rig, out.packet)
        assert out.q.shape == (len(names),)
        assert np.all((out.q >= 0) & (out.q <= layers - 1))
        assert np.abs(frame.q[:len(names)] - out.q).max() <= step / 2 + 1e-6
        assert not frame.q[len(names):].any()
        qs.append(out.q)
    qs = np.array(qs)
    # lp_d0 closes its eyes: the eyelids' Q follows the tracker's eye aspect ratio (which
    # only chose the states at enrollment; at run time the wavelet classifier alone decides)
    lids = qs[:, [names.index("eyelid_left"), names.index("eyelid_right")]].mean(axis=1)
    ratios = np.array(ratios)
    seen = np.isfinite(ratios)
    assert lids.max() >= 2.0
    assert np.corrcoef(lids[seen], ratios[seen])[0, 1] < -0.7
    assert all(np.ptp(qs[:, k]) > 0 for k in range(len(names)))  # every region varies
    # a frame without a face holds the last Q
    held = pipeline.process(np.zeros((512, 512, 3), np.uint8), 100.0)
    assert held.offsets is None and np.array_equal(held.q, qs[-1])


def test_video_without_a_face(generic_model: Path, grey_video, tmp_path: Path) -> None:
    video = grey_video()
    summary = encode_video(generic_model, video, tmp_path / "grey.fwlog")
    assert summary["packets"] == summary["frames"] == 6
    assert summary["face_frames"] == 0 and summary["tracking_lost"] == 6
    log = read_log(tmp_path / "grey.fwlog")
    assert all(int(f) & Flag.TRACKING_LOST and not int(f) & Flag.FACE_PRESENT
               for f in log.frames["flags"])


def test_errors_name_the_file(generic_model: Path, video: Path, tmp_path: Path) -> None:
    text = tmp_path / "clip.mp4"
    text.write_text("not a video")
    out = tmp_path / "out.fwlog"
    with pytest.raises(CaptureError) as err:
        encode_video(generic_model, text, out)
    assert str(text) in str(err.value)
    with pytest.raises(CaptureError, match="no such file"):
        encode_video(generic_model, tmp_path / "missing.mp4", out)
    bad = tmp_path / "broken.fwm"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    for path in (bad, tmp_path / "absent.fwm"):
        with pytest.raises(ModelFileError) as err:
            encode_video(path, video, out)
        assert str(path) in str(err.value)
    assert not out.exists()  # nothing written on a failed start
    calib = tmp_path / "calib.json"
    calib.write_text('{"fx": 500}')
    with pytest.raises(CaptureError, match="calib.json"):
        encode_video(generic_model, video, out, calib=calib)
    with pytest.raises(ValueError, match="--focal"):
        encode_video(generic_model, video, out, focal=-3.0)
