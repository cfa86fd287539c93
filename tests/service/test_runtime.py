"""The worker runtime over real processes: queue policies, queryables, error isolation, state across a crash,
graceful stop."""

from __future__ import annotations

import signal
import threading
import time

import pytest
import zenoh

from schemas import Ack, Header, Odometry, Status, decode, encode
from services.bus import QueryError, query
from services.journal import Journal
from services.runtime import Worker, WorkerConfig
from tests.service.conftest import read_jsonl, spinning, wait_until

pytestmark = pytest.mark.service
WORKER = "tests.service.workers_for_tests"


def _ack(seq: int, message: str = "") -> bytes:
    return encode(Ack(header=Header(robot="r1", seq=seq, stamp_ns=seq + 1), ok=True, message=message))


def _status(session, name: str) -> Status | None:
    frames = query(session, f"semloc/r1/{name}/status", reply_type=Status, timeout=0.5)
    return frames[0] if frames else None


def _count(session) -> int | None:
    replies = query(session, "semloc/r1/counter/count", reply_type=Ack, timeout=2.0)
    return int(replies[0].message) if replies else None


def test_queries_errors_state_and_graceful_stop(tmp_path, procs, session, hub):
    args = ["worker", WORKER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
            str(tmp_path / "state"), "--set", "snapshot_period_s=0.2", "--set", "status_period_s=0.2"]
    worker = procs.semloc(*args, name="counter")
    wait_until(lambda: _status(session, "counter"), 30, message="counter up")
    publisher = session.declare_publisher("semloc/r1/counter/in", congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    for seq, message in enumerate(["", "", "boom", "", "bad", "", ""]):
        publisher.put(_ack(seq, message))
    status = wait_until(lambda: (s := _status(session, "counter")) and s.received == 7 and s.processed == 5 and s,
                        20, message="7 frames handled")
    assert (status.errors, status.rejected) == (1, 1)  # a raising handler is counted, never fatal
    assert "boom" in status.last_error or "semantically invalid" in status.last_error
    assert worker.poll() is None
    # Typed request/reply, and an error reply for a failing handler.
    assert int(query(session, "semloc/r1/counter/add", Ack(header=Header(robot="r1"), ok=True, message="10"),
                     reply_type=Ack)[0].message) == 15
    with pytest.raises(QueryError, match="not a number"):
        query(session, "semloc/r1/counter/add", Ack(header=Header(robot="r1"), ok=True, message="x"))
    with pytest.raises(QueryError, match="needs a semloc.Ack request"):
        query(session, "semloc/r1/counter/add")

    time.sleep(0.6)  # > snapshot period
    worker.send_signal(signal.SIGKILL)
    worker.wait(10)
    restarted = procs.semloc(*args, name="counter2")
    wait_until(lambda: (s := _status(session, "counter")) and s.pid == restarted.pid, 30, message="restart")
    # Restored from the snapshot taken before the crash (the queryables are declared after the status one: wait).
    assert wait_until(lambda: _count(session), 10, message="count queryable after restart") == 15

    finals = []
    subscriber = session.declare_subscriber("semloc/r1/counter/status",
                                            lambda s: finals.append(decode(s.payload.to_bytes(), expected=Status)))
    publisher.put(_ack(100))
    wait_until(lambda: _count(session) == 16, 10, message="one more frame")
    restarted.send_signal(signal.SIGTERM)
    assert restarted.wait(20) == 0
    wait_until(lambda: finals and finals[-1].state == "stopped", 5, message="final status")
    subscriber.undeclare()
    restarted_again = procs.semloc(*args, name="counter3")
    wait_until(lambda: (s := _status(session, "counter")) and s.pid == restarted_again.pid, 30, message="restart")
    assert wait_until(lambda: _count(session), 10, message="count queryable") == 16  # the graceful stop saved it


@pytest.mark.parametrize("policy, depth", [("latest", 2), ("lossless", 4), ("lossless", 256)])
def test_queue_policies(tmp_path, procs, session, hub, policy, depth):
    name = f"sink_{policy}_{depth}"
    key = f"semloc/r1/policy/{name}"
    log = tmp_path / "frames.jsonl"
    procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", name, "--set", f"key={key}", "--set",
                 f"policy={policy}", "--set", f"depth={depth}", "--set", "process_delay_s=0.01", "--set",
                 f"log_path={log}", "--log-level", "WARNING", name=name)
    wait_until(lambda: _status(session, name), 30, message="sink up")
    publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    for seq in range(150):
        publisher.put(encode(Odometry(header=Header(robot="r1", seq=seq), v=1.0, omega=0.0, dt=0.01)))
    settled = wait_until(lambda: (s := _status(session, name)) and s.received == 150 and
                         s.processed + s.dropped + s.overflow == 150 and s, 30, message="queue drained")
    handled = [record["seq"] for record in read_jsonl(log)]
    assert len(handled) == settled.processed and handled == sorted(handled)  # whatever is handled, in order
    if policy == "latest":
        # 150 frames in a burst, 10 ms each to process, 2 slots: most are dropped, the freshest survive.
        assert settled.dropped > 50 and settled.processed >= depth and settled.overflow == 0
        assert handled[-1] == 149
    elif depth < 150:
        # lossless, no room for the burst: the arriving frames are refused and counted (zenoh's thread is never held)
        assert settled.overflow > 50 and settled.processed >= depth and settled.dropped == 0
        assert settled.inputs["frames"].overflow == settled.overflow and handled[:depth] == list(range(depth))
    else:
        # lossless with room for the burst: nothing lost
        assert settled.dropped == settled.overflow == 0 and handled == list(range(150))


