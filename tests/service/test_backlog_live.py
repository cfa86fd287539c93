"""Live frames behind a recovered backlog (services/runtime.py ``Input``): a sink worker whose lossless input is
recoverable, depth 16 and ~20 ms a frame, fed at 10 Hz by a recoverable publisher in the test's process through
tests/e2e/relay.py; the link cut for 10 s. When it returns, the gap's 100 frames come back first and take ~2 s to
handle; the ~20 live frames that arrive meanwhile wait behind them (docs/results/2026-12-07-backlog-live.md)."""

from __future__ import annotations

import threading
import time

import pytest

from schemas import Ack, Header, Status
from services.bus import BusConfig, FramePublisher, free_port, open_session, query
from tests.e2e.relay import Relay
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

KEY = "semloc/r1/heat/in"
RATE_HZ, BEFORE_S, CUT_S, AFTER_S = 10.0, 3.0, 10.0, 8.0
FRAME_BYTES = 4000  # (an Ack's message holds at most 4096 characters)


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
