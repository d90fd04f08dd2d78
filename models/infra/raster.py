"""Offscreen rendering of a triangle mesh, textured or grey-shaded (moderngl through EGL).

Camera (the "GL camera" of docs/DESIGN.md §2 and ``models.geometry``): intrinsics and a pose
that maps model to camera, X_cam = R X + t, with x right, y up and the camera looking along -z.
Pixels have their origin at the top-left, rows down, and pixel (i, j) has its centre at
(u, v) = (i, j), as dlib and OpenCV place it:

    u = cx + fx * X / (-Z),        v = cy - fy * Y / (-Z).

OpenGL's window x of pixel i spans [i, i + 1] with its centre at i + 1/2, and its rows count
from the bottom. So NDC x = 2 (u + 1/2) / W - 1 and NDC y = 1 - 2 (v + 1/2) / H, and with
w_clip = -Z the projection matrix is

    [ 2 fx / W   0          1 - 2 (cx + 1/2) / W    0              ]
    [ 0          2 fy / H   2 (cy + 1/2) / H - 1    0              ]
    [ 0          0          -(f + n) / (f - n)      -2 f n / (f - n)]
    [ 0          0          -1                      0              ]

with near and far planes n, f (mm). The framebuffer is therefore rendered bottom row first,
as OpenGL stores it, and flipped on readback; triangles are drawn from both sides.

Texture: (H, W, 3) uint8 RGB, top row first, sampled with facewire's v-up UVs
(texel row = (1 - v) * H), so the image is uploaded bottom row first to OpenGL's t = v.
Textured meshes are drawn unlit: the texture was captured under the scene's light and
shading it again would darken it twice. Untextured meshes are drawn grey with Lambert shading
(two-sided, per-vertex normals recomputed from the vertices of each frame, a light above-left
of the camera), for looking at geometry.

The mesh's triangles and UVs are uploaded once (``set_mesh``); each ``render`` writes the
frame's vertices into the same vertex buffer, since the morph moves them every frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Self

import numpy as np

from facewire.models.arrays import check_array
from facewire.models.geometry import Intrinsics, Pose, project, vertex_normals
from facewire.models.infra.egl import create_context, in_context
from facewire.protocol.errors import FacewireError


class RenderError(FacewireError, ValueError):
    """A render input has the wrong shape, dtype or value; the message names the field."""


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera to render from: intrinsics, a pose and clipping planes.

    Attributes:
        intrinsics: fx, fy, cx, cy in pixels of the output image, whose size it gives.
        pose: model to camera, X_cam = R X + t (mm).
        near, far: clipping distances in mm in front of the camera, 0 < near < far.
    """

    intrinsics: Intrinsics
    pose: Pose
    near: float = 10.0
    far: float = 10000.0

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise RenderError(f"camera.intrinsics: expected a models.geometry.Intrinsics, got "
                              f"{type(self.intrinsics).__name__}")
        if not isinstance(self.pose, Pose):
            raise RenderError(f"camera.pose: expected a models.geometry.Pose, got "
                              f"{type(self.pose).__name__}")
        if not (np.isfinite(self.near) and np.isfinite(self.far) and 0 < self.near < self.far):
            raise RenderError(f"camera.near, far: need finite 0 < near < far, got {self.near}, "
                              f"{self.far}")

    @classmethod
    def virtual(cls, width: int, height: int, pose: Pose, fov_y_deg: float = 30.0) -> Camera:
        """A square-pixel camera with its principal point at the image centre.

        Args:
            width, height: image size in pixels.
            pose: the camera's pose, e.g. from ``orbit_pose``.
            fov_y_deg: vertical field of view in degrees, in (0, 180).
        """
        if not 0 < fov_y_deg < 180:
            raise RenderError(f"fov_y_deg: expected (0, 180), got {fov_y_deg}")
        f = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2)
        try:
            intrinsics = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
        except ValueError as e:
            raise RenderError(f"camera.{e}") from e
        return cls(intrinsics, pose)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates of model points (``models.geometry.project``).

        Args:
            points: (K, 3) model-space points in mm, in front of the camera.

        Returns:
            (K, 2) float64 (u, v): column and row, origin top-left, pixel centres at integers.
        """
        return project(points, self.pose, self.intrinsics)

    def projection_matrix(self) -> np.ndarray:
        """(4, 4) float64 OpenGL projection, camera frame to clip space (module docstring)."""
        c, n, f = self.intrinsics, self.near, self.far
        w, h = c.width, c.height
        return np.array([
            [2 * c.fx / w, 0, 1 - 2 * (c.cx + 0.5) / w, 0],
            [0, 2 * c.fy / h, 2 * (c.cy + 0.5) / h - 1, 0],
            [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0, 0, -1, 0]])

    def view_matrix(self) -> np.ndarray:
        """(4, 4) float64 model-to-camera transform [R t; 0 1]."""
        m = np.eye(4)
        m[:3, :3] = self.pose.rotation
        m[:3, 3] = self.pose.translation
        return m


def orbit_pose(yaw_deg: float, pitch_deg: float, distance_mm: float,
               target: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
               ) -> Pose:
    """The pose of a camera on a sphere around ``target``, looking at it, model y up.

    Yaw 0, pitch 0 puts the camera on the model's +z axis, in front of the face. Positive yaw
    turns the camera about the model's y axis toward +x (the person's left: a three-quarter
    view of the left cheek); positive pitch raises it to look down.

    Args:
        yaw_deg, pitch_deg: angles in degrees.
        distance_mm: distance from the camera to ``target`` (> 0).
        target: (3,) model-space point in mm at the centre of the image.

    Returns:
        The pose, X_cam = R X + t.
    """
    if not distance_mm > 0:
        raise RenderError(f"distance_mm: must be positive, got {distance_mm}")
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    turn = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    tilt = np.array([[1, 0, 0], [0, np.cos(pitch), np.sin(pitch)],
                     [0, -np.sin(pitch), np.cos(pitch)]])  # rotation about x by -pitch
    camera_to_model = turn @ tilt
    centre = np.asarray(target, dtype=np.float64) + distance_mm * camera_to_model[:, 2]
    rotation = camera_to_model.T
    return Pose(rotation, -rotation @ centre)


# v_model: the fragment's model-space (x, y), mm, for a light field over model space
# (``receiver.render``; a fragment shader that does not read it ignores it).
VERTEX_TEXTURED = """
#version 330
uniform mat4 mvp;
in vec3 in_position;
in vec2 in_uv;
out vec2 v_uv;
out vec2 v_model;
void main() {
    gl_Position = mvp * vec4(in_position, 1.0);
    v_uv = in_uv;
    v_model = in_position.xy;
}
"""

_FRAGMENT_TEXTURED = """
#version 330
uniform sampler2D image;
in vec2 v_uv;
out vec4 f_color;
void main() {
    f_color = vec4(texture(image, v_uv).rgb, 1.0);
}
"""

_VERTEX_SHADED = """
#version 330
uniform mat4 mvp;
uniform mat3 rotation;
in vec3 in_position;
in vec3 in_normal;
out vec3 v_normal;
void main() {
    gl_Position = mvp * vec4(in_position, 1.0);
    v_normal = rotation * in_normal;
}
"""

_FRAGMENT_SHADED = """
#version 330
const vec3 light = normalize(vec3(-0.3, 0.5, 1.0));  // camera frame: above-left, in front
in vec3 v_normal;
out vec4 f_color;
void main() {
    float lambert = abs(dot(normalize(v_normal), light));
    f_color = vec4(vec3(0.8 * (0.25 + 0.75 * lambert)), 1.0);
}
"""


class OffscreenTarget:
    """A ``width`` x ``height`` RGB colour and depth target in a moderngl context, with
    ``samples``-fold multisampling when the driver offers it (resolved before reading).

    Attributes:
        samples: the multisample count in use (0: none).
    """

    def __init__(self, ctx: Any, width: int, height: int, samples: int) -> None:
        samples = min(samples, ctx.max_samples) if samples > 1 else 0
        self.samples = samples
        self._ctx = ctx
        self._resolved = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height))],
                                         depth_attachment=None if samples else
                                         ctx.depth_renderbuffer((width, height)))
        self._target = self._resolved
        if samples:
            self._target = ctx.framebuffer(
                color_attachments=[ctx.renderbuffer((width, height), samples=samples)],
                depth_attachment=ctx.depth_renderbuffer((width, height), samples=samples))
        self._pixels = np.empty((height, width, 3), dtype=np.uint8)

    def begin(self, background: tuple[float, float, float]) -> None:
        """Draw into the target from now on, cleared to ``background`` (RGB, 0..1)."""
        self._target.use()
        self._target.clear(*background, 1.0, depth=1.0)

    def read(self, out: np.ndarray | None = None) -> np.ndarray:
        """(height, width, 3) uint8 RGB of what was drawn, top row first: a new array, or
        ``out`` (an array of that shape and dtype, e.g. in shared memory) filled."""
        if self._target is not self._resolved:
            self._ctx.copy_framebuffer(self._resolved, self._target)
        self._resolved.read_into(self._pixels, components=3, alignment=1)
        if out is None:
            return self._pixels[::-1].copy()
        np.copyto(out, self._pixels[::-1])
        return out


def check_output(width: int, height: int, background: tuple[int, int, int]) -> None:
    """Refuse an output size that is not two positive ints or a background that is not an
    RGB triple in 0..255 (``RenderError`` naming the field)."""
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise RenderError(f"width, height: expected positive ints, got {width!r}, {height!r}")
    if len(background) != 3 or not all(0 <= c <= 255 for c in background):
        raise RenderError(f"background: expected 3 values in 0..255, got {background!r}")


class ContextOwner:
    """An object that owns a moderngl context (``self._ctx``): ``release`` frees it and
    everything in it; usable as a context manager."""

    _ctx: Any = None

    def release(self) -> None:
        """Free the OpenGL context and everything in it."""
        if self._ctx is not None:
            self._ctx.release()
            self._ctx = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class MeshRenderer(ContextOwner):
    """Renders one mesh offscreen through its own EGL OpenGL context.

    Usage: ``set_mesh`` once, ``set_texture`` (or not, for grey shading), then ``render``
    every frame with the frame's vertices. Call ``release`` (or use ``with``) when done.
    """

    def __init__(self, width: int, height: int, samples: int = 4,
                 background: tuple[int, int, int] = (0, 0, 0)) -> None:
        """Open the context and the framebuffers.

        Args:
            width, height: output image size in pixels.
            samples: multisample anti-aliasing samples per pixel (0 or 1: none); clamped to
                what the driver offers.
            background: RGB colour, 0..255, of pixels no triangle covers.

        Raises:
            EGLUnavailable: headless OpenGL cannot be used (the message says how to fix it).
        """
        import moderngl

        check_output(width, height, background)
        ctx = create_context()
        self._ctx = ctx
        self.width, self.height = width, height
        r, g, b = background
        self.background = (r / 255.0, g / 255.0, b / 255.0)
        self._frame = OffscreenTarget(ctx, width, height, samples)
        self.samples = self._frame.samples
        ctx.enable(moderngl.DEPTH_TEST)
        self._textured = ctx.program(vertex_shader=VERTEX_TEXTURED,
                                     fragment_shader=_FRAGMENT_TEXTURED)
        self._shaded = ctx.program(vertex_shader=_VERTEX_SHADED,
                                   fragment_shader=_FRAGMENT_SHADED)
        self._n_vertices = 0
        self._triangles: np.ndarray | None = None
        # moderngl's Buffer, VertexArray and Texture objects (set_mesh, set_texture)
        self._positions: Any = None
        self._normals: Any = None
        self._uv: Any = None
        self._indices: Any = None
        self._vao_textured: Any = None
        self._vao_shaded: Any = None
        self._texture: Any = None

    @in_context
    def set_mesh(self, n_vertices: int, triangles: np.ndarray,
                 uv: np.ndarray | None = None) -> None:
        """Upload the mesh's fixed parts: its triangles and UVs.

        Args:
            n_vertices: N, the number of vertices every ``render`` will pass.
            triangles: (M, 3) int32 vertex indices.
            uv: (N, 2) float32 texture coordinates, v up, or None (grey shading only).
        """
        if not isinstance(n_vertices, int) or n_vertices < 1:
            raise RenderError(f"n_vertices: expected a positive int, got {n_vertices!r}")
        check_array("triangles", triangles, np.int32, (None, 3), RenderError)
        if len(triangles) == 0 or triangles.min() < 0 or triangles.max() >= n_vertices:
            raise RenderError(f"triangles: empty, or a vertex index outside [0, {n_vertices})")
        if uv is not None:
            check_array("uv", uv, np.float32, (n_vertices, 2), RenderError)
        self._release_mesh()
        ctx = self._ctx
        self._n_vertices = n_vertices
        self._triangles = np.ascontiguousarray(triangles)
        self._positions = ctx.buffer(reserve=n_vertices * 12, dynamic=True)
        self._normals = ctx.buffer(reserve=n_vertices * 12, dynamic=True)
        self._indices = ctx.buffer(self._triangles.tobytes())
        self._vao_shaded = ctx.vertex_array(
            self._shaded, [(self._positions, "3f", "in_position"),
                           (self._normals, "3f", "in_normal")],
            index_buffer=self._indices, index_element_size=4)
        if uv is not None:
            self._uv = ctx.buffer(np.ascontiguousarray(uv).tobytes())
            self._vao_textured = ctx.vertex_array(
                self._textured, [(self._positions, "3f", "in_position"),
                                 (self._uv, "2f", "in_uv")],
                index_buffer=self._indices, index_element_size=4)

    @in_context
    def set_texture(self, texture: np.ndarray | None) -> None:
        """Upload the texture, or remove it (None) to draw grey-shaded geometry.

        Args:
            texture: (H, W, 3) uint8 RGB, top row first, or None.
        """
        import moderngl

        if self._texture is not None:
            self._texture.release()
            self._texture = None
        if texture is None:
            return
        check_array("texture", texture, np.uint8, (None, None, 3), RenderError)
        h, w = texture.shape[:2]
        self._texture = self._ctx.texture((w, h), 3, np.ascontiguousarray(texture[::-1]),
                                          alignment=1)
        self._texture.repeat_x = self._texture.repeat_y = False
        self._texture.build_mipmaps()
        self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)

    @in_context
    def render(self, vertices: np.ndarray, camera: Camera) -> np.ndarray:
        """Draw the mesh with this frame's vertices.

        Args:
            vertices: (N, 3) float32 model-space positions in mm.
            camera: a camera whose image size is this renderer's.

        Returns:
            (height, width, 3) uint8 RGB image, top row first.
        """
        if self._triangles is None:
            raise RenderError("render: call set_mesh first")
        check_array("vertices", vertices, np.float32, (self._n_vertices, 3), RenderError)
        size = (camera.intrinsics.width, camera.intrinsics.height)
        if size != (self.width, self.height):
            raise RenderError(f"camera: image {size[0]} x {size[1]}, renderer "
                              f"{self.width} x {self.height}")
        mvp = (camera.projection_matrix() @ camera.view_matrix()).astype(np.float32)
        self._positions.write(np.ascontiguousarray(vertices))
        if self._texture is not None:
            if self._vao_textured is None:
                raise RenderError("render: a texture needs the mesh's uv (set_mesh)")
            vao, program = self._vao_textured, self._textured
            self._texture.use(0)
            program["image"].value = 0
        else:
            vao, program = self._vao_shaded, self._shaded
            self._normals.write(vertex_normals(vertices, self._triangles))
            program["rotation"].write(camera.pose.rotation.T.astype(np.float32).tobytes())
        program["mvp"].write(mvp.T.tobytes())  # GLSL matrices are column-major
        self._frame.begin(self.background)
        vao.render()
        return self._frame.read()

    def _release_mesh(self) -> None:
        for obj in (self._vao_textured, self._vao_shaded, self._positions, self._normals,
                    self._uv, self._indices):
            if obj is not None:
                obj.release()
        self._vao_textured = self._uv = None
