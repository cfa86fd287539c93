"""A sink whose every ``slow_every``-th frame takes ``slow_s`` more: a stage whose rare long calls (a key frame, an
inference) drop the frames arriving meanwhile while it keeps up on average (run as
`worker: tests.service.uneven_worker`)."""

from __future__ import annotations

import time

from pydantic import Field

from schemas import Frame
from services.workers.sink import Sink, SinkConfig


class UnevenConfig(SinkConfig):
    slow_every: int = Field(40, ge=1, description="every this many frames, one is slow")
    slow_s: float = Field(1.0, ge=0, description="how much longer the slow one takes")


class UnevenSink(Sink):
    Config = UnevenConfig

    def on_frame(self, frame: Frame, payload: bytes) -> None:
        super().on_frame(frame, payload)
        if self.count % self.config.slow_every == 0:
            time.sleep(self.config.slow_s)


WORKER = UnevenSink
