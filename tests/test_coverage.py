"""Coverage (``sender.enroll.coverage``): which expression states a model's layers show,
judged on short ranges of real clips whose content is known (``../shared/data/SOURCES.md``),
through ``facewire model build --json`` and ``model info``, and stored in the model."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from facewire.cli import main
from facewire.models.modelfile import ModelFileError, load_model, save_model
from facewire.sender.enroll.coverage import (
    MEASURES,
    NEUTRAL_ONLY,
    STATE_NAMES,
    STATES,
    measure_coverage,
    missing_lines,
    reference,
)

# (clip, frames): the states its layers must show, and states they must not
CASES = {
    # lp_d14 0:60: a wink and a blink, a smile with teeth; the lips never part wide
    ("lp_d14.mp4", "0:60"): ({"eyes_closed", "smile_teeth"}, {"mouth_open", "mouth_wide"}),
    # lp_d18 60:150: the yawn and the wide-open mouth; eyes open, no frown
    ("lp_d18.mp4", "60:150"): ({"mouth_open", "mouth_wide"},
                               {"eyes_closed", "brows_furrowed", "gaze_left", "gaze_right"}),
    # lp_d3 170:260: the frown with the eyes shut; the mouth closed, no teeth, brows down
    ("lp_d3.mp4", "170:260"): ({"brows_furrowed"},
                               {"mouth_open", "smile_teeth", "brows_raised"}),
    # lp_d3 240:330: the end of the frown, then the surprise: brows up, mouth open
    ("lp_d3.mp4", "240:330"): ({"brows_raised", "mouth_open"}, {"smile_teeth", "mouth_wide"}),
    # openface_gaze 40:100: gaze shifts to either side; a neutral mouth
    ("openface_gaze.avi", "40:100"): ({"gaze_left", "gaze_right"},
                                      {"mouth_open", "smile_teeth", "brows_furrowed"}),
}


@pytest.mark.parametrize("case", list(CASES), ids=[f"{c}:{f}" for c, f in CASES])
def test_coverage_on_real_clips(shared_data, tmp_path, capsys, case):
    clip, frames = case
    path, video = tmp_path / "model.fwm", shared_data / "video" / clip
    assert main(["model", "build", str(video), "--frames", frames, "-o", str(path),
                 "--json"]) == 0
    text = capsys.readouterr().out
    summary = json.loads(text.strip().splitlines()[-1])
    covered, missing = CASES[case]
    coverage = summary["coverage"]
    assert set(coverage) == set(STATE_NAMES)
    for state in covered:
        assert coverage[state], (state, summary["coverage_detail"][state])
    for state in missing:
        assert not coverage[state], (state, summary["coverage_detail"][state])
    # one line per state not fully covered, in the text and the JSON alike
    lines = summary["coverage_lines"]
    assert len(lines) == sum(not v for v in coverage.values())
    assert NEUTRAL_ONLY not in lines
    for line in lines:
        assert line in text
    # stored in the model, and shown by model info
    model = load_model(path)
    assert model.coverage == coverage
    assert main(["model", "info", str(path), "--json"]) == 0
    info_text = capsys.readouterr().out
    assert json.loads(info_text.strip().splitlines()[-1])["coverage"] == coverage
    for line in missing_lines(coverage):
        assert line in info_text
    # the frames per region (sender.enroll.usage): in the build's JSON, a line each in its
    # text and in model info's; a wink or a blink is not an occluded eye
    used = summary["region_frames"]
    assert set(used) == set(summary["appearance"])
    for name, entry in used.items():
        assert entry["candidates"] == summary["frames"] and entry["used"], (name, entry)
        assert f"          {name}: {len(entry['used'])} of {summary['frames']} frames used" \
            in text and f"{name}: {len(entry['used'])} of" in info_text
    if "eyes_closed" in covered:
        for name in ("eyelid_left", "eyelid_right"):
            assert used[name]["rejected"].get("occluded", 0) <= 0.05 * summary["frames"]


def test_photo_reports_only_the_neutral(shared_data, tmp_path, capsys):
    out = tmp_path / "photo.fwm"
    photo = shared_data / "images" / "image_0001.png"
    assert main(["model", "build", str(photo), "-o", str(out), "--json"]) == 0
    text = capsys.readouterr().out
    summary = json.loads(text.strip().splitlines()[-1])
    assert summary["coverage"] == {name: False for name in STATE_NAMES}
    assert summary["coverage_lines"][0] == NEUTRAL_ONLY and NEUTRAL_ONLY in text
    assert len(summary["coverage_lines"]) == 1 + len(STATE_NAMES)
    assert load_model(out).coverage == summary["coverage"]
    assert main(["model", "info", str(out)]) == 0
    assert NEUTRAL_ONLY in capsys.readouterr().out


def _measures(**values: float) -> np.ndarray:
    row = np.array([{"ear_right": 0.3, "ear_left": 0.3, "iris_right": 0.5,
                     "iris_left": 0.5}.get(m, 0.0) for m in MEASURES])
    for name, v in values.items():
        row[MEASURES.index(name)] = v
    return row


def test_thresholds_on_made_up_layers():
    rest = _measures()
    ref = reference(np.stack([rest] * 5))
    layers = {
        "eyelid_right": np.stack([rest, _measures(ear_right=0.2), _measures(ear_right=0.1)]),
        "eyelid_left": np.stack([rest, _measures(ear_left=0.2)]),  # 0.67: lowered, not shut
        "eyeball_right": np.stack([rest, _measures(iris_right=0.8, iris_left=0.8)]),
        "eyeball_left": np.stack([rest, _measures(iris_right=0.8, iris_left=0.8)]),
        "forehead": np.stack([rest, _measures(brow_mm=3.5)]),
        "brow_furrow": np.stack([rest, _measures(furrow_mm=2.0)]),
        "mouth": np.stack([rest, _measures(mouth_gap=0.2, teeth=0.3)]),
    }
    c = measure_coverage(layers, ref)
    assert list(c.states) == list(STATE_NAMES)
    assert c.states == {"eyes_closed": False, "gaze_left": True, "gaze_right": False,
                        "gaze_up": False, "gaze_down": True, "brows_raised": True,
                        "brows_furrowed": False, "mouth_open": True, "mouth_wide": False,
                        "smile_teeth": True}
    assert c.lines[0].startswith("eyes closed: seen by eyelid_right only; in eyelid_left ")
    assert any(line.startswith("brows furrowed: not seen; ") for line in c.lines)
    assert c.detail["eyes_closed"]["eyelid_right"] == [1.0, pytest.approx(0.6667, abs=1e-4),
                                                       pytest.approx(0.3333, abs=1e-4)]
    # a stored coverage says the same, in STATES order whatever order it was stored in
    stored = dict(sorted(c.states.items()))
    labels = [s.label for s in STATES if not c.states[s.name]]
    assert [line.split(": ")[0] for line in missing_lines(stored)] == labels
    assert missing_lines({name: False for name in STATE_NAMES})[0] == NEUTRAL_ONLY


def test_coverage_is_optional_and_checked_in_the_file(generic_model, tmp_path, capsys):
    old = load_model(generic_model)
    assert old.coverage is None  # a model saved without it loads, and says so
    assert main(["model", "info", str(generic_model)]) == 0
    assert "coverage: not measured" in capsys.readouterr().out
    from dataclasses import replace

    path = tmp_path / "with.fwm"
    save_model(replace(old, coverage={"eyes_closed": True, "mouth_open": False}), path)
    assert load_model(path).coverage == {"eyes_closed": True, "mouth_open": False}
    # a bad value is refused by name
    bad = tmp_path / "bad.fwm"
    with zipfile.ZipFile(path) as z, zipfile.ZipFile(bad, "w") as out:
        for item in z.infolist():
            data = z.read(item)
            if item.filename == "model.json":
                data = data.replace(b'"eyes_closed": true', b'"eyes_closed": 1')
            out.writestr(item, data)
    with pytest.raises(ModelFileError, match="coverage"):
        load_model(bad)
