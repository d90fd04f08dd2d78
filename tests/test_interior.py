"""The mouth's interior (sender.enroll.interior, and step 7 of sender.enroll.layers): an opened
mouth shows a dark inside with teeth, or the person's own where an open-mouth frame saw it;
never the lips or skin stretched."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.geometry import project
from facewire.models.infra.progress import no_progress
from facewire.models.infra.video import read_frames
from facewire.models.landmarks import NONRIGID
from facewire.models.modelfile import PersonModel, load_model
from facewire.models.rig import Rig
from facewire.receiver.render import FaceRenderer
from facewire.sender.enroll.build import build_model, preview_cameras
from facewire.sender.enroll.interior import (
    MIN_WEIGHT,
    continued,
    disc_polar,
    fuse_seen,
    palette,
    seen_weight,
    synthetic,
)
from facewire.sender.enroll.layers import _observe, _RegionTexels

LIP = np.array([170.0, 90.0, 95.0], np.float32)
SKIN = np.array([200.0, 150.0, 130.0], np.float32)


def _grey(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)


def test_the_synthetic_interior_is_dark_with_teeth_under_the_upper_lip() -> None:
    rho, alpha = np.meshgrid(np.linspace(0.0, 1.0, 101), np.radians(np.arange(-180, 181)))
    inside = synthetic(rho.astype(np.float32), alpha.astype(np.float32), LIP, SKIN)
    back, rim = inside[:, 0], inside[:, -1]
    assert (_grey(back) < 0.25 * _grey(LIP)).all()  # the back of the mouth: in shadow
    side = np.abs(np.degrees(alpha[:, 0])) < 10  # the corners' walls: no teeth, darkened lip
    assert (_grey(rim[side]) <= 0.41 * _grey(LIP) + 1e-3).all()
    upper = inside[180 + 90, 22]  # under the upper lip's middle (rho 0.22)
    lower = inside[180 - 90, 22]
    assert _grey(upper) > _grey(SKIN[None])[0] * 0.6 > _grey(lower) > 2 * _grey(back[0])


def test_disc_coordinates_are_centred_on_the_cavity_disc() -> None:
    shape = (1024, 2048)  # MOUTH_UV (0.9, 0.55), radius 0.09 in u, 0.18 in v
    row, col = int((1 - 0.55) * 1024), int(0.9 * 2048)
    rho, alpha = disc_polar(slice(row - 184, row + 1), slice(col, col + 1), shape)
    assert rho[-1, 0] < 0.01 and abs(rho[0, 0] - 1.0) < 0.01  # the centre, the disc's top
    assert abs(np.degrees(alpha[0, 0]) - 90.0) < 1.0  # the top: the upper lip's side


def test_seen_weight_is_the_inner_lip_polygon_shrunk_and_softened() -> None:
    lips = np.array([[100, 100], [120, 90], [140, 88], [160, 90], [180, 100], [160, 130],
                     [140, 135], [120, 130]], np.float32)  # a mouth 45 px open
    x = np.array([[140.0, 140.0, 140.0, 100.0, 60.0]], np.float32)
    y = np.array([[112.0, 89.0, 137.0, 100.0, 112.0]], np.float32)
    w = seen_weight(lips, x, y)[0]
    assert w[0] > 0.99  # the middle of the opening
    assert max(w[1], w[2], w[3]) < 0.15  # on the lip line: mostly lip, not inside
    assert w[4] == 0.0


def test_several_frames_fuse_by_their_weighted_median() -> None:
    colours = np.array([[[[200.0, 200, 200]]], [[[190.0, 195, 200]]], [[[20.0, 30, 40]]]],
                       np.float32)  # two frames see teeth, one a hand
    weights = np.array([[[1.0]], [[0.8]], [[0.9]]], np.float32)
    fused, coverage = fuse_seen(colours, weights)
    assert fused[0, 0].tolist() == [190.0, 195.0, 200.0] and coverage[0, 0] == 1.0
    fused, coverage = fuse_seen(colours, np.zeros_like(weights) + 0.01)  # nobody saw it
    assert coverage[0, 0] == 0.0 and fused[0, 0].tolist() == [0.0, 0.0, 0.0]


@pytest.fixture(scope="session")
def closed_mouth_model(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """lp_d18 0:60 (issue 16's second reproduction): the mouth closed throughout."""
    path = tmp_path_factory.mktemp("closed") / "lp_d18_closed.fwm"
    build_model(shared_data / "video" / "lp_d18.mp4", path, slice(0, 60))
    return path


BACKGROUND = (0, 255, 0)  # the renderer's colour where no triangle is


def _opened(model: PersonModel, drop_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The front preview of the model with its jaw dropped: (480, 480, 3) RGB and the
    morphed inner-lip polygon (8, 2) px."""
    rig = Rig(model.mesh)
    residuals = np.zeros((len(NONRIGID), 3), np.float32)
    residuals[list(NONRIGID).index(57), 1] = -drop_mm  # the lower lip
    residuals[list(NONRIGID).index(8), 1] = -drop_mm  # the chin
    vertices = rig.morph(residuals)
    camera = preview_cameras(model.mesh)[0]
    q = np.array([r.rest for r in model.regions], np.float32)
    q[[r.name for r in model.regions].index("mouth")] = len(model.regions[-1].layers) - 1
    with FaceRenderer(model, camera.intrinsics.width, camera.intrinsics.height,
                      background=BACKGROUND) as renderer:
        image = renderer.render(vertices, q, camera)
    lips = project(vertices[model.mesh.landmarks[60:68]].astype(np.float64), camera.pose,
                   camera.intrinsics)
    return image, lips


@pytest.mark.parametrize("drop_mm", [6.0, 14.0, 31.75])
def test_a_model_without_an_open_mouth_opens_onto_a_dark_interior(
        closed_mouth_model: Path, drop_mm: float) -> None:
    """From a slightly open mouth to the widest the packet can carry (the lower lip and the
    chin down by its residuals' limit): the cavity is behind the lips (no background shows
    between them) and dark, with shadowed teeth, never a flat light plate (main at bcc747b:
    the made-up lower teeth, half opaque, filled a slightly open mouth with one)."""
    model = load_model(closed_mouth_model)
    image, lips = _opened(model, drop_mm)
    mask = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.rint(lips).astype(np.int32)], 1)
    mask = cv2.erode(mask, np.ones((5, 5), np.uint8)).astype(bool)
    assert mask.sum() > 40  # the mouth is open on the screen
    assert not (image[mask] == BACKGROUND).all(axis=1).any()  # the cavity fills it
    lip, skin = palette(model.texture, model.mesh)
    inside = image[mask].astype(np.float32)
    # neither lips nor skin: the old code showed them stretched there (all of it near them)
    near = np.minimum(np.linalg.norm(inside - lip, axis=1), np.linalg.norm(inside - skin, axis=1))
    assert (near < 20).mean() < 0.2, (near < 20).mean()
    grey = _grey(inside)
    assert np.percentile(grey, 25) < 0.7 * _grey(lip[None])[0]  # a dark inside
    assert (grey > 0.9 * _grey(skin[None])[0]).mean() < 0.05  # no light plate
    if drop_mm >= 14.0:
        assert (grey > 0.6 * _grey(skin[None])[0]).mean() > 0.02  # and teeth


def test_an_open_mouth_frame_gives_the_persons_own_teeth_where_it_saw_them(
        closed_mouth_model: Path, shared_data: Path) -> None:
    model = load_model(closed_mouth_model)
    video = shared_data / "video" / "lp_d18.mp4"
    texels = _RegionTexels(model, model.camera)
    observed, _ = _observe(model, model.camera, video, slice(118, 126), no_progress, texels,
                           {})
    seen = {o.index: o for o in observed}
    image = next(f.image for f in read_frames(video, slice(125, 126)))
    inside, weights = texels.cavity.interior([(image, seen[125])])
    cavity = texels.cavity
    w = weights[0]
    assert (w > 0.95).sum() > 500  # frame 125: a wide-open grin, upper teeth showing
    o = seen[125]
    colour = cavity.area.read(model.camera, image, o.rotation, o.translation, o.residuals)[0]
    c = np.where(w >= MIN_WEIGHT, w, 0.0)  # a mere brush of the polygon: unseen
    walls = continued(colour * (c > 0)[..., None], c, cavity.inside)
    assert walls is not None  # its own colours carry over the walls it did not see
    expected = c[..., None] * colour + (1.0 - c[..., None]) * walls
    np.testing.assert_allclose(inside[cavity.inside], expected[cavity.inside], atol=1e-3)
    assert (_grey(inside[w > 0.95]) > 170).sum() >= 50  # its own pixels: its own teeth
    assert (w[~cavity.inside] == 0).all()
    unseen = cavity.inside & (c == 0)
    assert np.abs(walls[unseen] - cavity.synthetic[unseen]).max() > 20  # not the made-up ones

