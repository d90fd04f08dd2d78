"""Appearance sampling: barycentric sample points read back the templates a synthetic face was
rendered with (real OpenGL through EGL), the offset grids catch a misplaced pose, and the
projection and bilinear reads agree with direct formulas.

The synthetic face: the generic head with a flat grey texture except where a region's
template area is painted with a known smooth pattern. A template area is defined by a front
view of the neutral generic head, so each texel's neutral surface point P (``uv_surface``)
gives its place in the template directly: a = (P.x - x0) / (x1 - x0) across, b = (y1 - P.y)
/ (y1 - y0) down. The head is then morphed by an expression, rendered from a posed camera,
and sampled with the same pose and residuals.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import EXPRESSION_UV, SYNTH_FX

from facewire.models.geometry import Intrinsics
from facewire.models.head import generic_head
from facewire.models.infra.raster import Camera as ViewCamera
from facewire.models.infra.raster import MeshRenderer, orbit_pose
from facewire.models.mesh import Mesh, Tag
from facewire.models.regions import (
    OFFSETS,
    REGIONS,
    SUPERSAMPLE,
    TEMPLATE_SIZE,
    RegionError,
    spec,
    template_samples,
)
from facewire.models.rig import Rig
from facewire.sender.appearance import AppearanceSampler, SurfacePoints, bilinear, project
from facewire.sender.classify import RegionClassifiers
from facewire.sender.enroll.texture import UVSurface, uv_surface

WIDTH, HEIGHT = 640, 480
INTRINSICS = Intrinsics(SYNTH_FX, SYNTH_FX, 319.5, 239.5, WIDTH, HEIGHT)
TEXTURE = (512, 1024)  # (H, W)
GREY = 128
PAINT_MARGIN_MM = 3.0  # the pattern goes on past the box, so blur at its edge reads pattern
# A skin region that the expression moves and an eyeball region (rigid, its own UV island).
# (eyelid_left is tested on its own below: the lids hide part of its box.)
NAMES = ("forehead", "eyeball_left")
PAINTED = 1  # the pattern painted, of the three each region's classifier knows


def _pattern(j: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smooth grey pattern j (about 60..200) at template coordinates a (across, 0..1 from x0)
    and b (down, 0..1 from y1). Low in spatial frequency (an eyeball cell is about one pixel
    wide in the renders, so finer patterns would be blurred by the rendering itself), and
    none of them linear (a shifted ramp normalises to itself: the offsets could not tell)."""
    if j == 0:
        return 60 + 140 * np.exp(-((a - 0.2) ** 2 + (b - 0.25) ** 2) / (2 * 0.3 ** 2))
    if j == 1:
        return 130 + 70 * np.sin(np.pi * (1.2 * a - 0.35)) * np.cos(0.9 * np.pi * (b - 0.35))
    return 60 + 140 * np.exp(-((a - 0.75) ** 2 + (b - 0.7) ** 2) / (2 * 0.3 ** 2))


def _templates() -> np.ndarray:
    """(3, 16, 16) float32: each pattern averaged over the SUPERSAMPLE^2 points of its cells,
    as the sampler averages them."""
    s = TEMPLATE_SIZE * SUPERSAMPLE
    b, a = (np.mgrid[0:s, 0:s] + 0.5) / s
    fine = np.stack([_pattern(j, a, b) for j in range(3)])
    return fine.reshape(3, TEMPLATE_SIZE, SUPERSAMPLE, TEMPLATE_SIZE, SUPERSAMPLE) \
        .mean(axis=(2, 4)).astype(np.float32)


TEMPLATES = _templates()


def _paint(texture: np.ndarray, mesh: Mesh, surface: UVSurface, name: str, j: int) -> None:
    """Paint pattern j over region ``name``'s template area (grown by PAINT_MARGIN_MM): the
    texels of the region's surface, facing the front, whose neutral (x, y) is in the box."""
    region = spec(name)
    x0, x1, y0, y1 = region.box
    tri = surface.triangles
    p = surface.positions
    tag = np.where(tri >= 0, mesh.tags[np.maximum(tri, 0)], 255)
    m = PAINT_MARGIN_MM
    inside = ((tag == region.tag) & (surface.normals[..., 2] > 0)
              & (p[..., 0] >= x0 - m) & (p[..., 0] <= x1 + m)
              & (p[..., 1] >= y0 - m) & (p[..., 1] <= y1 + m))
    a = (p[..., 0] - x0) / (x1 - x0)
    b = (y1 - p[..., 1]) / (y1 - y0)
    value = np.clip(np.rint(_pattern(j, a[inside], b[inside])), 0, 255).astype(np.uint8)
    texture[inside] = value[:, None]


