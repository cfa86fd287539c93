"""`semloc eval loopclosure|localization|mapping [DATASET] -o OUT.json`: one evaluation per module
(``eval_<kind>.py``), each a spec (``--spec``, ``--preset``, ``--set``) run by ``semloc_core.experiments``."""

from __future__ import annotations

import argparse

from services.commands import eval_localization, eval_loopclosure, eval_mapping

KINDS = {
    "loopclosure": (eval_loopclosure, "loop-closure precision/recall and the topological map"),
    "localization": (eval_localization, "localization error over time, convergence, heading"),
    "mapping": (eval_mapping, "object-map precision/recall per class"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kind", metavar="KIND", required=True)
    for kind, (module, help_text) in KINDS.items():
        kind_parser = sub.add_parser(kind, help=help_text, description=(module.__doc__ or help_text).strip(),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(kind_parser)
        kind_parser.set_defaults(_eval_run=module.run)


def run(args: argparse.Namespace) -> int:
    return int(args._eval_run(args) or 0)
