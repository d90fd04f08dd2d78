"""Whom the sender follows: the person's descriptors in the model file, the sender holding
that person among others (real dlib on openface_multi_face.avi), the person back after a
cutaway (hamilton_short.mp4), the build's choice of person, and the benchmark's identity
measures, which catch a tracker that follows the largest face."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import npy_bytes, write_zip, zip_members

from facewire.bench.identity import identity_measures, judge_frames
from facewire.bench.quality import measure_quality
from facewire.models.infra.progress import no_progress
from facewire.models.infra.video import read_frames
from facewire.models.modelfile import ModelFileError, PersonModel, load_model, save_model
from facewire.protocol.packet import Flag
from facewire.sender import identity
from facewire.sender.enroll.build import build_model
from facewire.sender.enroll.person import (
    PersonError,
    choose_person,
    faces_in,
    photo_descriptor,
)
from facewire.sender.identity import MATCH_DISTANCE, IdentityError, Person
from facewire.sender.pipeline import SenderPipeline, encode_video, identity_warning, sender_camera
from facewire.sender.tracker import LandmarkTracker, box_iou

CLIP = "openface_multi_face.avi"  # three people; the man in front has the largest face
FIRST = 60  # the first frame in which the detector sees all three


@pytest.fixture(scope="module")
def tracker() -> LandmarkTracker:
    return LandmarkTracker()


@pytest.fixture(scope="module")
def clip(shared_data: Path) -> Path:
    return shared_data / "video" / CLIP


@pytest.fixture(scope="module")
def people(clip: Path, tracker: LandmarkTracker) -> list:
    """The faces of frame FIRST, left to right: the man at the back left, the man in
    front (the largest), the man at the back right."""
    image = next(read_frames(clip, slice(FIRST, FIRST + 1))).image
    faces = faces_in(image, FIRST, tracker)
    assert len(faces) == 3
    assert max(faces, key=lambda f: f.box[2] - f.box[0]) is faces[1]
    return faces


def _with_descriptors(path: Path, descriptors: np.ndarray) -> PersonModel:
    return replace(load_model(path), descriptors=descriptors.astype(np.float32), sha256="",
                   file_bytes=0)


def test_descriptors_round_trip_and_an_older_model_still_loads(generic_model: Path,
                                                                tmp_path: Path) -> None:
    older = load_model(generic_model)
    assert older.descriptors is None  # a model without descriptors loads
    descriptors = np.random.default_rng(1).normal(0, 0.1, (3, 128)).astype(np.float32)
    path = tmp_path / "with.fwm"
    save_model(_with_descriptors(generic_model, descriptors), path)
    loaded = load_model(path)
    assert loaded.descriptors is not None and loaded.descriptors.dtype == np.float32
    np.testing.assert_array_equal(loaded.descriptors, descriptors)
    assert "arrays/descriptors.npy" in zip_members(path)
    assert "arrays/descriptors.npy" not in zip_members(generic_model)


@pytest.mark.parametrize("bad, declared, fragment", [
    (np.full((2, 128), np.nan, np.float32), [2, 128], "descriptors (arrays/descriptors.npy): "
                                                      "contains NaN or infinity"),
    (np.zeros((2, 64), np.float32), [2, 64], "arrays/descriptors.npy: expected shape (D, 128)"),
    (np.zeros((17, 128), np.float32), [17, 128], "descriptors (arrays/descriptors.npy): "
                                                 "expected shape (D, 128) with D in [1, 16]"),
    (np.zeros((2, 128), np.float64), [2, 128], "arrays/descriptors.npy: expected dtype float32"),
])
def test_a_corrupt_descriptor_member_is_refused_naming_it(generic_model: Path, tmp_path: Path,
                                                          bad: np.ndarray, declared: list,
                                                          fragment: str) -> None:
    good = tmp_path / "good.fwm"
    save_model(_with_descriptors(generic_model, np.zeros((2, 128), np.float32)), good)
    members = zip_members(good)
    manifest = json.loads(members["model.json"])
    manifest["members"]["arrays/descriptors.npy"] = {"dtype": bad.dtype.name, "shape": declared}
    members["model.json"] = json.dumps(manifest).encode()
    members["arrays/descriptors.npy"] = npy_bytes(bad)
    path = write_zip(tmp_path / "bad.fwm", members)
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    assert str(info.value).startswith(f"{path}: ") and fragment in str(info.value), info.value


def test_the_sender_warns_once_about_a_model_without_descriptors(generic_model: Path,
                                                                 clip: Path,
                                                                 tmp_path: Path) -> None:
    said: list[str] = []
    encode_video(generic_model, clip, tmp_path / "out.fwlog", frames=slice(0, 3),
                 learn=False, warn=said.append, audio=False)  # the clip has no sound to say
    assert len(said) == 1 and "cannot hold its person" in said[0]
    assert said[0] == identity_warning(load_model(generic_model), generic_model)
    assert "\n" not in said[0]


def test_a_model_of_one_person_never_drives_the_stream_with_another(
        generic_model: Path, clip: Path, people: list) -> None:
    # the man at the back right, a face 73 px wide beside the 125 px face of the man in front
    back = people[2]
    model = _with_descriptors(generic_model, back.descriptor[None])
    pipeline = SenderPipeline(model, sender_camera(640, 480), learn=False)
    hog = LandmarkTracker()
    followed = 0
    for frame in read_frames(clip, slice(FIRST, FIRST + 40)):
        out = pipeline.process(frame.image, frame.time)
        if out.points is None:
            continue
        box = (*out.points.min(axis=0), *out.points.max(axis=0))
        faces = hog.faces(frame.image)
        front = max(faces, key=lambda f: f[2] - f[0])
        assert box_iou(box, front) < 0.1, f"frame {frame.index}: the man in front drives it"
        followed += 1
    assert followed >= 35
    # the same without descriptors follows the largest face: the man in front
    pipeline = SenderPipeline(load_model(generic_model), sender_camera(640, 480), learn=False)
    out = pipeline.process(next(read_frames(clip, slice(FIRST, FIRST + 1))).image, 0.0)
    assert out.points is not None
    assert abs(out.points[:, 0].mean() - (people[1].box[0] + people[1].box[2]) / 2) < 40


def test_the_person_is_told_apart_and_chosen(clip: Path, tracker: LandmarkTracker,
                                             people: list, tmp_path: Path) -> None:
    sampled = [people] + [faces_in(f.image, f.index, tracker)
                          for f in read_frames(clip, slice(90, 151, 30))]
    for k, face in enumerate(people):
        person = Person(face.descriptor[None])
        distances = [person.distance_of(f.descriptor) for f in people]
        assert distances[k] == 0.0
        assert min(d for j, d in enumerate(distances) if j != k) >= MATCH_DISTANCE
    by_index = choose_person(sampled, 2, CLIP)
    assert (by_index.how, by_index.index, by_index.people) == ("index", 2, 3)
    assert by_index.summary()["index"] == 2 and "face 2 of 3" in by_index.line()
    # a photo of the man in front (a crop of another frame) picks him
    image = next(read_frames(clip, slice(150, 151))).image
    front = max(faces_in(image, 150, tracker), key=lambda f: f.box[2] - f.box[0])
    x0, y0, x1, y1 = front.box
    side = x1 - x0
    photo = tmp_path / "front.png"
    cv2.imwrite(str(photo), image[max(y0 - side, 0):y1 + side, max(x0 - side, 0):x1 + side])
    by_photo = choose_person(sampled, photo_descriptor(photo, tracker), CLIP, str(photo))
    assert (by_photo.how, by_photo.index) == ("photo", 1)
    with pytest.raises(PersonError, match=r"--person 3: frame 60 of .* holds 3 faces"):
        choose_person(sampled, 3, CLIP)
    with pytest.raises(PersonError, match="no face found in the photo"):
        photo_descriptor(_blank(tmp_path), tracker)


def _blank(tmp_path: Path) -> Path:
    path = tmp_path / "blank.png"
    cv2.imwrite(str(path), np.full((200, 200, 3), 128, np.uint8))
    return path


@pytest.fixture(scope="module")
def back_model(clip: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A geometry-only model of the man at the back right (``--person 2``), frames 60:90."""
    out = tmp_path_factory.mktemp("identity") / "back.fwm"
    result = build_model(clip, out, frames=slice(FIRST, FIRST + 30), appearance=False, person=2)
    summary = result.summary()
    assert summary["person"]["chosen"] == "index" and summary["person"]["index"] == 2
    assert summary["descriptors"] >= 4
    preview = cv2.imread(str(result.preview))
    assert preview.shape[0] > 480  # the person row below the renders
    return out


