"""The mapper worker's CPU a frame at the camera rate, against the same core calls in this process.

    .venv/bin/python benchmarks/mapper_worker.py [--frames 150] [--rate 15] [--repeats 3] [--uncalibrated]

The demo's detector (benchmarks/end_to_end.py --demo: 4-pixel blocks, four scales, hsv) turns the 30 fps table top
of benchmarks/end_to_end.py into Heatmaps frames (uint8, as the detector worker publishes them), once, in this
process. Then, per repeat:

* ``worker``: a real mapper worker process (deploy/demo.yaml's mapper settings: 2 cm voxels over the table,
  surprisal, 5 views, centroid positions, an ObjectMap every 2 s; its state journaled as in the demo) takes those
  frames and their camera poses over zenoh on loopback at ``--rate`` frames per second; its CPU time (every thread,
  from /proc) from the first frame until it has taken the last, divided by the frames it integrated (a worker
  that falls behind refuses frames once its queue of 16 is full: counted);
* ``in process``: the same frames through the worker's core calls - decode, ``VoxelMapper.integrate`` and the
  object extraction once per publication period (every ``2 s x rate`` frames) - CPU time a frame.

Ratio = worker / in process: what the process, the bus, the journal and the status cost on top of the mapping.

Extraction. The demo world's mapper_extraction.json is fitted on calibration scenes of that world; this table top
has none, so the mapper extracts with that file's settings in the surprisal's units (class scales ~4.5 x threshold
0.7: threshold 3; top-hat 2; cross-class suppression). ``--uncalibrated`` runs the worker's default extraction
instead (threshold 0.5, below the surprisal's background mean of 1: every local maximum of the volume is a
candidate), which is what benchmarks/end_to_end.py --full-graph gave its mapper before it took MAPPER_EXTRACTION.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from end_to_end import MAPPER_EXTRACTION, cpu_seconds, world  # noqa: E402

# deploy/demo.yaml's mapper (grid as benchmarks/end_to_end.py runs it); the extraction: see the module's docstring.
MAPPER = {"grid_min": [-1.3, -1.3, 0.7], "grid_max": [1.3, 1.3, 1.15], "voxel_size": 0.02,
          "volume": {"heatmap_background": "surprisal"}, "pose_frame": "camera", "publish_period_s": 2.0,
          "extraction": {"min_views": 5, "position": "centroid"}}


def heatmap_frames(dataset, dataset_path: Path, frames: int) -> tuple[list[bytes], tuple[str, ...]]:
    """The demo detector's Heatmaps of the first ``frames`` images, encoded as the detector worker publishes them."""
    from schemas import Header, encode
    from schemas.detection import Heatmaps
    from semloc_core.detection.config import build_detector
    from semloc_core.experiments.demo_world import DETECTOR
    from services.frames import camera_heatmaps

    detector = build_detector({**DETECTOR, "templates": str(dataset_path / "exemplars")})
    camera = dataset.camera
    image = SimpleNamespace(camera=0, width=camera.width, height=camera.height, T_body_cam=None)
    payloads = []
    for i in range(frames):
        entry = camera_heatmaps(image, detector.heatmaps(dataset.image(i)), "uint8")
        header = Header(robot="r1", stream="detector/heatmaps", seq=i, stamp_ns=int(dataset.stamps_ns[i]))
        payloads.append(encode(Heatmaps(header=header, classes=tuple(detector.classes), detector="templates",
                                        maps=[entry])))
    return payloads, tuple(detector.classes)


def in_process(payloads: list[bytes], poses: np.ndarray, camera, settings: dict, rate: float) -> float:
    """CPU ms a frame of the worker's core calls (decode, integrate, extraction once per publication period)."""
    from schemas import decode
    from schemas.detection import Heatmaps
    from semloc_core.mapping import VoxelGrid, VoxelMapper
    from services.workers.mapper import Mapper, MapperWorkerConfig

    config = MapperWorkerConfig(**settings)
    mapper = VoxelMapper(VoxelGrid.from_bounds(config.grid_min, config.grid_max, config.voxel_size),
                         tuple(config.classes), config.volume)
    heat = SimpleNamespace(config=config)  # Mapper._heat reads only the settings
    every = max(1, round(config.publish_period_s * rate))
    start = time.process_time()
    for i, payload in enumerate(payloads):
        frame = decode(payload, expected=Heatmaps)
        mapper.integrate(Mapper._heat(heat, frame.maps[0]), poses[i], camera)
        if (i + 1) % every == 0:
            mapper.semantic_map(config.extraction)
    return 1e3 * (time.process_time() - start) / len(payloads)


