"""`semloc restart NODE` against a graph run by `semloc up` (a real launcher and real workers over zenoh on loopback):
the node's process is replaced and nothing else; the new one knows it was the operator's restart, serves again and,
stateful, goes on from its state; a hung node (SIGSTOPped: SIGTERM waits) is killed after stop_timeout_s; a node
that gave up (max_restarts) comes back, with its automatic restarts counted afresh; a disabled or unknown node is
refused in one line naming the graph's nodes, as is a wildcard or an overlong name in a query off the bus."""

from __future__ import annotations

import os
import signal

import pytest
import yaml

from schemas import Ack, Header, Status, keys
from schemas.status import LauncherStatus
from services.bus import BusConfig, open_session, query
from services.cli import main
from tests.service.conftest import hub, make_image_folder, procs, read_jsonl, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
COUNTER = "tests.service.workers_for_tests"  # a stateful worker: its count survives restarts
STOP_TIMEOUT_S = 2


def _graph(tmp_path, hub: str):  # noqa: F811
    make_image_folder(tmp_path / "images", 10)
    graph = tmp_path / "ops.yaml"
    graph.write_text(yaml.safe_dump({
        "name": "ops", "robot": "r1", "hub": hub, "rerun": {"mode": "off"}, "state_dir": str(tmp_path / "state"),
        "stop_timeout_s": STOP_TIMEOUT_S, "restart": {"policy": "on-failure", "backoff_s": 0.1},
        "nodes": {
            "camera": {"worker": "camera", "config": {"source": str(tmp_path / "images"), "rate": 20, "loop": True}},
            "sink": {"worker": "sink", "config": {"log_path": str(tmp_path / "sink.jsonl")},
                     "inputs": {"frames": {"key": keys.camera_image("r1"), "policy": "lossless", "depth": 64}}},
            "counter": {"worker": COUNTER, "restart": {"policy": "on-failure", "backoff_s": 0.1, "max_restarts": 1}},
            "spare": {"worker": "sink", "enabled": False},
        }}))
    return graph


def _statuses(session) -> dict[str, Status]:
    return {s.worker: s for s in query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0,
                                       every_reply=True)}


def _view(session) -> dict:
    views = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=2.0)
    return views[0].nodes if views else {}


def _count(session) -> int | None:
    replies = query(session, "semloc/r1/counter/count", reply_type=Ack, timeout=2.0)
    return int(replies[0].message) if replies else None


def _run(argv, capsys) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_an_operator_restarts_one_node_of_a_running_graph(tmp_path, procs, hub, capsys):  # noqa: F811
    graph = _graph(tmp_path, hub)
    up = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="up")
    bus = ["--connect", hub]
    with open_session(BusConfig(connect=[hub])) as session:
        def running_again(name: str, old_pid: int) -> Status:
            return wait_until(lambda: (s := _statuses(session).get(name)) and s.pid != old_pid and
                              s.state == "running" and s, 60,
                              message=lambda: f"{name} running again\n{procs.log('up')[-3000:]}")

        first = wait_until(lambda: (s := _statuses(session)) and len(s) == 3 and
                           all(x.state == "running" for x in s.values()) and s, 90,
                           message=lambda: f"3 running workers\n{procs.log('up')[-3000:]}")
        assert [a.message for a in query(session, "semloc/r1/counter/add", Ack(header=Header(robot="r1"), ok=True,
                                                                                message="5"), timeout=5)] == ["5"]

        # A running node: a new process, told it is the operator's restart; the others untouched; frames flow to it.
        code, out, err = _run(["restart", "sink", *bus], capsys)
        assert (code, out, err) == (0, f"r1: ok: restarting node sink of graph ops (pid {first['sink'].pid}: "
                                       f"SIGTERM, SIGKILL after {STOP_TIMEOUT_S} s)\n", "")
        sink = running_again("sink", first["sink"].pid)
        assert (sink.restarts, sink.restart_reason) == (1, "operator")
        now = _statuses(session)
        assert {name: now[name].pid for name in ("camera", "counter")} == \
            {name: first[name].pid for name in ("camera", "counter")}
        assert (now["camera"].restarts, now["counter"].restarts) == (0, 0)
        view = _view(session)
        assert (view["sink"].restarts, view["sink"].restart_reason, view["sink"].pid) == (1, "operator", sink.pid)
        logged = len(read_jsonl(tmp_path / "sink.jsonl"))
        wait_until(lambda: len(read_jsonl(tmp_path / "sink.jsonl")) >= logged + 10, 30,
                   message="frames at the restarted sink")

        # A hung node does not act on SIGTERM: SIGKILL after stop_timeout_s, then the restart.
        os.kill(sink.pid, signal.SIGSTOP)
        assert _run(["restart", "sink", *bus], capsys)[0] == 0
        again = running_again("sink", sink.pid)
        assert (again.restarts, again.restart_reason, _view(session)["sink"].last_exit) == (2, "operator", -9)
        assert "node sink did not stop in time: SIGKILL" in procs.log("up")

        # A stateful node goes on from its state (its final snapshot, written on SIGTERM).
        assert _run(["restart", "counter", "--robot", "r1", *bus], capsys)[0] == 0
        counter = running_again("counter", first["counter"].pid)
        assert (counter.restarts, counter.restart_reason, _count(session)) == (1, "operator", 5)

        # max_restarts 1: one crash is restarted, the next gives up; the operator's word brings it back, and the
        # operator's restart is no failure: the next crash is restarted again.
        os.kill(counter.pid, signal.SIGKILL)
        crashed = running_again("counter", counter.pid)
        assert (crashed.restarts, crashed.restart_reason) == (2, "killed by SIGKILL (not sent by its launcher)")
        os.kill(crashed.pid, signal.SIGKILL)
        wait_until(lambda: _view(session)["counter"].finished, 10, message="counter gave up")
        code, out, err = _run(["restart", "counter", *bus], capsys)
        assert (code, err) == (0, "") and out == ("r1: ok: starting node counter of graph ops (it had killed by "
                                                  "SIGKILL (not sent by its launcher))\n"), out
        back = running_again("counter", crashed.pid)
        assert (back.restarts, back.restart_reason, _count(session)) == (3, "operator", 5)
        os.kill(back.pid, signal.SIGKILL)
        assert running_again("counter", back.pid).restarts == 4

        # Nothing to restart: one line naming the graph's nodes, exit code 1; the graph runs on.
        code, out, err = _run(["restart", "nosuch", *bus], capsys)
        assert (code, out, err) == (1, "r1: refused: no node 'nosuch' in graph ops (nodes: camera, counter, sink)\n",
                                    "")
        code, out, err = _run(["restart", "spare", *bus], capsys)
        assert (code, out) == (1, "r1: refused: node spare of graph ops is disabled (enabled: false); change the "
                                  "graph and start it again\n"), err
        # A query off the bus: a wildcard restarts no node, a name too long for a header is still answered.
        pids = {name: s.pid for name, s in _statuses(session).items()}
        for node, named in (("**", "'**'"), ("x" * 5000, repr("x" * 128))):
            key = keys.all_launcher_restart("r1").removesuffix("*") + node  # no name: keys.py would refuse it
            acks = query(session, key, reply_type=Ack, timeout=5)
            assert [(a.ok, a.message) for a in acks] == [
                (False, f"no node {named} in graph ops (nodes: camera, counter, sink)")]
        assert up.poll() is None and {name: s.pid for name, s in _statuses(session).items()} == pids
    up.send_signal(signal.SIGINT)
    assert up.wait(60) == 0, procs.log("up")
