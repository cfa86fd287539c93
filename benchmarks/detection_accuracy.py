"""Detection accuracy on simulated datasets: does each class's heatline peak at its objects' bearings?

    .venv/bin/python benchmarks/detection_accuracy.py --data-dir DIR [--scenarios hall tabletop]
        [--frames 300] [--seed 0] [--detector NAME | --config FILE.yaml] [--json out.json] [--markdown out.md]

Datasets: ``DIR/<scenario>`` (evaluated) and ``DIR/<scenario>_calibration`` (another seed, 400 frames: the
training world for the hard thresholds and, for ``selected-hsv``, the exemplar views). Missing ones are written first with ``semloc sim`` (same code path, so tabletop objects carry the real
RGB-D Object crops of the real data folder when present). The detector is one of the named configurations below (a
``semloc_core.detection.config`` mapping whose ``templates`` is a folder of the dataset) or a YAML file.

Every visible, unoccluded (<= 10 %), untruncated object at least 30 px tall must be found:

* soft: for a class with N such objects in the frame, the heatline's N strongest peaks (non-maximum suppression at
  5 deg) are its answer; an object is a hit when one of them lies within +-5 deg of its ground-truth bearing,
  otherwise a miss; a peak near no visible object of the class is a hallucination;
* hard (§4.5.2, Fig. 4.8): threshold + non-maximum suppression; every detection counts, also in frames without
  the class. The per-class thresholds are the least-error thresholds (at the observed frequency of object bins) of
  score likelihoods calibrated (§4.8.2) on the calibration seed, so nothing is tuned on the evaluated frames.

Reports hits, misses, hallucinations and hit rate per class and scenario (the issue's target: soft hit rate
>= 80 %).

An accuracy study, not a speed benchmark: counts and hit rates, no ratio (the seconds printed per scenario are
for the reader).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from semloc_core.bearing import BearingGrid  # noqa: E402
from semloc_core.detection.calibration import decision_threshold, fit_score_likelihoods, heatline_samples  # noqa: E402
from semloc_core.detection.config import build_detector  # noqa: E402
from semloc_core.detection.evaluation import (UsableCriteria, accumulate, run_detector, score_hard,  # noqa: E402
                                              score_soft)
from semloc_core.detection.heatlines import hard_heatlines  # noqa: E402
from semloc_core.io.dataset import open_dataset  # noqa: E402
from semloc_core.experiments.template_selection import select as select_templates  # noqa: E402
from semloc_core.experiments.template_selection import write_library  # noqa: E402

# Named detector configurations. ``templates`` is relative to the dataset folder. 6-pixel blocks and 7-block
# templates (42 px) on a 3-level pyramid: objects from ~30 px up are matched, at camera rate (benchmarks/detector.py).
_GEOMETRY = {"cell": 6, "template_cells": 7, "scales": [1.0, 0.7, 0.5]}
SELECTED = "<selected on the calibration world>"
DETECTORS = {
    "templates-rgb": {"kind": "templates", "templates": "exemplars", **_GEOMETRY},
    "templates-hsv": {"kind": "templates", "templates": "exemplars", **_GEOMETRY, "color_space": "hsv"},
    # The hand-held tabletop camera looks down on the table: the multi-view exemplars rendered from 35 deg above.
    "multiview35-templates-hsv": {"kind": "templates", "templates": "exemplars_multiview", "files": "*_el35.png",
                                  **_GEOMETRY, "color_space": "hsv", "mirror": False},
    "multiview-dot": {"kind": "multiview", "templates": "exemplars_multiview", "spread": 4,
                      "scales": [1.2, 0.85, 0.6, 0.42]},
    # The hall's objects are 30-60 px tall in a 1024x256 panorama: 4-px blocks, 9-block (36 px) templates, and
    # per class the views (of exemplars/ and exemplars_multiview/) chosen on the calibration world by
    # `semloc select-templates`; the library is that world's, so no template comes from the evaluated world.
    "selected-hsv": {"kind": "templates", "templates": SELECTED, "cell": 4, "template_cells": 9,
                     "scales": [1.0, 0.7, 0.5], "color_space": "hsv"},
}
DEFAULT_DETECTOR = {"hall": "selected-hsv", "tabletop": "templates-hsv"}


def ensure_dataset(data_dir: Path, name: str, scenario: str, seed: int, frames: int) -> Path:
    folder = data_dir / name
    if not (folder / "dataset.json").is_file():
        print(f"writing {folder} with semloc sim ...", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "services.cli", "sim", scenario, "-o", str(folder), "--frames",
                        str(frames), "--seed", str(seed)], cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return folder


def detector_for(dataset_folder: Path, config: dict):
    config = dict(config)
    config["templates"] = str(dataset_folder / config["templates"])  # an absolute path stays as it is
    return build_detector(config)


def calibrate_thresholds(dataset, detector, frames, criteria) -> dict:
    positives = {name: [] for name in detector.classes}
    negatives = {name: [] for name in detector.classes}
    for _, heatlines, objects in run_detector(dataset, detector, frames, BearingGrid(), criteria):
        p, n = heatline_samples(heatlines, [(o.class_name, o.bearing, o.usable) for o in objects])
        for name in detector.classes:
            positives[name].append(p[name])
            negatives[name].append(n[name])
    samples_d = {k: np.concatenate(v) for k, v in positives.items()}
    samples_not_d = {k: np.concatenate(v) for k, v in negatives.items()}
    usable = [k for k in detector.classes if samples_d[k].size >= 2 and samples_not_d[k].size >= 2]
    likelihoods = fit_score_likelihoods({k: samples_d[k] for k in usable}, {k: samples_not_d[k] for k in usable})
    # Least expected error at the observed frequency of object bins (the prior of a bin holding an object).
    return {k: (decision_threshold(likelihoods, k, samples_d[k].size / (samples_d[k].size + samples_not_d[k].size))
                if k in usable else 1.0) for k in detector.classes}


def evaluate(scenario: str, data_dir: Path, seed: int, calibration_seed: int, frames: int, calibration_frames: int,
             stride: int, config: dict, config_name: str) -> dict:
    criteria = UsableCriteria(min_height_px=30.0, max_occluded_fraction=0.1, allow_truncated=False)
    folder = ensure_dataset(data_dir, scenario, scenario, seed, frames)
    calibration_folder = ensure_dataset(data_dir, f"{scenario}_calibration", scenario, calibration_seed,
                                        calibration_frames)
    dataset, calibration = open_dataset(folder), open_dataset(calibration_folder)
    start = time.monotonic()
    if config["templates"] == SELECTED:
        library = data_dir / f"{scenario}_selected"
        write_library(library, select_templates(calibration, {**config, "templates": None},
                                                [calibration.exemplar_dir, calibration.multiview_dir],
                                                range(len(calibration)), criteria, max_per_class=4,
                                                tolerance_deg=5.0))
        config = {**config, "templates": str(library.resolve())}
    # Calibration data is training data: objects down to 20 px and 30 % occluded count as positives there, so rare
    # classes still get a density.
    thresholds = calibrate_thresholds(calibration, detector_for(calibration_folder, config),
                                      range(0, len(calibration), stride),
                                      UsableCriteria(min_height_px=20.0, max_occluded_fraction=0.3))
    detector = detector_for(folder, config)
    soft_total: dict = {}
    hard_total: dict = {}
    evaluated = 0
    for _, heatlines, objects in run_detector(dataset, detector, range(0, len(dataset), stride), BearingGrid(),
                                              criteria):
        accumulate(soft_total, score_soft(heatlines, objects))
        accumulate(hard_total, score_hard(hard_heatlines(heatlines, thresholds, nms_deg=5.0), objects))
        evaluated += 1
    return {
        "scenario": scenario, "dataset": str(folder), "seed": seed, "frames": evaluated, "stride": stride,
        "calibration_dataset": str(calibration_folder), "detector": config_name, "config": config,
        "thresholds": thresholds, "seconds": time.monotonic() - start,
        "soft": {k: soft_total[k].as_dict() for k in detector.classes if k in soft_total},
        "hard": {k: hard_total[k].as_dict() for k in detector.classes if k in hard_total},
    }


def markdown(results: list[dict]) -> str:
    lines = ["| scenario | detector | class | soft hits | soft misses | soft halluc. | soft hit rate | hard hits | "
             "hard misses | hard halluc. | hard hit rate |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    rate = lambda hits, misses: f"{hits / (hits + misses):.1%}" if hits + misses else "n/a"  # noqa: E731
    for result in results:
        tag = f"| {result['scenario']} | {result['detector']} |"
        for name in result["soft"]:
            s, h = result["soft"][name], result["hard"].get(name, {"hits": 0, "misses": 0, "hallucinations": 0})
            lines.append(f"{tag} {name} | {s['hits']} | {s['misses']} | {s['hallucinations']} | "
                         f"{rate(s['hits'], s['misses'])} | {h['hits']} | {h['misses']} | {h['hallucinations']} | "
                         f"{rate(h['hits'], h['misses'])} |")
        total = {kind: [sum(v[key] for v in result[kind].values()) for key in ("hits", "misses", "hallucinations")]
                 for kind in ("soft", "hard")}
        (sh, sm, sx), (hh, hm, hx) = total["soft"], total["hard"]
        lines.append(f"{tag} **all** | {sh} | {sm} | {sx} | **{rate(sh, sm)}** | {hh} | {hm} | {hx} | "
                     f"{rate(hh, hm)} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-dir", required=True, help="folder of the datasets (written with semloc sim if absent)")
    parser.add_argument("--scenarios", nargs="+", default=["hall", "tabletop"], choices=["hall", "tabletop"])
    parser.add_argument("--frames", type=int, default=300, help="frames of a dataset written here")
    parser.add_argument("--calibration-frames", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--calibration-seed", type=int, default=1)
    parser.add_argument("--stride", type=int, default=1, help="evaluate every n-th frame")
    parser.add_argument("--detector", choices=sorted(DETECTORS), help="named configuration (default per scenario)")
    parser.add_argument("--config", help="detector configuration YAML (templates relative to the dataset folder)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="override configuration entries (YAML values), e.g. color_space=rgb")
    parser.add_argument("--json", help="write every figure as JSON here")
    parser.add_argument("--markdown", help="write the table as Markdown here")
    args = parser.parse_args()
    data_dir = Path(args.data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for scenario in args.scenarios:
        if args.config:
            name, config = Path(args.config).stem, yaml.safe_load(Path(args.config).read_text())
        else:
            name = args.detector or DEFAULT_DETECTOR[scenario]
            config = dict(DETECTORS[name])
        for item in args.set:
            key, _, value = item.partition("=")
            config[key] = yaml.safe_load(value)
        result = evaluate(scenario, data_dir, args.seed, args.calibration_seed, args.frames, args.calibration_frames,
                          args.stride, config, name)
        results.append(result)
        print(f"{scenario}: {result['frames']} frames in {result['seconds']:.0f} s", file=sys.stderr)
    table = markdown(results)
    print(table)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
