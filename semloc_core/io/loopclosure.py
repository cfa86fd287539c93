"""Loop-closure files: engine state, vocabulary, feature caches (.npz, no pickle), topological maps (JSON, GraphML).

* ``save_engine_state(path, arrays, meta)`` / ``load_engine_state(path)``: what
  ``semloc_core.loopclosure.LoopClosureEngine.state()`` returns, in one ``.npz`` (the JSON metadata is stored as a
  UTF-8 byte array named ``__meta__``), written atomically.
* ``FileStorage(directory)``: the engine's storage in files (:mod:`semloc_core.loopclosure.storage`): each growing
  array ``<name>.array`` and each chunk ``<name>.<index>`` a raw binary file mapped into memory, each log
  ``<name>.log`` raw records appended; ``read_only``: what a disk that refuses writes holds, readable, nothing added.
* ``save_vocabulary`` / ``load_vocabulary``: a ``Vocabulary`` (``centers``, ``idf``).
* ``save_features`` / ``load_features``: a list of ``FeatureSequence`` (a cache, so SIFT runs once per image).
* ``save_matrices`` / ``load_matrices``: named (n, n) similarity matrices with the settings that made them (a cache
  for ``semloc eval loopclosure``: the full matrices are its expensive part).
* ``save_topomap(path, topomap, positions, stamps_ns)``: ``.json`` (format ``semloc.topomap`` v1) or ``.graphml`` by
  suffix, with each node's key-frame pose and stamp when given;
  ``load_topomap`` reads the JSON form.
* ``read_loop_samples(folder)``: an image folder with a ground-truth loop matrix in the layout of
  ``rtabmap_loop_samples`` (``images/1.jpg..N.jpg``, ``samples_GT.bmp`` with row = later frame, column = earlier).
"""

from __future__ import annotations

import errno
import json
import mmap
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from semloc_core.io.atomic import replace_text, replacing
from semloc_core.io.errors import FileFormatError
from semloc_core.loopclosure.bow import Vocabulary
from semloc_core.loopclosure.features import DESCRIPTOR_SIZE, FeatureSequence
from semloc_core.loopclosure.topomap import TopologicalMap

_META = "__meta__"


class LoopClosureFileError(FileFormatError):
    """A loop-closure file that cannot be read or does not hold what it should."""


def _save_npz(path, arrays: dict[str, np.ndarray], meta: dict | None = None) -> None:
    payload = {}
    for name, array in arrays.items():
        array = np.asarray(array)
        if array.dtype == object:
            raise ValueError(f"array {name!r} has dtype object, which cannot be stored without pickle")
        payload[name] = array
    if meta is not None:
        payload[_META] = np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), dtype=np.uint8)
    with replacing(path) as handle:
        np.savez(handle, **payload)


