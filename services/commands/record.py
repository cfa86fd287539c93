"""``semloc record -k 'semloc/**' -o session.mcap [--foxglove]``: record bus traffic (exact payloads) to MCAP, and
with ``--foxglove`` Foxglove-readable copies of images, poses, object maps and heatlines."""

from __future__ import annotations

import signal
import sys
import threading
import time

from services.bus import add_bus_arguments, bus_from_args, open_session
from services.recording import Recorder


def add_arguments(parser) -> None:
    parser.add_argument("-k", "--key", default="semloc/**", help="key expression to record (default semloc/**)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--count", type=int, help="stop after this many messages")
    parser.add_argument("--compress", action="store_true", help="zstd-compress MCAP chunks")
    parser.add_argument("--foxglove", action="store_true", help="also write images, poses, the object map and "
                        "heatlines in Foxglove's schemas (docs/ros2.md)")
    add_bus_arguments(parser)


def run(args) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open_session(bus_from_args(args)) as session:
        recorder = Recorder(session, args.key, args.output, compress=args.compress, foxglove=args.foxglove)
        print(f"recording {args.key} to {args.output} (Ctrl-C to stop)", file=sys.stderr, flush=True)
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
    print(f"recorded {recorder.count} messages to {args.output}", file=sys.stderr)
    return 0
