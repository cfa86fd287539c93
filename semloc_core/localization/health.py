"""Is the localizer still where it says it is? A monitor of the particle filter's estimate (issue "lost is noticed";
beyond the thesis, in the spirit of Thrun et al.'s augmented MCL, *Probabilistic Robotics* §8.3.5).

``HealthMonitor.update(...)`` takes, after each correction, the filter's ``PoseEstimate``, the estimate's
log-likelihood on this observation against the best of ``probes`` poses aligned with its detections
(``estimate_margin``), and optionally the pose another perception model estimates on the same frames and the poses
of a place just recognised; it returns a ``LocalizationState``:

* ``localized`` - the filter has converged, its hypothesis is tight and heavy, and the observations fit the estimate
  as well as they usually do;
* ``uncertain`` - the hypothesis is wide, the recent fit is below what this track has taught the monitor to
  expect, or the other model / a recognised place puts the robot elsewhere;
* ``lost`` - not converged since the last initialisation (initialising), the filter's recovery is running
  (``recovery_ratio`` below its ``lost_ratio``), other hypotheses hold more than ``1 - min_cluster_weight`` of the
  weight (the filter is searching), the recent fit is far below the expected one, or uncertain for ``lost_after``
  frames in a row.

The expected fit is learned, not set: ``margin`` = ℓ(estimate) − max(ℓ(estimate), ℓ(probes)) (≤ 0, nats), whose mean
and variance over the frames judged ``localized`` are kept (the track's mean, step 1/n down to ``slow_rate``); the
median of the last ``window`` frames' margins is compared with it in units of its standard error, a one-sided z test:
the recent frames fit worse than this track's frames did. Hysteresis: a worse verdict applies at once (the next frame is
already on the wrong pose), a better one only after ``recover_frames`` frames in a row - the frames a converged
estimate must stay within the threshold to count as converged in the evaluation.

The monitor never changes the filter: its probes come from its own random generator.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from enum import Enum

import numpy as np
from pydantic import Field

from semloc_core.localization.filter import PoseEstimate, Status
from semloc_core.settings import settings


class LocalizationState(str, Enum):
    LOCALIZED = "localized"
    UNCERTAIN = "uncertain"
    LOST = "lost"


@settings
class HealthConfig:
    """The monitor's parameters. Spread thresholds default to the filter's ``converged_*`` (None here)."""

    probes: int = Field(300, ge=1, description="poses aligned with the current detections weighed as the "
                        "reference of the estimate's fit")
    window: int = Field(5, ge=1, description="frames whose median margin is the short-term fit (a median: one "
                        "frame that fits badly - an occlusion - does not count, nor one good frame after many bad)")
    slow_rate: float = Field(0.01, gt=0, le=1, description="the learned average is the localized track's mean "
                             "(step 1/n) until 1/n falls to this rate")
    learn_frames: int = Field(10, ge=2, description="localized frames learned before the fit test applies")
    uncertain_z: float = Field(3.0, gt=0, description="short-term fit this many standard errors below the learned "
                               "mean: uncertain")
    lost_z: float = Field(6.0, gt=0, description="... this many: lost")
    min_std: float = Field(1.0, gt=0, description="floor of the learned margin's standard deviation (nats): a "
                           "track whose estimate is nearly always the best pose would otherwise call a frame a few "
                           "tenths of a nat worse lost")
    max_xy_std: float | None = Field(None, gt=0, description="hypothesis wider than this (m): uncertain (default: "
                                     "the filter's converged_xy_std)")
    max_theta_std: float | None = Field(None, gt=0, description="... or turned over more than this (rad; default "
                                        "the filter's converged_theta_std)")
    min_cluster_weight: float | None = Field(None, gt=0, le=1, description="heaviest hypothesis holding less: "
                                             "lost (default: the filter's converged_cluster_weight)")
    disagreement: float = Field(3.0, gt=0, description="another model's or a recognised place's pose this many "
                                "standard deviations (of the estimate's covariance plus place_std) away: uncertain")
    place_std: float = Field(0.5, gt=0, description="how far (m) from its recorded pose a recognised place may be "
                             "seen again (one standard deviation)")
    lost_after: int = Field(30, ge=1, description="uncertain this many frames in a row: lost")
    recover_frames: int = Field(5, ge=1, description="frames in a row a better verdict must hold to apply")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Verdict:
    """One frame's judgement: the state after hysteresis, the frame's own verdict and why."""

    state: LocalizationState
    raw: LocalizationState
    reason: str
    margin: float | None  # nats, this frame
    fit_z: float | None  # standard errors the recent margins' median is below the learned mean


def estimate_margin(perception, heatlines, pose, free_space, rng: np.random.Generator, probes: int,
                    view=None) -> float | None:
    """ℓ(pose) − max(ℓ(pose), ℓ(probe)) over ``probes`` poses aligned with the heatlines' detections in the free
    space (≤ 0 nats: how much better a pose elsewhere explains this observation). None when the observation carries
    no evidence or has no detection to align a probe with."""
    sampler = getattr(perception, "sample_poses", None)
    if sampler is None or heatlines is None:
        return None
    candidates = sampler(heatlines, probes, free_space, rng)
    if candidates.shape[0] == 0:
        return None
    candidates = candidates[free_space.contains(candidates[:, :2])]
    states = np.vstack([np.asarray(pose, dtype=np.float64).reshape(1, 3), candidates])
    weighing = perception.weigh(states, heatlines) if view is None else perception.weigh(states, heatlines, view)
    if not weighing.informative:
        return None
    log_likelihood = np.asarray(weighing.log_likelihood, dtype=np.float64)
    if not np.isfinite(log_likelihood[0]):
        return None
    best = float(np.max(log_likelihood[np.isfinite(log_likelihood)]))
    return float(log_likelihood[0] - best)


def pose_distance(estimate: PoseEstimate, other, extra_std: float = 0.0) -> float:
    """Mahalanobis distance (planar position) of ``other`` (x, y[, θ]) from the estimate, its covariance widened
    by ``extra_std`` (m) on each axis."""
    covariance = np.asarray(estimate.covariance, dtype=np.float64)[:2, :2] + extra_std ** 2 * np.eye(2)
    delta = np.asarray(other, dtype=np.float64)[:2] - np.asarray(estimate.pose, dtype=np.float64)[:2]
    try:
        return float(math.sqrt(max(float(delta @ np.linalg.solve(covariance, delta)), 0.0)))
    except np.linalg.LinAlgError:
        return math.inf


class HealthMonitor:
    """See the module docstring. ``converged_*``: the filter's thresholds, used where the config leaves them None."""

    def __init__(self, config: HealthConfig | None = None, converged_xy_std: float = 0.5,
                 converged_theta_std: float = math.radians(20.0), converged_cluster_weight: float = 0.9):
        self.config = config or HealthConfig()
        c = self.config
        self.max_xy_std = c.max_xy_std or converged_xy_std
        self.max_theta_std = c.max_theta_std or converged_theta_std
        self.min_cluster_weight = c.min_cluster_weight or converged_cluster_weight
        self.reset()

    @classmethod
    def for_filter(cls, filter_config, config: HealthConfig | None = None) -> "HealthMonitor":
        return cls(config, filter_config.converged_xy_std, filter_config.converged_theta_std,
                   filter_config.converged_cluster_weight)

    def reset(self) -> None:
        """Forget the state (a new initialisation); what was learned about the fit is kept: same sensor, same map."""
        self.state = LocalizationState.LOST
        self.pending: LocalizationState | None = None
        self.pending_count = 0
        self.uncertain_count = 0
        self.recent: deque = deque(maxlen=self.config.window)  # the last frames' margins
        if not hasattr(self, "learned"):
            self.learned = 0
            self.mean = 0.0
            self.variance = 0.0
        self.last = Verdict(self.state, self.state, "initialising", None, None)

    # ------------------------------------------------------------------ one frame
    def update(self, estimate: PoseEstimate, margin: float | None, other_pose=None, place_poses=None,
               lost_ratio: float = 0.5) -> Verdict:
        """The state after one correction (see the module docstring). ``other_pose``: another model's estimate of
        the same frame; ``place_poses`` (K, 3): recorded poses of a place recognised at this frame."""
        c = self.config
        if margin is not None and math.isfinite(margin):
            self.recent.append(float(margin))
        fit_z = self._fit_z()
        raw, reason = self._verdict(estimate, fit_z, other_pose, place_poses, lost_ratio)
        if raw is LocalizationState.UNCERTAIN:
            self.uncertain_count += 1
            if self.uncertain_count >= c.lost_after:
                raw, reason = LocalizationState.LOST, f"uncertain for {self.uncertain_count} frames"
        elif raw is LocalizationState.LOCALIZED:
            self.uncertain_count = 0
        self._apply(raw)
        if self.state is LocalizationState.LOCALIZED and margin is not None and math.isfinite(margin):
            self._learn(margin)
        self.last = Verdict(self.state, raw, reason, margin, fit_z)
        return self.last

    def _verdict(self, estimate, fit_z, other_pose, place_poses, lost_ratio) -> tuple[LocalizationState, str]:
        c = self.config
        if estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING):
            return LocalizationState.LOST, "initialising"
        if estimate.recovery_ratio < lost_ratio:
            return LocalizationState.LOST, f"recovery running (fit ratio {estimate.recovery_ratio:.2f})"
        if fit_z is not None and fit_z >= c.lost_z:
            return LocalizationState.LOST, f"observations fit {fit_z:.1f} standard errors below the usual"
        covariance = np.asarray(estimate.covariance, dtype=np.float64)
        xy_std = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:2, :2]).max()), 0.0))
        theta_std = math.sqrt(max(float(covariance[2, 2]), 0.0))
        if estimate.cluster_weight < self.min_cluster_weight:  # hypotheses compete: the filter is searching
            return LocalizationState.LOST, f"the hypothesis holds {estimate.cluster_weight:.2f} of the weight"
        if xy_std > self.max_xy_std or theta_std > self.max_theta_std:
            return LocalizationState.UNCERTAIN, f"spread {xy_std:.3f} m, {math.degrees(theta_std):.1f} deg"
        if fit_z is not None and fit_z >= c.uncertain_z:
            return LocalizationState.UNCERTAIN, f"observations fit {fit_z:.1f} standard errors below the usual"
        if other_pose is not None and pose_distance(estimate, other_pose) > c.disagreement:
            return LocalizationState.UNCERTAIN, "the other perception model disagrees"
        if place_poses is not None and len(place_poses):
            nearest = min(pose_distance(estimate, p, c.place_std) for p in np.asarray(place_poses).reshape(-1, 3))
            if nearest > c.disagreement:
                return LocalizationState.UNCERTAIN, "a recognised place puts the robot elsewhere"
        return LocalizationState.LOCALIZED, "converged and fitting"

    def _apply(self, raw: LocalizationState) -> None:
        """Hysteresis: worse at once, better after ``recover_frames`` frames in a row."""
        order = {LocalizationState.LOCALIZED: 0, LocalizationState.UNCERTAIN: 1, LocalizationState.LOST: 2}
        if order[raw] >= order[self.state]:
            self.state, self.pending, self.pending_count = raw, None, 0
            return
        if self.pending is None or order[raw] != order[self.pending]:
            self.pending, self.pending_count = raw, 0
        self.pending_count += 1
        if self.pending_count >= self.config.recover_frames:
            self.state, self.pending, self.pending_count = raw, None, 0

    def _fit_z(self) -> float | None:
        c = self.config
        if not self.recent or self.learned < c.learn_frames:
            return None
        std = max(math.sqrt(self.variance), c.min_std)
        # the standard error of a median of n normal draws: sqrt(pi / 2) sigma / sqrt(n)
        return (self.mean - float(np.median(self.recent))) / (math.sqrt(math.pi / 2) * std / math.sqrt(len(self.recent)))

    def _learn(self, margin: float) -> None:
        """Running mean and variance of the margin over localized frames (step 1/n, at least ``slow_rate``); once
        learned, a margin is winsorised at ``uncertain_z`` standard deviations below the mean, so that an outlier
        frame the window's median forgives does not widen what counts as usual."""
        c = self.config
        if self.learned >= c.learn_frames:
            margin = max(margin, self.mean - c.uncertain_z * max(math.sqrt(self.variance), c.min_std))
        self.learned += 1
        rate = max(1.0 / self.learned, self.config.slow_rate)
        delta = margin - self.mean
        self.mean += rate * delta
        self.variance = (1.0 - rate) * (self.variance + rate * delta * delta)

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict:
        return {"state": self.state.value, "pending": None if self.pending is None else self.pending.value,
                "pending_count": self.pending_count, "uncertain_count": self.uncertain_count, "recent": list(self.recent),
                "learned": self.learned, "mean": self.mean, "variance": self.variance}

    def restore(self, snapshot: dict) -> None:
        state = LocalizationState(snapshot.get("state", "lost"))
        pending = snapshot.get("pending")
        values = {k: float(snapshot.get(k, 0.0)) for k in ("mean", "variance")}
        if not all(math.isfinite(v) for v in values.values()) or values["variance"] < 0:
            raise ValueError("health snapshot: mean and variance must be finite, the variance >= 0")
        recent = [float(v) for v in snapshot.get("recent", [])]
        if not all(math.isfinite(v) for v in recent):
            raise ValueError("health snapshot: the recent margins must be finite")
        self.state = state
        self.pending = None if pending is None else LocalizationState(pending)
        self.pending_count = int(snapshot.get("pending_count", 0))
        self.uncertain_count = int(snapshot.get("uncertain_count", 0))
        self.recent = deque(recent, maxlen=self.config.window)
        self.learned = int(snapshot.get("learned", 0))
        self.mean, self.variance = values["mean"], values["variance"]
        self.last = Verdict(self.state, self.state, "restored", None, None)
