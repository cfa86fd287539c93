"""Kernels that replace a numpy expression give its bits."""

from __future__ import annotations

import math

import numba
import numpy as np

from semloc_core.localization import DifferentialDriveModel, Odometry, OmniDriveModel, _kernels


@numba.njit(cache=True)
def _wrap_all(angles, out):
    for i in range(angles.shape[0]):
        out[i] = _kernels._wrap_angle(angles[i])


def test_wrap_angle_is_numpys_floor_modulo_bit_for_bit():
    rng = np.random.default_rng(0)
    two_pi = 2 * math.pi
    edges = np.array([0.0, -0.0, math.pi, -math.pi, two_pi - math.pi, -two_pi - math.pi, 3 * math.pi, -3 * math.pi,
                      7 * math.pi, -7 * math.pi, 1e300, -1e300, 5e-324, -5e-324, np.nan, np.inf, -np.inf])
    near_edges = np.concatenate([np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf)])
    angles = np.concatenate([rng.uniform(-20, 20, 200_000), rng.uniform(-4, 4, 200_000), edges, near_edges,
                             math.pi * rng.integers(-9, 9, 1000)])
    out = np.empty_like(angles)
    _wrap_all(angles, out)
    with np.errstate(invalid="ignore"):
        expected = (angles + math.pi) % (2 * math.pi) - math.pi
    same = (out.view(np.int64) == expected.view(np.int64)) | (np.isnan(out) & np.isnan(expected))
    assert same.all(), angles[~same][:5]


def test_motion_models_are_their_numpy_expressions_bit_for_bit():
    """Eq. 4.5 and the omni model written in numpy with the same draws: the kernels give the same bits."""
    rng = np.random.default_rng(1)
    states = np.column_stack([rng.uniform(-5, 5, 20_000), rng.uniform(-5, 5, 20_000),
                              rng.uniform(-math.pi, math.pi, 20_000)])
    states[:4, 2] = [math.pi - 1e-12, -math.pi, np.nextafter(math.pi, 0), 0.0]
    for odometry in (Odometry.from_velocity(0.5, 0.1, 0.1), Odometry.from_velocity(0.2, -3.0, 0.5),
                     Odometry(0.0, 0.0, 0.0, 0.1)):
        model = DifferentialDriveModel()
        moved = model.sample(states, odometry, 1.0, np.random.default_rng(2))
        v, omega = odometry.velocity
        speed_std = math.sqrt(model.alpha3 * v * v + model.alpha4 * omega * omega) + model.min_speed_std
        turn_std = math.sqrt(model.alpha1 * omega * omega + model.alpha2 * v * v) + model.min_rotation_std
        draws = np.random.default_rng(2)
        speed = v + draws.normal(0.0, speed_std, states.shape[0])
        turn = (omega + draws.normal(0.0, turn_std, states.shape[0])) * odometry.dt
        heading = states[:, 2] + turn / 2
        expected = np.column_stack([states[:, 0] + speed * odometry.dt * np.cos(heading),
                                    states[:, 1] + speed * odometry.dt * np.sin(heading),
                                    (states[:, 2] + turn + math.pi) % (2 * math.pi) - math.pi])
        np.testing.assert_array_equal(moved, expected)

        omni = OmniDriveModel()
        moved = omni.sample(states, odometry, 1.0, np.random.default_rng(3))
        t, r = math.hypot(odometry.dx, odometry.dy), abs(odometry.dtheta)
        t_std = math.sqrt(omni.alpha3 * t * t + omni.alpha4 * r * r) + omni.min_translation_std
        r_std = math.sqrt(omni.alpha1 * r * r + omni.alpha2 * t * t) + omni.min_rotation_std
        draws = np.random.default_rng(3)
        step_x = odometry.dx + draws.normal(0.0, t_std, states.shape[0])
        step_y = odometry.dy + draws.normal(0.0, t_std, states.shape[0])
        dtheta = odometry.dtheta + draws.normal(0.0, r_std, states.shape[0])
        c, s = np.cos(states[:, 2]), np.sin(states[:, 2])
        expected = np.column_stack([states[:, 0] + c * step_x - s * step_y, states[:, 1] + s * step_x + c * step_y,
                                    (states[:, 2] + dtheta + math.pi) % (2 * math.pi) - math.pi])
        np.testing.assert_array_equal(moved, expected)


def test_free_space_without_polygons_is_the_bounds_test():
    from semloc_core.localization import FreeSpace

    rng = np.random.default_rng(4)
    free_space = FreeSpace(np.array([[0.0, -1.0], [10.0, 5.0]]))
    points = np.concatenate([rng.uniform(-2, 12, (5000, 2)), [[0.0, -1.0], [10.0, 5.0], [np.nextafter(10.0, 11), 0.0],
                                                              [np.nan, 0.0], [5.0, np.inf], [-0.0, 0.0]]])
    expected = ((points[:, 0] >= 0.0) & (points[:, 0] <= 10.0) & (points[:, 1] >= -1.0) & (points[:, 1] <= 5.0))
    np.testing.assert_array_equal(free_space.contains(points), expected)


def test_sines_and_cosines_are_numpys_bit_for_bit():
    rng = np.random.default_rng(5)
    theta = np.concatenate([rng.uniform(-math.pi, math.pi, 300_000), rng.uniform(-1e4, 1e4, 20_000),
                            [0.0, -0.0, math.pi, -math.pi, math.pi / 2, 1e-300, 5e-324]])
    sines, cosines = np.empty_like(theta), np.empty_like(theta)
    _kernels.sines_cosines(theta, sines, cosines)
    np.testing.assert_array_equal(sines, np.sin(theta))
    np.testing.assert_array_equal(cosines, np.cos(theta))
