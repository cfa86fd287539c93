"""deploy/secure/ with real routers and a real localizer: mutual TLS refuses clients without a certificate of the
CA, and the access-control rules let the base station observe but not act, and the operator steer.

Two secure launchers as `semloc up deploy/two-machines/{base,robot}.yaml --secure DIR` builds them (the robot's router
connected to the base station's over mutual TLS), the localizer behind the base station's router. Attackers come in
on both routers' TLS listeners; what they achieved is read from the localizer's own Status counters, asked by a
process on the base station's host (loopback: the robot's rights), and every refusal is checked against an allowed
action that moves the same counter.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh

from schemas import Ack, Header, Odometry, Pose2D, Status, decode, keys
from schemas.localization import PoseEstimate
from schemas.status import LogRequest, LogTail
from services.bus import BusConfig, BusError, TlsFiles, open_session, publish, query
from services.security import ACCESS_CONTROL_FILE, link_problems
from tests.security.helpers import ROBOT, SECURE, TWO, client, identity, secure_configs, secure_launcher
from tests.service.conftest import REPO_ROOT, free_port, wait_until

pytestmark = pytest.mark.service


@dataclass
class SecureGraph:
    base_tls: str  # the base station's TLS listener
    robot_tls: str  # the robot's TLS listener
    base_hub: str  # the base station's loopback hub (its own processes)
    pki: Path
    truth: np.ndarray  # the data set's true poses (x, y, theta)


@pytest.fixture(scope="module")
def secure_graph(tmp_path_factory, pki, sim_dataset):
    tmp = tmp_path_factory.mktemp("secure-graph")
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    truth = np.load(dataset / "poses.npz", allow_pickle=False)["poses2d"]
    base_tls, robot_tls, base_hub, robot_hub = (free_port() for _ in range(4))
    configs = secure_configs(tmp / "secure", base_tls, robot_tls)
    base = secure_launcher(TWO / "base.yaml", {
        "hub": f"tcp/127.0.0.1:{base_hub}", "rerun": {"mode": "off"}, "state_dir": str(tmp / "state"),
        "nodes": {"loopclosure": {"enabled": False}, "mapper": {"enabled": False}, "monitor": {"enabled": False},
                  "localizer": {"config": {"map": str(dataset / "semantic_map.json"), "score_likelihood": "synthetic",
                                           "initial_pose": [float(v) for v in truth[0]], "seed": 0}}},
    }, pki, configs / "base-router.json5", tmp / "base")
    # The robot's router alone (its camera and detector off): the attackers' way in from the robot's side.
    robot = secure_launcher(TWO / "robot.yaml", {
        "hub": f"tcp/127.0.0.1:{robot_hub}", "nodes": {"camera": {"enabled": False}, "detector": {"enabled": False}},
    }, pki, configs / "robot-router.json5", tmp / "robot")
    graph = SecureGraph(f"tls/localhost:{base_tls}", f"tls/localhost:{robot_tls}", f"tcp/127.0.0.1:{base_hub}", pki,
                        truth)
    with base, robot:
        # Ready when the operator reaches the localizer from the robot's side: both routers, their link, the rules.
        with client(graph.robot_tls, identity(pki, "operator")) as operator:
            wait_until(lambda: query(operator, keys.status(ROBOT, "localizer"), timeout=1.0), 90, interval=0.3,
                       message="the localizer's status through both secure routers")
        yield graph


def localizer_status(session) -> Status:
    return query(session, keys.status(ROBOT, "localizer"), reply_type=Status, timeout=5.0)[0]


def odometry(stamp_ns: int) -> Odometry:
    return Odometry(header=Header(robot=ROBOT, stream=keys.odometry(ROBOT), stamp_ns=stamp_ns), v=0.0, omega=0.0,
                    dt=0.1)


def pose_request(pose) -> Pose2D:
    return Pose2D(header=Header(robot=ROBOT, stream="operator", stamp_ns=time.time_ns()), x=float(pose[0]),
                  y=float(pose[1]), theta=float(pose[2]), covariance=np.diag([1e-4, 1e-4, 1e-4]))


def test_access_rules_use_the_keys_of_schemas_keys():
    """Every key expression of the rules is one that schemas/keys.py defines (keys are defined there only)."""
    defined = {keys.robot_all(ROBOT), keys.robot_statuses(ROBOT), keys.robot_alive(ROBOT), keys.ALL_ALIVE,
               keys.ALL_LAUNCHERS_ALIVE}
    for name in dir(keys):
        function = getattr(keys, name)
        if callable(function) and name not in ("worker_of", "check_name", "status", "alive"):
            try:
                defined.add(function(ROBOT))
            except TypeError:
                pass
    config = zenoh.Config()
    config.insert_json5("access_control", (SECURE / ACCESS_CONTROL_FILE).read_text().replace("${ROBOT}", ROBOT))
    rules = json.loads(config.get_json("access_control/rules"))
    used = {key for rule in rules for key in rule["key_exprs"]}
    assert used <= defined, sorted(used - defined)
    assert keys.mapper_save(ROBOT) in used  # issue 30's command has its rule already


@pytest.mark.parametrize("who, cause", [
    ("none", "the router requires a client certificate"),
    ("foreign/operator", "the router does not trust this client's certificate"),
])
@pytest.mark.parametrize("side", ["robot", "base"])
def test_clients_without_a_certificate_of_the_ca_cannot_connect(secure_graph, who, cause, side):
    endpoint = secure_graph.robot_tls if side == "robot" else secure_graph.base_tls
    ca = str(secure_graph.pki / "ca.pem")
    tls = TlsFiles(ca=ca) if who == "none" else identity(secure_graph.pki, who)
    with client(secure_graph.base_hub) as local:
        before = localizer_status(local)
        start = time.monotonic()
        with pytest.raises(BusError) as refused:
            client(endpoint, tls).close()
        assert time.monotonic() - start < 15  # at once, not retried in the background
        assert str(refused.value) == f"cannot connect to {endpoint}: {cause}" + (
            " (--tls DIR/NAME)" if who == "none" else " (signed by another CA)")
        # The router itself refuses (not only semloc's own checks): zenoh alone cannot open a session either.
        with pytest.raises(zenoh.ZError):
            raw_client(endpoint, tls).close()
        after = localizer_status(local)
    assert (after.received, after.queries, after.errors) == (before.received, before.queries, before.errors)


def raw_client(endpoint: str, tls: TlsFiles) -> zenoh.Session:
    """A zenoh client with these TLS files and none of semloc's own checks (what the router alone decides)."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for field, value in tls.zenoh_settings().items():
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    return zenoh.open(config)


