"""Is the localizer still where it says it is? A monitor of the particle filter's estimate (issue "lost is noticed";
beyond the thesis, in the spirit of Thrun et al.'s augmented MCL, *Probabilistic Robotics* §8.3.5).

``HealthMonitor.update(...)`` takes, after each correction, the filter's ``PoseEstimate`` and what
``estimate_margin`` weighed for it: the estimate against ``probes`` poses aligned with the frame's detections, and
its *rivals* (``Rivals``: such poses found at earlier frames, farther than three converged spreads from the estimate,
carried along the estimate's motion); optionally the pose another perception model estimates and the poses of a
place just recognised. It returns a ``LocalizationState``:

* ``localized`` - the filter has converged, its hypothesis is heavy and either tight or ruled in by the last frames
  (below), and no pose elsewhere explains the last ``rival_frames`` frames clearly better than the estimate;
* ``uncertain`` - the hypothesis is wider than the filter's converged spread while the last frames do not rule out
  every pose elsewhere, or so wide that it reaches poses elsewhere (three converged spreads); the second perception
  model finds a pose elsewhere that explains the last frames clearly better (``second_model``: the two models'
  agreement), or the other model's pose / a recognised place puts the robot elsewhere; or, given the odometry
  (``update(moved=...)``), a localized estimate jumped to another hypothesis (where no motion from the last one
  leads) fewer than ``rival_frames`` frames ago: its rivals start again and must weigh it first; the same for a pose
  given to the filter (``reset(given=True)``: an operator's ``set-pose``), from its first correction on;
* ``lost`` - not converged since the last initialisation (initialising), the filter's recovery is running
  (``recovery_ratio`` below its ``lost_ratio``), other hypotheses hold more than ``1 - min_cluster_weight`` of the
  weight (the filter is searching), a rival explains the last frames clearly better - its evidence against the
  estimate above log(c / (1 - c)), c = ``min_cluster_weight``, the odds the filter's own convergence test asks of
  the estimate - or uncertain for ``lost_after`` frames in a row.

No threshold is learned or set per scene: the rival test compares likelihoods summed over the same frames, on the
filter's own scale of odds. A *pose elsewhere* is one beyond three spreads of the hypothesis, at least three of the
filter's converged spreads: nearer, it lies in the hypothesis's own tail. The spread is not the error: a filter
tracking with larger steps or a flatter likelihood holds a wider hypothesis around a good estimate (the demo's
simulated table top: 0.06-0.23 m with errors under 0.15 m, the two uncorrelated), so a hypothesis wider than the
converged spread is only uncertain while the evidence of the last frames leaves a pose elsewhere within the
convergence odds of the estimate; once every pose elsewhere is that far behind (or dropped, more than ``prune`` nats
behind), the width is the filter's own imprecision, not a doubt about where the robot is.

A single frame says little - poses aligned with one frame's detections often explain that frame several nats better
than the true pose itself - so the evidence is summed over ``rival_frames`` frames along the motion, the runtime
form of the information bound (``evaluation.information_margins``). The margin ℓ(estimate) − max(ℓ(estimate),
ℓ(probes)) of each frame is reported, not tested. Hysteresis: a worse verdict applies at once (the next frame is
already on the wrong pose), a better one only after ``recover_frames`` frames in a row - the frames a converged
estimate must stay within the threshold to count as converged in the evaluation.

The monitor never changes the filter: its probes come from its own random generator.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import Enum

import numpy as np
from pydantic import Field

from semloc_core.geometry import wrap_angle
from semloc_core.localization.filter import PoseEstimate, Status, compose_motion
from semloc_core.settings import settings


GIVEN = "a given pose the observations have not weighed yet"


class LocalizationState(str, Enum):
    LOCALIZED = "localized"
    UNCERTAIN = "uncertain"
    LOST = "lost"


@settings
class HealthConfig:
    """The monitor's parameters. Spread thresholds default to the filter's ``converged_*`` (None here)."""

    probes: int = Field(300, ge=1, description="poses aligned with the current detections weighed as the "
                        "reference of the estimate's fit")
    max_xy_std: float | None = Field(None, gt=0, description="hypothesis wider than this (m) while the last frames "
                                     "do not rule out a pose elsewhere, or wider than three times this: uncertain "
                                     "(default: the filter's converged_xy_std)")
    max_theta_std: float | None = Field(None, gt=0, description="... or turned over more than this (rad; default "
                                        "the filter's converged_theta_std)")
    min_cluster_weight: float | None = Field(None, gt=0, le=1, description="heaviest hypothesis holding less: "
                                             "lost (default: the filter's converged_cluster_weight)")
    disagreement: float = Field(3.0, gt=0, description="another model's or a recognised place's pose this many "
                                "standard deviations (of the estimate's covariance plus place_std) away: uncertain")
    place_std: float | None = Field(None, gt=0, description="how far (m) from its recorded pose a recognised place "
                                    "may be seen again (one standard deviation; default: 5 x the filter's "
                                    "converged_xy_std, 0.5 m on a table top, 5 m in the hall)")
    rivals: int = Field(100, ge=0, description="poses elsewhere followed along the estimate's motion as its rivals "
                        "(0: none; see Rivals)")
    rival_frames: int = Field(10, ge=1, description="frames over which a rival's evidence against the estimate is "
                              "summed")
    second_model: bool = Field(False, description="the other perception model (A beside B, B beside A) weighs "
                               "the same estimate and probes against rivals of its own; its rival ahead: uncertain "
                               "(the two models' agreement)")
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
    rival: float | None = None  # the best rival's evidence against the estimate over the last rival_frames (nats),
    # of those beyond three spreads of the hypothesis
    second_rival: float | None = None  # ... by the second perception model


class Rivals:
    """Poses elsewhere that explained recent frames, carried along the estimate's own motion: the runtime form of
    the information bound (``evaluation.information_margins``). Each frame (``carry``, then ``observe``) every rival
    is moved by the estimate's motion since the last frame (h ⊕ (e⁻¹ ⊕ e')) and weighed, keeping the last ``frames``
    log-likelihood differences ℓ(rival) − ℓ(estimate); the best of the frame's probes farther than ``far_xy`` (or
    turned more than ``far_theta``) from the estimate join (``capacity`` / ``frames`` of them a frame, the followed
    rivals kept first, at most ``capacity`` in all). A rival more than ``prune`` nats behind, or come within
    ``far_xy`` of the estimate, is dropped. ``log_odds``: the best sum over the last ``frames`` frames,
    log p(z_{t-W+1..t} | rival) − log p(z_{t-W+1..t} | estimate) - the evidence of those frames for a pose elsewhere
    against the estimate."""

    def __init__(self, capacity: int = 100, frames: int = 10, far_xy: float = 0.3, far_theta: float = math.pi / 6,
                 prune: float = 10.0):
        self.capacity, self.frames, self.far_xy, self.far_theta, self.prune = capacity, frames, far_xy, far_theta, prune
        self.reset()

    def reset(self) -> None:
        self.poses = np.zeros((0, 3))
        self.differences = np.zeros((0, self.frames))  # NaN: not seen then (the rival is younger)
        self.last_pose: np.ndarray | None = None
        self.observed = 0  # frames weighed since the reset

    def carry(self, pose: np.ndarray) -> None:
        """Move the rivals by the estimate's motion from the last frame's ``pose`` to this one."""
        if self.last_pose is None or not self.poses.shape[0]:
            return
        x0, y0, t0 = self.last_pose
        c0, s0 = math.cos(t0), math.sin(t0)
        dx, dy = pose[0] - x0, pose[1] - y0
        step = (c0 * dx + s0 * dy, -s0 * dx + c0 * dy, float(wrap_angle(pose[2] - t0)))  # in the estimate's frame
        c, s = np.cos(self.poses[:, 2]), np.sin(self.poses[:, 2])
        self.poses = np.stack([self.poses[:, 0] + c * step[0] - s * step[1], self.poses[:, 1] + s * step[0]
                               + c * step[1], wrap_angle(self.poses[:, 2] + step[2])], axis=1)

    def _far(self, poses: np.ndarray, pose: np.ndarray, far_xy: float | None = None,
             far_theta: float | None = None) -> np.ndarray:
        far_xy = self.far_xy if far_xy is None else far_xy
        far_theta = self.far_theta if far_theta is None else far_theta
        turn = np.abs(wrap_angle(poses[:, 2] - pose[2]))
        return (np.hypot(poses[:, 0] - pose[0], poses[:, 1] - pose[1]) > far_xy) | (turn > far_theta)

    def observe(self, pose, log_likelihood: float, rival_log_likelihood: np.ndarray, probes: np.ndarray,
                probe_log_likelihood: np.ndarray) -> None:
        """One frame: the estimate's and the (carried) rivals' log-likelihoods, this frame's probes and theirs."""
        pose = np.asarray(pose, dtype=np.float64)
        differences = np.roll(self.differences, -1, axis=1)
        differences[:, -1] = rival_log_likelihood - log_likelihood
        old_total = np.nansum(differences, axis=1)
        old = np.flatnonzero(np.isfinite(differences[:, -1]) & (old_total > -self.prune) & self._far(self.poses, pose))
        # the followed rivals first (a lucky probe's one frame must not evict a rival's ten), then this frame's best
        # probes: capacity / frames of them, so that the set turns over once every `frames` frames at most
        fresh_count = max(self.capacity // self.frames, 1)
        old = old[np.argsort(-old_total[old], kind="stable")][:self.capacity - fresh_count]
        difference = probe_log_likelihood - log_likelihood
        new = np.flatnonzero(self._far(probes, pose) & np.isfinite(difference) & (difference > -self.prune))
        new = new[np.argsort(-difference[new], kind="stable")][:self.capacity - old.size]
        fresh = np.full((new.size, self.frames), np.nan)
        fresh[:, -1] = difference[new]
        self.poses = np.vstack([self.poses[old], probes[new]])
        self.differences = np.vstack([differences[old], fresh])
        self.last_pose = pose
        self.observed = min(self.observed + 1, self.frames)  # at least `frames` is all that matters

    def log_odds(self, pose=None, far_xy: float | None = None, far_theta: float | None = None) -> float | None:
        """The best rival's evidence over the last ``frames`` frames against the estimate (nats); None while no
        rival has been followed that long. With ``pose`` (the estimate the rivals were carried to), only the rivals
        farther than ``far_xy`` or turned more than ``far_theta`` from it count."""
        complete = np.isfinite(self.differences).all(axis=1)
        if pose is not None:
            complete &= self._far(self.poses, np.asarray(pose, dtype=np.float64), far_xy, far_theta)
        return float(self.differences[complete].sum(axis=1).max()) if complete.any() else None

    def snapshot(self) -> dict:
        return {"poses": self.poses.tolist(), "differences": np.where(np.isfinite(self.differences),
                                                                        self.differences, None).tolist(),
                "last_pose": None if self.last_pose is None else self.last_pose.tolist(), "observed": self.observed}

    def restore(self, snapshot: dict) -> None:
        poses = np.asarray(snapshot.get("poses", []), dtype=np.float64).reshape(-1, 3)
        differences = np.asarray(snapshot.get("differences", []), dtype=np.float64).reshape(-1, self.frames)
        last = snapshot.get("last_pose")
        if poses.shape[0] != differences.shape[0] or not np.isfinite(poses).all():
            raise ValueError("health snapshot: rivals' poses and differences must match, poses finite")
        self.poses, self.differences = poses, differences
        self.last_pose = None if last is None else np.asarray(last, dtype=np.float64).reshape(3)
        observed = int(snapshot.get("observed", 0))  # older snapshots: nothing ruled out for `frames` frames
        if observed < 0:
            raise ValueError("health snapshot: rivals' observed frames must be >= 0")
        self.observed = min(observed, self.frames)


def estimate_margin(perception, heatlines, pose, free_space, rng: np.random.Generator, probes: int,
                    view=None, rivals: Rivals | None = None, second=None) -> float | None:
    """ℓ(pose) − max(ℓ(pose), ℓ(probe)) over ``probes`` poses aligned with the heatlines' detections in the free
    space (≤ 0 nats: how much better a pose elsewhere explains this observation). None when the observation carries
    no evidence or has no detection to align a probe with. With ``rivals``, they are carried to ``pose``, weighed
    in the same call and updated with this frame's probes; ``second`` (perception, Rivals): another perception
    model weighing the same estimate and probes against its own rivals (the two models' agreement)."""
    sampler = getattr(perception, "sample_poses", None)
    if sampler is None or heatlines is None:
        return None
    pose = np.asarray(pose, dtype=np.float64).reshape(3)
    followed = [rivals, None if second is None else second[1]]
    for each in followed:
        if each is not None:
            each.carry(pose)
            each.last_pose = pose
    candidates = sampler(heatlines, probes, free_space, rng)
    if candidates.shape[0] == 0:
        return None
    candidates = candidates[free_space.contains(candidates[:, :2])]
    n = candidates.shape[0]
    margin = None
    for model, each in [(perception, rivals)] + ([] if second is None else [tuple(second)]):
        carried = each.poses if each is not None else np.zeros((0, 3))
        states = np.vstack([pose.reshape(1, 3), candidates, carried])
        weighing = model.weigh(states, heatlines) if view is None else model.weigh(states, heatlines, view)
        log_likelihood = np.asarray(weighing.log_likelihood, dtype=np.float64)
        if not weighing.informative or not np.isfinite(log_likelihood[0]):
            if model is perception:
                return None
            continue
        if each is not None:
            each.observe(pose, float(log_likelihood[0]), log_likelihood[1 + n:], candidates, log_likelihood[1:1 + n])
        if model is perception:
            probe_values = log_likelihood[:1 + n]
            margin = float(log_likelihood[0] - np.max(probe_values[np.isfinite(probe_values)]))
    return margin


def judge(monitor: "HealthMonitor", particle_filter, estimate: PoseEstimate, heatlines, view, rng: np.random.Generator,
          moved=None, place_poses=None, second_perception=None) -> "Verdict":
    """The monitor's verdict on ``estimate``, the filter's after a step with ``heatlines`` (probes from ``rng``:
    the filter's course is the same without it); ``moved`` the step's odometry (dx, dy, dθ; None: unknown),
    ``place_poses`` a recognised place's opinion, ``second_perception`` the other model (its rivals the
    monitor's)."""
    margin = None
    if heatlines is not None and estimate.status is not Status.UNINITIALIZED:
        second = None if second_perception is None or monitor.second_rivals is None else (
            second_perception, monitor.second_rivals)
        margin = estimate_margin(particle_filter.perception, heatlines, estimate.pose, particle_filter.free_space,
                                 rng, monitor.config.probes, view, monitor.rivals, second)
    return monitor.update(estimate, margin, place_poses=place_poses, lost_ratio=particle_filter.config.lost_ratio,
                          moved=moved)


def hypothesis_spreads(covariances) -> np.ndarray:
    """(..., 2): the position std along the widest axis (m) and the heading std (rad) of pose covariances (..., 3, 3)
    - the statistics of the filter's convergence test, here of the hypothesis the estimate reports."""
    covariances = np.asarray(covariances, dtype=np.float64)
    xy = np.sqrt(np.maximum(np.linalg.eigvalsh(covariances[..., :2, :2])[..., -1], 0.0))
    return np.stack([xy, np.sqrt(np.maximum(covariances[..., 2, 2], 0.0))], axis=-1)


def confident_places(loop_poses, beliefs, min_log_odds: float) -> np.ndarray | None:
    """The recorded poses (K, 3) of a recognised place whose loops' log-odds (``beliefs``, K) reach
    ``min_log_odds`` and whose pose was recorded (NaN rows: seen while not localized); None when none is left. A
    loop is an opinion only at the odds the monitor asks of everything else: the loop-closure worker also reports
    loops it gives itself little chance (the demo's table top: P under 0.45, frames 1.6-3.3 m apart, which made a
    good estimate uncertain)."""
    loop_poses = np.asarray(loop_poses, dtype=np.float64).reshape(-1, 3)
    beliefs = np.asarray(beliefs, dtype=np.float64).reshape(-1)
    if beliefs.shape[0] != loop_poses.shape[0]:
        raise ValueError(f"{loop_poses.shape[0]} place poses for {beliefs.shape[0]} beliefs")
    kept = loop_poses[np.isfinite(loop_poses).all(axis=1) & (beliefs >= min_log_odds)]
    return kept if kept.shape[0] else None


def pose_distance(estimate: PoseEstimate, other, extra_std: float = 0.0) -> float:
    """Mahalanobis distance (planar position) of ``other`` (x, y[, θ]) from the estimate, its covariance widened
    by ``extra_std`` (m) on each axis."""
    return float(pose_distances(estimate, np.asarray(other, dtype=np.float64).reshape(1, -1), extra_std)[0])


def pose_distances(estimate: PoseEstimate, others, extra_std: float = 0.0) -> np.ndarray:
    """``pose_distance`` of each row of ``others`` (K, 2 or 3) at once: a place recognised with many loops costs one
    solve, not one per loop."""
    covariance = np.asarray(estimate.covariance, dtype=np.float64)[:2, :2] + extra_std ** 2 * np.eye(2)
    delta = np.asarray(others, dtype=np.float64)[:, :2] - np.asarray(estimate.pose, dtype=np.float64)[:2]
    try:
        solved = np.linalg.solve(covariance, delta.T).T
    except np.linalg.LinAlgError:
        return np.full(delta.shape[0], math.inf)
    return np.sqrt(np.maximum(delta[:, 0] * solved[:, 0] + delta[:, 1] * solved[:, 1], 0.0))


class HealthMonitor:
    """See the module docstring. ``converged_*``: the filter's thresholds, used where the config leaves them None."""

    def __init__(self, config: HealthConfig | None = None, converged_xy_std: float = 0.5,
                 converged_theta_std: float = math.radians(20.0), converged_cluster_weight: float = 0.9):
        self.config = config or HealthConfig()
        c = self.config
        self.max_xy_std = c.max_xy_std or converged_xy_std
        self.max_theta_std = c.max_theta_std or converged_theta_std
        self.min_cluster_weight = c.min_cluster_weight or converged_cluster_weight
        # how far from its recorded pose a place is seen again: the loop-closure engine's loops join frames a few of
        # the map's own scale apart (the hall's at P >= 0.99: 53 % within 4 m, 87 % within 8 m; the table tops' and
        # the demo's 0.5 m at converged_xy_std 0.1 m)
        self.place_std = c.place_std or 5.0 * converged_xy_std
        # a rival is a pose the filter would call another hypothesis: beyond three of its converged spreads
        self.elsewhere_xy, self.elsewhere_theta = 3 * self.max_xy_std, 3 * self.max_theta_std
        self.rivals = Rivals(c.rivals, c.rival_frames, self.elsewhere_xy, self.elsewhere_theta) if c.rivals else None
        # the second perception model's rivals (weighed by the caller: estimate_margin(..., second=...))
        self.second_rivals = Rivals(c.rivals, c.rival_frames, self.elsewhere_xy, self.elsewhere_theta) \
            if c.rivals and c.second_model else None
        # lost: a rival ahead by the odds of the filter's own convergence test (c / (1 - c), 9:1 at c = 0.9) - the
        # last frames' evidence favours a pose elsewhere as firmly as convergence asks of the estimate. Evidence
        # merely even says nothing: it is summed over the last frames only, while the estimate also rests on the
        # frames before (on the shared table tops a pose elsewhere is within 9:1 of a correct estimate on 5-88 %
        # of the frames, docs/results/2026-12-05-localization-lost.md)
        self.rival_lost = math.log(self.min_cluster_weight / (1.0 - self.min_cluster_weight))
        self.reset()

    def place_opinion(self, loop_poses, beliefs) -> np.ndarray | None:
        """The poses of a recognised place that count as an opinion (``update(place_poses=...)``): recorded, of
        loops at the convergence odds (``confident_places``)."""
        return confident_places(loop_poses, beliefs, self.rival_lost)

    @classmethod
    def for_filter(cls, filter_config, config: HealthConfig | None = None) -> "HealthMonitor":
        return cls(config, filter_config.converged_xy_std, filter_config.converged_theta_std,
                   filter_config.converged_cluster_weight)

    def reset(self, given: bool = False) -> None:
        """Forget the state and the rivals (a new initialisation). ``given``: the filter starts from a pose given to
        it (an operator's ``set-pose``), a hypothesis no frame has weighed. Lost (initialising) until the first
        verdict, which applies at once: converged, the given pose is ``uncertain`` and held there as a jump is, until
        the rivals have weighed it over ``rival_frames`` frames (a wrong one is then ``lost``)."""
        self.state = LocalizationState.LOST
        self.pending: LocalizationState | None = None
        self.pending_count = 0
        self.uncertain_count = 0
        for followed in (self.rivals, self.second_rivals):
            if followed is not None:
                followed.reset()
        self.last = Verdict(self.state, self.state, "initialising", None)
        self.last_pose: np.ndarray | None = None  # the last estimate judged
        # frames since the estimate last jumped to another hypothesis, or since a pose was given (both held)
        self.since_jump: int | None = 0 if given else None
        self.last_jump: float | None = None  # how far (m); None: a given pose

    # ------------------------------------------------------------------ one frame
    def update(self, estimate: PoseEstimate, margin: float | None, other_pose=None, place_poses=None,
               lost_ratio: float = 0.5, moved=None) -> Verdict:
        """The state after one correction (see the module docstring). ``other_pose``: another model's estimate of
        the same frame; ``place_poses`` (K, 3): recorded poses of a place recognised at this frame; ``moved``: the
        odometry (dx, dy, dθ in the body frame) since the last update (None: unknown)."""
        c = self.config
        # Another hypothesis took over a localized track (a history-checked proposal, recovery particles): the
        # estimate lies where no motion from the last one leads (farther than three converged spreads). The
        # rivals, poses elsewhere followed along the estimate's own motion, were carried along the jump and say
        # nothing about it: they start again, and the new hypothesis is not localized before they have weighed it
        # over rival_frames frames (the hall, seed 1: a history-checked proposal 35 m off took over a localized
        # track, the places recorded it at the next two frames, and that held a later restart there off the truth
        # for 12 frames). A jump while lost or uncertain is the recovery the hysteresis already waits for.
        if moved is not None and self.last_pose is not None:
            expected = compose_motion(self.last_pose, np.asarray(moved, dtype=np.float64))
            jump = float(np.hypot(*(np.asarray(estimate.pose[:2]) - expected[:2])))
            if jump > self.elsewhere_xy and self.state is LocalizationState.LOCALIZED:
                self.since_jump, self.last_jump = 0, jump
                for followed in (self.rivals, self.second_rivals):
                    if followed is not None:
                        followed.reset()
        self.last_pose = np.array(estimate.pose, dtype=np.float64)
        spreads = hypothesis_spreads(estimate.covariance)
        # a rival counts beyond three spreads of the hypothesis (at least three converged ones, as the rivals are
        # gathered): a pose nearer lies in the hypothesis's own tail, which the filter moves over by itself
        reach = (3 * max(self.max_xy_std, float(spreads[0])), 3 * max(self.max_theta_std, float(spreads[1])))
        rival, second_rival = (None if each is None else each.log_odds(estimate.pose, *reach)
                               for each in (self.rivals, self.second_rivals))
        raw, reason = self._verdict(estimate, spreads, rival, second_rival, other_pose, place_poses, lost_ratio)
        # the first verdict on a given pose applies at once: the lost before it was the filter's initialisation (a
        # PoseEstimate still localizing is lost), not evidence the hysteresis should wait out
        given_first = self.since_jump == 0 and self.last_jump is None
        if self.since_jump == 0 and raw is LocalizationState.LOCALIZED:
            raw, reason = LocalizationState.UNCERTAIN, GIVEN
            if self.last_jump is not None:
                reason = f"another hypothesis: the estimate jumped {self.last_jump:.1f} m"
        unjudged = self.since_jump is not None and self.since_jump < c.rival_frames
        if self.since_jump is not None:
            self.since_jump += 1
        if raw is LocalizationState.UNCERTAIN:
            self.uncertain_count += 1
            if self.uncertain_count >= c.lost_after:
                raw, reason = LocalizationState.LOST, f"uncertain for {self.uncertain_count} frames"
        elif raw is LocalizationState.LOCALIZED:
            self.uncertain_count = 0
        self._apply(raw, hold=unjudged, at_once=given_first)
        self.last = Verdict(self.state, raw, reason, margin, rival, second_rival)
        return self.last

    def _verdict(self, estimate, spreads, rival, second_rival, other_pose, place_poses,
                 lost_ratio) -> tuple[LocalizationState, str]:
        c = self.config
        if estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING):
            return LocalizationState.LOST, "initialising"
        if estimate.recovery_ratio < lost_ratio:
            return LocalizationState.LOST, f"recovery running (fit ratio {estimate.recovery_ratio:.2f})"
        if rival is not None and rival >= self.rival_lost:
            return LocalizationState.LOST, f"a pose elsewhere explains the last frames better ({rival:+.1f} nats)"
        xy_std, theta_std = (float(v) for v in spreads)
        if estimate.cluster_weight < self.min_cluster_weight:  # hypotheses compete: the filter is searching
            return LocalizationState.LOST, f"the hypothesis holds {estimate.cluster_weight:.2f} of the weight"
        spread = f"spread {xy_std:.3f} m, {math.degrees(theta_std):.1f} deg"
        if xy_std > self.elsewhere_xy or theta_std > self.elsewhere_theta:
            return LocalizationState.UNCERTAIN, f"{spread}: the hypothesis reaches poses elsewhere"
        # wider than the filter's converged spread: localized still when the last rival_frames frames rule out
        # every pose elsewhere at the same odds (no rival within them, the others pruned). Without rivals: the
        # spread alone
        ruled_out = (self.rivals is not None and self.rivals.observed >= self.rivals.frames
                     and (rival is None or rival <= -self.rival_lost))
        if (xy_std > self.max_xy_std or theta_std > self.max_theta_std) and not ruled_out:
            return LocalizationState.UNCERTAIN, f"{spread}, and the last frames do not rule out a pose elsewhere"
        if second_rival is not None and second_rival >= self.rival_lost:
            return (LocalizationState.UNCERTAIN, f"the other perception model finds a pose elsewhere that explains "
                    f"the last frames better ({second_rival:+.1f} nats)")
        if other_pose is not None and pose_distance(estimate, other_pose) > c.disagreement:
            return LocalizationState.UNCERTAIN, "the other perception model disagrees"
        if place_poses is not None and len(place_poses):
            nearest = float(pose_distances(estimate, np.asarray(place_poses).reshape(-1, 3), self.place_std).min())
            if nearest > c.disagreement:
                return LocalizationState.UNCERTAIN, "a recognised place puts the robot elsewhere"
        return LocalizationState.LOCALIZED, "converged and fitting"

    def _apply(self, raw: LocalizationState, hold: bool = False, at_once: bool = False) -> None:
        """Hysteresis: worse (or ``at_once``) at once, better after ``recover_frames`` frames in a row, and not while
        ``hold`` (a new hypothesis the rivals have not yet weighed over ``rival_frames``)."""
        order = {LocalizationState.LOCALIZED: 0, LocalizationState.UNCERTAIN: 1, LocalizationState.LOST: 2}
        if at_once or order[raw] >= order[self.state]:
            self.state, self.pending, self.pending_count = raw, None, 0
            return
        if self.pending is None or order[raw] != order[self.pending]:
            self.pending, self.pending_count = raw, 0
        self.pending_count += 1
        if self.pending_count >= self.config.recover_frames and not hold:
            self.state, self.pending, self.pending_count = raw, None, 0

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict:
        return {"state": self.state.value, "pending": None if self.pending is None else self.pending.value,
                "pending_count": self.pending_count, "uncertain_count": self.uncertain_count,
                "last_pose": None if self.last_pose is None else self.last_pose.tolist(),
                "since_jump": self.since_jump, "last_jump": self.last_jump,
                **({} if self.rivals is None else {"rivals": self.rivals.snapshot()}),
                **({} if self.second_rivals is None else {"second_rivals": self.second_rivals.snapshot()})}

    def restore(self, snapshot: dict) -> None:
        state = LocalizationState(snapshot.get("state", "lost"))
        pending = None if snapshot.get("pending") is None else LocalizationState(snapshot["pending"])
        for name, followed in (("rivals", self.rivals), ("second_rivals", self.second_rivals)):
            if followed is not None:
                followed.restore(snapshot.get(name, {}))  # checked before anything else changes
        self.state, self.pending = state, pending
        self.pending_count = int(snapshot.get("pending_count", 0))
        self.uncertain_count = int(snapshot.get("uncertain_count", 0))
        last_pose = snapshot.get("last_pose")
        self.last_pose = None if last_pose is None else np.asarray(last_pose, dtype=np.float64).reshape(3)
        self.since_jump = None if snapshot.get("since_jump") is None else int(snapshot["since_jump"])
        last_jump = snapshot.get("last_jump")
        self.last_jump = None if last_jump is None else float(last_jump)
        self.last = Verdict(self.state, self.state, "restored", None)
