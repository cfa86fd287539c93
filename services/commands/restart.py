"""``semloc restart NODE``: restart one node of a running graph, asking the launcher that runs it (``semloc up``) over
the bus. The launcher stops the node's process (SIGTERM, then SIGKILL after the graph's stop_timeout_s) and starts
it again at once, whatever its restart policy: a node that gave up (max_restarts), finished, or stopped on a bad
file starts again too. ``semloc status`` then shows one restart more, reason ``operator``; workers with state go on
from it. One line per graph that answered (a graph without NODE refuses, naming its nodes); exit code 1 when no graph
restarted it, e.g.

  semloc restart detector --robot r1
"""

from __future__ import annotations

import argparse

from services.commands import add_launcher_query_arguments, ask_launchers, key_name


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # One node: a name with a wildcard would be a key expression naming several.
    parser.add_argument("node", type=key_name("node name"), metavar="NODE", help="the node's name in the graph file")
    add_launcher_query_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from schemas import keys

    replies = ask_launchers("restart", args, lambda robot: keys.all_launcher_restart(robot, args.node))
    if replies is None:
        return 1
    for ack in replies:
        print(f"{ack.header.robot}: {'ok' if ack.ok else 'refused'}: {ack.message}", flush=True)
    return 0 if any(ack.ok for ack in replies) else 1
