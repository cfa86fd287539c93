"""deploy/secure/'s routers with the radio link between them cut and restored (tests/e2e/test_link_loss.py does it
for the plain ones): the access control lets the localizer ask the camera's cache for the odometry of the gap, so
that it goes on from where the robot is (docs/deploy.md, "When the link drops")."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.e2e.relay import Relay
from tests.e2e.two_machines import assert_gap_bridged, graph_overrides, run_split_graph, wait_for_gap_odometry
from tests.security.helpers import TWO, secure_configs, secure_launcher
from tests.service.conftest import free_port, wait_until

pytestmark = pytest.mark.service
CUT_S = 10.0
POSES_AFTER = 8


def test_odometry_of_a_gap_crosses_the_secure_routers(tmp_path, pki, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=120, seed=0))
    base_tls, robot_tls, base_port, robot_port = (free_port() for _ in range(4))
    seen: dict = {}

    def cut_and_restore(poses, at_robot, at_base) -> None:
        relay.cut("refuse")
        time.sleep(CUT_S)
        seen["before"] = len(poses)
        relay.restore()
        wait_until(lambda: len(poses) >= seen["before"] + POSES_AFTER, 30, interval=0.2,
                   message=lambda: f"{POSES_AFTER} poses after the link returned (got {len(poses) - seen['before']})")
        wait_for_gap_odometry(at_base, CUT_S)

    with Relay(base_tls) as relay:
        configs = secure_configs(tmp_path / "secure", base_tls, robot_tls)
        robot_router = configs / "robot-router.json5"  # dialling the relay in front of the base station's router
        robot_router.write_text(robot_router.read_text().replace(f"tls/localhost:{base_tls}",
                                                                 f"tls/localhost:{relay.port}"))
        base, robot = graph_overrides(dataset, tmp_path)
        base["hub"], robot["hub"] = f"tcp/127.0.0.1:{base_port}", f"tcp/127.0.0.1:{robot_port}"
        run = run_split_graph(
            secure_launcher(TWO / "base.yaml", base, pki, configs / "base-router.json5", tmp_path / "base"),
            secure_launcher(TWO / "robot.yaml", robot, pki, robot_router, tmp_path / "robot"), base_port, robot_port,
            then=cut_and_restore)
    # Without the rule for the recovery's keys every message of the gap was refused and counted missed (43 of 43).
    assert_gap_bridged(run, dataset, seen["before"], CUT_S, POSES_AFTER)
