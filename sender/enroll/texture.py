"""The person model's base texture: camera frames projected onto the mesh's UV layout.

This module holds the texture's space, each view's projection onto it and the filling of
its holes; how the projected views are fused into one texture is ``sender.enroll.fusion``.

Texture space. A texture of ``H`` rows and ``W`` columns (default 512 x 1024, the paper's
2:1) is sampled with facewire's v-up UVs (``models.mesh``): texel (row r, column c) has its
centre at ``u = (c + 1/2) / W``, ``v = 1 - (r + 1/2) / H``, where OpenGL samples it.

1. Surface of each texel (``uv_surface``). The mesh is drawn into a W x H float framebuffer
   with its UVs as positions, ``gl_Position = (2u - 1, 2v - 1, 0, 1)`` (OpenGL's window row j
   counts from the bottom, at v = (j + 1/2) / H, so the readback is flipped to top row first).
   The rasteriser evaluates each covering triangle at the texel centre, so every texel inside
   a UV triangle gets its model-space point P (mm), its interpolated vertex normal n and the
   triangle's index. Normals are averaged over vertices that share a position, so the two
   copies of a vertex on a UV seam get one normal and weigh views alike on both sides.
   Texels outside every triangle are "uncovered". The layout must lie in [0, 1]^2 and be
   one-to-one: a second pass counts the triangles over each texel (additive blending) and
   more than 1 % of covered texels under two or more (a mirrored or stacked layout) is
   refused, since one texel cannot hold two surface points' colours.

2. One view (``project_views``): a BGR image and a ``models.infra.raster.Camera``
   (intrinsics and the head pose, ``X_cam = R P + t``, pixel centres at integers). A depth
   pass renders the camera's depth map ``D = -Z_cam`` (mm) and the cosine of the view angle
   at each pixel. Each texel's P projects to ``(x, y) = (cx + fx X / d, cy - fy Y / d)``
   with ``d = -Z_cam``; its view angle is ``cos a = n . (C - P) / |C - P|`` with
   ``C = -R^T t`` the camera centre. With the pixel size ``s = d / f`` (mm,
   ``f = (fx + fy) / 2``) a surface turned by ``a`` changes depth by ``s tan a`` per pixel,
   so the texel is *visible* when ``cos a > cos_min``, ``d > near``, (x, y) lies in the
   image, and all four pixels of its bilinear footprint hold depth within

       tol = s (1 + 1.5 tan a)            (the footprint reaches sqrt(2) pixels away)

   of d: a nearer surface (occluder), the background or another surface at a silhouette in
   the footprint rejects the texel. Its colour is the image sampled bilinearly at (x, y) and
   its weight is

       w = ((cos a - cos_min) / (1 - cos_min))^k * smoothstep(clip((e - 2.5) / feather, 0, 1)),

   where ``e`` is the distance in pixels from (x, y) to the nearest *edge pixel* of the
   camera's image: background, the image border, or a depth step between 4-neighbours larger
   than the same tolerance taken at the more frontal of the two pixels (an occluder's rim is
   grazing, the surface behind it usually is not), i.e. an occlusion boundary; and, when the
   view's silhouette is given (``sender.enroll.silhouette``), every pixel outside the person:
   the mesh's outline is the generic head's beyond the jaw, and where it is wider than the
   real head its texels would take the room's colours. The 2.5 px
   margin keeps the footprint (up to sqrt(2) px from (x, y)) off the pixel next to an edge,
   whose colour is part background in any real or anti-aliased image. The first factor
   prefers views that see the surface frontally (a texel's footprint in the image shrinks
   with cos a, so grazing views are blurred and stretched); the second fades a view out over
   ``feather`` pixels before its coverage ends, so where one view's coverage stops the next
   view has already taken over and no seam appears.

   Colours are taken as the camera saw them (lit), and point-sampled: a view whose pixels are
   much finer than the texels (a close-up) is not low-passed first.

3. Fusion: the views projected by ``sample_views`` are fused into one texture by
   ``sender.enroll.fusion.fuse_views`` (exposure, a robust consensus, alignment, colour).

4. Holes (``fill_holes``): texels no view saw and texels outside the UV islands. First
   ``pad`` rings around the valid texels are grown, each new texel the mean of its valid
   8-neighbours, so bilinear sampling at island borders reads the border's own colour. The
   rest is filled by push-pull (Gortler et al. 1996, "The Lumigraph"): pull builds a pyramid
   of weighted means, level l+1 = pyrDown(w_l c_l) / pyrDown(w_l) with weight
   w_{l+1} = min(1, 4 pyrDown(w_l)); push goes back down, c_l <- w_l c_l + (1 - w_l)
   pyrUp(c_{l+1}). Valid texels (weight 1) keep their colour exactly; every hole gets a
   smooth blend of the nearest valid colours, at the scale of the hole, and the whole texture
   is filled, so mipmaps never average in a black background.

"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from facewire.models.infra.egl import create_context, in_context
from facewire.models.infra.raster import Camera
from facewire.models.mesh import Mesh
from facewire.protocol.errors import FacewireError
from facewire.sender.texels import welded_normals

DEFAULT_SIZE = (512, 1024)
MAX_SIZE = 8192
MAX_OVERLAP = 0.01  # fraction of covered texels that two UV triangles may share
_MAX_TRIANGLES = 2 ** 24  # triangle index + 1 travels as a float32
EDGE_MARGIN_PX = 2.5  # a bilinear footprint (sqrt 2) plus the blended pixel at a rim


class TextureError(FacewireError, ValueError):
    """A texture input has the wrong shape, dtype or value; the message names the field."""


@dataclass(frozen=True, eq=False)
class UVSurface:
    """The mesh surface point behind every texel of an (H, W) texture.

    Attributes:
        positions: (H, W, 3) float32 model-space points in mm (0 where uncovered).
        normals: (H, W, 3) float32 unit normals (0 where uncovered).
        triangles: (H, W) int32 index of the mesh triangle at the texel, -1 where uncovered.
    """

    positions: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray

    @property
    def covered(self) -> np.ndarray:
        """(H, W) bool: the texel lies inside a UV triangle."""
        return self.triangles >= 0

    @property
    def size(self) -> tuple[int, int]:
        """(H, W): texture rows and columns."""
        return self.triangles.shape


def uv_surface(mesh: Mesh, size: tuple[int, int] = DEFAULT_SIZE) -> UVSurface:
    """Rasterise the mesh in UV space: the surface point, normal and triangle of each texel.

    Args:
        mesh: the mesh; its UVs should form a non-overlapping layout in [0, 1]^2.
        size: (H, W) texture rows and columns, each in [1, 8192].

    Returns:
        The texel surface (see ``UVSurface``).

    Raises:
        TextureError: bad mesh or size.
        EGLUnavailable: headless OpenGL cannot be used.
    """
    if not isinstance(mesh, Mesh):
        raise TextureError(f"mesh: expected a models.mesh.Mesh, got {type(mesh).__name__}")
    height, width = _check_size(size)
    if len(mesh.triangles) >= _MAX_TRIANGLES:
        raise TextureError(f"mesh.triangles: {len(mesh.triangles)}, more than the "
                           f"{_MAX_TRIANGLES - 1} a float32 triangle index holds exactly")
    if mesh.uv.size and (mesh.uv.min() < 0 or mesh.uv.max() > 1):
        raise TextureError(f"mesh.uv: outside [0, 1] (range {mesh.uv.min():.4g} .. "
                           f"{mesh.uv.max():.4g}); the layout must lie in the texture")
    normals = welded_normals(mesh)
    with _Gl() as gl:
        positions, normal_id, layers = gl.uv_pass(mesh, normals, width, height)
    triangles = np.rint(normal_id[..., 3]).astype(np.int32) - 1
    covered = triangles >= 0
    overlap = np.count_nonzero(layers > 1.5) / max(1, int(np.count_nonzero(covered)))
    if overlap > MAX_OVERLAP:
        raise TextureError(f"mesh.uv: triangles overlap on {100 * overlap:.1f} % of the "
                           f"covered texels (at most {100 * MAX_OVERLAP:g} %); a texture needs "
                           f"a one-to-one UV layout (no mirrored or stacked islands)")
    normals = normal_id[..., :3]
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    normals = np.where(covered[..., None] & (length > 1e-12), normals / np.maximum(length, 1e-12),
                       0).astype(np.float32)
    positions = np.where(covered[..., None], positions[..., :3], 0).astype(np.float32)
    return UVSurface(np.ascontiguousarray(positions), np.ascontiguousarray(normals), triangles)


def check_views(mesh: object, surface: object, views: object, *, sharpness: float,
                cos_min: float, feather_px: float, silhouettes: object = None) -> None:
    """Check the inputs of ``sample_views`` (see ``sender.enroll.fusion.fuse_views``).

    Raises:
        TextureError: the first bad input, named.
    """
    if not isinstance(mesh, Mesh):
        raise TextureError(f"mesh: expected a models.mesh.Mesh, got {type(mesh).__name__}")
    _check_surface(surface, len(mesh.triangles))
    if not (np.isfinite(sharpness) and sharpness >= 0):
        raise TextureError(f"sharpness: expected a number >= 0, got {sharpness}")
    if not 0 <= cos_min < 1:
        raise TextureError(f"cos_min: expected [0, 1), got {cos_min}")
    if not (np.isfinite(feather_px) and feather_px > 0):
        raise TextureError(f"feather_px: expected a positive number, got {feather_px}")
    if not isinstance(views, (list, tuple)) or len(views) == 0:
        raise TextureError("views: expected a non-empty list of (image, camera)")
    for i, view in enumerate(views):
        _check_view(i, view)
    if silhouettes is None:
        return
    if not isinstance(silhouettes, (list, tuple)) or len(silhouettes) != len(views):
        raise TextureError(f"silhouettes: expected a list of {len(views)} masks, one per view")
    for i, (mask, (image, _)) in enumerate(zip(silhouettes, views)):
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ \
                or mask.shape != image.shape[:2]:
            raise TextureError(f"silhouettes[{i}]: expected a {image.shape[:2]} bool array, "
                               f"got {_describe(mask)}")


def sample_views(mesh: Mesh, surface: UVSurface, views: list[tuple[np.ndarray, Camera]], *,
                 sharpness: float, cos_min: float, feather_px: float,
                 silhouettes: list[np.ndarray] | None = None,
                 ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Project each view onto the covered texels (module docstring, 2); inputs as checked by
    ``check_views``; ``silhouettes``: per view the person's pixels, (h, w) bool
    (``sender.enroll.silhouette``), the others edge pixels; None: every pixel may be.

    Returns:
        Per view, in the given order: the colour (K, 3) float32 BGR as the camera saw it and
        the weight (K,) float32 (0: not visible) of the K covered texels (row-major).

    Raises:
        EGLUnavailable: headless OpenGL cannot be used.
    """
    covered = surface.covered
    points = surface.positions[covered]
    normals = surface.normals[covered]
    colours, weights = [], []
    with _Gl() as gl:
        for i, (image, camera) in enumerate(views):
            depth, cos_pixel = gl.depth_pass(mesh, camera)
            person = None if silhouettes is None else silhouettes[i]
            colour, weight = _sample_view(image, camera, depth, cos_pixel, person, points,
                                          normals, sharpness, cos_min, feather_px)
            colours.append(colour)
            weights.append(weight)
    return colours, weights


