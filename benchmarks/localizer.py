"""Localizer speed: perception updates and full filter steps per second, against dense numpy, and a size sweep.

    .venv/bin/python benchmarks/localizer.py [--repeats 30] [--sweep 1000,10000,50000,100000,200000] [--json OUT]

Targets (issue 35): a filter step <= 2 ms at 1,000 particles and >= 100 steps/s at 10,000 with the view geometry,
on one core (the kernels are single-threaded numba; NUMBA_NUM_THREADS and OPENBLAS_NUM_THREADS are printed).

Workload (issue 6): 10,000 particles, 5 classes, 360 bearing bins (a full panorama, every bin observed), 20 objects
(4 per class) in a 10 m x 10 m map. Heatlines are synthetic-scores heatlines (§4.8.3) seen from a pose in the map.

* ``weigh B`` / ``weigh A``: one perception update (model B eq. 4.27 in log space, model A eq. 4.6) with the fast
  path, against ``log_likelihood_reference`` / ``inner_product_reference`` - the same equations written
  straightforwardly in numpy over (particles x classes x bins). ``weigh B + view`` adds the optional view geometry
  of a 1024 x 256 panorama at 1.2 m, every bin with its elevation span (objects outside the image or hidden behind
  nearer ones are not expected; in this world nearly every object is in view, and all take part in the occlusion
  test). The observation's tables are
  built once (the heatlines object is the same) and not timed here.
* ``filter step B``: predict (eq. 4.5) + correct + resample when due + estimate, against the same filter whose
  perception model is the dense numpy one. Each step gets its own Heatlines object, as the localizer worker's
  frames do, so the per-observation work (the model's prefix tables, the detections) is part of every step.
* sweep: filter step time (model B, without and with the view geometry) and peak traced memory (tracemalloc: numpy
  allocations, including those made for the numba kernels) from 1k to 200k particles (KLD adaptation off, so the
  set keeps its size).

Every figure is a median over repeats after a warm-up (numba compiles on first use), wall-clock with the CPU time
in brackets; the load average is printed. The machine may be shared: run it again when figures look off.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.bearing import Heatlines  # noqa: E402
from semloc_core.camera import EquirectangularCamera, forward_extrinsic  # noqa: E402
from semloc_core.io.semantic_map import SemanticMap  # noqa: E402
from semloc_core.localization import (DifferentialDriveModel, FilterConfig, FreeSpace, GenerativeScoreModel,  # noqa: E402
                                      InnerProductModel, Odometry, ParticleFilter, ViewGeometry, Weighing,
                                      inner_product_reference, log_likelihood_reference, synthetic_scores_heatlines,
                                      synthetic_scores_likelihood, visible_objects)

CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")


def make_world(seed: int = 0):
    rng = np.random.default_rng(seed)
    objects = [{"class": CLASSES[k % 5], "position": [*rng.uniform(0.5, 9.5, 2), 0.4], "size": [0.3, 0.3, 0.5]}
               for k in range(20)]
    semantic_map = SemanticMap.from_objects(objects, bounds=[[0, 0], [10, 10]])
    observed = np.ones(360, dtype=bool)
    pose = np.array([5.0, 5.0, 0.3])
    heatlines = synthetic_scores_heatlines(visible_objects(pose, semantic_map, observed, CLASSES), observed)
    return semantic_map, heatlines, pose


class DenseModelB:
    """Model B through the dense numpy reference (same equations, same interface)."""

    def __init__(self, semantic_map, likelihood):
        self.semantic_map, self.likelihood = semantic_map, likelihood

    def weigh(self, states, heatlines, view=None):
        log_likelihood = log_likelihood_reference(states, heatlines, self.semantic_map, self.likelihood, view=view)
        return Weighing(log_likelihood, np.ones_like(log_likelihood), True)


def median_time(function, repeats: int) -> float:
    return median_times(function, repeats)[0]


def median_times(function, repeats: int) -> tuple[float, float]:
    """(wall, CPU) medians in seconds over ``repeats`` calls after a warm-up."""
    function()  # warm-up (numba compilation, caches)
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        function()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def make_filter(perception, semantic_map, n: int, seed: int = 0) -> ParticleFilter:
    config = FilterConfig(max_particles=n, min_particles=min(500, n), adaptive=False)
    particle_filter = ParticleFilter(DifferentialDriveModel(), perception, FreeSpace.from_map(semantic_map), config,
                                     rng=seed)
    particle_filter.initialize_global(n)
    return particle_filter


def filter_step(particle_filter, heatlines, view=None):
    """One frame: predict, correct with a new frame's heatlines (a fresh object, as the worker decodes each frame),
    estimate."""
    frame = Heatlines(heatlines.classes, heatlines.scores, heatlines.observed)
    particle_filter.predict(Odometry.from_velocity(0.5, 0.1, 0.1))
    particle_filter.correct(frame, force=True, view=view)
    return particle_filter.estimate()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=10000)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--reference-repeats", type=int, default=3)
    parser.add_argument("--sweep", default="1000,10000,50000,100000,200000")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args(argv)

    semantic_map, heatlines, _ = make_world()
    likelihood = synthetic_scores_likelihood(CLASSES)
    model_b = GenerativeScoreModel(semantic_map, likelihood)
    model_a = InnerProductModel(semantic_map)
    rng = np.random.default_rng(1)
    n = args.particles
    states = np.column_stack([rng.uniform(0, 10, n), rng.uniform(0, 10, n), rng.uniform(-math.pi, math.pi, n)])
    results: dict = {"particles": n, "classes": 5, "bins": 360, "objects": 20, "rows": []}

    def row(name, fast, reference):
        ratio = reference / fast
        results["rows"].append({"what": name, "fast_ms": fast * 1e3, "fast_hz": 1 / fast,
                                "numpy_ms": reference * 1e3, "numpy_hz": 1 / reference, "speedup": ratio})
        print(f"{name:<16} fast {fast * 1e3:8.2f} ms ({1 / fast:7.1f} Hz)   numpy {reference * 1e3:9.1f} ms "
              f"({1 / reference:6.2f} Hz)   speed-up x{ratio:6.1f}")

    print(f"load average {os.getloadavg()[0]:.1f}; {n} particles, 5 classes, 360 bins, 20 objects; medians of "
          f"{args.repeats} (fast) and {args.reference_repeats} (numpy) runs")
    fast = median_time(lambda: model_b.weigh(states, heatlines), args.repeats)
    reference = median_time(lambda: log_likelihood_reference(states, heatlines, semantic_map, likelihood),
                            args.reference_repeats)
    row("weigh B", fast, reference)
    view = ViewGeometry.from_camera(EquirectangularCamera(1024, 256, forward_extrinsic(1.2)), 360, camera_height=1.2)
    fast = median_time(lambda: model_b.weigh(states, heatlines, view), args.repeats)
    reference = median_time(lambda: log_likelihood_reference(states, heatlines, semantic_map, likelihood, view=view),
                            args.reference_repeats)
    row("weigh B + view", fast, reference)
    fast = median_time(lambda: model_a.weigh(states, heatlines), args.repeats)
    reference = median_time(lambda: inner_product_reference(states, heatlines, semantic_map),
                            args.reference_repeats)
    row("weigh A", fast, reference)
    fast_filter = make_filter(model_b, semantic_map, n)
    dense_filter = make_filter(DenseModelB(semantic_map, likelihood), semantic_map, n)
    fast = median_time(lambda: filter_step(fast_filter, heatlines), args.repeats)
    reference = median_time(lambda: filter_step(dense_filter, heatlines), args.reference_repeats)
    row("filter step B", fast, reference)
    fast = median_time(lambda: filter_step(fast_filter, heatlines, view), args.repeats)
    reference = median_time(lambda: filter_step(dense_filter, heatlines, view), args.reference_repeats)
    row("step B + view", fast, reference)

    print("\nsweep (filter step B, fast path, without / with the view geometry; peak = tracemalloc peak during one "
          "step)")
    results["sweep"] = []
    for count in (int(v) for v in args.sweep.split(",") if v):
        row = {"particles": count}
        for label, step_view in (("", None), ("_view", view)):
            particle_filter = make_filter(model_b, semantic_map, count)
            wall, cpu = median_times(lambda: filter_step(particle_filter, heatlines, step_view),
                                     max(3, args.repeats // 3))
            row.update({f"step{label}_ms": wall * 1e3, f"step{label}_cpu_ms": cpu * 1e3, f"hz{label}": 1 / wall})
        tracemalloc.start()
        filter_step(particle_filter, heatlines, view)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        row["peak_mb"] = peak / 2**20
        results["sweep"].append(row)
        print(f"  {count:>7} particles: {row['step_ms']:8.2f} ms/step ({row['step_cpu_ms']:.2f} CPU, "
              f"{row['hz']:7.1f} Hz); with view {row['step_view_ms']:8.2f} ms ({row['step_view_cpu_ms']:.2f} CPU, "
              f"{row['hz_view']:7.1f} Hz), peak {row['peak_mb']:7.1f} MB")
    targets = {row["particles"]: row for row in results["sweep"]}
    if 1000 in targets and 10000 in targets:
        small, large = targets[1000]["step_ms"], targets[10000]["hz_view"]
        reference = next(r for r in results["rows"] if r["what"] == "step B + view")
        against = (f" (the numpy filter step with view at {n:,} particles in this run: {reference['numpy_ms']:.0f} ms, "
                   f"x{reference['numpy_ms'] * large / 1e3:.0f} the sweep's)" if n == 10000 else "")
        print(f"targets: 1,000 particles <= 2 ms a step: {small:.2f} ms {'OK' if small <= 2.0 else 'FAIL'}; "
              f"10,000 with view >= 100 Hz: {large:.1f} Hz {'OK' if large >= 100 else 'FAIL'}{against}")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; NUMBA_NUM_THREADS="
          f"{os.environ.get('NUMBA_NUM_THREADS', 'unset')}, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')} (the kernels are single-threaded)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
