"""`facewire model build PHOTO`: a model from one real photo (LFPW), end to end through the
command line, and its bad inputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from facewire.cli import main
from facewire.models.modelfile import load_model
from facewire.receiver.render import FaceRenderer
from facewire.sender.enroll.build import PREVIEW_HEIGHT, is_photo, preview_cameras


@pytest.mark.parametrize("image", ["image_0001.png", "image_0010.png"])
def test_photo_model(shared_data, tmp_path, capsys, image):
    out = tmp_path / "photo.fwm"
    assert main(["model", "build", str(shared_data / "images" / image), "-o", str(out),
                 "--json"]) == 0
    text = capsys.readouterr().out
    summary = json.loads(text.strip().splitlines()[-1])
    # one frame, the neutral only: no regions, no layers
    assert (summary["frames"], summary["face_frames"], summary["neutral_frame"]) == (1, 1, 0)
    assert (summary["regions"], summary["layers"]) == (0, 0)
    assert summary["bytes"] == out.stat().st_size

    assert main(["model", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["sha256"] == summary["sha256"] and info["source_video"] == image
    assert info["regions"] == 0

    preview = cv2.imread(str(out.with_name("photo.preview.png")))
    assert preview is not None and preview.shape[0] >= PREVIEW_HEIGHT
    # the receiver's own renderer draws the model: the same face as the preview's front view
    model = load_model(out)
    camera = preview_cameras(model.mesh)[0]
    with FaceRenderer(model, PREVIEW_HEIGHT, PREVIEW_HEIGHT, background=(40, 40, 40)) as r:
        rgb = r.render(model.mesh.vertices.astype(np.float32), np.zeros(0, np.float32), camera)
    front = preview[:PREVIEW_HEIGHT, PREVIEW_HEIGHT:2 * PREVIEW_HEIGHT, ::-1].astype(np.float32)
    face = slice(PREVIEW_HEIGHT // 3, 2 * PREVIEW_HEIGHT // 3)
    centre = rgb[face, face].reshape(-1, 3).astype(np.float32)
    assert centre[:, 0].mean() > centre[:, 2].mean() + 10  # skin: red over blue
    assert np.abs(rgb.astype(np.float32) - front)[face, face].mean() < 6.0


def test_photo_suffixes():
    for name in ("a.jpg", "b.JPEG", "c.png", "d.bmp", "e.webp"):
        assert is_photo(name)
    assert not is_photo("clip.mp4") and not is_photo("photo")


def test_photo_without_face(tmp_path, capsys):
    wall = tmp_path / "wall.jpg"
    rng = np.random.default_rng(3)
    cv2.imwrite(str(wall), cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), np.uint8),
                                            (9, 9), 0))
    assert main(["model", "build", str(wall), "-o", str(tmp_path / "m.fwm")]) == 2
    err = _errors(capsys.readouterr().err)
    assert len(err) == 1 and "wall.jpg" in err[0] and "no face" in err[0]
    assert not (tmp_path / "m.fwm").exists()


def test_unreadable_photo(tmp_path, capsys):
    bad = tmp_path / "notes.png"
    bad.write_text("this is not an image")
    assert main(["model", "build", str(bad), "-o", str(tmp_path / "m.fwm")]) == 2
    err = _errors(capsys.readouterr().err)
    assert len(err) == 1 and "notes.png" in err[0] and "Traceback" not in err[0]
    missing = tmp_path / "nobody.jpg"
    assert main(["model", "build", str(missing), "-o", str(tmp_path / "m.fwm")]) == 2
    assert "nobody.jpg" in capsys.readouterr().err


def test_photo_refuses_a_frame_range(shared_data, tmp_path, capsys):
    photo = shared_data / "images" / "image_0001.png"
    assert main(["model", "build", str(photo), "-o", str(tmp_path / "m.fwm"),
                 "--frames", "0:5"]) == 2
    assert "--frames" in capsys.readouterr().err


def _errors(stderr: str) -> list[str]:
    """The error lines of stderr (the progress bar's lines aside): ``facewire: ...``."""
    lines = [line.strip() for line in stderr.replace("\r", "\n").splitlines()]
    assert "Traceback" not in stderr
    return [line for line in lines if line.startswith("facewire:")]


def _green(texture: np.ndarray) -> np.ndarray:
    """(H, W) bool: the texels of an RGB texture that are the painted green."""
    t = texture.astype(np.int16)
    return (t[..., 1] > 180) & (t[..., 0] < 90) & (t[..., 2] < 90)


def test_a_photos_texture_takes_no_colour_from_beside_the_face(shared_data, tmp_path):
    """The generic head is wider than the face: its sides must not take what the photo shows
    beside the cheek (build_photo's photo_face_texels). Everything beside and below the jaw
    contour is painted green; the texture has none of it."""
    from facewire.sender.enroll.build import build_photo
    from facewire.sender.tracker import LandmarkTracker

    image = cv2.imread(str(shared_data / "images" / "image_0001.png"), cv2.IMREAD_COLOR)
    points = LandmarkTracker().track(image).points
    assert points is not None
    up = points[17:27].mean(axis=0) - points[8]
    reach = 4.0 * float(sum(image.shape[:2])) * up / np.linalg.norm(up)
    face = np.zeros(image.shape[:2], np.uint8)
    polygon = np.concatenate([points[0:17], [points[16] + reach, points[0] + reach]])
    cv2.fillPoly(face, [np.rint(polygon).astype(np.int32)], 1)
    painted = image.copy()
    painted[face == 0] = (0, 255, 0)
    build = build_photo(painted, tmp_path / "painted.fwm")
    texture = build.model.texture
    assert not _green(texture).any(), int(_green(texture).sum())
    # the painted photo's face did make the texture (skin: red over blue at its middle)
    h, w = texture.shape[:2]
    middle = texture[h // 3:h // 2, w // 4:w // 2].reshape(-1, 3).astype(np.float32)
    assert middle[:, 0].mean() > middle[:, 2].mean() + 10
