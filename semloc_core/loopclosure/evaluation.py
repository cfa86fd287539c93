"""Whole-sequence similarity matrices and the exhaustive batch pipeline (the thesis's offline computation).

Matrices are (n, n) with the earlier frame as row and the later as column; entries outside the scored region
(i < j - w) are ``-inf``. They serve as the reference the incremental engine is compared with, and as the
baselines' scores in ``semloc eval loopclosure``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from semloc_core.loopclosure.bow import BowVector, Vocabulary
from semloc_core.loopclosure.features import FeatureSequence, l1_distances
from semloc_core.eval.pr import (
    PRCurve,
    average_precision,
    interpolated_average_precision,
    interpolated_precision,
    max_recall_at_full_precision,
    pr_curve,
)
from semloc_core.loopclosure.decision import decide
from semloc_core.loopclosure.mrf import MrfParams, MrfResult, Normalization, infer_batch
from semloc_core.loopclosure.similarity import AlignmentParams, dp_similarity, pair_scores, ratio_test_matches
from semloc_core.loopclosure.topomap import TopologicalMap, map_from_beliefs

SCORES = ("dp", "sift", "sym", "bow")


def scored_pairs(n: int, window: int) -> tuple[np.ndarray, np.ndarray]:
    """(earlier, later) indices of every pair the thesis scores: i < j - w."""
    if window < 0:
        raise ValueError("window must be >= 0")
    later, earlier = np.nonzero(np.tril(np.ones((n, n), bool), -(window + 1)))
    return earlier, later


def evaluated_pairs(n: int, window: int, ignore: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Scored pairs minus those the ground truth leaves undecided (``ignore[i, j]``, e.g. soft loops)."""
    earlier, later = scored_pairs(n, window)
    if ignore is None:
        return earlier, later
    keep = ~np.asarray(ignore, bool)[earlier, later]
    return earlier[keep], later[keep]


def similarity_columns(
    frames: Sequence[FeatureSequence],
    columns: Sequence[int],
    window: int = 30,
    alignment: AlignmentParams = AlignmentParams(),
    ratio: float = 0.8,
    bow: Sequence[BowVector] | None = None,
) -> dict[str, np.ndarray]:
    """Columns j of M (pairs (i, j), i < j - w) for the DP score and the baselines; (n, len(columns)) each.

    The later frame is the query: its features are aligned against the replicated earlier frame's. Splitting the
    work by columns lets a caller spread it over processes.
    """
    n = len(frames)
    names = SCORES if bow is not None else SCORES[:3]
    out = {name: np.full((n, len(columns)), -np.inf) for name in names}
    for c, j in enumerate(columns):
        for i in range(j - window):
            s = pair_scores(frames[j], frames[i], alignment, ratio)
            out["dp"][i, c] = s.dp
            out["sift"][i, c] = s.sift
            out["sym"][i, c] = s.sym
            if bow is not None:
                out["bow"][i, c] = bow[j].similarity(bow[i])
    return out


def similarity_matrices(
    frames: Sequence[FeatureSequence],
    window: int = 30,
    alignment: AlignmentParams = AlignmentParams(),
    ratio: float = 0.8,
    vocabulary: Vocabulary | None = None,
) -> dict[str, np.ndarray]:
    """(n, n) M for the DP score and the baselines M^SIFT, M^SYM (and BoW TF-IDF when a vocabulary is given)."""
    bow = [vocabulary.vector(f.descriptors) for f in frames] if vocabulary is not None else None
    return similarity_columns(frames, range(len(frames)), window, alignment, ratio, bow)


def recall_at_precision(curve: PRCurve, precision: float) -> float:
    """The highest recall of a threshold whose precision is at least ``precision`` (0 when none is)."""
    reach = curve.precision >= precision
    return float(curve.recall[reach].max()) if reach.any() else 0.0


def curve_summary(curve: PRCurve) -> dict:
    """AP (area under the interpolated envelope), the thesis's 101-point interpolated AP, recall at 100 % and 90 %
    precision, interpolated precision at 50 % recall."""
    return {
        "average_precision": average_precision(curve),
        "interpolated_average_precision": interpolated_average_precision(curve),
        "recall_at_100_precision": max_recall_at_full_precision(curve),
        "recall_at_90_precision": recall_at_precision(curve, 0.9),
        "precision_at_50_recall": float(interpolated_precision(curve)[50]),
        "positives": curve.positives,
    }


def decision_quality(decisions, labels) -> dict:
    """Precision and recall of a binary decision (D after inference)."""
    decisions = np.asarray(decisions, bool).reshape(-1)
    labels = np.asarray(labels, bool).reshape(-1)
    true_positives = int(np.sum(decisions & labels))
    return {"precision": true_positives / max(int(decisions.sum()), 1),
            "recall": true_positives / max(int(labels.sum()), 1),
            "predicted": int(decisions.sum()), "true_positives": true_positives}


