"""One-line descriptions of what is wrong in a value: what a settings class, a file reader and a worker's
configuration say when pydantic refuses a value (``objects[0].position[0]: Input should be a finite number (got
inf)``). A leaf module: it imports nothing of semloc, so every package may use it."""

from __future__ import annotations


def one_line(text) -> str:
    """``text`` on one line: newlines and runs of blanks become single spaces."""
    return " ".join(str(text).split())



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
