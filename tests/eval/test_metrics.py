"""Evaluation metrics on hand-computed cases (ties, empty cases, recall at 100 % precision edge cases)."""

import json

import numpy as np
import pytest

from semloc_core.eval.loops import frame_decisions, loop_ground_truth, pair_distances
from semloc_core.eval.objects import match_objects, object_map_figures
from semloc_core.eval.pr import (
    average_precision,
    interpolated_average_precision,
    interpolated_precision,
    loop_pairs,
    max_recall_at_full_precision,
    pr_curve,
)
from semloc_core.eval.report import error_plot_png, json_text, markdown_table, matrix_png, pr_plot_png
from semloc_core.eval.trajectory import (
    convergence_index,
    heading_errors,
    position_errors,
    rmse,
    trajectory_figures,
)


def test_pr_curve_by_hand():
    # Scores 0.9 (T), 0.8 (F), 0.7 (T), 0.6 (T), 0.5 (F); P = 3.
    c = pr_curve([0.9, 0.8, 0.7, 0.6, 0.5], [1, 0, 1, 1, 0])
    np.testing.assert_array_equal(c.thresholds, [0.9, 0.8, 0.7, 0.6, 0.5])
    np.testing.assert_array_equal(c.tp, [1, 1, 2, 3, 3])
    np.testing.assert_array_equal(c.fp, [0, 1, 1, 1, 2])
    np.testing.assert_allclose(c.precision, [1, 1 / 2, 2 / 3, 3 / 4, 3 / 5])
    np.testing.assert_allclose(c.recall, [1 / 3, 1 / 3, 2 / 3, 1, 1])
    assert max_recall_at_full_precision(c) == pytest.approx(1 / 3)
    # Envelope: 1 up to r = 1/3, then 3/4 up to r = 1.
    assert average_precision(c) == pytest.approx(1 / 3 * 1 + 2 / 3 * 0.75)
    p = interpolated_precision(c, [0.0, 0.3, 0.34, 0.7, 1.0])
    np.testing.assert_allclose(p, [1, 1, 0.75, 0.75, 0.75])


def test_ties_are_accepted_together():
    # A true and a false pair tied at the top: no threshold takes one without the other.
    c = pr_curve([0.9, 0.9, 0.5], [True, False, True])
    np.testing.assert_array_equal(c.tp, [1, 2])
    np.testing.assert_array_equal(c.fp, [1, 1])
    assert max_recall_at_full_precision(c) == 0.0
    # Ties between positives only are harmless.
    c = pr_curve([0.9, 0.9, 0.5], [True, True, False])
    assert max_recall_at_full_precision(c) == 1.0 and len(c) == 2


@pytest.mark.parametrize("scores, labels, expected", [
    ([0.9, 0.8, 0.7], [0, 1, 1], 0.0),          # the best score is wrong
    ([0.9, 0.8, 0.7], [1, 1, 1], 1.0),          # no negative at all
    ([0.9, 0.8, 0.7, 0.1], [1, 1, 0, 1], 2 / 3),  # a negative ranked above the last positive
    ([0.5, 0.5, 0.5], [1, 0, 1], 0.0),          # everything tied, one negative
    ([0.3], [1], 1.0),
])
def test_max_recall_at_full_precision_edges(scores, labels, expected):
    assert max_recall_at_full_precision(pr_curve(scores, labels)) == pytest.approx(expected)


def test_no_positive_is_an_error_and_bad_input_rejected():
    with pytest.raises(ValueError, match="no positive"):
        pr_curve([0.1, 0.2], [0, 0])
    with pytest.raises(ValueError, match="NaN"):
        pr_curve([np.nan], [1])
    with pytest.raises(ValueError, match="scores for"):
        pr_curve([0.1, 0.2], [1])
    with pytest.raises(ValueError, match="boolean"):
        pr_curve([0.1, 0.2], [1, 2])


def test_interpolated_average_precision_and_unreached_recall():
    c = pr_curve([0.9, 0.1], [1, 0], positives=2)  # half the positives were never scored
    assert c.recall[-1] == 0.5
    p = interpolated_precision(c)
    assert np.all(p[:51] == 1.0) and np.all(p[51:] == 0.0)
    assert interpolated_average_precision(c) == pytest.approx(51 / 101)
    assert average_precision(c) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="below"):
        pr_curve([0.9], [1], positives=0)


