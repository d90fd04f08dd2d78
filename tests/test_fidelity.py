"""Tests for bench.fidelity: face box, grayscale SSIM, PSNR and the x264 reference encode."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from facewire.bench.fidelity import face_box, face_mask, gray_ssim, psnr, x264_reference
from facewire.models.infra.video import read_frames

C1, C2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2


def scene(height: int = 64, width: int = 80, seed: int = 0) -> np.ndarray:
    """A textured grey image: blurred noise over a gradient, uint8."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.normal(0, 40, (height, width)), (0, 0), 2.0)
    ramp = np.linspace(60, 190, width)[None, :]
    return np.clip(ramp + noise, 0, 255).astype(np.uint8)


def ssim_by_loops(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM written out window by window (Wang et al. 2004), independent of cv2's filter."""
    d = np.arange(11) - 5
    g = np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * 1.5 ** 2))
    g /= g.sum()
    x, y = a.astype(np.float64), b.astype(np.float64)
    values = []
    for i in range(x.shape[0] - 10):
        for j in range(x.shape[1] - 10):
            px, py = x[i:i + 11, j:j + 11], y[i:i + 11, j:j + 11]
            mx, my = (g * px).sum(), (g * py).sum()
            vx, vy = (g * (px - mx) ** 2).sum(), (g * (py - my) ** 2).sum()
            cxy = (g * (px - mx) * (py - my)).sum()
            values.append((2 * mx * my + C1) * (2 * cxy + C2)
                          / ((mx ** 2 + my ** 2 + C1) * (vx + vy + C2)))
    return float(np.mean(values))


def test_identical_images() -> None:
    x = scene()
    assert gray_ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    assert psnr(x, x) == math.inf


def test_known_values_by_hand() -> None:
    # flat images: no variance, so SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    a, b = np.full((20, 30), 100, np.uint8), np.full((20, 30), 120, np.uint8)
    assert gray_ssim(a, b) == pytest.approx((2 * 100 * 120 + C1) / (100 ** 2 + 120 ** 2 + C1),
                                            rel=1e-12)
    # MSE 100: 10 log10(255^2 / 100)
    assert psnr(np.zeros((4, 4), np.uint8), np.full((4, 4), 10, np.uint8)) == pytest.approx(
        28.1308036, abs=1e-6)
    assert psnr(np.zeros((2, 2, 3), np.uint8), np.full((2, 2, 3), 255, np.uint8)) == 0.0


def test_ssim_matches_a_window_by_window_implementation() -> None:
    x = scene(19, 23, seed=1)
    rng = np.random.default_rng(2)
    y = np.clip(x + rng.normal(0, 12, x.shape), 0, 255).astype(np.uint8)
    expected = ssim_by_loops(x, y)
    assert 0.3 < expected < 0.95
    assert gray_ssim(x, y) == pytest.approx(expected, abs=1e-10)


def test_ssim_and_psnr_fall_as_noise_grows() -> None:
    x = scene(96, 128)
    rng = np.random.default_rng(3)
    unit = rng.normal(0, 1, x.shape)
    ssims, psnrs = [], []
    for sigma in (2, 5, 10, 20, 40):
        y = np.clip(np.rint(x + sigma * unit), 0, 255).astype(np.uint8)
        ssims.append(gray_ssim(x, y))
        psnrs.append(psnr(x, y))
    assert all(s0 > s1 for s0, s1 in itertools.pairwise(ssims)), ssims
    assert all(p0 > p1 for p0, p1 in itertools.pairwise(psnrs)), psnrs
    assert ssims[0] < 1 and psnrs[0] < math.inf
    # sigma 2 and rounding (variance 1/12): MSE about 4.08
    assert psnrs[0] == pytest.approx(10 * math.log10(255 ** 2 / (4 + 1 / 12)), abs=0.2)


def test_ssim_of_bgr_is_ssim_of_grey() -> None:
    x = np.dstack([scene(seed=4), scene(seed=5), scene(seed=6)])
    y = np.ascontiguousarray(x[:, ::-1])
    gx, gy = cv2.cvtColor(x, cv2.COLOR_BGR2GRAY), cv2.cvtColor(y, cv2.COLOR_BGR2GRAY)
    assert gray_ssim(x, y) == pytest.approx(gray_ssim(gx, gy), abs=1e-12)


