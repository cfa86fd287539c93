"""The backward filter pass (semloc_core.localization.smoothing): from a localized stretch, a second filter run back
over the frames the live filter was wrong on keeps the true pose there; only its first localized stretch counts; it
never changes the live filter's course; its memory is capped."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from semloc_core.localization import Status
from semloc_core.localization.health import HealthMonitor, LocalizationState, Verdict, judge
from semloc_core.localization.filter import PoseEstimate, compose_motion
from semloc_core.localization.smoothing import BackwardPass, BackwardSmoother, PastFrame, SmoothingConfig
from tests.localization.test_filter import _filter
from tests.localization.worlds import kidnapped, tabletop


def _live(world, start_wrong: bool = True, config: SmoothingConfig | None = SmoothingConfig(), frames=None):
    """The live filter along ``world`` (started tight at the pose mirrored through the table's centre: wrong until
    its recovery finds the truth), judged by its monitor, feeding a smoother; returns the live estimates, states
    and the passes that ended (anchor, reason, poses)."""
    particle_filter = _filter(world)
    if start_wrong:
        wrong = world.poses[0] * [-1.0, -1.0, 1.0]
        particle_filter.initialize_pose(wrong, np.diag([0.02, 0.02, 0.05]) ** 2)
    else:
        particle_filter.initialize_global()
    monitor = HealthMonitor.for_filter(particle_filter.config)
    smoother = None if config is None else BackwardSmoother(
        config, lambda rng: _filter(world, seed=rng), lambda: HealthMonitor.for_filter(particle_filter.config),
        monitor.config.rival_frames, np.random.default_rng(7))
    rng, probes = np.random.default_rng(100), np.random.default_rng(200)
    estimates, states, ended = [], [], []
    for k in range(frames or world.poses.shape[0]):
        heatlines, odometry = world.heatlines(k), world.odometry(k, rng)
        estimate = particle_filter.step(heatlines, odometry, world.dt)
        moved = None if odometry is None else (odometry.dx, odometry.dy, odometry.dtheta)
        verdict = judge(monitor, particle_filter, estimate, heatlines, None, probes, moved)
        estimates.append(estimate.pose)
        states.append(verdict.state.value)
        if smoother is not None:
            smoother.record(PastFrame(k, heatlines, None, moved, world.dt),
                            verdict.state is LocalizationState.LOCALIZED,
                            estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING), particle_filter.snapshot)
            ended += smoother.advance()
    if smoother is not None:
        ended += smoother.finish()
    return np.asarray(estimates), states, ended


@pytest.mark.parametrize("seed, kidnap_at, reason", [
    (3, None, "oldest stored frame"),  # back to the first frame (less the last commit_after)
    (5, 60, "after its first stretch"),  # the pass loses the pose on the way back: its first stretch only
])
def test_the_pass_fills_the_frames_the_live_filter_was_wrong_on_with_the_true_pose(seed, kidnap_at, reason):
    world = tabletop(frames=300, seed=seed)
    if kidnap_at is not None:
        world = kidnapped(world, kidnap_at)
    estimates, states, ended = _live(world)
    errors = np.hypot(*(estimates[:, :2] - world.poses[:, :2]).T)
    anchor = states.index("localized", 10)  # the first stretch after the recovery (0-9: the wrong start's)
    assert (errors[:anchor - 20] > 1.0).all()  # the live filter is wrong over the frames before
    passes = [(a, r, poses) for a, r, poses in ended if a == anchor]
    assert len(passes) == 1
    _, stop, poses = passes[0]
    assert reason in stop
    keys = [k for k, _, _ in poses]
    assert len(keys) >= 30 and keys == list(range(keys[0], keys[0] - len(keys), -1)) and keys[0] < anchor
    filled = np.array([pose for _, pose, _ in poses])
    assert np.hypot(*(filled[:, :2] - world.poses[keys, :2]).T).max() < 0.5
    assert all(np.allclose(c, c.T) for _, _, c in poses)


def test_the_pass_never_changes_the_live_filter():
    world = tabletop(frames=200, seed=3)
    with_pass, states, ended = _live(world)
    without, states_without, _ = _live(world, config=None)
    assert ended and ended[0][2]  # a pass ran and filled frames
    assert np.array_equal(with_pass, without) and states == states_without


def test_max_frames_caps_how_far_back_a_pass_reaches():
    world = tabletop(frames=200, seed=3)
    _, states, ended = _live(world, config=SmoothingConfig(max_frames=40))
    anchor, _, poses = ended[0]
    assert poses and min(k for k, _, _ in poses) >= anchor - 40 + 1


class _Scripted:
    """A filter and monitor playing back verdicts ('L' localized, 'u' uncertain, 'x' lost), one per step."""

    def __init__(self, script: str):
        self.script = iter(script)
        self.perception, self.free_space = None, None
        self.config = SimpleNamespace(lost_ratio=0.5)
        self.moves = []

    def step(self, heatlines, odometry, dt, view=None):
        self.moves.append((odometry.dx, odometry.dy, odometry.dtheta, dt))
        return PoseEstimate(np.zeros(3), np.eye(3) * 1e-4, Status.CONVERGED, 100, 100.0, 1.0, 1, 1.0)

    def update(self, estimate, margin, place_poses=None, lost_ratio=0.5, moved=None):
        state = {"L": LocalizationState.LOCALIZED, "u": LocalizationState.UNCERTAIN,
                 "x": LocalizationState.LOST}[next(self.script)]
        return Verdict(state, state, "scripted", margin)


@pytest.mark.parametrize("script, unknown_at, commit_after, kept, reason", [
    ("xxLLLLuLLL", None, 0, [7, 6, 5, 4], "uncertain after its first stretch"),  # the first stretch only
    ("xxLLLLxLLL", None, 2, [7, 6], "lost after its first stretch"),  # less its last commit_after
    ("LLLLLLLLLL", None, 3, [9, 8, 7, 6, 5, 4, 3], "oldest stored frame"),
    ("LLLLLLLLLL", 6, 0, [9, 8, 7, 6], "unknown odometry"),  # no pose over an unknown motion
])
def test_the_first_rule(script, unknown_at, commit_after, kept, reason):
    frames = [PastFrame(k, None, None, None if k == unknown_at else (0.1, 0.0, 0.05), 0.1) for k in range(11)]
    scripted = _Scripted(script)
    backward = BackwardPass(scripted, scripted, frames, np.random.default_rng(0), commit_after)
    while not backward.done:
        backward.step()
    assert [k for k, _, _ in backward.poses()] == kept and reason in backward.stop_reason
    undo = scripted.moves[0]  # the odometry inverted: u then u⁻¹ is no motion, over u's dt
    assert np.allclose(compose_motion(np.array([0.1, 0.0, 0.05]), np.array(undo[:3])), 0.0, atol=1e-12)
    assert undo[3] == 0.1
