"""Which localized estimates the places keep (semloc_core.localization.place_poses): a filter wrong for a stretch
that the monitor calls localized until its rivals have weighed it leaves no pose of that stretch recorded, and a
good track is still recorded."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.localization import Odometry, Status
from semloc_core.localization.health import HealthConfig, HealthMonitor
from semloc_core.localization.filter import compose_motion
from semloc_core.localization.motion import OmniDriveModel
from semloc_core.localization.place_poses import PlacePoseConfig, PoseRecorder
from tests.localization.test_filter import _filter
from tests.localization.test_health import _monitored
from tests.localization.worlds import kidnapped, tabletop


def _recorded(states, poses, config: PlacePoseConfig, moved=None, scale=(), dt=None, motion=None) -> np.ndarray:
    """The poses (T, 3; NaN: none) the places keep of ``poses`` judged ``states`` frame by frame; ``moved``: the
    odometry before each frame (None: none), over ``dt`` seconds (None: unknown, nothing carried back)."""
    recorder = PoseRecorder(config, *(scale or (None, None, None)))
    recorded = np.full((len(states), 3), np.nan)
    for k, (state, pose) in enumerate(zip(states, poses)):
        step = None if moved is None or k == 0 else moved[k]
        noise = None if motion is None or step is None or dt is None else motion.increment_std(Odometry(*step, dt))
        committed, retracted = recorder.update(k, pose, state == "localized", state == "initialising", step, dt=dt,
                                               motion_std=noise)
        for key, kept in committed:
            recorded[key] = kept
        recorded[retracted] = np.nan
    return recorded


def _lap(world, particle_filter):
    """The filter and its monitor along ``world``: estimates, states (initialising where the filter is), the
    odometry before each frame (noise-free) and the monitor."""
    estimates, states = [], []

    def after_step(k, estimate, state):
        estimates.append(estimate.pose)
        states.append("initialising" if estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING)
                      else state.value)

    errors, _, _ = _monitored(world, particle_filter, after_step=after_step)
    steps = [Odometry.between(world.poses[k - 1], world.poses[k], world.dt) for k in range(1, len(states))]
    moved = [None] + [(0.0, 0.0, 0.0) if k in world.teleports else (step.dx, step.dy, step.dtheta)
                      for k, step in enumerate(steps, 1)]  # the odometry sees no teleport
    return np.asarray(estimates), states, moved, errors, HealthMonitor.for_filter(particle_filter.config)


def _kept_errors(world, recorded):
    kept = np.isfinite(recorded).all(axis=1)
    return np.hypot(*(recorded[kept, :2] - world.poses[kept, :2]).T), kept


@pytest.mark.parametrize("commit_after", [0, None])
def test_a_stretch_the_filter_abandons_for_another_hypothesis_is_withdrawn(commit_after):
    """Kidnapped, the filter stays localized on the old track until the monitor's rivals say lost, then its recovery
    brings it back localized at the truth, off the old track by the odometry: the stretch is withdrawn - its wrong
    frames after the teleport (recorded at once, they are kept) and, the cost of a kidnapping, its good track
    before - and the track after the recovery kept."""
    at = 150
    world = kidnapped(tabletop(frames=300, seed=3), at=at)
    particle_filter = _filter(world)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.02, 0.02, 0.05]) ** 2)
    estimates, states, moved, errors, monitor = _lap(world, particle_filter)
    scale = (monitor.config.rival_frames, monitor.elsewhere_xy, monitor.elsewhere_theta)
    assert any(states[k] == "localized" and errors[k] > 0.5 for k in range(at, len(states)))
    back = next(k for k in range(at, len(states)) if states[k] == "localized" and errors[k] < 0.1)
    assert errors[back:].max() < 0.1  # recovered

    at_once, _ = _kept_errors(world, _recorded(states, estimates, PlacePoseConfig(commit_after=0, retract=False),
                                               moved, scale))
    assert (at_once > 0.5).any()  # the earlier rule keeps the wrong frames
    kept_errors, kept = _kept_errors(world, _recorded(states, estimates, PlacePoseConfig(commit_after=commit_after),
                                                      moved, scale))
    assert kept_errors.size and kept_errors.max() < 0.1
    assert not kept[:back].any()
    good = [k for k in range(back, len(states)) if states[k] == "localized"]
    assert kept[back:].sum() >= len(good) - monitor.config.rival_frames


@pytest.mark.parametrize("seed, at", [(3, 150), (4, 120)])
def test_a_kidnapping_the_filter_does_not_notice_leaves_no_wrong_pose(seed, at):
    """Recovery off: after the kidnapping the filter stays converged on the old track, and the monitor calls it
    localized until its rivals have followed a pose near the truth for rival_frames frames. Recorded at once, those
    frames leave wrong poses in the places; committed after rival_frames, none, and the track before stays (the
    filter never comes back localized elsewhere)."""
    world = kidnapped(tabletop(frames=260, seed=seed), at=at)
    particle_filter = _filter(world, recovery_alpha_slow=0.0)
    particle_filter.initialize_pose(world.poses[0], np.diag([0.02, 0.02, 0.05]) ** 2)
    estimates, states, moved, errors, monitor = _lap(world, particle_filter)
    scale = (monitor.config.rival_frames, monitor.elsewhere_xy, monitor.elsewhere_theta)
    assert errors[at + 10:].min() > 0.5 and any(states[k] == "localized" for k in range(at, len(states)))
    at_once, _ = _kept_errors(world, _recorded(states, estimates, PlacePoseConfig(commit_after=0, retract=False),
                                               moved, scale))
    assert (at_once > 0.5).any()
    delayed, kept = _kept_errors(world, _recorded(states, estimates, PlacePoseConfig(), moved, scale))
    assert delayed.size and delayed.max() < 0.5, delayed.max()
    good = [k for k in range(at) if states[k] == "localized"]
    assert kept[:at].sum() >= len(good) - monitor.config.rival_frames - 1


@pytest.mark.parametrize("commit_after, retract, states, jump, kept", [
    (0, False, "LLLuLL", 0, [0, 1, 2, 4, 5]),  # the earlier rule: every localized estimate at once
    (2, False, "LLLLuLL", 5, [0, 1]),  # committed once followed by two localized; pending ones dropped
    (2, True, "LLLLuLLLL", 0, [0, 1, 5, 6]),  # back on the same track (a false alarm): kept
    (2, True, "LLLLuLLLL", 5, [5, 6]),  # back elsewhere: the stretch is withdrawn
    (2, True, "LLLLuLLLL", -0.2, [0, 1, 5, 6]),  # within same_track_xy (0.3 m) of the track
    (2, True, "LLLLuLLLLuLLLL", 0, [0, 1, 5, 6, 10, 11]),  # one track over two false alarms
    (2, True, "LLLLLLLL", 5, [0, 1, 2, 3, 4, 5]),  # the last two wait for their confirmation
    (0, True, "LLuL", 5, [3]),
    (2, True, "LLLLiLLLL", 5, [0, 1, 5, 6]),  # a restart without the pose is no evidence against the stretch
])
def test_commit_after_and_retract(commit_after, retract, states, jump, kept):
    """A track along x at 0.1 m a frame, the odometry exact; after the first gap the estimates are ``jump`` m off
    the track."""
    n = len(states)
    truth = np.column_stack([0.1 * np.arange(n), np.zeros(n), np.zeros(n)])
    gap = next((k for k, s in enumerate(states) if s != "L"), n)
    poses = truth + np.where(np.arange(n) > gap, jump, 0.0)[:, None] * [1.0, 0.0, 0.0]
    named = {"L": "localized", "u": "uncertain", "i": "initialising"}
    recorded = _recorded([named[s] for s in states], poses,
                         PlacePoseConfig(commit_after=commit_after, retract=retract, same_track_xy=0.3),
                         moved=[(0.1, 0.0, 0.0)] * n)
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == kept
    assert np.array_equal(recorded[kept], poses[kept])
    # without odometry across the gap the stretch is not judged: kept
    unjudged = _recorded([named[s] for s in states], poses, PlacePoseConfig(commit_after=commit_after,
                                                                             retract=retract))
    assert set(kept) <= set(np.flatnonzero(np.isfinite(unjudged).all(axis=1)))


def test_defaults_are_the_monitors_and_snapshots_round_trip():
    assert PoseRecorder().commit_after == HealthConfig().rival_frames
    assert PoseRecorder(rival_frames=4).commit_after == 4
    assert PoseRecorder(PlacePoseConfig(commit_after=2), rival_frames=4).commit_after == 2
    assert PoseRecorder(elsewhere_xy=0.3).same_track_xy == 0.3
    assert PoseRecorder(PlacePoseConfig(same_track_xy=0.2), elsewhere_xy=0.3).same_track_xy == 0.2
    recorder = PoseRecorder(PlacePoseConfig(commit_after=3))
    for k in range(5):
        recorder.update(k, (k, 0.0, 0.0), True)
    restored = PoseRecorder(PlacePoseConfig(commit_after=3))
    restored.restore(recorder.snapshot())
    assert [k for k, _, _ in restored.pending] == [2, 3, 4] and restored.stretch == [0, 1]
    assert restored.update(5, (5, 0.0, 0.0), True)[0][0][0] == 2
    assert restored.update(6, (6, 0.0, 0.0), False, moved=(1.0, 0.0, 0.0)) == ([], [])  # judged at the next
    again = PoseRecorder(PlacePoseConfig(commit_after=3))
    again.restore(restored.snapshot())
    assert again.update(7, (9, 0.0, 0.0), True, moved=(1.0, 0.0, 0.0)) == ([], [0, 1, 2])  # 2 m off the track
    with pytest.raises(ValueError, match="finite"):
        restored.restore({"pending": [[1, [np.nan, 0.0, 0.0]]]})
    with pytest.raises(ValueError, match="commit_after"):
        PlacePoseConfig(commit_after=-1)


def test_a_track_kept_over_a_false_alarm_is_withdrawn_with_the_stretch_that_abandons_it():
    """Stretches 0-3 and 5-8 on one track (back on it after the first gap), then the filter comes back 5 m off:
    both go, as one hypothesis."""
    states = ["localized"] * 4 + ["lost"] + ["localized"] * 4 + ["lost"] + ["localized"] * 4
    poses = np.column_stack([0.1 * np.arange(14), np.zeros(14), np.zeros(14)])
    poses[10:, 0] += 5.0
    recorded = _recorded(states, poses, PlacePoseConfig(commit_after=2, same_track_xy=0.3),
                         moved=[(0.1, 0.0, 0.0)] * 14)
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == [10, 11]


@pytest.mark.parametrize("spread, kept", [(0.05, [5, 6]), (0.2, [0, 1, 5, 6])])
def test_the_same_track_reaches_three_spreads_of_the_hypotheses(spread, kept):
    """Back 0.5 m off the carried track: another hypothesis for a tight one (3 x 0.05 m, at least same_track_xy
    0.3 m), the same track for one 0.2 m wide (0.6 m), as the monitor counts a rival beyond three spreads."""
    states = ["localized"] * 4 + ["lost"] + ["localized"] * 4
    poses = np.column_stack([0.1 * np.arange(9), np.zeros(9), np.zeros(9)])
    poses[5:, 0] += 0.5
    recorder = PoseRecorder(PlacePoseConfig(commit_after=2, same_track_xy=0.3))
    recorded = np.full((9, 3), np.nan)
    for k, (state, pose) in enumerate(zip(states, poses)):
        committed, retracted = recorder.update(k, pose, state == "localized", moved=(0.1, 0.0, 0.0),
                                               spread=(spread, 0.01))
        for key, value in committed:
            recorded[key] = value
        recorded[retracted] = np.nan
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == kept


def test_a_global_start_gets_the_first_localized_pose_carried_back_along_the_odometry():
    """Started globally, the filter searches before it is localized: those frames hold no pose until the first
    stretch commits, then its first pose carried back along the (noisy) odometry gives them poses as close to the
    truth as a localized estimate (the converged spread), as far as the filter's motion noise allows."""
    world = tabletop(frames=200, seed=3)
    particle_filter = _filter(world)
    particle_filter.initialize_global()
    estimates, states, moved, errors, monitor = _lap(world, particle_filter)
    scale = (monitor.config.rival_frames, monitor.elsewhere_xy, monitor.elsewhere_theta)
    first = states.index("localized")
    assert first > 5 and errors[first] < 0.1
    without = _recorded(states, estimates, PlacePoseConfig(backfill=False), moved, scale, world.dt,
                        particle_filter.motion)
    recorded = _recorded(states, estimates, PlacePoseConfig(), moved, scale, world.dt, particle_filter.motion)
    assert not np.isfinite(without[:first]).any()
    filled = np.flatnonzero(np.isfinite(recorded[:first]).all(axis=1))
    assert filled.size >= 5 and filled[-1] == first - 1
    errors_filled, _ = _kept_errors(world, np.where(np.isfinite(without), np.nan, recorded))
    assert errors_filled.max() < particle_filter.config.converged_xy_std, errors_filled.max()


