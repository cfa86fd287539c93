"""A sink whose setup takes ``setup_s`` of sleep and ``setup_cpu_s`` of CPU (a worker loading a model or compiling
kernels), for the launcher's start tests (run as `worker: tests.service.slow_start_worker`)."""

from __future__ import annotations

import os
import time

from pydantic import Field

from services.workers.sink import Sink, SinkConfig


class SlowStartConfig(SinkConfig):
    setup_s: float = Field(0.0, ge=0, description="time spent in setup before subscribing")
    setup_cpu_s: float = Field(0.0, ge=0, description="CPU time the setup's thread then burns")
    cpu: int | None = Field(None, description="the CPU the setup's thread is pinned to (a test starves it there)")


class SlowStartSink(Sink):
    Config = SlowStartConfig

    def setup(self) -> None:
        c = self.config
        if c.cpu is not None:
            os.sched_setaffinity(0, {c.cpu})  # this thread only
        self.sleep(c.setup_s)  # reports `starting` meanwhile; its input does not exist yet
        end = time.thread_time() + c.setup_cpu_s
        while time.thread_time() < end:
            pass
        super().setup()


WORKER = SlowStartSink
