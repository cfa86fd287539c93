"""Atomic state snapshots for workers whose state must survive a crash (topological map, voxel map, pose).

A snapshot is one ``.npz`` file (no pickle) holding named arrays plus a JSON document under the reserved name
``__meta__``. It is written to a temporary file in the same directory, fsynced, then renamed over the old one, so a
crash at any moment leaves either the previous snapshot or the new one, never a torn file. ``journal_segment`` is
where the worker's journal (services/journal.py) continues: the snapshot holds every record of the segments before
it. A snapshot that cannot be used is never overwritten: :func:`set_aside` renames it (and what belongs to it).
A disk that refuses writes (:func:`refused_write`: read-only, full) makes no snapshot unusable.
"""

from __future__ import annotations

import errno
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from semloc_core.io.atomic import fsync_directory, replacing

META = "__meta__"
JOURNAL = "__journal__"
RESERVED = (META, JOURNAL)
# A disk that refuses writes: read-only (remounted so after an I/O error), full, over a quota or a file size limit,
# not writable by this user. A state file read from it is as good as it was.
REFUSED_WRITES = frozenset({errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES})


class StateError(ValueError):
    """A snapshot file is unreadable or malformed."""


@dataclass
class State:
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    journal_segment: int = 0  # the first journal segment not in this snapshot


def save_state(path: str | Path, state: State) -> Path:
    path = Path(path)
    for name in RESERVED:
        if name in state.arrays:
            raise ValueError(f"array name {name!r} is reserved")
    for name, array in state.arrays.items():
        if np.asarray(array).dtype.hasobject:
            raise ValueError(f"state array {name!r} has dtype object; only plain numeric arrays are stored")
    meta = np.frombuffer(json.dumps(state.meta, allow_nan=False).encode(), dtype=np.uint8)
    journal = np.array(int(state.journal_segment), np.int64)
    with replacing(path) as stream:
        np.savez(stream, **{META: meta, JOURNAL: journal}, **{k: np.asarray(v) for k, v in state.arrays.items()})
    return path


def load_state(path: str | Path) -> State | None:
    """The snapshot at ``path``, or None if there is none. Raises :class:`StateError` if it is corrupt."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
        meta = json.loads(arrays.pop(META).tobytes().decode()) if META in arrays else {}
        if not isinstance(meta, dict):
            raise ValueError("its metadata is not a JSON object")
        journal = arrays.pop(JOURNAL, np.array(0))
        if journal.shape != () or journal.dtype.kind not in "iu" or int(journal) < 0:
            raise ValueError("bad journal position")
    except Exception as error:
        raise StateError(f"cannot read state snapshot {path}: {error}") from None
    return State(arrays=arrays, meta=meta, journal_segment=int(journal))


def refused_write(error: BaseException | None) -> OSError | None:
    """The OSError in ``error`` or what caused it that is a disk refusing a write (``REFUSED_WRITES``), if any."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, OSError) and error.errno in REFUSED_WRITES:
            return error
        seen.add(id(error))
        # (a context suppressed, ``raise ... from None``, is not a cause: load_state's read error is its own)
        error = error.__cause__ if error.__cause__ is not None or error.__suppress_context__ else error.__context__
    return None


def set_aside(paths, stamp: str | None = None) -> list[Path]:
    """Rename each existing path (a snapshot and what belongs to it: its journal, its store) to
    ``<name>.corrupt-<UTC time>``, never replacing anything; returns the new paths."""
    stamp = stamp or time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    moved = []
    for path in map(Path, paths):
        if not path.exists():
            continue
        target = path.with_name(f"{path.name}.corrupt-{stamp}")
        counter = 1
        while target.exists():
            target = path.with_name(f"{path.name}.corrupt-{stamp}-{counter}")
            counter += 1
        path.rename(target)
        moved.append(target)
    if moved:
        fsync_directory(moved[0].parent)
    return moved
