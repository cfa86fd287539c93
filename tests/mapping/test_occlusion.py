"""Occlusion from depth images: voxels hidden behind the surface a frame sees get neither a view nor heat."""

import numpy as np
import pytest

from semloc_core.mapping import MapperConfig, VoxelGrid, VoxelMapper, backproject_reference
from semloc_core.mapping.backprojection import (_UNLIMITED_DEPTH, backproject_block, downsample_heatmaps,
                                                pad_heatmaps, slice_homography_terms, surface_depths)
from semloc_core.mapping.synthetic import SyntheticObject, look_at, plane_depth, render_heatmaps

from .conftest import CLASSES

FAR = np.float32(_UNLIMITED_DEPTH)  # "nothing seen here" in the padded surface

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.02)


def _depths(camera, poses):
    """A wall across the middle of the grid, and a patch without return in every frame."""
    depths = []
    for T in poses:
        depth = plane_depth(camera, T, [0.55, 0.6, 0.0], [1.0, 0.3, 0.0])
        depth[10:30, 20:50] = np.nan
        depths.append(depth)
    return depths


@pytest.mark.parametrize("margin", [0.0, 0.15])
@pytest.mark.parametrize("downsample", [1, 2])
def test_fast_path_equals_per_voxel_projection_with_occlusion(camera, objects, poses, margin, downsample):
    frames = [render_heatmaps(camera, T, objects, len(CLASSES), background=0.05) for T in poses]
    depths = _depths(camera, poses)
    mapper = VoxelMapper(GRID, CLASSES, MapperConfig(occlusion_margin=margin, heatmap_downsample=downsample))
    open_map = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_downsample=downsample))
    ref = np.zeros((len(CLASSES),) + GRID.volume_shape, np.float32)
    ref_views = np.zeros(GRID.volume_shape, np.float32)
    for heat, depth, T in zip(frames, depths, poses):
        mapper.integrate(heat, T, camera, depth=depth)
        open_map.integrate(heat, T, camera)
        small, cam = downsample_heatmaps(heat, camera, downsample)
        surface = surface_depths(depth, cam.height, cam.width)
        values, seen = backproject_reference(GRID, small, cam, T, surface=surface, occlusion_margin=margin)
        ref += values
        ref_views += seen
    acc = np.stack([mapper.hough_volume(c) for c in CLASSES])
    assert ref.max() > 1.0
    assert np.abs(acc - ref).max() <= 1e-4 * ref.max()
    np.testing.assert_allclose(mapper.view_count(), ref_views, atol=1e-4)
    # The wall hides a large part of the grid from every view: the test can tell occlusion from none.
    hidden = open_map.view_count() - mapper.view_count()
    assert hidden.min() >= -1e-4 and (hidden > 1).mean() > 0.2


def test_surface_keeps_the_farthest_depth_of_each_footprint():
    depth = np.array([[1.0, 2.0, 5.0, 5.0],
                      [1.0, 1.0, 5.0, np.nan],
                      [3.0, 3.0, 0.0, 4.0],
                      [3.0, 3.0, 4.0, -1.0]], np.float32)
    surface = surface_depths(depth, 2, 2)
    assert surface.shape == (4, 4) and surface.dtype == np.float32
    # The pixel's footprint: its farthest surface; no return anywhere in it hides nothing.
    np.testing.assert_array_equal(surface[1:3, 1:3], [[2.0, FAR], [3.0, FAR]])
    # The zero border of the padded heatmaps hides nothing either.
    assert np.all(surface[0] == FAR) and np.all(surface[:, -1] == FAR)
    # Same size: unchanged but for the missing returns.
    same = surface_depths(np.full((3, 5), 0.7, np.float32), 3, 5)
    np.testing.assert_array_equal(same[1:-1, 1:-1], np.float32(0.7))


def test_an_object_hidden_in_some_frames_keeps_its_mean_score(camera):
    """Seen in one frame, hidden behind a box without any class's heat in the next: with depth its mean heat is
    the first frame's; without, the hidden frame halves it."""
    bowl = SyntheticObject(0, np.array([0.55, 0.6, 0.08]), np.array([0.16, 0.16, 0.08]))
    T = look_at([0.55, -0.3, 0.5], bowl.centre)
    heat = render_heatmaps(camera, T, [bowl], len(CLASSES), background=0.0)
    far = np.full((camera.height, camera.width), 20.0, np.float32)
    occluder = np.full_like(far, 0.4)  # a box 0.4 m in front of the camera fills the view
    config = MapperConfig(occlusion_margin=0.1)
    with_depth, without, alone = (VoxelMapper(GRID, CLASSES, config) for _ in range(3))
    with_depth.integrate(heat, T, camera, depth=far)
    with_depth.integrate(np.zeros_like(heat), T, camera, depth=occluder)
    without.integrate(heat, T, camera, depth=far)
    without.integrate(np.zeros_like(heat), T, camera)
    alone.integrate(heat, T, camera, depth=far)
    centre = tuple(GRID.indices_of(bowl.centre)[0][::-1])  # (k, j, i)
    assert with_depth.view_count()[centre] == pytest.approx(1.0)
    assert without.view_count()[centre] == pytest.approx(2.0)
    score = with_depth.score_volume("bowl")[centre]
    assert score > 0.1
    assert score == pytest.approx(alone.score_volume("bowl")[centre])
    assert without.score_volume("bowl")[centre] == pytest.approx(score / 2)
    # Voxels in front of the box (less than 0.4 + 0.1 m deep) were seen by both frames.
    near = (GRID.centres(np.argwhere(with_depth.view_count() > 0)[:, ::-1]) - T[:3, 3]) @ T[:3, :3]
    twice = with_depth.view_count()[with_depth.view_count() > 0] > 1.5
    assert twice.any() and np.all(near[twice, 2] <= 0.5 + GRID.voxel_size)


@pytest.mark.parametrize("depth, message", [
    (np.zeros((60, 80), np.float32), r"depth must be a float \(120, 160\)"),
    (np.zeros((120, 160), np.int32), "depth must be a float"),
    (np.zeros((120, 160, 1), np.float32), "depth must be a float"),
])
def test_bad_depth_is_refused_and_leaves_the_map_alone(camera, depth, message):
    mapper = VoxelMapper(GRID, CLASSES)
    with pytest.raises(ValueError, match=message):
        mapper.integrate(np.zeros((5, 120, 160)), look_at([0.5, -0.5, 0.5], [0.5, 0.5, 0.0]), camera, depth=depth)
    assert mapper.frames == 0 and not mapper.view_count().any()


@pytest.mark.parametrize("margin", [-0.1, np.nan, np.inf])
def test_bad_occlusion_margin_is_refused(margin):
    with pytest.raises(ValueError, match="occlusion_margin"):
        MapperConfig(occlusion_margin=margin)


def test_kernel_refuses_a_surface_of_another_size(camera):
    heat = np.zeros((5, 120, 160), np.float32)
    padded = pad_heatmaps(heat)
    A, d = slice_homography_terms(GRID, camera.K, look_at([0.5, -0.5, 0.5], [0.5, 0.5, 0.0]))
    acc = np.zeros((5,) + GRID.volume_shape, np.float32)
    views = np.zeros(GRID.volume_shape, np.float32)
    with pytest.raises(ValueError, match="surface depths must be"):
        backproject_block(acc, views, padded, A, d, 0.05, np.inf, 160, 120,
                          surface=np.zeros((10, 10), np.float32))
