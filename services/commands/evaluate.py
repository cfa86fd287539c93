"""`semloc eval loopclosure|localization|mapping DATASET ... --json OUT`: a thin dispatcher.

Each evaluation lives in its own module, ``services/commands/eval_<kind>.py``, owned by the engineer of that
capability. The interface (docs/evaluation.md):

* ``add_arguments(parser)``: declare the positional ``dataset`` and ``--json`` (required) plus its own options;
* ``run(args) -> int``: evaluate, write every figure to the JSON file at ``args.json`` (PNG plots and a Markdown
  table next to it), return the exit status (0 = success, 2 = bad input).

A kind whose module is absent is not offered. Modules import heavy dependencies inside ``run``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util

KINDS: dict[str, tuple[str, str]] = {
    "loopclosure": ("services.commands.eval_loopclosure", "loop-closure precision/recall and the topological map"),
    "localization": ("services.commands.eval_localization", "localization error over time, convergence, heading"),
    "mapping": ("services.commands.eval_mapping", "object-map precision/recall per class"),
}


def available_kinds() -> dict[str, tuple[str, str]]:
    return {kind: spec for kind, spec in KINDS.items() if importlib.util.find_spec(spec[0]) is not None}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kind", metavar="KIND", required=True)
    for kind, (module_name, help_text) in available_kinds().items():
        module = importlib.import_module(module_name)
        kind_parser = sub.add_parser(kind, help=help_text, description=(module.__doc__ or help_text).strip())
        module.add_arguments(kind_parser)
        kind_parser.set_defaults(_eval_run=module.run)


def run(args: argparse.Namespace) -> int:
    return int(args._eval_run(args) or 0)
