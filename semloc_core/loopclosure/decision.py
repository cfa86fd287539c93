"""Loop decisions at a stated precision, from the MRF's beliefs (issue 33).

The max-marginal log-odds after inference rank the pairs well, but ``belief > 0`` is no statement about precision:
where it lands depends on the share of loops among the pairs, on the lens and on the texture. Instead the
decision threshold is chosen for a target precision from the beliefs' own distribution, with no ground truth
(the two-group model of empirical Bayes, Efron 2004; the tail-area false discovery rate of Storey 2002):

* Most pairs are not loops, and the unrelated ones make the bulk of the beliefs. Their distribution (the *null*) is
  fitted as a Gaussian N(mu, s) to the central half of the empirical distribution (quantiles 0.25-0.75: Efron's
  empirical null by central matching, 2004), where loops are rare: Phi((b - mu) / s) = F(b) there, a straight line
  b = mu + s Phi^-1(F) fitted by least squares. Not to the lower half: the beliefs' lower tail is wider than their
  upper one, and a Gaussian fitted to it carries that spread over, over-predicting the unrelated pairs just above
  the bulk 1.4-2.4 times on the real samples (results/2026-12-06-loop-decision-recall.md).
  The distribution is that of a uniform sample of all the pairs (``null_sample``; by default the beliefs given, as
  the batch's full lattice): a lattice of retrieved candidates is no such sample (the engine fits its null to the
  pairs it drew at random, weighted as its background statistics are). Every pair is
  counted as a possible unrelated one (the null's weight is 1, Storey's conservative choice): fitting the weight
  as well was tried, and on the fitted range it trades off against the deviation (on two-group samples with known
  loops it misjudged the precision by up to 0.17; tests/loopclosure/test_decision.py).
* Among the N pairs, the K with the highest beliefs are expected to hold N (1 - Phi((b_K - mu) / s)) unrelated
  pairs, so their expected precision is one minus that over K. The decision takes the largest K whose expected
  precision reaches the target (``target_precision``, 0.95 by default) and reports that expected precision.
* A set at a target precision is allowed its share of unrelated pairs, and the tail-area rule fills that allowance
  even where the beliefs have run out of loops (after a clear gap, the next pairs are the null's own tail). So the
  decided pairs also stop before the first one that is more likely unrelated than a loop: its *local* false
  discovery rate (Efron's lfdr: the null's expected count of beliefs within half its deviation of the pair's, over
  the count observed there) must stay at most one half. With places counted (below) it rarely binds at 0.95; at
  lower targets it keeps the set from the pairs where the Gaussian's tail is least trusted (off, the expected
  precision fell 0.1 below the measured one: results/2026-12-05-loop-decisions-2.md).
* The null above is one of unrelated imagery. The false decisions where it failed (results/2026-12-05-loop-decoys.md)
  are not unrelated: near misses of the same place (the demo's table top: the same view 25-40 deg further round)
  and look-alike places. So the decided pairs are also counted against the engine's own definition of a place,
  frames at most r apart (``place_radius``, the map's temporal radius): among a query frame's decided partners, a
  run of consecutive earlier frames is one visit, its strongest partner where the query is,
  and a partner more than r frames from that one another place: a near miss, counted as a false decision on top
  of the null's expected count (the engine's lattice and the eval's full one alike). The threshold rises until the
  expected precision with them reaches the target
  (never falls below the null's own). Where a place spans more than 2r + 1 frames of the sequence (a looser
  ground truth) this is conservative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.special import ndtr, ndtri

_FIT_QUANTILES = np.linspace(0.25, 0.75, 49)  # the central half of the beliefs: where the null is fitted
MIN_NULL_SAMPLE = 20  # beliefs a null is fitted to at least
_PLACE_STEPS = 64  # thresholds tried at most when off-place partners are counted (between the null's and the top)


@dataclass(frozen=True)
class NullFit:
    """The unrelated pairs' beliefs: N(``location``, ``scale``)."""

    location: float
    scale: float

    def survival(self, values) -> np.ndarray:
        """Share of the pairs expected to be unrelated and above ``values``."""
        return ndtr(-(np.asarray(values, np.float64) - self.location) / self.scale)


