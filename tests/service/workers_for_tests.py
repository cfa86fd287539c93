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
    """Counts Ack frames; 'boom' raises, 'bad' is rejected; answers `.../count` queries; state survives crashes
    (snapshots, and the journal of counted frames and additions between them)."""

    Config = CounterConfig

    def setup(self) -> None:
        self.count = 0
        self.seen: list[int] = []
        self.echo = self.output("echo", f"semloc/{self.robot}/{self.name}/echo", Ack)
        frames = self.input("in", self.config.key, Ack, self.on_ack, policy="lossless", raw=True)
        self.queryable("count", f"semloc/{self.robot}/{self.name}/count", self.on_count)
        additions = self.queryable("add", f"semloc/{self.robot}/{self.name}/add", self.on_add, request=Ack,
                                   check=self.check_number)
        self.journal_stream("in", frames, self.count_frame)
        self.journal_stream("add", additions, self.add)

    def on_ack(self, frame: Ack, payload: bytes) -> None:
        if frame.message == "boom":
            raise RuntimeError("boom")
        if frame.message == "bad":
            raise FrameError("semantically invalid")
        self.count_frame(frame)
        self.journal_write("in", payload)

    def count_frame(self, frame: Ack) -> None:
        self.count += 1
        self.seen.append(frame.header.seq)
        self.echo.publish(Ack(header=self.echo.header(stamp_ns=frame.header.stamp_ns), ok=True,
                              message=str(self.count)))

    def on_count(self, _request) -> Ack:
        return Ack(header=self.echo.header(), ok=True, message=str(self.count))

    def on_add(self, request: Ack) -> Ack:
        if not request.message.isdigit():
            raise ValueError(f"not a number: {request.message!r}")
        self.add(request)
        self.journal_write("add", request)
        return self.on_count(None)

    def check_number(self, request: Ack) -> None:
        if not request.message.isdigit():
            raise FrameError(f"not a number: {request.message[:20]!r}", reason="range")

    def add(self, request: Ack) -> None:
        self.count += int(request.message)

    def snapshot(self) -> State:
        return State(arrays={"seen": np.asarray(self.seen, dtype=np.int64)}, meta={"count": self.count})

    def restore(self, state: State) -> None:
        self.count = int(state.meta["count"])
        self.seen = state.arrays["seen"].tolist()


WORKER = Counter
