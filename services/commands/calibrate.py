"""semloc calibrate [DATASET] -o FILE: fit the detector's score likelihoods p(z|d), p(z|not d) (thesis §4.8.2).

Runs the detector over the dataset's frames, labels every observed bearing bin with the ground-truth objects and
fits both densities by KDE; writes the semloc.score_likelihood JSON file the localizer loads and a PNG plot of the
densities next to it. The detector defaults to the §4.3 templates of the dataset's own exemplars; any detector
configuration: --set detector=CONFIG.yaml. The settings are the spec's fields
(semloc_core/experiments/detector_calibration.py), e.g.

  semloc calibrate datasets/tabletop -o tabletop_likelihoods.json --set stride=2
"""

from __future__ import annotations

import argparse

from services.commands import add_spec_options, build_spec, fail, frame_progress, print_json
from services.config import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="?", help="a semloc dataset folder with per-frame object ground truth")
    add_spec_options(parser, "calibrate", example="detector=detector.yaml or min_height=30", seed=False,
                     cache=False, output="score-likelihood JSON file to write (its plot: the same name, .png)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from semloc_core.experiments import detector_calibration as calibration
    from semloc_core.io.calibration import save_score_likelihoods
    from semloc_core.io.dataset import DatasetError
    from semloc_core.io.detector_models import DetectorModelError

    try:
        spec = build_spec(args, calibration.CalibrationSpec, "calibrate", dataset=args.dataset)
        likelihoods = calibration.run(spec, frame_progress(args.quiet))
    except (ConfigError, DatasetError, DetectorModelError, OSError, ValueError) as error:
        return fail("calibrate", error)
    output = save_score_likelihoods(likelihoods, args.output)
    plot = output.with_suffix(".png")
    plot.write_bytes(calibration.likelihoods_png(likelihoods))
    z = likelihoods.z
    summary = {}
    for k, name in enumerate(likelihoods.classes):
        summary[name] = {"n_d": int(likelihoods.n_d[k]), "mean_z_d": float(np.trapezoid(z * likelihoods.pdf_d[k], z)),
                         "n_not_d": int(likelihoods.n_not_d[k]),
                         "mean_z_not_d": float(np.trapezoid(z * likelihoods.pdf_not_d[k], z))}
    if args.json:
        print_json({"output": str(output), "plot": str(plot), "classes": summary})
        return 0
    for name, s in summary.items():
        print(f"{name:>16s}: n_d={s['n_d']:7d} mean z|d={s['mean_z_d']:.3f}   "
              f"n_not_d={s['n_not_d']:8d} mean z|not d={s['mean_z_not_d']:.3f}")
    print(f"wrote {output} and {plot}")
    return 0
