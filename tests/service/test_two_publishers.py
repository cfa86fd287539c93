"""Two publishers on one stream (docs/runtime.md, "Status, liveliness, health"): their numbers interleave, which is
no loss on the way; the consumer names the stream they share until only one remains. A real sink worker over zenoh on
loopback, fed by the publisher every worker output uses (services.bus.FramePublisher)."""

from __future__ import annotations

import time

import pytest

from schemas import Ack, Header, Status, keys
from services.bus import FramePublisher, query
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service
SHARED = "semloc/r1/test/shared"
RATE_HZ = 20.0


def _sink_status(session) -> Status | None:
    frames = query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0, every_reply=True)
    return next((frame for frame in frames if frame.worker == "sink"), None)


def test_two_publishers_on_one_stream_are_named_not_counted_as_lost(procs, session, hub):
    procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "sink", "--set", f"key={SHARED}",
                 "--set", "status_period_s=0.25", name="sink")
    wait_until(lambda: (s := _sink_status(session)) is not None and s.state == "running", 60,
               message=lambda: f"the sink running: {_sink_status(session)}")
    # an old process still numbering from 5000, a new one from 0: interleaved, each jump between them is a "gap"
    old, new = FramePublisher(session, SHARED), FramePublisher(session, SHARED)
    wait_until(lambda: old.publisher.matching_status.matching, 10, message="the sink subscribed")
    sent = {"old": 0, "new": 0}

    def play(seconds: float, publishers: dict[str, tuple[FramePublisher, int]], until=None) -> Status | None:
        """Each of ``publishers`` (name: (publisher, first number)) sends at RATE_HZ for ``seconds`` or until
        ``until(status)``; the sink's last status."""
        status, start, next_poll = None, time.monotonic(), time.monotonic() + 0.5
        while time.monotonic() < start + seconds:
            for name, (publisher, first) in publishers.items():
                seq = first + sent[name]
                publisher.put_frame(Ack(header=Header(robot="r1", stream=SHARED, seq=seq, stamp_ns=seq + 1), ok=True))
                sent[name] += 1
            if time.monotonic() >= next_poll:
                status, next_poll = _sink_status(session), time.monotonic() + 0.5
                if status is not None and until is not None and until(status):
                    break
            time.sleep(1 / RATE_HZ)
        return status

    # A publisher restarted (one replaced by the old one): one after the other, not two at once.
    replaced = FramePublisher(session, SHARED)
    sent["replaced"] = 0
    play(1.0, {"replaced": (replaced, 0)})
    replaced.undeclare()
    seen = []
    play(3.0, {"old": (old, 5000)}, until=lambda s: seen.append(s) and False)
    assert seen and all(s.state == "running" for s in seen), [(s.state, s.state_reason) for s in seen]

    named = lambda s: s.state == "degraded" and f"2 publishers on {SHARED}" in s.state_reason  # noqa: E731
    both = {"old": (old, 5000), "new": (new, 0)}
    status = play(20.0, both, until=named)
    assert status is not None and named(status), status and (status.state, status.state_reason)
    # everything sent arrived (loopback, a lossless queue of 1024): not one frame lost on the way
    arrived = lambda s: s.inputs["frames"].received == sum(sent.values())  # noqa: E731
    status = wait_until(lambda: (s := _sink_status(session)) and arrived(s) and s, 10,
                        message=lambda: f"{sum(sent.values())} frames received: {_sink_status(session)}")
    assert status.inputs["frames"].lost_in_transit == 0, status.inputs["frames"]

    # The new one alone: running again once the old one's frames leave the window, still nothing lost.
    old.undeclare()
    status = play(30.0, {"new": both["new"]}, until=lambda s: s.state == "running")
    assert status is not None and status.state == "running", status and (status.state, status.state_reason)
    assert status.inputs["frames"].lost_in_transit == 0, status.inputs["frames"]
    new.undeclare()