@dataclass
class ScoreEvaluation:
    """``decisions``: D (belief > 0, the thesis's); ``at_target``: the decisions at the target precision
    (:mod:`.decision`), their measured precision and recall beside the precision expected of them; ``at_precision``
    the same at each target precision reported (keyed by its text, e.g. "0.9"; the target's among them)."""

    raw: PRCurve
    after: PRCurve
    decisions: dict
    inference: MrfResult
    at_target: dict
    at_precision: dict

    def summary(self) -> dict:
        return {"raw": curve_summary(self.raw), "after_inference": curve_summary(self.after),
                "decisions": self.decisions, "decisions_at_target": self.at_target,
                "decisions_at_precision": self.at_precision,
                "normalization": (None if self.inference.normalization is None else
                                  {"location": self.inference.normalization.location,
                                   "scale": self.inference.normalization.scale})}


def evaluate_score(M: np.ndarray, gt: np.ndarray, window: int, mrf: MrfParams = MrfParams(),
                   ignore: np.ndarray | None = None, counts=None, target_precision: float = 0.95,
                   place_radius: int | None = None, report_precisions: Sequence[float] = ()) -> ScoreEvaluation:
    """PR of a similarity matrix raw and after batch inference (ranked by max-marginal log-odds), D's quality and
    the decisions at ``target_precision`` and at each of ``report_precisions`` (thresholds from the beliefs of
    every scored pair; ``place_radius``: decided partners beyond it from their visit's strongest count as false,
    as the engine's ``decision_places``).

    Inference runs on every scored pair; pairs in ``ignore`` are then left out of the counts. ``counts``: the
    frames' feature counts (the MRF's "features" background).
    """
    earlier, later = evaluated_pairs(M.shape[0], window, ignore)
    labels = gt[earlier, later]
    result = infer_batch(M, mrf, window=window, counts=counts)
    scored_earlier, scored_later = scored_pairs(M.shape[0], window)
    at_precision = {}
    for target in sorted({*report_precisions, target_precision}):
        decision = decide(result.beliefs[scored_earlier, scored_later], target, cells=(scored_earlier, scored_later),
                          place_radius=place_radius)
        at_precision[f"{target:g}"] = {**decision_quality(result.beliefs[earlier, later] >= decision.threshold,
                                                          labels), **decision.summary()}
    return ScoreEvaluation(
        pr_curve(M[earlier, later], labels),
        pr_curve(result.beliefs[earlier, later], labels),
        decision_quality(result.decisions[earlier, later], labels),
        result,
        at_precision[f"{target_precision:g}"],
        at_precision,
    )


def same_place_pairs(n: int, gt: np.ndarray, positions: np.ndarray | None, gt_distance: float | None,
                     temporal: int) -> np.ndarray:
    """(n, n) symmetric: frames at the same place - within ``gt_distance`` when positions are known, otherwise a
    ground-truth loop or at most ``temporal`` frames apart."""
    if positions is not None and gt_distance is not None:
        p = np.asarray(positions, float)[:, :2]
        return np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1]) < gt_distance
    index = np.arange(n)
    return gt | gt.T | (np.abs(index[:, None] - index[None, :]) <= temporal)


def evaluate_topomap(topomap: TopologicalMap, same_place: np.ndarray) -> dict:
    """The map's acceptance figures: one node per frame, spatial distinctiveness, compactness."""
    n = topomap.frame_node.size
    node = topomap.frame_node
    assigned = node >= 0
    same_node = (node[:, None] == node[None, :]) & assigned[:, None] & assigned[None, :]
    pairs = np.triu(same_node, 1)
    within = int(np.sum(pairs & same_place))
    total = int(pairs.sum())
    return {
        "frames": n,
        "frames_in_exactly_one_node": int(assigned.sum()),
        "nodes": topomap.n_nodes,
        "nodes_per_frame": topomap.n_nodes / max(n, 1),
        "edges": int(len(topomap.edges)),
        "same_node_pairs": total,
        "same_node_pairs_at_same_place": within,
        "same_place_fraction": within / total if total else 1.0,
    }