@dataclass(frozen=True)
class Decision:
    """``threshold``: pairs with belief >= it are loops (+inf: none reaches the target); ``expected_precision`` of
    those (None when none is decided); ``decided`` how many of the ``pairs``; the ``null`` it came from;
    ``off_place`` how many decided pairs lie more than the place radius from their visit's strongest partner
    (counted as false; 0 when places are not counted)."""

    threshold: float
    expected_precision: float | None
    decided: int
    pairs: int
    target_precision: float
    null: NullFit | None
    off_place: int = 0

    def summary(self) -> dict:
        return {"threshold": self.threshold if np.isfinite(self.threshold) else None,
                "expected_precision": self.expected_precision, "decided": self.decided, "pairs": self.pairs,
                "target_precision": self.target_precision, "off_place": self.off_place,
                "null": None if self.null is None else self.null.__dict__}


def fit_null(beliefs, weights=None) -> NullFit | None:
    """The Gaussian fitted to the central half of ``beliefs`` (finite ones; each standing for ``weights`` pairs,
    1 by default); None with fewer than 20 or no spread."""
    beliefs = np.asarray(beliefs, np.float64).reshape(-1)
    finite = np.isfinite(beliefs)
    if weights is None:
        return _fit_sorted(np.sort(beliefs[finite]))
    weights = np.asarray(weights, np.float64).reshape(-1)
    if weights.shape != beliefs.shape or np.any(weights[finite] <= 0):
        raise ValueError("one positive weight per belief")
    order = np.argsort(beliefs[finite])
    return _fit_sorted(beliefs[finite][order], weights[finite][order])


def _fit_sorted(values: np.ndarray, weights: np.ndarray | None = None) -> NullFit | None:
    """:func:`fit_null` of the finite beliefs sorted in increasing order (with their weights)."""
    if values.size < MIN_NULL_SAMPLE:
        return None
    if weights is None:
        quantiles = np.quantile(values, _FIT_QUANTILES)
    else:  # the weighted quantiles: each value at the middle of its share of the cumulative weight
        cumulative = np.cumsum(weights)
        quantiles = np.interp(_FIT_QUANTILES, (cumulative - 0.5 * weights) / cumulative[-1], values)
    # Phi((x - mu) / s) = F  <=>  x = mu + s Phi^-1(F): a least-squares line through the central half's quantiles.
    slope, intercept = np.polyfit(ndtri(_FIT_QUANTILES), quantiles, 1)
    return NullFit(float(intercept), float(slope)) if slope > 0 else None


def decide(beliefs, target_precision: float = 0.95, pairs: int | None = None, cells=None,
           place_radius: int | None = None, null_sample=None, null_weights=None,
           ascending: np.ndarray | None = None) -> Decision:
    """The threshold on ``beliefs`` (one per pair; -inf for pairs that cannot be loops, e.g. never scored, which
    count as pairs but never as decisions) at which the expected precision reaches ``target_precision``.
    ``pairs``: how many pairs there are in all, when more than the beliefs given (the others, never scored, count
    like -inf ones). ``cells`` = (earlier, later) frames of each belief and ``place_radius`` r: decided partners
    more than r frames from their visit's strongest one count as false too (module docstring). ``null_sample``:
    beliefs of a uniform sample of the pairs (each standing for ``null_weights`` of them) to fit the null to, when
    ``beliefs`` are no such sample. ``ascending``: the finite beliefs in increasing order, when the caller keeps
    them so (the engine's lattice)."""
    if not 0 < target_precision <= 1:
        raise ValueError(f"target precision must be in (0, 1], got {target_precision}")
    if place_radius is not None and cells is None:
        raise ValueError("counting places needs the cells (earlier, later) of the beliefs")
    beliefs = np.asarray(beliefs, np.float64).reshape(-1)
    if np.any(np.isnan(beliefs)):
        raise ValueError("beliefs contain NaN")
    if pairs is not None and pairs < beliefs.size:
        raise ValueError(f"{pairs} pairs in all, fewer than the {beliefs.size} beliefs given")
    pairs = beliefs.size if pairs is None else int(pairs)
    finite = np.isfinite(beliefs)
    if ascending is None:
        ascending = np.sort(beliefs[finite])  # one sort for the fit, the ranking and the local fdr
    elif ascending.size != np.count_nonzero(finite):
        raise ValueError("ascending must hold the finite beliefs")
    null = _fit_sorted(ascending) if null_sample is None else fit_null(null_sample, null_weights)
    if null is None:
        return Decision(np.inf, None, 0, pairs, target_precision, None)
    ranked = ascending[::-1]
    precision = _reaching_precisions(ranked, pairs, null, target_precision)
    reach = np.flatnonzero(precision >= target_precision)
    if not reach.size:
        return Decision(np.inf, None, 0, pairs, target_precision, null)
    k = int(reach.max())
    unlikely = np.flatnonzero(_local_fdr(ranked[: k + 1], ascending, pairs, null) > 0.5)
    if unlikely.size:
        k = int(unlikely[0]) - 1
        if k < 0:
            return Decision(np.inf, None, 0, pairs, target_precision, null)
    decision = Decision(float(ranked[k]), float(precision[k]), k + 1, pairs, target_precision, null)
    if place_radius is None:
        return decision
    return _with_places(decision, beliefs, cells, place_radius, ranked[: k + 1])


