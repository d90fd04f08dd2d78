"""A person model as a browser loads it: a glTF file, a rig file, and one file per update.

The browser receiver (``receiver/web/``) cannot read a ``.fwm`` (a zip of ``.npy`` arrays)
without a zip and npy parser of its own, and it needs the morph's weights, which a model file
does not hold. The gateway (``receiver.gateway``) serves these three instead, made from the
model here; the page's ``model.js`` reads them and refuses anything malformed.

Model: ``model_glb`` (glTF 2.0 binary, ``models.gltf``'s container)
-------------------------------------------------------------------
One node (scale 0.001: the positions are stored in mm, the node makes them glTF's metres)
with one triangle primitive: ``POSITION`` float32 (N, 3), mm, model space; ``TEXCOORD_0``
float32 (N, 2), glTF's v down (1 - facewire's v); indices uint16 when N < 65536, else uint32,
the mesh's triangles in its order. The material's base colour is image 0, the neutral
texture. Every image is a PNG embedded in the binary chunk, its bytes the model file's own
(``models.modelfile.png_members``: never decoded and encoded again), its ``name`` the model
file's member name. The document's root ``extras.facewire`` holds the regions, packet
order::

    {"format": 1,
     "regions": [{"name": str, "opacity": [k numbers], "rest": float, "layers": k,
                  "areas": [{"uv_rect": [u0, v0, u1, v1], "size": [h, w],
                             "layers": [k image indices], "mask": image index}, ...]}]}

(``Region`` and ``Area`` of ``models.modelfile``: areas main first; layers (h, w) RGB, row 0
at v = v1; masks (h, w) grey). The texture's (H, W) is its PNG's. Beside ``regions``,
``framing``: ``{"centre": [x, y, z], "field": mm, "fov_deg": deg}``, the head centre and
field a virtual view aims at (``models.framing.head_field``, ``FOV_DEG``), for the page's
orbit view.

Rig and update files (``rig_bin``, ``update_bin``): one container
-----------------------------------------------------------------
Little-endian::

    magic 4 bytes (b"FWRG" rig, b"FWUP" update) | uint32 version = 1 | uint32 J
    J bytes of UTF-8 JSON, padded with spaces so that 12 + J is a multiple of 8
    the body: the arrays (and blobs) the JSON places, each at an offset (from the body's
    start) that is a multiple of 8

The JSON's ``arrays`` maps a name to ``{"dtype": "f8" | "f4" | "u4", "shape": [...],
"offset": int}``, C order; ``blobs`` lists ``[offset, length]`` byte ranges.

Rig (``rig_bin``): what the page needs to compute the (N, 9) morph weights once at load
(``models.rig.Rig.weights``), small (about 10 kB for 11,000 vertices where the weights
themselves would be 0.4 MB). With the RBF solution ``models.morph.RbfSolution`` of the rig's
field and the centre map S (M, 9) (column k: the centre displacements, x component, of a unit
residual of non-rigid point k: 1 at its centre, ``follow`` of the mandible phantoms for the
chin), the weights of vertex n are

    B[n] = rows(p_n) @ (z @ S),   rows(p) = [h_i(||p - x_i||)]_i ++ alpha [(p - x0) / ell, 1]

with h_i(r) = sqrt(r^2 + s_i^2) (multiquadric) or exp(-(r / s_i)^2) (Gaussian: no affine
part), p_n the vertex in the kernel space (``models.rig.lips_apart``: the glb's position with
y lowered by ``lip_drop`` at ``lip_vertices``), and zero rows at the eyeballs' vertices.
A frame's vertices are then ``v + B @ d``, d (9, 3) = u t1_k + v t2_k of the packet's
residuals (``Rig.from_tangent``). JSON keys: ``kernel``, ``vertices`` (N), ``scale`` (ell),
``balance`` (alpha), ``arrays``: ``centres`` f8 (M, 3) kernel space, ``shape`` f8 (M,),
``origin`` f8 (3,), ``z`` f8 (M + 4 or M, 9) = z @ S, ``tangents`` f4 (9, 2, 3),
``frozen`` u4 (E,) eyeball vertices, ``lip_vertices`` u4 (L,), ``lip_drop`` f8 (L,).

Update (``update_bin``): one model version step (``models.update``): each region that
differs, all of its new state list, each state either a state of the previous version or
new images::

    {"format": 1,
     "regions": [{"index": i, "name": str, "opacity": [k'], "rest": float,
                  "states": [{"from": j} | {"images": [one blob per area, main first]}]}],
     "blobs": [[offset, length], ...]}

The blobs are the new states' PNGs (``models.archive.png_bytes``, as a model file stores
them). The mesh, regions' names, rectangles and sizes stay as they were. A texture patch
(``models.patch``) adds ``"texture": [{"rect": [row, col, h, w], "image": blob}]``: the
texels of the smallest rectangle holding every changed texel, as one PNG of the new texture
there; the regions whose layers it moved are listed as changed, their states as new images.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from facewire.models.archive import png_bytes
from facewire.models.fields import ModelError
from facewire.models.framing import FOV_DEG, head_field
from facewire.models.gltf import BinBuilder, embed_base_colour, glb_bytes, mesh_document
from facewire.models.modelfile import PersonModel, Region, png_members
from facewire.models.patch import changed_rect
from facewire.models.rig import N_RESIDUALS, Rig, lips_apart

FORMAT = 1
RIG_MAGIC = b"FWRG"
UPDATE_MAGIC = b"FWUP"
_HEAD = struct.Struct("<4sII")


def model_glb(model: PersonModel) -> bytes:
    """The model's mesh, images and regions as a glTF 2.0 binary (module docstring)."""
    mesh = model.mesh
    builder = BinBuilder()
    doc = mesh_document(builder, mesh.vertices, mesh.triangles, mesh.uv, None, in_mm=True)
    doc["asset"]["generator"] = "facewire models.webmodel"
    members = png_members(model)
    names = list(members)
    embed_base_colour(doc, builder, members[names[0]][1])
    doc["images"][0]["name"] = names[0]
    index = {names[0]: 0}
    for name in names[1:]:
        index[name] = len(doc["images"])
        doc["images"].append({"bufferView": builder.view(members[name][1]),
                              "mimeType": "image/png", "name": name})
    regions = []
    for r in model.regions:
        areas = []
        for n, area in enumerate(r.parts()):
            folder = f"regions/{r.name}" + (f"/area_{n}" if n else "")
            areas.append({"uv_rect": list(area.uv_rect), "size": list(area.mask.shape),
                          "layers": [index[f"{folder}/layer_{j:02d}.png"]
                                     for j in range(len(area.layers))],
                          "mask": index[f"{folder}/mask.png"]})
        regions.append({"name": r.name, "opacity": list(r.opacity), "rest": r.rest,
                        "layers": len(r.layers), "areas": areas})
    centre, field = head_field(mesh.vertices[mesh.landmarks].astype(np.float64))
    doc["extras"] = {"facewire": {"format": FORMAT, "regions": regions, "framing": {
        "centre": [float(c) for c in centre], "field": field, "fov_deg": FOV_DEG}}}
    return glb_bytes(doc, builder)


