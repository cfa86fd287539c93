"""Camera reconnect: a network camera that goes away and comes back, under deploy/local.yaml's launcher.

    .venv/bin/python benchmarks/camera_reconnect.py [--repeats 3] [--outage-s 4] [--kinds down,stall]

The camera node of deploy/local.yaml (the other nodes off; its calibration, restart policy and defaults) reads an
MJPEG stream over HTTP served here (tests/service/mjpeg_server.py, 640x480 at 20 fps). Each outage is either
``down`` (the server closes every socket and refuses connections: a camera rebooting) or ``stall`` (sockets stay
open, no byte is sent: a dead stream behind a router), for ``--outage-s``; before each, the camera has delivered
frames for the restart policy's ``reset_after_s`` (a crash loop's backoff would start over). Timed, as this process
sees the bus: from the outage to the camera's first Status that is not ``running`` (its status period, 1 s, is in
it), from the outage and from the camera's return to its first frame, and whether the frames came from a new process.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.restart import load, local_graph  # noqa: E402
from schemas import Status, decode, keys  # noqa: E402
from services.bus import BusConfig, open_session  # noqa: E402
from services.launcher import Launcher  # noqa: E402
from tests.service.mjpeg_server import MjpegServer  # noqa: E402

ROBOT = "r1"


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise SystemExit(f"camera_reconnect: timed out after {timeout} s waiting for {what}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="outages of each kind")
    parser.add_argument("--outage-s", type=float, default=4.0, help="how long the camera is away")
    parser.add_argument("--kinds", default="down,stall", help="comma-separated: down, stall")
    args = parser.parse_args()
    kinds = args.kinds.split(",")
    if not set(kinds) <= {"down", "stall"}:
        parser.error("--kinds: down, stall")

    server = MjpegServer(size=(640, 480), fps=20)
    server.serve()
    frames: list[float] = []
    statuses: list[tuple[float, Status]] = []
    results: dict[str, list[dict]] = {kind: [] for kind in kinds}
    print(f"start ({load()})")
    with tempfile.TemporaryDirectory(prefix="semloc-camera-reconnect-") as folder:
        off = {"enabled": False}
        graph = local_graph(folder, {"camera": {"config": {"source": server.url}}, "detector": off,
                                     "loopclosure": off, "localizer": off, "mapper": off, "monitor": off})
        launcher = Launcher(graph, run_dir=Path(folder) / "run").start()
        try:
            with open_session(BusConfig(connect=[graph.hub], listen=["tcp/127.0.0.1:0"])) as session:
                session.declare_subscriber(keys.camera_image(ROBOT, "front"),
                                           lambda _: frames.append(time.monotonic()))
                session.declare_subscriber(keys.status(ROBOT, "camera"), lambda sample: statuses.append(
                    (time.monotonic(), decode(sample.payload.to_bytes(), expected=Status))))
                wait_for(lambda: frames, 120, "the first frame")
                for _ in range(args.repeats):
                    for kind in kinds:
                        steady = time.monotonic()  # frames for reset_after_s: a first failure, not a crash loop's
                        wait_for(lambda: frames[-1] > steady + graph.restart.reset_after_s, 120, "steady frames")
                        pid = statuses[-1][1].pid
                        getattr(server, kind)()
                        died = time.monotonic()
                        time.sleep(args.outage_s)
                        server.serve()
                        back = time.monotonic()
                        first = wait_for(lambda: next((t for t in frames if t > back), None), 120, "frames again")
                        time.sleep(1.5)  # the statuses of the first frames
                        seen = [(t, s) for t, s in statuses if t > died]
                        reported = next(((t, s) for t, s in seen if s.state != "running"), None)
                        after = [s for t, s in seen if t > first]
                        results[kind].append({
                            "reported": None if reported is None or reported[0] > first else reported[0] - died,
                            "reason": "" if reported is None else f"{reported[1].state}: {reported[1].state_reason}",
                            "first": first - died, "resumed": first - back,
                            "new_process": bool(after) and after[-1].pid != pid})
        finally:
            launcher.stop()
            server.down()

    print(f"camera node of deploy/local.yaml, outages of {args.outage_s:g} s, medians of {args.repeats} ({load()}):")
    for kind, runs in results.items():
        reported = [r["reported"] for r in runs if r["reported"] is not None]
        print(f"  {kind:5s} outage to not running: "
              f"{f'{statistics.median(reported):.2f} s' if reported else '-'} ({len(reported)} of {len(runs)} "
              f"reported before the first frame again); outage to first frame "
              f"{statistics.median(r['first'] for r in runs):.2f} s, camera's return to first frame "
              f"{statistics.median(r['resumed'] for r in runs):.2f} s (range "
              f"{min(r['resumed'] for r in runs):.2f}-{max(r['resumed'] for r in runs):.2f}); "
              f"new process {sum(r['new_process'] for r in runs)} of {len(runs)}")
        for reason in dict.fromkeys(r["reason"] for r in runs if r["reason"]):
            print(f"        {reason[:160]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
