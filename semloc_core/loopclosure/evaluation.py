"""Whole-sequence similarity matrices and the exhaustive batch pipeline (the thesis's offline computation).

Matrices are (n, n) with the earlier frame as row and the later as column; entries outside the scored region
(i < j - w) are ``-inf``. They serve as the reference the incremental engine is compared with, and as the
baselines' scores in ``semloc eval loopclosure``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from semloc_core.loopclosure.bow import Vocabulary
from semloc_core.loopclosure.features import FeatureSequence
from semloc_core.loopclosure.mrf import MrfParams, MrfResult, infer_batch
from semloc_core.loopclosure.similarity import AlignmentParams, dp_similarity, pair_scores
from semloc_core.loopclosure.topomap import TopologicalMap, build_topological_map

SCORES = ("dp", "sift", "sym", "bow")


def scored_pairs(n: int, window: int) -> tuple[np.ndarray, np.ndarray]:
    """(earlier, later) indices of every pair the thesis scores: i < j - w."""
    if window < 0:
        raise ValueError("window must be >= 0")
    later, earlier = np.nonzero(np.tril(np.ones((n, n), bool), -(window + 1)))
    return earlier, later


def similarity_matrices(
    frames: Sequence[FeatureSequence],
    window: int = 30,
    alignment: AlignmentParams = AlignmentParams(),
    ratio: float = 0.8,
    vocabulary: Vocabulary | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, np.ndarray]:
    """M for the DP score and the baselines M^SIFT, M^SYM (and BoW TF-IDF when a vocabulary is given).

    The later frame is the query (its features are aligned against the replicated earlier frame's).
    """
    n = len(frames)
    out = {name: np.full((n, n), -np.inf) for name in SCORES[:3]}
    bow = [vocabulary.vector(f.descriptors) for f in frames] if vocabulary is not None else None
    if bow is not None:
        out["bow"] = np.full((n, n), -np.inf)
    for j in range(n):
        for i in range(j - window):
            s = pair_scores(frames[j], frames[i], alignment, ratio)
            out["dp"][i, j] = s.dp
            out["sift"][i, j] = s.sift
            out["sym"][i, j] = s.sym
            if bow is not None:
                out["bow"][i, j] = bow[j].similarity(bow[i])
        if progress is not None:
            progress(j + 1, n)
    return out


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
    normalizer: float | None = None,
) -> BatchResult:
    """The thesis's offline pipeline: exhaustive DP matrix, batch loopy BP, algorithm 3.1."""
    n = len(frames)
    M = np.full((n, n), -np.inf)
    for j in range(n):
        for i in range(j - window):
            M[i, j] = dp_similarity(frames[j], frames[i], alignment)
    result = infer_batch(M, mrf, normalizer)
    earlier, later = np.nonzero(result.decisions)
    topomap = build_topological_map(n, np.stack([earlier, later], axis=1), temporal_radius)
    return BatchResult(M, result, topomap)
