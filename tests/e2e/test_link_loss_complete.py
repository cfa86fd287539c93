"""What crosses a cut link comes back with it (docs/deploy.md, "When the link drops"): deploy/two-machines/ on one
machine with loop closure and mapper at the base station and a saver at the robot (`semloc up --save`), the link
cut for 10 s through a relay (tests/e2e/relay.py) while the data set plays, heatmaps and heatlines made recoverable
as docs/deploy.md shows. Checked against the data set: every heatmap the detector made of its frames is integrated by the mapper with its pose, and the saved trajectory has a
pose for the frames of the gap. `python -m tests.e2e.test_link_loss_complete --demo-world` measures a cut and an
uncut run side by side on `semloc demo --fast`'s world, whose fitted extraction makes the objects found comparable
with its true ones (docs/results/2026-12-07-link-complete.md); `--restart-localizer` a localizer restarted mid-cut,
`--restart-mapper` the mapper (with `--cut-only`: the test's run); `--mode freeze` a silent link instead of a reset
one, `--cut-s S` its length, `--lossless-bps B` a lossless stream across it (docs/results/2026-12-07-link-freeze.md)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from schemas import Image, Status, decode, keys
from schemas.localization import PoseEstimate
from schemas.loopclosure import TopoMap
from schemas.mapping import ObjectMap
from semloc_core.io.semantic_map import load_semantic_map
from semloc_core.io.trajectory import read_tum
from services.bus import free_port, query, stream_qos
from services.frames import semantic_map_from_frame
from tests.e2e.relay import Relay
from tests.e2e.test_run_outputs import tum_rmse
from tests.e2e.two_machines import (CAMERA_RATE_HZ, plain_launchers, position_errors, run_split_graph,
                                    wait_for_gap_odometry)
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

FRAMES = 120  # 30 s at CAMERA_RATE_HZ
CUT_S = 10.0
BASE_WORKERS = ("localizer", "loopclosure", "mapper")
FOUND_WITHIN_M = 0.1  # an object found: one of its class this close to a true one
WATCH_S = 0.5  # CutWatch's sampling period
RADIO_BUFFER_BYTES = 32 << 10  # what the link holds (tests/e2e/relay.py): frozen, it fills as a radio's would
LOSSLESS_KEY = "semloc/r1/test/lossless"  # CutWatch's stream across the link


def full_graph(dataset: Path, tmp_path: Path, relay_port: int | None, base_port: int, world=None):
    """(base, robot, robot port) launchers: the test graph of tests/e2e/two_machines.py with loop closure and mapper
    at the base station and a saver at the robot; ``world``: a demo world's detector, map and fitted extraction
    (semloc_core.experiments.demo_world), its data set ``dataset``."""
    base, robot, _, robot_port = plain_launchers(tmp_path, dataset, base_port=base_port, link_port=relay_port,
                                                 overrides=_overrides(dataset, tmp_path, world))
    return base, robot, robot_port


def _overrides(dataset: Path, tmp_path: Path, world) -> tuple[dict, dict]:
    classes = sorted(p.name for p in (dataset / "exemplars").iterdir() if p.is_dir()) if world is None else None
    mapper = {"detector_file": None, "classes": classes, "publish_period_s": 1.0,
              "volume": {"heatmap_background": "surprisal"},  # deploy/demo.yaml's
              "extraction": {"min_views": 5, "position": "centroid", "threshold": 0.5}}
    # heatmaps and heatlines recoverable (not by default: keys.RECOVERABLE_STREAMS says why), as docs/deploy.md shows
    recover = {"recover": True}
    # A deeper queue for the mapper's heatmaps (docs/deploy.md: it absorbs a longer burst). Live ones behind the gap's
    # take no room of it; yet a loaded CI machine (load 9-13) starves the mapper after the backlog too: 1 of 13 runs
    # at the default 16 failed, unexplained (results: cut-restart-flake, backlog-live). What is refused is counted.
    base = {"nodes": {"loopclosure": {"enabled": True},
                      "mapper": {"enabled": True, "config": mapper, "inputs": {"heatmaps": recover | {"depth": 64}}},
                      "localizer": {"inputs": {"heatlines": recover}}}}
    robot = {"nodes": {"saver": {"worker": "saver", "config": {"folder": str(tmp_path / "save"), "period_s": 1.0}},
                       "detector": {"outputs": {"heatmaps": {"recover": 300}, "heatlines": {"recover": 300}}}}}
    if world is not None:
        from services.demo_run import DemoSpec, world_overrides

        demo = world_overrides(DemoSpec(), world)["nodes"]  # the mapper's and the localizer's files
        mapper.update(demo["mapper"]["config"])
        mapper["extraction"] = {"min_views": 5, "position": "centroid", **demo["mapper"]["config"]["extraction"]}
        base["nodes"]["localizer"]["config"] = {"score_likelihood": str(world.score_likelihood)}
        # the world's detector (over the test's, whose every field it sets)
        robot["nodes"]["detector"]["config"] = {"detector": yaml.safe_load(Path(world.detector).read_text())}
    return base, robot


def _status(session, worker: str) -> Status | None:
    replies = query(session, keys.status("r1", worker), reply_type=Status, timeout=2.0)
    return replies[0] if replies else None


class CutWatch:
    """What the robot's side does while the link is cut, seen from a client of each machine's router: when each
    stream's messages arrived at the robot (images, odometry, heatlines, heatmaps, poses), each worker's state and
    each launcher's router link every WATCH_S, and when the poses of the gap's images reached the robot."""

    STREAMS = {"image": keys.camera_image("r1"), "odometry": keys.odometry("r1"),
               "heatlines": keys.detector_heatlines("r1"), "heatmaps": keys.detector_heatmaps("r1")}

    def __init__(self, at_robot, at_base, base, robot, lossless_bps: float = 0.0):
        self.at_robot, self.at_base, self.launchers = at_robot, at_base, {"base": base, "robot": robot}
        self._stop = threading.Event()
        self.lossless = {"sent": 0, "received": 0}
        if lossless_bps:
            at_base.declare_subscriber(LOSSLESS_KEY, lambda s: self.lossless.__setitem__(
                "received", self.lossless["received"] + 1))
            self._sender = threading.Thread(target=self._send, args=(lossless_bps,), daemon=True)
            self._sender.start()
        self.arrivals: dict[str, list[float]] = {name: [] for name in self.STREAMS}
        self.image_stamps: list[tuple[float, int]] = []
        self.poses: list[tuple[float, int]] = []  # (arrival, stamp)
        self.samples: list[dict] = []
        self.cut_at = self.restored_at = None

        def on(name):
            def record(sample) -> None:
                now = time.monotonic()
                self.arrivals[name].append(now)
                if name == "image":
                    self.image_stamps.append((now, decode(sample.payload.to_bytes(), expected=Image).header.stamp_ns))
            return record

        self.subscribers = [at_robot.declare_subscriber(key, on(name)) for name, key in self.STREAMS.items()]
        self.subscribers.append(at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: self.poses.append(
            (time.monotonic(), decode(s.payload.to_bytes(), expected=PoseEstimate).header.stamp_ns))))

    def _send(self, bps: float) -> None:
        """A lossless stream from the robot to the base station at ``bps`` bytes a second (100 messages a second),
        as a robot's odometry and heatlines are at their real rates (100 Hz, 10 Hz of 7 kB: ~90 kB/s)."""
        publisher = self.at_robot.declare_publisher(LOSSLESS_KEY, congestion_control=stream_qos(False)[0])
        payload = bytes(int(bps / 100))
        while not self._stop.wait(0.01):
            publisher.put(payload)
            self.lossless["sent"] += 1
        publisher.undeclare()

    def cut(self) -> None:
        self.cut_at = time.monotonic()

    def restored(self) -> None:
        self.restored_at = time.monotonic()

    def sample_for(self, seconds: float) -> None:
        """Sample the workers' states and the launchers' links every WATCH_S for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            at = time.monotonic()
            sample = {"t": round(at - self.cut_at, 2),
                      "links": {name: launcher.view().router_links for name, launcher in self.launchers.items()}}
            for worker in ("camera", "detector", "saver"):
                frame = _status(self.at_robot, worker)
                sample[worker] = None if frame is None else (
                    frame.state, frame.state_reason, {k: v.published for k, v in frame.outputs.items()})
            frame = _status(self.at_base, "localizer")
            sample["localizer"] = None if frame is None else (frame.state, frame.state_reason)
            self.samples.append(sample)
            time.sleep(max(0.0, WATCH_S - (time.monotonic() - at)))

    def summary(self) -> dict:
        cut, back = self.cut_at, self.restored_at
        streams = {}
        for name, times in self.arrivals.items():
            inside = [t for t in times if cut <= t <= back]
            edges = [cut, *inside, back]
            streams[name] = {"count": len(inside), "hz": round(len(inside) / (back - cut), 2),
                             "largest_gap_s": round(float(np.diff(edges).max()), 2)}
        lost = {name: next((s["t"] for s in self.samples if s["links"][name] == 0), None) for name in self.launchers}
        states = {w: sorted({f"{s[w][0]}: {s[w][1]}" for s in self.samples if s[w] is not None} |
                            ({"no answer"} if any(s[w] is None for s in self.samples) else set()))
                  for w in ("camera", "detector", "saver", "localizer")}
        published = {w: [s[w][2] for s in self.samples if s[w] is not None] for w in ("camera", "detector")}
        rates = {w: {k: round((seen[-1][k] - seen[0][k]) / (self.samples[-1]["t"] - self.samples[0]["t"]), 2)
                     for k in seen[0]} if len(seen) > 1 else None for w, seen in published.items()}
        gap_images = {stamp for at, stamp in self.image_stamps if cut <= at <= back}
        arrived = {stamp: at for at, stamp in self.poses if stamp in gap_images and at > back}
        return {"streams_at_robot": streams, "published_hz": rates, "link_lost_after_s": lost, "states": states,
                "gap_images": len(gap_images), "gap_poses_after": len(arrived),
                "gap_poses_in_s": round(max(arrived.values()) - back, 2) if arrived else None}

    def close(self) -> None:
        self._stop.set()
        for subscriber in self.subscribers:
            subscriber.undeclare()


def measure(tmp_path: Path, dataset: Path, cut_s: float | None, world=None, restart_mapper: bool = False,
            mode: str = "refuse", frames: int = FRAMES, lossless_bps: float = 0.0) -> dict:
    """One run of the whole data set (``frames``), cut (``mode``, tests/e2e/relay.py) for ``cut_s`` once 10 poses
    came back (None: never), the mapper SIGKILLed 3 s into the cut and restarted by its launcher from its state_dir
    (``restart_mapper``), a lossless stream of ``lossless_bps`` crossing the link (:class:`CutWatch`); the counters
    and the maps once every frame went through, and what the robot's side did during the cut (``during``)."""
    base_port = free_port()
    seen: dict = {}

    def then(poses, at_robot, at_base) -> None:
        watch = CutWatch(at_robot, at_base, base, robot, lossless_bps)
        if cut_s is not None:
            relay.cut(mode)
            watch.cut()
            watch.sample_for(min(3.0, cut_s))
            if restart_mapper:
                os.kill(base.nodes["mapper"].pid, signal.SIGKILL)
                wait_until(lambda: getattr(_status(at_base, "mapper"), "state", None) == "running", 60,
                           message="the mapper restarted")
            watch.sample_for(max(0.0, cut_s - (time.monotonic() - watch.cut_at)))
            relay.restore()
            watch.restored()
        last: dict = {}

        def done() -> bool:  # the camera played everything and the base station's queues are empty
            detector, mapper = _status(at_robot, "detector"), _status(at_base, "mapper")
            if detector is None or mapper is None:
                return False
            heatmaps, poses = mapper.inputs["heatmaps"], mapper.inputs["pose"]
            # the poses too: a recovered pose backlog can arrive after the heatmaps (a CI run read 97 of 120); and
            # no heatmap left waiting in the mapper for its pose
            state = (detector.outputs["heatmaps"].published, heatmaps.processed, heatmaps.queued,
                     poses.processed, poses.queued, mapper.details.get("heatmaps_waiting"))
            settled = state == last.get("state") and state[2] == state[4] == state[5] == 0
            last["state"] = state
            # or the camera finished (stopped): what the detector missed is counted, not waited for
            return settled and (state[0] >= frames - 2 or _status(at_robot, "camera") is None)

        wait_until(done, 120, interval=3.0, message=lambda: f"every frame through ({last})")
        time.sleep(2.5)  # the last map published and saved
        seen["status"] = {w: _status(at_base if w in ("mapper", "loopclosure", "localizer") else at_robot, w)
                          for w in ("detector", "mapper", "loopclosure", "localizer", "saver")}
        seen["objects"] = query(at_base, keys.mapper_map("r1"), reply_type=ObjectMap, timeout=5.0)
        seen["topomap"] = query(at_base, keys.loopclosure_topomap("r1"), reply_type=TopoMap, timeout=5.0)
        seen["during"] = watch.summary() if cut_s is not None else None
        if lossless_bps:
            seen["during"]["lossless"] = dict(watch.lossless)
        watch.close()

    with Relay(base_port, buffer_bytes=RADIO_BUFFER_BYTES) as relay:
        base, robot, robot_port = full_graph(dataset, tmp_path, relay.port, base_port, world)
        run_split_graph(base, robot, base_port, robot_port, then=then, base_workers=BASE_WORKERS)
    return summarise(seen, dataset, tmp_path / "save" / "trajectory.tum") | {"during": seen["during"]}


