"""Heatline sources built from ground truth (thesis §4.8.3).

Each source turns what is really in view - per visible object its class, the bearing of its centre and its angular
width (the ground-truth box, in bearing) - into ``Heatlines`` on a bearing grid:

* ``synthetic_scores_heatlines``: ẑ_i(θ) = exp(-((θ - x_i)/w_i)²), max over the instances of a class, floored at
  0.01 (§4.8.3); to be scored with ``synthetic_scores_likelihood`` (N(0.75, 0.25) vs N(0.25, 0.25)).
* ``simulated_dpm_heatlines``: eq. 4.29, z(θ) ~ p(z|d) within w_i of an instance, ~ p(z|d̄) elsewhere, with the
  learned (calibrated) score likelihoods - the detector's score statistics without the detector.

The hard (thresholded) variant of §4.5.2 is ``semloc_core.detection.heatlines.hard_heatlines``.

``visible_objects`` computes the ground-truth views from a pose and a map (no occlusion), for worlds built from
arrays; the simulator provides occlusion-aware views of its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.geometry import wrap_angle
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization.score_likelihood import ScoreLikelihood

SYNTHETIC_FLOOR = 0.01  # §4.8.3: "a small noise floor of 0.01 is added to avoid completely degenerate heatlines"


@dataclass(frozen=True, eq=False)
class ObjectViews:
    """Objects in view in one frame: ``class_names`` and, per object, ``class_index``, ``bearing`` of its centre
    (radians, body frame, docs/conventions.md) and ``width`` (angular width of its box, radians, > 0)."""

    class_names: tuple[str, ...]
    class_index: np.ndarray
    bearing: np.ndarray
    width: np.ndarray

    def __post_init__(self) -> None:
        class_index = np.asarray(self.class_index, dtype=np.int64).reshape(-1)
        bearing = np.asarray(self.bearing, dtype=np.float64).reshape(-1)
        width = np.asarray(self.width, dtype=np.float64).reshape(-1)
        if not (class_index.shape == bearing.shape == width.shape):
            raise ValueError(f"class_index, bearing, width must have one value per object, got "
                             f"{class_index.shape}, {bearing.shape}, {width.shape}")
        if class_index.size and (class_index.min() < 0 or class_index.max() >= len(self.class_names)):
            raise ValueError(f"class_index must index {len(self.class_names)} class names")
        if not (np.all(np.isfinite(bearing)) and np.all(np.isfinite(width)) and np.all(width > 0)):
            raise ValueError("bearings must be finite and widths finite and positive")
        object.__setattr__(self, "class_names", tuple(self.class_names))
        object.__setattr__(self, "class_index", class_index)
        object.__setattr__(self, "bearing", bearing)
        object.__setattr__(self, "width", width)


def _grid_difference(n_bins: int, bearings: np.ndarray) -> np.ndarray:
    """(objects, bins) signed bearing differences θ_bin - x_i, wrapped."""
    return wrap_angle(BearingGrid(n_bins).centers[None, :] - bearings[:, None])


def _check_observed(observed, n_bins: int) -> np.ndarray:
    observed = np.asarray(observed, dtype=bool)
    if observed.shape != (n_bins,):
        raise ValueError(f"observed mask must be ({n_bins},), got {observed.shape}")
    return observed


def synthetic_scores_heatlines(views: ObjectViews, observed, floor: float = SYNTHETIC_FLOOR) -> Heatlines:
    """§4.8.3 synthetic scores: max over instances of exp(-((θ - x_i)/w_i)²), at least ``floor``, in view only."""
    observed = _check_observed(observed, np.asarray(observed).shape[0])
    n_bins = observed.shape[0]
    scores = np.full((len(views.class_names), n_bins), floor, dtype=np.float64)
    if views.bearing.size:
        bumps = np.exp(-(_grid_difference(n_bins, views.bearing) / views.width[:, None]) ** 2)
        for c in range(len(views.class_names)):
            members = views.class_index == c
            if members.any():
                scores[c] = np.maximum(scores[c], bumps[members].max(axis=0))
    scores[:, ~observed] = 0.0
    return Heatlines(views.class_names, scores.astype(np.float32), observed)


def simulated_dpm_heatlines(views: ObjectViews, observed, likelihood: ScoreLikelihood,
                            rng: np.random.Generator) -> Heatlines:
    """Eq. 4.29: per bin, z ~ p(z|d) if |θ - x_i| <= w_i for an instance of the class, else z ~ p(z|d̄)."""
    observed = _check_observed(observed, np.asarray(observed).shape[0])
    n_bins = observed.shape[0]
    scores = np.zeros((len(views.class_names), n_bins))
    near = (np.abs(_grid_difference(n_bins, views.bearing)) <= views.width[:, None]) if views.bearing.size else None
    for c, name in enumerate(views.class_names):
        members = views.class_index == c
        detected = near[members].any(axis=0) if near is not None and members.any() else np.zeros(n_bins, bool)
        scores[c, observed] = likelihood.sample(likelihood.index(name), detected[observed], rng)
    return Heatlines(views.class_names, scores.astype(np.float32), observed)


def visible_objects(pose, semantic_map: SemanticMap, observed, class_names: Sequence[str] | None = None,
                    max_range: float = math.inf, default_size: float = 0.3) -> ObjectViews:
    """Ground-truth views from a planar pose: every mapped object within ``max_range`` whose bearing falls in an
    observed bin; angular width from its horizontal size (``default_size`` metres when the map has none).
    No occlusion."""
    pose = np.asarray(pose, dtype=np.float64)
    observed = np.asarray(observed, dtype=bool)
    grid = BearingGrid(observed.shape[0])
    names = tuple(class_names) if class_names is not None else semantic_map.class_names
    keep = np.array([semantic_map.class_names[k] in names for k in semantic_map.class_index], dtype=bool)
    delta = semantic_map.positions[:, :2] - pose[:2]
    distance = np.hypot(delta[:, 0], delta[:, 1])
    bearing = wrap_angle(np.arctan2(delta[:, 1], delta[:, 0]) - pose[2])
    size = np.where(semantic_map.sizes[:, :2].max(axis=1) > 0, semantic_map.sizes[:, :2].max(axis=1), default_size)
    width = 2.0 * np.arctan2(0.5 * size, np.maximum(distance, 1e-6))
    keep &= (distance <= max_range) & (distance > 0) & observed[grid.index(bearing)]
    class_index = np.array([names.index(semantic_map.class_names[k]) for k in semantic_map.class_index[keep]],
                           dtype=np.int64)
    return ObjectViews(names, class_index, bearing[keep], width[keep])


def field_of_view_mask(n_bins: int, center: float = 0.0, width: float = 2 * math.pi) -> np.ndarray:
    """Observed mask of the bins whose centre lies within ``width`` around bearing ``center`` (radians)."""
    centers = BearingGrid(n_bins).centers
    if width >= 2 * math.pi:
        return np.ones(n_bins, dtype=bool)
    return np.abs(wrap_angle(centers - center)) <= width / 2
