"""Soak: does any worker of the demo graph grow without bound, and does loop-closure state stay small?

(a) The demo graph (deploy/demo.yaml, the `semloc demo --fast` world: a table top, two laps) with the camera
    looping over the world at --rate (default 10 Hz, above what the pipeline sustains: every worker runs flat out,
    `latest` queues dropping what it cannot take), with state snapshots and journals on, for --minutes. The RSS of
    every worker is sampled every --sample-s; after --warmup-minutes its growth is fitted (least squares) and
    printed in MB/h, % of its size at the end of the warm-up per hour (goal: <= 5 %/h) and MB per 1,000 frames
    handled (the hourly figure scales with the rate the machine gives the worker). Also each worker's
    frames per second and, at the end, the loop-closure worker's snapshot and store on disk and the frames its map
    keeps (a key-frame showing a view the map holds is a visit of that frame, not kept: engine.cull_redundant).
(b) The loop-closure engine alone with its file storage, fed a looping `route` (cached SIFT features of
    benchmarks/loopclosure.py, cycled: every lap revisits all the earlier ones) and keeping every frame (the
    worst case for the state: a robot that never sees a view twice): at --scale-frames frames, the snapshot's size
    and write time, the restore time (load + from_state, as the worker does), the store on disk and the process's
    RSS.

    .venv/bin/python benchmarks/soak.py --minutes 30 [--rate 10] [--sample-s 10] [--warmup-minutes 5]
                                        [--scale-frames 1000 5000 10000] [--skip-graph] [--skip-scaling]

A memory and state-size study, not a speed benchmark: no reference run and no ratio; growth is a least-squares
fit over the samples, (b)'s write and restore times single measurements.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from schemas import Status, keys  # noqa: E402
from services.bus import BusConfig, QueryError, open_session, query  # noqa: E402
from services.demo_report import MAIN_INPUT  # noqa: E402

STATEFUL = ("loopclosure", "localizer", "mapper")
WORKERS = ("camera", "detector") + STATEFUL


def memory_mb(pid: int) -> dict[str, float] | None:
    """VmRSS, RssAnon and RssFile of a process, in MB (None once it is gone)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except (FileNotFoundError, ProcessLookupError):
        return None
    values = {}
    for line in lines:
        name, _, rest = line.partition(":")
        if name in ("VmRSS", "RssAnon", "RssFile"):
            values[name] = int(rest.split()[0]) / 1024
    return values


