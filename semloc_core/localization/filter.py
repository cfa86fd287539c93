"""Monte Carlo localization over (x, y, θ) against a map of labelled objects (thesis §4.4, §4.7).

``ParticleFilter`` composes three interchangeable parts and keeps the particle set:

* a motion model (``motion``): ``sample(states, odometry, dt, rng)``;
* a perception model (``perception``): ``weigh(states, heatlines) -> Weighing``;
* the free space (``free_space``): where global initialisation and recovery draw particles.

Per frame: ``predict(odometry, dt)`` then ``correct(heatlines)``, or ``step(heatlines, odometry, dt)``; the pose is
``estimate()``. What it adds to the thesis's filter, with nav2 AMCL's conveniences in mind:

* resampling only when the effective sample size falls below ``resample_ess_ratio`` x N, with the low-variance
  sampler, and a KLD-adaptive particle count (``min_particles`` .. ``max_particles``);
* augmented MCL (Thrun et al., *Probabilistic Robotics* table 8.3; AMCL's ``recovery_alpha_slow/fast``): short-
  and long-term averages of how well the particles explain the observations; when the short-term one falls behind,
  random particles from the free space are injected - how the filter recovers from kidnapping;
* an estimate that is the weighted mean (circular for θ) and covariance of the heaviest cluster of particles (or of
  all of them, as in the thesis), with a status: ``uninitialized``, ``localizing`` (never converged since the last
  initialisation), ``converged``, ``lost``; optional automatic global relocalization after being lost for a while;
* ``initialize_pose(mean, covariance)`` and ``initialize_global()`` (AMCL's initial pose and global localization
  service), ``update_min_distance`` / ``update_min_angle`` (AMCL's ``update_min_d/a``), and a snapshot of the
  particle set to persist and restore;
* sensor resetting: part of a global initialisation (at the first observation) and of the recovery particles are
  drawn aligned with a detection of the current heatlines (``observation_sampling``); a sharp likelihood (model B)
  otherwise needs a particle within a few degrees of the truth, which 10^4 uniform particles rarely provide;
* optional tempering of a correction so that the effective sample size stays above ``min_ess_ratio`` x N;
* optional history-checked proposals (``history_frames``; beyond the thesis and AMCL): poses aligned with the
  current detections are carried back along the odometry of the last ``history_frames`` observations and weighed
  against all of them, as are the filter's own particles. A proposal that explains that window better than every
  particle by more than ``history_margin`` nats, and leads them on the newest half of the window too, joins the
  set with the window's evidence as its weight (the windowed form of Thrun et al.'s dual MCL). Without it a cloud
  that settled on the wrong poses while the observations were still ambiguous waits for the random injection of
  augmented MCL to land near the truth.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from enum import Enum

import numpy as np
from pydantic import Field

from semloc_core.bearing import Heatlines
from semloc_core.geometry import wrap_angle
from semloc_core.localization import _kernels
from semloc_core.localization.free_space import FreeSpace
from semloc_core.localization.motion import Odometry
from semloc_core.localization.resampling import (effective_sample_size, kld_resample, low_variance_resample,
                                                  normalize_log_weights)
from semloc_core.settings import settings


class NonFiniteStepError(ArithmeticError):
    """A predict or correct step would have left the particle set non-finite (NaN or infinite poses or weights,
    e.g. from an absurd odometry): it was refused and the filter kept its previous state (counted in
    ``ParticleFilter.refused_steps``)."""


class Status(str, Enum):
    UNINITIALIZED = "uninitialized"
    LOCALIZING = "localizing"
    CONVERGED = "converged"
    LOST = "lost"


@settings
class FilterConfig:
    """Particle-filter parameters (names follow nav2 AMCL where one exists). Distances in metres, angles in radians.

    ``kld_bin_xy``/``kld_bin_theta`` and ``cluster_cell`` should be a few times finer than the map's scale (nav2's
    0.5 m / 10° suit a building; a table top wants ~0.05 m).
    """

    min_particles: int = Field(500, ge=1, description="fewest particles KLD sampling may keep (AMCL min_particles)")
    max_particles: int = Field(10000, ge=1, description="most particles; also the global initialisation's size "
                               "(AMCL max_particles)")
    adaptive: bool = Field(True, description="KLD-adaptive particle count (false: always max_particles)")
    kld_epsilon: float = Field(0.05, gt=0, lt=1, description="KLD error bound (AMCL pf_err)")
    kld_probability: float = Field(0.99, gt=0.5, lt=1, description="probability that the KLD error bound holds "
                                   "(AMCL pf_z)")
    kld_bin_xy: float = Field(0.5, gt=0, description="KLD histogram cell (m); ~ a tenth of the map's scale")
    kld_bin_theta: float = Field(math.radians(10.0), gt=0, description="KLD histogram heading bin (rad)")
    resample_ess_ratio: float = Field(0.5, ge=0, le=1, description="resample when ESS < ratio x N (1: every "
                                      "update, as the thesis)")
    recovery_alpha_slow: float = Field(0.001, ge=0, le=1, description="slow fit average rate; 0 disables recovery "
                                       "(AMCL recovery_alpha_slow)")
    recovery_alpha_fast: float = Field(0.1, ge=0, le=1, description="fast fit average rate (AMCL "
                                       "recovery_alpha_fast)")
    recovery_max_fraction: float = Field(0.25, ge=0, le=1, description="random particles injected per resampling, "
                                         "at most this share of max_particles")
    recovery_probes: int = Field(500, ge=0, description="poses aligned with the current detections weighed each "
                                 "update as the reference of the recovery fit (0: the particles only)")
    lost_ratio: float = Field(0.5, ge=0, le=1, description="w_fast / w_slow below this: the estimate no longer "
                              "explains the observations (status lost)")
    relocalize_after: int = Field(0, ge=0, description="lost for this many corrections in a row: global "
                                  "relocalization (0: never)")
    update_min_distance: float = Field(0.0, ge=0, description="skip corrections until moved this far (m; AMCL "
                                       "update_min_d; needs odometry)")
    update_min_angle: float = Field(0.0, ge=0, description="... or turned this much (rad; AMCL update_min_a)")
    confine_to_free_space: bool = Field(True, description="particles outside the map's free space get no weight")
    min_ess_ratio: float = Field(0.0, ge=0, lt=1, description="temper a correction (likelihood ** beta) so that "
                                 "ESS stays >= this x N (0: off)")
    outlier_probability: float = Field(0.05, ge=0, lt=1, description="prior that a frame is not explained by the "
                                       "map (occlusion, clutter, a misdetection): mixed in as a likelihood equal for "
                                       "every pose, so that no single correction lowers a particle's weight by more "
                                       "than ~1/outlier_probability against the best one (0: eq. 4.28 as is)")
    observation_sampling: float = Field(0.5, ge=0, le=1, description="share of global-initialisation and recovery "
                                        "particles aligned with a detection of the current observation (sensor "
                                        "resetting; needs a perception model with sample_poses)")
    estimate_from_cluster: bool = Field(True, description="report the heaviest hypothesis (false: the weighted mean "
                                        "of all particles, the thesis's estimate)")
    cluster_cell: float = Field(0.5, gt=0, description="grid cell (m) linking particles into one hypothesis")
    converged_cluster_weight: float = Field(0.9, gt=0, le=1, description="converged: the heaviest hypothesis holds "
                                            "this share of the weight ...")
    converged_xy_std: float = Field(0.5, gt=0, description="... its position std (largest axis) is below this "
                                    "(m) ...")
    converged_theta_std: float = Field(math.radians(20.0), gt=0, description="... and its heading std below this "
                                       "(rad)")
    recovery_track_mean: bool = Field(False, description="after the first convergence the long-term fit average "
                                      "is the track's mean fit (step 1/n) until 1/n falls to recovery_alpha_slow")
    history_frames: int = Field(0, ge=0, description="window of past observations (and their odometry) on which "
                                "proposals aligned with the current detections are checked against the particles "
                                "(0: off; needs odometry)")
    history_probes: int = Field(1000, ge=0, description="proposals checked on that window per correction")
    history_margin: float = Field(10.0, ge=0, description="nats a proposal must explain the window better than "
                                  "every particle by to join the set")
    history_inject: float = Field(0.1, ge=0, le=1, description="share of max_particles added as copies of the "
                                  "winning proposals")

    def __post_init__(self) -> None:
        if self.min_particles > self.max_particles:
            raise ValueError(f"need min_particles <= max_particles, got {self.min_particles}, {self.max_particles}")
        if self.recovery_alpha_slow and not self.recovery_alpha_slow < self.recovery_alpha_fast:
            raise ValueError("recovery_alpha_slow must be smaller than recovery_alpha_fast")

    @classmethod
    def from_dict(cls, values: dict) -> "FilterConfig":
        return cls(**values)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class PoseEstimate:
    """The filter's answer: ``pose`` (x, y, θ), ``covariance`` (3, 3) over (x, y, θ), and how much to trust it."""

    pose: np.ndarray
    covariance: np.ndarray
    status: Status
    n_particles: int
    effective_sample_size: float
    cluster_weight: float  # share of the weight in the hypothesis reported (1.0 for the all-particle mean)
    n_clusters: int
    recovery_ratio: float  # w_fast / w_slow (1.0 until recovery has statistics)
    mean_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))  # weighted mean of all particles
    mean_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


