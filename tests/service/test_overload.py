"""Health under load (docs/runtime.md, "Status, liveliness, health"): a worker that cannot keep up with its input
says so and says running again once it can, one that drops in bursts with time to spare does not; a node the
machine starves of CPU is not killed as hung, a SIGSTOPped one is. Real worker processes over zenoh on loopback."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml
import zenoh

from schemas import Ack, Header, Status, encode, keys
from schemas.status import LauncherStatus
from services.bus import BusConfig, open_session, query
from services.runtime import Worker, WorkerConfig
from tests.service.conftest import spinning, wait_until

pytestmark = pytest.mark.service
LOADED = "tests.service.loaded_worker"  # a sink whose rare calls are long, or that has the machine starve it
STEADY = "semloc/r1/test/steady"


def _statuses(session) -> dict[str, Status]:
    frames = query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0, every_reply=True)
    return {frame.worker: frame for frame in frames}


def _launcher_view(session) -> dict:
    views = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=1.0)
    return views[0].nodes if views else {}


def _sink(procs, hub: str, name: str, policy: str, depth: int, *settings: str, worker: str = "sink") -> None:
    options = [option for setting in settings for option in ("--set", setting)]
    procs.semloc("worker", worker, "--connect", hub, "--robot", "r1", "--name", name, "--set", f"key={STEADY}",
                 "--set", f"policy={policy}", "--set", f"depth={depth}", "--set", "status_period_s=0.25", *options,
                 name=name)


def test_a_worker_that_cannot_keep_up_says_so_until_it_can_one_dropping_in_bursts_does_not(procs, session, hub):
    # 40 frames/s, then 4/s, to handlers of 50 ms (capacity 20/s), and to one of 5 ms whose every 40th call takes
    # 1 s more (uneven): that one drops the 38 frames of each long call, yet their median time fits in its idle time
    # (a mean of 30 ms would not: the long calls are what drops come from).
    _sink(procs, hub, "latest", "latest", 2, "process_delay_s=0.05")
    _sink(procs, hub, "lossless", "lossless", 4, "process_delay_s=0.05")
    _sink(procs, hub, "uneven", "latest", 2, "process_delay_s=0.005", "slow_every=40", "slow_s=1.0", worker=LOADED)
    wait_until(lambda: len(s := _statuses(session)) == 3 and all(x.state == "running" for x in s.values()), 60,
               message=lambda: f"3 running sinks: {_statuses(session)}")
    publisher = session.declare_publisher(STEADY, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscribers matched")
    seq = 0

    def play(seconds: float, hz: float, until=None) -> dict[str, list[Status]]:
        """Publish at ``hz`` for ``seconds`` (or until ``until(statuses)``); the statuses seen per worker."""
        nonlocal seq
        seen: dict[str, list[Status]] = {}
        start = next_frame = time.monotonic()
        next_poll = start + 0.5
        while (now := time.monotonic()) < start + seconds:
            if now >= next_frame:
                publisher.put(encode(Ack(header=Header(robot="r1", seq=seq, stamp_ns=seq + 1), ok=True)))
                seq += 1
                next_frame += 1 / hz
            if now >= next_poll:
                for name, status in _statuses(session).items():
                    seen.setdefault(name, []).append(status)
                next_poll = now + 0.5
                if until is not None and until({n: s[-1] for n, s in seen.items()}):
                    break
            time.sleep(max(0.0, min(next_frame, next_poll) - time.monotonic()))
        return seen

    both_degraded = lambda s: all(s.get(n) and s[n].state == "degraded" for n in ("latest", "lossless"))  # noqa: E731
    seen = play(25.0, 40.0, until=both_degraded)
    assert both_degraded({name: statuses[-1] for name, statuses in seen.items()}), \
        {n: (s[-1].state, s[-1].state_reason) for n, s in seen.items()}
    # 2 s more: the latest sink says degraded once its window asks 100 %, when the lossless one's status (sent
    # apart from it) may still have read 99 % (a loaded run); the window then holds 40 % more of the demand
    more = play(2.0, 40.0)
    last = {name: (more.get(name) or statuses)[-1] for name, statuses in seen.items()}
    assert both_degraded(last), {n: (s.state, s.state_reason) for n, s in last.items()}
    for name, verb, counter in (("latest", "dropped", "dropped"), ("lossless", "refused", "overflow")):
        match = re.fullmatch(rf"falling behind on frames: {verb} (\d+) of (\d+) frames in the last 10 s "
                             r"\(busy (\d+) %, needed (\d+) %\)", last[name].state_reason)
        assert match, last[name].state_reason
        lost, arrived, busy, needed = map(int, match.groups())
        assert 0 < lost <= getattr(last[name], counter) and lost < arrived <= last[name].received
        assert busy >= 50 and needed >= 100, last[name].state_reason  # 40/s x 50 ms: twice what it has
        # What its own queue refused arrived: not lost on the way (the gap it leaves in the numbering)
        assert last[name].inputs["frames"].lost_in_transit == 0, last[name].inputs["frames"]
    uneven = play(6.0, 40.0)["uneven"]  # its long calls' drops in the window as well
    assert uneven[-1].dropped > 0 and {s.state for s in seen["uneven"] + uneven} == {"running"}, \
        [(s.state, s.state_reason, s.busy_fraction) for s in seen["uneven"] + uneven]

    # Slower than it handles them: running again, the lossless one once its refusals leave the 10 s window.
    recovered = lambda s: all(s.get(n) and s[n].state == "running" for n in ("latest", "lossless"))  # noqa: E731
    seen = play(25.0, 4.0, until=recovered)
    last = {name: statuses[-1] for name, statuses in seen.items()}
    assert recovered(last), {n: (s.state, s.state_reason) for n, s in last.items()}
    assert {s.state for s in seen["uneven"]} == {"running"}


def test_a_handler_still_running_counts_as_busy(session):
    """A call of seconds is the window's work before it returns: busy_fraction without it says idle."""
    worker = Worker(WorkerConfig(robot="r1", name="long"))
    worker.session = session
    entered, release = threading.Event(), threading.Event()

    def long_call(frame):
        entered.set()
        release.wait(10)

    worker.input("frames", "semloc/r1/long/frames", Ack, long_call)
    with spinning(worker):
        session.put("semloc/r1/long/frames", encode(Ack(header=Header(robot="r1"), ok=True)))
        try:
            assert entered.wait(10)
            time.sleep(1.0)
            status = worker.status()
        finally:
            release.set()
    assert status.processed == 0 and status.busy_fraction > 0.5, status.busy_fraction


