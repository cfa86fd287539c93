"""A thin radio link between the robot and the base station (docs/deploy.md, "A thin link"): deploy/two-machines/ on
one machine as tests/e2e/test_two_machines.py runs it, the robot router's link through tests/e2e/relay.py limited to
less than the images' bit rate. The robot's camera keeps its rate, the poses come back with a bounded latency, and
what the link dropped is counted, and said, where it was missed: the base station's monitor. (Before, images waited
for the link: the camera's loop with them, until its launcher killed it as hung at 1 Mbit/s; poses came seconds late,
later and later: docs/results/2026-12-07-thin-link.md.)"""

from __future__ import annotations

import json
import os
import signal
import statistics
import time
from pathlib import Path

import pytest

from schemas import decode, keys
from schemas.localization import PoseEstimate
from tests.e2e.relay import Relay
from tests.e2e.two_machines import CAMERA_RATE_HZ, measure_link, plain_launchers, run_split_graph
from tests.service.conftest import free_port, wait_until

pytestmark = pytest.mark.service

LINK_BPS = 1e6  # less than the images alone (4 frames/s of 40-50 KB JPEG) and the heatmaps the monitor takes
SECONDS = 10.0


def test_thin_link_keeps_the_robot_at_its_rate(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=120, seed=0))
    seen: dict = {}
    base_port = free_port()
    with Relay(base_port, rate_bps=LINK_BPS) as relay:
        base, robot, _, robot_port = plain_launchers(tmp_path, dataset, base_port=base_port, link_port=relay.port,
                                                    camera={"loop": True, "stamp": "wall"}, monitor=True)
        run_split_graph(base, robot, base_port, robot_port, poses_wanted=3, images_wanted=1,
                        then=lambda poses, at_robot, at_base: seen.update(measure_link(at_robot, at_base, SECONDS)))
    status, latencies = seen["status"], seen["latencies"]
    half = len(latencies) // 2
    figures = json.dumps({"camera_hz": seen["camera_hz"], "latencies": [round(t, 2) for t in latencies],
                          **{w: s and [s.state, s.state_reason, {k: [i.received, i.lost_in_transit]
                                                                  for k, i in s.inputs.items()}]
                             for w, s in status.items()}})
    # The robot's own loop runs at the camera's rate, and says so.
    assert seen["camera_hz"] > 0.85 * CAMERA_RATE_HZ, figures
    assert status["camera"].state == status["detector"].state == "running", figures
    # The poses come back, late by the link's queue, not by a queue that grows.
    assert len(latencies) >= 0.5 * CAMERA_RATE_HZ * SECONDS and half, figures
    assert max(latencies) < 3.0, figures
    assert statistics.median(latencies[half:]) < statistics.median(latencies[:half]) + 0.5, figures
    # Images the link could not carry were dropped on the way, counted where they were missed, and said.
    # (images at 1.5 Mbit/s sharing a 1 Mbit/s link: a third of them at least; a heatmap's gap is counted with the
    # next one to arrive, if any)
    assert status["monitor"].inputs["frames"].lost_in_transit >= 0.25 * CAMERA_RATE_HZ * SECONDS, figures
    assert status["monitor"].state == "degraded", figures
    reason = status["monitor"].state_reason
    assert reason.startswith("losing frames on the way") and "semloc/r1/camera/front/image" in reason, figures


HEATMAPS_BEFORE_KILL = 120  # a cache of many more frames than a restarted mapper misses


