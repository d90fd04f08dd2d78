"""``facewire model build --guided``: the routine (``sender.enroll.routine``), its recording
(``sender.enroll.guided``) and the build from it, with real video standing in for the camera.

lp_d3.mp4 (30 fps, 11.8 s) stands in: with a 0.6 s lead-in and 0.3 s takes the routine's 11
prompts take 9.9 s of it, 9 frames each. The person in it does not follow the prompts, so
the test is that each region's states come from its own prompts' frames, the neutral from
the neutral take, as the build says (unguided, the eyelids' closed state and the mouth's
widest come from other takes of this recording).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import write_video

from facewire.cli import main
from facewire.models.modelfile import load_model
from facewire.models.regions import REGION_NAMES
from facewire.sender.capture import open_source
from facewire.sender.enroll.guided import (
    MAX_TRIES,
    RECORD,
    Cue,
    GuidedError,
    overlay,
    record_routine,
)
from facewire.sender.enroll.routine import ROUTINE, Guide, Schedule

FACEWIRE = str(Path(sys.executable).with_name("facewire"))
LEAD, TAKE = "0.6", "0.3"
MISSING_CAMERA = "camera:7"


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FACEWIRE, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def guided(shared_data: Path, tmp_path_factory: pytest.TempPathFactory
           ) -> tuple[subprocess.CompletedProcess[str], dict, Path]:
    """``model build --guided lp_d3.mp4``, run as a user runs it: the process, its JSON
    summary and the model."""
    out = tmp_path_factory.mktemp("guided") / "me.fwm"
    done = run("model", "build", "--guided", str(shared_data / "video" / "lp_d3.mp4"),
               "--lead-seconds", LEAD, "--prompt-seconds", TAKE, "-o", str(out),
               "--no-self-check", "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    return done, json.loads(done.stdout.strip().splitlines()[-1]), out


def test_routine_prompts_every_region_in_order() -> None:
    assert [p.name for p in ROUTINE] == [
        "neutral", "brows_up", "frown", "eyes_closed", "look_left", "look_right", "look_up",
        "look_down", "smile", "smile_wide", "mouth_open"]
    assert {r for p in ROUTINE for r in p.feeds} == set(REGION_NAMES)
    guide = Guide.of_labels(["neutral", "neutral", None, "eyes_closed", "look_up", "smile"])
    assert guide.neutral == {0, 1}
    assert guide.regions["eyelid_left"] == guide.regions["eyelid_right"] == {3}
    assert guide.regions["eyeball_left"] == {4} and guide.regions["mouth"] == {5}
    assert guide.regions["forehead"] == frozenset()
    with pytest.raises(ValueError, match="--prompt-seconds"):
        Schedule(1.0, 0.0)
    with pytest.raises(ValueError, match="--lead-seconds"):
        Schedule(float("nan"), 1.0)


def test_prompts_appear_in_order_and_each_region_takes_its_prompts_frames(guided) -> None:
    done, s, out = guided
    announced = [line for line in done.stderr.replace("\r", "\n").splitlines()
                 if line.startswith("[")]
    assert announced == [f"[{k}/{len(ROUTINE)}] {p.text}" for k, p in enumerate(ROUTINE, 1)]
    takes = {t["prompt"]: range(*t["frames"]) for t in s["guided"]["prompts"]}
    assert [t["prompt"] for t in s["guided"]["prompts"]] == [p.name for p in ROUTINE]
    assert all(len(frames) == 9 for frames in takes.values())
    assert s["neutral_frame"] in takes["neutral"]
    for name, region in s["appearance"].items():
        prompted = [f for p in ROUTINE if name in p.feeds for f in takes[p.name]]
        others = [f for j, f in enumerate(region["frames"]) if j != region["rest"]]
        assert region["prompted"] and all(f in prompted for f in others), (name, region)
        assert region["frames"][region["rest"]] == s["neutral_frame"]
    for eyelid in ("eyelid_left", "eyelid_right"):  # the closed state: the last, the extreme
        assert s["appearance"][eyelid]["frames"][-1] in takes["eyes_closed"]
    assert s["appearance"]["forehead"]["frames"][-1] in takes["brows_up"]
    assert s["appearance"]["mouth"]["frames"][-1] in [*takes["smile"], *takes["smile_wide"],
                                                      *takes["mouth_open"]]
    assert (s["source"]["video"], s["source"]["start"], s["source"]["stop"]) == (
        "lp_d3.mp4", 18, 297)  # the stand-in's frames, first take (after a lead-in) to last
    assert "built from: lp_d3.mp4 frames 18:297" in done.stdout
    model = load_model(out)
    assert len(model.regions) == len(REGION_NAMES) and model.coverage == s["coverage"]
    assert "coverage: " in done.stdout and "guided:   " in done.stdout
    assert f"11. {ROUTINE[-1].text}: frames 90:99, 9 with a face" in done.stdout


def test_missing_camera_is_the_same_one_line_error_as_send(
        generic_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if Path(f"/dev/video{MISSING_CAMERA[7:]}").exists():
        pytest.skip(f"{MISSING_CAMERA} exists on this machine")
    send = main(["send", "--model", str(generic_model), "--source", MISSING_CAMERA])
    sent = capsys.readouterr()
    build = main(["model", "build", "--guided", MISSING_CAMERA, "-o", str(tmp_path / "m.fwm")])
    built = capsys.readouterr()
    assert build == send == 2
    assert built.err == sent.err and built.out == sent.out == ""
    assert built.err.count("\n") == 1 and built.err.startswith(f"facewire: {MISSING_CAMERA}: ")
    assert not (tmp_path / "m.fwm").exists()


@pytest.mark.parametrize("args, field", [
    (["video.mp4", "--guided", "camera:0"], "give one of"),
    (["--guided", "camera:0", "--frames", "0:10"], "--frames"),
    (["--guided", "camera:0", "--prompt-seconds", "0"], "--prompt-seconds"),
    ([], "give one of")])
def test_bad_guided_arguments_are_one_line_errors(args: list[str], field: str, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["model", "build", *args, "-o", str(tmp_path / "m.fwm")]) == 2
    err = capsys.readouterr().err
    assert field in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_lost_face_is_prompted_again_then_kept(tmp_path: Path) -> None:
    """A grey video: no face in any take, so every prompt is asked MAX_TRIES times, the
    last take kept with 0 face frames; a video too short for the routine is refused."""
    rate, take = 25, 0.2  # 5 frames a take
    frames = round(len(ROUTINE) * MAX_TRIES * take * rate) + 2
    video = write_video(tmp_path / "grey.mp4", [np.full((120, 160, 3), 128, np.uint8)] * frames,
                        rate)
    said: list[str] = []
    cues: list[Cue] = []
    written: list[np.ndarray] = []
    with open_source(str(video)) as source:
        recording = record_routine(source, written.append, Schedule(0.0, take),
                                   lambda cue, image: cues.append(cue), said.append)
    assert [t.tries for t in recording.takes] == [MAX_TRIES] * len(ROUTINE)
    assert all(t.face_frames == 0 and t.frames[1] - t.frames[0] == 5 for t in recording.takes)
    assert len(said) == len(ROUTINE) * MAX_TRIES
    assert said[1] == f"[1/{len(ROUTINE)}] {ROUTINE[0].text} (again: a face in 0 of 5 frames)"
    assert len(written) == len(recording.labels) == len(ROUTINE) * MAX_TRIES * 5
    assert recording.labels.count(None) == len(ROUTINE) * (MAX_TRIES - 1) * 5
    assert all(c.phase == RECORD and c.face is False for c in cues)
    drawn = overlay(np.full((120, 160, 3), 128, np.uint8), cues[0])
    assert drawn.shape == (120, 160, 3) and (drawn[:20] != 128).any()

    short = write_video(tmp_path / "short.mp4", [np.full((120, 160, 3), 128, np.uint8)] * 20,
                        rate)
    with open_source(str(short)) as source, pytest.raises(GuidedError, match="short.mp4: ended "
                                                          "0.8 s into the routine"):
        record_routine(source, written.append, Schedule(0.0, take), name=source.name)


def test_view_shows_each_prompt_on_the_live_page(tmp_path: Path) -> None:
    """``--view`` on a faceless video, paced in real time (3.3 s): the page's statistics name
    the prompts in routine order and its frame has the prompt's band drawn over it; the
    build then finds no face: one line, exit 2."""
    video = write_video(tmp_path / "grey.mp4", [np.full((120, 160, 3), 128, np.uint8)] * 90,
                        25)
    process = subprocess.Popen(
        [FACEWIRE, "model", "build", "--guided", str(video), "--lead-seconds", "0",
         "--prompt-seconds", "0.1", "--view", "--view-port", "0", "-o",
         str(tmp_path / "m.fwm"), "--no-self-check"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    assert process.stderr is not None
    lines: list[str] = []
    drain = threading.Thread(target=lambda: lines.extend(process.stderr or ()), daemon=True)
    url = process.stderr.readline().strip().rsplit(" ", 1)[-1]
    drain.start()
    assert url.startswith("http://127.0.0.1:"), url
    seen: list[str] = []
    frame = None
    while process.poll() is None:
        try:
            with urllib.request.urlopen(url + "stats.json", timeout=2) as reply:
                prompt = json.load(reply)["stats"].get("prompt")
            if prompt and (not seen or seen[-1] != prompt):
                seen.append(prompt)
            if frame is None and prompt:
                with urllib.request.urlopen(url + "frame.jpg", timeout=2) as reply:
                    frame = cv2.imdecode(np.frombuffer(reply.read(), np.uint8), cv2.IMREAD_COLOR)
        except (OSError, ValueError):
            pass  # the page closed between the check and the request
        time.sleep(0.05)
    drain.join(5)
    texts = [f"{k}/{len(ROUTINE)}: {p.text}" for k, p in enumerate(ROUTINE, 1)]
    assert len(seen) >= 5 and seen == sorted(seen, key=texts.index), seen
    assert frame is not None and frame.shape == (120, 160, 3)
    assert (frame[:20] < 100).mean() > 0.5 and abs(int(frame[100, 80, 0]) - 128) < 8
    assert process.returncode == 2
    assert lines[-1] == f"facewire: {video} (its guided recording): no face found in frames 0..82\n"


def test_a_take_that_loses_the_face_is_taken_again(shared_data: Path, tmp_path: Path) -> None:
    """lp_d0 with its first 5 frames blanked: the neutral's first take (frames 0-4) has no
    face, so it is asked again and the second take (5-9) is kept; the blank take's frames
    stay in the recording without a prompt."""
    from facewire.models.infra.video import read_frames

    images = [f.image for f in read_frames(shared_data / "video" / "lp_d0.mp4", slice(0, 62))]
    images[:5] = [np.full_like(images[0], 128)] * 5
    video = write_video(tmp_path / "blank_start.mp4", images, 25)
    said: list[str] = []
    with open_source(str(video)) as source:
        recording = record_routine(source, lambda image: None, Schedule(0.0, 0.2),
                                   say=said.append)
    first = recording.takes[0]
    assert (first.tries, first.frames, first.source_frames, first.face_frames) == (
        2, (5, 10), (5, 10), 5)
    assert said[:2] == [f"[1/{len(ROUTINE)}] {ROUTINE[0].text}",
                        f"[1/{len(ROUTINE)}] {ROUTINE[0].text} (again: a face in 0 of 5 frames)"]
    assert recording.labels[:10] == (None,) * 5 + ("neutral",) * 5
    assert all(t.tries == 1 and t.face_frames == 5 for t in recording.takes[1:])
    assert recording.source_frames == (0, 60)
    assert recording.guide(source).origin_range is not None
