"""Detection frames: ``Heatmaps`` (per-class score maps per member camera), ``HeatmapLevels`` (a window detector's
per-level maps) and ``Heatlines`` (scores over bearing).

Conventions (docs/detection.md, docs/conventions.md):

* A heatmap is ``(classes, rows, cols)`` covering its camera image uniformly: cell ``(r, q)`` covers pixels
  ``u in [q W/cols, (q+1) W/cols)``, ``v in [r H/rows, (r+1) H/rows)`` of the ``image_width`` x ``image_height``
  image (``cv2.resize``'s convention). Scores are in [0, 1]; on the wire they may be quantised: the score is
  ``value * scale`` (``scale = 1/255`` for uint8, 1 for floats). ``T_body_cam`` repeats the image's per-frame
  attitude override, if it had one, so a consumer back-projects with the attitude the detector used.
* ``HeatmapLevels`` holds ``(classes, levels, rows, cols)`` per camera, on the heatmap's cell grid: level ``l`` is
  what the detector answers at pyramid scale ``level_scales[l]`` (a window there fits objects of ``1 / scale``
  times its size). Its max over levels is the frame's ``Heatmaps``. The mapper uses it to bound each vote's depth
  (docs/mapping.md, scale-selected back-projection).
* A heatline is ``(classes, bins)`` over the full turn: bin ``i`` covers bearings ``[-pi + i 2pi/bins, ...)`` in the
  body frame (counter-clockwise from body x). ``observed`` marks the bins inside the field of view; a bin outside
  carries no evidence. ``hard`` is true for the thresholded, non-maximum-suppressed binary variant (§4.5.2).

Converters to and from ``semloc_core`` objects live in ``services.workers.detector`` (schemas depend on nothing of
ours).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from schemas.base import Array, Frame, FrameError, Sub
from schemas.camera import MAX_CAMERAS, MAX_SIDE, RigidTransform, Side
from schemas.limits import SCORE_TOLERANCE

MAX_CLASSES = 1024
MAX_BINS = 36_000
MAX_HEATMAP_ELEMENTS = 64 << 20
MAX_LEVELS = 16
ClassName = Annotated[str, Field(min_length=1, max_length=128)]
SCORES = "every score value * scale in [0, 1]"
Scale = Annotated[float, Field(gt=0.0, le=1e6)]


def _distinct(names):
    if len(set(names)) != len(names):
        raise ValueError(f"class names must be distinct, got {list(names)}")
    return names


def check_scores(values: np.ndarray, scale: float, what: str = "scores") -> None:
    """Scores ``values * scale`` within [0, 1] (FrameError ``range``); from the array's extremes."""
    if not values.size:
        return
    low, high = float(values.min()) * scale, float(values.max()) * scale
    if low < 0.0 or high > 1.0 + SCORE_TOLERANCE:
        raise FrameError(f"{what} span [{low:.6g}, {high:.6g}], outside [0, 1]", reason="range")


class _CameraMaps(Sub):
    """What the heatmaps of one member camera share: the image they cover and the score scale."""

    camera: Annotated[int, Field(ge=0, lt=MAX_CAMERAS)] = 0
    image_width: Side
    image_height: Side
    scores: Array(("uint8", "float16", "float32"), ndim=3, finite=True, max_elements=MAX_HEATMAP_ELEMENTS,
                  description=SCORES)
    scale: Scale = 1.0
    T_body_cam: RigidTransform | None = None

    @model_validator(mode="after")
    def _grid(self):
        rows, cols = self.scores.shape[-2:]
        if not (1 <= rows <= MAX_SIDE and 1 <= cols <= MAX_SIDE):
            raise ValueError(f"heatmap grid {rows}x{cols} out of range")
        check_scores(self.scores, self.scale, f"camera {self.camera}'s scores")
        return self

    def values(self) -> np.ndarray:
        """Scores as float32, the shape of ``scores``."""
        return self.scores.astype(np.float32) * np.float32(self.scale)


class CameraHeatmaps(_CameraMaps):
    """The heatmaps of one member camera: ``scores`` (classes, rows, cols); score = value * ``scale``."""


