"""The 68-point scheme's constants and measures, and the landmark file readers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facewire.models import landmarks as lm
from facewire.models import mesh
from facewire.models.landmark_files import LandmarkFileError, read_openface_csv, read_pts

# ---------------------------------------------------------------------------------------------
# scheme


def test_feature_sets_match_the_design() -> None:
    assert lm.N_LANDMARKS == 68
    assert lm.RIGID.tolist() == [36, 39, 42, 45, 27, 30, 31, 35, 33]
    assert lm.NONRIGID.tolist() == [19, 21, 22, 24, 48, 54, 51, 57, 8]
    assert lm.FEATURES.tolist() == lm.RIGID.tolist() + lm.NONRIGID.tolist()
    assert len(set(lm.FEATURES.tolist())) == 18
    assert len(lm.HELD_OUT) == 50
    assert not set(lm.HELD_OUT.tolist()) & set(lm.FEATURES.tolist())
    assert sorted(lm.HELD_OUT.tolist() + lm.FEATURES.tolist()) == list(range(68))
    assert np.all(np.diff(lm.HELD_OUT) > 0)


def test_groups_partition_the_68_points_in_order() -> None:
    merged = np.concatenate(list(lm.GROUPS.values()))
    assert merged.tolist() == list(range(68))
    sizes = {name: len(g) for name, g in lm.GROUPS.items()}
    assert sizes == {
        "jaw": 17, "right_brow": 5, "left_brow": 5, "nose_bridge": 4, "nostrils": 5,
        "right_eye": 6, "left_eye": 6, "outer_lip": 12, "inner_lip": 8,
    }  # fmt: skip


def test_constants_are_read_only() -> None:
    shared = (lm.RIGID, lm.NONRIGID, lm.FEATURES, lm.HELD_OUT, lm.MIRROR, lm.JAW, lm.PHANTOM_MIRROR)
    for a in shared:
        with pytest.raises(ValueError):
            a[0] = 1


def test_mirror_is_an_involution_with_the_midline_fixed() -> None:
    m = lm.MIRROR
    assert sorted(m.tolist()) == list(range(68))
    assert np.array_equal(m[m], np.arange(68))
    fixed = set(np.flatnonzero(m == np.arange(68)).tolist())
    assert fixed == {8, 27, 28, 29, 30, 33, 51, 57, 62, 66}
    pairs = [(36, 45), (39, 42), (37, 44), (41, 46), (48, 54), (60, 64), (31, 35), (0, 16)]
    for a, b in pairs + [(17, 26), (21, 22)]:
        assert m[a] == b and m[b] == a


def test_mirror_maps_groups_and_feature_sets_onto_each_other() -> None:
    m = lm.MIRROR
    partner = {
        "jaw": "jaw", "right_brow": "left_brow", "left_brow": "right_brow",
        "nose_bridge": "nose_bridge", "nostrils": "nostrils", "right_eye": "left_eye",
        "left_eye": "right_eye", "outer_lip": "outer_lip", "inner_lip": "inner_lip",
    }  # fmt: skip
    for name, group in lm.GROUPS.items():
        assert set(m[group].tolist()) == set(lm.GROUPS[partner[name]].tolist()), name
    for s in (lm.RIGID, lm.NONRIGID, lm.FEATURES, lm.HELD_OUT):
        assert set(m[s].tolist()) == set(s.tolist())


def _face_frame(points: np.ndarray) -> np.ndarray:
    """Points with x along the outer-eye line, origin between the outer corners, unit distance."""
    u = points[45] - points[36]
    d = np.linalg.norm(u)
    u = u / d
    v = np.array([-u[1], u[0]])
    rel = points - (points[36] + points[45]) / 2
    return np.stack([rel @ u, rel @ v], axis=1) / d


def test_mirror_pairs_sit_symmetrically_on_a_real_frontal_face(shared_data: Path) -> None:
    # image_0001 is a near-frontal face with human annotations.
    q = _face_frame(read_pts(shared_data / "images" / "image_0001.pts"))
    m = lm.MIRROR
    paired = m != np.arange(68)
    # partners lie on opposite sides of the midline, at about the same height
    assert np.all(q[paired, 0] * q[m[paired], 0] < 0)
    assert np.abs(q[:, 1] - q[m, 1]).max() < 0.15
    # midline points lie near the midline
    assert np.abs(q[~paired, 0]).max() < 0.1
    # the person's right side (points 36-41) is on the image's left
    assert np.all(q[lm.RIGHT_EYE, 0] < 0) and np.all(q[lm.LEFT_EYE, 0] > 0)


def test_phantoms() -> None:
    assert lm.N_PHANTOMS == 13 == len(set(lm.PHANTOM_NAMES))
    pm = lm.PHANTOM_MIRROR
    assert np.array_equal(pm[pm], np.arange(13))
    for i, name in enumerate(lm.PHANTOM_NAMES):
        partner = lm.PHANTOM_NAMES[pm[i]]
        if name.endswith("_right"):
            assert partner == name[: -len("_right")] + "_left"
        elif not name.endswith("_left"):
            assert partner == name


def test_counts_agree_with_the_mesh() -> None:
    assert mesh.N_LANDMARKS == lm.N_LANDMARKS
    assert mesh.N_PHANTOMS == lm.N_PHANTOMS


# ---------------------------------------------------------------------------------------------
# measures


def _synthetic_face(right_open: float, left_open: float) -> np.ndarray:
    """68 points with eyes 30 px wide whose lids are ``open`` px above and below the corners."""
    p = np.random.default_rng(1).uniform(0, 200, size=(68, 2))
    for eye, x0, h in ((lm.RIGHT_EYE, 50.0, right_open), (lm.LEFT_EYE, 120.0, left_open)):
        # corner, upper lid x2, corner, lower lid x2 (image y down: upper lid has smaller y)
        p[eye] = [
            (x0, 80), (x0 + 10, 80 - h), (x0 + 20, 80 - h),
            (x0 + 30, 80), (x0 + 20, 80 + h), (x0 + 10, 80 + h),
        ]  # fmt: skip
    return p


def test_eye_aspect_ratio_known_values() -> None:
    ear = lm.eye_aspect_ratio(_synthetic_face(5.0, 0.0))
    assert ear.shape == (2,) and ear.dtype == np.float32
    np.testing.assert_allclose(ear, [(10 + 10) / 60, 0.0], atol=1e-6)


def test_eye_aspect_ratio_is_invariant_to_similarity_transforms() -> None:
    p = _synthetic_face(4.0, 6.0)
    a = np.deg2rad(25)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    q = 2.5 * p @ rot.T + [13.0, -7.0]
    np.testing.assert_allclose(lm.eye_aspect_ratio(q), lm.eye_aspect_ratio(p), rtol=1e-5)


def test_eye_aspect_ratio_on_real_open_eyes(shared_data: Path) -> None:
    for name in ("image_0001.pts", "image_0010.pts"):
        ear = lm.eye_aspect_ratio(read_pts(shared_data / "images" / name))
        assert np.all((ear > 0.15) & (ear < 0.6)), (name, ear)


def test_eye_aspect_ratio_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="shape"):
        lm.eye_aspect_ratio(np.zeros((67, 2)))
    with pytest.raises(ValueError, match="NaN"):
        lm.eye_aspect_ratio(np.full((68, 2), np.nan))


def test_outer_eye_distance_batches() -> None:
    p = np.zeros((3, 4, 68, 2), np.float32)
    p[..., 45, 0] = 3.0
    p[..., 45, 1] = 4.0
    d = lm.outer_eye_distance(p)
    assert d.shape == (3, 4)
    np.testing.assert_allclose(d, 5.0)


def test_nme() -> None:
    truth = _synthetic_face(5.0, 5.0)
    d = float(np.linalg.norm(truth[36] - truth[45]))
    assert float(lm.nme(truth, truth)) == 0.0
    np.testing.assert_allclose(lm.nme(truth + [3.0, 4.0], truth), 5.0 / d)
    # only the chosen points count
    pred = truth.copy()
    pred[lm.HELD_OUT] += 10.0
    assert float(lm.nme(pred, truth, lm.FEATURES)) == 0.0
    np.testing.assert_allclose(lm.nme(pred, truth, lm.HELD_OUT), np.sqrt(200.0) / d)
    np.testing.assert_allclose(lm.nme(pred, truth), np.sqrt(200.0) * 50 / 68 / d)
    # per frame over a batch, each normalised by its own truth
    batch_truth = np.stack([truth, 2 * truth])
    batch_pred = batch_truth + [3.0, 4.0]
    np.testing.assert_allclose(lm.nme(batch_pred, batch_truth), [5.0 / d, 2.5 / d])


def test_nme_rejects_bad_input() -> None:
    t = _synthetic_face(5.0, 5.0)
    with pytest.raises(ValueError, match="shapes differ"):
        lm.nme(np.stack([t, t]), t)
    with pytest.raises(ValueError, match="indices"):
        lm.nme(t, t, np.array([0, 68]))
    with pytest.raises(ValueError, match="indices"):
        lm.nme(t, t, np.array([1, 1]))
    with pytest.raises(ValueError, match="indices"):
        lm.nme(t, t, np.array([], dtype=int))
    flat = t.copy()
    flat[45] = flat[36]
    with pytest.raises(ValueError, match="coincide"):
        lm.nme(t, flat)


# ---------------------------------------------------------------------------------------------
# .pts


def test_read_pts_real_files(shared_data: Path) -> None:
    for name in ("image_0001.pts", "image_0010.pts"):
        path = shared_data / "images" / name
        p = read_pts(path)
        assert p.shape == (68, 2) and p.dtype == np.float32
        # the file's numbers minus one (1-based to 0-based)
        lines = path.read_text().splitlines()
        first = [float(v) for v in lines[3].split()]
        last = [float(v) for v in lines[70].split()]
        np.testing.assert_allclose(p[0], np.array(first) - 1, atol=1e-4)
        np.testing.assert_allclose(p[67], np.array(last) - 1, atol=1e-4)
        # a plausible face: the chin (8) is below the nose tip (30), which is below the eyes
        assert p[8, 1] > p[30, 1] > max(p[36, 1], p[45, 1])
        assert p[36, 0] < p[45, 0]


def _pts_text(points: np.ndarray) -> str:
    rows = "\n".join(f"{x:.3f} {y:.3f}" for x, y in points)
    return f"version: 1\nn_points:  68\n{{\n{rows}\n}}\n"


def test_read_pts_round_trip_and_crlf(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).uniform(1, 500, size=(68, 2)).round(3)
    path = tmp_path / "a.pts"
    path.write_bytes(_pts_text(pts).replace("\n", "\r\n").encode())
    np.testing.assert_allclose(read_pts(path), pts - 1, atol=1e-4)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("version: 1", "version: 2"), r":1: expected 'version: 1'"),
        (lambda t: t.replace("n_points:  68", "n_points: 39"), r":2: expected 'n_points: 68'"),
        (lambda t: t.replace("{", "("), r":3: expected '\{'"),
        (lambda t: t.replace("}", ""), "expected 72 non-blank lines"),
        (lambda t: t.replace("\n}", "\n1 2\n}"), "expected 72 non-blank lines"),
        (lambda t: t.replace("10.000 20.000", "10.000 abc"), r":14: expected a number, got 'abc'"),
        (lambda t: t.replace("10.000 20.000", "10.000 nan"), r":14: expected a finite number"),
        (lambda t: t.replace("10.000 20.000", "10.000"), r":14: expected 'x y' for point 10"),
    ],
)
def test_read_pts_errors_name_file_and_line(tmp_path: Path, edit, message: str) -> None:
    pts = np.full((68, 2), 5.0)
    pts[10] = [10.0, 20.0]
    path = tmp_path / "bad.pts"
    path.write_text(edit(_pts_text(pts)))
    with pytest.raises(LandmarkFileError, match=message) as info:
        read_pts(path)
    assert "bad.pts" in str(info.value)


def test_read_pts_missing_and_oversized(tmp_path: Path) -> None:
    with pytest.raises(LandmarkFileError, match="cannot read"):
        read_pts(tmp_path / "none.pts")
    big = tmp_path / "big.pts"
    big.write_bytes(b" " * (64 * 1024 + 1))
    with pytest.raises(LandmarkFileError, match="more than"):
        read_pts(big)


# ---------------------------------------------------------------------------------------------
# OpenFace CSV


def _openface_csv(rows: list[tuple[int, int, np.ndarray]], sep: str = ", ") -> str:
    """An OpenFace-style CSV: frame, face_id, timestamp, confidence, success, x_*, y_*, an AU."""
    header = ["frame", "face_id", "timestamp", "confidence", "success"]
    header += [f"x_{i}" for i in range(68)] + [f"y_{i}" for i in range(68)] + ["AU45_r"]
    lines = [sep.join(header)]
    for frame, success, pts in rows:
        confidence = "0.98" if success else "0.00"
        cells = [str(frame), "0", f"{(frame - 1) / 30:.3f}", confidence, str(success)]
        cells += [f"{v:.1f}" for v in pts[:, 0]] + [f"{v:.1f}" for v in pts[:, 1]] + ["0.25"]
        lines.append(sep.join(cells))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("sep", [", ", ","])
def test_read_openface_csv(tmp_path: Path, sep: str) -> None:
    rng = np.random.default_rng(2)
    a, b = rng.uniform(0, 640, (68, 2)).round(1), rng.uniform(0, 640, (68, 2)).round(1)
    path = tmp_path / "of.csv"
    path.write_text(_openface_csv([(1, 1, a), (2, 0, np.zeros((68, 2))), (3, 1, b)], sep))
    track = read_openface_csv(path)
    assert track.frame.tolist() == [1, 2, 3]
    assert track.success.tolist() == [True, False, True]
    np.testing.assert_allclose(track.timestamp, [0.0, 1 / 30, 2 / 30], atol=1e-3)
    np.testing.assert_allclose(track.confidence, [0.98, 0.0, 0.98])
    assert track.landmarks.shape == (3, 68, 2) and track.landmarks.dtype == np.float32
    np.testing.assert_allclose(track.landmarks[0], a, atol=1e-4)
    np.testing.assert_allclose(track.landmarks[2], b, atol=1e-4)
    assert np.isnan(track.landmarks[1]).all()


def test_read_openface_csv_without_landmark_columns(shared_data: Path) -> None:
    path = shared_data / "openface" / "openface_default.openface.csv"
    with pytest.raises(LandmarkFileError, match=r"no 2D landmark columns x_0\.\.x_67") as info:
        read_openface_csv(path)
    assert path.name in str(info.value) and "-2Dfp" in str(info.value)


def test_read_openface_csv_errors_name_line_and_column(tmp_path: Path) -> None:
    pts = np.full((68, 2), 7.0)
    good = _openface_csv([(1, 1, pts), (2, 1, pts)])
    path = tmp_path / "of.csv"

    path.write_text(good.replace("7.0, 0.25\n2,", "x, 0.25\n2,", 1))
    with pytest.raises(LandmarkFileError, match=r"of\.csv:2: column 'y_67': expected a number"):
        read_openface_csv(path)

    lines = good.splitlines()
    path.write_text("\n".join([lines[0], lines[1], lines[2].rsplit(",", 1)[0]]) + "\n")
    with pytest.raises(LandmarkFileError, match=r"of\.csv:3: 141 fields, header has 142"):
        read_openface_csv(path)

    path.write_text(good.replace("\n2, 0,", "\n2, 1,"))
    with pytest.raises(LandmarkFileError, match=r"of\.csv:3: more than one face_id"):
        read_openface_csv(path)

    path.write_text(good.replace("0.98, 1,", "0.98, 2,", 1))
    with pytest.raises(LandmarkFileError, match=r"of\.csv:2: expected an integer frame"):
        read_openface_csv(path)

    path.write_text(good.replace("success", "succes"))
    with pytest.raises(LandmarkFileError, match=r"of\.csv:1: missing column\(s\) success"):
        read_openface_csv(path)

    path.write_text(lines[0] + "\n")
    with pytest.raises(LandmarkFileError, match="no data rows"):
        read_openface_csv(path)

    path.write_text("")
    with pytest.raises(LandmarkFileError, match="empty file"):
        read_openface_csv(path)
