"""Atomic state snapshots for workers whose state must survive a crash (topological map, voxel map, pose).

A snapshot is one ``.npz`` file (no pickle) holding named arrays plus a JSON document under the reserved name
``__meta__``. It is written to a temporary file in the same directory, fsynced, then renamed over the old one, so a
crash at any moment leaves either the previous snapshot or the new one, never a torn file.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

META = "__meta__"


class StateError(ValueError):
    """A snapshot file is unreadable or malformed."""


@dataclass
class State:
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)


def save_state(path: str | Path, state: State) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if META in state.arrays:
        raise ValueError(f"array name {META!r} is reserved")
    for name, array in state.arrays.items():
        if np.asarray(array).dtype.hasobject:
            raise ValueError(f"state array {name!r} has dtype object; only plain numeric arrays are stored")
    meta = np.frombuffer(json.dumps(state.meta, allow_nan=False).encode(), dtype=np.uint8)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as stream:
            np.savez(stream, **{META: meta}, **{k: np.asarray(v) for k, v in state.arrays.items()})
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
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
    except Exception as error:
        raise StateError(f"cannot read state snapshot {path}: {error}") from None
    return State(arrays=arrays, meta=meta)
