"""Recognised places propose poses (issue 34; thesis ch. 6's hybrid of a topological and a metric map).

The loop-closure worker's places carry the poses at which their frames were seen while the localizer was
``localized`` (the hybrid map's nodes). When it recognises a place - a loop with a belief - while the localizer is
lost or initialising, ``place_proposals`` draws poses around that place's recorded poses, and
``ParticleFilter.inject`` puts them in the particle set: a mixture proposal in the manner of sensor resetting
(Lenser & Veloso 2000) and Thrun et al.'s mixture MCL (*Probabilistic Robotics* §8.3.5). A wrong recognition must
cost little, so the proposals stay a minority of the set (at most ``max_share`` of ``max_particles``, scaled by
the loop's probability) and are weighed by the next heatlines like any particle: where the heatlines do not agree
they die out at the next resampling.

Proposals alone are a minority that the next heatlines may drown: where a pose far away explains a few frames
slightly better (the hall carried back onto an earlier stretch: 1.5-2 nats a frame for 5 frames, a pose 23 m
away), the proposals' cluster loses to it again. So while the localizer is not localized (lost or uncertain), each
recognition is also evidence in its own right: ``place_log_factor`` weighs every particle by how well its position
agrees with the place's recorded poses (a bounded likelihood: at most ``max_odds`` between a particle at the place
and one far from it, scaled by the loop's probability). Repeated recognitions of the same place add up as
consecutive heatlines do; a wrong recognition costs the true hypothesis at most log(``max_odds``) nats a frame, and
none while the localizer is localized.

The loop's belief is the loop-closure MRF's max-marginal log-odds (``LoopClosure.beliefs``); its probability is
the logistic of it.
"""

from __future__ import annotations

import math
from dataclasses import asdict

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from semloc_core.geometry import wrap_angle
from semloc_core.localization.health import LocalizationState
from semloc_core.settings import settings

# Places beyond which a particle's nearest one is found by a k-d tree rather than a loop over them (a decision may
# carry 1e5 loops: the loop took 1.5 s for 5,000 particles, the tree 0.05 s; at 10 places the loop is 5x quicker:
# benchmarks/place_weighing.py)
TREE_PLACES = 64


@settings
class PlaceProposalConfig:
    """How many poses a recognised place proposes, and how far from its recorded poses."""

    max_share: float = Field(0.2, ge=0, lt=0.5, description="at most this share of max_particles per "
                             "recognition, at loop probability 1 (a minority: a wrong place costs little)")
    min_probability: float = Field(0.5, ge=0, le=1, description="loops less probable than this propose nothing")
    position_std: float | None = Field(None, gt=0, description="how far (m) from a recorded pose the place is "
                                       "seen again (one standard deviation, per axis; default: the filter's "
                                       "converged_xy_std, the scale it calls one position)")
    heading_std: float = Field(math.radians(20.0), gt=0, description="... and turned (rad)")
    min_interval: int = Field(10, ge=1, description="corrections between two injections: the heatlines weigh one "
                              "before the next (injections at a wrong place every frame add up)")
    max_odds: float = Field(9.0, ge=1, description="while not localized, each recognition also weighs the "
                            "particles: one far from every recorded pose of the place loses at most this factor "
                            "against one at it, at loop probability 1 (the filter's convergence odds; 1: off). A "
                            "wrong recognition costs the true hypothesis at most log(max_odds) nats a frame")

    def to_dict(self) -> dict:
        return asdict(self)


class PlaceProposer:
    """``place_proposals`` at most once every ``min_interval`` corrections (``step``: the correction's number).
    Its only state is the step of the last injection (``last_step``; snapshot it with the filter)."""

    def __init__(self, config: PlaceProposalConfig | None = None):
        self.config = config or PlaceProposalConfig()
        self.last_step: int | None = None

    def restart(self) -> None:
        """The localizer restarted without its pose: a place may propose at once (the interval spaces injections into
        one hypothesis; a restarted filter has none)."""
        self.last_step = None

    def propose(self, step: int, place_poses, beliefs, max_particles: int, rng: np.random.Generator,
                position_std: float = 0.5, estimate=None) -> np.ndarray:
        if self.last_step is not None and 0 <= step - self.last_step < self.config.min_interval:
            return np.zeros((0, 3))
        proposals = place_proposals(place_poses, beliefs, max_particles, self.config, rng, position_std, estimate)
        if proposals.shape[0]:
            self.last_step = int(step)
        return proposals

    def recognised(self, step: int, particle_filter, place_poses, beliefs, state: LocalizationState,
                   rng: np.random.Generator, place_std: float, estimate_pose) -> tuple[int, bool]:
        """What a recognised place does to the filter, as the worker and the evaluation apply it: while ``state`` is
        lost, a minority of particles drawn around its recorded poses (``propose``); while it is not localized, the
        particles weighed by their agreement with it (``weigh``). Returns (particles injected, whether weighed)."""
        injected = 0
        if state is LocalizationState.LOST:
            proposals = self.propose(step, place_poses, beliefs, particle_filter.config.max_particles, rng,
                                     particle_filter.config.converged_xy_std, estimate_pose)
            injected = particle_filter.inject(proposals)
        weighed = state is not LocalizationState.LOCALIZED and self.weigh(particle_filter, place_poses, beliefs,
                                                                          place_std)
        return injected, weighed

    def weigh(self, particle_filter, place_poses, beliefs, place_std: float) -> bool:
        """Weigh ``particle_filter``'s particles by ``place_log_factor`` (while not localized, at every recognition:
        repeated recognitions add up like consecutive heatlines; ``place_std``: ``HealthMonitor.place_std``). A place
        with a recorded pose within ``place_std`` of the estimate, whose hypothesis holds the filter's converged
        share of the weight, adds nothing: the filter already holds it (weighing there changed the course of a lap
        without a kidnapping). Returns whether the weights changed."""
        if not particle_filter.initialized:
            return False
        place_poses, _, usable = _usable_places(place_poses, beliefs, self.config)
        estimate = particle_filter.estimate()
        if (estimate.cluster_weight >= particle_filter.config.converged_cluster_weight and usable.any()
                and np.hypot(*(place_poses[usable, :2] - estimate.pose[:2]).T).min() < place_std):
            return False
        factor = place_log_factor(particle_filter.states, place_poses, beliefs, self.config, place_std)
        if factor is None:
            return False
        particle_filter.reweigh(factor)
        return True


