"""What the localizer's state costs beside the filter (issue 34): the particle filter's step against the health
monitor's weighing of each frame - probes only, with its rivals, and with the second perception model weighing the
same poses - on the filter tests' table top (synthetic heatlines, tracking from the true pose). Prints medians (ms)
and each monitor variant's ratio to the filter step, measured in the same process.

    .venv/bin/python benchmarks/localization_health.py [--frames 200]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.localization import InnerProductModel  # noqa: E402
from semloc_core.localization.health import HealthConfig, HealthMonitor, estimate_margin  # noqa: E402
from tests.localization.test_filter import _filter  # noqa: E402
from tests.localization.worlds import tabletop  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    args = parser.parse_args(argv)
    world = tabletop(frames=args.frames, seed=3)
    particle_filter = _filter(world)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.02, 0.02, 0.05]) ** 2)
    second = InnerProductModel(world.semantic_map)
    variants = {"probes": HealthConfig(rivals=0), "rivals": HealthConfig(),
                "rivals + second model": HealthConfig(second_model=True)}
    monitors = {name: HealthMonitor.for_filter(particle_filter.config, config) for name, config in variants.items()}
    times: dict[str, list[float]] = {"filter step": [], **{name: [] for name in variants}}
    rng, probe_rng = np.random.default_rng(100), np.random.default_rng(200)
    for k in range(world.poses.shape[0]):
        heatlines = world.heatlines(k)
        start = time.perf_counter()
        estimate = particle_filter.step(heatlines, world.odometry(k, rng), world.dt)
        times["filter step"].append(time.perf_counter() - start)
        for name, monitor in monitors.items():
            start = time.perf_counter()
            pair = None if monitor.second_rivals is None else (second, monitor.second_rivals)
            margin = estimate_margin(particle_filter.perception, heatlines, estimate.pose, particle_filter.free_space,
                                     probe_rng, monitor.config.probes, rivals=monitor.rivals, second=pair)
            monitor.update(estimate, margin)
            times[name].append(time.perf_counter() - start)
    step = float(np.median(times["filter step"][5:]))
    print(f"{args.frames} frames, {particle_filter.states.shape[0]} particles at the end")
    for name, values in times.items():
        median = float(np.median(values[5:]))
        print(f"{name:>24}: {1e3 * median:6.2f} ms  ({median / step:.2f} x the filter step)")
    print(f"medians; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
