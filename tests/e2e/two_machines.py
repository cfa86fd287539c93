"""deploy/two-machines/ on one machine, plain or secure: two routers on loopback ports, the camera and detector
behind the robot's, the localizer behind the base station's (tests/e2e/test_two_machines.py,
tests/security/test_secure_two_machines.py)."""

from __future__ import annotations

import contextlib
import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from schemas import Image, Status, decode, keys
from schemas.detection import Heatlines
from schemas.localization import PoseEstimate
from services.bus import BusConfig, open_session, query
from services.config import deep_merge
from services.launcher import Launcher, load_graph
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
TWO = REPO_ROOT / "deploy" / "two-machines"
CAMERA_RATE_HZ = 4  # frames (and odometry messages) a second


def graph_overrides(dataset: Path, tmp_path: Path, every_frame: bool = False) -> tuple[dict, dict]:
    """(base station's, robot's) overrides of the graph files for a run on ``dataset``: the localizer alone at the
    base station, starting at the true first pose; camera and detector on the robot. ``every_frame``: lossless
    queues from the camera to the localizer, so that every frame is answered (a run repeatable frame for frame)."""
    truth = np.load(dataset / "poses.npz", allow_pickle=False)["poses2d"]
    detector = {"kind": "templates", "templates": str(dataset / "exemplars"), "cell": 8, "scales": [1.0, 0.7]}
    base = {
        "rerun": {"mode": "off"}, "state_dir": str(tmp_path / "state"),
        "nodes": {"loopclosure": {"enabled": False}, "mapper": {"enabled": False}, "monitor": {"enabled": False},
                  "localizer": {"config": {"map": str(dataset / "semantic_map.json"), "score_likelihood": "synthetic",
                                           "initial_pose": [float(v) for v in truth[0]], "seed": 0,
                                           "initial_covariance": [0.0025, 0.0025, 0.003],
                                           # No random particles (AMCL's default): with the uncalibrated
                                           # synthetic score likelihood a few injected particles can outscore
                                           # the tracked ones when a loaded machine drops frames.
                                           "filter": {"max_particles": 2000, "min_particles": 200,
                                                      "recovery_alpha_slow": 0.0}}}},
    }
    robot = {"nodes": {"camera": {"config": {"source": str(dataset), "rate": CAMERA_RATE_HZ, "wait_for_subscriber_s": 30}},
                       "detector": {"config": {"detector_file": None, "detector": detector}}}}
    if every_frame:
        lossless = {"policy": "lossless", "depth": 64}
        base["nodes"]["localizer"]["inputs"] = {"heatlines": lossless}
        # Heatlines wait for the odometry that reaches their stamp, however loaded the machine: the same motion
        # before each update in every run.
        base["nodes"]["localizer"]["config"]["odometry_wait_s"] = 30.0
        robot["nodes"]["detector"]["inputs"] = {"image": lossless}
    return base, robot


def plain_launchers(tmp_path: Path, dataset: Path, every_frame: bool = False, base_port: int | None = None,
                    link_port: int | None = None, odometry_cache: int | None = None, camera: dict | None = None,
                    monitor: bool = False,
                    overrides: tuple[dict, dict] = ({}, {})) -> tuple[Launcher, Launcher, int, int]:
    """(base launcher, robot launcher, base hub port, robot hub port) of the plain files: the robot's router
    connects to the base station's over TCP (deploy/two-machines/robot-router.json5 with BASE_HOST set), at
    ``link_port`` if given (a relay standing for the radio link), else straight at the base station's hub port.
    ``odometry_cache``: the odometry messages the camera keeps for the localizer (default: its own). ``camera``: more
    of the camera's settings; ``monitor``: the base station's monitor on (it counts every stream of the robot);
    ``overrides``: (base station's, robot's) merged over the test's."""
    base_port, robot_port = base_port or free_port(), free_port()
    base, robot = (deep_merge(mine, extra) for mine, extra in zip(graph_overrides(dataset, tmp_path, every_frame),
                                                                  overrides))
    robot["nodes"]["camera"]["config"].update(camera or {})
    if monitor:
        base["nodes"]["monitor"]["enabled"] = True
    if odometry_cache is not None:
        robot["nodes"]["camera"]["outputs"] = {"odometry": {"recover": odometry_cache}}
    base["hub"] = f"tcp/127.0.0.1:{base_port}"
    robot.update(hub=f"tcp/127.0.0.1:{robot_port}",
                 hub_zenoh_config=str(robot_router_config(tmp_path, link_port or base_port)))
    return (Launcher(load_graph(TWO / "base.yaml", base), run_dir=tmp_path / "base"),
            Launcher(load_graph(TWO / "robot.yaml", robot), run_dir=tmp_path / "robot"), base_port, robot_port)


