"""End-to-end latency: camera -> pose over the bus at 30 fps on `tabletop`, against the same core calls in one process.

    .venv/bin/python benchmarks/end_to_end.py [--frames 150] [--repeats 3] [--rate 30] [--scales 0.8]
        [--particles 2000] [--full-graph] [--json out.json]

Distributed (the system): deploy/demo.yaml's camera, detector and localizer as separate processes over zenoh on
loopback (``--full-graph`` adds loop closure and mapper, which share the 2 cores), the camera playing a simulated
table top at ``--rate`` frames per second. The camera stamps each image with the moment it published it (wall
clock, same machine) and this process notes when the heatlines and the pose of that stamp arrive: camera -> pose
latency = pose arrival - the moment the camera published the image, per frame, for the frames that got a pose (the
detector takes the latest image: frames it cannot keep up with are dropped, and counted).

Reference (same run, this process): the same frames, already decoded in memory, through the same core calls -
``detector.heatmaps`` -> ``HeatlineProjector.project`` -> ``ParticleFilter.predict/correct/estimate`` - with the
same detector and filter settings; its per-frame time is what the pipeline costs without processes, bus, codecs,
queues or rerun. Ratio = distributed / reference.

The detector here is the template detector with 8-pixel blocks at one scale (``--scales 0.8``: ~16 ms a frame on this
machine) and the filter keeps 2,000 particles (~2 ms): at 30 fps a frame must cost well under the 33 ms between
frames, or it waits for the previous one in the detector's queue. The demo's 4-pixel, 4-scale detector takes ~180 ms
a frame alone, which no transport can bring under 50 ms (``--scales 1.2,0.85,0.6,0.42`` shows it).
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DETECTOR = {"kind": "templates", "cell": 8, "template_cells": 9, "color_space": "hsv"}
FILTER = {"min_particles": 500, "kld_bin_xy": 0.05, "kld_bin_theta": math.radians(5),
          "cluster_cell": 0.05, "converged_xy_std": 0.1, "converged_theta_std": math.radians(10), "recovery_alpha_slow": 0.0}


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def world(frames: int, cache: Path) -> Path:
    """A 30 fps table-top data set (generated object looks: no dependency on the real data folder), cached."""
    from semloc_core.sim import make_scenario

    folder = cache / f"tabletop-30fps-s0-f{frames}"
    if not (folder / "dataset.json").is_file():
        print(f"writing {folder} ...", file=sys.stderr)
        make_scenario("tabletop", seed=0, frames=frames).write(folder, multiview=False)
    return folder


def percentiles(values) -> dict:
    values = np.asarray(values, float)
    return {"p50": float(np.percentile(values, 50)), "p95": float(np.percentile(values, 95)), "n": int(values.size)}


# ------------------------------------------------------------------------------------------------ reference
def reference(dataset_path: Path, detector_config: dict) -> dict:
    """The pipeline's core calls in this process, frame after frame: per-frame time (ms)."""
    from semloc_core import bearing
    from semloc_core.detection.config import build_detector
    from semloc_core.detection.heatlines import HeatlineProjector
    from semloc_core.io.dataset import open_dataset
    from semloc_core.io.semantic_map import load_semantic_map
    from semloc_core.localization import (FilterConfig, FreeSpace, GenerativeScoreModel, OmniDriveModel,
                                          ParticleFilter, RandomWalkModel, synthetic_scores_likelihood)
    from semloc_core.localization import Odometry as CoreOdometry

    dataset = open_dataset(dataset_path)
    images = [dataset.image(i) for i in range(len(dataset))]  # decoded up front: the camera's work is not timed
    detector = build_detector(detector_config)
    projector = HeatlineProjector(dataset.camera, tuple(detector.classes), bearing.BearingGrid(360))
    semantic_map = load_semantic_map(dataset_path / "semantic_map.json")
    settings = dict(FILTER)
    for name in ("kld_bin_theta", "converged_theta_std"):
        settings[name] = math.radians(settings.pop(f"{name}_deg"))
    motion = OmniDriveModel(0.05, 0.01, 0.05, 0.01, fallback=RandomWalkModel(0.2, 0.2))
    model = GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(tuple(detector.classes)),
                                 sigma=math.radians(5.0), exponent=0.3)
    pf = ParticleFilter(motion, model, FreeSpace.from_map(semantic_map), FilterConfig(**settings),
                        rng=np.random.default_rng(0))
    pf.initialize_pose(dataset.poses2d[0], np.diag([0.25, 0.25, 0.0685]))
    odometry = dataset.odometry.as_array()
    times = []
    for i, image in enumerate(images):
        start = time.perf_counter()
        heatmaps = detector.heatmaps(image)
        heatlines = projector.project([heatmaps], T_body_cam=[dataset.T_body_cam[i]])
        step = CoreOdometry.from_twist(*odometry[i]) if odometry[i, 3] > 0 else None
        pf.predict(step, float(odometry[i, 3]) or 1 / 30)
        pf.correct(heatlines)
        pf.estimate()
        times.append((time.perf_counter() - start) * 1e3)
    return {"latency_ms": percentiles(times[5:]), "frames": len(times)}  # the first frames warm caches up