def summarise(seen: dict, dataset: Path, trajectory: Path) -> dict:
    status = seen["status"]
    mapper_in = status["mapper"].inputs
    truth = load_semantic_map(dataset / "semantic_map.json")
    found = semantic_map_from_frame(seen["objects"][0]) if seen["objects"] else None
    stamps = read_tum(trajectory)[0] if trajectory.exists() else np.zeros(0)
    topomap = seen["topomap"][0] if seen["topomap"] else None
    return {
        "heatmaps_sent": status["detector"].outputs["heatmaps"].published,
        "heatmaps_integrated": mapper_in["heatmaps"].processed,
        "heatmaps_recovered": mapper_in["heatmaps"].recovered, "heatmaps_missed": mapper_in["heatmaps"].missed,
        "heatmaps_already_held": mapper_in["heatmaps"].already_held,
        "heatmaps_refused": mapper_in["heatmaps"].overflow,  # live ones its full queue refused (since the restart)
        "map_frames": seen["objects"][0].frames if seen["objects"] else 0,  # integrated, over restarts
        **{name: status["mapper"].details.get(name) for name in (  # never integrated, by reason (over restarts)
            "heatmaps_waiting", "heatmaps_without_pose", "heatmaps_over_pending")},
        "mapper_poses": mapper_in["pose"].processed,
        "objects_true": len(truth.positions), "objects": 0 if found is None else len(found.positions),
        "objects_found": 0 if found is None else sum(e < FOUND_WITHIN_M for e in errors(truth, found)),
        "object_error_m": None if found is None else float(np.median(errors(truth, found))),
        "keyframes": 0 if topomap is None else len(topomap.keyframes),
        "places": 0 if topomap is None else len(set(topomap.frame_node[topomap.frame_node >= 0].tolist())),
        "loop_images": status["loopclosure"].inputs["image"].processed,
        "poses_made": status["localizer"].outputs["pose"].published,
        "trajectory_lines": int(len(stamps)),
        "trajectory_gap_s": float(np.diff(np.sort(stamps)).max()) if len(stamps) > 1 else None,
        "trajectory_rmse_m": tum_rmse(dataset / "groundtruth_body.tum", trajectory)[0] if len(stamps) else None,
        "odometry_recovered": status["localizer"].inputs["odom"].recovered,
        "heatlines_recovered": status["localizer"].inputs["heatlines"].recovered,
    }


