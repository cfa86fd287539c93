"""``semloc logs [WORKER] [-f]``: the nodes' logs of a running graph, asked of its launcher over the bus (each
``semloc up`` keeps its nodes' output in RUN_DIR/logs/ and answers for them). Without WORKER, every node's, each
line prefixed with its node; ``-f`` follows them until the graph stops or Ctrl-C. Exit code 1 when no launcher
answered (or it has no such node), e.g.

  semloc logs localizer -f
  semloc logs --robot r1 --tail 20000
"""

from __future__ import annotations

import argparse
import sys
import time

from services.bus import add_bus_arguments
from services.commands import robot_or_every

FOLLOW_PERIOD_S = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("worker", nargs="?", default="", help="the node whose log to show (default: every node)")
    parser.add_argument("-f", "--follow", action="store_true", help="keep printing what the logs get")
    parser.add_argument("--tail", type=int, default=8192, metavar="BYTES",
                        help="how much of the end of each log to show first (default 8192)")
    parser.add_argument("--robot", default="*", type=robot_or_every,
                        help="only this robot's launchers (default: every one)")
    parser.add_argument("--wait", type=float, default=5.0, help="seconds to wait for a launcher to answer")
    add_bus_arguments(parser)


def _print(tail, prefix: bool) -> None:
    for node, chunk in tail.logs.items():
        for line in chunk.text.splitlines(keepends=True):
            sys.stdout.write(f"[{node}] {line}" if prefix else line)
    sys.stdout.flush()


def run(args: argparse.Namespace) -> int:
    from schemas import FrameError, Header, keys
    from schemas.status import LogRequest, LogTail
    from services.bus import QueryError, bus_from_args, open_session, query
    from services.commands import answers_of_each_robot, fail

    if not 0 <= args.tail <= 1 << 20:
        return fail("logs", f"--tail must be within 0 .. {1 << 20} bytes, got {args.tail}")

    def request_of(robot: str, offsets: dict[str, int] | None = None) -> LogRequest:
        return LogRequest(header=Header(robot=robot, stream="semloc logs"), node=args.worker, offsets=offsets or {},
                          tail_bytes=args.tail)

    with open_session(bus_from_args(args)) as session:
        tails = answers_of_each_robot("logs", session, args.robot, keys.all_launcher_logs, request_of, LogTail,
                                      args.wait, "launcher")
        if tails is None:
            return 1
        prefix = not args.worker or len(tails) > 1
        for tail in tails:
            if not tail.logs:
                print(f"semloc logs: graph {tail.graph} keeps no log files (semloc up --console)", file=sys.stderr)
            _print(tail, prefix)
        if not args.follow:
            return 0
        # Follow each launcher from where its logs ended, on the key its robot and launcher name make (not the
        # stream its reply names: that came off the bus, and would send the next requests anywhere); a launcher
        # that stops answering has stopped.
        offsets = {keys.launcher_logs(tail.header.robot, tail.launcher):
                   (tail, {node: chunk.end for node, chunk in tail.logs.items()}) for tail in tails}
        while offsets:
            try:
                time.sleep(FOLLOW_PERIOD_S)
            except KeyboardInterrupt:
                return 0
            for stream, (tail, ends) in list(offsets.items()):
                request = request_of(tail.header.robot, ends)
                try:
                    [fresh] = query(session, stream, request, reply_type=LogTail, timeout=2.0) or [None]
                except (QueryError, FrameError):
                    fresh = None
                if fresh is None:
                    print(f"semloc logs: graph {tail.graph} stopped answering", file=sys.stderr)
                    del offsets[stream]
                    continue
                _print(fresh, prefix)
                ends.update({node: chunk.end for node, chunk in fresh.logs.items()})
        return 0
