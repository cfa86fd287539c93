"""Localizer speed: perception updates and full filter steps per second, against dense numpy, and a size sweep.

    .venv/bin/python benchmarks/localizer.py [--repeats 30] [--sweep 1000,10000,50000,100000,200000] [--json OUT]

Workload (issue 6): 10,000 particles, 5 classes, 360 bearing bins (a full panorama, every bin observed), 20 objects
(4 per class) in a 10 m x 10 m map. Heatlines are synthetic-scores heatlines (§4.8.3) seen from a pose in the map.

* ``weigh B`` / ``weigh A``: one perception update (model B eq. 4.27 in log space, model A eq. 4.6) with the fast
  path, against ``log_likelihood_reference`` / ``inner_product_reference`` - the same equations written
  straightforwardly in numpy over (particles x classes x bins). ``weigh B + view`` adds the optional view geometry
  (objects outside a panorama's image or hidden behind nearer ones are not expected).
* ``filter step B``: predict (eq. 4.5) + correct + resample when due + estimate, against the same filter whose
  perception model is the dense numpy one.
* sweep: filter step time and peak traced memory (tracemalloc: numpy allocations, including those made for the
  numba kernels) from 1k to 200k particles (KLD adaptation off, so the set keeps its size).

Every figure is a median over repeats after a warm-up (numba compiles on first use). The machine may be shared:
run it again when figures look off.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

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

    def weigh(self, states, heatlines):
        log_likelihood = log_likelihood_reference(states, heatlines, self.semantic_map, self.likelihood)
        return Weighing(log_likelihood, np.ones_like(log_likelihood), True)


def median_time(function, repeats: int) -> float:
    function()  # warm-up (numba compilation, caches)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def make_filter(perception, semantic_map, n: int, seed: int = 0) -> ParticleFilter:
    config = FilterConfig(max_particles=n, min_particles=min(500, n), adaptive=False)
    particle_filter = ParticleFilter(DifferentialDriveModel(), perception, FreeSpace.from_map(semantic_map), config,
                                     rng=seed)
    particle_filter.initialize_global(n)
    return particle_filter


def filter_step(particle_filter, heatlines):
    particle_filter.predict(Odometry.from_velocity(0.5, 0.1, 0.1))
    particle_filter.correct(heatlines, force=True)
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

    print(f"{n} particles, 5 classes, 360 bins, 20 objects; medians of {args.repeats} (fast) and "
          f"{args.reference_repeats} (numpy) runs")
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

    print("\nsweep (filter step B, fast path; peak = tracemalloc peak during one step)")
    results["sweep"] = []
    for count in (int(v) for v in args.sweep.split(",") if v):
        particle_filter = make_filter(model_b, semantic_map, count)
        seconds = median_time(lambda: filter_step(particle_filter, heatlines), max(3, args.repeats // 3))
        tracemalloc.start()
        filter_step(particle_filter, heatlines)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        results["sweep"].append({"particles": count, "step_ms": seconds * 1e3, "hz": 1 / seconds,
                                 "peak_mb": peak / 2**20})
        print(f"  {count:>7} particles: {seconds * 1e3:8.2f} ms/step ({1 / seconds:7.1f} Hz), "
              f"peak {peak / 2**20:7.1f} MB")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
