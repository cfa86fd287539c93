"""A source that publishes ``frames`` numbered frames the moment it runs, waiting for no subscriber (a recorded source
whose setup costs nothing): the launcher's start_after test (run as `worker: tests.service.eager_source`)."""

from __future__ import annotations

from pydantic import Field

from schemas import Ack
from services.runtime import Worker, WorkerConfig


class EagerConfig(WorkerConfig):
    key: str = Field(description="where the frames go")
    frames: int = Field(10, ge=1, description="frames published at once when it runs")


class EagerSource(Worker):
    Config = EagerConfig

    def setup(self) -> None:
        self.frames_out = self.output("frames", self.config.key, Ack)

    def run(self) -> None:
        for _ in range(self.config.frames):
            self.frames_out.publish(Ack(header=self.frames_out.header(), ok=True))
        super().run()


WORKER = EagerSource
