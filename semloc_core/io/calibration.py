"""Detector score likelihoods p(z|d) and p(z|not d) (thesis §4.7.3, §4.8.2): the file the localizer loads.

Written by ``semloc calibrate`` (``semloc_core.detection.calibration.fit_score_likelihoods``), read by the
localizer's generative perception model (eq. 4.23-4.27). On disk it is JSON (no pickle)::

    {
      "format": "semloc.score_likelihood",
      "version": 1,
      "z": {"min": 0.0, "max": 1.0, "count": 1000},     # one uniform score grid shared by every class
      "classes": {
        "bowl": {
          "pdf_d":     [1000 floats],   # p(z | d): density of heatline scores at bearings holding an object
          "pdf_not_d": [1000 floats],   # p(z | not d): density at bearings holding none
          "n_d": 1234, "n_not_d": 56789,  # how many samples each density was fitted to
          "bandwidth_d": 0.031, "bandwidth_not_d": 0.012
        },
        ...
      },
      "detector": {...},                 # free-form: what produced the scores (kind, template library, scales...)
      "source": "datasets/tabletop"      # free-form: the data the densities were fitted on
    }

The grid value ``z[i] = min + i * (max - min) / (count - 1)``. Each density integrates to 1 over the grid
(trapezoid rule). Looking a score up interpolates linearly between grid points; a score outside the grid takes the
density at the nearest end. ``floor`` keeps the log-likelihood finite where a density is (numerically) zero.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from semloc_core.io.atomic import replace_text
from semloc_core.io.errors import FileFormatError

FORMAT_NAME = "semloc.score_likelihood"
FORMAT_VERSION = 1


class CalibrationFormatError(FileFormatError):
    """A score-likelihood file or object that does not follow the format."""


def _per_class(value, count: int, dtype) -> np.ndarray:
    """Optional per-class statistics: zeros when absent, else exactly one value per class."""
    if value is None:
        return np.zeros(count, dtype)
    array = np.asarray(value, dtype)
    if array.size != count:
        raise CalibrationFormatError(f"expected one value per class ({count}), got {array.size}")
    return array.reshape(count)


@dataclass(frozen=True, eq=False)
class ScoreLikelihoods:
    """Per-class densities on one uniform score grid: ``pdf_d`` and ``pdf_not_d`` are (classes, count) float64."""

    classes: tuple[str, ...]
    z_min: float
    z_max: float
    pdf_d: np.ndarray
    pdf_not_d: np.ndarray
    n_d: np.ndarray = field(default=None)
    n_not_d: np.ndarray = field(default=None)
    bandwidth_d: np.ndarray = field(default=None)
    bandwidth_not_d: np.ndarray = field(default=None)
    detector: dict = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        classes = tuple(str(name) for name in self.classes)
        if not classes or len(set(classes)) != len(classes) or any(not name for name in classes):
            raise CalibrationFormatError(f"classes must be unique non-empty names, got {classes}")
        if not (np.isfinite(self.z_min) and np.isfinite(self.z_max) and self.z_min < self.z_max):
            raise CalibrationFormatError(f"score grid needs finite min < max, got [{self.z_min}, {self.z_max}]")
        pdf_d = np.array(self.pdf_d, dtype=np.float64, ndmin=2)
        pdf_not_d = np.array(self.pdf_not_d, dtype=np.float64, ndmin=2)
        for name, pdf in (("pdf_d", pdf_d), ("pdf_not_d", pdf_not_d)):
            if pdf.shape[0] != len(classes) or pdf.shape[1] < 2:
                raise CalibrationFormatError(f"{name} must be (classes={len(classes)}, count>=2), got {pdf.shape}")
            if not np.all(np.isfinite(pdf)) or np.any(pdf < 0):
                raise CalibrationFormatError(f"{name} must be finite and non-negative")
        if pdf_d.shape != pdf_not_d.shape:
            raise CalibrationFormatError(f"pdf_d {pdf_d.shape} and pdf_not_d {pdf_not_d.shape} differ in shape")
        count = len(classes)
        object.__setattr__(self, "classes", classes)
        object.__setattr__(self, "z_min", float(self.z_min))
        object.__setattr__(self, "z_max", float(self.z_max))
        object.__setattr__(self, "pdf_d", pdf_d)
        object.__setattr__(self, "pdf_not_d", pdf_not_d)
        object.__setattr__(self, "n_d", _per_class(self.n_d, count, np.int64))
        object.__setattr__(self, "n_not_d", _per_class(self.n_not_d, count, np.int64))
        object.__setattr__(self, "bandwidth_d", _per_class(self.bandwidth_d, count, np.float64))
        object.__setattr__(self, "bandwidth_not_d", _per_class(self.bandwidth_not_d, count, np.float64))

    @property
    def count(self) -> int:
        return int(self.pdf_d.shape[1])

    @property
    def z(self) -> np.ndarray:
        """The score grid, shape (count,)."""
        return np.linspace(self.z_min, self.z_max, self.count)

    def class_index(self, class_name: str) -> int:
        try:
            return self.classes.index(class_name)
        except ValueError:
            raise KeyError(f"class {class_name!r} is not calibrated (have {list(self.classes)})") from None

    def _interpolate(self, table: np.ndarray, scores: np.ndarray) -> np.ndarray:
        # Uniform grid: index arithmetic instead of a search, so a (particles x bins) lookup stays cheap.
        position = (np.clip(scores, self.z_min, self.z_max) - self.z_min) * ((self.count - 1) / (self.z_max - self.z_min))
        lower = np.minimum(position.astype(np.int64), self.count - 2)
        fraction = position - lower
        return table[..., lower] * (1.0 - fraction) + table[..., lower + 1] * fraction

    def lookup(self, class_name: str, scores, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """(p(z|d), p(z|not d)) for scores of one class, any shape; both at least ``floor``."""
        k = self.class_index(class_name)
        scores = np.asarray(scores, dtype=np.float64)
        return (np.maximum(self._interpolate(self.pdf_d[k], scores), floor),
                np.maximum(self._interpolate(self.pdf_not_d[k], scores), floor))

    def tables(self, class_names, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """(pdf_d, pdf_not_d) rows for ``class_names`` in that order, floored; shape (len(class_names), count)."""
        rows = [self.class_index(name) for name in class_names]
        return np.maximum(self.pdf_d[rows], floor), np.maximum(self.pdf_not_d[rows], floor)

    def to_dict(self) -> dict:
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "z": {"min": self.z_min, "max": self.z_max, "count": self.count},
            "classes": {
                name: {
                    "pdf_d": self.pdf_d[k].tolist(),
                    "pdf_not_d": self.pdf_not_d[k].tolist(),
                    "n_d": int(self.n_d[k]),
                    "n_not_d": int(self.n_not_d[k]),
                    "bandwidth_d": float(self.bandwidth_d[k]),
                    "bandwidth_not_d": float(self.bandwidth_not_d[k]),
                }
                for k, name in enumerate(self.classes)
            },
            "detector": self.detector,
            "source": self.source,
        }

    @classmethod
    def from_dict(cls, document: dict) -> "ScoreLikelihoods":
        if not isinstance(document, dict):
            raise CalibrationFormatError("a score-likelihood document must be a JSON object")
        if document.get("format") != FORMAT_NAME:
            raise CalibrationFormatError(f"expected format {FORMAT_NAME!r}, got {document.get('format')!r}")
        if document.get("version") != FORMAT_VERSION:
            raise CalibrationFormatError(
                f"unsupported version {document.get('version')!r} (this semloc reads version {FORMAT_VERSION})")
        try:
            grid = document["z"]
            z_min, z_max, count = float(grid["min"]), float(grid["max"]), int(grid["count"])
            entries = document["classes"]
            if not isinstance(entries, dict) or not entries:
                raise CalibrationFormatError("'classes' must be a non-empty mapping of class name to densities")
            names = tuple(entries)
            pdf_d = [entries[name]["pdf_d"] for name in names]
            pdf_not_d = [entries[name]["pdf_not_d"] for name in names]
            if any(len(row) != count for row in pdf_d + pdf_not_d):
                raise CalibrationFormatError(f"every density must have z.count = {count} values")
            return cls(
                classes=names, z_min=z_min, z_max=z_max, pdf_d=pdf_d, pdf_not_d=pdf_not_d,
                n_d=[entries[name].get("n_d", 0) for name in names],
                n_not_d=[entries[name].get("n_not_d", 0) for name in names],
                bandwidth_d=[entries[name].get("bandwidth_d", 0.0) for name in names],
                bandwidth_not_d=[entries[name].get("bandwidth_not_d", 0.0) for name in names],
                detector=dict(document.get("detector") or {}),
                source=str(document.get("source") or ""),
            )
        except CalibrationFormatError:
            raise
        except (KeyError, TypeError, ValueError) as error:
            raise CalibrationFormatError(f"malformed score-likelihood document: {error!r}") from error


def save_score_likelihoods(likelihoods: ScoreLikelihoods, path) -> Path:
    """Write JSON atomically (a reader never sees a half-written file)."""
    path = Path(path)
    return replace_text(path, json.dumps(likelihoods.to_dict(), allow_nan=False))


def load_score_likelihoods(path) -> ScoreLikelihoods:
    path = Path(path)
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CalibrationFormatError(f"{path}: not a readable JSON score-likelihood file: {error}") from error
    try:
        return ScoreLikelihoods.from_dict(document)
    except CalibrationFormatError as error:
        raise CalibrationFormatError(f"{path}: {error}") from error
