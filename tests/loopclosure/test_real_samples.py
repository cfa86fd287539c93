"""The real rtabmap loop samples (84 indoor frames, hand-labelled loops): scores against their ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.camera import PinholeCamera
from semloc_core.io.loopclosure import read_loop_samples
from semloc_core.eval.pr import average_precision as average_precision_of
from semloc_core.eval.pr import pr_curve
from semloc_core.loopclosure.bow import train_vocabulary
from semloc_core.loopclosure.evaluation import evaluate_score, scored_pairs, similarity_matrices
from semloc_core.loopclosure.features import FeatureParams, extract_features

from ..conftest import shared_path

pytestmark = pytest.mark.shared_data


def average_precision(score, y):
    order = np.argsort(-score, kind="stable")
    hits = y[order]
    return float((np.cumsum(hits) / np.arange(1, hits.size + 1))[hits].mean())


@pytest.fixture(scope="module")
def samples():
    images, gt = read_loop_samples(shared_path("rtabmap_loop_samples"))
    camera = PinholeCamera.from_fov(512, 384, 60.0)
    frames = [extract_features(cv2.imread(str(p)), camera, FeatureParams(max_features=300)) for p in images]
    return frames, gt


def test_reader_gives_the_documented_ground_truth(samples):
    frames, gt = samples
    assert len(frames) == 84 and gt.shape == (84, 84)
    assert gt.sum() == 228 and not np.tril(gt).any()


@pytest.fixture(scope="module")
def matrices(samples):
    frames, _ = samples
    vocabulary = train_vocabulary([f.descriptors for f in frames if len(f)], words=1000)
    return similarity_matrices(frames, 30, vocabulary=vocabulary)


def test_dp_ranks_real_revisits_above_chance_and_above_sift_counts(samples, matrices):
    frames, gt = samples
    window = 30
    earlier, later = scored_pairs(len(frames), window)
    y = gt[earlier, later]
    base_rate = y.mean()
    dp = average_precision(matrices["dp"][earlier, later], y)
    sift = average_precision(matrices["sift"][earlier, later], y)
    assert dp > max(0.5, 3 * base_rate)
    assert dp > sift


def test_inference_raises_the_dp_score_above_the_bow_score(samples, matrices):
    """Acceptance (issue 5): on the real samples DP with inference beats BoW (the FAB-MAP stand-in, whose vocabulary
    is even learnt on these frames) as a score and after the same inference, and inference raises the DP score's
    AP. Both with the default background, per feature count."""
    frames, gt = samples
    counts = [len(f) for f in frames]
    dp = evaluate_score(matrices["dp"], gt, 30, counts=counts)
    bow = evaluate_score(matrices["bow"], gt, 30, counts=counts)
    dp_after = average_precision_of(dp.after)
    assert dp_after > average_precision_of(dp.raw)
    assert dp_after > average_precision_of(bow.raw)
    assert dp_after > average_precision_of(bow.after)


def test_keyframes_by_image_change_keep_the_dp_ranking_of_every_frame(samples, matrices):
    """The worker's key-frame gate on the real images (no odometry: image change alone), each frame answered by its
    latest key-frame: the DP's AP over every frame's pairs stays within 0.02 of scoring every frame."""
    from semloc_core.experiments.loopclosure_data import LoopSequence, scores_on_all_frames
    from semloc_core.loopclosure.keyframes import KeyframeParams, select_keyframes, thumbnail

    frames, gt = samples
    images, _ = read_loop_samples(shared_path("rtabmap_loop_samples"))
    n, window = len(frames), 30
    kept = select_keyframes(np.arange(n, dtype=float), None, (thumbnail(cv2.imread(str(p))) for p in images),
                            KeyframeParams())
    assert 0.8 * n <= kept.size < n  # hand-held frames a step apart: most are new views, a few are not
    # The key-frames' own matrix: their pairs more than `window` key-frames apart (the DP of a pair depends on the
    # two frames only, so those entries are the full matrix's).
    sub = matrices["dp"][np.ix_(kept, kept)].copy()
    index = np.arange(kept.size)
    sub[~(index[None, :] > index[:, None] + window)] = -np.inf
    ignore = np.zeros_like(gt)
    full = LoopSequence("samples", "samples", n, None, None, None, gt, ignore, None, None, "", np.arange(n, dtype=float),
                        None)
    every = scores_on_all_frames(full, kept, {"dp": sub}, window)["dp"]["average_precision"]
    earlier, later = scored_pairs(n, window)
    all_frames = average_precision_of(pr_curve(matrices["dp"][earlier, later], gt[earlier, later]))
    assert abs(every - all_frames) <= 0.02, (every, all_frames, kept.size)


def test_robot_camera_variants_dp_first_and_its_expected_precision_holds(tmp_path):
    """Acceptance (issue 33) on the real samples at 160x120 and degraded as a robot camera (fisheye with a rim, body
    overlay, a darker second half, blur, noise, JPEG), default settings: DP with inference has the highest AP of
    every score, SeqSLAM included; the precision expected of the DP's and the engine's decisions is the measured
    one within 0.1; on the robot camera the decisions reach 0.9."""
    from semloc_core.experiments.loopclosure import LoopClosureSpec, run

    spec = LoopClosureSpec(dataset=str(shared_path("rtabmap_loop_samples")), degrade=["small", "robot"], jobs=1)
    report = run(spec).report
    for name, variant in report["variants"].items():
        scores = variant["scores"]
        dp = scores["dp"]["after_inference"]["average_precision"]
        assert all(dp > s["after_inference"]["average_precision"] for k, s in scores.items() if k != "dp"), name
        for decided in (scores["dp"]["decisions_at_target"], variant["engine"]["decisions_at_target"]):
            assert decided["recall"] > 0.3, name
            assert abs(decided["precision"] - decided["expected_precision"]) <= 0.1, (name, decided)
            frames = decided["frames"]  # frames 40-83 revisit the start (the ground truth's band)
            assert frames["revisit_frames"] == 44 and frames["frame_precision"] >= 0.9, (name, frames)
        # The DP's and the engine's decisions at the acceptance's 0.9 as at the target: the precision expected of
        # them is the measured one.
        for entry in (scores["dp"], variant["engine"]):
            assert set(entry["decisions_at_precision"]) == {"0.9", "0.95"}, name
            for decided in entry["decisions_at_precision"].values():
                assert abs(decided["precision"] - decided["expected_precision"]) <= 0.1, (name, decided)
        assert 1000 <= variant["calibration"]["t_match"] <= 2500
    robot = report["variants"]["robot"]
    assert robot["scores"]["dp"]["decisions_at_target"]["precision"] >= 0.9
    assert robot["engine"]["decisions_at_target"]["precision"] >= 0.9


def test_keyframe_subset_with_degradation_variants():
    """eval loopclosure's key-frames (image change alone, no poses) and degradation variants together: both variants
    evaluate the same key-frames of the 84 frames, the DP with inference ranks their loops well, and the key-frames'
    DP answering every frame keeps most of it."""
    from semloc_core.experiments.loopclosure import LoopClosureSpec, run

    spec = LoopClosureSpec(dataset=str(shared_path("rtabmap_loop_samples")), degrade=["none", "small"], jobs=1,
                           keyframes={"enabled": True}, engine={"enabled": False})
    variants = run(spec).report["variants"]
    assert set(variants) == {"none", "small"}
    kept = {name: (v["frames"], v["dataset_frames"], v["keyframes"]["kept"]) for name, v in variants.items()}
    assert kept["none"] == kept["small"] and 0.8 * 84 <= kept["none"][0] < 84, kept
    for name, v in variants.items():
        assert v["scores"]["dp"]["after_inference"]["average_precision"] > 0.8, name
        assert v["keyframes"]["all_frames"]["dp"]["average_precision"] > 0.6, name


def test_engine_alone_gives_the_engine_figures_without_the_batch():
    """batch=false (long sequences): the engine's row on the real samples at 160x120 - it ranks their loops and its
    expected precision holds - and nothing of the batch (no score, no full matrix)."""
    from semloc_core.experiments.loopclosure import LoopClosureSpec, run

    spec = LoopClosureSpec(dataset=str(shared_path("rtabmap_loop_samples")), degrade=["small"], jobs=1, batch=False)
    result = run(spec)
    report = result.report
    assert report["scores"] == {} and "M_dp" not in result.pngs
    assert [row["score"] for row in result.rows] == ["engine"]
    engine = report["engine"]
    assert engine["after_inference"]["average_precision"] > 0.75, engine["after_inference"]
    decided = engine["decisions_at_target"]
    assert decided["recall"] > 0.3 and abs(decided["precision"] - decided["expected_precision"]) <= 0.1, decided
    with pytest.raises(ValueError, match="engine alone"):
        run(LoopClosureSpec(dataset=spec.dataset, degrade=["small"], batch=False, engine={"enabled": False}))