def weighted_pose_mean(states: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (circular for θ) and covariance of poses (N, 3); the θ residuals are wrapped."""
    states = np.ascontiguousarray(states, dtype=np.float64)
    return _pose_moments(states, np.asarray(weights, dtype=np.float64), np.sin(states[:, 2]), np.cos(states[:, 2]))


def _pose_moments(states, weights, sin_theta, cos_theta, labels=None, label: int = -1):
    """``weighted_pose_mean`` of the poses labelled ``label`` (all: -1), given each θ's sine and cosine."""
    mean, covariance = np.zeros(3), np.empty((3, 3))
    labels = np.zeros(0, dtype=np.int64) if labels is None else labels
    if not _kernels.pose_moments(states, weights, sin_theta, cos_theta, labels, label, mean, covariance) > 0:
        return np.zeros(3), np.full((3, 3), np.nan)
    return mean, covariance


def compose_motion(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Body-frame motion ``first`` then ``second`` (each dx, dy, dθ in the frame at its start) as one motion."""
    c, s = math.cos(first[2]), math.sin(first[2])
    return np.array([first[0] + c * second[0] - s * second[1], first[1] + s * second[0] + c * second[1],
                     float(wrap_angle(first[2] + second[2]))])


def uncompose_motion(poses: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """The poses (N, 3) from which body-frame ``motion`` (dx, dy, dθ) leads to ``poses``."""
    theta = poses[:, 2] - motion[2]
    c, s = np.cos(theta), np.sin(theta)
    return np.column_stack([poses[:, 0] - c * motion[0] + s * motion[1], poses[:, 1] - s * motion[0] - c * motion[1],
                            wrap_angle(theta)])


def outlier_mixture(log_likelihood: np.ndarray, outlier_probability: float) -> np.ndarray:
    """Log of (1 - ε) p(z|x) / p(z|x*) + ε over the particles x, x* the best of them, ε ``outlier_probability``.

    The perception models treat every frame as explained by the map; a frame that is not - an object hidden by
    clutter, a misdetection, a map error - then pulls the whole cloud to wherever it fits best, by tens of nats
    (eq. 4.27 multiplies hundreds of correlated bins), and the particles at the true pose are gone before the next
    frame could bring them back. Mixing in an outlier frame whose likelihood does not depend on the pose (set to
    the best particle's, the scale of the frame's likelihood being unknown) bounds what one frame can do: a particle
    loses at most a factor ~1/ε against the best one, and frames that agree still compound. -inf (outside the free
    space) stays -inf."""
    log_likelihood = np.ascontiguousarray(log_likelihood, dtype=np.float64)
    mixed = np.empty_like(log_likelihood)
    if not _kernels.outlier_mixture(log_likelihood, float(np.log1p(-outlier_probability)),
                                    math.log(outlier_probability), mixed):
        return log_likelihood
    return mixed


def _largest_eigenvalue(a: float, b: float, c: float) -> float:
    """The largest eigenvalue of the symmetric 2 x 2 matrix [[a, b], [b, c]] (np.linalg.eigvalsh costs ~30 µs of
    call overhead, a tenth of a 1,000-particle step)."""
    return float(0.5 * (a + c) + math.hypot(0.5 * (a - c), b))


def _log_sum_exp(log_values: np.ndarray) -> float:
    """log Σ exp over the finite entries (at least one): the largest plus the log of the rest's sum relative to it
    (``np.logaddexp.reduce`` adds them one at a time, a log and an exp each)."""
    top = log_values.max()
    if not (np.isfinite(top) and np.isfinite(log_values).all()):
        log_values = log_values[np.isfinite(log_values)]
        top = log_values.max()
    return float(top + np.log(np.exp(log_values - top).sum()))


def _tempering(log_prior: np.ndarray, log_likelihood: np.ndarray, min_ess_ratio: float, steps: int = 12) -> float:
    """Largest beta in (0, 1] with ESS(prior x likelihood ** beta) >= min_ess_ratio x N (bisection).

    When the particles are too sparse for the likelihood's peak (a global localization with a sharp model), the full
    update leaves one or two particles and the set collapses onto a wrong place; tempering widens the likelihood to
    the resolution the particles have, and leaves it untouched (beta = 1) once they are dense enough."""
    n = log_prior.shape[0]
    finite = np.isfinite(log_likelihood)
    if not finite.all() and finite.any():
        log_likelihood = np.where(finite, log_likelihood, -np.inf)

    def ess(beta: float) -> float:
        combined = log_prior + beta * log_likelihood
        return effective_sample_size(normalize_log_weights(combined))

    target = min_ess_ratio * n
    if ess(1.0) >= target:
        return 1.0
    low, high = 0.0, 1.0
    for _ in range(steps):
        middle = 0.5 * (low + high)
        if ess(middle) >= target:
            low = middle
        else:
            high = middle
    return max(low, 1e-6)


class ParticleFilter:
    """See the module docstring. ``rng`` makes runs reproducible."""

    # What the filter keeps per particle: its pose (3 float64), log weight (float64) and injected flag (bool); a
    # global initialisation of max_particles peaks at about five times that (170 B measured with the table top's
    # free space), an update higher still.
    KEPT_BYTES_PER_PARTICLE = 3 * 8 + 8 + 1

    def __init__(self, motion, perception, free_space: FreeSpace, config: FilterConfig | None = None,
                 rng: np.random.Generator | int | None = None):
        for name, part, method in (("motion", motion, "sample"), ("perception", perception, "weigh")):
            if not callable(getattr(part, method, None)):
                raise TypeError(f"{name} model must have a {method}() method, got {type(part).__name__}")
        if not isinstance(free_space, FreeSpace):
            raise TypeError(f"free_space must be a FreeSpace, got {type(free_space).__name__}")
        self.motion = motion
        self.perception = perception
        self.free_space = free_space
        self.config = config or FilterConfig()
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.states = np.zeros((0, 3))
        self.log_weights = np.zeros(0)
        self._weights = None  # (the log weights, their normalised weights)
        self._injected = np.zeros(0, dtype=bool)
        self._reset_statistics()
        self.relocalizations = 0
        self.tempering = 1.0
        self._heatlines = None
        self.history_injections = 0  # corrections at which history-checked proposals joined the set
        self.refused_steps = 0  # predict/correct steps refused because they would have made the state non-finite

    # ------------------------------------------------------------------ initialisation
    def _reset_statistics(self) -> None:
        self.w_slow = 0.0
        self.w_fast = 0.0
        self.converged_once = False
        self._updates_since_seed = -1  # recovery updates since the averages were seeded at the first convergence
        self.lost_count = 0
        self.moved_distance = 0.0
        self.moved_angle = 0.0
        self.pending_first_update = True
        self.seed_from_observation = False
        self.last_injected = 0
        self._estimate: PoseEstimate | None = None
        self._summary_cache = None
        # The last observations (heatlines, view, body-frame motion since the observation before) for the history
        # check, and the motion since the last observation; None once a prediction had no odometry.
        self._history: deque = deque(maxlen=max(self.config.history_frames, 1))
        self._motion_since_correct: np.ndarray | None = np.zeros(3)

    def initialize_global(self, n: int | None = None) -> None:
        """Uniform particles over the free space, uniform headings (global localization)."""
        n = self.config.max_particles if n is None else int(n)
        self.states = self.free_space.sample_poses(n, self.rng)
        self.log_weights = np.full(n, -math.log(n))
        self._reset_statistics()
        self._injected = np.zeros(n, dtype=bool)
        self.seed_from_observation = True  # part of the set is re-drawn from the first observation

    def initialize_pose(self, mean, covariance, n: int | None = None) -> None:
        """Particles drawn from N(mean, covariance) over (x, y, θ) (AMCL's initial pose)."""
        mean = np.asarray(mean, dtype=np.float64).reshape(-1)
        covariance = np.asarray(covariance, dtype=np.float64)
        if mean.shape != (3,) or not np.all(np.isfinite(mean)):
            raise ValueError(f"initial pose must be finite (x, y, theta), got {mean}")
        if covariance.shape != (3, 3) or not np.all(np.isfinite(covariance)):
            raise ValueError(f"initial covariance must be a finite 3x3 matrix, got shape {covariance.shape}")
        covariance = 0.5 * (covariance + covariance.T)
        if np.linalg.eigvalsh(covariance).min() < -1e-12:
            raise ValueError("initial covariance must be positive semi-definite")
        n = self.config.max_particles if n is None else int(n)
        states = self.rng.multivariate_normal(mean, covariance, size=n, method="eigh")
        states[:, 2] = wrap_angle(states[:, 2])
        self.states = states
        self.log_weights = np.full(n, -math.log(n))
        self._reset_statistics()
        self._injected = np.zeros(n, dtype=bool)

    def inject(self, poses) -> int:
        """A mixture proposal (sensor resetting; e.g. the poses a recognised place proposes,
        ``semloc_core.localization.proposals``): the set becomes ``max_particles`` particles, ``poses`` (M, 3) and
        the rest resampled from the current set by weight, all of equal weight, so that the next correction weighs
        the proposals against the tracked particles. The proposals count as injected (the recovery fit leaves them
        out, as augmented MCL's random particles). At most half the set; returns how many were injected."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(poses).all():
            raise ValueError("injected poses must be finite")
        if not self.initialized or poses.shape[0] == 0:
            return 0
        poses = poses[: self.config.max_particles // 2]
        chosen = low_variance_resample(self.weights, self.config.max_particles - poses.shape[0], self.rng)
        kept = self.states[chosen]
        poses = poses.copy()
        poses[:, 2] = wrap_angle(poses[:, 2])
        self.states = np.concatenate([kept, poses])
        self.log_weights = np.full(self.states.shape[0], -math.log(self.states.shape[0]))
        self._injected = np.concatenate([np.zeros(kept.shape[0], dtype=bool), np.ones(poses.shape[0], dtype=bool)])
        self.last_injected = poses.shape[0]
        self._estimate = None
        self._summary_cache = None
        return poses.shape[0]

    def reweigh(self, log_factor) -> None:
        """Multiply each particle's weight by ``exp(log_factor)`` (N,): evidence from outside the heatlines (a
        recognised place, ``semloc_core.localization.proposals.place_log_factor``). The next correction resamples
        when the weights have become uneven."""
        log_factor = np.asarray(log_factor, dtype=np.float64).reshape(-1)
        if log_factor.shape[0] != self.states.shape[0] or not np.isfinite(log_factor).all():
            raise ValueError(f"need one finite log factor per particle ({self.states.shape[0]}), got "
                             f"{log_factor.shape[0]}")
        if log_factor.shape[0] == 0:
            return
        log_weights = self.log_weights + log_factor
        self.log_weights = log_weights - _log_sum_exp(log_weights)
        self._estimate = None
        self._summary_cache = None

    @property
    def initialized(self) -> bool:
        return self.states.shape[0] > 0

    @property
    def weights(self) -> np.ndarray:
        """The normalised weights (read-only; computed once per set of log weights: a correction needs them for its
        prior, the resampling test and the estimate, and the next correction's prior is the last estimate's). The log
        weights are replaced, never changed in place, so that this holds."""
        cached = self._weights
        if cached is None or cached[0] is not self.log_weights:
            weights = normalize_log_weights(self.log_weights)
            weights.flags.writeable = False
            self._weights = cached = (self.log_weights, weights)
        return cached[1]

    # ------------------------------------------------------------------ filtering
    def _refuse(self, what: str) -> None:
        self.refused_steps += 1
        raise NonFiniteStepError(f"{what} would make the particle set non-finite: refused, previous state kept")

    def predict(self, odometry: Odometry | None = None, dt: float = 1.0) -> None:
        """Motion update (eq. 4.5 or the configured model); ``dt`` is used when there is no odometry. Raises
        :class:`NonFiniteStepError` (the particles unchanged) if the moved particles would not be finite."""
        if not self.initialized:
            return
        if odometry is not None and not isinstance(odometry, Odometry):
            raise TypeError(f"odometry must be an Odometry, got {type(odometry).__name__}")
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be finite and >= 0, got {dt}")
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is caught just below, and refused
            moved = self.motion.sample(self.states, odometry, dt, self.rng)
        if not np.isfinite(moved).all():
            self._refuse("the motion update")
        self.states = moved
        if odometry is not None:
            self.moved_distance += math.hypot(odometry.dx, odometry.dy)
            self.moved_angle += abs(odometry.dtheta)
            if self._motion_since_correct is not None:
                self._motion_since_correct = compose_motion(
                    self._motion_since_correct, np.array([odometry.dx, odometry.dy, odometry.dtheta]))
        else:
            self._motion_since_correct = None  # the history cannot be carried back without odometry
        self._estimate = None
        self._summary_cache = None

    def correct(self, heatlines: Heatlines, force: bool = False, view=None) -> bool:
        """Perception update (eq. 4.6 or 4.28) and, when due, resampling. Returns False when skipped. Raises
        :class:`NonFiniteStepError` (the particle set unchanged) if the weighing or its result is not finite.

        ``view``: an optional ``ViewGeometry`` of the frame (objects outside the image or hidden are not expected).
        """
        if not self.initialized:
            return False
        config = self.config
        moved_enough = (self.moved_distance >= config.update_min_distance
                        or self.moved_angle >= config.update_min_angle)
        if not (force or self.pending_first_update or moved_enough):
            return False
        states, seeded = self.states, False
        if self.seed_from_observation:
            count = int(round(config.observation_sampling * states.shape[0]))
            aligned = self._observation_poses(heatlines, count)
            if aligned.shape[0] or count == 0:  # otherwise wait for an observation with a detection
                states, seeded = np.concatenate([aligned, states[aligned.shape[0]:]]), True
        weighing = (self.perception.weigh(states, heatlines) if view is None
                    else self.perception.weigh(states, heatlines, view))
        # -inf (no support) is a valid log-likelihood; NaN, +inf (their max is one of them) or a non-finite fit are
        # not
        if (not np.max(weighing.log_likelihood, initial=-np.inf) < np.inf or not np.isfinite(weighing.fit).all()
                or not np.isfinite(states).all()):
            self._refuse("the perception update")
        previous = (self.states, self.log_weights, self._injected)  # (replaced below, never changed in place)
        self.states = states
        if seeded:
            self.seed_from_observation = False
        self._heatlines = heatlines
        self.moved_distance = self.moved_angle = 0.0
        self.pending_first_update = False
        self._estimate = None
        self._summary_cache = None
        if not weighing.informative:
            return True
        prior = self.weights
        log_likelihood = np.asarray(weighing.log_likelihood, dtype=np.float64)
        inside = self.free_space.contains(self.states[:, :2]) if config.confine_to_free_space else None
        if inside is not None:
            if inside.any():
                log_likelihood = np.where(inside, log_likelihood, -np.inf)
        if config.outlier_probability > 0:
            log_likelihood = outlier_mixture(log_likelihood, config.outlier_probability)
        self._remember(heatlines, view)
        self.tempering = 1.0
        if config.min_ess_ratio > 0:
            self.tempering = _tempering(self.log_weights, log_likelihood, config.min_ess_ratio)
            log_likelihood = self.tempering * log_likelihood
        self.log_weights = self.log_weights + log_likelihood
        if not np.isfinite(self.log_weights).any():  # nothing survived: keep the prior rather than collapse
            self.log_weights = np.log(np.maximum(prior, 1e-300))
        self.log_weights = self.log_weights - _log_sum_exp(self.log_weights)
        # The predictive fit of the tracked particles: random particles injected at the last resampling are left
        # out, or their (expectedly poor) fit would keep the short-term average low and injection going for ever.
        tracked = prior * ~self._injected
        tracked_sum = float(tracked.sum())
        if tracked_sum <= 0:
            tracked, tracked_sum = prior, float(prior.sum())
        fit = np.maximum(np.asarray(weighing.fit, dtype=np.float64), 0.0)
        reference = self._reference_fit(heatlines, view, fit, inside)
        if reference > 0:
            self._update_recovery(min(float(tracked @ fit) / tracked_sum / reference, 1.0))
        self._history_check(heatlines)
        inject = self._injection_fraction()
        n = self.states.shape[0]
        if effective_sample_size(self.weights) < config.resample_ess_ratio * n or inject > 0.01:
            self._resample(inject)
        if not (np.isfinite(self.states).all() and not np.isnan(self.log_weights).any()):
            self.states, self.log_weights, self._injected = previous
            self._estimate = self._summary_cache = None
            self._refuse("the perception update")
        self._update_status()
        return True

    def step(self, heatlines: Heatlines | None, odometry: Odometry | None = None, dt: float = 1.0,
             view=None) -> PoseEstimate:
        """predict + correct + estimate, for one frame (``heatlines`` None: prediction only)."""
        self.predict(odometry, dt)
        if heatlines is not None:
            self.correct(heatlines, view=view)
        return self.estimate()

    def _observation_poses(self, heatlines, count: int) -> np.ndarray:
        """Poses aligned with a detection of ``heatlines`` (empty without a sampler, heatlines or detections)."""
        sampler = getattr(self.perception, "sample_poses", None)
        if count <= 0 or sampler is None or heatlines is None:
            return np.zeros((0, 3))
        return sampler(heatlines, count, self.free_space, self.rng)

    def _reference_fit(self, heatlines, view, fit: np.ndarray, inside: np.ndarray | None) -> float:
        """The best fit any pose reaches on this observation, as far as the filter can tell: over the particles and
        ``recovery_probes`` poses aligned with its detections (the sensor-resetting proposals).

        The recovery averages track the tracked particles' fit *relative to* this reference. A model's fit is
        relative to an ideal pose that explains every bin (model B) or all the observed mass (model A); how close
        the real best pose comes to it varies with the content of the frame (clutter, a detector's flat response,
        how many objects are in view), and the raw fit drifting with the content kept the short-term average below
        the long-term one for hundreds of frames while tracking correctly - injecting random particles at every
        update. Relative to the probes it is ~1 whatever the frame shows while tracking, and drops when poses
        elsewhere explain the observation better than the tracked ones (a kidnapping). ``inside``: which particles
        lie in the free space (None: not confined to it)."""
        config = self.config
        best = float(fit[inside].max()) if inside is not None and inside.any() else float(fit.max(initial=0.0))
        if config.recovery_alpha_slow <= 0 or config.recovery_probes <= 0:
            return best
        probes = self._observation_poses(heatlines, config.recovery_probes)
        if probes.shape[0]:
            weighing = (self.perception.weigh(probes, heatlines) if view is None
                        else self.perception.weigh(probes, heatlines, view))
            probe_fit = np.maximum(np.asarray(weighing.fit, dtype=np.float64), 0.0)
            if config.confine_to_free_space:
                probe_fit = probe_fit[self.free_space.contains(probes[:, :2])]
            best = max(best, float(probe_fit.max(initial=0.0)))
        return best

    # ------------------------------------------------------------------ history-checked proposals
    def _remember(self, heatlines, view) -> None:
        if self.config.history_frames <= 0:
            return
        if self._motion_since_correct is None:  # no odometry since the last observation: start a new window
            self._history.clear()
            motion = np.zeros(3)
        else:
            motion = self._motion_since_correct
        self._history.append((heatlines, view, motion))
        self._motion_since_correct = np.zeros(3)

    def window_log_likelihood(self, poses: np.ndarray, per_frame: bool = False) -> np.ndarray:
        """Sum of the log-likelihoods of the remembered observations (newest first) at ``poses`` (N, 3) of the
        newest observation carried back along the odometry between them; each frame's term is mixed with the
        outlier prior over the poses given, as in a correction. ``per_frame``: the terms (N, frames), newest
        first, instead of their sum."""
        poses = np.asarray(poses, dtype=np.float64)
        terms = np.zeros((poses.shape[0], len(self._history)))
        for k, (heatlines, view, motion) in enumerate(reversed(self._history)):
            weighing = (self.perception.weigh(poses, heatlines) if view is None
                        else self.perception.weigh(poses, heatlines, view))
            log_likelihood = np.asarray(weighing.log_likelihood, dtype=np.float64)
            if self.config.outlier_probability > 0:
                log_likelihood = outlier_mixture(log_likelihood, self.config.outlier_probability)
            terms[:, k] = log_likelihood
            poses = uncompose_motion(poses, motion)  # to the observation before
        return terms if per_frame else terms.sum(axis=1)

    def _history_check(self, heatlines) -> None:
        """Add the proposals that explain the remembered window better than every particle (module docstring)."""
        config = self.config
        if (config.history_frames <= 0 or config.history_probes <= 0 or config.history_inject <= 0
                or len(self._history) < config.history_frames):
            return
        probes = self._observation_poses(heatlines, config.history_probes)
        if probes.shape[0] == 0:
            return
        if config.confine_to_free_space:
            probes = probes[self.free_space.contains(probes[:, :2])]
        weights = self.weights
        sample = np.unique(low_variance_resample(weights, min(config.history_probes, len(weights)), self.rng))
        terms = self.window_log_likelihood(np.concatenate([probes, self.states[sample]]), per_frame=True)
        scores = terms.sum(axis=1)
        probe_scores, particle_scores = scores[:probes.shape[0]], scores[probes.shape[0]:]
        best_particle = float(particle_scores.max(initial=-np.inf))
        # The odometry carrying a pose back drifts (the hall's: 1.7-3 m over 10 frames), so the
        # oldest frames judge even the true pose at a pose that is off, and a proposal elsewhere can fit them
        # better by the drift alone (synthetic scores: a 5.9 m jump at a 62-degree turn). A winner must
        # therefore also lead on the newest half of the window, where the carried-back poses are still close.
        recent = terms[:, :(terms.shape[1] + 1) // 2].sum(axis=1)
        best_recent = float(recent[probes.shape[0]:].max(initial=-np.inf))
        winners = np.flatnonzero((probe_scores > best_particle + config.history_margin)
                                 & (recent[:probes.shape[0]] > best_recent))
        if winners.size == 0 or not np.isfinite(best_particle):
            return
        # The winners as a group against the particle set: posterior odds = the window's likelihood ratio between
        # the best of each (the set's older evidence is the particles' only advantage, and it was gathered on poses
        # this window now rules out). Within the group, copies drawn by their window likelihood.
        gain = probe_scores[winners] - best_particle
        n_new = max(1, int(round(config.history_inject * config.max_particles)))
        chosen = winners[self.rng.choice(winners.size, size=n_new, p=normalize_log_weights(gain))]
        log_group = float(np.logaddexp.reduce(self.log_weights)) + float(gain.max())
        self.states = np.concatenate([self.states, probes[chosen]])
        self.log_weights = np.concatenate([self.log_weights, np.full(n_new, log_group - math.log(n_new))])
        self.log_weights = self.log_weights - np.logaddexp.reduce(self.log_weights)
        self._injected = np.concatenate([self._injected, np.ones(n_new, dtype=bool)])
        self.history_injections += 1
        self._estimate = None
        self._summary_cache = None

    def _update_recovery(self, average_fit: float) -> None:
        config = self.config
        if config.recovery_alpha_slow <= 0:
            return
        alpha_slow = config.recovery_alpha_slow
        if self.config.recovery_track_mean and self._updates_since_seed >= 0:
            # Since the first convergence the long-term average is the mean fit of the track (1/n), until 1/n falls
            # to alpha_slow: seeded with the short-term average of the moment the track formed, an exponential
            # average kept that moment's fit for ~1/alpha_slow updates, and where it was above the track's usual
            # fit (hall: 0.88 against 0.81-0.87) random particles were injected at every update for hundreds of
            # frames, each batch a chance for a random cluster to take over the estimate.
            self._updates_since_seed += 1
            alpha_slow = max(alpha_slow, 1.0 / (self._updates_since_seed + 1))
        self.w_slow = average_fit if self.w_slow == 0 else self.w_slow + alpha_slow * (average_fit - self.w_slow)
        self.w_fast = average_fit if self.w_fast == 0 else self.w_fast + config.recovery_alpha_fast * (
            average_fit - self.w_fast)

    @property
    def recovery_ratio(self) -> float:
        return self.w_fast / self.w_slow if self.w_slow > 0 else 1.0

    def _injection_fraction(self) -> float:
        if self.config.recovery_alpha_slow <= 0:
            return 0.0
        return float(min(max(0.0, 1.0 - self.recovery_ratio), self.config.recovery_max_fraction))

    def _resample(self, inject_fraction: float) -> None:
        config = self.config
        weights = self.weights
        # augmented MCL (Probabilistic Robotics table 8.3): a share of uniform free-space poses. The share is of
        # max_particles, as when AMCL's KLD loop draws random samples (each fills a new bin and grows the set to
        # max_particles): a converged set of a few hundred particles would otherwise search the whole map with a
        # handful. As in AMCL the rest of the set is resampled from the tracked particles, so that the tracked
        # hypothesis keeps (1 - share) of the set: had it kept only its KLD count (a few hundred) beside thousands
        # of random poses, any random cluster explaining one frame as well would become the heaviest and be
        # reported. The averages are kept (AMCL resets them, which makes recovery a one-shot injection):
        # injection goes on at every update until the short-term fit is back to the long-term level.
        n_random = int(round(inject_fraction * config.max_particles))
        if n_random:
            chosen = low_variance_resample(weights, config.max_particles - n_random, self.rng)
        elif config.adaptive:
            chosen = kld_resample(self.states, weights, self.rng, config.min_particles, config.max_particles,
                                  config.kld_epsilon, config.kld_probability, config.kld_bin_xy, config.kld_bin_theta)
        else:
            chosen = low_variance_resample(weights, config.max_particles, self.rng)
        states = self.states[chosen]
        n_kept = states.shape[0]
        self.last_injected = n_random
        self._injected = np.zeros(n_kept + n_random, dtype=bool)
        if n_random:
            aligned = self._observation_poses(self._heatlines, int(round(config.observation_sampling * n_random)))
            uniform = self.free_space.sample_poses(n_random - aligned.shape[0], self.rng)
            states = np.concatenate([states, aligned, uniform])
            self._injected[n_kept:] = True
        self.states = states
        self.log_weights = np.full(states.shape[0], -math.log(states.shape[0]))
        self._estimate = None
        self._summary_cache = None

    # ------------------------------------------------------------------ estimate and status
    def _summary(self):
        """(weights, mean, covariance, n_clusters, best pose, best covariance, best share), once per particle set.
        The hypotheses are the 8-connected occupied cells of an xy grid of ``cluster_cell``."""
        if self._summary_cache is None:
            weights, states = self.weights, np.ascontiguousarray(self.states)
            sin_theta, cos_theta = np.empty(states.shape[0]), np.empty(states.shape[0])
            _kernels.sines_cosines(states[:, 2], sin_theta, cos_theta)
            mean, covariance = _pose_moments(states, weights, sin_theta, cos_theta)
            labels = np.empty(states.shape[0], dtype=np.int64)
            # a cloud spread over a huge area: no meaningful cluster
            n_clusters = _kernels.cluster_labels(states, self.config.cluster_cell, 4_000_000, labels)
            cluster_weights = np.bincount(labels, weights=weights, minlength=n_clusters)
            best = int(np.argmax(cluster_weights))
            if n_clusters > 1:
                pose, pose_covariance = _pose_moments(states, weights, sin_theta, cos_theta, labels, best)
            else:
                pose, pose_covariance = mean, covariance
            self._summary_cache = (weights, mean, covariance, n_clusters, pose, pose_covariance,
                                   float(cluster_weights[best]))
        return self._summary_cache

    def estimate(self) -> PoseEstimate:
        if self._estimate is not None:
            return self._estimate
        if not self.initialized:
            nan3 = np.full(3, np.nan)
            return PoseEstimate(nan3, np.full((3, 3), np.nan), Status.UNINITIALIZED, 0, 0.0, 0.0, 0,
                                self.recovery_ratio, nan3, np.full((3, 3), np.nan))
        weights, mean, covariance, n_clusters, pose, pose_covariance, share = self._summary()
        if not self.config.estimate_from_cluster:
            pose, pose_covariance = mean, covariance
        self._estimate = PoseEstimate(pose, pose_covariance, self._status, self.states.shape[0],
                                      effective_sample_size(weights), share, n_clusters, self.recovery_ratio, mean,
                                      covariance)
        return self._estimate

    def _converged(self) -> bool:
        config = self.config
        _, _, _, _, _, covariance, share = self._summary()
        if share < config.converged_cluster_weight:
            return False
        xy_std = math.sqrt(max(_largest_eigenvalue(covariance[0, 0], covariance[0, 1], covariance[1, 1]), 0.0))
        theta_std = math.sqrt(max(float(covariance[2, 2]), 0.0))
        return xy_std <= config.converged_xy_std and theta_std <= config.converged_theta_std

    def _update_status(self) -> None:
        config = self.config
        explained = self.recovery_ratio >= config.lost_ratio
        if self._converged() and explained:
            if not self.converged_once:
                # Seed the recovery averages with the converged fit: the slow average would otherwise keep the
                # poor fit of the global-localization phase for ~1/alpha_slow updates and mask a kidnapping.
                self.w_slow = self.w_fast = max(self.w_fast, 1e-300)
                self._updates_since_seed = 0
            self.converged_once = True
            self.lost_count = 0
            return
        if not self.converged_once:
            return
        self.lost_count += 1
        if config.relocalize_after and self.lost_count >= config.relocalize_after:
            self.initialize_global()
            self.relocalizations += 1

    @property
    def _status(self) -> Status:
        if not self.initialized:
            return Status.UNINITIALIZED
        if not self.converged_once:
            return Status.LOCALIZING
        return Status.LOST if self.lost_count else Status.CONVERGED

    @property
    def status(self) -> Status:
        return self._status

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict:
        """The filter's state as plain arrays, numbers and the random generator's state (for npz + JSON / msgpack;
        no pickle): :meth:`restore` continues exactly where this filter is, draw for draw. Not included: the
        history window (``history_frames``), observations and view geometries the caller keeps
        (:attr:`history`, :meth:`restore_history`); without it a restored filter starts the window anew, and draws
        differently until it is full again."""
        return {
            "states": self.states.copy(), "log_weights": self.log_weights.copy(), "injected": self._injected.copy(),
            "motion_since_correct": (None if self._motion_since_correct is None
                                     else self._motion_since_correct.copy()),
            "w_slow": self.w_slow, "w_fast": self.w_fast, "converged_once": self.converged_once,
            "lost_count": self.lost_count, "relocalizations": self.relocalizations,
            "updates_since_seed": self._updates_since_seed, "moved_distance": self.moved_distance,
            "moved_angle": self.moved_angle, "pending_first_update": self.pending_first_update,
            "seed_from_observation": self.seed_from_observation, "last_injected": self.last_injected,
            "tempering": self.tempering, "history_injections": self.history_injections,
            "rng": self.rng.bit_generator.state,
        }

    @property
    def history(self) -> list[tuple]:
        """The remembered window, oldest first: (heatlines, view, motion (dx, dy, dθ) since the observation before)."""
        return list(self._history)

    def restore_history(self, history) -> None:
        """The window of :attr:`history` back, after :meth:`restore`: the history-checked proposals go on as if the
        filter had never stopped (they run, and draw, only once the window is full). All or nothing."""
        entries = []
        for heatlines, view, motion in history:
            motion = np.asarray(motion, dtype=np.float64).reshape(-1)
            if motion.shape != (3,) or not np.all(np.isfinite(motion)):
                raise ValueError("history: each observation's motion must be 3 finite numbers")
            entries.append((heatlines, view, motion))
        self._history = deque(entries, maxlen=self._history.maxlen)

    def restore(self, snapshot: dict) -> None:
        """Restore :meth:`snapshot` (entries it lacks keep their initial values); all or nothing."""
        states = np.asarray(snapshot["states"], dtype=np.float64)
        log_weights = np.asarray(snapshot["log_weights"], dtype=np.float64)
        if states.ndim != 2 or states.shape[1] != 3 or log_weights.shape != (states.shape[0],):
            raise ValueError("snapshot states must be (N, 3) with N log weights")
        if not np.all(np.isfinite(states)):
            raise ValueError("snapshot states must be finite")
        injected = np.asarray(snapshot.get("injected", np.zeros(states.shape[0], bool)), dtype=bool)
        if injected.shape != (states.shape[0],):
            raise ValueError("snapshot: one injected flag per particle")
        motion = snapshot.get("motion_since_correct", np.zeros(3))
        motion = None if motion is None else np.asarray(motion, dtype=np.float64).reshape(-1)
        if motion is not None and (motion.shape != (3,) or not np.all(np.isfinite(motion))):
            raise ValueError("snapshot: the motion since the last correction must be 3 finite numbers")
        rng = snapshot.get("rng")
        if rng is not None:
            probe = np.random.default_rng()
            probe.bit_generator.state = rng  # raises on a state of another generator
        self._reset_statistics()
        self.states = states.copy()
        self.log_weights = log_weights.copy()
        self._injected = injected.copy()
        self._motion_since_correct = motion
        self.w_slow = float(snapshot.get("w_slow", 0.0))
        self.w_fast = float(snapshot.get("w_fast", 0.0))
        self.converged_once = bool(snapshot.get("converged_once", False))
        self.lost_count = int(snapshot.get("lost_count", 0))
        self.relocalizations = int(snapshot.get("relocalizations", 0))
        self._updates_since_seed = int(snapshot.get("updates_since_seed", -1))
        self.moved_distance = float(snapshot.get("moved_distance", 0.0))
        self.moved_angle = float(snapshot.get("moved_angle", 0.0))
        self.pending_first_update = bool(snapshot.get("pending_first_update", True))
        self.seed_from_observation = bool(snapshot.get("seed_from_observation", False))
        self.last_injected = int(snapshot.get("last_injected", 0))
        self.tempering = float(snapshot.get("tempering", 1.0))
        self.history_injections = int(snapshot.get("history_injections", 0))
        if rng is not None:
            self.rng.bit_generator.state = rng
