"""One module per `semloc` sub-command: ``add_arguments(parser)`` and ``run(args) -> int``.

Modules import their heavy dependencies inside ``run`` so that ``semloc --help`` stays fast.
"""

import sys
import time
from collections.abc import Callable


def strided_frames(count: int, stride: int, limit: int | None) -> list[int]:
    """Every ``stride``-th frame index of a data set of ``count`` frames, at most ``limit`` of them."""
    return list(range(0, count, stride))[:limit]


def frame_progress(total: int, quiet: bool) -> Callable[[int], None]:
    """A ``progress(done)`` callback printing "frame done/total (rate)" on stderr every 10 frames and at the end."""
    start = time.monotonic()

    def progress(done: int) -> None:
        if not quiet and (done % 10 == 0 or done == total):
            rate = done / max(time.monotonic() - start, 1e-9)
            print(f"\r  frame {done}/{total} ({rate:.1f} frames/s)", end="", file=sys.stderr, flush=True)

    return progress