def worker(payloads: list[bytes], poses: np.ndarray, calibration: Path, settings: dict, rate: float,
           run_dir: Path) -> dict:
    """The mapper worker over zenoh: CPU ms per integrated frame, and its handler's figures from its Status."""
    import zenoh

    from schemas import Header, Pose3D, Status, encode, keys
    from schemas.mapping import ObjectMap
    from services.bus import BusConfig, free_port, open_session, query

    hub = f"tcp/127.0.0.1:{free_port()}"
    args = ["worker", "mapper", "--connect", hub, "--robot", "r1", "--state-dir", str(run_dir / "state"),
            "--set", f"calibration={calibration}"]
    for name, value in settings.items():
        args += ["--set", f"{name}={json.dumps(value)}"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("SEMLOC__")}
    with open(run_dir / "mapper.log", "ab") as log, open_session(BusConfig(listen=[hub])) as session:
        process = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=REPO, env=env, stdout=log,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            deadline = time.monotonic() + 120
            while not query(session, keys.status("r1", "mapper"), timeout=0.5):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the mapper did not start; see {run_dir / 'mapper.log'}")
            block = zenoh.CongestionControl.BLOCK
            poses_out = session.declare_publisher(keys.groundtruth_pose("r1"), congestion_control=block)
            heat_out = session.declare_publisher(keys.detector_heatmaps("r1"), congestion_control=block)
            while not (poses_out.matching_status.matching and heat_out.matching_status.matching):
                time.sleep(0.05)
            time.sleep(0.5)
            cpu_start = cpu_seconds(process.pid)
            started = time.monotonic()
            for i, payload in enumerate(payloads):
                time.sleep(max(0.0, started + i / rate - time.monotonic()))
                heat_out.put(payload)
                poses_out.put(encode(Pose3D.from_matrix(Header(robot="r1", seq=i, stamp_ns=_stamp(payload),
                                                               frame_id="world"), poses[i])))
            deadline = time.monotonic() + 300
            while True:  # until every frame sent is integrated or refused by a full queue (the worker fell behind)
                status = query(session, keys.status("r1", "mapper"), reply_type=Status, timeout=2.0)
                heat = status[0].inputs.get("heatmaps") if status else None
                if heat is not None and heat.processed + heat.overflow + heat.rejected >= len(payloads):
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the mapper took {heat.processed if heat else 0} frames in 300 s")
                time.sleep(0.1)
            cpu = cpu_seconds(process.pid) - cpu_start
            elapsed = time.monotonic() - started
            replies = query(session, keys.mapper_map("r1"), reply_type=ObjectMap, timeout=5.0)
        finally:
            process.terminate()
            process.wait(30)
    return {"cpu_ms_per_frame": 1e3 * cpu / max(heat.processed, 1), "elapsed_s": elapsed,
            "objects": len(replies[0].class_index) if replies else 0, "handler_ms": heat.handler_ms,
            "processed": heat.processed, "refused": heat.overflow}


def _stamp(payload: bytes) -> int:
    from schemas import decode

    return decode(payload).header.stamp_ns


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=150, help="frames of the 30 fps table top (default 150)")
    parser.add_argument("--rate", type=float, default=15.0, help="frames per second sent (default 15)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--uncalibrated", action="store_true", help="the worker's default extraction (see above)")
    parser.add_argument("--cache", default=None, help="where the data set is kept (default ~/.cache/semloc/bench)")
    args = parser.parse_args()
    from semloc_core.experiments.demo_world import default_cache_dir
    from semloc_core.io.camera_model import save_camera
    from semloc_core.io.dataset import open_dataset

    dataset_path = world(150, Path(args.cache) if args.cache else default_cache_dir() / "bench")
    dataset = open_dataset(dataset_path)
    frames = min(args.frames, len(dataset))
    print(f"demo detector over {frames} frames ...", file=sys.stderr, flush=True)
    payloads, classes = heatmap_frames(dataset, dataset_path, frames)
    poses = np.asarray(dataset.T_world_cam[:frames])
    settings = {**MAPPER, "classes": list(classes)}
    if not args.uncalibrated:
        settings["extraction"] = MAPPER_EXTRACTION
    rows = []
    with tempfile.TemporaryDirectory(prefix="semloc-mapper-worker-") as tmp:
        calibration = save_camera(dataset.camera, Path(tmp) / "camera.yaml")
        for repeat in range(args.repeats):
            reference = in_process(payloads, poses, dataset.camera, settings, args.rate)
            run_dir = Path(tmp) / f"run{repeat}"
            run_dir.mkdir()
            distributed = worker(payloads, poses, calibration, settings, args.rate, run_dir)
            load = os.getloadavg()
            rows.append((distributed["cpu_ms_per_frame"], reference))
            print(f"run {repeat + 1} (load {load[0]:.1f} {load[1]:.1f}): worker {distributed['cpu_ms_per_frame']:.1f} "
                  f"ms CPU a frame (handler mean {distributed['handler_ms'] or 0:.1f} ms wall, "
                  f"{distributed['processed']} frames integrated, {distributed['refused']} refused by its full queue, "
                  f"{distributed['objects']} objects), in process "
                  f"{reference:.1f} ms CPU a frame, ratio {distributed['cpu_ms_per_frame'] / reference:.2f}",
                  file=sys.stderr, flush=True)
    worker_ms = statistics.median(r[0] for r in rows)
    reference_ms = statistics.median(r[1] for r in rows)
    ratio = statistics.median(r[0] / r[1] for r in rows)
    extraction = "uncalibrated (threshold 0.5)" if args.uncalibrated else "fitted-like (threshold 3, top-hat 2)"
    print(f"mapper at {args.rate:g} fps, {frames} frames, extraction {extraction}, median of {args.repeats}:")
    print(f"  worker      {worker_ms:6.1f} ms CPU a frame")
    print(f"  in process  {reference_ms:6.1f} ms CPU a frame")
    print(f"  ratio worker / in process {ratio:.2f}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
