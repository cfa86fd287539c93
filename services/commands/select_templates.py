"""semloc select-templates [DATASET] -o LIBRARY: choose each class's exemplar views on a training world.

Matches every candidate exemplar (default: the dataset's exemplars/ and exemplars_multiview/, each with its
mirror) over the dataset's frames once, then keeps per class the views that find its objects best (greedy forward
selection). Writes LIBRARY as a template library with LIBRARY/detector.yaml (ready as a detector configuration) and
LIBRARY/selection.json (every step). Use a world other than the one you evaluate on: this is training. The settings
are the spec's fields (semloc_core/experiments/template_selection.py), e.g.

  semloc select-templates worlds/hall_train -o library/hall --set detector_settings={cell: 4, template_cells: 9}
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.commands import add_spec_options, build_spec, fail, frame_progress, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="a semloc dataset folder with per-frame object ground truth")
    add_spec_options(parser, "select-templates", example="max_per_class=2 or detector_settings.cell=4", seed=False,
                     cache=False, output="template library folder to write")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments import template_selection as selection
    from semloc_core.io.dataset import DatasetError
    from semloc_core.io.detector_models import DetectorModelError

    try:
        spec = build_spec(args, selection.SelectionSpec, "select-templates", dataset=args.dataset)
        chosen = selection.run(spec, frame_progress(args.quiet))
    except (ConfigError, DatasetError, DetectorModelError, OSError, ValueError) as error:
        return fail("select-templates", error)
    record = selection.write_library(Path(args.output), chosen)
    if args.json:
        print_json(record)
        return 0
    for class_name, steps in record["classes"].items():
        last = steps[-1]
        print(f"{class_name:>16s}: {len(steps)} view(s), {last['hits']}/{last['hits'] + last['misses']} found on the "
              f"training frames: {', '.join(Path(s['source']).name for s in steps)}")
    print(f"wrote {args.output}")
    return 0
