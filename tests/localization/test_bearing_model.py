"""Calibrating model B's bearing model on training frames: bin correlation (the exponent) and σ (eq. 4.26)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.bearing import Heatlines
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import ScoreLikelihood
from semloc_core.localization.bearing_model import correlation_bins, fit_sigma


def _frames(rng, n_frames, window, observed):
    """Heatlines whose background is white noise smoothed by a box of ``window`` bins."""
    out = []
    for _ in range(n_frames):
        noise = rng.normal(0.0, 1.0, 360 + window)
        smooth = np.convolve(noise, np.ones(window) / window, mode="valid")[:360]
        out.append(Heatlines(("mug",), smooth[None].astype(np.float32), observed))
    return out


@pytest.mark.parametrize("window", [1, 5, 9])
def test_correlation_bins_of_box_smoothed_noise(window):
    # a box of w bins: rho_k = 1 - k/w, so 1 + 2 sum rho_k = w (exactly, for the full sum); scores are centred per
    # frame, which biases the estimate low by ~w / (observed bins): a 150-degree camera keeps that small
    observed = np.zeros(360, bool)
    observed[100:250] = True
    tau = correlation_bins(_frames(np.random.default_rng(window), 400, window, observed), cutoff=0.0)
    assert tau == pytest.approx(window, rel=0.12)
    panorama = correlation_bins(_frames(np.random.default_rng(7), 100, window, np.ones(360, bool)), cutoff=0.0)
    assert panorama == pytest.approx(window, rel=0.12)
    assert correlation_bins([]) == 1.0


def test_fit_sigma_recovers_the_spread_the_scores_were_drawn_with():
    """Scores drawn from eq. 4.23 with P = a Gaussian of 3 degrees around each mug: the maximum-likelihood sigma
    over a grid is 3 degrees."""
    rng = np.random.default_rng(0)
    likelihood = ScoreLikelihood.gaussian(["mug"], 0.7, 0.15, 0.2, 0.15)
    semantic_map = SemanticMap.from_objects([{"class": "mug", "position": [2.0, 0.0]},
                                             {"class": "mug", "position": [1.5, 1.2]}], bounds=[[-3, -3], [3, 3]])
    centres = -np.pi + (np.arange(360) + 0.5) * (2 * np.pi / 360)
    frames = []
    for _ in range(60):
        pose = np.array([rng.uniform(-1, 0), rng.uniform(-1, 0), rng.uniform(-0.3, 0.3)])
        probability = np.zeros(360)
        for x, y in semantic_map.positions[:, :2]:
            bearing = math.atan2(y - pose[1], x - pose[0]) - pose[2]
            gap = (centres - bearing + np.pi) % (2 * np.pi) - np.pi
            probability = np.maximum(probability, np.exp(-0.5 * (gap / math.radians(3.0)) ** 2))
        detected = rng.random(360) < probability
        scores = np.where(detected, rng.normal(0.7, 0.15, 360), rng.normal(0.2, 0.15, 360))
        lines = Heatlines(("mug",), scores[None].astype(np.float32), np.abs(centres) < math.radians(60))
        frames.append((semantic_map, pose, lines, None))
    sigma, totals = fit_sigma(frames, likelihood, sigmas_deg=(1.5, 2.0, 3.0, 4.0, 5.0, 8.0))
    assert math.degrees(sigma) == pytest.approx(3.0)
    assert totals[3.0] > totals[5.0] > totals[8.0]
    with pytest.raises(ValueError):
        fit_sigma([], likelihood)