def _load_npz(path) -> tuple[dict[str, np.ndarray], dict | None]:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise LoopClosureFileError(f"cannot read {path}: {error}") from None
    meta = None
    if _META in arrays:
        try:
            meta = json.loads(arrays.pop(_META).tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise LoopClosureFileError(f"{path}: bad metadata: {error}") from None
    return arrays, meta


def _read_only(path: Path) -> OSError:
    return OSError(errno.EROFS, "opened read-only (its disk refused writes)", str(path))


class FileLog:
    """Records of one dtype appended to a file (``<name>.log``); a torn last record is dropped when it is opened
    (``read_only``: not counted; a truncation only shortens what is read)."""

    persistent = True

    def __init__(self, path, dtype, read_only: bool = False) -> None:
        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.read_only = read_only
        self._fd = os.open(self.path, os.O_RDONLY if read_only else os.O_RDWR | os.O_CREAT, 0o644)
        size = os.fstat(self._fd).st_size
        self._length = size // self.dtype.itemsize
        if size % self.dtype.itemsize and not read_only:
            os.ftruncate(self._fd, self._length * self.dtype.itemsize)

    def __len__(self) -> int:
        return self._length

    def append(self, records: np.ndarray) -> None:
        if self.read_only:
            raise _read_only(self.path)
        data = np.ascontiguousarray(records, dtype=self.dtype).reshape(-1)
        view = memoryview(data).cast("B")
        offset = self._length * self.dtype.itemsize
        written = 0
        while written < len(view):
            written += os.pwrite(self._fd, view[written:], offset + written)
        self._length += data.size

    def read(self) -> np.ndarray:
        out = np.empty(self._length, self.dtype)
        view = memoryview(out).cast("B")
        done = 0
        while done < len(view):
            chunk = os.preadv(self._fd, [view[done:]], done)
            if chunk <= 0:
                raise LoopClosureFileError(f"{self.path}: shorter than its {self._length} records")
            done += chunk
        return out

    def truncate(self, length: int) -> None:
        if not 0 <= length <= self._length:
            raise ValueError(f"cannot truncate {self.path} of {self._length} records to {length}")
        if not self.read_only:
            os.ftruncate(self._fd, length * self.dtype.itemsize)
        self._length = int(length)

    def flush(self) -> None:
        if not self.read_only:
            os.fdatasync(self._fd)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _allocate(fd: int, path: Path, start: int, end: int) -> None:
    """Give bytes [start, end) of a mapped file their disk blocks before anything is written there: a full disk
    is then an OSError naming the file, not a SIGBUS at the first write into a page the file system cannot back."""
    if end > start:
        try:
            os.posix_fallocate(fd, start, end - start)
        except OSError as error:
            raise OSError(error.errno, error.strerror, str(path)) from None


class FileArray:
    """A growing array in a file mapped into memory: grown by extending the file (sparse beyond the rows reserved)
    and mapping it again; earlier mappings stay valid (and are released with the storage's). The rows reserved get
    their disk blocks first (``_allocate``); a read-only storage's cannot grow."""

    def __init__(self, storage: "FileStorage", path: Path, dtype, row_shape: tuple[int, ...]) -> None:
        self.storage, self.path = storage, path
        self.dtype, self.row_shape = np.dtype(dtype), tuple(row_shape)
        self.row_bytes = self.dtype.itemsize * int(np.prod(self.row_shape, dtype=np.int64))
        if not path.exists():
            storage.made.append(path.name)
        self._fd = os.open(path, os.O_RDONLY if storage.read_only else os.O_RDWR | os.O_CREAT, 0o644)
        rows = os.fstat(self._fd).st_size // self.row_bytes
        self.data = np.zeros((0, *self.row_shape), self.dtype)
        self._allocated = 0  # bytes given their disk blocks by this process (from the start of the file)
        if rows:
            self._map(rows)

    def _map(self, rows: int) -> None:
        size = rows * self.row_bytes
        if os.fstat(self._fd).st_size < size:
            os.ftruncate(self._fd, size)
        mapped = mmap.mmap(self._fd, size, access=mmap.ACCESS_READ if self.storage.read_only else mmap.ACCESS_DEFAULT)
        self.storage._maps.append(mapped)
        self.data = np.frombuffer(mapped, self.dtype, rows * (self.row_bytes // self.dtype.itemsize)).reshape(
            (rows, *self.row_shape))

    def reserve(self, rows: int) -> np.ndarray:
        """The array, its first ``rows`` rows backed on disk (OSError, nothing changed, when the disk cannot)."""
        if self.storage.read_only:
            raise _read_only(self.path)
        if rows * self.row_bytes > self._allocated:
            _allocate(self._fd, self.path, self._allocated, rows * self.row_bytes)
            self._allocated = rows * self.row_bytes
        if rows > self.data.shape[0]:
            self._map(max(rows, 2 * self.data.shape[0], (16 << 20) // self.row_bytes))
        return self.data

    def flush(self) -> None:
        if not self.storage.read_only:
            os.fdatasync(self._fd)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class FileStorage:
    """The loop-closure engine's storage in a directory: chunks are files mapped into memory (written in place,
    shared with the page cache), logs are files appended to. ``release`` drops the mapped pages from the process
    (they stay in the kernel's page cache and come back on the next access), so the descriptors of a long run do
    not accumulate in the process's resident memory. ``made``: the files it had to create or resize (none when
    an engine reopens what it wrote before). ``read_only``: the files opened for reading only and mapped read-only
    (a disk that refuses writes: a state is restored from it, and nothing added until it is opened again
    writable); a file missing or of another size is an error (OSError, LoopClosureFileError)."""

    persistent = True

    def __init__(self, directory, read_only: bool = False) -> None:
        self.directory = Path(directory)
        self.read_only = read_only
        if not read_only:
            self.directory.mkdir(parents=True, exist_ok=True)
        self._chunks: dict[tuple[str, int], np.ndarray] = {}
        self._arrays: dict[str, FileArray] = {}
        self._maps: list[mmap.mmap] = []
        self._logs: dict[str, FileLog] = {}
        self.made: list[str] = []

    def array(self, name: str, dtype, row_shape: tuple[int, ...] = ()) -> FileArray:
        array = self._arrays.get(name)
        if array is None:
            array = self._arrays[name] = FileArray(self, self.directory / f"{name}.array", dtype, row_shape)
        return array

    def chunk(self, name: str, index: int, shape: tuple[int, ...], dtype) -> np.ndarray:
        key = (name, int(index))
        array = self._chunks.get(key)
        if array is not None:
            if array.shape != tuple(shape) or array.dtype != np.dtype(dtype):
                raise ValueError(f"chunk {name}[{index}] is {array.shape} {array.dtype}, not {shape} {dtype}")
            return array
        count = int(np.prod(shape))
        size = count * np.dtype(dtype).itemsize
        path = self.directory / f"{name}.{int(index):05d}"
        fd = os.open(path, os.O_RDONLY if self.read_only else os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if os.fstat(fd).st_size != size and self.read_only:
                raise LoopClosureFileError(f"{path} holds {os.fstat(fd).st_size} bytes, not the {size} of its chunk")
            if os.fstat(fd).st_size != size:  # new (zero-filled), or left with another size by an older run
                os.ftruncate(fd, size)
                self.made.append(path.name)
            if not self.read_only:
                _allocate(fd, path, 0, size)  # (a chunk is written whole)
            mapped = mmap.mmap(fd, size, access=mmap.ACCESS_READ if self.read_only else mmap.ACCESS_DEFAULT)
        finally:
            os.close(fd)
        self._maps.append(mapped)
        array = self._chunks[key] = np.frombuffer(mapped, dtype, count).reshape(shape)
        return array

    def log(self, name: str, dtype) -> FileLog:
        log = self._logs.get(name)
        if log is None:
            path = self.directory / f"{name}.log"
            if not path.exists():
                self.made.append(path.name)
            log = self._logs[name] = FileLog(path, dtype, self.read_only)
        elif log.dtype != np.dtype(dtype):
            raise ValueError(f"log {name} holds {log.dtype}, not {np.dtype(dtype)}")
        return log

    def flush(self) -> None:
        if self.read_only:
            return
        for mapped in self._maps:
            mapped.flush()
        for part in (*self._logs.values(), *self._arrays.values()):
            part.flush()
        handle = os.open(self.directory, os.O_RDONLY)
        try:
            os.fsync(handle)
        finally:
            os.close(handle)

    def release(self) -> None:
        for mapped in self._maps:
            mapped.madvise(mmap.MADV_DONTNEED)

    def close(self) -> None:
        """Close the files (their mappings stay valid while arrays refer to them)."""
        for part in (*self._logs.values(), *self._arrays.values()):
            part.close()
        self._logs.clear()
        self._arrays.clear()

    def size_bytes(self) -> int:
        """Bytes the storage's files take on disk."""
        return sum(p.stat().st_blocks * 512 for p in self.directory.iterdir() if p.is_file())


def save_engine_state(path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    _save_npz(path, arrays, meta)


def load_engine_state(path) -> tuple[dict[str, np.ndarray], dict]:
    arrays, meta = _load_npz(path)
    if meta is None:
        raise LoopClosureFileError(f"{path} holds no engine metadata")
    return arrays, meta


def save_vocabulary(path, vocabulary: Vocabulary) -> None:
    _save_npz(path, {"centers": vocabulary.centers, "idf": vocabulary.idf}, {"format": "semloc.vocabulary",
                                                                             "version": 1})


def load_vocabulary(path) -> Vocabulary:
    arrays, meta = _load_npz(path)
    if not meta or meta.get("format") != "semloc.vocabulary" or "centers" not in arrays or "idf" not in arrays:
        raise LoopClosureFileError(f"{path} is not a semloc vocabulary")
    try:
        return Vocabulary(arrays["centers"], arrays["idf"])
    except ValueError as error:
        raise LoopClosureFileError(f"{path}: {error}") from None


def save_features(path, sequences: list[FeatureSequence], meta: dict | None = None) -> None:
    """Cache feature sequences; ``meta`` (JSON-able) records how they were made (camera, SIFT settings)."""
    lengths = np.array([len(s) for s in sequences], np.int64)

    def cat(parts, shape, dtype):
        return np.concatenate(parts) if parts else np.zeros(shape, dtype)

    arrays = {
        "lengths": lengths,
        "bearings": cat([s.bearings for s in sequences], (0,), np.float64),
        "descriptors": cat([s.descriptors for s in sequences], (0, DESCRIPTOR_SIZE), np.uint8),
        "camera_index": cat([s.camera_index for s in sequences], (0,), np.int16),
        "points": cat([s.points for s in sequences], (0, 2), np.float32),
    }
    _save_npz(path, arrays, {"format": "semloc.features", "version": 1, **(meta or {})})


def load_features(path) -> tuple[list[FeatureSequence], dict]:
    arrays, meta = _load_npz(path)
    if not meta or meta.get("format") != "semloc.features":
        raise LoopClosureFileError(f"{path} is not a semloc feature cache")
    try:
        lengths = arrays["lengths"].astype(np.int64)
        ends = np.cumsum(lengths)
        total = int(ends[-1]) if ends.size else 0
        if np.any(lengths < 0) or any(arrays[k].shape[0] != total for k in ("bearings", "descriptors",
                                                                             "camera_index", "points")):
            raise ValueError("array lengths disagree")
        out = []
        for a, b in zip((ends - lengths).tolist(), ends.tolist()):
            out.append(FeatureSequence(arrays["bearings"][a:b], arrays["descriptors"][a:b],
                                       arrays["camera_index"][a:b], arrays["points"][a:b]))
    except (KeyError, ValueError) as error:
        raise LoopClosureFileError(f"{path}: {error}") from None
    return out, meta


def save_matrices(path, matrices: dict[str, np.ndarray], meta: dict) -> None:
    """Cache similarity matrices; ``meta`` (JSON-able) records what they were computed from."""
    _save_npz(path, matrices, {"format": "semloc.similarity_matrices", "version": 1, **meta})


def load_matrices(path) -> tuple[dict[str, np.ndarray], dict]:
    arrays, meta = _load_npz(path)
    if not meta or meta.get("format") != "semloc.similarity_matrices":
        raise LoopClosureFileError(f"{path} is not a semloc similarity-matrix cache")
    return arrays, meta


def save_topomap(path, topomap: TopologicalMap, positions=None, stamps_ns=None) -> None:
    """``.json`` or ``.graphml`` by suffix, atomically; ``positions`` (nodes, 3) planar poses of the key-frames (NaN:
    unknown) and ``stamps_ns`` their stamps, when known."""
    path = Path(path)
    if path.suffix == ".graphml":
        text = topomap.to_graphml(positions, stamps_ns)
    elif path.suffix == ".json":
        text = json.dumps(topomap.to_json_dict(positions, stamps_ns), indent=1)
    else:
        raise ValueError(f"topological map files end in .json or .graphml, got {path.name}")
    replace_text(path, text)


def load_topomap(path) -> TopologicalMap:
    path = Path(path)
    try:
        return TopologicalMap.from_json_dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise LoopClosureFileError(f"cannot read topological map {path}: {error}") from None


def read_loop_samples(folder) -> tuple[list[Path], np.ndarray]:
    """Image paths in frame order and the ground truth gt[earlier, later] (bool, strictly upper triangular).

    Layout (``rtabmap_loop_samples``): ``images/<k>.jpg`` numbered from 1 (any of jpg/png), and an N x N
    ``samples_GT.bmp`` (or ``*GT*.png``/``.bmp``) whose non-zero entry (i, j) marks a loop between frames i and j.
    """
    import cv2

    folder = Path(folder)
    image_dir = folder / "images" if (folder / "images").is_dir() else folder
    pattern = re.compile(r"^(\d+)\.(jpg|jpeg|png|bmp)$", re.IGNORECASE)
    numbered = sorted((int(m.group(1)), p) for p in image_dir.iterdir() if (m := pattern.match(p.name)))
    if not numbered:
        raise LoopClosureFileError(f"no numbered images in {image_dir}")
    images = [p for _, p in numbered]
    gt_files = sorted(p for p in folder.iterdir() if "gt" in p.stem.lower() and p.suffix.lower() in (".bmp", ".png"))
    if not gt_files:
        raise LoopClosureFileError(f"no ground-truth matrix (*GT*.bmp/png) in {folder}")
    matrix = cv2.imread(str(gt_files[0]), cv2.IMREAD_GRAYSCALE)
    if matrix is None or matrix.shape != (len(images), len(images)):
        raise LoopClosureFileError(
            f"{gt_files[0]} must be a {len(images)}x{len(images)} image, got {None if matrix is None else matrix.shape}"
        )
    loops = matrix > 0
    gt = np.triu(loops | loops.T, 1)
    return images, gt
