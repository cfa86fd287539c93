"""What the backward pass costs a live frame (issue 34): on the filter tests' table top the filter starts at a wrong
pose, is lost until its recovery finds the truth, and the smoother's pass then runs ``steps_per_frame`` steps per
live frame. Prints, in the same process, the median of the live step (filter step and the monitor's verdict) and of
the smoother's work per frame while a pass runs (its record and advance), and their ratio.

    .venv/bin/python benchmarks/localization_smoothing.py [--frames 300] [--steps-per-frame 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.localization import Status  # noqa: E402
from semloc_core.localization.health import HealthMonitor, LocalizationState, judge  # noqa: E402
from semloc_core.localization.smoothing import BackwardSmoother, PastFrame, SmoothingConfig  # noqa: E402
from tests.localization.test_filter import _filter  # noqa: E402
from tests.localization.worlds import tabletop  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--steps-per-frame", type=int, default=SmoothingConfig().steps_per_frame)
    args = parser.parse_args(argv)
    world = tabletop(frames=args.frames, seed=3)
    particle_filter = _filter(world)
    particle_filter.initialize_pose(world.poses[0] * [-1.0, -1.0, 1.0], np.diag([0.02, 0.02, 0.05]) ** 2)
    monitor = HealthMonitor.for_filter(particle_filter.config)
    smoother = BackwardSmoother(SmoothingConfig(steps_per_frame=args.steps_per_frame),
                                lambda rng: _filter(world, seed=rng),
                                lambda: HealthMonitor.for_filter(particle_filter.config), monitor.config.rival_frames,
                                np.random.default_rng(7))
    rng, probes = np.random.default_rng(100), np.random.default_rng(200)
    live, added, ended = [], [], []
    for k in range(world.poses.shape[0]):
        heatlines, odometry = world.heatlines(k), world.odometry(k, rng)
        start = time.perf_counter()
        estimate = particle_filter.step(heatlines, odometry, world.dt)
        moved = None if odometry is None else (odometry.dx, odometry.dy, odometry.dtheta)
        verdict = judge(monitor, particle_filter, estimate, heatlines, None, probes, moved)
        live.append(time.perf_counter() - start)
        start = time.perf_counter()
        smoother.record(PastFrame(k, heatlines, None, moved, world.dt), verdict.state is LocalizationState.LOCALIZED,
                        estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING), particle_filter.snapshot)
        running = bool(smoother.passes)
        ended += smoother.advance()
        if running or ended and ended[-1][0] == k:
            added.append(time.perf_counter() - start)
    step = float(np.median(live[5:]))
    print(f"{args.frames} frames, {particle_filter.states.shape[0]} particles at the end, "
          f"{args.steps_per_frame} pass steps per frame")
    for anchor, reason, poses in ended:
        print(f"  pass from frame {anchor}: {len(poses)} poses ({reason})")
    if not added:
        print(f"no backward pass ran in {args.frames} frames: no ratio (more --frames)")
        return 1
    median = float(np.median(added))
    print(f"{'live step':>22}: {1e3 * step:6.2f} ms")
    print(f"{'pass, per live frame':>22}: {1e3 * median:6.2f} ms  ({median / step:.2f} x the live step, "
          f"{len(added)} frames)")
    print(f"medians; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
