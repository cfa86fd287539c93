"""Image similarity scores between feature sequences (thesis §3.3.2 and the baselines of §3.6).

* :func:`dp_similarity` - cyclic (rotation-invariant) dynamic-programming alignment of two bearing-sorted
  sequences. Which feature pairs may align (``AlignmentParams.match``): in the thesis every pair whose descriptors
  are closer than ``t_match`` in L1 (``"threshold"``); ``"mutual"``: mutual nearest neighbours passing Lowe's ratio
  test both ways (the M^SYM correspondences); ``"threshold_or_mutual"``: either.
* :func:`band_count` - the bearing-band count U (issue 33): the one-to-one matches of a pair that agree on one
  rotation and scale of the horizon; with ``AlignmentParams.band_half_width`` > 0 it replaces the DP's k in the
  thesis score (:func:`pair_count`).
* :func:`sift_match_count` - M^SIFT, features of the query whose nearest neighbour passes Lowe's ratio test.
* :func:`symmetric_match_count` - M^SYM, ratio-test matches found in both directions.
* The bag-of-words TF-IDF score standing in for FAB-MAP lives in :mod:`semloc_core.loopclosure.bow`.

Thesis parameters (§3.6.2) and their signs here: ``t_match = 1000`` (VLFeat's descriptor scale, which OpenCV's
SIFT shares; see :mod:`.features`; our default is 1700, measured), ``s_match = 1`` (reward of a matched pair), ``s_gap = 0.1`` (the thesis writes
-0.1: the cost of leaving a feature unaligned) and ``s_miss = 0`` (cost of aligning two features that do not
match). The DP finds the optimal alignment A under these three values; its score is the thesis's
``Score(A) = s_match*k - s_gap*(n-k) - s_gap*(m-k)`` with k the matched pairs of A.

Why the ratio test (docs/loopclosure.md and its results: loop-dp-ranking). A global threshold has to hold for every feature
of every frame, while the distance between two views of one point grows with viewpoint, exposure and resolution
and the distance to an unrelated feature shrinks in texture-poor, repetitive images: on small, degraded and aliased
sequences no single ``t_match`` serves (aliased corridors through a robot camera: DP AP after inference 0.72 at
1300, 0.83 at 2100, 0.58 at 2500), and the one calibrated from consecutive frames is below what revisits need. The
ratio test compares each candidate with the runner-up in the same frame, so it adapts per feature with no constant;
the DP then keeps the correspondences that agree in bearing order, which the counts M^SIFT and M^SYM cannot check.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from semloc_core.loopclosure.features import FeatureSequence, l1_match_matrix, match_and_squared_l2
from semloc_core.settings import settings

# Scores run in integers: units of 1e-4 (parameters must be multiples of it), packed with the match count k in
# the low bits, so one integer max picks the best score and, among equal scores, the most matches - branch-free,
# 3.5x faster than carrying (score, k) separately in floats.
SCORE_UNIT = 1e-4
_K_BITS = 20
_MAX_PARAM = 1000.0
_MAX_CELLS_SPAN = 100_000  # n + 2m; keeps packed values far from int64 overflow
MatchRule = Literal["threshold", "mutual", "threshold_or_mutual"]
# Grid step of log s for the band count: 2 % of scale moves a feature at 90 deg by 1.8 deg, within the narrowest
# band calibrated on the simulated routes (tau 1.8 deg).
BAND_LOG_SCALE_STEP = 0.02
MAX_LOG_SCALE = 0.36  # the grid's bound whatever L says (scales 0.70..1.43; beyond, a lens change, not a viewpoint)


@settings
class AlignmentParams:
    """Cyclic DP parameters: thesis §3.6.2 values (s_gap and s_miss as positive costs) except the match rule.

    ``band_half_width`` > 0 scores a pair by the bearing-band count U (below) instead of the DP's k; the sequence's
    calibration sets it and ``band_max_log_scale`` (:mod:`.calibration`), the thesis's preset leaves it 0.

    ``match``: ``"threshold"`` is the thesis's ``|f_a - f_b|_1 < t_match``; ``"mutual"`` and
    ``"threshold_or_mutual"`` add the ratio test (module docstring; it needs every feature pair, so the engine's
    word index cannot serve them). ``t_match`` is 1700 on VLFeat's scale rather than the thesis's 1000: measured on
    the real rtabmap samples and the simulated route, 1000 rejects a third to a half of the verified correspondences
    between revisits, 1700 accepts 85-92 % of them (docs/loopclosure.md).
    """

    match: MatchRule = Field("threshold", description="which feature pairs may align: within t_match (thesis), "
                             "mutual ratio-test nearest neighbours, or either")
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe's ratio of the mutual rule (nearest / second nearest, "
                         "L2)")
    t_match: float = Field(1700.0, gt=0, allow_inf_nan=False, description="L1 descriptor match threshold of the "
                           "'threshold' rule (VLFeat scale)")
    s_match: float = Field(1.0, gt=0, le=_MAX_PARAM, description="score of a matched pair")
    s_gap: float = Field(0.1, ge=0, le=_MAX_PARAM, description="cost of a gap (a feature left unaligned)")
    s_miss: float = Field(0.0, ge=0, le=_MAX_PARAM, description="cost of an aligned pair that does not match")
    band_half_width: float = Field(0.0, ge=0, lt=np.pi, allow_inf_nan=False, description="tau (radians) of the "
                                   "bearing-band count that replaces the DP's k; 0: the DP's k (thesis)")
    band_max_log_scale: float = Field(0.0, ge=0, le=MAX_LOG_SCALE, allow_inf_nan=False, description="L: the band "
                                      "count searches scales |log s| <= L")

    def __post_init__(self) -> None:
        for name in ("s_match", "s_gap", "s_miss"):  # scores run in integers of SCORE_UNIT
            value = getattr(self, name)
            if abs(value / SCORE_UNIT - round(value / SCORE_UNIT)) > 1e-6:
                raise ValueError(f"{name}: must be a multiple of {SCORE_UNIT}, got {value}")






@njit(cache=True)
def _cyclic_alignment(match: np.ndarray, s_match: int, s_miss: int, s_gap: int):
    """Optimal cyclic alignment of the query (rows) against the reference (columns); returns (dp value, k).

    The reference is replicated (columns 0..2m-1 read match[:, j % m], Figure 3.1) and the first and last rows are
    free, so the alignment may start and end anywhere in the doubled reference: any rotation of the reference
    aligns, at the price of allowing a reference feature to be matched twice (one-to-many), as in the thesis.
    Each cell holds score * 2^K_BITS + k (score in SCORE_UNITs, k = matched pairs on its best path), so ties in
    score favour more matches; the thesis's score needs k.
    """
    n, m = match.shape
    width = 2 * m
    step_match = (s_match << _K_BITS) + 1
    step_miss = -(s_miss << _K_BITS)
    gap = -(s_gap << _K_BITS)
    prev = np.zeros(width + 1, np.int64)  # row 0: free start anywhere in the doubled reference
    cur = np.zeros(width + 1, np.int64)
    for i in range(1, n + 1):
        row = match[i - 1]
        left = i * gap  # column 0: the first i query features left unaligned
        cur[0] = left
        for half in range(2):
            base = half * m
            for jj in range(m):
                j = base + jj + 1
                diag = prev[j - 1] + (step_match if row[jj] else step_miss)
                up = prev[j] + gap  # query feature i left unaligned
                side = left + gap  # reference feature j left unaligned
                best = diag if diag > up else up
                best = best if best > side else side
                cur[j] = best
                left = best
        prev, cur = cur, prev
    best = prev[0]
    for j in range(1, width + 1):  # free end anywhere in the last row
        if prev[j] > best:
            best = prev[j]
    return best >> _K_BITS, best & ((1 << _K_BITS) - 1)


@njit(cache=True)
def _segment_cost(di: int, dj: int, diagonal: int, gap: int) -> int:
    """Cheapest DP path advancing di query and dj reference features without a match: min(di, dj) diagonal
    (non-match) steps at ``diagonal`` each and |di - dj| gaps."""
    d = di if di < dj else dj
    return d * diagonal + gap * (di + dj - 2 * d)


@njit(cache=True)
def _free_segment_cost(di: int, lo: int, hi: int, diagonal: int, gap: int) -> int:
    """Cheapest such path when the reference advance may be anything in [lo, hi] (the DP's free first and last
    rows). The cost is piecewise linear in dj with its only break at dj = di, so the minimum is at an end or there."""
    best = _segment_cost(di, lo, diagonal, gap)
    other = _segment_cost(di, hi, diagonal, gap)
    if other < best:
        best = other
    if lo < di < hi:
        other = _segment_cost(di, di, diagonal, gap)
        if other < best:
            best = other
    return best


@njit(cache=True)
def _sparse_chain(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap, predecessor):
    """The recursion of :func:`_sparse_cyclic_alignment`: (best packed value, the match cell it ends at (-1: none),
    the cells' DP rows and columns in the order they were visited). ``predecessor``: empty, or one entry per cell
    (2 * count), which then receives each cell's best predecessor cell (-1: entered from the free first row)."""
    diagonal = s_miss if s_miss < 2 * s_gap else 2 * s_gap
    cells = 2 * count
    width = 2 * m
    trace = predecessor.shape[0] > 0
    rows = np.empty(cells, np.int64)
    cols = np.empty(cells, np.int64)
    for e in range(count):  # match (i, j) sits at DP cell (i + 1, j + 1) and, in the replica, (i + 1, j + 1 + m)
        rows[2 * e] = query_rows[e] + 1
        rows[2 * e + 1] = query_rows[e] + 1
        cols[2 * e] = reference_cols[e] + 1
        cols[2 * e + 1] = reference_cols[e] + 1 + m
    order = np.argsort(rows * (width + 1) + cols)
    rows = rows[order]
    cols = cols[order]
    step_match = (s_match << _K_BITS) + 1
    value = np.empty(cells, np.int64)
    best = -(_free_segment_cost(n, 0, width, diagonal, s_gap) << _K_BITS)  # no match at all
    best_end = -1
    row_begin = 0
    for e in range(cells):
        i, j = rows[e], cols[e]
        if e and rows[e - 1] < i:
            row_begin = e  # cells before row_begin lie in earlier rows
        # Enter (i - 1, j - 1) from the free first row, or from an earlier match cell up and to the left.
        v = -(_free_segment_cost(i - 1, 0, j - 1, diagonal, s_gap) << _K_BITS)
        came = -1
        for f in range(row_begin):
            if cols[f] < j:
                w = value[f] - (_segment_cost(i - 1 - rows[f], j - 1 - cols[f], diagonal, s_gap) << _K_BITS)
                if w > v:
                    v = w
                    came = f
        v += step_match
        value[e] = v
        if trace:
            predecessor[e] = came
        end = v - (_free_segment_cost(n - i, 0, width - j, diagonal, s_gap) << _K_BITS)  # free last row
        if end > best:
            best = end
            best_end = e
    return best, best_end, rows, cols


@njit(cache=True)
def _sparse_cyclic_alignment(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap):
    """The optimal cyclic alignment of :func:`_cyclic_alignment` computed from the list of matching pairs only.

    The DP's best path, between two consecutive matched cells, costs what the cheapest unmatched path between them
    costs (``_segment_cost``: diagonal steps cost s_miss, or two gaps when cheaper). So the path is a chain of match
    cells increasing in both coordinates of the doubled reference, and its value is a longest-path recursion over
    the 2 * count match cells: O(count^2) instead of O(n * m), with the same packed (score, k) values and hence the
    same result, ties included (tested against the dense DP).
    """
    best = _sparse_chain(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap, np.empty(0, np.int64))[0]
    return best >> _K_BITS, best & ((1 << _K_BITS) - 1)


@njit(cache=True)
def _traced_alignment(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap):
    """The pairs the optimal cyclic alignment matched: (query rows, reference columns), k of each, in path order."""
    predecessor = np.empty(2 * count, np.int64)
    best, e, rows, cols = _sparse_chain(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap, predecessor)
    k = best & ((1 << _K_BITS) - 1)
    aligned_rows = np.empty(k, np.int64)
    aligned_cols = np.empty(k, np.int64)
    t = k - 1
    while e >= 0 and t >= 0:
        aligned_rows[t] = rows[e] - 1
        aligned_cols[t] = (cols[e] - 1) % m
        e = predecessor[e]
        t -= 1
    return aligned_rows, aligned_cols


@njit(cache=True)
def _align_match_list(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap):
    """(DP value, k) from a list of matching pairs: the sparse recursion when the matches are few (the usual case:
    about 10 of 150 x 150 descriptor pairs match between route frames), the dense DP otherwise. Same result."""
    if 2 * count * count <= n * 2 * m:
        return _sparse_cyclic_alignment(query_rows, reference_cols, count, n, m, s_match, s_miss, s_gap)
    match = np.zeros((n, m), np.bool_)
    for e in range(count):
        match[query_rows[e], reference_cols[e]] = True
    return _cyclic_alignment(match, s_match, s_miss, s_gap)


@njit(cache=True)
def _align_match_matrix(match, s_match, s_miss, s_gap):
    """(DP value, k) of a dense match matrix, through the sparse recursion when it has few matches."""
    n, m = match.shape
    count = 0
    for i in range(n):
        for j in range(m):
            count += match[i, j]
    if 2 * count * count > n * 2 * m:
        return _cyclic_alignment(match, s_match, s_miss, s_gap)
    rows = np.empty(count, np.int64)
    cols = np.empty(count, np.int64)
    e = 0
    for i in range(n):
        for j in range(m):
            if match[i, j]:
                rows[e] = i
                cols[e] = j
                e += 1
    return _sparse_cyclic_alignment(rows, cols, count, n, m, s_match, s_miss, s_gap)


# --- the bearing-band count (issue 33) ------------------------------------------------------------------------
#
# The DP's k counts pairs in consistent bearing *order*; a wide-angle lens, a zoom or a shift of viewpoint keeps the
# order of a place's features but moves them along the horizon by a common rotation and stretches them by a common
# scale. The band count asks the geometric question directly: of all candidate matches (query feature i, reference
# feature j) of a pair, how many agree on one similarity of the horizon, b_q = s * b_r + theta (mod 2 pi)? For each
# scale s = exp(l) on a grid |l| <= L the residuals r_e = wrap(b_q[i_e] - s * b_r[j_e]) of a place's true matches
# fall in one circular band [theta - tau, theta + tau]; unrelated matches spread over the circle. The count is
#
#     U = max_l  max_theta  min(#distinct i, #distinct j  among matches with r_e in the band)
#
# (one-to-one: a feature matched to many in the band counts once, as the DP's alignment is one-to-one). tau and L
# come from the sequence's near pairs (:mod:`.calibration`). Measured on the demo's table top, the simulated worlds
# and RTAB-Map's samples: docs/loopclosure.md, results (loop-band-count).

def band_log_scales(max_log_scale: float) -> np.ndarray:
    """The grid of log s the band count searches: multiples of BAND_LOG_SCALE_STEP with |log s| <= max_log_scale
    (capped at MAX_LOG_SCALE), ascending; 0 (no scale change) is always on it."""
    if not np.isfinite(max_log_scale) or max_log_scale < 0:
        raise ValueError(f"max_log_scale must be finite and >= 0, got {max_log_scale}")
    steps = int(np.floor(min(max_log_scale, MAX_LOG_SCALE) / BAND_LOG_SCALE_STEP + 1e-9))
    return np.arange(-steps, steps + 1) * BAND_LOG_SCALE_STEP


@njit(cache=True)
def _band_count(query_rows, reference_cols, count, query_bearings, reference_bearings, half_width, log_scales,
                residual, order, row_hits, col_hits):
    """U (module comment above) of the first ``count`` matches; O(count) per scale.

    Work arrays (their contents on entry do not matter beyond their sizes): ``residual``, ``order`` hold >= count
    entries; ``row_hits``, ``col_hits`` one per query / reference feature, all zero (left zero on return).
    The scales go from the middle of the grid (s = 1, where most revisits are) up to its end, then from the middle
    down, so a good count is found early and the scales that cannot beat it are skipped. Each scale's residuals are
    re-sorted from its neighbour's order by insertion: a step of 0.02 in log s moves each residual by less than 0.07
    rad, so the order is nearly sorted (only residuals that cross +-pi travel far). A window then slides over the
    sorted circle (each residual as the band's lower edge, the band's end pushed as far as 2 tau allows), keeping
    per-feature hit counts so the distinct counts change by at most one per added or removed match.
    """
    if count == 0:
        return 0
    two_pi = 2.0 * np.pi
    width = 2.0 * half_width
    scales = log_scales.shape[0]
    middle = scales // 2
    middle_order = np.empty(count, np.int64)
    best = 0
    for step in range(scales):
        t = middle + step if middle + step < scales else scales - 1 - step
        if step == 0:
            for e in range(count):
                order[e] = e
        elif t == middle - 1:  # the downward leg starts from the middle scale's order
            for e in range(count):
                order[e] = middle_order[e]
        s = np.exp(log_scales[t])
        for e in range(count):
            o = order[e]
            r = query_bearings[query_rows[o]] - s * reference_bearings[reference_cols[o]]
            # wrap to [-pi, pi) by whole turns: |r| < pi (1 + s) + 2 pi, so a loop of a step or two (cheaper than %)
            while r >= np.pi:
                r -= two_pi
            while r < -np.pi:
                r += two_pi
            residual[e] = r
        if step == 0 and count > 32:  # the first scale: sorted from scratch (a few: by insertion below)
            first = np.argsort(residual[:count])
            sorted_residual = residual[first]
            for e in range(count):
                residual[e] = sorted_residual[e]
                order[e] = first[e]
        for e in range(1, count):  # insertion sort, (residual, order) together (a pass over them when sorted)
            v = residual[e]
            o = order[e]
            f = e - 1
            while f >= 0 and residual[f] > v:
                residual[f + 1] = residual[f]
                order[f + 1] = order[f]
                f -= 1
            residual[f + 1] = v
            order[f + 1] = o
        if step == 0:
            for e in range(count):
                middle_order[e] = order[e]
        # The most matches any band holds at this scale bounds its one-to-one count: skip the scale when that cannot
        # beat the best so far (a scan without the hit counts, a third of the cost).
        most = 0
        end = 0
        for start in range(count):
            if end < start:
                end = start
            while end < start + count:
                x = residual[end] if end < count else residual[end - count] + two_pi
                if x - residual[start] > width:
                    break
                end += 1
            if end - start > most:
                most = end - start
        if most <= best:
            continue
        rows_in = 0
        cols_in = 0
        end = 0  # window: sorted positions [start, end) of the doubled circle (position p >= count: p - count + 2 pi)
        for start in range(count):
            if end < start:
                end = start
            while end < start + count:
                p = end if end < count else end - count
                x = residual[p] if end < count else residual[p] + two_pi
                if x - residual[start] > width:
                    break
                o = order[p]
                row_hits[query_rows[o]] += 1
                if row_hits[query_rows[o]] == 1:
                    rows_in += 1
                col_hits[reference_cols[o]] += 1
                if col_hits[reference_cols[o]] == 1:
                    cols_in += 1
                end += 1
            u = rows_in if rows_in < cols_in else cols_in
            if u > best:
                best = u
            if end > start:  # the lower edge leaves the window
                o = order[start]
                row_hits[query_rows[o]] -= 1
                if row_hits[query_rows[o]] == 0:
                    rows_in -= 1
                col_hits[reference_cols[o]] -= 1
                if col_hits[reference_cols[o]] == 0:
                    cols_in -= 1
        for p in range(start + 1, end):  # what is still in the window (start = count - 1 was removed above)
            o = order[p if p < count else p - count]
            row_hits[query_rows[o]] -= 1
            col_hits[reference_cols[o]] -= 1
    return best


def _check_band(query_bearings, reference_bearings, half_width: float) -> tuple[np.ndarray, np.ndarray]:
    q = np.ascontiguousarray(query_bearings, np.float64).reshape(-1)
    r = np.ascontiguousarray(reference_bearings, np.float64).reshape(-1)
    if not (np.isfinite(q).all() and np.isfinite(r).all()):
        raise ValueError("bearings must be finite")
    if np.abs(q).max(initial=0.0) > np.pi or np.abs(r).max(initial=0.0) > np.pi:
        raise ValueError("bearings must be radians in [-pi, pi]")
    if not np.isfinite(half_width) or half_width <= 0 or half_width >= np.pi:
        raise ValueError(f"band half-width tau must be in (0, pi), got {half_width}")
    return q, r


def band_count(query_rows, reference_cols, query_bearings, reference_bearings, half_width: float,
               log_scales: np.ndarray) -> int:
    """U of the matches (query_rows[e], reference_cols[e]) between frames of these bearings (radians): the most
    one-to-one matches whose residuals b_q - s * b_r fall in one circular band of half-width ``half_width`` (tau),
    over the scales exp(``log_scales``) (:func:`band_log_scales`)."""
    q, r = _check_band(query_bearings, reference_bearings, half_width)
    rows = np.ascontiguousarray(query_rows, np.int64).reshape(-1)
    cols = np.ascontiguousarray(reference_cols, np.int64).reshape(-1)
    if rows.size != cols.size:
        raise ValueError(f"{rows.size} query rows but {cols.size} reference columns")
    if rows.size and (rows.min() < 0 or rows.max() >= q.size or cols.min() < 0 or cols.max() >= r.size):
        raise ValueError("a match indexes a feature outside its frame")
    scales = np.ascontiguousarray(log_scales, np.float64).reshape(-1)
    if scales.size == 0 or not np.isfinite(scales).all() or np.any(np.diff(scales) < 0):
        raise ValueError("log_scales must be finite, ascending and not empty")
    k = rows.size
    return int(_band_count(rows, cols, k, q, r, float(half_width), scales, np.empty(k), np.empty(k, np.int64),
                           np.zeros(q.size, np.int64), np.zeros(r.size, np.int64)))


def _units(value: float) -> int:
    return int(round(value / SCORE_UNIT))


def _check_lengths(n: int, m: int) -> None:
    if n + 2 * m > _MAX_CELLS_SPAN or n >= 1 << _K_BITS:
        raise ValueError(f"sequences of {n} and {m} features are too long for the packed DP")


def descriptor_matches(query: np.ndarray, reference: np.ndarray, t_match: float) -> np.ndarray:
    """Boolean (n, m) matrix of the uint8 descriptor pairs whose L1 distance is below ``t_match``."""
    if len(query) == 0 or len(reference) == 0:
        return np.zeros((len(query), len(reference)), np.bool_)
    return l1_match_matrix(query, reference, float(t_match))


def alignment_matches(query: np.ndarray, reference: np.ndarray, params: AlignmentParams) -> np.ndarray:
    """Boolean (n, m) matrix of the uint8 descriptor pairs the DP may align, under ``params.match``."""
    if params.match == "threshold":
        return descriptor_matches(query, reference, params.t_match)
    if len(query) == 0 or len(reference) == 0:
        return np.zeros((len(query), len(reference)), np.bool_)
    match, d2 = match_and_squared_l2(query, reference, float(params.t_match))
    return _rule_matches(match, d2, params)


def _rule_matches(match: np.ndarray, d2: np.ndarray, params: AlignmentParams, forward=None, backward=None):
    """The match matrix of ``params.match`` from the threshold's ``match`` and the squared L2 distances ``d2``
    (``forward``, ``backward``: the ratio-test matches at ``params.ratio`` each way, when already known)."""
    if params.match == "threshold":
        return match
    mutual = np.zeros(d2.shape, np.bool_)
    if d2.shape[0] >= 2 and d2.shape[1] >= 2:
        forward = _ratio_matches(d2, float(params.ratio)) if forward is None else forward
        backward = _ratio_matches(np.ascontiguousarray(d2.T), float(params.ratio)) if backward is None else backward
        rows = np.flatnonzero(forward >= 0)
        rows = rows[backward[forward[rows]] == rows]
        mutual[rows, forward[rows]] = True
    return mutual if params.match == "mutual" else match | mutual


def alignment_score(n: int, m: int, k: int, params: AlignmentParams) -> float:
    """Score(A) = s_match*k - s_gap*(n-k) - s_gap*(m-k) (§3.3.2)."""
    return params.s_match * k - params.s_gap * (n - k) - params.s_gap * (m - k)


def cyclic_alignment(match: np.ndarray, params: AlignmentParams = AlignmentParams()) -> tuple[float, int]:
    """(DP value, matched pairs k) of the optimal cyclic alignment for a precomputed match matrix."""
    match = np.ascontiguousarray(match, dtype=np.bool_)
    if match.ndim != 2:
        raise ValueError(f"match matrix must be 2-D, got shape {match.shape}")
    n, m = match.shape
    if n == 0 or m == 0:
        return -params.s_gap * (n + m), 0
    _check_lengths(n, m)
    value, k = _align_match_matrix(match, _units(params.s_match), _units(params.s_miss), _units(params.s_gap))
    return float(value) * SCORE_UNIT, int(k)


def aligned_pairs(match: np.ndarray, params: AlignmentParams = AlignmentParams()) -> tuple[np.ndarray, np.ndarray]:
    """The (query, reference) feature pairs the optimal cyclic alignment of a match matrix matched (k of them)."""
    match = np.ascontiguousarray(match, dtype=np.bool_)
    n, m = match.shape
    if n == 0 or m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _check_lengths(n, m)
    rows, cols = (a.astype(np.int64) for a in np.nonzero(match))
    return _traced_alignment(rows, cols, rows.size, n, m, _units(params.s_match), _units(params.s_miss),
                             _units(params.s_gap))


def pair_count(match: np.ndarray, query_bearings, reference_bearings,
               params: AlignmentParams = AlignmentParams()) -> int:
    """The count k of the thesis score of a pair with this match matrix: the bearing-band count U of its matches
    when ``params.band_half_width`` > 0, else the DP's matched pairs (§3.3.2)."""
    if params.band_half_width <= 0:
        return cyclic_alignment(match, params)[1]
    rows, cols = np.nonzero(np.asarray(match, np.bool_))
    if len(query_bearings) != match.shape[0] or len(reference_bearings) != match.shape[1]:
        raise ValueError(f"a ({match.shape[0]}, {match.shape[1]}) match matrix needs as many bearings, got "
                         f"{len(query_bearings)} and {len(reference_bearings)}")
    return band_count(rows, cols, query_bearings, reference_bearings, params.band_half_width,
                      band_log_scales(params.band_max_log_scale))


def dp_similarity(
    query: FeatureSequence, reference: FeatureSequence, params: AlignmentParams = AlignmentParams()
) -> float:
    """M_ij: the thesis score of the optimal cyclic alignment of two feature sequences (§3.3.2).

    The query's sequence is aligned against the replicated reference, so the score is invariant to any rotation of
    the reference (and, up to the one-to-many corner case, of the query).
    """
    k = pair_count(alignment_matches(query.descriptors, reference.descriptors, params), query.bearings,
                   reference.bearings, params)
    return alignment_score(len(query), len(reference), k, params)


# --- baselines (§3.6): SIFT ratio-test matches ------------------------------------------------------------------


def squared_l2_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) exact squared Euclidean distances between uint8 descriptor sets."""
    return match_and_squared_l2(np.ascontiguousarray(a), np.ascontiguousarray(b), 0.0)[1]


@njit(cache=True)
def _ratio_matches(d2: np.ndarray, ratio: float) -> np.ndarray:
    """For each row, the column of its nearest neighbour if it passes Lowe's ratio test, else -1."""
    n, m = d2.shape
    out = np.full(n, -1, np.int64)
    if m < 2:
        return out
    r2 = ratio * ratio
    for i in range(n):
        best, second, arg = np.inf, np.inf, -1
        for j in range(m):
            v = d2[i, j]
            if v < best:
                second = best
                best = v
                arg = j
            elif v < second:
                second = v
        if best < r2 * second:
            out[i] = arg
    return out


