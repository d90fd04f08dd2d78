"""The receiver's renderer and views, rendering for real through EGL (llvmpipe on a CPU).

Synthetic models only: the generic head with a textured neutral texture and the regions placed
as enrollment places them, and a flat square (a frontal plane whose UVs map affinely to
pixels: 6.25 pixels per texel) where the ramp and the blending are read off directly.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from facewire.models.draworder import draw_order
from facewire.models.geometry import Intrinsics, Pose
from facewire.models.head import generic_head
from facewire.models.infra.raster import Camera, MeshRenderer, RenderError, orbit_pose
from facewire.models.manifest import ModelInfo
from facewire.models.mesh import Mesh
from facewire.models.modelfile import Area, PersonModel, Region
from facewire.models.regions import RAMP_TEXELS, REGIONS, place, ramp_mask
from facewire.models.shading import LOG_GAIN_MAX, LOG_GAIN_MIN, SCALE_MM, log_gain
from facewire.models.texelgrid import texel_rect
from facewire.protocol.control import Camera as HelloCamera
from facewire.receiver.render import EACH_AREA, SHADERS, FaceRenderer, fragment_source
from facewire.receiver.views import head_centre, sender_view, virtual_view

MODEL_CAMERA = Intrinsics(640.0, 640.0, 319.5, 239.5, 640, 480)
HEAD_TEXTURE = (512, 1024)  # rows, columns: a face some 3 times finer than the views below
PLANE_TEXTURE = 64  # texels a side over the 100 mm square
PLANE_RECT = (16, 48)  # the plane's regions cover texels [16, 48) in rows and columns
PLANE_PX_PER_MM = 4.0
BASE_GREY = 100


def _region(name: str, texture_shape: tuple[int, int], rect: tuple[float, ...],
            layers: np.ndarray, opacity: tuple[float, ...]) -> Region:
    """A region over ``rect`` with the enrollment's 10-texel alpha ramp."""
    k, h, w, _ = layers.shape
    mask = np.round(ramp_mask((h, w)) * 255).astype(np.uint8)
    return Region(name, rect, rect, layers, mask, np.zeros((k, 16, 16), np.float32), opacity)


def _head_model(regions: list[Region], texture: np.ndarray) -> PersonModel:
    return PersonModel(generic_head(), texture, MODEL_CAMERA, ModelInfo("test"), tuple(regions))


def _placed(name: str) -> tuple[tuple[float, ...], tuple[slice, slice]]:
    """A region's uv_rect on the generic head for HEAD_TEXTURE, and its texel slices."""
    spec = next(r for r in REGIONS if r.name == name)
    rect = place(spec, HEAD_TEXTURE).uv_rect
    return rect, texel_rect(rect, HEAD_TEXTURE)[1]


