"""Live frames behind a recovered backlog (services/runtime.py ``Input``): a sink worker whose lossless input is
recoverable, depth 16 and ~20 ms a frame, fed at 10 Hz by a recoverable publisher in the test's process through
tests/e2e/relay.py; the link cut for 10 s. When it returns, the gap's 100 frames come back first and take ~2 s to
handle; the ~20 live frames that arrive meanwhile wait behind them (docs/results/2026-12-07-backlog-live.md). The
same, deterministic: ``Input`` fed fake samples, its handler standing for the time that passes."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest
import zenoh

from schemas import Ack, Header, Status, encode
from services import runtime
from services.bus import BusConfig, FramePublisher, free_port, open_session, query
from services.runtime import Input, Worker, WorkerConfig
from tests.e2e.relay import Relay
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

KEY = "semloc/r1/heat/in"
RATE_HZ, BEFORE_S, CUT_S, AFTER_S = 10.0, 3.0, 10.0, 8.0
FRAME_BYTES = 4000  # (an Ack's message holds at most 4096 characters)


class _Feed:
    """An in-process worker's recoverable lossless input (depth 16) fed fake samples of one publisher, as zenoh
    delivers them: a live frame reaches the counting subscription and the input, a recovered one the input only.
    ``during(handled)`` runs in the handler after each frame: the live frames that come meanwhile."""

    def __init__(self, depth: int = 16):
        self.worker = Worker(WorkerConfig(robot="r1", name="heat"))  # its thread owns it: no handling on zenoh's
        self.handled: list[int] = []
        self.during = lambda handled: None
        self.entry = Input(self.worker, "heatmaps", KEY, Ack, self.handle, "lossless", depth)
        self.entry.recover_handles = ("the publisher's cache",)  # recoverable: what the counting one missed is
        self.worker._inputs.append(self.entry)
        self.next_live = 0
        self.most_waiting_live = 0  # the most live frames not behind a backlog that ever waited

    def handle(self, frame: Ack) -> None:
        self.handled.append(frame.header.seq)
        self.during(len(self.handled))
        entry = self.entry
        self.most_waiting_live = max(self.most_waiting_live, entry.waiting - entry.backlog - entry.behind)

    @staticmethod
    def sample(seq: int):
        payload = encode(Ack(header=Header(robot="r1", stream=KEY, seq=seq, stamp_ns=1 + seq), ok=True))
        info = SimpleNamespace(source_id=SimpleNamespace(zid="z", eid=1), source_sn=seq)
        return SimpleNamespace(payload=zenoh.ZBytes(payload), source_info=info, key_expr=KEY, attachment=None)

    def live(self, count: int = 1) -> None:
        for _ in range(count):
            sample = self.sample(self.next_live)
            self.next_live += 1
            self.entry._on_live(sample)
            self.entry._on_sample(sample)

    def cut(self, frames: int) -> None:
        """``frames`` sent while the link was cut: the first live frame after it reaches the counting subscription
        at once, the recoverable one hands the gap's frames over first (from the cache), then that live one."""
        gap, self.next_live = range(self.next_live, self.next_live + frames), self.next_live + frames
        first = self.sample(self.next_live)
        self.entry._on_live(first)
        for seq in gap:
            self.entry._on_sample(self.sample(seq))
        self.entry._on_sample(first)
        self.next_live += 1

    def drain(self) -> None:
        while self.entry.queue:
            self.worker.spin_once(0)


def test_live_frames_behind_a_recovered_backlog_take_no_room_of_the_depth():
    """A 10 s cut at 10 Hz, 20 ms a frame: the gap's 100 frames come back, and while they are handled a live frame
    comes every 5 (21 behind them in all, more than the depth of 16): every frame handled, in order, none refused
    (before: 5 refused)."""
    feed = _Feed()
    feed.live(3)
    feed.drain()
    feed.during = lambda handled: feed.live() if handled <= 3 + 100 and handled % 5 == 0 else None
    feed.cut(100)
    feed.drain()
    entry = feed.entry
    assert entry.received - entry.live == 100  # all of the gap taken as recovered
    assert (entry.overflow, entry.missed) == (0, 0)
    assert feed.handled == list(range(feed.next_live)) and feed.next_live == 3 + 100 + 1 + 20
    assert (entry.backlog, entry.behind, entry.backlog_bytes, entry.held) == (0, 0, 0, 0)  # all given back


def test_a_worker_too_slow_for_the_stream_still_refuses_beyond_its_depth():
    """Without a backlog, 20 live frames that come while the worker is busy: 16 wait, 4 refused. With one of 10
    frames, a worker too slow for the stream (3 live frames come during each frame it handles): the 30 that came
    behind the recovered ones wait; the live ones that come after those are handled count against the depth again,
    and are refused beyond it."""
    feed = _Feed()
    feed.live(20)
    assert (feed.entry.overflow, feed.entry.waiting) == (4, 16)
    feed.drain()
    assert feed.handled == list(range(16))

    feed = _Feed()
    feed.live(1)
    feed.drain()
    feed.during = lambda handled: feed.live(3) if feed.next_live < 200 else None
    feed.cut(10)
    feed.drain()
    entry = feed.entry
    behind = 1 + 10 * 3  # the first live one after the gap, and those that came while the gap's were handled
    assert feed.handled[: 1 + 10 + behind] == list(range(1 + 10 + behind))
    assert feed.most_waiting_live == entry.depth and entry.overflow > 0 and entry.missed == 0
    assert entry.overflow + len(feed.handled) == feed.next_live  # each refused one counted


