"""Truthful health (issue 28): degraded and stalled workers, restart counts and reasons, `semloc status` of a whole
graph, a lost and regained bus; real worker processes over zenoh on loopback."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml
import zenoh

from schemas import Ack, Header, Status, encode, keys
from schemas.status import LauncherStatus
from services.bus import BusConfig, open_session, query
from tests.service.conftest import REPO_ROOT, make_image_folder, wait_until

pytestmark = pytest.mark.service
COUNTER = "tests.service.workers_for_tests"


def _statuses(session, robot: str = "r1") -> dict[str, Status]:
    """Every worker's Status, all replies (zenoh's default consolidation would keep one of a wildcard's)."""
    frames = query(session, keys.robot_statuses(robot), reply_type=Status, timeout=2.0, every_reply=True)
    return {frame.worker: frame for frame in frames}


def _launcher_view(session, robot: str = "r1") -> dict:
    views = query(session, keys.all_launcher_nodes(robot), reply_type=LauncherStatus, timeout=2.0)
    return views[0].nodes if views else {}


def _semloc_status(hub: str) -> tuple[int, dict]:
    done = subprocess.run([sys.executable, "-m", "services.cli", "status", "--connect", hub, "--json", "--wait", "15"],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
    return done.returncode, json.loads(done.stdout)["workers"]


def _ack(seq: int, message: str) -> bytes:
    return encode(Ack(header=Header(robot="r1", seq=seq, stamp_ns=seq + 1), ok=True, message=message))


def test_a_graph_reports_hung_crashed_and_dead_workers_and_restarts_them(tmp_path, procs, hub):
    make_image_folder(tmp_path / "images", 10)
    image_key = keys.camera_image("r1")
    sink = {"worker": "sink", "inputs": {"frames": {"key": image_key, "policy": "lossless", "depth": 16}}}
    graph = {
        "name": "health", "robot": "r1", "hub": hub, "stop_timeout_s": 5,
        "restart": {"policy": "on-failure", "backoff_s": 0.1},
        "heartbeat": {"stalled_after_s": 3.0, "restart_after_s": 8.0},
        "nodes": {
            "camera": {"worker": "camera", "config": {"source": str(tmp_path / "images"), "rate": 20, "loop": True}},
            "hung": sink, "crashed": sink, "counter": {"worker": COUNTER},
            "dead": {**sink, "restart": {"policy": "never"}},
        },
    }
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(graph))
    launcher = procs.semloc("up", str(tmp_path / "graph.yaml"), "--run-dir", str(tmp_path / "run"), name="launcher")
    stopped_pid = None
    try:
        with open_session(BusConfig(connect=[hub])) as session:
            first = wait_until(lambda: (s := _statuses(session)) and len(s) == 5 and
                               all(x.state == "running" for x in s.values()) and s, 60,
                               message=lambda: f"5 running workers; launcher log:\n{procs.log('launcher')[-3000:]}")
            assert all(s.restarts == 0 and s.restart_reason == "" for s in first.values())
            code, report = _semloc_status(hub)
            assert code == 0 and set(report) == {f"r1/{n}" for n in graph["nodes"]}, report
            assert {e["state"] for e in report.values()} == {"running"}

            # A crash: restarted, and the new process knows how often and why.
            os.kill(first["crashed"].pid, signal.SIGKILL)
            crashed = wait_until(lambda: (s := _statuses(session).get("crashed")) and s.pid != first["crashed"].pid
                                 and s, 30, message="the crashed worker restarted")
            assert (crashed.restarts, crashed.restart_reason) == (1, "killed by SIGKILL (not sent by its launcher)")

            # Dead for good (restart: never): its launcher still lists it, `semloc status` shows it down.
            os.kill(first["dead"].pid, signal.SIGKILL)
            wait_until(lambda: _launcher_view(session).get("dead", None) and
                       _launcher_view(session)["dead"].state == "down", 10, message="dead shown down by the launcher")
            code, report = _semloc_status(hub)
            assert code == 1 and len(report) == 5, report
            assert report["r1/dead"]["state"] == "down" and "killed by SIGKILL" in report["r1/dead"]["reason"]
            assert report["r1/crashed"]["state"] == "running" and report["r1/camera"]["state"] == "running"

            # Hung: SIGSTOP. It cannot say so itself; its launcher notices the silence within 5 s and restarts it.
            stopped_pid = first["hung"].pid
            os.kill(stopped_pid, signal.SIGSTOP)
            stopped_at = time.monotonic()
            wait_until(lambda: (v := _launcher_view(session)) and v["hung"].state == "stalled", 5.0, interval=0.1,
                       message=lambda: f"hung shown stalled; launcher view {_launcher_view(session).get('hung')}")
            seen_stalled_after = time.monotonic() - stopped_at
            restarted = wait_until(lambda: (s := _statuses(session).get("hung")) and s.pid != stopped_pid and s, 40,
                                   message="the hung worker restarted")
            assert restarted.restarts == 1 and restarted.restart_reason.startswith("hung: no heartbeat for "), \
                restarted.restart_reason
            assert seen_stalled_after <= 5.0
            assert "hung: no heartbeat" in procs.log("launcher")
            view = _launcher_view(session)
            assert view["hung"].restarts == 1 and view["dead"].finished and view["dead"].state == "down"
    finally:
        if stopped_pid is not None:
            try:
                os.kill(stopped_pid, signal.SIGKILL)  # already killed by the launcher when the test passed
            except ProcessLookupError:
                pass
        launcher.send_signal(signal.SIGINT)
        launcher.wait(30)


