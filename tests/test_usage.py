"""Per region, the enrollment frames used and rejected (``sender.enroll.usage``): counted from
the layers' own decisions, stored in the model (``region_frames``), printed by ``model info``."""

from __future__ import annotations

import json
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from facewire.cli import main
from facewire.models.fields import ModelError
from facewire.models.manifest import RegionFrames
from facewire.models.modelfile import ModelFileError, load_model, save_model
from facewire.sender.enroll.usage import region_frames, usage_line


def test_each_frame_is_counted_once_for_its_first_reason():
    """Ten candidates, eight with a pose; the eyeball's frame 3 is occluded and its lid
    closed: it counts as occluded only; the mouth took frames 2 and 5."""
    observed = [0, 1, 2, 3, 4, 5, 6, 7]
    occluded = np.zeros((8, 2), bool)
    occluded[[3, 4], 0] = True
    closed = np.zeros((8, 2), bool)
    closed[[3, 6], 0] = True
    no_cue = occluded | closed
    no_cue[7, 0] = True  # no iris found
    got = region_frames(10, occluded, closed, no_cue, observed, [[1, 2, 1], [5, 2]],
                        ["eyeball_left", "mouth"])
    assert got["eyeball_left"] == RegionFrames(10, (1, 2), {"no_face": 2, "occluded": 2,
                                                            "lid_closed": 1, "no_cue": 1})
    assert got["eyeball_left"].clean == 2
    assert got["mouth"] == RegionFrames(10, (2, 5), {"no_face": 2})
    assert usage_line(got["mouth"]) == "2 of 10 frames used; rejected: 2 no face; 6 clean " \
                                       "not chosen"
    nothing = RegionFrames(10, (), {"occluded": 10})
    assert usage_line(nothing) == ("no clean frame of 10 (rejected: 10 occluded): draws the "
                                   "base texture")


def _with_frames(generic_model: Path, tmp_path: Path) -> Path:
    """The generic model with one region and its ``region_frames``, saved."""
    from facewire.models.modelfile import Region

    old = load_model(generic_model)
    region = Region("mouth", (0.4, 0.1, 0.6, 0.3), (0.45, 0.15, 0.55, 0.25),
                    np.zeros((2, 8, 8, 3), np.uint8), np.full((8, 8), 255, np.uint8),
                    np.zeros((2, 16, 16), np.float32))
    path = tmp_path / "with.fwm"
    save_model(replace(old, regions=(region,), region_frames={
        "mouth": RegionFrames(140, (12, 90), {"occluded": 61, "no_face": 2})}), path)
    return path


def test_region_frames_are_stored_and_printed(generic_model, tmp_path, capsys):
    """They round-trip through the file, ``model info`` prints one line per region (and
    ``--json`` the key), and a model without them (older) loads and says so."""
    assert load_model(generic_model).region_frames is None
    assert main(["model", "info", str(generic_model)]) == 0
    assert "per region not recorded" in capsys.readouterr().out
    path = _with_frames(generic_model, tmp_path)
    assert load_model(path).region_frames == {
        "mouth": RegionFrames(140, (12, 90), {"occluded": 61, "no_face": 2})}
    assert main(["model", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert ("mouth: 2 of 140 frames used; rejected: 2 no face, 61 occluded; 75 clean not "
            "chosen") in out
    assert main(["model", "info", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["region_frames"] == {"mouth": {"candidates": 140, "used": [12, 90], "rejected": {
        "occluded": 61, "no_face": 2}, "clean": 75}}


@pytest.mark.parametrize(("old", "new", "fragment"), [
    (b'"candidates": 140', b'"candidates": -1', "region_frames.mouth.candidates: -1 outside"),
    (b'"candidates": 140', b'"candidates": 60', "region_frames.mouth: 2 used and 63 rejected "
                                                "of 60 candidates"),
    (b'"used": [\n    12,\n    90\n   ]', b'"used": [90, 12]', "region_frames.mouth.used: not "
                                                               "strictly increasing"),
    (b'"occluded": 61', b'"Occluded": 61', "region_frames.mouth.rejected: bad reason"),
    (b'"occluded": 61', b'"occluded": 0', "region_frames.mouth.rejected.occluded: 0 outside"),
    (b'"candidates": 140', b'"frames": 140', "region_frames.mouth: missing key 'candidates'"),
    (b'"region_frames": {\n  "mouth"', b'"region_frames": {\n  "eyes"',
     "region_frames.eyes: not a region of the model"),
])
def test_bad_region_frames_are_refused_by_name(generic_model, tmp_path, old, new, fragment):
    path = _with_frames(generic_model, tmp_path)
    bad = tmp_path / "bad.fwm"
    with zipfile.ZipFile(path) as z, zipfile.ZipFile(bad, "w") as out:
        for item in z.infolist():
            data = z.read(item)
            if item.filename == "model.json":
                assert old in data, data
                data = data.replace(old, new)
            out.writestr(item, data)
    with pytest.raises(ModelFileError, match=fragment):
        load_model(bad)


def test_records_are_checked_when_they_enter_a_model(generic_model):
    model = load_model(generic_model)
    with pytest.raises(ModelError, match="region_frames.mouth: not a region of the model"):
        replace(model, region_frames={"mouth": RegionFrames(3, (1,), {})})
    with pytest.raises(ModelError, match="region_frames: expected an object"):
        replace(model, region_frames=[RegionFrames(3, (1,), {})])  # type: ignore[arg-type]
