"""`facewire model build / info / export` end to end on real video, and their bad inputs."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest

from facewire.cli import main
from facewire.models.gltf import read_glb
from facewire.models.head import generic_head
from facewire.models.modelfile import load_model
from facewire.models.regions import REGION_NAMES, spec
from facewire.receiver.views import VIEW_KINDS, virtual_view
from facewire.sender.classify import RegionClassifiers
from facewire.sender.enroll.build import (
    COVERAGE_ROW_HEIGHT,
    PREVIEW_HEIGHT,
    REGION_ROW_HEIGHT,
    TEXTURE_SIZE,
    build_model,
    preview_cameras,
)


@pytest.fixture(scope="module")
def built(shared_data, tmp_path_factory):
    """lp_d0.mp4 (78 frames: gaze, smile, closed eyes) built through the command line."""
    out = tmp_path_factory.mktemp("build") / "lp.fwm"
    return out, shared_data / "video" / "lp_d0.mp4"


def test_build_info_export(built, capsys):
    out, video = built
    assert main(["model", "build", str(video), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    head = generic_head()
    assert {"vertices", "triangles", "regions", "layers", "bytes", "sha256"} <= summary.keys()
    assert (summary["vertices"], summary["triangles"]) == (len(head.vertices),
                                                           len(head.triangles))
    assert summary["bytes"] == out.stat().st_size
    assert out.stat().st_mode & 0o777 == 0o600  # a person's face: the owner's only
    assert summary["face_frames"] >= 70
    assert summary["occluded_enrollment_frames"] == 0  # no hand on lp_d0's face
    model = load_model(out)
    assert model.sha256 == summary["sha256"]
    assert model.texture.shape == (*TEXTURE_SIZE, 3)
    # the texture is filled: no black texel anywhere, the face is skin-coloured, not grey
    assert model.texture.max(axis=2).min() > 0
    # appearance: every region of models.regions, its states from distinct frames, and the
    # templates are what the sender samples, so each classifies as its own state
    assert [r.name for r in model.regions] == list(REGION_NAMES)
    assert summary["regions"] == len(REGION_NAMES) and summary["layers"] == sum(
        len(r.layers) for r in model.regions)
    classifiers = RegionClassifiers([r.templates for r in model.regions])
    for r, region in enumerate(model.regions):
        report = summary["appearance"][region.name]
        assert len(set(report["frames"])) == len(region.layers) == spec(region.name).layers
        samples = np.zeros((len(model.regions), 1, 16, 16), np.float32)
        for j, template in enumerate(region.templates):
            samples[r, 0] = template
            assert classifiers.classify(samples).q[r] == j
        # an eyelid's open states, up to its rest state, are transparent: the gaze shows
        assert region.opacity == tuple(
            0.0 if region.name.startswith("eyelid") and j <= region.rest else 1.0
            for j in range(len(region.layers)))
        assert 0 <= region.rest <= len(region.layers) - 1
        assert report["rest"] == round(region.rest, 4)
    closed = summary["appearance"]["eyelid_left"]["cue"]
    assert closed[-1] > closed[0] + 0.05  # lp_d0 closes its eyes: the last state is closed
    preview = cv2.imread(str(out.with_name("lp.preview.png")))
    assert preview.shape == (PREVIEW_HEIGHT + len(REGION_NAMES) * REGION_ROW_HEIGHT
                             + COVERAGE_ROW_HEIGHT, 3 * PREVIEW_HEIGHT, 3)
    front = preview[:, PREVIEW_HEIGHT:2 * PREVIEW_HEIGHT]
    face = front[PREVIEW_HEIGHT // 3:2 * PREVIEW_HEIGHT // 3,
                 PREVIEW_HEIGHT // 3:2 * PREVIEW_HEIGHT // 3].reshape(-1, 3).mean(axis=0)
    assert face[2] > face[0] + 10  # red over blue: skin seen, not background or grey

    assert main(["model", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["sha256"] == summary["sha256"] and info["neutral_frame"] == summary[
        "neutral_frame"]
    # the frames it was built from: all 78 of lp_d0, the file known by its bytes
    source = {"video": "lp_d0.mp4", "bytes": video.stat().st_size,
              "sha256": hashlib.sha256(video.read_bytes()).hexdigest(), "start": 0, "stop": 78}
    assert summary["source"] == info["source"] == source

    glb = out.with_suffix(".glb")
    assert main(["model", "export", str(out), "-o", str(glb)]) == 0
    exported = read_glb(glb)
    np.testing.assert_allclose(exported.positions, model.mesh.vertices, atol=1e-3)
    assert exported.texture is not None and exported.texture.shape == model.texture.shape


def test_unreadable_video(tmp_path, capsys):
    bad = tmp_path / "notes.mp4"
    bad.write_text("this is not a video")
    assert main(["model", "build", str(bad), "-o", str(tmp_path / "m.fwm")]) == 2
    err = capsys.readouterr().err
    assert "notes.mp4" in err and "Traceback" not in err
    assert not (tmp_path / "m.fwm").exists()


def test_video_without_face(grey_video, tmp_path, capsys):
    video = grey_video("wall.mp4", frames=20)
    assert main(["model", "build", str(video), "-o", str(tmp_path / "m.fwm")]) == 2
    err = capsys.readouterr().err
    assert "wall.mp4" in err and "no face" in err
    assert not (tmp_path / "m.fwm").exists()


def test_too_short_for_a_neutral_frame(shared_data, tmp_path, capsys):
    video = shared_data / "video" / "lp_d0.mp4"
    assert main(["model", "build", str(video), "-o", str(tmp_path / "m.fwm"),
                 "--frames", "0:3"]) == 2
    err = capsys.readouterr().err
    assert "lp_d0.mp4" in err and "Traceback" not in err
    assert not (tmp_path / "m.fwm").exists()


def test_bad_frame_range(shared_data, tmp_path, capsys):
    video = shared_data / "video" / "lp_d0.mp4"
    assert main(["model", "build", str(video), "-o", str(tmp_path / "m.fwm"),
                 "--frames", "9:2"]) == 2
    assert "--frames" in capsys.readouterr().err


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_corrupt_model_refused(built, tmp_path, capsys, damage):
    out, video = built
    if not out.exists():
        build_model(video, out, appearance=False)
    data = bytearray(out.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 3] ^= 0xFF
    bad = tmp_path / "bad.fwm"
    bad.write_bytes(bytes(data))
    for argv in (["model", "info", str(bad)], ["model", "export", str(bad), "-o",
                                                str(tmp_path / "x.glb")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "bad.fwm" in err and "Traceback" not in err
    assert not (tmp_path / "x.glb").exists()


def test_preview_frames_the_head_as_the_receiver_views():
    """One framing (models.framing): the preview's front and three-quarter cameras are the
    receiver's unturned virtual views at the preview's size."""
    mesh = generic_head()
    for preview, kind in zip(preview_cameras(mesh), VIEW_KINDS, strict=True):
        view = virtual_view(kind, mesh, np.zeros(3), PREVIEW_HEIGHT, PREVIEW_HEIGHT)
        assert preview.intrinsics == view.intrinsics
        np.testing.assert_allclose(preview.pose.rotation, view.pose.rotation, atol=1e-12)
        np.testing.assert_allclose(preview.pose.translation, view.pose.translation, atol=1e-9)
