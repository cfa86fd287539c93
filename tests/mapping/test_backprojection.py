"""The fast plane-by-plane back-projection against per-voxel projection of the same frames."""

import cv2
import numpy as np
import pytest

from semloc_core.camera import EquirectangularCamera, PinholeCamera
from semloc_core.mapping import MapperConfig, VoxelGrid, VoxelMapper, backproject_reference, slice_homography
from semloc_core.mapping.backprojection import (backproject_block, downsample_heatmaps, pad_heatmaps,
                                                slice_homography_terms)
from semloc_core.mapping.synthetic import look_at, render_heatmaps

from .conftest import CLASSES

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.02)


def _frames(camera, objects, poses, background=0.05):
    return [render_heatmaps(camera, T, objects, len(CLASSES), background=background) for T in poses]


def _reference(grid, frames, camera, poses, downsample=1, **depths):
    total = np.zeros((len(CLASSES),) + grid.volume_shape, np.float32)
    views = np.zeros(grid.volume_shape, np.float32)
    for heat, T in zip(frames, poses):
        heat, cam = downsample_heatmaps(heat, camera, downsample)
        values, in_view = backproject_reference(grid, heat, cam, T, **depths)
        total += values
        views += in_view
    return total, views


def _volumes(mapper):
    return np.stack([mapper.hough_volume(c) for c in CLASSES]), mapper.view_count()


@pytest.mark.parametrize(
    "config",
    [
        MapperConfig(),
        MapperConfig(heatmap_downsample=2),
        MapperConfig(tile_size=16, max_depth=1.0),
        MapperConfig(min_depth=0.3, max_depth=0.9),
    ],
    ids=["dense", "downsampled", "tiled-range", "depth-window"],
)
def test_fast_path_equals_per_voxel_projection(camera, objects, poses, config):
    # A camera inside the grid (voxels behind it and beside it) exercises the near-plane and span logic.
    poses = poses + [look_at([0.5, 0.5, 0.3], [1.0, 0.9, 0.0])]
    frames = _frames(camera, objects, poses)
    mapper = VoxelMapper(GRID, CLASSES, config)
    for heat, T in zip(frames, poses):
        mapper.integrate(heat, T, camera)
    acc, views = _volumes(mapper)
    ref, ref_views = _reference(GRID, frames, camera, poses, config.heatmap_downsample,
                                min_depth=config.min_depth, max_depth=config.max_depth)
    assert ref.max() > 1.0
    assert np.abs(acc - ref).max() <= 1e-4 * ref.max()
    np.testing.assert_allclose(views, ref_views, atol=1e-4)
    assert mapper.frames == len(poses)


def test_slice_homography_is_the_projection(camera):
    T = look_at([1.5, -0.4, 0.9], [0.5, 0.6, 0.1])
    rng = np.random.default_rng(1)
    for k in (0, 7, GRID.nz - 1):
        H = slice_homography(GRID, camera.K, T, k)
        ij = rng.integers(0, 50, (20, 2))
        p = np.c_[ij, np.ones(20)] @ H.T
        centres = GRID.centres(np.c_[ij, np.full(20, k)])
        uv, _ = camera.project_cam((centres - T[:3, 3]) @ T[:3, :3])
        np.testing.assert_allclose(p[:, :2] / p[:, 2:], uv, atol=1e-9)


def test_heatmaps_at_another_resolution_use_scaled_intrinsics(camera, objects, poses):
    """A detector may emit heatmaps smaller than the image: the mapper rescales K to them."""
    small = [render_heatmaps(camera, T, objects, len(CLASSES), height=60, width=80) for T in poses[:4]]
    mapper = VoxelMapper(GRID, CLASSES)
    for heat, T in zip(small, poses[:4]):
        mapper.integrate(heat, T, camera)
    ref, _ = _reference(GRID, small, camera, poses[:4])
    acc, _ = _volumes(mapper)
    assert np.abs(acc - ref).max() <= 1e-4 * ref.max()


