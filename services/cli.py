"""The `semloc` command: a thin dispatcher over services/commands/*.

Each sub-command lives in its own module (``add_arguments(parser)``, ``run(args) -> int``); this file only lists
them, in the order ``semloc --help`` shows them.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from semloc_core.io.errors import FileFormatError
from services.config import CONFIG_ERROR_EXIT, ConfigError

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("services.commands.demo", "run the whole system on a simulated world and print the results"),
    "up": ("services.commands.up", "launch a dataflow graph (deploy/*.yaml), one process per worker"),
    "status": ("services.commands.status", "list live workers and their counters"),
    "worker": ("services.commands.worker", "run one worker in this process"),
    "record": ("services.commands.record", "record bus traffic to an MCAP file"),
    "replay": ("services.commands.replay", "republish a recorded MCAP session with its original timing"),
    "certs": ("services.commands.certs", "make a development CA and the certificates of deploy/secure/"),
    "sim": ("services.commands.sim", "generate a simulated dataset with exact ground truth"),
    "eval": ("services.commands.evaluate", "evaluate loop closure, localization or mapping on a dataset"),
    "calibrate": ("services.commands.calibrate", "fit detector score likelihoods p(z|d), p(z|not d)"),
    "select-templates": ("services.commands.select_templates", "choose each class's exemplar views on a training world"),
    "train-detector": ("services.commands.train_detector", "train the linear window detector on frames with known objects"),
    "schema": ("services.commands.schema", "export the JSON Schema of every frame type"),
}


def _available() -> dict[str, tuple[str, str]]:
    return {name: spec for name, spec in COMMANDS.items() if importlib.util.find_spec(spec[0]) is not None}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="semloc", description="Semantic localization and mapping for robots.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in _available().items():
        module = importlib.import_module(module_name)
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(command_parser)
        command_parser.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from services.security import BusError

    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
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