def rig_bin(model: PersonModel, rig: Rig | None = None) -> bytes:
    """What the page needs to compute the morph weights (module docstring, "Rig").

    Args:
        model: the person model.
        rig: its rig, when the caller has one (``Rig(model.mesh)`` otherwise).
    """
    rig = Rig(model.mesh) if rig is None else rig
    solution = rig.field.solution()
    centre_map = np.zeros((len(rig.centres), N_RESIDUALS))
    for k in range(N_RESIDUALS):
        unit = np.zeros((N_RESIDUALS, 3), np.float32)
        unit[k, 0] = 1.0
        centre_map[:, k] = rig.centre_displacements(unit)[:, 0]
    vertices = model.mesh.vertices
    drop = vertices[:, 1].astype(np.float64) - lips_apart(model.mesh, vertices)[:, 1]
    lips = np.flatnonzero(drop)
    header = {"kernel": solution.kernel, "vertices": len(vertices), "scale": solution.scale,
              "balance": solution.balance}
    arrays = {"centres": solution.centres.astype("<f8"), "shape": solution.shape.astype("<f8"),
              "origin": solution.origin.astype("<f8"),
              "z": (solution.z @ centre_map).astype("<f8"),
              "tangents": rig.tangents.astype("<f4"),
              "frozen": rig.eyeball_vertices.astype("<u4"),
              "lip_vertices": lips.astype("<u4"), "lip_drop": drop[lips].astype("<f8")}
    return _container(RIG_MAGIC, header, arrays, [])


