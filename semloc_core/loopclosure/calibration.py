"""Self-calibration of the image-dependent constants from the sequence itself, without ground truth (issue 33).

The DP's match threshold ``t_match`` has to separate the descriptor distances of corresponding features from the
distances a feature of an unrelated frame can reach by chance, and both depend on the images (resolution, blur,
lens, texture). What matters is not the single distance but what the DP and the MRF make of it: the aligned
count, its gap penalties, repeated texture suppressed at the same threshold (``repeated_threshold`` = ``t_match``,
§3.6.4) and the MRF's background normalisation (a separation of single match counts chose 750-1200 on rendered
routes where the DP with inference ranks best at 1450-2000). Both sides are observable without ground truth:

* **Related pairs**: frames 1..g apart while their views still overlap (the same place, seen from further and
  further away; the larger gaps are the hard revisits a loop closure must still rank high). g (at most
  ``related_gap``) is read from the sequence: the largest gap up to which the median pair shares more mutual
  ratio-test matches (threshold-free) than the background's median + 3 robust deviations.
* **Background pairs**: frames at least ``min_separation`` apart (mostly other places; the few loops among them
  only make the estimate cautious).

For each candidate threshold t the DP scores both sets (features suppressed at t), standardises them as the MRF's
calibrated potential does (:func:`.mrf.background_normalization` of the background scores, a median line in the
frames' feature counts) and measures the separation as the AUC of related against background (Mann-Whitney;
its standard error after Hanley & McNeil 1982). The AUC curve is flat near its peak on a few dozen frames, so the
choice follows the one-standard-error rule: every threshold whose AUC is within one standard error (of the
difference) of the best is as good as the data can tell (not the noise's argmax), and ``t_match`` is their lower
quartile: inside the plateau, leaning towards the thesis's scale (1000). Where the data cannot tell thresholds apart
at all (a wall of look-alike shapes, every related pair above every background pair up to 2200) this keeps the
threshold low, where chance matches are rare.

**Static regions.** A lens rim, the robot's own body or an overlay give features at the same pixel in every frame,
which match between any two frames and carry no place information. Correspondences between consecutive frames
that moved less than ``static_px`` pixels are collected in a grid; a cell where such matches occur in at least
``static_share`` of the frame pairs (and make most of the cell's matches) is static, and features there are masked.
If the static cells would hold most of all matches the camera has not moved and nothing is masked.

The engine calibrates once its first ``frames`` frames are in (before the window lets it align anything, so every
score it computes uses the calibrated threshold); the batch evaluation calibrates on the same first frames, so both
align with the same threshold. Longer runs draw at most ``pairs`` related and ``pairs`` background pairs at random.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.stats import rankdata

from semloc_core.loopclosure.features import FeatureSequence, l1_distances, suppress_repeated
from semloc_core.loopclosure.mrf import background_normalization
from semloc_core.loopclosure.similarity import AlignmentParams, _align_match_matrix, _check_lengths, _units

CALIBRATION_MODES = ("sequence", "fixed")
_ALIGNMENT = AlignmentParams()  # the DP's scores (s_match, s_gap); t_match is the candidate
_UNITS = tuple(_units(v) for v in (_ALIGNMENT.s_match, _ALIGNMENT.s_miss, _ALIGNMENT.s_gap))
_GRID = 24  # static-region grid cells across the shorter image side
_THRESHOLDS = np.arange(600.0, 3001.0, 100.0)  # candidate t_match (VLFeat scale: L1, descriptors of L2 norm 512)


@dataclass(frozen=True)
class CalibrationParams:
    """``mode``: ``"sequence"`` derives t_match, the repeated-texture threshold and the static mask from the
    sequence; ``"fixed"`` keeps the configured constants (the thesis's preset). ``frames``: frames the engine
    calibrates on; ``related_gap``: at most frames 1..related_gap apart are related pairs; ``min_separation``: frames at
    least that far apart are background pairs; ``pairs``: at most this many of each (drawn at random);
    ``gap``: frames 1..gap apart give the static regions' correspondences, ``ratio`` (Lowe's ratio test),
    ``static_px``, ``static_share``: the static regions (see the module)."""

    mode: str = "sequence"
    frames: int = 30
    related_gap: int = 8
    min_separation: int = 15
    pairs: int = 200
    gap: int = 2
    ratio: float = 0.8
    static_px: float = 1.0
    static_share: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in CALIBRATION_MODES:
            raise ValueError(f"calibration mode must be one of {CALIBRATION_MODES}, got {self.mode!r}")
        if self.frames < 4 or self.gap < 1 or self.related_gap < 1 or self.min_separation < 2 or self.pairs < 1:
            raise ValueError("calibration needs frames >= 4, gap >= 1, related_gap >= 1, min_separation >= 2, "
                             "pairs >= 1")
        if self.related_gap >= self.min_separation:
            raise ValueError("calibration needs related_gap < min_separation (related pairs are not background)")
        if not 0 < self.ratio <= 1 or self.static_px <= 0 or not 0 < self.static_share <= 1:
            raise ValueError("calibration needs 0 < ratio <= 1, static_px > 0, 0 < static_share <= 1")


@dataclass(frozen=True, eq=False)
class Calibration:
    """What the sequence says: the match threshold, the repeated-texture threshold, the static cells (a boolean
    grid over each camera's image, ``cell`` pixels per cell; None: nothing static) and the statistics behind them."""

    t_match: float
    repeated_threshold: float
    cell: float = 1.0
    static: np.ndarray | None = None
    frames: int = 0
    stats: dict = field(default_factory=dict)

    def apply(self, sequence: FeatureSequence) -> FeatureSequence:
        """The frame's features without the static regions' and without repeated texture."""
        if self.static is not None and len(sequence):
            sequence = sequence.subset(~self.static_features(sequence))
        return suppress_repeated(sequence, self.repeated_threshold)

    def static_features(self, sequence: FeatureSequence) -> np.ndarray:
        if self.static is None or not len(sequence):
            return np.zeros(len(sequence), bool)
        cells = _cells(sequence.points, self.cell, self.static.shape)
        return self.static[cells[:, 0], cells[:, 1]]

    def summary(self) -> dict:
        return {"t_match": self.t_match, "repeated_threshold": self.repeated_threshold, "frames": self.frames,
                "static_cells": int(self.static.sum()) if self.static is not None else 0,
                "static_area": float(self.static.mean()) if self.static is not None else 0.0, **self.stats}

    def to_array(self) -> np.ndarray:
        """Flat float64: t_match, repeated threshold, cell, frames, grid rows, grid cols, then the grid."""
        grid = self.static if self.static is not None else np.zeros((0, 0), bool)
        return np.concatenate([[self.t_match, self.repeated_threshold, self.cell, self.frames, *grid.shape],
                               grid.reshape(-1).astype(np.float64)])

    @classmethod
    def from_array(cls, values) -> "Calibration":
        v = np.asarray(values, np.float64).reshape(-1)
        if v.size < 6:
            raise ValueError("calibration state too short")
        rows, cols = int(v[4]), int(v[5])
        if rows < 0 or cols < 0 or v.size != 6 + rows * cols:
            raise ValueError("calibration state: bad static grid")
        grid = v[6:].reshape(rows, cols) > 0.5 if rows * cols else None
        return cls(float(v[0]), float(v[1]), float(v[2]), grid, int(v[3]))


def _distances(query: FeatureSequence, reference: FeatureSequence) -> np.ndarray:
    return l1_distances(np.ascontiguousarray(query.descriptors),
                        np.ascontiguousarray(reference.descriptors)).astype(np.float64)


def _cells(points: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    rc = np.floor(np.asarray(points, np.float64)[:, ::-1] / cell).astype(np.int64)
    return np.clip(rc, 0, np.array(shape) - 1)


def mutual_matches(query: FeatureSequence, reference: FeatureSequence, ratio: float):
    """(query index, reference index, L1 distance) of mutual nearest neighbours (L1) passing the ratio test both
    ways."""
    return _mutual(_distances(query, reference), ratio)


def _mutual(d: np.ndarray, ratio: float):
    """:func:`mutual_matches` on the (query, reference) distance matrix."""
    if d.shape[0] < 2 or d.shape[1] < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    rows = np.arange(d.shape[0])
    forward = np.argpartition(d, 1, axis=1)[:, :2]
    first = np.where(d[rows, forward[:, 0]] <= d[rows, forward[:, 1]], forward[:, 0], forward[:, 1])
    second = np.where(first == forward[:, 0], forward[:, 1], forward[:, 0])
    best, runner = d[rows, first], d[rows, second]
    backward = np.argmin(d, axis=0)
    back_runner = np.partition(d, 1, axis=0)[1]
    ok = (best < ratio * runner) & (backward[first] == rows) & (best < ratio * back_runner[first])
    return rows[ok], first[ok], best[ok]


def calibrate(frames: Sequence[FeatureSequence], params: CalibrationParams = CalibrationParams(),
              image_size: tuple[int, int] | None = None) -> Calibration | None:
    """The calibration of a sequence of (unsuppressed) feature sequences; None when they are too few or too poor to
    say anything (fewer than ``params.gap + 2`` frames or no correspondence at all).

    ``image_size`` (width, height) of the (single) camera, for the static grid (default: the extent of the
    features' pixels)."""
    n = len(frames)
    if n < params.gap + 2:
        return None
    rng = np.random.default_rng(params.seed)
    # Correspondences between consecutive frames: distances, and where they did not move.
    distances, pair_of, static_points, static_pair = [], [], [], []
    pair = 0
    for a in range(n):
        for g in range(1, params.gap + 1):
            b = a + g
            if b >= n:
                continue
            q, r, dist = mutual_matches(frames[b], frames[a], params.ratio)
            same_camera = frames[b].camera_index[q] == frames[a].camera_index[r]
            q, r, dist = q[same_camera], r[same_camera], dist[same_camera]
            distances.append(dist)
            pair_of.append(np.full(dist.size, pair))
            moved = np.hypot(*(frames[b].points[q] - frames[a].points[r]).T)
            still = moved < params.static_px
            static_points.append(frames[b].points[q[still]])
            static_pair.append(np.full(int(still.sum()), pair))
            pair += 1
    true = np.concatenate(distances) if distances else np.zeros(0)
    if true.size == 0:
        return None
    static, cell, static_stats = _static_grid(frames, np.concatenate(static_points), np.concatenate(static_pair),
                                              pair, true.size, params, image_size)
    masked = [f.subset(~_mask(f, static, cell)) if static is not None else f for f in frames]
    # Related pairs (close in time) and background pairs (far apart), as the DP will see them (static regions masked).
    separation = min(params.min_separation, max(2, n // 2))  # a short calibration run: half of it apart
    related_gap = min(params.related_gap, separation - 1)
    related = [(a, b) for b in range(n) for a in range(max(0, b - related_gap), b)]
    background = [(a, b) for b in range(n) for a in range(b - separation + 1)]
    if not related or not background:
        return None
    related, background = (_sample(x, params.pairs, rng) for x in (related, background))
    t, related_gap, curve = _dp_threshold(masked, related, background, params.ratio)
    stats = {"correspondences": int(true.size), "correspondence_distance_median": float(np.median(true)),
             "related_gap": related_gap, "related_pairs": int(sum(b - a <= related_gap for a, b in related)),
             "background_pairs": len(background), "criterion": curve,
             **static_stats}
    return Calibration(t, t, cell, static, n, stats)


def _sample(pairs: list, most: int, rng: np.random.Generator) -> list:
    if len(pairs) <= most:
        return pairs
    return [pairs[k] for k in np.sort(rng.choice(len(pairs), most, replace=False))]


def _mask(sequence: FeatureSequence, static: np.ndarray | None, cell: float) -> np.ndarray:
    if static is None or not len(sequence):
        return np.zeros(len(sequence), bool)
    cells = _cells(sequence.points, cell, static.shape)
    return static[cells[:, 0], cells[:, 1]]


def _static_grid(frames, points, pair_of, pairs, matches, params: CalibrationParams, image_size):
    if image_size is None:
        every = np.concatenate([f.points for f in frames if len(f)]) if any(len(f) for f in frames) else None
        if every is None:
            return None, 1.0, {}
        image_size = (float(every[:, 0].max()) + 1, float(every[:, 1].max()) + 1)
    width, height = image_size
    cell = min(width, height) / _GRID
    shape = (int(np.ceil(height / cell)), int(np.ceil(width / cell)))
    if points.size == 0:
        return None, cell, {"static_matches": 0}
    cells = _cells(points, cell, shape)
    flat = cells[:, 0] * shape[1] + cells[:, 1]
    # In how many frame pairs each cell had a static match.
    seen = np.zeros(shape[0] * shape[1])
    np.add.at(seen, np.unique(flat * pairs + pair_of) // pairs, 1)
    static = (seen >= params.static_share * pairs).reshape(shape)
    # A dilation by one cell: a static edge's features sit on both sides of it.
    grown = static.copy()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            grown |= np.roll(np.roll(static, dr, 0), dc, 1) & _inside(shape, dr, dc)
    held = float(np.isin(flat, np.flatnonzero(static.reshape(-1))).sum()) / max(matches, 1)
    stats = {"static_matches": int(points.shape[0]), "static_share_of_matches": held}
    if not static.any() or held > 0.5:
        # Nothing static, or "static" is most of the image: the camera stood still, nothing to mask.
        return None, cell, stats
    return grown, cell, stats


def _inside(shape, dr, dc) -> np.ndarray:
    """Cells whose rolled neighbour did not wrap around the grid's edge."""
    mask = np.ones(shape, bool)
    if dr > 0:
        mask[:dr] = False
    elif dr < 0:
        mask[dr:] = False
    if dc > 0:
        mask[:, :dc] = False
    elif dc < 0:
        mask[:, dc:] = False
    return mask


def _self_nearest(sequence: FeatureSequence) -> np.ndarray:
    """Each feature's L1 distance to the nearest other feature of its own frame (inf when alone)."""
    if len(sequence) < 2:
        return np.full(len(sequence), np.inf)
    d = l1_distances(sequence.descriptors, sequence.descriptors).astype(np.float64)
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def _dp_threshold(frames, related, background, ratio) -> tuple[float, int, list]:
    """The median of the thresholds whose related-against-background AUC of the MRF's standardised DP scores is
    within one standard error of the best (module docstring), the related gap and the curve (every other
    threshold)."""
    thresholds = _THRESHOLDS
    pairs = related + background
    used = sorted({f for pair in pairs for f in pair})
    self_nearest = {f: _self_nearest(frames[f]) for f in used}
    # Features left after suppression at each threshold, per frame: (thresholds, frames) (unused frames 0).
    survivors = np.zeros((thresholds.size, len(frames)), np.int64)
    for f in used:
        survivors[:, f] = (self_nearest[f][None, :] >= thresholds[:, None]).sum(axis=1)
    scores = np.full((thresholds.size, len(pairs)), np.nan)
    mutual = np.zeros(len(pairs))  # threshold-free: mutual ratio-test matches
    for p, (a, b) in enumerate(pairs):
        if not len(frames[a]) or not len(frames[b]):
            continue
        # The later frame is the query, as in the engine.
        distances = l1_distances(np.ascontiguousarray(frames[b].descriptors),
                                 np.ascontiguousarray(frames[a].descriptors))
        _check_lengths(*distances.shape)
        mutual[p] = _mutual(distances, ratio)[0].size
        n, m, k = _matched_per_threshold(distances, self_nearest[b], self_nearest[a], thresholds, *_UNITS)
        scores[:, p] = _ALIGNMENT.s_match * k - _ALIGNMENT.s_gap * (n - k) - _ALIGNMENT.s_gap * (m - k)  # Score(A)
    first = np.array([a for a, _ in pairs])
    second = np.array([b for _, b in pairs])
    gap = second - first
    is_background = np.arange(len(pairs)) >= len(related)
    related_gap = _related_gap(gap[~is_background], mutual[~is_background], mutual[is_background])
    is_related = ~is_background & (gap <= related_gap)
    auc = np.full(thresholds.size, np.nan)
    error = np.full(thresholds.size, np.nan)
    for i in range(thresholds.size):
        z = _standardized(scores[i], survivors[i][first], survivors[i][second], is_background)
        ok = np.isfinite(z)
        auc[i], error[i] = _auc(z[ok & is_related], z[ok & is_background])
    if not np.isfinite(auc).any():
        return float(AlignmentParams().t_match), related_gap, []
    best = int(np.nanargmax(auc))
    # Indistinguishable from the best: within one standard error of the difference (independent errors; at an AUC
    # of 1 the best's own error is 0, and a threshold is tied only through its own).
    tied = thresholds[auc >= auc[best] - np.sqrt(error[best] ** 2 + error ** 2)]
    curve = [{"t_match": float(t), "auc": float(v), "auc_error": float(e), "features": float(c[used].mean())}
             for t, v, e, c in zip(thresholds[::2], auc[::2], error[::2], survivors[::2])]
    # Among them, towards the thesis's scale (t_match 1000, below every plateau measured): their lower quartile.
    return float(np.quantile(tied, 0.25, method="nearest")), related_gap, curve


def _related_gap(gaps, counts, background_counts) -> int:
    """The largest gap g such that at every gap up to g the median pair shares more mutual ratio-test matches than
    the background's median + 3 robust deviations (views that still overlap; at least 1)."""
    if not background_counts.size or not gaps.size:
        return 1
    centre = np.median(background_counts)
    limit = centre + 3 * max(1.4826 * np.median(np.abs(background_counts - centre)), 1.0)  # counts: at least 1
    related = 0
    for g in range(1, int(gaps.max()) + 1):
        at = counts[gaps == g]
        if not at.size or np.median(at) <= limit:
            break
        related = g
    return max(related, 1)


@njit(cache=True)
def _matched_per_threshold(distances, near_query, near_reference, thresholds, s_match, s_miss, s_gap):
    """For each threshold t: the features of each frame left after repeated-texture suppression at t (their nearest
    neighbour in their own frame at least t away) and the DP's matched pairs k on their match matrix (distance < t),
    bearing order kept."""
    count = thresholds.size
    n, m, k = np.zeros(count, np.int64), np.zeros(count, np.int64), np.zeros(count, np.int64)
    for i in range(count):
        t = thresholds[i]
        rows = np.flatnonzero(near_query >= t)
        cols = np.flatnonzero(near_reference >= t)
        n[i], m[i] = rows.size, cols.size
        if rows.size and cols.size:
            match = np.empty((rows.size, cols.size), np.bool_)
            for r in range(rows.size):
                for c in range(cols.size):
                    match[r, c] = distances[rows[r], cols[c]] < t
            k[i] = _align_match_matrix(match, s_match, s_miss, s_gap)[1]
    return n, m, k


def _standardized(scores, counts_a, counts_b, background) -> np.ndarray:
    """z of every score against the background pairs', as the MRF's calibrated potential standardises them (a
    median line in the frames' feature counts); the scores themselves when the background has no spread."""
    ok = background & np.isfinite(scores)
    norm = background_normalization(scores[ok], None, counts_a[ok], counts_b[ok]) if ok.sum() >= 2 else None
    return scores if norm is None else norm.standardize(scores, counts_a, counts_b)


def _auc(positive: np.ndarray, negative: np.ndarray) -> tuple[float, float]:
    """Mann-Whitney AUC (ties count half) and its standard error (Hanley & McNeil 1982, eq. 2)."""
    if not positive.size or not negative.size:
        return np.nan, np.nan
    ranks = rankdata(np.concatenate([positive, negative]))
    n1, n0 = positive.size, negative.size
    auc = (ranks[:n1].sum() - n1 * (n1 + 1) / 2) / (n1 * n0)
    q1, q2 = auc / (2 - auc), 2 * auc * auc / (1 + auc)
    variance = (auc * (1 - auc) + (n1 - 1) * (q1 - auc * auc) + (n0 - 1) * (q2 - auc * auc)) / (n1 * n0)
    return float(auc), float(np.sqrt(max(variance, 0.0)))
