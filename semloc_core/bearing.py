"""Bearing bins and heatlines (thesis §4.4.2, §4.7.2).

A heatline is, per object class, the detector score as a function of bearing in the body frame. Bins cover the full
turn [-pi, pi) so that heatlines from a pinhole camera, a rig and a panorama share one layout; ``observed`` marks the
bins inside the camera's field of view (a bin outside it carries no evidence, not a zero score).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semloc_core.geometry import wrap_angle


@dataclass(frozen=True)
class BearingGrid:
    n_bins: int = 360

    def __post_init__(self) -> None:
        if int(self.n_bins) < 4:
            raise ValueError(f"a bearing grid needs at least 4 bins, got {self.n_bins}")

    @property
    def bin_width(self) -> float:
        return 2.0 * np.pi / self.n_bins

    @property
    def centers(self) -> np.ndarray:
        """Bin centres in radians: -pi + (i + 0.5) * width."""
        return -np.pi + (np.arange(self.n_bins) + 0.5) * self.bin_width

    def index(self, bearing) -> np.ndarray:
        """Bin index of each bearing (radians, any range)."""
        idx = np.floor((wrap_angle(bearing) + np.pi) / self.bin_width).astype(np.int64)
        return np.clip(idx, 0, self.n_bins - 1)

@dataclass(frozen=True, eq=False)
class Heatlines:
    """Per-class scores over bearing: ``scores`` (classes, bins) float32, ``observed`` (bins,) bool."""

    classes: tuple[str, ...]
    scores: np.ndarray
    observed: np.ndarray

    def __post_init__(self) -> None:
        scores = np.asarray(self.scores, dtype=np.float32)
        observed = np.asarray(self.observed, dtype=bool)
        if scores.ndim != 2 or scores.shape[0] != len(self.classes):
            raise ValueError(f"scores must be (n_classes={len(self.classes)}, n_bins), got {scores.shape}")
        if observed.shape != (scores.shape[1],):
            raise ValueError(f"observed must be ({scores.shape[1]},), got {observed.shape}")
        if not np.all(np.isfinite(scores)):
            raise ValueError("heatline scores must be finite")
        object.__setattr__(self, "classes", tuple(self.classes))
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "observed", observed)

    @property
    def grid(self) -> BearingGrid:
        return BearingGrid(self.scores.shape[1])