class Scene:
    """The generic head, its texel surface, an expression and a posed camera."""

    def __init__(self, rig: Rig) -> None:
        self.mesh = generic_head()
        self.rig = rig
        self.surface = uv_surface(self.mesh, TEXTURE)
        self.residuals = rig.from_tangent(EXPRESSION_UV)  # brows up, smile, mouth open
        self.vertices = rig.morph(self.residuals)
        # 600 mm away, 15 degrees toward the person's left, 10 degrees from above
        pose = orbit_pose(15.0, 10.0, 600.0, (0.0, 0.0, 40.0))
        self.rotation, self.translation = pose.rotation, pose.translation
        self.camera = ViewCamera(INTRINSICS, pose)
        self.renderer = MeshRenderer(WIDTH, HEIGHT)
        self.renderer.set_mesh(len(self.mesh.vertices), self.mesh.triangles, self.mesh.uv)

    def texture(self, painted: dict[str, int]) -> np.ndarray:
        texture = np.full((*TEXTURE, 3), GREY, np.uint8)
        for name, j in painted.items():
            _paint(texture, self.mesh, self.surface, name, j)
        return texture

    def render_grey(self, texture: np.ndarray, shift_mm: np.ndarray | None = None
                    ) -> np.ndarray:
        """(H, W) uint8 grey image of the morphed head, moved by ``shift_mm`` (3,)."""
        vertices = self.vertices if shift_mm is None \
            else self.vertices + np.asarray(shift_mm, np.float32)
        self.renderer.set_texture(texture)
        rgb = self.renderer.render(vertices, self.camera)
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)

    def sampler(self, names: tuple[str, ...]) -> AppearanceSampler:
        return AppearanceSampler(self.mesh, self.rig, INTRINSICS, names)

    def seen(self, name: str, shift_mm: np.ndarray | None = None) -> np.ndarray:
        """(16, 16) fraction of each centre-grid cell of region ``name`` where the camera
        sees the region's own surface: a render with that surface white and all else black,
        read by the same sample points."""
        texture = np.zeros((*TEXTURE, 3), np.uint8)
        tri = self.surface.triangles
        texture[(tri >= 0) & (self.mesh.tags[np.maximum(tri, 0)] == spec(name).tag)] = 255
        grey = self.render_grey(texture, shift_mm)
        samples = self.sampler((name,)).sample(grey, self.rotation, self.translation,
                                               self.residuals)
        return samples[0, 0] / 255.0


@pytest.fixture(scope="module")
def scene(rig: Rig):
    made = Scene(rig)
    yield made
    made.renderer.release()


@pytest.fixture(scope="module")
def painted(scene: Scene) -> np.ndarray:
    """The texture with pattern PAINTED on every region of NAMES."""
    return scene.texture({name: PAINTED for name in NAMES})


def _cell_mm(name: str) -> np.ndarray:
    x0, x1, y0, y1 = spec(name).box
    return np.array([x1 - x0, y1 - y0]) / TEMPLATE_SIZE


def test_sampling_a_rendered_face_returns_the_template_it_was_rendered_with(
        scene: Scene, painted: np.ndarray) -> None:
    grey = scene.render_grey(painted)
    sampler = scene.sampler(NAMES)
    samples = sampler.sample(grey, scene.rotation, scene.translation, scene.residuals)
    assert samples.shape == (len(NAMES), 5, TEMPLATE_SIZE, TEMPLATE_SIZE)
    assert samples.dtype == np.float32
    truth = TEMPLATES[PAINTED]
    for r, name in enumerate(NAMES):
        error = np.abs(samples[r, 0] - truth)
        # the lids touch the eyeball box's corners (most at the lower outer one, here about
        # half of the last cell): the bound on single cells holds where nothing hides them
        visible = scene.seen(name) > 0.99
        assert visible.sum() >= 200, (name, visible.sum())  # measured: 256 and 240
        # measured (grey levels): forehead mean 0.49, max 1.45; eyeball_left mean 1.42, max
        # over the visible cells 4.8 (the render's blur: an eyeball cell is ~1 pixel); the
        # other offsets 8.1 .. 9.7
        assert error.mean() < 2.5 and error[visible].max() < 8.0, \
            (name, error.mean(), error[visible].max())
        # the other offsets read the pattern one cell off: clearly worse
        for o in range(1, 5):
            assert np.abs(samples[r, o] - truth).mean() > 4 * error.mean(), (name, o)

    classifiers = RegionClassifiers([TEMPLATES] * len(NAMES))
    result = classifiers.classify(samples)
    np.testing.assert_array_equal(result.offset, [0] * len(NAMES))
    assert np.abs(result.q - PAINTED).max() < 0.15, result.q

    # the points ride on the morphed mesh: ignoring the expression misreads the forehead,
    # while the eyeballs never move, so their samples do not change at all
    still = sampler.sample(grey, scene.rotation, scene.translation, np.zeros((9, 3), np.float32))
    forehead = NAMES.index("forehead")
    wrong = np.abs(still[forehead, 0] - truth).mean()
    right = np.abs(samples[forehead, 0] - truth).mean()
    assert wrong > 4 * right, (wrong, right)  # measured: 8.1 against 0.49
    eye = NAMES.index("eyeball_left")
    np.testing.assert_array_equal(still[eye], samples[eye])