def fill_holes(texture: np.ndarray, valid: np.ndarray, pad: int = 8) -> np.ndarray:
    """Fill every invalid texel from the valid ones around it (module docstring, 4).

    Args:
        texture: (H, W, C) uint8 image, any channel order, C >= 1.
        valid: (H, W) bool, the texels to keep (at least one).
        pad: rings of texels around valid ones filled by neighbour means before push-pull
            (>= 0).

    Returns:
        (H, W, C) uint8: equal to ``texture`` where ``valid``, filled elsewhere.

    Raises:
        TextureError: bad inputs, named, or no valid texel.
    """
    if not isinstance(texture, np.ndarray) or texture.dtype != np.uint8 or texture.ndim != 3 \
            or texture.shape[2] < 1 or texture.shape[0] < 1 or texture.shape[1] < 1:
        raise TextureError(f"texture: expected an (H, W, C) uint8 array, got "
                           f"{_describe(texture)}")
    if not isinstance(valid, np.ndarray) or valid.dtype != np.bool_ \
            or valid.shape != texture.shape[:2]:
        raise TextureError(f"valid: expected a {texture.shape[:2]} bool array, got "
                           f"{_describe(valid)}")
    if not (isinstance(pad, (int, np.integer)) and pad >= 0):
        raise TextureError(f"pad: expected an int >= 0, got {pad!r}")
    if not valid.any():
        raise TextureError("valid: no valid texel to fill from")
    colour = texture.astype(np.float32)
    weight = valid.astype(np.float32)
    for _ in range(pad):
        neighbours = cv2.boxFilter(weight, -1, (3, 3), normalize=False,
                                   borderType=cv2.BORDER_CONSTANT)
        ring = (weight == 0) & (neighbours > 0)
        if not ring.any():
            break
        sums = _channels(cv2.boxFilter(colour * weight[..., None], -1, (3, 3), normalize=False,
                                       borderType=cv2.BORDER_CONSTANT))
        colour[ring] = sums[ring] / neighbours[ring][:, None]
        weight[ring] = 1.0
    filled = _push_pull(colour, weight)
    out = np.clip(np.rint(filled), 0, 255).astype(np.uint8)
    out[valid] = texture[valid]
    return out


