"""Localization frames: ``PoseEstimate``, the localizer's answer (thesis §4.4, §4.7; docs/localization.md).

The planar pose ``(x, y, theta)`` of ``child_frame_id`` (the body) in ``header.frame_id`` (the map's world frame),
theta counter-clockwise from world x; ``covariance`` 3x3 over (x, y, theta) of the reported hypothesis. ``status``:

* ``localizing`` - has not converged since the last (global) initialisation;
* ``converged`` - the heaviest hypothesis holds most of the weight, is tight, and explains the observations;
* ``lost`` - was converged, and no longer is or no longer explains what the robot sees (recovery is running).

``state`` is the localizer's judgement of its estimate (``semloc_core.localization.health``; None from a localizer
without it): ``localized``, ``uncertain`` (wide, split, fitting worse than usual, or contradicted by the other
perception model or a recognised place; a jump to another hypothesis, or a pose given by ``set-pose``, until
the next frames have weighed it) or ``lost`` (initialising, recovering, or uncertain for long): a
``localizing`` status, initialising, comes with state ``lost`` (another is refused, ``invalid``).

``PastPoses`` carries the poses a backward filter pass gave the frames before a localized stretch
(``semloc_core.localization.smoothing``; docs/hybrid-localization.md): frames named by their capture stamps, each
before the stretch's first estimate (``anchor_stamp_ns``), newest first.

The particle set travels as a summary: the weighted mean and covariance of all particles (``mean``,
``mean_covariance``), the number of hypotheses (``clusters``), the share of weight in the one reported
(``cluster_weight``), and optionally a weighted sample (``sample`` (K, 3), ``sample_weights`` (K,)) for display.
``converged_std`` and ``motion_std`` (optional) give consumers the filter's scale: its converged spread and the noise
of the odometry increment it predicted with (the loop-closure worker's places judge and carry tracks by them).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from schemas.base import Array, Frame
from schemas.limits import MAX_COORDINATE, MAX_VARIANCE
from schemas.motion import Angle, Coordinate, Covariance, check_covariance

MAX_SAMPLE = 100_000
MAX_PARTICLES = 100_000_000
MAX_PAST_POSES = 100_000  # poses one PastPoses carries (a pass goes back at most smoothing.max_frames)
_POSES = (-MAX_COORDINATE, MAX_COORDINATE)  # bounds of (x, y, theta) rows: theta is wrapped, within them too
LocalizationStatus = Literal["localizing", "converged", "lost"]
LocalizationState = Literal["localized", "uncertain", "lost"]


class PoseEstimate(Frame, schema="semloc.PoseEstimate", version=1, max_bytes=8 << 20):
    """The localizer's pose of the body in the map, its covariance, status and a summary of the particle set."""

    x: Coordinate
    y: Coordinate
    theta: Angle
    covariance: Covariance(3)
    child_frame_id: Annotated[str, Field(max_length=128)] = "body"
    status: LocalizationStatus
    state: LocalizationState | None = Field(None, description="the localizer's judgement of the estimate (None: "
                                            "a localizer without it)")
    particles: Annotated[int, Field(ge=1, le=MAX_PARTICLES)]
    effective_sample_size: Annotated[float, Field(ge=0.0, le=MAX_PARTICLES, allow_inf_nan=False)]
    clusters: Annotated[int, Field(ge=1, le=MAX_PARTICLES)] = 1
    cluster_weight: Annotated[float, Field(ge=0.0, le=1.0 + 1e-9)] = 1.0
    recovery_ratio: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 1.0
    injected: Annotated[int, Field(ge=0, le=MAX_PARTICLES)] = 0
    mean: Array("float64", shape=(3,), finite=True, bounds=_POSES)
    mean_covariance: Covariance(3)
    converged_std: Array("float64", shape=(2,), finite=True, bounds=(0.0, MAX_COORDINATE)) | None = Field(
        None, description="the filter's converged spread (position std m, heading std rad; each > 0): the scale "
        "the places judge a track by (None: a localizer without it)")
    motion_std: Array("float64", shape=(2,), finite=True, bounds=(0.0, MAX_COORDINATE)) | None = Field(
        None, description="the noise the motion model gave the odometry increment this estimate was predicted with "
        "(translation std per axis m, rotation std rad; None: no odometry, or a localizer without it)")
    sample: Array("float32", shape=(None, 3), finite=True, max_elements=3 * MAX_SAMPLE, bounds=_POSES) | None = None
    sample_weights: Array("float32", ndim=1, finite=True, max_elements=MAX_SAMPLE, bounds=(0.0, 1.0)) | None = None

    @field_validator("covariance", "mean_covariance")
    @classmethod
    def _covariance(cls, value):
        return check_covariance(value)

    @model_validator(mode="after")
    def _consistent(self):
        if self.status == "localizing" and self.state not in (None, "lost"):
            raise ValueError(f"state {self.state} while localizing: a filter still initialising is lost")
        if self.converged_std is not None and np.any(self.converged_std <= 0):
            raise ValueError("converged_std must be positive (the filter's convergence thresholds are)")
        if (self.sample is None) != (self.sample_weights is None):
            raise ValueError("sample and sample_weights come together")
        if self.sample is not None and self.sample.shape[0] != self.sample_weights.shape[0]:
            raise ValueError(f"{self.sample.shape[0]} sample poses for {self.sample_weights.shape[0]} weights")
        return self

    def pose(self) -> np.ndarray:
        return np.array([self.x, self.y, self.theta])

    def localized(self) -> bool:
        """Whether the estimate is one to place things by (a map node's position): ``state`` localized, or
        from a localizer without ``state``, ``status`` converged."""
        return self.state == "localized" if self.state is not None else self.status == "converged"


class PastPoses(Frame, schema="semloc.PastPoses", version=1, max_bytes=16 << 20):
    """Poses of earlier frames from a backward filter pass (``semloc_core.localization.smoothing``): ``stamps_ns``
    the frames' capture stamps (newest first, each before ``anchor_stamp_ns``, the first estimate of the localized
    stretch the pass started from), ``poses`` (N, 3) x y theta in ``header.frame_id``, ``covariances`` (N, 3, 3)."""

    anchor_stamp_ns: Annotated[int, Field(ge=0)]
    stamps_ns: Array("int64", ndim=1, max_elements=MAX_PAST_POSES, bounds=(0, 2 ** 63 - 1),
                     description="strictly decreasing, each before anchor_stamp_ns")
    poses: Array("float64", shape=(None, 3), finite=True, max_elements=3 * MAX_PAST_POSES, bounds=_POSES)
    covariances: Array("float64", shape=(None, 3, 3), finite=True, max_elements=9 * MAX_PAST_POSES,
                       bounds=(-MAX_VARIANCE, MAX_VARIANCE), description="each symmetric, diagonal >= 0")

    @model_validator(mode="after")
    def _consistent(self):
        n = self.stamps_ns.shape[0]
        if self.poses.shape[0] != n or self.covariances.shape[0] != n:
            raise ValueError(f"{n} stamps, {self.poses.shape[0]} poses and {self.covariances.shape[0]} "
                             "covariances: one each per frame")
        if n and (np.any(np.diff(self.stamps_ns) >= 0) or self.stamps_ns[0] >= self.anchor_stamp_ns):
            raise ValueError("stamps must be strictly decreasing and before anchor_stamp_ns")
        check_covariance(self.covariances)
        return self
