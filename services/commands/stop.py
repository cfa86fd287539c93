"""``semloc stop``: stop running graphs, asking each ``semloc up`` over the bus (its launcher then stops every node
as Ctrl-C would). One line per graph that answered; exit code 1 when none did, e.g.

  semloc stop --robot r1
"""

from __future__ import annotations

import argparse

from services.bus import add_bus_arguments
from services.commands import robot_or_every


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", default="*", type=robot_or_every,
                        help="only this robot's graphs (default: every one)")
    parser.add_argument("--wait", type=float, default=5.0, help="seconds to wait for a launcher to answer")
    add_bus_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from schemas import Ack, keys
    from services.bus import bus_from_args, open_session
    from services.commands import answers_of_each_robot

    with open_session(bus_from_args(args)) as session:
        replies = answers_of_each_robot("stop", session, args.robot, keys.all_launcher_stop, lambda robot: None, Ack,
                                        args.wait, "graph")
    if replies is None:
        return 1
    for ack in replies:
        print(f"{ack.header.robot}: {ack.message}", flush=True)
    return 0 if all(ack.ok for ack in replies) else 1