def growth_per_hour(times_s: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """(slope in units per hour, the fitted value at the first time) of a least-squares line."""
    if times_s.size < 3 or np.ptp(times_s) <= 0:
        return float("nan"), float(values[0]) if values.size else float("nan")
    slope, intercept = np.polyfit(times_s - times_s[0], values, 1)
    return float(slope * 3600), float(intercept)


def _status(session, robot: str, worker: str) -> Status | None:
    try:
        replies = query(session, keys.status(robot, worker), reply_type=Status, timeout=1.0)
    except QueryError:
        return None
    return replies[0] if replies else None


def run_graph(args, workdir: Path) -> dict:
    """(a): the demo graph on a looping camera, RSS sampled; returns the samples and the fits."""
    from semloc_core.experiments.demo_world import ensure_world
    from semloc_core.experiments.spec import load_preset
    from services.bus import free_port
    from services.demo_run import DEMO_GRAPH, DemoOptions, DemoSpec, _overrides
    from services.launcher import Launcher, load_graph

    spec = DemoSpec.model_validate({**load_preset("demo", "fast"), "seed": 0, "appearance": args.appearance,
                                    "rate": args.rate, "localizer_start": "known"})
    cache = Path(args.cache_dir) if args.cache_dir else None
    world = ensure_world(spec.world(), cache)
    hub = f"tcp/127.0.0.1:{free_port()}"
    overrides = _overrides(spec, DemoOptions(workdir=workdir, cache_dir=cache, rerun="off"), world, workdir, hub,
                           "soak")
    overrides["nodes"]["camera"]["config"].update(loop=True, exit_at_end=False)
    overrides["restart"] = {"policy": "on-failure", "backoff_s": 0.5, "max_backoff_s": 5}
    graph = load_graph(DEMO_GRAPH, overrides)
    robot = graph.robot
    launcher = Launcher(graph, run_dir=workdir / "run")
    samples: dict[str, list] = {w: [] for w in WORKERS}
    processed: dict[str, list] = {w: [] for w in WORKERS}
    details: dict = {}  # the loop closure's last status details
    print(f"(a) demo graph, camera looping over {spec.frames} frames at {args.rate:g} Hz, {args.minutes:g} min; "
          f"RSS every {args.sample_s:g} s (logs in {workdir / 'run' / 'logs'})", flush=True)
    launcher.start()
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            started = time.monotonic()
            end = started + args.minutes * 60
            next_print = started
            while time.monotonic() < end:
                now = time.monotonic() - started
                pids = launcher.pids()
                for worker in WORKERS:
                    pid = pids.get(worker)
                    mem = memory_mb(pid) if pid else None
                    if mem is not None:
                        samples[worker].append((now, pid, mem["VmRSS"], mem["RssAnon"], mem["RssFile"]))
                    status = _status(session, robot, worker)
                    if status is not None and worker == "loopclosure":
                        details = dict(status.details)
                    if status is not None:
                        main = status.inputs.get(MAIN_INPUT.get(worker, ""))
                        count = (main.processed if main is not None
                                 else sum(o.published for o in status.outputs.values() if o.key.endswith("/image")))
                        processed[worker].append((now, status.pid, count))
                if time.monotonic() >= next_print:
                    line = ", ".join(f"{w} {samples[w][-1][2]:.0f} MB" for w in WORKERS if samples[w])
                    print(f"  {now / 60:5.1f} min: {line}", flush=True)
                    next_print += 60
                time.sleep(max(0.0, args.sample_s - (time.monotonic() - started - now)))
            store = workdir / "state" / robot / "loopclosure.store"
            snapshot = workdir / "state" / robot / "loopclosure.npz"
            disk = {"snapshot_mb": snapshot.stat().st_size / 1e6 if snapshot.exists() else None,
                    "store_mb": (sum(p.stat().st_blocks * 512 for p in store.rglob("*") if p.is_file()) / 1e6
                                 if store.exists() else None)}
    finally:
        launcher.stop()
    summary = launcher.summary()
    warmup = args.warmup_minutes * 60
    report = {"minutes": args.minutes, "rate_hz": args.rate, "warmup_minutes": args.warmup_minutes,
              "loopclosure_disk": disk, "loopclosure_map": {k: details.get(k) for k in ("map_frames", "frames")}, "restarts": {w: max(0, s["starts"] - 1) for w, s in summary.items()},
              "workers": {}}
    for worker in WORKERS:
        rows = np.array([r[:1] + r[2:] for r in samples[worker]], float).reshape(-1, 4)
        late = rows[rows[:, 0] >= warmup]
        entry: dict = {"samples": int(rows.shape[0])}
        if late.shape[0] >= 3:
            for column, name in ((1, "rss"), (2, "anon"), (3, "file")):
                slope, start = growth_per_hour(late[:, 0], late[:, column])
                entry[name] = {"at_warmup_mb": start, "end_mb": float(late[-1, column]), "mb_per_h": slope,
                               "percent_per_h": 100 * slope / start if start else float("nan")}
        counts = [r for r in processed[worker] if r[0] >= warmup]
        if len(counts) >= 2 and counts[-1][1] == counts[0][1]:  # the same process throughout
            entry["frames_per_s"] = (counts[-1][2] - counts[0][2]) / max(counts[-1][0] - counts[0][0], 1e-9)
        entry["processed_total"] = processed[worker][-1][2] if processed[worker] else None
        report["workers"][worker] = entry
    report["samples"] = {w: samples[w] for w in WORKERS}
    return report


def print_graph(report: dict) -> None:
    print(f"(a) RSS after the {report['warmup_minutes']:g}-minute warm-up, least-squares growth "
          f"(goal <= 5 %/h); restarts {report['restarts']}")
    # Per 1,000 frames too: a worker's growth per hour scales with the rate the machine gave it.
    print("    worker       frames/s   RSS at warm-up -> end   growth MB/h   %/h   | anon MB/h  file MB/h | "
          "MB/1k frames")
    for worker, entry in report["workers"].items():
        rss, anon, file = entry.get("rss"), entry.get("anon"), entry.get("file")
        if rss is None:
            print(f"    {worker:12s} (too few samples)")
            continue
        fps = entry.get("frames_per_s")
        fps = float("nan") if fps is None else fps
        per_1k = rss["mb_per_h"] / (3.6 * fps) if fps > 0 else float("nan")
        print(f"    {worker:12s} {fps:8.2f}   {rss['at_warmup_mb']:7.1f} -> "
              f"{rss['end_mb']:7.1f} MB   {rss['mb_per_h']:+8.1f}   {rss['percent_per_h']:+5.1f}   | "
              f"{anon['mb_per_h']:+8.1f}  {file['mb_per_h']:+8.1f} | {per_1k:+6.2f}")
    disk = report["loopclosure_disk"]
    if disk["snapshot_mb"] is not None:
        store = f"{disk['store_mb']:.1f} MB" if disk["store_mb"] is not None else "none"
        print(f"    loop closure on disk at the end: snapshot {disk['snapshot_mb']:.2f} MB, store {store} "
              f"({report['workers']['loopclosure'].get('processed_total')} frames handled by the last process)")
    kept = report.get("loopclosure_map", {})
    if kept.get("frames"):
        print(f"    loop closure map: keeps {kept['map_frames']} of its {kept['frames']} key-frames (the others are "
              "visits of a frame holding their view)")


def run_scaling(args) -> list[dict]:
    """(b): the engine with a file storage on a looping route; snapshot size and restore time at checkpoints."""
    from loopclosure import route_features  # benchmarks/loopclosure.py: the cached route features

    from semloc_core.io.loopclosure import FileStorage, load_vocabulary
    from semloc_core.loopclosure import EngineParams, LoopClosureEngine
    from services.state import State, load_state, save_state

    sequences, _, _ = route_features(args.seed, args.route_frames, 500, Path(args.features_cache))
    vocabulary = None
    if args.vocabulary:
        vocabulary = load_vocabulary(args.vocabulary)
    checkpoints = sorted(args.scale_frames)
    print(f"(b) loop-closure engine, file storage, route seed {args.seed} ({len(sequences)} frames) looped to "
          f"{checkpoints[-1]} frames, every frame kept", flush=True)
    root = Path(tempfile.mkdtemp(prefix="semloc-soak-"))
    rows = []
    try:
        engine = LoopClosureEngine(EngineParams(cull_redundant=False), vocabulary, FileStorage(root / "store"))
        started = time.process_time()
        window_start = time.process_time()
        for k in range(checkpoints[-1]):
            engine.add_frame(sequences[k % len(sequences)])
            if k + 1 not in checkpoints:
                continue
            cpu_per_frame = (time.process_time() - window_start) / max(1, k + 1 - (rows[-1]["frames"] if rows else 0))
            t = time.perf_counter()
            engine.flush()
            arrays, meta = engine.state()
            save_state(root / "loopclosure.npz", State(arrays, meta))
            write_s = time.perf_counter() - t
            t = time.perf_counter()
            state = load_state(root / "loopclosure.npz")
            restored = LoopClosureEngine.from_state(state.arrays, state.meta, FileStorage(root / "store"))
            restore_s = time.perf_counter() - t
            assert restored.n_frames == engine.n_frames
            del restored
            mem = memory_mb(os.getpid())
            store_mb = FileStorage(root / "store").size_bytes() / 1e6
            row = {"frames": k + 1, "snapshot_mb": (root / "loopclosure.npz").stat().st_size / 1e6,
                   "snapshot_write_s": write_s, "restore_s": restore_s, "store_mb": store_mb,
                   "rss_mb": mem["VmRSS"], "anon_mb": mem["RssAnon"], "cpu_ms_per_frame": 1e3 * cpu_per_frame,
                   "cpu_s": time.process_time() - started}
            rows.append(row)
            print(f"    {k + 1:6d} frames: snapshot {row['snapshot_mb']:.2f} MB (written in {write_s:.2f} s), "
                  f"restore {restore_s:.2f} s, store {store_mb:.0f} MB on disk, RSS {row['rss_mb']:.0f} MB "
                  f"(anon {row['anon_mb']:.0f}), {row['cpu_ms_per_frame']:.1f} ms CPU/frame since the last",
                  flush=True)
            window_start = time.process_time()
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=10.0, help="camera rate (Hz)")
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--warmup-minutes", type=float, default=None, help="default: a sixth of the run, <= 5")
    parser.add_argument("--appearance", choices=("generated", "auto", "real"), default="generated")
    parser.add_argument("--cache-dir", default=None, help="demo world cache (default: semloc demo's)")
    parser.add_argument("--workdir", default=None, help="state, logs (default: a temporary directory, removed)")
    parser.add_argument("--scale-frames", type=int, nargs="+", default=[1000, 5000, 10000])
    parser.add_argument("--seed", type=int, default=0, help="route seed of (b)")
    parser.add_argument("--route-frames", type=int, default=2000, help="route frames cycled in (b)")
    parser.add_argument("--features-cache", default=".semloc-cache/loopclosure",
                        help="benchmarks/loopclosure.py's --cache (route features are rendered into it if missing)")
    parser.add_argument("--vocabulary", default=None, help="vocabulary .npz for (b) (default: learnt online)")
    parser.add_argument("--skip-graph", action="store_true")
    parser.add_argument("--skip-scaling", action="store_true")
    parser.add_argument("--json", default=None, help="also write the figures (and RSS samples) as JSON")
    args = parser.parse_args()
    if args.warmup_minutes is None:
        args.warmup_minutes = min(5.0, args.minutes / 6)
    report: dict = {}
    if not args.skip_graph:
        workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="semloc-soak-graph-"))
        try:
            report["graph"] = run_graph(args, workdir)
        finally:
            if not args.workdir:
                shutil.rmtree(workdir, ignore_errors=True)
        print_graph(report["graph"])
    if not args.skip_scaling:
        report["scaling"] = run_scaling(args)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