def test_expired_certificate_and_plain_tcp_are_refused(secure_graph):
    expired = identity(secure_graph.pki, "expired/operator")
    with pytest.raises(BusError, match=r"^cannot connect to .*: this client's certificate .*operator.pem expired on"):
        client(secure_graph.robot_tls, expired)
    with pytest.raises(zenoh.ZError):  # checked here first, but the router refuses it too
        raw_client(secure_graph.robot_tls, expired).close()
    plain = secure_graph.robot_tls.replace("tls/localhost", "tcp/127.0.0.1")
    with pytest.raises(BusError, match=r"^cannot connect to tcp/127.0.0.1:\d+: the connection opens but the zenoh "):
        client(plain)


def test_a_router_of_another_ca_is_refused(tmp_path, pki):
    """The other direction: a client does not talk to an impostor router whose certificate another CA signed."""
    port = free_port()
    impostor = tmp_path / "impostor.json5"
    impostor.write_text(json.dumps({"mode": "router", "transport": {"link": {"tls": {
        "root_ca_certificate": str(pki / "ca.pem"), "listen_certificate": str(pki / "foreign" / "base-router.pem"),
        "listen_private_key": str(pki / "foreign" / "base-router-key.pem"), "enable_mtls": True}}}}))
    with open_session(BusConfig(mode="router", listen=[f"tls/127.0.0.1:{port}"], zenoh_config=str(impostor))):
        with pytest.raises(BusError) as refused:
            client(f"tls/localhost:{port}", identity(pki, "operator"))
    assert str(refused.value).startswith(f"cannot connect to tls/localhost:{port}: the router's certificate is not "
                                         f"signed by {pki / 'ca.pem'}")


