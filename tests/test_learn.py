"""The sender's learning on real footage: an expression the model lacks becomes a model update.

The model "built without the open mouth" is the conftest's lp_d0 model with its mouth
region cut down to its rest state (closed, as the neutral frame shows it), saved as a file:
lp_d0's frames 17-66 open the mouth (inner-lip gap 0.14-0.2 of the eye distance), which that
model has never seen. The full lp_d0 model on its own enrollment frames sees nothing new.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sessionlog import mouth_states

from facewire.cli import build_parser
from facewire.models.infra.video import read_frames, video_info
from facewire.models.modelfile import load_model, save_model
from facewire.models.update import MAX_LEARNED_LAYERS, decode_update, encode_update
from facewire.protocol.log import read_log
from facewire.protocol.packet import decode
from facewire.sender.learn import HOLD_FRAMES
from facewire.sender.pipeline import SenderPipeline, encode_video, sender_camera

OPENS = 17  # lp_d0's first frame with the mouth open (inner-lip gap over 0.05)


@pytest.fixture(scope="module")
def closed_mouth(person_model: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("learn") / "closed_mouth.fwm"
    save_model(mouth_states(load_model(person_model), 1), path)
    return path


def _run(model_path: Path, video: Path, frames: slice, learn: bool = True,
         background: bool = False, costs: list[float] | None = None
         ) -> tuple[SenderPipeline, list[tuple[int, object]], list[np.ndarray], list[int]]:
    """The pipeline over the frames: itself, the (frame, update) pairs it issued, its Q and
    its packets' serials; each frame's learning time appended to ``costs``."""
    info = video_info(video)
    pipeline = SenderPipeline(load_model(model_path), sender_camera(info.width, info.height),
                              rate_hz=info.rate_hz, learn=learn, background=background,
                              heal=False)  # the states' learning (the texture's: test_heal)
    if pipeline.learner is not None and pipeline.learner.prepared is not None:
        pipeline.learner.prepared.result()  # a session whose start is over (seconds before)
    issued, qs, serials = [], [], []
    for frame in read_frames(video, frames):
        out = pipeline.process(frame.image, frame.time)
        if costs is not None:
            costs.append(out.timings["learn"])
        qs.append(out.q)
        serials.append(decode(out.packet).serial)
        if out.update is not None:
            issued.append((frame.index, out.update))
    return pipeline, issued, qs, serials


def test_an_unseen_open_mouth_becomes_an_update_that_the_next_frames_use(
        closed_mouth: Path, shared_data: Path) -> None:
    video = shared_data / "video" / "lp_d0.mp4"
    pipeline, issued, qs, serials = _run(closed_mouth, video, slice(0, 40))
    assert [u.region for _, u in issued] == ["mouth"]
    frame, update = issued[0]
    # within half a second of the mouth opening, after the run the rule asks for
    assert OPENS + HOLD_FRAMES - 1 <= frame <= OPENS + 15
    base = load_model(closed_mouth)
    assert update.serial == 1 and update.base_sha256 == base.sha256
    assert update.position == 1 and update.replaces is None  # opener than the rest state
    assert pipeline.serial == 1 and pipeline.updates == [update]
    # what the transport will carry: its bytes decode, against the base, to the same state
    data = encode_update(update, base)
    assert len(data) < 20_000  # kilobytes: the changed texels at the frame's resolution
    back = decode_update(data, base, base.sha256)
    assert all(np.array_equal(a, b) for a, b in zip(back.layers, update.layers, strict=True))
    # the packets say which version their Q refers to: the frame that learned was
    # classified with the model file, the next ones with the update
    assert serials[:frame + 1] == [0] * (frame + 1) and set(serials[frame + 1:]) == {1}
    mouth = next(r for r in pipeline.model.regions if r.name == "mouth")
    assert mouth.templates.shape[0] == 2 and mouth.rest == 0.0
    assert np.array_equal(mouth.templates[1], update.template)
    assert pipeline.classifiers is not None and pipeline.classifiers.regions[6].k == 2
    # the open mouth's layer differs from the closed one where the lips parted
    assert np.abs(mouth.layers[1].astype(int) - mouth.layers[0].astype(int)).mean() > 5
    # the frames after it (mouth still open) read as the learned state
    m = [r.name for r in base.regions].index("mouth")
    after = np.array([q[m] for q in qs[frame + 1:]])
    assert np.median(after) > 0.8


def test_frames_like_the_enrollment_teach_nothing(person_model: Path, shared_data: Path
                                                  ) -> None:
    _, issued, _, _ = _run(person_model, shared_data / "video" / "lp_d0.mp4", slice(0, None))
    assert issued == []


def test_a_full_region_replaces_its_least_used_state_never_the_rest(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "full_mouth.fwm"
    save_model(mouth_states(load_model(person_model), MAX_LEARNED_LAYERS), path)
    pipeline, issued, _, _ = _run(path, shared_data / "video" / "lp_d0.mp4", slice(0, 40))
    assert len(issued) == 1
    update = issued[0][1]
    assert update.replaces is not None and update.replaces != 0  # 0: the rest state
    mouth = next(r for r in pipeline.model.regions if r.name == "mouth")
    assert mouth.templates.shape[0] == MAX_LEARNED_LAYERS and mouth.rest == 0.0
    assert np.array_equal(mouth.templates[update.position], update.template)


def test_no_learn_issues_nothing(closed_mouth: Path, shared_data: Path, tmp_path: Path
                                 ) -> None:
    video = shared_data / "video" / "lp_d0.mp4"
    off = encode_video(closed_mouth, video, tmp_path / "off.fwlog", slice(0, 40), learn=False)
    assert off["updates"] == 0 and off["update_regions"] == []
    parser = build_parser()
    for command in (["send", "--model", "m.fwm", "--source", "v.mp4"],
                    ["encode", "--model", "m.fwm", "--source", "v.mp4", "-o", "l.fwlog"]):
        assert parser.parse_args(command).no_learn is False  # learning is the default
        assert parser.parse_args([*command, "--no-learn"]).no_learn is True


def test_encode_logs_each_update_after_the_packet_of_its_frame(
        closed_mouth: Path, shared_data: Path, tmp_path: Path) -> None:
    video = shared_data / "video" / "lp_d0.mp4"
    summary = encode_video(closed_mouth, video, tmp_path / "on.fwlog", slice(0, 40), heal=False)
    assert summary["updates"] == 1 and summary["update_regions"] == ["mouth"]
    log = read_log(tmp_path / "on.fwlog")
    assert [u.serial for u in log.updates] == [1] and not log.missing_serials
    record = log.updates[0]
    serials = log.frames["serial"]
    assert set(serials[:record.before]) == {0} and set(serials[record.before:]) == {1}
    base = load_model(closed_mouth)
    update = decode_update(record.data, base, base.sha256)
    assert update.region == "mouth" and update.serial == 1


def test_in_the_background_the_frames_go_on_while_the_state_is_captured(
        closed_mouth: Path, shared_data: Path) -> None:
    video = shared_data / "video" / "lp_d0.mp4"
    inline, background = [], []
    _, [(at, update)], _, _ = _run(closed_mouth, video, slice(0, 40), costs=inline)
    _, [(later, learned)], _, serials = _run(closed_mouth, video, slice(0, 60),
                                             background=True, costs=background)
    assert learned.region == "mouth" and later > at  # issued by a later frame
    assert np.array_equal(learned.template, update.template)  # from the same held frames
    assert set(serials[later + 1:]) == {1}
    # no frame did it: the frames went on while the worker fused the held ones
    assert max(background[at:later + 1]) < inline[at] / 5, (background[at:later + 1],
                                                            inline[at])
