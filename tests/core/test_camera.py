import numpy as np
import pytest

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.camera import (
    CameraRig,
    EquirectangularCamera,
    PinholeCamera,
    column_bearings,
    pixel_bearings,
    project_body,
    rays_body,
)
from semloc_core.geometry import (
    invert_transform,
    level_frame_of_camera,
    make_transform,
    quaternion_to_rotation,
    rotation_about_y,
    rotation_about_z,
    rotation_to_quaternion,
    transform_to_pose2d,
    wrap_angle,
)

CAMERAS = [
    PinholeCamera.from_fov(640, 480, 60.0),
    PinholeCamera(640, 480, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), dist=[-0.2, 0.05, 0.001, 0.001]),
    EquirectangularCamera(1024, 256),
]


@pytest.mark.parametrize("camera", CAMERAS, ids=["pinhole", "pinhole-distorted", "equirect"])
def test_project_inverts_rays(camera):
    rng = np.random.default_rng(0)
    u = rng.uniform(5, camera.width - 5, 200)
    v = rng.uniform(5, camera.height - 5, 200)
    depth = rng.uniform(0.5, 20.0, 200)[:, None]
    points = rays_body(camera, u, v) * depth
    uv, visible = project_body(camera, points)
    assert visible.all()
    np.testing.assert_allclose(uv[:, 0], u, atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], v, atol=1e-3)


def test_pinhole_bearing_sign_and_fov():
    camera = PinholeCamera.from_fov(640, 480, 90.0)
    bearings = column_bearings(camera)
    # Centre column looks forward; the right edge is at -45 degrees (clockwise), the left edge at +45.
    assert abs(bearings[320]) < np.radians(0.2)
    assert bearings[0] == pytest.approx(np.radians(45.0), abs=np.radians(0.2))
    assert bearings[-1] == pytest.approx(np.radians(-45.0), abs=np.radians(0.2))
    assert camera.horizontal_fov == pytest.approx(np.pi / 2)


def test_equirect_covers_full_turn_and_points_behind():
    camera = EquirectangularCamera(360, 90)
    bearings = column_bearings(camera)
    assert np.allclose(np.diff(np.unwrap(bearings)), -np.radians(1.0))
    behind = np.array([[-5.0, 0.0, 0.0]])
    uv, visible = project_body(camera, behind)
    assert visible[0] and (uv[0, 0] < 1 or uv[0, 0] > 358)


def test_rig_members_cover_their_sectors():
    rig = CameraRig.ring(5, 320, 240, 72.0)
    for k, camera in enumerate(rig.cameras):
        centre = column_bearings(camera)[160]
        assert wrap_angle(centre - 2 * np.pi * k / 5) == pytest.approx(0.0, abs=np.radians(0.3))


def test_pitched_camera_bearings_use_extrinsic():
    # A camera pitched down 30 degrees: rays through the same column but different rows share one bearing only when
    # the extrinsic is accounted for.
    T = make_transform(rotation_about_y(np.radians(30.0)) @ CAMERAS[0].T_body_cam[:3, :3], (0, 0, 1.0))
    camera = PinholeCamera.from_fov(640, 480, 60.0, T_body_cam=T)
    point = np.array([[2.0, -1.0, 0.0]])  # on the floor, to the right
    uv, visible = project_body(camera, point)
    assert visible[0]
    bearings = pixel_bearings(camera)
    u, v = np.round(uv[0]).astype(int)
    assert bearings[v, u] == pytest.approx(np.arctan2(-1.0, 2.0), abs=np.radians(0.3))


def test_quaternion_roundtrip_and_transforms():
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quaternion_to_rotation(q)
        assert np.allclose(R @ R.T, np.eye(3))
        q2 = rotation_to_quaternion(R)
        assert np.allclose(q2, q if q[3] >= 0 else -q, atol=1e-9)
        T = make_transform(R, rng.normal(size=3))
        assert np.allclose(T @ invert_transform(T), np.eye(4))


def test_level_frame_and_pose2d():
    T_world_cam = make_transform(
        rotation_about_z(0.7) @ rotation_about_y(np.radians(25)) @ CAMERAS[0].T_body_cam[:3, :3], (1, 2, 1.5)
    )
    pose = transform_to_pose2d(level_frame_of_camera(T_world_cam))
    assert pose == pytest.approx([1, 2, 0.7])


def test_bearing_grid_and_heatlines_validate():
    grid = BearingGrid(360)
    assert grid.index(np.array([-np.pi, 0.0, np.pi - 1e-9, np.pi]))[:3].tolist() == [0, 180, 359]
    assert grid.index(np.pi) == 0  # pi wraps to -pi
    with pytest.raises(ValueError, match="finite"):
        Heatlines(("a",), np.full((1, 360), np.nan), np.ones(360, bool))
    with pytest.raises(ValueError, match="n_classes"):
        Heatlines(("a", "b"), np.zeros((1, 360)), np.ones(360, bool))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(width=0, height=10, K=np.eye(3)), "positive"),
        (dict(width=10, height=10, K=np.zeros((3, 3))), "focal"),
        (dict(width=10, height=10, K=np.eye(3), dist=[0.1, 0.2, 0.3]), "distortion"),
        (dict(width=10, height=10, K=np.eye(3), T_body_cam=np.eye(3)), "4x4"),
        (dict(width=10, height=10, K=np.eye(3), T_body_cam=np.diag([1, 1, -1, 1.0])), "rotation"),
    ],
)
def test_pinhole_rejects_bad_parameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PinholeCamera(**kwargs)