class _Exclusive:
    """Handlers and a timer that record when two pieces of worker code run at the same time."""

    def __init__(self):
        self.active = self.overlaps = 0
        self.seen: list[int] = []
        self.threads: set[int] = set()

    def enter(self):
        self.overlaps += self.active
        self.active += 1

    def leave(self):
        self.active -= 1

    def on_frame(self, frame):
        self.enter()
        self.seen.append(frame.header.seq)
        self.threads.add(threading.get_ident())
        time.sleep(0.0002 if frame.header.seq % 7 else 0.003)  # now and then slower than the stream: a backlog
        self.leave()

    def on_timer(self):
        self.enter()
        time.sleep(0.002)
        self.leave()


def test_worker_code_never_runs_twice_at_once_and_lossless_order_holds(session):
    """A lossless frame may be handled on zenoh's thread while the main thread idles (the fast path of
    Input._on_sample): worker code must still run one piece at a time, and frames in order."""
    worker = Worker(WorkerConfig(robot="r1", name="exclusive"))
    worker.session = session
    probe = _Exclusive()
    # Room for every frame: a full lossless queue refuses frames (test_queue_policies), this test is about order.
    worker.input("in", "semloc/r1/exclusive/in", Ack, probe.on_frame, policy="lossless", depth=512)
    worker.every(0.004, probe.on_timer)  # busy half the time: frames arrive both while it runs and while idle
    with spinning(worker) as main:
        publisher = session.declare_publisher("semloc/r1/exclusive/in",
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        for seq in range(400):
            publisher.put(_ack(seq))
            if seq % 20 == 0:
                time.sleep(0.05)  # idle gaps: the next frame may find the main thread waiting (fast path)
        wait_until(lambda: len(probe.seen) == 400, 30, message="all frames handled")
    assert probe.overlaps == 0
    assert probe.seen == list(range(400))
    assert worker._inputs[0].processed == 400 and worker._inputs[0].received == 400
    assert main.ident in probe.threads  # the main thread took its share (the backlog behind slow frames)
    assert len(probe.threads) >= 2  # and zenoh's thread handled frames that found the worker idle (the fast path)


def test_a_worker_behind_handles_frames_of_several_inputs_in_arrival_order(session):
    """Frames queued on two inputs while the worker is busy run in the order they arrived, not input by input (the
    localizer must integrate a frame's odometry before the heatlines computed from that frame)."""
    worker = Worker(WorkerConfig(robot="r1", name="arrival"))
    worker.session = session
    seen: list[tuple[str, int]] = []
    busy, release = threading.Event(), threading.Event()

    def block_once():
        if not busy.is_set():
            busy.set()
            release.wait(10)  # the worker is busy (on its main thread) while frames queue up on both inputs

    def on(name):
        return lambda frame: seen.append((name, frame.header.seq))

    # "heatlines" is declared first: input by input, its frames would all run before the odometry's
    worker.input("heatlines", "semloc/r1/arrival/heatlines", Ack, on("heatlines"), policy="lossless", depth=16)
    worker.input("odom", "semloc/r1/arrival/odom", Ack, on("odom"), policy="lossless", depth=16)
    worker.every(0.01, block_once)
    with spinning(worker):
        try:
            publishers = {name: session.declare_publisher(f"semloc/r1/arrival/{name}",
                                                          congestion_control=zenoh.CongestionControl.BLOCK)
                          for name in ("odom", "heatlines")}
            assert busy.wait(5), "the timer did not run"
            sent = []
            for seq in range(6):
                for name in ("odom", "heatlines"):
                    publishers[name].put(_ack(seq))
                    sent.append((name, seq))
                    # distinct arrival times: each input is delivered on its own zenoh thread, and on a loaded
                    # machine a thread may wake several milliseconds late (5 ms apart once swapped two frames)
                    time.sleep(0.03)
            wait_until(lambda: sum(i.received for i in worker._inputs) == len(sent), 10,
                       message="all frames queued")
        finally:
            release.set()
        wait_until(lambda: len(seen) == len(sent), 10, message="all frames handled")
    assert seen == sent, (seen, sent)


def test_a_latest_input_unanswered_at_start_is_asked_again_until_answered(session):
    """latest_input asks for the current value at setup; a restarted worker whose session has not yet met the
    publisher's process gets no answer then, and must not go without the value until the next publication (the
    test process never publishes it): it asks again until answered, and then stops asking."""
    worker = Worker(WorkerConfig(robot="r1", name="late"))
    worker.session = session
    values: list[str] = []
    asked: list[int] = []
    entry = worker.latest_input("model", "semloc/r1/late/model", Ack, lambda frame: values.append(frame.message))
    assert values == [] and entry.received == 0  # nothing answered at setup

    def answer(query_):
        asked.append(1)
        query_.reply("semloc/r1/late/model", _ack(7, "the model"))
        query_.drop()

    with spinning(worker):
        time.sleep(0.3)  # a few unanswered attempts
        queryable = session.declare_queryable("semloc/r1/late/model", answer)
        try:
            wait_until(lambda: values, 10, message="the value asked for again")
            answered = len(asked)
            time.sleep(1.0)  # the timer keeps running: no more questions once answered
            assert len(asked) == answered
        finally:
            queryable.undeclare()
    assert values == ["the model"] and entry.received == entry.processed == 1


def test_the_journal_brings_back_what_no_snapshot_holds(tmp_path, procs, session, hub):
    """SIGKILLed with no snapshot taken, the counter restarts from its journal: every counted frame and addition,
    none of its outputs published again; a graceful stop then snapshots and empties the journal."""
    args = ["worker", WORKER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
            str(tmp_path / "state"), "--set", "snapshot_period_s=1000", "--set", "journal_replay_s=1000",
            "--set", "status_period_s=0.2"]
    echoes = []
    subscriber = session.declare_subscriber("semloc/r1/counter/echo", lambda s: echoes.append(s.payload.to_bytes()))
    worker = procs.semloc(*args, name="counter")
    wait_until(lambda: _status(session, "counter"), 30, message="counter up")
    publisher = session.declare_publisher("semloc/r1/counter/in", congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    for seq in range(30):
        publisher.put(_ack(seq, "boom" if seq == 7 else ""))
    wait_until(lambda: _count(session) == 29, 20, message="29 frames counted")
    assert int(query(session, "semloc/r1/counter/add", Ack(header=Header(robot="r1"), ok=True, message="5"),
                     reply_type=Ack)[0].message) == 34
    status = _status(session, "counter")
    assert status.persistence.journal_records == 30 and status.persistence.snapshots == 0
    assert not (tmp_path / "state" / "r1" / "counter.npz").exists()
    wait_until(lambda: len(echoes) == 29, 10, message="29 echoes")
    worker.send_signal(signal.SIGKILL)
    worker.wait(10)
    published = len(echoes)

    restarted = procs.semloc(*args, name="counter2")
    status = wait_until(lambda: (s := _status(session, "counter")) and s.pid == restarted.pid
                        and s.state == "running" and s, 30, message="restart")
    assert wait_until(lambda: _count(session), 10, message="count queryable after restart") == 34
    assert status.persistence.replayed == 30 and not status.persistence.restored
    publisher.put(_ack(100))
    wait_until(lambda: _count(session) == 35, 10, message="one more frame")
    # the echo travels apart from the count's reply: wait for it, then for anything a replay might have published
    wait_until(lambda: len(echoes) > published, 10, message="the new frame's echo")
    time.sleep(0.5)
    assert len(echoes) == published + 1  # the replay published nothing
    restarted.send_signal(signal.SIGTERM)
    assert restarted.wait(20) == 0
    journal = tmp_path / "state" / "r1" / "counter.journal"
    assert sum(p.stat().st_size for p in journal.iterdir()) == 0  # the final snapshot holds it all
    again = procs.semloc(*args, name="counter3")
    status = wait_until(lambda: (s := _status(session, "counter")) and s.pid == again.pid
                        and s.state == "running" and s, 30, message="second restart")
    assert wait_until(lambda: _count(session), 10, message="count") == 35
    assert status.persistence.restored and status.persistence.replayed == 0
    subscriber.undeclare()


def test_journal_records_pass_the_inputs_check_when_replayed(tmp_path, procs, session, hub):
    """A journal is a file: a record that its source's checks refuse - the worker's check, or the robot check, as
    for a journal copied from another robot's state folder - is not applied, and is counted on its input or query
    under its reason, in the status's persistence note and the log."""
    journal = Journal(tmp_path / "state" / "r1" / "counter.journal")
    journal.open()
    for robot, message in (("r1", "5"), ("r1", "x"), ("r2", "100"), ("r1", "2")):
        journal.append("add", encode(Ack(header=Header(robot=robot), ok=True, message=message)))
    for seq, robot in enumerate(("r1", "r2", "r2", "r1")):
        journal.append("in", encode(Ack(header=Header(robot=robot, seq=seq, stamp_ns=seq + 1), ok=True)))
    journal.close()
    worker = procs.semloc("worker", WORKER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
                          str(tmp_path / "state"), "--set", "status_period_s=0.2", name="counter")
    status = wait_until(lambda: (s := _status(session, "counter")) and s.state == "running" and s, 30,
                        message="counter up")
    assert wait_until(lambda: _count(session), 10, message="count") == 5 + 2 + 2  # r1's additions and frames
    assert status.persistence.replayed == 4 and not status.persistence.restored
    assert status.inputs["query:add"].rejected_reasons == {"range": 1, "robot": 1}
    assert status.inputs["in"].rejected_reasons == {"robot": 2}
    assert "4 record(s) refused (range: 1, robot: 3)" in status.persistence.note
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(20) == 0
    assert "not a number: 'x'" in procs.log("counter")
    assert "4 record(s) refused by their inputs' checks (range: 1, robot: 3)" in procs.log("counter")


def test_an_unreadable_snapshot_is_set_aside_and_reported(tmp_path, procs, session, hub):
    state = tmp_path / "state" / "r1"
    state.mkdir(parents=True)
    garbage = b"PK\x03\x04 not a snapshot"
    (state / "counter.npz").write_bytes(garbage)
    args = ["worker", WORKER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
            str(tmp_path / "state"), "--set", "status_period_s=0.2"]
    # on_corrupt_state: stop - one line, exit 2 (the launcher does not restart), the snapshot left where it is
    stopped = procs.semloc(*args, "--set", "on_corrupt_state=stop", name="refusing")
    assert stopped.wait(60) == 2, procs.log("refusing")
    assert "counter.npz cannot be used" in procs.log("refusing")
    assert (state / "counter.npz").read_bytes() == garbage
    # the default: set aside (never overwritten), started empty, and said so in the status and the log
    worker = procs.semloc(*args, name="counter")
    status = wait_until(lambda: (s := _status(session, "counter")) and s.state == "running" and s, 30,
                        message="counter up")
    assert wait_until(lambda: _count(session) is not None and _count(session) + 1, 10, message="count") == 1
    moved = [p for p in state.iterdir() if p.name.startswith("counter.npz.corrupt-")]
    assert len(moved) == 1 and moved[0].read_bytes() == garbage
    assert status.persistence.set_aside == [str(moved[0])] and not status.persistence.restored
    assert "cannot be used" in status.persistence.note and "set aside" in status.last_error
    assert "cannot be used" in procs.log("counter")
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(20) == 0
    assert moved[0].read_bytes() == garbage  # the new snapshot went to counter.npz, beside it
    assert (state / "counter.npz").read_bytes() != garbage


def test_latency_percentiles_count_the_frames_owed_an_output_only(session):
    """A worker's latency p50/p95 (Status) are those of the inputs it owes an output: the cheap poses or odometry
    it also takes (``drives_output = False``) would otherwise pull the median down to their handlers' time."""
    worker = Worker(WorkerConfig(robot="r1", name="latency"))
    worker.session = session
    handled = []

    def slow(frame):
        time.sleep(0.03)
        handled.append(frame.header.seq)

    worker.input("frames", "semloc/r1/latency/frames", Ack, slow, policy="lossless", depth=64)
    poses = worker.input("poses", "semloc/r1/latency/poses", Ack, lambda frame: handled.append(-1),
                         policy="lossless", depth=64)
    poses.drives_output = False
    with spinning(worker):
        publishers = {name: session.declare_publisher(f"semloc/r1/latency/{name}",
                                                      congestion_control=zenoh.CongestionControl.BLOCK)
                      for name in ("frames", "poses")}
        for seq in range(10):
            publishers["frames"].put(_ack(seq))
            time.sleep(0.06)  # the poses come while the worker idles: handled at once
            for _ in range(3):
                publishers["poses"].put(_ack(seq))
            time.sleep(0.02)
        wait_until(lambda: len(handled) == 40, 10, message="all frames and poses handled")
    status = worker.status()
    assert status.processed == 40
    assert 30.0 <= status.latency_p50_ms < 1000.0   # the frames' 30 ms handler, not the poses' microseconds


def test_every_input_refuses_another_robots_frames_on_its_robots_key(session):
    """A frame whose header names another robot than its key does is refused (``robot``) on every input and
    request of the key's robot, first of all the input's checks; a key over every robot, an input's ``any_robot``
    and a foreign decoder take them all. An output's frames name the robot of its key."""
    worker = Worker(WorkerConfig(robot="r1", name="robots", outputs={"rewired": {"key": "semloc/r2/robots/out"}}))
    worker.session = session
    taken: dict[str, list[str]] = {name: [] for name in ("own", "every", "opted_out", "foreign")}
    checked: list[str] = []

    def take(name):
        return lambda frame: taken[name].append(frame.header.robot)

    def check(frame):
        checked.append(frame.header.robot)

    worker.input("own", "semloc/r1/robots/in", Ack, take("own"), policy="lossless", check=check)
    worker.input("every", "semloc/*/robots/in", Ack, take("every"), policy="lossless")
    worker.input("opted_out", "semloc/r1/robots/in", Ack, take("opted_out"), policy="lossless", any_robot=True)
    worker.input("foreign", "semloc/r1/robots/in", None, lambda item: taken["foreign"].append(item[0].header.robot),
                 policy="lossless", decoder=lambda payload: (decode(payload),))
    worker.queryable("ask", "semloc/r1/robots/ask", lambda request: request, request=Ack)
    assert worker.output("plain", "semloc/r1/robots/out").header().robot == "r1"
    assert worker.output("rewired", "semloc/r1/robots/out").header().robot == "r2"

    def ack(robot: str, seq: int) -> bytes:
        return encode(Ack(header=Header(robot=robot, seq=seq, stamp_ns=seq + 1), ok=True))

    sent = ["r1", "r2", "r1", "robot", "r1"]
    with spinning(worker):
        publisher = session.declare_publisher("semloc/r1/robots/in", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, 10, message="the worker's subscribers")
        for seq, robot in enumerate(sent):
            publisher.put(ack(robot, seq))
        wait_until(lambda: sum(i.received for i in worker._inputs) == 4 * len(sent), 10, message="every frame")
        wait_until(lambda: sum(i.processed for i in worker._inputs) == 3 * len(sent) + 3, 10, message="handled")
        replies = {(key, robot): [reply.ok is not None for reply in session.get(f"semloc/r1/robots/{key}",
                                                                                 payload=ack(robot, 0), timeout=10)]
                   for key in ("ask",) for robot in ("r1", "r2")}
    own = worker._inputs[0]
    assert taken["own"] == checked == ["r1"] * 3  # refused before the input's own check
    assert own.rejected == 2 and dict(own.rejected_reasons) == {"robot": 2}
    assert taken["every"] == taken["opted_out"] == taken["foreign"] == sent
    assert replies == {("ask", "r1"): [True], ("ask", "r2"): [False]}
    assert dict(worker._queryables[0].rejected_reasons) == {"robot": 1}



def test_a_recoverable_input_keeps_one_count_per_publisher(session):
    """The live count of a recoverable input keys each publisher by (zid, eid): zenoh hands every sample its own
    EntityGlobalId object, neither equal nor hashing alike, so keyed by those the count grew a key a frame (memory
    without bound on a long run) and a recovered frame was never seen behind a live one."""
    from services.bus import FramePublisher

    worker = Worker(WorkerConfig(robot="r1", name="recovering"))
    worker.session = session
    handled: list[int] = []
    entry = worker.input("in", "semloc/r1/recovering/in", Ack, lambda frame: handled.append(frame.header.seq),
                         policy="lossless", depth=512, recover=True)
    with spinning(worker):
        publisher = FramePublisher(session, "semloc/r1/recovering/in", recover=100)
        for seq in range(200):
            publisher.put_frame(Ack(header=Header(robot="r1", stream="in", seq=seq, stamp_ns=1000 + seq), ok=True))
        wait_until(lambda: len(handled) == 200 and entry.live == 200, 20, message="200 frames handled")
    assert len(entry.live_sn) == 1 and list(entry.live_sn.values()) == [199], entry.live_sn  # from 0
