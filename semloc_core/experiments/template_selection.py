"""Choosing each class's exemplar views on a training world (greedy forward selection,
``semloc_core.detection.selection``).

Every candidate exemplar (default: the dataset's ``exemplars/`` and ``exemplars_multiview/``, each with its
mirror) is matched over the dataset's frames once; per class the views that find its objects best under the soft
rule of the accuracy table are kept. :func:`write_library` writes them as a template library (``<class>/<view>.png``
with ``<class>/masks/``), its ``detector.yaml`` (``templates: .``) and ``selection.json`` (every step with its hits,
misses and hallucinations). Use a world other than the one you evaluate on: this is training.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from semloc_core.experiments.detector_calibration import default_detector_config, strided_frames
from semloc_core.experiments.spec import DataPath, DataPaths, Spec


class SelectionSpec(Spec):
    """``semloc select-templates``: the training world, the candidates and the rule a view is kept by."""

    dataset: DataPath | None = Field(None, description="a semloc dataset folder with per-frame object ground truth")
    libraries: DataPaths = Field([], description="candidate exemplar folders (default: the dataset's exemplars and "
                                                 "multi-view exemplars)")
    detector: DataPath | None = Field(None, description="template detector configuration YAML the library is chosen "
                                                        "for (default: calibrate's, docs/detection.md)")
    detector_settings: dict[str, Any] = Field({}, description="detector settings over the configuration's, e.g. "
                                                              "{cell: 4, template_cells: 9}")
    max_per_class: int = Field(4, ge=1, description="at most this many views per class")
    min_height: float = Field(30.0, ge=0, description="objects that must be found: px tall")
    max_occluded: float = Field(0.1, ge=0, le=1, description="... and at most this occluded")
    tolerance_deg: float = Field(5.0, gt=0, description="a peak this close to an object's bearing is a hit")
    frames: int | None = Field(None, ge=1, description="at most this many frames")
    stride: int = Field(1, ge=1, description="every n-th frame")


@dataclass
class Selection:
    """What :func:`run` chose: per class its steps (``semloc_core.detection.selection``), the candidates'
    ``(class, source)`` and the exemplars themselves, and the detector configuration they were chosen for."""

    chosen: dict
    exemplars: list
    candidates: list
    config: dict


def exemplar_heatlines(dataset, detector, frames, criteria, progress=None):
    """Each candidate exemplar's own heatline per frame: (frames, exemplars, bins), observed, objects, exemplars."""
    from semloc_core.bearing import BearingGrid
    from semloc_core.detection.evaluation import frame_images, frame_objects, frame_overrides
    from semloc_core.detection.heatlines import HeatlineProjector
    from semloc_core.detection.selection import exemplar_of_templates, per_exemplar

    index, exemplars = exemplar_of_templates(detector.templates)
    projector = HeatlineProjector(dataset.camera, [f"exemplar{k}" for k in range(len(exemplars))], BearingGrid())
    lines, observed, objects = [], [], []
    for done, i in enumerate(frames, start=1):
        maps = []
        for image in frame_images(dataset, i):
            hoge_maps, hqc_maps = detector.template_heatmaps(image)
            maps.append(per_exemplar(np.clip(hoge_maps * hqc_maps, 0.0, 1.0), index, len(exemplars)))  # eq. 4.4
        heatlines = projector.project(maps if len(maps) > 1 else maps[0], T_body_cam=frame_overrides(dataset, i))
        lines.append(heatlines.scores)
        observed.append(heatlines.observed)
        objects.append(frame_objects(dataset.visible_objects(i), criteria))
        if progress is not None:
            progress(done)
    return np.stack(lines), np.stack(observed), objects, exemplars