EXACT = OmniDriveModel(0.0, 0.0, 0.0, 0.0, min_translation_std=1e-4, min_rotation_std=1e-4)


@pytest.mark.parametrize("states, jump, motion, kept, shifted", [
    ("uuuLLLL", 0, EXACT, [0, 1, 2, 3, 4], []),  # before the first stretch
    ("LLLLuuLLLL", 0, EXACT, [0, 1, 4, 5, 6, 7], []),  # the gap; not the dropped pending (localized) 2-3
    ("LLLLuuLLLL", 5, EXACT, [4, 5, 6, 7], [4, 5, 6, 7]),  # nor the withdrawn stretch (a kidnapping or not)
    ("LLLLiiLLLL", 5, EXACT, [0, 1, 4, 5, 6, 7], [4, 5, 6, 7]),  # not over a restart
    ("uuuuuuuLLLL", 0, OmniDriveModel(0.0, 0.0, 0.0, 0.0, min_translation_std=0.045, min_rotation_std=0.0),
     [3, 4, 5, 6, 7, 8], []),  # within the converged spread: 4 x 0.045² < 0.1² < 5 x 0.045²
])
def test_backfill(states, jump, motion, kept, shifted):
    """A track along x at 0.1 m a frame, the odometry exact; after the first gap the estimates are ``jump`` m off
    the track (``shifted``: the kept poses that are)."""
    n = len(states)
    truth = np.column_stack([0.1 * np.arange(n), np.zeros(n), np.zeros(n)])
    gap = next((k for k, s in enumerate(states) if s != "L"), n)
    poses = truth + np.where(np.arange(n) > gap, jump, 0.0)[:, None] * [1.0, 0.0, 0.0]
    named = {"L": "localized", "u": "uncertain", "i": "initialising"}
    config = PlacePoseConfig(commit_after=2, same_track_xy=0.3)
    recorded = _recorded([named[s] for s in states], poses, config, [(0.1, 0.0, 0.0)] * n, dt=0.1, motion=motion)
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == kept
    expected = truth + np.isin(np.arange(n), shifted)[:, None] * [jump, 0.0, 0.0]
    assert np.allclose(recorded[kept], expected[kept])
    # unknown dt (the noise unknown): nothing carried back
    plain = _recorded([named[s] for s in states], poses, config, [(0.1, 0.0, 0.0)] * n, motion=motion)
    assert set(np.flatnonzero(np.isfinite(plain).all(axis=1))) < set(kept)


