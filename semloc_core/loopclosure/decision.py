"""Loop decisions at a stated precision, from the MRF's beliefs (issue 33).

The max-marginal log-odds after inference rank the pairs well, but ``belief > 0`` is no statement about precision:
where it lands depends on the share of loops among the pairs, on the lens and on the texture. Instead the
decision threshold is chosen for a target precision from the beliefs' own distribution, with no ground truth
(the two-group model of empirical Bayes, Efron 2004; the tail-area false discovery rate of Storey 2002):

* Most pairs are not loops, and the unrelated ones make the bulk of the beliefs. Their distribution (the *null*) is
  fitted as a Gaussian N(mu, s) to the lower half of the empirical distribution, where loops are rare:
  Phi((b - mu) / s) = F(b) there, a straight line b = mu + s Phi^-1(F) fitted by least squares. Every pair is
  counted as a possible unrelated one (the null's weight is 1, Storey's conservative choice): fitting the weight
  as well was tried, and on the lower half it trades off against the deviation (on two-group samples with known
  loops it misjudged the precision by up to 0.17; tests/loopclosure/test_decision.py).
* Among the N pairs, the K with the highest beliefs are expected to hold N (1 - Phi((b_K - mu) / s)) unrelated
  pairs, so their expected precision is one minus that over K. The decision takes the largest K whose expected
  precision reaches the target (``target_precision``, 0.95 by default) and reports that expected precision.
* A set at a target precision is allowed its share of unrelated pairs, and the tail-area rule fills that allowance
  even where the beliefs have run out of loops (after a clear gap, the next pairs are the null's own tail). So the
  decided pairs also stop before the first one that is more likely unrelated than a loop: its *local* false
  discovery rate (Efron's lfdr: the null's expected count of beliefs within half its deviation of the pair's, over
  the count observed there) must stay at most one half.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

_FIT_QUANTILES = np.linspace(0.02, 0.5, 49)  # the lower half of the beliefs: where the null is fitted


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
    those (None when none is decided); ``decided`` how many of the ``pairs``; the ``null`` it came from."""

    threshold: float
    expected_precision: float | None
    decided: int
    pairs: int
    target_precision: float
    null: NullFit | None

    def summary(self) -> dict:
        return {"threshold": self.threshold if np.isfinite(self.threshold) else None,
                "expected_precision": self.expected_precision, "decided": self.decided, "pairs": self.pairs,
                "target_precision": self.target_precision,
                "null": None if self.null is None else self.null.__dict__}


def fit_null(beliefs) -> NullFit | None:
    """The Gaussian fitted to the lower half of ``beliefs`` (finite ones); None with fewer than 20 or no spread."""
    values = np.sort(np.asarray(beliefs, np.float64)[np.isfinite(beliefs)])
    if values.size < 20:
        return None
    # Phi((x - mu) / s) = F  <=>  x = mu + s Phi^-1(F): a least-squares line through the lower half's quantiles.
    slope, intercept = np.polyfit(ndtri(_FIT_QUANTILES), np.quantile(values, _FIT_QUANTILES), 1)
    return NullFit(float(intercept), float(slope)) if slope > 0 else None


def decide(beliefs, target_precision: float = 0.95, pairs: int | None = None) -> Decision:
    """The threshold on ``beliefs`` (one per pair; -inf for pairs that cannot be loops, e.g. never scored, which
    count as pairs but never as decisions) at which the expected precision reaches ``target_precision``.
    ``pairs``: how many pairs there are in all, when more than the beliefs given (the others, never scored, count
    like -inf ones)."""
    if not 0 < target_precision <= 1:
        raise ValueError(f"target precision must be in (0, 1], got {target_precision}")
    beliefs = np.asarray(beliefs, np.float64).reshape(-1)
    if np.any(np.isnan(beliefs)):
        raise ValueError("beliefs contain NaN")
    if pairs is not None and pairs < beliefs.size:
        raise ValueError(f"{pairs} pairs in all, fewer than the {beliefs.size} beliefs given")
    pairs = beliefs.size if pairs is None else int(pairs)
    null = fit_null(beliefs)
    if null is None:
        return Decision(np.inf, None, 0, pairs, target_precision, None)
    ranked = np.sort(beliefs[np.isfinite(beliefs)])[::-1]
    precision = expected_precisions(ranked, pairs, null)
    reach = np.flatnonzero(precision >= target_precision)
    if not reach.size:
        return Decision(np.inf, None, 0, pairs, target_precision, null)
    k = int(reach.max())
    unlikely = np.flatnonzero(local_fdr(ranked, pairs, null)[: k + 1] > 0.5)
    if unlikely.size:
        k = int(unlikely[0]) - 1
        if k < 0:
            return Decision(np.inf, None, 0, pairs, target_precision, null)
    return Decision(float(ranked[k]), float(precision[k]), k + 1, pairs, target_precision, null)


def local_fdr(ranked: np.ndarray, pairs: int, null: NullFit) -> np.ndarray:
    """Local false discovery rate at each of the ``ranked`` beliefs (any order): the null's expected count of the
    ``pairs`` within half the null's deviation of the belief, over the count of beliefs observed there."""
    values = np.sort(ranked)
    h = 0.5 * null.scale
    observed = np.searchsorted(values, ranked + h, "right") - np.searchsorted(values, ranked - h, "left")
    expected = pairs * (null.survival(ranked - h) - null.survival(ranked + h))
    return expected / np.maximum(observed, 1)


def expected_precisions(ranked: np.ndarray, pairs: int, null: NullFit) -> np.ndarray:
    """Expected precision of the top K = 1, 2, ... beliefs (``ranked`` in decreasing order) among ``pairs``."""
    k = np.arange(1, ranked.size + 1)
    return 1.0 - np.minimum(pairs * null.survival(ranked) / k, 1.0)


def expected_precision(beliefs, threshold: float, null: NullFit | None) -> float | None:
    """Expected precision of the pairs with belief >= ``threshold`` under ``null``; None when there are none."""
    beliefs = np.asarray(beliefs, np.float64).reshape(-1)
    decided = int(np.sum(beliefs >= threshold))
    if null is None or not decided:
        return None
    return float(1.0 - min(beliefs.size * float(null.survival(threshold)) / decided, 1.0))
