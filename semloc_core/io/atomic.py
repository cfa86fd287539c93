"""Replacing a file atomically: the one way semloc writes a whole file (maps, snapshots, calibrations, models).

The new content goes to a temporary file beside the target (``<name>.<random>.tmp``), is fsynced, renamed over the
target, and the directory is fsynced: a reader, a crash or a power cut sees the old file or the new one, never half
of one. A write that fails (a full disk, a read-only folder, a file size limit) removes its temporary file, leaves
the target as it was, and raises ``OSError`` naming the target (``error.filename``) with the system's reason
(``error.strerror``, e.g. "No space left on device").
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO


def fsync_directory(directory) -> None:
    """Make a rename or a new file in ``directory`` durable."""
    handle = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


def remove_partial_writes(path) -> list[Path]:
    """Delete the temporary files writes of ``path`` left beside it (a process killed while writing, a folder made
    read-only mid-write); returns them."""
    path = Path(path)
    partial = sorted(path.parent.glob(f"{path.name}.*.tmp")) if path.parent.is_dir() else []
    for leftover in partial:
        leftover.unlink(missing_ok=True)
    return partial


@contextlib.contextmanager
def replacing(path) -> Iterator[BinaryIO]:
    """A binary stream whose content replaces ``path`` atomically when the block ends without an exception (see
    the module docstring); the folder is created if missing."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        while True:  # a new name: the process's umask sets its mode, as for any file it creates (mkstemp: 0600)
            name = path.with_name(f"{path.name}.{secrets.token_hex(4)}.tmp")
            try:
                fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                continue
            tmp = name
            break
        with os.fdopen(fd, "wb") as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
        tmp = None
        fsync_directory(path.parent)
    except OSError as error:
        raise OSError(error.errno, error.strerror or str(error), str(path)) from error
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def replace_bytes(path, data: bytes) -> Path:
    """Replace ``path`` with ``data``, atomically."""
    with replacing(path) as stream:
        stream.write(data)
    return Path(path)


def replace_text(path, text: str) -> Path:
    """Replace ``path`` with ``text`` (UTF-8), atomically."""
    return replace_bytes(path, text.encode("utf-8"))