@pytest.fixture(scope="module")
def textured() -> np.ndarray:
    """A neutral texture with detail at every scale (so its mipmaps matter)."""
    rng = np.random.default_rng(1)
    smooth = cv2.resize(rng.uniform(40, 220, (32, 64, 3)), HEAD_TEXTURE[::-1],
                        interpolation=cv2.INTER_CUBIC)
    return np.clip(smooth + rng.normal(0, 15, HEAD_TEXTURE + (3,)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def neutral_model(textured: np.ndarray) -> PersonModel:
    """The 7 regions in packet order, each state 0 neutral: the texture itself (opaque
    regions), or a transparent state of another colour (the eyelids)."""
    rng = np.random.default_rng(2)
    regions = []
    for spec in REGIONS:
        rect, (rows, cols) = _placed(spec.name)
        h, w = rows.stop - rows.start, cols.stop - cols.start
        layers = rng.integers(0, 256, (spec.layers, h, w, 3), dtype=np.uint8)
        if spec.transparent_open:
            opacity = (0.0,) + (1.0,) * (spec.layers - 1)
        else:
            layers[0] = textured[rows, cols]
            opacity = (1.0,) * spec.layers
        regions.append(_region(spec.name, HEAD_TEXTURE, rect, layers, opacity))
    return _head_model(regions, textured)


def _preview(model: PersonModel, vertices: np.ndarray, camera: Camera, samples: int,
             background: tuple[int, int, int]) -> np.ndarray:
    """What ``sender.enroll.build.render_preview`` draws: the mesh with the neutral texture
    alone."""
    mesh = model.mesh
    with MeshRenderer(camera.intrinsics.width, camera.intrinsics.height, samples=samples,
                      background=background) as renderer:
        renderer.set_mesh(len(mesh.vertices), mesh.triangles, mesh.uv)
        renderer.set_texture(model.texture)
        return renderer.render(vertices, camera)


def test_neutral_q_renders_exactly_the_texture(neutral_model: PersonModel) -> None:
    mesh = neutral_model.mesh
    background = (40, 40, 40)
    cameras = [virtual_view("front", mesh, np.zeros(3), 320, 320),
               virtual_view("three-quarter", mesh, np.array([0.1, 0.3, 0.0]), 320, 320)]
    with FaceRenderer(neutral_model, 320, 320, samples=4, background=background) as renderer:
        for camera in cameras:
            expected = _preview(neutral_model, mesh.vertices, camera, 4, background)
            got = renderer.render(mesh.vertices, np.zeros(8, np.float32), camera)
            assert np.array_equal(got, expected)
            # The regions are drawn: another state changes the face, around the eyes too.
            other = renderer.render(mesh.vertices, np.ones(8, np.float32), camera)
            assert (other != expected).any(axis=2).sum() > 500


def test_two_frames_write_the_same_vertex_buffer(neutral_model: PersonModel) -> None:
    mesh = neutral_model.mesh
    opened = mesh.vertices.copy()
    jaw = opened[:, 1] < -40.0
    opened[jaw, 1] -= 0.15 * (-40.0 - opened[jaw, 1])  # drop the chin: the jaw opens
    camera = virtual_view("front", mesh, np.zeros(3), 240, 240)
    q = np.zeros(7, np.float32)
    with FaceRenderer(neutral_model, 240, 240, samples=0) as renderer:
        buffer, name = renderer.vertex_buffer, renderer.vertex_buffer.glo
        first = renderer.render(mesh.vertices, q, camera)
        second = renderer.render(opened, q, camera)
        assert renderer.vertex_buffer is buffer and renderer.vertex_buffer.glo == name
    assert (first != second).any(axis=2).sum() > 100
    assert np.array_equal(first, _preview(neutral_model, mesh.vertices, camera, 0, (0, 0, 0)))
    assert np.array_equal(second, _preview(neutral_model, opened, camera, 0, (0, 0, 0)))


def test_fractional_q_blends_the_two_nearest_layers() -> None:
    """Q = 2.25 on a forehead of 4 layers, each a different colour per quadrant."""
    rect, (rows, cols) = _placed("forehead")
    h, w = rows.stop - rows.start, cols.stop - cols.start
    colours = np.random.default_rng(3).integers(0, 256, (4, 2, 2, 3))
    layers = np.empty((4, h, w, 3), np.uint8)
    for top in range(2):
        for left in range(2):
            layers[:, top * h // 2:(top + 1) * h // 2, left * w // 2:(left + 1) * w // 2] = \
                colours[:, top, left, None, None]
    model = _head_model([_region("forehead", HEAD_TEXTURE, rect, layers, (1.0,) * 4)],
                        np.full(HEAD_TEXTURE + (3,), 128, np.uint8))
    mesh = model.mesh
    # Forehead vertices facing the camera, well inside the layers and their quadrants.
    u0, v0, u1, v1 = rect
    col = (mesh.uv[:, 0] - u0) / (u1 - u0) * w
    row = (v1 - mesh.uv[:, 1]) / (v1 - v0) * h
    margin = RAMP_TEXELS + 3
    inside = ((col > margin) & (col < w - margin) & (row > margin) & (row < h - margin)
              & (np.abs(col - w / 2) > 3) & (np.abs(row - h / 2) > 3)
              & (mesh.vertices[:, 2] > 60.0))
    points = np.flatnonzero(inside)
    assert len(points) > 20
    target = mesh.vertices[points].mean(axis=0)
    # Frontal, 200 mm away: some 2 pixels per texel.
    camera = Camera.virtual(480, 480, orbit_pose(0.0, 0.0, 200.0, target), fov_y_deg=25.0)
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        image = renderer.render(mesh.vertices, np.array([2.25], np.float32), camera)
    px = np.rint(camera.project(mesh.vertices[points])).astype(int)
    assert ((px >= 0) & (px < 480)).all()
    got = image[px[:, 1], px[:, 0]].astype(np.float64)
    top, left = (row[points] < h / 2).astype(int), (col[points] < w / 2).astype(int)
    expected = 0.75 * colours[2, 1 - top, 1 - left] + 0.25 * colours[3, 1 - top, 1 - left]
    assert np.abs(got - expected).max() <= 1.0
    # Row 0 of a layer is its top: the quadrants are where they should be.
    assert len(set(zip(top, left))) == 4


def _plane_model(regions: list[Region], base: int | np.ndarray = BASE_GREY) -> PersonModel:
    """A flat 100 mm square in z = 0 facing +z, uv = (x + 50, y + 50) / 100, with a flat
    grey PLANE_TEXTURE texture or the texture ``base``."""
    n = 11
    x, y = np.meshgrid(np.linspace(-50, 50, n), np.linspace(-50, 50, n))
    vertices = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)]).astype(np.float32)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    triangles = np.concatenate([np.column_stack([a, a + 1, a + n + 1]),
                                np.column_stack([a, a + n + 1, a + n])]).astype(np.int32)
    mesh = Mesh(vertices, triangles, ((vertices[:, :2] + 50) / 100).astype(np.float32),
                np.zeros(len(triangles), np.uint8), np.zeros(68, np.int32),
                np.zeros(13, np.int32))
    texture = base if isinstance(base, np.ndarray) else \
        np.full((PLANE_TEXTURE, PLANE_TEXTURE, 3), base, np.uint8)
    return PersonModel(mesh, texture, MODEL_CAMERA, ModelInfo("plane"), tuple(regions))


