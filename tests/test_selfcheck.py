"""The build's self-check (``bench.selfcheck``): ``model build`` renders the finished model
at its own frames with the real sender pipeline, renderer and tracker, scores it, stores it,
and warns, naming a likely cause, when the score is poor. Real data, short ranges."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import write_zip, zip_members

from facewire.bench.selfcheck import (
    CAUSES,
    LOST_FRACTION,
    MAX_FRAMES,
    MIN_FACE_FRAMES,
    POOR_RENDER_NME,
    POOR_SSIM,
    Evidence,
    diagnose,
    pick_frames,
    read_picked,
    score_frames,
)
from facewire.cli import main
from facewire.models.fields import ModelError
from facewire.models.manifest import SelfCheck
from facewire.models.modelfile import ModelFileError, load_model, save_model

KEYS = ("self_check_ssim", "self_check_render_nme", "self_check_frames")


def _json(capsys: pytest.CaptureFixture[str]) -> tuple[dict, str, str]:
    captured = capsys.readouterr()
    return json.loads(captured.out.strip().splitlines()[-1]), captured.out, captured.err


@pytest.fixture(scope="module")
def lp_d0(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(video, model path): lp_d0's model from frames 0:40, built by the test below."""
    return shared_data / "video" / "lp_d0.mp4", tmp_path_factory.mktemp("sc") / "lp_d0.fwm"


@pytest.fixture(scope="module")
def built(lp_d0: tuple[Path, Path]) -> tuple[dict, str, str]:
    """``model build lp_d0.mp4 --frames 0:40 --json`` through the command: (json, out, err)."""
    video, out = lp_d0
    import contextlib
    import io

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        assert main(["model", "build", str(video), "--frames", "0:40", "-o", str(out),
                     "--json"]) == 0
    return json.loads(stdout.getvalue().strip().splitlines()[-1]), stdout.getvalue(), \
        stderr.getvalue()


def test_build_reports_and_stores_a_plausible_self_check(built, lp_d0, capsys) -> None:
    """lp_d0 0:40: every frame has a face, so all 40 are scored (no more than MAX_FRAMES);
    the model renders its own frames well (measured: SSIM 0.867, render NME 1.81 %) and no
    warning is printed; ``model info`` shows the same scores from the file."""
    s, out, err = built
    assert set(KEYS) <= s.keys()
    assert s["self_check_frames_picked"] == 40 and 36 <= s["self_check_frames"] <= 40
    assert s["self_check_face_missing"] == 0
    assert 0.8 < s["self_check_ssim"] < 1.0
    assert 0.5 < s["self_check_render_nme"] < 3.0
    assert s["self_check_ssim"] > POOR_SSIM and s["self_check_render_nme"] < POOR_RENDER_NME
    for part in ("mouth", "eyes", "brows"):
        assert 0 < s[f"self_check_render_nme_{part}"] < 5
    assert not s["self_check_poor"] and s["self_check_causes"] == [] \
        and s["self_check_lines"] == []
    assert 0 < s["self_check_seconds"] < s["seconds"]
    assert s["self_check_evidence"]["face_frames"] == 40
    assert set(s["self_check_cause_ratios"]) == set(CAUSES)
    assert f"self-check: face SSIM {s['self_check_ssim']:.3f}, render NME " \
           f"{s['self_check_render_nme']:.2f} % over {s['self_check_frames']} of the build's " \
           f"own frames" in out
    assert "WARNING" not in out + err
    model = load_model(lp_d0[1])
    assert model.self_check == SelfCheck(s["self_check_ssim"], s["self_check_render_nme"],
                                         s["self_check_frames"], False, ())
    assert main(["model", "info", str(lp_d0[1]), "--json"]) == 0
    info, text, _ = _json(capsys)
    assert info["self_check"] == {"ssim": s["self_check_ssim"],
                                  "render_nme": s["self_check_render_nme"],
                                  "frames": s["self_check_frames"], "poor": False,
                                  "causes": []}
    assert f"self-check: face SSIM {s['self_check_ssim']:.3f}" in text


