"""One module per `semloc` sub-command: ``add_arguments(parser)`` and ``run(args) -> int``.

Experiment commands (eval, calibrate, select-templates, train-detector) share one vocabulary
(:func:`add_spec_options`): a spec file (``--spec FILE``) or a preset (``--preset NAME``), overrides
(``--set a.b=value``), ``--cache DIR``, ``--seed N``, ``-o/--output``, ``--json`` and ``--quiet``; each builds the
experiment's spec (:func:`build_spec`), calls ``semloc_core.experiments.<experiment>.run(spec)`` and writes the
report. Command-line errors are one line, ``semloc <cmd>: <what is wrong>``, and exit code 2 (:func:`fail`).

Modules import their heavy dependencies inside ``run`` so that ``semloc --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

from semloc_core.experiments.spec import load_preset, preset_names, read_spec_file
from semloc_core.validation import one_line
from services.config import ConfigError, build, from_sets


def add_spec_options(parser: argparse.ArgumentParser, kind: str, *, example: str, output: str, seed: bool = True,
                     cache: bool = True) -> None:
    """The options every experiment command shares; ``kind`` names its presets, ``example`` a ``--set``."""
    names = preset_names(kind)
    parser.add_argument("--spec", metavar="FILE", help="spec file (YAML): the experiment's settings")
    parser.add_argument("--preset", choices=names or None, metavar="NAME",
                        help=f"a documented spec ({', '.join(names) or 'none yet'}); --spec and --set go over it")
    parser.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                        help=f"override a spec field (repeatable; YAML values), e.g. {example}")
    if cache:
        parser.add_argument("--cache", metavar="DIR", help="keep what is costly to compute here, reuse it next time")
    if seed:
        parser.add_argument("--seed", type=int, help="the spec's seed (= --set seed=N)")
    parser.add_argument("-o", "--output", required=True, help=output)
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def build_spec(args: argparse.Namespace, model, kind: str, **fields):
    """The spec: the preset < the spec file < ``fields`` given (not None) < --seed / --cache < --set.
    Raises ConfigError (one line)."""
    layers = []
    try:
        if args.preset:
            layers.append(load_preset(kind, args.preset))
        if args.spec:
            layers.append(read_spec_file(args.spec))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    common = {**fields, "seed": getattr(args, "seed", None), "cache": getattr(args, "cache", None)}
    layers.append({key: value for key, value in common.items() if value is not None})
    layers.append(from_sets(args.set))
    return build(model, *layers)


def logger(quiet: bool) -> Callable[[str], None]:
    """Progress lines on stderr (nothing with ``--quiet``)."""
    if quiet:
        return lambda message: None
    return lambda message: print(message, file=sys.stderr, flush=True)


def frame_progress(quiet: bool) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback printing "frame done/total (rate)" on stderr every 10 frames and at the
    end (a line of its own)."""
    start = time.monotonic()

    def progress(done: int, total: int) -> None:
        if not quiet and (done % 10 == 0 or done == total):
            rate = done / max(time.monotonic() - start, 1e-9)
            end = "\n" if done == total else ""
            print(f"\r  frame {done}/{total} ({rate:.1f} frames/s)", end=end, file=sys.stderr, flush=True)

    return progress


def fail(command: str, error) -> int:
    """``semloc <command>: <error>`` on stderr (one line); exit code 2."""
    print(f"semloc {command}: {one_line(error)}", file=sys.stderr, flush=True)
    return 2


def print_json(document) -> None:
    """``document`` (numpy values, dataclasses and NaN allowed) as JSON on stdout."""
    from semloc_core.eval.report import json_text

    print(json_text(document))


def key_name(what: str) -> Callable[[str], str]:
    """An argument's type: a name that is a single key chunk (schemas.base.check_name), ``what`` in its error."""
    from schemas.base import check_name

    def checked(value: str) -> str:
        try:
            return check_name(value, what)
        except ValueError as error:
            raise argparse.ArgumentTypeError(one_line(error)) from None
    return checked


def robot_or_every(value: str) -> str:
    """``--robot``'s value: a robot's name, or ``*`` for every robot on the bus (:func:`answers_of_each_robot`)."""
    return value if value == "*" else key_name("robot name")(value)


