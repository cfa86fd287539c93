"""deploy/two-machines/ on one machine: two zenoh routers on different loopback ports, the robot's workers behind one,
the base station's behind the other. Frames published at the robot's router reach the localizer behind the base
station's router, and its poses come back to a client of the robot's router."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from schemas import Image, decode, keys
from schemas.localization import PoseEstimate
from services.bus import BusConfig, open_session, query
from services.launcher import Launcher, load_graph
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
TWO = REPO_ROOT / "deploy" / "two-machines"
pytestmark = pytest.mark.service


def _client(port: int):
    return open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))


def test_graph_split_over_two_routers(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    truth = np.load(dataset / "poses.npz", allow_pickle=False)["poses2d"]
    base_port, robot_port = free_port(), free_port()
    robot_router = tmp_path / "robot-router.json5"
    # deploy/two-machines/robot-router.json5 with BASE_HOST pointing at the base station's router on this machine.
    robot_router.write_text((TWO / "robot-router.json5").read_text().replace("BASE_HOST:7447",
                                                                             f"127.0.0.1:{base_port}"))
    detector = {"kind": "templates", "templates": str(dataset / "exemplars"), "cell": 8, "scales": [1.0, 0.7]}
    base = load_graph(TWO / "base.yaml", {
        "hub": f"tcp/127.0.0.1:{base_port}", "rerun": {"mode": "off"}, "state_dir": str(tmp_path / "state"),
        "nodes": {"loopclosure": {"enabled": False}, "mapper": {"enabled": False}, "monitor": {"enabled": False},
                  "localizer": {"config": {"map": str(dataset / "semantic_map.json"), "score_likelihood": "synthetic",
                                           "initial_pose": [float(v) for v in truth[0]], "seed": 0,
                                           "initial_covariance": [0.0025, 0.0025, 0.003],
                                           # No random particles (AMCL's default): with the uncalibrated
                                           # synthetic score likelihood a few injected particles can outscore
                                           # the tracked ones when a loaded machine drops frames.
                                           "filter": {"max_particles": 2000, "min_particles": 200,
                                                      "recovery_alpha_slow": 0.0}}}},
    })
    robot = load_graph(TWO / "robot.yaml", {
        "hub": f"tcp/127.0.0.1:{robot_port}", "hub_zenoh_config": str(robot_router),
        "nodes": {"camera": {"config": {"source": str(dataset), "rate": 4, "wait_for_subscriber_s": 30}},
                  "detector": {"config": {"detector_file": None, "detector": detector}}},
    })
    base_launcher = Launcher(base, run_dir=tmp_path / "base")
    robot_launcher = Launcher(robot, run_dir=tmp_path / "robot")
    # Every robot node is a client of the robot's router only; every base node of the base station's.
    for launcher, port in ((robot_launcher, robot_port), (base_launcher, base_port)):
        for name in launcher.nodes:
            bus = yaml.safe_load((launcher.run_dir / f"{name}.yaml").read_text())["bus"]
            assert bus == {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}, (name, bus)
    poses, images_at_base = [], []
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
                wait_until(lambda: len(poses) >= 10, 120, interval=0.2, message="10 poses back at the robot")
                status = query(at_robot, keys.status("r1", "localizer"), timeout=2.0)[0]
                pose_sub.undeclare()
            image_sub.undeclare()
    heatlines = status.inputs["heatlines"]
    assert heatlines.received >= 10 and heatlines.rejected == 0
    assert len(images_at_base) >= 10
    # The poses are the localizer's answers to these frames: each carries the stamp of a frame of the data set and
    # lies near the camera's true position then (a sanity bound: the camera circles a table ~1.5 m away; accuracy
    # is the demo's business).
    stamps = np.load(dataset / "poses.npz", allow_pickle=False)["stamps_ns"]
    index = {int(s): i for i, s in enumerate(stamps)}
    errors = [np.hypot(*(p.pose()[:2] - truth[index[p.header.stamp_ns], :2])) for p in poses
              if p.header.stamp_ns in index]
    assert len(errors) == len(poses) >= 10
    assert max(errors) < 1.0, json.dumps([float(e) for e in errors])
