"""Precision-recall of loop-closure scores against a ground-truth matrix (§3.6.3).

The curve runs over every distinct score threshold (ties enter together); interpolated precision
``p_interp(r) = max_{r' >= r} p(r')`` is taken at r = 0, 0.01, ..., 1 (Everingham et al., 2010, as in the thesis),
and AP is its mean over those 101 levels. Pairs scored ``-inf`` (ruled out, e.g. by inference) enter only at the
last threshold, which predicts every pair positive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RECALL_LEVELS = np.linspace(0.0, 1.0, 101)


@dataclass(frozen=True)
class PrCurve:
    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    positives: int

    def interpolated(self, levels: np.ndarray = RECALL_LEVELS) -> np.ndarray:
        """p_interp(r) at each recall level (0 where the recall is never reached)."""
        out = np.zeros(len(levels))
        # Running maximum of precision from the high-recall end.
        best_from = np.maximum.accumulate(self.precision[::-1])[::-1]
        for k, level in enumerate(levels):
            reached = np.flatnonzero(self.recall >= level - 1e-12)
            if reached.size:
                out[k] = best_from[reached[0]]
        return out

    @property
    def average_precision(self) -> float:
        return float(self.interpolated().mean())

    @property
    def recall_at_full_precision(self) -> float:
        exact = self.precision >= 1.0 - 1e-12
        return float(self.recall[exact].max()) if exact.any() else 0.0

    def precision_at_recall(self, recall: float) -> float:
        reached = self.recall >= recall - 1e-12
        return float(self.precision[reached].max()) if reached.any() else 0.0

    def summary(self) -> dict:
        return {
            "average_precision": self.average_precision,
            "recall_at_100_precision": self.recall_at_full_precision,
            "precision_at_50_recall": self.precision_at_recall(0.5),
            "positives": self.positives,
        }


def precision_recall(scores, labels) -> PrCurve:
    """PR curve of ``scores`` (higher = more likely a loop) against boolean ``labels`` of the same shape."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    labels = np.asarray(labels, dtype=bool).reshape(-1)
    if scores.shape != labels.shape:
        raise ValueError(f"scores {scores.shape} and labels {labels.shape} differ in size")
    if np.any(np.isnan(scores)):
        raise ValueError("scores contain NaN")
    positives = int(labels.sum())
    if scores.size == 0 or positives == 0:
        return PrCurve(np.zeros(0), np.zeros(0), np.zeros(0), positives)
    order = np.argsort(-scores, kind="stable")
    sorted_scores, hits = scores[order], labels[order]
    true_positives = np.cumsum(hits)
    # Evaluate only at the last index of each run of equal scores: ties are accepted together.
    last = np.flatnonzero(np.append(sorted_scores[1:] != sorted_scores[:-1], True))
    predicted = last + 1
    precision = true_positives[last] / predicted
    recall = true_positives[last] / positives
    return PrCurve(sorted_scores[last], precision, recall, positives)


def decision_quality(decisions, labels) -> dict:
    """Precision and recall of a binary decision (e.g. D after inference)."""
    decisions = np.asarray(decisions, bool).reshape(-1)
    labels = np.asarray(labels, bool).reshape(-1)
    true_positives = int(np.sum(decisions & labels))
    return {
        "precision": true_positives / max(int(decisions.sum()), 1),
        "recall": true_positives / max(int(labels.sum()), 1),
        "predicted": int(decisions.sum()),
        "true_positives": true_positives,
    }