def answers(command: str, session, key: str, request, reply_type, wait: float, who: str) -> list | None:
    """The replies to an operator's query of a running graph (``services.bus.ask``), or None after one line on
    stderr - ``semloc <command>: no <who> answered on <key> ...`` or the error every answer was - for the command to
    exit 1."""
    from schemas import FrameError
    from services.bus import QueryError, ask

    try:
        replies = ask(session, key, request, reply_type=reply_type, wait=wait)
    except (QueryError, FrameError) as error:
        print(f"semloc {command}: {one_line(error)}", file=sys.stderr, flush=True)
        return None
    if not replies:
        print(f"semloc {command}: no {who} answered on {key} in {wait:g} s", file=sys.stderr, flush=True)
        return None
    return replies


def robots_on_bus(session) -> set[str]:
    """The robots whose workers' or launchers' liveliness tokens are on the bus now (a launcher's: a graph whose
    workers have not started, or wait for a restart). Valid names only: each is asked on its own keys."""
    from schemas import keys

    robots = set()
    for key in (keys.ALL_ALIVE, keys.ALL_LAUNCHERS_ALIVE):
        for reply in session.liveliness().get(key, timeout=0.5):
            if reply.ok is not None:
                robots |= {keys.robot_of(str(reply.ok.key_expr))} - {None}
    return robots


def answers_of_each_robot(command: str, session, robot: str, key_of: Callable[[str], str],
                          request_of: Callable[[str], object], reply_type, wait: float, who: str) -> list | None:
    """:func:`answers` to ``request_of(robot)`` on ``key_of(robot)``; with ``robot`` ``*``, over every robot on the
    bus (:func:`robots_on_bus`), each asked on its own keys with a request naming it. A router's access rules
    (deploy/secure/) let a query through only within one robot's keys, and a worker takes a request of its own robot
    only: one query over every robot's keys would reach nobody there. Asked again, as :func:`services.bus.ask` does,
    until something answers or ``wait`` seconds have passed (a new session meets the others' over a few hundred
    milliseconds)."""
    from schemas import FrameError, keys
    from services.bus import QueryError, query

    if robot != "*":
        return answers(command, session, key_of(robot), request_of(robot), reply_type, wait, who)
    deadline = time.monotonic() + wait
    replies, errors = [], []
    robots: set[str] = set()
    while True:
        # The robots met so far; asked only once a round meets no new one (a new session meets the others' tokens
        # one after another: asking at the first would leave the later ones out).
        met = robots_on_bus(session)
        if not robots >= met or not met:
            robots |= met
            if time.monotonic() < deadline:
                time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
                continue
        for name in sorted(robots):
            try:
                replies += query(session, key_of(name), request_of(name), reply_type=reply_type,
                                 timeout=max(0.5, deadline - time.monotonic()), every_reply=True)
            except (QueryError, FrameError) as error:
                errors.append(one_line(error))
        if replies or errors or time.monotonic() >= deadline:
            break
        time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
    if not replies:
        key = keys.for_robots(key_of, "*")
        problem = "; ".join(errors) or f"no {who} answered on {key} in {wait:g} s"
        print(f"semloc {command}: {one_line(problem)}", file=sys.stderr, flush=True)
        return None
    return replies


def add_launcher_query_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of an operator's query to the launchers of running graphs (``semloc stop``, ``semloc restart``)."""
    from services.bus import add_bus_arguments

    parser.add_argument("--robot", default="*", type=robot_or_every,
                        help="only this robot's graphs (default: every one)")
    parser.add_argument("--wait", type=float, default=5.0, help="seconds to wait for a launcher to answer")
    add_bus_arguments(parser)


def ask_launchers(command: str, args: argparse.Namespace, key_of: Callable[[str], str]) -> list | None:
    """The launchers' ``Ack`` to an operator's query with no payload on ``key_of(robot)``
    (:func:`answers_of_each_robot`, with :func:`add_launcher_query_arguments`' options), or None after one line."""
    from schemas import Ack
    from services.bus import bus_from_args, open_session

    with open_session(bus_from_args(args)) as session:
        return answers_of_each_robot(command, session, args.robot, key_of, lambda robot: None, Ack, args.wait, "graph")
