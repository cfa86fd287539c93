"""End-to-end latency: camera -> pose over the bus at 30 fps on `tabletop`, against the same core calls in one process.

    .venv/bin/python benchmarks/end_to_end.py [--frames 150] [--repeats 3] [--rate 30] [--scales 0.8]
        [--particles 2000] [--full-graph] [--demo] [--json out.json]

    # issue 35's acceptance: the demo's detector and filter, all five workers, camera at 15 fps
    .venv/bin/python benchmarks/end_to_end.py --demo --full-graph --rate 15

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

The detector here is the template detector with 8-pixel blocks at one scale (``--scales 0.8``) and the filter keeps
2,000 particles: at 30 fps a frame must cost well under the 33 ms between frames, or it waits for the previous one
in the detector's queue. ``--demo`` runs deploy/demo.yaml's settings instead: the demo's detector
(semloc_core/experiments/demo_world.py DETECTOR: 4-pixel blocks, levels 1.2 / 0.85 / 0.6 / 0.42, hsv) and its localizer (model B,
sigma 2 deg, tempered 0.3, omni-directional motion, 5,000 particles), in both the graph and the reference; targets:
poses at >= 10 Hz, camera -> pose p50 <= 100 ms.

Printed per run: camera -> pose p50 / p95, the pose rate (poses per second of playback), and each worker's
sustained rate and capacity from its last Status (rates over its last 10 s: 1000 / mean handler time is what the
stage could sustain on the loaded machine), with the stage that limits the pose rate.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
# The demo world's fitted mapper extraction (mapper_extraction.json: class scales ~4.5 x threshold 0.7, top-hat 2,
# cross-class suppression) in the surprisal's units, for worlds that have none fitted.
MAPPER_EXTRACTION = {"min_views": 5, "position": "centroid", "threshold": 3.0, "tophat": 2.0, "cross_class": True}
# The localizer's settings of the light configuration (model B, the worker's defaults otherwise but for these).
LOCALIZER = {"model": "B", "sigma_deg": 5.0, "likelihood_exponent": 0.3, "motion": "omni", "odom_alpha1": 0.05,
             "odom_alpha2": 0.01, "odom_alpha3": 0.05, "odom_alpha4": 0.01}


def world(frames: int, cache: Path) -> Path:
    """A 30 fps table-top data set (generated object looks: no dependency on the real data folder), cached."""
    from semloc_core.sim import make_scenario

    folder = cache / f"tabletop-30fps-s0-f{frames}"
    if not (folder / "dataset.json").is_file():
        print(f"writing {folder} ...", file=sys.stderr)
        make_scenario("tabletop", seed=0, frames=frames).write(folder, multiview=False)
    return folder


def cpu_seconds(pid: int | None) -> float | None:
    """CPU time (user + system, every thread) a running process has used, from /proc (None once it is gone)."""
    if pid is None:
        return None
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")   # utime, stime (fields 14, 15)


def percentiles(values) -> dict:
    values = np.asarray(values, float)
    return {"p50": float(np.percentile(values, 50)), "p95": float(np.percentile(values, 95)), "n": int(values.size)}


# ------------------------------------------------------------------------------------------------ reference
def reference(dataset_path: Path, detector_config: dict, localizer: dict) -> dict:
    """The pipeline's core calls in this process, frame after frame, with the localizer worker's settings
    (``localizer``: its config fields): per-frame time (ms)."""
    from semloc_core import bearing
    from semloc_core.detection.config import build_detector
    from semloc_core.detection.heatlines import HeatlineProjector
    from semloc_core.io.dataset import open_dataset
    from semloc_core.io.semantic_map import load_semantic_map
    from semloc_core.localization import (FilterConfig, FreeSpace, GenerativeScoreModel, OmniDriveModel,
                                          ParticleFilter, RandomWalkModel, synthetic_scores_likelihood)
    from semloc_core.localization import Odometry as CoreOdometry
    from services.workers.localizer import LocalizerConfig

    c = LocalizerConfig(**{k: v for k, v in localizer.items() if k not in ("filter", "initial_pose")})
    if c.model != "B" or c.motion != "omni" or c.view:
        raise ValueError("the reference runs model B with omni-directional motion and no view geometry")
    dataset = open_dataset(dataset_path)
    images = [dataset.image(i) for i in range(len(dataset))]  # decoded up front: the camera's work is not timed
    detector = build_detector(detector_config)
    projector = HeatlineProjector(dataset.camera, tuple(detector.classes), bearing.BearingGrid(360))
    semantic_map = load_semantic_map(dataset_path / "semantic_map.json")
    settings = dict(localizer["filter"])
    motion = OmniDriveModel(c.odom_alpha1, c.odom_alpha2, c.odom_alpha3, c.odom_alpha4,
                            fallback=RandomWalkModel(c.random_walk_translation_std, c.random_walk_rotation_std))
    model = GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(tuple(detector.classes)),
                                 sigma=math.radians(c.sigma_deg), visibility_radius=c.visibility_radius or math.inf,
                                 peak=c.peak_detection_probability, exponent=c.likelihood_exponent)
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
def distributed(dataset_path: Path, detector_file: Path, localizer: dict, rate: float, full_graph: bool,
                run_dir: Path) -> dict:
    from schemas import decode, keys
    from schemas.detection import Heatlines
    from schemas.localization import PoseEstimate
    from schemas import Status
    from services.bus import BusConfig, free_port, open_session, query
    from services.launcher import Launcher, load_graph

    hub = f"tcp/127.0.0.1:{free_port()}"
    truth = np.load(dataset_path / "poses.npz", allow_pickle=False)["poses2d"]
    nodes = {
        # Wall-clock stamps: each frame carries the moment the camera published it, so latency is measured from
        # there (a subscriber's own view of the image can lag behind the detector's by a few ms).
        "camera": {"config": {"source": str(dataset_path), "rate": rate, "stamp": "wall"}},
        "detector": {"config": {"detector_file": str(detector_file)}},
        "localizer": {"config": {**localizer, "map": str(dataset_path / "semantic_map.json"),
                                 "score_likelihood": "synthetic", "initial_pose": [float(v) for v in truth[0]]}},
        # The mapper as the demo runs it; this world has no fitted extraction, so the demo world's in the
        # surprisal's units (MAPPER_EXTRACTION). The worker's default threshold (0.5) is below the surprisal's
        # background mean of 1: every local maximum was a candidate, the map held ~440 objects and the extraction
        # every 2 s cost more than the integration (benchmarks/mapper_worker.py --uncalibrated).
        "mapper": {"enabled": full_graph, "config": {"detector_file": str(detector_file), "extraction_file": None,
                                                     "extraction": MAPPER_EXTRACTION}},
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

    with Launcher(processing, run_dir=run_dir / "graph") as launcher, \
            open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
        from services.demo_collector import Collector

        collector = Collector(session, graph.robot)  # only to know when every worker runs
        deadline = time.monotonic() + 120
        while len(collector.running(workers)) < len(workers):
            if time.monotonic() > deadline:
                raise RuntimeError(f"workers did not start; see {run_dir / 'graph' / 'logs'}")
            time.sleep(0.2)
        collector.close()  # (it decodes every image: not while timing)
        subscribers = [session.declare_subscriber(keys.detector_heatlines(graph.robot), record("heatlines", Heatlines)),
                       session.declare_subscriber(keys.localizer_pose(graph.robot), record("pose", PoseEstimate))]
        cpu_start = {worker: cpu_seconds(launcher.nodes[worker].pid) for worker in workers}
        started = time.monotonic()
        camera_cpu = None
        with Launcher(sensor, run_dir=run_dir / "camera") as camera:
            while not camera.wait(timeout=0.2):   # the camera's CPU time, sampled until it exits
                camera_cpu = cpu_seconds(camera.nodes["camera"].pid) or camera_cpu
                if time.monotonic() - started > 600:
                    break
        time.sleep(2.0)  # the last frames through the pipeline
        cpu = {worker: _difference(cpu_seconds(launcher.nodes[worker].pid), cpu_start[worker]) for worker in workers}
        cpu["camera"] = camera_cpu
        elapsed = time.monotonic() - started
        for subscriber in subscribers:
            subscriber.undeclare()
        statuses = {}
        for worker in workers:  # each worker's Status now: its rates over the last 10 s
            replies = query(session, keys.status(graph.robot, worker), reply_type=Status, timeout=5.0)
            if replies:
                statuses[worker] = replies[0]
    latency = {}
    for name, values in arrivals.items():
        first = {}
        for arrived, stamp in values:  # one figure per frame: its first output
            first.setdefault(stamp, arrived)
        latency[name] = [(arrived - stamp) * 1e-6 for stamp, arrived in first.items()]
    if not latency["pose"]:
        raise RuntimeError(f"no pose came back; see {run_dir}")
    frames = len(truth)
    from services.demo_report import MAIN_INPUT, pose_rate_limit

    stages = []
    for worker in workers:
        status = statuses.get(worker)
        main = status.inputs.get(MAIN_INPUT.get(worker, "")) if status is not None else None
        processed = main.processed if main else None
        stages.append({"stage": worker, "cpu_s": cpu[worker],
                       "cpu_ms_per_processed": (1e3 * cpu[worker] / processed
                                                if cpu[worker] is not None and processed else None),
                       "sustained_fps": main.rate_hz if main else None,
                       "handler_mean_ms": main.handler_ms if main else None,
                       "capacity_fps": 1e3 / main.handler_ms if main and main.handler_ms else None,
                       "processed": main.processed if main else None, "dropped": main.dropped if main else None,
                       "busy_fraction": status.busy_fraction if status is not None else None})
    camera_ms = None if cpu["camera"] is None else 1e3 * cpu["camera"] / frames
    return {"latency_ms": percentiles(latency["pose"]), "detector_latency_ms": percentiles(latency["heatlines"]),
            "camera_cpu_ms_per_frame": camera_ms, "elapsed_s": elapsed,
            "cores_used": sum(v for v in cpu.values() if v is not None) / elapsed,
            "frames_published": frames, "poses": len(latency["pose"]),
            "pose_rate_hz": len(latency["pose"]) / (frames / rate),
            "dropped_fraction": 1 - len(latency["pose"]) / frames,
            "stages": stages, "limit": pose_rate_limit(stages, rate)}


def _difference(end: float | None, start: float | None) -> float | None:
    return None if end is None or start is None else end - start


def cpu_budget(dist: dict, rate: float) -> list[str]:
    """The arithmetic of the graph's CPU at the camera rate: each stage's CPU per frame it processed (measured), what
    it would take at ``rate`` if it processed every frame, against the 2 cores' ``2000 / rate`` ms of CPU a frame."""
    lines, total = [], 0.0
    camera = dist["camera_cpu_ms_per_frame"]
    rows = [("camera", camera)] + [(s["stage"], s["cpu_ms_per_processed"]) for s in dist["stages"]]
    for stage, per_frame in rows:
        if per_frame is None:
            lines.append(f"    {stage:12s} CPU a frame: not measured")
            continue
        total += per_frame
        lines.append(f"    {stage:12s} {per_frame:6.1f} ms CPU a frame it processed -> {per_frame * rate / 1e3:4.2f} "
                     f"cores at {rate:g} fps")
    budget = 2e3 / rate
    fits = "fits" if total <= budget else "does NOT fit"
    lines.append(f"    every stage on every frame: {total:.1f} ms CPU a frame = {total * rate / 1e3:.2f} cores at "
                 f"{rate:g} fps, against {budget:.1f} ms a frame on 2 cores ({fits}); "
                 f"measured: {dist['cores_used']:.2f} cores over {dist['elapsed_s']:.0f} s")
    return lines