def _plane_region(name: str, colours: list[tuple[int, int, int]],
                  opacity: tuple[float, ...]) -> Region:
    """A region of constant-colour layers over the plane's texels PLANE_RECT."""
    lo, hi = PLANE_RECT
    rect = (lo / PLANE_TEXTURE, 1 - hi / PLANE_TEXTURE, hi / PLANE_TEXTURE,
            1 - lo / PLANE_TEXTURE)
    layers = np.array(colours, np.uint8)[:, None, None, :] * np.ones((1, hi - lo, hi - lo, 1),
                                                                   np.uint8)
    return _region(name, (PLANE_TEXTURE, PLANE_TEXTURE), rect, layers, opacity)


def _plane_camera(px_per_mm: float = PLANE_PX_PER_MM) -> Camera:
    """Frontal, 200 mm away, ``px_per_mm`` pixels per mm (the plane fills 400 x 400 px)."""
    f = px_per_mm * 200.0
    return Camera(Intrinsics(f, f, 239.5, 239.5, 480, 480),
                  Pose(np.eye(3), np.array([0.0, 0.0, -200.0])))


def _plane_uv(pixels: np.ndarray) -> np.ndarray:
    """Texture u (or 1 - v) of pixel columns (or rows) of ``_plane_camera``."""
    return ((pixels - 239.5) / PLANE_PX_PER_MM + 50.0) / 100.0


