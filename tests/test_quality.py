"""Tests for bench.quality: the packet-geometry NME core, the real benchmark, its errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facewire.bench.geometry import geometry_nme, project_landmarks
from facewire.bench.quality import (
    TARGET_NME_HELDOUT,
    TARGET_Q,
    OverlapError,
    check_overlap,
    format_quality,
    quality,
)
from facewire.bench.reference import OpenFaceError
from facewire.bench.speed import NoFaceError
from facewire.models.geometry import Intrinsics, Pose
from facewire.models.infra.raster import Camera as ViewCamera
from facewire.models.landmarks import HELD_OUT, outer_eye_distance
from facewire.models.modelfile import ModelFileError, load_model
from facewire.models.regions import REGION_NAMES
from facewire.models.rig import Rig
from facewire.protocol.packet import (
    FRAME_DTYPE,
    QUANTISERS,
    Flag,
    Frame,
    decode_frames,
    encode_frames,
)
from facewire.sender.enroll.build import build_model

FX, FY, CX, CY, W, H = 640.0, 640.0, 319.5, 239.5, 640, 480
# Quantisation half-steps of protocol.packet: rotation-vector component (degrees),
# translation x/y and z (mm), residual coordinate (mm): 0.05, 0.25, 0.5, 0.125.
_HALF = {q.name: q.step / 2 for q in QUANTISERS}
HALF_ROTATION_DEG, HALF_SHIFT_XY, HALF_SHIFT_Z, HALF_RESIDUAL = (
    _HALF["rotation"], _HALF["shift_xy"], _HALF["shift_z"], _HALF["residuals"])
_OFF = 0.98  # off the grid by 98 % of a half-step: near the worst rounding, never a tie

# (rotation vector in degrees, translation mm, residual scale mm): frontal and neutral, then
# turned, tilted and expressive heads at webcam distances, on the quantisation grid; then
# two off it, every pose value nearly half a step from its nearest code (the residuals,
# drawn at random, are off the grid everywhere).
POSES = [
    ((0.0, 0.0, 0.0), (0.0, 0.0, -600.0), 0.0),
    ((-10.0, 25.0, 3.0), (20.0, -15.0, -650.0), 6.0),
    ((15.0, -8.0, 10.0), (-30.0, 10.0, -500.0), 6.0),
    ((5.0, -30.0, -6.0), (12.5, 40.0, -720.0), 4.0),
    ((-4.0, 12.0, 0.0), (-5.0, -5.0, -450.0), 8.0),
    ((-12.0 + _OFF * HALF_ROTATION_DEG, 18.3 - _OFF * HALF_ROTATION_DEG,
      4.1 + _OFF * HALF_ROTATION_DEG),
     (35.5 + _OFF * HALF_SHIFT_XY, -22.0 - _OFF * HALF_SHIFT_XY, -430.0 + _OFF * HALF_SHIFT_Z),
     8.0),
    ((8.7 - _OFF * HALF_ROTATION_DEG, -27.2 + _OFF * HALF_ROTATION_DEG,
      -9.9 - _OFF * HALF_ROTATION_DEG),
     (-41.0 - _OFF * HALF_SHIFT_XY, 17.5 + _OFF * HALF_SHIFT_XY, -580.0 - _OFF * HALF_SHIFT_Z),
     8.0),
]
OFF_GRID = [5, 6]


def _truth(rig: Rig, rotvec_deg, translation, residuals) -> np.ndarray:
    """Exact projection of the morphed model (scipy rotation, raster camera)."""
    rotation = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    camera = ViewCamera(Intrinsics(FX, FY, CX, CY, W, H), Pose(rotation, translation))
    return camera.project(rig.landmarks(rig.from_tangent(residuals)))


@pytest.fixture(scope="module")
def synthetic(rig: Rig) -> dict:
    """Known poses and residuals, encoded and decoded; the exact landmarks they describe."""
    rng = np.random.default_rng(4)
    sent = np.zeros(len(POSES), FRAME_DTYPE)
    truths, residuals = [], []
    for f, (rotvec_deg, translation, scale) in enumerate(POSES):
        r = rng.uniform(-scale, scale, (9, 2))
        sent[f] = Frame(seq=f, flags=Flag.FACE_PRESENT, rotation=np.radians(rotvec_deg),
                        translation=np.array(translation), residuals=r).to_record()
        truths.append(_truth(rig, rotvec_deg, translation, r))
        residuals.append(r)
    packets, clamped = encode_frames(sent)
    assert not clamped.any()
    decoded, errors = decode_frames(packets)
    assert all(e is None for e in errors)
    return {"sent": sent, "decoded": decoded, "truth": truths, "residuals": residuals}


def test_off_grid_poses_are_off_by_nearly_half_a_step(synthetic: dict) -> None:
    """The bound below is exercised: on the off-grid poses quantisation moves every pose
    value by nearly its half-step (and never more), on the others by nothing."""
    sent, decoded = synthetic["sent"], synthetic["decoded"]
    rotation = np.degrees(np.abs(decoded["rotation"] - sent["rotation"]))
    shift = np.abs(decoded["translation"] - sent["translation"])
    on_grid = [f for f in range(len(POSES)) if f not in OFF_GRID]
    assert rotation[on_grid].max() < 1e-3 and shift[on_grid].max() < 1e-3
    for error, half in ((rotation[OFF_GRID], HALF_ROTATION_DEG),
                        (shift[OFF_GRID, :2], HALF_SHIFT_XY),
                        (shift[OFF_GRID, 2], HALF_SHIFT_Z)):
        assert (error > 0.95 * half).all() and (error <= half + 1e-4).all(), (error, half)


def _quantisation_bound(rig: Rig, pose: tuple, residuals: np.ndarray,
                        truth: np.ndarray) -> float:
    """An upper bound of the held-out NME that quantisation alone can cause.

    Per landmark i at model position X_i and camera position C_i (depth d_i = -C_z):
    - a rotation-vector error of at most h = 0.05 deg per component is a rotation by at most
      sqrt(3) h (the exponential map does not stretch), moving X_i by <= sqrt(3) h |X_i|;
    - the translation moves it by <= 0.25 mm in x and y, 0.5 mm in depth;
    - each residual coordinate is off by <= 0.125 mm, so point k's displacement (orthonormal
      tangents) by <= 0.125 sqrt(2), and landmark i by <= sum_k |B[i, k]| 0.125 sqrt(2).
    The lateral (x, y) and depth parts of a camera-frame error, e_xy and e_z, move the
    projection f C_xy / d by at most f (e_xy + |C_xy| e_z / d) / (d - e_z).
    """
    rotvec_deg, translation, _ = pose
    x = rig.landmarks(rig.from_tangent(residuals)).astype(np.float64)
    rotation = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    cam = x @ rotation.T + np.asarray(translation)
    weights = np.abs(rig.weights[rig.mesh.landmarks]).sum(axis=1)
    shape = (math.sqrt(3) * math.radians(HALF_ROTATION_DEG) * np.linalg.norm(x, axis=1)
             + weights * HALF_RESIDUAL * math.sqrt(2))
    e_xy = shape + math.hypot(HALF_SHIFT_XY, HALF_SHIFT_XY)
    e_z = shape + HALF_SHIFT_Z
    d = -cam[:, 2]
    lateral = np.linalg.norm(cam[:, :2], axis=1)
    pixels = max(FX, FY) * (e_xy + lateral * e_z / d) / (d - e_z)
    return float(pixels[HELD_OUT].mean() / outer_eye_distance(truth))


def test_decoded_packets_rebuild_the_landmarks_within_quantisation(rig: Rig,
                                                                   synthetic: dict) -> None:
    result = geometry_nme(rig, (FX, FY, CX, CY), synthetic["decoded"], synthetic["truth"])
    bounds = np.array([_quantisation_bound(rig, pose, r, t) for pose, r, t in
                       zip(POSES, synthetic["residuals"], synthetic["truth"])])
    assert np.isfinite(result.heldout).all()
    assert (result.heldout <= bounds).all(), (result.heldout, bounds)
    assert bounds.max() < 0.011  # the bound is tight enough to mean something: < 1.1 %
    # Off the grid, quantisation costs a good part of the bound (measured: 0.59 % and 0.49 %
    # of the eye distance against bounds of 1.06 % and 1.02 %); on it, only the residuals'
    # rounding (at most 0.08 %).
    assert (result.heldout[OFF_GRID] > bounds[OFF_GRID] / 3).all()
    # The neutral frontal frame carries no expression: pose alone explains it as well.
    assert result.rigid_only[0] == pytest.approx(result.heldout[0], abs=1e-12)
    # Expressive frames: the residuals explain what the pose alone cannot.
    assert (result.rigid_only[1:] > 2 * bounds[1:]).all()
    on_grid = [f for f in range(1, len(POSES)) if f not in OFF_GRID]
    assert (result.heldout[on_grid] < result.rigid_only[on_grid] / 10).all()
    assert (result.heldout[OFF_GRID] < result.rigid_only[OFF_GRID] / 4).all()


def test_a_wrong_residual_sign_or_a_dropped_rotation_is_caught(rig: Rig,
                                                               synthetic: dict) -> None:
    bounds = np.array([_quantisation_bound(rig, pose, r, t) for pose, r, t in
                       zip(POSES, synthetic["residuals"], synthetic["truth"])])
    flipped = synthetic["decoded"].copy()
    flipped["residuals"] *= -1
    wrong = geometry_nme(rig, (FX, FY, CX, CY), flipped, synthetic["truth"]).heldout
    assert (wrong[1:] > 3 * bounds[1:]).all(), (wrong, bounds)
    unrotated = synthetic["decoded"].copy()
    unrotated["rotation"] = 0.0
    wrong = geometry_nme(rig, (FX, FY, CX, CY), unrotated, synthetic["truth"]).heldout
    assert wrong[0] <= bounds[0]  # the frontal frame had no rotation to drop
    assert (wrong[1:] > 0.03).all(), wrong  # > 3 % of the eye distance


def test_frames_without_a_face_or_a_pose_are_not_measured(rig: Rig, synthetic: dict) -> None:
    decoded = synthetic["decoded"].copy()
    decoded["flags"][1] = Flag.TRACKING_LOST  # last good pose, no face this frame
    decoded["flags"][3] = Flag.FACE_PRESENT | Flag.TRACKING_LOST  # a face, its pose rejected
    tracked = list(synthetic["truth"])
    tracked[2] = None
    result = geometry_nme(rig, (FX, FY, CX, CY), decoded, tracked)
    assert np.isnan(result.heldout[[1, 2, 3]]).all()
    assert np.isnan(result.rigid_only[[1, 2, 3]]).all()
    assert np.isfinite(result.heldout[[0, 4]]).all()
    # A list of Frames gives the same as the record array.
    frames = [Frame.from_record(r) for r in decoded]
    again = geometry_nme(rig, (FX, FY, CX, CY), frames, tracked)
    np.testing.assert_array_equal(again.heldout, result.heldout)


def test_project_landmarks_matches_the_raster_camera(rig: Rig) -> None:
    rotvec_deg, translation, _ = POSES[1]
    got = project_landmarks(rig, (FX, FY, CX, CY), np.radians(rotvec_deg),
                            np.array(translation), None)
    np.testing.assert_allclose(got, _truth(rig, rotvec_deg, translation, np.zeros((9, 2))),
                               atol=1e-3)
    with pytest.raises(ValueError, match="behind the camera"):
        project_landmarks(rig, (FX, FY, CX, CY), np.zeros(3), np.array([0.0, 0.0, 600.0]),
                          None)


def test_bad_inputs_are_refused(rig: Rig, synthetic: dict) -> None:
    with pytest.raises(ValueError, match=f"tracked: 4 entries for {len(POSES)}"):
        geometry_nme(rig, (FX, FY, CX, CY), synthetic["decoded"], synthetic["truth"][:4])
    with pytest.raises(ValueError, match=r"tracked\[0\]: expected shape \(68, 2\)"):
        geometry_nme(rig, (FX, FY, CX, CY), synthetic["decoded"],
                     [np.zeros((5, 2))] + synthetic["truth"][1:])
    with pytest.raises(ValueError, match="camera"):
        geometry_nme(rig, (FX, -FY, CX, CY), synthetic["decoded"], synthetic["truth"])
    with pytest.raises(ValueError, match="decoded"):
        geometry_nme(rig, (FX, FY, CX, CY), np.zeros(len(POSES)), synthetic["truth"])


# --- the real benchmark -------------------------------------------------------------------

@pytest.fixture(scope="module")
def lp_d0_model(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model of lp_d0 built from its frames 0:40 (about 6 s), appearance included."""
    out = tmp_path_factory.mktemp("quality") / "lp_d0.fwm"
    build_model(shared_data / "video" / "lp_d0.mp4", out, frames=slice(0, 40))
    return out


