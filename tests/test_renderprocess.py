"""The renderer in its own process (``receiver.renderprocess``), for real: a spawned child
rendering through EGL (llvmpipe), a real person model built from lp_d0.mp4 and the states of
its real encoded stream, against the same ``StateRenderer`` in this process."""

from __future__ import annotations

import dataclasses
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from logsender import encoded_log

from facewire.models.infra.raster import RenderError
from facewire.models.modelfile import PersonModel, load_model
from facewire.receiver.playout import FrameState, replay_states
from facewire.receiver.renderprocess import RenderProcess, RenderProcessError
from facewire.receiver.scene import StateRenderer

SIZE = (320, 240)
FRAMES = 12


@pytest.fixture(scope="module")
def model(person_model: Path) -> PersonModel:
    return load_model(person_model)


@pytest.fixture(scope="module")
def states(person_model: Path, shared_data: Path) -> tuple[list[FrameState], object]:
    """The first played states of lp_d0.mp4 encoded with its own model, and its Hello."""
    log = encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    played = [s for s in replay_states(log.packets, log.times, log.hello.rate_hz)
              if s.seq is not None]
    return played[:FRAMES], log.hello


def _segment(name: str) -> Path:
    return Path("/dev/shm") / name.lstrip("/")


def test_the_child_draws_what_this_process_draws(model: PersonModel, states) -> None:
    """Frame for frame the same pixels (the same driver, the same inputs), through the
    pipelined submit/collect too, and after a model update whose regions only crossed."""
    played, hello = states
    with StateRenderer(model, *SIZE, hello.camera) as here, \
            RenderProcess(model, *SIZE, hello.camera) as child:
        name = child.shm_name
        assert _segment(name).exists()
        expected = [here.render(s) for s in played]
        assert any(image.any() for image in expected)  # the face is in view
        got = [child.render(s) for s in played]
        for k in range(0, len(played), 2):  # two in flight
            child.submit(played[k])
            child.submit(played[k + 1])
            got += [child.collect(), child.collect()]
        for k, image in enumerate(got):
            assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
            diff = np.abs(image.astype(int) - expected[k % len(played)])
            assert diff.max() <= 1, f"frame {k}: {diff.max()} levels apart"

        # a version with one region's layers changed (what models.update makes): the same
        # mesh and texture, so only that region is sent
        region = model.regions[0]
        changed = dataclasses.replace(region, layers=255 - region.layers)
        version = dataclasses.replace(model, regions=(changed, *model.regions[1:]))
        here.set_model(version)
        child.set_model(version)
        assert child.model is version
        lifted = [dataclasses.replace(s, q=np.full(8, 1.0, np.float32)) for s in played[:3]]
        for s in lifted:
            mine = here.render(s)
            assert np.abs(child.render(s).astype(int) - mine).max() <= 1
        assert not np.array_equal(mine, expected[2])  # the update shows
        # a texture patch (models.patch: the same mesh, a rectangle of the texture changed):
        # the texture crosses, and the child uploads the rectangle, as the renderer here does
        texture = version.texture.copy()
        texture[: texture.shape[0] // 2] = 255 - texture[: texture.shape[0] // 2]
        patched = dataclasses.replace(version, texture=texture)
        unpatched = mine
        here.set_model(patched)
        child.set_model(patched)
        assert child.model is patched
        for s in lifted:
            mine = here.render(s)
            assert np.abs(child.render(s).astype(int) - mine).max() <= 1
        assert np.abs(mine.astype(int) - unpatched).max() > 100  # the patch shows
        assert len(child.render_seconds) == 2 * len(played) + 2 * len(lifted)
    assert not _segment(name).exists()


def test_bad_input_is_refused_and_the_child_goes_on(model: PersonModel, states) -> None:
    played, hello = states
    with RenderProcess(model, *SIZE, hello.camera) as child:
        good = child.render(played[0])
        bad = dataclasses.replace(played[0], residuals=np.zeros((4, 2), np.float32))
        with pytest.raises(RenderError, match=r"render: uv"):
            child.render(bad)
        with pytest.raises(RenderError, match="q: contains NaN"):
            child.render(dataclasses.replace(played[0], q=np.full(8, np.nan, np.float32)))
        with pytest.raises(RenderError, match="expected a FrameState"):
            child.submit("a state")  # type: ignore[arg-type]
        with pytest.raises(RenderError, match="no frame in flight"):
            child.collect()
        child.submit(played[0])
        with pytest.raises(RenderError, match="not collected"):
            child.render(played[0])
        assert np.array_equal(child.collect(), good)
        assert np.array_equal(child.render(played[0]), good)  # still serving
        with pytest.raises(RenderError, match="another mesh"):
            child.set_model(load_model_copy(model))
    with pytest.raises(RenderError, match="view"):
        RenderProcess(model, *SIZE, hello.camera, view="top")
    with pytest.raises(RenderError, match="depth"):
        RenderProcess(model, *SIZE, hello.camera, depth=0)


def test_wait_says_when_the_oldest_frame_is_back(model: PersonModel, states) -> None:
    """``wait`` answers True once the oldest frame in flight is back, taking a model
    update's answer ahead of it; ``collect`` then gives that frame."""
    played, hello = states
    with RenderProcess(model, *SIZE, hello.camera) as child:
        with pytest.raises(RenderError, match="no frame in flight"):
            child.wait(0.0)
        first, second = child.render(played[0]), child.render(played[1])
        region = model.regions[0]
        version = dataclasses.replace(model, regions=(
            dataclasses.replace(region, layers=region.layers.copy()), *model.regions[1:]))
        child.submit(played[0])
        child.set_model(version)  # answered between the two frames
        child.submit(played[1])
        assert child.wait(60.0)
        assert np.array_equal(child.collect(), first)
        assert child.wait(60.0)  # the update's "ok" taken on the way
        assert child.in_flight == 1
        assert np.array_equal(child.collect(), second)
        assert child.model is version


def load_model_copy(model: PersonModel) -> PersonModel:
    """The same model with a mesh object of its own (a model of another mesh, to the
    renderer)."""
    return dataclasses.replace(model, mesh=dataclasses.replace(model.mesh))


def test_a_child_that_dies_is_reported_and_nothing_is_left(model: PersonModel,
                                                           states) -> None:
    played, hello = states
    child = RenderProcess(model, *SIZE, hello.camera)
    name = child.shm_name
    child.render(played[0])
    os.kill(child.pid, signal.SIGKILL)
    with pytest.raises(RenderProcessError, match=rf"pid {child.pid}\) was killed by SIGKILL"):
        child.render(played[1])
    with pytest.raises(RenderProcessError, match="SIGKILL"):  # and every call after
        child.submit(played[1])
    assert not _segment(name).exists()  # freed when the death was seen
    child.release()
    child = RenderProcess(model, *SIZE, hello.camera)
    child.submit(played[0])
    child.submit(played[1])
    child.collect()
    os.kill(child.pid, signal.SIGKILL)
    with pytest.raises(RenderProcessError, match="SIGKILL"):  # a frame in flight when it died
        for _ in range(3):  # the frame may have been drawn before: then the next one
            while not child.wait(0.5):
                pass
            child.collect()
            child.submit(played[2])
    child.release()
    child.release()  # idempotent


def test_a_released_renderer_says_so_and_frees_its_segment(model: PersonModel,
                                                            states) -> None:
    played, hello = states
    child = RenderProcess(model, *SIZE, hello.camera)
    name, pid = child.shm_name, child.pid
    child.release()
    assert not _segment(name).exists()
    assert not Path(f"/proc/{pid}").exists()  # ended and reaped
    with pytest.raises(RenderError, match="released"):
        child.render(played[0])
