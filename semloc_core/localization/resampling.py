"""Resampling: effective sample size, low-variance (systematic) resampling, KLD-adaptive sample count.

References: Thrun, Burgard, Fox, *Probabilistic Robotics*, table 4.4 (low-variance sampler) and table 8.4 (KLD
sampling, Fox 2003).
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np


def normalize_log_weights(log_weights) -> np.ndarray:
    """Normalised weights from log weights (stable); uniform if every weight is -inf or nan."""
    log_weights = np.asarray(log_weights, dtype=np.float64)
    top = log_weights.max(initial=-np.inf)
    if np.isfinite(top):  # no NaN, no +inf: -inf entries need no mask (exp(-inf - top) = 0)
        weights = np.exp(log_weights - top)
        return weights / weights.sum()
    finite = np.isfinite(log_weights)
    if not finite.any():
        return np.full(log_weights.shape, 1.0 / max(log_weights.size, 1))
    shifted = np.where(finite, log_weights - log_weights[finite].max(), -np.inf)
    weights = np.exp(shifted)
    return weights / weights.sum()


def effective_sample_size(weights) -> float:
    """ESS = 1 / Σ w² of normalised weights."""
    weights = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(weights * weights))


def low_variance_resample(weights, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of n particles drawn with one random offset and n equally spaced pointers (systematic resampling)."""
    weights = np.asarray(weights, dtype=np.float64)
    n = int(n)
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    cumulative = np.cumsum(weights)
    cumulative /= cumulative[-1]
    pointers = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cumulative, pointers, side="right"), weights.size - 1)


def kld_sample_count(k: np.ndarray | int, epsilon: float, z: float) -> np.ndarray:
    """Particles needed so that, with probability given by the normal quantile z, the KL divergence between the
    sample-based and the true posterior over k occupied bins stays below epsilon (Fox 2003)."""
    k = np.asarray(k, dtype=np.float64)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return np.where(k <= 1, 1.0, np.ceil(n))


def kld_resample(states, weights, rng: np.random.Generator, min_particles: int, max_particles: int,
                 epsilon: float = 0.05, probability: float = 0.99, bin_size_xy: float = 0.5,
                 bin_size_theta: float = math.radians(10.0)) -> np.ndarray:
    """Indices of a KLD-adaptive resample: as many particles as the occupied (x, y, θ) bins require, within
    [min_particles, max_particles].

    Draws ``max_particles`` with the low-variance sampler, shuffles them (so that every prefix is a fair sample), and
    keeps the shortest prefix whose length reaches the KLD bound for the number of bins that prefix occupies.
    """
    states = np.asarray(states, dtype=np.float64)
    if not 0 < min_particles <= max_particles:
        raise ValueError(f"need 0 < min_particles <= max_particles, got {min_particles}, {max_particles}")
    drawn = low_variance_resample(weights, max_particles, rng)
    rng.shuffle(drawn)
    chosen = states[drawn]
    _, first_index = np.unique(bin_keys(chosen, bin_size_xy, bin_size_theta), return_index=True)
    first_index.sort()
    lengths = np.arange(1, max_particles + 1)
    occupied = np.searchsorted(first_index, lengths - 1, side="right")  # bins occupied by the first `length`
    needed = kld_sample_count(occupied, epsilon, NormalDist().inv_cdf(probability))
    enough = np.flatnonzero((lengths >= needed) & (lengths >= min_particles))
    count = int(lengths[enough[0]]) if enough.size else max_particles
    return drawn[:count]


def bin_keys(states, bin_size_xy: float, bin_size_theta: float) -> np.ndarray:
    """One int64 per particle naming its (x, y, θ) histogram bin."""
    states = np.asarray(states, dtype=np.float64)
    kx = np.floor(states[:, 0] / bin_size_xy).astype(np.int64)
    ky = np.floor(states[:, 1] / bin_size_xy).astype(np.int64)
    kt = np.floor((states[:, 2] + math.pi) / bin_size_theta).astype(np.int64)
    if kx.size == 0:
        return kx
    kx -= kx.min()
    ky -= ky.min()
    kt -= kt.min()
    return (kx * (int(ky.max()) + 1) + ky) * (int(kt.max()) + 1) + kt
