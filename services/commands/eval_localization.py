"""semloc eval localization [DATASET] -o OUT.json: particle-filter localization against the dataset's object map.

For perception model A (eq. 4.6) and B (eq. 4.27), soft and hard heatlines, and the heatline sources synthetic,
dpm and detector: the position error over time, the time to converge from global initialisation, the RMSE after
convergence, the heading error, and with kidnap the frames needed to recover. TUM files of the estimates, plots
and a Markdown table go next to OUT. DATASET: a `semloc sim` folder or sim:NAME made in memory (sim:tabletop,
sim:hall). The settings are the spec's fields (semloc_core/experiments/localization.py), e.g.

  semloc eval localization sim:hall -o out/hall.json --set sources=synthetic,dpm
  semloc eval localization --preset hall-panorama -o out/hall4k.json --cache out/cache
  semloc eval localization --preset tabletop-scene -o out/s01.json \\
      --set scenario.trajectory=data:rgbd_scenes_v2_poses/01.pose
  semloc eval localization datasets/tabletop -o out/run.json --set estimate=run/trajectory.tum   # a live run's
"""

from __future__ import annotations

import argparse

from services.commands import add_spec_options, build_spec, fail, logger, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="dataset folder (semloc sim) or sim:NAME (tabletop, hall)")
    add_spec_options(parser, "localization", example="models=B or filter.history_frames=0",
                     output="report file (JSON); TUM files, plots and a table go next to it")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments import localization
    from semloc_core.experiments.localization_report import markdown, write_report
    from semloc_core.io.dataset import DatasetError

    try:
        spec = build_spec(args, localization.LocalizationSpec, "localization", dataset=args.dataset)
        result = localization.run(spec, logger(args.quiet))
    except (ConfigError, DatasetError, OSError, ValueError, TypeError) as error:
        return fail("eval localization", error)
    report = write_report(result, args.output)
    if args.json:
        print_json(report)
    else:
        print(markdown(report))
    return 0
