"""Which localized estimates the places keep (semloc_core.localization.place_poses): a filter wrong for a stretch
that the monitor calls localized until its rivals have weighed it leaves no pose of that stretch recorded, and a
good track is still recorded."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.localization.health import HealthConfig
from semloc_core.localization.place_poses import PlacePoseConfig, PoseRecorder
from tests.localization.test_filter import _filter
from tests.localization.test_health import _monitored
from tests.localization.worlds import kidnapped, tabletop


def _recorded(states, poses, config: PlacePoseConfig) -> np.ndarray:
    """The poses (T, 3; NaN: none) the places keep of ``poses`` judged ``states`` frame by frame."""
    recorder = PoseRecorder(config)
    recorded = np.full((len(states), 3), np.nan)
    for k, (state, pose) in enumerate(zip(states, poses)):
        committed, retracted = recorder.update(k, pose, state == "localized", state == "initialising")
        for key, kept in committed:
            recorded[key] = kept
        recorded[retracted] = np.nan
    return recorded


@pytest.mark.parametrize("seed, at", [(3, 150), (4, 120)])
def test_a_stretch_the_filter_is_wrong_on_while_still_localized_is_not_recorded(seed, at):
    """Recovery off: after the kidnapping the filter stays converged on the old track, and the monitor calls it
    localized until its rivals have followed a pose near the truth for rival_frames frames. Recorded at once, those
    frames leave wrong poses in the places; committed after rival_frames, none; the track before is recorded."""
    world = kidnapped(tabletop(frames=260, seed=seed), at=at)
    particle_filter = _filter(world, recovery_alpha_slow=0.0)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.02, 0.02, 0.05]) ** 2)
    estimates = []
    errors, _, states = _monitored(world, particle_filter,
                                   after_step=lambda k, estimate, state: estimates.append(estimate.pose))
    assert errors[at + 10:].min() > 0.5  # wrong after the kidnapping, and the filter does not know
    wrong = [k for k in range(at, len(states)) if states[k] == "localized"]
    assert wrong, "the monitor flags the kidnapping at once: nothing to test"

    def errors_of(recorded):
        kept = np.isfinite(recorded).all(axis=1)
        return np.hypot(*(recorded[kept, :2] - world.poses[kept, :2]).T), kept

    at_once, _ = errors_of(_recorded(states, estimates, PlacePoseConfig(commit_after=0, retract=False)))
    assert (at_once > 0.5).any()  # the earlier rule records the wrong stretch
    delayed, kept = errors_of(_recorded(states, estimates, PlacePoseConfig(retract=False)))
    assert delayed.size and delayed.max() < 0.5, delayed.max()
    # the good track before is kept but for its last rival_frames frames, pending when the kidnapping ended it
    good = [k for k in range(at) if states[k] == "localized"]
    assert kept[:at].sum() >= len(good) - HealthConfig().rival_frames - 1
    # retracting the stretch the kidnapping ended withdraws that good track too, and records nothing wrong
    retracted, _ = errors_of(_recorded(states, estimates, PlacePoseConfig(retract=True)))
    assert retracted.size < delayed.size and (retracted < 0.5).all()


@pytest.mark.parametrize("commit_after, retract, states, kept", [
    (0, False, "LLLuLL", [0, 1, 2, 4, 5]),  # the earlier rule: every localized estimate at once
    (2, False, "LLLLuLL", [0, 1]),  # committed once followed by two localized; pending ones dropped
    (2, True, "LLLLuLLLL", [5, 6]),  # the stretch ending in uncertain withdraws what it committed
    (2, True, "LLLLLLLL", [0, 1, 2, 3, 4, 5]),  # the last two wait for their confirmation
    (0, True, "LLuL", [3]),
    (2, True, "LLLLiLLLL", [0, 1, 5, 6]),  # a restart without the pose is no evidence against the stretch
])
def test_commit_after_and_retract(commit_after, retract, states, kept):
    poses = np.column_stack([np.arange(len(states)), np.zeros(len(states)), np.zeros(len(states))]).astype(float)
    named = {"L": "localized", "u": "uncertain", "i": "initialising"}
    recorded = _recorded([named[s] for s in states], poses,
                         PlacePoseConfig(commit_after=commit_after, retract=retract))
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == kept
    assert np.array_equal(recorded[kept], poses[kept])


def test_commit_after_defaults_to_the_monitors_window_and_snapshots_round_trip():
    assert PoseRecorder().commit_after == HealthConfig().rival_frames
    assert PoseRecorder(rival_frames=4).commit_after == 4
    assert PoseRecorder(PlacePoseConfig(commit_after=2), rival_frames=4).commit_after == 2
    recorder = PoseRecorder(PlacePoseConfig(commit_after=3))
    for k in range(5):
        recorder.update(k, (k, 0.0, 0.0), True)
    restored = PoseRecorder(PlacePoseConfig(commit_after=3))
    restored.restore(recorder.snapshot())
    assert [k for k, _ in restored.pending] == [2, 3, 4] and restored.stretch == [0, 1]
    assert restored.update(5, (5, 0.0, 0.0), True)[0][0][0] == 2
    assert restored.update(6, (6, 0.0, 0.0), False) == ([], [0, 1, 2])
    with pytest.raises(ValueError, match="finite"):
        restored.restore({"pending": [[1, [np.nan, 0.0, 0.0]]]})
    with pytest.raises(ValueError, match="commit_after"):
        PlacePoseConfig(commit_after=-1)