def _with_places(decision: Decision, beliefs: np.ndarray, cells, radius: int, ranked: np.ndarray) -> Decision:
    """The lowest threshold at or above ``decision``'s at which the null's expected false decisions plus the
    off-place partners leave the target precision (``ranked``: the beliefs decided by the null, decreasing)."""
    earlier, later = (np.asarray(c, np.int64).reshape(-1) for c in cells)
    if earlier.shape != beliefs.shape or later.shape != beliefs.shape:
        raise ValueError("cells must give the earlier and later frame of each belief")
    # Every threshold tried is at least the null's (ranked[-1]): only the pairs it decides are ever counted.
    candidates = beliefs >= ranked[-1]
    earlier, later, beliefs = earlier[candidates], later[candidates], beliefs[candidates]
    order = np.lexsort((earlier, later))
    earlier, later, values = earlier[order], later[order], beliefs[order]
    # Thresholds tried: the null's own and up to _PLACE_STEPS others evenly spaced in rank above it (the count of
    # off-place partners is not monotone in the threshold, so the lowest one reaching the target is taken).
    ranks = np.unique(np.linspace(ranked.size - 1, 0, min(ranked.size, _PLACE_STEPS)).round().astype(np.int64))[::-1]
    thresholds = ranked[ranks]
    k, count, off, precision = _lowest_reaching(earlier, later, values, thresholds, decision.null.survival(thresholds),
                                                decision.pairs, decision.target_precision, radius)
    if k < 0:
        return Decision(np.inf, None, 0, decision.pairs, decision.target_precision, decision.null)
    return Decision(float(thresholds[k]), precision, count, decision.pairs, decision.target_precision, decision.null,
                    off)


@njit(cache=True)
def _lowest_reaching(earlier: np.ndarray, later: np.ndarray, beliefs: np.ndarray, thresholds: np.ndarray,
                     unrelated: np.ndarray, pairs: int, target: float, radius: int) -> tuple[int, int, int, float]:
    """The first of the increasing ``thresholds`` (the lowest at least every belief given) at which the null's
    expected false decisions (``pairs`` times ``unrelated``, its survival there) plus the off-place partners
    (:func:`off_place_partners`) leave ``target`` precision: its index (-1: none), decided count, off-place count and
    precision. Visits are counted apart, so a rise of the threshold only recounts the visits it took a pair from
    (the visit splits in two where the pair was)."""
    size = beliefs.size
    off = _off_place_range(earlier, later, beliefs, thresholds[0], radius, 0, size)[1]
    # The pairs each threshold drops (belief below it, at least the one before): a counting sort by that threshold.
    step = np.searchsorted(thresholds, beliefs, side="right")
    first = np.zeros(thresholds.size + 2, np.int64)
    for i in range(size):
        first[step[i] + 1] += 1
    first = np.cumsum(first)
    order, filled = np.empty(size, np.int64), first.copy()
    for i in range(size):
        order[filled[step[i]]] = i
        filled[step[i]] += 1
    alive = np.ones(size, np.bool_)
    for k in range(thresholds.size):
        for i in range(first[k], first[k + 1]):
            e = order[i]
            low = e  # the visit of e: decided neighbours of one later frame, one earlier frame apart
            while low > 0 and alive[low - 1] and later[low - 1] == later[e] and earlier[low] - earlier[low - 1] <= 1:
                low -= 1
            high = e
            while (high + 1 < size and alive[high + 1] and later[high + 1] == later[e]
                   and earlier[high + 1] - earlier[high] <= 1):
                high += 1
            off -= _visit_off_place(earlier, beliefs, low, high, radius)
            alive[e] = False
            off += _visit_off_place(earlier, beliefs, low, e - 1, radius)
            off += _visit_off_place(earlier, beliefs, e + 1, high, radius)
        count = size - first[k + 1]
        precision = 1.0 - min((pairs * unrelated[k] + off) / count, 1.0)
        if precision >= target:
            return k, count, off, precision
    return -1, 0, 0, 0.0