def test_live_frames_behind_a_backlog_stay_within_its_byte_budget(monkeypatch):
    """The recovered frames and the live ones behind them share RECOVER_BUDGET_BYTES: with room for 40 frames, the
    gap's 10 and 5 live frames during each of those handled: the live ones behind take the budget's room, not the
    depth's (38 in a row, more than 16), and those that find it full are refused (``overflow``); the recovered ones
    all handled."""
    size = len(_Feed.sample(100).payload)  # (every frame here as long: numbers below 128)
    monkeypatch.setattr(runtime, "RECOVER_BUDGET_BYTES", 40 * size)
    feed = _Feed()
    feed.live(1)
    feed.drain()
    budget_used: list[int] = []
    feed.during = lambda handled: (budget_used.append(feed.entry.backlog_bytes),
                                   feed.live(5) if handled <= 1 + 10 else None)
    feed.cut(10)
    feed.drain()
    entry = feed.entry
    assert entry.missed == 0 and max(budget_used) <= 40 * size
    assert feed.handled[:49] == list(range(49)) and 49 not in feed.handled  # 11-48 live, behind the gap's 1-10
    assert entry.overflow + len(feed.handled) == feed.next_live > len(feed.handled)


def _status(session) -> Status | None:
    frames = query(session, "semloc/r1/heat/status", reply_type=Status, timeout=0.5)
    return frames[0] if frames else None


def measure(procs, depth: int = 16, handler_s: float = 0.02, cut_s: float = CUT_S) -> dict:
    """Frames sent at RATE_HZ for BEFORE_S, through a cut of ``cut_s``, and AFTER_S after it: the sink's counters
    once every frame sent is accounted for (handled, refused or missed)."""
    port = free_port()
    with open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session, Relay(port) as relay:
        worker = procs.semloc("worker", "sink", "--connect", f"tcp/127.0.0.1:{relay.port}", "--robot", "r1",
                              "--name", "heat", "--set", f"key={KEY}", "--set", "policy=lossless",
                              "--set", f"depth={depth}", "--set", f"process_delay_s={handler_s}",
                              "--set", "inputs.frames.recover=true", "--set", "status_period_s=0.2",
                              "--log-level", "WARNING", name="heat")
        wait_until(lambda: (s := _status(session)) and s.pid == worker.pid and s.state == "running", 60,
                   message="the sink running")
        publisher = FramePublisher(session, KEY, recover=int(RATE_HZ * (cut_s + 5)))
        sent = 0

        def play(seconds: float) -> None:
            nonlocal sent
            start = time.monotonic()
            for _ in range(int(seconds * RATE_HZ)):
                publisher.put_frame(Ack(header=Header(robot="r1", stream=KEY, seq=sent, stamp_ns=time.time_ns()),
                                        ok=True, message="x" * FRAME_BYTES))
                sent += 1
                time.sleep(max(0.0, start + sent / RATE_HZ - time.monotonic()))

        player = threading.Thread(target=lambda: play(BEFORE_S + cut_s + AFTER_S))
        player.start()
        time.sleep(BEFORE_S)
        relay.cut("refuse")
        time.sleep(cut_s)
        relay.restore()
        player.join()

        def settled():
            stats = (s := _status(session)) and s.inputs["frames"]
            return stats if stats and stats.processed + stats.overflow + stats.missed >= sent and not stats.queued \
                else None

        stats = wait_until(settled, 60, message=lambda: f"{sent} frames accounted for: {_status(session)}")
        publisher.undeclare()
    return {"sent": sent, "processed": stats.processed, "recovered": stats.recovered, "refused": stats.overflow,
            "missed": stats.missed, "handler_ms": stats.handler_ms}


def test_live_frames_behind_a_recovered_backlog_are_not_refused(procs):
    """A 10 s cut at 10 Hz: the gap's ~100 frames come back and the live ones behind them are handled too, none
    refused (before: the live frames beyond the depth of 16 that came while the gap's were handled were refused)."""
    result = measure(procs)
    assert result["recovered"] >= CUT_S * RATE_HZ * 0.8, result
    assert (result["refused"], result["missed"], result["processed"]) == (0, 0, result["sent"]), result


if __name__ == "__main__":  # python -m tests.service.test_backlog_live [RUNS]: the figures, one line a run
    import json
    import os
    import sys
    import tempfile
    from pathlib import Path

    from tests.service.conftest import Processes

    for _ in range(int(sys.argv[1]) if len(sys.argv) > 1 else 1):
        processes = Processes(Path(tempfile.mkdtemp(prefix="backlog-live-")))
        try:
            print(json.dumps({"load": os.getloadavg()[0], **measure(processes)}), flush=True)
        finally:
            processes.cleanup()
