"""The mapper's calibration file: what ``semloc eval mapping`` fits on calibration scenes (a demo world's
``mapper_extraction.json`` is one), read by the mapper's ``extraction_file`` and ``scale_depth_file``.

JSON, per heatmap source (``detector``, ``oracle``) and score mode (``normalised``, ``sum``)::

    {
      "detector": {
        "normalised": {"threshold": 0.65, "class_scales": {"bowl": 4.0, ...}, "tophat": 2.0, "cross_class": true,
                       "resting": false, "class_sizes": {"bowl": [0.2, 0.2, 0.1], ...},
                       "existence": {"reference": 0.65, "intercept": 1.06, "slope": 9.5, ...}, ...},
        "sum": {...},
        "scale_depth": {"scales": [1.2, 0.85, ...], "classes": {"bowl": {"depth_per_scale": 0.0047, ...}, ...}}
      },
      ...
    }

An extraction fit is a mapping of ``semloc_core.mapping.ExtractionConfig`` fields, checked by that class when it is
applied (``semloc_core.settings.updated``); the depth per scale has no such class and is checked here.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from semloc_core.io.errors import FileFormatError

# The extraction settings a calibration fits (the other fields of ExtractionConfig stay the mapper's own).
FITTED_EXTRACTION = ("threshold", "class_scales", "tophat", "cross_class", "resting", "class_sizes", "existence")


class MappingCalibrationError(FileFormatError):
    """A mapper calibration file that cannot be read or lacks what is asked of it."""


def _detector_entry(path, name: str, what: str) -> dict:
    """The ``detector`` -> ``name`` mapping of the calibration in ``path`` (``what``: the setting that names it)."""
    try:
        document = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise MappingCalibrationError(f"{what} {path}: cannot read it ({error})") from None
    source = document.get("detector") if isinstance(document, dict) else None
    entry = source.get(name) if isinstance(source, dict) else None
    if not isinstance(entry, dict):
        raise MappingCalibrationError(f"{what} {path}: no 'detector' -> '{name}' entry (is it a calibration "
                                      f"semloc eval mapping fitted on detector heatmaps?)")
    return entry


def extraction_fit(path, normalise: bool) -> dict:
    """The extraction settings fitted in ``path`` for the detector's score mode (``normalise``: normalised, else
    sum), as a mapping of ExtractionConfig fields; it has at least a threshold."""
    mode = "normalised" if normalise else "sum"
    entry = _detector_entry(path, mode, "extraction_file")
    if "threshold" not in entry:
        raise MappingCalibrationError(f"extraction_file {path}: {mode} has no threshold")
    return {name: entry[name] for name in FITTED_EXTRACTION if name in entry}


def _positive(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def scale_depth_fit(path) -> dict:
    """The depth per scale fitted in ``path`` (its ``detector.scale_depth``), checked: {"scales": [...], "classes":
    {name: metres per focal pixel per unit scale}}."""
    entry = _detector_entry(path, "scale_depth", "scale_depth_file")
    scales, classes = entry.get("scales"), entry.get("classes")
    if not (isinstance(scales, list) and scales and all(_positive(v) for v in scales)):
        raise MappingCalibrationError(f"scale_depth_file {path}: scales = {scales!r} is not a list of positive "
                                      f"numbers")
    if not (isinstance(classes, dict) and classes):
        raise MappingCalibrationError(f"scale_depth_file {path}: classes = {classes!r} is not a mapping of classes")
    depth_per_scale = {}
    for name, fit in classes.items():
        value = fit.get("depth_per_scale") if isinstance(fit, dict) else None
        if not _positive(value):
            raise MappingCalibrationError(f"scale_depth_file {path}: {name}.depth_per_scale = {value!r} is not a "
                                          f"positive number")
        depth_per_scale[name] = float(value)
    return {"scales": [float(v) for v in scales], "classes": depth_per_scale}
