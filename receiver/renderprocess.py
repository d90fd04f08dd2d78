"""The renderer in a process of its own: ``StateRenderer``'s interface, the drawing off the GIL.

moderngl holds the GIL while it draws (llvmpipe: 10-30 ms a frame), so a renderer in the
receiver's process stalls its packet reader, playout and encoder for that long.
``RenderProcess`` keeps ``receiver.scene.StateRenderer``'s interface (``render(state)``,
``set_model``, ``hello_camera``, ``model``, ``render_seconds``, ``release``) and runs the
``StateRenderer`` in a child process (``multiprocessing``, spawn: a fresh interpreter, no
inherited OpenGL context, sockets or threads; so a script that calls ``receive`` or
``replay_log`` guards its entry point with ``if __name__ == "__main__":``, as every spawned
``multiprocessing`` program must). The child owns the EGL context and the model's
GPU state; the parent's calling thread waits on a pipe while a frame is drawn, which releases
the GIL to its other threads.

Parent -> child, one pickled tuple per request on a ``multiprocessing`` pipe, each answered in
order:

- the model, once, before anything else (its mesh, texture and regions: a few MB, once);
- ``("render", slot, camera, rotation, translation, residuals, q, shade)``: the slot's inputs
  (``FrameState``: (3, 3) rotation, (3,) translation mm, (9, 2) residuals mm, (8,) Q,
  (3,) shade; ``camera`` the Hello's ``protocol.control.Camera`` when it changed, else
  None), about 500 bytes; answered ``("frame", slot, seconds)`` once the image is in ring
  slot ``slot``, ``seconds`` the child's morph, draw and readback time;
- ``("regions", {index: Region}, n, texture)``: a new version of the model (``models.update``
  or a texture patch, ``models.patch``: the same mesh) whose regions at those indices
  changed: only they cross the pipe, and the texture ((H, W, 3) uint8) only when it changed,
  else None; the child's ``StateRenderer.set_model`` uploads what changed (a patch's
  rectangle); answered ``("ok",)``;
- ``("close",)``: the child releases its context and exits.

Any request the child cannot carry out (bad input, a model it cannot take) is answered
``("error", kind, message)``, raised in the parent as ``RenderError`` (``EGLUnavailable``
for a missing OpenGL), and the child goes on serving.

Frames come back through ``multiprocessing.shared_memory``: a ring of ``depth`` slots of
(height, width, 3) uint8 RGB, top row first, made and unlinked by the parent. The child reads
the framebuffer straight into its slot (``FaceRenderer.render(out=)``); ``render`` copies the
slot out (one memory copy; no frame crosses the pipe), so the caller owns its image. With
``submit`` and ``collect`` up to ``depth`` frames are in flight, so the parent prepares
(and writes out) one frame while the child draws the next; ``wait(timeout)`` says whether
the oldest is back, so a caller that has other work collects it as soon as it is.

Failures. A child that dies (killed, crashed in the driver) closes its end of the pipe: the
waiting call raises ``RenderProcessError`` naming its exit code or signal, at once, and every
later call raises the same. ``release`` (or ``with``, or the object's finalizer at exit)
asks the child to close, waits at most ``CLOSE_S``, then kills it, and unlinks the shared
memory: nothing is left in /dev/shm. A parent killed outright leaves the segment to
``multiprocessing``'s resource tracker, which unlinks it, and the child sees the pipe close
and exits.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import signal
import time
import weakref
from collections import deque
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any, NoReturn, Self

import numpy as np

from facewire.models.infra.childpipe import receive_from
from facewire.models.infra.egl import EGLUnavailable
from facewire.models.infra.raster import RenderError, check_output
from facewire.models.modelfile import PersonModel
from facewire.protocol import control as ctl
from facewire.protocol.packet import Flag
from facewire.receiver.playout import FrameState
from facewire.receiver.scene import STATS_FRAMES, VIEWS, StateRenderer

DEPTH = 2  # ring slots: frames in flight
CLOSE_S = 5.0  # release: how long the child may take to close before it is killed
_ERRORS: dict[str, type[Exception]] = {"EGLUnavailable": EGLUnavailable}


class RenderProcessError(RenderError):
    """The render process died or could not start; says how (exit code, signal)."""


class RenderProcess:
    """``StateRenderer`` in a child process (module docstring).

    Args:
        model: the person model.
        width, height: output size, pixels.
        hello_camera: the sender's intrinsics (the Hello's); may be replaced later.
        view: one of ``receiver.scene.VIEWS``.
        depth: ring slots, the most frames ``submit`` may have in flight (>= 1).

    Attributes:
        model, width, height, view, hello_camera: as ``StateRenderer``'s.
        depth: as given.
        render_seconds: the child's time for each of the last ``STATS_FRAMES`` frames
            (morph, draw, readback into shared memory), s.
        pid: the child's process id.
        shm_name: the shared memory segment's name (/dev/shm/NAME on Linux).

    Raises:
        RenderError: a bad view, size or depth. EGLUnavailable: no headless OpenGL (from the
        child). RenderProcessError: the child could not start or died while setting up.
    """

    def __init__(self, model: PersonModel, width: int, height: int,
                 hello_camera: ctl.Camera, view: str = "camera", depth: int = DEPTH) -> None:
        if view not in VIEWS:
            raise RenderError(f"view: expected one of {', '.join(VIEWS)}, got {view!r}")
        check_output(width, height, (0, 0, 0))
        if not isinstance(depth, int) or depth < 1:
            raise RenderError(f"depth: expected an int >= 1, got {depth!r}")
        if not isinstance(model, PersonModel):
            raise RenderError(f"model: expected a PersonModel, got {type(model).__name__}")
        self.model, self.width, self.height, self.view = model, width, height, view
        self.depth = depth
        self.render_seconds: deque[float] = deque(maxlen=STATS_FRAMES)
        self._camera = hello_camera
        self._camera_sent = True  # the child starts with it
        self._pending: deque[int | None] = deque()  # replies due: a frame's slot, None: "ok"
        self._next_slot = 0
        self._dead: str | None = None
        self._link = _Link(width, height, depth)
        self._release = weakref.finalize(self, self._link.close)
        self.pid = self._link.start(view, hello_camera)
        assert self._link.shm is not None
        self.shm_name = self._link.shm.name
        try:
            self._send(model)
            self._expect("ok")
        except BaseException:
            self.release()
            raise

    @property
    def hello_camera(self) -> ctl.Camera:
        return self._camera

    @hello_camera.setter
    def hello_camera(self, camera: ctl.Camera) -> None:
        if camera != self._camera:
            self._camera, self._camera_sent = camera, False

    def render(self, state: FrameState) -> np.ndarray:
        """(height, width, 3) uint8 RGB: the face in ``state``, drawn by the child (the calling
        thread waits, without the GIL).

        Raises:
            RenderError: bad input (the child's message), or frames from ``submit`` not yet
            collected. RenderProcessError: the child died.
        """
        if self.in_flight:
            raise RenderError(f"render: {self.in_flight} submitted frames not collected")
        self.submit(state)
        return self.collect()

    @property
    def in_flight(self) -> int:
        """Frames submitted and not yet collected."""
        return sum(slot is not None for slot in self._pending)

    def submit(self, state: FrameState) -> None:
        """Send ``state`` to be drawn into the next ring slot; at most ``depth`` in flight
        (``collect`` gives them back in order).

        Raises:
            RenderError: ``depth`` frames are in flight already, or the state cannot be sent.
            RenderProcessError: the child died.
        """
        self._check_alive()
        if self.in_flight >= self._link.depth:
            raise RenderError(f"submit: {self._link.depth} frames in flight already; collect "
                              f"one first")
        if not isinstance(state, FrameState):
            raise RenderError(f"state: expected a FrameState, got {type(state).__name__}")
        slot = self._next_slot
        camera = None if self._camera_sent else self._camera
        self._send(("render", slot, camera, state.rotation, state.translation,
                    state.residuals, state.q, state.shade))
        self._camera_sent = True
        self._pending.append(slot)
        self._next_slot = (slot + 1) % self._link.depth

    def wait(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s (without the GIL) for the oldest frame in flight; True
        when it is back, so that ``collect`` returns at once (or raises at once, for a child
        that died or refused it).

        Raises:
            RenderError: nothing in flight. RenderProcessError: the child died.
        """
        if not self.in_flight:
            raise RenderError("wait: no frame in flight")
        self._check_alive()
        conn = self._link.conn
        assert conn is not None  # _check_alive
        deadline = time.monotonic() + max(0.0, timeout)
        while True:
            if not conn.poll(max(0.0, deadline - time.monotonic())):
                return False
            if self._pending[0] is not None:
                return True
            self._pending.popleft()  # a model update's answer first
            self._expect("ok")

    def collect(self) -> np.ndarray:
        """The oldest frame submitted, (height, width, 3) uint8 RGB, copied out of its slot.

        Raises:
            RenderError: nothing in flight, the child refused that frame's input, or a model
            update sent meanwhile (``set_model``). RenderProcessError: the child died.
        """
        if not self.in_flight:
            raise RenderError("collect: no frame in flight")
        self._settle()
        slot = self._pending.popleft()
        _, got, seconds = self._expect("frame")
        assert got == slot, f"render process answered slot {got} for slot {slot}"
        self.render_seconds.append(seconds)
        ring = self._link.ring
        assert ring is not None  # open while the child lives
        return ring[slot].copy()

    def set_model(self, model: PersonModel) -> None:
        """Render with another version of the model (``StateRenderer.set_model``): only the
        regions that changed are sent to the child, and the texture when it changed (a patch).
        Frames in flight are drawn with the old version; the child's answer is then
        awaited at the next ``collect``, else at once.

        Raises:
            RenderError: ``model``'s mesh is not this renderer's, or the child cannot take it
            (at once, or at the next ``collect``). RenderProcessError: the child died.
        """
        if not isinstance(model, PersonModel):
            raise RenderError(f"model: expected a PersonModel, got {type(model).__name__}")
        if model.mesh is not self.model.mesh:
            raise RenderError("model: a version of another mesh; make a new RenderProcess")
        if model is self.model:
            return
        old = self.model.regions
        changed = {i: r for i, r in enumerate(model.regions) if i >= len(old) or r is not old[i]}
        texture = None if model.texture is self.model.texture else model.texture
        self._send(("regions", changed, len(model.regions), texture))
        self._pending.append(None)
        self.model = model
        if not self.in_flight:
            self._settle()

    def release(self) -> None:
        """Stop the child and free the shared memory (idempotent)."""
        self._release()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.release()

    # -- the link ----------------------------------------------------------------------------

    def _settle(self) -> None:
        """Take the answers to the model updates at the head of the replies due."""
        while self._pending and self._pending[0] is None:
            self._pending.popleft()
            self._expect("ok")

    def _check_alive(self) -> None:
        if self._dead is not None:
            raise RenderProcessError(self._dead)
        if self._link.conn is None:
            raise RenderError("the renderer was released")

    def _send(self, message: object) -> None:
        self._check_alive()
        assert self._link.conn is not None  # _check_alive
        try:
            self._link.conn.send(message)
        except (BrokenPipeError, ConnectionResetError, EOFError):
            self._died()

    def _expect(self, kind: str) -> tuple[Any, ...]:
        """The child's next reply, which must be ``kind``; an error reply raised."""
        self._check_alive()
        conn, process = self._link.conn, self._link.process
        assert conn is not None and process is not None  # _check_alive
        try:
            reply = receive_from(process, conn)
        except (EOFError, ConnectionResetError, BrokenPipeError):
            self._died()
        if reply[0] == "error":
            _, name, message = reply
            raise _ERRORS.get(name, RenderError)(message)
        if reply[0] != kind:
            raise RenderProcessError(f"render process: expected {kind!r}, got {reply[0]!r}")
        return tuple(reply)

    def _died(self) -> NoReturn:
        """Record and raise that the child died (every later call raises it too)."""
        process = self._link.process
        assert process is not None
        process.join(CLOSE_S)
        code = process.exitcode
        how = "is not answering" if code is None else \
            f"was killed by {signal.Signals(-code).name}" if code < 0 else \
            f"exited with code {code}"
        self._dead = (f"the render process (pid {process.pid}) {how}; its last words, if "
                      f"any, are above on stderr")
        self._pending.clear()
        self._link.close()
        raise RenderProcessError(self._dead)


class _Link:
    """The child process, its pipe and the shared memory ring; ``close`` ends them all (the
    finalizer's callback, so it holds no reference to the ``RenderProcess``)."""

    def __init__(self, width: int, height: int, depth: int) -> None:
        self.width, self.height, self.depth = width, height, depth
        self.shm: SharedMemory | None = SharedMemory(create=True, size=depth * height * width * 3)
        self.ring: np.ndarray | None = np.ndarray((depth, height, width, 3), np.uint8,
                                                  buffer=self.shm.buf)
        self.conn: Connection | None = None
        self.process: Any = None

    def start(self, view: str, camera: ctl.Camera) -> int:
        """Start the child; its pid."""
        assert self.shm is not None
        context = multiprocessing.get_context("spawn")
        parent, child = context.Pipe()
        self.conn = parent
        self.process = context.Process(
            target=_child, name="facewire render",
            args=(child, self.shm.name, self.width, self.height, self.depth, view, camera),
            daemon=True)
        try:
            self.process.start()
        except Exception as exc:
            self.close()
            raise RenderProcessError(f"the render process could not start: {exc}") from exc
        finally:
            child.close()
        return int(self.process.pid)

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.send(("close",))
            except (BrokenPipeError, ConnectionResetError, EOFError, OSError):
                pass
        if self.process is not None:
            self.process.join(CLOSE_S)
            if self.process.exitcode is None:
                self.process.kill()
                self.process.join()
            self.process.close()
            self.process = None
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        if self.shm is not None:
            self.ring = None  # the ring is a view of the segment: gone before it closes
            self.shm.close()
            self.shm.unlink()
            self.shm = None


# -- the child ---------------------------------------------------------------------------------

def _child(conn: Connection, shm_name: str, width: int, height: int, depth: int,
           view: str, camera: ctl.Camera) -> None:
    """The child's loop (module docstring): serve requests until "close" or the pipe ends."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    shm = SharedMemory(name=shm_name)
    ring = np.ndarray((depth, height, width, 3), np.uint8, buffer=shm.buf)
    scene: StateRenderer | None = None
    try:
        try:
            model = conn.recv()
            scene = StateRenderer(model, width, height, camera, view)
            conn.send(("ok",))
        except (EOFError, OSError):
            return
        except Exception as exc:  # noqa: BLE001 - sent to the parent, raised there
            conn.send(("error", type(exc).__name__, str(exc)))
            return
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                return  # the parent is gone
            if message[0] == "close":
                return
            try:
                reply, scene = _serve(scene, ring, message)
                conn.send(reply)
            except Exception as exc:  # noqa: BLE001 - bad input: said, and the child goes on
                conn.send(("error", type(exc).__name__, f"{message[0]}: {exc}"))
    finally:
        if scene is not None:
            scene.release()
        del ring
        shm.close()


def _serve(scene: StateRenderer, ring: np.ndarray, message: tuple[Any, ...]
           ) -> tuple[tuple[Any, ...], StateRenderer]:
    """One request's reply (module docstring), and the scene that serves the next one."""
    kind = message[0]
    if kind == "render":
        _, slot, camera, rotation, translation, residuals, q, shade = message
        tick = time.perf_counter()
        if camera is not None:
            scene.hello_camera = camera
        state = FrameState(None, np.asarray(rotation), np.asarray(translation),
                           np.asarray(residuals), np.asarray(q), Flag(0), "received", 1.0,
                           shade=np.asarray(shade))
        scene.render(state, ring[slot])
        return ("frame", slot, time.perf_counter() - tick), scene
    if kind == "regions":
        _, changed, n, texture = message
        regions = tuple(changed[i] if i in changed else scene.model.regions[i]
                        for i in range(n))
        texture = scene.model.texture if texture is None else texture
        scene.set_model(dataclasses.replace(scene.model, regions=regions, texture=texture))
        return ("ok",), scene
    raise RenderError(f"unknown request {kind!r}")
