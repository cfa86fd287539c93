"""What a recognised place costs the localizer as its number of loops grows (a LoopClosure may carry 1e5): the
particles' weighing (``place_log_factor``, a k-d tree query) and the monitor's nearest place (``pose_distances``, one
solve) against the direct loops over the places they replaced, measured in the same process. Prints medians (ms) and
the ratio of each to its loop; the values agree (checked).

    .venv/bin/python benchmarks/place_weighing.py [--particles 5000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.localization.health import pose_distances  # noqa: E402
from semloc_core.localization.proposals import PlaceProposalConfig, place_log_factor  # noqa: E402


def factor_by_loop(positions, places, probability: float, place_std: float) -> np.ndarray:
    """The reference: the nearest place's squared distance by a loop over the places (the code before the tree)."""
    nearest = np.full(positions.shape[0], np.inf)
    for x, y in places[:, :2]:
        nearest = np.minimum(nearest, (positions[:, 0] - x) ** 2 + (positions[:, 1] - y) ** 2)
    return np.log1p(-probability * (1.0 - np.exp(-0.5 * nearest / place_std ** 2)))


def nearest_by_loop(estimate, places, extra_std: float) -> float:
    """The reference: one solve per place (the monitor's code before ``pose_distances``)."""
    covariance = np.asarray(estimate.covariance)[:2, :2] + extra_std ** 2 * np.eye(2)
    best = math.inf
    for place in places:
        delta = place[:2] - estimate.pose[:2]
        best = min(best, math.sqrt(max(float(delta @ np.linalg.solve(covariance, delta)), 0.0)))
    return best


def median_ms(run, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    config, place_std = PlaceProposalConfig(max_odds=9.0), 0.3
    positions = rng.uniform(-5, 5, (args.particles, 3))
    estimate = SimpleNamespace(covariance=np.diag([0.01, 0.01, 0.02]), pose=np.zeros(3))
    print(f"{args.particles} particles, medians of {args.repeats}")
    for count in (10, 1_000, 100_000):
        places = np.column_stack([rng.uniform(-5, 5, (count, 2)), rng.uniform(-3, 3, count)])
        beliefs = np.full(count, 20.0)  # every loop sure: the factor's probability is capped at 1 - 1 / max_odds
        p = 1.0 - 1.0 / config.max_odds
        factor = place_log_factor(positions, places, beliefs, config, place_std)
        np.testing.assert_allclose(factor, factor_by_loop(positions, places, p, place_std), rtol=1e-12, atol=1e-15)
        assert math.isclose(float(pose_distances(estimate, places, place_std).min()),
                            nearest_by_loop(estimate, places, place_std), rel_tol=1e-12)
        tree = median_ms(lambda: place_log_factor(positions, places, beliefs, config, place_std), args.repeats)
        loop = median_ms(lambda: factor_by_loop(positions, places, p, place_std), args.repeats)
        solve = median_ms(lambda: pose_distances(estimate, places, place_std).min(), args.repeats)
        solves = median_ms(lambda: nearest_by_loop(estimate, places, place_std), args.repeats)
        print(f"{count:>7} places: weighing {tree:8.2f} ms (loop {loop:8.2f} ms, {tree / loop:.3f} x); "
              f"nearest place {solve:7.2f} ms (loop {solves:8.2f} ms, {solve / solves:.3f} x)")


if __name__ == "__main__":
    main()
