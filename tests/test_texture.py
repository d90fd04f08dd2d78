"""Base texture from camera views: UV rasterisation, projection, occlusion, blending, filling."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from facewire.models.gltf import read_glb
from facewire.models.infra.raster import Camera, MeshRenderer, orbit_pose
from facewire.models.mesh import Mesh
from facewire.sender.enroll.fusion import project_views
from facewire.sender.enroll.texture import TextureError, fill_holes, uv_surface

TEX_H, TEX_W = 128, 256
IMG = 256
BIG_R, SMALL_R = 60.0, 20.0
SMALL_C = np.array([10.0, 8.0, 95.0])  # a small ball in front of the big one
BIG_U, BIG_V = (0.03, 0.63), (0.05, 0.95)
SMALL_U, SMALL_V = (0.70, 0.97), (0.20, 0.80)


def _sphere(radius: float, centre: np.ndarray, u_range: tuple[float, float],
            v_range: tuple[float, float], n_lat: int, n_lon: int):
    """A UV sphere: longitude along u (seam at the back, u = middle at +z), latitude along v.

    Returns vertices (N, 3) float32, uv (N, 2) float32 and triangles (M, 3) int64, wound
    counter-clockwise from outside.
    """
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n_lat + 1),
                             np.linspace(-np.pi, np.pi, n_lon + 1), indexing="ij")
    unit = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)],
                    -1).reshape(-1, 3)
    uv = np.stack([u_range[0] + (u_range[1] - u_range[0]) * (phi + np.pi) / (2 * np.pi),
                   v_range[1] - (v_range[1] - v_range[0]) * theta / np.pi], -1).reshape(-1, 2)
    idx = np.arange(unit.shape[0]).reshape(n_lat + 1, n_lon + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    lower = np.stack([a, c, d], -1)[:-1].reshape(-1, 3)  # the bottom row would be degenerate
    upper = np.stack([a, d, b], -1)[1:].reshape(-1, 3)  # so would the top row
    return ((radius * unit + centre).astype(np.float32), uv.astype(np.float32),
            np.concatenate([lower, upper]))


@pytest.fixture(scope="module")
def scene():
    """Two balls with separate UV islands, a painted texture and renders from 0 and 60 deg."""
    parts = [_sphere(BIG_R, np.zeros(3), BIG_U, BIG_V, 24, 48),
             _sphere(SMALL_R, SMALL_C, SMALL_U, SMALL_V, 12, 24)]
    offsets = np.cumsum([0] + [len(p[0]) for p in parts])
    triangles = np.concatenate([p[2] + o for p, o in zip(parts, offsets)]).astype(np.int32)
    mesh = Mesh(np.concatenate([p[0] for p in parts]), triangles,
                np.concatenate([p[1] for p in parts]), np.zeros(len(triangles), np.uint8),
                np.arange(68, dtype=np.int32), np.arange(13, dtype=np.int32))
    rows, cols = np.mgrid[0:TEX_H, 0:TEX_W].astype(np.float64)
    u, v = (cols + 0.5) / TEX_W, 1 - (rows + 0.5) / TEX_H
    # A smooth gradient (catches flips) times a smooth checker of 16 texels (catches shifts:
    # half a texel moves it by up to 14 levels).
    texture = np.clip(np.rint(np.stack([
        40 + 170 * u, 40 + 170 * v,
        128 + 70 * np.sin(2 * np.pi * 16 * u) * np.sin(2 * np.pi * 8 * v)], -1)), 0, 255)
    texture = texture.astype(np.uint8)
    cameras = {yaw: Camera.virtual(IMG, IMG, orbit_pose(yaw, 0.0, 350.0), fov_y_deg=30.0)
               for yaw in (0.0, 60.0)}
    with MeshRenderer(IMG, IMG) as renderer:
        renderer.set_mesh(len(mesh.vertices), mesh.triangles, mesh.uv)
        renderer.set_texture(texture)
        views = {yaw: (renderer.render(mesh.vertices, cam)[..., ::-1].copy(), cam)  # RGB->BGR
                 for yaw, cam in cameras.items()}
    return mesh, texture, uv_surface(mesh, (TEX_H, TEX_W)), views


def _cos_to(surface, camera: Camera) -> np.ndarray:
    """(H, W) cosine between each texel's normal and its ray to the camera centre."""
    centre = -camera.pose.rotation.T @ camera.pose.translation
    ray = centre - surface.positions
    return (surface.normals * ray).sum(-1) / np.linalg.norm(ray, axis=-1)


