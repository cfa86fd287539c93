"""``semloc record -k 'semloc/**' -o session.mcap [--foxglove]``: record bus traffic (exact payloads) to MCAP, and
with ``--foxglove`` Foxglove-readable copies of images, poses, object maps and heatlines. ``--split 500MB`` (or
``10min``): a folder of numbered complete splits (``session/session_0.mcap``, ...), ``--keep N`` of them at most
(services/recording.py, Recorder)."""

from __future__ import annotations

import argparse
import re
import signal
import sys
import threading
import time

from services.bus import add_bus_arguments, bus_from_args, open_session
from services.commands import fail
from services.recording import Recorder


SPLIT_UNITS = {"kb": ("bytes", 1e3), "mb": ("bytes", 1e6), "gb": ("bytes", 1e9), "s": ("s", 1.0), "min": ("s", 60.0),
               "h": ("s", 3600.0)}


def split_limit(text: str) -> tuple[str, float | int]:
    """``500MB`` -> ("bytes", 5e8), ``10min`` -> ("s", 600.0): a ``--split`` value."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*([a-zA-Z]+)\s*", text)
    if not match or match.group(2).lower() not in SPLIT_UNITS or float(match.group(1)) <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a positive size or time with its unit "
                                         f"({', '.join(SPLIT_UNITS)}), e.g. 500MB or 10min")
    kind, scale = SPLIT_UNITS[match.group(2).lower()]
    value = float(match.group(1)) * scale
    return kind, int(value) if kind == "bytes" else value


def add_arguments(parser) -> None:
    parser.add_argument("-k", "--key", default="semloc/**", help="key expression to record (default semloc/**)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write, not one that exists (split: the "
                        "folder of the splits, a trailing .mcap dropped)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--count", type=int, help="stop after this many messages")
    parser.add_argument("--split", action="append", type=split_limit, metavar="SIZE|TIME",
                        help="begin a new split file after this much: 500MB, 2GB, 600s, 10min, 1h (repeatable: "
                             "whichever comes first)")
    parser.add_argument("--keep", type=int, metavar="N", help="with --split: keep the newest N splits (the open one "
                        "included), deleting the oldest")
    parser.add_argument("--compress", action="store_true", help="zstd-compress MCAP chunks")
    parser.add_argument("--foxglove", action="store_true", help="also write images, poses, the object map and "
                        "heatlines in Foxglove's schemas (docs/ros2.md)")
    add_bus_arguments(parser)


def run(args) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    limits = dict(args.split or ())
    if args.keep is not None and not limits:
        return fail("record", "--keep needs --split (the splits it keeps)")
    with open_session(bus_from_args(args)) as session:
        try:
            recorder = Recorder(session, args.key, args.output, compress=args.compress, foxglove=args.foxglove,
                                split_bytes=limits.get("bytes"), split_s=limits.get("s"), keep=args.keep)
        except (ValueError, OSError) as error:  # OSError: the file cannot be made (its message names it)
            return fail("record", error.strerror if isinstance(error, OSError) and error.strerror else error)
        where = recorder.folder if recorder.splitting else args.output
        print(f"recording {args.key} to {where} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        start = time.monotonic()
        try:
            while not stop.is_set():
                if args.duration is not None and time.monotonic() - start >= args.duration:
                    break
                if args.count is not None and recorder.count >= args.count:
                    break
                if recorder.error:
                    break
                stop.wait(0.05)
        finally:
            recorder.close()
    if recorder.error:
        print(f"semloc record: {recorder.error}; the recording ends there ({recorder.count} messages, the last chunk's "
              f"lost, and {recorder.lost} after it)", file=sys.stderr)
        return 1
    splits = f" in {len(recorder.files)} splits ({recorder.deleted} older deleted)" if recorder.splitting else ""
    print(f"recorded {recorder.count} messages to {where}{splits}", file=sys.stderr)
    return 0