def test_loop_pairs_window_and_soft_ground_truth():
    n = 6
    gt = np.zeros((n, n), bool)
    gt[5, 0] = gt[0, 5] = True
    gt[4, 3] = gt[3, 4] = True  # inside the window: never scored
    soft = gt.copy()
    soft[5, 1] = soft[1, 5] = True  # near miss: ignored
    scores = np.arange(n * n, dtype=float).reshape(n, n)
    s, y, ij = loop_pairs(scores, gt, soft, window=2)
    # Pairs i > j + 2: (3,0) (4,0) (4,1) (5,0) (5,1) (5,2) minus the ignored (5,1).
    assert [tuple(p) for p in ij] == [(3, 0), (4, 0), (4, 1), (5, 0), (5, 2)]
    np.testing.assert_array_equal(y, [False, False, False, True, False])
    np.testing.assert_array_equal(s, scores[ij[:, 0], ij[:, 1]])
    curve = pr_curve(s, y)
    # (5,2) scores 32 > (5,0) = 30: one false positive above the only positive.
    assert max_recall_at_full_precision(curve) == 0.0
    assert average_precision(curve) == pytest.approx(0.5)


def test_loop_ground_truth_from_poses():
    positions = np.array([[0, 0, 0], [1, 0, 0], [5, 0, 0], [0.5, 0, 0]], float)
    axes = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]], float)
    hard, soft = loop_ground_truth(positions, axes, distance=1.0, soft_distance=2.0, max_angle=np.radians(45))
    assert hard[0, 1] and hard[1, 0] and not hard[0, 2]
    assert not hard[0, 3] and soft[0, 3]  # close but facing away: soft only
    assert not hard.diagonal().any() and np.array_equal(hard, hard.T)
    assert np.all(soft >= hard)
    with pytest.raises(ValueError, match="soft_distance"):
        loop_ground_truth(positions, distance=2, soft_distance=1)


def test_loop_decisions_per_frame_and_the_false_ones_distances_by_hand():
    # Five frames on a line, 1 m apart; [earlier, later]: frame 3 revisits 0 (soft: 1), frame 4 revisits nothing.
    positions = np.stack([np.arange(5.0), np.zeros(5)], axis=1)
    hard, soft, evaluated = (np.zeros((5, 5), bool) for _ in range(3))
    hard[0, 3] = soft[1, 3] = True
    evaluated[np.triu_indices(5, 2)] = True
    decided = np.zeros((5, 5), bool)
    decided[1, 3] = decided[0, 4] = decided[1, 4] = True  # a soft partner (right), two false ones 4 m and 3 m off
    frames = frame_decisions(decided, hard, soft, evaluated)
    assert frames["revisit_frames"] == 1 and frames["revisit_frames_recognised"] == 1  # frame 3, by its soft one
    assert frames["frames_with_loop"] == 2 and frames["frame_precision"] == 0.5 and frames["frame_recall"] == 1.0
    false = pair_distances(decided & ~hard & ~soft, positions)
    assert false["count"] == 2 and false["quartiles_m"] == [3.25, 3.5, 3.75]
    assert pair_distances(np.zeros((5, 5), bool), positions) == {"count": 0, "quartiles_m": None}
    assert frame_decisions(np.zeros((5, 5), bool), hard, soft, evaluated)["frame_precision"] is None
    with pytest.raises(ValueError):
        frame_decisions(decided, hard[:4], soft, evaluated)


