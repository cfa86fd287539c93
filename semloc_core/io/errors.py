"""The one error type of a file semloc cannot use, and one-line descriptions of what is wrong in it.

Every file format's error (``MapFormatError``, ``CameraFormatError``, ``DetectorModelError``, ...) is a
:class:`FileFormatError`: its message is one line naming the file, the field at fault (when there is one) and what
is wrong, e.g. ``map.json: objects[0].position[0]: Input should be a finite number (got inf)``. A worker whose file
is bad ends with exit code 2 and that line, and is not restarted (restarting cannot fix a file).
"""

from __future__ import annotations


def one_line(text) -> str:
    """``text`` on one line: newlines and runs of blanks become single spaces."""
    return " ".join(str(text).split())


class FileFormatError(ValueError):
    """A file that cannot be read, does not follow its format, or holds values outside its ranges. The message is
    made one line (see the module docstring); say the file, the field and what is wrong."""

    def __init__(self, message):
        super().__init__(one_line(message))


def field_path(location) -> str:
    """``("objects", 0, "position", 1)`` -> ``objects[0].position[1]`` (a pydantic error location)."""
    text = ""
    for part in location:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "<document>"


def describe_validation(error, limit: int = 3) -> str:
    """One line of a pydantic ``ValidationError``: ``field: what is wrong (got value)`` for its first ``limit``
    errors."""
    parts = []
    for item in error.errors(include_url=False)[:limit]:
        got = item.get("input")
        # nothing to show: no one value (a whole document, a field that is missing)
        whole = isinstance(got, (dict, list)) or got is None or not item["loc"] or item["type"] == "missing"
        shown = "" if whole else f" (got {one_line(repr(got))[:40]})"
        message = item["msg"].removeprefix("Value error, ")
        parts.append(f"{field_path(item['loc'])}: {message}{shown}")
    more = error.error_count() - limit
    return "; ".join(parts) + (f" (+{more} more)" if more > 0 else "")
