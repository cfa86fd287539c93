"""The radio link between the robot's router and the base station's drops and comes back (docs/deploy.md, "When the
link drops"): deploy/two-machines/ on one machine as tests/e2e/test_two_machines.py runs it, the robot router's
connect endpoint pointing at a relay (tests/e2e/relay.py) in front of the base station's router. The link is cut for
five leases, then restored: both launchers and `semloc status` say the link is down while it is, the robot's router
tries again about every second and connects again, the poses come back to the robot, and the odometry of the gap
reaches the localizer when the link returns (recovered from the camera's cache), so that its first poses after the
gap are where the robot is, not where it was when the link dropped."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.bus import BusConfig, free_port, open_session, stream_qos
from services.launcher import Launcher, load_graph
from tests.e2e.relay import Relay
from tests.e2e.test_link_loss_complete import LOSSLESS_KEY
from tests.e2e.two_machines import (CAMERA_RATE_HZ, REPO_ROOT, TWO, assert_gap_bridged, plain_launchers,
                                    robot_router_config, run_split_graph, wait_for_gap_odometry)
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

CUT_S = 10.0  # five leases (deploy/two-machines/robot-router.json5: 2 s)
RETRY_S = 1.0  # the robot router's connect/retry/period_max_ms
POSES_AFTER = 8
SMALL_CACHE = 10  # odometry messages: a quarter of the cut's


def _links(launcher) -> tuple:
    view = launcher.view()
    return view.router_links, view.router_links_lost, view.router_links_regained, view.router_link_down_s


@pytest.mark.parametrize("odometry_cache", [None, SMALL_CACHE], ids=["default cache", "small cache"])
def test_link_cut_and_restored(tmp_path, sim_dataset, odometry_cache):
    dataset = Path(sim_dataset("tabletop", frames=120, seed=0))
    base_port = free_port()
    seen: dict = {}

    def cut_and_restore(poses, at_robot, at_base) -> None:
        seen["links_up"] = [_links(launcher) for launcher in (base, robot)]
        relay.cut("refuse")
        cut_at = time.monotonic()
        before = len(poses)
        time.sleep(2.5)  # beyond the lease: both routers have noticed
        seen["links_cut"] = [_links(launcher) for launcher in (base, robot)]
        status = subprocess.run([sys.executable, "-m", "services.cli", "status", "--mode", "client", "--connect",
                                 f"tcp/127.0.0.1:{robot_port}", "--wait", "2"], cwd=REPO_ROOT, capture_output=True,
                                text=True, timeout=30)
        seen["status"] = (status.returncode, status.stdout.splitlines()[-1:])
        time.sleep(max(0.0, CUT_S - (time.monotonic() - cut_at)))
        seen["during"] = len(poses) - before
        relay.restore()
        restored, seen["before"] = time.monotonic(), len(poses)
        accepted = relay.accepted
        wait_until(lambda: relay.accepted > accepted, 10, message="the robot's router connecting again")
        seen["reconnect_s"] = time.monotonic() - restored
        wait_until(lambda: len(poses) >= seen["before"] + POSES_AFTER, 30, interval=0.2,
                   message=lambda: f"{POSES_AFTER} poses after the link returned (got {len(poses) - seen['before']})")
        seen["poses_back_s"] = time.monotonic() - restored
        wait_for_gap_odometry(at_base, CUT_S)
        seen["links_back"] = [_links(launcher) for launcher in (base, robot)]
        seen["attempts"] = [round(t - cut_at, 2) for t in relay.refused]

    with Relay(base_port) as relay:
        base, robot, _, robot_port = plain_launchers(tmp_path, dataset, base_port=base_port, link_port=relay.port,
                                                    odometry_cache=odometry_cache)
        run = run_split_graph(base, robot, base_port, robot_port, then=cut_and_restore)
    figures = json.dumps(seen)
    # Each launcher's router counts its link to the other: (open, lost, regained, down for s).
    assert seen["links_up"] == [(1, 0, 0, None)] * 2, figures
    assert all(links[:3] == (0, 1, 0) and 2.0 < links[3] < CUT_S for links in seen["links_cut"]), figures
    assert seen["status"][0] == 1 and "ROUTER LINK DOWN" in seen["status"][1][0], figures
    assert seen["during"] <= 1, figures  # one in flight at the cut at most: nothing crosses a cut link
    # The router tries again about every RETRY_S while the link is down (zenoh's default: after 1 s, 2 s, then every
    # 4 s), so it is back within about that of the link's return, and the poses with it.
    attempts = seen["attempts"]
    assert len(attempts) >= 4 and max(np.diff(attempts)) < RETRY_S + 0.8, figures
    assert seen["reconnect_s"] < RETRY_S + 1.5, figures
    assert seen["links_back"] == [(1, 1, 1, None)] * 2, figures
    if odometry_cache == SMALL_CACHE:
        # What the camera still kept came back, the rest is counted as missed for good.
        odometry = run.localizer.inputs["odom"]
        assert 0 < odometry.recovered <= SMALL_CACHE, (figures, odometry)
        assert odometry.recovered + odometry.missed >= 0.8 * CUT_S * CAMERA_RATE_HZ, (figures, odometry)
    else:
        assert_gap_bridged(run, dataset, seen["before"], CUT_S, POSES_AFTER)


def _robot_router(tmp_path, relay) -> Launcher:
    """The robot's launcher without its nodes: its router is what is watched."""
    return Launcher(load_graph(TWO / "robot.yaml", {
        "hub": f"tcp/127.0.0.1:{free_port()}", "hub_zenoh_config": str(robot_router_config(tmp_path, relay.port)),
        "nodes": {"camera": {"enabled": False}, "detector": {"enabled": False}}}), run_dir=tmp_path / "robot")