@njit(cache=True)
def _visit_off_place(earlier: np.ndarray, beliefs: np.ndarray, low: int, high: int, radius: int) -> int:
    """Members of the visit low..high (every one decided; none when high < low) more than ``radius`` frames from
    its strongest one (the first with its highest belief)."""
    peak = low
    for i in range(low + 1, high + 1):
        if beliefs[i] > beliefs[peak]:
            peak = i
    off = 0
    for i in range(low, high + 1):
        if abs(earlier[i] - earlier[peak]) > radius:
            off += 1
    return off


@njit(cache=True)
def off_place_partners(earlier: np.ndarray, later: np.ndarray, beliefs: np.ndarray, threshold: float,
                       radius: int) -> tuple[int, int]:
    """The pairs decided at ``threshold`` (belief at least it; all given sorted by later, then earlier frame) and how
    many of them lie more than ``radius`` frames from their visit's strongest partner: a visit is a run of
    consecutive earlier frames decided for one later frame, its strongest partner the first with its highest belief.
    One pass, no allocation (the engine re-decides as its lattice grows, at up to _PLACE_STEPS thresholds each)."""
    return _off_place_range(earlier, later, beliefs, threshold, radius, 0, earlier.size)


@njit(cache=True)
def _off_place_range(earlier: np.ndarray, later: np.ndarray, beliefs: np.ndarray, threshold: float, radius: int,
                     start: int, stop: int) -> tuple[int, int]:
    """:func:`off_place_partners` of the entries start..stop-1 (taken in place: a slice costs more than a small
    later frame's count)."""
    decided = off = 0
    first = previous = -1  # the current run's first decided entry and its latest one
    for k in range(start, stop + 1):
        if k < stop:
            if beliefs[k] < threshold:
                continue
            decided += 1
            if previous >= 0 and later[k] == later[previous] and earlier[k] - earlier[previous] <= 1:
                previous = k
                continue
        if first >= 0:  # the run first..previous ends: count its members far from its strongest one
            peak = first
            for i in range(first + 1, previous + 1):
                if beliefs[i] >= threshold and beliefs[i] > beliefs[peak]:
                    peak = i
            for i in range(first, previous + 1):
                if beliefs[i] >= threshold and abs(earlier[i] - earlier[peak]) > radius:
                    off += 1
        first = previous = k
    return decided, off


def local_fdr(ranked: np.ndarray, pairs: int, null: NullFit) -> np.ndarray:
    """Local false discovery rate at each of the ``ranked`` beliefs (any order): the null's expected count of the
    ``pairs`` within half the null's deviation of the belief, over the count of beliefs observed there."""
    return _local_fdr(ranked, np.sort(ranked), pairs, null)


def _local_fdr(ranked: np.ndarray, values: np.ndarray, pairs: int, null: NullFit) -> np.ndarray:
    """:func:`local_fdr` at ``ranked`` among the beliefs ``values`` (sorted in increasing order)."""
    h = 0.5 * null.scale
    observed = np.searchsorted(values, ranked + h, "right") - np.searchsorted(values, ranked - h, "left")
    expected = pairs * (null.survival(ranked - h) - null.survival(ranked + h))
    return expected / np.maximum(observed, 1)


def expected_precisions(ranked: np.ndarray, pairs: int, null: NullFit) -> np.ndarray:
    """Expected precision of the top K = 1, 2, ... beliefs (``ranked`` in decreasing order) among ``pairs``."""
    k = np.arange(1, ranked.size + 1)
    return 1.0 - np.minimum(pairs * null.survival(ranked) / k, 1.0)


def _reaching_precisions(ranked: np.ndarray, pairs: int, null: NullFit, target: float) -> np.ndarray:
    """:func:`expected_precisions` of the top beliefs, as many as could reach ``target``: past a rank K whose
    expected false decisions among all ``ranked`` already exceed twice the target's share, no lower belief (more
    likely unrelated, and not more than all of them decided) reaches it."""
    size = 1024
    while size < ranked.size and not pairs * null.survival(ranked[size - 1]) > 2 * (1 - target) * ranked.size:
        size *= 4
    return expected_precisions(ranked[:size], pairs, null)


def expected_precision(beliefs, threshold: float, null: NullFit | None) -> float | None:
    """Expected precision of the pairs with belief >= ``threshold`` under ``null``; None when there are none."""
    beliefs = np.asarray(beliefs, np.float64).reshape(-1)
    decided = int(np.sum(beliefs >= threshold))
    if null is None or not decided:
        return None
    return float(1.0 - min(beliefs.size * float(null.survival(threshold)) / decided, 1.0))
