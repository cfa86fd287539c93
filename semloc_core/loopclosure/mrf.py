"""Loop-closure detection with an MRF on the similarity matrix (thesis §3.4).

The lattice H has one binary node per image pair (i, j), i earlier than j: 1 = the two images close a loop. Node
potentials come from the normalised similarity p = M_ij / F: phi(1) = p, phi(0) = 1 - p. Each node is tied to its 8
neighbours (i +- 1, j +- 1) by psi(0,0) = psi(1,1) = alpha * G(M_ij, M_kl), psi(0,1) = psi(1,0) = 1, with
G(x, y) = exp(-(x - y)^2 / sigma^2), sigma = 0.05 F (eqs. 3.1-3.2). Generalised max-product belief propagation on
the node/edge cluster graph, damped (lambda = 0.5) for 20 iterations, gives max-marginals whose argmax is D.

Implementation notes.

* Binary max-product runs in the log domain with one number per message: mu = log m(1) - log m(0). For pairwise
  factors the cluster-graph schedule (node clusters, then edge clusters) is the synchronous pairwise update
  mu_{c->e} = max(0, a + J) - max(J, a), with a the log-odds at c without e's message and J = log(alpha G).
  Damping mixes the new log message with the previous one.
* ``coupling="thesis"`` uses J = log(alpha G) as written: when neighbouring scores differ by more than
  sigma * sqrt(ln alpha) the factor *rewards* different labels. ``coupling="attractive"`` (the default, see
  docs/loopclosure.md for the measurements behind it) uses J = max(0, log(alpha G)): similar neighbours still pull
  towards the same label, dissimilar ones are left independent instead of being pushed apart.
* Cells with p = 0 (a score at or below the offset, the window |i - j| <= w, the lower triangle, and pairs that
  were never scored) have phi(1) = 0: their label is fixed at 0, so the message they send is the constant -J(p_c, 0)
  whatever they receive. Only cells with p > 0 are stored ("live"), which makes the lattice sparse when only
  retrieved candidates are scored.
* ``phi(0) = 0`` (p = 1, the maximum of M) would be an infinite log-odds: p is clipped to ``1 - 1e-6``.

Two drivers share one numba kernel: :func:`infer_batch` (every cell, zero messages, 20 synchronous iterations:
the thesis) and :class:`IncrementalMrf`, which adds one column per new frame and re-runs the iterations only on the
last ``band`` columns, warm-started from the stored messages, holding the messages older cells send fixed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numba import njit
from pydantic import Field

from semloc_core.settings import settings

from semloc_core.loopclosure.storage import MemoryLog, RecentRecords

# Neighbour directions (d_row, d_col); direction 7 - d is the opposite of d.
DIRECTIONS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64)
_D_ROW = np.ascontiguousarray(DIRECTIONS[:, 0])
_D_COL = np.ascontiguousarray(DIRECTIONS[:, 1])
_MAX_P = 1.0 - 1e-6
Coupling = Literal["attractive", "thesis"]
COUPLINGS = get_args(Coupling)


Potential = Literal["calibrated", "thesis"]
Background = Literal["features", "features_spread", "global"]


@settings
class MrfParams:
    """MRF parameters. Thesis §3.6.2: sigma = 0.05 F, alpha = 2, damping 0.5, 20 iterations.

    ``potential``: how a score becomes the node potential.

    * ``"thesis"``: phi(1) = p = (M - offset) / (F - offset) clipped to [0, 1] (the thesis's M / F with offset 0);
      ``sigma`` is a fraction of F. Scores at or below the offset are ruled out (phi(1) = 0).
    * ``"calibrated"``: log phi(1)/phi(0) = kappa * (z - z0), z = (M - m) / s the score in robust standard
      deviations of the background (m, s: median and 1.4826 MAD of the scores of unrelated pairs); ``sigma`` is in
      the same units. A pair nobody scored counts as a background pair (z = 0).

    ``background`` (calibrated potential): where m and s come from.

    * ``"global"``: one median and deviation for all pairs.
    * ``"features"`` (default; the DP's): a frame's own median, modelled as a linear function of its feature count
      n (fitted, robustly, to the background scores; :func:`background_normalization`); a pair (i, j) is compared
      with m = (m(n_i) + m(n_j)) / 2, in units of one deviation of the scores about it. Every score depends on the
      feature counts - the DP's by construction (each unaligned feature costs s_gap: a frame's median score falls by
      0.09 per feature, r = -0.99, on the real samples and both route seeds alike) - so one global background puts
      the pairs of feature-poor frames above those of feature-rich ones. Measured in docs/loopclosure.md: it raises
      the AP of every score, raw and after inference, on all three data sets. Without feature counts (or when all
      frames have the same count) it is the global background.
    * ``"features_spread"``: the deviation too is a line in the count, and a pair is compared in units of
      sqrt(s(n_i) s(n_j)): for counts of matches, whose spread grows with the features there are to match (the
      evaluation's M^SIFT, M^SYM and BoW). The count moves a DP score's centre, not its spread (gap costs); a
      deviation line fitted to the DP's scores followed the pairs of feature-rich frames down where most pairs see
      the same scene (the demo's table top: 13.9 to 8.5 over 252-450 features), which put their near misses up to
      1.6 times as far above the background as the same score of a feature-poor pair (DP AP after inference there
      0.861, one deviation 0.908; real samples 0.837 / 0.841; docs/results/2026-12-05-loopclosure-decisions.md).
    * ``"global"``: one median and deviation for all pairs.

    ``coupling``: see the module docstring.
    """

    potential: Potential = Field("calibrated", description="MRF node potential")
    z0: float = Field(2.5, allow_inf_nan=False, description="calibrated potential: even odds at z0 background "
                      "deviations")
    kappa: float = Field(2.0, gt=0, allow_inf_nan=False, description="calibrated potential: log-odds per background "
                         "deviation")
    offset: float = Field(0.0, allow_inf_nan=False, description="thesis potential: the DP score mapped to phi(1) = 0")
    sigma: float | None = Field(None, gt=0, description="edge sigma: a fraction of F (thesis potential; default "
                                "0.05) or background deviations (calibrated; default 5)")
    alpha: float = Field(2.0, ge=1, description="edge weight alpha")
    damping: float = Field(0.5, ge=0, lt=1, description="loopy BP message damping")
    iterations: int = Field(20, ge=1, description="loopy BP iterations")
    coupling: Coupling = Field("attractive", description="MRF edge potential")
    background: Background = Field("features", description="calibrated potential: background median per feature count "
                            "of the two frames and one deviation ('features'), deviation per count too "
                            "('features_spread'), or one of each for all pairs ('global')")

    def __post_init__(self) -> None:
        if self.sigma is None:
            object.__setattr__(self, "sigma", 0.05 if self.potential == "thesis" else 5.0)

    @property
    def attractive(self) -> bool:
        return self.coupling == "attractive"

    @property
    def prior_theta(self) -> float:
        """Log-odds of a pair outside the window that was never scored: ruled out (thesis) or background."""
        return -np.inf if self.potential == "thesis" else -self.kappa * self.z0


@dataclass(frozen=True)
class Normalization:
    """Where scores sit: thesis - p = (M - location) / scale (location = offset, scale = F - offset);
    calibrated - z = (M - m) / s, the background's median m and robust deviation s. These may depend on the two
    frames' feature counts (``MrfParams.background = "features"``): a frame with n features has median
    ``location + location_slope * n`` and deviation ``scale + scale_slope * n`` (at least ``min_scale``); a pair
    is compared with the mean of its frames' medians in units of the geometric mean of their deviations."""

    location: float
    scale: float
    location_slope: float = 0.0
    scale_slope: float = 0.0
    min_scale: float | None = None

    def __post_init__(self) -> None:
        if self.min_scale is None:
            object.__setattr__(self, "min_scale", float(self.scale) if not self.scale_slope else 0.5 * self.scale)
        values = (self.location, self.scale, self.location_slope, self.scale_slope, self.min_scale)
        # Per feature count the deviation line may cross zero below the counts it was fitted on (min_scale floors
        # it); one global deviation must be positive itself.
        positive = self.min_scale > 0 and (self.scale > 0 or self.per_count)
        if not (all(np.isfinite(v) for v in values) and positive):
            raise ValueError(f"normalization needs finite values and positive scales, got {self}")

    @property
    def per_count(self) -> bool:
        return bool(self.location_slope or self.scale_slope)

    def frame_scale(self, counts) -> np.ndarray:
        return np.maximum(self.scale + self.scale_slope * np.asarray(counts, np.float64), self.min_scale)

    def standardize(self, scores, counts_a=None, counts_b=None) -> np.ndarray:
        """z of each score of a pair of frames with ``counts_a`` and ``counts_b`` features."""
        scores = np.asarray(scores, dtype=np.float64)
        if not self.per_count:
            return (scores - self.location) / self.scale
        if counts_a is None or counts_b is None:
            raise ValueError("this normalization depends on the frames' feature counts: give them")
        a = np.asarray(counts_a, np.float64)
        b = np.asarray(counts_b, np.float64)
        location = self.location + 0.5 * self.location_slope * (a + b)
        return (scores - location) / np.sqrt(self.frame_scale(a) * self.frame_scale(b))

    def to_array(self) -> np.ndarray:
        return np.array([self.location, self.scale, self.location_slope, self.scale_slope, self.min_scale])

    @classmethod
    def from_array(cls, values) -> "Normalization | None":
        values = np.asarray(values, np.float64).reshape(-1)
        if values.size == 0:
            return None
        if values.size == 2:  # location and scale only
            return cls(float(values[0]), float(values[1]))
        return cls(*(float(v) for v in values[:5]))


def background_normalization(scores, weights=None, counts_a=None, counts_b=None,
                             spread_per_count: bool = False) -> Normalization | None:
    """Median and 1.4826 MAD of scores of (mostly) unrelated pairs; None without enough spread.

    ``weights``: how many pairs each score stands for (a sample drawn from a column of many pairs counts for all
    of them), so the statistics are those of every pair the sample came from; equal weights give np.median's.
    ``counts_a``, ``counts_b``: the feature counts of each pair's two frames. Given, the median of a frame's scores
    is fitted as a line in its count: every score is a sample of both its frames' backgrounds, the median line is
    the weighted least-absolute-deviations line through (count, score); the deviation is 1.4826 times the weighted
    median of the pairs' |score - mean of their frames' medians| (``MrfParams.background = "features"``), or, with
    ``spread_per_count``, a line too, the one through (count, 1.4826 |score - median line|) ("features_spread").
    With a single count this is the global median and MAD."""
    values = np.asarray(scores, dtype=np.float64).reshape(-1)
    w = np.ones(values.size) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != values.shape or np.any(~np.isfinite(w)) or np.any(w <= 0):
        raise ValueError("one positive finite weight per score")
    keep = np.isfinite(values)
    if counts_a is not None:
        a = np.asarray(counts_a, np.float64).reshape(-1)[keep]
        b = np.asarray(counts_b, np.float64).reshape(-1)[keep]
    values, w = values[keep], w[keep]
    if values.size < 2:
        return None
    if counts_a is None or np.ptp(np.concatenate([a, b])) == 0:
        median = _weighted_median(values, w)
        deviations = np.abs(values - median)
        scale = 1.4826 * _weighted_median(deviations, w)
        if not scale > 0:
            mean = np.average(values, weights=w)
            scale = float(np.sqrt(np.average((values - mean) ** 2, weights=w)))
        return Normalization(median, scale) if scale > 0 else None
    x = np.concatenate([a, b])
    y = np.concatenate([values, values])
    ww = np.concatenate([w, w])
    intercept, slope = _lad_line(x, y, ww)
    if not spread_per_count:
        scale = 1.4826 * _weighted_median(np.abs(values - (intercept + slope * 0.5 * (a + b))), w)
        return Normalization(intercept, scale, slope) if scale > 0 else None
    deviations = 1.4826 * np.abs(y - (intercept + slope * x))
    scale_intercept, scale_slope = _lad_line(x, deviations, ww)
    # The deviation at the sample's typical count; the line is not trusted below half of it.
    typical = scale_intercept + scale_slope * _weighted_median(x, ww)
    if not typical > 0:
        return None
    return Normalization(intercept, scale_intercept, slope, scale_slope, 0.5 * typical)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value at half the total weight (the mean of the two middle values when it falls between them)."""
    order = np.argsort(values, kind="stable")
    v, cumulative = values[order], np.cumsum(weights[order])
    half = 0.5 * cumulative[-1]
    k = int(np.searchsorted(cumulative, half))
    if k + 1 < v.size and np.isclose(cumulative[k], half, rtol=1e-12, atol=0.0):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[k])


def _merge_sorted(ascending: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``ascending`` (sorted) with the finite ``values`` merged in: the array np.sort of both gives."""
    values = np.sort(values[np.isfinite(values)])
    return np.insert(ascending, np.searchsorted(ascending, values), values)


def _lad_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, iterations: int = 60) -> tuple[float, float]:
    """Weighted least-absolute-deviations line y ~ a + b x by iteratively reweighted least squares (started from
    the weighted least-squares line; residuals floored at 1e-6 of y's spread)."""
    floor = 1e-6 * max(float(np.ptp(y)), 1e-12)
    x0 = float(np.average(x, weights=w))
    a, b = _irls_line(np.ascontiguousarray(x - x0, np.float64), np.ascontiguousarray(y, np.float64),
                      np.ascontiguousarray(w, np.float64), floor, iterations)
    return float(a - b * x0), float(b)


@njit(cache=True)
def _irls_line(xc: np.ndarray, y: np.ndarray, w: np.ndarray, floor: float, iterations: int) -> tuple[float, float]:
    """The iterations of :func:`_lad_line` on centred x (a well-conditioned 2 x 2 system), its weighted sums taken
    as numpy takes them (:func:`_weighted_sums`): the same line to the bit, without a dozen numpy passes per
    iteration (the engine re-fits its background as it grows: 2 ms at 2,000 samples, the slowest of its frames)."""
    u = w.copy()
    a = b = 0.0
    for _ in range(iterations + 1):
        s0, s1, s2, t0, t1 = _weighted_sums(u, xc, y)
        det = s0 * s2 - s1 * s1
        if not det > 0:
            break
        a, b = (s2 * t0 - s1 * t1) / det, (s0 * t1 - s1 * t0) / det
        for i in range(y.size):
            u[i] = w[i] / max(abs(y[i] - a - b * xc[i]), floor)
    return a, b


@njit(cache=True)
def _weighted_sums(u: np.ndarray, x: np.ndarray, y: np.ndarray):
    """Sums of u, u x, u x x, u y and u x y, each as numpy sums the contiguous array of its terms: halved (at a
    multiple of 8) down to blocks of at most 128 (:func:`_block_sums`), the halves' sums added. The halving walks an
    explicit stack (numba's cache cannot hold a recursive function)."""
    starts, counts, stage = np.zeros(64, np.int64), np.zeros(64, np.int64), np.zeros(64, np.int64)
    left = np.empty((64, 5))  # each halved block's first half's sums, while its second half is summed
    sums, scratch = np.empty(5), np.empty((5, 8))
    top = 0
    counts[0] = y.size
    while top >= 0:
        start, count = starts[top], counts[top]
        if count <= 128:
            _block_sums(u, x, y, start, count, sums, scratch)
            top -= 1
            continue
        half = count // 2
        half -= half % 8
        if stage[top] == 0:  # sum the first half
            stage[top] = 1
            top += 1
            starts[top], counts[top], stage[top] = start, half, 0
        elif stage[top] == 1:  # the first half's sums are in: sum the second half
            left[top] = sums
            stage[top] = 2
            top += 1
            starts[top], counts[top], stage[top] = start + half, count - half, 0
        else:
            for m in range(5):
                sums[m] = left[top, m] + sums[m]
            top -= 1
    return sums[0], sums[1], sums[2], sums[3], sums[4]


@njit(cache=True)
def _block_sums(u: np.ndarray, x: np.ndarray, y: np.ndarray, start: int, count: int, sums: np.ndarray,
                running: np.ndarray) -> None:
    """:func:`_weighted_sums` of at most 128 terms into ``sums``: below 8 one running sum, else eight (``running``)
    over the terms in turn, added pairwise, then the remainder one by one."""
    end = start + count
    i = start
    if count < 8:
        sums[:] = 0.0
    else:
        for j in range(8):
            k = start + j
            ux = u[k] * x[k]
            running[0, j], running[1, j], running[2, j], running[3, j], running[4, j] = (
                u[k], ux, ux * x[k], u[k] * y[k], ux * y[k])
        i = start + 8
        while i < end - count % 8:
            for j in range(8):
                k = i + j
                ux = u[k] * x[k]
                running[0, j] += u[k]
                running[1, j] += ux
                running[2, j] += ux * x[k]
                running[3, j] += u[k] * y[k]
                running[4, j] += ux * y[k]
            i += 8
        for m in range(5):
            r = running[m]
            sums[m] = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < end:
        ux = u[i] * x[i]
        sums[0] += u[i]
        sums[1] += ux
        sums[2] += ux * x[i]
        sums[3] += u[i] * y[i]
        sums[4] += ux * y[i]
        i += 1


def thesis_normalization(scores, offset: float, normalizer: float | None = None) -> Normalization | None:
    """F = max(M) (or the given F) and the offset; None when F does not exceed the offset."""
    if normalizer is None:
        values = np.asarray(scores, dtype=np.float64)
        values = values[np.isfinite(values)]
        if values.size == 0:
            return None
        normalizer = float(values.max())
    return Normalization(offset, normalizer - offset) if normalizer > offset else None


def default_normalization(scores, params: MrfParams, counts_a=None, counts_b=None) -> Normalization | None:
    """The thesis's F = max(M), or the background of the given scores (per feature count, when known)."""
    if params.potential == "thesis":
        return thesis_normalization(scores, params.offset)
    if params.background != "global":
        return background_normalization(scores, None, counts_a, counts_b, params.background == "features_spread")
    return background_normalization(scores)


def node_potentials(scores, params: MrfParams, normalization: Normalization, counts_a=None, counts_b=None):
    """(log-odds theta, value entering G, live mask) of scored pairs (between frames with ``counts_a`` and
    ``counts_b`` features, needed when the normalization depends on them)."""
    scores = np.asarray(scores, dtype=np.float64)
    if params.potential == "thesis":
        p = normalized_potential(scores, normalization.location + normalization.scale, normalization.location)
        live = p > 0
        return _log_odds(np.where(live, p, 1.0)), p, live
    z = normalization.standardize(scores, counts_a, counts_b)
    live = np.isfinite(z)
    z = np.where(live, z, 0.0)
    return params.kappa * (z - params.z0), z, live


def normalized_potential(M, normalizer: float, offset: float = 0.0) -> np.ndarray:
    """phi(1) = p = (M - offset) / (F - offset), clipped to [0, 1] (§3.4; offset 0 is the thesis's M / F)."""
    if not normalizer > offset:
        raise ValueError(f"normalizer F ({normalizer}) must exceed the offset ({offset})")
    p = (np.asarray(M, dtype=np.float64) - offset) / (normalizer - offset)
    return np.clip(np.nan_to_num(p, nan=0.0, neginf=0.0, posinf=1.0), 0.0, 1.0)


def _log_odds(p: np.ndarray) -> np.ndarray:
    p = np.minimum(p, _MAX_P)
    return np.log(p) - np.log1p(-p)


@njit(cache=True)
def _coupling(p_a: float, p_b: float, sigma: float, log_alpha: float, attractive: bool) -> float:
    """J = log(alpha * G(M_a, M_b)) (eq. 3.1), floored at 0 for the attractive variant."""
    z = (p_a - p_b) / sigma
    j = log_alpha - z * z
    if attractive and j < 0.0:
        return 0.0
    return j


@njit(cache=True)
def _run_bp(theta, value, nbr, fixed_in, msg, sources, sigma, log_alpha, attractive, damping, iterations):
    """Synchronous damped max-product iterations; only messages sent by ``sources`` are recomputed.

    theta (C,) log-odds of phi; value (C,) p; nbr (C, 8) live neighbour index or -1; fixed_in (C,) sum of the
    constant messages from clamped neighbours; msg (C, 8) incoming messages (msg[c, d] comes from direction d),
    updated in place.
    """
    # The couplings depend on the potentials, not on the messages: computed once rather than every iteration. A
    # source without a live neighbour (a fifth of a late band's cells: lone draws and retrievals) sends nothing.
    active = np.empty(sources.shape[0], np.int64)
    count = 0
    for s in range(sources.shape[0]):
        for d in range(8):
            if nbr[sources[s], d] >= 0:
                active[count] = sources[s]
                count += 1
                break
    couplings = np.zeros((count, 8))
    for s in range(count):
        c = active[s]
        for d in range(8):
            e = nbr[c, d]
            if e >= 0:
                couplings[s, d] = _coupling(value[c], value[e], sigma, log_alpha, attractive)
    new = np.empty((count, 8))
    for _ in range(iterations):
        for s in range(count):
            c = active[s]
            total = theta[c] + fixed_in[c]
            for d in range(8):
                total += msg[c, d]
            for d in range(8):
                e = nbr[c, d]
                if e < 0:
                    new[s, d] = 0.0
                    continue
                cavity = total - msg[c, d]  # everything c knows except what e told it
                coupling = couplings[s, d]
                mu = max(0.0, cavity + coupling) - max(coupling, cavity)
                new[s, d] = damping * msg[e, 7 - d] + (1.0 - damping) * mu
        for s in range(count):
            c = active[s]
            for d in range(8):
                e = nbr[c, d]
                if e >= 0:
                    msg[e, 7 - d] = new[s, d]


@njit(cache=True)
def _beliefs(theta, fixed_in, msg, cells):
    out = np.empty(cells.shape[0])
    for s in range(cells.shape[0]):
        c = cells[s]
        total = theta[c] + fixed_in[c]
        for d in range(8):
            total += msg[c, d]
        out[s] = total
    return out


@njit(cache=True)
def _find_row(rows, start, stop, row):
    """Index of ``row`` in the sorted rows[start:stop], or -1."""
    lo, hi = start, stop
    while lo < hi:
        mid = (lo + hi) // 2
        if rows[mid] < row:
            lo = mid + 1
        else:
            hi = mid
    if lo < stop and rows[lo] == row:
        return lo
    return -1


@njit(cache=True)
def _link(rows, cols, col_start, col_offset, n_cols, first, stop, value, sigma, log_alpha, attractive, window,
          prior_theta, nbr, fixed_in):
    """Neighbour table and summed constant messages from non-live neighbours of cells ``first..stop-1``.

    Cells are stored column by column (column l occupies col_start[l - col_offset]..col_start[l - col_offset + 1]-1,
    rows ascending; columns before ``col_offset`` are no longer stored here); the lattice is n_cols x n_cols. A
    neighbour outside it has no factor. A neighbour inside it but not stored is either structural (the window or the
    lower triangle: label fixed at 0) or an unscored pair with log-odds ``prior_theta`` and no other information
    (-inf: also fixed at 0); both have value 0 and send a constant.
    """
    for c in range(first, stop):
        i, j = rows[c], cols[c]
        acc = 0.0
        for d in range(8):
            k = i + _D_ROW[d]
            l_ = j + _D_COL[d]
            if k < 0 or l_ < 0 or k >= n_cols or l_ >= n_cols:
                nbr[c, d] = -1
                continue
            e = -1
            if l_ >= col_offset:
                e = _find_row(rows, col_start[l_ - col_offset], col_start[l_ - col_offset + 1], k)
            nbr[c, d] = e
            if e < 0:
                coupling = _coupling(value[c], 0.0, sigma, log_alpha, attractive)
                prior = prior_theta if k < l_ - window else -np.inf
                acc += max(0.0, prior + coupling) - max(coupling, prior)
        fixed_in[c] = acc


@dataclass(frozen=True)
class MrfResult:
    """(n, n) max-marginal log-odds (``-inf`` where the pair is ruled out) and the MAP labelling D = belief > 0."""

    beliefs: np.ndarray
    decisions: np.ndarray
    normalization: Normalization | None


def _columnwise(rows: np.ndarray, cols: np.ndarray, n: int):
    order = np.lexsort((rows, cols))
    rows, cols = rows[order], cols[order]
    col_start = np.zeros(n + 1, np.int64)
    np.add.at(col_start, cols + 1, 1)
    return order, rows, cols, np.cumsum(col_start)


def infer_cells(
    rows,
    cols,
    scores,
    n: int,
    params: MrfParams = MrfParams(),
    normalization: Normalization | None = None,
    window: int = 0,
    counts=None,
) -> tuple[np.ndarray, Normalization | None]:
    """Batch inference on the scored cells (earlier i, later j) of an (n, n) lattice.

    Pairs with j - i <= ``window`` and the lower triangle are not loops by construction; other pairs not listed are
    unscored (see :class:`MrfParams`). ``normalization`` defaults to the thesis's F = max(M), or to the background
    statistics of the given scores; ``counts`` (n,) the frames' feature counts (the "features" background).
    Returns each cell's max-marginal log-odds (``-inf`` if ruled out).
    """
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    cols = np.asarray(cols, dtype=np.int64).reshape(-1)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if not (rows.shape == cols.shape == scores.shape):
        raise ValueError("rows, cols and scores must have the same length")
    if np.any(np.isnan(scores)):
        raise ValueError("scores contain NaN")
    if rows.size and (rows.min() < 0 or cols.min() < 0 or rows.max() >= n or cols.max() >= n):
        raise ValueError(f"cells must lie inside the {n}x{n} lattice")
    if np.any(cols - rows <= window):
        raise ValueError(f"scored cells must have j - i > window ({window})")
    counts_a = counts_b = None
    if counts is not None:
        counts = np.asarray(counts, np.float64).reshape(-1)
        if counts.shape != (n,):
            raise ValueError(f"counts must have one value per frame ({n})")
        counts_a, counts_b = counts[rows], counts[cols]
    if normalization is None:
        normalization = default_normalization(scores, params, counts_a, counts_b)
    beliefs = np.full(rows.size, -np.inf)
    if normalization is None:
        return beliefs, None
    theta_all, value_all, live_all = node_potentials(scores, params, normalization, counts_a, counts_b)
    live = np.flatnonzero(live_all)
    if np.unique(rows[live] * n + cols[live]).size != live.size:
        raise ValueError("duplicate cells")
    order, r, c, col_start = _columnwise(rows[live], cols[live], n)
    value = value_all[live][order]
    theta = theta_all[live][order]
    log_alpha = float(np.log(params.alpha))
    nbr = np.empty((r.size, 8), np.int64)
    fixed_in = np.empty(r.size)
    _link(r, c, col_start, 0, n, 0, r.size, value, params.sigma, log_alpha, params.attractive, window,
          params.prior_theta, nbr, fixed_in)
    msg = np.zeros((r.size, 8))
    cells = np.arange(r.size, dtype=np.int64)
    _run_bp(theta, value, nbr, fixed_in, msg, cells, params.sigma, log_alpha, params.attractive, params.damping,
            params.iterations)
    beliefs[live[order]] = _beliefs(theta, fixed_in, msg, cells)
    return beliefs, normalization


def infer_batch(M, params: MrfParams = MrfParams(), normalization: Normalization | None = None,
                window: int = 0, counts=None) -> MrfResult:
    """The batch inference on a full (n, n) similarity matrix: pairs i < j - window with a finite M are scored.

    With ``params.potential == "thesis"`` and the default normalization this is the thesis's computation (F =
    max(M)); entries that are not loop candidates must be ``-inf`` (or at most the offset). ``counts``: the
    frames' feature counts (see ``MrfParams.background``).
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(f"M must be square, got shape {M.shape}")
    n = M.shape[0]
    rows, cols = np.nonzero(np.triu(np.isfinite(M), window + 1))
    cell_beliefs, normalization = infer_cells(rows, cols, M[rows, cols], n, params, normalization, window, counts)
    beliefs = np.full((n, n), -np.inf)
    beliefs[rows, cols] = cell_beliefs
    return MrfResult(beliefs, beliefs > 0, normalization)


ARCHIVE_DTYPE = np.dtype([("row", np.int64), ("col", np.int64), ("score", np.float64), ("belief", np.float64)])
_KEEP_BEYOND_BAND = 4  # columns before the band kept live: inference and relinking read at most 2 of them
_ARCHIVE_CELLS = 1024  # cells archived at a time
# Final cells of released columns kept (the latest): as many as the engine's background sample, which pins a median
# or a quantile to ~1/sqrt(20,000) of the spread.
RETAINED_CELLS = 20_000


class IncrementalMrf:
    """The lattice grown one column (frame) at a time, with inference on the last ``band`` columns only.

    ``add_column(rows, scores)`` appends column j = number of columns so far with the scores of pairs (i, j),
    i < j - window; it re-runs ``params.iterations`` synchronous iterations on the messages sent by cells of columns
    j-band+1..j, warm-started from the stored messages; messages sent by older cells stay as they were. A column's
    decisions are final once it leaves the band.

    The normalization is fixed (``normalization=``), supplied per column (``add_column(..., normalization=)``, as
    the engine does with its background estimate), or else running: F = the maximum score so far (thesis), or the
    median and deviation of every score so far (calibrated). When it changes, the band's potentials follow; older
    columns keep the decisions they were given. ``add_column(..., count=)``: the new frame's feature count, for a
    normalization that depends on it (``MrfParams.background``).

    Memory stays bounded: the cells of final columns (a few columns behind the band, which nothing reads again) are
    moved, as (row, col, score, belief) records, to ``archive`` (a log of :mod:`.storage`; default in memory);
    :meth:`cells`, :meth:`cells_from` and :meth:`dense` read them back. The cells of a column given up
    (:meth:`release_column`: a redundant frame's) are kept in a bounded sample instead once final.
    """

    def __init__(self, params: MrfParams = MrfParams(), band: int = 30, normalization: Normalization | None = None,
                 window: int = 0, archive=None) -> None:
        if band < 1 or window < 0:
            raise ValueError("band must be >= 1 and window >= 0")
        self.params = params
        self.band = int(band)
        self.window = int(window)
        self.fixed = normalization is not None
        self.normalization = normalization
        self._log_alpha = float(np.log(params.alpha))
        self._archive = archive if archive is not None else MemoryLog(ARCHIVE_DTYPE)
        if self._archive.dtype != ARCHIVE_DTYPE:
            raise ValueError(f"the archive must hold {ARCHIVE_DTYPE} records")
        self._seen: list[np.ndarray] = []  # every score, for a running calibrated normalization
        self._seen_counts: list[np.ndarray] = []  # and its two frames' feature counts
        self._counts = np.zeros(64)  # feature count of each frame (column)
        self._size = 0  # live cells
        self._base = len(self._archive)  # cells archived before the live ones
        self._first_col = 0  # the first live column
        capacity = 64
        self._rows = np.zeros(capacity, np.int64)
        self._cols = np.zeros(capacity, np.int64)
        self._scores = np.zeros(capacity)
        self._value = np.zeros(capacity)
        self._theta = np.zeros(capacity)
        self._fixed_in = np.zeros(capacity)
        self._nbr = np.full((capacity, 8), -1, np.int64)
        self._msg = np.zeros((capacity, 8))
        self._beliefs = np.zeros(capacity)
        self._col_start = [0]  # local index of the first cell of each live column, and the end
        self._released: set[int] = set()  # live columns whose cells go to _retained, not the archive, once final
        self._retained = RecentRecords(ARCHIVE_DTYPE, RETAINED_CELLS)
        # The finite beliefs of the first _sorted_archived archived cells, in increasing order (sorted_beliefs).
        self._sorted_archived, self._sorted_final = 0, np.zeros(0)

    # --- growth ---------------------------------------------------------------------------------------------

    @property
    def n_columns(self) -> int:
        return self._first_col + len(self._col_start) - 1

    @property
    def n_cells(self) -> int:
        """Cells of the lattice (:meth:`cells`)."""
        return self._base + len(self._retained) + self._size

    def _start(self, column: int) -> int:
        """Local index of the first live cell of ``column`` (a live column, or n_columns for the end)."""
        return self._col_start[column - self._first_col]

    def set_count(self, column: int, count: float) -> None:
        """The feature count of a column that has no cells yet (a frame whose features changed before it was
        aligned: the engine's calibration)."""
        live = column >= self._first_col
        if not 0 <= column < self.n_columns or (live and self._start(column + 1) != self._start(column)):
            raise ValueError(f"column {column} does not exist or already has cells")
        self._counts[column] = count

    def _reserve(self, extra: int) -> None:
        need = self._size + extra
        capacity = self._rows.size
        if need <= capacity:
            return
        while capacity < need:
            capacity *= 2
        for name in ("_rows", "_cols", "_scores", "_value", "_theta", "_fixed_in", "_beliefs"):
            old = getattr(self, name)
            new = np.zeros(capacity, old.dtype)
            new[: self._size] = old[: self._size]
            setattr(self, name, new)
        for name, fill in (("_nbr", -1), ("_msg", 0.0)):
            old = getattr(self, name)
            new = np.full((capacity, 8), fill, old.dtype)
            new[: self._size] = old[: self._size]
            setattr(self, name, new)

    def _archive_final_columns(self) -> None:
        """Move the cells of columns nothing reads again (more than ``_KEEP_BEYOND_BAND`` before the band) to the
        archive, once there are ``_ARCHIVE_CELLS`` of them."""
        keep = self.n_columns - self.band - _KEEP_BEYOND_BAND
        if keep <= self._first_col:
            return
        cut = self._start(keep)
        if cut < _ARCHIVE_CELLS:
            return
        records = np.empty(cut, ARCHIVE_DTYPE)
        records["row"], records["col"] = self._rows[:cut], self._cols[:cut]
        records["score"], records["belief"] = self._scores[:cut], self._beliefs[:cut]
        if self._released:
            released = np.isin(records["col"], np.fromiter(self._released, np.int64))
            self._retained.append(records[released])
            records = records[~released]
            self._released = {j for j in self._released if j >= keep}
        self._archive.append(records)
        s = self._size
        for name in ("_rows", "_cols", "_scores", "_value", "_theta", "_fixed_in", "_beliefs", "_msg"):
            array = getattr(self, name)
            array[: s - cut] = array[cut:s]
        # Links into the archived cells are dropped: only cells of the oldest live columns had them, and those
        # neither send messages nor get relinked any more.
        nbr = self._nbr[cut:s]
        self._nbr[: s - cut] = np.where(nbr >= cut, nbr - cut, -1)
        self._size = s - cut
        self._base += records.size
        del self._col_start[: keep - self._first_col]
        self._col_start = [start - cut for start in self._col_start]
        self._first_col = keep

    def release_column(self, column: int) -> None:
        """Once final, the cells of live ``column`` (a frame that left the map) are not archived: the latest
        ``RETAINED_CELLS`` of such cells stay in the lattice's figures (:meth:`cells`: what the decision threshold
        is estimated on), older ones are dropped."""
        if not self._first_col <= column < self.n_columns:
            raise ValueError(f"column {column} is not live")
        self._released.add(int(column))

    def _running_normalization(self, scores: np.ndarray, counts_a: np.ndarray,
                               counts_b: np.ndarray) -> Normalization | None:
        if self.params.potential == "thesis":
            finite = scores[np.isfinite(scores)]
            current = self.normalization.location + self.normalization.scale if self.normalization else -np.inf
            top = max(current, float(finite.max()) if finite.size else -np.inf)
            return thesis_normalization([], self.params.offset, top) if np.isfinite(top) else None
        if scores.size:
            finite = np.isfinite(scores)
            self._seen.append(scores[finite])
            self._seen_counts.append(np.stack([counts_a[finite], counts_b[finite]]))
        if not self._seen:
            return None
        seen_counts = np.concatenate(self._seen_counts, axis=1)
        return default_normalization(np.concatenate(self._seen), self.params, seen_counts[0], seen_counts[1])

    def add_column(self, rows, scores, normalization: Normalization | None = None, count: float = 0.0) -> None:
        """Append the next column: scores of pairs (rows[k], j) for the new frame j; see the class docstring."""
        j = self.n_columns
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if rows.shape != scores.shape:
            raise ValueError("rows and scores must have the same length")
        if rows.size and (rows.min() < 0 or rows.max() >= j - self.window):
            raise ValueError(f"rows of column {j} must be earlier frames outside the window (0..{j - self.window - 1})")
        if np.unique(rows).size != rows.size:
            raise ValueError("duplicate rows in one column")
        if np.any(np.isnan(scores)):
            raise ValueError("scores contain NaN")
        self._archive_final_columns()
        if j == self._counts.size:
            self._counts = np.concatenate([self._counts, np.zeros_like(self._counts)])
        self._counts[j] = count
        counts_a = self._counts[rows]
        counts_b = np.full(rows.size, float(count))
        if normalization is None and not self.fixed:
            normalization = self._running_normalization(scores, counts_a, counts_b)
        elif self.fixed:
            normalization = self.normalization
        changed = normalization != self.normalization
        self.normalization = normalization
        first = self._size
        if normalization is not None and rows.size:
            theta, value, live = node_potentials(scores, self.params, normalization, counts_a, counts_b)
            order = np.argsort(rows[live], kind="stable")
            rows, scores, theta, value = rows[live][order], scores[live][order], theta[live][order], value[live][order]
        else:
            rows, scores, theta, value = (np.zeros(0, np.int64),) + (np.zeros(0),) * 3
        added = rows.size
        self._reserve(added)
        stop = first + added
        self._rows[first:stop] = rows
        self._cols[first:stop] = j
        self._scores[first:stop] = scores
        self._theta[first:stop] = theta
        self._value[first:stop] = value
        self._msg[first:stop] = 0.0
        self._beliefs[first:stop] = 0.0
        self._size = stop
        self._col_start.append(stop)
        first_col = j - 1
        if changed and normalization is not None:
            # The band's potentials follow the new normalization (older columns are final).
            first_col = max(0, j - self.band)
            cells = np.arange(self._start(first_col), first)
            if cells.size:
                t, v, _ = node_potentials(self._scores[cells], self.params, normalization,
                                          self._counts[self._rows[cells]], self._counts[self._cols[cells]])
                self._theta[cells], self._value[cells] = t, v
            first_col -= 1
        self._relink(max(0, first_col), j)
        self._infer()

    def _relink(self, first_col: int, last_col: int) -> None:
        starts = np.asarray(self._col_start, dtype=np.int64)
        first, stop = self._start(first_col), self._start(last_col + 1)
        s = self._size
        p = self.params
        _link(self._rows[:s], self._cols[:s], starts, self._first_col, self.n_columns, first, stop, self._value[:s],
              p.sigma, self._log_alpha, p.attractive, self.window, p.prior_theta, self._nbr[:s], self._fixed_in[:s])

    def band_cells(self) -> np.ndarray:
        """Local indices of the cells of the band's columns."""
        first_col = max(0, self.n_columns - self.band)
        return np.arange(self._start(first_col), self._size, dtype=np.int64)

    def _infer(self) -> None:
        cells = self.band_cells()
        if cells.size == 0:
            return
        s = self._size
        p = self.params
        _run_bp(self._theta[:s], self._value[:s], self._nbr[:s], self._fixed_in[:s], self._msg[:s], cells, p.sigma,
                self._log_alpha, p.attractive, p.damping, p.iterations)
        self._beliefs[cells] = _beliefs(self._theta[:s], self._fixed_in[:s], self._msg[:s], cells)

    # --- results --------------------------------------------------------------------------------------------

    def column(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, scores, beliefs) of the live cells of column j; belief > 0 is a loop closure."""
        if not 0 <= j < self.n_columns:
            raise IndexError(f"column {j} out of range 0..{self.n_columns - 1}")
        if j < self._first_col:
            archived = self._archive.read()
            mine = archived[archived["col"] == j]
            return mine["row"].copy(), mine["score"].copy(), mine["belief"].copy()
        a, b = self._start(j), self._start(j + 1)
        return self._rows[a:b].copy(), self._scores[a:b].copy(), self._beliefs[a:b].copy()

    def cells_from(self, column: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, beliefs) of the live cells of columns ``column`` and later."""
        column = min(max(0, column), self.n_columns)
        s = self._size
        a = self._start(max(column, self._first_col))
        rows, cols, beliefs = self._rows[a:s].copy(), self._cols[a:s].copy(), self._beliefs[a:s].copy()
        if column < self._first_col:
            archived = self._archive.read()
            archived = archived[archived["col"] >= column]
            rows, cols = np.concatenate([archived["row"], rows]), np.concatenate([archived["col"], cols])
            beliefs = np.concatenate([archived["belief"], beliefs])
        return rows, cols, beliefs

    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, scores, beliefs) of every cell - archived, the released columns' still held, live - in
        column order."""
        s = self._size
        final = self._archive.read()
        if len(self._retained):
            final = np.concatenate([final, self._retained.read()])
            final = final[np.argsort(final["col"], kind="stable")]
        return (np.concatenate([final["row"], self._rows[:s]]), np.concatenate([final["col"], self._cols[:s]]),
                np.concatenate([final["score"], self._scores[:s]]),
                np.concatenate([final["belief"], self._beliefs[:s]]))

    def sorted_beliefs(self, beliefs: np.ndarray) -> np.ndarray:
        """The finite ``beliefs`` of :meth:`cells` (as it returned them) in increasing order. Archived beliefs are
        final, so those are kept sorted as they are archived and each call sorts only the newly archived and the
        live ones (with released columns' cells held, which come in column order among them: all of them)."""
        archived = self._base
        if len(self._retained) or beliefs.size != self.n_cells:
            return np.sort(beliefs[np.isfinite(beliefs)])
        if archived > self._sorted_archived:
            self._sorted_final = _merge_sorted(self._sorted_final, beliefs[self._sorted_archived:archived])
            self._sorted_archived = archived
        return _merge_sorted(self._sorted_final, beliefs[archived:])

    def dense(self) -> MrfResult:
        n = self.n_columns
        beliefs = np.full((n, n), -np.inf)
        rows, cols, _, b = self.cells()
        beliefs[rows, cols] = b
        return MrfResult(beliefs, beliefs > 0, self.normalization)

    # --- state ----------------------------------------------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        """The live cells and the index; the archived cells too when the archive is not persistent (a persistent
        one is found again by its length, ``archived``)."""
        s = self._size
        norm = self.normalization
        state = {
            "rows": self._rows[:s].copy(),
            "cols": self._cols[:s].copy(),
            "scores": self._scores[:s].copy(),
            "messages": self._msg[:s].copy(),
            "beliefs": self._beliefs[:s].copy(),
            "theta": self._theta[:s].copy(),
            "value": self._value[:s].copy(),
            "col_start": np.asarray(self._col_start, np.int64),
            "first_col": np.array(self._first_col, np.int64),
            "archived": np.array(self._base, np.int64),
            "normalization": norm.to_array() if norm else np.zeros(0),
            "seen": np.concatenate(self._seen) if self._seen else np.zeros(0),
            "seen_counts": np.concatenate(self._seen_counts, axis=1) if self._seen_counts else np.zeros((2, 0)),
            "counts": self._counts[: self.n_columns].copy(),
            "released": np.array(sorted(self._released), np.int64),
        }
        retained = self._retained.read()
        state.update({f"retained_{name}": retained[name].copy() for name in ARCHIVE_DTYPE.names})
        if not getattr(self._archive, "persistent", False):
            archived = self._archive.read()
            state.update({f"archive_{name}": archived[name].copy() for name in ARCHIVE_DTYPE.names})
        return state

    @classmethod
    def from_state(cls, state: dict, params: MrfParams, band: int, window: int,
                   fixed: Normalization | None = None, archive=None) -> "IncrementalMrf":
        """The lattice of :meth:`state`; ``archive``: the persistent archive it was saved with (truncated to the
        state's length), else the archived cells come from the state."""
        archived = int(np.asarray(state.get("archived", 0)))
        if archive is None:
            archive = MemoryLog(ARCHIVE_DTYPE)
            if archived:
                records = np.empty(archived, ARCHIVE_DTYPE)
                try:
                    for name in ARCHIVE_DTYPE.names:
                        records[name] = state[f"archive_{name}"]
                except (KeyError, ValueError):
                    raise ValueError("MRF state: the archived cells are missing or inconsistent") from None
                archive.append(records)
        elif len(archive) < archived:
            raise ValueError(f"MRF state: the archive holds {len(archive)} cells, the state {archived}")
        else:
            archive.truncate(archived)
        mrf = cls(params, band, fixed, window, archive)
        rows = np.asarray(state["rows"], np.int64)
        cols = np.asarray(state["cols"], np.int64)
        col_start = np.asarray(state["col_start"], np.int64)
        first_col = int(np.asarray(state.get("first_col", 0)))
        count = rows.size
        if not (cols.shape == (count,) and np.shape(state["scores"]) == (count,)
                and np.shape(state["messages"]) == (count, 8) and np.shape(state["beliefs"]) == (count,)
                and np.shape(state["theta"]) == (count,) and np.shape(state["value"]) == (count,)):
            raise ValueError("inconsistent MRF state arrays")
        if col_start.ndim != 1 or col_start.size < 1 or col_start[0] != 0 or col_start[-1] != count \
                or np.any(np.diff(col_start) < 0) or first_col < 0:
            raise ValueError("inconsistent MRF column index")
        if fixed is None:
            mrf.normalization = Normalization.from_array(state["normalization"])
        seen = np.asarray(state["seen"], np.float64)
        seen_counts = np.asarray(state["seen_counts"], np.float64).reshape(2, -1)
        counts = np.asarray(state["counts"], np.float64).reshape(-1)
        if seen_counts.shape[1] != seen.size or counts.size != first_col + col_start.size - 1:
            raise ValueError("inconsistent MRF background or feature counts")
        mrf._seen = [seen] if seen.size else []
        mrf._seen_counts = [seen_counts] if seen.size else []
        mrf._counts = np.concatenate([counts, np.zeros(max(64, counts.size))])
        mrf._reserve(count)
        mrf._size = count
        mrf._first_col = first_col
        mrf._rows[:count] = rows
        mrf._cols[:count] = cols
        mrf._scores[:count] = state["scores"]
        mrf._msg[:count] = state["messages"]
        mrf._beliefs[:count] = state["beliefs"]
        mrf._col_start = col_start.tolist()
        released = np.asarray(state["released"], np.int64).reshape(-1)
        if released.size and (released.min() < first_col or released.max() >= mrf.n_columns):
            raise ValueError("MRF state: released columns must be live")
        mrf._released = set(released.tolist())
        try:
            retained = np.empty(np.shape(state["retained_row"])[0], ARCHIVE_DTYPE)
            for name in ARCHIVE_DTYPE.names:
                retained[name] = state[f"retained_{name}"]
        except (KeyError, ValueError, IndexError):
            raise ValueError("MRF state: the retained cells are missing or inconsistent") from None
        if retained.size > RETAINED_CELLS:
            raise ValueError("MRF state: more retained cells than kept")
        mrf._retained.append(retained)
        mrf._theta[:count] = state["theta"]
        mrf._value[:count] = state["value"]
        if count:
            mrf._relink(first_col, mrf.n_columns - 1)
        return mrf
