"""`semloc calibrate DATASET -o FILE`: fit the detector's score likelihoods p(z|d), p(z|not d) (thesis §4.8.2).

Runs the detector over the dataset's frames, turns each frame into heatlines, labels every observed bearing bin
with the ground-truth objects (near a usable object of the class: d; far from every object of the class: not d),
fits both densities by KDE (1000 points, robust bandwidth) and writes the ``semloc.score_likelihood`` JSON file the
localizer loads, plus a PNG plot of the densities. The detector defaults to the §4.3 templates built from the
dataset's own exemplars; ``--detector CONFIG.yaml`` uses any detector configuration (docs/detection.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from services.commands import frame_progress, strided_frames


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="a semloc dataset folder (semloc sim) with per-frame object ground truth")
    parser.add_argument("-o", "--output", required=True, help="score-likelihood JSON file to write")
    parser.add_argument("--detector", help="detector configuration YAML (default: hsv templates from the "
                                           "dataset's exemplars, see docs/detection.md)")
    parser.add_argument("--frames", type=int, default=None, help="use at most this many frames")
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--bins", type=int, default=360, help="bearing bins over the full turn (default 360)")
    parser.add_argument("--positive-deg", type=float, default=2.0,
                        help="bins within this of a usable object's bearing are positives (default 2)")
    parser.add_argument("--negative-deg", type=float, default=10.0,
                        help="bins farther than this from every object of the class are negatives (default 10)")
    parser.add_argument("--min-height", type=float, default=20.0,
                        help="positives come from objects at least this tall (px, default 20)")
    parser.add_argument("--max-occluded", type=float, default=0.3,
                        help="... and at most this fraction occluded (default 0.3)")
    parser.add_argument("--plot", help="PNG of the densities (default: OUTPUT with .png)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def default_detector_config(exemplar_dir) -> dict:
    """The §4.3 templates of the dataset's own exemplars, with the settings evaluated in docs/detection.md."""
    return {"kind": "templates", "templates": str(exemplar_dir), "cell": 6, "template_cells": 7,
            "scales": [1.0, 0.7, 0.5], "color_space": "hsv"}