def errors(truth, found) -> list[float]:
    """Each true object's distance to the nearest found one of its class (inf: none)."""
    found_names = np.asarray(found.class_names)[found.class_index]
    return [float(min(np.linalg.norm(found.positions[found_names == name] - position, axis=1), default=np.inf))
            for name, position in zip(np.asarray(truth.class_names)[truth.class_index], truth.positions)]


def test_a_cut_loses_nothing_the_cache_holds(tmp_path, sim_dataset):
    """A 10 s cut while the data set plays, the mapper killed and restarted from its state during it: it integrates
    every heatmap the detector made once, each with its pose, those of the gap recovered after it, those its state
    held before the cut not again (the detector's cache holds them all); the localizer weighs the gap's heatlines
    too, so the trajectory the robot's saver writes has a pose for every frame, the gap's included. Without recovery
    43 of 120 heatmaps and poses were lost and the trajectory had a 1.47 s hole; a mapper restarted during the cut got
    none of the gap (docs/results/2026-12-07-link-complete.md, 2026-12-07-restart-during-cut.md)."""
    dataset = Path(sim_dataset("tabletop", frames=FRAMES, seed=0))
    got = measure(tmp_path, dataset, CUT_S, restart_mapper=True)
    figures = json.dumps(got, default=float)
    gap_frames = 0.8 * CUT_S * CAMERA_RATE_HZ
    assert got["heatmaps_sent"] >= FRAMES - 2, figures
    # over the restart: each heatmap integrated once, with its pose (the mapper counts one it could not integrate under
    # its reason: heatmaps_without_pose, heatmaps_over_pending)
    assert got["map_frames"] == got["heatmaps_sent"], figures
    assert got["heatmaps_recovered"] >= gap_frames and got["heatmaps_missed"] == 0, figures
    assert got["heatmaps_already_held"] >= 10, figures  # those of the 10 poses before the cut at least
    assert got["heatlines_recovered"] >= gap_frames and got["odometry_recovered"] >= gap_frames, figures
    # every frame the localizer made a pose of reached the saver; frames 1/30 s apart in the data set's time
    assert got["trajectory_lines"] == got["poses_made"] >= FRAMES - 10, figures
    assert got["trajectory_gap_s"] < 0.3, figures


