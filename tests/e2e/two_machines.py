"""deploy/two-machines/ on one machine, plain or secure: two routers on loopback ports, the camera and detector
behind the robot's, the localizer behind the base station's (tests/e2e/test_two_machines.py,
tests/security/test_secure_two_machines.py)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from schemas import Image, Status, decode, keys
from schemas.localization import PoseEstimate
from services.bus import BusConfig, open_session, query
from services.launcher import Launcher, load_graph
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
TWO = REPO_ROOT / "deploy" / "two-machines"


def graph_overrides(dataset: Path, tmp_path: Path) -> tuple[dict, dict]:
    """(base station's, robot's) overrides of the graph files for a run on ``dataset``: the localizer alone at the
    base station, starting at the true first pose; camera and detector on the robot."""
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
    robot = {"nodes": {"camera": {"config": {"source": str(dataset), "rate": 4, "wait_for_subscriber_s": 30}},
                       "detector": {"config": {"detector_file": None, "detector": detector}}}}
    return base, robot


def plain_launchers(tmp_path: Path, dataset: Path) -> tuple[Launcher, Launcher, int, int]:
    """(base launcher, robot launcher, base hub port, robot hub port) of the plain files: the robot's router
    connects to the base station's over TCP (deploy/two-machines/robot-router.json5 with BASE_HOST set)."""
    base_port, robot_port = free_port(), free_port()
    robot_router = tmp_path / "robot-router.json5"
    robot_router.write_text((TWO / "robot-router.json5").read_text().replace("BASE_HOST:7447",
                                                                             f"127.0.0.1:{base_port}"))
    base, robot = graph_overrides(dataset, tmp_path)
    base["hub"] = f"tcp/127.0.0.1:{base_port}"
    robot.update(hub=f"tcp/127.0.0.1:{robot_port}", hub_zenoh_config=str(robot_router))
    return (Launcher(load_graph(TWO / "base.yaml", base), run_dir=tmp_path / "base"),
            Launcher(load_graph(TWO / "robot.yaml", robot), run_dir=tmp_path / "robot"), base_port, robot_port)


@dataclass
class SplitRun:
    poses: list[PoseEstimate]  # received by a client of the robot's router
    images_at_base: list[int]  # stamps of the images a client of the base station's router received
    localizer: Status  # the localizer's own counters at the end
    observed: list = field(default_factory=list)  # what `observe` collected


def _client(port: int):
    return open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))


def run_split_graph(base_launcher: Launcher, robot_launcher: Launcher, base_port: int, robot_port: int,
                    observe=None) -> SplitRun:
    """Start the base station, then the robot; collect poses at the robot's router until 10 have come back.
    Every node must be a client of its own machine's router (loopback). ``observe(collect)``, if given, is entered
    while the graph runs (e.g. an observer's subscription on another endpoint) and appends to ``collect``."""
    for launcher, port in ((robot_launcher, robot_port), (base_launcher, base_port)):
        for name in launcher.nodes:
            bus = yaml.safe_load((launcher.run_dir / f"{name}.yaml").read_text())["bus"]
            assert bus == {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}, (name, bus)
    poses, images_at_base, observed = [], [], []
    with base_launcher:
        with _client(base_port) as at_base:
            wait_until(lambda: query(at_base, keys.status("r1", "localizer"), timeout=1.0), 60,
                       interval=0.3, message="the base station's localizer")
            # A client of the base station's router sees the robot's images; one of the robot's router gets poses.
            image_sub = at_base.declare_subscriber(keys.camera_image("r1"), lambda s: images_at_base.append(
                decode(s.payload.to_bytes(), expected=Image).header.stamp_ns))
            with robot_launcher, _client(robot_port) as at_robot:
                pose_sub = at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: poses.append(
                    decode(s.payload.to_bytes(), expected=PoseEstimate)))
                if observe is not None:
                    with observe(observed):
                        wait_until(lambda: len(poses) >= 10, 120, interval=0.2, message="10 poses back at the robot")
                else:
                    wait_until(lambda: len(poses) >= 10, 120, interval=0.2, message="10 poses back at the robot")
                status = query(at_robot, keys.status("r1", "localizer"), reply_type=Status, timeout=2.0)[0]
                pose_sub.undeclare()
            image_sub.undeclare()
    return SplitRun(poses, images_at_base, status, observed)


def position_errors(dataset: Path, poses: list[PoseEstimate]) -> list[tuple[int, float]]:
    """(stamp, distance from the true position then) of every pose carrying a stamp of the data set."""
    data = np.load(dataset / "poses.npz", allow_pickle=False)
    index = {int(s): i for i, s in enumerate(data["stamps_ns"])}
    return [(p.header.stamp_ns, float(np.hypot(*(p.pose()[:2] - data["poses2d"][index[p.header.stamp_ns], :2]))))
            for p in poses if p.header.stamp_ns in index]
