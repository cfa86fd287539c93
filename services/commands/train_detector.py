"""semloc train-detector [DATASET] -o MODEL_DIR: train the linear window detector on frames with known objects.

Learns per class a linear filter over the §4.3 cell features whose heat peaks where an object's 3-D centre projects,
from a training world: a `semloc sim` folder with per-frame object ground truth, or tabletop (default
trajectories: the six simulator walks orbit:200 ... orbit:205, not the orbits the mapping evaluation calibrates
on). Writes MODEL_DIR/model.npz, MODEL_DIR/detector.yaml (kind: linear, ready as a detector configuration) and
MODEL_DIR/training.json. Use worlds other than the ones you evaluate on: this is training. The settings are the
spec's fields (semloc_core/experiments/detector_training.py), e.g.

  semloc train-detector tabletop -o models/tabletop
  semloc train-detector tabletop -o models/quick --set trajectories=[orbit:200] --set stride=8
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.commands import add_spec_options, build_spec, fail, logger, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="a semloc dataset folder with per-frame object ground truth, or "
                                                   "'tabletop'")
    add_spec_options(parser, "train-detector", example="rounds=3 or trajectories=[orbit:200]", cache=False,
                     output="model folder to write (model.npz, detector.yaml, training.json)")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments import detector_training as training

    log = logger(args.quiet)
    try:
        spec = build_spec(args, training.TrainingSpec, "train-detector", dataset=args.dataset)
        model = training.run(spec, log)
    except (ConfigError, OSError, ValueError) as error:
        return fail("train-detector", error)
    out = Path(args.output)
    detector_file = training.write_model(model, out)
    if args.json:
        print_json(model.info)
        return 0
    for name, stats in model.info["classes"].items():
        log(f"  {name}: window {stats['window']}, {stats['positives']} positives, {stats['negatives']} negatives, "
            f"training recall {stats['train_positive_recall']:.3f}, false {stats['train_negative_false']:.4f}")
    log(f"wrote {out / 'model.npz'} and {detector_file} ({model.info['seconds']:.0f} s)")
    return 0
