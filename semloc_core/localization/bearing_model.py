"""Calibrating the two free parameters of model B's bearing model on training frames (thesis §4.7.3, §4.8.2).

Eq. 4.26 models the detection probability around an object's bearing as a Gaussian of spread σ ("a field of view
threshold, in this case 5°"), and eq. 4.18 (assumption 4) treats the scores of neighbouring bearing bins as
independent given the objects. Both depend on the heatline source, not on the world: how wide a detector's response
is around an object (its template size, the projection to bearings) and over how many bins one response or one
background fluctuation extends. Like the score likelihoods p(z|d), p(z|d̄) of §4.8.2 they are therefore fitted on
training frames of other worlds, and then used unchanged where the localizer runs:

* ``correlation_bins``: the integrated autocorrelation time τ of the heatline scores along bearing (in bins) -
  how many consecutive bins carry one independent score. The product of eq. 4.18 counts every bin; over τ
  correlated bins it counts the same evidence τ times, so the log-likelihood is tempered by 1/τ
  (``GenerativeScoreModel(exponent=...)``) - the role of nav2 AMCL's ``max_beams``, which keeps a few beams of a
  scan because neighbouring beams are not independent. Needs no ground truth.
* ``fit_sigma``: the σ of eq. 4.26 that maximises the likelihood (eq. 4.27) of the training frames at their
  ground-truth poses. With σ wider than the source's response, the tails of the expected Gaussians fall where the
  heatline shows background and a pose pays for them; poses from which same-class instances overlap in bearing
  pay less, which pulled the estimate away from the objects (the table top, synthetic scores: 0.4 m).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from semloc_core.bearing import Heatlines


def correlation_bins(heatlines: Iterable[Heatlines], max_lag: int = 60, cutoff: float = 0.05) -> float:
    """Integrated autocorrelation time (bins) of heatline scores along bearing: 1 + 2 Σ_k ρ_k, summed up to the
    first lag whose autocorrelation falls below ``cutoff``; ρ_k pools every frame's observed bins (scores centred
    per frame and class, pairs of observed bins k apart within one frame; a panorama wraps). The median over the
    classes. 1.0 when nothing was observed."""
    sums: dict[str, np.ndarray] = {}
    for lines in heatlines:
        observed = np.asarray(lines.observed, dtype=bool)
        n_bins = observed.shape[0]
        lags = min(max_lag, n_bins // 2)
        wraps = bool(observed.all())
        for row, name in enumerate(lines.classes):
            z = np.asarray(lines.scores[row], dtype=np.float64)
            if observed.sum() < 4:
                continue
            centred = np.where(observed, z - z[observed].mean(), 0.0)
            acc = sums.setdefault(name, np.zeros((3, max_lag + 1)))
            acc[0, 0] += float(centred[observed] @ centred[observed])
            acc[1, 0] += float(observed.sum())
            for lag in range(1, lags + 1):
                if wraps:
                    a, b, both = centred, np.roll(centred, -lag), observed
                else:
                    a, b = centred[:-lag], centred[lag:]
                    both = observed[:-lag] & observed[lag:]
                acc[0, lag] += float(a[both] @ b[both]) if not wraps else float(a @ b)
                acc[1, lag] += float(both.sum())
    taus = []
    for acc in sums.values():
        if acc[1, 0] == 0 or acc[0, 0] <= 0:
            continue
        variance = acc[0, 0] / acc[1, 0]
        tau = 1.0
        for lag in range(1, max_lag + 1):
            if acc[1, lag] == 0:
                break
            rho = acc[0, lag] / acc[1, lag] / variance
            if rho < cutoff:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return float(np.median(taus)) if taus else 1.0


def fit_sigma(frames: Sequence[tuple], likelihood, sigmas_deg: Sequence[float] = (
        1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 8.0), peak: float = 1.0) -> tuple[float, dict]:
    """The σ (radians) of eq. 4.26 among ``sigmas_deg`` that maximises Σ_frames log p(z | x_true, M) (eq. 4.27).

    ``frames``: ``(semantic_map, pose, heatlines, view)`` - the frame's world map, its ground-truth planar pose, its
    heatlines and its ``ViewGeometry`` (or None); frames of several worlds may be pooled. Returns
    (σ, {σ in degrees: total log-likelihood})."""
    from semloc_core.localization.perception import GenerativeScoreModel

    if not frames:
        raise ValueError("fitting sigma needs at least one frame")
    totals = {}
    for sigma_deg in sigmas_deg:
        models: dict[int, GenerativeScoreModel] = {}
        total = 0.0
        for semantic_map, pose, lines, view in frames:
            model = models.get(id(semantic_map))
            if model is None:
                model = models[id(semantic_map)] = GenerativeScoreModel(
                    semantic_map, likelihood, sigma=math.radians(sigma_deg), peak=peak)
            weighing = model.weigh(np.asarray(pose, dtype=np.float64)[None], lines, view)
            if weighing.informative:
                total += float(weighing.log_likelihood[0])
        totals[float(sigma_deg)] = total
    best = max(totals, key=totals.get)
    return math.radians(best), totals