def test_bench_quality_judges_whom_the_sender_followed(back_model: Path, clip: Path,
                                                       people: list) -> None:
    model = load_model(back_model)
    assert model.descriptors is not None
    assert Person(model.descriptors).distance_of(people[2].descriptor) < MATCH_DISTANCE
    assert Person(model.descriptors).distance_of(people[1].descriptor) >= MATCH_DISTANCE
    r = measure_quality(back_model, clip, frames=slice(FIRST + 30, FIRST + 45))
    assert r["identity_switches"] == 0 and r["identity_unrecognised"] == 0
    assert r["identity_frames"] == r["tracked_frames"] >= 12
    assert 0 <= r["identity_distance_max"] < MATCH_DISTANCE
    assert (r["reacquire_s"] is None) == (r["returns"] == r["reacquire_missed"])


def test_the_face_is_absent_while_the_person_is_gone_and_back_when_they_return(
        generic_model: Path, clip: Path, people: list) -> None:
    # the man at the back right covered by a grey patch on frames 70-84 (his box, grown):
    # the packets say no face then, though two other faces are in the picture, and say it
    # again within 0.5 s of his return
    back = people[2]
    model = _with_descriptors(generic_model, back.descriptor[None])
    pipeline = SenderPipeline(model, sender_camera(640, 480), learn=False)
    x0, y0, x1, y1 = back.box
    pad = (x1 - x0) // 2
    present = {}
    for frame in read_frames(clip, slice(FIRST, FIRST + 45)):
        image = frame.image.copy()
        if 70 <= frame.index < 85:
            image[max(y0 - pad, 0):y1 + pad, max(x0 - pad, 0):x1 + pad] = 128
        out = pipeline.process(image, frame.time)
        present[frame.index] = bool(out.frame.flags & Flag.FACE_PRESENT)
        if out.points is not None:
            centre = out.points.mean(axis=0)
            assert x0 - pad <= centre[0] <= x1 + pad, f"frame {frame.index}: not his face"
    assert all(present[i] for i in range(FIRST, 70))
    assert not any(present[i] for i in range(71, 85))
    back_at = min(i for i in range(85, FIRST + 45) if present[i])
    assert back_at - 85 <= 15  # frames at 30 Hz: 0.5 s
    assert all(present[i] for i in range(back_at, FIRST + 45))


