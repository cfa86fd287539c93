"""``semloc replay session.mcap [--speed X]``: republish a recorded session with its original timing (a folder of
splits, ``semloc record --split``: its files in order, as one session).

A robot log (ROS 1 bag, ROS 2 bag, ROS 2 MCAP) is replayed as the camera worker's frames; the camera worker's
settings for it are given with ``--set``: ``camera`` (the camera name in the keys, default front), ``topic`` (the
image topic, default the only one), ``log.*`` (odometry topic, frames; docs/ros2.md)."""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

from schemas.keys import DEFAULT_ROBOT
from services.bus import add_bus_arguments, bus_from_args, open_session
from services.config import ConfigError, build, from_sets
from services.camera_sources import SourceError
from services.recording import DEFAULT_REPLAY_EXCLUDE, is_robot_log, is_split_recording, replay


def add_arguments(parser) -> None:
    parser.add_argument("input", help="MCAP file written by `semloc record` (or its folder of splits, played in "
                        "order as one session), or a robot log (ROS 1 bag, ROS 2 bag, "
                        "ROS 2 MCAP) replayed as the camera worker's frames (docs/ros2.md)")
    parser.add_argument("--robot", default=DEFAULT_ROBOT,
                        help=f"robot log: robot name of the keys (default {DEFAULT_ROBOT}, the deploy graphs')")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="robot log: a camera worker setting, camera=NAME (default front), topic=TOPIC (default: "
                             "the only one) or log.FIELD=VALUE")
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("-k", "--key", action="append", help="only keys matching this (repeatable; * and **)")
    parser.add_argument("--exclude", action="append", help="skip keys matching this (repeatable)")
    parser.add_argument("--include-status", action="store_true", help="also replay recorded Status frames")
    parser.add_argument("--loop", action="store_true", help="start over at the end")
    parser.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="SECONDS",
                        help="wait up to SECONDS for every key to have a subscriber before starting (then "
                             "names the keys nobody subscribes to)")
    add_bus_arguments(parser)


def run(args) -> int:
    robot_log = is_robot_log(args.input)
    if not Path(args.input).is_file() and not robot_log and not is_split_recording(args.input):
        print(f"semloc replay: no such file {args.input}", file=sys.stderr)
        return 2
    if args.speed <= 0:
        print("semloc replay: --speed must be positive", file=sys.stderr)
        return 2
    from services.ros2.logs import LogTopics

    try:
        settings = from_sets(args.set)
        if unknown := sorted(set(settings) - {"camera", "topic", "log"}):
            raise ConfigError(f"--set {unknown[0]}: not a robot log setting (camera, topic, log.*)")
        topics = build(LogTopics, settings.get("log") or {})
    except ConfigError as error:
        print(f"semloc replay: {error}", file=sys.stderr)
        return 2
    robot_log_settings = {"robot": args.robot, "camera": str(settings.get("camera", "front")),
                          "topic": settings.get("topic"), "topics": topics}
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    exclude = tuple(args.exclude or ()) + (() if args.include_status else DEFAULT_REPLAY_EXCLUDE)
    with open_session(bus_from_args(args)) as session:
        try:
            sent = replay(session, args.input, speed=args.speed, include=tuple(args.key or ("**",)), exclude=exclude,
                          wait_for_subscribers_s=args.wait_for_subscribers, stop=stop, loop=args.loop,
                          robot_log=robot_log_settings if robot_log else None)
        except SourceError as error:
            print(f"semloc replay: {error}", file=sys.stderr)
            return 2
    if not sent and not stop.is_set():
        print(f"semloc replay: nothing to replay in {args.input} (no message on the keys asked for)", file=sys.stderr)
        return 1
    print(f"replayed {sent} messages from {args.input}", file=sys.stderr)
    return 0
