"""The journal of a stateful worker: every state change since the last snapshot, so a killed worker loses at most
the frame it was handling (docs/runtime.md, "State that survives a crash").

A worker appends one record per committed input (its stream name and the frame's encoded bytes) once the handler
has applied it. Records are written to the kernel at once (a SIGKILL loses nothing written) and made durable
(``fdatasync``) every ``commit_period_s`` by a background thread (a power cut loses at most that much). Records live
in numbered segment files ``<dir>/<segment>.journal``; a snapshot starts a new segment and records the first segment
it does not contain, so after a restart the worker restores the snapshot and replays the segments from there.

Record layout (little endian): ``b"SJ"``, u16 stream-name length, u32 payload length, u32 CRC-32 of name and
payload, then the name (UTF-8) and the payload. A torn or corrupt record ends its segment: it is the write the
process was killed in (or a disk error); it and what follows in that segment are skipped and counted.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path

from semloc_core.io.atomic import fsync_directory

MAGIC = b"SJ"
HEADER = struct.Struct("<2sHII")
SEGMENT = re.compile(r"^(\d{10})\.journal$")
MAX_RECORD = 1 << 30

log = logging.getLogger("semloc.journal")


def _segment_path(directory: Path, segment: int) -> Path:
    return directory / f"{segment:010d}.journal"


class Journal:
    """Append-only, segmented record log with group commit. Not thread-safe for writers (one writer: the worker's
    main thread); the commit thread only syncs."""

    def __init__(self, directory: str | Path, commit_period_s: float = 0.5):
        if commit_period_s <= 0:
            raise ValueError("commit_period_s must be positive")
        self.directory = Path(directory)
        self.commit_period_s = float(commit_period_s)
        self.segment: int | None = None  # the segment being written
        self._fd: int | None = None
        self._dirty = False
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.torn = 0  # records skipped while reading (a torn tail, a bad checksum)

    # ------------------------------------------------------------------ reading
    def segments(self) -> list[int]:
        if not self.directory.is_dir():
            return []
        return sorted(int(m.group(1)) for p in self.directory.iterdir() if (m := SEGMENT.match(p.name)))

    def records(self, first_segment: int = 0) -> Iterator[tuple[str, bytes]]:
        """(stream, payload) of every intact record of the segments from ``first_segment`` on, in order."""
        for segment in self.segments():
            if segment >= first_segment:
                yield from self._read_segment(_segment_path(self.directory, segment))

    def _read_segment(self, path: Path) -> Iterator[tuple[str, bytes]]:
        data = path.read_bytes()
        offset = 0
        while offset < len(data):
            if len(data) - offset < HEADER.size:
                self._skip(path, offset, "torn record header")
                return
            magic, name_length, payload_length, crc = HEADER.unpack_from(data, offset)
            start = offset + HEADER.size
            end = start + name_length + payload_length
            if magic != MAGIC or payload_length > MAX_RECORD or end > len(data):
                self._skip(path, offset, "torn record" if magic == MAGIC else "bad record header")
                return
            body = memoryview(data)[start:end]
            if zlib.crc32(body) != crc:
                self._skip(path, offset, "bad checksum")
                return
            try:
                name = bytes(body[:name_length]).decode()
            except UnicodeDecodeError:
                self._skip(path, offset, "bad stream name")
                return
            yield name, bytes(body[name_length:])
            offset = end

    def _skip(self, path: Path, offset: int, why: str) -> None:
        self.torn += 1
        log.warning("journal %s: %s at byte %d; the rest of the segment is skipped", path, why, offset)

    # ------------------------------------------------------------------ writing
    def open(self, segment: int | None = None) -> int:
        """Start writing a new segment (default: after the newest on disk); starts the commit thread."""
        self.directory.mkdir(parents=True, exist_ok=True)
        if segment is None:
            existing = self.segments()
            segment = existing[-1] + 1 if existing else 0
        with self._lock:
            self._close_fd()
            self._fd = os.open(_segment_path(self.directory, segment), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            self.segment = segment
        fsync_directory(self.directory)
        if self._thread is None:
            self._thread = threading.Thread(target=self._commit_loop, name="semloc-journal", daemon=True)
            self._thread.start()
        return segment

    def append(self, stream: str, payload: bytes | bytearray | memoryview) -> None:
        """Write one record (to the kernel: it survives the process; durable at the next commit). A write that
        fails (OSError naming the segment) leaves the segment as it was before it."""
        if self._fd is None:
            raise RuntimeError("journal is not open")
        name = stream.encode()
        payload = memoryview(payload).cast("B")
        if len(name) > 0xFFFF or len(payload) > MAX_RECORD:
            raise ValueError("journal record too large")
        crc = zlib.crc32(payload, zlib.crc32(name))
        parts = [HEADER.pack(MAGIC, len(name), len(payload), crc), name, payload]
        total = sum(len(p) for p in parts)
        with self._lock:
            end = os.lseek(self._fd, 0, os.SEEK_END)
            try:
                written = os.writev(self._fd, parts)
                while written < total:  # a short write (a disk filling up): write the rest
                    rest = b"".join(bytes(p) for p in parts)[written:]
                    written += os.write(self._fd, rest)
            except OSError as error:
                # A full disk or a file size limit: the part written is cut off again, so the segment ends with its
                # last whole record and the records a later append adds are not hidden behind a torn one.
                try:
                    os.ftruncate(self._fd, end)
                except OSError:
                    pass  # the reader stops at the torn record: no record after it is trusted
                raise OSError(error.errno, error.strerror, str(_segment_path(self.directory, self.segment))) \
                    from error
            self._dirty = True

    def commit(self) -> None:
        """Make every record written so far durable."""
        with self._lock:
            if self._fd is not None and self._dirty:
                os.fdatasync(self._fd)
                self._dirty = False

    def rotate(self) -> int:
        """Commit the current segment and start the next one; returns the new segment's number."""
        self.commit()
        return self.open(None if self.segment is None else self.segment + 1)

    def discard_before(self, segment: int) -> None:
        """Delete the segments before ``segment`` (a snapshot now holds them)."""
        for old in self.segments():
            if old < segment:
                _segment_path(self.directory, old).unlink(missing_ok=True)

    def _commit_loop(self) -> None:
        while not self._closing.wait(self.commit_period_s):
            try:
                self.commit()
            except OSError as error:  # a disk error: reported, the worker goes on
                log.error("journal commit failed: %s", error)

    def _close_fd(self) -> None:
        if self._fd is not None:
            if self._dirty:
                os.fdatasync(self._fd)
                self._dirty = False
            os.close(self._fd)
            self._fd = None

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            self._close_fd()
