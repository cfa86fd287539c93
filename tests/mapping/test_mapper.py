"""The mapper end to end on synthetic heatmaps with exact ground truth: objects, memory, snapshots, files."""

import numpy as np
import pytest

from semloc_core.io.semantic_map import load_semantic_map, save_semantic_map
from semloc_core.io.voxel_map import VoxelMapFileError, load_ply, load_voxel_snapshot, save_ply, save_voxel_snapshot
from semloc_core.mapping import ExtractionConfig, MapperConfig, MapperMemoryError, VoxelGrid, VoxelMapper
from semloc_core.mapping.synthetic import SyntheticObject, orbit_poses, render_heatmaps

from .conftest import CLASSES

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.01)


@pytest.fixture(scope="module")
def mapped(camera, objects, poses):
    mapper = VoxelMapper(GRID, CLASSES)
    for T in poses:
        mapper.integrate(render_heatmaps(camera, T, objects, len(CLASSES), background=0.05), T, camera)
    return mapper


def _match(found, objects):
    """Nearest ground-truth object of the same class for each found object: (found, truth, distance)."""
    pairs = []
    for f in found:
        same = [o for o in objects if CLASSES[o.class_index] == f.class_name]
        d = [np.linalg.norm(f.position - o.centre) for o in same]
        pairs.append((f, same[int(np.argmin(d))] if d else None, min(d) if d else np.inf))
    return pairs


def test_every_object_found_where_it_is_and_nothing_else(mapped, objects):
    found = mapped.extract(ExtractionConfig(threshold=0.5))
    assert sorted(f.class_name for f in found) == sorted(CLASSES)
    for f, truth, distance in _match(found, objects):
        assert distance < 0.01, (f.class_name, f.position, truth.centre)
        assert 0.5 < f.score <= 1.06  # mean heat over the views: 1 at the centre, plus the 0.05 background


def test_semantic_map_export_round_trips(mapped, objects, tmp_path):
    semantic_map = mapped.semantic_map(ExtractionConfig(threshold=0.5))
    path = tmp_path / "objects.json"
    save_semantic_map(semantic_map, path)
    loaded = load_semantic_map(path)
    assert loaded.class_names == CLASSES
    assert loaded.has_height.all() and len(loaded) == len(objects)
    for o in objects:
        (index,) = loaded.objects_of(CLASSES[o.class_index])
        np.testing.assert_allclose(loaded.positions[index], o.centre, atol=0.01)
        assert np.all(loaded.sizes[index] > 0)
    np.testing.assert_allclose(loaded.bounds, GRID.bounds[:, :2])
    # Sizes: the class's bounding volume by default, the measured extent on request.
    np.testing.assert_allclose(loaded.sizes, 0.2)
    measured = mapped.semantic_map(ExtractionConfig(threshold=0.5, export_size="extent"))
    found = {f.class_name: f.extent for f in mapped.extract(ExtractionConfig(threshold=0.5))}
    for k, c in enumerate(measured.class_index):
        np.testing.assert_allclose(measured.sizes[k], found[measured.class_names[c]])


def test_view_normalisation_counts_frames(mapped, poses):
    views = mapped.view_count()
    assert views.max() == len(poses)  # the table centre is in every view
    assert views.min() < len(poses) - 3  # the grid's corners are not
    raw = mapped.score_volume("bowl", normalise=False)
    np.testing.assert_allclose(raw, mapped.hough_volume("bowl") / len(poses), rtol=1e-6)


def test_threshold_above_every_score_finds_nothing(mapped):
    assert mapped.extract(ExtractionConfig(threshold=1.5)) == []


def test_tiles_follow_the_explored_space(camera, objects, poses):
    """Tiled storage allocates only the columns a frustum (clipped at max_depth) reached, and sums the same."""
    dense = VoxelMapper(GRID, CLASSES, MapperConfig(max_depth=0.8))
    tiled = VoxelMapper(GRID, CLASSES, MapperConfig(max_depth=0.8, tile_size=20))
    for T in poses[:3]:
        heat = render_heatmaps(camera, T, objects, len(CLASSES))
        dense.integrate(heat, T, camera)
        stats = tiled.integrate(heat, T, camera)
        assert stats.blocks_updated > 0
    assert 0.2 < tiled.allocated_fraction < 1.0
    assert tiled.memory_bytes < dense.memory_bytes
    for c in CLASSES:
        np.testing.assert_array_equal(tiled.hough_volume(c), dense.hough_volume(c))
    np.testing.assert_array_equal(tiled.view_count(), dense.view_count())


def test_memory_limit_refuses_oversized_grids():
    floor = VoxelGrid.from_bounds([0, 0, 0], [40, 20, 2.5], 0.05)  # a building floor at 5 cm: 16 M voxels
    with pytest.raises(MapperMemoryError, match="tile_size"):
        VoxelMapper(floor, CLASSES, MapperConfig(memory_limit_mb=256))
    tiled = VoxelMapper(floor, CLASSES, MapperConfig(memory_limit_mb=256, tile_size=64, max_depth=4.0))
    assert tiled.memory_bytes == 0


