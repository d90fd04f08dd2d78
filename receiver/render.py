"""The receiver's renderer: the morphed mesh with the neutral texture and the 3D-texture regions.

Each frame the receiver has the morphed vertices (N, 3), one value Q per texture region and a
camera; ``FaceRenderer.render`` draws them offscreen through EGL (moderngl), with the
conventions of ``models.infra.raster`` (GL camera, projection from pinhole intrinsics with pixel
centres at integers, multisampled framebuffer resolved and flipped on readback, texture rows
uploaded bottom first so OpenGL's t is facewire's v). Textured meshes are drawn unlit: the
texture carries the captured light, and the frame's ``shade`` (the packet's) says how the
live light differs from it: every fragment's colour, composited from the texture and the
regions' layers alike, is multiplied at the end by the gain ``models.shading`` defines at
the fragment's model-space (x, y) (interpolated from the morphed vertices; zeros: the
texture's own light, exactly). The triangles and UVs are uploaded once; a frame writes the
vertices into the same buffer (one buffer write) and sets a few uniforms.

Regions (the paper's 3D-texture reconstruction). Region r of the model covers ``uv_rect``
(u0, v0, u1, v1) with k layers L_j (h x w texels, row 0 at v = v1) and alpha
a_j = opacity[j] * mask / 255 over the texture; each of its further areas (``Region.areas``,
the eyelids' lid skin) is drawn the same way with its own rectangle, layers and mask and the
region's opacities and Q, so below "region" means one area of one region. Its layers form a
volume indexed by Q in [0, k - 1] (clamped): the value at (s, t, Q) is the trilinear
interpolation of the stack, bilinear within layers i = floor(Q) and i + 1 and linear
between them with weight Q - i, which is what sampling a 3D texture at depth (Q + 0.5) / k
with LINEAR filtering gives. With
local coordinates s = (u - u0) / (u1 - u0), t = (v - v0) / (v1 - v0) in the rectangle, the
volume is stored premultiplied, relative to the neutral texture B under the region:

    alpha a_j,    colour d_j = a_j (L_j - B)        (float16, per texel),

and a fragment composites the interpolated (a, d) of each region over the colour so far,
starting from the texture, c = B(uv):

    c <- c (1 - a) + (a B(uv) + d)  =  c + a (B(uv) - c) + d.

a B + d is the premultiplied layer colour a L, so this is the "over" operator with
premultiplied colour: a transparent state (opacity 0, the eyelids' open states) has a = d = 0,
and interpolating it with an opaque neighbour never leaks its colour. Storing d relative to B
(rather than a L) makes a layer equal to the texture under it contribute exactly nothing,
whatever the filtering: Q = 0 on a model whose first layers are its neutral texture renders
bit for bit what ``models.infra.raster.MeshRenderer`` draws with the texture alone, and in the
alpha ramp the separately filtered a L and a cannot disagree with the filtered B.

Minification. The model's texture is typically 3-5 times finer than the face on screen (a
2048-texel texture, a face of 300 pixels), so it is mipmapped, and the regions must be too,
or they alias against the smooth skin around them (on a real model at 640 x 480, unfiltered
layers doubled the error against the layers baked into the texture: p99 8 levels, not 3). A
3D texture's mipmaps halve its depth too (they would mix appearance states), so each region
is a 2D array texture of its k layers, mipmapped per layer down to 1/2^``MIP_LEVELS``, and
the shader interpolates between layers i and i + 1 itself: at full resolution this is
exactly the 3D texture's trilinear sampling (LINEAR in s and t, clamped to the edge, linear
in Q). The layers are padded with ``PAD`` = 2^``MIP_LEVELS`` texels of a = d = 0 on every
side (a few more on the right and at the bottom, to make the sizes multiples of ``PAD``, so
that every level halves exactly): at every mip level the outermost texels are then exactly
0, so the rectangle's edge
shows no seam, and a fragment outside the padded rectangle (clamped to that edge) is left
exactly as it was; the shader needs no inside-the-rectangle test, and samples in uniform
control flow, as implicit derivatives for mipmapping require.

Cost on a CPU rasterizer. llvmpipe executes a fragment shader for every pixel of a triangle
with both sides of every branch, so one shader sampling all regions would make every face
pixel pay for them (7 regions: 6 times the time of the texture alone). The triangles are
therefore grouped by the regions their UV bounding box meets (padded rectangles), and each
group is drawn by its own program that composites only those regions (a dozen groups for
the 7 regions; most triangles meet none); a triangle's fragments have UVs inside its UV
bounding box, so the result is the same as compositing every region everywhere. All groups
share the one vertex buffer and one index buffer (``models.draworder``: sorted by group,
keeping the mesh's order within a group; the model's preview draws in the same order).

Model updates (``models.update``). A new version of the model has the same mesh, texture and
region rectangles and more (or other) states in one region: ``update_regions`` uploads that
region's volumes again (k may have grown) and keeps the rest, unless the draw order changed
(a region gained a transparent state), when the caller makes a new renderer
(``receiver.scene.StateRenderer.set_model``). A texture patch (``models.patch``) changes
texels of the texture: ``update_regions`` writes the rectangle that changed
(``receiver.patches``) and rebuilds the texture's mipmaps, and uploads the volumes of the
regions whose layers the patch moved. On llvmpipe an upload costs 7-19 ms, against
12 ms for a 640 x 480 frame.

Draw order. A region whose layers are all opaque (every opacity 1) is composited before the
regions with a transparent state, each set in the model's (packet) order: the eyeballs'
gaze goes first and the eyelids over it, so an open lid shows the gaze and a closing lid
covers it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.models.draworder import MIP_LEVELS, PAD, padded, region_areas, triangle_groups
from facewire.models.infra.egl import create_context, in_context
from facewire.models.infra.raster import (
    Camera,
    ContextOwner,
    OffscreenTarget,
    RenderError,
    check_output,
)
from facewire.models.modelfile import Area, PersonModel
from facewire.models.patch import changed_rect
from facewire.protocol.packet import N_REGIONS
from facewire.receiver.patches import upload_rect

DEFAULT_SAMPLES = 0  # no multisampling: too slow on llvmpipe (FaceRenderer)
_NO_SHADE = np.zeros(3, np.float32)

SHADERS = Path(__file__).with_name("web")  # face.vert, face.frag: also the page's shaders
EACH_AREA = "// each area"  # face.frag's mark of a line written once per composited area


def fragment_source(areas: Sequence[int]) -> str:
    """``face.frag`` for a program compositing ``areas`` (indices): each line marked
    ``EACH_AREA`` written once per area with ``#`` replaced by its index (as render.js's
    ``fragment`` does)."""
    lines: list[str] = []
    for line in (SHADERS / "face.frag").read_text().splitlines():
        if line.endswith(EACH_AREA):
            lines += [line.replace("#", str(a)) for a in areas]
        else:
            lines.append(line)
    return "\n".join(lines) + "\n"


def area_volume(texture: np.ndarray, area: Area, opacity: tuple[float, ...]) -> np.ndarray:
    """An area's layers as stored on the GPU: premultiplied, relative to the texture, padded
    (``models.draworder``).

    Args:
        texture: (H, W, 3) uint8 RGB neutral texture, row 0 at v = 1.
        area: one of a region's ``parts()``; its k layers cover its ``uv_rect``, row 0 at
            v = v1.
        opacity: the region's k layer opacities.

    Returns:
        (k, H', W', 4) float32 (d_r, d_g, d_b, a), 0..1 scale, row 0 at the top: the layers
        at rows and columns [PAD, PAD + h) x [PAD, PAD + w), zeros around them, H' and W' the
        smallest multiples of PAD with at least PAD zeros on every side (module docstring).
    """
    k, h, w, _ = area.layers.shape
    u0, v0, u1, v1 = area.uv_rect
    big_h, big_w = texture.shape[:2]
    # The texture under each layer texel's centre (bilinear; exactly the texture's own texels
    # when the rectangle lies on texel edges with one layer texel per texture texel).
    u = u0 + (np.arange(w) + 0.5) / w * (u1 - u0)
    v = v1 - (np.arange(h) + 0.5) / h * (v1 - v0)
    map_x = np.broadcast_to((u * big_w - 0.5)[None, :], (h, w)).astype(np.float32)
    map_y = np.broadcast_to(((1.0 - v) * big_h - 0.5)[:, None], (h, w)).astype(np.float32)
    under = cv2.remap(texture.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
    alpha = (np.asarray(opacity, np.float32)[:, None, None]
             * (area.mask.astype(np.float32) / 255.0)[None])
    volume = np.zeros((k, padded(h), padded(w), 4), np.float32)
    inner = volume[:, PAD:PAD + h, PAD:PAD + w]
    inner[..., :3] = alpha[..., None] * (area.layers.astype(np.float32) - under) / 255.0
    inner[..., 3] = alpha
    return volume


@dataclass(frozen=True)
class _Group:
    """One draw call: triangles [first, first + count) (in indices) of the sorted index
    buffer, drawn by the program compositing their areas; its per-frame uniforms (each
    area's layer uniform, with the index of the region whose Q sets it)."""

    vao: Any
    first: int
    count: int
    mvp: Any
    shade: Any
    layers: list[tuple[Any, int]]


class FaceRenderer(ContextOwner):
    """Renders a person model's morphed mesh with its texture regions, offscreen (EGL).

    Usage: ``with FaceRenderer(model, w, h) as r: image = r.render(vertices, q, camera)``.

    Attributes:
        width, height: output image size in pixels.
        samples: multisample samples per pixel in use (0: none).
        n_vertices: N, the vertices every frame passes.
        layers: the number of layers of each region, packet order.
        vertex_buffer: the one buffer each frame's vertices are written into.
    """

    def __init__(self, model: PersonModel, width: int, height: int,
                 samples: int = DEFAULT_SAMPLES,
                 background: tuple[int, int, int] = (0, 0, 0)) -> None:
        """Open the context, upload the mesh, the texture and the region volumes.

        Args:
            model: the person model (at most 8 regions, the packet's Q slots).
            width, height: output image size in pixels.
            samples: multisample anti-aliasing samples per pixel (0 or 1: none); clamped to
                what the driver offers. Off by default (``DEFAULT_SAMPLES``): on llvmpipe 4
                samples make a frame 2.5 to 4 times slower; on a GPU they cost little.
            background: RGB colour, 0..255, of pixels no triangle covers.

        Raises:
            RenderError: bad arguments (the message names the field).
            EGLUnavailable: headless OpenGL cannot be used (the message says how to fix it).
        """
        if not isinstance(model, PersonModel):
            raise RenderError(f"model: expected a PersonModel, got {type(model).__name__}")
        check_output(width, height, background)
        if not isinstance(samples, int) or samples < 0:
            raise RenderError(f"samples: expected an int >= 0, got {samples!r}")
        if len(model.regions) > N_REGIONS:
            raise RenderError(f"model.regions: {len(model.regions)} regions, a packet carries "
                              f"at most {N_REGIONS}")
        self.width, self.height = width, height
        self.n_vertices = len(model.mesh.vertices)
        self.layers = tuple(len(r.layers) for r in model.regions)
        r, g, b = background
        self.background = (r / 255.0, g / 255.0, b / 255.0)
        self._ctx = create_context()
        try:
            self._setup(model, samples)
        except BaseException:
            self.release()
            raise

    @in_context
    def _setup(self, model: PersonModel, samples: int) -> None:
        """Create the framebuffers, buffers, textures and programs (``__init__``)."""
        import moderngl

        ctx, mesh, width, height = self._ctx, model.mesh, self.width, self.height
        self._frame = OffscreenTarget(ctx, width, height, samples)
        self.samples = self._frame.samples
        ctx.enable(moderngl.DEPTH_TEST)

        texture = model.texture
        self._texture = ctx.texture((texture.shape[1], texture.shape[0]), 3,
                                    np.ascontiguousarray(texture[::-1]), alignment=1)
        self._texture.repeat_x = self._texture.repeat_y = False
        self._texture.build_mipmaps()
        self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        areas = region_areas(model.regions)  # area a is texture unit 1 + a
        self._model = model
        self._areas = [i for i, _ in areas]
        self._volumes = [self._upload(texture, part, model.regions[i].opacity)
                         for i, part in areas]

        triangles, groups, rects = triangle_groups(mesh.uv, mesh.triangles, areas)
        self.vertex_buffer = ctx.buffer(reserve=self.n_vertices * 12, dynamic=True)
        self._uv = ctx.buffer(np.ascontiguousarray(mesh.uv).tobytes())
        self._indices = ctx.buffer(triangles.tobytes())
        self._groups = []
        vertex = (SHADERS / "face.vert").read_text()
        for mask, first, count in groups:
            met = [a for a in range(len(areas)) if mask >> a & 1]
            program = ctx.program(vertex_shader=vertex, fragment_shader=fragment_source(met))
            program["image"].value = 0
            for a in met:
                u0, v0, u1, v1 = rects[a]
                program[f"rect{a}"].value = (u0, v0, 1.0 / (u1 - u0), 1.0 / (v1 - v0))
                program[f"volume{a}"].value = 1 + a
            vao = ctx.vertex_array(program, [(self.vertex_buffer, "3f", "in_position"),
                                             (self._uv, "2f", "in_uv")],
                                   index_buffer=self._indices, index_element_size=4)
            self._groups.append(_Group(vao, 3 * first, 3 * count, program["mvp"],
                                       program["shade"],
                                       [(program[f"layer{a}"], areas[a][0]) for a in met]))

    def _upload(self, texture: np.ndarray, area: Area, opacity: tuple[float, ...]) -> Any:
        """One area's volume (``area_volume``) as a mipmapped float16 2D array texture."""
        import moderngl

        volume = area_volume(texture, area, opacity)
        k, h, w, _ = volume.shape
        array = self._ctx.texture_array((w, h, k), 4,
                                        np.ascontiguousarray(volume[:, ::-1], np.float16),
                                        dtype="f2")
        array.repeat_x = array.repeat_y = False
        array.build_mipmaps(max_level=MIP_LEVELS)
        array.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        return array

    def can_update(self, model: PersonModel) -> bool:
        """Whether ``model`` is this renderer's model with other region states (a version
        made by ``models.update``: the same mesh, texture, regions' rectangles and draw
        order), so that ``update_regions`` can take it."""
        old = self._model
        return (model.mesh is old.mesh and model.texture.shape == old.texture.shape
                and len(model.regions) == len(old.regions)
                and [i for i, _ in region_areas(model.regions)] == self._areas
                and all(a.uv_rect == b.uv_rect and a.layers.shape[1:] == b.layers.shape[1:]
                        for r, q in zip(model.regions, old.regions, strict=True)
                        for a, b in zip(r.parts(), q.parts(), strict=True)))

    @in_context
    def update_regions(self, model: PersonModel) -> int:
        """Take a new version of the model (``can_update``): the texels of the texture that
        changed (``receiver.patches``) and the volumes of the regions that changed (other
        objects than the current model's) are uploaded again; the number of regions
        uploaded.

        Raises:
            RenderError: ``model`` cannot be taken (``can_update``), or the renderer was
                released.
        """
        if self._ctx is None:
            raise RenderError("update_regions: the renderer was released")
        if not self.can_update(model):
            raise RenderError("update_regions: another mesh, texture, region layout or draw "
                              "order: make a new renderer")
        if model.texture is not self._model.texture:
            rect = changed_rect(self._model.texture, model.texture)
            if rect is not None:
                viewport, data = upload_rect(model.texture, rect)
                self._texture.write(data, viewport=viewport, alignment=1)
                self._texture.build_mipmaps()
        changed = {i for i, (new, old) in enumerate(zip(model.regions, self._model.regions,
                                                         strict=True)) if new is not old}
        for a, (i, part) in enumerate(region_areas(model.regions)):
            if i in changed:
                self._volumes[a].release()
                self._volumes[a] = self._upload(model.texture, part, model.regions[i].opacity)
        self._model = model
        self.layers = tuple(len(r.layers) for r in model.regions)
        return len(changed)

    @in_context
    def render(self, vertices: np.ndarray, q: np.ndarray, camera: Camera,
               shade: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Draw one frame.

        Args:
            vertices: (N, 3) float32 morphed model-space positions, mm.
            q: (R,) or (8,) float32 region values in layers, packet order (R = the model's
                regions; of 8 values, the first R are used); each is clamped to [0, k - 1].
            camera: a ``models.infra.raster.Camera`` whose image size is this renderer's.
            shade: (3,) the light's log-gain field (``models.shading``); None: zeros, the
                texture's own light.
            out: (height, width, 3) uint8 array to write the image into (e.g. a slot of
                ``receiver.renderprocess``'s shared memory), or None for a new array.

        Returns:
            (height, width, 3) uint8 RGB image, top row first (``out`` when given).

        Raises:
            RenderError: wrong shapes or dtypes, non-finite values, a camera of another size,
                or a released renderer.
        """
        if self._ctx is None:
            raise RenderError("render: the renderer was released")
        if not isinstance(vertices, np.ndarray) or vertices.dtype != np.float32 \
                or vertices.shape != (self.n_vertices, 3):
            raise RenderError(f"vertices: expected a float32 array of shape "
                              f"({self.n_vertices}, 3), got {_describe(vertices)}")
        if not np.isfinite(vertices).all():
            raise RenderError("vertices: contains NaN or infinity")
        n_regions = len(self.layers)
        if not isinstance(q, np.ndarray) or q.dtype != np.float32 \
                or q.shape not in ((n_regions,), (N_REGIONS,)):
            raise RenderError(f"q: expected a float32 array of shape ({n_regions},) or "
                              f"({N_REGIONS},), got {_describe(q)}")
        if not np.isfinite(q[:n_regions]).all():
            raise RenderError("q: contains NaN or infinity")
        if shade is None:
            shade = _NO_SHADE
        if not isinstance(shade, np.ndarray) or shade.shape != (3,) \
                or not np.isfinite(shade).all():
            raise RenderError(f"shade: expected 3 finite values, got {_describe(shade)}")
        if out is not None and (not isinstance(out, np.ndarray) or out.dtype != np.uint8
                                or out.shape != (self.height, self.width, 3)):
            raise RenderError(f"out: expected a uint8 array of shape ({self.height}, "
                              f"{self.width}, 3), got {_describe(out)}")
        if not isinstance(camera, Camera):
            raise RenderError(f"camera: expected a models.infra.raster.Camera, got "
                              f"{type(camera).__name__}")
        size = (camera.intrinsics.width, camera.intrinsics.height)
        if size != (self.width, self.height):
            raise RenderError(f"camera: image {size[0]} x {size[1]}, renderer "
                              f"{self.width} x {self.height}")

        self.vertex_buffer.write(np.ascontiguousarray(vertices))
        mvp = (camera.projection_matrix() @ camera.view_matrix()).astype(np.float32)
        mvp_bytes = mvp.T.tobytes()  # GLSL matrices are column-major
        layers = []
        for k, value in zip(self.layers, q):
            depth = min(max(float(value), 0.0), k - 1.0)
            below = float(np.floor(depth))
            layers.append((below, min(below + 1.0, k - 1.0), depth - below))
        self._texture.use(0)
        for i, volume in enumerate(self._volumes):
            volume.use(1 + i)
        self._frame.begin(self.background)
        light = tuple(float(s) for s in shade)
        for group in self._groups:
            group.mvp.write(mvp_bytes)
            group.shade.value = light
            for uniform, i in group.layers:
                uniform.value = layers[i]
            group.vao.render(vertices=group.count, first=group.first)
        return self._frame.read(out)



def _describe(a: object) -> str:
    """'float64 array of shape (3, 2)' or the type's name, for error messages."""
    if isinstance(a, np.ndarray):
        return f"a {a.dtype.name} array of shape {a.shape}"
    return type(a).__name__