def _check_ratio(ratio: float) -> None:
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"ratio must be in (0, 1], got {ratio}")


def ratio_test_matches(query: FeatureSequence, reference: FeatureSequence, ratio: float = 0.8) -> np.ndarray:
    """Index into ``reference`` of each query feature's ratio-test match, -1 where it has none."""
    _check_ratio(ratio)
    if len(query) == 0:
        return np.zeros(0, np.int64)
    if len(reference) < 2:
        return np.full(len(query), -1, np.int64)
    return _ratio_matches(squared_l2_distances(query.descriptors, reference.descriptors), float(ratio))


def sift_match_count(query: FeatureSequence, reference: FeatureSequence, ratio: float = 0.8) -> int:
    """M^SIFT: number of query features with a ratio-test match in the reference (Lowe, 2004)."""
    return int(np.count_nonzero(ratio_test_matches(query, reference, ratio) >= 0))


def symmetric_match_count(query: FeatureSequence, reference: FeatureSequence, ratio: float = 0.8) -> int:
    """M^SYM: ratio-test matches found from query to reference and from reference to query."""
    _check_ratio(ratio)
    if len(query) < 2 or len(reference) < 2:
        return 0
    d2 = squared_l2_distances(query.descriptors, reference.descriptors)
    forward = _ratio_matches(d2, float(ratio))
    backward = _ratio_matches(np.ascontiguousarray(d2.T), float(ratio))
    hits = forward >= 0
    return int(np.count_nonzero(backward[forward[hits]] == np.flatnonzero(hits)))


