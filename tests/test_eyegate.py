"""The eyelids' Q gated by the landmarks' eye aspect ratio (sender.eyegate), alone and in the
real sender pipeline on lp_d0.mp4 (eyes open, looking aside, and closed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facewire.models.infra.video import read_frames
from facewire.models.landmarks import eye_aspect_ratio
from facewire.models.modelfile import load_model
from facewire.sender.eyegate import OPEN_RATIO, EyeGate
from facewire.sender.pipeline import SenderPipeline, sender_camera


def test_an_open_eye_holds_its_eyelid_at_rest_and_a_closed_one_does_not(
        person_model: Path) -> None:
    model = load_model(person_model)
    names = [r.name for r in model.regions]
    lids = {name: names.index(name) for name in ("eyelid_right", "eyelid_left")}
    neutral = model.mesh.vertices[model.mesh.landmarks].astype(np.float64)
    gate = EyeGate(model.regions, neutral)
    points = neutral[:, :2] * [4.0, -4.0] + 300.0  # the neutral face, seen from the front
    q = np.array([len(r.layers) - 1 for r in model.regions], np.float32)  # all at the end
    gated = gate.apply(q, points)
    for r in lids.values():
        assert gated[r] == min(q[r], model.regions[r].rest)
    others = [r for r in range(len(q)) if r not in lids.values()]
    np.testing.assert_array_equal(gated[others], q[others])
    closing = points.copy()
    closing[[37, 38]] = 0.6 * points[[37, 38]] + 0.4 * points[[41, 40]]  # right upper lid down
    assert eye_aspect_ratio(closing)[0] < OPEN_RATIO * eye_aspect_ratio(points)[0]
    gated = gate.apply(q, closing)
    assert gated[lids["eyelid_right"]] == q[lids["eyelid_right"]]  # the templates decide
    assert gated[lids["eyelid_left"]] == min(q[lids["eyelid_left"]],
                                             model.regions[lids["eyelid_left"]].rest)


def test_in_the_pipeline_open_eyes_never_close_and_closed_eyes_still_do(
        person_model: Path, shared_data: Path) -> None:
    model = load_model(person_model)
    lid = [r.name for r in model.regions].index("eyelid_left")
    rest = model.regions[lid].rest
    pipeline = SenderPipeline(model, sender_camera(512, 512), rate_hz=25.0)
    neutral_ear = eye_aspect_ratio(
        model.mesh.vertices[model.mesh.landmarks][:, :2].astype(np.float64))[1]
    open_q, closed_q = [], []
    for f in read_frames(shared_data / "video" / "lp_d0.mp4"):
        out = pipeline.process(f.image, f.index / 25.0)
        if out.points is None or out.offsets is None:
            continue
        ratio = eye_aspect_ratio(out.points)[1] / neutral_ear
        (open_q if ratio >= OPEN_RATIO else closed_q).append(float(out.q[lid]))
    assert len(open_q) > 20 and max(open_q) <= rest
    assert closed_q and max(closed_q) > rest + 1.0  # lp_d0 closes its eyes: a lid closes
