"""How soon a heatline source singles out the true pose, with no particle filter in the way.

    .venv/bin/python benchmarks/localization_information.py --preset hall-panorama --cache CACHE \\
        [--set templates=front] [--source detector] [--set frames=80] [--hypotheses 100000]

Takes the same spec as ``semloc eval localization`` (DATASET, ``--preset``, ``--spec``, ``--set``, ``--cache``,
``--seed``: the heatlines, the calibration and the fitted σ and exponent are computed as that experiment does, or
read from the cache when it ran there first). ``--hypotheses`` start poses are drawn uniformly over the map's free
space and carried along the ground truth's own relative motion
(``semloc_core.localization.evaluation.information_margins``): a filter with perfect odometry and a particle at
every hypothesis. Each sums model B's log-likelihood (eq. 4.27, with the view
geometry as the evaluation uses it) of the source's heatlines.

Printed per frame: the share of hypotheses farther than ``--far`` (the preset's convergence threshold) that score
above the truth on that frame alone, how many score above it summed over the frames so far, and the margin. The
last line is the first frame from which no far hypothesis sums above the truth: no filter can settle on the
truth earlier on these heatlines (except by never sampling the poses that beat it). Compare it with the
evaluation's time to converge to see what the filter loses.

With ``--set kidnap=K`` (and ``jump``, as the evaluation takes them) the frames are those the kidnapped run continues
with after the teleport, and the hypotheses have no memory of the frames before it: the printed frame (counted
from the kidnapping) bounds how soon any filter can recover from it.

An information study, not a speed benchmark: shares, counts and margins, no timing.
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
    from semloc_core.experiments import heatline_cache
    from semloc_core.experiments import localization_calibration as calibrating
    from semloc_core.experiments.localization import LocalizationSpec, filter_preset_of, open_dataset_of
    from semloc_core.experiments.localization_detector import DETECTOR_MIN_PIXELS
    from semloc_core.experiments.spec import load_preset, preset_names, read_spec_file
    from semloc_core.localization import GenerativeScoreModel, ScoreLikelihood, synthetic_scores_likelihood
    from semloc_core.localization.evaluation import information_margins
    from semloc_core.localization.experiment import (frame_observations, ground_truth_heatlines, make_sequence,
                                                     view_geometry)
    from semloc_core.localization.free_space import FreeSpace
    from services.config import ConfigError, build, from_sets

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", nargs="?", help="as semloc eval localization's")
    parser.add_argument("--preset", choices=preset_names("localization"), help="a localization preset")
    parser.add_argument("--spec", help="a localization spec file")
    parser.add_argument("--set", action="append", default=[], metavar="PATH=VALUE", help="a spec field")
    parser.add_argument("--cache", help="the evaluation's cache folder")
    parser.add_argument("--seed", type=int, help="the spec's seed (the hypotheses' too)")
    parser.add_argument("--source", default="detector", choices=("synthetic", "detector"))
    parser.add_argument("--hypotheses", type=int, default=100_000, help="uniform start poses (100,000)")
    parser.add_argument("--far", type=float, default=None, help="metres (default: the preset's convergence threshold)")
    parser.add_argument("--every", type=int, default=3, help="print every n-th frame")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.hypotheses < 1:
        parser.error("--hypotheses must be >= 1")
    try:
        layers = [load_preset("localization", args.preset) if args.preset else {},
                  read_spec_file(args.spec) if args.spec else {},
                  {k: v for k, v in {"dataset": args.dataset, "seed": args.seed, "cache": args.cache}.items()
                   if v is not None}, from_sets(args.set)]
        spec = build(LocalizationSpec, *layers)
    except (ConfigError, ValueError) as error:
        print(f"localization_information: {error}", file=sys.stderr)
        return 2
    log = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))

    dataset = open_dataset_of(spec)
    preset = filter_preset_of(spec, dataset)
    far = preset.converge_threshold if args.far is None else args.far
    if spec.kidnap is None:
        indices = list(range(0, len(dataset), spec.stride))[:spec.frames]
    else:
        try:
            sequence = make_sequence(dataset, spec.stride, spec.frames, spec.kidnap, spec.jump)
        except ValueError as error:
            print(f"kidnap: {error}", file=sys.stderr)
            return 2
        indices = [int(i) for i in sequence.indices[spec.kidnap:]]
    classes = dataset.semantic_map.class_names
    if args.source == "detector":
        chosen = calibrating.template_views(spec, log)
        calibration, _ = calibrating.detector_calibration(spec, log, chosen)
        if calibration is None:
            print("the detector source needs a calibration (a sim:NAME dataset or calibration.file)", file=sys.stderr)
            return 2
        likelihood = ScoreLikelihood.from_calibration(calibration)
        heatlines = heatline_cache.cached_detector_heatlines(spec, dataset, indices,
                                                             heatline_cache.heatline_key(spec, dataset, preset),
                                                             chosen, log)
        minimum = DETECTOR_MIN_PIXELS
        thresholds = {c: decision_threshold(calibration, c) for c in calibration.classes}
    else:
        chosen = None
        likelihood = synthetic_scores_likelihood(classes)
        heatlines = ground_truth_heatlines(frame_observations(dataset, indices, classes, 360, preset.min_box_px),
                                           "synthetic")
        minimum = preset.min_box_px
        thresholds = 0.5
    bearing = calibrating.fitted_bearing_model(spec, args.source, likelihood, thresholds, log, chosen)
    sigma = preset.sigma if bearing["sigma_deg"] is None else math.radians(bearing["sigma_deg"])
    model = GenerativeScoreModel(dataset.semantic_map, likelihood, sigma=sigma,
                                 visibility_radius=preset.visibility_radius, peak=spec.perception.peak,
                                 exponent=bearing["exponent"])
    frames = [(heatlines[i], view_geometry(dataset, i, 360, minimum) if spec.perception.view else None)
              for i in indices]
    hypotheses = FreeSpace.from_map(dataset.semantic_map).sample_poses(args.hypotheses,
                                                                      np.random.default_rng(spec.seed))
    start = time.perf_counter()
    margins = information_margins(model, np.asarray(dataset.poses2d)[indices], frames, hypotheses, far)
    after = "" if spec.kidnap is None else f" after the kidnapping at {spec.kidnap} (frame {indices[0]} on)"
    print(f"{spec.dataset} {spec.scenario.camera or ''} source {args.source} templates {spec.templates}: "
          f"{len(indices)} frames{after}, {args.hypotheses} hypotheses, far > {far} m, sigma "
          f"{math.degrees(sigma):.1f} deg, exponent {bearing['exponent']:.3f} ({time.perf_counter() - start:.0f} s)")
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
