"""Sink: subscribes to a key and counts, checks and optionally records what arrives (tests, `semloc status`)."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, Field

from schemas import Frame
from services.runtime import Policy, Worker, WorkerConfig


def arrays(value) -> list[np.ndarray]:
    """Every array of a frame, in field order (depth first)."""
    if isinstance(value, np.ndarray):
        return [value]
    if isinstance(value, BaseModel):
        return [a for name in type(value).model_fields for a in arrays(getattr(value, name))]
    if isinstance(value, (list, tuple)):
        return [a for item in value for a in arrays(item)]
    if isinstance(value, dict):
        return [a for item in value.values() for a in arrays(item)]
    return []


class SinkConfig(WorkerConfig):
    key: str = Field("semloc/**", description="key expression to subscribe to")
    policy: Policy = Field("lossless", description="queue policy of the input")
    depth: int = Field(1024, ge=1, description="queue depth")
    log_path: str | None = Field(None, description="append one JSON line per frame (schema, seq, stamp, sha256)")
    process_delay_s: float = Field(0.0, ge=0, description="simulated processing time per frame")


class Sink(Worker):
    """Counts every frame on a key; can log each frame's schema, sequence number, stamp and payload hash."""

    Config = SinkConfig

    def setup(self) -> None:
        self.count = 0
        self._log = None
        if self.config.log_path:
            Path(self.config.log_path).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.config.log_path, "a", buffering=1)  # noqa: SIM115 - closed in teardown
        # any_robot: a monitor counts what is on the key, another robot's frames too (taking them mixes nothing)
        self.input("frames", self.config.key, None, self.on_frame, policy=self.config.policy, depth=self.config.depth,
                   raw=True, any_robot=True)

    def on_frame(self, frame: Frame, payload: bytes) -> None:
        self.count += 1
        if self.config.process_delay_s:
            time.sleep(self.config.process_delay_s)
        if self._log is not None:
            record = {
                "schema": frame.schema_name,
                "stream": frame.header.stream,
                "seq": frame.header.seq,
                "stamp_ns": frame.header.stamp_ns,
                "received_ns": time.time_ns(),
                "bytes": len(payload),
                "sha256": hashlib.sha256(payload).hexdigest(),
                "arrays_sha256": [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() for a in arrays(frame)],
            }
            self._log.write(json.dumps(record) + "\n")

    def teardown(self) -> None:
        if self._log is not None:
            self._log.close()


WORKER = Sink