def test_the_judge_catches_a_tracker_that_follows_the_largest_face(
        generic_model: Path, clip: Path, people: list) -> None:
    # the tracker without a person follows the man in front; judged with a model of the
    # man at the back right, every one of its frames is a switch, by both rules: the
    # tracked face is another person of the run's census, and the person is elsewhere
    back = people[2]
    model = _with_descriptors(generic_model, back.descriptor[None])
    largest = LandmarkTracker()
    images, tracked = [], []
    for frame in read_frames(clip, slice(FIRST + 30, FIRST + 45)):
        images.append(frame.image)
        tracked.append(largest.track(frame.image).points)
    assert all(p is not None for p in tracked)
    judge = LandmarkTracker()
    r = identity_measures(model, images, tracked, [k / 30 for k in range(len(images))],
                          np.ones(len(images), bool), judge, no_progress)
    assert r["identity_switches"] == r["identity_frames"] == len(images)
    assert r["identity_unrecognised"] == 0
    # the sender's own tracker on the same frames: his face on every frame (and
    # test_bench_quality_judges_whom_the_sender_followed: no switch)
    pipeline = SenderPipeline(model, sender_camera(640, 480), learn=False)
    his = [pipeline.process(image, k / 30).points for k, image in enumerate(images)]
    verdicts = judge_frames(Person(model.descriptors), images, his, judge, no_progress)
    assert len(verdicts) >= 12 and {v for _, v in verdicts.values()} == {"person"}


def test_the_person_is_back_within_half_a_second_after_a_cutaway(
        generic_model: Path, shared_data: Path) -> None:
    # hamilton_short: the singer (frames 82-210), then the audience (211-274: other people,
    # one of them a face the detector finds); edited as a broadcast cuts away and back: the
    # singer at 165-179, the audience at 211-259 (1.6 s), the singer at 180-199
    source = shared_data / "video" / "hamilton_short.mp4"
    order = [*range(165, 180), *range(211, 260), *range(180, 200)]
    images = {f.index: f.image for f in read_frames(source, slice(165, 260))}
    tracker = LandmarkTracker()
    seed = [faces_in(images[k], k, tracker) for k in (170, 190)]
    assert [len(faces) for faces in seed] == [1, 1]
    model = _with_descriptors(generic_model, np.stack([f[0].descriptor for f in seed]))
    pipeline = SenderPipeline(model, sender_camera(640, 360), learn=False)
    run = [images[k] for k in order]
    times = [k / 29.97 for k in range(len(order))]
    present, tracked = [], []
    for image, t in zip(run, times, strict=True):
        out = pipeline.process(image, t)
        present.append(bool(out.frame.flags & Flag.FACE_PRESENT))
        tracked.append(out.points)
    assert sum(present[:15]) >= 15 - 3  # the first check may retry a near miss
    _assert_back_after_the_cutaway(model, run, tracked, times, present, 15, tracker)