def test_real_video_held_out_frames(lp_d0_model: Path, shared_data: Path,
                                    tmp_path: Path) -> None:
    plot = tmp_path / "nme.png"
    r, out = quality(lp_d0_model, shared_data / "video" / "lp_d0.mp4", frames=slice(40, 78),
                     plot=plot)
    assert r["frames"] == 38
    assert r["face_frames"] == r["tracked_frames"] >= 35
    assert r["measured_frames"] == r["face_frames"] - r["pose_lost_frames"] >= 35
    assert r["payload_kbps"] == pytest.approx(43 * 8 * 30 / 1000)
    for key in ("nme_heldout_mean", "nme_heldout_median", "nme_heldout_p95",
                "nme_rigid_only_mean"):
        assert isinstance(r[key], float) and math.isfinite(r[key]) and r[key] > 0, key
    assert r["nme_heldout_median"] <= r["nme_heldout_p95"]
    assert r["nme_heldout_mean"] < r["nme_rigid_only_mean"]
    assert r["met"]["below_rigid_only"]
    assert r["nme_heldout_mean"] <= TARGET_NME_HELDOUT == 3.0  # the docstring's target (2.58)
    assert r["met"]["nme_heldout"]
    # appearance fidelity: our rendering and x264 measured in the same face boxes
    for key in ("face_ssim_mean", "face_psnr_mean", "h264_kbps", "h264_face_ssim_mean",
                "h264_face_psnr_mean"):
        assert isinstance(r[key], float) and math.isfinite(r[key]), key
    assert 0.2 < r["face_ssim_mean"] < 1 and 0.2 < r["h264_face_ssim_mean"] < 1
    assert r["met"]["face_ssim_above_h264"] == (r["face_ssim_mean"] > r["h264_face_ssim_mean"])
    # what the viewer sees: the tracker finds our rendered face on every measured frame and
    # its points lie near the real frame's (measured: 1.94 %; x264 at its floor 2.62 %)
    assert r["real_face_missing"] == 0 and r["render_face_missing"] == 0
    assert r["render_nme_frames"] == r["measured_frames"]
    for key in ("render_nme_mean", "render_nme_mouth", "render_nme_eyes", "render_nme_brows"):
        assert isinstance(r[key], float) and 0 < r[key] < 6, key
    assert r["h264_render_nme_frames"] + r["h264_face_missing"] == r["render_nme_frames"]
    assert r["met"]["render_nme_at_most_h264"] == (
        r["render_face_missing"] <= r["h264_face_missing"]
        and (r["h264_render_nme_mean"] is None
             or r["render_nme_mean"] <= r["h264_render_nme_mean"]))
    assert 0 < r["nme_unweighted_mean"] and r["overlap_frames"] == 0
    # steadiness (bench.jitter): the still pairs judged and the rendering's jitter over them
    assert r["jitter_still_frames"] >= 10 and isinstance(r["render_jitter_ratio"], float)
    assert r["jitter_still_below"] == 0.005 and r["jitter_real_motion"] > 0
    assert r["render_jitter_ratio"] == pytest.approx(
        r["jitter_render_motion"] / r["jitter_real_motion"], rel=0.01)
    assert r["filter_lag_frames"] is None or abs(r["filter_lag_frames"]) <= 5
    assert r["model_source"]["video"] == "lp_d0.mp4"
    assert (r["model_source"]["start"], r["model_source"]["stop"]) == (0, 40)
    text = "\n".join(out)
    q_plot, face_plot = tmp_path / "nme-q.png", tmp_path / "nme-face.png"
    assert text == format_quality(r) + f"\nplot: {plot}\nplot: {q_plot}\nplot: {face_plot}"
    assert face_plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"mean {r['nme_heldout_mean']:.2f} %" in text
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert q_plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # appearance: every region's decoded Q within its layers, and the eyes' Q follows the
    # cues that ordered their states (on frames the model was not built from)
    regions = {q["name"]: q for q in r["q_regions"]}
    assert [q["name"] for q in r["q_regions"]] == list(REGION_NAMES)
    for name, q in regions.items():
        assert 0 <= q["min"] <= q["mean"] <= q["max"] <= q["layers"] - 1, name
    assert regions["eyeball_left"]["cue_r"] > 0.5
    assert "q_reference" not in r  # only with --reference


