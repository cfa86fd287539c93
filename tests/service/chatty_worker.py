"""A worker that warns ``lines`` times, writes a line straight to fd 2 (as a C library or a segfault dump does) and
then fails in setup: the launcher's bounded logs (run as `worker: tests.service.chatty_worker`)."""

from __future__ import annotations

import os

from pydantic import Field

from services.runtime import Worker, WorkerConfig

RAW_LINE = b"raw stderr, not through logging\n"


class ChattyConfig(WorkerConfig):
    lines: int = Field(2000, ge=0, description="warnings logged before the failure")


class Chatty(Worker):
    Config = ChattyConfig

    def setup(self) -> None:
        for index in range(self.config.lines):
            self.logger.warning("chatty line %d of %d %s", index, self.config.lines, "x" * 120)
        os.write(2, RAW_LINE)
        raise RuntimeError(f"chatty failure after {self.config.lines} lines")


WORKER = Chatty
