"""A worker that takes memory on command, for the memory tests (run as `worker: tests.service.memory_worker`).

A query on ``semloc/<robot>/<name>/grow`` with an Ack whose message is a number of MiB makes it allocate that much
more and touch every page (resident, not only reserved); it answers with the MiB it holds. Under a
memory limit smaller than what it is asked to hold, the kernel kills it."""

from __future__ import annotations

import numpy as np

from schemas import Ack, FrameError
from services.runtime import Worker


class Grower(Worker):
    """Holds as much memory as it is asked for (queries on .../grow)."""

    def setup(self) -> None:
        self.held: list[np.ndarray] = []
        self.queryable("grow", f"semloc/{self.robot}/{self.name}/grow", self.on_grow, request=Ack,
                       check=self.check_size)

    def check_size(self, request: Ack) -> None:
        if not request.message.isdigit():
            raise FrameError(f"not a number of MiB: {request.message[:20]!r}", reason="range")

    def on_grow(self, request: Ack) -> Ack:
        for _ in range(int(request.message)):  # a MiB at a time: the kernel sees it grow, as a real leak grows
            self.held.append(np.ones(1 << 20, np.uint8))
        return Ack(header=request.header, ok=True, message=str(len(self.held)))


WORKER = Grower