def test_a_router_says_why_it_cannot_link(secure_graph, tmp_path):
    """A router retries its links in the background; `semloc up` reports once why one fails (link_problems)."""
    pki = secure_graph.pki

    def router_config(name: str, directory: Path) -> Path:
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"mode": "router", "connect": {"endpoints": [secure_graph.base_tls]}, "transport": {
            "link": {"tls": {"root_ca_certificate": str(pki / "ca.pem"), "enable_mtls": True,
                             "connect_certificate": str(directory / f"{name}.pem"),
                             "connect_private_key": str(directory / f"{name}-key.pem")}}}}))
        return path

    assert link_problems(router_config(f"{ROBOT}-router", pki)) == []
    assert link_problems(router_config("operator", pki / "foreign")) == [
        f"cannot connect to {secure_graph.base_tls}: the router does not trust this client's certificate (signed by "
        "another CA) (zenoh keeps trying)"]


def test_base_station_observes_but_cannot_act(secure_graph):
    graph = secure_graph
    station = identity(graph.pki, "base-station")
    poses, statuses, to_stranger = [], [], []
    with client(graph.base_hub) as local, client(graph.robot_tls, station) as at_robot, \
            client(graph.base_tls, station) as at_base, \
            client(graph.base_tls, identity(graph.pki, "stranger")) as stranger:
        at_base.declare_subscriber(keys.localizer_pose(ROBOT), lambda s: poses.append(
            decode(s.payload.to_bytes(), expected=PoseEstimate)))
        at_robot.declare_subscriber(keys.status(ROBOT, "localizer"), lambda s: statuses.append(
            decode(s.payload.to_bytes(), expected=Status)))
        # A certificate of the CA with a name no rule knows connects, and may do nothing at all.
        for key in (keys.localizer_pose(ROBOT), keys.status(ROBOT, "localizer")):
            stranger.declare_subscriber(key, lambda s: to_stranger.append(str(s.key_expr)))
        before = localizer_status(local)
        for session in (at_robot, at_base, stranger):
            for index in range(5):
                publish(session, keys.odometry(ROBOT), odometry(time.time_ns() + index))
            assert query(session, keys.localizer_relocalize(ROBOT), timeout=1.0) == []
            assert query(session, keys.localizer_set_initial_pose(ROBOT), pose_request(graph.truth[3]),
                         timeout=1.0) == []
            assert query(session, keys.mapper_map(ROBOT), timeout=1.0) == []
        time.sleep(1.5)  # what got through has arrived by now: a hop on loopback takes milliseconds
        after = localizer_status(local)
        assert after.inputs["odom"].received == before.inputs["odom"].received
        assert (after.queries, after.errors, after.rejected) == (before.queries, before.errors, before.rejected)
        # The same put from a process on the base station's host reaches the localizer: the counter can move.
        publish(local, keys.odometry(ROBOT), odometry(time.time_ns()))
        wait_until(lambda: localizer_status(local).inputs["odom"].received == before.inputs["odom"].received + 1, 30,
                   interval=0.2, message="a local odometry message at the localizer")
        # The station receives the localizer's status (on the robot's side) and its poses (on its own).
        wait_until(lambda: statuses, 30, message="the localizer's status at the base station")
        assert statuses[-1].worker == "localizer" and statuses[-1].header.robot == ROBOT
        with client(graph.robot_tls, identity(graph.pki, "operator")) as operator:
            acks = query(operator, keys.localizer_set_initial_pose(ROBOT), pose_request(graph.truth[2]),
                         reply_type=Ack, timeout=10.0)
        assert [a.ok for a in acks] == [True]
        pose = wait_until(lambda: poses and poses[-1], 30, message="the announced pose at the base station")
        assert np.hypot(*(pose.pose()[:2] - graph.truth[2, :2])) < 0.05
        assert query(stranger, keys.status(ROBOT, "localizer"), timeout=1.0) == []
    assert to_stranger == []