def _push_pull(colour: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 colours with weights in [0, 1] -> every texel filled (weight 1 kept)."""
    if weight.min() >= 1.0:
        return colour
    if min(weight.shape) <= 1:
        total = weight.sum()
        return np.broadcast_to((colour * weight[..., None]).sum(axis=(0, 1)) / total,
                               colour.shape).astype(np.float32)
    den = cv2.pyrDown(weight)
    num = _channels(cv2.pyrDown(colour * weight[..., None]))
    coarse = np.where(den[..., None] > 1e-12, num / np.maximum(den, 1e-12)[..., None], 0)
    coarse = _push_pull(coarse.astype(np.float32), np.minimum(1.0, 4.0 * den))
    height, width = weight.shape
    up = _channels(cv2.pyrUp(coarse, dstsize=(width, height)))
    return weight[..., None] * colour + (1.0 - weight[..., None]) * up


def _channels(a: np.ndarray) -> np.ndarray:
    """OpenCV drops a trailing channel axis of length 1; put it back."""
    return a[..., None] if a.ndim == 2 else a


def _sample_view(image: np.ndarray, camera: Camera, depth: np.ndarray, cos_pixel: np.ndarray,
                 person: np.ndarray | None, points: np.ndarray, normals: np.ndarray,
                 sharpness: float, cos_min: float, feather_px: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Colour (K, 3) float32 BGR and weight (K,) float32 of K texel points in one view
    (``person``: its silhouette, (h, w) bool, or None)."""
    pose, k = camera.pose, camera.intrinsics
    rotation = pose.rotation.astype(np.float32)
    cam = points @ rotation.T + pose.translation.astype(np.float32)
    dist = -cam[:, 2]
    centre = (-pose.rotation.T @ pose.translation).astype(np.float32)
    ray = centre - points
    cos = np.einsum("ij,ij->i", normals, ray) / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
    h, w = depth.shape
    safe = np.maximum(dist, camera.near)
    x = k.cx + k.fx * cam[:, 0] / safe
    y = k.cy - k.fy * cam[:, 1] / safe
    ok = (dist > camera.near) & (cos > cos_min) & (x >= 0) & (x <= w - 1) & (y >= 0) \
        & (y <= h - 1)
    focal = 0.5 * (k.fx + k.fy)
    tol = _tolerance(dist, cos, focal, cos_min)
    i0 = np.clip(np.floor(x), 0, w - 1).astype(np.intp)
    j0 = np.clip(np.floor(y), 0, h - 1).astype(np.intp)
    i1, j1 = np.minimum(i0 + 1, w - 1), np.minimum(j0 + 1, h - 1)
    for jj, ii in ((j0, i0), (j0, i1), (j1, i0), (j1, i1)):
        ok &= np.abs(depth[jj, ii] - dist) < tol
    edges = _edges(depth, cos_pixel, focal, cos_min)
    if person is not None:
        edges |= ~person
    edge_distance = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2,
                                          cv2.DIST_MASK_PRECISE)
    x = np.where(ok, x, -10).astype(np.float32)
    y = np.where(ok, y, -10).astype(np.float32)
    colour = _remap(image.astype(np.float32), x, y)
    e = _remap(edge_distance, x, y)[:, 0]
    fade = np.clip((e - EDGE_MARGIN_PX) / feather_px, 0.0, 1.0)
    angle = np.clip((cos - cos_min) / (1.0 - cos_min), 0.0, 1.0) ** sharpness
    weight = np.where(ok, angle * fade * fade * (3.0 - 2.0 * fade), 0.0).astype(np.float32)
    return colour, weight


