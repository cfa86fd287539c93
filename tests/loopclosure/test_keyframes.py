"""Key-frame choice for loop closure (semloc_core.loopclosure.keyframes): the motion gates as AMCL's, the image
change, the rate bound; and the evaluation's key-frame subsequence against its dataset's ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.localization.motion import Odometry
from semloc_core.loopclosure.keyframes import (KeyframeParams, appearance_change, keyframe_reason, select_keyframes,
                                               thumbnail)
from tests.loopclosure.test_worker import STEP, WIDTH, _wall

MOTION_ONLY = KeyframeParams(min_change=None)


def _line(n: int, step: float, turn: float = 0.0) -> np.ndarray:
    """Poses along a path: each frame ``step`` m forward and ``turn`` rad left of the previous one."""
    poses = np.zeros((n, 3))
    for i in range(1, n):
        x, y, theta = poses[i - 1]
        poses[i] = [x + step * math.cos(theta), y + step * math.sin(theta), theta + turn]
    return poses


@pytest.mark.parametrize("step, turn, every", [(0.051, 0.0, 4), (0.0, math.radians(5.1), 6), (0.5, 0.0, 1)])
def test_motion_gates_open_every_min_distance_or_min_turn(step, turn, every):
    n = 25
    kept = select_keyframes(np.arange(n) / 30.0, _line(n, step, turn), [None] * n, MOTION_ONLY)
    assert kept.tolist() == list(range(0, n, every))


def test_without_motion_or_change_only_the_first_frame_is_a_keyframe():
    wall = _wall()
    image = wall[:, :WIDTH]
    n = 20
    assert select_keyframes(np.arange(n) / 30.0, np.zeros((n, 3)), [thumbnail(image)] * n,
                            KeyframeParams()).tolist() == [0]


def test_image_change_alone_follows_the_view():
    # A camera panning along a wall without odometry: 5-pixel steps of a 160-pixel view are one view; a key-frame
    # comes once the view has moved on (each one then far from its predecessor, none far from its successor).
    wall = _wall()
    xs = list(range(0, 600, 5))
    thumbs = [thumbnail(wall[:, x : x + WIDTH]) for x in xs]
    params = KeyframeParams()
    kept = select_keyframes(np.arange(len(xs)) / 30.0, None, thumbs, params)
    assert 0 == kept[0] and 5 <= len(kept) <= len(xs) // 2
    gaps = np.diff([xs[k] for k in kept])
    assert gaps.min() >= 10 and gaps.max() <= STEP
    for a, b in zip(kept[:-1], kept[1:]):
        assert appearance_change(thumbs[a], thumbs[b]) >= params.min_change
        assert appearance_change(thumbs[a], thumbs[b - 1]) < params.min_change


def test_min_interval_bounds_the_keyframe_rate_at_camera_rate():
    # 30 fps, every frame a new view and a long way on: at most one key-frame per 0.25 s.
    rng = np.random.default_rng(0)
    n = 90
    thumbs = [thumbnail(rng.integers(0, 255, (48, 64), np.uint8)) for _ in range(n)]
    stamps = np.arange(n) / 30.0
    kept = select_keyframes(stamps, _line(n, 1.0), thumbs, KeyframeParams(min_interval_s=0.25))
    assert np.all(np.diff(stamps[kept]) >= 0.25 - 1e-9)
    assert len(kept) == math.ceil(n / 8)  # every 8th frame: 8 / 30 s is the first interval >= 0.25 s


def test_reasons_and_checks():
    params = KeyframeParams()
    assert keyframe_reason(params, None, None, None) == "first"
    assert keyframe_reason(params, 1.0, Odometry(0.15, 0.15, 0.0, 1.0), None) == "distance"
    assert keyframe_reason(params, 1.0, Odometry(0.0, 0.0, -0.6, 1.0), None) == "turn"
    assert keyframe_reason(params, 1.0, Odometry(0.0, 0.0, 2 * math.pi, 1.0), None) is None  # a full turn: back
    assert keyframe_reason(params, 1.0, Odometry(0.1, 0.0, 0.1, 1.0), 0.6) == "appearance"
    assert keyframe_reason(params, 1.0, Odometry(0.1, 0.0, 0.1, 1.0), 0.3) is None
    # time no odometry covers: how far the body went is unknown, whatever the motion it did see - a key-frame when
    # the most it can have gone then would open a motion gate
    still = Odometry(0.0, 0.0, 0.0, 1.0)
    assert keyframe_reason(params, 1.0, still, 0.0, (0.2, 0.0)) == "odometry_gap"
    assert keyframe_reason(params, 1.0, still, 0.0, (0.0, 0.6)) == "odometry_gap"
    assert keyframe_reason(params, 1.0, still, 0.0, (0.19, 0.5)) is None  # (microseconds of jitter, say)
    assert keyframe_reason(KeyframeParams(min_interval_s=2.0), 1.0, still, 0.0, (9.0, 9.0)) is None
    assert keyframe_reason(KeyframeParams(min_distance=None, min_turn=None), 1.0, still, 0.0, (9.0, 9.0)) is None
    assert np.all(thumbnail(np.full((10, 10), 7, np.uint8)) == 0)  # a flat image: nothing to correlate
    for bad in ({"min_distance": 0.0}, {"min_turn": -1.0}, {"min_change": math.nan}, {"min_interval_s": -1.0}):
        with pytest.raises(ValueError):
            KeyframeParams(**bad)
    with pytest.raises(ValueError):
        thumbnail(np.zeros((1, 5)))
