"""SeqSLAM-style sequence matching (Milford and Wyeth 2012), the sequence baseline of ``semloc eval loopclosure``.

Each frame becomes a tiny grey image (``width`` x ``height``, 64 x 32 as in OpenSeqSLAM) normalised in ``patch``-pixel
patches (zero mean, unit deviation each), which keeps the appearance and discards the light. Frames are compared
by the mean absolute difference of these images; the difference matrix is contrast-enhanced locally (each value
in units of the mean and deviation of the ``enhance_window`` values around it in its column); a pair (i, j) is
then scored by the best straight trajectory of ``length`` frames ending at it, with a speed ratio between
``min_speed`` and ``max_speed`` (both directions of travel, since a route may be revisited either way): the sum of
the enhanced differences along it. The similarity is minus that sum, so higher means more alike, as for the
other scores; the first ``length`` - 1 frames, which have no full trajectory, use the part they have (rescaled).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit


@dataclass(frozen=True)
class SeqSlamParams:
    width: int = 64
    height: int = 32
    patch: int = 8
    enhance_window: int = 10
    length: int = 10
    min_speed: float = 0.8
    max_speed: float = 1.2
    speeds: int = 5
    both_directions: bool = True

    def __post_init__(self) -> None:
        if self.width < self.patch or self.height < self.patch or self.patch < 2:
            raise ValueError("SeqSLAM images must hold at least one patch of >= 2 pixels")
        if self.enhance_window < 1 or self.length < 1 or self.speeds < 1:
            raise ValueError("enhance_window, length and speeds must be >= 1")
        if not 0 < self.min_speed <= self.max_speed:
            raise ValueError("need 0 < min_speed <= max_speed")


def thumbnail(image: np.ndarray, params: SeqSlamParams = SeqSlamParams()) -> np.ndarray:
    """The frame as SeqSLAM sees it: (height, width) float32, patch-normalised."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    small = cv2.resize(image, (params.width, params.height), interpolation=cv2.INTER_AREA).astype(np.float32)
    out = np.zeros_like(small)
    p = params.patch
    for r in range(0, params.height - p + 1, p):
        for c in range(0, params.width - p + 1, p):
            block = small[r:r + p, c:c + p]
            out[r:r + p, c:c + p] = (block - block.mean()) / max(float(block.std()), 1e-3)
    return out


def difference_matrix(thumbnails: np.ndarray) -> np.ndarray:
    """(n, n) mean absolute difference between every two thumbnails."""
    flat = np.asarray(thumbnails, np.float32).reshape(len(thumbnails), -1)
    return _sad(flat)


@njit(cache=True)
def _sad(flat):
    n, d = flat.shape
    out = np.zeros((n, n), np.float32)
    for i in range(n):
        for j in range(i + 1, n):
            total = 0.0
            for k in range(d):
                total += abs(flat[i, k] - flat[j, k])
            out[i, j] = out[j, i] = total / d
    return out


def enhance(difference: np.ndarray, window: int) -> np.ndarray:
    """Local contrast enhancement: each value of column j in units of the mean and deviation of rows i-w..i+w."""
    d = np.asarray(difference, np.float64)
    n = d.shape[0]
    out = np.empty_like(d)
    for i in range(n):
        lo, hi = max(0, i - window), min(n, i + window + 1)
        block = d[lo:hi]
        out[i] = (d[i] - block.mean(axis=0)) / np.maximum(block.std(axis=0), 1e-6)
    return out


@njit(cache=True)
def _sequence_scores(enhanced, length, speeds, window):
    """Best trajectory sum ending at each pair (i, j), i < j - window; +inf elsewhere."""
    n = enhanced.shape[0]
    out = np.full((n, n), np.inf)
    for j in range(n):
        for i in range(max(0, j - window)):
            best = np.inf
            for s in range(speeds.shape[0]):
                v = speeds[s]
                total = 0.0
                count = 0
                for k in range(length):
                    jj = j - k
                    ii = int(np.round(i - v * k))
                    if jj < 0 or ii < 0 or ii >= n:
                        break
                    total += enhanced[ii, jj]
                    count += 1
                if count:
                    total = total * length / count
                    if total < best:
                        best = total
            out[i, j] = best
    return out


def similarity_matrix(thumbnails: np.ndarray, window: int, params: SeqSlamParams = SeqSlamParams()) -> np.ndarray:
    """(n, n) SeqSLAM similarity of pairs (earlier i, later j), i < j - window; -inf elsewhere."""
    n = len(thumbnails)
    if n == 0:
        return np.zeros((0, 0))
    enhanced = enhance(difference_matrix(thumbnails), params.enhance_window)
    speeds = np.linspace(params.min_speed, params.max_speed, params.speeds)
    if params.both_directions:
        speeds = np.concatenate([speeds, -speeds])
    scores = _sequence_scores(enhanced, params.length, speeds, window)
    out = np.full((n, n), -np.inf)
    finite = np.isfinite(scores)
    out[finite] = -scores[finite]
    return out