def test_backfilled_poses_are_withdrawn_with_their_stretch_and_snapshots_keep_them():
    """Frames 0-1 are filled from stretch 2-5; the filter comes back 5 m off at 7: 0-3 withdrawn together, and the
    new stretch carries its own pose back to the lost frames 6 and 0-1, past the withdrawn localized 2-5."""
    recorder = PoseRecorder(PlacePoseConfig(commit_after=2, same_track_xy=0.3))
    states = [False, False, True, True, True, True, False, True, True, True]
    noise = EXACT.increment_std(Odometry(0.1, 0.0, 0.0, 0.1))
    out = []
    for k, localized in enumerate(states):
        pose = (0.1 * k + (5.0 if k >= 7 else 0.0), 0.0, 0.0)
        out.append(recorder.update(k, pose, localized, moved=None if k == 0 else (0.1, 0.0, 0.0), dt=0.1,
                                   motion_std=noise))
        if k == 4:
            assert recorder.last_backfilled == [1, 0]
            restored = PoseRecorder(PlacePoseConfig(commit_after=2, same_track_xy=0.3))
            restored.restore(recorder.snapshot())
            assert [e[:3] for e in restored.recent] == [e[:3] for e in recorder.recent]
            recorder = restored
    assert sorted(out[7][1]) == [0, 1, 2, 3]
    assert [k for k, _ in out[9][0]] == [6, 1, 0, 7]
    with pytest.raises(ValueError, match="odometry"):
        recorder.restore({"recent": [[0, [0.1, 0.0, float("nan"), 0.1], False]]})


