"""A worker restored from its state asks the recoverable publishers' caches only for about what its state misses
(docs/deploy.md, "When the link drops"; services/bus.py ``CacheHistory``): the counter of
tests/service/workers_for_tests.py, its input recoverable, fed by a recoverable publisher in the test's process
keeping 300 frames; before, the whole cache came back over the link and the runtime dropped what the state held
(docs/results/2026-12-07-restart-fetch.md)."""

from __future__ import annotations

import contextlib
import signal
import time
from pathlib import Path

import pytest

from schemas import Ack, Header, decode
from services.bus import HISTORY_MARGIN_S, FramePublisher
from tests.service.conftest import wait_until
from tests.service.test_restored_history import KEY, WORKER, _count, _running, _status

pytestmark = pytest.mark.service

HELD = 300  # frames counted before the stop: the publisher's cache holds them all
MISSED = 10  # sent while the worker is down
SPACING_S = 0.01  # between the held frames: 3 s of them, of which the cache sends the last HISTORY_MARGIN_S


def _args(connect: str, state: Path) -> list[str]:
    """The counter's command line: its input recoverable, its state in ``state``, snapshots at a stop only."""
    return ["worker", WORKER, "--connect", connect, "--robot", "r1", "--name", "counter", "--state-dir", str(state),
            "--set", "inputs.in.recover=true", "--set", "status_period_s=0.2", "--set", "snapshot_period_s=1000",
            "--set", "journal_replay_s=1000"]


def _put(publisher: FramePublisher, seqs, ahead_s: float) -> None:
    """Frames of the stream ``KEY`` (as a semloc output's), each stamped with the wall clock ``ahead_s`` ahead: a
    capturing clock ahead of the publisher's."""
    for seq in seqs:
        stamp = time.time_ns() + int(ahead_s * 1e9)
        publisher.put_frame(Ack(header=Header(robot="r1", stream=KEY, seq=seq, stamp_ns=stamp), ok=True,
                                message="x" * 4000))  # 4 KB
        time.sleep(SPACING_S)


def _wait_subscribed(session, key: str) -> None:
    """Until a subscription to ``key`` is known to ``session``: a plain publisher's matching status there (a
    recoverable publisher, zenoh-ext's, has none)."""
    probe = session.declare_publisher(key)
    try:
        wait_until(lambda: probe.matching_status.matching, 10, message=f"a subscriber on {key} known to the session")
    finally:
        probe.undeclare()


def _cached_frames(session):
    """A recoverable publisher of ``KEY`` whose cache holds frames 0-9, and how to put the next ones."""
    publisher = FramePublisher(session, KEY, recover=50)

    def put(seq: int) -> None:
        publisher.put_frame(Ack(header=Header(robot="r1", stream=KEY, seq=seq, stamp_ns=time.time_ns()), ok=True))

    for seq in range(10):
        put(seq)
    return publisher, put


@pytest.mark.parametrize("ahead_s", [0.0, 10.0])
def test_a_restored_worker_is_sent_what_it_misses_not_the_whole_cache(tmp_path, procs, session, hub, ahead_s):
    """300 frames counted over 3 s, the worker stopped (its snapshot holds them), 10 sent while it is down: restarted,
    it counts those 10, in order, and the cache answers it at most a third of the 300 it holds already (those published
    from HISTORY_MARGIN_S before the newest stamp held; before: all 300, dropped as already held). Stamped 10 s ahead
    of the publisher's clock (more than the margin: the time asked for misses the 10), the answer does not reach a frame
    held, so the rest is asked for: the 10 still come, and the 300 with them."""
    args = _args(hub, tmp_path / "state")
    echoes: list[int] = []  # the sequence numbers counted, in the order counted (each echo carries its frame's stamp)
    stamps: dict[int, int] = {}
    subscriber = session.declare_subscriber(
        "semloc/r1/counter/echo", lambda s: echoes.append(decode(s.payload.to_bytes(), expected=Ack).header.stamp_ns))
    publisher = FramePublisher(session, KEY, recover=HELD + MISSED)
    original = publisher.put_frame
    publisher.put_frame = lambda frame: (stamps.setdefault(frame.header.stamp_ns, frame.header.seq), original(frame))
    worker = procs.semloc(*args, name="counter")
    _running(session, worker)
    _put(publisher, range(HELD), ahead_s)
    wait_until(lambda: _count(session) == HELD, 30, message="the frames counted")
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(20) == 0
    time.sleep(HISTORY_MARGIN_S)  # the frames sent while it is down: after the margin of the newest held
    _put(publisher, range(HELD, HELD + MISSED), ahead_s)

    restarted = procs.semloc(*args, name="counter2")
    _running(session, restarted)
    wait_until(lambda: _count(session) == HELD + MISSED, 20,
               message=lambda: f"{HELD + MISSED} frames counted (got {_count(session)})")
    wait_until(lambda: len(echoes) >= HELD + MISSED, 10, message="the echoes")
    stats = _status(session).inputs["in"]
    assert [stamps[stamp] for stamp in echoes] == list(range(HELD + MISSED))  # each once, in order
    assert (stats.recovered, stats.missed) == (MISSED, 0), stats
    if ahead_s < HISTORY_MARGIN_S:
        assert stats.already_held <= HELD // 3, stats
    else:  # the time asked for missed the frames: the rest of the cache was asked for
        assert stats.already_held == HELD, stats
    subscriber.undeclare()
    publisher.undeclare()


