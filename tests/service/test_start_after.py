"""start_after (deploy/README.md): a node's first start waits until the nodes it names run, so a recorded source
played through `semloc up` loses no frame to a consumer still in its setup; a restart does not wait, but meets the
nodes running then; a dependency that never runs holds it for start_after_timeout_s only, one stopped for good not
at all. Real worker processes over zenoh on loopback."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from schemas import Status, keys
from schemas.status import LauncherStatus
from services.bus import BusConfig, free_port, open_session, query
from services.runtime import MEET_TIMEOUT_S, START_AFTER_ENV, Worker, WorkerConfig
from tests.service.conftest import make_image_folder, read_jsonl, wait_until

pytestmark = pytest.mark.service
SLOW = "tests.service.slow_start_worker"  # a sink whose setup takes setup_s
EAGER = "tests.service.eager_source"  # publishes its frames the moment it runs


def _graph(tmp_path: Path, hub: str, nodes: dict, **graph) -> Path:
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump({"name": "after", "robot": "r1", "hub": hub, "stop_timeout_s": 5,
                                    "restart": {"policy": "on-failure", "backoff_s": 0.1}, "nodes": nodes, **graph}))
    return path


def _camera(images: Path, camera: str = "front", **node) -> dict:
    return {"worker": "camera", **node, "config": {"source": str(images), "camera": camera, "rate": 30, "loop": True}}


def _sink(log_path: Path, worker: str = "sink", key: str = keys.camera_image("r1"), **config) -> dict:
    return {"worker": worker, "config": {"log_path": str(log_path), **config},
            "inputs": {"frames": {"key": key, "policy": "lossless", "depth": 256}}}


def _status(session, worker: str) -> Status | None:
    frames = query(session, keys.status("r1", worker), reply_type=Status, timeout=1.0)
    return frames[0] if frames else None


def _launcher_view(session) -> dict:
    views = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=1.0)
    return views[0].nodes if views else {}


def test_consumers_still_starting_get_every_frame_and_a_restart_does_not_wait(tmp_path, procs, hub):
    make_image_folder(tmp_path / "images", 10)
    logs = {"slow": tmp_path / "slow.jsonl", "fast": tmp_path / "fast.jsonl"}
    graph = _graph(tmp_path, hub, {"camera": _camera(tmp_path / "images", start_after=["slow", "fast"]),
                                   "slow": _sink(logs["slow"], SLOW, setup_s=4.0), "fast": _sink(logs["fast"])})
    procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    with open_session(BusConfig(connect=[hub])) as session:
        # While slow sets up, the camera has no process and the launcher's view says what it waits for.
        waiting = wait_until(lambda: _launcher_view(session).get("camera"), 30, message="the launcher's view")
        assert waiting.state == "starting" and waiting.pid is None and "slow" in waiting.state_reason

        def received():
            records = {name: read_jsonl(path) for name, path in logs.items()}
            return records if all(len(r) >= 20 for r in records.values()) else None

        records = wait_until(received, 60, message="20 frames at each consumer")
        for name, frames in records.items():  # from the camera's first frame on, none missing
            assert [r["seq"] for r in frames] == list(range(len(frames))), name

        # Camera and slow killed together: the camera's restart does not wait for slow to run again.
        camera, slow = _status(session, "camera"), _status(session, "slow")
        for status in (camera, slow):
            os.kill(status.pid, signal.SIGKILL)
        wait_until(lambda: (s := _status(session, "camera")) and s.pid != camera.pid and s.state == "running", 30,
                   message="the restarted camera running")
        again = _status(session, "slow")
        assert again is None or again.state == "starting"
        count = len(read_jsonl(logs["fast"]))
        wait_until(lambda: len(read_jsonl(logs["fast"])) >= count + 5, 30, message="frames of the restarted camera")
    # it met the node running then, not the one killed with it (never met: MEET_TIMEOUT_S lost)
    log = (tmp_path / "run" / "logs" / "camera.log").read_text()
    assert "met r1/fast (restart)" in log and "not met" not in log, log


def test_a_source_reaches_every_consumer_it_waited_for_from_its_first_frame(tmp_path, procs, hub):
    """Peers do not relay for each other: a new session meets the running ones one by one after it opens, so a
    source publishing at once reached some of the nodes it waited for and not others (the camera's first frame
    missed the slow sink of the test above once, under load). Its first start meets them before its setup
    (services/runtime.py, START_AFTER_ENV)."""
    key, frames = "semloc/r1/test/eager", 10
    logs = {f"sink{index}": tmp_path / f"sink{index}.jsonl" for index in range(4)}
    source = {"worker": EAGER, "start_after": list(logs), "config": {"key": key, "frames": frames}}
    graph = _graph(tmp_path, hub, {"source": source, **{name: _sink(log, key=key) for name, log in logs.items()}})
    procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    with open_session(BusConfig(connect=[hub])) as session:
        wait_until(lambda: (s := _status(session, "source")) and s.state == "running", 60,
                   message=lambda: f"the source running; launcher log:\n{procs.log('launcher')}")
        # every frame sent is handled within seconds: a sink short of them lost some
        wait_until(lambda: all((s := _status(session, name)) and s.processed == frames for name in logs), 10,
                   message=lambda: f"{frames} frames at each sink: {[_status(session, n).received for n in logs]}")
    assert {name: [r["seq"] for r in read_jsonl(log)] for name, log in logs.items()} == {
        name: list(range(frames)) for name in logs}
    log = (tmp_path / "run" / "logs" / "source.log").read_text()
    assert f"met {', '.join(f'r1/{name}' for name in logs)} (start_after)" in log and "not met" not in log, log


def test_a_restarted_source_reaches_every_running_consumer_from_its_first_frame(tmp_path, procs, hub):
    """A restart waits for no node to run, but its process meets those running then before its setup, as a first
    start meets those it waited for: killed three times, the source's restarts reach all four sinks from their first
    frame (before, a restart met none and its first frames missed sinks its session had not met yet)."""
    key, frames, kills = "semloc/r1/test/eager", 10, 3
    logs = {f"sink{index}": tmp_path / f"sink{index}.jsonl" for index in range(4)}
    source = {"worker": EAGER, "start_after": list(logs), "config": {"key": key, "frames": frames}}
    graph = _graph(tmp_path, hub, {"source": source, **{name: _sink(log, key=key) for name, log in logs.items()}})
    procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")

    def processed(count: int):
        return lambda: all((s := _status(session, name)) and s.processed == count for name in logs)

    with open_session(BusConfig(connect=[hub])) as session:
        for run in range(kills + 1):
            started = wait_until(lambda: (s := _status(session, "source")) and s.restarts == run
                                 and s.state == "running" and s, 60,
                                 message=lambda: f"the source running; launcher log:\n{procs.log('launcher')}")
            # every frame sent is handled within seconds: a sink short of them lost some
            wait_until(processed(frames * (run + 1)), 10, message=lambda: f"run {run}: {frames} more frames at each "
                       f"sink: {[_status(session, name).processed for name in logs]}")
            if run < kills:
                os.kill(started.pid, signal.SIGKILL)
    assert {name: [r["seq"] for r in read_jsonl(log)] for name, log in logs.items()} == {
        name: list(range(frames)) * (kills + 1) for name in logs}
    met = re.findall(r"met (.*) \((start_after|restart)\)", (tmp_path / "run" / "logs" / "source.log").read_text())
    # a restart meets the sinks whose status said running at that moment (on a loaded machine one may be late to)
    sinks = {f"r1/{name}" for name in logs}
    assert [why for _, why in met] == ["start_after"] + ["restart"] * kills, met
    assert set(met[0][0].split(", ")) == sinks and all(set(names.split(", ")) <= sinks for names, _ in met), met


def test_a_start_held_for_workers_meets_them_before_its_setup(monkeypatch):
    """The runtime's side of it: a new peer's session that met the workers named (their liveliness tokens, declared
    before their subscribers, as Worker.main does) reaches every one of them from its first publication. Without the
    meeting about half of them missed it."""
    hub, key = f"tcp/127.0.0.1:{free_port()}", "semloc/r1/test/first"
    got: dict[str, list[bytes]] = {f"sink{index}": [] for index in range(4)}
    monkeypatch.setenv(START_AFTER_ENV, ",".join(f"r1/{name}" for name in got))
    with contextlib.ExitStack() as stack:
        stack.enter_context(open_session(BusConfig(listen=[hub])))
        declared = []
        for name in got:
            peer = stack.enter_context(open_session(BusConfig(connect=[hub])))
            declared += [peer.liveliness().declare_token(keys.alive("r1", name)),
                         peer.declare_subscriber(key, lambda sample, name=name: got[name].append(
                             sample.payload.to_bytes()))]
        for attempt in range(10):
            payload = str(attempt).encode()
            with open_session(BusConfig(connect=[hub])) as session:
                Worker(WorkerConfig(robot="r1", name="source"))._meet_started_after(session)
                session.put(key, payload)
                wait_until(lambda: all(payload in received for received in got.values()), 5,
                           message=lambda: f"attempt {attempt} at every peer: {got}")


def test_a_worker_not_met_holds_the_start_for_a_bounded_time(tmp_path, procs, session, hub, monkeypatch):
    """A worker named that is gone by then (stopped meanwhile) is never met: the process goes on after
    MEET_TIMEOUT_S, saying whom it did not meet, and meets those that are there at once."""
    procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "there", name="there")
    wait_until(lambda: (s := _status(session, "there")) and s.state == "running", 60, message="the sink running")
    monkeypatch.setenv(START_AFTER_ENV, "r1/there,r1/gone")
    started = time.monotonic()
    procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "late", "--set", "key=semloc/r1/x",
                 name="late")
    wait_until(lambda: (s := _status(session, "late")) and s.state == "running", 60,
               message=lambda: procs.log("late"))
    took = time.monotonic() - started
    assert f"not met {MEET_TIMEOUT_S:.0f} s after the start, going on without them: r1/gone" in procs.log("late")
    assert MEET_TIMEOUT_S <= took < MEET_TIMEOUT_S + 30, took


def test_a_dependency_that_never_runs_holds_for_the_timeout_one_stopped_for_good_not_at_all(tmp_path, procs, hub):
    make_image_folder(tmp_path / "images", 5)
    (tmp_path / "a_file").write_text("")
    frames = tmp_path / "frames.jsonl"
    graph = _graph(tmp_path, hub, {
        # waits for ever, but `broken` stops without running (its log folder is a file) and `fast` runs
        "cam_a": _camera(tmp_path / "images", "a", start_after=["broken", "fast"], start_after_timeout_s=None),
        "cam_b": _camera(tmp_path / "images", "b", start_after=["stuck"], start_after_timeout_s=2),
        "broken": {**_sink(tmp_path / "a_file" / "log.jsonl"), "restart": {"policy": "never"}},
        "stuck": _sink(tmp_path / "stuck.jsonl", SLOW, setup_s=600),
        "fast": _sink(frames, key="semloc/r1/camera/*/image"),
    })
    procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    wait_until(lambda: {r["stream"] for r in read_jsonl(frames)} == {keys.camera_image("r1", c) for c in "ab"}, 60,
               message=lambda: f"both cameras' frames; launcher log:\n{procs.log('launcher')}")
    log = procs.log("launcher")
    assert "node cam_a does not wait for broken: stopped without running" in log
    assert "node cam_b starts without stuck: not running 2 s after the launch (start_after_timeout_s)" in log


def test_a_start_the_machine_starves_is_not_killed_one_that_sleeps_is(tmp_path, procs, hub):
    # Four busy processes share one CPU with `starved`'s setup (1.5 s of CPU): a fifth of it makes that about 8 s of
    # wall time, past start_timeout_s, though it could run for only a few. `sleeper` could run and does not. Each
    # hog in its own session, as other software's services are: the kernel's autogroups share a CPU by session.
    cpu = max(os.sched_getaffinity(0))
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True,
                             preexec_fn=lambda: os.sched_setaffinity(0, {cpu})) for _ in range(4)]
    try:
        graph = _graph(tmp_path, hub, {
            "starved": _sink(tmp_path / "starved.jsonl", SLOW, setup_cpu_s=1.5, cpu=cpu),
            "sleeper": _sink(tmp_path / "sleeper.jsonl", SLOW, setup_s=600),
        }, heartbeat={"start_timeout_s": 6})
        procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
        with open_session(BusConfig(connect=[hub])) as session:
            running = wait_until(lambda: (s := _status(session, "starved")) and s.state == "running" and s, 30,
                                 message=lambda: f"starved running; launcher log:\n{procs.log('launcher')}")
            wait_until(lambda: "node sleeper" in procs.log("launcher") and "killed" in procs.log("launcher"), 15,
                       message=lambda: f"sleeper killed; launcher log:\n{procs.log('launcher')}")
        log = procs.log("launcher")
        assert running.restarts == 0 and "node starved (pid" not in log, log
        assert re.search(r"node sleeper \(pid \d+\) hung: not running \d+ s after its start \(\d+ s of it waiting "
                         r"for a CPU\): killed", log), log
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
