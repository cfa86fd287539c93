"""`semloc sim SCENARIO -o DIR`: generate a simulated dataset with exact ground truth (docs/sim.md)."""

from __future__ import annotations

import argparse
import json
import sys
import time

SCENARIO_NAMES = ("tabletop", "hall", "route", "aliased")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", choices=SCENARIO_NAMES)
    parser.add_argument("-o", "--output", required=True, help="dataset folder to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=None, help="frame count (default: the scenario's)")
    parser.add_argument("--trajectory", default=None,
                        help="tabletop: an RGB-D Scenes v2 .pose or TUM file to follow; route/aliased: JSON list of "
                             "grid nodes; hall: JSON list of [x, y] waypoints")
    parser.add_argument("--exemplars", default="auto",
                        help="tabletop: folder of real object crops (rgbd_object_exemplars), 'auto' (../shared/data "
                             "if present) or 'none' (generated appearances)")
    parser.add_argument("--camera", default=None,
                        help="hall/route/aliased: panorama (1024x256), panorama:WxH, rig or pinhole")
    parser.add_argument("--no-realism", action="store_true", help="bare renders: no noise, blur, lighting drift")
    parser.add_argument("--no-multiview", action="store_true", help="skip the multi-view exemplars")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=JSON",
                        help="any scenario option, value as JSON (e.g. --option clutter=0 --option 'blocks=[3,2]')")


def _progress(done: int, total: int, start: float) -> None:
    width = 30
    filled = int(width * done / max(total, 1))
    rate = done / max(time.perf_counter() - start, 1e-9)
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} frames  {rate:5.1f} fps")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops
    from semloc_core.io.trajectory import TrajectoryFormatError, read_trajectory
    from semloc_core.sim import make_scenario

    options: dict = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep:
            print(f"semloc sim: --option needs KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    if args.camera:
        options["camera"] = args.camera
    if args.no_realism:
        options["realism"] = False
    trajectory = None
    if args.trajectory:
        path = Path(args.trajectory)
        try:
            if args.scenario == "tabletop":
                trajectory = read_trajectory(path)[1]
            else:
                trajectory = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, TrajectoryFormatError) as error:
            print(f"semloc sim: cannot read trajectory {path}: {error}", file=sys.stderr)
            return 2
    if args.scenario == "tabletop" and args.exemplars != "none":
        folder = default_exemplar_dir() if args.exemplars == "auto" else Path(args.exemplars)
        if folder is not None:
            try:
                crops, others = load_exemplar_crops(folder)
            except FileNotFoundError as error:
                print(f"semloc sim: {error}", file=sys.stderr)
                return 2
            options.setdefault("crops", crops)
            options.setdefault("clutter_crops", others)
            print(f"object appearances from {folder} ({len(crops)} classes)", file=sys.stderr)
    try:
        scenario = make_scenario(args.scenario, seed=args.seed, frames=args.frames, trajectory=trajectory,
                                 **options)
    except (TypeError, ValueError) as error:
        print(f"semloc sim: {error}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    out = scenario.write(args.output, progress=lambda d, t: _progress(d, t, start),
                         multiview=not args.no_multiview)
    print(f"wrote {len(scenario)} frames of {args.scenario} (seed {args.seed}) to {out}")
    return 0
