"""Self-calibration of the image-dependent constants from the sequence itself, without ground truth (issue 33).

The DP's match threshold ``t_match`` has to separate the descriptor distances of corresponding features from the
distances a feature of an unrelated frame can reach by chance, and both depend on the images (resolution, blur,
lens, texture). Both are observable without ground truth:

* **Correspondences**: mutual nearest neighbours that pass Lowe's ratio test between frames 1..``gap`` apart
  (consecutive frames see the same place).
* **Chance**: the distance from each feature to its nearest neighbour in a frame at least ``min_separation``
  frames away (mostly another place; the few loops among them only make the estimate cautious).

``t_match`` is the threshold that best separates a pair of frames of the same place from a pair of unrelated frames
by the count the DP sees: with ``n`` features per frame, a same-place pair gains ``m(t)`` true matches (the
correspondences accepted at t), an unrelated pair counts ``n F(t)`` chance matches (F the share of chance distances
below t), Poisson, with a floor of one match:

    t_match = argmax_t  m(t) / sqrt(n F(t) + 1)

Repeated texture (features with a match inside their own frame, §3.6.4) is suppressed at the threshold being
tried, as the DP will see it (``repeated_threshold`` = ``t_match``).

**Static regions.** A lens rim, the robot's own body or an overlay give features at the same pixel in every frame,
which match between any two frames and carry no place information. Correspondences between consecutive frames
that moved less than ``static_px`` pixels are collected in a grid; a cell where such matches occur in at least
``static_share`` of the frame pairs (and make most of the cell's matches) is static, and features there are masked.
If the static cells would hold most of all matches the camera has not moved and nothing is masked.

**The bearing band** (issue 33; the count U of :mod:`.similarity`). Near frames see one place, so the DP's aligned
pairs between frames 1..``gap`` apart show how far bearings of one place scatter about a common rotation and scale
of the horizon. First the rotation rule: tau_rot, the 95th percentile of the aligned pairs' shifts b_q - b_r about
their circular median. Then each near pair with at least 5 aligned pairs gets its best scale (the log s of the grid
whose band of half-width tau_rot holds most of them; the mean of ties). L is the 95th percentile of |best log s|, and
the band's half-width tau is the 95th percentile of the residuals b_q - s b_r about their circular median at that
scale. Too few aligned near pairs leave tau = 0: the DP's k.

The engine calibrates once its first ``frames`` frames are in (before the window lets it align anything, so every
score it computes uses the calibrated threshold); the batch evaluation calibrates on the whole sequence.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from semloc_core.geometry import wrap_angle
from semloc_core.loopclosure.features import FeatureSequence, l1_distances, suppress_repeated
from semloc_core.loopclosure.similarity import (MAX_LOG_SCALE, AlignmentParams, aligned_pairs, alignment_matches,
                                                band_count, band_log_scales)

CALIBRATION_MODES = ("sequence", "fixed")
_GRID = 24  # static-region grid cells across the shorter image side
_THRESHOLDS = np.arange(600.0, 3601.0, 50.0)  # candidate t_match (VLFeat scale: L1, descriptors of L2 norm 512)
_BAND_QUANTILE = 0.95  # the bearing band holds this share of the near pairs' aligned pairs
_BAND_MIN_ALIGNED = 3  # aligned pairs a near pair needs to show a shift about its median ...
_SCALE_MIN_ALIGNED = 5  # ... and to show a scale
_MIN_HALF_WIDTH = np.radians(0.1)  # bearings are not exact: a sequence whose near frames agree perfectly keeps a band


@dataclass(frozen=True)
class CalibrationParams:
    """``mode``: ``"sequence"`` derives t_match, the repeated-texture threshold and the static mask from the
    sequence; ``"fixed"`` keeps the configured constants (the thesis's preset). ``frames``: frames the engine
    calibrates on; ``gap``: frames 1..gap apart give the correspondences; ``min_separation``: frames at least that
    far apart give the chance distances; ``ratio``: Lowe's ratio test; ``static_px``, ``static_share``: the static
    regions (see the module)."""

    mode: str = "sequence"
    frames: int = 30
    gap: int = 2
    min_separation: int = 15
    pairs: int = 200
    ratio: float = 0.8
    static_px: float = 1.0
    static_share: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in CALIBRATION_MODES:
            raise ValueError(f"calibration mode must be one of {CALIBRATION_MODES}, got {self.mode!r}")
        if self.frames < 4 or self.gap < 1 or self.min_separation < 2 or self.pairs < 1:
            raise ValueError("calibration needs frames >= 4, gap >= 1, min_separation >= 2, pairs >= 1")
        if not 0 < self.ratio <= 1 or self.static_px <= 0 or not 0 < self.static_share <= 1:
            raise ValueError("calibration needs 0 < ratio <= 1, static_px > 0, 0 < static_share <= 1")


@dataclass(frozen=True, eq=False)
class Calibration:
    """What the sequence says: the match threshold, the repeated-texture threshold, the static cells (a boolean
    grid over each camera's image, ``cell`` pixels per cell; None: nothing static), the statistics behind them and
    the bearing band (half-width tau in radians, 0: none; scale bound L)."""

    t_match: float
    repeated_threshold: float
    cell: float = 1.0
    static: np.ndarray | None = None
    frames: int = 0
    stats: dict = field(default_factory=dict)
    band_half_width: float = 0.0
    band_max_log_scale: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.band_half_width < np.pi and 0 <= self.band_max_log_scale <= MAX_LOG_SCALE):
            raise ValueError(f"calibration: band tau {self.band_half_width} must be in [0, pi), L "
                             f"{self.band_max_log_scale} in [0, {MAX_LOG_SCALE}]")

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
                "static_area": float(self.static.mean()) if self.static is not None else 0.0,
                "band_half_width_deg": float(np.degrees(self.band_half_width)),
                "band_max_log_scale": self.band_max_log_scale,
                "band_scales": int(band_log_scales(self.band_max_log_scale).size) if self.band_half_width else 0,
                **self.stats}

    def to_array(self) -> np.ndarray:
        """Flat float64: t_match, repeated threshold, cell, frames, band tau, band L, grid rows, grid cols, then the
        grid."""
        grid = self.static if self.static is not None else np.zeros((0, 0), bool)
        return np.concatenate([[self.t_match, self.repeated_threshold, self.cell, self.frames, self.band_half_width,
                                self.band_max_log_scale, *grid.shape], grid.reshape(-1).astype(np.float64)])

    @classmethod
    def from_array(cls, values) -> "Calibration":
        v = np.asarray(values, np.float64).reshape(-1)
        if v.size < 8 or not np.isfinite(v[:8]).all():
            raise ValueError("calibration state too short or not finite")
        rows, cols = int(v[6]), int(v[7])
        if rows < 0 or cols < 0 or v.size != 8 + rows * cols:
            raise ValueError("calibration state: bad static grid")
        grid = v[8:].reshape(rows, cols) > 0.5 if rows * cols else None
        return cls(float(v[0]), float(v[1]), float(v[2]), grid, int(v[3]), band_half_width=float(v[4]),
                   band_max_log_scale=float(v[5]))


def _distances(query: FeatureSequence, reference: FeatureSequence) -> np.ndarray:
    return l1_distances(np.ascontiguousarray(query.descriptors),
                        np.ascontiguousarray(reference.descriptors)).astype(np.float64)


def _cells(points: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    rc = np.floor(np.asarray(points, np.float64)[:, ::-1] / cell).astype(np.int64)
    return np.clip(rc, 0, np.array(shape) - 1)


def mutual_matches(query: FeatureSequence, reference: FeatureSequence, ratio: float):
    """(query index, reference index, L1 distance) of mutual nearest neighbours (L1) passing the ratio test both
    ways."""
    if len(query) < 2 or len(reference) < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    d = _distances(query, reference)
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
              image_size: tuple[int, int] | None = None,
              alignment: AlignmentParams = AlignmentParams()) -> Calibration | None:
    """The calibration of a sequence of (unsuppressed) feature sequences; None when they are too few or too poor to
    say anything (fewer than ``params.gap + 2`` frames or no correspondence at all).

    ``image_size`` (width, height) of the (single) camera, for the static grid (default: the extent of the
    features' pixels); ``alignment``: the DP whose aligned near pairs give the bearing band (its t_match is the
    calibrated one)."""
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
    # Same-place correspondences again, on the frames as the DP will see them (static regions masked).
    correspondences = []
    for a in range(n):
        for g in range(1, params.gap + 1):
            if a + g < n:
                correspondences.append((a + g, a, *mutual_matches(masked[a + g], masked[a], params.ratio)))
    # Chance: nearest neighbours in frames far apart.
    separation = min(params.min_separation, max(2, n // 2))  # a short calibration run: half of it apart
    far = [(a, b) for b in range(n) for a in range(b - separation + 1)]
    if not far:
        return None
    chosen = [far[k] for k in rng.choice(len(far), min(params.pairs, len(far)), replace=False)]
    self_nearest = [_self_nearest(f) for f in masked]
    t, curve = _best_threshold(masked, correspondences, chosen, self_nearest)
    stats = {"correspondences": int(sum(c[4].size for c in correspondences)),
             "correspondence_distance_median": float(np.median(np.concatenate([c[4] for c in correspondences])))
             if any(c[4].size for c in correspondences) else None,
             "chance_pairs": len(chosen), "criterion": curve, **static_stats}
    found = Calibration(t, t, cell, static, n, stats)
    tau, bound, band_stats = _bearing_band([found.apply(f) for f in frames], params.gap,
                                           replace(alignment, t_match=t, band_half_width=0.0))
    stats.update(band_stats)
    return Calibration(t, t, cell, static, n, stats, tau, bound)


def _about_circular_median(angles: np.ndarray) -> np.ndarray:
    """|angle - m| (wrapped) with m the circular median: the angle of the set closest to all others in sum."""
    spread = np.abs(wrap_angle(angles[:, None] - angles[None, :])).sum(axis=1)
    return np.abs(wrap_angle(angles - angles[np.argmin(spread)]))


def _bearing_band(frames: Sequence[FeatureSequence], gap: int, alignment: AlignmentParams):
    """(tau, L, stats) of the bearing band from the DP's aligned pairs between frames 1..gap apart (module
    docstring); tau = 0 when too few near pairs align."""
    aligned = []
    for b in range(1, len(frames)):
        for a in range(max(0, b - gap), b):
            query, reference = frames[b], frames[a]
            rows, cols = aligned_pairs(alignment_matches(query.descriptors, reference.descriptors, alignment),
                                       alignment)
            if rows.size >= _BAND_MIN_ALIGNED:
                aligned.append((query.bearings[rows].astype(np.float64), reference.bearings[cols].astype(np.float64)))
    scale_pairs = [(q, r) for q, r in aligned if q.size >= _SCALE_MIN_ALIGNED]
    if not scale_pairs:
        return 0.0, 0.0, {"band": f"fewer than {_SCALE_MIN_ALIGNED} aligned pairs between near frames: the DP's k"}
    tau_rotation = max(float(np.quantile(np.concatenate([_about_circular_median(q - r) for q, r in aligned]),
                                         _BAND_QUANTILE)), _MIN_HALF_WIDTH)
    grid = band_log_scales(MAX_LOG_SCALE)
    best_scales, residuals = [], []
    for q, r in scale_pairs:
        index = np.arange(q.size)
        counts = np.array([band_count(index, index, q, r, tau_rotation, grid[t:t + 1]) for t in range(grid.size)])
        best = float(grid[counts == counts.max()].mean())
        best_scales.append(best)
        residuals.append(_about_circular_median(wrap_angle(q - np.exp(best) * r)))
    tau = max(float(np.quantile(np.concatenate(residuals), _BAND_QUANTILE)), _MIN_HALF_WIDTH)
    bound = float(min(np.quantile(np.abs(best_scales), _BAND_QUANTILE), MAX_LOG_SCALE))
    return tau, bound, {"band_near_pairs": len(scale_pairs),
                        "band_rotation_half_width_deg": float(np.degrees(tau_rotation))}


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


def _best_threshold(frames, correspondences, chance_pairs, self_nearest) -> tuple[float, list]:
    """argmax_t m(t) / sqrt(n(t) F(t) + 1) with repeated texture suppressed at t (module docstring)."""
    thresholds = _THRESHOLDS
    # True matches accepted at t among features that survive suppression at t (both ends).
    true_counts = np.zeros(thresholds.size)
    for b, a, q, r, dist in correspondences:
        survive_q, survive_r = self_nearest[b][q], self_nearest[a][r]
        keep = (dist[:, None] < thresholds) & (survive_q[:, None] >= thresholds) & (survive_r[:, None] >= thresholds)
        true_counts += keep.sum(axis=0)
    true_counts /= max(len(correspondences), 1)
    # Chance matches: per query feature surviving at t, whether its nearest surviving reference feature is within t.
    chance = np.zeros(thresholds.size)
    features = np.zeros(thresholds.size)
    for a, b in chance_pairs:
        query, reference = frames[b], frames[a]
        if not len(query) or not len(reference):
            continue
        d = _distances(query, reference)
        # Nearest reference feature among those surviving at t: for each t, min over survivors.
        order = np.argsort(self_nearest[a])[::-1]  # survivors at t are a prefix of this order (largest first)
        d_sorted = d[:, order]
        survivors = np.searchsorted(-self_nearest[a][order], -thresholds, side="right")  # how many have >= t
        running = np.minimum.accumulate(d_sorted, axis=1)
        nearest = np.where(survivors > 0, running[:, np.maximum(survivors - 1, 0)], np.inf)  # (q, t)
        alive = self_nearest[b][:, None] >= thresholds
        chance += np.sum(alive & (nearest < thresholds), axis=0)
        features += alive.sum(axis=0)
    pairs = max(len(chance_pairs), 1)
    chance_matches = chance / pairs  # n(t) F(t): chance matches of an unrelated pair
    criterion = true_counts / np.sqrt(chance_matches + 1.0)
    best = int(np.argmax(criterion))
    curve = [{"t_match": float(t), "true_matches": float(m), "chance_matches": float(c), "features": float(f / pairs)}
             for t, m, c, f in zip(thresholds[::4], true_counts[::4], chance_matches[::4], features[::4])]
    return float(thresholds[best]), curve
