"""Which camera frames loop closure processes: key-frames chosen by motion and appearance change.

SIFT and the DP cost far more than a camera frame's interval at 15-30 fps, and consecutive frames of a slow camera
are nearly the same place. A frame becomes a key-frame when, since the last key-frame, the body moved
``min_distance`` metres or turned ``min_turn`` radians (the gate AMCL puts on its filter updates: ``update_min_d``
0.2 m, ``update_min_a`` pi/6), or the image changed by ``min_change`` (1 - the normalised cross-correlation of
small blurred grey thumbnails, :func:`appearance_change`; what catches motion without odometry, and a changed
scene); never sooner than ``min_interval_s`` after the last one, which bounds the key-frame rate (and so the
per-frame cost) whatever the camera's rate. The first frame is always a key-frame, and so is the first after time
no odometry covers (a reboot, a link gap, a refused message) long enough to hide a motion gate's worth of motion at
the odometry's speed limits, once ``min_interval_s`` allows (``odometry_gap``): how far the body went then is
unknown, so the motion gates cannot say it stayed; the motion counts afresh from that key-frame.

Pure functions on arrays: the caller keeps the last key-frame's thumbnail, stamp and the odometry increment
accumulated since (``semloc_core.localization.motion``: ``OdometryBuffer``, ``compose``), and the time since that no
odometry covers.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from pydantic import Field

from semloc_core.geometry import wrap_angle
from semloc_core.settings import settings

THUMBNAIL_SIZE = (32, 24)  # (width, height): the layout of a scene, not its texture


@settings
class KeyframeParams:
    """The key-frame gates (any one opens it, after ``min_interval_s``); a null gate is off. ``enabled``: whether a
    worker gates its images at all (the loop-closure worker's ``keyframes``; the evaluation's, off by default)."""

    enabled: bool = Field(True, description="process key-frames only (false: every image)")
    min_distance: float | None = Field(0.2, gt=0, description="metres moved since the last key-frame (odometry; "
                                       "AMCL's update_min_d)")
    min_turn: float | None = Field(math.pi / 6, gt=0, description="radians turned since the last key-frame "
                                   "(odometry; AMCL's update_min_a)")
    min_change: float | None = Field(0.4, gt=0, allow_inf_nan=False, description="image change since the last "
                                     "key-frame (1 - NCC of 32x24 grey thumbnails)")
    min_interval_s: float = Field(0.0, ge=0, allow_inf_nan=False, description="at most one key-frame per this long")


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


def keyframe_reason(params: KeyframeParams, since_s: float | None, motion, change: float | None,
                    uncovered: tuple[float, float] | None = None) -> str | None:
    """Why a frame is a key-frame ("first", "odometry_gap", "distance", "turn" or "appearance"), or None when it is
    not.

    ``since_s``: seconds since the last key-frame (None: there was none yet); ``motion``: the odometry increment
    since the last key-frame, with ``dx``, ``dy`` (metres, body frame) and ``dtheta`` (radians), as
    ``semloc_core.localization.motion.Odometry`` (None: no odometry); ``change``: :func:`appearance_change` against the last
    key-frame's thumbnail (None: not computed); ``uncovered``: the most the body can have moved (metres, radians)
    in the time since the last key-frame that no odometry covers, which ``motion`` leaves out (the odometry's speed
    and turn-rate limits times that time; None: none)."""
    if since_s is None:
        return "first"
    if since_s < params.min_interval_s:
        return None
    if uncovered is not None and ((params.min_distance is not None and uncovered[0] >= params.min_distance)
                                  or (params.min_turn is not None and uncovered[1] >= params.min_turn)):
        return "odometry_gap"
    if motion is not None:
        if params.min_distance is not None and math.hypot(motion.dx, motion.dy) >= params.min_distance:
            return "distance"
        if params.min_turn is not None and abs(float(wrap_angle(motion.dtheta))) >= params.min_turn:
            return "turn"
    if change is not None and params.min_change is not None and change >= params.min_change:
        return "appearance"
    return None


class _Increment(NamedTuple):
    dx: float
    dy: float
    dtheta: float


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
        if poses is not None and kept:  # the pose reached, in the body frame of the last key-frame
            (x0, y0, t0), (x1, y1, t1) = poses[kept[-1]], poses[index]
            c, s = math.cos(t0), math.sin(t0)
            motion = _Increment(c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0), t1 - t0)
        change = None if thumb is None or last_thumb is None else appearance_change(thumb, last_thumb)
        if keyframe_reason(params, since, motion, change) is not None:
            kept.append(index)
            last_thumb = thumb
    return np.asarray(kept, np.int64)
