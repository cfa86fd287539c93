"""`semloc train-detector DATASET -o MODEL_DIR`: train the linear window detector on frames with known objects.

Learns per class a linear filter over the §4.3 cell features whose heat peaks where an object's 3-D centre projects
(``semloc_core.detection.linear``), from a training world: a ``semloc sim`` folder with per-frame object ground
truth, or ``tabletop`` with ``--trajectory orbit:SEED ...`` (the simulator's calibration walks, as ``semloc eval
mapping`` calibrates on). Writes ``MODEL_DIR/model.npz`` and ``MODEL_DIR/detector.yaml`` (``kind: linear``, ready
for ``--detector`` and the detector worker's ``detector_file``). Use worlds other than the ones you evaluate on:
this is training.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import yaml

DEFAULT_SCALES = [1.2, 0.85, 0.6, 0.42, 0.3, 0.21]
DEFAULT_TRAINING_SEEDS = range(200, 206)  # tabletop walks of their own: not eval mapping's calibration orbits


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="a semloc dataset folder with per-frame object ground truth, or 'tabletop'")
    parser.add_argument("-o", "--output", required=True, help="model folder to write (model.npz, detector.yaml)")
    parser.add_argument("--trajectory", nargs="*", default=None,
                        help="tabletop: orbit:SEED (the simulator's walk) or a pose file, one world each "
                             "(default: the six walks orbit:200 ... orbit:205 - not the orbits semloc eval mapping "
                             "calibrates on; a model of the first three barely answers on 04's second bowl, docs/mapping.md)")
    parser.add_argument("--frames", type=int, default=600, help="tabletop: frames per world (600)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stride", type=int, default=4, help="every n-th frame (4)")
    parser.add_argument("--classes", nargs="*", default=None, help="default: every class of the ground truth")
    parser.add_argument("--cell", type=int, default=4, help="feature cell, pixels (4)")
    parser.add_argument("--window-cells", type=int, default=9, help="window's longer side, cells (9)")
    parser.add_argument("--scales", type=float, nargs="+", default=DEFAULT_SCALES,
                        help=f"pyramid levels ({' '.join(map(str, DEFAULT_SCALES))})")
    parser.add_argument("--color-space", choices=["rgb", "hsv"], default="hsv")
    parser.add_argument("--l2", type=float, default=1e-3, help="L2 weight of the logistic regression (1e-3)")
    parser.add_argument("--rounds", type=int, default=2, help="hard-negative mining rounds (2)")
    parser.add_argument("--random-negatives", type=int, default=40, help="random negatives per frame and class (40)")
    parser.add_argument("--hard-negatives", type=int, default=20, help="hard negatives per frame, class, round (20)")
    parser.add_argument("--clutter", type=int, default=None,
                        help="tabletop: distractor objects per world (the simulator's default, 3); more show the "
                             "mining more look-alikes")
    parser.add_argument("--ignore-radius", type=float, default=0.1,
                        help="windows centred within this fraction of an object's box size of its centre are neither "
                             "positives nor negatives (0.1: at the positive's level, windows a cell off are "
                             "negatives, which teaches the filter to peak on the centre)")
    parser.add_argument("--max-occluded", type=float, default=0.2,
                        help="objects more occluded than this (or cut by the image edge) are not positives (0.2)")


def training_objects(dataset, i: int, classes: tuple[str, ...], max_occluded: float) -> list:
    """The frame's objects of ``classes`` as ``TrainingObject``: the pixel their 3-D centre projects to, their
    unoccluded box's size; positives unless occluded or truncated."""
    from semloc_core.detection.linear import TrainingObject

    T = dataset.T_world_cam[i]
    positions = dataset.semantic_map.positions
    out = []
    for seen in dataset.visible_objects(i):
        if seen.class_name not in classes or seen.camera != 0:
            continue
        centre_cam = (positions[seen.object_index] - T[:3, 3]) @ T[:3, :3]
        if centre_cam[2] <= 0:
            continue
        uv = dataset.camera.project_cam(centre_cam[None])[0][0]
        x0, y0, x1, y1 = seen.box
        positive = seen.occluded_fraction <= max_occluded and not seen.truncated
        out.append(TrainingObject(classes.index(seen.class_name), (float(uv[0]), float(uv[1])),
                                  (float(x1 - x0), float(y1 - y0)), positive))
    return out


def run(args: argparse.Namespace) -> int:
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.linear import train_linear_model
    from semloc_core.io.detector_models import save_linear_model

    from services.commands.eval_mapping import open_scenes

    def log(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    problems = [text for bad, text in [
        (args.stride < 1, "--stride must be >= 1"), (args.window_cells < 1, "--window-cells must be >= 1"),
        (args.cell < 1, "--cell must be >= 1"), (not args.l2 > 0, "--l2 must be positive"),
        (args.rounds < 0 or args.random_negatives < 0 or args.hard_negatives < 0,
         "--rounds, --random-negatives and --hard-negatives must be >= 0"),
        (not 0 <= args.max_occluded <= 1, "--max-occluded must be a fraction in [0, 1]"),
        (not 0 <= args.ignore_radius <= 2, "--ignore-radius must be in [0, 2] (a fraction of the box size)"),
        (args.clutter is not None and args.clutter < 0, "--clutter must be >= 0")] if bad]
    if problems:
        log("semloc train-detector: " + "; ".join(problems))
        return 2
    if args.trajectory is None and args.dataset == "tabletop":
        args.trajectory = [f"orbit:{seed}" for seed in DEFAULT_TRAINING_SEEDS]
    scenes = open_scenes(args, log)
    classes = tuple(args.classes or sorted({c for _, d in scenes for c in d.semantic_map.class_names}))
    params = FeatureParams(cell=args.cell, color_space=args.color_space)
    total = sum(len(range(0, len(d), args.stride)) for _, d in scenes)
    start = time.perf_counter()

    def frames():
        for name, dataset in scenes:
            for i in range(0, len(dataset), args.stride):
                yield dataset.image(i), training_objects(dataset, i, classes, args.max_occluded)

    def progress(stage: str, count: int) -> None:
        if stage == "features":
            if count % 25 == 0 or count == total:
                log(f"  features {count} / {total} frames ({time.perf_counter() - start:.0f} s)")
        else:
            log(f"  {stage}: {count} negatives ({time.perf_counter() - start:.0f} s)")

    try:
        model = train_linear_model(frames(), classes, params, args.scales, args.window_cells, args.l2,
                                   args.random_negatives, args.hard_negatives, args.rounds, radius=args.ignore_radius,
                                   seed=args.seed, progress=progress)
    except ValueError as error:
        log(f"semloc train-detector: {error}")
        return 2
    model.info.update({"dataset": args.dataset, "trajectory": args.trajectory, "stride": args.stride,
                       "clutter": args.clutter, "seconds": round(time.perf_counter() - start, 1)})
    out = Path(args.output)
    save_linear_model(out / "model.npz", model)
    (out / "detector.yaml").write_text(yaml.safe_dump({"kind": "linear", "model": "model.npz"}))
    (out / "training.json").write_text(json.dumps(model.info, indent=2))
    for name, stats in model.info["classes"].items():
        log(f"  {name}: window {stats['window']}, {stats['positives']} positives, {stats['negatives']} negatives, "
            f"training recall {stats['train_positive_recall']:.3f}, false {stats['train_negative_false']:.4f}")
    log(f"wrote {out / 'model.npz'} and {out / 'detector.yaml'} ({time.perf_counter() - start:.0f} s)")
    return 0