@dataclass(frozen=True)
class PairScores:
    dp: float
    sift: int
    sym: int


def pair_scores(
    query: FeatureSequence,
    reference: FeatureSequence,
    params: AlignmentParams = AlignmentParams(),
    ratio: float = 0.8,
) -> PairScores:
    """The DP score and both SIFT baselines of one pair, from one pass over the descriptor pairs."""
    _check_ratio(ratio)
    if len(query) == 0 or len(reference) == 0:
        return PairScores(alignment_score(len(query), len(reference), 0, params), 0, 0)
    match, d2 = match_and_squared_l2(query.descriptors, reference.descriptors, float(params.t_match))
    forward = _ratio_matches(d2, float(ratio))
    backward = _ratio_matches(np.ascontiguousarray(d2.T), float(ratio))
    same = params.ratio == ratio
    k = pair_count(_rule_matches(match, d2, params, *((forward, backward) if same else ())), query.bearings,
                   reference.bearings, params)
    dp = alignment_score(len(query), len(reference), k, params)
    if len(query) < 2 or len(reference) < 2:
        return PairScores(dp, 0, 0)
    hits = forward >= 0
    sym = int(np.count_nonzero(backward[forward[hits]] == np.flatnonzero(hits)))
    return PairScores(dp, int(np.count_nonzero(hits)), sym)
