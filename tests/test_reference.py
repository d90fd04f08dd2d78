"""OpenFace reference reading, Q agreement (correlations, blink events) and the Q plot."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.bench.qplot import DPI, FIG_WIDTH_IN, HEADER_IN, PANEL_IN, STRIP_IN, plot_q
from facewire.bench.reference import (
    OpenFaceError,
    OpenFaceReference,
    match_events,
    q_agreement,
    read_openface,
)

LAYERS = {"eyelid_left": 4, "eyelid_right": 4, "forehead": 3, "mouth": 5, "eyeball_left": 3,
          "eyeball_right": 3}
HEADER = "frame, face_id, timestamp, confidence, success, AU01_r, AU02_r, AU25_r, AU26_r, " \
         "AU45_r, AU45_c"


def _csv(path: Path, rows: list[str], header: str = HEADER) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def _row(frame: int, au45_r: float = 0.0, au45_c: int = 0, success: int = 1) -> str:
    return f"{frame}, 0, {(frame - 1) / 15:.3f}, 0.98, {success}, 0.5, 0.2, 0.1, 0.3, " \
           f"{au45_r:.2f}, {au45_c}.0"


def _reference(au45_c: np.ndarray, au: dict[str, np.ndarray] | None = None,
               success: np.ndarray | None = None) -> OpenFaceReference:
    """A reference held in memory: frames 0..F-1, AU45_c as given, other AUs as given."""
    n = len(au45_c)
    columns = {name: np.zeros(n) for name in ("AU01_r", "AU02_r", "AU25_r", "AU26_r",
                                              "AU45_r")}
    columns["AU45_c"] = np.asarray(au45_c, np.float64)
    columns.update(au or {})
    return OpenFaceReference(path=Path("memory.csv"), frames=np.arange(n),
                             success=np.ones(n, bool) if success is None else success,
                             confidence=np.ones(n), au=columns)


def _eyelids(closed: np.ndarray) -> dict[str, np.ndarray]:
    """Eyelid Q: k-1 (closed) where ``closed``, else 0."""
    q = np.where(closed, LAYERS["eyelid_left"] - 1, 0).astype(np.float64)
    return {"eyelid_left": q, "eyelid_right": q.copy()}


def _events(n: int, onsets: list[int], length: int = 3) -> np.ndarray:
    flag = np.zeros(n, bool)
    for onset in onsets:
        flag[onset:onset + length] = True
    return flag


# Reading the real files.

@pytest.mark.parametrize("name, rows, events", [("openface_default", 288, 9),
                                                ("openface_lighting", 88, 3)])
def test_reads_real_openface_csv(shared_data: Path, name: str, rows: int, events: int) -> None:
    ref = read_openface(shared_data / "openface" / f"{name}.openface.csv")
    assert ref.frames.dtype == np.int64
    np.testing.assert_array_equal(ref.frames, np.arange(rows))  # CSV frame 1 = video frame 0
    assert ref.success.dtype == bool and ref.success.all()
    assert set(np.unique(ref.au["AU45_c"])) == {0.0, 1.0}
    assert all(v.shape == (rows,) and v.dtype == np.float64 for v in ref.au.values())
    assert {"AU01_r", "AU02_r", "AU25_r", "AU26_r", "AU45_r", "AU28_c"} <= set(ref.au)
    assert "frame" not in ref.au and "success" not in ref.au
    assert 0 < ref.confidence.min() <= ref.confidence.max() <= 1
    # The reference's own blinks (runs of AU45_c == 1), as counted by hand from the file.
    onsets = np.flatnonzero(np.diff(np.r_[0.0, ref.au["AU45_c"]]) == 1)
    assert len(onsets) == events


def test_first_row_values_and_spaces_after_commas(tmp_path: Path) -> None:
    ref = read_openface(_csv(tmp_path / "a.csv", [_row(2, 1.5, 1), _row(1, 0.25, 0)]))
    np.testing.assert_array_equal(ref.frames, [0, 1])  # sorted by frame
    np.testing.assert_array_equal(ref.au["AU45_r"], [0.25, 1.5])
    np.testing.assert_array_equal(ref.au["AU45_c"], [0.0, 1.0])
    np.testing.assert_array_equal(ref.confidence, [0.98, 0.98])


# Malformed files.

def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(OpenFaceError, match="nowhere.csv: no such file"):
        read_openface(tmp_path / "nowhere.csv")


def test_missing_column_named(tmp_path: Path) -> None:
    path = _csv(tmp_path / "short.csv", ["1, 0, 0.0, 0.9, 1, 0.1, 0.0"],
                header="frame, face_id, timestamp, confidence, success, AU01_r, AU45_c")
    with pytest.raises(OpenFaceError, match=r"short\.csv: line 1: missing column\(s\) AU02_r, "
                                             r"AU25_r, AU26_r, AU45_r$"):
        read_openface(path)


def test_bad_number_names_line_and_column(tmp_path: Path) -> None:
    rows = [_row(1), _row(2), _row(3).replace("0.98", "n/a")]
    path = _csv(tmp_path / "bad.csv", rows)
    with pytest.raises(OpenFaceError, match=r"bad\.csv: line 4, column 'confidence': 'n/a'"):
        read_openface(path)


def test_duplicate_frame_names_both_lines(tmp_path: Path) -> None:
    path = _csv(tmp_path / "twice.csv", [_row(1), _row(2), _row(2)])
    with pytest.raises(OpenFaceError, match=r"twice\.csv: lines 3 and 4, column 'frame'"):
        read_openface(path)


@pytest.mark.parametrize("bad, match", [
    (_row(1, au45_c=2), r"line 2, column 'AU45_c': 2 is not 0 or 1"),
    (_row(1, success=5), r"line 2, column 'success': 5 is not 0 or 1"),
    (_row(1).replace("1, 0, ", "0.5, 0, ", 1), r"line 2, column 'frame': 0.5 is not an integer"),
    ("1, 0, 0.0", r"line 2: 3 cells, the header has 11"),
])
def test_bad_values(tmp_path: Path, bad: str, match: str) -> None:
    with pytest.raises(OpenFaceError, match=match):
        read_openface(_csv(tmp_path / "v.csv", [bad]))


def test_header_only(tmp_path: Path) -> None:
    with pytest.raises(OpenFaceError, match="no data rows"):
        read_openface(_csv(tmp_path / "h.csv", []))


# Correlations.

def test_correlated_q_gives_r_near_one_shuffled_near_zero(shared_data: Path) -> None:
    ref = read_openface(shared_data / "openface" / "openface_default.openface.csv")
    rng = np.random.default_rng(0)
    brows = ref.au["AU01_r"] + ref.au["AU02_r"]
    mouth = ref.au["AU25_r"] + ref.au["AU26_r"]
    eyes = ref.au["AU45_r"] / 5 * (LAYERS["eyelid_left"] - 1)
    noise = rng.normal(0, 0.02, len(ref.frames))
    q = {"forehead": 2 * brows / brows.max() + noise, "mouth": 4 * mouth / mouth.max() + noise,
         "eyelid_left": eyes + noise, "eyelid_right": eyes - noise}
    good = q_agreement(q, ref.frames, LAYERS, ref)
    for key in ("eyelid_au45", "forehead_au01_au02", "mouth_au25_au26"):
        assert good[key]["r"] > 0.97, key
        assert good[key]["frames"] == 288 and good[key]["reason"] is None
    shuffled = {name: rng.permutation(v) for name, v in q.items()}
    shuffled["eyelid_right"] = shuffled["eyelid_left"]
    bad = q_agreement(shuffled, ref.frames, LAYERS, ref)
    for key in ("eyelid_au45", "forehead_au01_au02", "mouth_au25_au26"):
        assert abs(bad[key]["r"]) < 0.2, key


def test_only_common_successful_finite_frames_count() -> None:
    n = 40
    x = np.sin(np.arange(n) / 3.0)
    success = np.ones(n, bool)
    success[[3, 20, 21]] = False
    ref = _reference(np.zeros(n), {"AU25_r": x}, success)
    q = np.r_[x[10:], np.full(5, 7.0)] * 2  # our frames 10..44; 40..44 absent in the reference
    q[3] = np.nan  # video frame 13
    result = q_agreement({"mouth": q}, np.arange(10, 45), LAYERS, ref)
    assert result["frames_compared"] == 28  # frames 10..39 but 20, 21
    assert result["mouth_au25_au26"] == {"r": 1.0, "frames": 27, "reason": None}


def test_missing_region_and_constant_series_give_null_with_reason() -> None:
    n = 20
    ref = _reference(np.zeros(n), {"AU01_r": np.linspace(0, 2, n)})
    q = {"forehead": np.linspace(0, 2, n), "mouth": np.full(n, 1.0),
         "eyelid_left": np.zeros(n)}
    result = q_agreement(q, np.arange(n), LAYERS, ref)
    assert result["forehead_au01_au02"]["r"] == 1.0
    assert result["mouth_au25_au26"] == {"r": None, "frames": n,
                                         "reason": "our Q is constant over 20 frames"}
    assert result["eyelid_au45"] == {"r": None, "frames": 0, "reason": "no eyelid_right Q"}
    assert result["blink_f1"] is None and result["blink_reason"] == "no eyelid_right Q"
    text = json.dumps(result, allow_nan=False)  # JSON without NaN
    assert "NaN" not in text


def test_bad_inputs_rejected() -> None:
    ref = _reference(np.zeros(5))
    with pytest.raises(ValueError, match=r"q\['mouth'\]: expected shape \(5,\)"):
        q_agreement({"mouth": np.zeros(4)}, np.arange(5), LAYERS, ref)
    with pytest.raises(ValueError, match="appears twice"):
        q_agreement({}, np.array([0, 1, 1]), LAYERS, ref)
    with pytest.raises(ValueError, match=r"layers\['eyelid_left'\]"):
        q_agreement(_eyelids(np.zeros(5, bool)), np.arange(5), {}, ref)


# Blink events.

ONSETS = [10, 30, 52, 80]


@pytest.mark.parametrize("shift, matched", [(0, 4), (2, 4), (-2, 4), (3, 0), (-3, 0)])
def test_blink_matching_tolerance(shift: int, matched: int) -> None:
    n = 100
    ref = _reference(_events(n, ONSETS).astype(float))
    q = _eyelids(_events(n, [o + shift for o in ONSETS]))
    result = q_agreement(q, np.arange(n), LAYERS, ref)
    assert result["blink_events"] == result["blink_events_reference"] == 4
    assert result["blink_matched"] == matched
    assert result["blink_f1"] == result["blink_precision"] == result["blink_recall"] \
        == matched / 4
    unmatched = result["disagreements"]
    if matched:
        assert unmatched == {"ours_unmatched": [], "reference_unmatched": []}
    else:
        assert unmatched["reference_unmatched"] == [[o, o + 2] for o in ONSETS]
        assert unmatched["ours_unmatched"] == [[o + shift, o + shift + 2] for o in ONSETS]


def test_blink_threshold_is_half_range_and_counts_differ() -> None:
    n = 60
    ref = _reference(_events(n, [10, 40]).astype(float))
    eyelid = np.zeros(n)
    eyelid[10:13] = 1.6  # Q/(k-1) = 0.53 > 0.5: a blink
    eyelid[25:28] = 1.5  # exactly half: not a blink
    eyelid[50:52] = 3.0  # a blink the reference does not have
    result = q_agreement({"eyelid_left": eyelid, "eyelid_right": eyelid}, np.arange(n),
                         LAYERS, ref)
    assert (result["blink_events"], result["blink_events_reference"],
            result["blink_matched"]) == (2, 2, 1)
    assert result["blink_precision"] == result["blink_recall"] == result["blink_f1"] == 0.5
    assert result["disagreements"] == {"ours_unmatched": [[50, 51]],
                                       "reference_unmatched": [[40, 42]]}


def test_blink_run_ends_at_a_missing_frame() -> None:
    n = 30
    ref = _reference(_events(n, [10], length=6).astype(float))
    q = _eyelids(_events(n, [10], length=6))
    q["eyelid_left"][12] = np.nan  # no face on frame 12: both sides split there
    result = q_agreement(q, np.arange(n), LAYERS, ref)
    assert result["blink_events"] == result["blink_events_reference"] == 2
    assert result["blink_matched"] == 2
    assert result["blink_frames"] == n - 1


def test_matching_is_one_to_one_and_greedy_by_distance() -> None:
    # Our 11 is 1 from 10 and 12; 12 is 0 from 12: (12, 12) first, then (11, 10).
    assert match_events(np.array([11, 12]), np.array([10, 12]), 2) == [(0, 0), (1, 1)]
    # One reference event, two of ours within reach: only the nearer matches.
    assert match_events(np.array([8, 11]), np.array([10]), 2) == [(1, 0)]
    assert match_events(np.array([], np.int64), np.array([3]), 2) == []


def test_no_blinks_anywhere_gives_null_f1() -> None:
    n = 20
    result = q_agreement(_eyelids(np.zeros(n, bool)), np.arange(n), LAYERS,
                         _reference(np.zeros(n)))
    assert result["blink_events"] == result["blink_events_reference"] == 0
    assert result["blink_f1"] is None and "either side" in result["blink_reason"]


# The plot.

def test_plot_q_writes_png_of_expected_size(tmp_path: Path) -> None:
    n = 90
    times = np.arange(n) / 30
    q = {"eyeball_left": 1 + np.sin(times * 3), "eyeball_right": 1 + np.sin(times * 3 + 0.2),
         "eyelid_left": np.where(np.arange(n) % 40 < 3, 3.0, 0.0)}
    q["eyeball_left"][20:25] = np.nan
    crop = np.zeros((24, 48, 3), np.uint8)
    crop[:, :24] = (255, 0, 0)  # blue in BGR
    thumbnails = [(0.5, crop), (1.5, crop[:, :, 0]), (2.5, crop)]
    path = tmp_path / "q.png"
    plot_q(times, q, LAYERS, thumbnails, path, title="gaze")
    image = cv2.imread(str(path))
    # Two panels (eyeball pair, eyelid) and the thumbnail strip.
    height = round((HEADER_IN + STRIP_IN + 2 * PANEL_IN) * DPI)
    assert image.shape == (height, round(FIG_WIDTH_IN * DPI), 3)
    plain = tmp_path / "plain.png"
    plot_q(times, {"mouth": q["eyelid_left"]}, LAYERS, [], plain)
    assert cv2.imread(str(plain)).shape[0] == round((HEADER_IN + PANEL_IN) * DPI)


def test_plot_q_rejects_bad_input(tmp_path: Path) -> None:
    times = np.arange(5) / 30
    with pytest.raises(ValueError, match=r"layers\['brow_furrow'\]"):
        plot_q(times, {"brow_furrow": np.zeros(5)}, LAYERS, [], tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"thumbnails\[0\]"):
        plot_q(times, {"mouth": np.zeros(5)}, LAYERS, [(0.1, np.zeros((4, 4, 3)))],
               tmp_path / "x.png")
    with pytest.raises(ValueError, match="11 given, at most 10"):
        plot_q(times, {"mouth": np.zeros(5)}, LAYERS, [(0.1, np.zeros((4, 4), np.uint8))] * 11,
               tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
