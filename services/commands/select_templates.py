"""`semloc select-templates DATASET -o LIBRARY`: choose each class's exemplar views on a training world.

Matches every candidate exemplar (default: the dataset's ``exemplars/`` and ``exemplars_multiview/``, each with its
mirror) over the dataset's frames once, then keeps per class the views that find its objects best under the soft
rule of the accuracy table (greedy forward selection, ``semloc_core.detection.selection``). Writes ``LIBRARY`` as a
template library (``<class>/<view>.png`` with ``<class>/masks/``), ``LIBRARY/detector.yaml`` (the template detector
configuration with ``templates: .``, ready for ``--detector`` / the detector worker's ``detector_file``) and
``LIBRARY/selection.json`` (every step with its hits, misses and hallucinations). Use a world other than the one
you evaluate on: this is training.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.commands import frame_progress, strided_frames


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="a semloc dataset folder with per-frame object ground truth (training world)")
    parser.add_argument("-o", "--output", required=True, help="template library folder to write")
    parser.add_argument("--library", action="append", default=None,
                        help="candidate exemplar folder (repeatable; default: the dataset's exemplars and "
                             "multi-view exemplars)")
    parser.add_argument("--detector", help="template detector configuration YAML whose settings the library is "
                                           "chosen for (default: calibrate's, docs/detection.md)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="override detector settings (YAML values), e.g. cell=4 template_cells=9")
    parser.add_argument("--max-per-class", type=int, default=4, help="at most this many views per class (4)")
    parser.add_argument("--min-height", type=float, default=30.0, help="objects that must be found: px tall (30)")
    parser.add_argument("--max-occluded", type=float, default=0.1, help="... and at most this occluded (0.1)")
    parser.add_argument("--tolerance-deg", type=float, default=5.0, help="a peak this close is a hit (5)")
    parser.add_argument("--frames", type=int, default=None, help="use at most this many frames")
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


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


def write_library(folder: Path, chosen: dict, exemplars, candidates, config: dict) -> dict:
    """Copy the chosen exemplars (image + mask) into a template library; returns the selection record."""
    folder.mkdir(parents=True, exist_ok=True)
    by_source = {exemplar.path: exemplar for exemplar in candidates}
    record = {"format": "semloc.template_selection", "version": 1, "classes": {}}
    for class_name, steps in chosen.items():
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
    config = {**config, "templates": ".", "files": None}
    (folder / "detector.yaml").write_text(yaml.safe_dump({k: v for k, v in config.items() if v is not None},
                                                         sort_keys=False))
    (folder / "selection.json").write_text(json.dumps(record, indent=1))
    return record


def select(dataset, config: dict, libraries, frames, criteria, max_per_class: int, tolerance_deg: float,
           output: Path, progress=None) -> dict:
    """Run the selection on ``dataset`` and write the library; every class of the candidates must get a view."""
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
                         f"--min-height")
    return write_library(output, chosen, exemplars, candidates, config)


def run(args) -> int:
    from semloc_core.detection.evaluation import UsableCriteria
    from semloc_core.io.dataset import DatasetError, open_dataset
    from semloc_core.io.detector_models import DetectorModelError, load_detector_config

    from services.commands.calibrate import default_detector_config

    try:
        dataset = open_dataset(args.dataset)
        libraries = args.library or [d for d in (dataset.exemplar_dir, dataset.multiview_dir) if d is not None]
        if not libraries:
            raise DatasetError(f"{args.dataset} has no exemplars: give --library DIR")
        config = load_detector_config(args.detector) if args.detector else default_detector_config(libraries[0])
        for item in args.set:
            key, _, value = item.partition("=")
            config[key] = yaml.safe_load(value)
        if config.get("kind") != "templates":
            raise DetectorModelError("template selection is for the §4.3 template detector (kind: templates)")
    except (DatasetError, DetectorModelError, OSError) as error:
        print(f"semloc select-templates: {error}", file=sys.stderr)
        return 2
    if args.stride < 1 or args.max_per_class < 1:
        print("semloc select-templates: --stride and --max-per-class must be >= 1", file=sys.stderr)
        return 2
    frames = strided_frames(len(dataset), args.stride, args.frames)
    progress = frame_progress(len(frames), args.quiet)

    criteria = UsableCriteria(args.min_height, args.max_occluded, allow_truncated=False)
    try:
        record = select(dataset, config, libraries, frames, criteria, args.max_per_class, args.tolerance_deg,
                        Path(args.output), progress)
    except (ValueError, DetectorModelError) as error:
        print(f"\nsemloc select-templates: {error}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(file=sys.stderr)
    for class_name, steps in record["classes"].items():
        last = steps[-1]
        print(f"{class_name:>16s}: {len(steps)} view(s), {last['hits']}/{last['hits'] + last['misses']} found on the "
              f"training frames: {', '.join(Path(s['source']).name for s in steps)}")
    print(f"wrote {args.output}")
    return 0