def test_trajectory_figures_by_hand():
    stamps = np.arange(10) * 1_000_000_000  # 1 s apart
    truth = np.zeros((10, 3))
    estimate = np.zeros((10, 3))
    estimate[:, 0] = [5, 4, 3, 0.6, 0.4, 0.3, 0.2, 0.1, 0.1, 0.1]
    estimate[:, 2] = np.radians([90, 0, 0, 0, 0, 0, 0, 0, 10, -10])
    e = position_errors(estimate, truth)
    np.testing.assert_allclose(e, estimate[:, 0])
    assert convergence_index(e, stamps, 0.5, hold_s=3) == 4
    assert convergence_index(e, stamps, 0.05, hold_s=3) is None
    # Good to the end of a short sequence counts even when shorter than the hold.
    assert convergence_index([1, 1, 0.1], [0, 1, 2], 0.5, hold_s=100) == 2
    f = trajectory_figures(estimate, truth, stamps, 0.5, 3)
    assert f["time_to_converge_s"] == 4.0
    assert f["rmse_after_convergence"] == pytest.approx(np.sqrt(np.mean(np.array([0.4, 0.3, 0.2, 0.1, 0.1, 0.1]) ** 2)))
    assert f["rmse"] == pytest.approx(rmse(e))
    assert f["heading_rmse_after_convergence_deg"] == pytest.approx(np.sqrt(200 / 6))
    np.testing.assert_allclose(heading_errors([[0, 0, 3.1]], [[0, 0, -3.1]]), [2 * np.pi - 6.2])
    json.dumps(f)


def test_object_map_matching_by_hand():
    gt_classes = ["mug", "mug", "can"]
    gt = [[0, 0], [1, 0], [3, 0]]
    pred_classes = ["mug", "mug", "can", "can"]
    pred = [[0.05, 0], [0.02, 0], [3.3, 0], [2.95, 0]]
    scores = [0.9, 0.8, 0.7, 0.6]
    match, _ = match_objects(pred_classes, pred, gt_classes, gt, 0.1, scores)
    # The 0.9 mug takes gt 0; the 0.8 mug has only gt 1 left (0.98 m away): false positive. Cans: 0.3 m is too far.
    np.testing.assert_array_equal(match, [0, -1, -1, 2])
    f = object_map_figures(pred_classes, pred, gt_classes, gt, 0.1, scores)
    assert (f["tp"], f["fp"], f["fn"]) == (2, 2, 1)
    assert f["precision"] == 0.5 and f["recall"] == pytest.approx(2 / 3)
    assert f["per_class"]["mug"]["recall"] == 0.5 and f["per_class"]["can"]["precision"] == 0.5
    assert f["per_class"]["can"]["mean_position_error"] == pytest.approx(0.05)
    # Can AP: the 0.7 can is wrong, the 0.6 one right, 1 positive -> precision 1/2 at recall 1.
    assert f["per_class"]["can"]["average_precision"] == pytest.approx(0.5)
    # Nothing predicted: recall 0, precision 0 (there was something to find).
    empty = object_map_figures([], np.zeros((0, 2)), gt_classes, gt, 0.1)
    assert empty["recall"] == 0 and empty["precision"] == 0 and empty["fn"] == 3
    json.dumps(f)


def test_reports_are_png_markdown_json():
    c = pr_curve([0.9, 0.8, 0.7], [1, 0, 1])
    for png in (pr_plot_png({"a": c}), pr_plot_png({"a": c}, interpolated=True, dashed={"a": c}),
                error_plot_png([0, 1, 2], {"run": [3, 1, 0.2]}, threshold=0.5), matrix_png(np.eye(4))):
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
    table = markdown_table([{"name": "dp", "ap": 0.51234, "ok": True, "none": None}])
    assert table.splitlines()[0] == "| name | ap | ok | none |"
    assert "| dp | 0.5123 | yes | — |" in table
    doc = json.loads(json_text({"curve": c, "x": np.float32(1.5), "n": np.nan, "a": np.arange(2)}))
    assert doc["x"] == 1.5 and doc["n"] is None and doc["a"] == [0, 1] and doc["curve"]["tp"] == [1, 1, 2]


def test_compare_semantic_maps():
    from semloc_core.eval.objects import compare_maps
    from semloc_core.io.semantic_map import SemanticMap

    truth = SemanticMap.from_objects([{"class": "bowl", "position": [0, 0, 0.8]},
                                      {"class": "cap", "position": [1, 0, 0.8]}])
    predicted = SemanticMap.from_objects([{"class": "cap", "position": [1.05, 0, 0.8], "score": 0.9},
                                          {"class": "bowl", "position": [0.5, 0, 0.8], "score": 0.4}])
    f = compare_maps(predicted, truth, distance=0.1)
    assert f["per_class"]["cap"]["tp"] == 1 and f["per_class"]["bowl"]["fp"] == 1 and f["fn"] == 1
