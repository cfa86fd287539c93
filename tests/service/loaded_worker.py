"""A sink under load, for the health tests (run as `worker: tests.service.loaded_worker`).

* ``slow_every`` / ``slow_s``: every ``slow_every``-th frame takes ``slow_s`` more: a stage whose rare long calls
  (a key frame, an inference) drop the frames arriving meanwhile while it keeps up on average.
* ``starve_for_s``: its first frame has the machine starve it of CPU for that long. Every thread of its own goes to
  SCHED_IDLE on CPU ``cpu`` (weight 3 against a busy process's 1024), ``hogs`` busy processes pinned there start and
  end by themselves after ``starve_for_s``, and its session's autogroup goes to nice 19. The hogs share its session:
  where the kernel groups tasks by session (autogroups) it shares a CPU between sessions first, so only busy
  processes of its own session take its session's share from it; busy processes of other sessions on that CPU (the
  test's) take that share.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

from pydantic import Field

from schemas import Frame
from services.workers.sink import Sink, SinkConfig

HOG = "import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end: pass\n"


class LoadedConfig(SinkConfig):
    slow_every: int | None = Field(None, ge=1, description="every this many frames, one is slow (None: none)")
    slow_s: float = Field(1.0, ge=0, description="how much longer the slow one takes")
    starve_for_s: float | None = Field(None, gt=0, description="how long its first frame has it starved (None: not)")
    hogs: int = Field(2, ge=1, description="busy processes of its session on its CPU")
    cpu: int = Field(0, ge=0, description="the CPU it and the hogs share")


class LoadedSink(Sink):
    Config = LoadedConfig

    def on_frame(self, frame: Frame, payload: bytes) -> None:
        super().on_frame(frame, payload)
        c = self.config
        if c.slow_every and self.count % c.slow_every == 0:
            time.sleep(c.slow_s)
        if c.starve_for_s and self.count == 1:
            self.starve(c.starve_for_s)

    def starve(self, seconds: float) -> None:
        c = self.config
        self.hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(seconds=seconds)], stdin=subprocess.DEVNULL,
                                      preexec_fn=lambda: os.sched_setaffinity(0, {c.cpu})) for _ in range(c.hogs)]
        for tid in map(int, os.listdir("/proc/self/task")):
            os.sched_setaffinity(tid, {c.cpu})
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        with contextlib.suppress(OSError):  # no autogroups: SCHED_IDLE alone
            Path("/proc/self/autogroup").write_text("19")
        self.logger.info("starving: %d hogs on CPU %d for %.1f s", c.hogs, c.cpu, seconds)


WORKER = LoadedSink
