"""A thin radio link between the robot and the base station: does the robot's loop keep its rate, and how late do
the poses come back?

    .venv/bin/python benchmarks/thin_link.py [--rates 20,5,1] [--seconds 30] [--camera-hz 10]

deploy/two-machines/ on one machine (tests/e2e/two_machines.py: camera and detector behind the robot's router, the
localizer behind the base station's), the robot router's link to the base station through tests/e2e/relay.py limited
to each rate (Mbit/s, each direction; ``0``: not limited). A client of the base station's router subscribes to the
images and the heatmaps, as loop closure and mapper do, and the monitor takes every stream. The camera plays a simulated table top in a loop, stamped
with the wall clock at publication, so a pose's latency at the robot is its arrival less its stamp. Printed per rate:
the camera's and the detector's rates (their Status), images and heatmaps that reached the base station, the poses'
latency at a client of the robot's router (p50, p95, max; first and second half of the run: a queue that grows
shows as a second half later than the first), and each worker's state and reason.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from schemas import keys  # noqa: E402
from semloc_core.sim import make_scenario  # noqa: E402
from services.bus import BusConfig, free_port, open_session, query  # noqa: E402
from services.launcher import Launcher, load_graph  # noqa: E402
from tests.e2e.relay import Relay  # noqa: E402
from tests.e2e.two_machines import TWO, graph_overrides, measure_link, robot_router_config  # noqa: E402


def _percentiles(values: list[float]) -> str:
    if not values:
        return "none"
    values = sorted(values)
    return (f"p50 {statistics.median(values) * 1e3:.0f} / p95 {values[int(0.95 * (len(values) - 1))] * 1e3:.0f} / "
            f"max {values[-1] * 1e3:.0f} ms ({len(values)})")


def _client(port: int):
    return open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))


def run(dataset: Path, folder: Path, rate_mbps: float, seconds: float, camera_hz: float) -> dict:
    base_port, robot_port = free_port(), free_port()
    base, robot = graph_overrides(dataset, folder)
    robot["nodes"]["camera"]["config"].update(rate=camera_hz, loop=True, stamp="wall")
    base["hub"] = f"tcp/127.0.0.1:{base_port}"
    base["nodes"]["monitor"]["enabled"] = True  # it takes every stream: what the link lost shows in its status
    received = {"image": 0, "heatmaps": 0}

    def count(stream: str):
        return lambda _sample: received.__setitem__(stream, received[stream] + 1)

    with Relay(base_port, rate_bps=rate_mbps * 1e6 or None) as relay:
        robot.update(hub=f"tcp/127.0.0.1:{robot_port}", hub_zenoh_config=str(robot_router_config(folder, relay.port)))
        with Launcher(load_graph(TWO / "base.yaml", base), run_dir=folder / "base"), _client(base_port) as at_base:
            subs = [at_base.declare_subscriber(keys.camera_image("r1"), count("image")),
                    at_base.declare_subscriber(keys.detector_heatmaps("r1"), count("heatmaps"))]
            deadline = time.monotonic() + 60
            while not query(at_base, keys.status("r1", "localizer"), timeout=1.0) and time.monotonic() < deadline:
                time.sleep(0.3)
            with Launcher(load_graph(TWO / "robot.yaml", robot), run_dir=folder / "robot"), \
                    _client(robot_port) as at_robot:
                deadline = time.monotonic() + 60
                while not measure_link(at_robot, at_base, 1.0)["latencies"] and time.monotonic() < deadline:
                    pass  # until the graph runs end to end: poses come back
                before, started = dict(received), time.monotonic()
                seen = measure_link(at_robot, at_base, seconds)
                elapsed = time.monotonic() - started
            for sub in subs:
                sub.undeclare()
    latencies = seen["latencies"]
    half = len(latencies) // 2
    result = {"rate_mbps": rate_mbps, "camera_hz": round(seen["camera_hz"], 2),
              "poses_hz": round(len(latencies) / seconds, 2), "latency": _percentiles(latencies),
              "first_half": _percentiles(latencies[:half]), "second_half": _percentiles(latencies[half:]),
              "at_base_hz": {k: round((v - before[k]) / elapsed, 2) for k, v in received.items()}}
    for worker, status in seen["status"].items():
        result[worker] = "no answer" if status is None else {
            "state": status.state, "reason": status.state_reason,
            "inputs": {k: [v.rate_hz and round(v.rate_hz, 1), v.received, v.dropped,
                           getattr(v, "lost_in_transit", None)]  # a branch without the counter: None
                       for k, v in status.inputs.items() if not k.startswith("query:")}}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rates", default="20,5,1", help="link rates, Mbit/s (0: not limited)")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--camera-hz", type=float, default=10.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        dataset = make_scenario("tabletop", seed=0, frames=120).write(Path(tmp) / "data")
        for rate in (float(r) for r in args.rates.split(",")):
            print(json.dumps(run(Path(dataset), Path(tmp) / f"run-{rate:g}", rate, args.seconds, args.camera_hz),
                             default=str), flush=True)


if __name__ == "__main__":
    main()
