"""The operator's commands against a graph run by `semloc up` (a real launcher, a real localizer process, over zenoh
on loopback) and a second robot's localizer: `semloc localize set-pose` moves each robot's estimate (seen on the
pose stream) with a request naming that robot, `relocalize` spreads it,
`semloc logs` shows and follows the nodes' logs, `semloc stop` ends the graph; once it is gone, each says in one
line that nothing answered and exits 1. The graph names its map relative to its own folder, and is started from
another directory."""

from __future__ import annotations

import math
import shutil
import threading

import numpy as np
import pytest
import yaml

from schemas import Ack, Header, Pose2D, decode, encode, keys
from schemas.localization import PoseEstimate
from schemas.status import LogChunk, LogTail
from services.bus import BusConfig, QueryError, open_session, query
from services.cli import main
from services.launcher import Launcher, load_graph
from tests.service.conftest import REPO_ROOT, hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
MAX_PARTICLES = 2000


def _graph(tmp_path, hub: str):
    """The graph of robot r1, and the config of a second robot's localizer (the same but for its map's path)."""
    files = tmp_path / "graph" / "files"
    files.mkdir(parents=True)
    shutil.copy(REPO_ROOT / "deploy" / "local" / "map.json", files / "map.json")
    config = {"map": "files/map.json",  # beside the graph file, not in the launcher's directory
              "seed": 3, "motion": "random_walk", "sample_size": 50,
              "filter": {"max_particles": MAX_PARTICLES, "min_particles": 200}}
    graph = tmp_path / "graph" / "ops.yaml"
    graph.write_text(yaml.safe_dump({
        "name": "ops", "robot": "r1", "hub": hub, "rerun": {"mode": "off"},
        "restart": {"policy": "never"},
        "nodes": {"localizer": {"worker": "localizer", "config": config}}}))
    other = tmp_path / "r2-localizer.yaml"
    other.write_text(yaml.safe_dump({**config, "map": str(files / "map.json")}))
    return graph, other


def _run(argv, capsys) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_operator_commands_drive_a_running_graph(tmp_path, procs, hub, capsys):  # noqa: F811
    graph, other = _graph(tmp_path, hub)
    up = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="up")
    bus = ["--connect", hub]
    second = procs.semloc("worker", "localizer", "--config", str(other), "--robot", "r2", *bus, name="r2")
    estimates: list[PoseEstimate] = []
    lock = threading.Lock()

    def on_pose(sample):
        with lock:
            estimates.append(decode(sample.payload.to_bytes()))

    with open_session(BusConfig(connect=[hub])) as session:
        subscriber = session.declare_subscriber(keys.localizer_pose("r1"), on_pose)

        def localizer_runs(robot):
            try:
                return any(s.state == "running" for s in query(session, keys.status(robot, "localizer"), timeout=1))
            except Exception:
                return False

        wait_until(lambda: localizer_runs("r1"), 90, message=lambda: f"the localizer running\n{procs.log('up')}")
        wait_until(lambda: localizer_runs("r2"), 90, message=lambda: f"r2's localizer running\n{procs.log('r2')}")

        # set-pose: a request to each robot, naming it; one line each, and the estimate on the pose stream is the
        # pose given
        code, out, err = _run(["localize", "set-pose", "0.8", "-1.2", "90", "--degrees",
                               "--cov", "1e-4", "1e-4", "1e-4", *bus], capsys)
        assert (code, err) == (0, ""), err
        assert out.splitlines() == ["r1: ok: initial pose set", "r2: ok: initial pose set"]

        def at(x, y, theta):
            with lock:
                return any(math.hypot(e.x - x, e.y - y) < 0.03 and abs(math.remainder(e.theta - theta, math.tau)) < 0.05
                           for e in estimates)

        wait_until(lambda: at(0.8, -1.2, math.pi / 2), 10, message=lambda: f"the pose set, got {estimates[-3:]}")
        # a request naming another robot is refused by the runtime, counted under "robot"
        with pytest.raises(QueryError, match=r"FrameError\(robot\)"):
            query(session, keys.localizer_set_initial_pose("r1"),
                  Pose2D(header=Header(robot="r2"), x=0.0, y=0.0, theta=0.0), reply_type=Ack, timeout=10)
        [status] = query(session, keys.status("r1", "localizer"), timeout=5)
        assert status.inputs["query:set_initial_pose"].rejected_reasons == {"robot": 1}
        second.terminate()
        assert second.wait(30) == 0, procs.log("r2")

        # relocalize: the particles spread over the whole map again
        with lock:
            estimates.clear()
        code, out, err = _run(["localize", "relocalize", "--robot", "r1", *bus], capsys)
        assert (code, out.splitlines()) == (0, ["r1: ok: global relocalization started"]), err

        def spread():
            with lock:
                return [e for e in estimates if e.status == "localizing" and e.particles == MAX_PARTICLES]

        [relocalized, *_] = wait_until(spread, 10, message=lambda: f"a global estimate, got {estimates[-3:]}")
        assert np.sqrt(relocalized.covariance[0][0]) > 1.0  # over a 9 m map, not around the pose set

        # logs: the localizer's log holds both commands; an unknown node is refused in one line
        code, out, err = _run(["logs", "localizer", *bus], capsys)
        assert code == 0, err
        assert "initial pose set to (0.800, -1.200, 1.571)" in out and "global relocalization" in out
        assert not any(line.startswith("[") for line in out.splitlines())  # one node: no prefixes
        code, out, err = _run(["logs", "nosuch", *bus], capsys)
        assert code == 1 and "no node 'nosuch'" in err and len(err.splitlines()) == 1

        # logs -f follows: a later command's line arrives, prefixed with its node
        follower = procs.semloc("logs", "-f", *bus, name="follow")
        wait_until(lambda: "[localizer]" in procs.log("follow"), 60, message=lambda: procs.log("follow"))
        assert _run(["localize", "set-pose", "-0.5", "0.25", "0", *bus], capsys)[0] == 0
        wait_until(lambda: "[localizer] " in procs.log("follow") and
                   "initial pose set to (-0.500, 0.250, 0.000)" in procs.log("follow"), 30,
                   message=lambda: procs.log("follow"))
        subscriber.undeclare()

    # stop: the launcher acknowledges, stops its nodes and `semloc up` ends; the follower notices
    code, out, err = _run(["stop", *bus], capsys)
    assert (code, out.splitlines()) == (0, ["r1: stopping graph ops (nodes: localizer)"]), err
    assert up.wait(60) == 0, procs.log("up")
    assert "stop requested over the bus" in procs.log("up")
    assert follower.wait(30) == 0 and "graph ops stopped answering" in procs.log("follow")

    # on a bus where nothing answers any more: one line each, exit code 1
    with open_session(BusConfig(listen=[hub])):
        for argv, what in ((["localize", "set-pose", "0", "0", "0"], "no localizer answered"),
                           (["localize", "relocalize"], "no localizer answered"),
                           (["logs"], "no launcher answered"), (["stop"], "no graph answered")):
            code, out, err = _run([*argv, *bus, "--wait", "1"], capsys)
            assert (code, out) == (1, ""), (argv, out, err)
            assert err.startswith(f"semloc {argv[0]}") and what in err and len(err.splitlines()) == 1, err