def test_distortion_is_removed_before_the_homographies(poses):
    """With lens distortion the fast path first undistorts the heatmaps onto a canvas holding the whole image; it
    then agrees with per-voxel projection through the distortion model up to that extra interpolation."""
    K = np.array([[131.25, 0.0, 79.625], [0.0, 131.25, 59.625], [0.0, 0.0, 1.0]])
    distorted = PinholeCamera(160, 120, K, dist=np.array([-0.2, 0.05, 0.001, -0.001, 0.0]))
    rng = np.random.default_rng(3)
    # Smooth random heatmaps fading to zero at the border, so that the hard image edge, which each path
    # resamples differently, does not hide the geometry being tested.
    to_edge = np.minimum(np.minimum(np.arange(120), np.arange(120)[::-1])[:, None],
                         np.minimum(np.arange(160), np.arange(160)[::-1])[None, :])
    taper = np.clip(to_edge / 12.0 - 0.5, 0.0, 1.0).astype(np.float32)
    frames = []
    for _ in poses[:3]:
        coarse = rng.random((len(CLASSES), 12, 16), dtype=np.float32)
        frames.append(np.stack([cv2.GaussianBlur(cv2.resize(c, (160, 120)), (0, 0), 6) * taper for c in coarse]))
    mapper = VoxelMapper(GRID, CLASSES)
    for heat, T in zip(frames, poses[:3]):
        mapper.integrate(heat, T, distorted)
    ref, _ = _reference(GRID, frames, distorted, poses[:3])
    acc, _ = _volumes(mapper)
    assert ref.max() > 0.5
    assert np.abs(acc - ref).max() <= 0.02 * ref.max()
    # Ignoring the distortion instead is visibly wrong: the check above can fail.
    ideal = VoxelMapper(GRID, CLASSES)
    for heat, T in zip(frames, poses[:3]):
        ideal.integrate(heat, T, PinholeCamera(160, 120, K))
    assert np.abs(_volumes(ideal)[0] - ref).max() > 0.1 * ref.max()


@pytest.mark.parametrize(
    "heatmaps, pose, error, message",
    [
        (np.zeros((4, 120, 160)), np.eye(4), ValueError, "expected 5 heatmaps"),
        (np.full((5, 120, 160), np.nan), np.eye(4), ValueError, "non-finite"),
        (np.zeros((5, 120, 160, 1)), np.eye(4), ValueError, r"\(classes, height, width\)"),
        (np.zeros((5, 120, 160)), np.diag([2.0, 1, 1, 1]), ValueError, "rotation"),
        (np.zeros((5, 120, 160)), np.eye(3), ValueError, "4x4"),
        (np.array([["a"] * 3] * 3), np.eye(4), ValueError, "numeric"),
    ],
)
def test_bad_input_is_rejected_and_leaves_the_map_alone(camera, heatmaps, pose, error, message):
    mapper = VoxelMapper(GRID, CLASSES)
    with pytest.raises(error, match=message):
        mapper.integrate(heatmaps, pose, camera)
    assert mapper.frames == 0 and not mapper.view_count().any()


def test_non_pinhole_camera_is_refused():
    mapper = VoxelMapper(GRID, CLASSES)
    with pytest.raises(TypeError, match="PinholeCamera"):
        mapper.integrate(np.zeros((5, 32, 64)), np.eye(4), EquirectangularCamera(64, 32))


def test_threads_give_the_same_bytes(camera, objects, poses):
    """The slices of a block are dealt to threads; every voxel is computed alike, so any split gives the same
    bytes (and the same summed coverage) as one thread."""
    grid = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.01)
    padded = pad_heatmaps(render_heatmaps(camera, poses[0], objects, len(CLASSES), background=0.05))
    A, d = slice_homography_terms(grid, camera.K, poses[0])
    results = []
    for threads in (1, 2, 3):
        acc = np.zeros((len(CLASSES),) + grid.volume_shape, np.float32)
        views = np.zeros(grid.volume_shape, np.float32)
        covered = backproject_block(acc, views, padded, A, d, 0.05, np.inf, camera.width, camera.height,
                                    threads=threads)
        results.append((acc, views, covered))
    assert results[0][2] > 0.2 * grid.num_voxels and results[0][0].max() > 0.5
    for acc, views, covered in results[1:]:
        np.testing.assert_array_equal(acc, results[0][0])
        np.testing.assert_array_equal(views, results[0][1])
        assert covered == results[0][2]
    with pytest.raises(ValueError, match="threads"):
        backproject_block(acc, views, padded, A, d, 0.05, np.inf, camera.width, camera.height, threads=0)