def test_operator_sets_the_initial_pose(secure_graph):
    graph = secure_graph
    target = graph.truth[12]
    with client(graph.base_hub) as local, client(graph.robot_tls, identity(graph.pki, "operator")) as operator:
        before = localizer_status(local)
        acks = query(operator, keys.localizer_set_initial_pose(ROBOT), pose_request(target), reply_type=Ack,
                     timeout=10.0)
        assert [(a.ok, a.message) for a in acks] == [(True, "initial pose set")]
        # It took effect: the localizer's own estimate is now there (asked by the operator: a snapshot query).
        estimate = query(operator, keys.localizer_pose(ROBOT), reply_type=PoseEstimate, timeout=10.0)[0]
        assert np.hypot(*(estimate.pose()[:2] - target[:2])) < 0.05
        assert abs(np.angle(np.exp(1j * (estimate.pose()[2] - target[2])))) < 0.05
        after = localizer_status(local)
    assert after.queries == before.queries + 2 and after.errors == before.errors


def test_operator_sets_the_pose_of_every_robot_it_finds(secure_graph):
    """`semloc localize set-pose` without --robot finds the robots by their workers' liveliness tokens: the
    operator may ask (the rule "find-robots") and gets this robot's tokens; the base station finds none."""
    graph, pki = secure_graph, secure_graph.pki
    target = graph.truth[16]
    pose = [f"{float(v)!r}" for v in target]

    def set_pose(who: str, endpoint: str) -> subprocess.Popen:
        return _semloc("localize", "set-pose", *pose, "--cov", "1e-4", "1e-4", "1e-4", "--wait", "10",
                       "--mode", "client", "--connect", endpoint, "--tls", str(pki / who))
    runs = {("operator", "robot"): set_pose("operator", graph.robot_tls),
            ("operator", "base"): set_pose("operator", graph.base_tls),
            ("base-station", "base"): set_pose("base-station", graph.base_tls)}
    results = {name: (process.wait(120), *process.communicate()) for name, process in runs.items()}
    for side in ("robot", "base"):
        code, out, err = results["operator", side]
        assert (code, out) == (0, f"{ROBOT}: ok: initial pose set\n"), (side, err)
    code, out, err = results["base-station", "base"]
    assert code == 1 and out == "" and "no localizer answered" in err, err
    with client(graph.base_hub) as local:
        estimate = query(local, keys.localizer_pose(ROBOT), reply_type=PoseEstimate, timeout=10.0)[0]
    assert np.hypot(*(estimate.pose()[:2] - target[:2])) < 0.05


def test_only_the_operator_reads_the_launchers_logs_and_may_stop_them(secure_graph):
    """`semloc logs` and `semloc stop` from the operator's machine: both launchers answer the operator (connected to the
    robot's router), and neither the base station's certificate nor an unknown one."""
    graph = secure_graph
    request = LogRequest(header=Header(robot=ROBOT, stream="semloc logs"), tail_bytes=4096)
    with client(graph.robot_tls, identity(graph.pki, "operator")) as operator:
        tails = query(operator, keys.all_launcher_logs(ROBOT), request, reply_type=LogTail, timeout=10.0)
    by_graph = {tail.graph: tail for tail in tails}
    assert sorted(by_graph) == ["base", "robot"]  # both machines' launchers answer
    assert by_graph["base"].logs["localizer"].text  # the localizer's own log lines
    for who, endpoint in (("base-station", graph.robot_tls), ("base-station", graph.base_tls),
                          ("stranger", graph.base_tls)):
        with client(endpoint, identity(graph.pki, who)) as session:
            assert query(session, keys.all_launcher_logs(ROBOT), request, timeout=1.0) == [], who
            assert query(session, keys.all_launcher_stop(ROBOT), timeout=1.0) == [], who
    with client(graph.base_hub) as local:  # the base station's graph is still up: nobody stopped it
        assert localizer_status(local).worker == "localizer"


