"""The `semloc` command: a thin dispatcher over services/commands/*, the one module outside that folder that
imports it.

Each sub-command lives in its own module (``add_arguments(parser)``, ``run(args) -> int``); this file only lists
them, in the order ``semloc --help`` shows them.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from semloc_core.io.errors import FileFormatError
from services.config import CONFIG_ERROR_EXIT, ConfigError

# command -> (its module under services/commands, its help). A command's module is imported only when the parser
# of that command is built: `semloc worker` (every node the launcher starts, again at each restart) would otherwise
# import every command's dependencies (the launcher, MCAP, cryptography, OpenCV...) before its worker's.
COMMANDS = {
    "demo": ("demo", "run the whole system on a simulated world and print the results"),
    "up": ("up", "launch a dataflow graph (deploy/*.yaml), one process per worker"),
    "status": ("status", "list live workers and their counters"),
    "localize": ("localize", "set a running localizer's pose, or ask for global relocalization"),
    "logs": ("logs", "show (and follow) the logs of a running graph's nodes"),
    "restart": ("restart", "restart one node of a running graph"),
    "stop": ("stop", "stop running graphs"),
    "worker": ("worker", "run one worker in this process"),
    "record": ("record", "record bus traffic to an MCAP file"),
    "replay": ("replay", "republish a recorded MCAP session with its original timing"),
    "map": ("map", "save a running graph's maps (semloc map save DIR)"),
    "export": ("export", "a recorded session as TUM, JSON and GraphML files"),
    "certs": ("certs", "make a development CA and the certificates of deploy/secure/"),
    "sim": ("sim", "generate a simulated dataset with exact ground truth"),
    "eval": ("evaluate", "evaluate loop closure, localization or mapping on a dataset"),
    "calibrate": ("calibrate", "fit detector score likelihoods p(z|d), p(z|not d)"),
    "calibrate-camera": ("calibrate_camera", "calibrate a camera from views of a chessboard (pinhole or fisheye)"),
    "select-templates": ("select_templates", "choose each class's exemplar views on a training world"),
    "train-detector": ("train_detector", "train the linear window detector on frames with known objects"),
    "schema": ("schema", "export the JSON Schema of every frame type"),
}


# A worker is one process and a graph runs several on the machine's cores: a BLAS thread pool in each one spins
# against the others. The loop-closure worker's vocabulary training took 8 ms of CPU per (23k x 128) x 128 product on
# two OpenBLAS threads while the other workers ran, against 0.9 ms on one; in the demo on a loaded machine its
# handler p50 fell from 1.1-2.1 s to 0.4 s. Set before numpy loads OpenBLAS; a value in the environment wins.
WORKER_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1"}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("semloc")
    except PackageNotFoundError:  # a checkout run without installing it
        return "(not installed)"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The `semloc` parser with every command, or with the command ``only`` alone (its module alone imported)."""
    parser = argparse.ArgumentParser(prog="semloc", description="Semantic localization and mapping for robots.")
    parser.add_argument("--version", action="version", version=f"semloc {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        if only is not None and name != only:
            continue
        module = importlib.import_module(f"services.commands.{module_name}")
        command_parser = sub.add_parser(name, help=help_text, description=(module.__doc__ or help_text).strip(),
                                        formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(command_parser)
        command_parser.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "worker":
        for name, value in WORKER_ENVIRONMENT.items():
            os.environ.setdefault(name, value)
    args = build_parser(argv[0] if argv and argv[0] in COMMANDS else None).parse_args(argv)
    from services.security import BusError

    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader left (`semloc status | head`): no traceback. stdout goes to devnull so the interpreter's last
        # flush does not raise again; 1, as Python's own documentation has it.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except BusError as error:
        # One line (the endpoint and the cause), no traceback. A credential problem is the caller's to fix (2, and
        # the launcher leaves such a node stopped); nothing listening yet may pass (1: restarted).
        print(f"semloc {args.command}: {error}", file=sys.stderr)
        return 1 if error.transient else CONFIG_ERROR_EXIT
    except (FileFormatError, ConfigError) as error:  # a file or setting no retry can fix: one line, no traceback
        print(f"semloc {args.command}: {error}", file=sys.stderr)
        return CONFIG_ERROR_EXIT


if __name__ == "__main__":
    sys.exit(main())
