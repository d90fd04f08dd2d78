"""A playout state to pixels: the per-slot steps every receiver shares (live and replay).

Per slot: the playout's ``FrameState`` (pose, tangent residuals r, Q; held or eased when
concealed) gives ``vertices = rig.morph(rig.from_tangent(r))``; the camera is the sender's
(``receiver.views.sender_view``: the Hello's intrinsics with the state's pose, scaled to the
output size) or a virtual front or three-quarter one (``virtual_view``); the image is
``receiver.render.FaceRenderer.render(vertices, Q, camera, shade)``, the state's light
(``models.shading``) applied in every view alike. ``rest_q`` is what a playout
eases to when the face is lost: each region's rest state.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Self

import numpy as np

from facewire.models.infra.raster import RenderError
from facewire.models.modelfile import PersonModel
from facewire.models.rig import Rig
from facewire.protocol import control as ctl
from facewire.protocol.packet import N_REGIONS
from facewire.receiver.playout import FrameState
from facewire.receiver.render import FaceRenderer
from facewire.receiver.views import VIEW_KINDS, sender_view, virtual_view

VIEWS = ("camera", *VIEW_KINDS)
STATS_FRAMES = 108_000  # render times kept for the summaries' medians: an hour at 30 Hz


def rest_q(model: PersonModel) -> np.ndarray:
    """(8,) float32: each region's rest Q (``Region.rest``) in packet order, 0 beyond the
    model's regions: what the playout shows for a face at rest or lost (``Playout(rest_q=)``)."""
    rest = np.zeros(N_REGIONS, np.float32)
    rest[:len(model.regions)] = [r.rest for r in model.regions]
    return rest


class StateRenderer:
    """A playout state to pixels: the per-slot steps of every receiver (live and replay).

    ``vertices = rig.morph(rig.from_tangent(state.residuals))``; the camera is the sender's
    (``view="camera"``: ``sender_view`` with ``hello_camera`` and the state's pose) or a
    virtual one (``virtual_view``, the head turning by the state's rotation); the image is
    ``FaceRenderer.render(vertices, state.q, camera, state.shade)``.

    Args:
        model: the person model.
        width, height: output size, pixels.
        hello_camera: the sender's intrinsics (the Hello's); may be replaced later.
        view: one of ``VIEWS``.

    Attributes:
        model, rig, width, height, view, hello_camera: as given (``rig`` built from the mesh).
        render_seconds: the time each of the last ``STATS_FRAMES`` ``render`` calls took, s.

    Raises:
        RenderError: a bad view or size. EGLUnavailable: no headless OpenGL.
    """

    def __init__(self, model: PersonModel, width: int, height: int,
                 hello_camera: ctl.Camera, view: str = "camera") -> None:
        if view not in VIEWS:
            raise RenderError(f"view: expected one of {', '.join(VIEWS)}, got {view!r}")
        self.model, self.width, self.height, self.view = model, width, height, view
        self.hello_camera = hello_camera
        self.rig = Rig(model.mesh)
        self.render_seconds: deque[float] = deque(maxlen=STATS_FRAMES)
        self._renderer = FaceRenderer(model, width, height)

    def render(self, state: FrameState, out: np.ndarray | None = None) -> np.ndarray:
        """(height, width, 3) uint8 RGB: the face in ``state`` (written into ``out`` when
        given: ``FaceRenderer.render``)."""
        tick = time.perf_counter()
        vertices = self.rig.morph(self.rig.from_tangent(state.residuals))
        if self.view == "camera":
            camera = sender_view(self.hello_camera, state.rotation, state.translation,
                                 self.width, self.height)
        else:
            camera = virtual_view(self.view, self.model.mesh, state.rotation, self.width,
                                  self.height)
        image = self._renderer.render(vertices, state.q, camera, state.shade, out)
        self.render_seconds.append(time.perf_counter() - tick)
        return image

    def set_model(self, model: PersonModel) -> None:
        """Render with another version of the model (``models.update``: the same mesh, so the
        same rig): the regions that changed are uploaded again, or, when the update changed
        more (the draw order, the texture), a renderer is made anew.

        Raises:
            RenderError: ``model``'s mesh is not this renderer's.
        """
        if model.mesh is not self.model.mesh:
            raise RenderError("model: a version of another mesh; make a new StateRenderer")
        if self._renderer.can_update(model):
            self._renderer.update_regions(model)
        else:
            renderer = FaceRenderer(model, self.width, self.height)
            self._renderer.release()
            self._renderer = renderer
        self.model = model

    def release(self) -> None:
        """Free the renderer's OpenGL context."""
        self._renderer.release()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.release()