class _CameraMapsFrame(Frame):
    """What the heatmap frames share: distinct class names, the detector's name, per-camera maps checked against
    them (``_check_entry``)."""

    classes: tuple[ClassName, ...] = Field(min_length=1, max_length=MAX_CLASSES)
    detector: Annotated[str, Field(max_length=64)] = ""

    @field_validator("classes")
    @classmethod
    def _distinct_classes(cls, names):
        return _distinct(names)

    @model_validator(mode="after")
    def _consistent(self):
        cameras = [entry.camera for entry in self.maps]
        if len(set(cameras)) != len(cameras):
            raise ValueError(f"camera indices must be distinct, got {cameras}")
        for entry in self.maps:
            self._check_entry(entry)
        return self


class Heatmaps(_CameraMapsFrame, schema="semloc.Heatmaps", version=1, max_bytes=256 << 20):
    """Soft detections of one image frame: one heatmap per class and member camera (thesis §4.3, §4.6, §5.3)."""

    maps: Annotated[list[CameraHeatmaps], Field(min_length=1, max_length=MAX_CAMERAS)]

    def _check_entry(self, entry: CameraHeatmaps) -> None:
        if entry.scores.shape[0] != len(self.classes):
            raise ValueError(f"camera {entry.camera}: {entry.scores.shape[0]} heatmaps for {len(self.classes)} "
                             f"classes")


class CameraHeatmapLevels(_CameraMaps):
    """One member camera's per-level heatmaps: ``scores`` (classes, levels, rows, cols); score = value * ``scale``."""

    scores: Array(("uint8", "float16", "float32"), ndim=4, finite=True, max_elements=MAX_HEATMAP_ELEMENTS,
                  description=SCORES)


class HeatmapLevels(_CameraMapsFrame, schema="semloc.HeatmapLevels", version=1, max_bytes=256 << 20):
    """A window detector's per-level heatmaps of one image frame (published beside its ``Heatmaps``)."""

    level_scales: tuple[Annotated[float, Field(gt=0.0, le=8.0)], ...] = Field(min_length=1, max_length=MAX_LEVELS)
    maps: Annotated[list[CameraHeatmapLevels], Field(min_length=1, max_length=MAX_CAMERAS)]

    def _check_entry(self, entry: CameraHeatmapLevels) -> None:
        classes, levels = entry.scores.shape[:2]
        if (classes, levels) != (len(self.classes), len(self.level_scales)):
            raise ValueError(f"camera {entry.camera}: heatmaps of {classes} classes x {levels} levels for "
                             f"{len(self.classes)} classes x {len(self.level_scales)} level scales")


class Heatlines(Frame, schema="semloc.Heatlines", version=1, max_bytes=16 << 20):
    """Per-class detector scores over bearing in the body frame (thesis §4.4.2, §4.7.2)."""

    classes: tuple[ClassName, ...] = Field(min_length=1, max_length=MAX_CLASSES)
    scores: Array(("float32", "float16", "uint8"), ndim=2, finite=True, max_elements=MAX_CLASSES * MAX_BINS,
                  description=SCORES)
    scale: Scale = 1.0
    observed: Array("bool", ndim=1, max_elements=MAX_BINS)
    hard: bool = False

    @field_validator("classes")
    @classmethod
    def _distinct_classes(cls, names):
        return _distinct(names)

    @model_validator(mode="after")
    def _consistent(self):
        classes, bins = self.scores.shape
        if classes != len(self.classes):
            raise ValueError(f"{classes} heatlines for {len(self.classes)} classes")
        if not 4 <= bins <= MAX_BINS:
            raise ValueError(f"heatlines need 4..{MAX_BINS} bins, got {bins}")
        if self.observed.shape != (bins,):
            raise ValueError(f"observed must have {bins} entries, got shape {self.observed.shape}")
        check_scores(self.scores, self.scale)
        return self

    def values(self) -> np.ndarray:
        """Scores as float32 (classes, bins)."""
        return self.scores.astype(np.float32) * np.float32(self.scale)
