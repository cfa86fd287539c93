"""`semloc sim SCENARIO -o DIR`: generate a simulated dataset with exact ground truth (docs/sim.md).

Scenario options (the camera, realism, clutter, ...: semloc_core.sim.make_scenario's) are set with --set, e.g.
``semloc sim hall -o datasets/hall4k --set camera=panorama:4096x1024`` or ``--set realism=false``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from services.commands import fail, print_json
from services.config import ConfigError, from_sets

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
                        help="tabletop: folder of real object crops (rgbd_object_exemplars), 'auto' (the data "
                             "folder's, if present) or 'none' (generated appearances)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a scenario option (YAML value), e.g. camera=panorama, realism=false, clutter=0, "
                             "blocks=[3,2]")
    parser.add_argument("--no-multiview", action="store_true", help="skip the multi-view exemplars")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


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

    from semloc_core.experiments.tabletop import crop_options
    from semloc_core.io.trajectory import TrajectoryFormatError, read_trajectory
    from semloc_core.sim import make_scenario

    try:
        options = from_sets(args.set)
    except ConfigError as error:
        return fail("sim", error)
    trajectory = None
    if args.trajectory:
        path = Path(args.trajectory)
        try:
            trajectory = read_trajectory(path)[1] if args.scenario == "tabletop" else json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, TrajectoryFormatError) as error:
            return fail("sim", f"cannot read trajectory {path}: {error}")
    if args.scenario == "tabletop":
        try:
            crops = crop_options(args.exemplars)
        except FileNotFoundError as error:
            return fail("sim", error)
        options = {**crops, **options}
        if crops and not args.quiet:
            print(f"object appearances from real crops ({len(crops['crops'])} classes)", file=sys.stderr)
    try:
        scenario = make_scenario(args.scenario, seed=args.seed, frames=args.frames, trajectory=trajectory,
                                 **options)
    except (TypeError, ValueError) as error:
        return fail("sim", error)
    start = time.perf_counter()
    out = scenario.write(args.output, progress=None if args.quiet else (lambda d, t: _progress(d, t, start)),
                         multiview=not args.no_multiview)
    if args.json:
        print_json({"scenario": args.scenario, "seed": args.seed, "frames": len(scenario), "path": str(out)})
    else:
        print(f"wrote {len(scenario)} frames of {args.scenario} (seed {args.seed}) to {out}")
    return 0
