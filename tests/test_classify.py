"""Haar-wavelet template classifier: transform against PyWavelets, exactness at the templates,
blends between adjacent templates, brightness and contrast, offsets and input validation.

The ordered families are synthetic 16 x 16 grey images: an eye whose upper lid closes, an
iris that moves left to right (gaze) and a mouth that opens, each scaled to 78..178 grey
levels so every gain and offset of the documented range stays within 0..255.
"""

from __future__ import annotations

import numpy as np
import pytest
import pywt

from facewire.sender.classify import (
    ETA,
    HAAR_MATRIX,
    SCALE_INDEX,
    RegionClassifiers,
    TemplateClassifier,
    haar_pyramid,
)

N = 16
_Y, _X = (np.mgrid[0:N, 0:N] + 0.5) / N * 2 - 1  # pixel centres in [-1, 1], y down


def _soft(d: np.ndarray, width: float = 0.07) -> np.ndarray:
    return 1 / (1 + np.exp(-d / width))


def _skin(seed: int) -> np.ndarray:
    return 150 + 8 * _Y + np.random.default_rng(seed).normal(0, 1.5, (N, N))


def _eye(closed: float) -> np.ndarray:
    """Upper lid (with lashes and a crease above it) closing onto the lower lid."""
    span = np.clip(1 - (_X / 0.85) ** 2, 0, None)
    low = 0.25 + 0.2 * span
    up = low - (1 - closed) * 0.8 * span
    inside = _soft(_Y - up) * _soft(low - _Y) * (span > 0)
    r = np.hypot(_X, _Y - 0.05)
    ball = 178 - 80 * _soft(0.33 - r) - 20 * _soft(0.13 - r)
    img = _skin(7) * (1 - inside) + ball * inside
    img -= 60 * np.exp(-((_Y - up) / 0.07) ** 2) * (np.abs(_X) < 0.9) * (0.4 + 0.6 * span)
    img -= 15 * np.exp(-((_Y - (up - 0.5 + 0.2 * closed)) / 0.08) ** 2) * span
    return img


def _gaze(right: float) -> np.ndarray:
    """Iris and pupil moving across the eyeball, lid shadows above and below."""
    img = 176 - 40 * np.exp(-((_Y + 1) / 0.4) ** 2) - 20 * np.exp(-((_Y - 1) / 0.4) ** 2)
    r = np.hypot(_X - (right - 0.5), _Y)
    return img - 70 * _soft(0.35 - r) - 25 * _soft(0.14 - r)


def _mouth(opening: float) -> np.ndarray:
    """Lips parting over a dark interior, the upper teeth showing as it opens."""
    img = _skin(3) - 10 - 30 * np.exp(-((_Y / 0.35) ** 2) - (_X / 0.8) ** 8)
    h = 0.05 + 0.45 * opening
    inside = _soft(h - np.abs(_Y)) * _soft(0.6 - np.abs(_X))
    teeth = _soft(0.12 - np.abs(_Y + h - 0.08), 0.04) * min(1.0, 3 * opening)
    return img * (1 - inside) + (70 + 110 * teeth) * inside


def _family(draw, k: int) -> np.ndarray:
    out = np.stack([draw(v) for v in np.linspace(0, 1, k)])
    return (78 + (out - out.min()) * (100 / np.ptp(out))).astype(np.float32)


FAMILIES = {"eyelid": _family(_eye, 5), "gaze": _family(_gaze, 5), "mouth": _family(_mouth, 4)}


def _blend(templates: np.ndarray, j: int, t: float) -> np.ndarray:
    return ((1 - np.float32(t)) * templates[j] + np.float32(t) * templates[j + 1]).astype(
        np.float32)


def _pywt(x: np.ndarray) -> np.ndarray:
    return np.stack([pywt.coeffs_to_array(pywt.wavedec2(a.astype(np.float64), "haar",
                                                        mode="periodization", level=4))[0].ravel()
                     for a in x])


def _random(rng: np.random.Generator, *shape: int) -> np.ndarray:
    return (rng.random(shape) * 255).astype(np.float32)