def loop_probability(beliefs) -> np.ndarray:
    """The probability of each loop from its max-marginal log-odds (the logistic function)."""
    beliefs = np.asarray(beliefs, dtype=np.float64)
    return 0.5 * (1.0 + np.tanh(0.5 * beliefs))  # = 1 / (1 + exp(-b)), without overflow


def place_proposals(place_poses, beliefs, max_particles: int, config: PlaceProposalConfig,
                    rng: np.random.Generator, position_std: float = 0.5, estimate=None) -> np.ndarray:
    """Poses (M, 3) around the recorded poses of the recognised places (``place_poses`` (K, 3), NaN rows: a
    frame seen while not localized, which proposes nothing), ``beliefs`` (K,) their loops' log-odds. M =
    ``max_share`` x ``max_particles`` x the most probable loop's probability; each pose drawn from a place chosen
    in proportion to its probability, then Gaussian in position (``config.position_std``, else ``position_std``)
    and heading. A place within two standard deviations of ``estimate`` (x, y, θ), in position and heading, has
    nothing to add - the filter already holds it - and proposes nothing: otherwise every loop of a place the filter
    has just been brought to would inject again, and the proposals' own spread would keep the weight split.
    Empty when nothing qualifies."""
    place_poses = np.asarray(place_poses, dtype=np.float64).reshape(-1, 3)
    probability = loop_probability(beliefs).reshape(-1)
    if probability.shape[0] != place_poses.shape[0]:
        raise ValueError(f"{place_poses.shape[0]} place poses for {probability.shape[0]} beliefs")
    usable = np.isfinite(place_poses).all(axis=1) & (probability >= config.min_probability)
    if not usable.any():
        return np.zeros((0, 3))
    std = config.position_std or position_std
    if estimate is not None:
        estimate = np.asarray(estimate, dtype=np.float64).reshape(3)
        near = ((np.hypot(*(place_poses[:, :2] - estimate[:2]).T) < 2 * std)
                & (np.abs(wrap_angle(place_poses[:, 2] - estimate[2])) < 2 * config.heading_std))
        usable &= ~near
    if not usable.any():
        return np.zeros((0, 3))
    poses, probability = place_poses[usable], probability[usable]
    count = int(round(config.max_share * max_particles * float(probability.max())))
    if count == 0:
        return np.zeros((0, 3))
    chosen = rng.choice(poses.shape[0], size=count, p=probability / probability.sum())
    noise = rng.normal(size=(count, 3)) * [std, std, config.heading_std]
    proposals = poses[chosen] + noise
    proposals[:, 2] = wrap_angle(proposals[:, 2])
    return proposals


def place_log_factor(positions, place_poses, beliefs, config: PlaceProposalConfig,
                     place_std: float) -> np.ndarray | None:
    """The log-likelihood factor (N,) a recognised place gives particles at ``positions`` (N, >= 2; x, y first):
    log(1 - p (1 - κ)), κ = max_j exp(-d_j² / 2 s²) over the recorded poses (``place_poses`` (K, 3), NaN rows
    ignored) of loops at least ``min_probability`` probable, d_j the distance to pose j, s = ``place_std``, how far
    from its recorded pose a place is seen again (a panorama is recognised from any heading, so the heading does
    not count), p the most probable loop's probability capped at 1 - 1 / ``max_odds``. A particle at the place keeps
    its weight, one far from it keeps 1 - p, at least 1 / ``max_odds``. None when nothing qualifies or ``max_odds``
    is 1."""
    place_poses, probability, usable = _usable_places(place_poses, beliefs, config)
    if config.max_odds <= 1 or not usable.any():
        return None
    p = min(float(probability[usable].max()), 1.0 - 1.0 / config.max_odds)
    positions = np.asarray(positions, dtype=np.float64)[:, :2]
    places = place_poses[usable, :2]
    if places.shape[0] <= TREE_PLACES:
        nearest = np.full(positions.shape[0], np.inf)
        for x, y in places:
            nearest = np.minimum(nearest, (positions[:, 0] - x) ** 2 + (positions[:, 1] - y) ** 2)
    else:  # each particle's nearest place by a k-d tree, its squared distance the same sum of squares
        closest = places[cKDTree(places).query(positions)[1]]
        nearest = (positions[:, 0] - closest[:, 0]) ** 2 + (positions[:, 1] - closest[:, 1]) ** 2
    kernel = np.exp(-0.5 * nearest / place_std ** 2)
    return np.log1p(-p * (1.0 - kernel))


def _usable_places(place_poses, beliefs, config: PlaceProposalConfig):
    """(place poses (K, 3), their loops' probabilities (K,), which of them count: recorded and at least
    ``min_probability`` probable)."""
    place_poses = np.asarray(place_poses, dtype=np.float64).reshape(-1, 3)
    probability = loop_probability(beliefs).reshape(-1)
    if probability.shape[0] != place_poses.shape[0]:
        raise ValueError(f"{place_poses.shape[0]} place poses for {probability.shape[0]} beliefs")
    return place_poses, probability, np.isfinite(place_poses).all(axis=1) & (probability >= config.min_probability)