def test_alpha_ramp_is_linear_over_ten_texels() -> None:
    model = _plane_model([_plane_region("patch", [(200, 200, 200)], (1.0,))])
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        image = renderer.render(model.mesh.vertices, np.zeros(1, np.float32), _plane_camera())
    centre = 240
    for profile, along in ((image[centre, :, 1], "row"), (image[:, centre, 1], "column")):
        pixels = np.arange(480)
        texel = _plane_uv(pixels) * PLANE_TEXTURE
        # Distance in texels from the region's near edge (left, or top), inward.
        depth = texel - PLANE_RECT[0]
        alpha = (profile.astype(np.float64) - BASE_GREY) / (200 - BASE_GREY)
        # The ramp's texel j (centre at depth j + 1/2) has alpha j / 10; bilinear filtering
        # joins them linearly: alpha = (depth - 1/2) / 10, 0 before, 1 after.
        expected = np.clip((depth - 0.5) / RAMP_TEXELS, 0.0, 1.0)
        near = (depth > -5) & (depth < 20)
        assert np.abs(alpha - expected)[near].max() <= 0.012, along
        ramp = (depth > 1.0) & (depth < RAMP_TEXELS)
        slope = np.polyfit(depth[ramp], alpha[ramp], 1)[0]
        assert slope == pytest.approx(1 / RAMP_TEXELS, rel=0.02), along
        assert (alpha[near & (depth < 0.5)] == 0).all()
        assert (alpha[(depth > RAMP_TEXELS + 1) & (depth < 20)] == 1).all()


def test_minified_region_matches_its_layer_baked_into_the_texture() -> None:
    """Four texels to a pixel, a region of noise over a texture of noise looks like the
    texture with the layer composited into it (both mipmapped): no aliasing, no seam."""
    rng = np.random.default_rng(4)
    size, lo, hi = 512, 128, 371  # 243 texels: padded unevenly to 288
    base = rng.integers(40, 220, (size, size, 3), dtype=np.uint8)
    layer = rng.integers(0, 256, (1, hi - lo, hi - lo, 3), dtype=np.uint8)
    rect = (lo / size, 1 - hi / size, hi / size, 1 - lo / size)
    region = _region("noise", (size, size), rect, layer, (1.0,))
    alpha = region.mask[..., None] / 255.0
    baked = base.copy()
    baked[lo:hi, lo:hi] = np.rint(base[lo:hi, lo:hi] * (1 - alpha) + layer[0] * alpha)
    camera = _plane_camera(px_per_mm=size / 100 / 4)
    model = _plane_model([region], base)
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        got = renderer.render(model.mesh.vertices, np.zeros(1, np.float32), camera)
    expected = _preview(_plane_model([], baked), model.mesh.vertices, camera, 0, (0, 0, 0))
    error = np.abs(got.astype(int) - expected)
    assert error.max() <= 2 and error.mean() < 0.3


def test_transparent_state_does_not_leak_its_colour() -> None:
    """Opacity (0, 1): halfway between a transparent red state and an opaque blue one is
    half the texture and half blue, with no red."""
    model = _plane_model([_plane_region("lid", [(255, 0, 0), (0, 0, 255)], (0.0, 1.0))])
    camera = _plane_camera()
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        images = {q: renderer.render(model.mesh.vertices, np.array([q], np.float32), camera)
                  for q in (0.0, 0.5, 1.0)}
    centre = images[0.5][230:250, 230:250].reshape(-1, 3).astype(np.float64)
    expected = 0.5 * np.array([BASE_GREY] * 3) + 0.5 * np.array([0, 0, 255])
    assert np.abs(centre - expected).max() <= 1.0
    assert (images[0.0][40:440, 40:440] == BASE_GREY).all()  # the whole plane: no trace
    assert (images[1.0][230:250, 230:250] == [0, 0, 255]).all()


def test_eyeball_is_drawn_under_the_eyelid() -> None:
    """In packet order the eyelid comes first; its transparent open state shows the gaze
    layer under it, its closed state covers it."""
    lid = _plane_region("eyelid_left", [(0, 0, 0), (200, 150, 120)], (0.0, 1.0))
    gaze = _plane_region("eyeball_left", [(250, 250, 250), (20, 20, 20)], (1.0, 1.0))
    model = _plane_model([lid, gaze])
    assert draw_order(model.regions) == [1, 0]
    camera = _plane_camera()
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        def centre(q: list[float]) -> np.ndarray:
            image = renderer.render(model.mesh.vertices, np.array(q, np.float32), camera)
            return image[240, 240]
        assert centre([0.0, 1.0]).tolist() == [20, 20, 20]  # open lid: the gaze shows
        assert centre([1.0, 1.0]).tolist() == [200, 150, 120]  # closed lid covers it
        assert np.abs(centre([0.5, 0.0]).astype(float) - [225, 200, 185]).max() <= 1