def _remap(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (K, C) float32 of an (h, w[, C]) float32 image at (K,) float32 x, y
    (pixel centres at integers; 0 outside the image).

    cv2.remap refuses maps longer than 32767, so the K points are laid out in rows of 1024.
    """
    k = len(x)
    rows = -(-k // 1024)
    maps = np.full((2, rows * 1024), -10, np.float32)
    maps[0, :k], maps[1, :k] = x, y
    out = cv2.remap(image, maps[0].reshape(rows, 1024), maps[1].reshape(rows, 1024),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return _channels(out).reshape(rows * 1024, -1)[:k]


def _tolerance(dist: np.ndarray, cos: np.ndarray, focal: float, cos_min: float) -> np.ndarray:
    """Depth tolerance (mm) of one bilinear footprint: s (1 + 1.5 tan a), s = d / f."""
    c = np.clip(cos, max(cos_min, 1e-3), 1.0)
    return dist / focal * (1.0 + 1.5 * np.sqrt(1.0 - c * c) / c)


def _edges(depth: np.ndarray, cos_pixel: np.ndarray, focal: float, cos_min: float) -> np.ndarray:
    """(h, w) bool: background, image border, or a depth step to a 4-neighbour."""
    finite = np.isfinite(depth)
    d = np.where(finite, depth, 0.0)
    tol = _tolerance(d, cos_pixel, focal, cos_min)
    edge = ~finite
    for a, b in (((slice(1, None), slice(None)), (slice(None, -1), slice(None))),  # rows
                 ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))):  # columns
        jump = finite[a] & finite[b] & (np.abs(d[a] - d[b]) > np.minimum(tol[a], tol[b]))
        edge[a] |= jump
        edge[b] |= jump
    edge[0, :] = edge[-1, :] = True
    edge[:, 0] = edge[:, -1] = True
    return edge


def _check_size(size: object) -> tuple[int, int]:
    if not (isinstance(size, tuple) and len(size) == 2
            and all(isinstance(s, (int, np.integer)) and 1 <= s <= MAX_SIZE for s in size)):
        raise TextureError(f"size: expected (rows, columns), ints in [1, {MAX_SIZE}], "
                           f"got {size!r}")
    return int(size[0]), int(size[1])


def _check_surface(surface: object, n_triangles: int) -> None:
    if not isinstance(surface, UVSurface):
        raise TextureError(f"surface: expected a UVSurface, got {type(surface).__name__}")
    shape = surface.triangles.shape
    for name, dtype, want in (("positions", np.float32, shape + (3,)),
                              ("normals", np.float32, shape + (3,)),
                              ("triangles", np.int32, shape)):
        a = getattr(surface, name)
        if not isinstance(a, np.ndarray) or a.dtype != dtype or a.shape != want:
            raise TextureError(f"surface.{name}: expected {want} {np.dtype(dtype).name}, "
                               f"got {_describe(a)}")
    if surface.triangles.max() < 0:
        raise TextureError("surface: no texel lies inside a UV triangle")
    if surface.triangles.max() >= n_triangles:
        raise TextureError(f"surface.triangles: index {int(surface.triangles.max())} but the "
                           f"mesh has {n_triangles} triangles (surface of another mesh?)")


def _check_view(i: int, view: object) -> None:
    if not (isinstance(view, tuple) and len(view) == 2):
        raise TextureError(f"views[{i}]: expected a tuple (image, camera)")
    image, camera = view
    if not isinstance(camera, Camera):
        raise TextureError(f"views[{i}] camera: expected a models.infra.raster.Camera, got "
                           f"{type(camera).__name__}")
    want = (camera.intrinsics.height, camera.intrinsics.width, 3)
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != want:
        raise TextureError(f"views[{i}] image: expected {want} uint8 BGR (the camera's size), "
                           f"got {_describe(image)}")


def _describe(a: object) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.shape} {a.dtype.name}"
    return type(a).__name__


_VERTEX_UV = """
#version 330
in vec3 in_position;
in vec3 in_normal;
in vec2 in_uv;
out vec3 v_position;
out vec3 v_normal;
void main() {
    gl_Position = vec4(2.0 * in_uv - 1.0, 0.0, 1.0);
    v_position = in_position;
    v_normal = in_normal;
}
"""

_FRAGMENT_UV = """
#version 330
in vec3 v_position;
in vec3 v_normal;
layout(location = 0) out vec4 out_position;
layout(location = 1) out vec4 out_normal;
void main() {
    out_position = vec4(v_position, 1.0);
    out_normal = vec4(v_normal, float(gl_PrimitiveID + 1));
}
"""

_VERTEX_COUNT = """
#version 330
in vec2 in_uv;
void main() {
    gl_Position = vec4(2.0 * in_uv - 1.0, 0.0, 1.0);
}
"""

_FRAGMENT_COUNT = """
#version 330
out float f_count;
void main() {
    f_count = 1.0;
}
"""

_VERTEX_DEPTH = """
#version 330
uniform mat4 mvp;
uniform mat4 view;
in vec3 in_position;
in vec3 in_normal;
out float v_depth;
out vec3 v_normal;
out vec3 v_camera;
void main() {
    vec4 camera = view * vec4(in_position, 1.0);
    gl_Position = mvp * vec4(in_position, 1.0);
    v_depth = -camera.z;
    v_camera = camera.xyz;
    v_normal = mat3(view) * in_normal;
}
"""

_FRAGMENT_DEPTH = """
#version 330
in float v_depth;
in vec3 v_normal;
in vec3 v_camera;
out vec4 f_out;
void main() {
    float cosine = abs(dot(normalize(v_normal), normalize(-v_camera)));
    f_out = vec4(v_depth, cosine, 1.0, 0.0);
}
"""


class _Gl:
    """An EGL OpenGL context with the two passes: UV-space surface, camera depth.

    Each pass makes the context current (``models.infra.egl.in_context``), so a caller's own
    contexts, e.g. a ``MeshRenderer``, are not disturbed.
    """

    def __init__(self) -> None:
        self._ctx = create_context()
        self._uv = self._ctx.program(vertex_shader=_VERTEX_UV, fragment_shader=_FRAGMENT_UV)
        self._depth = self._ctx.program(vertex_shader=_VERTEX_DEPTH,
                                        fragment_shader=_FRAGMENT_DEPTH)
        self._count = self._ctx.program(vertex_shader=_VERTEX_COUNT,
                                        fragment_shader=_FRAGMENT_COUNT)
        self._mesh: Mesh | None = None
        self._depth_vao: Any = None  # moderngl.VertexArray, made by depth_pass

    def __enter__(self) -> _Gl:
        return self

    def __exit__(self, *exc: object) -> None:
        self._ctx.release()

    @in_context
    def uv_pass(self, mesh: Mesh, normals: np.ndarray, width: int,
                height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """UV-space passes, top row first: (H, W, 4) float32 (position, covered) and
        (normal, triangle + 1), and (H, W) float32 the number of triangles at each texel."""
        import moderngl

        ctx = self._ctx
        limit = ctx.info["GL_MAX_RENDERBUFFER_SIZE"]
        if max(width, height) > limit:
            raise TextureError(f"size: {height} x {width} exceeds this OpenGL's limit {limit}")
        index = ctx.buffer(np.ascontiguousarray(mesh.triangles))
        uv = ctx.buffer(np.ascontiguousarray(mesh.uv))
        vao = ctx.vertex_array(self._uv, [
            (ctx.buffer(np.ascontiguousarray(mesh.vertices)), "3f", "in_position"),
            (ctx.buffer(np.ascontiguousarray(normals)), "3f", "in_normal"),
            (uv, "2f", "in_uv")], index_buffer=index, index_element_size=4)
        fbo = ctx.framebuffer(color_attachments=[
            ctx.renderbuffer((width, height), components=4, dtype="f4") for _ in range(2)])
        fbo.use()
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        vao.render(moderngl.TRIANGLES)
        surface = [np.frombuffer(fbo.read(components=4, dtype="f4", attachment=k),
                                 np.float32).reshape(height, width, 4)[::-1] for k in range(2)]
        count_vao = ctx.vertex_array(self._count, [(uv, "2f", "in_uv")], index_buffer=index,
                                     index_element_size=4)
        count_fbo = ctx.framebuffer(color_attachments=[
            ctx.renderbuffer((width, height), components=1, dtype="f4")])
        count_fbo.use()
        count_fbo.clear(0.0)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE
        count_vao.render(moderngl.TRIANGLES)
        ctx.disable(moderngl.BLEND)
        layers = np.frombuffer(count_fbo.read(components=1, dtype="f4"),
                               np.float32).reshape(height, width)[::-1]
        return surface[0], surface[1], layers

    @in_context
    def depth_pass(self, mesh: Mesh, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) float32 depth -Z_cam in mm (inf: background) and |cos| of the view angle."""
        import moderngl

        ctx = self._ctx
        if self._mesh is not mesh:
            self._mesh = mesh
            self._depth_vao = ctx.vertex_array(self._depth, [
                (ctx.buffer(np.ascontiguousarray(mesh.vertices)), "3f", "in_position"),
                (ctx.buffer(welded_normals(mesh)), "3f", "in_normal")],
                index_buffer=ctx.buffer(np.ascontiguousarray(mesh.triangles)),
                index_element_size=4)
        w, h = camera.intrinsics.width, camera.intrinsics.height
        fbo = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer((w, h), components=4, dtype="f4")],
            depth_attachment=ctx.depth_renderbuffer((w, h)))
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        mvp = (camera.projection_matrix() @ camera.view_matrix()).astype(np.float32)
        self._depth["mvp"].write(mvp.T.tobytes())  # GLSL matrices are column-major
        self._depth["view"].write(camera.view_matrix().astype(np.float32).T.tobytes())
        self._depth_vao.render(moderngl.TRIANGLES)
        out = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32).reshape(h, w, 4)
        out = out[::-1]
        for obj in (*fbo.color_attachments, fbo.depth_attachment, fbo):
            obj.release()
        depth = np.where(out[..., 2] > 0.5, out[..., 0], np.inf).astype(np.float32)
        return depth, out[..., 1].copy()
