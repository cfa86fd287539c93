"""semloc eval mapping [DATASET] -o OUT.json: the voxel mapper's object map against ground truth (thesis ch. 5).

Heatmaps of the scenes' frames are back-projected along the ground-truth poses into a voxel grid over the table,
objects are extracted and matched to the ground-truth objects: per class and scene, precision, recall, false
positives, position errors. With calibration.fit the extraction is fitted on these scenes and written as
<stem>_calibration.json; localize.trajectory closes the loop (a trajectory localized with the mapped and the
ground-truth map). Maps, top views and a Markdown table go next to OUT. DATASET: a `semloc sim` folder, or
tabletop to render scenes on the fly, one per entry of trajectories. The settings are the spec's fields
(semloc_core/experiments/mapping.py), e.g.

  semloc eval mapping --preset calibrate-templates -o out/cal/cal.json --cache out/hm
  semloc eval mapping --preset real-templates -o out/all/all.json --cache out/hm \\
      --set calibration.file=out/cal/cal_calibration.json
  semloc eval mapping tabletop -o out/o.json --set trajectories=[orbit:100] --set heatmaps=oracle
"""

from __future__ import annotations

import argparse

from services.commands import add_spec_options, build_spec, fail, logger, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="a semloc sim dataset folder, or 'tabletop' (rendered on the fly)")
    add_spec_options(parser, "mapping", example="heatmaps=both or extraction.position=centroid",
                     output="report file (JSON); maps, top views and a table go next to it")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments import mapping
    from semloc_core.experiments.mapping_report import markdown, write_report

    try:
        spec = build_spec(args, mapping.MappingSpec, "mapping", dataset=args.dataset)
        result = mapping.run(spec, logger(args.quiet))
    except (ConfigError, OSError, ValueError, TypeError) as error:
        return fail("eval mapping", error)
    write_report(result, args.output)
    if args.json:
        print_json(result.report)
    else:
        print(markdown(result))
    return 0