GAP_FRAMES = int(CUT_S * CAMERA_RATE_HZ)
POSES_AFTER = 8  # live poses after the gap's


def _heatlines_recoverable() -> tuple[dict, dict]:
    """(base station's, robot's) overrides: the localizer's heatlines recoverable, as docs/deploy.md shows."""
    return ({"nodes": {"localizer": {"inputs": {"heatlines": {"recover": True}}}}},
            {"nodes": {"detector": {"outputs": {"heatlines": {"recover": 300}}}}})


def localizer_across_a_cut(tmp_path: Path, dataset: Path, cut: bool = True, restart: bool = False,
                           wall_stamps: bool = False, every_frame: bool = False) -> dict:
    """The localizer alone at the base station (tests/e2e/test_link_loss.py's graph, its heatlines recoverable), the
    link cut for CUT_S once 10 poses came back (``cut``), the localizer SIGKILLed 3 s into the cut and restarted by its
    launcher from its state_dir (``restart``): its counters, and each pose's position error by stamp (``errors``;
    ``after``: the stamps of the gap's poses and POSES_AFTER more, in the order they came) - or, with ``wall_stamps``
    (the camera stamps its frames with the wall clock), each pose's latency at the robot (``latency``: seconds after
    the link returned, arrival less stamp; docs/results/2026-12-07-restart-during-cut.md). ``every_frame``: lossless
    queues (tests/e2e/two_machines.py), a run repeatable frame for frame."""
    base_port, seen, latency = free_port(), {}, []

    def then(poses, at_robot, at_base) -> None:
        if wall_stamps:
            at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: latency.append((time.time(), time.time(
            ) - decode(s.payload.to_bytes(), expected=PoseEstimate).header.stamp_ns * 1e-9)))
        if cut:
            relay.cut("refuse")
        time.sleep(3.0)
        if restart:
            os.kill(base.nodes["localizer"].pid, signal.SIGKILL)
            wait_until(lambda: getattr(_status(at_base, "localizer"), "state", None) == "running", 60,
                       message="the localizer restarted")
        time.sleep(CUT_S - 3.0)
        seen["before"] = len(poses)
        relay.restore()
        seen["restored"] = time.time()
        wanted = seen["before"] + GAP_FRAMES + POSES_AFTER
        wait_until(lambda: len(poses) >= wanted, 60, message=lambda: f"{wanted} poses (got {len(poses)})")
        if cut:  # or counted missed; a restarted localizer got none before (measured, so not assumed here)
            with contextlib.suppress(AssertionError):
                wait_for_gap_odometry(at_base, CUT_S)
        time.sleep(10.0 if wall_stamps else 0.0)

    with Relay(base_port) as relay:
        camera = {"stamp": "wall"} if wall_stamps else None
        base, robot, _, robot_port = plain_launchers(tmp_path, dataset, every_frame, base_port=base_port,
                                                    link_port=relay.port, camera=camera,
                                                    overrides=_heatlines_recoverable())
        run = run_split_graph(base, robot, base_port, robot_port, then=then)
    odometry, heatlines = run.localizer.inputs["odom"], run.localizer.inputs["heatlines"]
    got = {"restarts": run.localizer.restarts, "odometry_recovered": odometry.recovered,
           "odometry_missed": odometry.missed, "odometry_already_held": odometry.already_held,
           "heatlines_recovered": heatlines.recovered, "heatlines_already_held": heatlines.already_held,
           "heatlines_missed": heatlines.missed, "poses_before": seen["before"]}
    if wall_stamps:
        got["latency"] = [(round(at - seen["restored"], 3), round(late, 3)) for at, late in latency
                          if at >= seen["restored"]]
    else:
        got["errors"] = {stamp: error for stamp, error in position_errors(dataset, run.poses)}
        got["after"] = [p.header.stamp_ns for p in run.poses[seen["before"]:]]
    return got