def _behind_small_ball(surface, camera: Camera, margin: float) -> np.ndarray:
    """(H, W) bool: the texel is on the big ball, and the segment from the camera centre to
    its point passes through the small ball, at least ``margin`` mm inside its surface."""
    centre = -camera.pose.rotation.T @ camera.pose.translation
    p = surface.positions.astype(np.float64)
    d = p - centre
    s = np.clip(((SMALL_C - centre) * d).sum(-1) / (d * d).sum(-1), 0, 1)
    closest = centre + s[..., None] * d
    on_big = surface.covered & (np.linalg.norm(p, axis=-1) < BIG_R + 1)
    return on_big & (np.linalg.norm(closest - SMALL_C, axis=-1) < SMALL_R - margin)


def test_texels_land_on_the_surface_with_v_up_and_centred_texels(scene):
    mesh, _, surface, _ = scene
    assert surface.size == (TEX_H, TEX_W)
    rows, cols = np.nonzero(surface.covered)
    uv = np.column_stack([(cols + 0.5) / TEX_W, 1 - (rows + 0.5) / TEX_H])  # texel centres
    # Each texel centre lies in its triangle's UV image, and its point is the same
    # barycentric blend of the triangle's corners (half a texel off would move it ~0.45 mm).
    corners = mesh.triangles[surface.triangles[rows, cols]]
    a, b, c = (mesh.uv[corners[:, k]].astype(np.float64) for k in range(3))
    m = np.stack([b - a, c - a], axis=2)  # (K, 2, 2)
    beta, gamma = np.linalg.solve(m, (uv - a)[..., None])[..., 0].T
    weights = np.column_stack([1 - beta - gamma, beta, gamma])
    assert (weights > -1e-4).all()
    expected = np.einsum("kj,kjd->kd", weights, mesh.vertices[corners].astype(np.float64))
    np.testing.assert_allclose(surface.positions[rows, cols], expected, atol=0.01)
    on_big = np.linalg.norm(surface.positions[rows, cols], axis=1) < BIG_R + 1
    radial = expected[on_big] / np.linalg.norm(expected[on_big], axis=1)[:, None]
    assert ((surface.normals[rows, cols][on_big] * radial).sum(1) > 0.995).all()
    # Coverage is decided at texel centres: the equator row is covered from the first to the
    # last column whose centre lies in the big ball's u range, then nothing up to the small
    # ball's island.
    first, last = int(np.ceil(BIG_U[0] * TEX_W - 0.5)), int(np.floor(BIG_U[1] * TEX_W - 0.5))
    equator = surface.covered[TEX_H // 2, :int(SMALL_U[0] * TEX_W - 0.5)]
    assert np.flatnonzero(equator).tolist() == list(range(first, last + 1))
    assert (surface.triangles[~surface.covered] == -1).all()
    assert (surface.positions[~surface.covered] == 0).all()


def test_frontal_round_trip_recovers_the_painted_texture(scene):
    mesh, texture, surface, views = scene
    image, camera = views[0.0]
    recovered, weight = project_views(mesh, surface, [(image, camera)])
    assert recovered.dtype == np.uint8 and recovered.shape == (TEX_H, TEX_W, 3)
    assert weight.dtype == np.float32 and weight.shape == (TEX_H, TEX_W)
    frontal = surface.covered & (_cos_to(surface, camera) > 0.7) \
        & ~_behind_small_ball(surface, camera, margin=-3.0)
    seen = frontal & (weight > 0)
    assert seen.sum() > 0.95 * frontal.sum() > 800
    # Tolerance: two bilinear resamplings (texture -> render -> texture) of a smooth pattern;
    # measured mean 0.2, max 3 levels. Half a texel's misregistration gives mean 2, max 13.
    error = np.abs(recovered.astype(int) - texture.astype(int))[seen]
    assert error.mean() < 0.6 and error.max() <= 5
    assert (recovered[weight == 0] == 0).all()


def test_back_side_and_occluded_texels_get_no_weight(scene):
    mesh, _, surface, views = scene
    image, camera = views[0.0]
    _, weight = project_views(mesh, surface, [(image, camera)])
    cos = _cos_to(surface, camera)
    back = surface.covered & (cos < 0)
    hidden = surface.covered & (cos > 0.3) & _behind_small_ball(surface, camera, margin=1.0)
    assert back.sum() > 3000 and hidden.sum() > 100
    assert (weight[back] == 0).all() and (weight[hidden] == 0).all()
    # The hidden texels face the camera: only the depth test removes them. Texels as frontal
    # that nothing hides are all seen (below cos 0.5 the small ball's own texels come within
    # a few pixels of its rim, where the weight is 0).
    in_front = surface.covered & (cos > 0.5) & ~_behind_small_ball(surface, camera, -3.0)
    assert in_front.sum() > 2000 and (weight[in_front] > 0).all()
    # Weight favours frontal views: it falls with the view angle.
    seen = weight > 0
    assert np.corrcoef(cos[seen], weight[seen])[0, 1] > 0.6


def test_two_views_cover_more_and_agree_where_both_see(scene):
    mesh, texture, surface, views = scene
    front, front_w = project_views(mesh, surface, [views[0.0]])
    side, side_w = project_views(mesh, surface, [views[60.0]])
    both, both_w = project_views(mesh, surface, [views[0.0], views[60.0]])
    np.testing.assert_array_equal(both_w > 0, (front_w > 0) | (side_w > 0))
    np.testing.assert_allclose(both_w, front_w + side_w, rtol=1e-5, atol=1e-7)
    assert (both_w > 0).sum() > 1.2 * max((front_w > 0).sum(), (side_w > 0).sum())
    shared = (front_w > 0) & (side_w > 0)
    assert shared.sum() > 500
    difference = np.abs(front.astype(int) - side.astype(int))[shared]
    assert difference.mean() < 1.0 and np.percentile(difference, 99) <= 6
    error = np.abs(both.astype(int) - texture.astype(int))[both_w > 0]
    assert error.mean() < 1.0


def test_a_later_view_is_matched_to_the_first_views_exposure(scene):
    mesh, texture, surface, views = scene
    image, camera = views[60.0]
    balance = np.array([0.75, 0.9, 0.8])  # BGR: darker, and a different white balance
    darker = np.clip(np.rint(image * balance), 0, 255).astype(np.uint8)
    front_w = project_views(mesh, surface, [views[0.0]])[1]
    both, both_w = project_views(mesh, surface, [views[0.0], (darker, camera)])
    side_only = (both_w > 0) & (front_w == 0)
    assert side_only.sum() > 2000
    error = np.abs(both.astype(int) - texture.astype(int))
    # Uncorrected, the side-only texels are 10-25 % darker per channel (mean error 24).
    assert error[side_only].mean() < 1.5 and error[both_w > 0].mean() < 1.5


@pytest.mark.parametrize("pad", [0, 8])
def test_fill_keeps_valid_texels_and_fills_a_hole_with_its_surroundings(pad):
    texture = np.zeros((64, 256, 3), np.uint8)
    texture[:, :128] = (200, 60, 30)
    texture[:, 128:] = (20, 120, 220)
    valid = np.ones((64, 256), bool)
    valid[28:36, 40:48] = False
    valid[2:10, 200:230] = False
    holes = texture.copy()
    holes[~valid] = 0
    filled = fill_holes(holes, valid, pad=pad)
    np.testing.assert_array_equal(filled[valid], texture[valid])
    np.testing.assert_array_equal(filled[28:36, 40:48], texture[28:36, 40:48])
    np.testing.assert_array_equal(filled[2:10, 200:230], texture[2:10, 200:230])


def test_fill_leaves_no_gap_and_pads_islands_with_their_own_colour():
    rng = np.random.default_rng(3)
    texture = np.zeros((96, 192, 3), np.uint8)
    valid = np.zeros((96, 192), bool)
    valid[10:40, 10:70] = True  # island A: noisy colours within 100..140
    texture[10:40, 10:70] = rng.integers(100, 141, (30, 60, 3))
    valid[50:90, 120:180] = True  # island B: uniform
    texture[50:90, 120:180] = (230, 30, 90)
    filled = fill_holes(texture, valid, pad=4)
    np.testing.assert_array_equal(filled[valid], texture[valid])
    # Every texel is a blend of valid colours (per channel between their least and greatest):
    # no black gap anywhere.
    lo, hi = texture[valid].min(axis=0), texture[valid].max(axis=0)
    assert (filled >= lo).all() and (filled <= hi).all()
    # The 4 rings around island B are its colour exactly, so bilinear and mip sampling at its
    # border never read anything else; further out the fill blends towards island A.
    ring = np.zeros((96, 192), bool)
    ring[50 - 4:90 + 4, 120 - 4:180 + 4] = True
    ring[50:90, 120:180] = False
    assert (filled[ring] == (230, 30, 90)).all()
    assert np.abs(filled[45, 95].astype(int) - (230, 30, 90)).sum() > 30


def test_bad_inputs_are_named(scene):
    mesh, _, surface, views = scene
    image, camera = views[0.0]
    with pytest.raises(TextureError, match="size"):
        uv_surface(mesh, (0, 256))
    with pytest.raises(TextureError, match="size"):
        uv_surface(mesh, [128, 256])
    with pytest.raises(TextureError, match="mesh"):
        uv_surface(mesh.vertices, (8, 16))
    with pytest.raises(TextureError, match=r"mesh\.uv: outside"):
        uv_surface(dataclasses.replace(mesh, uv=mesh.uv * 1.5), (8, 16))
    stacked = dataclasses.replace(mesh, uv=np.where(np.arange(len(mesh.uv))[:, None] < 1225,
                                                    mesh.uv, mesh.uv - (0.5, 0)).clip(0, 1)
                                  .astype(np.float32))
    with pytest.raises(TextureError, match="overlap"):
        uv_surface(stacked, (32, 64))
    with pytest.raises(TextureError, match=r"views\[0\] image.*uint8"):
        project_views(mesh, surface, [(image.astype(np.float32), camera)])
    with pytest.raises(TextureError, match=r"views\[1\] image.*\(256, 256, 3\)"):
        project_views(mesh, surface, [(image, camera), (image[:200], camera)])
    with pytest.raises(TextureError, match=r"views\[0\] camera"):
        project_views(mesh, surface, [(image, "camera")])
    with pytest.raises(TextureError, match="views"):
        project_views(mesh, surface, [])
    with pytest.raises(TextureError, match="surface"):
        project_views(mesh, mesh, [(image, camera)])
    small = dataclasses.replace(mesh, triangles=mesh.triangles[:100],
                                tags=mesh.tags[:100])
    with pytest.raises(TextureError, match=r"surface\.triangles.*another mesh"):
        project_views(small, surface, [(image, camera)])
    with pytest.raises(TextureError, match="cos_min"):
        project_views(mesh, surface, [(image, camera)], cos_min=1.0)
    valid = np.ones((4, 4), bool)
    with pytest.raises(TextureError, match="texture.*uint8"):
        fill_holes(np.zeros((4, 4, 3), np.float32), valid)
    with pytest.raises(TextureError, match="valid.*bool"):
        fill_holes(np.zeros((4, 4, 3), np.uint8), valid.astype(np.uint8))
    with pytest.raises(TextureError, match="valid.*bool"):
        fill_holes(np.zeros((4, 4, 3), np.uint8), valid[:3])
    with pytest.raises(TextureError, match="no valid texel"):
        fill_holes(np.zeros((4, 4, 3), np.uint8), ~valid)


def test_a_callers_renderer_keeps_working_around_our_passes(scene):
    mesh, texture, _, views = scene
    near = Camera.virtual(64, 64, orbit_pose(0.0, 0.0, 250.0))
    far = Camera.virtual(64, 64, orbit_pose(0.0, 0.0, 500.0))
    with MeshRenderer(64, 64) as renderer:
        renderer.set_mesh(len(mesh.vertices), mesh.triangles, mesh.uv)
        renderer.set_texture(texture)
        expected = renderer.render(mesh.vertices, far)
        renderer.render(mesh.vertices, near)
        surface = uv_surface(mesh, (16, 32))  # opens and closes its own GL context
        project_views(mesh, surface, [views[0.0]])
        np.testing.assert_array_equal(renderer.render(mesh.vertices, far), expected)


def test_lee_perry_smith_rebuilt_from_two_views_has_no_gaps(shared_data):
    """Render the scan from 0 and 40 degrees, rebuild its texture from those two images, and
    render it again: no black texel shows from the front or the three-quarter views."""
    folder = shared_data / "meshes/lee-perry-smith"
    scan = read_glb(folder / "LeePerrySmith.glb", mm_per_unit=50.0)
    mesh = Mesh(scan.positions, scan.triangles, scan.uv, np.zeros(len(scan.triangles), np.uint8),
                np.arange(68, dtype=np.int32), np.arange(13, dtype=np.int32))
    original = cv2.cvtColor(cv2.imread(str(folder / "Map-COL.jpg")), cv2.COLOR_BGR2RGB)
    original = np.ascontiguousarray(original[::-1])  # the file is stored v up (test_raster)
    nose = mesh.vertices[np.argmax(mesh.vertices[:, 2])]
    target = np.array([0.0, nose[1] + 20.0, 0.0])

    def camera(yaw: float) -> Camera:
        return Camera.virtual(IMG, IMG, orbit_pose(yaw, 0.0, 700.0, target), fov_y_deg=25.0)

    with MeshRenderer(IMG, IMG) as renderer:
        renderer.set_mesh(len(mesh.vertices), mesh.triangles, mesh.uv)
        renderer.set_texture(original)
        views = [(renderer.render(mesh.vertices, camera(y))[..., ::-1].copy(), camera(y))
                 for y in (0.0, 40.0)]
        surface = uv_surface(mesh, (256, 512))
        texture, weight = project_views(mesh, surface, views)
        rebuilt = fill_holes(texture, weight > 0)
        for yaw in (0.0, 35.0, -35.0):
            renderer.set_texture(original)
            reference = renderer.render(mesh.vertices, camera(yaw))
            renderer.set_texture(rebuilt)
            image = renderer.render(mesh.vertices, camera(yaw))
            head = reference.max(axis=2) > 0
            # No gap or dark seam: no pixel of the head loses a quarter of its brightness
            # (measured: at most 13 %; the unfilled texture leaves 2500-12000 such pixels).
            brightness = image[head].sum(axis=1) / reference[head].astype(int).sum(axis=1)
            assert brightness.min() > 0.75, yaw
            # Measured 1.3, 1.0 and 3.1 (the right side, -35, was seen only at a slant).
            difference = np.abs(image.astype(int) - reference.astype(int))[head]
            assert difference.mean() < (2.0 if yaw >= 0 else 4.5), yaw
    assert 0.2 < (weight > 0).mean() < 0.4
