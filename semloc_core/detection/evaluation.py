"""Running a detector over a dataset with object ground truth: heatlines per frame, hit/miss/hallucination counts,
score samples for calibration.

Used by ``semloc calibrate`` (score likelihoods, §4.8.2) and ``benchmarks/detection_accuracy.py`` (the issue's
accuracy table). A dataset is anything with ``len``, ``image(i)`` (BGR, or a tuple per rig camera), ``camera``,
``T_body_cam_at(i)`` and ``visible_objects(i)`` (``semloc_core.io.dataset.Dataset`` and simulated scenarios).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.camera import CameraRig, members
from semloc_core.detection.heatlines import HeatlineProjector, heatline_peaks
from semloc_core.geometry import angle_diff


@dataclass(frozen=True)
class GroundTruthObject:
    """One object seen in a frame, reduced to what heatlines can be checked against."""

    class_name: str
    bearing: float      # radians, body frame
    usable: bool        # visible, unoccluded, tall enough: counted as a hit or a miss
    height_px: float
    object_index: int


@dataclass(frozen=True)
class UsableCriteria:
    """Which ground-truth objects a heatline must find (the issue's "visible, unoccluded, >= 30 px tall")."""

    min_height_px: float = 30.0
    max_occluded_fraction: float = 0.1
    allow_truncated: bool = False


def frame_objects(visible, criteria: UsableCriteria = UsableCriteria()) -> list[GroundTruthObject]:
    """Ground-truth objects of one frame; an object seen by several rig cameras counts once (its best view)."""
    best: dict[int, GroundTruthObject] = {}
    for obj in visible:
        height = float(obj.box[3] - obj.box[1])
        usable = (height >= criteria.min_height_px and obj.occluded_fraction <= criteria.max_occluded_fraction
                  and (criteria.allow_truncated or not obj.truncated) and obj.visible_pixels > 0)
        candidate = GroundTruthObject(obj.class_name, float(obj.bearing), usable, height, int(obj.object_index))
        previous = best.get(candidate.object_index)
        if previous is None or (candidate.usable, candidate.height_px) > (previous.usable, previous.height_px):
            best[candidate.object_index] = candidate
    return list(best.values())


def frame_images(dataset, i: int) -> list[np.ndarray]:
    images = dataset.image(i)
    return list(images) if isinstance(images, (tuple, list)) else [images]


def frame_overrides(dataset, i: int):
    """The per-frame T_body_cam for the projector: a 4x4 for a single camera, None entries for a rig."""
    if isinstance(dataset.camera, CameraRig):
        return None
    return dataset.T_body_cam_at(i)


def run_detector(dataset, detector, frames, grid: BearingGrid = BearingGrid(),
                 criteria: UsableCriteria = UsableCriteria()):
    """Yield ``(frame index, Heatlines, [GroundTruthObject])`` for each frame index in ``frames``."""
    projector = HeatlineProjector(dataset.camera, detector.classes, grid)
    n_cameras = len(members(dataset.camera))
    for i in frames:
        images = frame_images(dataset, i)
        if len(images) != n_cameras:
            raise ValueError(f"frame {i}: {len(images)} images for {n_cameras} cameras")
        heatmaps = [detector.heatmaps(image) for image in images]
        heatlines = projector.project(heatmaps, T_body_cam=frame_overrides(dataset, i))
        yield i, heatlines, frame_objects(dataset.visible_objects(i), criteria)


# ---------------------------------------------------------------------------------------------------- scoring


@dataclass
class ClassCounts:
    hits: int = 0
    misses: int = 0
    hallucinations: int = 0
    peak_errors_deg: list = field(default_factory=list)

    @property
    def hit_rate(self) -> float:
        total = self.hits + self.misses
        return self.hits / total if total else float("nan")

    def as_dict(self) -> dict:
        errors = np.abs(self.peak_errors_deg) if self.peak_errors_deg else np.zeros(0)
        return {"hits": self.hits, "misses": self.misses, "hallucinations": self.hallucinations,
                "hit_rate": self.hit_rate, "median_abs_error_deg": float(np.median(errors)) if errors.size else None}


def score_soft(heatlines: Heatlines, objects: list[GroundTruthObject], tolerance_deg: float = 5.0) -> dict:
    """Soft heatlines, no threshold: per class with N usable objects, its N strongest peaks (non-maximum suppressed
    at ``tolerance_deg``) are the heatline's answer. A usable object is hit when one of them lies within
    ``tolerance_deg`` of its bearing; a peak near no visible object of the class (usable or not) is a
    hallucination. Classes with no usable object in the frame are not scored (a soft detector makes no claim)."""
    grid = heatlines.grid
    separation = max(1, int(round(np.radians(tolerance_deg) / grid.bin_width)))
    counts = {name: ClassCounts() for name in heatlines.classes}
    for k, name in enumerate(heatlines.classes):
        usable = [o for o in objects if o.class_name == name and o.usable]
        if not usable:
            continue
        peaks = heatline_peaks(heatlines.scores[k], heatlines.observed, separation, max_peaks=len(usable))
        _match(grid.centers[peaks], usable, [o for o in objects if o.class_name == name], tolerance_deg, counts[name])
    return counts


def score_hard(hard: Heatlines, objects: list[GroundTruthObject], tolerance_deg: float = 5.0) -> dict:
    """Hard (binary) heatlines: every detection (a run of ones, at its centre) is matched; unlike soft scoring,
    classes without any usable object are scored too (their detections are hallucinations unless near a visible
    object of the class)."""
    grid = hard.grid
    counts = {name: ClassCounts() for name in hard.classes}
    for k, name in enumerate(hard.classes):
        bearings = _run_centres(hard.scores[k] > 0.5, grid)
        usable = [o for o in objects if o.class_name == name and o.usable]
        _match(bearings, usable, [o for o in objects if o.class_name == name], tolerance_deg, counts[name])
    return counts


def _run_centres(binary: np.ndarray, grid: BearingGrid) -> np.ndarray:
    """Bearings of the centres of circular runs of True bins."""
    if not binary.any():
        return np.zeros(0)
    if binary.all():
        return np.zeros(1)
    start = int(np.flatnonzero(~binary)[0])
    rolled = np.roll(binary, -start)
    edges = np.diff(np.concatenate([[0], rolled.astype(np.int8), [0]]))
    begins, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    centres = (begins + ends - 1) / 2.0 + start
    return -np.pi + (centres + 0.5) * grid.bin_width


def _match(peak_bearings, usable, visible, tolerance_deg: float, counts: ClassCounts) -> None:
    tolerance = np.radians(tolerance_deg)
    peak_bearings = np.asarray(peak_bearings, float)
    used = np.zeros(len(peak_bearings), bool)
    for obj in sorted(usable, key=lambda o: -o.height_px):
        if len(peak_bearings) == 0:
            counts.misses += 1
            continue
        error = np.abs(angle_diff(peak_bearings, obj.bearing))
        error[used] = np.inf
        best = int(np.argmin(error))
        if error[best] <= tolerance:
            used[best] = True
            counts.hits += 1
            counts.peak_errors_deg.append(float(np.degrees(angle_diff(peak_bearings[best], obj.bearing))))
        else:
            counts.misses += 1
    for bearing, matched in zip(peak_bearings, used):
        if matched:
            continue
        near_visible = any(abs(angle_diff(bearing, o.bearing)) <= tolerance for o in visible)
        if not near_visible:
            counts.hallucinations += 1


def accumulate(total: dict, frame_counts: dict) -> None:
    for name, counts in frame_counts.items():
        into = total.setdefault(name, ClassCounts())
        into.hits += counts.hits
        into.misses += counts.misses
        into.hallucinations += counts.hallucinations
        into.peak_errors_deg.extend(counts.peak_errors_deg)

