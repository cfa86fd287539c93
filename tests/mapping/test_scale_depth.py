"""Scale-selected back-projection (semloc_core.mapping.scale_depth): a window detector's level says how far."""

import numpy as np
import pytest

from semloc_core.mapping import ExtractionConfig, MapperConfig, VoxelGrid, VoxelMapper
from semloc_core.mapping.scale_depth import (calibration_mismatch, depth_bands, fit_depth_per_scale, level_depths,
                                             reach_over_levels)
from semloc_core.mapping.synthetic import SyntheticObject, render_heatmaps, render_level_heatmaps

from .conftest import CLASSES

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.01)
SCALES = (1.2, 0.85, 0.6, 0.42, 0.3, 0.21)


def _depths(camera, depth_per_scale=0.0085):
    # The trained detector's soda can answers at about this depth per focal pixel per unit scale (docs/mapping.md):
    # at the test camera's focal length the levels answer 1.34 m ... 0.23 m away.
    return level_depths([depth_per_scale] * len(CLASSES), SCALES, camera.K[0, 0])


@pytest.mark.parametrize("depths", [[0.5, 1.0, 2.0], [2.0, 0.5, 1.0], [0.8]])
def test_depth_bands_cover_the_range_once_and_meet_halfway_in_log(depths):
    bands = depth_bands([depths], 0.05, 10.0)[0]
    order = np.argsort(depths)
    edges = bands[order]
    assert edges[0, 0] == 0.05 and edges[-1, 1] == 10.0
    np.testing.assert_allclose(edges[1:, 0], edges[:-1, 1])  # contiguous, no overlap
    sorted_depths = np.sort(depths)
    np.testing.assert_allclose(edges[1:, 0], np.sqrt(sorted_depths[1:] * sorted_depths[:-1]))
    assert np.all((bands[:, 0] <= depths) & (np.asarray(depths) < bands[:, 1]))


def test_fit_recovers_the_depth_per_scale_from_noisy_levels():
    rng = np.random.default_rng(0)
    truth = 0.0085
    scale = rng.choice(SCALES, 400)
    focal = rng.choice([525.0, 262.5], 400)
    depth = truth * focal * scale * np.exp(rng.normal(0.0, 0.1, 400))
    fit = fit_depth_per_scale(depth, focal, scale)
    assert fit["samples"] == 400
    assert abs(np.log(fit["depth_per_scale"] / truth)) < 0.02
    assert 0.07 < fit["log_spread"] < 0.13
    with pytest.raises(ValueError, match="same number"):
        fit_depth_per_scale([1.0], [525.0, 1.0], [1.0])
    with pytest.raises(ValueError, match="positive"):
        fit_depth_per_scale([1.0], [525.0], [0.0])


@pytest.mark.parametrize("background", ["none", "median", "surprisal"])
def test_identical_levels_give_the_single_map_volume(camera, objects, poses, background):
    """Every level the same map: each voxel takes that map whatever its band, so both paths agree (the bands of a
    class cover every depth exactly once, and the surprisal is judged on the max over levels)."""
    single = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_background=background))
    levels = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_background=background))
    depths = _depths(camera)
    for T in poses:
        heat = render_heatmaps(camera, T, objects, len(CLASSES), background=0.05)
        single.integrate(heat, T, camera)
        levels.integrate(np.repeat(heat[:, None], len(SCALES), axis=1), T, camera, level_depths=depths)
    for name in CLASSES:
        a, b = single.hough_volume(name), levels.hough_volume(name)
        assert np.abs(a - b).max() <= 1e-4 * a.max()
    # A voxel exactly on a band edge is counted by both bands; nothing else differs.
    assert np.abs(single.view_count() - levels.view_count()).max() <= 1.0
    assert np.mean(single.view_count() != levels.view_count()) < 1e-3


def test_a_look_alike_of_the_wrong_size_gets_no_consistent_vote(camera, objects, poses):
    """A clutter box the soda-can filter answers on at the level of a can 60 % as far: the rays of every view
    meet at the box (a phantom can in the single map), their votes in front of it land in different places."""
    clutter = SyntheticObject(4, np.array([0.3, 0.35, 0.1]), np.array([0.12, 0.12, 0.12]))
    world = [o for o in objects if o.class_index != 4] + [clutter]
    depths = _depths(camera)
    single, levels = VoxelMapper(GRID, CLASSES), VoxelMapper(GRID, CLASSES)
    for T in poses:
        single.integrate(render_heatmaps(camera, T, world, len(CLASSES)), T, camera)
        levels.integrate(render_level_heatmaps(camera, T, world, len(CLASSES), depths,
                                               depth_factor={len(world) - 1: 0.6}), T, camera, level_depths=depths)
    config = ExtractionConfig(threshold=0.5)

    def cans(mapper):
        return [o for o in mapper.extract(config) if o.class_name == "soda_can"]

    assert len(cans(single)) == 1 and np.linalg.norm(cans(single)[0].position - clutter.centre) < 0.02
    assert cans(levels) == []
    # The real objects, seen at their own size, are all still there.
    found = {o.class_name: o for o in levels.extract(config)}
    for o in world[:-1]:
        assert np.linalg.norm(found[CLASSES[o.class_index]].position - o.centre) < 0.02


def test_per_level_input_is_checked(camera, poses):
    mapper = VoxelMapper(GRID, CLASSES)
    depths = _depths(camera)
    heat = np.zeros((len(CLASSES), len(SCALES), 120, 160), np.float32)
    with pytest.raises(ValueError, match="per-level heatmaps"):
        mapper.integrate(heat[:, :3], poses[0], camera, level_depths=depths)
    with pytest.raises(ValueError, match="level_depths"):
        mapper.integrate(heat, poses[0], camera, level_depths=depths[:2])
    with pytest.raises(ValueError, match="non-finite"):
        mapper.integrate(np.full_like(heat, np.nan), poses[0], camera, level_depths=depths)
    llr = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_llr={name: [-1.0, 1.0] for name in CLASSES}))
    with pytest.raises(ValueError, match="fitted on single heatmaps"):
        llr.integrate(heat, poses[0], camera, level_depths=depths)
    with pytest.raises(ValueError, match="depth_per_scale"):
        level_depths([0.0], SCALES, 525.0)


@pytest.mark.parametrize("reach, expected", [(0, [0, 1, 0, 0]), (1, [1, 1, 1, 0]), (2, [1, 1, 1, 1])])
def test_reach_takes_the_max_over_neighbouring_levels_in_depth_order(reach, expected):
    # Levels listed out of depth order: depth order is 2, 0, 1, 3 (level 0 answers, it is second nearest).
    depths = np.array([[1.0, 2.0, 0.5, 4.0]])
    maps = np.zeros((1, 4, 2, 2), np.float32)
    maps[0, 0] = 1.0
    out = reach_over_levels(maps, depths, reach)
    np.testing.assert_array_equal(out[0, np.argsort(depths[0]), 0, 0], expected)


@pytest.mark.parametrize("scales, classes, reason", [
    (SCALES, CLASSES, None),
    (tuple(s * (1 + 1e-9) for s in SCALES), CLASSES[:2], None),
    (SCALES[:3], CLASSES, "level scales"),
    ((1.0,) + SCALES[1:], CLASSES, "level scales"),
    (SCALES, CLASSES + ("bottle",), "no depth per scale for classes ['bottle']"),
])
def test_a_calibration_of_another_detector_says_why(scales, classes, reason):
    problem = calibration_mismatch(SCALES, {name: 0.004 for name in CLASSES}, scales, classes)
    assert problem is None if reason is None else reason in problem
