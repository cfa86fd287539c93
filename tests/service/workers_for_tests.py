"""A small stateful worker used by the runtime service tests (run as `semloc worker tests.service.workers_for_tests`)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from schemas import Ack, FrameError
from services.runtime import Worker, WorkerConfig
from services.state import State


class CounterConfig(WorkerConfig):
    key: str = Field("semloc/r1/counter/in")


class Counter(Worker):
    """Counts Ack frames; 'boom' raises, 'bad' is rejected; answers `.../count` queries; state survives crashes."""

    Config = CounterConfig

    def setup(self) -> None:
        self.count = 0
        self.seen: list[int] = []
        self.echo = self.output("echo", f"semloc/{self.robot}/{self.name}/echo", Ack)
        self.input("in", self.config.key, Ack, self.on_ack, policy="lossless")
        self.queryable("count", f"semloc/{self.robot}/{self.name}/count", self.on_count)
        self.queryable("add", f"semloc/{self.robot}/{self.name}/add", self.on_add, request=Ack)

    def on_ack(self, frame: Ack) -> None:
        if frame.message == "boom":
            raise RuntimeError("boom")
        if frame.message == "bad":
            raise FrameError("semantically invalid")
        self.count += 1
        self.seen.append(frame.header.seq)
        self.echo.publish(Ack(header=self.echo.header(stamp_ns=frame.header.stamp_ns), ok=True,
                              message=str(self.count)))

    def on_count(self, _request) -> Ack:
        return Ack(header=self.echo.header(), ok=True, message=str(self.count))

    def on_add(self, request: Ack) -> Ack:
        if not request.message.isdigit():
            raise ValueError(f"not a number: {request.message!r}")
        self.count += int(request.message)
        return self.on_count(None)

    def snapshot(self) -> State:
        return State(arrays={"seen": np.asarray(self.seen, dtype=np.int64)}, meta={"count": self.count})

    def restore(self, state: State) -> None:
        self.count = int(state.meta["count"])
        self.seen = state.arrays["seen"].tolist()


WORKER = Counter
