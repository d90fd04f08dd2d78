"""Shared fixtures: the real third-party material, a generic model and synthetic videos.

Tests that need ``../shared/data`` ask for the ``shared_data`` fixture. Without the folder they
skip with a reason, except under ``FACEWIRE_REQUIRE_REAL_DATA=1`` (set by CI), where they fail.
"""

from __future__ import annotations

import io
import os
import threading
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest

from facewire.protocol.transport import free_loopback_endpoint

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# A synthetic scene for the sender's tests: the 640x480 intrinsics guess (fx = fy = width) as
# the Hello carries it and as a matrix, and an expression in tangent coordinates (u, v), mm,
# NONRIGID order: brows up, smile, mouth open.
SYNTH_FX = 640.0
EXPRESSION_UV = np.array([[0.0, 3.0], [0.5, 2.0], [-0.5, 2.0], [0.0, 3.0], [-3.0, 2.0],
                          [3.0, 2.0], [0.0, 1.5], [0.0, -6.0], [0.0, -5.0]], np.float32)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real test material; skip (or fail under CI) when it is absent."""
    if not (SHARED_DATA / "SOURCES.md").is_file():
        message = f"real test material not found at {SHARED_DATA}"
        if os.environ.get("FACEWIRE_REQUIRE_REAL_DATA") == "1":
            pytest.fail(message + " (FACEWIRE_REQUIRE_REAL_DATA=1)")
        pytest.skip(message)
    return SHARED_DATA


@pytest.fixture(scope="session")
def rig():
    """The animation rig of the generic head (``models.rig.Rig``)."""
    from facewire.models.head import generic_head
    from facewire.models.rig import Rig

    return Rig(generic_head())


@pytest.fixture(scope="session")
def generic_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generic head with a flat grey texture, saved as a model file."""
    from facewire.models.geometry import Intrinsics
    from facewire.models.head import generic_head
    from facewire.models.manifest import ModelInfo
    from facewire.models.modelfile import PersonModel, save_model

    model = PersonModel(mesh=generic_head(), texture=np.full((64, 128, 3), 170, np.uint8),
                        camera=Intrinsics(640.0, 640.0, 319.5, 239.5, 640, 480),
                        info=ModelInfo(name="generic"))
    path = tmp_path_factory.mktemp("model") / "generic.fwm"
    save_model(model, path)
    return path


@pytest.fixture(scope="session")
def person_model(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A full model (geometry, texture, appearance regions) built from lp_d0.mp4's 78 frames
    (gaze left and right, a smile, eyes closed), as ``facewire model build`` makes it."""
    from facewire.sender.enroll.build import build_model

    path = tmp_path_factory.mktemp("person") / "lp_d0.fwm"
    build_model(shared_data / "video" / "lp_d0.mp4", path)
    return path


def chosen_views(clip: Path, frames: slice) -> tuple[list[tuple[np.ndarray, Any]],
                                                     list[np.ndarray], Any, Any]:
    """The texture views a build of ``frames`` of ``clip`` chooses, as it sees them: each
    (image, camera) and its (68, 2) landmarks, the fit and its UV surface (at the build's
    ``TEXTURE_SIZE``)."""
    from facewire.models.geometry import intrinsics_guess
    from facewire.models.infra.progress import no_progress
    from facewire.models.infra.raster import Camera
    from facewire.models.infra.video import read_frames, video_info
    from facewire.sender.enroll import build
    from facewire.sender.enroll.evidence import frame_scores, texture_views
    from facewire.sender.enroll.registration import sharp_frames
    from facewire.sender.enroll.texture import uv_surface
    from facewire.sender.tracker import LandmarkTracker

    def read(s: slice):
        return read_frames(clip, s)

    indices, points, blur, _, _ = build._track(read, frames, None, no_progress, str(clip),
                                               False, LandmarkTracker())
    info = video_info(clip)
    camera = intrinsics_guess(info.width, info.height)
    fit = build._fit(points, camera, "clip", sharp_frames(blur, [p is not None for p in points]))
    surface = uv_surface(fit.mesh, build.TEXTURE_SIZE)
    chosen, _ = texture_views(fit, frame_scores(points, fit, camera, blur))
    images = build._decode(read, {indices[k] for k in chosen})
    pairs = [(images[indices[k]], Camera(camera, fit.poses[k])) for k in chosen]
    return pairs, [points[k] for k in chosen], fit, surface


def write_video(path: Path, images: list[np.ndarray], rate: int = 25, rotation: int = 0) -> Path:
    """Encode (H, W, 3) uint8 BGR images as a real H.264 file with PyAV.

    ``rotation`` (degrees counter-clockwise) goes in the stream's display matrix, as a phone
    writes it; when it is a multiple of 90 the images, given upright, are stored turned by
    ``-rotation`` (sideways for 90 and 270), so that the matrix stands them upright again.
    """
    if rotation % 90 == 0:
        images = [np.ascontiguousarray(np.rot90(image, -(rotation // 90))) for image in images]
    h, w = images[0].shape[:2]
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=rate)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        if rotation:
            stream.set_display_rotation(rotation)
        for image in images:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


@pytest.fixture
def grey_video(tmp_path: Path) -> Callable[..., Path]:
    """``grey_video(name, frames=6)``: an H.264 file of a flat grey 160x120 image: no face."""
    def make(name: str = "grey.mp4", frames: int = 6) -> Path:
        return write_video(tmp_path / name, [np.full((120, 160, 3), 128, np.uint8)] * frames)
    return make


@pytest.fixture()
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty working folder (the current one) and an empty model cache in ``tmp_path``."""
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    monkeypatch.setenv("FACEWIRE_CACHE", str(tmp_path / "cache"))
    return tmp_path


def zip_members(path: Path) -> dict[str, bytes]:
    """Every member of the zip file at ``path``, by name."""
    with zipfile.ZipFile(path) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def write_zip(path: Path, members: dict[str, bytes]) -> Path:
    """A zip file at ``path`` holding ``members`` (deflated), in their order."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def npy_bytes(array: np.ndarray) -> bytes:
    """``array`` as the bytes of a ``.npy`` file."""
    out = io.BytesIO()
    np.save(out, array, allow_pickle=False)
    return out.getvalue()


free_endpoint = free_loopback_endpoint


def start(target: Any, **kwargs: Any) -> tuple[threading.Thread, threading.Event, dict]:
    """``target(stop=..., **kwargs)`` on a thread; its summary (or ``error``) in the dict."""
    stop = threading.Event()
    result: dict[str, Any] = {}

    def run() -> None:
        try:
            result.update(target(stop=stop, **kwargs))
        except Exception as exc:  # reported to the test through the dict
            result["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, stop, result
