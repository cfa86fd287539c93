"""Calibrating a detector's scores (thesis §4.8.2): p(z|d) and p(z|not d) per class, fitted on a dataset with
object ground truth.

The detector runs over the dataset's frames; each frame becomes heatlines; every observed bearing bin is labelled
with the ground-truth objects (near a usable object of the class: d; far from every object of the class: not d);
both densities are fitted by KDE (1000 points, robust bandwidth). The result is the ``ScoreLikelihoods`` the
localizer's perception model B loads (``semloc_core.io.calibration``). The detector defaults to the §4.3 templates
built from the dataset's own exemplars.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from semloc_core.experiments.spec import DataPath, Spec


class CalibrationSpec(Spec):
    """``semloc calibrate``: which frames, how bins are labelled, which objects give positives."""

    dataset: DataPath | None = Field(None, description="a semloc dataset folder with per-frame object ground truth")
    detector: DataPath | None = Field(None, description="detector configuration YAML (default: the dataset's "
                                                        "exemplars as hsv templates, default_detector_config)")
    frames: int | None = Field(None, ge=1, description="at most this many frames")
    stride: int = Field(1, ge=1, description="every n-th frame")
    bins: int = Field(360, ge=4, description="bearing bins over the full turn")
    positive_deg: float = Field(2.0, gt=0, description="bins within this of a usable object's bearing are d")
    negative_deg: float = Field(10.0, gt=0, description="bins farther than this from every object of the class: "
                                                        "not d")
    min_height: float = Field(20.0, ge=0, description="positives come from objects at least this tall (px)")
    max_occluded: float = Field(0.3, ge=0, le=1, description="... and at most this fraction occluded")


def strided_frames(count: int, stride: int, limit: int | None) -> list[int]:
    """Every ``stride``-th frame index of a data set of ``count`` frames, at most ``limit`` of them."""
    return list(range(0, count, stride))[:limit]


def default_detector_config(exemplar_dir) -> dict:
    """The §4.3 templates of the dataset's own exemplars, with the settings evaluated in docs/detection.md."""
    return {"kind": "templates", "templates": str(exemplar_dir), "cell": 6, "template_cells": 7,
            "scales": [1.0, 0.7, 0.5], "color_space": "hsv"}


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


def run(spec: CalibrationSpec, progress=None):
    """The spec's dataset calibrated: ``ScoreLikelihoods`` whose ``detector`` says what was fitted and how.
    ``progress(done, total)`` is called per frame. Raises DatasetError, DetectorModelError or OSError for unusable
    inputs, ValueError when a class has too few samples."""
    from semloc_core.detection.config import build_detector
    from semloc_core.io.dataset import DatasetError, open_dataset

    if spec.dataset is None:
        raise ValueError("no dataset given")
    dataset = open_dataset(spec.dataset)
    if dataset.exemplar_dir is None and not spec.detector:
        raise DatasetError(f"{spec.dataset} has no exemplars: give a detector configuration")
    config = spec.detector or default_detector_config(dataset.exemplar_dir)
    detector = build_detector(config)
    frames = strided_frames(len(dataset), spec.stride, spec.frames)
    likelihoods = calibrate(dataset, detector, frames, spec.bins, spec.positive_deg, spec.negative_deg,
                            spec.min_height, spec.max_occluded,
                            None if progress is None else (lambda done: progress(done, len(frames))))
    detector_info = default_detector_config(dataset.exemplar_dir) if not spec.detector else \
        {"config": str(Path(spec.detector).resolve())}
    return type(likelihoods)(likelihoods.classes, likelihoods.z_min, likelihoods.z_max, likelihoods.pdf_d,
                             likelihoods.pdf_not_d, likelihoods.n_d, likelihoods.n_not_d,
                             likelihoods.bandwidth_d, likelihoods.bandwidth_not_d,
                             {**detector_info, "bins": spec.bins, "positive_deg": spec.positive_deg,
                              "negative_deg": spec.negative_deg, "min_height_px": spec.min_height,
                              "max_occluded_fraction": spec.max_occluded, "frames": len(frames)},
                             str(Path(spec.dataset).resolve()))


def likelihoods_png(likelihoods) -> bytes:
    """The fitted densities, one panel per class, as PNG bytes."""
    import io

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
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    return buffer.getvalue()
