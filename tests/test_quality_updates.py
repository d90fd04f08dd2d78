"""bench quality with model updates: each frame drawn with the model version its packet
names, as a receiver that holds the session's updates draws it (real frames, real EGL)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from sessionlog import learned_update, mouth_states

from facewire.bench.encoding import decode_run, encode_frames
from facewire.bench.quality import measure_quality
from facewire.bench.rendering import render_scores
from facewire.cli import build_parser
from facewire.models.infra.progress import no_progress
from facewire.models.infra.video import read_frames
from facewire.models.modelfile import load_model, save_model
from facewire.models.update import apply_update
from facewire.protocol.packet import Flag
from facewire.sender.pipeline import SenderPipeline, sender_camera, wire_camera

AT = 3  # the frames from AT on refer to the update


def test_each_frame_is_rendered_with_the_version_its_serial_names(person_model: Path,
                                                                   shared_data: Path) -> None:
    base = load_model(person_model)
    updated = apply_update(base, learned_update(base, "mouth", 1, base.sha256))
    frames = list(read_frames(shared_data / "video" / "lp_d0.mp4", slice(20, 26)))
    height, width = frames[0].image.shape[:2]
    pipeline = SenderPipeline(base, sender_camera(width, height))
    run = encode_frames(pipeline, frames, no_progress)
    assert run.versions == {0: base}  # a sender that learned nothing: the model file only
    decoded = decode_run(run.packets, run.indices).copy()
    mouth = [r.name for r in base.regions].index("mouth")
    decoded["q"][:, mouth] = base.regions[mouth].layers.shape[0]  # the learned state
    decoded["serial"][AT:] = 1
    flags = decoded["flags"].astype(np.int64)
    posed = ((flags & Flag.FACE_PRESENT) != 0) & ((flags & Flag.TRACKING_LOST) == 0)
    assert posed.all()
    camera = wire_camera(pipeline.camera)

    def faces(model, versions=None) -> dict[int, np.ndarray]:
        return render_scores(model, camera, decoded, run.tracked, posed, run.images,
                             no_progress, pipeline.tracker, keep_faces=True,
                             truths=run.tracked, versions=versions).faces

    before, after = faces(base), faces(updated)
    shown = faces(base, {0: base, 1: updated})
    assert (np.abs(after[AT].astype(int) - before[AT]).max(axis=2) > 40).sum() > 50
    for k in range(len(frames)):
        assert np.array_equal(shown[k], before[k] if k < AT else after[k]), k


def test_bench_quality_with_learn_scores_the_session_its_updates_made(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    closed = tmp_path / "closed_mouth.fwm"
    save_model(mouth_states(load_model(person_model), 1), closed)
    video = shared_data / "video" / "lp_d0.mp4"
    kept = measure_quality(closed, video, slice(0, 40), allow_overlap=True)
    learned = measure_quality(closed, video, slice(0, 40), allow_overlap=True, learn=True)
    assert kept["model_updates"] == []
    updates = learned["model_updates"]
    assert [u["serial"] for u in updates] == list(range(1, len(updates) + 1))
    states = [u for u in updates if u["kind"] == "state"]
    assert len(states) == 1  # the mouth's open state, learned between the healing's patches
    assert 17 < states[0]["first_frame"] < 40  # after the mouth opened
    assert learned["patches"] == len(updates) - 1
    assert build_parser().parse_args(["bench", "quality", "--model", "m", "--source", "v",
                                      "--learn"]).learn is True
