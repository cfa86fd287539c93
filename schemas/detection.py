"""Detection frames: ``Heatmaps`` (per-class score maps per member camera) and ``Heatlines`` (scores over bearing).

Conventions (docs/detection.md, docs/conventions.md):

* A heatmap is ``(classes, rows, cols)`` covering its camera image uniformly: cell ``(r, q)`` covers pixels
  ``u in [q W/cols, (q+1) W/cols)``, ``v in [r H/rows, (r+1) H/rows)`` of the ``image_width`` x ``image_height``
  image (``cv2.resize``'s convention). Scores are in [0, 1]; on the wire they may be quantised: the score is
  ``value * scale`` (``scale = 1/255`` for uint8, 1 for floats). ``T_body_cam`` repeats the image's per-frame
  attitude override, if it had one, so a consumer back-projects with the attitude the detector used.
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

from schemas.base import Array, Frame, Sub
from schemas.camera import MAX_CAMERAS, MAX_SIDE, RigidTransform, Side

MAX_CLASSES = 1024
MAX_BINS = 36_000
MAX_HEATMAP_ELEMENTS = 64 << 20
ClassName = Annotated[str, Field(min_length=1, max_length=128)]
Scale = Annotated[float, Field(gt=0.0, le=1e6)]


def _distinct(names):
    if len(set(names)) != len(names):
        raise ValueError(f"class names must be distinct, got {list(names)}")
    return names


class CameraHeatmaps(Sub):
    """The heatmaps of one member camera: ``scores`` (classes, rows, cols); score = value * ``scale``."""

    camera: Annotated[int, Field(ge=0, lt=MAX_CAMERAS)] = 0
    image_width: Side
    image_height: Side
    scores: Array(("uint8", "float16", "float32"), ndim=3, finite=True, max_elements=MAX_HEATMAP_ELEMENTS)
    scale: Scale = 1.0
    T_body_cam: RigidTransform | None = None

    @model_validator(mode="after")
    def _grid(self):
        _, rows, cols = self.scores.shape
        if not (1 <= rows <= MAX_SIDE and 1 <= cols <= MAX_SIDE):
            raise ValueError(f"heatmap grid {rows}x{cols} out of range")
        return self

    def values(self) -> np.ndarray:
        """Scores as float32 (classes, rows, cols)."""
        return self.scores.astype(np.float32) * np.float32(self.scale)


class Heatmaps(Frame, schema="semloc.Heatmaps", version=1, max_bytes=256 << 20):
    """Soft detections of one image frame: one heatmap per class and member camera (thesis §4.3, §4.6, §5.3)."""

    classes: tuple[ClassName, ...] = Field(min_length=1, max_length=MAX_CLASSES)
    detector: Annotated[str, Field(max_length=64)] = ""
    maps: Annotated[list[CameraHeatmaps], Field(min_length=1, max_length=MAX_CAMERAS)]

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
            if entry.scores.shape[0] != len(self.classes):
                raise ValueError(f"camera {entry.camera}: {entry.scores.shape[0]} heatmaps for "
                                 f"{len(self.classes)} classes")
        return self


class Heatlines(Frame, schema="semloc.Heatlines", version=1, max_bytes=16 << 20):
    """Per-class detector scores over bearing in the body frame (thesis §4.4.2, §4.7.2)."""

    classes: tuple[ClassName, ...] = Field(min_length=1, max_length=MAX_CLASSES)
    scores: Array(("float32", "float16", "uint8"), ndim=2, finite=True, max_elements=MAX_CLASSES * MAX_BINS)
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
        return self

    def values(self) -> np.ndarray:
        """Scores as float32 (classes, bins)."""
        return self.scores.astype(np.float32) * np.float32(self.scale)