def _f(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=150, help="frames of the 30 fps table top (default 150: 5 s)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rate", type=float, default=30.0, help="camera frames per second (default 30)")
    parser.add_argument("--scales", default="0.8", help="detector pyramid scales, comma-separated (default 0.8)")
    parser.add_argument("--particles", type=int, default=2000, help="localizer's max particles (default 2000)")
    parser.add_argument("--full-graph", action="store_true", help="also run loop closure and mapper")
    parser.add_argument("--demo", action="store_true", help="deploy/demo.yaml's detector and localizer settings "
                                                            "(overrides --scales and --particles)")
    parser.add_argument("--cache", default=None, help="where the data set is kept (default ~/.cache/semloc/bench)")
    parser.add_argument("--json", help="write every figure here")
    args = parser.parse_args()
    from semloc_core.experiments.demo_world import default_cache_dir

    import yaml

    if args.demo:
        demo_graph = yaml.safe_load((REPO / "deploy" / "demo.yaml").read_text())
        localizer = {k: v for k, v in demo_graph["nodes"]["localizer"]["config"].items()
                     if k not in ("map", "score_likelihood", "rerun_particles")}
        from semloc_core.experiments.demo_world import DETECTOR as DEMO_DETECTOR

        DETECTOR.update(cell=DEMO_DETECTOR["cell"], scales=DEMO_DETECTOR["scales"])
    else:
        DETECTOR["scales"] = [float(v) for v in args.scales.split(",")]
        localizer = {**LOCALIZER, "filter": {**FILTER, "max_particles": args.particles}}
    cache = Path(args.cache) if args.cache else default_cache_dir() / "bench"
    dataset = world(args.frames, cache)
    runs = []
    with tempfile.TemporaryDirectory(prefix="semloc-e2e-") as tmp:
        detector_file = Path(tmp) / "detector.yaml"
        detector_config = {**DETECTOR, "templates": str(dataset / "exemplars")}
        detector_file.write_text(yaml.safe_dump(detector_config))
        for repeat in range(args.repeats):
            ref = reference(dataset, detector_config, localizer)
            dist = distributed(dataset, detector_file, localizer, args.rate, args.full_graph,
                               Path(tmp) / f"run{repeat}")
            runs.append({"reference": ref, "distributed": dist, "load": os.getloadavg()[0],
                         "ratio_p50": dist["latency_ms"]["p50"] / ref["latency_ms"]["p50"]})
            print(f"run {repeat + 1} (load {os.getloadavg()[0]:.1f}): camera -> pose p50 "
                  f"{dist['latency_ms']['p50']:.1f} ms, p95 {dist['latency_ms']['p95']:.1f} ms "
                  f"({dist['poses']}/{dist['frames_published']} frames got a pose: {dist['pose_rate_hz']:.1f} Hz); "
                  f"reference p50 {ref['latency_ms']['p50']:.1f} ms, p95 {ref['latency_ms']['p95']:.1f} ms",
                  file=sys.stderr, flush=True)
            for stage in dist["stages"]:
                busy = stage["busy_fraction"]
                print(f"  {stage['stage']:12s} sustained {_f(stage['sustained_fps'])} fps, handler "
                      f"{_f(stage['handler_mean_ms'])} ms (capacity {_f(stage['capacity_fps'])} fps), busy "
                      f"{_f(None if busy is None else 100 * busy, 0)} %, processed {stage['processed']}, dropped "
                      f"{stage['dropped']}", file=sys.stderr)
            limit = dist["limit"]
            print(f"  pose rate limited by the {limit['stage']} ({limit['rate_hz']:.1f} fps)", file=sys.stderr,
                  flush=True)
            print("  CPU budget (the machine's load inflates CPU times less than wall times):", file=sys.stderr)
            for line in cpu_budget(dist, args.rate):
                print(line, file=sys.stderr, flush=True)
    median = lambda path: statistics.median(path(r) for r in runs)  # noqa: E731
    summary = {
        "rate_hz": args.rate, "frames": args.frames, "repeats": args.repeats, "full_graph": args.full_graph,
        "detector": DETECTOR, "localizer": localizer, "demo_settings": args.demo,
        "load": median(lambda r: r["load"]), "pose_rate_hz": median(lambda r: r["distributed"]["pose_rate_hz"]),
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
    print(f"  poses at {summary['pose_rate_hz']:.1f} Hz (camera {args.rate:g} fps); load average {summary['load']:.1f} "
          f"on {os.cpu_count()} cores")
    if args.demo:
        met = summary["pose_rate_hz"] >= 10 and summary["distributed_p50_ms"] <= 100
        target = "poses >= 10 Hz and p50 <= 100 ms"
    else:
        met, target = summary["distributed_p50_ms"] < 50, "p50 < 50 ms"
    print(f"  ratio distributed / one process (p50): {summary['ratio_p50']:.2f}   target {target}: "
          f"{'met' if met else 'NOT met'}")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "runs": runs}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