def test_a_localizer_restarted_during_a_cut_goes_on_as_if_never_stopped(tmp_path, sim_dataset):
    """Killed 3 s into a 10 s cut and restarted from its state, the localizer gets the gap's odometry and heatlines
    from the robot's caches when the link returns, not those its state held (the caches keep them too), and weighs
    them as it would have: it makes a pose of every frame of the gap, and those and the 8 after it are the uncut
    run's (equal to the millimetre in 4 of 6 runs; in 2 they were 0.02 m off from the gap's first frame on, up to
    0.13 m later: hence 0.15 m. Not the restore: a restarted run already differed before the cut once its localizer
    missed frame 0 at start-up, docs/results/2026-12-07-localizer-restore.md). Before, it made no pose of the gap's
    frames, and its first 8 after it were 0.09-0.14 m further off than the uncut run's (docs/results/2026-12-07-restart-during-cut.md)."""
    dataset = Path(sim_dataset("tabletop", frames=FRAMES, seed=0))
    uncut = localizer_across_a_cut(tmp_path / "uncut", dataset, cut=False, every_frame=True)
    got = localizer_across_a_cut(tmp_path / "restart", dataset, restart=True, every_frame=True)
    after = got["after"][:GAP_FRAMES + POSES_AFTER]
    apart = {stamp: round(abs(got["errors"][stamp] - uncut["errors"][stamp]), 3) for stamp in after
             if stamp in got["errors"] and stamp in uncut["errors"]}
    figures = json.dumps({k: v for k, v in got.items() if k not in ("errors", "after")} | {"apart_m": apart})
    assert got["restarts"] == 1, figures
    for stream in ("odometry", "heatlines"):
        assert got[f"{stream}_recovered"] >= 0.8 * GAP_FRAMES and got[f"{stream}_missed"] == 0, figures
        assert got[f"{stream}_already_held"] >= 1, figures  # the state's, in the caches too: not weighed again
    assert len(apart) == GAP_FRAMES + POSES_AFTER and max(apart.values()) < 0.15, figures


