"""Offscreen rendering through EGL: projection to the pixel, unlit textures, depth, real scan."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facewire.models.geometry import Intrinsics, Pose
from facewire.models.gltf import read_glb
from facewire.models.infra.egl import EGLUnavailable
from facewire.models.infra.raster import Camera, MeshRenderer, RenderError, orbit_pose

W, H = 160, 120  # not square, so a swapped width and height shows


@pytest.fixture(scope="module", params=[4, 0], ids=["msaa", "single-sample"])
def renderer(request):
    with MeshRenderer(W, H, samples=request.param) as r:
        yield r


def _odd_camera(pose: Pose) -> Camera:
    """Unequal focal lengths and an off-centre, fractional principal point."""
    return Camera(Intrinsics(fx=150.0, fy=170.0, cx=70.3, cy=52.8, width=W, height=H), pose)


def _weighted_centroid(image: np.ndarray) -> np.ndarray:
    """(u, v) centroid of the image's brightness, pixel centres at integers."""
    weight = image.astype(np.float64).sum(axis=2)
    rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    return np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()


def _triangle() -> tuple[np.ndarray, np.ndarray]:
    """A small, tilted triangle around (10, -5, 20) mm."""
    vertices = np.array([[0, 0, 20], [25, 4, 16], [8, -22, 28]], np.float32)
    return vertices, np.array([[0, 1, 2]], np.int32)


def test_rendered_triangle_lands_where_the_projection_formula_says(renderer):
    vertices, triangles = _triangle()
    camera = _odd_camera(orbit_pose(25.0, -10.0, 450.0, np.array([10.0, -5.0, 20.0])))
    renderer.set_mesh(len(vertices), triangles)
    renderer.set_texture(None)
    image = renderer.render(vertices, camera)
    corners = camera.project(vertices)
    # A projective map sends the triangle to the triangle of the projected corners, whose
    # area centroid is their mean; flat shading makes the brightness centroid the same.
    tolerance = 0.15 if renderer.samples else 0.35
    np.testing.assert_allclose(_weighted_centroid(image), corners.mean(axis=0), atol=tolerance)
    # A pixel is lit only if a sample inside it (within half a pixel of its centre) is covered.
    rows, cols = np.nonzero(image.max(axis=2) > 0)
    lit = np.column_stack([cols, rows])
    assert (lit >= corners.min(axis=0) - 0.5).all() and (lit <= corners.max(axis=0) + 0.5).all()


def test_moving_the_vertices_moves_the_image(renderer):
    vertices, triangles = _triangle()
    camera = _odd_camera(Pose(np.eye(3), np.array([0.0, 0.0, -400.0])))
    renderer.set_mesh(len(vertices), triangles)
    renderer.set_texture(None)
    first = renderer.render(vertices, camera)
    moved = vertices + np.float32([-30, 12, 5])
    second = renderer.render(moved, camera)
    assert not np.array_equal(first, second)
    tolerance = 0.15 if renderer.samples else 0.35
    np.testing.assert_allclose(_weighted_centroid(second), camera.project(moved).mean(axis=0),
                               atol=tolerance)


def _pixel_aligned_quad(texels_x: int, texels_y: int, px_per_texel: int, left: int, top: int):
    """A quad facing a 1 px/mm camera whose texel centres fall on pixel centres.

    Returns vertices, triangles, uv (v up) and the camera.
    """
    camera = Camera(Intrinsics(fx=500.0, fy=500.0, cx=79.0, cy=59.0, width=W, height=H),
                    Pose(np.eye(3), np.array([0.0, 0.0, -500.0])))
    u0, u1 = left - 0.5, left - 0.5 + texels_x * px_per_texel  # pixel edges
    v0, v1 = top - 0.5, top - 0.5 + texels_y * px_per_texel
    x0, x1 = u0 - camera.intrinsics.cx, u1 - camera.intrinsics.cx
    y0, y1 = camera.intrinsics.cy - v0, camera.intrinsics.cy - v1
    vertices = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # top edge is v = 1
    triangles = np.array([[0, 3, 2], [0, 2, 1]], np.int32)
    return vertices, triangles, uv, camera