def test_no_self_check_skips_it(shared_data: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "quick.fwm"
    assert main(["model", "build", str(shared_data / "video" / "lp_d0.mp4"), "--frames",
                 "0:20", "-o", str(out), "--no-self-check", "--json"]) == 0
    s, text, _ = _json(capsys)
    assert not any(k.startswith("self_check") for k in s)
    assert "self-check: skipped (--no-self-check)" in text
    assert load_model(out).self_check is None
    assert main(["model", "info", str(out)]) == 0
    assert "self-check: not stored" in capsys.readouterr().out


def test_another_persons_frames_score_poorly_and_warn(built, lp_d0, shared_data) -> None:
    """lp_d0's model scored on lp_d18's frames (another person): the scores fall well below
    the model's own (measured: SSIM 0.79, render NME 4.6 % against 0.88 and 1.9 %), the
    verdict is poor, and the warning names a cause (of the 40-frame model: render NME 1.81 %)."""
    s = built[0]
    model = load_model(lp_d0[1])
    video = shared_data / "video" / "lp_d18.mp4"
    picked = read_picked(video, list(range(0, 120, 4)))
    # the model's own sender takes no other person's face (sender.identity): nothing to score
    assert score_frames(model, picked[:4], 30.0)["self_check_frames"] == 0
    # scored as a model that does not hold its person would be (older models)
    other = score_frames(replace(model, descriptors=None, sha256="", file_bytes=0), picked,
                         30.0)
    assert other["self_check_frames"] >= 25
    assert other["self_check_render_nme"] > s["self_check_render_nme"] + 1.5
    assert other["self_check_render_nme"] > POOR_RENDER_NME
    assert other["self_check_ssim"] < s["self_check_ssim"] - 0.05
    verdict = diagnose(other, Evidence(**s["self_check_evidence"]))
    assert verdict.poor and verdict.causes and set(verdict.causes) <= set(CAUSES)
    assert verdict.lines[0].startswith("WARNING: the model renders its own enrollment frames "
                                       "poorly (") and "render NME" in verdict.lines[0]
    assert verdict.lines[1].startswith("likely cause: ")
    assert any(cause in verdict.lines[1] for cause in CAUSES)


def test_a_wrong_model_scores_poorly(built, lp_d0, shared_data) -> None:
    """The same model with its texture shifted by an eighth of its width draws the wrong
    skin over every feature: at its own frames the tracker puts the eyes and mouth where the
    shifted texture has them (measured: render NME 37 %), and the verdict is poor. With a
    flat grey texture the tracker finds no face at all."""
    s = built[0]
    model = load_model(lp_d0[1])
    frames = read_picked(lp_d0[0], pick_frames(list(range(40)), 12))
    assert len(frames) == 12
    evidence = Evidence(**s["self_check_evidence"])
    shifted = replace(model, texture=np.roll(model.texture, model.texture.shape[1] // 8,
                                             axis=1), regions=(), region_frames=None, sha256="",
                      file_bytes=0)
    scores = score_frames(shifted, frames, 25.0)
    assert scores["self_check_render_nme"] > 3 * POOR_RENDER_NME > s["self_check_render_nme"]
    verdict = diagnose(scores, evidence)
    assert verdict.poor and f"render NME {scores['self_check_render_nme']:.2f} % > " \
        in verdict.lines[0]
    grey = replace(shifted, texture=np.full_like(model.texture, 170))
    scores = score_frames(grey, frames[:4], 25.0)
    assert scores["self_check_face_missing"] == 4 and scores["self_check_render_nme"] is None
    verdict = diagnose(scores, evidence)
    assert verdict.poor and "the tracker found no face on 4 of 4 renderings" in verdict.lines[0]


def test_the_warning_names_the_cause_the_evidence_shows() -> None:
    """A poor score is blamed on the causes past their thresholds, worst first; with none
    past, on the nearest; a photo is never blamed on motion, frame count or pose spread."""
    poor = {"self_check_ssim": POOR_SSIM - 0.1, "self_check_render_nme": 2.0}
    good = {"self_check_ssim": POOR_SSIM + 0.2, "self_check_render_nme": 1.0}
    clean = Evidence(frames=200, face_frames=200, posed_frames=200, speed_deg_s=10.0,
                     speed_mm_s=20.0, landmark_error_pct=2.0, yaw_range_deg=30.0)
    assert diagnose(good, clean) == diagnose(good, clean) and not diagnose(good, clean).poor
    assert diagnose(good, replace(clean, posed_frames=10)).lines == ()
    lost = replace(clean, posed_frames=int(200 * (1 - 2 * LOST_FRACTION)))
    verdict = diagnose(poor, lost)
    assert verdict.poor and verdict.causes == ("occlusion",)
    assert verdict.lines[1:] == ("likely cause: occlusion", "  occlusion: 80 of 200 frames "
                                 "without a face or pose (threshold 20 %); tracked points "
                                 "2.0 % of the eye distance from the fitted model (threshold "
                                 "6 %)")
    both = replace(lost, face_frames=MIN_FACE_FRAMES // 4, speed_deg_s=1000.0)
    assert diagnose(poor, both).causes == ("motion", "too few frames", "occlusion")
    narrow = replace(clean, yaw_range_deg=0.5)
    assert diagnose(poor, narrow).causes == ("too little pose spread",)
    nearest = diagnose(poor, clean)
    assert len(nearest.causes) == 1 and "none of motion, occlusion" in nearest.lines[1]
    photo = Evidence(1, 1, 1, None, None, 30.0, 0.0, photo=True)
    assert diagnose(poor, photo).causes == ("occlusion",)
    unscored = diagnose({"self_check_ssim": None, "self_check_render_nme": None}, clean)
    assert unscored.poor and "no frame could be scored" in unscored.lines[0]


def test_pick_frames_spreads_evenly() -> None:
    assert pick_frames(list(range(10))) == list(range(10))
    picked = pick_frames(list(range(0, 600, 2)))
    assert len(picked) == MAX_FRAMES and picked[0] == 0 and picked[-1] == 598
    assert np.ptp(np.diff(picked)) <= 2


def test_a_photo_scores_itself(shared_data: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "photo.fwm"
    assert main(["model", "build", str(shared_data / "images" / "image_0001.png"), "-o",
                 str(out), "--json"]) == 0
    s, _, _ = _json(capsys)
    assert s["self_check_frames_picked"] == 1 and s["self_check_frames"] == 1
    assert 0.5 < s["self_check_ssim"] < 1 and 0 < s["self_check_render_nme"] < 5
    assert s["self_check_evidence"]["photo"] and s["self_check_evidence"]["frames"] == 1
    assert load_model(out).self_check is not None


def test_the_stored_self_check_is_validated(built, lp_d0, tmp_path: Path) -> None:
    model = load_model(lp_d0[1])
    check = SelfCheck(0.5, 6.25, 12, True, ("motion", "occlusion"))
    path = lp_d0[1].with_name("poor.fwm")
    save_model(replace(model, self_check=check, sha256="", file_bytes=0), path)
    assert load_model(path).self_check == check
    for bad, field in ((dict(ssim=1.5), "self_check.ssim"),
                       (dict(render_nme=-1.0), "self_check.render_nme"),
                       (dict(render_nme=float("nan")), "self_check.render_nme"),
                       (dict(frames=-1), "self_check.frames"),
                       (dict(poor=1), "self_check.poor"),
                       (dict(causes=("x" * 65,)), r"self_check.causes\[0\]"),
                       (dict(causes=("a",) * 9), "self_check.causes")):
        with pytest.raises(ModelError, match=field):
            SelfCheck(**{**check.as_dict(), "causes": check.causes, **bad})
    members = zip_members(path)
    manifest = json.loads(members["model.json"])
    for entry, field in (({**manifest["self_check"], "frames": "x"}, "self_check.frames"),
                         ({**manifest["self_check"], "extra": 1}, "self_check: unknown key"),
                         ([], "self_check: expected an object")):
        members["model.json"] = json.dumps({**manifest, "self_check": entry}).encode()
        with pytest.raises(ModelFileError, match=field):
            load_model(write_zip(tmp_path / "bad.fwm", members))
