"""The demo's run (`semloc demo`, docs/demo.md): the whole system on a simulated table top, with its results.

1. A ``tabletop`` world is generated (or taken from the cache): a hand-held camera goes round a table with objects
   several times (semloc_core/experiments/demo_world.py).
2. Camera, detector, loop closure, localizer and mapper start as separate processes talking over zenoh on loopback
   (deploy/demo.yaml, through the launcher's Python API); the camera starts once every other worker runs.
3. The sequence plays with a progress display; every worker logs to rerun under one recording id; the demo
   collects what they publish (services/demo_collector.py) and logs ground truth, errors and latencies.
4. The recordings are merged into ``run.rrd`` with the viewer layout (services/blueprint.py), and the results table
   (loop closure P/R, localization RMSE, mapping P/R, per-stage throughput and latency) is printed and written as
   Markdown, JSON and PNG plots (services/demo_report.py).

What is played is a :class:`DemoSpec` (presets ``full``, the default, and ``fast``); how it is shown and where it
goes, :class:`DemoOptions`.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import Field

from semloc_core.experiments.demo_world import WorldSpec
from semloc_core.experiments.spec import Spec
from services.config import deep_merge

DEMO_GRAPH = "demo"  # the built-in graph (deploy/demo.yaml)
WORKER_ROLES = ("detector", "loopclosure", "localizer", "mapper")


class DemoSpec(Spec):
    """What the demo plays: its world and how fast (the defaults are the ``full`` preset)."""

    frames: int = Field(300, ge=20, description="frames of the world")
    laps: float = Field(3.0, ge=0.5, le=20, description="times the camera goes round the table")
    seed: int = Field(0, description="world seed")
    appearance: Literal["auto", "real", "generated"] = Field(
        "auto", description="object looks: real RGB-D Object crops (auto: when the data folder has them) or "
                            "generated textures")
    calibration_frames: int = Field(90, ge=10, description="frames of each calibration scene")
    rate: float = Field(10.0, gt=0, description="frames per second played (a stage that cannot keep up drops to "
                                                "the newest frame; the results name the one limiting the pose rate)")
    localizer_start: Literal["global", "known"] = Field(
        "known", description="global: localize from scratch over the whole room; known: start from the first "
                             "frame's true pose with AMCL's default uncertainty (0.5 m, 15 deg)")
    timeout_s: float = Field(900.0, gt=0, description="give up after this many seconds of playback")
    prune_levels: bool = Field(True, description="the detector matches each pyramid level only where objects of "
                                                 "its size can be, from the localizer's pose and the camera's true "
                                                 "height (issue 35)")

    def world(self) -> WorldSpec:
        return WorldSpec(frames=self.frames, laps=self.laps, seed=self.seed, appearance=self.appearance,
                         calibration_frames=self.calibration_frames)


@dataclass
class DemoOptions:
    """Where the demo's output goes and how it is shown."""

    workdir: Path = Path("runs/demo")      # run.rrd, results.{md,json}, plots/ and the workers' logs
    cache_dir: Path | None = None          # generated worlds (default: semloc_core.experiments.demo_world's)
    rerun: Literal["save", "connect", "serve", "off"] = "save"
    rerun_url: str | None = None           # rerun connect: the viewer's URL (default: the local viewer)
    rerun_ports: tuple[int, int] = (9090, 9876)  # rerun serve: the web viewer's and the gRPC server's
    viewer: object = None                  # rerun serve: set by run_demo, the recording serving the web viewer
    record: bool = False                   # also record the bus traffic to WORKDIR/session.mcap
    graph: Path | str = DEMO_GRAPH           # a graph file or a built-in graph's name
    robot: str | None = None               # robot namespace (default: the graph's)
    quiet: bool = False                    # only the results table
    command: str = "semloc demo"           # as reported in results.json


