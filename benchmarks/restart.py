"""Restart: how long a stateful worker of a running graph is gone after a SIGKILL, against a bare Python start.

    .venv/bin/python benchmarks/restart.py [--kills 5] [--starts 5] [--operator]

deploy/local.yaml's loop closure, localizer and mapper (camera, detector and monitor off) run under the launcher with
their state on (snapshots and journals in a temporary folder). Each is SIGKILLed ``--kills`` times, one worker at a
time, each kill after the worker ran longer than the restart policy's ``reset_after_s``, so every restart is a
first restart and waits the graph's ``backoff_s`` (a crash loop backs off further). The restart time is from the
kill to the new process's first ``running`` Status, as this process receives it (the issue's target: < 2 s).
``--operator``: ``semloc restart WORKER`` instead of the SIGKILL, timed from the command's start (its own Python
start, the query, the worker's graceful stop with its final snapshot, the new process's start; no backoff, no wait).

Reference, measured in this process just before: ``--starts`` wall times of a bare ``python -c pass`` and of
``semloc worker KIND --print-config`` (the interpreter, the imports of the command and of the worker, its config;
no bus), the floor any restart by a new process pays. Prints medians (and the load average beside them), the
restart's ratio to the bare Python start, and the new process's CPU time when it reported running.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from schemas import Status, keys  # noqa: E402
from services.bus import BusConfig, QueryError, free_port, open_session, query  # noqa: E402
from services.launcher import Launcher, load_graph  # noqa: E402

STATEFUL = ("loopclosure", "localizer", "mapper")
ROBOT = "r1"


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def median_wall(command: list[str], times: int) -> float:
    walls = []
    for _ in range(times):
        started = time.perf_counter()
        subprocess.run(command, cwd=REPO_ROOT, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        walls.append(time.perf_counter() - started)
    return statistics.median(walls)


def status(session, worker: str) -> Status | None:
    try:
        replies = query(session, keys.status(ROBOT, worker), reply_type=Status, timeout=1.0)
    except QueryError:
        return None
    return replies[0] if replies else None


def wait_for(predicate, timeout: float, what: str, interval: float = 0.01):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise SystemExit(f"restart benchmark: timed out after {timeout} s waiting for {what}")


def local_graph(folder: str, nodes: dict):
    """deploy/local.yaml on a free hub port, its state in ``folder``, ``nodes`` overriding its nodes'."""
    return load_graph(REPO_ROOT / "deploy" / "local.yaml", {
        "hub": f"tcp/127.0.0.1:{free_port()}", "state_dir": str(Path(folder) / "state"), "nodes": nodes})


def load() -> str:
    return "load average " + " ".join(f"{value:.2f}" for value in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=5, help="restarts measured per worker")
    parser.add_argument("--starts", type=int, default=5, help="reference starts measured per command")
    parser.add_argument("--operator", action="store_true", help="restart by `semloc restart`, not a SIGKILL")
    args = parser.parse_args()

    print(f"reference ({load()}):")
    bare = median_wall([sys.executable, "-c", "pass"], args.starts)
    print(f"  python -c pass: {bare:.3f} s")
    floors = {}
    for worker in STATEFUL:
        floors[worker] = median_wall([sys.executable, "-m", "services.cli", "worker", worker, "--print-config"],
                                     args.starts)
        print(f"  semloc worker {worker} --print-config: {floors[worker]:.3f} s")

    with tempfile.TemporaryDirectory(prefix="semloc-restart-") as folder:
        off = {"enabled": False}
        graph = local_graph(folder, {"camera": off, "detector": off, "monitor": off})
        hub = graph.hub
        policy = graph.restart
        launcher = Launcher(graph, run_dir=Path(folder) / "run").start()
        restarts: dict[str, list[float]] = {worker: [] for worker in STATEFUL}
        cpu: dict[str, list[float]] = {worker: [] for worker in STATEFUL}
        try:
            with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
                wait_for(lambda: all((s := status(session, w)) and s.state == "running" for w in STATEFUL), 180,
                         "the workers running")
                running_since = {worker: time.monotonic() for worker in STATEFUL}
                for _ in range(args.kills):
                    for worker in STATEFUL:
                        pid = launcher.pids()[worker]
                        if args.operator:
                            killed_at = time.monotonic()
                            command = subprocess.Popen([sys.executable, "-m", "services.cli", "restart", worker,
                                                        "--robot", ROBOT, "--connect", hub], cwd=REPO_ROOT,
                                                       stdout=subprocess.DEVNULL)
                        else:
                            # a first restart: the worker ran longer than reset_after_s since its last start
                            time.sleep(max(0.0, running_since[worker] + policy.reset_after_s + 0.5 - time.monotonic()))
                            killed_at = time.monotonic()
                            launcher.nodes[worker].signal_group(signal.SIGKILL)
                        new = wait_for(lambda: (s := status(session, worker)) and s.pid != pid
                                       and s.state == "running" and s, 120, f"{worker} restarted")
                        restarts[worker].append(time.monotonic() - killed_at)
                        if args.operator and command.wait(60) != 0:
                            raise SystemExit(f"restart benchmark: semloc restart {worker} exited {command.returncode}")
                        running_since[worker] = time.monotonic()
                        cpu[worker].append(cpu_seconds(new.pid))
        finally:
            launcher.stop()

    how = "by semloc restart" if args.operator else f"after SIGKILL (backoff_s {policy.backoff_s:g} s)"
    print(f"restart {how}, median of {args.kills} ({load()}):")
    for worker in STATEFUL:
        median = statistics.median(restarts[worker])
        print(f"  {worker:12s} {median:.3f} s (range {min(restarts[worker]):.3f}-{max(restarts[worker]):.3f}), "
              f"{median / bare:.1f}x a bare python start, {median / floors[worker]:.2f}x its --print-config start; "
              f"CPU of the new process when running {statistics.median(cpu[worker]):.2f} s")
    worst = max(statistics.median(values) for values in restarts.values())
    print(f"slowest median restart {worst:.3f} s (target < 2 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
