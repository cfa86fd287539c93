"""semloc eval loopclosure [DATASET] -o OUT.json: loop-closure precision-recall and the topological map.

For the DP score and the three baselines (M^SIFT, M^SYM, BoW TF-IDF): PR raw and after batch inference, AP, recall
at 100 % precision; the incremental engine on the same features; the map's figures. PNG plots, the engine's map
and a Markdown table go next to OUT. DATASET: a `semloc sim` folder, scenario:NAME[:key=value,...] rendered on the
fly, or an image folder with a ground-truth loop matrix. The settings are the spec's fields
(semloc_core/experiments/loopclosure.py), e.g.

  semloc eval loopclosure datasets/route -o out/route/eval.json --cache out/cache --set jobs=1
  semloc eval loopclosure --preset rtabmap-samples -o out/rtabmap/eval.json --set features.t_match=1000
"""

from __future__ import annotations

import argparse

from services.commands import add_spec_options, build_spec, fail, logger, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="dataset folder, scenario:NAME[:k=v,...] or image folder")
    add_spec_options(parser, "loopclosure", example="window=20 or mrf.potential=thesis", seed=False,
                     output="report file (JSON); plots, the engine's map and a table go next to it")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments import loopclosure
    from semloc_core.experiments.loopclosure import LoopClosureSpec

    log = logger(args.quiet)
    try:
        spec = build_spec(args, LoopClosureSpec, "loopclosure", dataset=args.dataset)
        result = loopclosure.run(spec, log)
    except (ConfigError, ValueError, OSError) as error:
        return fail("eval loopclosure", error)
    loopclosure.write_report(result, args.output)
    log(f"wrote {args.output}")
    if args.json:
        print_json(result.report)
    else:
        print(loopclosure.markdown(result))
    return 0
