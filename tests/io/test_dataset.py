"""Dataset readers: the simulator's layout round trip, real image folders, TUM and RGB-D Scenes pose files."""

import json

import cv2
import numpy as np
import pytest

from semloc_core.geometry import make_transform, quaternion_to_rotation, rotation_about_x, rotation_about_z
from semloc_core.io.dataset import (
    Dataset,
    DatasetError,
    Odometry,
    increment_to_twist,
    open_dataset,
    relative_increments,
    twist_to_increment,
)
from semloc_core.io.trajectory import (
    TrajectoryFormatError,
    gravity_from_camera_poses,
    level_real_trajectory,
    read_rgbd_scenes_poses,
    read_tum,
    write_tum,
)
from tests.conftest import shared_path


def test_simulated_dataset_round_trip(sim_scenario, sim_dataset):
    scenario = sim_scenario("tabletop", frames=8, seed=5)
    folder = sim_dataset("tabletop", frames=8, seed=5)
    d = open_dataset(folder)
    assert len(d) == 8 and d.name == "tabletop"
    for i in (0, 7):
        assert np.array_equal(d.image(i), scenario.image(i))
        assert d.visible_objects(i) == scenario.visible_objects(i)
    np.testing.assert_array_equal(d.stamps_ns, scenario.stamps_ns)
    np.testing.assert_allclose(d.T_world_body, scenario.T_world_body)
    np.testing.assert_allclose(d.T_body_cam, scenario.T_body_cam)
    np.testing.assert_allclose(d.T_world_cam, scenario.T_world_cam)
    np.testing.assert_allclose(d.poses2d, scenario.poses2d)
    np.testing.assert_allclose(d.odometry.as_array(), scenario.odometry.as_array())
    np.testing.assert_array_equal(d.loop_gt, scenario.loop_gt)
    np.testing.assert_array_equal(d.loop_gt_soft, scenario.loop_gt_soft)
    assert d.semantic_map.to_document() == scenario.semantic_map.to_document()
    np.testing.assert_allclose(d.camera.K, scenario.camera.K)
    assert set(d.exemplars()) == set(scenario.world.class_names)
    for name, masks in d.exemplar_masks().items():
        assert np.array_equal(masks[0], scenario.exemplar_masks()[name][0])
        assert masks[0].shape == d.exemplars()[name][0].shape[:2]
    # The TUM file agrees with the poses (evo reads it).
    stamps, T = read_tum(folder / "groundtruth.txt")
    np.testing.assert_allclose(T, scenario.T_world_cam, atol=1e-6)
    np.testing.assert_allclose(stamps, scenario.stamps_ns / 1e9)


def test_multiview_exemplars_round_trip(sim_scenario, tmp_path):
    from semloc_core.io.dataset import read_multiview_folder, write_multiview_folder

    views = sim_scenario("hall", frames=2, seed=0).multiview_exemplars()
    assert set(views) == {"clock", "trashcan", "payphone", "ticket_machine"}
    write_multiview_folder(tmp_path, views)
    back = read_multiview_folder(tmp_path)
    for name, class_views in views.items():
        assert len(back[name]) == len(class_views) == 24
        for a, b in zip(class_views, back[name]):
            assert np.array_equal(a.image, b.image) and np.array_equal(a.mask, b.mask)
            assert abs(a.azimuth - b.azimuth) < 1e-9 and abs(a.elevation - b.elevation) < 1e-9
        # Views from different sides differ (the objects are not billboards).
        assert not np.array_equal(class_views[0].image, class_views[6].image)


def test_image_folder_with_loop_matrix(tmp_path):
    (tmp_path / "images").mkdir()
    for k in range(1, 13):
        cv2.imwrite(str(tmp_path / "images" / f"{k}.jpg"), np.full((24, 32, 3), 10 * k, np.uint8))
    gt = np.zeros((12, 12), np.uint8)
    gt[10, 2] = gt[11, 3] = 255
    cv2.imwrite(str(tmp_path / "samples_GT.bmp"), gt)
    d = open_dataset(tmp_path)
    assert len(d) == 12 and d.has_images and not d.has_poses
    # Natural order: 2.jpg comes before 10.jpg.
    assert d.image(1)[0, 0, 0] == 20 and d.image(9)[0, 0, 0] == 100
    assert d.loop_gt[10, 2] and d.loop_gt[2, 10] and d.loop_gt.sum() == 4
    assert d.metadata["camera_assumed"] and d.camera.width == 32
    with pytest.raises(DatasetError, match="no ground-truth poses"):
        _ = d.poses2d
    cv2.imwrite(str(tmp_path / "samples_GT.bmp"), np.zeros((5, 5), np.uint8))
    with pytest.raises(DatasetError, match="does not match"):
        open_dataset(tmp_path)


