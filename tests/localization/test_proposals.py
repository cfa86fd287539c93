"""Recognised places propose poses (semloc_core.localization.proposals, ParticleFilter.inject): a kidnapping the
filter alone does not recover from is recovered at the first recognised place; a wrong place costs nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.localization.evaluation import first_settled
from semloc_core.localization.health import HealthConfig, LocalizationState
from semloc_core.localization.proposals import (PlaceProposalConfig, PlaceProposer, loop_probability, place_log_factor,
                                               place_proposals)
from tests.localization.test_filter import _filter
from tests.localization.test_health import _monitored
from tests.localization.worlds import kidnapped, tabletop

CONFIG = PlaceProposalConfig(position_std=0.05, heading_std=math.radians(10))
PLACE_STD = 0.5  # HealthMonitor.place_std at the table top's converged_xy_std (0.1 m)


def _run_with_places(world, particle_filter, recognised_place, seed=0, weigh=True):
    """Filter + monitor along the world (test_health); the poses recorded while localized form the places;
    ``recognised_place(k, recorded)`` -> (place poses, beliefs) recognised at frame k (or None), which while lost
    proposes poses and, while not localized (``weigh``), weighs the particles, as the evaluation and the worker do.
    Returns errors, states, the frames with injections."""
    proposal_rng, proposer = np.random.default_rng(seed + 300), PlaceProposer(CONFIG)
    recorded = np.full((world.poses.shape[0], 3), np.nan)  # the hybrid map: each frame's pose while localized
    injections = []

    def after_step(k, estimate, state):
        if state is LocalizationState.LOCALIZED:
            recorded[k] = estimate.pose
        recognised = recognised_place(k, recorded)
        if recognised is not None and state is LocalizationState.LOST:
            poses = proposer.propose(k, *recognised, particle_filter.config.max_particles, proposal_rng,
                                     estimate=estimate.pose)
            if particle_filter.inject(poses):
                injections.append(k)
        if weigh and recognised is not None and state is not LocalizationState.LOCALIZED:
            proposer.weigh(particle_filter, *recognised, place_std=PLACE_STD)

    errors, _, states = _monitored(world, particle_filter, seed, after_step)
    return errors, states, injections


def _nearest_earlier(world, at):
    """A place recognition stand-in: the earlier frame (before the kidnapping) nearest the true pose."""
    def recognise(k, recorded):
        if k <= at:
            return None
        distances = np.hypot(*(world.poses[:at, :2] - world.poses[k, :2]).T)
        earlier = int(np.argmin(distances))
        return (recorded[earlier:earlier + 1], np.array([3.0])) if distances[earlier] < 0.1 else None
    return recognise


def test_a_recognised_place_recovers_a_kidnapping_the_filter_alone_does_not():
    """Recovery off: alone the filter stays on the old track (test_filter); the monitor says lost, the place the
    robot was carried to was recorded on the first lap, and its proposals bring the estimate back."""
    world = kidnapped(tabletop(frames=300, seed=3), at=150)
    particle_filter = _filter(world, recovery_alpha_slow=0.0)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.02, 0.02, 0.05]) ** 2)
    errors, states, injections = _run_with_places(world, particle_filter, _nearest_earlier(world, 150))
    assert errors[140:150].max() < 0.06 and errors[151] > 0.5
    # lost once a pose near the truth has been followed for rival_frames (test_health); injected at the next loop
    lost = states.index("lost", 150)
    assert lost <= 150 + HealthConfig().rival_frames and injections and injections[0] == lost
    recovered = 150 + int(np.argmax(errors[150:] < 0.1))
    assert recovered <= lost + 10 and errors[recovered:].max() < 0.1, np.round(errors[150:180], 2)
    assert states[-1] == "localized"


@pytest.mark.parametrize("weigh, every", [(False, 1), (True, 2)])
def test_a_wrong_place_costs_nothing_while_tracking_and_little_when_lost(weigh, every):
    """Places recognised in the wrong spot (half a turn away, probability ~0.95; with the weighing at every other
    frame): while localized nothing is injected; during a global initialisation they are weighed like any particle
    and the filter converges anyway."""
    world = tabletop(frames=200, seed=2)

    def wrong(k, recorded):
        return (world.poses[(k + 100) % 200][None], np.array([3.0])) if k % every == 0 else None

    particle_filter = _filter(world)
    particle_filter.initialize_global()
    errors, states, injections = _run_with_places(world, particle_filter, wrong, weigh=weigh)
    assert injections  # while initialising
    assert errors[-100:].max() < 0.1 and states[-1] == "localized"
    assert not [k for k in injections if states[k] == "localized"]


def test_a_place_wrong_at_every_frame_holds_the_filter_off_and_says_lost():
    """The weighing's limit: a place recognised wrongly at every frame at ~0.95 costs the true pose 2.2 nats a frame
    while the state is not localized, as much as these heatlines give it, so the filter does not settle - and the
    state says so."""
    world = tabletop(frames=200, seed=2)
    particle_filter = _filter(world)
    particle_filter.initialize_global()
    errors, states, _ = _run_with_places(world, particle_filter,
                                         lambda k, recorded: (world.poses[(k + 100) % 200][None], np.array([3.0])))
    assert first_settled(errors, 0.1, 10) is None and np.mean(errors[-100:] > 0.5) > 0.5 and states[-1] == "lost"


def test_proposals_scale_with_the_loop_probability_and_skip_unrecorded_places():
    rng = np.random.default_rng(0)
    config = PlaceProposalConfig(max_share=0.2, position_std=0.1, heading_std=0.1)
    assert loop_probability([0.0, 50.0, -800.0]) == pytest.approx([0.5, 1.0, 0.0])
    places = np.array([[1.0, 2.0, 0.5], [np.nan] * 3])
    sure = place_proposals(places, [10.0, 10.0], 10_000, config, rng)
    assert sure.shape == (2000, 3) and np.allclose(sure.mean(axis=0), [1.0, 2.0, 0.5], atol=0.02)
    assert place_proposals(places, [np.log(3.0), 10.0], 10_000, config, rng).shape == (1500, 3)
    assert place_proposals(places, [-1.0, 10.0], 10_000, config, rng).shape == (0, 3)  # improbable
    assert place_proposals(places[1:], [10.0], 10_000, config, rng).shape == (0, 3)  # never recorded
    with pytest.raises(ValueError, match="beliefs"):
        place_proposals(places, [1.0], 100, config, rng)
    # a place the estimate is already at proposes nothing; one elsewhere (or turned away) does
    assert place_proposals(places, [10.0, 10.0], 10_000, config, rng, estimate=[1.1, 2.1, 0.6]).shape == (0, 3)
    assert place_proposals(places, [10.0, 10.0], 10_000, config, rng, estimate=[1.5, 2.0, 0.5]).shape == (2000, 3)
    assert place_proposals(places, [10.0, 10.0], 10_000, config, rng, estimate=[1.0, 2.0, 2.5]).shape == (2000, 3)
    default_std = place_proposals(places, [10.0, 10.0], 10_000, PlaceProposalConfig(), rng, position_std=0.05)
    assert 0.04 < default_std[:, 0].std() < 0.06
    # at most one injection every min_interval corrections
    proposer = PlaceProposer(PlaceProposalConfig(min_interval=3))
    counts = [len(proposer.propose(step, places, [10.0, 10.0], 100, rng)) for step in range(7)]
    assert counts == [20, 0, 0, 20, 0, 0, 20]


def test_inject_keeps_the_majority_resampled_and_marks_the_proposals():
    world = tabletop(frames=10, seed=1)
    particle_filter = _filter(world, max_particles=1000, min_particles=100)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.01, 0.01, 0.01]) ** 2, n=300)
    assert particle_filter.inject(np.tile([1.0, 1.0, 7.0], (800, 1))) == 500  # at most half the set
    assert particle_filter.states.shape == (1000, 3) and particle_filter._injected.sum() == 500
    assert np.all(np.abs(particle_filter.states[:, 2]) <= math.pi)
    with pytest.raises(ValueError, match="finite"):
        particle_filter.inject([[np.nan, 0.0, 0.0]])


def test_a_place_weighs_particles_by_their_distance_from_its_poses_at_bounded_odds():
    config = PlaceProposalConfig(max_odds=9.0)
    places = np.array([[1.0, 2.0, 0.5], [np.nan] * 3, [5.0, 2.0, -3.0]])
    particles = np.array([[1.0, 2.0, 2.0], [1.0, 2.5, 0.0], [5.0, 2.0, 0.0], [30.0, -8.0, 1.0]])
    sure = place_log_factor(particles, places, [20.0, 20.0, 20.0], config, place_std=0.5)
    # at a recorded pose (any heading) nothing lost; one std away exp(-1/2) of the way; far: the odds' floor
    assert sure[0] == pytest.approx(0.0) and sure[2] == pytest.approx(0.0)
    assert sure[1] == pytest.approx(math.log(1 - 8 / 9 * (1 - math.exp(-0.5))))
    assert sure[3] == pytest.approx(math.log(1 / 9.0))
    # the loop's probability below the cap scales the factor; improbable or unrecorded places weigh nothing
    unsure = place_log_factor(particles, places, [math.log(3.0), -5.0, -5.0], config, place_std=0.5)
    assert unsure[3] == pytest.approx(math.log(0.25)) and unsure[0] == pytest.approx(0.0)
    assert place_log_factor(particles, places, [-1.0, 20.0, -1.0], config, 0.5) is None
    assert place_log_factor(particles, places, [20.0] * 3, PlaceProposalConfig(max_odds=1.0), 0.5) is None
    with pytest.raises(ValueError, match="beliefs"):
        place_log_factor(particles, places, [1.0], config, 0.5)


def test_a_place_of_many_loops_weighs_each_particle_by_its_nearest_pose():
    """A decision may carry up to 1e5 loops (schemas.loopclosure.MAX_CANDIDATES): each particle's factor is that of
    its nearest recorded pose, as the direct minimum over every pose gives it."""
    rng = np.random.default_rng(4)
    places = np.column_stack([rng.uniform(-5, 5, (3000, 2)), rng.uniform(-3, 3, 3000)])
    places[::7] = np.nan  # not recorded
    beliefs = rng.uniform(-2.0, 6.0, 3000)
    particles = np.column_stack([rng.uniform(-6, 6, (800, 2)), np.zeros(800)])
    config = PlaceProposalConfig(max_odds=9.0)
    factor = place_log_factor(particles, places, beliefs, config, place_std=0.2)
    usable = np.isfinite(places[:, 0]) & (loop_probability(beliefs) >= config.min_probability)
    squared = ((particles[:, None, :2] - places[None, usable, :2]) ** 2).sum(axis=2).min(axis=1)
    p = min(float(loop_probability(beliefs[usable]).max()), 1 - 1 / 9.0)
    np.testing.assert_allclose(factor, np.log1p(-p * (1 - np.exp(-0.5 * squared / 0.2 ** 2))), rtol=1e-12, atol=1e-15)


def test_reweigh_multiplies_the_weights_and_moves_the_estimate():
    world = tabletop(frames=10, seed=1)
    particle_filter = _filter(world, max_particles=1000, min_particles=100)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.01, 0.01, 0.01]) ** 2, n=500)
    particle_filter.inject(np.tile(world.poses[0] + [1.0, 0.0, 0.0], (400, 1)))  # a second hypothesis 1 m away
    assert particle_filter.estimate().cluster_weight == pytest.approx(0.6, abs=0.01)
    proposer = PlaceProposer(PlaceProposalConfig(max_odds=9.0))
    assert proposer.weigh(particle_filter, world.poses[:1] + [1.0, 0.0, 0.0], [20.0], place_std=0.1)
    estimate = particle_filter.estimate()  # the place's hypothesis now holds 0.4 x 9 against 0.6
    assert estimate.cluster_weight == pytest.approx(3.6 / 4.2, abs=0.01)
    assert np.hypot(*(estimate.pose[:2] - world.poses[0, :2] - [1.0, 0.0])) < 0.05
    assert not proposer.weigh(particle_filter, world.poses[:1], [-5.0], place_std=0.1)  # improbable: no change
    with pytest.raises(ValueError, match="finite"):
        particle_filter.reweigh(np.full(particle_filter.states.shape[0], np.nan))