def plot_likelihoods(likelihoods, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(likelihoods.classes)
    columns = min(count, 3)
    rows = -(-count // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.0 * rows), squeeze=False)
    z = likelihoods.z
    for k, name in enumerate(likelihoods.classes):
        axis = axes[k // columns][k % columns]
        axis.plot(z, likelihoods.pdf_not_d[k], color="tab:red", label=f"p(z|not d), n={likelihoods.n_not_d[k]}")
        axis.plot(z, likelihoods.pdf_d[k], color="tab:green", label=f"p(z|d), n={likelihoods.n_d[k]}")
        axis.set_title(name)
        axis.set_xlabel("heatline score z")
        axis.legend(fontsize=7)
    for k in range(count, rows * columns):
        axes[k // columns][k % columns].axis("off")
    figure.suptitle("detector score likelihoods (KDE, thesis §4.8.2)")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def calibration_samples(dataset, detector, frames, bins: int = 360, positive_deg: float = 2.0,
                        negative_deg: float = 10.0, min_height: float = 20.0, max_occluded: float = 0.3,
                        progress=None) -> tuple[dict, dict]:
    """Heatline scores of ``detector`` on ``dataset`` per class: ({class: scores at objects}, {class: elsewhere})."""
    from semloc_core.bearing import BearingGrid
    from semloc_core.detection.calibration import heatline_samples
    from semloc_core.detection.evaluation import UsableCriteria, run_detector

    positives = {name: [] for name in detector.classes}
    negatives = {name: [] for name in detector.classes}
    criteria = UsableCriteria(min_height_px=min_height, max_occluded_fraction=max_occluded)
    for done, (_, heatlines, objects) in enumerate(run_detector(dataset, detector, frames, BearingGrid(bins),
                                                                criteria), start=1):
        triples = [(o.class_name, o.bearing, o.usable) for o in objects]
        frame_positives, frame_negatives = heatline_samples(heatlines, triples, positive_deg, negative_deg)
        for name in detector.classes:
            positives[name].append(frame_positives[name])
            negatives[name].append(frame_negatives[name])
        if progress is not None:
            progress(done)
    return positives, negatives


def fit_pooled(detector, samples: list[tuple[dict, dict]], min_height: float = 20.0, max_occluded: float = 0.3):
    """The ``ScoreLikelihoods`` of the samples of one or more data sets, pooled."""
    from semloc_core.detection.calibration import fit_score_likelihoods

    def pooled(which: int) -> dict:
        return {name: np.concatenate([a for s in samples for a in s[which][name]] or [np.zeros(0)])
                for name in detector.classes}

    samples_d, samples_not_d = pooled(0), pooled(1)
    missing = [name for name in detector.classes if samples_d[name].size < 2 or samples_not_d[name].size < 2]
    if missing:
        raise ValueError(f"too few samples for classes {missing}: does the dataset show them (>= {min_height:g} px, "
                         f"<= {max_occluded:.0%} occluded)?")
    return fit_score_likelihoods(samples_d, samples_not_d)


def calibrate(dataset, detector, frames, bins: int = 360, positive_deg: float = 2.0, negative_deg: float = 10.0,
              min_height: float = 20.0, max_occluded: float = 0.3, progress=None):
    """Score samples of ``detector`` on ``dataset`` and the fitted ``ScoreLikelihoods``."""
    samples = calibration_samples(dataset, detector, frames, bins, positive_deg, negative_deg, min_height,
                                  max_occluded, progress)
    return fit_pooled(detector, [samples], min_height, max_occluded)


def run(args) -> int:
    from semloc_core.detection.config import build_detector
    from semloc_core.io.calibration import save_score_likelihoods
    from semloc_core.io.dataset import DatasetError, open_dataset
    from semloc_core.io.detector_models import DetectorModelError

    try:
        dataset = open_dataset(args.dataset)
        if dataset.exemplar_dir is None and not args.detector:
            raise DatasetError(f"{args.dataset} has no exemplars: give --detector CONFIG.yaml")
        config = args.detector or default_detector_config(dataset.exemplar_dir)
        detector = build_detector(config)
    except (DatasetError, DetectorModelError, OSError) as error:
        print(f"semloc calibrate: {error}", file=sys.stderr)
        return 2
    if args.stride < 1 or args.bins < 4:
        print("semloc calibrate: --stride must be >= 1 and --bins >= 4", file=sys.stderr)
        return 2
    frames = strided_frames(len(dataset), args.stride, args.frames)
    progress = frame_progress(len(frames), args.quiet)

    try:
        likelihoods = calibrate(dataset, detector, frames, args.bins, args.positive_deg, args.negative_deg,
                                args.min_height, args.max_occluded, progress)
    except ValueError as error:
        print(f"\nsemloc calibrate: {error}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(file=sys.stderr)
    detector_info = default_detector_config(dataset.exemplar_dir) if not args.detector else \
        {"config": str(Path(args.detector).resolve())}
    likelihoods = type(likelihoods)(likelihoods.classes, likelihoods.z_min, likelihoods.z_max, likelihoods.pdf_d,
                                    likelihoods.pdf_not_d, likelihoods.n_d, likelihoods.n_not_d,
                                    likelihoods.bandwidth_d, likelihoods.bandwidth_not_d,
                                    {**detector_info, "bins": args.bins, "positive_deg": args.positive_deg,
                                     "negative_deg": args.negative_deg, "min_height_px": args.min_height,
                                     "max_occluded_fraction": args.max_occluded,
                                     "frames": len(frames)},
                                    str(Path(args.dataset).resolve()))
    output = save_score_likelihoods(likelihoods, args.output)
    plot = plot_likelihoods(likelihoods, Path(args.plot) if args.plot else output.with_suffix(".png"))
    z = likelihoods.z
    for k, name in enumerate(likelihoods.classes):
        mean_d = float(np.trapezoid(z * likelihoods.pdf_d[k], z))
        mean_not_d = float(np.trapezoid(z * likelihoods.pdf_not_d[k], z))
        print(f"{name:>16s}: n_d={likelihoods.n_d[k]:7d} mean z|d={mean_d:.3f}   "
              f"n_not_d={likelihoods.n_not_d[k]:8d} mean z|not d={mean_not_d:.3f}")
    print(f"wrote {output} and {plot}")
    return 0