def test_robot_started_while_the_base_station_is_out_of_reach(tmp_path):
    """The robot's launcher starts with the link down: its router opens at once, says the link is down from the
    start, and connects once the base station's router answers."""
    base_port = free_port()
    with Relay(base_port) as relay:
        relay.cut("refuse")
        with _robot_router(tmp_path, relay) as robot:
            time.sleep(1.5)
            links = _links(robot)
            assert links[:3] == (0, 0, 0) and links[3] > 1.0, links
            status = subprocess.run([sys.executable, "-m", "services.cli", "status", "--json", "--mode", "client",
                                     "--connect", robot.graph.hub, "--wait", "2"], cwd=REPO_ROOT, capture_output=True,
                                    text=True, timeout=30)
            seen = json.loads(status.stdout)["launchers"][robot.launcher_id]  # --json says what the text says
            assert status.returncode == 1 and seen["link_down"] and seen["router_link_down_s"] > 1.0, seen
            assert (seen["router_links"], seen["router_links_lost"], seen["graph"]) == (0, 0, "robot"), seen
            with open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{base_port}"])):
                relay.restore()
                wait_until(lambda: _links(robot)[0] == 1, 5, message=lambda: f"the link ({_links(robot)})")
                assert _links(robot) == (1, 0, 0, None)


def test_silent_drop_noticed_within_the_lease(tmp_path):
    """Out of range nothing answers and nothing closes: the routers notice by their lease (2 s), and the link comes
    back when the radio does."""
    base_port = free_port()
    with Relay(base_port) as relay, open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{base_port}"])), \
            _robot_router(tmp_path, relay) as robot:
        wait_until(lambda: _links(robot)[0] == 1, 10, message="the link")
        relay.cut("freeze")
        cut_at = time.monotonic()
        wait_until(lambda: _links(robot)[0] == 0, 5, interval=0.1, message=lambda: f"the loss ({_links(robot)})")
        noticed = time.monotonic() - cut_at
        assert 1.0 < noticed < 4.0 and _links(robot)[:3] == (0, 1, 0), (noticed, _links(robot))
        time.sleep(1.0)
        relay.restore()
        restored = time.monotonic()
        wait_until(lambda: _links(robot)[0] == 1, 5, interval=0.1, message=lambda: f"the link back ({_links(robot)})")
        assert time.monotonic() - restored < 3.0 and _links(robot) == (1, 1, 1, None), _links(robot)


def _base_router(port: int, tmp_path) -> Launcher:
    """The base station's launcher without its nodes: its router answers the robot launcher's probes."""
    return Launcher(load_graph(TWO / "base.yaml", {
        "hub": f"tcp/127.0.0.1:{port}",
        "nodes": {name: {"enabled": False} for name in ("loopclosure", "localizer", "mapper", "monitor")}}),
        run_dir=tmp_path / "base")


# Lossless streams both ways when the link falls silent: enough (1 MB/s) that the robot's router is still reading,
# seconds into the silence, what crossed before it, as in the whole pipeline (at 100 kB/s zenoh's lease closes it).
BUSY_HZ, BUSY_BYTES = 100, 10_000