# ---------------------------------------------------------------------------------------------------- helpers
class Display:
    """Progress on stderr: a rewritten line on a terminal, a line every few seconds otherwise."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.last_print = 0.0
        self.open_line = False

    def say(self, message: str) -> None:
        if self.quiet:
            return
        self.end_line()
        print(message, file=sys.stderr, flush=True)

    def progress(self, text: str, force: bool = False) -> None:
        if self.quiet:
            return
        if self.tty:
            sys.stderr.write("\r\033[K" + text)
            sys.stderr.flush()
            self.open_line = True
        elif force or time.monotonic() - self.last_print >= 10.0:
            print(text, file=sys.stderr, flush=True)
            self.last_print = time.monotonic()

    def end_line(self) -> None:
        if self.open_line:
            sys.stderr.write("\n")
            sys.stderr.flush()
            self.open_line = False

    def bar(self, done: int, total: int, width: int = 24) -> str:
        filled = int(width * done / max(total, 1))
        return "[" + "#" * filled + "." * (width - filled) + "]"


def _clean(workdir: Path) -> None:
    """Remove what a previous demo left in ``workdir`` (only the demo's own entries)."""
    for name in ("state", "rerun", "run", "plots"):
        shutil.rmtree(workdir / name, ignore_errors=True)
    for name in ("run.rrd", "results.md", "results.json", "session.mcap"):
        (workdir / name).unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------------- run
class DemoError(RuntimeError):
    """The run failed (a worker did not start, the camera failed, playback timed out)."""


def run_demo(spec: DemoSpec, options: DemoOptions) -> tuple[dict, str]:
    """Play the demo: (results document, Markdown table), also written to the work directory. Raises ConfigError,
    ValueError or FileNotFoundError for a bad graph or world, DemoError when the run fails."""
    from services.launcher import find_graph

    find_graph(options.graph)  # a wrong graph is said at once, not after the world is built
    started = time.monotonic()
    display = Display(options.quiet)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", force=True)
    try:
        return _run(spec, options, display, started)
    finally:
        display.end_line()


def _world(spec: DemoSpec, options: DemoOptions, display):
    from semloc_core.experiments.demo_world import ensure_world

    stage_started = {}

    def progress(stage: str, done: int, total: int) -> None:
        start = stage_started.setdefault(stage, time.monotonic())
        rate = done / max(time.monotonic() - start, 1e-9)
        display.progress(f"  {stage:18s} {display.bar(done, total)} {done}/{total} ({rate:.1f}/s)",
                         force=done == total)
        if done == total:
            display.end_line()

    return ensure_world(spec.world(), options.cache_dir, log=display.say, progress=progress)


def _overrides(spec: DemoSpec, options: DemoOptions, world, workdir: Path, hub: str, recording_id: str) -> dict:
    if options.rerun == "off":
        rerun = {"mode": "off"}
    elif options.rerun == "connect":
        rerun = {"mode": "grpc", "recording_id": recording_id}
        if options.rerun_url:
            rerun["url"] = options.rerun_url
    elif options.rerun == "serve":  # the demo's own recording serves (_open_demo_recording); the workers stream to it
        from services.viz import grpc_url

        rerun = {"mode": "grpc", "recording_id": recording_id, "url": grpc_url(options.rerun_ports[1])}
    else:
        rerun = {"mode": "save", "path": str(workdir / "rerun"), "recording_id": recording_id}
    # The demo's own recording carries the layout, with a heatmap tab per class (the merged run.rrd has it).
    rerun["layout"] = False
    overrides = deep_merge({"hub": hub, "rerun": rerun, "state_dir": str(workdir / "state")},
                           world_overrides(spec, world))
    if options.robot:
        overrides["robot"] = options.robot
    return overrides


def world_overrides(spec: DemoSpec, world) -> dict:
    """The demo graph's WORLD/ files and the settings that depend on the world (played at ``spec.rate``), as graph
    overrides: what `semloc demo` and `semloc up demo` run."""
    from semloc_core.experiments.demo_world import mapper_grid, pruning_settings

    grid_min, grid_max = mapper_grid(world)
    localizer = {"map": str(world.semantic_map), "score_likelihood": str(world.score_likelihood), "seed": spec.seed}
    if spec.localizer_start == "known":
        from semloc_core.io.dataset import open_dataset

        x, y, theta = (float(v) for v in open_dataset(world.dataset).poses2d[0])
        localizer["initial_pose"] = [x, y, theta]
    else:
        # From scratch, the filter needs augmented MCL's random particles to find (and re-find) the pose.
        localizer["filter"] = {"recovery_alpha_slow": 0.001, "recovery_alpha_fast": 0.1}
    return {
        "nodes": {
            "camera": {"config": {"source": str(world.dataset), "rate": spec.rate}},
            "detector": {"config": {"detector_file": str(world.detector),
                                    **({"prune": {**pruning_settings(world), "height_pose": True}}
                                       if spec.prune_levels else {})}},
            "localizer": {"config": localizer},
            "mapper": {"config": {"detector_file": str(world.detector), "grid_min": grid_min, "grid_max": grid_max,
                                  "extraction": {"support_z": float(world.info["table"]["surface_z"]),
                                                 "support_polygon": world.info["table"]["corners"]},
                                  "extraction_file": str(world.mapper_extraction)}},
        },
    }


def _split(graph, hub: str):
    """(the processing graph without the camera, a camera-only graph joining the first one's hub)."""
    from services.bus import BusConfig

    nodes = dict(graph.nodes)
    camera = nodes.pop("camera").model_copy(update={"start_after": []})  # the demo waits itself (_wait_running)
    processing = graph.model_copy(update={"nodes": nodes})
    sensor = graph.model_copy(update={"name": f"{graph.name}-camera", "hub": None, "nodes": {"camera": camera},
                                      "bus": BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])})
    return processing, sensor


