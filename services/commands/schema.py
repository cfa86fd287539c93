"""``semloc schema``: export the JSON Schema of every frame type (schemas/jsonschema/ by default)."""

from __future__ import annotations

import sys
from pathlib import Path

from schemas import export


def add_arguments(parser) -> None:
    parser.add_argument("-o", "--output", type=Path, default=export.DEFAULT_DIR, help="output directory")
    parser.add_argument("--check", action="store_true", help="only report differences; exit 1 if any")


def run(args) -> int:
    if args.check:
        problems = export.differences(args.output)
        for problem in problems:
            print(problem, file=sys.stderr)
        return 1 if problems else 0
    for path in export.write(args.output):
        print(path)
    return 0
