"""Matching heatmaps to poses by capture time: a bounded, time-ordered pose buffer with interpolation.

Heatmaps and poses come from different producers (detector, odometry, ground truth, localizer) and need not
share stamps. A heatmap stamped ``t`` takes the pose stamped exactly ``t`` if there is one, else the pose
interpolated between the poses just before and after ``t`` (position linearly, rotation by quaternion slerp) when
they are at most ``tolerance`` apart; it must wait while no pose after ``t`` has arrived, and is unmatchable once
one has but the gap is too wide (or ``t`` is older than the buffer).
"""

from __future__ import annotations

import bisect
from enum import Enum

import numpy as np

from semloc_core.geometry import quaternion_to_rotation, rotation_to_quaternion


class Match(str, Enum):
    FOUND = "found"
    WAIT = "wait"  # no pose at or after the stamp yet
    MISSING = "missing"  # never matchable: gap too wide, or older than the buffer


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Rigid transform ``alpha`` of the way from T0 to T1 (linear translation, slerp rotation)."""
    q0 = rotation_to_quaternion(T0[:3, :3])
    q1 = rotation_to_quaternion(T1[:3, :3])
    dot = float(np.dot(q0, q1))
    if dot < 0:  # the shorter way round
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
    else:
        angle = np.arccos(np.clip(dot, -1.0, 1.0))
        q = (np.sin((1 - alpha) * angle) * q0 + np.sin(alpha * angle) * q1) / np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q / np.linalg.norm(q))
    T[:3, 3] = (1 - alpha) * T0[:3, 3] + alpha * T1[:3, 3]
    return T


class PoseBuffer:
    """Poses by integer stamp (ns), oldest dropped beyond ``capacity``."""

    def __init__(self, capacity: int = 4096, tolerance_ns: int = 50_000_000):
        if capacity < 2 or tolerance_ns < 0:
            raise ValueError("capacity must be >= 2 and tolerance_ns >= 0")
        self.capacity = int(capacity)
        self.tolerance_ns = int(tolerance_ns)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, T: np.ndarray) -> None:
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("a pose must be a finite 4x4 transform")
        index = bisect.bisect_left(self._stamps, stamp_ns)
        if index < len(self._stamps) and self._stamps[index] == stamp_ns:
            self._poses[index] = T  # a re-sent pose replaces the old one
            return
        self._stamps.insert(index, int(stamp_ns))
        self._poses.insert(index, T)
        if len(self._stamps) > self.capacity:
            del self._stamps[0], self._poses[0]

    def snapshot(self) -> dict[str, np.ndarray]:
        """The buffered poses: ``stamps`` (k,) ns and ``poses`` (k, 4, 4)."""
        return {"stamps": np.array(self._stamps, np.int64),
                "poses": np.array(self._poses, np.float64).reshape(-1, 4, 4)}

    def restore(self, snapshot: dict) -> None:
        stamps = np.asarray(snapshot["stamps"], np.int64).reshape(-1)
        poses = np.asarray(snapshot["poses"], np.float64)
        if poses.shape != (stamps.size, 4, 4) or not np.all(np.isfinite(poses)) or np.any(np.diff(stamps) <= 0):
            raise ValueError("pose buffer: increasing stamps, one finite 4x4 pose each")
        self._stamps = stamps[-self.capacity:].tolist()
        self._poses = list(poses[-self.capacity:])

    def lookup(self, stamp_ns: int) -> tuple[Match, np.ndarray | None]:
        stamps = self._stamps
        index = bisect.bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns:
            return Match.FOUND, self._poses[index]
        if index == len(stamps):
            return Match.WAIT, None
        if index == 0:
            return Match.MISSING, None
        before, after = stamps[index - 1], stamps[index]
        if after - before > self.tolerance_ns:
            # A single pose within tolerance on either side still serves (e.g. odometry at a slower rate).
            nearest = index - 1 if stamp_ns - before <= after - stamp_ns else index
            if abs(stamps[nearest] - stamp_ns) <= self.tolerance_ns // 2:
                return Match.FOUND, self._poses[nearest]
            return Match.MISSING, None
        alpha = (stamp_ns - before) / (after - before)
        return Match.FOUND, interpolate_pose(self._poses[index - 1], self._poses[index], alpha)