def test_overlap_with_the_build_frames_through_the_cli(lp_d0_model: Path, shared_data: Path,
                                                      tmp_path: Path) -> None:
    """The model was built from lp_d0's frames 0:40: scoring 30:45 is refused in one line
    (exit 2) before any work; with --allow-overlap it runs and says so; model info shows the
    range; another video with the model's frame numbers is not refused."""
    video = shared_data / "video" / "lp_d0.mp4"
    facewire = str(Path(sys.executable).with_name("facewire"))

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([facewire, *args], capture_output=True, text=True, timeout=300)

    refused = run("bench", "quality", "--model", str(lp_d0_model), "--source", str(video),
                  "--frames", "30:45", "--json")
    assert refused.returncode == 2 and refused.stdout == ""
    assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith(f"facewire: {video}: frames 30:45 include 10 of the "
                                     f"frames 0:40 the model was built from")
    assert "--allow-overlap" in refused.stderr
    allowed = run("bench", "quality", "--model", str(lp_d0_model), "--source", str(video),
                  "--frames", "36:44", "--allow-overlap", "--json")
    assert allowed.returncode == 0, allowed.stderr
    r = json.loads(allowed.stdout.splitlines()[-1])
    assert r["overlap_frames"] == 4 and r["frames"] == 8
    assert "OVERLAP: 4 of these frames are among the model's build frames 0:40" in allowed.stdout
    info = run("model", "info", str(lp_d0_model), "--json")
    assert info.returncode == 0
    assert "built from: lp_d0.mp4 frames 0:40" in info.stdout
    source = json.loads(info.stdout.splitlines()[-1])["source"]
    assert (source["video"], source["start"], source["stop"]) == ("lp_d0.mp4", 0, 40)
    assert source["bytes"] == video.stat().st_size
    # The same frame numbers of another file are not the model's frames.
    model = load_model(lp_d0_model)
    other = shared_data / "video" / "lp_d18.mp4"
    assert check_overlap(model, other, slice(0, 20)) == 0
    assert check_overlap(model, video, slice(40, None)) == 0
    assert check_overlap(model, video, slice(0, None), allow_overlap=True) == 40
    with pytest.raises(OverlapError, match="include 1 of the frames 0:40"):
        check_overlap(model, video, slice(39, 50))


