"""An image folder's timestamps file: one ``<seconds> [file name]`` per line (the camera worker's folder source)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from semloc_core.io.errors import FileFormatError


class TimestampsFormatError(FileFormatError):
    """A timestamps file that cannot be read or does not fit its images."""


def read_timestamps(path, names: list[str]) -> list[int]:
    """Per-image stamps in ns from a text file: one ``<seconds> [file name]`` per line ('#' comments).

    With file names, lines are matched by name (every image needs one); without, line i is image i.
    """
    path = Path(path)
    stamps: dict[str, int] = {}
    ordered: list[int] = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise TimestampsFormatError(f"{path}: cannot read it ({error})") from None
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            seconds = float(parts[0])
        except ValueError:
            raise TimestampsFormatError(f"{path}:{number}: expected '<seconds> [file name]', got {line!r}") from None
        if not np.isfinite(seconds) or seconds < 0:
            raise TimestampsFormatError(f"{path}:{number}: bad timestamp {parts[0]!r}")
        ns = int(round(seconds * 1e9))
        if len(parts) > 1:
            stamps[Path(parts[1]).name] = ns
        else:
            ordered.append(ns)
    if stamps:
        missing = [n for n in names if n not in stamps]
        if missing:
            raise TimestampsFormatError(f"{path}: no timestamp for {len(missing)} images, e.g. {missing[0]}")
        result = [stamps[n] for n in names]
    else:
        if len(ordered) < len(names):
            raise TimestampsFormatError(f"{path}: {len(ordered)} timestamps for {len(names)} images")
        result = ordered[: len(names)]
    if any(b < a for a, b in zip(result, result[1:])):
        raise TimestampsFormatError(f"{path}: timestamps are not in increasing order")
    return result