@pytest.mark.parametrize("length, turn", [(2.0, 0.0), (2.0, 0.9), (2.0, -0.9), (4.0, 0.0)])
def test_a_track_that_moves_through_the_gap_is_the_same_track(length, turn):
    """As on the hall's laps: ``length`` m a frame, turning ``turn`` rad a frame, the estimates and the odometry
    exact. A stretch that ends and comes back on the track after a gap is kept, however far the track moved in the
    frame that ended the stretch (farther than the same track's reach, 3 m / 45 deg: its odometry is carried too)."""
    states = ["localized"] * 6 + ["lost"] * 3 + ["localized"] * 6
    step = (length, 0.0, turn)
    poses = [np.zeros(3)]
    for _ in states[1:]:
        poses.append(compose_motion(poses[-1], np.asarray(step)))
    recorded = _recorded(states, np.asarray(poses), PlacePoseConfig(commit_after=2), moved=[step] * len(states),
                         scale=(None, 3.0, np.radians(45)))
    assert np.flatnonzero(np.isfinite(recorded).all(axis=1)).tolist() == [0, 1, 2, 3, 9, 10, 11, 12]


@pytest.mark.parametrize("withdraw, anchor, keys, accepted, refused", [
    (None, 6, [5, 4, 3, 2], [3, 2], {"posed": 2}),  # 4-5 back-filled already
    (None, 0, [3], [], {"anchor": 1}),  # the anchor's stretch was never committed
    (None, 6, [3, 99], [3], {"unknown": 1}),
    ("after", 6, [3, 2], [3, 2], {}),  # withdrawn with the anchor's stretch
    ("before", 6, [3, 2], [], {"anchor": 2}),  # the anchor's stretch was withdrawn already
])
def test_a_backward_pass_fills_unposed_frames_and_its_poses_go_with_the_anchors_stretch(withdraw, anchor, keys,
                                                                                        accepted, refused):
    """Frames 0-1 a short stretch (never committed), 2-5 lost, 6-9 localized (committed from 6, carried back to
    4-5 within the converged spread: 2 x 0.065² < 0.1² < 3 x 0.065²), lost at 10, back localized at 11: on the
    track, or 5 m off (``withdraw``: the stretch is withdrawn after or before the pass's poses arrive)."""
    noisy = OmniDriveModel(0.0, 0.0, 0.0, 0.0, min_translation_std=0.065, min_rotation_std=0.0)
    recorder = PoseRecorder(PlacePoseConfig(commit_after=2, same_track_xy=0.3))
    noise = noisy.increment_std(Odometry(0.1, 0.0, 0.0, 0.1))
    states = [True, True, False, False, False, False, True, True, True, True, False]
    for k, localized in enumerate(states):
        recorder.update(k, (0.1 * k, 0.0, 0.0), localized, moved=None if k == 0 else (0.1, 0.0, 0.0), dt=0.1,
                        motion_std=noise)
        if k == 8:  # the stretch has committed 6 and carried it back
            assert sorted(recorder.last_backfilled) == [4, 5]

    def back_at_11():
        off = 5.0 if withdraw else 0.0
        return recorder.update(11, (1.1 + off, 0.0, 0.0), True, moved=(0.1, 0.0, 0.0), dt=0.1, motion_std=noise)[1]

    retracted = back_at_11() if withdraw == "before" else []
    got, reasons = recorder.fill(anchor, keys)
    assert got == accepted and reasons == refused
    assert recorder.fill(anchor, accepted) == ([], {"posed": len(accepted)} if accepted else {})  # once only
    if withdraw != "before":
        retracted = back_at_11()
    assert set(retracted) == ({4, 5, 6, 7, *accepted} if withdraw else set())