def update_bin(previous: PersonModel, version: PersonModel) -> bytes:
    """The step from one model version to the next (module docstring, "Update").

    Args:
        previous: version n - 1 (``models.update.ModelVersions.model``).
        version: version n: the same mesh and region layout, other states or texels.

    Raises:
        ModelError: ``version`` is not a version of ``previous``'s model (names the field).
    """
    if (len(previous.regions) != len(version.regions)
            or not np.array_equal(previous.mesh.vertices, version.mesh.vertices)
            or previous.texture.shape != version.texture.shape):
        raise ModelError("update: version: not a version of the previous model (another mesh, "
                         "texture or number of regions)")
    regions: list[dict[str, Any]] = []
    blobs: list[bytes] = []
    for i, (old, new) in enumerate(zip(previous.regions, version.regions, strict=True)):
        if new is old:
            continue
        old_parts, new_parts = old.parts(), new.parts()
        if new.name != old.name or len(new_parts) != len(old_parts) or any(
                a.uv_rect != b.uv_rect or a.layers.shape[1:] != b.layers.shape[1:]
                or not np.array_equal(a.mask, b.mask)
                for a, b in zip(old_parts, new_parts, strict=True)):
            raise ModelError(f"update: region {new.name!r}: its name, areas or masks differ "
                             f"from the previous version's")
        states = _states(old, new, blobs)
        if states == [{"from": j} for j in range(len(old.layers))] \
                and new.opacity == old.opacity and new.rest == old.rest:
            continue
        regions.append({"index": i, "name": new.name, "opacity": list(new.opacity),
                        "rest": new.rest, "states": states})
    header: dict[str, Any] = {"format": FORMAT, "regions": regions}
    rect = changed_rect(previous.texture, version.texture)
    if rect is not None:
        rows, cols = rect
        header["texture"] = [{"rect": [rows.start, cols.start, rows.stop - rows.start,
                                       cols.stop - cols.start], "image": len(blobs)}]
        blobs.append(png_bytes(np.ascontiguousarray(version.texture[rows, cols])))
    offsets, size = [], 0
    for blob in blobs:
        offsets.append([size, len(blob)])
        size += -(-len(blob) // 8) * 8
    return _container(UPDATE_MAGIC, {**header, "blobs": offsets}, {}, blobs)


def _states(old: Region, new: Region, blobs: list[bytes]) -> list[dict[str, Any]]:
    """Each of ``new``'s states as a state of ``old`` it equals ({"from": j}) or as new
    images (appended to ``blobs``)."""
    old_parts, new_parts = old.parts(), new.parts()
    unused = list(range(len(old.layers)))
    states: list[dict[str, Any]] = []
    for j in range(len(new.layers)):
        same = next((i for i in unused if all(np.array_equal(a.layers[i], b.layers[j])
                                              for a, b in zip(old_parts, new_parts,
                                                              strict=True))), None)
        if same is not None:
            unused.remove(same)
            states.append({"from": same})
            continue
        states.append({"images": list(range(len(blobs), len(blobs) + len(new_parts)))})
        blobs.extend(png_bytes(part.layers[j]) for part in new_parts)
    return states


def _container(magic: bytes, header: dict[str, Any], arrays: dict[str, np.ndarray],
               blobs: list[bytes]) -> bytes:
    """The container of the module docstring: ``header`` plus ``arrays`` placed, then the
    arrays' bytes and the blobs', each at a multiple of 8."""
    body: list[bytes] = []
    size = 0

    def put(data: bytes) -> int:
        nonlocal size
        at = size
        body.append(data + b"\0" * (-len(data) % 8))
        size += len(body[-1])
        return at

    placed = {}
    for name, array in arrays.items():
        placed[name] = {"dtype": array.dtype.str[1:], "shape": list(array.shape),
                        "offset": put(np.ascontiguousarray(array).tobytes())}
    for blob in blobs:
        put(blob)
    if arrays:
        header = {**header, "arrays": placed}
    text = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-(_HEAD.size + len(text)) % 8)
    return _HEAD.pack(magic, FORMAT, len(text)) + text + b"".join(body)
