"""Precision-recall, interpolated precision and AP."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.loopclosure.metrics import decision_quality, precision_recall


def test_perfect_and_inverted_rankings():
    labels = np.array([1, 1, 0, 0, 0], bool)
    perfect = precision_recall([5, 4, 3, 2, 1], labels)
    assert perfect.average_precision == pytest.approx(1.0)
    assert perfect.recall_at_full_precision == 1.0
    worst = precision_recall([1, 2, 3, 4, 5], labels)
    assert worst.recall_at_full_precision == 0.0
    assert worst.average_precision == pytest.approx(0.4)  # every level is first reached with all 5 predicted


def test_interpolation_and_ties():
    labels = np.array([1, 0, 1, 0], bool)
    curve = precision_recall([4, 3, 2, 1], labels)
    assert curve.precision.tolist() == pytest.approx([1.0, 0.5, 2 / 3, 0.5])
    interpolated = curve.interpolated(np.array([0.0, 0.5, 0.6, 1.0]))
    assert interpolated.tolist() == pytest.approx([1.0, 1.0, 2 / 3, 2 / 3])
    tied = precision_recall([1, 1, 1, 1], labels)  # one threshold: everything at once
    assert tied.precision.tolist() == [0.5] and tied.recall.tolist() == [1.0]
    assert precision_recall([3, -np.inf, 2, -np.inf], labels).recall.tolist() == [0.5, 1.0, 1.0]


def test_decision_quality():
    q = decision_quality([1, 1, 0, 0], [1, 0, 1, 0])
    assert q == {"precision": 0.5, "recall": 0.5, "predicted": 2, "true_positives": 1}