def _assert_back_after_the_cutaway(model: PersonModel, run: list[np.ndarray],
                                   tracked: list[np.ndarray | None], times: list[float],
                                   present: list[bool], away: int,
                                   tracker: LandmarkTracker) -> None:
    """The singer's packets: none while the audience (49 frames from ``away``) is shown,
    from within 0.5 s of his return to the end, and no switch."""
    back = away + 49
    assert not any(present[away:back]), "the audience drove the singer's stream"
    back_at = min(k for k in range(back, len(run)) if present[k])
    assert times[back_at] - times[back] <= 0.5
    assert all(present[back_at:])
    r = identity_measures(model, run, tracked, times, np.array(present), tracker, no_progress)
    assert r["returns"] == 1 and r["reacquire_missed"] == 0
    assert r["reacquire_s"] is not None and r["reacquire_s"] <= 0.5
    assert r["identity_switches"] == 0


def test_the_checks_apart_answer_later_with_the_same_distances(clip: Path, people: list,
                                                               tracker: LandmarkTracker) -> None:
    image = next(read_frames(clip, slice(FIRST, FIRST + 1))).image
    points = [tracker.points_in(image, f.box) for f in people]
    here = Person(people[2].descriptor[None])
    apart = Person(people[2].descriptor[None], apart=True)
    try:
        tickets = [apart.submit(image, p) for p in points]
        assert apart.poll() == {}  # the frame path went on; the child answers later
        answers: dict[int, float] = {}
        deadline = time.monotonic() + 60
        while len(answers) < len(tickets) and time.monotonic() < deadline:
            answers.update(apart.poll())
            time.sleep(0.01)
        expected = [here.distance(image, p) for p in points]
        assert [answers[t] for t in tickets] == pytest.approx(expected, abs=1e-6)
        assert expected[2] < MATCH_DISTANCE <= min(expected[:2])
        apart._process.kill()  # the child killed (as the out-of-memory killer would)
        apart._process.join()
        apart.submit(image, points[0])
        with pytest.raises(IdentityError, match=r"the identity process \(pid \d+\) exited"):
            apart.poll()
    finally:
        apart.close()


def test_a_live_sender_holds_the_person_with_the_checks_apart(
        generic_model: Path, shared_data: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the cutaway of the test above, played at its rate as a camera gives it (the singer
    # first for 1 s), and the descriptor network
    # forbidden in this process: every check is answered by the identity process, frames
    # later, while the frames go on
    source = shared_data / "video" / "hamilton_short.mp4"
    order = [*range(150, 180), *range(211, 260), *range(180, 200)]
    images = {f.index: f.image for f in read_frames(source, slice(150, 260))}
    tracker = LandmarkTracker()
    seed = [faces_in(images[k], k, tracker) for k in (170, 190)]
    model = _with_descriptors(generic_model, np.stack([f[0].descriptor for f in seed]))

    def forbidden() -> None:
        raise AssertionError("a descriptor was computed on the frame path")

    monkeypatch.setattr(identity, "_network", forbidden)
    pipeline = SenderPipeline(model, sender_camera(640, 360), learn=False, identify_apart=True)
    run = [images[k] for k in order]
    times = [k / 29.97 for k in range(len(order))]
    present, tracked = [], []
    start = time.monotonic()
    try:
        for image, t in zip(run, times, strict=True):
            time.sleep(max(0.0, start + t - time.monotonic()))
            out = pipeline.process(image, t)
            present.append(bool(out.frame.flags & Flag.FACE_PRESENT))
            tracked.append(out.points)
    finally:
        pipeline.close()
    monkeypatch.undo()
    assert all(present[15:30]), "the singer was not taken within 0.5 s"
    _assert_back_after_the_cutaway(model, run, tracked, times, present, 30, tracker)
