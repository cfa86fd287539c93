"""The bearing-band count U (issue 33): equal to a plain implementation of its definition, kept under rotation
and scale of the horizon, low between unrelated frames, and bad input refused."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.eval.pr import average_precision, pr_curve
from semloc_core.loopclosure.calibration import Calibration, calibrate
from semloc_core.loopclosure.similarity import (AlignmentParams, aligned_pairs, band_count, band_log_scales,
                                                cyclic_alignment, dp_similarity, pair_count)

from .synthetic import ground_truth, synthetic_sequence


def plain_band_count(rows, cols, query_bearings, reference_bearings, half_width, log_scales) -> int:
    """U by its definition, in plain numpy: for each scale and each residual as the band's lower edge, the distinct
    query and reference features of the matches in the band."""
    best = 0
    for log_scale in log_scales:
        residual = np.mod(query_bearings[rows] - np.exp(log_scale) * reference_bearings[cols] + np.pi, 2 * np.pi) \
            - np.pi
        for lower in residual:
            inside = np.mod(residual - lower, 2 * np.pi) <= 2 * half_width
            inside |= residual == lower
            best = max(best, min(np.unique(rows[inside]).size, np.unique(cols[inside]).size))
    return best


def random_pair(seed: int, n: int, m: int, matches: int, true_share: float, rotation: float, log_scale: float,
                noise: float):
    """Bearings of two frames and candidate matches: a share of them true (query bearing = s * reference bearing +
    rotation + noise), the rest random pairs, some features matched several times."""
    rng = np.random.default_rng(seed)
    reference = np.sort(rng.uniform(-np.pi, np.pi, m))
    query = np.sort(rng.uniform(-np.pi, np.pi, n))
    true = int(true_share * matches)
    cols = rng.integers(0, m, matches)
    rows = rng.integers(0, n, matches)
    moved = np.mod(np.exp(log_scale) * reference[cols[:true]] + rotation + rng.normal(0, noise, true) + np.pi,
                   2 * np.pi) - np.pi
    query = np.concatenate([query, moved])  # the true matches' query features, appended
    rows[:true] = n + np.arange(true)
    return rows, cols, query, reference


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("matches, true_share", [(0, 0.0), (1, 1.0), (7, 0.5), (40, 0.6), (120, 0.3), (60, 0.0)])
@pytest.mark.parametrize("half_width, max_log_scale", [(0.03, 0.0), (0.08, 0.2), (0.5, 0.36)])
def test_band_count_equals_its_definition(seed, matches, true_share, half_width, max_log_scale):
    rows, cols, query, reference = random_pair(seed, 30, 25, matches, true_share, rotation=2.5 - seed,
                                               log_scale=0.1 * (seed % 3 - 1), noise=0.02)
    scales = band_log_scales(max_log_scale)
    expected = plain_band_count(rows, cols, query, reference, half_width, scales) if matches else 0
    assert band_count(rows, cols, query, reference, half_width, scales) == expected


@pytest.mark.parametrize("rotation", [0.0, 1.0, -3.0, np.pi])
@pytest.mark.parametrize("log_scale", [-0.16, 0.0, 0.12])
def test_a_rotated_and_zoomed_view_keeps_its_count(rotation, log_scale):
    """Every one of 60 true matches is counted at any rotation and at a zoom inside the grid; with the grid at
    s = 1 only, a zoom loses most of them."""
    rows, cols, query, reference = random_pair(1, 10, 80, 60, 1.0, rotation, log_scale, noise=0.005)
    cols = np.arange(60)  # one-to-one
    query = np.mod(np.exp(log_scale) * reference[cols] + rotation + np.pi, 2 * np.pi) - np.pi
    rows = np.arange(60)
    assert band_count(rows, cols, query, reference, 0.03, band_log_scales(0.2)) == 60
    if log_scale:
        assert band_count(rows, cols, query, reference, 0.03, band_log_scales(0.0)) < 30


def test_unrelated_frames_count_little():
    """Random matches between unrelated frames: the band holds about the share 2 tau / 2 pi of them."""
    rng = np.random.default_rng(5)
    counts = []
    for _ in range(20):
        rows, cols = rng.integers(0, 300, 80), rng.integers(0, 300, 80)
        counts.append(band_count(rows, cols, rng.uniform(-np.pi, np.pi, 300), rng.uniform(-np.pi, np.pi, 300), 0.08,
                                 band_log_scales(0.2)))
    assert max(counts) <= 15  # against 80 for a place's own matches


def test_many_matches_of_one_feature_count_once():
    reference = np.linspace(-3, 3, 20)
    query = np.zeros(1)
    rows, cols = np.zeros(20, np.int64), np.arange(20)
    assert band_count(rows, cols, query, reference, np.pi - 1e-3, band_log_scales(0.0)) == 1


@pytest.mark.parametrize("case, message", [
    ({"query_bearings": np.array([np.nan, 0.0])}, "finite"),
    ({"reference_bearings": np.array([0.0, np.inf])}, "finite"),
    ({"query_bearings": np.array([0.0, 7.0])}, "radians"),
    ({"reference_cols": np.array([0])}, "query rows but"),
    ({"reference_cols": np.array([0, 5])}, "outside its frame"),
    ({"half_width": 0.0}, "tau"),
    ({"half_width": np.nan}, "tau"),
    ({"log_scales": np.array([0.1, 0.0])}, "ascending"),
])
def test_bad_input_is_refused(case, message):
    args = {"query_rows": np.array([0, 1]), "reference_cols": np.array([0, 1]),
            "query_bearings": np.array([0.0, 1.0]), "reference_bearings": np.array([0.0, 1.0]), "half_width": 0.1,
            "log_scales": band_log_scales(0.1)}
    with pytest.raises(ValueError, match=message):
        band_count(**{**args, **case})


@pytest.mark.parametrize("bound", [-0.1, np.nan])
def test_bad_scale_bound_is_refused(bound):
    with pytest.raises(ValueError, match="max_log_scale"):
        band_log_scales(bound)


@pytest.mark.parametrize("seed", range(8))
def test_the_traced_alignment_has_the_dp_k_and_is_a_valid_path(seed):
    rng = np.random.default_rng(seed)
    match = rng.random((25, 30)) < 0.06 * (1 + seed % 3)
    _, k = cyclic_alignment(match)
    rows, cols = aligned_pairs(match)
    assert rows.size == k and match[rows, cols].all()
    assert np.all(np.diff(rows) > 0)  # one query feature per pair, in order; the reference cyclically in order
    assert np.count_nonzero(np.diff(cols) <= 0) <= 1


def test_the_calibrated_band_ranks_revisits_at_least_as_well_as_the_dp():
    """Against the simulator's ground truth (poses within 2 m), over three synthetic routes whose revisits come back
    in both directions: the score with the band count calibrated on the first 30 frames (no ground truth) has the
    DP's AP or better on average."""
    dp, band = [], []
    for seed in range(3):
        poses, frames = synthetic_sequence(seed=seed, spacing=1.0, landmarks=300)
        truth = ground_truth(poses, 2.0, 4)
        first, second = np.nonzero(np.triu(np.ones(truth.shape, bool), 5))
        calibration = calibrate(frames[:30])
        assert 0 < calibration.band_half_width < np.pi / 2 and calibration.summary()["band_scales"] >= 1
        for scores, tau in ((dp, 0.0), (band, calibration.band_half_width)):
            params = AlignmentParams(t_match=calibration.t_match, band_half_width=tau,
                                     band_max_log_scale=calibration.band_max_log_scale)
            values = [dp_similarity(frames[b], frames[a], params) for a, b in zip(first, second)]
            scores.append(average_precision(pr_curve(np.array(values), truth[first, second])))
    assert min(band) > 0.85
    assert np.mean(band) >= np.mean(dp) - 0.005


def test_the_band_survives_the_calibration_state():
    _, frames = synthetic_sequence(seed=1, spacing=1.0, landmarks=300)
    calibration = calibrate(frames[:30])
    again = Calibration.from_array(calibration.to_array())
    assert (again.band_half_width, again.band_max_log_scale) == (calibration.band_half_width,
                                                                 calibration.band_max_log_scale)


def test_pair_count_is_the_dp_k_without_a_band_and_refuses_mismatched_bearings():
    rng = np.random.default_rng(0)
    match = rng.random((12, 15)) < 0.2
    bearings_q, bearings_r = np.sort(rng.uniform(-3, 3, 12)), np.sort(rng.uniform(-3, 3, 15))
    assert pair_count(match, bearings_q, bearings_r) == cyclic_alignment(match)[1]
    with pytest.raises(ValueError, match="as many bearings"):
        pair_count(match, bearings_q[:-1], bearings_r, AlignmentParams(band_half_width=0.1))