def test_only_the_operator_may_restart_a_node(secure_graph):
    """`semloc restart localizer` from the operator's machine (connected to the robot's router) restarts the localizer
    run behind the base station's router: a new process, told it is the operator's restart; the robot's launcher,
    which runs no localizer, says so. The base station's certificate and an unknown one reach no launcher."""
    graph, pki = secure_graph, secure_graph.pki
    with client(graph.base_hub) as local:
        before = localizer_status(local)
        for who, endpoint in (("base-station", graph.robot_tls), ("base-station", graph.base_tls),
                              ("stranger", graph.base_tls)):
            with client(endpoint, identity(pki, who)) as session:
                assert query(session, keys.all_launcher_restart(ROBOT, "localizer"), timeout=1.0) == [], who
        assert localizer_status(local).pid == before.pid
        restart = _semloc("restart", "localizer", "--wait", "10", "--mode", "client", "--connect", graph.robot_tls,
                          "--tls", str(pki / "operator"))
        code, out, err = restart.wait(120), *restart.communicate()
        assert code == 0, err
        assert sorted(out.splitlines()) == [
            f"{ROBOT}: ok: restarting node localizer of graph base (pid {before.pid}: SIGTERM, SIGKILL after 5 s)",
            f"{ROBOT}: refused: no node 'localizer' in graph robot (nodes: none)"], out
        after = wait_until(lambda: (s := query(local, keys.status(ROBOT, "localizer"), reply_type=Status, timeout=2.0))
                           and s[0].pid != before.pid and s[0].state == "running" and s[0], 90, interval=0.3,
                           message="the localizer running again")
    assert (after.restarts, after.restart_reason) == (before.restarts + 1, "operator")


def test_operator_commands_without_robot_ask_each_robot_it_finds(secure_graph):
    """`semloc localize relocalize`, `logs` and `status` without --robot: each finds the robots by their workers'
    liveliness tokens and asks each on that robot's keys, which the rules allow (a query over every robot's keys
    lies within none). The base station, which may neither ask which robots there are nor call controls, gets
    nothing, and the localizer counts the operator's one relocalization only."""
    graph, pki = secure_graph, secure_graph.pki

    def semloc(who: str, endpoint: str, *command: str) -> subprocess.Popen:
        return _semloc(*command, "--wait", "10", "--mode", "client", "--connect", endpoint, "--tls", str(pki / who))
    with client(graph.base_hub) as local:
        before = localizer_status(local)
        runs = {  # started together: each is a Python start-up
            ("operator", "relocalize"): semloc("operator", graph.robot_tls, "localize", "relocalize"),
            ("operator", "logs"): semloc("operator", graph.base_tls, "logs", "--tail", "4096"),
            ("operator", "status"): semloc("operator", graph.robot_tls, "status", "--json"),
            ("base-station", "relocalize"): semloc("base-station", graph.base_tls, "localize", "relocalize"),
            ("base-station", "logs"): semloc("base-station", graph.robot_tls, "logs"),
        }
        results = {name: (process.wait(120), *process.communicate()) for name, process in runs.items()}
        after = localizer_status(local)
        # Relocalized: back at a known pose for the other tests.
        with client(graph.robot_tls, identity(pki, "operator")) as operator:
            assert [a.ok for a in query(operator, keys.localizer_set_initial_pose(ROBOT), pose_request(graph.truth[0]),
                                        reply_type=Ack, timeout=10.0)] == [True]
    code, out, err = results["operator", "relocalize"]
    assert (code, out) == (0, f"{ROBOT}: ok: global relocalization started\n"), err
    assert after.queries == before.queries + 1 and after.errors == before.errors
    code, out, err = results["operator", "logs"]
    assert code == 0 and "[localizer] " in out, err  # the base station's launcher's localizer
    assert "graph robot keeps no log files" in err  # the robot's launcher (no nodes here) answered too
    code, out, err = results["operator", "status"]
    seen = json.loads(out)["workers"]
    assert sorted(seen) == [f"{ROBOT}/localizer"], err
    assert seen[f"{ROBOT}/localizer"]["status"]["worker"] == "localizer" and seen[f"{ROBOT}/localizer"]["launcher"]
    # Found by the launchers' tokens too (a graph whose workers do not run): the operator gets both launchers'.
    with client(graph.robot_tls, identity(pki, "operator")) as operator, \
            client(graph.base_tls, identity(pki, "base-station")) as station:
        def launchers(session) -> list[str]:
            return sorted(str(reply.ok.key_expr).split("/")[3]
                          for reply in session.liveliness().get(keys.ALL_LAUNCHERS_ALIVE, timeout=2.0) if reply.ok)
        found = wait_until(lambda: len(launchers(operator)) == 2 and launchers(operator), 30,
                           message="both launchers' tokens at the operator")
        assert [name.split("-")[0] for name in found] == ["base", "robot"]  # the launcher's id starts with its graph
        assert launchers(station) == []
    code, out, err = results["base-station", "relocalize"]
    assert (code, out) == (1, "") and "no localizer answered on semloc/*/localizer/relocalize in 10 s" in err, err
    code, out, err = results["base-station", "logs"]
    assert (code, out) == (1, "") and "no launcher answered on semloc/*/launcher/*/logs in 10 s" in err, err


