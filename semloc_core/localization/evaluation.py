"""Running a filter over a sequence and scoring it against ground truth (thesis §4.8.4, Fig. 4.14).

* ``run_filter`` steps a ``ParticleFilter`` through frames (heatlines, odometry, dt) and records a ``Trace``: the
  estimate, its covariance and status, the particle count and the time each step took.
* ``localization_metrics`` turns a trace and the ground truth into the figures the evaluation reports: position
  error per frame and its running RMSE ("RMSE over time"), time to converge (first frame after which the error
  stays under a threshold for ``hold`` frames), RMSE after convergence, heading error, and, for each teleport of
  the ground truth (kidnapping), the frames it took to recover.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from semloc_core.geometry import wrap_angle
from semloc_core.localization.filter import ParticleFilter, Status
from semloc_core.localization.health import HealthMonitor, LocalizationState, judge
from semloc_core.localization.motion import Odometry
from semloc_core.localization.smoothing import PastFrame


@dataclass
class Trace:
    """Per-frame record of a filter run."""

    poses: list = field(default_factory=list)  # (3,) estimate
    covariances: list = field(default_factory=list)  # (3, 3)
    statuses: list = field(default_factory=list)  # Status values (str)
    particles: list = field(default_factory=list)
    cluster_weights: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    states: list = field(default_factory=list)  # LocalizationState values (str), with a monitor
    margins: list = field(default_factory=list)  # the estimate's fit margin (nats; None: no evidence)
    reasons: list = field(default_factory=list)  # why the monitor judged each frame so
    rivals: list = field(default_factory=list)  # the best rival's evidence against the estimate (nats; None: none)
    second_rivals: list = field(default_factory=list)  # ... by the second perception model

    def arrays(self) -> dict:
        return {"poses": np.asarray(self.poses, dtype=float).reshape(-1, 3),
                "covariances": np.asarray(self.covariances, dtype=float).reshape(-1, 3, 3),
                "statuses": list(self.statuses), "particles": np.asarray(self.particles, dtype=np.int64),
                "cluster_weights": np.asarray(self.cluster_weights, dtype=float),
                "seconds": np.asarray(self.seconds, dtype=float), "states": list(self.states),
                "margins": list(self.margins), "reasons": list(self.reasons), "rivals": list(self.rivals),
                "second_rivals": list(self.second_rivals)}


def run_filter(particle_filter: ParticleFilter, frames: Iterable[tuple], monitor: HealthMonitor | None = None,
               monitor_rng: np.random.Generator | int | None = None, places=None, second_perception=None,
               smoother=None) -> Trace:
    """Step the (initialised) filter through ``frames`` of (heatlines or None, odometry or None, dt[, view]);
    with a ``monitor``, judge each estimate (``Trace.states``), its probes drawn from ``monitor_rng`` (the filter's
    course is the same with or without it). The step time excludes the monitor. ``places`` (with a monitor): called
    after each step as ``places.after_step(step, estimate, state, particle_filter, odometry)`` (the step's
    ``Odometry``, None: none), its ``opinion`` (recorded
    poses of a place just recognised) going to the monitor at the next step
    (``semloc_core.experiments.localization_places.RecognisedPlaces``). ``second_perception``: the other
    perception model, weighing the estimate and the probes for the monitor's ``second_rivals``. ``smoother`` (with
    ``places``; ``semloc_core.localization.smoothing.BackwardSmoother``): fed every step, its passes advanced a few
    steps a step and run to their end after the last, their poses going to ``places.fill_past``."""
    trace = Trace()
    rng = np.random.default_rng(monitor_rng)
    for step, frame in enumerate(frames):
        heatlines, odometry, dt = frame[:3]
        view = frame[3] if len(frame) > 3 else None
        start = time.perf_counter()
        estimate = particle_filter.step(heatlines, odometry, dt, view)
        trace.seconds.append(time.perf_counter() - start)
        if monitor is not None:
            moved = None if odometry is None else (odometry.dx, odometry.dy, odometry.dtheta)
            verdict = judge(monitor, particle_filter, estimate, heatlines, view, rng, moved,
                            None if places is None else places.opinion, second_perception)
            if places is not None:
                places.after_step(step, estimate, verdict.state, particle_filter, odometry)
            if smoother is not None:
                smoother.record(PastFrame(step, heatlines, view, moved, odometry.dt if odometry else 0.0),
                                verdict.state is LocalizationState.LOCALIZED,
                                estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING), particle_filter.snapshot)
                for anchor, _reason, poses in smoother.advance():
                    places.fill_past(anchor, poses)
            trace.states.append(verdict.state.value)
            trace.margins.append(verdict.margin)
            trace.reasons.append(verdict.reason)
            trace.rivals.append(verdict.rival)
            trace.second_rivals.append(verdict.second_rival)
        trace.poses.append(np.asarray(estimate.pose, dtype=float))
        trace.covariances.append(np.asarray(estimate.covariance, dtype=float))
        trace.statuses.append(estimate.status.value)
        trace.particles.append(estimate.n_particles)
        trace.cluster_weights.append(estimate.cluster_weight)
    if smoother is not None:
        for anchor, _reason, poses in smoother.finish():
            places.fill_past(anchor, poses)
    return trace


def first_settled(errors: np.ndarray, threshold: float, hold: int, start: int = 0) -> int | None:
    """First frame k >= start from which the error stays below ``threshold`` for ``hold`` frames (or to the end)."""
    below = np.asarray(errors) < threshold
    n = below.shape[0]
    for k in range(start, n):
        if below[k] and below[k:min(n, k + hold)].all():
            return k
    return None


def localization_metrics(estimates, ground_truth, converge_threshold: float, hold: int = 10,
                         teleports: Iterable[int] = (), recover_threshold: float | None = None) -> dict:
    """Figures of a run; ``estimates`` and ``ground_truth`` are (T, 3) planar poses (NaN rows = no estimate).

    ``time_to_converge`` and ``rmse_after_convergence`` use the first stretch before any teleport;
    ``recoveries`` lists, per teleport frame, how many frames it took to get back under ``recover_threshold``
    (default: ``converge_threshold``) for ``hold`` frames (None: never).
    """
    estimates = np.asarray(estimates, dtype=float)
    ground_truth = np.asarray(ground_truth, dtype=float)
    if estimates.shape != ground_truth.shape or estimates.ndim != 2 or estimates.shape[1] != 3:
        raise ValueError(f"estimates {estimates.shape} and ground truth {ground_truth.shape} must both be (T, 3)")
    errors = np.hypot(*(estimates[:, :2] - ground_truth[:, :2]).T)
    errors = np.where(np.isfinite(errors), errors, np.inf)
    heading_errors = np.abs(wrap_angle(estimates[:, 2] - ground_truth[:, 2]))
    frames = errors.shape[0]
    running = np.sqrt(np.cumsum(np.where(np.isfinite(errors), errors, 0.0) ** 2) / np.arange(1, frames + 1))
    teleports = sorted(int(t) for t in teleports)
    first_stretch = teleports[0] if teleports else frames
    converged = first_settled(errors[:first_stretch], converge_threshold, hold)
    after = errors[converged:first_stretch] if converged is not None else np.zeros(0)
    recover_threshold = converge_threshold if recover_threshold is None else recover_threshold
    recoveries = []
    for index, teleport in enumerate(teleports):
        end = teleports[index + 1] if index + 1 < len(teleports) else frames
        settled = first_settled(errors[:end], recover_threshold, hold, start=teleport)
        recoveries.append({"frame": teleport, "frames_to_recover": None if settled is None else settled - teleport})
    finite = np.isfinite(errors)
    return {
        "frames": frames,
        "converge_threshold_m": converge_threshold,
        "hold_frames": hold,
        "time_to_converge_frames": converged,
        "rmse_after_convergence_m": float(np.sqrt(np.mean(after ** 2))) if after.size else None,
        "median_error_after_convergence_m": float(np.median(after)) if after.size else None,
        "rmse_m": float(np.sqrt(np.mean(errors[finite] ** 2))) if finite.any() else None,
        "heading_rmse_after_convergence_deg": (float(np.degrees(np.sqrt(np.mean(
            heading_errors[converged:first_stretch] ** 2)))) if after.size else None),
        "recoveries": recoveries,
        "errors_m": [float(e) if np.isfinite(e) else None for e in errors],
        "running_rmse_m": running.tolist(),
        "heading_errors_deg": np.degrees(heading_errors).tolist(),
    }


def state_metrics(states, errors, far: float, near: float) -> dict:
    """How well the monitor's states (``localized`` / ``uncertain`` / ``lost`` per frame) tell where the estimate
    is: the share of frames flagged (not ``localized``) among those whose error exceeds ``far``, and among those
    whose error is under ``near`` (issue 34's acceptance: >= 0.9 and <= 0.05), and those frames' counts."""
    errors = np.asarray([np.inf if e is None else e for e in errors], dtype=float)
    flagged = np.asarray([s != "localized" for s in states], dtype=bool)
    if flagged.shape != errors.shape:
        raise ValueError(f"{flagged.shape[0]} states for {errors.shape[0]} errors")
    far_frames, near_frames = errors > far, errors < near
    return {"far_m": far, "near_m": near, "far_frames": int(far_frames.sum()), "near_frames": int(near_frames.sum()),
            "flagged_when_far": float(flagged[far_frames].mean()) if far_frames.any() else None,
            "flagged_when_near": float(flagged[near_frames].mean()) if near_frames.any() else None,
            "flagged_far_frames": int(flagged[far_frames].sum()),
            "flagged_near_frames": int(flagged[near_frames].sum()),
            "states": {state: int(sum(s == state for s in states)) for state in ("localized", "uncertain", "lost")}}


def carry_rigidly(hypotheses, start_pose, pose) -> np.ndarray:
    """Where each of ``hypotheses`` (N, 3), taken as the pose at ``start_pose``, is when the robot is at ``pose``:
    ``h ⊕ (start_pose⁻¹ ⊕ pose)``, the motion between the two applied in each hypothesis's own frame."""
    hypotheses = np.asarray(hypotheses, dtype=float)
    step = Odometry.between(start_pose, pose, 0.0)  # the motion in the start's body frame
    c, s = np.cos(hypotheses[:, 2]), np.sin(hypotheses[:, 2])
    return np.stack([hypotheses[:, 0] + c * step.dx - s * step.dy, hypotheses[:, 1] + s * step.dx + c * step.dy,
                     wrap_angle(hypotheses[:, 2] + step.dtheta)], axis=1)


def information_margins(perception, ground_truth, frames, hypotheses, far: float) -> dict:
    """How soon a sequence of observations singles out the true pose, with no filter in the way.

    Every hypothesis of ``hypotheses`` (N, 3) is a start pose carried along the ground truth's own relative motion
    (``carry_rigidly``) - a particle filter with perfect odometry and a particle at each hypothesis - and sums the
    perception model's log-likelihood of each frame's observation (``frames``: per step ``(heatlines, view)``,
    aligned with ``ground_truth`` (T, 3)). The truth itself is carried the same way from its first pose.

    Returns per step: ``share_above_single`` (the share of hypotheses farther than ``far`` metres from the truth
    whose log-likelihood of that frame alone exceeds the truth's), ``above_cumulative`` (how many of them exceed the
    truth's summed log-likelihood), ``margin`` (the truth's sum minus the best far one's), and ``singled_out``: the
    first step from which no far hypothesis exceeds the truth's sum (None: not by the end). No filter on these
    observations and this motion can settle on the truth before ``singled_out`` unless the far hypotheses were never
    sampled.
    """
    ground_truth = np.asarray(ground_truth, dtype=float)
    hypotheses = np.asarray(hypotheses, dtype=float)
    if ground_truth.ndim != 2 or ground_truth.shape[1] != 3 or len(ground_truth) != len(frames):
        raise ValueError(f"ground_truth must be (T, 3) with one row per frame ({len(frames)}), got "
                         f"{ground_truth.shape}")
    if hypotheses.ndim != 2 or hypotheses.shape[1] != 3 or len(hypotheses) == 0:
        raise ValueError(f"hypotheses must be (N, 3) with N >= 1, got {hypotheses.shape}")
    start = np.vstack([ground_truth[:1], hypotheses])
    total = np.zeros(len(start))
    share, above, margin = [], [], []
    for k, (heatlines, view) in enumerate(frames):
        states = carry_rigidly(start, ground_truth[0], ground_truth[k])
        log_likelihood = np.asarray(perception.weigh(states, heatlines, view).log_likelihood, dtype=float)
        total += log_likelihood
        is_far = np.hypot(states[1:, 0] - ground_truth[k, 0], states[1:, 1] - ground_truth[k, 1]) > far
        share.append(float(np.mean(log_likelihood[1:][is_far] > log_likelihood[0])) if is_far.any() else 0.0)
        above.append(int(np.sum(total[1:][is_far] > total[0])))
        margin.append(float(total[0] - total[1:][is_far].max()) if is_far.any() else float("inf"))
    above_array = np.asarray(above)
    still_above = np.flatnonzero(above_array > 0)
    singled_out = 0 if still_above.size == 0 else int(still_above[-1]) + 1
    return {"share_above_single": share, "above_cumulative": above, "margin": margin,
            "singled_out": singled_out if singled_out < len(above) else None}