def test_a_closed_eyelid_covers_the_lid_skin_too(textured: np.ndarray) -> None:
    """The eyelid's further area (its lid skin) follows the eyelid's Q: open (transparent)
    it leaves the texture, closed it draws its own layer over the lids."""
    spec = next(r for r in REGIONS if r.name == "eyelid_left")
    placement = place(spec, HEAD_TEXTURE)
    rows, cols = texel_rect(placement.uv_rect, HEAD_TEXTURE)[1]
    skin_rows, skin_cols = texel_rect(placement.areas[0], HEAD_TEXTURE)[1]
    closed = (180, 120, 90)

    def layers(h: int, w: int) -> np.ndarray:
        return np.array([(0, 0, 0), closed], np.uint8)[:, None, None] \
            * np.ones((1, h, w, 1), np.uint8)

    skin = layers(skin_rows.stop - skin_rows.start, skin_cols.stop - skin_cols.start)
    region = replace(
        _region("eyelid_left", HEAD_TEXTURE, placement.uv_rect,
                layers(rows.stop - rows.start, cols.stop - cols.start), (0.0, 1.0)),
        areas=(Area(placement.areas[0], skin, np.round(ramp_mask(skin.shape[1:3]) * 255)
                    .astype(np.uint8)),))
    model = _head_model([region], textured)
    mesh = model.mesh
    camera = virtual_view("front", mesh, np.zeros(3), 480, 480)
    upper_lid = mesh.vertices[mesh.landmarks[[43, 44]]]
    # just above the upper lid margin, on the skin (the lid opening is below it)
    x, y = camera.project(upper_lid + [0.0, 1.5, 1.0]).round().astype(int).T
    with FaceRenderer(model, 480, 480) as renderer:
        opened = renderer.render(mesh.vertices, np.zeros(1, np.float32), camera)
        shut = renderer.render(mesh.vertices, np.ones(1, np.float32), camera)
    assert np.array_equal(opened, _preview(model, mesh.vertices, camera, 0, (0, 0, 0)))
    assert (np.abs(shut[y, x].astype(int) - closed) <= 1).all()
    assert (np.abs(opened[y, x].astype(int) - closed) > 10).any(axis=1).all()


def test_the_light_multiplies_texture_and_layers_alike() -> None:
    """A shade makes one half of the plane darker and the other brighter, by exactly the gain
    ``models.shading`` gives at each pixel's model (x, y), over the texture and a region's
    layer alike; zeros render exactly what no shade renders; the gain is clipped far away."""
    model = _plane_model([_plane_region("patch", [(150, 60, 30)], (1.0,))])
    camera = _plane_camera()
    q = np.zeros(1, np.float32)
    shade = np.array([0.1, 0.6, -0.3], np.float32)
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        plain = renderer.render(model.mesh.vertices, q, camera)
        assert np.array_equal(renderer.render(model.mesh.vertices, q, camera,
                                              np.zeros(3, np.float32)), plain)
        lit = renderer.render(model.mesh.vertices, q, camera, shade)
        steep = renderer.render(model.mesh.vertices, q, camera,
                                np.array([-0.9, 0.0, -0.98], np.float32))
    # The plane's pixels (40 px margin) and their model (x, y): 4 px per mm, centred.
    rows, cols = np.mgrid[40:440, 40:440]
    xy = np.column_stack([(cols.ravel() - 239.5) / PLANE_PX_PER_MM,
                          -(rows.ravel() - 239.5) / PLANE_PX_PER_MM])
    gain = np.exp(log_gain(shade, xy)).reshape(400, 400, 1)
    before = plain[40:440, 40:440].astype(np.float64)
    after = lit[40:440, 40:440].astype(np.float64)
    error = np.abs(after - before * gain)
    assert error.max() <= 1.5 and error.mean() < 0.3  # rounding to 8 bits, half-float layers
    left, right = after[:, :200].mean() / before[:, :200].mean(), \
        after[:, 200:].mean() / before[:, 200:].mean()
    assert left < 0.97 < 1.2 < right  # s1 > 0: the person's left (+x, image right) brighter
    patch = (slice(215, 265), slice(215, 265))  # inside the layer, past its ramp
    assert (plain[patch] == [150, 60, 30]).all()
    assert np.abs(lit[patch] - plain[patch] * gain[175:225, 175:225]).max() <= 1.5
    # -0.9 - 0.98 y / 100 mm: clipped at e^-1 above y = 10.2 mm (the top edge would be at
    # e^-1.38), e^-0.42 at the bottom edge (y = -48.9 mm)
    top, bottom = steep[45, 100:380].mean() / BASE_GREY, steep[435, 100:380].mean() / BASE_GREY
    assert top == pytest.approx(np.exp(-1.0), abs=0.01)
    assert (steep[45:130, 100:380] == steep[45, 100]).all()  # flat where clipped
    assert bottom == pytest.approx(np.exp(-0.9 + 0.98 * 48.9 / 100), abs=0.01)