# ------------------------------------------------------------------------------------------------ distributed
def distributed(dataset_path: Path, detector_file: Path, rate: float, full_graph: bool, run_dir: Path) -> dict:
    from schemas import decode, keys
    from schemas.detection import Heatlines
    from schemas.localization import PoseEstimate
    from services.bus import BusConfig, open_session
    from services.launcher import Launcher, load_graph

    hub = f"tcp/127.0.0.1:{_free_port()}"
    truth = np.load(dataset_path / "poses.npz", allow_pickle=False)["poses2d"]
    nodes = {
        # Wall-clock stamps: each frame carries the moment the camera published it, so latency is measured from
        # there (a subscriber's own view of the image can lag behind the detector's by a few ms).
        "camera": {"config": {"source": str(dataset_path), "rate": rate, "stamp": "wall"}},
        "detector": {"config": {"detector_file": str(detector_file)}},
        "localizer": {"config": {"map": str(dataset_path / "semantic_map.json"), "score_likelihood": "synthetic",
                                 "initial_pose": [float(v) for v in truth[0]], "filter": FILTER}},
        "mapper": {"enabled": full_graph, "config": {"detector_file": str(detector_file)}},
        "loopclosure": {"enabled": full_graph},
    }
    graph = load_graph(REPO / "deploy" / "demo.yaml", {"hub": hub, "rerun": {"mode": "off"},
                                                        "state_dir": str(run_dir / "state"), "nodes": nodes})
    processing = graph.model_copy(update={"nodes": {k: v for k, v in graph.nodes.items() if k != "camera"}})
    sensor = graph.model_copy(update={"name": "bench-camera", "hub": None, "nodes": {"camera": graph.nodes["camera"]},
                                      "bus": BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])})
    workers = [n for n, spec in processing.nodes.items() if spec.enabled]
    arrivals = {"heatlines": [], "pose": []}

    def record(name, frame_type):
        def callback(sample):
            arrived = time.time_ns()
            arrivals[name].append((arrived, decode(sample.payload.to_bytes(), expected=frame_type).header.stamp_ns))
        return callback

    with Launcher(processing, run_dir=run_dir / "graph"), \
            open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
        from services.demo_collector import Collector

        collector = Collector(session, graph.robot)  # only to know when every worker runs
        deadline = time.monotonic() + 120
        while len(collector.running(workers)) < len(workers):
            if time.monotonic() > deadline:
                raise RuntimeError(f"workers did not start; see {run_dir / 'graph' / 'logs'}")
            time.sleep(0.2)
        collector.close()
        subscribers = [session.declare_subscriber(keys.detector_heatlines(graph.robot), record("heatlines", Heatlines)),
                       session.declare_subscriber(keys.localizer_pose(graph.robot), record("pose", PoseEstimate))]
        with Launcher(sensor, run_dir=run_dir / "camera") as camera:
            camera.wait(timeout=600)
        time.sleep(2.0)  # the last frames through the pipeline
        for subscriber in subscribers:
            subscriber.undeclare()
    latency = {}
    for name, values in arrivals.items():
        first = {}
        for arrived, stamp in values:  # one figure per frame: its first output
            first.setdefault(stamp, arrived)
        latency[name] = [(arrived - stamp) * 1e-6 for stamp, arrived in first.items()]
    if not latency["pose"]:
        raise RuntimeError(f"no pose came back; see {run_dir}")
    frames = len(truth)
    return {"latency_ms": percentiles(latency["pose"]), "detector_latency_ms": percentiles(latency["heatlines"]),
            "frames_published": frames, "poses": len(latency["pose"]),
            "dropped_fraction": 1 - len(latency["pose"]) / frames}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=150, help="frames of the 30 fps table top (default 150: 5 s)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rate", type=float, default=30.0, help="camera frames per second (default 30)")
    parser.add_argument("--scales", default="0.8", help="detector pyramid scales, comma-separated (default 0.8)")
    parser.add_argument("--particles", type=int, default=2000, help="localizer's max particles (default 2000)")
    parser.add_argument("--full-graph", action="store_true", help="also run loop closure and mapper")
    parser.add_argument("--cache", default=None, help="where the data set is kept (default ~/.cache/semloc/bench)")
    parser.add_argument("--json", help="write every figure here")
    args = parser.parse_args()
    from semloc_core.experiments.demo_world import default_cache_dir

    DETECTOR["scales"] = [float(v) for v in args.scales.split(",")]
    FILTER["max_particles"] = args.particles
    cache = Path(args.cache) if args.cache else default_cache_dir() / "bench"
    dataset = world(args.frames, cache)
    runs = []
    with tempfile.TemporaryDirectory(prefix="semloc-e2e-") as tmp:
        detector_file = Path(tmp) / "detector.yaml"
        detector_config = {**DETECTOR, "templates": str(dataset / "exemplars")}
        import yaml

        detector_file.write_text(yaml.safe_dump(detector_config))
        for repeat in range(args.repeats):
            ref = reference(dataset, detector_config)
            dist = distributed(dataset, detector_file, args.rate, args.full_graph, Path(tmp) / f"run{repeat}")
            runs.append({"reference": ref, "distributed": dist,
                         "ratio_p50": dist["latency_ms"]["p50"] / ref["latency_ms"]["p50"]})
            print(f"run {repeat + 1}: camera -> pose p50 {dist['latency_ms']['p50']:.1f} ms, p95 "
                  f"{dist['latency_ms']['p95']:.1f} ms ({dist['poses']}/{dist['frames_published']} frames got a "
                  f"pose); reference p50 {ref['latency_ms']['p50']:.1f} ms, p95 {ref['latency_ms']['p95']:.1f} ms",
                  file=sys.stderr, flush=True)
    median = lambda path: statistics.median(path(r) for r in runs)  # noqa: E731
    summary = {
        "rate_hz": args.rate, "frames": args.frames, "repeats": args.repeats, "full_graph": args.full_graph,
        "detector": DETECTOR, "max_particles": args.particles,
        "distributed_p50_ms": median(lambda r: r["distributed"]["latency_ms"]["p50"]),
        "distributed_p95_ms": median(lambda r: r["distributed"]["latency_ms"]["p95"]),
        "detector_p50_ms": median(lambda r: r["distributed"]["detector_latency_ms"]["p50"]),
        "dropped_fraction": median(lambda r: r["distributed"]["dropped_fraction"]),
        "reference_p50_ms": median(lambda r: r["reference"]["latency_ms"]["p50"]),
        "reference_p95_ms": median(lambda r: r["reference"]["latency_ms"]["p95"]),
        "ratio_p50": median(lambda r: r["ratio_p50"]),
    }
    graph = "full graph" if args.full_graph else "camera, detector, localizer"
    print(f"camera -> pose at {args.rate:g} fps on tabletop ({graph}), median of {args.repeats} runs:")
    print(f"  distributed   p50 {summary['distributed_p50_ms']:6.1f} ms   p95 {summary['distributed_p95_ms']:6.1f} ms"
          f"   (detector output p50 {summary['detector_p50_ms']:.1f} ms; frames without a pose "
          f"{100 * summary['dropped_fraction']:.0f} %)")
    print(f"  one process   p50 {summary['reference_p50_ms']:6.1f} ms   p95 {summary['reference_p95_ms']:6.1f} ms")
    print(f"  ratio distributed / one process (p50): {summary['ratio_p50']:.2f}   target p50 < 50 ms: "
          f"{'met' if summary['distributed_p50_ms'] < 50 else 'NOT met'}")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "runs": runs}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
