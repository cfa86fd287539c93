"""Detection accuracy on simulated scenarios: does each class's heatline peak at its objects' bearings?

    .venv/bin/python benchmarks/detection_accuracy.py [--scenarios hall tabletop] [--frames 300] [--seed 0]
        [--json out.json] [--markdown out.md]

For every frame of each scenario the §4.3 template detector (single exemplar per class + mirror, HOGE x HQC,
templates built from the scenario's own rendered exemplars) produces heatlines. Every visible, unoccluded (<= 10 %),
untruncated object at least 30 px tall must be found:

* soft: for a class with N such objects in the frame, the heatline's N strongest peaks (non-maximum suppression at
  5 deg) are its answer; an object is a hit when one of them lies within +-5 deg of its ground-truth bearing,
  otherwise a miss; a peak near no visible object of the class is a hallucination;
* hard (§4.5.2, Fig. 4.8): threshold + non-maximum suppression; every detection counts, also in frames without
  the class. The per-class thresholds are the least-error thresholds of score likelihoods calibrated (§4.8.2) on a
  different seed of the same scenario, so nothing is tuned on the evaluated frames.

Reports hits, misses, hallucinations and hit rate per class and scenario (the issue's target: soft hit rate
>= 80 %).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.bearing import BearingGrid  # noqa: E402
from semloc_core.detection.calibration import decision_threshold, fit_score_likelihoods, heatline_samples  # noqa: E402
from semloc_core.detection.evaluation import (UsableCriteria, accumulate, run_detector, score_hard,  # noqa: E402
                                              score_soft)
from semloc_core.detection.features import FeatureParams  # noqa: E402
from semloc_core.detection.heatlines import hard_heatlines  # noqa: E402
from semloc_core.detection.templates import MatchParams, TemplateDetector, build_templates  # noqa: E402

# Detector settings per scenario: 4-pixel blocks and 9-block templates (36 px) so that 30-px objects are
# matched at a modest upscale; the pyramid spans the object sizes each scenario shows.
SETTINGS = {
    "tabletop": {"cell": 4, "template_cells": 9, "scales": (1.2, 0.85, 0.6, 0.42)},
    "hall": {"cell": 4, "template_cells": 9, "scales": (1.2, 0.85, 0.6)},
}


def build_detector(scenario, settings: dict, use_masks: bool = True) -> TemplateDetector:
    params = FeatureParams(cell=settings["cell"], color_space=settings.get("color_space", "rgb"))
    exemplars = scenario.exemplars()
    masks = scenario.exemplar_masks() if use_masks else {}
    templates = []
    for name, images in exemplars.items():
        for k, image in enumerate(images):
            mask = masks.get(name, [None] * len(images))[k] if use_masks else None
            mask = None if mask is None else np.asarray(mask) > 0
            templates += build_templates(image, name, params, settings["template_cells"], mask=mask, mirror=True)
    return TemplateDetector(templates, params, MatchParams(tuple(settings["scales"])))


def calibrate_thresholds(scenario, detector, frames, criteria) -> tuple[dict, object]:
    positives = {name: [] for name in detector.classes}
    negatives = {name: [] for name in detector.classes}
    for _, heatlines, objects in run_detector(scenario, detector, frames, BearingGrid(), criteria):
        p, n = heatline_samples(heatlines, [(o.class_name, o.bearing, o.usable) for o in objects])
        for name in detector.classes:
            positives[name].append(p[name])
            negatives[name].append(n[name])
    samples_d = {k: np.concatenate(v) for k, v in positives.items()}
    samples_not_d = {k: np.concatenate(v) for k, v in negatives.items()}
    usable = [k for k in detector.classes if samples_d[k].size >= 2 and samples_not_d[k].size >= 2]
    likelihoods = fit_score_likelihoods({k: samples_d[k] for k in usable}, {k: samples_not_d[k] for k in usable})
    # Least expected error at the observed frequency of object bins (the prior of a bin holding an object).
    thresholds = {k: (decision_threshold(likelihoods, k, prior_d=samples_d[k].size / (samples_d[k].size
                                                                                     + samples_not_d[k].size))
                      if k in usable else 1.0) for k in detector.classes}
    return thresholds, likelihoods


def evaluate(name: str, seed: int, calibration_seed: int, frames: int, calibration_frames: int, stride: int,
             settings: dict,
             use_masks: bool) -> dict:
    from semloc_core.sim.scenarios import make_scenario

    criteria = UsableCriteria(min_height_px=30.0, max_occluded_fraction=0.1, allow_truncated=False)
    scenario = make_scenario(name, seed=seed, frames=frames)
    training = make_scenario(name, seed=calibration_seed, frames=calibration_frames)
    detector = build_detector(scenario, settings, use_masks)
    start = time.monotonic()
    thresholds, _ = calibrate_thresholds(training, build_detector(training, settings, use_masks),
                                         range(0, len(training), stride), criteria)
    soft_total: dict = {}
    hard_total: dict = {}
    evaluated = 0
    for _, heatlines, objects in run_detector(scenario, detector, range(0, len(scenario), stride), BearingGrid(),
                                              criteria):
        accumulate(soft_total, score_soft(heatlines, objects))
        accumulate(hard_total, score_hard(hard_heatlines(heatlines, thresholds, nms_deg=5.0), objects))
        evaluated += 1
    elapsed = time.monotonic() - start
    return {
        "scenario": name, "seed": seed, "frames": evaluated, "calibration_seed": calibration_seed,
        "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()},
        "masks": use_masks, "thresholds": thresholds, "seconds": elapsed,
        "soft": {k: soft_total.get(k).as_dict() for k in detector.classes if k in soft_total},
        "hard": {k: hard_total.get(k).as_dict() for k in detector.classes if k in hard_total},
    }


def markdown(results: list[dict]) -> str:
    lines = ["| scenario | class | soft hits | soft misses | soft halluc. | soft hit rate | hard hits | hard misses "
             "| hard halluc. | hard hit rate | hard threshold |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for result in results:
        for name in result["soft"]:
            s, h = result["soft"][name], result["hard"].get(name, {})
            lines.append(f"| {result['scenario']} | {name} | {s['hits']} | {s['misses']} | {s['hallucinations']} | "
                         f"{s['hit_rate']:.1%} | {h.get('hits', 0)} | {h.get('misses', 0)} | "
                         f"{h.get('hallucinations', 0)} | {h.get('hit_rate', float('nan')):.1%} | "
                         f"{result['thresholds'][name]:.3f} |")
        soft_hits = sum(v["hits"] for v in result["soft"].values())
        soft_all = soft_hits + sum(v["misses"] for v in result["soft"].values())
        hard_hits = sum(v["hits"] for v in result["hard"].values())
        hard_all = hard_hits + sum(v["misses"] for v in result["hard"].values())
        lines.append(f"| {result['scenario']} | **all** | {soft_hits} | {soft_all - soft_hits} | "
                     f"{sum(v['hallucinations'] for v in result['soft'].values())} | "
                     f"**{soft_hits / max(soft_all, 1):.1%}** | {hard_hits} | {hard_all - hard_hits} | "
                     f"{sum(v['hallucinations'] for v in result['hard'].values())} | "
                     f"{hard_hits / max(hard_all, 1):.1%} | |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=["hall", "tabletop"], choices=sorted(SETTINGS))
    parser.add_argument("--frames", type=int, default=300, help="frames per scenario")
    parser.add_argument("--calibration-frames", type=int, default=150, help="frames of the calibration seed")
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--calibration-seed", type=int, default=1,
                        help="seed of the scenario the hard thresholds are calibrated on")
    parser.add_argument("--no-masks", action="store_true", help="rectangular templates (the thesis's), no masks")
    parser.add_argument("--cell", type=int, help="override the block size")
    parser.add_argument("--template-cells", type=int, help="override the template size in blocks")
    parser.add_argument("--scales", type=float, nargs="+", help="override the pyramid scales")
    parser.add_argument("--color-space", choices=["rgb", "hsv"], help="override the HQC colour model")
    parser.add_argument("--json", help="write every figure as JSON here")
    parser.add_argument("--markdown", help="write the table as Markdown here")
    args = parser.parse_args()
    results = []
    for name in args.scenarios:
        settings = dict(SETTINGS[name])
        for key, value in (("cell", args.cell), ("template_cells", args.template_cells), ("scales", args.scales),
                           ("color_space", args.color_space)):
            if value is not None:
                settings[key] = tuple(value) if isinstance(value, list) else value
        result = evaluate(name, args.seed, args.calibration_seed, args.frames, args.calibration_frames, args.stride,
                          settings, not args.no_masks)
        results.append(result)
        print(f"{name}: {result['frames']} frames in {result['seconds']:.0f} s", file=sys.stderr)
    table = markdown(results)
    print(table)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