def test_the_localizers_scale_and_noise_come_with_its_estimates():
    """``follow_scale``: the same track reaches three of the localizer's converged spread unless configured; a
    snapshot from before entries carried their noise restores with the default model's; without ``motion_std``
    the default model's wide noise stops the back-fill sooner than the localizer's exact one."""
    recorder = PoseRecorder()
    recorder.follow_scale((0.1, 0.2))
    assert (recorder.same_track_xy, recorder.same_track_theta) == pytest.approx((0.3, 0.6))
    configured = PoseRecorder(PlacePoseConfig(same_track_xy=0.5))
    configured.follow_scale((0.1, 0.2))
    assert (configured.same_track_xy, configured.same_track_theta) == pytest.approx((0.5, 0.6))
    recorder.restore({"recent": [[0, None, False], [1, [0.1, 0.0, 0.0, 0.1], False]]})
    assert len(recorder.recent[1][1]) == 6 and min(recorder.recent[1][1][4:]) > 0
    states = ["uncertain"] * 6 + ["localized"] * 4
    truth = np.column_stack([0.1 * np.arange(10), np.zeros(10), np.zeros(10)])
    config = PlacePoseConfig(commit_after=2, same_track_xy=0.3)
    exact = _recorded(states, truth, config, [(0.1, 0.0, 0.0)] * 10, dt=0.1, motion=EXACT)
    default = _recorded(states, truth, config, [(0.1, 0.0, 0.0)] * 10, dt=0.1)
    assert np.isfinite(exact[:6]).all() and np.isfinite(default[:6]).all(axis=1).sum() < 6