def robot_router_config(folder: Path, port: int) -> Path:
    """deploy/two-machines/robot-router.json5 connecting to ``port`` on loopback, written in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "robot-router.json5"
    path.write_text((TWO / "robot-router.json5").read_text().replace("BASE_HOST:7447", f"127.0.0.1:{port}"))
    return path


@dataclass
class SplitRun:
    poses: list[PoseEstimate]  # received by a client of the robot's router
    images_at_base: list[int]  # stamps of the images a client of the base station's router received
    heatlines_at_base: dict[int, str]  # stamp -> digest of the detector's heatlines received there
    localizer: Status  # the localizer's own counters at the end
    observed: list = field(default_factory=list)  # what `observe` collected


def _client(port: int):
    return open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))


def run_split_graph(base_launcher: Launcher, robot_launcher: Launcher, base_port: int, robot_port: int,
                    observe=None, poses_wanted: int = 10, images_wanted: int = 10, then=None,
                    base_workers: tuple[str, ...] = ("localizer",)) -> SplitRun:
    """Start the base station, then the robot; collect poses at the robot's router until ``poses_wanted`` have
    come back and ``images_wanted`` images have reached a client of the base station's router.
    Every node must be a client of its own machine's router (loopback). ``observe(collect)``, if given, is entered
    while the graph runs (e.g. an observer's subscription on another endpoint) and appends to ``collect``.
    ``then(poses, at_robot, at_base)``, if given, runs after that, the poses still being collected. The robot
    starts once each of ``base_workers`` runs (its kernels compiled)."""
    for launcher, port in ((robot_launcher, robot_port), (base_launcher, base_port)):
        for name in launcher.nodes:
            bus = yaml.safe_load((launcher.run_dir / f"{name}.yaml").read_text())["bus"]
            assert bus == {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}, (name, bus)
    poses, images_at_base, observed, heatlines_at_base = [], [], [], {}

    def on_heatlines(sample) -> None:
        payload = sample.payload.to_bytes()
        heatlines_at_base[decode(payload, expected=Heatlines).header.stamp_ns] = hashlib.sha256(payload).hexdigest()

    with base_launcher, _client(base_port) as at_base:
        def ready(worker: str) -> bool:
            replies = query(at_base, keys.status("r1", worker), reply_type=Status, timeout=1.0)
            return bool(replies) and replies[0].state == "running"

        wait_until(lambda: all(ready(w) for w in base_workers), 120, interval=0.3,
                   message=f"the base station's {', '.join(base_workers)}")
        heatlines_sub = at_base.declare_subscriber(keys.detector_heatlines("r1"), on_heatlines)
        with observe(observed) if observe is not None else contextlib.nullcontext(), robot_launcher, \
                _client(robot_port) as at_robot:
            # A client of the robot's router gets the poses; one of the base station's router sees the robot's images
            # - once the detector listens: the camera starts with its first subscriber, which must be the detector
            # for every frame to be detected.
            pose_sub = at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: poses.append(
                decode(s.payload.to_bytes(), expected=PoseEstimate)))
            wait_until(lambda: "image" in _counters(at_robot, "detector").get("in", {}), 60, interval=0.2,
                       message="the robot's detector")
            image_sub = at_base.declare_subscriber(keys.camera_image("r1"), lambda s: images_at_base.append(
                decode(s.payload.to_bytes(), expected=Image).header.stamp_ns))
            # Images are counted from the subscription on, which is declared after the first frames may have gone
            # by: wait for them too rather than stopping at the poses.
            wait_until(lambda: len(poses) >= poses_wanted and len(images_at_base) >= images_wanted, 120, interval=0.2,
                       message=lambda: (
                f"{poses_wanted} poses back at the robot and images at the base (got {len(poses)} poses, "
                f"{len(images_at_base)} images; detector "
                f"{_counters(at_robot, 'detector')}, localizer {_counters(at_base, 'localizer')})"))
            if then is not None:
                then(poses, at_robot, at_base)
            status = query(at_robot, keys.status("r1", "localizer"), reply_type=Status, timeout=2.0)[0]
            # Each launcher hears its running nodes' heartbeats, through its router's access control if any.
            for launcher in (base_launcher, robot_launcher):
                heard = {name: node.heartbeat_age_s is not None for name, node in launcher.view().nodes.items()
                         if node.pid is not None}
                assert heard and all(heard.values()), (launcher.graph.name, heard)
            pose_sub.undeclare()
            image_sub.undeclare()
        heatlines_sub.undeclare()
    return SplitRun(poses, images_at_base, heatlines_at_base, status, observed)


def _counters(session, worker: str) -> dict:
    """A worker's input and output counters, from its Status ({} while it does not answer)."""
    frame = _status(session, worker)
    return {} if frame is None else {"in": {k: v.received for k, v in frame.inputs.items()},
                                     "out": {k: v.published for k, v in frame.outputs.items()}}


def position_errors(dataset: Path, poses: list[PoseEstimate]) -> list[tuple[int, float]]:
    """(stamp, distance from the true position then) of every pose carrying a stamp of the data set."""
    data = np.load(dataset / "poses.npz", allow_pickle=False)
    index = {int(s): i for i, s in enumerate(data["stamps_ns"])}
    return [(p.header.stamp_ns, float(np.hypot(*(p.pose()[:2] - data["poses2d"][index[p.header.stamp_ns], :2]))))
            for p in poses if p.header.stamp_ns in index]


def wait_for_gap_odometry(at_base, cut_s: float) -> None:
    """Until the localizer has the odometry of a cut of ``cut_s``, recovered or counted missed: the first heatlines
    after the gap may make poses while its odometry is still on its way."""
    def accounted() -> bool:
        replies = query(at_base, keys.status("r1", "localizer"), reply_type=Status, timeout=1.0)
        odometry = replies[0].inputs["odom"] if replies else None
        return odometry is not None and odometry.recovered + odometry.missed >= 0.8 * cut_s * CAMERA_RATE_HZ

    wait_until(accounted, 15, interval=0.2, message="the gap's odometry recovered or counted missed")


def assert_gap_bridged(run: SplitRun, dataset: Path, poses_before: int, cut_s: float, poses_after: int) -> None:
    """The odometry of a cut of ``cut_s`` came back with the link, all of it (keys.RECOVERABLE_STREAMS),
    so the ``poses_after`` poses after the link returned are about as close to the truth as the ``poses_before``
    before it (the odometry's own drift over a 10 s gap apart: 0.07-0.13 m here); without it they were 1.7 m off
    after 10 s (1.4-3.6 m after 5-30 s, docs/results/2026-12-07-link-loss.md): the robot moved while the base station
    heard nothing."""
    recovered = run.localizer.inputs["odom"]
    assert recovered.recovered >= 0.8 * cut_s * CAMERA_RATE_HZ and recovered.missed == 0, recovered
    before, after = (dict(position_errors(dataset, poses)) for poses in (
        run.poses[:poses_before], run.poses[poses_before:poses_before + poses_after]))
    assert len(after) == poses_after and before, after
    judged = [(p.state, round(after[p.header.stamp_ns], 3)) for p in run.poses[poses_before:][:poses_after]]
    assert max(after.values()) < max(before.values()) + 0.5, (judged, sorted(before.values()))


def measure_link(at_robot, at_base, seconds: float) -> dict:
    """Over ``seconds`` of a running split graph whose camera stamps its frames with the wall clock (``stamp:
    wall``): the camera's image rate (its Status), the poses' latency at a client of the robot's router (arrival less
    stamp, s, in arrival order), and the Status of the robot's camera and detector and of the base station's
    localizer and monitor (None: no answer)."""
    arrivals: list[float] = []
    pose_sub = at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: arrivals.append(
        time.time() - decode(s.payload.to_bytes(), expected=PoseEstimate).header.stamp_ns / 1e9))

    def images() -> tuple[float, int]:
        camera = _status(at_robot, "camera")
        return time.monotonic(), camera.outputs["image"].published if camera and "image" in camera.outputs else 0

    (start, first), _ = images(), time.sleep(seconds)
    end, last = images()
    pose_sub.undeclare()
    statuses = {w: _status(at_robot, w) for w in ("camera", "detector")}
    statuses.update({w: _status(at_base, w) for w in ("localizer", "monitor")})
    return {"camera_hz": (last - first) / (end - start), "latencies": arrivals, "status": statuses}


def _status(session, worker: str) -> Status | None:
    replies = query(session, keys.status("r1", worker), reply_type=Status, timeout=2.0)
    return replies[0] if replies else None
