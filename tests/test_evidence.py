"""Clean evidence for the model: robust fusion of views, and a real occluder kept out.

The reproduction of issue 16's first failure (``bench.occluded``): a real clip with a real
patch (dark hair from hamilton_short) pasted over the mouth in many of its first frames,
written as H.264; the model built from it must not show the patch anywhere over the mouth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.infra.raster import Camera, MeshRenderer, orbit_pose
from facewire.models.mesh import Mesh
from facewire.sender.enroll.fusion import project_views
from facewire.sender.enroll.texture import uv_surface

IMG = 200
TEX = (128, 256)


def _ball() -> Mesh:
    """A UV sphere of radius 60 mm at the origin, u around, v from pole to pole."""
    n_lat, n_lon = 24, 48
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n_lat + 1),
                             np.linspace(-np.pi, np.pi, n_lon + 1), indexing="ij")
    unit = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)],
                    -1).reshape(-1, 3)
    uv = np.stack([0.02 + 0.96 * (phi + np.pi) / (2 * np.pi), 0.98 - 0.96 * theta / np.pi],
                  -1).reshape(-1, 2)
    idx = np.arange(len(unit)).reshape(n_lat + 1, n_lon + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    triangles = np.concatenate([np.stack([a, c, d], -1)[:-1].reshape(-1, 3),
                                np.stack([a, d, b], -1)[1:].reshape(-1, 3)]).astype(np.int32)
    return Mesh((60 * unit).astype(np.float32), triangles, uv.astype(np.float32),
                np.zeros(len(triangles), np.uint8), np.arange(68, dtype=np.int32),
                np.arange(13, dtype=np.int32))


def test_an_outlying_view_gives_nothing_even_when_it_is_the_first():
    """Five views of a painted ball; the first (the reference the others' exposure is matched
    to, where it takes part) has a black disc over the middle of the ball, as a hand over a
    mouth. The fused texture there is the others' colour: within 4 grey levels of the
    texture built without the disc, where a mean of the views would be some 27 levels
    darker (main's weighted mean, 917b2b3: 38 levels off; this test failed there)."""
    mesh = _ball()
    rows, cols = np.mgrid[0:TEX[0], 0:TEX[1]].astype(np.float64)
    u, v = (cols + 0.5) / TEX[1], 1 - (rows + 0.5) / TEX[0]
    paint = np.clip(np.rint(np.stack([60 + 150 * u, 60 + 150 * v, 150 + 0 * u], -1)), 0,
                    255).astype(np.uint8)
    cameras = [Camera.virtual(IMG, IMG, orbit_pose(yaw, pitch, 350.0), fov_y_deg=30.0)
               for yaw, pitch in ((0, 0), (8, 0), (-8, 0), (0, 8), (0, -8))]
    with MeshRenderer(IMG, IMG) as renderer:
        renderer.set_mesh(len(mesh.vertices), mesh.triangles, mesh.uv)
        renderer.set_texture(paint)
        images = [renderer.render(mesh.vertices, cam)[..., ::-1].copy() for cam in cameras]
    surface = uv_surface(mesh, TEX)
    clean, clean_w = project_views(mesh, surface, list(zip(images, cameras)))
    occluded = images[0].copy()
    cv2.circle(occluded, (IMG // 2, IMG // 2), 22, (18, 14, 12), -1)
    views = [(occluded, cameras[0]), *zip(images[1:], cameras[1:])]
    fused, fused_w = project_views(mesh, surface, views)
    # The texels under the disc: those the first view alone would see darkened.
    alone, _ = project_views(mesh, surface, [(occluded, cameras[0])])
    disc = (clean_w > 0) & (fused_w > 0) & (alone.astype(int).sum(axis=2) < 3 * 40)
    assert disc.sum() > 100
    error = np.abs(fused[disc].astype(int) - clean[disc].astype(int)).mean()
    assert error < 4.0, error
    mean_like = 0.2 * alone[disc].astype(int) + 0.8 * clean[disc].astype(int)
    assert np.abs(mean_like - clean[disc]).mean() > 20  # what a plain mean would have shown


def _dark_share(image: np.ndarray) -> float:
    """The fraction of an RGB image's pixels darker than the occluder's bound (luma < 40)."""
    luma = image.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    return float((luma < 40).mean())


@pytest.fixture(scope="module")
def occluded_models(shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    """Models of lp_d3 frames 0:90, from the clean frames and from the occluded ones."""
    from facewire.bench.occluded import occlude
    from facewire.models.modelfile import load_model
    from facewire.sender.enroll.build import build_model

    work = tmp_path_factory.mktemp("occluded")
    clip = shared_data / "video" / "lp_d3.mp4"
    made = occlude(clip, work / "occluded.mp4", slice(0, 90))
    build_model(clip, work / "clean.fwm", slice(0, 90))
    built = build_model(made.path, work / "occluded.fwm")
    return made, load_model(work / "clean.fwm"), load_model(work / "occluded.fwm"), built


def test_the_reproduction_is_real_and_deterministic(occluded_models):
    from facewire.bench.occluded import choose_frames

    made, _, _, _ = occluded_models
    chosen = choose_frames(90, 0.6, 0.25, 16)
    assert np.array_equal(chosen, choose_frames(90, 0.6, 0.25, 16))
    assert set(made.occluded) <= set(np.flatnonzero(chosen))
    assert 0.3 * made.frames < len(made.occluded) < 0.7 * made.frames  # many, not all
    assert max(made.occluded) < 0.6 * made.frames  # only in the first part


def _mouth_area(mesh: Mesh, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The texels of the UV box of the mouth's landmark vertices 48-67, grown by a quarter of
    its size on every side."""
    uv = mesh.uv[mesh.landmarks[48:68]].astype(np.float64)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    (u0, v0), (u1, v1) = lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo)
    return (slice(int((1 - v1) * shape[0]), int(np.ceil((1 - v0) * shape[0]))),
            slice(int(u0 * shape[1]), int(np.ceil(u1 * shape[1]))))


def test_no_texture_over_the_mouth_carries_the_occluder(occluded_models):
    """The base texture around the mouth is within 12 levels (mean absolute, RGB) of the
    clean model's, and no mouth layer is darker than the clean model's darkest by more
    than 10 % of its texels. On main (917b2b3) three of the mouth's four states were the
    patch itself (the tracker reads a dark patch as an open mouth): 95 %, 94 % and 83 % dark
    texels against 31 % at most for the clean model, and this test failed."""
    _, clean, occluded, _ = occluded_models
    area = _mouth_area(clean.mesh, clean.texture.shape[:2])
    difference = np.abs(occluded.texture[area].astype(int) - clean.texture[area].astype(int))
    assert difference.mean() < 12.0, difference.mean()
    mouth = {m.name: m for m in clean.regions}["mouth"], \
        {m.name: m for m in occluded.regions}["mouth"]
    clean_dark = max(_dark_share(layer) for layer in mouth[0].layers)
    occluded_dark = [_dark_share(layer) for layer in mouth[1].layers]
    assert max(occluded_dark) < clean_dark + 0.10, (occluded_dark, clean_dark)


def test_the_build_says_which_frames_it_kept_out(occluded_models):
    """The occluded frames are found by the ring around the mouth (``sender.enroll.evidence``,
    4): the mouth takes none of them, and the report counts them; the base texture's views
    are listed, the neutral first."""
    made, _, _, built = occluded_models
    mouth = built.appearance["mouth"]
    assert not set(mouth["frames"]) & set(made.occluded)
    assert mouth["occluded_frames"] >= 0.8 * len(made.occluded)
    evidence = built.summary()["texture_evidence"]
    assert evidence["views"][0] == built.model.info.neutral_frame
    assert built.model.info.neutral_frame not in made.occluded
    assert 3 <= len(evidence["views"]) <= 9


def test_a_blurred_face_box_scores_less_sharp():
    """``sharpness``: the variance of the Laplacian in the landmarks' box falls with blur,
    and does not depend on the face's size in the frame (the box is resized first)."""
    from facewire.sender.clean import sharpness

    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (60, 60, 3), dtype=np.uint8)
    texture = cv2.resize(texture, (240, 240), interpolation=cv2.INTER_CUBIC)
    frame = np.full((400, 400, 3), 128, np.uint8)
    frame[80:320, 80:320] = texture
    points = np.array([[80 + 240 * a, 80 + 240 * b] for a, b in
                       rng.random((68, 2))], np.float64)
    points[0], points[1] = (80, 80), (319, 319)
    sharp = sharpness(frame, points)
    blurred = sharpness(cv2.GaussianBlur(frame, (0, 0), 3.0), points)
    assert blurred < 0.3 * sharp
    half = cv2.resize(frame, (200, 200), interpolation=cv2.INTER_AREA)
    assert 0.5 < sharpness(half, points / 2) / sharp < 2.0


@pytest.fixture(scope="module")
def occluded_eye(shared_data: Path, occluded_models, tmp_path_factory: pytest.TempPathFactory):
    """lp_d3 frames 0:90 with the dark patch over the right eye (``bench.occluded --over
    right_eye``), and the layers enrolled from it on the clean model of the same frames."""
    from facewire.bench.occluded import occlude
    from facewire.sender.enroll.layers import enroll_regions

    work = tmp_path_factory.mktemp("occluded_eye")
    made = occlude(shared_data / "video" / "lp_d3.mp4", work / "eye.mp4", slice(0, 90),
                   over="right_eye")
    return made, enroll_regions(occluded_models[1], made.path)


def test_an_occluded_eye_gives_its_layers_nothing(occluded_eye):
    """The right eye's eyelid and eyeball take no patched frame (on main, 9691a01, where
    the eyes were not judged, they did), the ring test finds most patched frames and says
    so in the region's counts, and the left eye, not patched, loses few frames."""
    made, enrolled = occluded_eye
    patched = set(made.occluded)
    for name in ("eyelid_right", "eyeball_right"):
        frames = enrolled.usage[name]
        assert frames.used and not set(frames.used) & patched, (name, frames)
        assert frames.rejected.get("occluded", 0) >= 0.8 * len(patched), (name, frames)
    for name in ("eyelid_left", "eyeball_left"):
        assert enrolled.usage[name].rejected.get("occluded", 0) <= 0.1 * made.frames
    assert enrolled.usage["mouth"].rejected.get("occluded", 0) <= 0.1 * made.frames


def test_a_region_with_no_clean_frame_draws_the_base_texture(shared_data: Path,
                                                               occluded_models, tmp_path):
    """Every frame of lp_d3 0:30 with the patch over the mouth, enrolled on the model of the
    clean frames: no frame is clean for the mouth. The enrollment still succeeds; the mouth
    uses no frame, says why, and its layers are transparent (the receiver draws the base
    texture there); the eyes keep their layers. On main (9691a01) the mouth fell back to
    the occluded frames."""
    from facewire.bench.occluded import occlude
    from facewire.sender.enroll.layers import enroll_regions
    from facewire.sender.enroll.usage import usage_line

    made = occlude(shared_data / "video" / "lp_d3.mp4", tmp_path / "all.mp4", slice(0, 30),
                   part=1.0, gap=0.0)
    assert len(made.occluded) == 30
    enrolled = enroll_regions(occluded_models[1], made.path)
    frames = enrolled.usage["mouth"]
    assert frames.used == () and frames.rejected == {"occluded": 30}
    assert usage_line(frames).startswith("no clean frame of 30")
    mouth = {r.name: r for r in enrolled.regions}["mouth"]
    assert all(o == 0.0 for o in mouth.opacity)
    assert enrolled.report["mouth"]["frames"] == []
    assert all(enrolled.usage[name].used for name in ("eyelid_left", "eyelid_right"))