def test_a_graph_whose_workers_do_not_run_is_found_by_its_launcher(tmp_path, hub, capsys):  # noqa: F811
    """Without --robot the commands ask the robots they find by liveliness tokens; a graph none of whose workers runs
    (not started yet, waiting for a restart; here: none enabled) has its launcher's token, and `semloc stop` reaches
    it as before."""
    graph = tmp_path / "idle.yaml"
    graph.write_text(yaml.safe_dump({"name": "idle", "robot": "r3", "hub": hub, "rerun": {"mode": "off"},
                                     "nodes": {"localizer": {"worker": "localizer", "enabled": False}}}))
    with Launcher(load_graph(graph), run_dir=tmp_path / "run") as launcher:
        code, out, err = _run(["stop", "--connect", hub, "--wait", "10"], capsys)
        assert (code, out) == (0, "r3: stopping graph idle (nodes: none)\n"), err
        assert launcher.stop_requested.is_set()


def test_logs_follow_asks_the_launcher_on_its_own_key_not_the_one_its_reply_names(procs, session, hub):  # noqa: F811
    """A launcher's reply comes off the bus: `semloc logs -f` follows it on the key its robot and launcher name make.
    The reply's stream names another key here; following it would send every later request there."""
    asked = {"logs": 0, "elsewhere": 0}
    lock = threading.Lock()

    def answer(query_, where: str):
        with lock:
            asked[where] += 1
        header = Header(robot="r9", stream="semloc/r9/elsewhere/logs")
        tail = LogTail(header=header, launcher="ops-1", graph="ops",
                       logs={"node": LogChunk(start=0, end=6, text="hello\n")})
        query_.reply(str(query_.key_expr), encode(tail))
        query_.drop()

    queryables = [session.declare_queryable(keys.launcher_logs("r9", "ops-1"), lambda q: answer(q, "logs")),
                  session.declare_queryable("semloc/r9/elsewhere/logs", lambda q: answer(q, "elsewhere"))]
    try:
        follower = procs.semloc("logs", "-f", "--robot", "r9", "--connect", hub, name="follow")
        wait_until(lambda: asked["logs"] >= 3 or follower.poll() is not None, 30,
                   message=lambda: f"{asked}; {procs.log('follow')}")
        assert follower.poll() is None, procs.log("follow")
        assert asked["elsewhere"] == 0 and "hello" in procs.log("follow")
    finally:
        for queryable in queryables:
            queryable.undeclare()