def test_a_live_sample_before_its_publishers_token_waits_for_its_cache(session, hub):
    """A publisher whose liveliness token has not come (or never does: here it declares none) while its live samples
    do: its first live sample has its cache asked, and waits behind the answer: a frame of the gap comes before it,
    not after (the runtime would then have ended the state's check on the live one and taken held frames as new)."""
    import zenoh
    import zenoh.ext

    from services.bus import BusConfig, CacheHistory, encode, open_session

    publisher = zenoh.ext.declare_advanced_publisher(  # a recoverable publisher without its token
        session, KEY, cache=zenoh.ext.CacheConfig(50),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None))

    def put(seq: int) -> None:
        frame = Ack(header=Header(robot="r1", stream=KEY, seq=seq, stamp_ns=time.time_ns()), ok=True)
        publisher.put(encode(frame), timestamp=session.new_timestamp())

    for seq in range(10):
        put(seq)
    got: list[int] = []
    with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as restored:
        history = CacheHistory(restored, KEY, lambda s: got.append(decode(s.payload.to_bytes()).header.seq))
        subscriber = restored.declare_subscriber(KEY, history.on_sample)
        _wait_subscribed(session, KEY)
        history.start(True, {("r1", KEY): 0})  # the state holds nothing of these: all 10 are missed
        put(10)
        wait_until(lambda: 10 in got, 10, message=lambda: f"the live frame (got {got})")
        subscriber.undeclare()
        history.undeclare()
    publisher.undeclare()
    assert got == list(range(11))


@contextlib.contextmanager
def _restored_history(session, hub, got: list, prepare=lambda history: None, handed: list | None = None):
    """A restored subscriber's CacheHistory of ``KEY`` (its seqs into ``got``) in a session of its own, started with
    nothing of the stream held (every frame cached is missed); ``prepare`` runs on it first, ``handed`` counts the
    live samples the subscription handed over."""
    from services.bus import BusConfig, CacheHistory, open_session

    with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as restored:
        history = CacheHistory(restored, KEY, lambda s: got.append(decode(s.payload.to_bytes()).header.seq))
        prepare(history)

        def on_sample(sample) -> None:
            history.on_sample(sample)
            if handed is not None:
                handed.append(1)

        subscriber = restored.declare_subscriber(KEY, on_sample)
        _wait_subscribed(session, KEY)
        history.start(True, {("r1", KEY): 0})
        try:
            yield history
        finally:
            subscriber.undeclare()
            history.undeclare()


def test_a_live_sample_right_after_the_answer_comes_after_it(session, hub):
    """A live sample that arrives once a cache's answer is in but before it is passed on (the asking thread slow to
    go on: a loaded machine) waits behind it. Before, it went first, and the whole answer was then dropped as passed
    already (its numbers below the live one's), uncounted: a mapper restarted during a cut integrated 78 of 120
    heatmaps, none of the gap recovered (docs/results/2026-12-07-cut-restart-flake.md)."""
    import threading

    publisher, put = _cached_frames(session)
    got: list[int] = []
    returned: list[int] = []  # the live samples the subscription has handed over

    def slow_drain(history) -> None:
        drain = history._drain

        def slowed() -> None:  # the asking thread, the answer in: a live sample comes before it goes on
            if threading.current_thread().name == "semloc-history" and not returned:
                put(10)
                wait_until(lambda: returned, 10, message="the live sample handed over")
            drain()

        history._drain = slowed

    with _restored_history(session, hub, got, slow_drain, returned):
        wait_until(lambda: 10 in got, 10, message=lambda: f"the live frame (got {got})")
    publisher.undeclare()
    assert got == list(range(11))


