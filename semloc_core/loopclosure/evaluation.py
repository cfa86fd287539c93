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
from semloc_core.loopclosure.features import FeatureSequence
from semloc_core.eval.pr import (
    PRCurve,
    average_precision,
    interpolated_average_precision,
    interpolated_precision,
    max_recall_at_full_precision,
    pr_curve,
)
from semloc_core.loopclosure.mrf import MrfParams, MrfResult, Normalization, infer_batch
from semloc_core.loopclosure.similarity import AlignmentParams, dp_similarity, pair_scores
from semloc_core.loopclosure.topomap import TopologicalMap, build_topological_map

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


def curve_summary(curve: PRCurve) -> dict:
    """AP (area under the interpolated envelope), the thesis's 101-point interpolated AP, recall at 100 % precision,
    interpolated precision at 50 % recall."""
    return {
        "average_precision": average_precision(curve),
        "interpolated_average_precision": interpolated_average_precision(curve),
        "recall_at_100_precision": max_recall_at_full_precision(curve),
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
    raw: PRCurve
    after: PRCurve
    decisions: dict
    inference: MrfResult

    def summary(self) -> dict:
        return {"raw": curve_summary(self.raw), "after_inference": curve_summary(self.after),
                "decisions": self.decisions,
                "normalization": (None if self.inference.normalization is None else
                                  {"location": self.inference.normalization.location,
                                   "scale": self.inference.normalization.scale})}


def evaluate_score(M: np.ndarray, gt: np.ndarray, window: int, mrf: MrfParams = MrfParams(),
                   ignore: np.ndarray | None = None) -> ScoreEvaluation:
    """PR of a similarity matrix raw and after batch inference (ranked by max-marginal log-odds), and D's quality.

    Inference runs on every scored pair; pairs in ``ignore`` are then left out of the counts.
    """
    earlier, later = evaluated_pairs(M.shape[0], window, ignore)
    labels = gt[earlier, later]
    result = infer_batch(M, mrf, window=window)
    return ScoreEvaluation(
        pr_curve(M[earlier, later], labels),
        pr_curve(result.beliefs[earlier, later], labels),
        decision_quality(result.decisions[earlier, later], labels),
        result,
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
) -> BatchResult:
    """The thesis's offline pipeline: exhaustive DP matrix, batch loopy BP, algorithm 3.1."""
    n = len(frames)
    M = np.full((n, n), -np.inf)
    for j in range(n):
        for i in range(j - window):
            M[i, j] = dp_similarity(frames[j], frames[i], alignment)
    result = infer_batch(M, mrf, normalization, window)
    earlier, later = np.nonzero(result.decisions)
    topomap = build_topological_map(n, np.stack([earlier, later], axis=1), temporal_radius)
    return BatchResult(M, result, topomap)
