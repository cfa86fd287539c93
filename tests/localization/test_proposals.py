"""Recognised places propose poses (semloc_core.localization.proposals, ParticleFilter.inject): a kidnapping the
filter alone does not recover from is recovered at the first recognised place; a wrong place costs nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.localization.health import HealthConfig, LocalizationState
from semloc_core.localization.proposals import PlaceProposalConfig, PlaceProposer, loop_probability, place_proposals
from tests.localization.test_filter import _filter
from tests.localization.test_health import _monitored
from tests.localization.worlds import kidnapped, tabletop

CONFIG = PlaceProposalConfig(position_std=0.05, heading_std=math.radians(10))


def _run_with_places(world, particle_filter, recognise, seed=0):
    """Filter + monitor along the world (test_health); the poses recorded while localized form the places;
    ``recognise(k, recorded)`` -> (place poses, beliefs) recognised at frame k (or None). Returns errors, states,
    the frames with injections."""
    proposal_rng, proposer = np.random.default_rng(seed + 300), PlaceProposer(CONFIG)
    recorded = np.full((world.poses.shape[0], 3), np.nan)  # the hybrid map: each frame's pose while localized
    injections = []

    def after_step(k, estimate, state):
        if state is LocalizationState.LOCALIZED:
            recorded[k] = estimate.pose
        recognised = recognise(k, recorded)
        if recognised is not None and state is LocalizationState.LOST:
            poses = proposer.propose(k, *recognised, particle_filter.config.max_particles, proposal_rng,
                                     estimate=estimate.pose)
            if particle_filter.inject(poses):
                injections.append(k)

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


def test_a_wrong_place_costs_nothing_while_tracking_and_little_when_lost():
    """Places recognised in the wrong spot (half a turn away, probability ~0.95): while localized nothing is
    injected; during a global initialisation they are weighed like any particle and the filter converges anyway."""
    world = tabletop(frames=200, seed=2)

    def wrong(k, recorded):
        return world.poses[(k + 100) % 200][None], np.array([3.0])

    particle_filter = _filter(world)
    particle_filter.initialize_global()
    errors, states, injections = _run_with_places(world, particle_filter, wrong)
    assert injections  # while initialising
    assert errors[-100:].max() < 0.1 and states[-1] == "localized"
    assert not [k for k in injections if states[k] == "localized"]


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
