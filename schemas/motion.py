"""Motion frames: ``Odometry`` (v, omega over dt), ``Pose2D`` (x, y, theta) and ``Pose3D`` (position +
quaternion xyzw), each stamped with an optional covariance.

Conventions (docs/conventions.md): world z up; body x forward, y left; theta counter-clockwise from world x;
quaternions (x, y, z, w). ``header.frame_id`` names the reference frame (e.g. ``"world"``), ``child_frame_id`` the
frame whose pose is given (e.g. ``"body"``, ``"cam0"``).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, field_validator

from schemas.base import Array, Frame
from schemas.limits import (MAX_ANGLE, MAX_COORDINATE, MAX_ODOMETRY_DT, MAX_SPEED, MAX_TURN_RATE, MAX_VARIANCE,
                            PSD_TOLERANCE)

Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False)]
Angle = Annotated[float, Field(ge=-MAX_ANGLE, le=MAX_ANGLE, allow_inf_nan=False)]
Speed = Annotated[float, Field(ge=-MAX_SPEED, le=MAX_SPEED, allow_inf_nan=False)]
TurnRate = Annotated[float, Field(ge=-MAX_TURN_RATE, le=MAX_TURN_RATE, allow_inf_nan=False)]
_FRAME_NAME = Annotated[str, Field(max_length=128)]


def Covariance(size: int):
    """A size x size covariance: finite entries of magnitude <= MAX_VARIANCE (symmetry checked by the model)."""
    return Array("float64", shape=(size, size), finite=True, bounds=(-MAX_VARIANCE, MAX_VARIANCE))


def check_covariance(value: np.ndarray | None) -> np.ndarray | None:
    """A covariance (or a stack of them, (..., n, n)) as it came (None as None), or ValueError when one is not
    symmetric or not positive semi-definite: an eigenvalue below -PSD_TOLERANCE times its largest entry (float
    rounding of a sum of outer products) is a negative variance along some axis."""
    if value is None:
        return None
    if not np.allclose(value, np.swapaxes(value, -1, -2), rtol=1e-6, atol=1e-9):
        raise ValueError("covariance must be symmetric")
    if np.any(np.diagonal(value, axis1=-2, axis2=-1) < 0):
        raise ValueError("covariance diagonal must be non-negative")
    if value.size:
        lowest = np.linalg.eigvalsh(0.5 * (value + np.swapaxes(value, -1, -2)))[..., 0]
        if np.any(lowest < -PSD_TOLERANCE * np.abs(value).max(axis=(-2, -1))):
            raise ValueError("covariance must be positive semi-definite")
    return value


class Odometry(Frame, schema="semloc.Odometry", version=1, max_bytes=64 << 10):
    """Planar motion of the body over the ``dt`` seconds ending at ``header.stamp_ns``, as a constant twist:
    forward speed ``v`` (m/s, body x), lateral speed ``v_lateral`` (m/s, body y = left; 0 for a wheeled robot,
    not for a hand-held camera) and turn rate ``omega`` (rad/s, counter-clockwise). ``covariance`` is 3x3 over
    (v, v_lateral, omega). Ranges (schemas.limits): speeds within +-MAX_SPEED, omega within +-MAX_TURN_RATE, dt in
    (0, MAX_ODOMETRY_DT]; a consumer holds tighter ones (the localizer's max_speed, max_turn_rate, max_gap_s)."""

    v: Speed
    v_lateral: Speed = 0.0
    omega: TurnRate
    dt: Annotated[float, Field(gt=0.0, le=MAX_ODOMETRY_DT)]
    covariance: Covariance(3) | None = None

    @field_validator("covariance")
    @classmethod
    def _covariance(cls, value):
        return check_covariance(value)


class Pose2D(Frame, schema="semloc.Pose2D", version=1, max_bytes=64 << 10):
    """Planar pose (x, y, theta) of ``child_frame_id`` in ``header.frame_id``; covariance 3x3 over (x, y, theta).
    x, y within +-MAX_COORDINATE, theta within +-MAX_ANGLE."""

    x: Coordinate
    y: Coordinate
    theta: Angle
    child_frame_id: _FRAME_NAME = "body"
    covariance: Covariance(3) | None = None

    @field_validator("covariance")
    @classmethod
    def _covariance(cls, value):
        return check_covariance(value)


class Pose3D(Frame, schema="semloc.Pose3D", version=1, max_bytes=64 << 10):
    """Pose of ``child_frame_id`` in ``header.frame_id``: ``position`` (3,) metres, unit ``orientation`` (4,)
    quaternion (x, y, z, w); covariance 6x6 over (x, y, z, rotation vector x, y, z). Position within
    +-MAX_COORDINATE."""

    position: Array("float64", shape=(3,), finite=True, bounds=(-MAX_COORDINATE, MAX_COORDINATE))
    orientation: Array("float64", shape=(4,), finite=True)
    child_frame_id: _FRAME_NAME = "body"
    covariance: Covariance(6) | None = None

    @field_validator("covariance")
    @classmethod
    def _covariance(cls, value):
        return check_covariance(value)

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q):
        if abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
            raise ValueError(f"orientation must be a unit quaternion, norm is {np.linalg.norm(q)}")
        return q

    def matrix(self) -> np.ndarray:
        """The 4x4 transform T_frame_child."""
        x, y, z, w = (float(c) for c in self.orientation)
        T = np.eye(4)
        T[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        T[:3, 3] = self.position
        return T

    @classmethod
    def from_matrix(cls, header, T: np.ndarray, *, child_frame_id: str = "body", covariance=None) -> "Pose3D":
        """Build from a 4x4 rigid transform (quaternion by Shepperd's method, w >= 0)."""
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"expected a 4x4 transform, got {T.shape}")
        R = T[:3, :3]
        trace = np.trace(R)
        if trace > 0:
            s = 2.0 * np.sqrt(trace + 1.0)
            q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
        else:
            i = int(np.argmax(np.diag(R)))
            j, k = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
            q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
            q[i] = 0.25 * s
            q[j] = (R[j, i] + R[i, j]) / s
            q[k] = (R[k, i] + R[i, k]) / s
        q = np.asarray(q)
        q = q / np.linalg.norm(q)
        if q[3] < 0:
            q = -q
        return cls(header=header, position=T[:3, 3].copy(), orientation=q, child_frame_id=child_frame_id,
                   covariance=covariance)