def _semloc(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)


def test_commands_take_the_credentials_and_fail_in_one_line(secure_graph, tmp_path):
    graph, pki = secure_graph, secure_graph.pki
    bus = ["--mode", "client", "--connect", graph.base_tls]
    runs = {  # started together: each is a Python start-up
        "status": _semloc("status", "--robot", ROBOT, "--json", *bus, "--tls", str(pki / "base-station")),
        "status-foreign": _semloc("status", "--robot", ROBOT, *bus, "--tls", str(pki / "foreign" / "operator")),
        "record-none": _semloc("record", "-o", str(tmp_path / "x.mcap"), "--duration", "1", *bus),
        "worker-expired": _semloc("worker", "sink", "--robot", ROBOT, *bus, "--tls", str(pki / "expired" / "operator")),
        "replay-missing": _semloc("replay", str(REPO_ROOT / "pyproject.toml"), *bus, "--tls", str(tmp_path / "nobody")),
    }
    results = {name: (process.wait(120), *process.communicate()) for name, process in runs.items()}
    code, out, err = results["status"]
    assert code == 0, err
    seen = json.loads(out)["workers"][f"{ROBOT}/localizer"]
    assert seen["status"]["worker"] == "localizer" and seen["launcher"]["worker"] == "localizer"  # both allowed
    expected = {
        "status-foreign": f"semloc status: cannot connect to {graph.base_tls}: the router does not trust this "
                          "client's certificate (signed by another CA)",
        "record-none": f"semloc record: cannot connect to {graph.base_tls}: a tls/ endpoint needs TLS credentials",
        "worker-expired": f"semloc worker: cannot connect to {graph.base_tls}: this client's certificate "
                          f"{pki / 'expired' / 'operator.pem'} expired on",
        "replay-missing": f"semloc replay: cannot connect to {graph.base_tls}: TLS CA certificate "
                          f"{tmp_path / 'ca.pem'} does not exist",
    }
    for name, start in expected.items():
        code, _, err = results[name]
        # A worker logs its config first; the error is then its one line of its own.
        lines = [line for line in err.strip().splitlines() if " semloc.sink: config " not in line]
        assert (code, len(lines)) == (2, 1) and lines[0].startswith(start), (name, code, err)