def test_failing_handlers_and_silence_show_degraded_with_one_line_errors(procs, session, hub):
    procs.semloc("worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--set",
                 "status_period_s=0.2", "--set", "degraded_after_failures=3", "--set", "degraded_silence_s=1.5",
                 name="counter")
    status = lambda: _statuses(session).get("counter")  # noqa: E731
    wait_until(lambda: (s := status()) and s.state == "running", 30, message="counter running")
    publisher = session.declare_publisher("semloc/r1/counter/in", congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    for seq in range(3):  # every handler call raises
        publisher.put(_ack(seq, "boom"))
    degraded = wait_until(lambda: (s := status()) and s.errors == 3 and s, 20, message="3 errors")
    assert degraded.state == "degraded" and "last 3 handler calls failed" in degraded.state_reason
    assert degraded.last_error == "input in: RuntimeError: boom" and degraded.last_error_ns > 0  # the traceback is
    assert "Traceback" in procs.log("counter")  # in the log
    publisher.put(_ack(3, ""))  # one call that works: running again
    wait_until(lambda: (s := status()) and s.processed == 1 and s.state == "running", 20, message="running again")

    # Inputs keep arriving (rejected by the handler) and nothing is published: degraded after 1.5 s.
    seq = 4
    deadline = time.monotonic() + 30
    while not ((s := status()) and s.state == "degraded") and time.monotonic() < deadline:
        publisher.put(_ack(seq, "bad"))
        seq += 1
        time.sleep(0.1)
    assert s.state == "degraded" and s.state_reason.startswith("inputs arrive but nothing was published"), s
    publisher.put(_ack(seq, ""))
    wait_until(lambda: (s := status()) and s.state == "running", 20, message="running after a publication")


def test_a_lost_and_regained_bus_is_logged_and_counted(procs, hub):
    bus = BusConfig(listen=[hub])
    router = open_session(bus)
    try:
        procs.semloc("worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--set",
                     "status_period_s=0.2", name="counter")
        first = wait_until(lambda: _statuses(router).get("counter"), 30, message="counter up")
        assert first.bus_transports == 1 and first.bus_lost == first.bus_regained == 0
        router.close()  # the worker's only peer goes away...
        wait_until(lambda: "bus lost" in procs.log("counter"), 10, message="the loss logged")
        router = open_session(bus)  # ...and comes back on the same endpoint
        after = wait_until(lambda: (s := _statuses(router).get("counter")) and s.bus_regained == 1 and s, 30,
                           message="the worker back on the bus")
        assert after.bus_lost == 1 and after.bus_transports == 1 and after.state == "running"
        assert "bus regained after" in procs.log("counter")
    finally:
        router.close()


def test_a_worker_waiting_for_its_camera_model_says_so(procs, session, hub):
    """A loop-closure worker without calibration skips every image until the camera model arrives: degraded with
    the reason and the count, then running once the model is there (it was `running` while doing nothing)."""
    import numpy as np

    from schemas import Image
    from schemas.camera import camera_image
    from semloc_core.camera import PinholeCamera
    from services.frames import camera_model_frame

    procs.semloc("worker", "loopclosure", "--connect", hub, "--robot", "r1", "--set", "status_period_s=0.2",
                 "--set", "keyframes.enabled=false", name="loopclosure")
    status = lambda: _statuses(session).get("loopclosure")  # noqa: E731
    wait_until(lambda: (s := status()) and s.state == "running", 60,
               message=lambda: f"loop closure running; log:\n{procs.log('loopclosure')[-3000:]}")
    images = session.declare_publisher(keys.camera_image("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: images.matching_status.matching, 10, message="image subscriber matched")
    rng = np.random.default_rng(0)
    seq = 0

    def send_image():
        nonlocal seq
        pixels = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
        images.put(encode(Image(header=Header(robot="r1", seq=seq, stamp_ns=(seq + 1) * 100_000_000),
                                images=[camera_image(pixels)])))
        seq += 1

    def degraded():
        send_image()
        return (s := status()) and s.state == "degraded" and s

    waiting = wait_until(degraded, 30, interval=0.2, message="degraded for want of a camera model")
    assert waiting.state_reason.startswith("no camera model yet: ") and "frame(s) skipped" in waiting.state_reason
    assert "no camera model yet: 1 frame(s) skipped" in procs.log("loopclosure")
    model = camera_model_frame(PinholeCamera.from_fov(160, 120, 90.0), Header(robot="r1", seq=0, stamp_ns=1))
    session.put(keys.camera_model("r1"), encode(model))

    def running():
        send_image()
        return (s := status()) and s.state == "running"

    wait_until(running, 30, interval=0.2, message="running once the camera model arrived")
    assert "no camera model yet no more" in procs.log("loopclosure")


def test_status_says_when_a_worker_went_on_from_a_saved_state(tmp_path, procs, session, hub):
    """`semloc up` started again in the same folder resumes its stateful workers from `state_dir` (runs/state): the
    new run's map holds the previous run's frames. `semloc status` says so; a fresh worker shows no such line."""
    def counter(name: str):
        return procs.semloc("worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
                            str(tmp_path / "state"), name=name)

    def status_text() -> str:
        done = subprocess.run([sys.executable, "-m", "services.cli", "status", "--connect", hub, "--wait", "15"],
                              cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
        return done.stdout

    first = counter("first")
    wait_until(lambda: (s := _statuses(session).get("counter")) and s.state == "running", 30, message="running")
    assert "  state:" not in status_text()
    first.send_signal(signal.SIGINT)  # a graceful stop writes the final snapshot
    first.wait(30)
    counter("second")
    wait_until(lambda: (s := _statuses(session).get("counter")) and s.state == "running" and s.pid != first.pid, 30,
               message="running again")
    assert "  state: restored from its snapshot, 0 journal record(s) replayed" in status_text().splitlines()