def test_a_silent_link_with_lossless_traffic_is_reported(tmp_path):
    """A silent link with lossless streams waiting for it: zenoh does not say it is down (its lease counts what its
    router reads, and it reads a backlog), so the launcher's probes across it tell (a probe answered says the link
    carried from the time it was sent): the robot's launcher says it is down within the lease (2 s), a probe period
    (0.5 s) and a margin for the answer's way (1 s), down since the silence began, counted once, and up again within
    a probe and a retry of the link after it returns. Before, it said `up` through the silence
    (docs/results/2026-12-07-link-silent-status.md)."""
    base_port, robot_port = free_port(), free_port()
    stop = threading.Event()
    with Relay(base_port, buffer_bytes=32 << 10) as relay, _base_router(base_port, tmp_path) as base, \
            Launcher(load_graph(TWO / "robot.yaml", {
                "hub": f"tcp/127.0.0.1:{robot_port}",
                "hub_zenoh_config": str(robot_router_config(tmp_path, relay.port)),
                "nodes": {"camera": {"enabled": False}, "detector": {"enabled": False}}}),
                run_dir=tmp_path / "robot") as robot, \
            open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{robot_port}"])) as near, \
            open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{base_port}"])) as far:
        # Both ways, as the pipeline's odometry and heatlines go to the base station and its poses come back.
        arrived: dict[str, list[float]] = {"robot": [], "base": []}
        publishers = []
        for at, sender, receiver in (("base", near, far), ("robot", far, near)):
            key = f"{LOSSLESS_KEY}/to_{at}"
            receiver.declare_subscriber(key, lambda _, at=arrived[at]: at.append(time.monotonic()))
            publishers.append(sender.declare_publisher(key, congestion_control=stream_qos(False)[0]))

        def send() -> None:
            while not stop.wait(1 / BUSY_HZ):
                for publisher in publishers:
                    publisher.put(bytes(BUSY_BYTES))

        sending = threading.Thread(target=send, daemon=True)
        sending.start()
        try:
            wait_until(lambda: min(map(len, arrived.values())) > BUSY_HZ, 20, message="the streams across the link")
            time.sleep(1.0)  # a probe answered: the link is known to answer
            assert _links(robot) == (1, 0, 0, None) and _links(base)[:3] == (1, 0, 0), (_links(robot), _links(base))
            relay.cut("freeze")
            cut_at = time.monotonic()
            wait_until(lambda: _links(robot)[0] == 0, 6, interval=0.1, message=lambda: f"the loss ({_links(robot)})")
            noticed = time.monotonic() - cut_at
            time.sleep(max(0.0, 4.0 - noticed))
            during = _links(robot)
            relay.restore()
            restored = time.monotonic()
            wait_until(lambda: _links(robot)[0] == 1, 6, interval=0.1,
                       message=lambda: f"the link back ({_links(robot)})")
            back, after = time.monotonic() - restored, _links(robot)
        finally:
            relay.restore()  # a failure with the link frozen: the sessions close at once
            stop.set()
            sending.join(timeout=5)
    figures = (round(noticed, 2), during, round(back, 2), after)
    assert 1.0 < noticed < 3.5, figures
    assert during[:3] == (0, 1, 0) and during[3] > 3.0, figures  # down since the silence began, counted once
    assert back < 3.0 and after[:3] == (1, 1, 1), figures


SILENT_S = 6.0  # three leases
LOSSLESS_HZ, LOSSLESS_BYTES = 100, 1000  # a robot's lossless streams crossing the link (odometry, heatlines): 100 kB/s
# A router in a process of its own, as each machine's is: BusConfig as JSON in argv[1]; says "up" once open.
ROUTER = ("import sys, time; from services.bus import BusConfig, open_session; "
          "s = open_session(BusConfig.model_validate_json(sys.argv[1])); print('up', flush=True); time.sleep(600)")


def _router(bus: BusConfig) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-c", ROUTER, bus.model_dump_json()], cwd=REPO_ROOT,
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "up"
    return process


def test_a_silent_link_holds_neither_router(tmp_path):
    """Each machine's router in a process of its own (the robot's with deploy/two-machines/robot-router.json5), a
    lossless stream crossing the link when it falls silent for three leases: the robot's router goes on forwarding
    that stream to a subscriber on the robot, held at most `bus.block_wait_ms` at a time for the link. Before (zenoh's
    5 s wait for room on the link) it forwarded nothing for 5.0-8.6 s once the link's queue was full
    (docs/results/2026-12-07-link-freeze.md)."""
    base_port, robot_port = free_port(), free_port()
    arrivals: dict[str, list[float]] = {"robot": [], "base": []}
    stop = threading.Event()
    with Relay(base_port, buffer_bytes=32 << 10) as relay:
        routers = [_router(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{base_port}"])),
                   _router(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{robot_port}"],
                                     zenoh_config=str(robot_router_config(tmp_path, relay.port))))]
        try:
            with open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{robot_port}"])) as sender, \
                    open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{robot_port}"])) as neighbour, \
                    open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{base_port}"])) as far:
                for name, session in (("robot", neighbour), ("base", far)):
                    session.declare_subscriber(LOSSLESS_KEY, lambda _, at=arrivals[name]: at.append(time.monotonic()))
                publisher = sender.declare_publisher(LOSSLESS_KEY, congestion_control=stream_qos(False)[0])

                def send() -> None:
                    while not stop.wait(1 / LOSSLESS_HZ):
                        publisher.put(bytes(BUSY_BYTES))

                sending = threading.Thread(target=send, daemon=True)
                sending.start()
                wait_until(lambda: len(arrivals["base"]) > LOSSLESS_HZ, 30, message="the stream across the link")
                relay.cut("freeze")
                cut_at = time.monotonic()
                time.sleep(SILENT_S)
                relay.restore()
                restored = time.monotonic()
                wait_until(lambda: arrivals["base"][-1] > restored, 15, message="the stream across the link again")
                stop.set()
                sending.join(timeout=5)
        finally:
            stop.set()
            for router in routers:
                router.kill()
                router.wait()
    during = [t for t in arrivals["robot"] if cut_at <= t <= restored]
    largest = float(np.diff([cut_at, *during, restored]).max())
    assert largest < 1.5 and len(during) >= 0.8 * SILENT_S * LOSSLESS_HZ, (round(largest, 2), len(during))