if __name__ == "__main__":
    import tempfile

    root = Path(tempfile.mkdtemp(prefix="link-complete-"))
    world = None
    if "--demo-world" in sys.argv:  # semloc demo --fast's world (cached, else generated)
        from semloc_core.experiments.demo_world import ensure_world
        from services.demo_run import DemoSpec

        world = ensure_world(DemoSpec(frames=FRAMES, laps=2, calibration_frames=60, appearance="generated").world())
        data = world.dataset
    else:
        from semloc_core.sim import make_scenario

        data = make_scenario("tabletop", frames=FRAMES, seed=0).write(root / "data", multiview=False)
    if "--restart-localizer" in sys.argv:  # the poses of the gap and after it against an uncut run's
        uncut = localizer_across_a_cut(root / "uncut", Path(data), cut=False)
        restarted = localizer_across_a_cut(root / "restart", Path(data), restart=True)
        after = restarted.pop("after")
        errors, reference = restarted.pop("errors"), uncut["errors"]
        restarted["errors_after_m"] = [round(errors[s], 3) for s in after if s in errors]
        restarted["uncut_errors_then_m"] = [round(reference[s], 3) for s in after if s in reference]
        print("restarted", json.dumps(restarted), flush=True)
        sys.exit(0)
    if "--catch-up" in sys.argv:  # after a 10 s cut: each pose's latency at the robot from the link's return
        print("catch-up", json.dumps(localizer_across_a_cut(root / "catch-up", Path(data), wall_stamps=True)),
              flush=True)
        sys.exit(0)
    mode = sys.argv[sys.argv.index("--mode") + 1] if "--mode" in sys.argv else "refuse"  # relay.cut's
    cut_s = float(sys.argv[sys.argv.index("--cut-s") + 1]) if "--cut-s" in sys.argv else CUT_S
    runs = (("uncut", None), ("cut", cut_s)) if "--cut-only" not in sys.argv else (("cut", cut_s),)
    for label, cut in runs:
        restart = cut is not None and "--restart-mapper" in sys.argv  # the mapper killed 3 s into the cut
        got = measure(root / label, Path(data), cut, world, restart, mode, lossless_bps=float(
            sys.argv[sys.argv.index("--lossless-bps") + 1]) if "--lossless-bps" in sys.argv else 0.0)
        print(label, json.dumps(got, default=float), flush=True)
    if len(runs) == 2:  # the cut run's saved poses against the uncut run's, stamp by stamp
        (uncut_stamps, uncut_poses), (cut_stamps, cut_poses) = (
            read_tum(root / label / "save" / "trajectory.tum") for label in ("uncut", "cut"))
        at = {round(t * 1e6): pose[:3, 3] for t, pose in zip(uncut_stamps, uncut_poses)}
        apart = [float(np.linalg.norm(pose[:3, 3] - at[round(t * 1e6)])) for t, pose in zip(cut_stamps, cut_poses)
                 if round(t * 1e6) in at]
        print("apart", json.dumps({"common": len(apart), "max_m": max(apart, default=None),
                                   "over_1mm": sum(a > 1e-3 for a in apart)}), flush=True)