def test_ssim_is_averaged_over_the_mask_only() -> None:
    x = scene(seed=9)
    y = x.copy()
    y[:, : x.shape[1] // 2] = 255 - y[:, : x.shape[1] // 2]  # the left half differs
    right = np.zeros(x.shape, bool)
    right[:, x.shape[1] // 2 + 8:] = True  # SSIM windows there see only the right half
    assert gray_ssim(x, y, right) == pytest.approx(1.0)
    assert gray_ssim(x, y) < 0.9
    with pytest.raises(ValueError, match="mask"):
        gray_ssim(x, y, right[:-1])


def test_the_face_mask_covers_the_face_not_the_corners() -> None:
    points = np.zeros((68, 2))
    angles = np.linspace(np.pi, 0, 17)
    points[:17] = np.column_stack([100 + 60 * np.cos(angles), 100 + 60 * np.sin(angles)])
    points[17:27] = np.column_stack([np.linspace(50, 150, 10), np.full(10, 80.0)])
    points[27:] = [100.0, 110.0]
    box = face_box(points, 300, 300)
    mask = face_mask(points, box)
    x0, y0, x1, y1 = box
    assert mask.shape == (y1 - y0, x1 - x0)
    assert mask[int(110 - y0), int(100 - x0)]  # the nose
    assert not mask[0, 0] and not mask[-1, 0] and not mask[-1, -1]  # box corners
    assert mask[int(70 - y0), int(100 - x0)]  # raised above the brows: the forehead


def test_measures_reject_bad_input() -> None:
    x = scene()
    with pytest.raises(ValueError, match="differ"):
        gray_ssim(x, x[:-1])
    with pytest.raises(ValueError, match="at least 11"):
        gray_ssim(x[:10], x[:10])
    with pytest.raises(ValueError, match="a: expected a uint8"):
        gray_ssim(x.astype(np.float32), x)
    with pytest.raises(ValueError, match="differ in shape"):
        psnr(x, x[:, :-1])
    with pytest.raises(ValueError, match="b: expected"):
        psnr(x, x.astype(np.int16))


def square_face(cx: float, cy: float, side: float) -> np.ndarray:
    """68 points spread over a square (only the extremes matter to face_box)."""
    t = np.linspace(0, 1, 68)
    return np.stack([cx - side / 2 + side * t, cy - side / 2 + side * ((t * 7) % 1)], axis=1)


def test_face_box_grows_the_landmark_box() -> None:
    points = square_face(320, 240, 100)  # x 270..370, y 190..~290
    ya, yb = points[:, 1].min(), points[:, 1].max()
    x0, y0, x1, y1 = face_box(points, 640, 480)
    assert (x0, x1) == (260, 381)  # 10 px either side, x1 exclusive
    assert y0 == math.floor(ya - 0.4 * (yb - ya))  # margin + forehead above the brows
    assert y1 == math.ceil(yb + 0.1 * (yb - ya)) + 1
    assert face_box(points, 640, 480, margin=0, forehead=0) == (270, math.floor(ya), 371,
                                                                 math.ceil(yb) + 1)


def test_face_box_stays_inside_the_image() -> None:
    for cx, cy in ((10, 15), (630, 470), (320, 5), (-20, 240)):
        x0, y0, x1, y1 = face_box(square_face(cx, cy, 120), 640, 480)
        assert 0 <= x0 < x1 <= 640 and 0 <= y0 < y1 <= 480
    with pytest.raises(ValueError, match="outside"):
        face_box(square_face(-300, 240, 100), 640, 480)
    with pytest.raises(ValueError, match="points"):
        face_box(np.zeros((5, 2)), 640, 480)
    with pytest.raises(ValueError, match="points"):
        face_box(np.full((68, 2), np.nan), 640, 480)


@pytest.fixture(scope="module")
def clip(shared_data: Path) -> list[np.ndarray]:
    """30 real frames (512x512, 25 Hz) of lp_d0.mp4, BGR."""
    return [f.image for f in read_frames(shared_data / "video" / "lp_d0.mp4", slice(0, 30))]


def test_x264_reference_on_a_real_clip(clip: list[np.ndarray], tmp_path: Path) -> None:
    high = x264_reference(clip, 25.0, 300.0, tmp_path)
    low = x264_reference(clip, 25.0, 60.0, tmp_path)
    for result, target in ((high, 300.0), (low, 60.0)):
        assert len(result.frames) == len(clip)
        assert result.frames[0].shape == clip[0].shape and result.frames[0].dtype == np.uint8
        assert result.path.is_file() and result.path.suffix == ".mp4"
        assert 0 < result.kbps < result.file_kbps  # the container costs something
        seconds = len(clip) / 25.0
        assert result.file_kbps == pytest.approx(result.path.stat().st_size * 8 / seconds
                                                 / 1000)
        # the stream rate is the H.264 packets' bytes: the file less its container (the
        # muxer rewrites x264's start codes as 4-byte lengths: a byte here and there)
        with av.open(str(result.path)) as container:
            packets = sum(p.size for p in container.demux(container.streams.video[0]))
        assert result.kbps == pytest.approx(packets * 8 / seconds / 1000, rel=1e-3)
        assert abs(result.kbps / target - 1) < 0.25  # reachable here: lands near the target
    assert low.kbps < 0.5 * high.kbps
    # decoded frame k is input frame k, better at the higher rate
    q_high = np.mean([psnr(a, b) for a, b in zip(clip, high.frames)])
    q_low = np.mean([psnr(a, b) for a, b in zip(clip, low.frames)])
    assert q_high > q_low > 28
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x264_300kbps.mp4",
                                                          "x264_60kbps.mp4"]


def test_x264_reference_reports_its_floor(clip: list[np.ndarray], tmp_path: Path) -> None:
    floor = x264_reference(clip, 25.0, 1.0, tmp_path)  # far below what x264 can do
    assert len(floor.frames) == len(clip)
    assert floor.asked_kbps > 1  # raised to x264's own estimated minimum
    assert floor.kbps > 5  # the rate actually reached is reported, not the target


def test_x264_reference_rejects_bad_input(clip: list[np.ndarray], tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="even"):
        x264_reference([f[:-1] for f in clip[:2]], 25.0, 100.0, tmp_path)
    with pytest.raises(ValueError, match="frames: empty"):
        x264_reference([], 25.0, 100.0, tmp_path)
    with pytest.raises(ValueError, match=r"frames\[1\]"):
        x264_reference([clip[0], clip[1][:, :-2]], 25.0, 100.0, tmp_path)
    with pytest.raises(ValueError, match="target_kbps"):
        x264_reference(clip[:2], 25.0, 0.0, tmp_path)
    with pytest.raises(ValueError, match="not a folder"):
        x264_reference(clip[:2], 25.0, 100.0, tmp_path / "missing")