def test_texture_shows_unlit_at_texel_centres_with_v_up(renderer):
    texture = np.random.default_rng(3).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    s, left, top = 15, 20, 10
    vertices, triangles, uv, camera = _pixel_aligned_quad(6, 4, s, left, top)
    renderer.set_mesh(4, triangles, uv)
    renderer.set_texture(texture)
    image = renderer.render(vertices, camera)
    centres = image[top + s // 2::s, left + s // 2::s][:4, :6]
    assert np.abs(centres.astype(int) - texture).max() <= 2


def test_texture_is_not_shaded_when_the_surface_turns_away(renderer):
    colour = np.array([200, 120, 40], np.uint8)
    vertices, triangles, uv, _ = _pixel_aligned_quad(6, 4, 15, 20, 10)
    renderer.set_mesh(4, triangles, uv)
    renderer.set_texture(np.tile(colour, (4, 6, 1)))
    camera = Camera.virtual(W, H, orbit_pose(65.0, 20.0, 500.0), fov_y_deg=40.0)
    image = renderer.render(vertices, camera)
    inside = cv2.erode((image.max(axis=2) > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    assert inside.sum() > 100
    assert np.abs(image[inside > 0].astype(int) - colour).max() <= 2


def test_near_triangle_hides_far_one_whatever_the_draw_order(renderer):
    # Left texel red, right texel blue; each quad samples one texel centre.
    texture = np.array([[[255, 0, 0], [0, 0, 255]]], np.uint8)
    near, _, _, camera = _pixel_aligned_quad(4, 4, 10, 40, 30)     # pixels 40..79, 30..69
    far = near + np.float32([20, -20, -100])                         # further, offset
    quad = np.array([[0, 3, 2], [0, 2, 1]], np.int32)
    uv = np.array([[0.25, 0.5]] * 4 + [[0.75, 0.5]] * 4, np.float32)
    for order in ([0, 1], [1, 0]):
        triangles = np.concatenate([quad + 4 * k for k in order])
        renderer.set_mesh(8, triangles, uv)
        renderer.set_texture(texture)
        image = renderer.render(np.concatenate([near, far]), camera).astype(int)
        overlap = camera.project(np.concatenate([near, far])[[2, 4]]).mean(axis=0)
        u, v = np.round(overlap).astype(int)
        assert abs(image[v, u] - [255, 0, 0]).max() <= 2, f"draw order {order}"
        only_far = np.round(camera.project(far[[1]])[0] + [-3, 3]).astype(int)
        assert abs(image[only_far[1], only_far[0]] - [0, 0, 255]).max() <= 2


def test_grey_shading_darkens_surfaces_turned_from_the_light(renderer):
    vertices, triangles, _, camera = _pixel_aligned_quad(4, 4, 10, 40, 30)
    renderer.set_mesh(4, triangles)
    renderer.set_texture(None)
    facing = renderer.render(vertices, camera)
    centre = vertices.mean(axis=0)
    turned_rotation = orbit_pose(70.0, 0.0, 1.0).rotation  # the quad turned 70 deg about y
    turned = ((vertices - centre) @ turned_rotation + centre).astype(np.float32)
    side = renderer.render(turned, camera)
    brightness = [img[img.max(axis=2) > 0].mean() for img in (facing, side)]
    assert brightness[0] > 150 and brightness[1] < 0.6 * brightness[0]


def test_orbit_pose_looks_at_the_target_from_the_right_side():
    target = np.array([5.0, -3.0, 40.0])
    pose = orbit_pose(30.0, 20.0, 500.0, target)
    rotation, translation = pose.rotation, pose.translation
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation @ target + translation, [0, 0, -500.0], atol=1e-9)
    centre = -rotation.T @ translation
    yaw, pitch = np.radians(30.0), np.radians(20.0)
    expected = target + 500 * np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch),
                                        np.cos(yaw) * np.cos(pitch)])
    np.testing.assert_allclose(centre, expected, atol=1e-9)
    camera = Camera.virtual(W, H, pose)
    np.testing.assert_allclose(camera.project(target[None])[0], [(W - 1) / 2, (H - 1) / 2])
    # Model up stays image up: a point above the target is on a smaller row.
    assert camera.project((target + [0, 10, 0])[None])[0, 1] < (H - 1) / 2


