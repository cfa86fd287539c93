"""Precision-recall of scored pairs (thesis §3.6.3): PR curve, interpolated precision (Everingham et al. 2010),
average precision and the maximum recall at 100 % precision.

Conventions:

* A threshold ``t`` accepts every pair scored ``>= t``. The curve has one point per **distinct** score, from the
  highest down: tied pairs are accepted together, so a tie between a true and a false pair never yields a point
  that counts one without the other.
* ``labels`` are True for positives. Pairs to ignore (soft ground truth) are removed before (``loop_pairs``).
* With no positive at all, recall is undefined: the functions that need it raise ``ValueError``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RECALL_LEVELS = np.linspace(0.0, 1.0, 101)  # r in {0, 0.01, ..., 1} (thesis §3.6.3)


@dataclass(frozen=True, eq=False)
class PRCurve:
    """One point per distinct score, highest first: accepting scores >= ``thresholds[k]`` gives ``tp[k]`` true and
    ``fp[k]`` false positives, ``precision[k]`` and ``recall[k]``. ``positives`` = all positives (P)."""

    thresholds: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    positives: int
    negatives: int

    def __len__(self) -> int:
        return int(self.thresholds.shape[0])

    def to_dict(self) -> dict:
        return {"thresholds": self.thresholds.tolist(), "precision": self.precision.tolist(),
                "recall": self.recall.tolist(), "tp": self.tp.tolist(), "fp": self.fp.tolist(),
                "positives": self.positives, "negatives": self.negatives}


def _check(scores, labels) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, float).ravel()
    labels = np.asarray(labels).ravel()
    if scores.shape != labels.shape:
        raise ValueError(f"{scores.size} scores for {labels.size} labels")
    if labels.dtype != bool:
        if not np.all(np.isin(labels, (0, 1))):
            raise ValueError("labels must be boolean (or 0/1)")
        labels = labels.astype(bool)
    if np.any(np.isnan(scores)):
        raise ValueError("scores contain NaN")
    return scores, labels


def pr_curve(scores, labels, positives: int | None = None) -> PRCurve:
    """The precision-recall curve of ``scores`` against boolean ``labels`` (ties grouped, see module doc).

    ``positives``: the total number of positives when some were never scored (a detector's missed objects);
    defaults to the number of True labels.
    """
    scores, labels = _check(scores, labels)
    negatives = int(labels.size - labels.sum())
    if positives is None:
        positives = int(labels.sum())
    elif positives < labels.sum():
        raise ValueError(f"positives={positives} is below the {int(labels.sum())} positive labels")
    if positives == 0:
        raise ValueError("no positive pairs: recall is undefined")
    if labels.size == 0:
        raise ValueError("no scores")
    order = np.argsort(-scores, kind="stable")
    s = scores[order]
    y = labels[order]
    tp_cum = np.cumsum(y)
    fp_cum = np.cumsum(~y)
    # The last index of each run of equal scores closes a threshold.
    last = np.flatnonzero(np.append(s[1:] != s[:-1], True))
    tp = tp_cum[last].astype(np.int64)
    fp = fp_cum[last].astype(np.int64)
    return PRCurve(thresholds=s[last], tp=tp, fp=fp, precision=tp / (tp + fp), recall=tp / positives,
                   positives=positives, negatives=negatives)


def interpolated_precision(curve: PRCurve, recall_levels=RECALL_LEVELS) -> np.ndarray:
    """p_interp(r) = max over points with recall >= r of their precision; 0 where no point reaches r."""
    levels = np.asarray(recall_levels, float)
    # Running maximum from the high-recall end.
    envelope = np.maximum.accumulate(curve.precision[::-1])[::-1]
    idx = np.searchsorted(curve.recall, levels - 1e-12, side="left")
    out = np.zeros(levels.shape)
    ok = idx < len(curve)
    out[ok] = envelope[idx[ok]]
    return out


def average_precision(curve: PRCurve) -> float:
    """Area under the interpolated curve (all points, PASCAL VOC 2010+): sum of recall steps x envelope."""
    envelope = np.maximum.accumulate(curve.precision[::-1])[::-1]
    recall = np.concatenate([[0.0], curve.recall])
    return float(np.sum(np.diff(recall) * envelope))


def interpolated_average_precision(curve: PRCurve, recall_levels=RECALL_LEVELS) -> float:
    """Mean of p_interp over the recall levels (101 by default, thesis eq. 2)."""
    return float(np.mean(interpolated_precision(curve, recall_levels)))


def max_recall_at_full_precision(curve: PRCurve) -> float:
    """The largest recall reached with no false positive (0 when the top-scored pair, or a tie with it, is
    negative)."""
    perfect = curve.fp == 0
    return float(curve.recall[perfect].max()) if perfect.any() else 0.0


def loop_pairs(scores, gt, soft=None, window: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scored pairs of a loop-closure evaluation: (scores, labels, (i, j) index pairs).

    Pairs are ``i > j + window`` (row = later frame; thesis §3.3: M_ij for i < j - w, i.e. frames more than ``w``
    apart). Positives are ``gt``; pairs in ``soft`` but not in ``gt`` are ignored (neither counted right nor
    wrong). ``scores`` is read at [i, j] with i the later frame (use a symmetric matrix if your scores are).
    """
    scores = np.asarray(scores, float)
    gt = np.asarray(gt, bool)
    n = gt.shape[0]
    if scores.shape != (n, n) or gt.shape != (n, n):
        raise ValueError(f"scores {scores.shape} and ground truth {gt.shape} must both be (N, N)")
    if window < 0:
        raise ValueError("the window must be >= 0")
    i, j = np.tril_indices(n, -(window + 1))
    keep = np.ones(i.size, bool)
    if soft is not None:
        soft = np.asarray(soft, bool)
        if soft.shape != (n, n):
            raise ValueError(f"soft ground truth {soft.shape} must be (N, N)")
        keep = ~(soft[i, j] & ~gt[i, j])
    i, j = i[keep], j[keep]
    return scores[i, j], gt[i, j], np.stack([i, j], axis=1)