def mapper_restarted_on_a_thin_link(tmp_path: Path, dataset: Path, rate_bps: float, after_s: float = 30.0) -> dict:
    """The graph of tests/e2e/test_link_loss_complete.py (mapper at the base station, its heatmaps recoverable) over a
    link of ``rate_bps``, the camera looping with wall-clock stamps; once the mapper integrated HEATMAPS_BEFORE_KILL
    heatmaps it is SIGKILLed and restarted by its launcher from its state. Measured over ``after_s`` from its restart:
    what the caches' history answered it (its log: samples, kB, seconds, live samples waiting behind it), its
    heatmaps counters, and the poses' latency at the robot (arrival less stamp) before and after the restart: what
    the answer delays on the link (docs/results/2026-12-07-restart-fetch.md)."""
    from tests.e2e.test_link_loss_complete import _overrides, _status

    base_port, seen, latencies = free_port(), {}, []

    def then(poses, at_robot, at_base) -> None:
        sizes: list[int] = []
        heatmaps = at_base.declare_subscriber(keys.detector_heatmaps("r1"), lambda s: sizes.append(len(s.payload)))
        at_robot.declare_subscriber(keys.localizer_pose("r1"), lambda s: latencies.append((time.time(), time.time(
        ) - decode(s.payload.to_bytes(), expected=PoseEstimate).header.stamp_ns * 1e-9)))
        wait_until(lambda: (s := _status(at_base, "mapper")) and s.inputs["heatmaps"].processed
                   >= HEATMAPS_BEFORE_KILL, 300, interval=1.0, message="the mapper's heatmaps")
        pid = base.nodes["mapper"].pid
        seen["killed"] = time.time()
        os.kill(pid, signal.SIGKILL)
        sent = _published(at_robot)
        wait_until(lambda: (s := _status(at_base, "mapper")) and s.pid != pid and s.state == "running", 120,
                   message="the mapper restarted")
        seen["restarted"] = time.time()
        seen["sent_while_down"] = _published(at_robot) - sent
        time.sleep(after_s)
        seen["mapper"] = _status(at_base, "mapper").inputs["heatmaps"]
        seen["heatmap_kb"] = statistics.median(sizes) / 1024 if sizes else None
        heatmaps.undeclare()

    def _published(at_robot) -> int:
        return wait_until(lambda: (s := _status(at_robot, "detector")) and s.outputs["heatmaps"].published, 30,
                          message="the detector's status")

    base_nodes, robot_nodes = _overrides(dataset, tmp_path, None)
    base_nodes["nodes"]["loopclosure"]["enabled"] = False  # its images and CPU are not what is measured
    with Relay(base_port, rate_bps=rate_bps) as relay:
        base, robot, _, robot_port = plain_launchers(tmp_path, dataset, base_port=base_port, link_port=relay.port,
                                                    camera={"loop": True, "stamp": "wall"},
                                                    overrides=(base_nodes, robot_nodes))
        run_split_graph(base, robot, base_port, robot_port, then=then, base_workers=("localizer", "mapper"))
    log = base.nodes["mapper"].log_path.read_text()
    mapper = seen["mapper"]
    return {"history": [line.split("semloc.bus", 1)[-1].strip() for line in log.splitlines() if "history of" in line],
            "heatmap_kb": seen["heatmap_kb"], "sent_while_down": seen["sent_while_down"], "recovered": mapper.recovered, "already_held": mapper.already_held,
            "missed": mapper.missed, "processed_after_restart": mapper.processed,
            "pose_latency_before_s": _spread([late for at, late in latencies if at < seen["killed"]]),
            "pose_latency_after_restart_s": _spread([late for at, late in latencies if at >= seen["restarted"]])}


def _spread(values: list[float]) -> list:
    """[count, p50, p95, max] of ``values`` (seconds, rounded)."""
    if not values:
        return [0]
    ordered = sorted(values)
    return [len(ordered), *(round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2) for q in (0.5, 0.95)),
            round(ordered[-1], 2)]


if __name__ == "__main__":
    import sys
    import tempfile

    from semloc_core.sim import make_scenario

    root = Path(tempfile.mkdtemp(prefix="thin-link-"))
    data = make_scenario("tabletop", frames=120, seed=0).write(root / "data", multiview=False)
    for rate in (float(r) * 1e6 for r in sys.argv[sys.argv.index("--restart-mapper") + 1].split(",")):
        print(f"{rate / 1e6:g} Mbit/s", json.dumps(mapper_restarted_on_a_thin_link(root / f"{rate:g}", Path(data),
                                                                                    rate)), flush=True)
