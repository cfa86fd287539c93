"""``semloc stop``: stop running graphs, asking each ``semloc up`` over the bus (its launcher then stops every node
as Ctrl-C would). One line per graph that answered; exit code 1 when none did, e.g.

  semloc stop --robot r1
"""

from __future__ import annotations

import argparse

from services.commands import add_launcher_query_arguments, ask_launchers


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_launcher_query_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from schemas import keys

    replies = ask_launchers("stop", args, keys.all_launcher_stop)
    if replies is None:
        return 1
    for ack in replies:
        print(f"{ack.header.robot}: {ack.message}", flush=True)
    return 0 if all(ack.ok for ack in replies) else 1
