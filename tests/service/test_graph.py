"""Acceptance: a graph of real worker processes launched by `semloc up`, `semloc status`, restart on SIGKILL,
no orphan after SIGINT."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest
import yaml

from schemas import Status
from services.bus import BusConfig, open_session, query
from tests.service.conftest import REPO_ROOT, make_image_folder, read_jsonl, wait_until

pytestmark = pytest.mark.service


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _write_graph(tmp_path: Path, hub: str, camera: dict, sink: dict) -> Path:
    graph = {
        "name": "test",
        "robot": "r1",
        "hub": hub,
        "restart": {"policy": "on-failure", "backoff_s": 0.1},
        "stop_timeout_s": 5,
        "nodes": {
            "camera": {"worker": "camera", "config": camera},
            "sink": {"worker": "sink", "config": sink,
                     "inputs": {"frames": {"key": "semloc/r1/camera/front/image", "policy": "lossless"}}},
            "detector": {"worker": "detector_that_does_not_exist", "optional": True},
        },
    }
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(graph))
    return path


def _status(session, worker: str) -> Status | None:
    frames = query(session, f"semloc/r1/{worker}/status", reply_type=Status, timeout=1.0)
    return frames[0] if frames else None


def test_camera_to_consumer_from_graph_file(tmp_path, procs, hub):
    files = make_image_folder(tmp_path / "images", 100)
    sink_log = tmp_path / "sink.jsonl"
    graph = _write_graph(tmp_path, hub, camera={"source": str(tmp_path / "images"), "rate": 50,
                                                "wait_for_subscriber_s": 20, "exit_at_end": False},
                         sink={"key": "unused/when/inputs/override", "log_path": str(sink_log)})
    launcher = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    wait_until(lambda: len(read_jsonl(sink_log)) >= 100, 60, message="100 frames at the sink")
    time.sleep(0.3)
    records = read_jsonl(sink_log)
    assert len(records) == 100
    assert [r["seq"] for r in records] == list(range(100))  # every frame, in order
    for record, file in zip(records, files):
        pixels = cv2.imread(str(file), cv2.IMREAD_COLOR)
        assert record["arrays_sha256"] == [hashlib.sha256(pixels.tobytes()).hexdigest()]  # identical content

    # --wait: on a loaded CI machine one worker's reply once took longer than the default 3 s (the command returns
    # as soon as every worker it sees has answered)
    status = subprocess.run([sys.executable, "-m", "services.cli", "status", "--connect", hub, "--json",
                             "--wait", "15"],
                            cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
    assert status.returncode == 0, status.stderr
    report = json.loads(status.stdout)["workers"]
    assert set(report) == {"r1/camera", "r1/sink"}
    camera, sink = report["r1/camera"]["status"], report["r1/sink"]["status"]
    assert camera["outputs"]["image"]["published"] == 100
    assert sink["received"] == sink["processed"] == 100 and sink["rejected"] == sink["dropped"] == 0
    assert sink["inputs"]["frames"]["policy"] == "lossless"
    assert sink["latency_p50_ms"] is not None
    launcher.send_signal(signal.SIGINT)
    assert launcher.wait(20) == 0


def test_sigkilled_worker_is_restarted_and_sigint_leaves_no_process(tmp_path, procs, hub):
    make_image_folder(tmp_path / "images", 10)
    sink_log = tmp_path / "sink.jsonl"
    graph = _write_graph(tmp_path, hub, camera={"source": str(tmp_path / "images"), "rate": 20, "loop": True},
                         sink={"log_path": str(sink_log)})
    launcher = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    with open_session(BusConfig(connect=[hub])) as session:
        first = wait_until(lambda: _status(session, "camera"), 30, message="camera status")
        wait_until(lambda: len(read_jsonl(sink_log)) >= 5, 30, message="frames flowing")
        os.kill(first.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        # The launcher restarts it (a new process of the node) within 2 s...
        new_pid = wait_until(lambda: [p for p in _children(launcher.pid) if p != first.pid and
                                      b"camera" in Path(f"/proc/{p}/cmdline").read_bytes()], 2.0,
                             interval=0.02, message="a new camera process")
        restart_delay = time.monotonic() - killed_at
        # ...and the stream resumes: frames published by the new process reach the consumer.
        count_at_kill = len(read_jsonl(sink_log))
        second = wait_until(lambda: (s := _status(session, "camera")) and s.pid != first.pid and s, 30,
                            message="status of the restarted camera")
        assert second.pid in new_pid
        wait_until(lambda: len(read_jsonl(sink_log)) >= count_at_kill + 5, 30, message="stream resumed")
    assert restart_delay < 2.0
    workers = _children(launcher.pid)
    assert len(workers) == 2
    launcher.send_signal(signal.SIGINT)
    assert launcher.wait(20) == 0
    time.sleep(0.2)
    assert [pid for pid in workers if _alive(pid)] == []
    assert "restart 1" in (tmp_path / "launcher.log").read_text()