def test_rtabmap_loop_samples():
    folder = shared_path("rtabmap_loop_samples")
    d = open_dataset(folder)
    assert len(d) == 84 and d.image(0).shape == (384, 512, 3)
    assert np.tril(d.loop_gt, -1).sum() == 228 and np.array_equal(d.loop_gt, d.loop_gt.T)


def test_tum_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.stack([make_transform(rotation_about_z(a) @ rotation_about_x(b), rng.normal(size=3))
                      for a, b in rng.uniform(-3, 3, (6, 2))])
    write_tum(tmp_path / "t.txt", np.arange(6) * 0.1, poses)
    stamps, back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back, poses, atol=1e-8)
    d = open_dataset(tmp_path / "t.txt")
    np.testing.assert_allclose(d.T_world_cam, poses, atol=1e-8)
    assert d.stamps_ns[1] == 100_000_000
    (tmp_path / "bad.txt").write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(TrajectoryFormatError, match="8 numbers"):
        read_tum(tmp_path / "bad.txt")
    (tmp_path / "nan.txt").write_text("0 1 2 nan 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match="non-finite"):
        read_tum(tmp_path / "nan.txt")


def test_gravity_and_table_of_a_synthetic_handheld_circle():
    """Cameras circling a table, looking down at it, expressed in a tilted first-camera frame: recover up."""
    rng = np.random.default_rng(1)
    from semloc_core.sim.trajectories import look_at

    T_world = np.stack([look_at((1.1 * np.cos(a), 1.1 * np.sin(a), 1.2 + 0.03 * rng.normal()),
                                (0.1 * rng.normal(), 0.1 * rng.normal(), 0.8), roll=0.02 * rng.normal())
                        for a in np.linspace(0, 5, 200)])
    T_ref_world = np.linalg.inv(T_world[0])
    T_ref = T_ref_world @ T_world
    up_ref = gravity_from_camera_poses(T_ref)
    np.testing.assert_allclose(up_ref, T_ref_world[:3, :3] @ [0, 0, 1], atol=0.03)
    T_level, table = level_real_trajectory(T_ref, surface_z=0.75)
    # Heights above the table are preserved, the table is under the gaze, the cameras circle it.
    np.testing.assert_allclose(T_level[:, 2, 3] - 0.75, T_world[:, 2, 3] - 0.75, atol=0.08)
    radius = np.linalg.norm(T_level[:, :2, 3] - table["centre"], axis=1)
    assert np.all(np.abs(radius - 1.1) < 0.2)


@pytest.mark.parametrize("scene", ["01", "05", "13"])
def test_rgbd_scenes_poses_are_levelled(scene):
    path = shared_path("rgbd_scenes_v2_poses", f"{scene}.pose")
    T = read_rgbd_scenes_poses(path)
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-9)
    d = open_dataset(path)
    cams = d.T_world_cam
    # Level: roll stays small and the camera looks down at the table from above it.
    x_axes = cams[:, :3, 0]
    assert np.percentile(np.abs(np.degrees(np.arcsin(x_axes[:, 2]))), 95) < 8
    assert np.median(cams[:, 2, 3]) > 0.75 + 0.2
    assert np.median(cams[:, 2, 2]) < -0.1
    # The first camera looks along +x.
    assert cams[0, 0, 2] > 0.9 * np.hypot(cams[0, 0, 2], cams[0, 1, 2])


def test_odometry_twist_algebra():
    rng = np.random.default_rng(2)
    inc = np.column_stack([rng.normal(size=50), rng.normal(size=50), rng.uniform(-3, 3, 50)])
    inc[0, 2] = 0.0
    np.testing.assert_allclose(twist_to_increment(*increment_to_twist(inc).T), inc, atol=1e-12)
    poses = np.cumsum(rng.normal(size=(20, 3)) * 0.3, axis=0)
    o = Odometry(*increment_to_twist(relative_increments(poses)).T, np.ones(20))
    out = o.integrate(poses[0])
    np.testing.assert_allclose(out[:, :2], poses[:, :2], atol=1e-9)


def test_dataset_checks_shapes():
    with pytest.raises(DatasetError, match="T_world_body"):
        Dataset("x", 3, T_world_body=np.zeros((2, 4, 4)))
    with pytest.raises(DatasetError, match="loop_gt"):
        Dataset("x", 3, loop_gt=np.zeros((3, 2)))
    d = Dataset("x", 2)
    with pytest.raises(DatasetError, match="no images"):
        d.image(0)
    with pytest.raises(DatasetError, match="not exist"):
        open_dataset("/nonexistent/path")


def test_corrupt_dataset_json_is_reported(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(DatasetError, match="not a semloc.dataset"):
        open_dataset(tmp_path)
    (tmp_path / "dataset.json").write_text("{")
    with pytest.raises(DatasetError, match="cannot read"):
        open_dataset(tmp_path)
    assert quaternion_to_rotation([0, 0, 0, 1]).shape == (3, 3)
