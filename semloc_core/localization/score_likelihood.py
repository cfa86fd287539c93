"""Detector score likelihoods p(z|d) and p(z|d̄) (thesis eq. 4.24, §4.7.3, §4.8.2-4.8.3).

Model B needs, per object class, the density of a detector score ``z`` at a bearing where an object is (``d``) and
where none is (``d̄``). The thesis learns them by kernel density estimation and samples them at 1000 points; here
they are kept in that same form: one increasing score grid and two densities per class, linearly interpolated.
Scores outside the grid take the end values. Densities are floored so that a score the calibration never saw
costs a large but finite penalty instead of ``log(0)``.

Sources:

* ``ScoreLikelihood.gaussian`` - normal densities (the *synthetic-scores* model of §4.8.3: N(0.75, 0.25) and
  N(0.25, 0.25), see ``synthetic_scores_likelihood``).
* ``ScoreLikelihood.from_calibration`` - the densities of a ``semloc.score_likelihood`` file
  (``semloc_core.io.calibration``, written by ``semloc calibrate``); ``load_score_likelihood(path)`` reads one.
* ``ScoreLikelihood.binary`` - hit and false-alarm rates of a hard (0/1) detector, for hardened heatlines.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

DEFAULT_DENSITY_FLOOR = 1e-6


@dataclass(frozen=True, eq=False)
class ScoreLikelihood:
    """Per-class score densities on a shared grid: ``detection`` = p(z|d), ``background`` = p(z|d̄), each (C, G)."""

    classes: tuple[str, ...]
    grid: np.ndarray
    detection: np.ndarray
    background: np.ndarray
    floor: float = DEFAULT_DENSITY_FLOOR

    def __post_init__(self) -> None:
        classes = tuple(str(c) for c in self.classes)
        if not classes or len(set(classes)) != len(classes):
            raise ValueError(f"score likelihood classes must be non-empty and unique, got {classes}")
        grid = np.asarray(self.grid, dtype=np.float64).reshape(-1)
        if grid.size < 2 or not np.all(np.isfinite(grid)) or not np.all(np.diff(grid) > 0):
            raise ValueError("score grid must hold at least 2 finite, strictly increasing values")
        shape = (len(classes), grid.size)
        arrays = {}
        for name in ("detection", "background"):
            values = np.asarray(getattr(self, name), dtype=np.float64)
            if values.ndim == 1 and values.shape[0] == grid.size:
                values = np.broadcast_to(values, shape).copy()
            if values.shape != shape:
                raise ValueError(f"{name} densities must be (n_classes={shape[0]}, n_grid={shape[1]}), "
                                 f"got {values.shape}")
            if not np.all(np.isfinite(values)) or np.any(values < 0):
                raise ValueError(f"{name} densities must be finite and non-negative")
            arrays[name] = values
        if not (np.isfinite(self.floor) and self.floor > 0):
            raise ValueError(f"density floor must be positive, got {self.floor}")
        object.__setattr__(self, "classes", classes)
        object.__setattr__(self, "grid", grid)
        object.__setattr__(self, "detection", arrays["detection"])
        object.__setattr__(self, "background", arrays["background"])
        object.__setattr__(self, "floor", float(self.floor))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def gaussian(cls, classes: Sequence[str], detection_mean, detection_std, background_mean, background_std,
                 n_grid: int = 1000, floor: float = DEFAULT_DENSITY_FLOOR) -> "ScoreLikelihood":
        """Normal p(z|d) = N(detection_mean, detection_std), p(z|d̄) = N(background_mean, background_std).

        Means and standard deviations are scalars or one value per class. The grid spans every mean ± 8 std.
        """
        classes = tuple(classes)
        c = len(classes)
        params = [np.broadcast_to(np.asarray(v, dtype=float), (c,)) for v in
                  (detection_mean, detection_std, background_mean, background_std)]
        if np.any(params[1] <= 0) or np.any(params[3] <= 0):
            raise ValueError("standard deviations must be positive")
        low = min((params[0] - 8 * params[1]).min(), (params[2] - 8 * params[3]).min())
        high = max((params[0] + 8 * params[1]).max(), (params[2] + 8 * params[3]).max())
        grid = np.linspace(low, high, int(n_grid))
        return cls(classes, grid, _normal_pdf(grid[None], params[0][:, None], params[1][:, None]),
                   _normal_pdf(grid[None], params[2][:, None], params[3][:, None]), floor=floor)

    @classmethod
    def from_calibration(cls, calibration, floor: float = DEFAULT_DENSITY_FLOOR) -> "ScoreLikelihood":
        """From ``semloc_core.io.calibration.ScoreLikelihoods`` (the calibration file's densities)."""
        return cls(calibration.classes, calibration.z, calibration.pdf_d, calibration.pdf_not_d, floor=floor)

    @classmethod
    def binary(cls, classes: Sequence[str], hit_rate=0.9, false_alarm_rate=0.05,
               floor: float = DEFAULT_DENSITY_FLOOR) -> "ScoreLikelihood":
        """Likelihood of a hard detector whose heatlines are 0/1: P(z=1|d) = hit_rate, P(z=1|d̄) = false_alarm_rate.

        Both may be per class. Scores between 0 and 1 interpolate linearly (a bin half-covered by a detection).
        """
        classes = tuple(classes)
        hit = np.broadcast_to(np.asarray(hit_rate, dtype=float), (len(classes),))
        false_alarm = np.broadcast_to(np.asarray(false_alarm_rate, dtype=float), (len(classes),))
        for name, rate in (("hit_rate", hit), ("false_alarm_rate", false_alarm)):
            if np.any(rate <= 0) or np.any(rate >= 1):
                raise ValueError(f"{name} must be in (0, 1), got {rate}")
        grid = np.array([0.0, 1.0])
        return cls(classes, grid, np.stack([1 - hit, hit], axis=1), np.stack([1 - false_alarm, false_alarm], axis=1),
                   floor=floor)

    # ------------------------------------------------------------------ evaluation
    def subset(self, classes: Sequence[str]) -> "ScoreLikelihood":
        """The likelihoods of some classes, in the given order (KeyError names the missing class)."""
        rows = [self.index(c) for c in classes]
        return ScoreLikelihood(tuple(classes), self.grid, self.detection[rows], self.background[rows], self.floor)

    def index(self, class_name: str) -> int:
        try:
            return self.classes.index(class_name)
        except ValueError:
            raise KeyError(f"no score likelihood for class {class_name!r} (have {list(self.classes)})") from None

    def log_densities(self, scores, class_rows: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """log p(z|d) and log p(z|d̄) of a (C, B) score array; row c uses likelihood row ``class_rows[c]``."""
        scores = np.asarray(scores, dtype=np.float64)
        if scores.ndim != 2:
            raise ValueError(f"scores must be (n_classes, n_bins), got {scores.shape}")
        rows = range(scores.shape[0]) if class_rows is None else class_rows
        if len(rows) != scores.shape[0]:
            raise ValueError(f"need one likelihood row per score row ({scores.shape[0]}), got {len(rows)}")
        log_d = np.empty_like(scores)
        log_b = np.empty_like(scores)
        for out_row, row in enumerate(rows):
            log_d[out_row] = np.log(np.maximum(np.interp(scores[out_row], self.grid, self.detection[row]), self.floor))
            log_b[out_row] = np.log(np.maximum(np.interp(scores[out_row], self.grid, self.background[row]),
                                               self.floor))
        return log_d, log_b

    def sample(self, class_row: int, detected: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Draw scores z ~ p(z|d) where ``detected`` is True and z ~ p(z|d̄) elsewhere (inverse CDF on the grid)."""
        detected = np.asarray(detected, dtype=bool)
        out = np.empty(detected.shape, dtype=np.float64)
        for mask, pdf in ((detected, self.detection[class_row]), (~detected, self.background[class_row])):
            n = int(mask.sum())
            if n:
                out[mask] = _inverse_cdf_sample(self.grid, pdf, rng.random(n))
        return out


def load_score_likelihood(path, floor: float = DEFAULT_DENSITY_FLOOR) -> ScoreLikelihood:
    """Read a ``semloc.score_likelihood`` JSON file (raises ``CalibrationFormatError`` with the reason)."""
    from semloc_core.io.calibration import load_score_likelihoods

    return ScoreLikelihood.from_calibration(load_score_likelihoods(path), floor=floor)


def synthetic_scores_likelihood(classes: Sequence[str]) -> ScoreLikelihood:
    """The *synthetic-scores* model of §4.8.3: p(z|d) ~ N(0.75, 0.25), p(z|d̄) ~ N(0.25, 0.25)."""
    return ScoreLikelihood.gaussian(classes, 0.75, 0.25, 0.25, 0.25)


def _normal_pdf(x, mean, std):
    return np.exp(-0.5 * ((x - mean) / std) ** 2) / (std * np.sqrt(2 * np.pi))


def _inverse_cdf_sample(grid: np.ndarray, pdf: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    # Trapezoid CDF of the piecewise-linear density; sampling inverts it linearly within each grid step.
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(grid))])
    if cdf[-1] <= 0:
        raise ValueError("cannot sample a score density that integrates to zero")
    return np.interp(uniform * cdf[-1], cdf, grid)
