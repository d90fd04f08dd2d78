"""The person's silhouette (``sender.enroll.silhouette``) and the base texture kept within it,
on latentsync_demo2 0:50 as the build sees it: a phone's portrait clip whose fitted head is
wider than the man's on one side, where the texture took the shelf and the tiles behind him.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import chosen_views

from facewire.sender.enroll.occluders import OccluderError
from facewire.sender.enroll.silhouette import (
    CROP_SIDE,
    CROP_UP,
    SilhouetteFinder,
    check_silhouette_model,
)
from facewire.sender.enroll.texture import EDGE_MARGIN_PX, TextureError

FEATHER_PX = 8.0  # the build's (fuse_views' default)
FOOTPRINT_PX = 1.5  # a texel this near a pixel (rounded) may read it: sqrt(2) px, bilinear


@pytest.fixture(scope="module")
def views(shared_data: Path):
    """latentsync_demo2 0:50 as the build sees it: the chosen views (image, camera), their
    landmarks and silhouettes, the fitted mesh and its UV surface."""
    pairs, faces, fit, surface = chosen_views(shared_data / "video" / "latentsync_demo2.mp4",
                                              slice(0, 50))
    with SilhouetteFinder() as finder:
        silhouettes = [finder.find(image, face) for (image, _), face in zip(pairs, faces)]
    return pairs, faces, silhouettes, fit.mesh, surface


def _face_hull(shape: tuple[int, ...], face: np.ndarray) -> np.ndarray:
    hull = cv2.convexHull(face.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros(shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.rint(hull).astype(np.int32)], 1)
    return mask > 0


def test_the_silhouette_holds_the_face_and_not_the_room(views) -> None:
    pairs, faces, silhouettes, _, _ = views
    for (image, _), face, person in zip(pairs, faces, silhouettes):
        assert person.shape == image.shape[:2] and person.dtype == np.bool_
        hull = _face_hull(image.shape, face)
        assert person[hull].mean() > 0.99  # the face is the person's
        # Above the head, beside it: the wall. The crop around the face (its box, 2.4 times
        # its side) holds the head, the shoulders and the room; the person is not all of it.
        low, high = face.min(axis=0), face.max(axis=0)
        side = (high - low).max()
        above = person[max(int(low[1] - 0.9 * side), 0):int(low[1] - 0.6 * side),
                       int(low[0] - 0.5 * side):int(low[0] - 0.2 * side)]
        assert above.size > 0 and above.mean() < 0.05
        assert 0.2 < person.mean() / hull.mean() < 6
        centre = (low + high) / 2 - [0.0, CROP_UP * (high - low)[1]]
        rows, cols = np.nonzero(person)  # nothing beyond the crop (it was not looked at)
        assert np.abs(cols - centre[0]).max() <= CROP_SIDE * side / 2 + 1
        assert np.abs(rows - centre[1]).max() <= CROP_SIDE * side / 2 + 1


def test_no_texel_takes_the_room_and_the_rest_are_as_before(views) -> None:
    from facewire.sender.enroll.texture import sample_views

    pairs, _, silhouettes, mesh, surface = views
    covered = surface.covered
    _, before = sample_views(mesh, surface, pairs, sharpness=4.0, cos_min=0.1,
                             feather_px=FEATHER_PX)
    _, after = sample_views(mesh, surface, pairs, sharpness=4.0, cos_min=0.1,
                            feather_px=FEATHER_PX, silhouettes=silhouettes)
    took_room = 0
    for (_, camera), person, w0, w1 in zip(pairs, silhouettes, before, after):
        xy = camera.project(surface.positions[covered].astype(np.float64))
        h, w = person.shape
        col = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
        distance = cv2.distanceTransform(person.astype(np.uint8), cv2.DIST_L2,
                                         cv2.DIST_MASK_PRECISE)  # to the nearest non-person
        d = distance[row, col]
        took_room += int(((w0 > 0) & (d < FOOTPRINT_PX)).sum())
        assert not ((w1 > 0) & (d < FOOTPRINT_PX)).any()  # none from the room
        assert (w1 <= w0 + 1e-6).all()  # the silhouette only takes weight away
        inside = d > EDGE_MARGIN_PX + FEATHER_PX + 2  # well within the person: untouched
        np.testing.assert_allclose(w1[inside], w0[inside], atol=1e-6)
    # Without the silhouettes the fitted head's texels took the room behind the man (4279
    # texels over the nine views, measured): the clip shows what this guards against. Each
    # such texel gets its view's colour whole where no other view sees it, however small
    # its weight (the fusion's weighted mean).
    assert took_room > 2000


def test_bad_inputs_are_named(views) -> None:
    from facewire.sender.enroll.fusion import fuse_views

    pairs, faces, silhouettes, mesh, surface = views
    with pytest.raises(TextureError, match="silhouettes: expected a list of"):
        fuse_views(mesh, surface, pairs, silhouettes=silhouettes[:-1])
    with pytest.raises(TextureError, match=r"silhouettes\[0\]: expected"):
        fuse_views(mesh, surface, pairs, silhouettes=[s[:-1] for s in silhouettes])
    with pytest.raises(TextureError, match=r"silhouettes\[0\]: expected"):
        fuse_views(mesh, surface, pairs, silhouettes=[s.astype(np.uint8) for s in silhouettes])
    with SilhouetteFinder() as finder:
        with pytest.raises(OccluderError, match="image: expected"):
            finder.find(pairs[0][0].astype(np.float32), faces[0])
        with pytest.raises(OccluderError, match="points: expected"):
            finder.find(pairs[0][0], faces[0][:10])
        # a face too small for a crop: nobody, not an error
        assert not finder.find(pairs[0][0], np.full((68, 2), 5.0)).any()
    assert "selfie_segmentation.tflite" in check_silhouette_model()
