"""A sink whose setup takes ``setup_s`` (a worker loading a model or compiling kernels), for the launcher's
start_after tests (run as `worker: tests.service.slow_start_worker`)."""

from __future__ import annotations

from pydantic import Field

from services.workers.sink import Sink, SinkConfig


class SlowStartConfig(SinkConfig):
    setup_s: float = Field(0.0, ge=0, description="time spent in setup before subscribing")


class SlowStartSink(Sink):
    Config = SlowStartConfig

    def setup(self) -> None:
        self.sleep(self.config.setup_s)  # reports `starting` meanwhile; its input does not exist yet
        super().setup()


WORKER = SlowStartSink
