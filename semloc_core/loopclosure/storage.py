"""Where the loop-closure engine keeps what only grows with the map: the frames' descriptors and visual words
(:class:`.matching.FrameStore`) and the lattice's final cells (:class:`.mrf.IncrementalMrf`).

Three kinds of container, all append-only in use (and :class:`RecentRecords`, the latest records of a stream, for
what the engine keeps a bounded sample of):

* ``array(name, dtype, row_shape)`` - one array that grows (``reserve(rows)``, zero-filled; ``data`` is the whole
  array, a new object after it grew). Frames are written into it once, at the end.
* ``chunk(name, index, shape, dtype)`` - a fixed-size array, created zero-filled on first use and the same data on
  every later call (also after a restart, for a persistent storage).
* ``log(name, dtype)`` - a sequence of records that only grows, read back whole, truncated to a snapshot's length
  when the engine restarts from it.

:class:`MemoryStorage` (here) keeps them in memory: the engine's default, for experiments, tests and benchmarks. A
persistent storage keeps them in files (``semloc_core.io.loopclosure.FileStorage``): the engine's snapshot then
holds only its index and the lengths of the logs, so its size and restore time do not grow with the descriptors,
and the descriptors need not stay in the process's memory (``release``).
"""

from __future__ import annotations

import numpy as np


class MemoryLog:
    """Records of one dtype, appended and read back whole."""

    def __init__(self, dtype) -> None:
        self.dtype = np.dtype(dtype)
        self._parts: list[np.ndarray] = []
        self._length = 0

    def __len__(self) -> int:
        return self._length

    def append(self, records: np.ndarray) -> None:
        records = np.ascontiguousarray(records, dtype=self.dtype).reshape(-1)
        if records.size:
            self._parts.append(records.copy())
            self._length += records.size

    def read(self) -> np.ndarray:
        if len(self._parts) > 1:
            self._parts = [np.concatenate(self._parts)]
        return self._parts[0].copy() if self._parts else np.zeros(0, self.dtype)

    def truncate(self, length: int) -> None:
        if not 0 <= length <= self._length:
            raise ValueError(f"cannot truncate a log of {self._length} records to {length}")
        self._parts = [self.read()[:length]] if length else []
        self._length = int(length)


class RecentRecords:
    """The latest ``size`` records of one dtype appended, oldest first, in memory of fixed size: two arrays' worth,
    the newest records copied to the front once the end is reached (every ``size`` records at most)."""

    def __init__(self, dtype, size: int) -> None:
        if size < 1:
            raise ValueError("size must be >= 1")
        self.dtype, self.size = np.dtype(dtype), int(size)
        self._data = np.zeros(0, self.dtype)  # grown to 2 * size as records come
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, records: np.ndarray) -> None:
        records = np.asarray(records, self.dtype).reshape(-1)[-self.size:]
        k = records.size
        if self._end + k > self._data.size:
            if self._data.size < 2 * self.size:
                grown = np.zeros(min(2 * self.size, max(2 * self._data.size, self._end + k, 64)), self.dtype)
                grown[: self._end] = self._data[: self._end]
                self._data = grown
            if self._end + k > self._data.size:  # full: the records that stay go to the front
                kept = min(len(self), self.size - k)
                self._data[:kept] = self._data[self._end - kept:self._end]
                self._start, self._end = 0, kept
        self._data[self._end:self._end + k] = records
        self._end += k
        self._start = max(self._start, self._end - self.size)

    def read(self) -> np.ndarray:
        """The records held, oldest first (a copy)."""
        return self._data[self._start:self._end].copy()


class MemoryArray:
    """A growing array in memory (capacity doubled, contents copied)."""

    def __init__(self, dtype, row_shape: tuple[int, ...]) -> None:
        self.data = np.zeros((0, *row_shape), dtype)

    def reserve(self, rows: int) -> np.ndarray:
        if rows > self.data.shape[0]:
            grown = np.zeros((max(rows, 2 * self.data.shape[0], 1024), *self.data.shape[1:]), self.data.dtype)
            grown[: self.data.shape[0]] = self.data
            self.data = grown
        return self.data


class MemoryStorage:
    """Chunks and logs in memory (nothing survives the process; the engine's state then embeds them)."""

    persistent = False

    def __init__(self) -> None:
        self._chunks: dict[tuple[str, int], np.ndarray] = {}
        self._arrays: dict[str, MemoryArray] = {}
        self._logs: dict[str, MemoryLog] = {}

    def array(self, name: str, dtype, row_shape: tuple[int, ...] = ()) -> MemoryArray:
        array = self._arrays.get(name)
        if array is None:
            array = self._arrays[name] = MemoryArray(dtype, tuple(row_shape))
        return array

    def chunk(self, name: str, index: int, shape: tuple[int, ...], dtype) -> np.ndarray:
        key = (name, int(index))
        array = self._chunks.get(key)
        if array is None:
            array = self._chunks[key] = np.zeros(shape, dtype)
        elif array.shape != tuple(shape) or array.dtype != np.dtype(dtype):
            raise ValueError(f"chunk {name}[{index}] has shape {array.shape} {array.dtype}, not {shape} {dtype}")
        return array

    def log(self, name: str, dtype) -> MemoryLog:
        log = self._logs.get(name)
        if log is None:
            log = self._logs[name] = MemoryLog(dtype)
        elif log.dtype != np.dtype(dtype):
            raise ValueError(f"log {name} holds {log.dtype}, not {np.dtype(dtype)}")
        return log

    def flush(self) -> None:
        """Make everything written durable (nothing to do in memory)."""

    def release(self) -> None:
        """Let go of resident copies of stored data that is not in use (nothing to do in memory)."""