def test_one_glsl_source_for_python_and_the_page() -> None:
    """The shaders are the page's files (served beside render.js), GLSL ES 3.00 for both;
    a program's fragment shader has one line per composited area; the light's formula uses
    models.shading's constants."""
    frag = fragment_source([0, 3])
    assert frag.startswith("#version 300 es\n") and "#;" not in frag and "#," not in frag
    assert "uniform sampler2DArray volume0;" in frag and "uniform vec4 rect3;" in frag
    assert frag.count("c = over(c, base, volume") == 2 and "volume1" not in frag
    # no placeholder left in the code of a line written once per area (its mark stays a comment)
    assert not any("#" in line.split("//")[0] for line in frag.splitlines()
                   if line.endswith(EACH_AREA))
    assert "over(c, base, volume" not in fragment_source([])
    assert (SHADERS / "face.vert").read_text().startswith("#version 300 es\n")
    assert (SHADERS / "render.js").is_file()  # the page's renderer fetches them beside it
    gain = f"p.x / {SCALE_MM:.1f} + shade.z * p.y / {SCALE_MM:.1f}"
    assert gain in frag and f"clamp(g, {LOG_GAIN_MIN:.1f}, {LOG_GAIN_MAX:.1f})" in frag


def test_bad_inputs_raise_value_errors() -> None:
    model = _plane_model([_plane_region("patch", [(200, 200, 200)] * 3, (1.0,) * 3)])
    vertices = model.mesh.vertices
    camera = _plane_camera()
    q = np.zeros(1, np.float32)
    with FaceRenderer(model, 480, 480, samples=0) as renderer:
        with pytest.raises(RenderError, match="vertices"):
            renderer.render(vertices[:-1], q, camera)
        with pytest.raises(RenderError, match="vertices"):
            renderer.render(vertices.astype(np.float64), q, camera)
        bad = vertices.copy()
        bad[3, 0] = np.nan
        with pytest.raises(RenderError, match="vertices"):
            renderer.render(bad, q, camera)
        with pytest.raises(RenderError, match="q"):
            renderer.render(vertices, np.zeros(5, np.float32), camera)
        with pytest.raises(RenderError, match="q"):
            renderer.render(vertices, np.array([np.inf], np.float32), camera)
        with pytest.raises(RenderError, match="shade"):
            renderer.render(vertices, q, camera, np.array([0.0, np.nan, 0.0], np.float32))
        with pytest.raises(RenderError, match="shade"):
            renderer.render(vertices, q, camera, np.zeros(2, np.float32))
        small = Camera(Intrinsics(400.0, 400.0, 159.5, 119.5, 320, 240),
                       Pose(np.eye(3), np.array([0.0, 0.0, -200.0])))
        with pytest.raises(RenderError, match="camera"):
            renderer.render(vertices, q, small)
        # 8 values (a packet's) are accepted; values beyond [0, k - 1] are clamped.
        high = renderer.render(vertices, np.full(8, 9.0, np.float32), camera)
        assert np.array_equal(high, renderer.render(vertices, np.array([2.0], np.float32),
                                                    camera))
    assert issubclass(RenderError, ValueError)
    with pytest.raises(RenderError, match="regions"):
        FaceRenderer(_plane_model([_plane_region(f"r{i}", [(0, 0, 0)], (1.0,))
                                   for i in range(9)]), 64, 64)
    with pytest.raises(RenderError, match="width"):
        FaceRenderer(model, 0, 480)


