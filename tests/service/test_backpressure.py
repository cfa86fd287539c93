"""No head-of-line blocking (issue 28): a slow lossless subscriber neither slows the publisher nor a fast subscriber
next to it; its overflow is counted and its memory bounded. Real sink workers over zenoh on loopback; speed itself
is measured by benchmarks/backpressure.py, this test only compares counts."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from schemas import Header, Image, Status, keys
from services.bus import FramePublisher, query
from tests.service.conftest import read_jsonl, wait_until

pytestmark = pytest.mark.service
FRAMES, DEPTH, SLOW_S = 300, 8, 0.1
SHAPE = (480, 640, 3)


def _statuses(session) -> dict[str, Status]:
    frames = query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0, every_reply=True)
    return {frame.worker: frame for frame in frames}


def _private_resident(pid: int) -> int:
    """Resident bytes less zenoh's shared-memory pool pages (the publisher's memory, mapped by its subscribers)."""
    fields = dict.fromkeys(("VmRSS", "RssShmem"), 0)
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in fields:
            fields[name] = int(value.split()[0]) << 10
    return fields["VmRSS"] - fields["RssShmem"]


def test_a_slow_lossless_subscriber_holds_back_neither_the_publisher_nor_a_fast_one(tmp_path, procs, session, hub):
    key = keys.camera_image("r1")
    slow_log = tmp_path / "slow.jsonl"
    common = ["--connect", hub, "--robot", "r1", "--set", f"key={key}", "--log-level", "WARNING"]
    slow = procs.semloc("worker", "sink", "--name", "slow", "--set", "policy=lossless", "--set", f"depth={DEPTH}",
                        "--set", f"process_delay_s={SLOW_S}", "--set", f"log_path={slow_log}", *common, name="slow")
    procs.semloc("worker", "sink", "--name", "fast", "--set", "policy=latest", "--set", "depth=2", *common, name="fast")
    # Both subscriptions known to this session (a publisher's matching status says only "at least one"): a sink's
    # status lists its input once it declared its subscriber, and zenoh sends a declaration ahead of any later reply
    # on the sink's link to this session (at its highest priority).
    def subscribed():
        found = _statuses(session)
        return all(name in found and "frames" in found[name].inputs for name in ("slow", "fast"))

    wait_until(subscribed, 60, message=lambda: f"both sinks subscribed: {_statuses(session)}")
    publisher = FramePublisher(session, key)
    baseline = _private_resident(slow.pid)
    peak = baseline
    pixels = np.random.default_rng(0).integers(0, 256, SHAPE, dtype=np.uint8)
    start = time.monotonic()
    for seq in range(FRAMES):  # ~60 frames/s: six times what the slow subscriber handles
        publisher.put_frame(Image.from_pixels(Header(robot="r1", stream=key, seq=seq, stamp_ns=seq + 1), pixels))
        if seq % 20 == 0:
            peak = max(peak, _private_resident(slow.pid))
        time.sleep(max(0.0, start + (seq + 1) / 60 - time.monotonic()))
    # Sent: had the slow subscriber pushed back, the publisher could not have finished before it handled most frames.
    at_end = _statuses(session)["slow"]
    assert at_end.processed < FRAMES / 2, at_end

    def settled():
        found = _statuses(session)
        fast, slow_status = found.get("fast"), found.get("slow")
        done = (fast and slow_status and fast.received == FRAMES and slow_status.received == FRAMES
                and slow_status.processed + slow_status.overflow == FRAMES)
        return found if done else None

    found = wait_until(settled, 60, message=lambda: f"every frame counted: {_statuses(session)}")
    fast, slow_status = found["fast"], found["slow"]
    # The fast subscriber got every frame; the slow one handled what its queue held and counted the rest as its own.
    assert fast.overflow == 0 and slow_status.dropped == 0 and slow_status.rejected == 0
    assert slow_status.overflow == slow_status.inputs["frames"].overflow > FRAMES / 2
    assert fast.received > 2 * slow_status.processed
    handled = [record["seq"] for record in read_jsonl(slow_log)]
    assert handled == sorted(handled) and handled[:DEPTH] == list(range(DEPTH))  # in order, the first ones kept
    # Its memory: at most its queue (depth frames waiting plus the one in the handler) and a margin.
    frame_bytes = int(np.prod(SHAPE))
    assert peak - baseline <= (DEPTH + 1) * frame_bytes + (50 << 20), (peak - baseline) / 2**20
