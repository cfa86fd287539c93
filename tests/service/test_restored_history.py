"""A worker restored from its state gets from the recoverable publishers' caches what its state misses, and nothing
it holds (docs/deploy.md, "When the link drops"): the counter of tests/service/workers_for_tests.py, its input made
recoverable, fed by a recoverable publisher in the test's process while it runs, while it is down, and after."""

from __future__ import annotations

import signal

import pytest

from schemas import Ack, Header, Status, decode
from services.bus import FramePublisher, query
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

WORKER = "tests.service.workers_for_tests"
KEY = "semloc/r1/counter/in"


def _status(session) -> Status | None:
    frames = query(session, "semloc/r1/counter/status", reply_type=Status, timeout=0.5)
    return frames[0] if frames else None


def _count(session) -> int | None:
    replies = query(session, "semloc/r1/counter/count", reply_type=Ack, timeout=2.0)
    return int(replies[0].message) if replies else None


def _running(session, process) -> Status:
    return wait_until(lambda: (s := _status(session)) and s.pid == process.pid and s.state == "running" and s, 30,
                      message="the counter running")


def _put(publisher: FramePublisher, seqs) -> None:
    for seq in seqs:
        publisher.put_frame(Ack(header=Header(robot="r1", stream="in", seq=seq, stamp_ns=1000 + seq), ok=True))


@pytest.mark.parametrize("stop", ["graceful", "kill"])
def test_a_restored_worker_gets_what_its_state_misses_once(tmp_path, procs, session, hub, stop):
    """Stopped after 10 frames (a graceful stop snapshots them; a SIGKILL leaves them in the journal), 10 more sent
    while it is down: restarted, it counts those 10 from the publisher's cache, in order, before the live ones, and
    not the first 10 again (already held); a worker started without state gets none of the cache."""
    args = ["worker", WORKER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
            str(tmp_path / "state"), "--set", "inputs.in.recover=true", "--set", "status_period_s=0.2",
            "--set", "snapshot_period_s=1000", "--set", "journal_replay_s=1000"]
    echoes: list[int] = []  # the stamps of the frames counted, in the order counted (each echo carries its stamp)
    subscriber = session.declare_subscriber(
        "semloc/r1/counter/echo", lambda s: echoes.append(decode(s.payload.to_bytes(), expected=Ack).header.stamp_ns))
    publisher = FramePublisher(session, KEY, recover=100)
    worker = procs.semloc(*args, name="counter")
    _running(session, worker)
    _put(publisher, range(10))
    wait_until(lambda: _count(session) == 10, 20, message="10 frames counted")
    if stop == "graceful":
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(20) == 0
    else:
        worker.send_signal(signal.SIGKILL)
        worker.wait(10)
    _put(publisher, range(10, 20))  # nobody listens: only the cache keeps them

    restarted = procs.semloc(*args, name="counter2")
    _running(session, restarted)
    _put(publisher, range(20, 25))
    wait_until(lambda: _count(session) == 25, 20, message=lambda: f"25 frames counted (got {_count(session)})")
    wait_until(lambda: len(echoes) >= 25, 10, message="25 echoes")
    stats = _status(session).inputs["in"]
    assert echoes == [1000 + seq for seq in range(25)]  # each once, in order
    assert (stats.recovered, stats.already_held, stats.missed) == (10, 10, 0), stats
    assert _count(session) == 25

    restarted.send_signal(signal.SIGTERM)
    assert restarted.wait(20) == 0
    fresh = procs.semloc(*[a if a != str(tmp_path / "state") else str(tmp_path / "other") for a in args],
                         name="counter3")
    _running(session, fresh)
    _put(publisher, range(25, 27))
    wait_until(lambda: _count(session) == 2, 20, message=lambda: f"2 frames counted (got {_count(session)})")
    stats = _status(session).inputs["in"]
    assert (stats.recovered, stats.already_held) == (0, 0), stats
    subscriber.undeclare()
    publisher.undeclare()
