"""Scale-selected back-projection: a window detector's pyramid level says how far its object is.

A window detector answers at pyramid level ``s`` for objects whose image fills its window there, i.e. whose box is
``window / s`` pixels; an object of physical extent ``E`` at depth ``Z`` (along the optical axis) spans
``f·E / Z`` pixels (focal length ``f``), so level ``s`` answers for objects at ``Z = (E / window) · f · s``. The
class constant ``depth_per_scale = E / window`` (metres per focal pixel per unit scale) is fitted on frames with
ground truth: each well-seen object's depth over ``f · s`` of the level answering it most strongly at its centre.

The §5.4 back-projection spreads a heatmap pixel along its whole ray (a cone behind each detection, peaks of other
objects' cones crossing it). With the levels, voxel ``X`` at depth ``Z`` of a frame takes, for each class, the
heat of the one level whose depth band holds ``Z`` (bands meet halfway between adjacent levels' depths, in log
depth): only detections of the right apparent size vote for it. This is an extension of the thesis (whose DOT
templates carry no scale), measured in docs/mapping.md.
"""

from __future__ import annotations

import numpy as np


def level_depths(depth_per_scale, scales, focal: float) -> np.ndarray:
    """(classes, levels) depth in metres at which each class's window at each level answers, for a camera of
    focal length ``focal`` pixels (of the image the detector saw)."""
    per_scale = np.asarray(depth_per_scale, dtype=float).reshape(-1)
    s = np.asarray(scales, dtype=float).reshape(-1)
    if not (np.all(np.isfinite(per_scale)) and np.all(per_scale > 0)):
        raise ValueError(f"depth_per_scale must be positive and finite, got {per_scale}")
    if not (s.size and np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError(f"scales must be positive and finite, got {s}")
    if not (np.isfinite(focal) and focal > 0):
        raise ValueError(f"focal length must be positive, got {focal}")
    return per_scale[:, None] * s[None, :] * float(focal)


def calibration_mismatch(fitted_scales, fitted_classes, scales, classes) -> str | None:
    """Why a scale-depth calibration (its pyramid ``fitted_scales`` and the classes it has a depth per scale for)
    does not fit a detector's level maps (``scales``, ``classes``), or None if it does."""
    fitted, given = [float(v) for v in fitted_scales], [float(v) for v in scales]
    if len(fitted) != len(given) or not np.allclose(given, fitted, rtol=1e-6, atol=0):
        return f"level scales {given} differ from the scale-depth calibration's {fitted}"
    missing = [name for name in classes if name not in fitted_classes]
    if missing:
        return f"the scale-depth calibration has no depth per scale for classes {missing}"
    return None


def depth_bands(depths, near: float, far: float) -> np.ndarray:
    """(classes, levels, 2) [near, far) depth band of each level: adjacent levels' bands meet at the geometric mean
    of their depths; the nearest level's band starts at ``near``, the farthest's ends at ``far`` (so a class's
    bands cover [near, far] once)."""
    d = np.asarray(depths, dtype=float)
    if d.ndim != 2 or not np.all(d > 0):
        raise ValueError(f"depths must be (classes, levels) and positive, got shape {d.shape}")
    bands = np.empty(d.shape + (2,))
    for c in range(d.shape[0]):
        order = np.argsort(d[c])
        sorted_depths = d[c, order]
        edges = np.concatenate([[near], np.sqrt(sorted_depths[:-1] * sorted_depths[1:]), [far]])
        edges = np.clip(edges, near, far)
        bands[c, order, 0] = edges[:-1]
        bands[c, order, 1] = edges[1:]
    return bands


def reach_over_levels(level_maps, depths, reach: int) -> np.ndarray:
    """(classes, levels, H, W) maps where each level holds the max over the levels within ``reach`` steps of it in
    depth order (per class, ``depths`` (classes, levels)); ``reach`` 0 returns the maps unchanged."""
    maps = np.asarray(level_maps)
    d = np.asarray(depths, dtype=float)
    if reach <= 0 or maps.ndim != 4 or maps.shape[:2] != d.shape:
        return maps  # (a shape mismatch is the mapper's to report)
    out = np.empty(maps.shape, np.result_type(maps.dtype, np.float32))
    for c in range(maps.shape[0]):
        order = np.argsort(d[c])
        for rank, level in enumerate(order):
            near = order[max(rank - reach, 0):rank + reach + 1]
            out[c, level] = maps[c, near].max(axis=0)
    return out


def fit_depth_per_scale(depths, focals, scales) -> dict:
    """``depth_per_scale`` of one class from samples (object depth Z, focal f, answering level's scale s): the
    median of ``Z / (f·s)``, with the spread of its log (median absolute deviation × 1.4826) and the count."""
    z, f, s = (np.asarray(a, dtype=float).reshape(-1) for a in (depths, focals, scales))
    if not (z.size == f.size == s.size) or z.size == 0:
        raise ValueError("need the same number (> 0) of depths, focal lengths and scales")
    if not (np.all(np.isfinite(z) & (z > 0)) and np.all(np.isfinite(f) & (f > 0))
            and np.all(np.isfinite(s) & (s > 0))):
        raise ValueError("depths, focal lengths and scales must be positive and finite")
    log_ratio = np.log(z / (f * s))
    centre = float(np.median(log_ratio))
    return {"depth_per_scale": float(np.exp(centre)),
            "log_spread": float(1.4826 * np.median(np.abs(log_ratio - centre))), "samples": int(z.size)}