def _run(spec: DemoSpec, options: DemoOptions, display, started) -> tuple[dict, str]:
    import numpy as np

    from semloc_core.io.dataset import open_dataset
    from services.bus import BusConfig, free_port, open_session
    from services.launcher import Launcher, load_graph

    display.say("semloc demo: camera -> detector, loop closure, localizer, mapper; simulated table top")
    world = _world(spec, options, display)
    info = world.info
    display.say(f"world: {info['frames']} frames at {world.fps:g} fps, {info['laps']} laps round a "
                f"{2 * info['table']['half_extent'][0]:.1f} x {2 * info['table']['half_extent'][1]:.1f} m table "
                f"with {info['object_count']} objects, {info['loop_pairs']} true loop pairs "
                f"({world.appearance} object appearances)")
    workdir = Path(options.workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    _clean(workdir)
    hub = f"tcp/127.0.0.1:{free_port()}"
    recording_id = f"semloc-demo-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    graph = load_graph(options.graph, _overrides(spec, options, world, workdir, hub, recording_id))
    missing = [role for role in ("camera",) + WORKER_ROLES if role not in graph.nodes]
    if missing:
        raise ValueError(f"{options.graph}: the demo needs nodes named {missing}")
    robot = graph.robot
    processing, sensor = _split(graph, hub)
    dataset = open_dataset(world.dataset)
    stamps = np.asarray(dataset.stamps_ns, np.int64)
    index_of_stamp = {int(s): i for i, s in enumerate(stamps)}
    truth2d = np.asarray(dataset.poses2d, float)

    rec = viz = None
    if graph.rerun.mode != "off":
        rec, viz = _open_demo_recording(graph, options, robot, workdir, recording_id, dataset, stamps, truth2d)

    workers = [name for name in processing.nodes if processing.nodes[name].enabled]
    launcher = Launcher(processing, run_dir=workdir / "run")
    camera_launcher = Launcher(sensor, run_dir=workdir / "run" / "camera")
    display.say(f"starting {', '.join(workers)} (logs in {workdir / 'run' / 'logs'})")
    collector = session = recorder = None
    final_map = topomap = None
    launcher.start()
    playback = {"start": None, "end": None}
    try:
        session = open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"]))
        from services.demo_collector import Collector

        collector = Collector(session, robot, camera=str(graph.nodes["camera"].config.get("camera", "front")),
                              on_pose=viz.on_pose if viz else None, on_output=viz.on_output if viz else None,
                              on_image=viz.on_image if viz else None)
        _wait_running(launcher, collector, workers, display)
        if options.record:
            from schemas import keys
            from services.recording import Recorder

            recorder = Recorder(session, keys.robot_all(robot), workdir / "session.mcap", compress=True)
        display.say(f"playing {info['frames']} frames at {spec.rate:g} Hz")
        camera_launcher.start()
        playback["start"] = time.monotonic()
        _play(camera_launcher, launcher, collector, workers, info["frames"], truth2d, index_of_stamp, display,
              spec.timeout_s)
        playback["end"] = collector.last_image or time.monotonic()
        display.progress("draining the pipeline ...", force=True)
        deadline = time.monotonic() + 60.0
        time.sleep(1.0)
        while time.monotonic() < deadline and not collector.settled(workers, quiet_s=2.5):
            _show(collector, workers, info["frames"], truth2d, index_of_stamp, display, playback["start"])
            time.sleep(0.5)
        display.end_line()
        final_map, topomap = _final_queries(session, robot)
        snapshot = collector.snapshot()
    finally:
        display.end_line()
        if recorder is not None:
            recorder.close()
            display.say(f"recording ended early: {recorder.error} ({recorder.lost} messages lost)" if recorder.error
                        else f"recorded {recorder.count} messages to {recorder.path}")
        if collector is not None:
            collector.close()
        camera_launcher.stop()
        launcher.stop()
        if session is not None:
            session.close()
    if viz is not None and topomap is not None:
        _log_topomap(viz, topomap, index_of_stamp, truth2d)
    if rec is not None:
        rec.flush(timeout_sec=10.0)
        if options.rerun == "serve":
            options.viewer = rec  # serving until the caller lets it go
        else:
            rec.disconnect()
    rrd = None
    if graph.rerun.mode == "save":
        rrd = _merge_recordings(workdir / "rerun", workdir / "run.rrd", display)
    summary = launcher.summary()
    crashed = {name: s for name, s in summary.items() if s["starts"] > 1 or s["last_exit"] not in (0, None)}
    return _report(spec, options, world, dataset, snapshot, final_map, topomap, playback, started, workdir, rrd,
                   crashed, {role: role for role in ("camera",) + WORKER_ROLES if role in graph.nodes}, display)


def _open_demo_recording(graph, options, robot, workdir, recording_id, dataset, stamps, truth2d):
    import rerun as rr

    from services.blueprint import semloc_blueprint
    from services.demo_viz import DemoViz

    blueprint = semloc_blueprint(robot, dataset.semantic_map.class_names)
    rec = rr.RecordingStream("semloc", recording_id=recording_id)
    if graph.rerun.mode == "save":
        (workdir / "rerun").mkdir(parents=True, exist_ok=True)
        rec.save(str(workdir / "rerun" / "demo.rrd"), default_blueprint=blueprint)
    elif options.rerun == "serve":
        from services.viz import RerunConfig, serve

        web_port, grpc_port = options.rerun_ports
        display_url = serve(rec, RerunConfig(web_port=web_port, grpc_port=grpc_port), blueprint)
        print(f"rerun web viewer: {display_url}", file=sys.stderr, flush=True)
    else:
        rec.connect_grpc(graph.rerun.url, default_blueprint=blueprint)
    viz = DemoViz(rec, robot, stamps, truth2d)
    viz.log_world(dataset.semantic_map, dataset.T_world_cam)
    return rec, viz


def _wait_running(launcher, collector, workers, display, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        running = collector.running(workers)
        if len(running) == len(workers):
            return
        summary = launcher.summary()
        dead = [n for n in workers if summary[n]["finished"]]
        if dead:
            raise DemoError(f"worker(s) {dead} stopped before the camera started; see "
                               f"{launcher.run_dir / 'logs'}")
        display.progress(f"  waiting for workers: {len(running)}/{len(workers)} running "
                         f"({', '.join(sorted(set(workers) - set(running)))} starting)")
        time.sleep(0.2)
    display.end_line()
    raise DemoError(f"workers did not all start within {timeout:.0f} s (running: {collector.running(workers)}); "
                       f"see {launcher.run_dir / 'logs'}")


def _show(collector, workers, frames, truth2d, index_of_stamp, display, start) -> None:
    import numpy as np

    from services.demo_report import MAIN_INPUT

    processed = collector.processed(MAIN_INPUT)
    with collector.lock:
        published = len(collector.images.arrivals)
        pose = collector.poses[-1] if collector.poses else None
        maps = collector.object_maps[-1][1] if collector.object_maps else None
        loops = sum(1 for _, f in collector.loopclosure_frames.get("events", []) if f.status == "loop_found")
    parts = [f"{display.bar(published, frames)} frame {published}/{frames}"]
    for worker in workers:
        text = f"{worker} {processed.get(worker, 0)}"
        if worker == "localizer" and pose is not None and pose.stamp_ns in index_of_stamp:
            truth = truth2d[index_of_stamp[pose.stamp_ns]]
            text += f" (err {float(np.hypot(*(pose.pose[:2] - truth[:2]))):.2f} m)"
        elif worker == "mapper" and maps is not None:
            text += f" ({len(maps)} obj)"
        elif worker == "loopclosure":
            text += f" ({loops} loops)"
        parts.append(text)
    parts.append(f"{time.monotonic() - start:.0f} s")
    display.progress(" | ".join(parts))


def _play(camera_launcher, launcher, collector, workers, frames, truth2d, index_of_stamp, display, timeout) -> None:
    start = time.monotonic()
    while not camera_launcher.finished():
        if time.monotonic() - start > timeout:
            raise DemoError(f"playback did not finish within {timeout:.0f} s")
        _show(collector, workers, frames, truth2d, index_of_stamp, display, start)
        time.sleep(0.5)
    _show(collector, workers, frames, truth2d, index_of_stamp, display, start)
    display.end_line()
    exit_code = camera_launcher.summary()["camera"]["last_exit"]
    if exit_code not in (0, None):
        raise DemoError(f"the camera exited with code {exit_code}; see {camera_launcher.run_dir / 'logs'}")


def _final_queries(session, robot):
    """The mapper's final object map and the loop-closure worker's topological map (None when unavailable)."""
    from schemas import FrameError, keys
    from schemas.loopclosure import TopoMap
    from schemas.mapping import ObjectMap
    from services.bus import QueryError, query

    results = []
    for key, frame_type in ((keys.mapper_map(robot), ObjectMap), (keys.loopclosure_topomap(robot), TopoMap)):
        try:
            replies = query(session, key, reply_type=frame_type, timeout=10.0)
        except (QueryError, FrameError) as error:
            logging.getLogger("semloc.demo").warning("query %s failed: %s", key, error)
            replies = []
        results.append(replies[0] if replies else None)
    return tuple(results)


def _log_topomap(viz, topomap, index_of_stamp, truth2d) -> None:
    import numpy as np

    frames = [index_of_stamp.get(int(s), -1) for s in topomap.keyframe_stamps_ns]
    positions = np.array([truth2d[f, :2] if f >= 0 else [np.nan, np.nan] for f in frames]).reshape(-1, 2)
    positions = np.nan_to_num(positions)
    edges = [(int(a), int(b)) for a, b in np.asarray(topomap.edges)]
    viz.log_topology(int(topomap.header.stamp_ns), list(range(len(frames))), positions, edges, [])
    if topomap.keyframe_poses is not None:  # the hybrid map: each place at the pose recorded while localized
        viz.log_places(int(topomap.header.stamp_ns), np.asarray(topomap.keyframe_poses, float))


def _merge_recordings(folder: Path, output: Path, display) -> Path | None:
    """Every worker's .rrd (same recording id) and the demo's (with the blueprint) -> one file, its chunks compacted
    (``rerun rrd optimize``: ~20 % smaller and faster to load than a plain merge). The parts are removed after."""
    parts = sorted(folder.glob("*.rrd"))
    if not parts:
        display.say("rerun: no recordings to merge")
        return None
    command = [sys.executable, "-m", "rerun_cli", "rrd", "optimize", *map(str, parts), "-o", str(output)]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0 or not output.is_file():
        display.say(f"rerun: merging failed ({result.stderr.strip()[-400:]}); the parts stay in {folder}")
        return None
    shutil.rmtree(folder, ignore_errors=True)
    return output


def _report(spec: DemoSpec, options: DemoOptions, world, dataset, snapshot, final_map, topomap, playback, started,
            workdir, rrd, crashed, nodes, display) -> tuple[dict, str]:
    import numpy as np

    from semloc_core.eval.report import json_text
    from services import demo_report as report

    stamps = np.asarray(dataset.stamps_ns, np.int64)
    index_of_stamp = {int(s): i for i, s in enumerate(stamps)}
    truth2d = np.asarray(dataset.poses2d, float)
    lc_frames = snapshot["loopclosure_frames"]
    events = [f for _, f in lc_frames.get("events", [])]
    rows = [f for _, f in lc_frames.get("similarity", [])]
    if "loopclosure" in nodes:
        loop = report.loop_closure_results(events, rows, index_of_stamp, dataset.loop_gt, dataset.loop_gt_soft,
                                           positions=dataset.T_world_cam[:, :3, 3] if dataset.has_poses else None)
        if loop.get("available"):
            loop["places"] = report.place_results(topomap, index_of_stamp, truth2d)
    else:
        loop = {"available": False, "reason": "no loop-closure node"}
    if final_map is None and snapshot["object_maps"]:
        final_map = snapshot["object_maps"][-1][1]
    duration = (playback["end"] or time.monotonic()) - (playback["start"] or started)
    first = snapshot["first_image"]
    last = snapshot["last_image"]
    playback_s = (last - first) if first is not None and last is not None and last > first else duration
    doc = {
        "format": "semloc.demo_results", "version": 1, "command": options.command,
        "world": {**world.info, "appearance": world.appearance, "path": str(world.path)},
        "run": {"rate_hz": spec.rate, "frames_played": len(snapshot["images"].arrivals),
                "playback_s": playback_s, "total_s": time.monotonic() - started,
                "localizer_start": spec.localizer_start, "restarts_or_failures": crashed,
                "rrd": str(rrd) if rrd else None, "machine_cpus": os.cpu_count()},
        "loop_closure": loop,
        "localization": report.localization_results(snapshot["poses"], index_of_stamp, truth2d, stamps,
                                                    dataset.odometry),
        "mapping": report.mapping_results(final_map, dataset.semantic_map),
        "stages": report.stage_results(snapshot, nodes, playback_s),
    }
    doc["pose_rate"] = {**report.pose_rate_limit(doc["stages"], spec.rate),
                        "poses_hz": len(snapshot["poses"]) / playback_s if playback_s > 0 else None}
    from services.demo_figure import overview_png

    from semloc_core.io.atomic import replace_text

    # A full or read-only disk loses the files, not the results: the table is still printed, the error said.
    doc["run"]["write_error"] = None
    try:
        plots = report.write_plots(doc, dataset.semantic_map, truth2d, stamps, workdir / "plots")
        plots.append(overview_png(workdir / "plots" / "overview.png", doc, snapshot, dataset, topomap))
    except OSError as error:
        plots, doc["run"]["write_error"] = [], f"cannot write {error.filename}: {error.strerror}"
    doc["plots"] = [str(p.relative_to(workdir)) for p in plots]
    doc["run"]["total_s"] = time.monotonic() - started
    markdown = report.results_markdown(doc)
    public = report.public(doc)
    try:
        replace_text(workdir / "results.md", markdown)
        replace_text(workdir / "results.json", json_text(public))
    except OSError as error:  # the first failure says it (the plots' when they failed too)
        public["run"]["write_error"] = doc["run"]["write_error"] = (doc["run"]["write_error"] or
                                                                    f"cannot write {error.filename}: {error.strerror}")
    display.end_line()
    return public, markdown