def select(dataset, config: dict, libraries, frames, criteria, max_per_class: int, tolerance_deg: float,
           progress=None) -> Selection:
    """Run the selection on ``dataset``; every class of the candidates must get a view."""
    from semloc_core.detection.config import build_detector
    from semloc_core.detection.selection import select_exemplars
    from semloc_core.detection.templates import TemplateDetector
    from semloc_core.io.detector_models import load_template_library

    candidates = []
    for library in libraries:
        for exemplars in load_template_library(library, config.get("files")).values():
            candidates += exemplars
    detectors = [build_detector({**config, "templates": str(library)}) for library in libraries]
    detector = TemplateDetector([t for d in detectors for t in d.templates], detectors[0].params, detectors[0].match)
    lines, observed, objects, exemplars = exemplar_heatlines(dataset, detector, frames, criteria, progress)
    chosen = select_exemplars(lines, observed, [name for name, _ in exemplars], objects, max_per_class,
                              tolerance_deg)
    missing = [name for name in detector.classes if name not in chosen]
    if missing:
        raise ValueError(f"no usable object of {missing} in the training frames: choose another world or lower "
                         f"min_height")
    return Selection(chosen, exemplars, candidates, config)


def run(spec: SelectionSpec, progress=None) -> Selection:
    """The spec's selection (``progress(done, total)`` per frame). Raises DatasetError, DetectorModelError or
    OSError for unusable inputs, ValueError when a class finds no view."""
    from semloc_core.detection.evaluation import UsableCriteria
    from semloc_core.io.dataset import DatasetError, open_dataset
    from semloc_core.io.detector_models import DetectorModelError, load_detector_config

    if spec.dataset is None:
        raise ValueError("no dataset given")
    dataset = open_dataset(spec.dataset)
    libraries = spec.libraries or [d for d in (dataset.exemplar_dir, dataset.multiview_dir) if d is not None]
    if not libraries:
        raise DatasetError(f"{spec.dataset} has no exemplars: give libraries")
    config = load_detector_config(spec.detector) if spec.detector else default_detector_config(libraries[0])
    config.update(spec.detector_settings)
    if config.get("kind") != "templates":
        raise DetectorModelError("template selection is for the §4.3 template detector (kind: templates)")
    frames = strided_frames(len(dataset), spec.stride, spec.frames)
    criteria = UsableCriteria(spec.min_height, spec.max_occluded, allow_truncated=False)
    return select(dataset, config, libraries, frames, criteria, spec.max_per_class, spec.tolerance_deg,
                  None if progress is None else (lambda done: progress(done, len(frames))))


def write_library(folder: Path, selection: Selection) -> dict:
    """Copy the chosen exemplars (image + mask) into a template library with its ``detector.yaml`` and
    ``selection.json``; returns the selection record."""
    import cv2
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    exemplars = selection.exemplars
    by_source = {exemplar.path: exemplar for exemplar in selection.candidates}
    record = {"format": "semloc.template_selection", "version": 1, "classes": {}}
    for class_name, steps in selection.chosen.items():
        (folder / class_name / "masks").mkdir(parents=True, exist_ok=True)
        names = []
        for step in steps:
            exemplar = by_source[exemplars[step.exemplar][1]]
            source = Path(exemplar.path)
            # Two libraries may both hold e.g. clock_00.png: the second keeps its library's name in front.
            name = f"{source.stem}.png"
            if name in names:
                name = f"{source.parent.parent.name}_{name}"
            names.append(name)
            cv2.imwrite(str(folder / class_name / name), exemplar.image)
            if exemplar.mask is not None:
                cv2.imwrite(str(folder / class_name / "masks" / name), exemplar.mask.astype(np.uint8) * 255)
        record["classes"][class_name] = [
            {"file": f"{class_name}/{name}", "source": exemplars[step.exemplar][1], "hits": step.hits,
             "misses": step.misses, "hallucinations": step.hallucinations}
            for name, step in zip(names, steps)]
    config = {**selection.config, "templates": ".", "files": None}
    (folder / "detector.yaml").write_text(yaml.safe_dump({k: v for k, v in config.items() if v is not None},
                                                         sort_keys=False))
    (folder / "selection.json").write_text(json.dumps(record, indent=1))
    return record