@pytest.mark.parametrize("tile_size", [None, 32])
def test_snapshot_restore_continues_exactly(camera, objects, poses, tmp_path, tile_size):
    config = MapperConfig(tile_size=tile_size, heatmap_downsample=2)
    frames = [(render_heatmaps(camera, T, objects, len(CLASSES)), T) for T in poses[:6]]
    straight = VoxelMapper(GRID, CLASSES, config)
    for heat, T in frames:
        straight.integrate(heat, T, camera)
    first = VoxelMapper(GRID, CLASSES, config)
    for heat, T in frames[:3]:
        first.integrate(heat, T, camera)
    path = tmp_path / "map.npz"
    save_voxel_snapshot(path, first.snapshot())
    restored = VoxelMapper.from_snapshot(load_voxel_snapshot(path))
    assert restored.frames == 3 and restored.config == config and restored.class_names == CLASSES
    for heat, T in frames[3:]:
        restored.integrate(heat, T, camera)
    for c in CLASSES:
        np.testing.assert_array_equal(restored.hough_volume(c), straight.hough_volume(c))
    np.testing.assert_array_equal(restored.view_count(), straight.view_count())


def test_corrupt_snapshots_are_refused(mapped, tmp_path):
    arrays = mapped.snapshot()
    broken = dict(arrays, acc_0=arrays["acc_0"][:, :-1])
    with pytest.raises(ValueError, match="acc_0"):
        VoxelMapper.from_snapshot(broken)
    with pytest.raises(ValueError, match="snapshot"):
        VoxelMapper.from_snapshot({"meta": np.frombuffer(b'{"format": "x"}', np.uint8)})
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(VoxelMapFileError):
        load_voxel_snapshot(path)
    with pytest.raises(ValueError, match="pickle"):
        save_voxel_snapshot(tmp_path / "x.npz", {"bad": np.array([{}], dtype=object)})


def test_hot_voxels_ply(mapped, objects, tmp_path):
    cloud = mapped.hot_voxels(fraction=0.8)
    assert set(np.unique(cloud["class_index"])) == set(range(len(CLASSES)))
    for o in objects:  # the hottest voxels of each class sit on its object
        mine = cloud["class_index"] == o.class_index
        assert np.linalg.norm(cloud["points"][mine].mean(axis=0) - o.centre) < 0.03
    path = tmp_path / "hot.ply"
    save_ply(path, cloud["points"], cloud["colors"], {"score": cloud["score"], "class_index": cloud["class_index"]})
    vertices = load_ply(path)
    np.testing.assert_allclose(np.c_[vertices["x"], vertices["y"], vertices["z"]], cloud["points"], atol=1e-6)
    np.testing.assert_array_equal(vertices["red"], cloud["colors"][:, 0])
    np.testing.assert_array_equal(vertices["class_index"], cloud["class_index"])


def test_objects_seen_from_few_views_need_normalisation(camera):
    """An object inside the view of a few frames only: its summed score is diluted by the frames that never saw
    it, while the view-normalised score (mean heat over the frames that saw it) is unaffected."""
    grid = VoxelGrid.from_bounds([0, 0, 0], [2.0, 1.0, 0.3], 0.02)
    always = SyntheticObject(0, np.array([0.3, 0.5, 0.1]), np.array([0.1, 0.1, 0.1]))
    rarely = SyntheticObject(1, np.array([1.7, 0.5, 0.1]), np.array([0.1, 0.1, 0.1]))
    from semloc_core.mapping.synthetic import look_at

    mapper = VoxelMapper(grid, ("a", "b"))
    eyes = [(0.3 + 0.4 * np.cos(a), 0.5 + 0.4 * np.sin(a), 0.5) for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    views = [look_at(e, always.centre) for e in eyes]
    views += [look_at((1.7 + 0.4 * np.cos(a), 0.5 + 0.4 * np.sin(a), 0.5), rarely.centre) for a in (0.0, 2.0, 4.0)]
    for T in views:
        mapper.integrate(render_heatmaps(camera, T, [always, rarely], 2), T, camera)
    summed = mapper.extract(ExtractionConfig(threshold=0.4, normalise=False))
    normalised = mapper.extract(ExtractionConfig(threshold=0.4, normalise=True, min_views=3))
    assert [o.class_name for o in summed] == ["a"]
    assert sorted(o.class_name for o in normalised) == ["a", "b"]
    b = [o for o in normalised if o.class_name == "b"][0]
    assert np.linalg.norm(b.position - rarely.centre) < 0.02


def test_mode_position_stays_on_an_object_seen_from_few_similar_directions(camera):
    # A robot passing a table sees a box from a 29-degree arc only (7 views): the back-projected peak is a cone
    # that widens away from the cameras, so the mass above half its peak - and its centroid - lies behind the
    # object. The maximum of that mass smoothed at 2 cm stays closer: the kernel does not reach the cone's far,
    # wide part.
    box = SyntheticObject(0, np.array([0.55, 0.6, 0.15]), np.array([0.2, 0.2, 0.3]))
    arc = orbit_poses(box.centre, 0.8, 0.4, 7, start_angle=-0.25, sweep=0.5)
    mapper = VoxelMapper(GRID, CLASSES)
    for T in arc:
        mapper.integrate(render_heatmaps(camera, T, [box], len(CLASSES)), T, camera)
    error = {}
    for position in ("peak", "centroid", "mode"):
        found = [o for o in mapper.extract(ExtractionConfig(threshold=0.5, min_views=1, position=position))
                 if o.class_name == "bowl"]
        assert len(found) == 1
        error[position] = np.linalg.norm(found[0].position - box.centre)
    assert error["peak"] < 0.01
    assert error["centroid"] > 0.03  # the cone's far side pulls it
    assert error["mode"] < error["centroid"] / 2
