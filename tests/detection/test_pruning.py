"""Level pruning (issue 35): the rows each pyramid level runs on hold the simulator's objects of that level's size,
and the template detector matched on those rows keeps the exhaustive heatmaps there."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.detection.config import build_detector
from semloc_core.detection.templates import TemplateDetector
from semloc_core.detection.pruning import (PruneParams, build_pruner, class_shapes, grown_polygon, height_from_pose,
                                           work_share)
from semloc_core.experiments.demo_world import DETECTOR
from semloc_core.experiments.tabletop import table_support
from semloc_core.geometry import inside_polygon
from semloc_core.io.dataset import open_dataset

FRAMES = 8


@pytest.fixture(scope="module")
def tabletop(sim_dataset):
    folder = sim_dataset("tabletop", frames=FRAMES, seed=5)
    dataset = open_dataset(folder)
    detector = build_detector({**DETECTOR, "templates": str(folder / "exemplars")})
    support_z, corners = table_support(dataset)
    pruner = build_pruner(detector, dataset.camera, dataset.semantic_map, support_z,
                          float(np.median(dataset.T_world_cam[:, 2, 3])), corners)
    return dataset, detector, pruner


def _seen(dataset, i, classes):
    """The frame's objects of the detector's classes, mostly visible and whole."""
    return [seen for seen in dataset.visible_objects(i)
            if seen.class_name in classes and seen.occluded_fraction <= 0.1 and not seen.truncated]


def _pose_height(dataset, pruner, frame, gap_s=0.0):
    """The camera's height from the frame's true 3-D pose (the detector's ``height_pose``)."""
    return height_from_pose(dataset.T_world_body[frame], dataset.T_body_cam[frame], gap_s, pruner.params)


@pytest.mark.parametrize("height_from", ["configured", "pose"])
@pytest.mark.parametrize("frame", range(0, FRAMES, 2))
def test_each_object_lies_in_the_rows_of_the_level_nearest_its_size(tabletop, frame, height_from):
    dataset, detector, pruner = tabletop
    height = _pose_height(dataset, pruner, frame) if height_from == "pose" else None
    rows = pruner.rows(dataset.poses2d[frame], dataset.T_body_cam[frame], height)
    grid_rows = detector.output_shape((dataset.camera.height, dataset.camera.width))[0]
    objects = _seen(dataset, frame, detector.classes)
    assert objects
    for seen in objects:
        u0, v0, u1, v1 = seen.box
        size = max(u1 - u0, v1 - v0)
        centre_row = (v0 + v1) / 2 * grid_rows / dataset.camera.height
        for level in detector.levels_for(size, size):   # the level nearest the object's true size
            assert level in rows, (seen.class_name, size, rows)
            first, last = rows[level]
            assert first - 1 <= centre_row <= last + 1, (seen.class_name, size, level, centre_row, rows[level])
    assert pruner.share(rows) < 1.0


def test_rows_follow_the_camera_height(tabletop):
    """A camera far above the table sees every object small: the coarse levels (large objects) drop out."""
    dataset, detector, pruner = tabletop
    pose, attitude = dataset.poses2d[0], dataset.T_body_cam[0]
    near = pruner.rows(pose, attitude)
    pruner_high = build_pruner(detector, dataset.camera, dataset.semantic_map, pruner.scene.support_z,
                               pruner.camera_height + 3.0, pruner.scene.polygon)
    far = pruner_high.rows(pose, attitude)
    coarsest = min(detector.match.scales)
    assert coarsest in near and coarsest not in far


def test_the_pose_height_asks_less_and_follows_the_pose(tabletop):
    """The camera's height from its pose, to within a few cm, narrows every frame's rows against the configured
    height +- its tolerance; a pose 3 m higher drops the coarse level (and disagrees with the configured height);
    a pose long before the image, whose tolerance would exceed the configured one, is not used."""
    dataset, detector, pruner = tabletop
    for frame in range(FRAMES):
        pose, attitude = dataset.poses2d[frame], dataset.T_body_cam[frame]
        height = _pose_height(dataset, pruner, frame)
        assert height[0] == pytest.approx(dataset.T_world_cam[frame, 2, 3])
        assert height[1] == pruner.params.pose_height_tolerance
        assert pruner.agrees(height)   # the true height is within the configured one's tolerance
        assert pruner.share(pruner.rows(pose, attitude, height)) <= pruner.share(pruner.rows(pose, attitude))
    pose, attitude = dataset.poses2d[0], dataset.T_body_cam[0]
    high = (_pose_height(dataset, pruner, 0)[0] + 3.0, pruner.params.pose_height_tolerance)
    assert min(detector.match.scales) not in pruner.rows(pose, attitude, high)
    assert not pruner.agrees(high)   # the worker counts it and prunes by the configured height
    stale = _pose_height(dataset, pruner, 0, gap_s=1.0)
    assert stale[1] == pytest.approx(pruner.params.pose_height_tolerance + pruner.params.vertical_speed)
    assert pruner.rows(pose, attitude, (stale[0] + 3.0, stale[1])) == pruner.rows(pose, attitude)
    sigma = 0.05   # a pose's own standard deviation, when larger, sets its accuracy
    assert height_from_pose(dataset.T_world_body[0], attitude, 0.0, pruner.params, sigma)[1] == pytest.approx(0.15)


def test_band_heatmaps_keep_the_exhaustive_heat_inside_and_none_far_outside(tabletop):
    dataset, detector, _ = tabletop
    image = dataset.image(0)
    full = detector.heatmaps(image)
    grid_rows = full.shape[1]
    everywhere = {s: (0, grid_rows) for s in detector.match.scales}
    np.testing.assert_array_equal(detector.heatmaps(image, rows=everywhere), full)
    band = (grid_rows // 3, 2 * grid_rows // 3)
    pruned = detector.heatmaps(image, rows={s: band for s in detector.match.scales})
    reach = math.ceil((max(max(t.shape) for t in detector.templates) // 2 + 1) / min(detector.match.scales)) + 1
    inside = slice(band[0] + reach, band[1] - reach)
    # the features' normalisation is the band's own (its 99th percentile of block energy): close, not equal
    np.testing.assert_allclose(pruned[:, inside], full[:, inside], atol=0.06)
    assert np.abs(pruned[:, inside] - full[:, inside]).mean() < 0.01
    assert not pruned[:, :max(0, band[0] - 2 * reach)].any()
    assert (pruned >= 0).all() and (pruned <= 1).all()


def test_pruned_levels_on_threads_give_the_same_heatmaps(tabletop):
    dataset, detector, pruner = tabletop
    threaded = TemplateDetector(detector.templates, detector.params, detector.match, threads=2)
    for frame in (1, 5):
        rows = pruner.rows(dataset.poses2d[frame], dataset.T_body_cam[frame])
        image = dataset.image(frame)
        np.testing.assert_array_equal(threaded.heatmaps(image, rows=rows), detector.heatmaps(image, rows=rows))


def test_rows_are_checked(tabletop):
    dataset, detector, _ = tabletop
    image = dataset.image(0)
    for rows in ({0.33: (0, 10)}, {detector.match.scales[0]: (5, 5)}, {detector.match.scales[0]: (0, 10 ** 6)}):
        with pytest.raises(ValueError, match="rows"):
            detector.heatmaps(image, rows=rows)
    assert not detector.heatmaps(image, rows={}).any()   # no level sees an object: no heat, never a threshold


@pytest.mark.parametrize("clockwise", [False, True])
def test_grown_polygon_holds_every_point_within_the_margin(clockwise):
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])
    polygon = grown_polygon(square[::-1] if clockwise else square, 0.2)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 2.5, (4000, 2))
    nearest = np.clip(points, [0.0, 0.0], [2.0, 1.0])   # the closest point of the rectangle
    within = np.hypot(*(points - nearest).T) <= 0.2
    inside = inside_polygon(points[:, 0], points[:, 1], polygon)
    assert inside[within].all()
    assert not inside[np.abs(points - np.clip(points, -0.2, [2.2, 1.2])).max(axis=1) > 1e-9].any()


def test_class_shapes_and_work_share():
    sizes = np.array([[0.06, 0.06, 0.12], [0.3, 0.2, 0.05], [0.07, 0.07, 0.11]])
    shapes = class_shapes(sizes, np.array([0, 1, 0]), 3)
    np.testing.assert_allclose(shapes[0], [0.11, 0.12, 0.11, 0.12])
    np.testing.assert_allclose(shapes[1], [0.05, 0.05, 0.2, np.hypot(0.3, 0.2)])
    np.testing.assert_allclose(shapes[2], [0.05, 0.12, 0.11, np.hypot(0.3, 0.2)])   # absent: any of the map's
    assert work_share({1.0: (0, 60)}, (1.0, 0.5), 120) == pytest.approx(0.5 / 1.25)
    with pytest.raises(ValueError):
        PruneParams(size_factor=0.5)
    with pytest.raises(ValueError):
        class_shapes(np.zeros((0, 3)), [], 1)