def descriptor_distances(frames: Sequence[FeatureSequence], loop_pairs, unrelated_pairs, ratio: float = 0.8,
                         epipolar_px: float = 1.5, min_inliers: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """What ``t_match`` has to separate (§3.6.2), measured on the data: (L1 distances of verified correspondences
    between frames of the same place, L1 distance from each feature to its nearest neighbour in a frame of an
    unrelated place), on VLFeat's descriptor scale.

    A verified correspondence is a ratio-test match between two frames' features seen by the same camera that is an
    epipolar inlier (Sampson distance below ``epipolar_px``) of a fundamental matrix fitted by RANSAC to at least
    ``min_inliers`` of them: the geometric check the DP does without, used here only to tell true correspondences
    from chance ones. Meaningful for pinhole images (and rig members), not for panoramas.
    """
    rng = np.random.default_rng(seed)
    verified = []
    for a, b in np.asarray(loop_pairs, np.int64).reshape(-1, 2).tolist():
        query, reference = frames[b], frames[a]
        match = ratio_test_matches(query, reference, ratio)
        hit = np.flatnonzero(match >= 0)
        for member in np.unique(query.camera_index[hit]).tolist():
            q = hit[(query.camera_index[hit] == member) & (reference.camera_index[match[hit]] == member)]
            if q.size < min_inliers:
                continue
            inliers = _epipolar_inliers(query.points[q].astype(np.float64),
                                        reference.points[match[q]].astype(np.float64), epipolar_px, rng)
            if inliers.sum() < min_inliers:
                continue
            q = q[inliers]
            diff = query.descriptors[q].astype(np.int32) - reference.descriptors[match[q]].astype(np.int32)
            verified.append(np.abs(diff).sum(axis=1))
    nearest = []
    for a, b in np.asarray(unrelated_pairs, np.int64).reshape(-1, 2).tolist():
        query, reference = frames[b].descriptors, frames[a].descriptors
        if len(query) and len(reference):
            nearest.append(l1_distances(query, reference).min(axis=1))
    join = (lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64))
    return join(verified), join(nearest)


def _epipolar_inliers(p1: np.ndarray, p2: np.ndarray, threshold: float, rng: np.random.Generator,
                      iterations: int = 300) -> np.ndarray:
    """RANSAC over 8-point fundamental matrices with our own generator (OpenCV's RANSAC draws from its global RNG):
    the inlier mask of the best model by Sampson distance."""
    import cv2

    x1 = np.column_stack([p1, np.ones(len(p1))])
    x2 = np.column_stack([p2, np.ones(len(p2))])
    best = np.zeros(len(p1), bool)
    for _ in range(iterations):
        sample = rng.choice(len(p1), 8, replace=False)
        F, _ = cv2.findFundamentalMat(p1[sample], p2[sample], cv2.FM_8POINT)
        if F is None or F.shape != (3, 3):
            continue
        Fx1, Ftx2 = x1 @ F.T, x2 @ F
        residual = np.sum(x2 * Fx1, axis=1)
        sampson = residual**2 / np.maximum(Fx1[:, 0]**2 + Fx1[:, 1]**2 + Ftx2[:, 0]**2 + Ftx2[:, 1]**2, 1e-12)
        inliers = sampson < threshold**2
        if inliers.sum() > best.sum():
            best = inliers
    return best


def distance_summary(verified: np.ndarray, unrelated: np.ndarray, thresholds) -> dict:
    """Percentiles of both distance sets and, per threshold, the share of each it accepts (distance < t)."""
    def percentiles(values):
        return ({str(q): float(np.percentile(values, q)) for q in (10, 50, 75, 90, 95)} if values.size else {})

    return {
        "verified_correspondences": {"count": int(verified.size), "percentiles": percentiles(verified)},
        "unrelated_nearest_neighbours": {"count": int(unrelated.size), "percentiles": percentiles(unrelated)},
        "accepted": [{"t_match": float(t),
                      "verified": float(np.mean(verified < t)) if verified.size else None,
                      "unrelated": float(np.mean(unrelated < t)) if unrelated.size else None}
                     for t in sorted(set(float(t) for t in thresholds))],
    }


@dataclass
class BatchResult:
    M: np.ndarray
    mrf: MrfResult
    topomap: TopologicalMap


def batch_pipeline(
    frames: Sequence[FeatureSequence],
    window: int = 30,
    alignment: AlignmentParams = AlignmentParams(),
    mrf: MrfParams = MrfParams(),
    temporal_radius: int = 2,
    normalization: Normalization | None = None,
    map_min_belief: float | None = None,
) -> BatchResult:
    """The thesis's offline pipeline: exhaustive DP matrix, batch loopy BP, algorithm 3.1.

    The map is built from D (``map_min_belief`` None) or, like the engine's, from the loops at least that sure."""
    n = len(frames)
    M = np.full((n, n), -np.inf)
    for j in range(n):
        for i in range(j - window):
            M[i, j] = dp_similarity(frames[j], frames[i], alignment)
    result = infer_batch(M, mrf, normalization, window, counts=[len(f) for f in frames])
    return BatchResult(M, result, map_from_beliefs(result.beliefs, map_min_belief, temporal_radius))
