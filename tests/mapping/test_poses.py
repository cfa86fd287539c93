import numpy as np
import pytest

from semloc_core.geometry import make_transform, rotation_about_x, rotation_about_z
from semloc_core.mapping.poses import Match, PoseBuffer, interpolate_pose


def _pose(yaw, x):
    return make_transform(rotation_about_z(yaw) @ rotation_about_x(0.3), (x, 2 * x, 0.5))


def test_interpolation_halfway_is_the_middle_pose():
    T = interpolate_pose(_pose(0.2, 1.0), _pose(0.6, 2.0), 0.5)
    np.testing.assert_allclose(T, _pose(0.4, 1.5), atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(_pose(0.2, 1.0), _pose(0.6, 2.0), 0.0), _pose(0.2, 1.0), atol=1e-12)


def test_lookup_exact_interpolated_waiting_and_missing():
    buffer = PoseBuffer(capacity=4, tolerance_ns=100)
    assert buffer.lookup(5)[0] is Match.WAIT
    buffer.add(100, _pose(0.0, 0.0))
    buffer.add(150, _pose(0.5, 1.0))
    match, T = buffer.lookup(150)
    assert match is Match.FOUND and np.array_equal(T, _pose(0.5, 1.0))
    match, T = buffer.lookup(125)
    assert match is Match.FOUND
    np.testing.assert_allclose(T, _pose(0.25, 0.5), atol=1e-12)
    assert buffer.lookup(151)[0] is Match.WAIT  # no pose after it yet
    assert buffer.lookup(99)[0] is Match.MISSING  # older than the buffer
    buffer.add(400, _pose(1.0, 2.0))  # a gap wider than the tolerance
    assert buffer.lookup(300)[0] is Match.MISSING
    assert buffer.lookup(180)[0] is Match.FOUND  # near enough to the pose at 150
    for stamp in (500, 600, 700):
        buffer.add(stamp, _pose(0.0, 0.0))
    assert len(buffer) == 4 and buffer.newest_stamp == 700


def test_bad_pose_is_refused():
    with pytest.raises(ValueError, match="4x4"):
        PoseBuffer().add(0, np.full((4, 4), np.nan))
