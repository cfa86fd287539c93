"""``semloc localize set-pose X Y THETA`` / ``semloc localize relocalize``: an operator's commands to a running
localizer (its ``set_initial_pose`` and ``relocalize`` queries, as nav2's AMCL takes ``/initialpose`` and
``reinitialize_global_localization``). Each answering localizer prints one line; the exit code is 1 when nothing
answered or a localizer refused, e.g.

  semloc localize set-pose 1.2 -0.4 90 --degrees --cov 0.04 0.04 0.07
  semloc localize relocalize --robot r1
"""

from __future__ import annotations

import argparse
import math

from services.bus import add_bus_arguments
from services.commands import robot_or_every

DEFAULT_WAIT_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    set_pose = sub.add_parser("set-pose", help="set the pose estimate (x, y in metres, theta in radians)",
                              description="Set the localizer's pose estimate: its particles are drawn around it. "
                                          "Its state is not `localized` before its rival_frames heatlines have "
                                          "weighed the pose.")
    set_pose.add_argument("x", type=float)
    set_pose.add_argument("y", type=float)
    set_pose.add_argument("theta", type=float)
    set_pose.add_argument("--degrees", action="store_true", help="THETA in degrees")
    set_pose.add_argument("--cov", type=float, nargs=3, metavar=("VAR_X", "VAR_Y", "VAR_THETA"),
                          help="the pose's variances (m^2, m^2, rad^2; default: the localizer's initial_covariance)")
    relocalize = sub.add_parser("relocalize", help="global relocalization: particles over the whole map",
                                description="Ask for global relocalization: the localizer spreads its particles "
                                            "over the whole map and converges again.")
    for action in (set_pose, relocalize):
        action.add_argument("--robot", default="*", type=robot_or_every,
                            help="only this robot's localizer (default: every one)")
        action.add_argument("--wait", type=float, default=DEFAULT_WAIT_S, help="seconds to wait for an answer")
        add_bus_arguments(action)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from schemas import Ack, FrameError, Header, Pose2D, keys
    from services.bus import bus_from_args, open_session
    from services.commands import answers_of_each_robot, fail

    command = f"localize {args.action}"

    def pose_of(robot: str) -> Pose2D:  # the header names the robot asked: its localizer takes no other's
        theta = math.radians(args.theta) if args.degrees else args.theta
        covariance = None if args.cov is None else np.diag(args.cov)
        return Pose2D(header=Header(robot=robot, stream="semloc localize", frame_id="world"), x=args.x, y=args.y,
                      theta=math.remainder(theta, 2 * math.pi), covariance=covariance)

    if args.action == "relocalize":
        key_of, request_of = keys.localizer_relocalize, lambda robot: None
    else:
        key_of, request_of = keys.localizer_set_initial_pose, pose_of
    try:  # a bad pose is refused before any robot is asked
        request_of("robot" if args.robot == "*" else args.robot)
    except (ValueError, FrameError) as error:
        return fail(command, error)
    with open_session(bus_from_args(args)) as session:
        replies = answers_of_each_robot(command, session, args.robot, key_of, request_of, Ack, args.wait, "localizer")
    if replies is None:
        return 1
    for ack in replies:
        print(f"{ack.header.robot}: {'ok' if ack.ok else 'refused'}: {ack.message}", flush=True)
    return 0 if all(ack.ok for ack in replies) else 1