def test_matrix_is_orthonormal_with_power_of_two_entries() -> None:
    w = HAAR_MATRIX.astype(np.float64)
    np.testing.assert_array_equal(w.T @ w, np.eye(256))
    magnitudes = set(np.unique(np.abs(HAAR_MATRIX)).tolist())
    assert magnitudes <= {0.0, 0.5, 0.25, 0.125, 0.0625}
    assert not HAAR_MATRIX.flags.writeable


@pytest.mark.parametrize("n", [1, 5, 35])
def test_pyramid_matches_pywavelets(n: int) -> None:
    x = _random(np.random.default_rng(n), n, N, N)
    reference = _pywt(x)
    exact = x.reshape(n, 256).astype(np.float64) @ HAAR_MATRIX.astype(np.float64)
    assert np.abs(exact - reference).max() <= 1e-6 * 255
    got = haar_pyramid(x)
    assert got.dtype == np.float32 and got.shape == (n, 256)
    error = np.abs(got - reference)
    # float32 sums of up to 256 terms: the approximation (about 2000) is good to a few ulps
    assert error.max() <= 1e-6 * 16 * 255
    assert error[:, SCALE_INDEX >= 3].max() <= 1e-4


def test_scale_index_follows_the_pyramid_levels() -> None:
    _, slices = pywt.coeffs_to_array(pywt.wavedec2(np.zeros((N, N)), "haar",
                                                   mode="periodization", level=4))
    expected = np.full((N, N), -1)
    expected[slices[0]] = 0
    for scale, details in enumerate(slices[1:], start=1):
        for key in ("da", "ad", "dd"):
            expected[details[key]] = scale
    np.testing.assert_array_equal(SCALE_INDEX, expected.ravel())


