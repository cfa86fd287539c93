"""Which camera frames loop closure processes: key-frames chosen by motion and appearance change.

SIFT and the DP cost far more than a camera frame's interval at 15-30 fps, and consecutive frames of a slow camera
are nearly the same place. A frame becomes a key-frame when, since the last key-frame, the body moved
``min_distance`` metres or turned ``min_turn`` radians (the gate AMCL puts on its filter updates: ``update_min_d``
0.2 m, ``update_min_a`` pi/6), or the image changed by ``min_change`` (1 - the normalised cross-correlation of
small blurred grey thumbnails, :func:`appearance_change`; what catches motion without odometry, and a changed
scene); never sooner than ``min_interval_s`` after the last one, which bounds the key-frame rate (and so the
per-frame cost) whatever the camera's rate. The first frame is always a key-frame.

Pure functions on arrays: the caller keeps the last key-frame's thumbnail, stamp and the odometry increment
accumulated since (``semloc_core.localization.motion``: ``OdometryBuffer``, ``compose``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from semloc_core.geometry import wrap_angle
from semloc_core.localization.motion import Odometry

THUMBNAIL_SIZE = (32, 24)  # (width, height): the layout of a scene, not its texture
REASONS = ("first", "distance", "turn", "appearance")
MIN_TURN_DEG = 30.0  # AMCL's update_min_a, pi/6


@dataclass(frozen=True)
class KeyframeParams:
    """The key-frame gates (any one opens it, after ``min_interval_s``); ``None`` switches a gate off."""

    min_distance: float | None = 0.2
    min_turn: float | None = math.radians(MIN_TURN_DEG)
    min_change: float | None = 0.4
    min_interval_s: float = 0.0

    def __post_init__(self):
        for name in ("min_distance", "min_turn", "min_change"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive (or None: gate off), got {value}")
        if not (math.isfinite(self.min_interval_s) and self.min_interval_s >= 0):
            raise ValueError(f"min_interval_s must be >= 0, got {self.min_interval_s}")


_GATES = KeyframeParams()


class KeyframeSettings(BaseModel):
    """The gates as settings (the loop-closure worker's ``keyframes``, the evaluation's ``keyframes``): degrees for
    the turn; a null gate is off."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="process key-frames only (false: every image)")
    min_distance: float | None = Field(_GATES.min_distance, gt=0, description="metres moved since the last "
                                       "key-frame (odometry; AMCL's update_min_d)")
    min_turn_deg: float | None = Field(MIN_TURN_DEG, gt=0, description="degrees turned since the "
                                       "last key-frame (odometry; AMCL's update_min_a)")
    min_change: float | None = Field(_GATES.min_change, gt=0, description="image change since the last key-frame "
                                     "(1 - NCC of 32x24 thumbnails)")
    min_interval_s: float = Field(_GATES.min_interval_s, ge=0, description="at most one key-frame per this long")

    def params(self) -> KeyframeParams:
        return KeyframeParams(self.min_distance, None if self.min_turn_deg is None else math.radians(self.min_turn_deg),
                              self.min_change, self.min_interval_s)


def thumbnail(image: np.ndarray) -> np.ndarray:
    """A (24, 32) float32 grey thumbnail of ``image`` (H x W grey or H x W x 3 BGR), zero mean and unit norm (a flat
    image gives zeros): what :func:`appearance_change` compares."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.shape[0] < 2 or image.shape[1] < 2:
        raise ValueError(f"image must be H x W or H x W x 3 with H, W >= 2, got shape {image.shape}")
    small = cv2.resize(image.astype(np.float32), THUMBNAIL_SIZE, interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (3, 3), 0)
    small -= small.mean()
    norm = float(np.linalg.norm(small))
    return small / norm if norm > 1e-6 else np.zeros_like(small)


def appearance_change(a: np.ndarray, b: np.ndarray) -> float:
    """1 - normalised cross-correlation of two thumbnails: 0 for the same view, ~1 for unrelated ones, up to 2."""
    if a.shape != b.shape:
        raise ValueError(f"thumbnails differ in shape: {a.shape} vs {b.shape}")
    return float(1.0 - np.dot(a.ravel(), b.ravel()))


def keyframe_reason(params: KeyframeParams, since_s: float | None, motion: Odometry | None,
                    change: float | None) -> str | None:
    """Why a frame is a key-frame (one of :data:`REASONS`), or None when it is not.

    ``since_s``: seconds since the last key-frame (None: there was none yet); ``motion``: the odometry increment
    since the last key-frame (None: no odometry); ``change``: :func:`appearance_change` against the last
    key-frame's thumbnail (None: not computed)."""
    if since_s is None:
        return "first"
    if since_s < params.min_interval_s:
        return None
    if motion is not None:
        if params.min_distance is not None and math.hypot(motion.dx, motion.dy) >= params.min_distance:
            return "distance"
        if params.min_turn is not None and abs(float(wrap_angle(motion.dtheta))) >= params.min_turn:
            return "turn"
    if change is not None and params.min_change is not None and change >= params.min_change:
        return "appearance"
    return None


def select_keyframes(stamps_s: np.ndarray, poses: np.ndarray | None, thumbnails, params: KeyframeParams) -> np.ndarray:
    """Indices of the key-frames of a whole sequence, in order: ``poses`` (n, 3) of the body (x, y, theta) stand
    for the odometry (None: appearance only); ``thumbnails`` yields each frame's :func:`thumbnail` (or None when the
    appearance gate is off). The same rule as a live worker applies frame by frame."""
    stamps_s = np.asarray(stamps_s, float)
    if poses is not None:
        poses = np.asarray(poses, float)
        if poses.shape != (len(stamps_s), 3):
            raise ValueError(f"poses must be ({len(stamps_s)}, 3), got {poses.shape}")
    kept: list[int] = []
    last_thumb = None
    for index, thumb in enumerate(thumbnails):
        if index >= len(stamps_s):
            raise ValueError("more thumbnails than stamps")
        since = None if not kept else stamps_s[index] - stamps_s[kept[-1]]
        motion = None
        if poses is not None and kept:
            motion = Odometry.between(poses[kept[-1]], poses[index], float(since))
        change = None if thumb is None or last_thumb is None else appearance_change(thumb, last_thumb)
        if keyframe_reason(params, since, motion, change) is not None:
            kept.append(index)
            last_thumb = thumb
    return np.asarray(kept, np.int64)