def _rodrigues(rotation: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotation, np.float64))[0]


def test_sender_view_reproduces_and_scales_the_sender_projection() -> None:
    hello = HelloCamera(601.0, 612.0, 322.3, 236.8, 640, 480)
    rotation, translation = np.array([0.1, -0.25, 0.05]), np.array([12.0, -8.0, -550.0])
    points = generic_head().vertices[generic_head().landmarks].astype(np.float64)
    cam = points @ _rodrigues(rotation).T + translation
    u = hello.cx + hello.fx * cam[:, 0] / -cam[:, 2]
    v = hello.cy - hello.fy * cam[:, 1] / -cam[:, 2]
    same = sender_view(hello, rotation, translation, 640, 480)
    assert np.allclose(same.project(points), np.column_stack([u, v]), atol=1e-9)
    assert np.allclose(sender_view(hello, _rodrigues(rotation), translation, 640, 480)
                       .project(points), same.project(points), atol=1e-9)
    # Twice the size in x, 1.5 times in y: the frame resized (pixel edges at -1/2, W - 1/2).
    scaled = sender_view(hello, rotation, translation, 1280, 720).project(points)
    assert np.allclose(scaled, np.column_stack([2 * (u + 0.5) - 0.5, 1.5 * (v + 0.5) - 0.5]),
                       atol=1e-9)
    with pytest.raises(RenderError, match="rotation"):
        sender_view(hello, np.zeros(4), translation, 640, 480)
    with pytest.raises(RenderError, match="translation"):
        sender_view(hello, rotation, np.zeros(2), 640, 480)


def test_virtual_views_keep_the_head_centre_at_the_image_centre() -> None:
    mesh = generic_head()
    centre, field = head_centre(mesh)
    landmarks = mesh.vertices[mesh.landmarks].astype(np.float64)
    assert np.allclose(head_centre(landmarks)[0], centre)
    nose = landmarks[30]
    for size in ((480, 480), (640, 360)):
        w, h = size
        image_centre = np.array([(w - 1) / 2, (h - 1) / 2])
        for rotation in (np.zeros(3), np.array([0.2, -0.4, 0.1])):
            front = virtual_view("front", mesh, rotation, w, h)
            side = virtual_view("three-quarter", landmarks, rotation, w, h)
            for camera in (front, side):
                assert np.allclose(camera.project(centre[None])[0], image_centre, atol=1e-6)
                # The whole face is in the picture and fills a good part of it.
                px = camera.project(landmarks)
                assert ((px >= 0) & (px < [w, h])).all()
                assert np.ptp(px[:, 1]) > 0.3 * h
        # Front, unturned: the nose is straight ahead; three-quarter: seen from the person's
        # left (the model's +x), the nose points to the image's left.
        straight = virtual_view("front", mesh, np.zeros(3), w, h).project(nose[None])[0]
        assert abs(straight[0] - (w - 1) / 2) < 0.02 * w
        turned = virtual_view("three-quarter", mesh, np.zeros(3), w, h).project(nose[None])[0]
        assert turned[0] < (w - 1) / 2 - 0.05 * h
    # The head turns by the received rotation: yawing it toward +x moves the nose right.
    yawed = virtual_view("front", mesh, np.array([0.0, 0.3, 0.0]), 480, 480)
    assert yawed.project(nose[None])[0, 0] > 239.5 + 10
    with pytest.raises(RenderError, match="kind"):
        virtual_view("profile", mesh, np.zeros(3), 480, 480)
    with pytest.raises(RenderError, match="head"):
        virtual_view("front", landmarks[:10], np.zeros(3), 480, 480)
    assert field > 0