def test_a_node_the_machine_starves_is_shown_stalled_not_killed_a_stopped_one_is(tmp_path, procs, hub):
    # `starved` starves itself on its first frame for 8 s (tests/service/loaded_worker.py), with two busy processes
    # of other sessions on its CPU; `stopped` is SIGSTOPped. Both fall silent for longer than restart_after_s.
    cpu = max(os.sched_getaffinity(0))
    trigger = "semloc/r1/test/starve"
    sink = {"worker": "sink", "config": {"key": "semloc/r1/test/none", "status_period_s": 0.25}}
    starved = {"worker": LOADED, "config": {"key": trigger, "status_period_s": 0.25, "cpu": cpu, "starve_for_s": 8}}
    graph = {"name": "starved", "robot": "r1", "hub": hub, "stop_timeout_s": 5,
             "nodes": {"starved": starved, "stopped": sink}, "restart": {"policy": "on-failure", "backoff_s": 0.1},
             "heartbeat": {"stalled_after_s": 1.0, "restart_after_s": 3.0}}
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(graph))
    procs.semloc("up", str(tmp_path / "graph.yaml"), "--run-dir", str(tmp_path / "run"), name="launcher")
    hogs = []
    with open_session(BusConfig(connect=[hub])) as session:
        first = wait_until(lambda: len(s := _statuses(session)) == 2 and all(x.state == "running" for x in s.values())
                           and s, 60, message=lambda: f"2 running nodes; launcher log:\n{procs.log('launcher')}")
        # and the launcher has heard them run: a node starved before its launcher did stays `starting` (a CI run
        # at load 6 read that)
        wait_until(lambda: len(v := _launcher_view(session)) == 2 and all(n.state == "running" for n in v.values()),
                   30, message=lambda: f"the launcher's view of 2 running nodes:\n{procs.log('launcher')}")
        try:
            hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True,
                                     preexec_fn=lambda: os.sched_setaffinity(0, {cpu})) for _ in range(2)]
            session.put(trigger, encode(Ack(header=Header(robot="r1"), ok=True)))
            os.kill(first["stopped"].pid, signal.SIGSTOP)
            views, end = [], time.monotonic() + 9.0
            while time.monotonic() < end:
                views.append(_launcher_view(session))
                time.sleep(0.5)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
        shown = [v["starved"] for v in views if "starved" in v]
        assert all(n.restarts == 0 for n in shown), procs.log("launcher")
        assert max(n.heartbeat_age_s or 0 for n in shown) > 2 * 3.0, shown  # silent well past restart_after_s
        assert any(n.state == "stalled" and re.fullmatch(r"no heartbeat for [\d.]+ s \([\d.]+ s of it waiting for a "
                                                         r"CPU\)", n.state_reason) for n in shown), shown
        back = wait_until(lambda: (s := _statuses(session).get("starved")) and s.state == "running" and s, 20,
                          message=lambda: f"starved running again; launcher log:\n{procs.log('launcher')}")
        assert (back.pid, back.restarts) == (first["starved"].pid, 0), procs.log("launcher")
        restarted = wait_until(lambda: (s := _statuses(session).get("stopped")) and s.pid != first["stopped"].pid
                               and s, 20, message=lambda: f"stopped restarted; launcher log:\n{procs.log('launcher')}")
        assert re.fullmatch(r"hung: no heartbeat for 3\.\d s", restarted.restart_reason), restarted.restart_reason