@pytest.mark.parametrize("offset", [1, 2, 3, 4])
@pytest.mark.parametrize("name", NAMES)
def test_a_misplaced_pose_is_caught_by_the_matching_diagonal_offset(
        scene: Scene, painted: np.ndarray, name: str, offset: int) -> None:
    # The head is rendered moved by one template cell diagonally (a few pixels: forehead
    # 3.75 x 1.56 mm, eyeball 1.06 x 0.44 mm, ~1 px/mm) and sampled at the unmoved pose:
    # offset o's grid, moved by OFFSETS[o] cells on the head, lands on the painted cells.
    shift = np.zeros(3)
    shift[:2] = OFFSETS[offset] * _cell_mm(name)
    grey = scene.render_grey(painted, shift)
    samples = scene.sampler(NAMES).sample(grey, scene.rotation, scene.translation,
                                          scene.residuals)
    r = NAMES.index(name)
    error = np.abs(samples[r, offset] - TEMPLATES[PAINTED])
    # measured: forehead 0.57 .. 0.89, eyeball 1.8 .. 2.3; Q 0.96 .. 1.06
    assert error.mean() < 3.0, error.mean()
    result = RegionClassifiers([TEMPLATES] * len(NAMES)).classify(samples)
    assert result.offset[r] == offset
    assert abs(result.q[r] - PAINTED) < 0.15, result.q[r]


def test_eyelid_region_reads_the_eyeball_where_the_lids_leave_it_visible(scene: Scene) -> None:
    # The eyelid box is taller than the lid opening: the lids hide its top and bottom rows,
    # in this view as from the front. Paint the eyeball only (the brief's rule: the region's
    # own surface), and learn which cells see it from a render with the eyeball white and
    # everything else black, sampled by the same points.
    name = "eyelid_left"
    texture = scene.texture({name: PAINTED})
    sampler = scene.sampler((name,))
    samples = sampler.sample(scene.render_grey(texture), scene.rotation, scene.translation,
                             scene.residuals)[0, 0]
    seen = scene.seen(name)

    open_cells, lid_cells = seen > 0.99, seen < 0.01
    # measured: 154 open cells, 10 wholly hidden, 51 more than half hidden (top and bottom)
    assert open_cells.sum() > 100 and (seen < 0.5).sum() > 20 and lid_cells.any(), \
        (open_cells.sum(), (seen < 0.5).sum(), lid_cells.sum())
    truth = TEMPLATES[PAINTED]
    error = np.abs(samples - truth)[open_cells]
    # measured: 0.87 / 2.8 grey levels (mean / max)
    assert error.mean() < 2.5 and error.max() < 8.0, (error.mean(), error.max())
    np.testing.assert_allclose(samples[lid_cells], GREY, atol=1.0)
    # every cell mixes the two in the proportion seen (measured: 0.88 / 3.8)
    blend = np.abs(samples - (seen * truth + (1 - seen) * GREY))
    assert blend.mean() < 2.5 and blend.max() < 8.0, (blend.mean(), blend.max())


# ---------------------------------------------------------------------------------------
# projection and reading