def test_a_cache_that_answered_nothing_is_asked_again_when_heard(session, hub):
    """A cache asked while it cannot be reached (a restarted worker asking during a link cut zenoh had not noticed
    yet: its publisher's token still seen, the answer 0 samples in 0.0 s; results/2026-12-07-loopclosure-restart.md)
    is asked again when its publisher is next heard. Before, it was asked once: the frames it kept were never asked
    for again, and the first live one passed alone."""
    publisher, put = _cached_frames(session)
    got: list[int] = []
    unreachable, asked = [True], []

    def cut(history) -> None:
        get = history._get

        def cut_get(selector: str) -> list:  # the cut: nothing comes back
            asked.append(selector)
            return [] if unreachable[0] else get(selector)

        history._get = cut_get

    with _restored_history(session, hub, got, cut) as history:
        wait_until(lambda: asked and history._asking == 0, 10, message="the cache asked, and its answer in")
        unreachable[0] = False  # the link is back
        put(10)
        wait_until(lambda: 10 in got, 10, message=lambda: f"the live frame (got {got})")
    publisher.undeclare()
    assert got == list(range(11))


def measure(root, rate_bps: float, live_s: float = 15.0) -> dict:
    """The test's restart (no clock ahead) with the worker behind tests/e2e/relay.py at ``rate_bps`` (a thin link),
    frames sent at 10 Hz from its restart on for ``live_s``: what the cache's answer cost (the worker's log: samples,
    kB, seconds, live frames waiting behind it), its counters, and how late the live frames were counted (the echo's
    arrival less the frame's stamp: the link both ways and the wait; first 5 s and the rest, median and max)."""
    import statistics
    import threading

    from services.bus import BusConfig, free_port, open_session
    from tests.e2e.relay import Relay
    from tests.service.conftest import Processes

    root, port = Path(root), free_port()
    procs, late = Processes(root), []
    with open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session, Relay(port, rate_bps=rate_bps) as relay:
        args = _args(f"tcp/127.0.0.1:{relay.port}", root / "state")
        echo = session.declare_subscriber("semloc/r1/counter/echo", lambda s: late.append(
            (time.time(), time.time() - decode(s.payload.to_bytes(), expected=Ack).header.stamp_ns * 1e-9)))
        publisher = FramePublisher(session, KEY, recover=HELD + MISSED)
        try:
            worker = procs.semloc(*args, name="counter")
            _running(session, worker)
            _put(publisher, range(HELD), 0.0)
            wait_until(lambda: _count(session) == HELD, 120, message="the frames counted")
            worker.send_signal(signal.SIGTERM)
            assert worker.wait(20) == 0
            time.sleep(HISTORY_MARGIN_S)
            _put(publisher, range(HELD, HELD + MISSED), 0.0)
            restarted = procs.semloc(*args, name="counter2")
            started = time.time()
            live = threading.Thread(target=lambda: [(_put(publisher, [HELD + MISSED + i], 0.0), time.sleep(0.09))
                                                    for i in range(int(live_s * 10))])
            live.start()
            live.join()
            time.sleep(3.0)
            stats = _running(session, restarted).inputs["in"]
        finally:
            echo.undeclare()
            publisher.undeclare()
            procs.cleanup()
    after = [(at - started, lateness) for at, lateness in late if at >= started]
    spread = [[round(statistics.median(part), 2), round(max(part), 2)] if part else None
              for part in ([v for t, v in after if t < 5], [v for t, v in after if t >= 5])]
    return {"history": [line.split("semloc.bus: ", 1)[1] for line in procs.log("counter2").splitlines()
                        if "history of" in line],
            "counted": stats.processed, "expected": MISSED + int(live_s * 10), "recovered": stats.recovered,
            "already_held": stats.already_held, "missed": stats.missed, "late_first_5s": spread[0],
            "late_after": spread[1]}


if __name__ == "__main__":  # python -m tests.service.test_restore_fetch 1,5 (Mbit/s)
    import json
    import sys
    import tempfile

    for rate in sys.argv[1].split(","):
        print(f"{rate} Mbit/s", json.dumps(measure(tempfile.mkdtemp(prefix="restore-fetch-"), float(rate) * 1e6)),
              flush=True)