def _level_maps(camera, objects, pose, levels, seed=0):
    """(classes, levels, H, W): each level a differently scaled and noised copy of the frame's heatmaps."""
    rng = np.random.default_rng(seed)
    base = render_heatmaps(camera, pose, objects, len(CLASSES), background=0.05)
    return np.stack([base * rng.uniform(0.3, 1.0) + rng.uniform(0, 0.1, base.shape).astype(np.float32)
                     for _ in range(levels)], axis=1).astype(np.float32)


@pytest.mark.parametrize("levels", [1, 3, 6])
def test_level_bands_equal_one_banded_pass_per_class_and_level(camera, objects, poses, levels):
    """Scale-selected back-projection in one pass: each class samples the level whose depth band holds the voxel
    - the same volume as back-projecting each (class, level) map on its own, restricted to its band (the
    per-voxel-checked single-map path), and the same view count as a single-map pass."""
    from semloc_core.mapping.scale_depth import depth_bands

    grid = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.01)
    maps = _level_maps(camera, objects, poses[0], levels)
    rng = np.random.default_rng(1)
    depths = rng.uniform(0.4, 2.5, (len(CLASSES), levels))  # any level order per class
    bands = depth_bands(depths, 0.05, np.inf)
    A, d = slice_homography_terms(grid, camera.K, poses[0])
    acc = np.zeros((len(CLASSES),) + grid.volume_shape, np.float32)
    views = np.zeros(grid.volume_shape, np.float32)
    covered = backproject_block(acc, views, pad_heatmaps(maps.reshape((-1,) + maps.shape[2:])), A, d, 0.05, np.inf,
                                camera.width, camera.height, level_bands=bands)
    expected = np.zeros_like(acc)
    for c in range(len(CLASSES)):
        for level in range(levels):
            near, far = bands[c, level]
            if far > near:
                backproject_block(expected[c:c + 1], np.zeros_like(views), pad_heatmaps(maps[c, level:level + 1]),
                                  A, d, near, far, camera.width, camera.height)
    single_views = np.zeros_like(views)
    single_covered = backproject_block(np.zeros_like(acc), single_views, pad_heatmaps(maps.max(axis=1)), A, d, 0.05,
                                       np.inf, camera.width, camera.height)
    assert acc.max() > 0.3
    np.testing.assert_allclose(acc, expected, rtol=0, atol=1e-6 * expected.max())
    np.testing.assert_array_equal(views, single_views)
    assert covered == pytest.approx(single_covered)


@pytest.mark.parametrize("bands, message", [
    ([[[0.05, 1.0], [0.9, 5.0]]] * len(CLASSES), "overlap"),
    ([[[0.05, 1.0], [1.2, 5.0]]] * len(CLASSES), "gap"),
    ([[[1.0, 0.5], [0.5, 5.0]]] * len(CLASSES), "overlap or are reversed"),
    ([[[0.05, 1.0], [1.0, np.nan]]] * len(CLASSES), "finite"),
    ([[[0.05, 1.0], [1.0, 5.0]]] * 2, "classes"),
])
def test_bad_level_bands_are_refused(camera, poses, bands, message):
    grid = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [0.2, 0.2, 0.1], 0.02)
    A, d = slice_homography_terms(grid, camera.K, poses[0])
    padded = pad_heatmaps(np.zeros((2 * len(CLASSES), camera.height, camera.width), np.float32))
    acc = np.zeros((len(CLASSES),) + grid.volume_shape, np.float32)
    with pytest.raises(ValueError, match=message):
        backproject_block(acc, np.zeros(grid.volume_shape, np.float32), padded, A, d, 0.05, np.inf, camera.width,
                          camera.height, level_bands=np.array(bands, dtype=float))
