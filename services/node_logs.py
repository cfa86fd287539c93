"""A node's log, bounded: the launcher reads everything the node's process writes to stdout and stderr from a pipe
and appends it to ``<run_dir>/logs/<name>.log``, moved to ``<name>.log.1`` (``.1`` to ``.2``, ..., the oldest beyond
``keep`` deleted) once it holds ``max_mb``: each file ends at a line's end and is at most ``max_mb`` long (a longer
line: a file of its own).

The launcher pipes rather than the worker rotating its own file: every byte goes through one writer (a Python
traceback, faulthandler's dump of a segfault, a C library's message on fd 2, several processes of one node in a
restart loop), nothing renames a file a child still writes to, and the launcher, which reads the crash line for
`semloc status` and serves `semloc logs`, knows where each byte went.

Offsets (``end``, :meth:`NodeLog.read`) count every byte of the log from the start of the file the launcher found, so
a reader's offset stays valid across rotations; bytes rotated out of every kept file are gone.
"""

from __future__ import annotations

import fcntl
import logging
import os
import sys
import threading
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger("semloc.launcher")

PIPE_READ_BYTES = 1 << 20  # the pipe's size too (F_SETPIPE_SZ): a node logging 50 MB/s is not held up
PIPE_WAIT_S = 0.02  # after a short read, so the log is written in batches, not a line at a time


class LogPolicy(BaseModel):
    """How large a node's log grows (a graph's ``logs``; every node of the graph)."""

    model_config = ConfigDict(extra="forbid")

    max_mb: float = Field(10.0, gt=0, description="a log file past this many MB is rotated (<name>.log.1)")
    keep: int = Field(3, ge=1, description="rotated files kept (<name>.log.1 .. .<keep>); the oldest is deleted")


class NodeLog:
    """``path`` and its rotated files, written a chunk at a time (:meth:`write`) and read by offset (:meth:`read`);
    thread-safe."""

    def __init__(self, path: Path, policy: LogPolicy):
        self.path, self.max_bytes, self.keep = Path(path), int(policy.max_mb * 1e6), policy.keep
        self._lock = threading.Lock()
        # open while the launcher runs; raises when the log cannot be written
        self._file = open(self.path, "ab", buffering=0)  # noqa: SIM115
        self.end = self._file.seek(0, os.SEEK_END)  # a previous launcher's lines (a graph started again) come first
        self._begins = [0]  # the offset where each kept file begins, oldest first; the last is ``path``'s
        self.write_failures = 0

    def _file_at(self, index: int) -> Path:
        """The ``index``-th kept file (oldest first): ``path`` last, ``path.1`` before it, ..."""
        back = len(self._begins) - 1 - index
        return self.path if back == 0 else self.path.with_name(f"{self.path.name}.{back}")

    def write(self, data: bytes) -> None:
        with self._lock:
            try:
                while len(data) > (room := self.max_bytes - (self.end - self._begins[-1])):
                    # the file is filled up to a line's end, so a traceback reads whole
                    cut = data.rfind(b"\n", 0, room) + 1 if room > 0 else 0
                    if not cut and self.end == self._begins[-1]:  # a line longer than a file: alone in one
                        cut = data.find(b"\n") + 1 or len(data)
                    self._append(data[:cut])
                    data = data[cut:]
                    self._rotate()
                self._append(data)
            except OSError as error:
                # A full or read-only disk: the node runs on (its pipe is always drained), its output to the
                # launcher's own.
                self.write_failures += 1
                if self.write_failures == 1:
                    log.error("cannot write %s: %s; its output goes to the launcher's", self.path, error.strerror)
                sys.stderr.buffer.write(data)
                sys.stderr.flush()

    def _append(self, data: bytes) -> None:
        self._file.write(data)
        self.end += len(data)

    def _rotate(self) -> None:
        self._file.close()
        self.path.with_name(f"{self.path.name}.{self.keep}").unlink(missing_ok=True)
        for back in range(self.keep - 1, 0, -1):
            rotated = self.path.with_name(f"{self.path.name}.{back}")
            if rotated.exists():
                rotated.rename(self.path.with_name(f"{self.path.name}.{back + 1}"))
        self.path.rename(self.path.with_name(f"{self.path.name}.1"))
        self._begins = (self._begins + [self.end])[-(self.keep + 1):]
        self._file = open(self.path, "ab", buffering=0)  # noqa: SIM115

    def read(self, start: int, end: int) -> tuple[int, bytes]:
        """(first offset read, bytes) of ``[start, end)``, from the oldest byte kept when ``start`` is older."""
        with self._lock:  # no rotation while reading
            end = min(end, self.end)
            first = max(start, self._begins[0])
            chunks = []
            for index, begin in enumerate(self._begins):
                stop = self._begins[index + 1] if index + 1 < len(self._begins) else end
                lo, hi = max(first, begin), min(end, stop)
                if lo >= hi:
                    continue
                try:
                    with open(self._file_at(index), "rb") as stream:
                        stream.seek(lo - begin)
                        chunks.append(stream.read(hi - lo))
                except OSError:  # removed by hand: what follows is still read
                    chunks, first = [], hi
            return first, b"".join(chunks)


def pump(stream, node_log: NodeLog) -> threading.Thread:
    """A thread copying the pipe ``stream`` (a child's stdout) into ``node_log`` until the child and its children
    close it."""
    def run() -> None:
        fd = stream.fileno()
        try:
            fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_READ_BYTES)
        except (AttributeError, OSError):  # not Linux, or over the system's limit: the default 64 KiB pipe
            pass
        try:
            while data := os.read(fd, PIPE_READ_BYTES):
                node_log.write(data)
                if len(data) < PIPE_READ_BYTES // 4:
                    # A line at a time costs two system calls a line: wait for more (the pipe holds 1 MiB)
                    time.sleep(PIPE_WAIT_S)
        finally:
            stream.close()

    thread = threading.Thread(target=run, name="node-log", daemon=True)
    thread.start()
    return thread