@pytest.mark.parametrize("restart", [True, False])
def test_a_new_run_of_the_estimates_ends_the_stretch_unjudged_and_drops_what_is_pending(restart):
    """Keys 0-5 localized along x (0-3 committed, 4-5 pending), then a new run of the same keys (a session replayed
    again, the robot carried back): uncertain at 0-1, localized 2 m off from 2 on. With ``restart`` between the
    runs, the first run's poses stay and the second commits only its own (0-1 carried back); without it, the first
    run's stretch is judged by the second's estimates and withdrawn (2 m off its track)."""
    recorder = PoseRecorder(PlacePoseConfig(commit_after=2, same_track_xy=0.3))
    first = []
    for k in range(6):
        committed, withdrawn = recorder.update(k, (0.1 * k, 0.0, 0.0), True, moved=None if k == 0 else (0.1, 0.0, 0.0),
                                               dt=0.1)
        first += [key for key, _ in committed]
        assert withdrawn == []
    assert first == [0, 1, 2, 3]
    if restart:
        recorder.restart()
    second, withdrawn = [], []
    for k, localized in enumerate([False, False, True, True, True, True]):
        committed, retracted = recorder.update(k, (2.0 + 0.1 * k, 0.0, 0.0), localized, moved=(0.1, 0.0, 0.0), dt=0.1)
        second += [(key, round(float(pose[0]), 6)) for key, pose in committed]
        withdrawn += retracted
    if restart:
        assert withdrawn == [] and sorted(second) == [(0, 2.0), (1, 2.1), (2, 2.2), (3, 2.3)]
    else:  # the defect the restart removes
        assert withdrawn == [0, 1, 2, 3]