@pytest.fixture(scope="module")
def openface_default(shared_data: Path, tmp_path_factory: pytest.TempPathFactory
                     ) -> tuple[Path, Path, dict, list[str]]:
    """Issue 5's measurement: openface_default, model from its first 6 s (90 frames), measured
    on the rest against OpenFace's action units: (model, video, result, report lines)."""
    video = shared_data / "video" / "openface_default.wmv"
    model = tmp_path_factory.mktemp("openface_default") / "od.fwm"
    build_model(video, model, frames=slice(0, 90))
    reference = shared_data / "openface" / "openface_default.openface.csv"
    r, out = quality(model, video, frames=slice(90, None), reference=reference)
    return model, video, r, out


def test_agreement_with_openface(openface_default: tuple, tmp_path: Path) -> None:
    """The targets of bench.quality's docstring: eyelid r >= 0.6 and blink F1 >= 0.7
    (measured: 0.78 and 0.80)."""
    model, video, r, out = openface_default
    a = r["q_reference"]
    assert a["frames_compared"] >= 190
    assert a["eyelid_au45"]["r"] >= TARGET_Q["eyelid_au45"] == 0.6
    assert a["blink_f1"] >= TARGET_Q["blink_f1"] == 0.7
    assert a["blink_events_reference"] == 7
    assert r["met"]["eyelid_au45"] and r["met"]["blink_f1"]
    assert any(line.startswith("blinks: F1") for line in out)
    with pytest.raises(OpenFaceError, match="absent.csv"):
        quality(model, video, frames=slice(90, 100), reference=tmp_path / "absent.csv")


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="measured r = -0.17 against OpenFace's AU01 + AU02: on these "
                   "frames the forehead's Q does not follow even the brow-raise cue its "
                   "states were ordered by at enrollment (cue r 0.09), so the forehead "
                   "classifier, not the reference, misses; strict, so that a fix shows")
def test_forehead_agreement_with_openface(openface_default: tuple) -> None:
    """The forehead target of bench.quality's docstring: r >= 0.4 with AU01 + AU02."""
    _, _, r, _ = openface_default
    forehead = r["q_reference"]["forehead_au01_au02"]["r"]
    assert forehead is not None and forehead >= TARGET_Q["forehead_au01_au02"] == 0.4


def test_missing_or_corrupt_model(tmp_path: Path) -> None:
    missing = tmp_path / "nobody.fwm"
    with pytest.raises(ModelFileError, match="nobody.fwm"):
        quality(missing, tmp_path / "any.mp4")
    corrupt = tmp_path / "corrupt.fwm"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ModelFileError, match="corrupt.fwm"):
        quality(corrupt, tmp_path / "any.mp4")


def test_unreadable_video_or_no_face(generic_model: Path, grey_video, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="absent.mp4"):
        quality(generic_model, tmp_path / "absent.mp4")
    text = tmp_path / "notes.mp4"
    text.write_text("not a video")
    with pytest.raises(ValueError, match="notes.mp4"):
        quality(generic_model, text)
    grey = grey_video()
    with pytest.raises(NoFaceError, match="grey.mp4: no face"):
        quality(generic_model, grey)
