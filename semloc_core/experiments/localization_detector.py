"""The localization experiment's detector: the §4.3 template detector built from a world's exemplar views, and
its heatlines of a dataset's frames."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

# The configuration whose accuracy docs/detection.md reports (benchmarks/detection_accuracy.py "templates-hsv",
# the default of both scenes): 6-px blocks, 7-block templates, 3-level pyramid, hue x saturation colours.
DETECTOR_SETTINGS = {"cell": 6, "template_cells": 7, "scales": (1.0, 0.7, 0.5), "color_space": "hsv"}
# Calibration training data as ``semloc calibrate``: objects down to 20 px and 30 % occluded are positives.
CALIBRATION_CRITERIA = {"min_height_px": 20.0, "max_occluded_fraction": 0.3}
# Model B expects (ViewGeometry) exactly the objects p(z|d) was fitted on: those at least as tall as the calibration's
# positives. (30 px, the accuracy table's "usable" size, left 20-30 px objects that the detector does respond to
# unexpected, which pulled the estimate to poses where they fall out of view: scene 01, 0.24 m against 0.11 m.)
DETECTOR_MIN_PIXELS = CALIBRATION_CRITERIA["min_height_px"]
# templates: the thesis's one exemplar per class, or views chosen on the calibration worlds as
# `semloc select-templates` chooses them (its criteria: objects >= 30 px, <= 10 % occluded, hit within 5 deg).
TEMPLATE_CHOICES = ("front", "selected")
SELECTION_CRITERIA = {"min_height_px": 30.0, "max_occluded_fraction": 0.1}
SELECTION_MAX_PER_CLASS = 4
SELECTION_TOLERANCE_DEG = 5.0


def candidate_views(dataset) -> dict[str, list[tuple[str, np.ndarray, np.ndarray | None]]]:
    """Each class's exemplar views in ``dataset``: ``(key, image, mask)``, its canonical exemplars (``front<k>``)
    then its multi-view exemplars (``az<deg>_el<deg>``, if the dataset has them). A key names a viewpoint, so a view
    chosen on one world is found again among another world's renders of its own objects."""
    from semloc_core.io.dataset import DatasetError

    masks = dataset.exemplar_masks() if hasattr(dataset, "exemplar_masks") else {}
    out: dict[str, list] = {}
    for name, images in dataset.exemplars().items():
        class_masks = masks.get(name) or [None] * len(images)
        out[name] = [(f"front{k}", image, mask) for k, (image, mask) in enumerate(zip(images, class_masks))]
    try:
        multiview = dataset.multiview_exemplars() if hasattr(dataset, "multiview_exemplars") else {}
    except DatasetError:
        multiview = {}
    for name, views in multiview.items():
        out.setdefault(name, []).extend(
            (f"az{math.degrees(v.azimuth):.0f}_el{math.degrees(v.elevation):.0f}", v.image, v.mask) for v in views)
    return out


def template_detector(views: dict, settings: dict = DETECTOR_SETTINGS):
    """The template detector of ``{class: [(key, image, mask)]}``; each view with its mirror, ``source``
    ``class/key``."""
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.templates import MatchParams, TemplateDetector, build_templates, mask_uniform_background

    params = FeatureParams(cell=settings["cell"], color_space=settings["color_space"])
    templates = []
    for name, class_views in sorted(views.items()):
        for key, image, mask in class_views:
            mask = mask_uniform_background(image) if mask is None else np.asarray(mask) > 0
            templates += build_templates(image, name, params, settings["template_cells"], mask=mask, mirror=True,
                                         source=f"{name}/{key}")
    return TemplateDetector(templates, params, MatchParams(tuple(settings["scales"])))


def scene_detector(*datasets, chosen: dict | None = None):
    """The template detector of every class of ``datasets`` (views of a class shared by several: the first's):
    each class's canonical exemplars, or with ``chosen`` (``{class: [view key]}``, chosen on calibration worlds)
    those views."""
    views: dict = {}
    for dataset in datasets:
        for name, class_views in candidate_views(dataset).items():
            if name in views:
                continue
            keys = (chosen or {}).get(name)
            if keys is None:
                views[name] = [v for v in class_views if v[0].startswith("front")]
                continue
            by_key = {v[0]: v for v in class_views}
            if missing := [k for k in keys if k not in by_key]:
                raise ValueError(f"{getattr(dataset, 'name', 'the dataset')} has no exemplar view {missing} of "
                                 f"{name!r} (chosen on the calibration worlds); it needs multi-view exemplars")
            views[name] = [by_key[k] for k in keys]
    return template_detector(views)


def detector_heatlines(dataset, indices, log: Callable[[str], None], chosen: dict | None) -> dict:
    """The scene detector's heatlines of ``indices`` of ``dataset``, per frame index."""
    from semloc_core.detection.evaluation import run_detector

    detector = scene_detector(dataset, chosen=chosen)
    out = {}
    start = time.perf_counter()
    for done, (i, heatlines, _) in enumerate(run_detector(dataset, detector, [int(i) for i in indices]), start=1):
        out[int(i)] = heatlines
        if done % 50 == 0:
            log(f"  detector: {done}/{len(indices)} frames ({done / (time.perf_counter() - start):.1f} frames/s)")
    return out