def test_bad_inputs_are_named(renderer):
    vertices, triangles = _triangle()
    renderer.set_mesh(3, triangles)
    renderer.set_texture(None)
    camera = _odd_camera(Pose(np.eye(3), np.array([0.0, 0.0, -400.0])))
    with pytest.raises(RenderError, match="vertices: expected dtype float32"):
        renderer.render(vertices.astype(np.float64), camera)
    with pytest.raises(RenderError, match="vertices: expected shape"):
        renderer.render(vertices[:2], camera)
    with pytest.raises(RenderError, match="camera: image"):
        renderer.render(vertices, Camera.virtual(W + 1, H, Pose(np.eye(3), np.zeros(3))))
    with pytest.raises(RenderError, match="triangles"):
        renderer.set_mesh(3, triangles + 1)
    with pytest.raises(RenderError, match="camera.pose: expected a models.geometry.Pose"):
        Camera(Intrinsics(150.0, 170.0, 70.3, 52.8, W, H), (np.eye(3), np.zeros(3)))
    with pytest.raises(RenderError, match="camera.near, far"):
        Camera(Intrinsics(150.0, 170.0, 70.3, 52.8, W, H), Pose(np.eye(3), np.zeros(3)),
               near=0.0)


def test_missing_egl_gives_the_install_hint(monkeypatch):
    import moderngl

    def no_context(*args, **kwargs):
        raise Exception("eglGetDisplay failed")

    monkeypatch.setattr(moderngl, "create_standalone_context", no_context)
    with pytest.raises(EGLUnavailable, match="apt-get install"):
        MeshRenderer(16, 16)


def test_lee_perry_smith_renders_as_a_face(shared_data):
    """The scan's file v is v up (against glTF): its Map-COL.jpg must be sampled flipped."""
    import dlib

    folder = shared_data / "meshes/lee-perry-smith"
    mesh = read_glb(folder / "LeePerrySmith.glb", mm_per_unit=50.0)  # ~50 mm per file unit
    texture = cv2.cvtColor(cv2.imread(str(folder / "Map-COL.jpg")), cv2.COLOR_BGR2RGB)
    nose = mesh.positions[np.argmax(mesh.positions[:, 2])]
    pose = orbit_pose(0.0, 0.0, 700.0, np.array([0.0, nose[1] + 20.0, 0.0]))
    camera = Camera.virtual(256, 256, pose, fov_y_deg=25.0)
    detector = dlib.get_frontal_face_detector()
    background = (40, 60, 90)
    with MeshRenderer(256, 256, background=background) as r:
        r.set_mesh(len(mesh.positions), mesh.triangles, mesh.uv)
        r.set_texture(np.ascontiguousarray(texture[::-1]))
        image = r.render(mesh.positions, camera)
        r.set_texture(texture)
        wrong_v = r.render(mesh.positions, camera)
    covered = (image != background).any(axis=2)
    assert 0.25 < covered.mean() < 0.75
    skin = image[covered].astype(int)
    assert (skin[:, 0] > skin[:, 2]).mean() > 0.9  # skin tones: red above blue
    faces = detector(image, 0)
    assert len(faces) == 1
    u, v = camera.project(nose[None])[0]
    box = faces[0]
    assert box.left() < u < box.right() and box.top() < v < box.bottom()
    assert len(detector(wrong_v, 0)) == 0  # the texture read the glTF way is scrambled