def test_scores_follow_the_definition() -> None:
    """phi_j = sum of eta |c_j - a'| over template j's kept coefficients, from PyWavelets
    on the samples rounded to 1/64 grey level, as the classifier rounds them."""
    rng = np.random.default_rng(3)
    templates = FAMILIES["eyelid"]
    classifier = TemplateClassifier(templates)
    samples = np.concatenate([_random(rng, 3, N, N), templates[:2] * 0.7 + 20])

    def features(x: np.ndarray) -> np.ndarray:
        x = np.rint(x.astype(np.float64) * 64) / 64
        spread = np.maximum(x.std(axis=(1, 2)), classifier.floor)
        return _pywt((x - x.mean(axis=(1, 2), keepdims=True)) / spread[:, None, None])

    rounded = np.rint(templates.astype(np.float64) * 64) / 64
    assert classifier.floor == pytest.approx(max(2.0, 0.5 * rounded.std(axis=(1, 2)).min()),
                                             rel=1e-12)
    c, a = features(templates), features(samples)
    eta = np.asarray(ETA)[SCALE_INDEX]
    for j in range(len(templates)):
        eligible = np.flatnonzero((eta > 0) & (SCALE_INDEX > 0))
        strongest = eligible[np.argsort(-np.abs(c[j, eligible]), kind="stable")[:50]]
        assert set(classifier.kept[j].tolist()) == set(strongest.tolist())
    phi = np.stack([(eta[kept] * np.abs(c[j, kept] - a[:, kept])).sum(axis=1)
                    for j, kept in enumerate(classifier.kept)], axis=1)
    np.testing.assert_allclose(classifier.scores(samples), phi, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("k", [1, 2, 3, 6, 64])
def test_random_templates_classify_as_their_own_index_in_any_batch(k: int) -> None:
    rng = np.random.default_rng(k)
    templates = _random(rng, k, N, N)
    other = _random(rng, 4, N, N)  # a second region, so the templates sit mid-batch
    frame = RegionClassifiers([other, templates])
    for j in range(k):
        samples = _random(rng, 2, 5, N, N)
        samples[1, j % 5] = templates[j]
        result = frame.classify(samples)
        assert result.q[1] == j and result.offset[1] == j % 5 and result.score[1] == 0
        single = frame.regions[1].classify(samples[1])
        assert single.q == j and single.offset == j % 5 and single.score == 0


@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_family_templates_classify_as_their_own_index(name: str) -> None:
    templates = FAMILIES[name]
    classifier = TemplateClassifier(templates)
    rng = np.random.default_rng(5)
    for j in range(len(templates)):
        samples = np.stack([np.roll(templates[j], (2, -2), axis=(0, 1)), templates[j],
                            _random(rng, N, N)])
        result = classifier.classify(samples)
        assert (result.q, result.offset, result.score) == (j, 1, 0)


@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_blends_of_adjacent_templates_lie_between_them_monotonically(name: str) -> None:
    templates = FAMILIES[name]
    classifier = TemplateClassifier(templates)
    for j in range(len(templates) - 1):
        q = np.array([classifier.classify(_blend(templates, j, t)[None]).q
                      for t in np.linspace(0, 1, 21)])
        assert q[0] == j and q[-1] == j + 1
        assert np.all((q >= j) & (q <= j + 1)), q
        assert np.all(np.diff(q) >= 0), q
        assert j + 0.25 < q[10] < j + 0.75, q  # the midpoint blend is near the middle


@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_brightness_and_contrast_in_the_documented_range_barely_move_q(name: str) -> None:
    templates = FAMILIES[name]
    classifier = TemplateClassifier(templates)
    changes = [(g, o) for g in (0.6, 1.0, 1.6) for o in (-40.0, 0.0, 40.0) if (g, o) != (1, 0)]
    for j in range(len(templates) - 1):
        for t in (0.0, 0.25, 0.5, 0.75):
            sample = _blend(templates, j, t)
            q = classifier.classify(sample[None]).q
            for gain, offset in changes:
                changed = (128 + gain * (sample - 128) + offset).astype(np.float32)
                assert changed.min() >= 0 and changed.max() <= 255
                moved = classifier.classify(changed[None]).q
                assert abs(moved - q) <= 0.1, (j, t, gain, offset, q, moved)


@pytest.mark.parametrize("name", ["eyelid", "mouth"])
def test_a_featureless_sample_is_not_amplified_into_noise(name: str) -> None:
    """Uniform grey plus faint noise lies below the floor: its Q must not follow the noise
    (normalised to unit contrast, the noise alone picks a template: Q spreads over 1-2)."""
    classifier = TemplateClassifier(FAMILIES[name])
    rng = np.random.default_rng(11)
    noise = 0.7
    assert noise < classifier.floor / 4
    q = [classifier.classify((128 + rng.normal(0, noise, (1, N, N))).astype(np.float32)).q
         for _ in range(40)]
    assert np.ptp(q) < 0.1, q


def test_the_well_matching_offset_wins_in_every_region() -> None:
    rng = np.random.default_rng(2)
    names = sorted(FAMILIES)
    frame = RegionClassifiers([TemplateClassifier(FAMILIES[n], keep)  # mixed k and n_keep
                               for n, keep in zip(names, (50, 30, 63), strict=True)])
    for trial in range(5):
        samples = np.empty((len(names), 5, N, N), np.float32)
        truth = []
        for r, name in enumerate(names):
            templates = FAMILIES[name]
            j = int(rng.integers(len(templates)))
            good = (trial + r) % 5
            for o in range(5):  # the others are misplaced by 2-3 pixels
                shift = (0, 0) if o == good else tuple(rng.choice([-3, -2, 2, 3], 2))
                samples[r, o] = np.roll(templates[j], shift, axis=(0, 1))
            samples[r] += rng.normal(0, 1.0, (5, N, N)).astype(np.float32)
            truth.append((j, good))
        result = frame.classify(samples)
        for r, (j, good) in enumerate(truth):
            assert result.offset[r] == good
            assert abs(result.q[r] - j) < 0.2, (names[r], j, result.q[r])
            single = frame.regions[r].classify(samples[r])  # sums padded to another n_keep
            assert single.offset == result.offset[r]
            assert single.q == pytest.approx(result.q[r], rel=1e-6)
            assert single.score == pytest.approx(result.score[r], rel=1e-6)
        assert result.q.dtype == np.float32 and result.q.shape == (len(names),)


def test_identical_or_flat_templates_still_give_a_defined_q() -> None:
    """A region the enrollment video never varied: templates 1 and 2 alike (after
    brightness and contrast), or all templates flat."""
    eye = FAMILIES["eyelid"]
    alike = TemplateClassifier(np.stack([eye[0], eye[2], eye[2] * 0.5 + 60, eye[4]]))
    assert alike.classify(eye[0][None]).q == 0
    assert alike.classify(eye[2][None]).q == 1  # the lower of the two alike wins the tie
    assert alike.classify(eye[4][None]).q == 3
    for t in (0.25, 0.5, 0.75):
        q = alike.classify(_blend(eye, 2, t)[None]).q
        assert np.isfinite(q) and 0 <= q <= 3
    flat = TemplateClassifier(np.full((3, N, N), 90, np.float32))
    for sample in (eye[:1], np.full((1, N, N), 90, np.float32)):
        q = flat.classify(sample).q
        assert np.isfinite(q) and 0 <= q <= 2


def test_one_template_gives_q_zero() -> None:
    rng = np.random.default_rng(4)
    classifier = TemplateClassifier(_random(rng, 1, N, N))
    result = classifier.classify(_random(rng, 5, N, N))
    assert result.q == 0 and result.score > 0


_BAD_TEMPLATES = {
    "not an array": [[0.0]],
    "float64": np.zeros((3, N, N)),
    "15 columns": np.zeros((3, N, N - 1), np.float32),
    "one image": np.zeros((N, N), np.float32),
    "no templates": np.zeros((0, N, N), np.float32),
    "65 templates": np.zeros((65, N, N), np.float32),
    "NaN": np.full((2, N, N), np.nan, np.float32),
}


@pytest.mark.parametrize("case, match", [
    ("not an array", "templates: expected a numpy array"),
    ("float64", "templates: expected float32"),
    ("15 columns", "templates: expected shape"),
    ("one image", "templates: expected shape"),
    ("no templates", "templates: 0 templates"),
    ("65 templates", "templates: 65 templates"),
    ("NaN", "templates: contains NaN"),
])
def test_bad_templates_are_rejected(case: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        TemplateClassifier(_BAD_TEMPLATES[case])


@pytest.mark.parametrize("n_keep", [0, 64, 2.5, True])
def test_bad_n_keep_is_rejected(n_keep) -> None:
    with pytest.raises(ValueError, match="n_keep"):
        TemplateClassifier(FAMILIES["eyelid"], n_keep)


def test_bad_samples_are_rejected() -> None:
    frame = RegionClassifiers([FAMILIES["eyelid"], FAMILIES["gaze"]])
    good = np.full((2, 5, N, N), 128, np.float32)
    bad = good.copy()
    bad[1, 3, 4, 4] = np.inf
    cases = [(good.astype(np.float64), "samples: expected float32"),
             (good[:1], r"samples: expected shape \(R=2"),
             (good[:, :0], r"samples: expected shape \(R=2"),
             (good[0], "samples: expected shape"),
             (good[..., :8], "samples: expected shape"),
             (bad, "samples: contains NaN or infinity"),
             (good.tolist(), "samples: expected a numpy array")]
    for samples, match in cases:
        with pytest.raises(ValueError, match=match):
            frame.classify(samples)
    with pytest.raises(ValueError, match="samples: contains NaN"):
        frame.regions[0].classify(bad[1])
    with pytest.raises(ValueError, match="samples: expected shape"):
        haar_pyramid(good)
    with pytest.raises(ValueError, match=r"regions\[1\]: templates: expected float32"):
        RegionClassifiers([FAMILIES["eyelid"], FAMILIES["gaze"].astype(np.float64)])
    with pytest.raises(ValueError, match="regions: expected a non-empty sequence"):
        RegionClassifiers([])
