"""The cyclic DP similarity and the SIFT-count baselines."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.loopclosure.features import FeatureSequence, normalize_descriptors
from semloc_core.loopclosure.similarity import (
    AlignmentParams,
    alignment_matches,
    alignment_score,
    cyclic_alignment,
    descriptor_matches,
    dp_similarity,
    pair_scores,
    sift_match_count,
    symmetric_match_count,
)

from .synthetic import ground_truth, sift_like, synthetic_sequence


def random_sequence(n: int, seed: int) -> FeatureSequence:
    rng = np.random.default_rng(seed)
    return FeatureSequence.from_unsorted(rng.uniform(-np.pi, np.pi, n), normalize_descriptors(sift_like(n, rng)))


def lcs(match: np.ndarray) -> int:
    """Longest common subsequence length for a boolean match matrix (plain Python, independent of the kernel)."""
    n, m = match.shape
    table = [[0] * (m + 1) for _ in range(n + 1)]
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            table[i][j] = max(table[i - 1][j], table[i][j - 1], table[i - 1][j - 1] + int(match[i - 1, j - 1]))
    return table[n][m]


def test_identical_sequences_align_completely():
    seq = random_sequence(60, 0)
    params = AlignmentParams()
    assert dp_similarity(seq, seq, params) == pytest.approx(params.s_match * 60)


def test_disjoint_sequences_score_the_gap_cost_of_every_feature():
    a, b = random_sequence(30, 1), random_sequence(40, 2)
    assert not descriptor_matches(a.descriptors, b.descriptors, 1000.0).any()
    assert dp_similarity(a, b) == pytest.approx(-0.1 * (30 + 40))


@pytest.mark.parametrize("angle", [0.3, 1.7, -2.9, np.pi])
def test_score_is_invariant_to_rotating_the_reference(angle):
    rng = np.random.default_rng(3)
    a = random_sequence(50, 3)
    noisy = normalize_descriptors(a.descriptors.astype(float) + rng.uniform(0, 40, a.descriptors.shape))
    b = FeatureSequence(a.bearings, noisy)
    assert dp_similarity(a, b.rotated(angle)) == pytest.approx(dp_similarity(a, b))


def test_order_matters():
    a = random_sequence(80, 4)
    rng = np.random.default_rng(4)
    shuffled = FeatureSequence(a.bearings, a.descriptors[rng.permutation(80)])
    # Every feature still has its exact match, but only a short ordered subsequence can be aligned.
    assert descriptor_matches(a.descriptors, shuffled.descriptors, 1000.0).sum() >= 80
    _, k_shuffled = cyclic_alignment(descriptor_matches(a.descriptors, shuffled.descriptors, 1000.0))
    assert k_shuffled < 30
    assert dp_similarity(a, shuffled) < dp_similarity(a, a) - 50


@pytest.mark.parametrize("seed", range(6))
def test_match_count_is_the_lcs_against_the_replicated_reference(seed):
    """With a negligible gap cost and forbidden substitutions the DP maximises k: the LCS of the query and the
    doubled reference (cyclic alignment with free ends, one-to-many allowed, as in the thesis)."""
    rng = np.random.default_rng(seed)
    match = rng.random((7, 6)) < 0.3
    _, k = cyclic_alignment(match, AlignmentParams(s_gap=1e-4, s_miss=1e3))
    assert k == lcs(np.concatenate([match, match], axis=1))
    rotations = max(lcs(np.roll(match, r, axis=1)) for r in range(6))
    assert k >= rotations


def test_thesis_score_formula():
    params = AlignmentParams(s_match=1.0, s_gap=0.1)
    assert alignment_score(100, 80, 30, params) == pytest.approx(30 - 0.1 * 70 - 0.1 * 50)


def test_threshold_is_strict():
    a = FeatureSequence(np.zeros(1), np.zeros((1, 128), np.uint8))
    descriptor = np.zeros((1, 128), np.uint8)
    descriptor[0, :4] = 250  # L1 distance 1000 from the zero descriptor
    b = FeatureSequence(np.zeros(1), descriptor)
    assert not descriptor_matches(a.descriptors, b.descriptors, 1000.0).any()
    assert descriptor_matches(a.descriptors, b.descriptors, 1000.5).all()


def test_ratio_test_baselines_count_exact_matches():
    a = random_sequence(40, 5)
    rng = np.random.default_rng(5)
    order = rng.permutation(40)
    extra = random_sequence(10, 6)
    b = FeatureSequence.from_unsorted(
        np.concatenate([a.bearings[order], extra.bearings]),
        np.concatenate([a.descriptors[order], extra.descriptors]),
    )
    assert sift_match_count(a, b) == 40
    assert symmetric_match_count(a, b) == 40
    # A duplicated descriptor in the reference makes its match ambiguous: the ratio test drops it.
    dup = FeatureSequence.from_unsorted(np.append(b.bearings, 0.0), np.concatenate([b.descriptors, a.descriptors[:1]]))
    assert sift_match_count(a, dup) == 39
    scores = pair_scores(a, dup)
    assert (scores.sift, scores.sym) == (39, symmetric_match_count(a, dup))


def test_symmetric_matches_are_a_subset():
    a, b = random_sequence(50, 7), random_sequence(60, 8)
    mixed = FeatureSequence.from_unsorted(np.concatenate([b.bearings, a.bearings[:20]]),
                                          np.concatenate([b.descriptors, a.descriptors[:20]]))
    assert symmetric_match_count(a, mixed) <= sift_match_count(a, mixed)
    assert symmetric_match_count(a, mixed) >= 20


def test_empty_sequences():
    empty = FeatureSequence.empty()
    seq = random_sequence(10, 9)
    assert dp_similarity(empty, seq) == pytest.approx(-1.0)
    assert sift_match_count(empty, seq) == 0 and symmetric_match_count(seq, empty) == 0


def test_dp_separates_revisits_better_than_sift_counts_on_a_synthetic_route():
    """Same place (GT within 2 m) vs elsewhere, in a world with clutter: the layout term pays off."""
    poses, frames = synthetic_sequence(seed=1, spacing=1.0, landmarks=300)
    window = 8
    gt = ground_truth(poses, 2.0, window)
    earlier, later = np.nonzero(np.triu(np.ones(gt.shape, bool), window + 1))
    y = gt[earlier, later]
    dp = np.array([dp_similarity(frames[j], frames[i]) for i, j in zip(earlier, later)])
    sift = np.array([sift_match_count(frames[j], frames[i]) for i, j in zip(earlier, later)])

    def average_precision(score):
        order = np.argsort(-score, kind="stable")
        hits = y[order]
        precision = np.cumsum(hits) / np.arange(1, hits.size + 1)
        return float(precision[hits].mean())

    assert y.sum() > 50
    assert average_precision(dp) > 0.85
    assert average_precision(dp) > average_precision(sift) + 0.05


def test_parameters_must_fit_the_integer_score_unit():
    with pytest.raises(ValueError, match="multiple"):
        AlignmentParams(s_gap=0.12345)
    AlignmentParams(s_gap=0.1234, s_miss=0.5)


@pytest.mark.parametrize("rule", ["threshold", "mutual", "threshold_or_mutual"])
@pytest.mark.parametrize("seed", range(3))
def test_match_rules_select_their_pairs(rule, seed):
    """"mutual" aligns exactly the M^SYM correspondences, "threshold_or_mutual" those and the threshold's; the
    one-pass pair_scores agrees with dp_similarity under every rule."""
    poses, frames = synthetic_sequence(seed=seed, noise=0.4, clutter=20)
    query, reference = frames[30], frames[2]
    params = AlignmentParams(match=rule, t_match=1200.0)
    match = alignment_matches(query.descriptors, reference.descriptors, params)
    threshold = descriptor_matches(query.descriptors, reference.descriptors, 1200.0)
    mutual = alignment_matches(query.descriptors, reference.descriptors, AlignmentParams(match="mutual"))
    assert mutual.sum() == symmetric_match_count(query, reference) and (mutual.sum(axis=1) <= 1).all()
    expected = {"threshold": threshold, "mutual": mutual, "threshold_or_mutual": threshold | mutual}[rule]
    assert np.array_equal(match, expected)
    assert pair_scores(query, reference, params).dp == dp_similarity(query, reference, params)


@pytest.mark.parametrize("later_noise", [0.2, 0.5])
def test_mutual_matches_keep_revisits_a_low_threshold_loses(later_noise):
    """Ground truth: poses within 2 m. The second traversal's descriptors are noisier (other light, another
    viewpoint) than the consecutive frames t_match is calibrated on: with the threshold alone the DP loses the
    revisits; adding the mutual ratio-test matches keeps them, and the DP ranks them above the M^SYM count."""
    from semloc_core.eval.pr import average_precision, pr_curve
    from semloc_core.loopclosure.calibration import calibrate

    from .synthetic import LandmarkWorld, loop_route

    rng = np.random.default_rng(3)
    world = LandmarkWorld.random(400, 10.0, rng)
    poses = loop_route(10.0, 0.5)[::2]
    first_lap = len(poses) // 2
    frames = [world.observe(p, rng, noise=0.2 if k < first_lap else later_noise, keep=0.5, clutter=40,
                            max_range=4.0) for k, p in enumerate(poses)]
    calibration = calibrate(frames[:30])
    frames = [calibration.apply(f) for f in frames]
    truth = ground_truth(poses, 2.0, 4)
    earlier, later = np.nonzero(np.triu(np.ones(truth.shape, bool), 5))

    def ap(score):
        values = np.array([score(frames[j], frames[i]) for i, j in zip(earlier, later)], float)
        return average_precision(pr_curve(values, truth[earlier, later]))

    def dp(rule):
        return ap(lambda q, r: dp_similarity(q, r, AlignmentParams(match=rule, t_match=calibration.t_match)))

    either, threshold = dp("threshold_or_mutual"), dp("threshold")
    assert either >= threshold - 0.02
    assert either > ap(symmetric_match_count) + 0.05
    if later_noise > 0.2:
        assert either > threshold + 0.3
