"""Object-map precision and recall at a distance threshold, per class (thesis ch. 5; docs/evaluation.md).

A predicted object is a true positive if it is matched to a ground-truth object of the same class within
``distance`` metres; each ground-truth object is matched at most once. Matching is greedy by descending predicted
score (ties: input order), each prediction taking the nearest unmatched ground-truth object in range — the PASCAL
convention. Unmatched predictions are false positives, unmatched ground-truth objects false negatives.
"""

from __future__ import annotations

import numpy as np

from semloc_core.eval.pr import average_precision, pr_curve


def _positions(positions, count: int, name: str) -> np.ndarray:
    a = np.asarray(positions, float)
    if count == 0:
        return np.zeros((0, 3))
    if a.ndim != 2 or a.shape[0] != count:
        raise ValueError(f"{name}: expected ({count}, 2 or 3) positions, got {a.shape}")
    return a


def match_objects(pred_classes, pred_positions, gt_classes, gt_positions, distance: float, pred_scores=None,
                  planar: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching; returns (matched ground-truth index per prediction or -1, prediction order used)."""
    pred_positions = _positions(pred_positions, len(pred_classes), "predictions")
    gt_positions = _positions(gt_positions, len(gt_classes), "ground truth")
    if distance <= 0:
        raise ValueError("the matching distance must be positive")
    dims = 2 if planar else 3
    if pred_positions.shape[1] < dims or (len(gt_classes) and gt_positions.shape[1] < dims):
        raise ValueError(f"positions need {dims} coordinates")
    scores = np.ones(len(pred_classes)) if pred_scores is None else np.asarray(pred_scores, float)
    order = np.argsort(-scores, kind="stable")
    match = np.full(len(pred_classes), -1, np.int64)
    taken = np.zeros(len(gt_classes), bool)
    gt_classes = np.asarray(gt_classes, dtype=object)
    for p in order:
        candidates = np.flatnonzero((gt_classes == pred_classes[p]) & ~taken)
        if candidates.size == 0:
            continue
        d = np.linalg.norm(gt_positions[candidates, :dims] - pred_positions[p, :dims], axis=1)
        best = int(np.argmin(d))
        if d[best] <= distance:
            match[p] = candidates[best]
            taken[candidates[best]] = True
    return match, order


def object_map_figures(pred_classes, pred_positions, gt_classes, gt_positions, distance: float = 0.1,
                       pred_scores=None, planar: bool = True) -> dict:
    """Precision, recall, F1 overall and per class, with TP/FP/FN counts and the matched errors (JSON-ready).

    With scores, each class also gets its AP over the score threshold (unmatched ground truth = missed).
    """
    pred_classes = list(pred_classes)
    gt_classes = list(gt_classes)
    match, _ = match_objects(pred_classes, pred_positions, gt_classes, gt_positions, distance, pred_scores, planar)
    pred_positions = _positions(pred_positions, len(pred_classes), "predictions")
    gt_positions = _positions(gt_positions, len(gt_classes), "ground truth")
    dims = 2 if planar else 3

    def figures(pred_idx, gt_count):
        tp = int(np.sum(match[pred_idx] >= 0))
        fp = int(len(pred_idx) - tp)
        fn = int(gt_count - tp)
        precision = tp / (tp + fp) if tp + fp else (1.0 if gt_count == 0 else 0.0)
        recall = tp / gt_count if gt_count else 1.0
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        matched = [p for p in pred_idx if match[p] >= 0]
        errors = [float(np.linalg.norm(pred_positions[p, :dims] - gt_positions[match[p], :dims])) for p in matched]
        out = {"tp": tp, "fp": fp, "fn": fn, "precision": precision, "recall": recall, "f1": f1,
               "mean_position_error": float(np.mean(errors)) if errors else None}
        return out

    classes = sorted(set(pred_classes) | set(gt_classes))
    per_class = {}
    for c in classes:
        pred_idx = [k for k, pc in enumerate(pred_classes) if pc == c]
        gt_count = sum(1 for g in gt_classes if g == c)
        per_class[c] = figures(pred_idx, gt_count)
        if pred_scores is not None and gt_count and pred_idx:
            s = np.asarray(pred_scores, float)[pred_idx]
            y = match[pred_idx] >= 0
            curve = pr_curve(s, y, positives=gt_count)
            per_class[c]["average_precision"] = average_precision(curve)
    overall = figures(list(range(len(pred_classes))), len(gt_classes))
    return {"distance_m": distance, "planar": planar, **overall, "per_class": per_class,
            "matches": match.tolist()}


def compare_maps(predicted, truth, distance: float = 0.1, planar: bool = True) -> dict:
    """``object_map_figures`` of two ``SemanticMap``s (the predicted map's scores rank its objects)."""
    pred_classes = [predicted.class_names[k] for k in predicted.class_index]
    gt_classes = [truth.class_names[k] for k in truth.class_index]
    return object_map_figures(pred_classes, predicted.positions, gt_classes, truth.positions, distance,
                              predicted.scores, planar)