def _random_points(mesh: Mesh, shape: tuple[int, ...], seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    face = np.flatnonzero(mesh.tags == Tag.SKIN)
    triangles = rng.choice(face, size=shape)
    bary = rng.dirichlet(np.ones(3), size=shape).astype(np.float32)
    return triangles, bary


def test_surface_points_follow_the_morph_and_project_through_the_pose(rig: Rig) -> None:
    mesh = generic_head()
    triangles, bary = _random_points(mesh, (40, 25), seed=5)
    points = SurfacePoints(mesh, rig, triangles, bary)
    assert points.shape == (40, 25)
    residuals = rig.from_tangent(EXPRESSION_UV)
    morphed = rig.morph(residuals).astype(np.float64)[mesh.triangles[triangles]]
    expected = np.einsum("...k,...kc->...c", bary.astype(np.float64), morphed).reshape(-1, 3)
    positions = points.positions(residuals)
    assert positions.shape == (1000, 3) and positions.dtype == np.float32
    np.testing.assert_allclose(positions, expected, atol=1e-3)
    assert np.abs(positions - points.positions(np.zeros((9, 3)))).max() > 1.0

    pose = orbit_pose(-20.0, 8.0, 550.0, (5.0, -10.0, 40.0))
    rotation, translation = pose.rotation, pose.translation
    x, y = points.project(residuals, rotation, translation, INTRINSICS)
    assert x.shape == y.shape == (1000,) and x.dtype == y.dtype == np.float32
    direct = project(positions, rotation, translation, INTRINSICS)
    np.testing.assert_allclose(x, direct[0], atol=2e-3)
    np.testing.assert_allclose(y, direct[1], atol=2e-3)
    # the renderer's camera projects the same points to the same pixels
    view = ViewCamera(INTRINSICS, pose)
    pixels = view.project(expected)
    np.testing.assert_allclose(x, pixels[:, 0], atol=2e-3)
    np.testing.assert_allclose(y, pixels[:, 1], atol=2e-3)


def test_project_pushes_points_behind_the_camera_to_1_mm() -> None:
    camera = Intrinsics(500.0, 400.0, 100.0, 80.0, 200, 160)
    points = np.array([[2.0, -1.0, -0.25], [2.0, -1.0, 3.0], [2.0, -1.0, -1.0],
                       [2.0, -1.0, -4.0]], np.float32)
    x, y = project(points, np.eye(3), np.zeros(3), camera)
    # d = -Z: 0.25 and -3 become 1; 1 and 4 stay
    np.testing.assert_allclose(x, [100 + 500 * 2, 100 + 500 * 2, 100 + 500 * 2, 100 + 500 * 2 / 4])
    np.testing.assert_allclose(y, [80 + 400, 80 + 400, 80 + 400, 80 + 400 / 4])


def _direct_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation with pixel centres at integers and the border replicated."""
    h, w = image.shape[:2]
    xc, yc = np.clip(x.astype(np.float64), 0, w - 1), np.clip(y.astype(np.float64), 0, h - 1)
    x0, y0 = np.floor(xc).astype(int), np.floor(yc).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = xc - x0, yc - y0
    if image.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    img = image.astype(np.float64)
    return ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x1])
            + fy * ((1 - fx) * img[y1, x0] + fx * img[y1, x1]))


def test_bilinear_interpolates_and_replicates_the_border() -> None:
    rng = np.random.default_rng(11)
    h, w = 21, 34
    image = rng.random((h, w)).astype(np.float32)
    x = rng.uniform(-4, w + 3, (7, 9)).astype(np.float32)
    y = rng.uniform(-4, h + 3, (7, 9)).astype(np.float32)
    out = bilinear(image, x, y)
    assert out.shape == (7, 9) and out.dtype == np.float32
    # measured: 5e-8 (float images are interpolated in float)
    np.testing.assert_allclose(out, _direct_bilinear(image, x, y), atol=1e-5)
    # pixel centres are at integers, (0, 0) the top-left one
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    np.testing.assert_array_equal(bilinear(image, cols, rows), image)
    # far outside: the nearest border pixel
    far = bilinear(image, np.float32([[-50, w + 60, -50, w + 60, 5]]),
                   np.float32([[-70, -70, h + 30, h + 30, -9]]))
    np.testing.assert_array_equal(far[0], [image[0, 0], image[0, -1], image[-1, 0],
                                           image[-1, -1], image[0, 5]])


def test_bilinear_reads_colour_uint8_images() -> None:
    rng = np.random.default_rng(12)
    h, w = 30, 40
    rows, cols = np.mgrid[0:h, 0:w]
    # gentle slopes (<= 5 grey levels per pixel), so 1/32-pixel rounding stays small
    image = np.stack([2 * cols + 3 * rows, 5 * cols, 200 - 4 * rows], axis=-1)
    image = (image + rng.integers(0, 2, image.shape)).astype(np.uint8)
    x = rng.uniform(-3, w + 2, 500).astype(np.float32)
    y = rng.uniform(-3, h + 2, 500).astype(np.float32)
    out = bilinear(image, x, y)
    assert out.shape == (500, 3) and out.dtype == np.float32
    # uint8 output rounds (0.5), and OpenCV's 1/32-pixel fixed-point weights move it by at
    # most 6 / 64 more here (measured: 0.499)
    np.testing.assert_allclose(out, _direct_bilinear(image, x, y), atol=0.5 + 6 / 64 + 1e-6)


def test_bilinear_reads_a_long_flat_array_of_points() -> None:
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    x = np.full(40000, 1.5, np.float32)
    y = np.full(40000, 1.0, np.float32)
    np.testing.assert_allclose(bilinear(image, x, y), 5.5)
    assert bilinear(image, x[:0], y[:0]).shape == (0,)


@pytest.mark.parametrize("triangles, bary", [
    (np.array([1, 2]), np.full((3, 3), 1 / 3)),        # one weight triple too many
    (np.array([[1, 2]]), np.full((2, 3), 1 / 3)),      # shapes differ
    (np.array([1, 2]), np.full((2, 2), 0.5)),          # two weights per point
    (np.array([-1, 2]), np.full((2, 3), 1 / 3)),       # negative index
    (np.array([5, 10 ** 7]), np.full((2, 3), 1 / 3)),  # past the last triangle
    (np.array([0.5, 1.0]), np.full((2, 3), 1 / 3)),    # not integer indices
    (np.array([1, 2]), np.full((2, 3), np.nan)),       # NaN weights
], ids=["count", "shape", "weights", "negative", "past-the-end", "float", "nan"])
def test_bad_surface_points_are_refused(rig: Rig, triangles: np.ndarray, bary: np.ndarray
                                        ) -> None:
    with pytest.raises(ValueError, match="bary|triangles"):
        SurfacePoints(generic_head(), rig, triangles, bary)


def test_sampler_reads_each_shared_point_once_and_matches_the_full_grids(rig: Rig) -> None:
    # The five offset grids are one grid moved by whole template cells: the sampler projects
    # and reads each distinct point once. Its cells must equal those of every grid point
    # projected, read and averaged on its own.
    mesh = generic_head()
    names = tuple(r.name for r in REGIONS)
    sampler = AppearanceSampler(mesh, rig, INTRINSICS, names)
    s = TEMPLATE_SIZE * SUPERSAMPLE
    distinct = (s + 2 * SUPERSAMPLE) ** 2  # the centre grid and a one-cell rim
    assert sampler.points.shape == (len(names) * distinct,)
    rng = np.random.default_rng(21)
    grey = cv2.GaussianBlur(rng.integers(0, 256, (HEIGHT, WIDTH), np.uint8), (5, 5), 1.5)
    residuals = rig.from_tangent(EXPRESSION_UV)
    pose = orbit_pose(-12.0, 6.0, 620.0, (0.0, 0.0, 40.0))
    rotation, translation = pose.rotation, pose.translation
    samples = sampler.sample(grey, rotation, translation, residuals)

    grids = [template_samples(spec(name)) for name in names]
    full = SurfacePoints(mesh, rig, np.stack([t for t, _ in grids]),
                         np.stack([b for _, b in grids]))
    x, y = full.project(residuals, rotation, translation, INTRINSICS)
    values = bilinear(grey, x, y).reshape(len(names), 5, TEMPLATE_SIZE, SUPERSAMPLE,
                                          TEMPLATE_SIZE, SUPERSAMPLE)
    expected = values.sum(axis=(3, 5)) / SUPERSAMPLE**2  # integer sums: exact
    np.testing.assert_array_equal(samples, expected)
    assert samples.std() > 5.0  # the frame's texture was read, not a flat border


def test_sampler_refuses_an_unknown_region_and_samples_none(rig: Rig) -> None:
    mesh = generic_head()
    with pytest.raises(RegionError, match="'nose'"):
        AppearanceSampler(mesh, rig, INTRINSICS, ("forehead", "nose"))
    empty = AppearanceSampler(mesh, rig, INTRINSICS, ())
    out = empty.sample(np.zeros((HEIGHT, WIDTH), np.uint8), np.eye(3), np.array([0, 0, -600.0]),
                       np.zeros((9, 3), np.float32))
    assert out.shape == (0, 5, TEMPLATE_SIZE, TEMPLATE_SIZE)
