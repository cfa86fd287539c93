"""How soon a heatline source singles out the true pose, with no particle filter in the way.

    .venv/bin/python benchmarks/localization_information.py sim:hall --camera panorama:4096x1024 \\
        --cache CACHE [--templates selected] [--source detector] [--frames 80] [--hypotheses 100000]

Takes the same dataset options as ``semloc eval localization`` and its ``--cache`` (the heatlines, the
calibration and the fitted σ and exponent are computed as that command does, or read from the cache when it ran
there first). ``--hypotheses`` start poses are drawn uniformly over the map's free space and carried along the
ground truth's own relative motion (``semloc_core.localization.evaluation.information_margins``): a filter with
perfect odometry and a particle at every hypothesis. Each sums model B's log-likelihood (eq. 4.27, with the view
geometry as the evaluation uses it) of the source's heatlines.

Printed per frame: the share of hypotheses farther than ``--far`` (the preset's convergence threshold) that score
above the truth on that frame alone, how many score above it summed over the frames so far, and the margin. The
last line is the first frame from which no far hypothesis sums above the truth: no filter can settle on the
truth earlier on these heatlines (except by never sampling the poses that beat it). Compare it with the
evaluation's time to converge to see what the filter loses.

With ``--kidnap K`` (and ``--jump``, as the evaluation takes them) the frames are those the kidnapped run continues
with after the teleport, and the hypotheses have no memory of the frames before it: the printed frame (counted
from the kidnapping) bounds how soon any filter can recover from it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    sys.path.insert(0, str(REPO))
    from semloc_core.detection.calibration import decision_threshold
    from semloc_core.localization import GenerativeScoreModel, ScoreLikelihood, synthetic_scores_likelihood
    from semloc_core.localization.evaluation import information_margins
    from semloc_core.localization.experiment import (PRESETS, frame_observations, ground_truth_heatlines,
                                                     make_sequence, preset_for, view_geometry)
    from semloc_core.localization.free_space import FreeSpace
    from services.commands import eval_localization as ev

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ev.add_arguments(parser)
    parser.set_defaults(json="unused.json")
    parser.add_argument("--source", default="detector", choices=("synthetic", "detector"))
    parser.add_argument("--hypotheses", type=int, default=100_000, help="uniform start poses (100,000)")
    parser.add_argument("--far", type=float, default=None, help="metres (default: the preset's convergence threshold)")
    parser.add_argument("--every", type=int, default=3, help="print every n-th frame")
    for action in parser._actions:  # --json is the evaluation's output, not needed here
        if action.dest == "json":
            action.required = False
    args = parser.parse_args(argv)
    if args.hypotheses < 1:
        parser.error("--hypotheses must be >= 1")
    log = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))

    dataset = ev._open(args)
    preset = preset_for(dataset) if args.preset == "auto" else PRESETS[args.preset]
    far = preset.converge_threshold if args.far is None else args.far
    if args.kidnap is None:
        indices = list(range(0, len(dataset), max(1, args.stride)))[:args.frames]
    else:
        try:
            sequence = make_sequence(dataset, args.stride, args.frames, args.kidnap, args.jump)
        except ValueError as error:
            print(f"--kidnap: {error}", file=sys.stderr)
            return 2
        indices = [int(i) for i in sequence.indices[args.kidnap:]]
    classes = dataset.semantic_map.class_names
    if args.source == "detector":
        chosen = ev._template_views(args, log)
        calibration, _ = ev.detector_calibration(args, log, chosen)
        if calibration is None:
            print("the detector source needs a calibration (a sim:NAME dataset or --calibration FILE)", file=sys.stderr)
            return 2
        likelihood = ScoreLikelihood.from_calibration(calibration)
        heatlines = ev.cached_detector_heatlines(args, dataset, indices, ev.heatline_key(args, dataset, preset),
                                                 chosen, log)
        minimum = ev.DETECTOR_MIN_PIXELS
        thresholds = {c: decision_threshold(calibration, c) for c in calibration.classes}
    else:
        chosen = None
        likelihood = synthetic_scores_likelihood(classes)
        heatlines = ground_truth_heatlines(frame_observations(dataset, indices, classes, 360, preset.min_box_px),
                                           "synthetic")
        minimum = preset.min_box_px
        thresholds = 0.5
    bearing = ev.fitted_bearing_model(args, args.source, likelihood, thresholds, log, chosen)
    sigma = preset.sigma if bearing["sigma_deg"] is None else math.radians(bearing["sigma_deg"])
    model = GenerativeScoreModel(dataset.semantic_map, likelihood, sigma=sigma,
                                 visibility_radius=preset.visibility_radius, peak=args.peak,
                                 exponent=bearing["exponent"])
    frames = [(heatlines[i], view_geometry(dataset, i, 360, minimum) if args.view else None) for i in indices]
    hypotheses = FreeSpace.from_map(dataset.semantic_map).sample_poses(args.hypotheses,
                                                                      np.random.default_rng(args.seed))
    start = time.perf_counter()
    margins = information_margins(model, np.asarray(dataset.poses2d)[indices], frames, hypotheses, far)
    after = "" if args.kidnap is None else f" after the kidnapping at {args.kidnap} (frame {indices[0]} on)"
    print(f"{args.dataset} {args.camera or ''} source {args.source} templates {args.templates}: {len(indices)} "
          f"frames{after}, {args.hypotheses} hypotheses, far > {far} m, sigma {math.degrees(sigma):.1f} deg, exponent "
          f"{bearing['exponent']:.3f} ({time.perf_counter() - start:.0f} s)")
    print("frame | far poses above the truth on the frame alone | above it summed so far | margin (nats)")
    for k in range(len(indices)):
        if k % args.every == 0 or k == len(indices) - 1:
            print(f"{k:5d} | {100 * margins['share_above_single'][k]:5.1f} % | {margins['above_cumulative'][k]:6d} | "
                  f"{margins['margin'][k]:+8.1f}")
    singled = margins["singled_out"]
    print(f"singled out from frame {singled}" if singled is not None else "not singled out by the last frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
