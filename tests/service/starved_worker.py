"""A sink that has the machine starve it of CPU, for the launcher's heartbeat tests (run as
`worker: tests.service.starved_worker`).

Its first frame moves every thread of its own to SCHED_IDLE on CPU ``cpu`` (weight 3 against a busy process's 1024)
and starts ``hogs`` busy processes pinned there, which end by themselves after ``starve_for_s``, and lowers its
session's autogroup to nice 19. The hogs share its session: where the kernel groups tasks by session (autogroups),
it shares a CPU between sessions first, so only busy processes of its own session take its session's share from it;
busy processes of other sessions on that CPU (the test's) take that share."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

from pydantic import Field

from schemas import Frame
from services.workers.sink import Sink, SinkConfig

HOG = "import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end: pass\n"


class StarvedConfig(SinkConfig):
    starve_for_s: float = Field(8.0, gt=0, description="how long its hogs run")
    hogs: int = Field(2, ge=1, description="busy processes of its session on its CPU")
    cpu: int = Field(0, ge=0, description="the CPU it and the hogs share")


class StarvedSink(Sink):
    Config = StarvedConfig

    def on_frame(self, frame: Frame, payload: bytes) -> None:
        super().on_frame(frame, payload)
        if self.count > 1:
            return
        c = self.config
        self.hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(seconds=c.starve_for_s)],
                                      stdin=subprocess.DEVNULL, preexec_fn=lambda: os.sched_setaffinity(0, {c.cpu}))
                     for _ in range(c.hogs)]
        for tid in map(int, os.listdir("/proc/self/task")):
            os.sched_setaffinity(tid, {c.cpu})
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        with contextlib.suppress(OSError):  # no autogroups: SCHED_IDLE alone
            Path("/proc/self/autogroup").write_text("19")
        self.logger.info("starving: %d hogs on CPU %d for %.1f s", c.hogs, c.cpu, c.starve_for_s)


WORKER = StarvedSink
