"""Acceptance: >= 1,000 hostile payloads into a worker's input: it stays up, counts each one as rejected, and
processes the valid frame sent afterwards."""

from __future__ import annotations

import struct

import msgpack
import numpy as np
import pytest
import zenoh

from schemas import Header, Image, Odometry, Pose2D, Status, encode
from services.bus import query
from tests.service.conftest import repack, wait_until

pytestmark = pytest.mark.service
KEY = "semloc/r1/hostile/in"
HEADER = Header(robot="r1", stream="hostile", seq=1, stamp_ns=1)


def hostile_payloads(count: int, seed: int = 1) -> list[bytes]:
    rng = np.random.default_rng(seed)
    image = Image.from_pixels(HEADER, rng.integers(0, 256, (16, 16, 3), dtype=np.uint8))
    image_bytes = encode(image)
    odometry = Odometry(header=HEADER, v=1.0, omega=0.0, dt=0.1, covariance=np.eye(3))
    odometry_bytes = encode(odometry)

    def array(body):
        return body["images"][0]["data"]

    def nan_covariance() -> bytes:
        data = bytearray(odometry_bytes)
        struct.pack_into("<d", data, len(data) - 72 + 8 * int(rng.integers(0, 9)), float("nan"))
        return bytes(data)

    def wrong_dtype() -> dict:
        dtype = str(rng.choice(["float32", "int16", "uint16", "float64"]))
        return {"dtype": dtype, "shape": [16, 16 * 3 // np.dtype(dtype).itemsize]}

    makers = [
        lambda: bytes(rng.integers(0, 256, int(rng.integers(0, 2000)), dtype=np.uint8)),  # random bytes
        lambda: image_bytes[: int(rng.integers(0, len(image_bytes) - 1))],  # truncated
        lambda: repack(image, lambda b: b.update(schema=f"semloc.Unknown{int(rng.integers(1e6))}")),
        lambda: repack(image, lambda b: b.update(version=int(rng.integers(2, 1000)))),
        lambda: repack(image, lambda b: array(b).update(**wrong_dtype())),  # wrong dtype, same byte count
        lambda: repack(image, lambda b: array(b).update(shape=[16, 16, int(rng.integers(4, 9))])),  # shape/bytes
        lambda: repack(image, lambda b: array(b).update(shape=[10_000, 10_000], nbytes=100_000_000)),  # 100 MB
        nan_covariance,  # NaN where forbidden
        lambda: repack(Pose2D(header=HEADER, x=0, y=0, theta=0), lambda b: b.update(x=float("inf"))),
        lambda: repack(odometry, lambda b: b.update(dt=-1.0)),
        lambda: struct.pack("<I", 0xFFFFFFFF) + bytes(int(rng.integers(0, 64))),
        lambda: struct.pack("<I", 3) + msgpack.packb([1, 2]),
    ]
    return [makers[i % len(makers)]() for i in range(count)]


def test_hostile_payloads_are_counted_and_the_worker_survives(procs, session, hub):
    worker = procs.semloc("worker", "sink", "--connect", hub, "--robot", "r1", "--name", "victim",
                          "--set", f"key={KEY}",
                          "--set", "status_period_s=0.2", "--log-level", "WARNING", name="victim")

    def victim_status():
        assert worker.poll() is None, procs.log("victim")
        frames = query(session, "semloc/r1/victim/status", reply_type=Status, timeout=0.5)
        return frames[0] if frames else None

    wait_until(victim_status, 30, message="victim up")
    publisher = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    bad = hostile_payloads(1200)
    for payload in bad:
        publisher.put(payload)
    publisher.put(encode(Odometry(header=HEADER, v=0.2, omega=0.1, dt=0.05)))
    seen = []

    def all_handled():
        seen.append(s := victim_status())
        return s if s and s.received >= len(bad) + 1 and s.processed + s.rejected + s.errors + s.dropped == s.received \
            else None

    def last_seen():
        s = next((s for s in reversed(seen) if s), None)
        counts = s and {k: getattr(s, k) for k in ("state", "received", "processed", "rejected", "errors", "dropped")}
        return f"all payloads received and handled; last status {counts}\n{procs.log('victim')[-2000:]}"

    status = wait_until(all_handled, 30, message=last_seen)
    assert worker.poll() is None and status.state == "running"
    assert status.rejected == len(bad)
    assert status.processed == 1 and status.errors == 0 and status.dropped == 0, (status, status.last_error)
    assert status.inputs["frames"].rejected == len(bad)
    reasons = status.inputs["frames"].rejected_reasons
    assert sum(reasons.values()) == len(bad)
    assert {"decode", "schema", "array", "invalid"} <= set(reasons), reasons
