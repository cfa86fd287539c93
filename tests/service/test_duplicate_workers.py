"""Two processes as one (docs/runtime.md, "Status, liveliness, health"): two workers started with one robot and name
both answer on its status key, and `semloc status` lists each and names them; two replays of one recording are two
publishers to a consumer. Real workers and `semloc` commands over zenoh on loopback."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from schemas import Ack, Header, Status, encode, keys
from services.bus import query
from services.recording import Recorder
from tests.service.conftest import REPO_ROOT, wait_until

pytestmark = pytest.mark.service
SHARED = "semloc/r1/test/shared"


def _sinks(session) -> list[Status]:
    frames = query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0, every_reply=True)
    return [frame for frame in frames if frame.worker == "sink"]


def _status(hub: str, *args: str) -> str:
    result = subprocess.run([sys.executable, "-m", "services.cli", "status", "--connect", hub, "--robot", "r1",
                             "--wait", "10", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    return result.stdout


def test_status_lists_two_workers_with_one_name_and_names_them(procs, session, hub):
    for name in ("sink-a", "sink-b"):  # an old process still running beside its replacement
        procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "sink", "--set", f"key={SHARED}",
                     name=name)
    pids = {process.pid for process in procs.started}
    wait_until(lambda: {s.pid for s in _sinks(session)} == pids, 60,
               message=lambda: f"both sinks answering: {[s.pid for s in _sinks(session)]} of {pids}")

    text = _status(hub)
    rows = [line.split() for line in text.splitlines() if line.startswith("r1/sink ")]
    assert {int(row[2]) for row in rows} == pids, text
    [named] = [line for line in text.splitlines() if "workers answer as" in line]
    assert named.startswith("  ! 2 workers answer as r1/sink: ") and all(f"pid {pid} on " in named for pid in pids), \
        named

    worker = json.loads(_status(hub, "--json"))["workers"]["r1/sink"]
    assert {worker["status"]["pid"]} | {s["pid"] for s in worker["duplicates"]} == pids, worker["duplicates"]
    assert worker["duplicate"].startswith("2 workers answer as r1/sink: "), worker["duplicate"]


def test_two_replays_of_one_recording_are_two_publishers(tmp_path, procs, session, hub):
    recording = tmp_path / "session.mcap"
    recorder = Recorder(session, SHARED, recording)
    for seq in range(40):  # 2 s at 20 Hz
        session.put(SHARED, encode(Ack(header=Header(robot="r1", stream=SHARED, seq=seq, stamp_ns=seq + 1), ok=True)))
        time.sleep(0.05)
    wait_until(lambda: recorder.count == 40, 10, message="40 frames recorded")
    recorder.close()
    procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "sink", "--set", f"key={SHARED}",
                 "--set", "status_period_s=0.25", name="sink")
    wait_until(lambda: [s for s in _sinks(session) if s.state == "running"], 60, message="the sink running")
    for name in ("replay-a", "replay-b"):
        procs.semloc("replay", str(recording), "--connect", hub, "--loop", "--wait-for-subscribers", "20", name=name)

    # Each replay's samples name it: their numbers interleave, two publishers, not frames lost on the way. Without a
    # publisher named the sink saw one stream starting over and over, and said nothing of two.
    named = lambda s: s.state == "degraded" and f"2 publishers on {SHARED}" in s.state_reason  # noqa: E731
    [status] = wait_until(lambda: [s for s in _sinks(session) if named(s)], 60, message=lambda: "the sink naming "
                          f"two publishers: {[(s.state, s.state_reason) for s in _sinks(session)]}")
    assert status.inputs["frames"].lost_in_transit == 0, status.inputs["frames"]
