"""Heat log-likelihood ratios (samples, fit, accumulation) and the support-plane constraint of extraction."""

import numpy as np
import pytest

from semloc_core.mapping import ExtractionConfig, MapperConfig, VoxelGrid, VoxelMapper
from semloc_core.mapping.extraction import extract_all
from semloc_core.mapping.likelihood import (check_llr_tables, fit_heat_llr, heat_samples, heat_surprisal, heat_to_llr,
                                            level_surprisal)
from semloc_core.mapping.synthetic import render_heatmaps

from .conftest import CLASSES

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.01)
# A detector with a class-dependent floor, as the template detector has on a table (docs/mapping.md): the bowl
# template answers 0.45 on average everywhere, the others 0.05.
FLOORS = np.array([0.45, 0.05, 0.05, 0.05, 0.05], np.float32)


def _detector_heat(camera, T, objects, rng):
    blobs = render_heatmaps(camera, T, objects, len(CLASSES), peak=0.5)
    noise = rng.uniform(-0.05, 0.05, blobs.shape).astype(np.float32)
    return np.clip(FLOORS[:, None, None] + noise + blobs, 0.0, 1.0)


def _centres_and_boxes(camera, T, objects):
    R, t = T[:3, :3], T[:3, 3]
    centres, boxes = [], []
    for o in objects:
        corners = o.centre + 0.5 * o.size * np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
        uv, inside = camera.project_cam((corners - t) @ R)
        (u, v), centre_inside = camera.project_cam(R.T @ (o.centre - t))
        if centre_inside:
            centres.append((o.class_index, float(u), float(v)))
        if inside.any():
            boxes.append((o.class_index, (*uv.min(axis=0), *uv.max(axis=0))))
    return centres, boxes


def test_heat_samples_take_centres_and_skip_boxes():
    heat = np.zeros((2, 30, 40), np.float32)
    heat[0, 10, 20] = 1.0
    heat[1] = 0.25
    # Image 80 x 60: heatmap cell (10, 20) is centred on pixel (40.5, 20.5).
    pos, neg = heat_samples(heat, (80, 60), [(0, 40.5, 20.5), (1, 500.0, 20.0)], [(0, (30.0, 10.0, 50.0, 30.0))])
    assert pos[0] == pytest.approx([1.0]) and pos[1].size == 0  # a centre off the image gives no sample
    assert neg[0].max() == 0.0  # the peak lies in the box (grown by a quarter of its size): never a negative
    # The box, grown to [25, 55] x [5, 35] pixels, hides cells q 13..27 and r 3..17 of class 0 only.
    assert neg[0].size == 30 * 40 - 15 * 15 and neg[1].size == 30 * 40


def test_llr_table_is_signed_monotone_and_checked():
    rng = np.random.default_rng(0)
    tables = fit_heat_llr({"a": [rng.normal(0.7, 0.08, 400)]}, {"a": [rng.normal(0.2, 0.08, 20000)]})
    z = np.linspace(0, 1, len(tables["a"]))
    llr = np.asarray(tables["a"])
    assert np.all(np.diff(llr) >= 0)
    assert llr[np.searchsorted(z, 0.2)] < -1 and llr[np.searchsorted(z, 0.7)] > 1
    assert abs(z[np.argmin(np.abs(llr))] - 0.45) < 0.05  # equal densities halfway between the two modes
    with pytest.raises(ValueError, match="lack classes"):
        check_llr_tables(tables, ("a", "b"))
    with pytest.raises(ValueError, match="replaces background removal"):
        MapperConfig(heatmap_llr=tables, heatmap_background="median")
    np.testing.assert_allclose(heat_to_llr(np.full((1, 2, 2), 0.7), check_llr_tables(tables, ("a",))),
                               llr[70], rtol=1e-6)


def test_likelihood_ratios_find_objects_under_a_class_dependent_floor(camera, objects, poses):
    # Fit the ratios on one realisation of the detector's noise, map with another.
    fit_rng, map_rng = np.random.default_rng(1), np.random.default_rng(2)
    positives = {name: [] for name in CLASSES}
    negatives = {name: [] for name in CLASSES}
    for T in poses:
        centres, boxes = _centres_and_boxes(camera, T, objects)
        pos, neg = heat_samples(_detector_heat(camera, T, objects, fit_rng), (camera.width, camera.height),
                                centres, boxes)
        for c, name in enumerate(CLASSES):
            positives[name].append(pos[c])
            negatives[name].append(neg[c])
    llr = fit_heat_llr(positives, negatives)
    raw = VoxelMapper(GRID, CLASSES)
    evidence = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_llr=llr))
    for T in poses:
        heat = _detector_heat(camera, T, objects, map_rng)
        raw.integrate(heat, T, camera)
        evidence.integrate(heat, T, camera)
    # Raw heat: the bowl's floor alone reaches the level of the other objects, so one threshold cannot serve
    # every class.
    assert len(raw.extract(ExtractionConfig(threshold=0.3))) > len(objects) + 3
    # Evidence: one threshold for every class (mean log-likelihood ratio per view: e to the 1 = 2.7 times likelier
    # an object than background, on average per view).
    found = evidence.extract(ExtractionConfig(threshold=1.0))
    assert sorted(f.class_name for f in found) == sorted(CLASSES)
    for f in found:
        truth = objects[CLASSES.index(f.class_name)]
        # 13 positives make a nearly binary ratio: the core every view calls "object" saturates at the clip and
        # the position is that core's centroid - within 2.5 cm here (the raw-heat peak of clean blobs: 1 cm).
        assert np.linalg.norm(f.position - truth.centre) < 0.025, (f.class_name, f.position, truth.centre)
    restored = VoxelMapper.from_snapshot(evidence.snapshot())
    assert restored.config.heatmap_llr == llr


def test_support_plane_keeps_only_peaks_resting_on_it():
    grid = VoxelGrid.from_bounds([0, 0, 0], [1.0, 1.0, 0.4], 0.02)
    z, y, x = (grid.axis_centres(a) for a in (2, 1, 0))

    def blob(centre, peak):
        d2 = (x[None, None, :] - centre[0]) ** 2 + (y[None, :, None] - centre[1]) ** 2 + (z[:, None, None] - centre[2]) ** 2
        return (peak * np.exp(-d2 / (2 * 0.03**2))).astype(np.float32)

    # Support at 0.1 m, objects at most 0.08 m tall: a centre can be at 0.10..0.14 m. The strongest blob lies below
    # the support (the table's texture), another floats above (a template answering on a tall box's top) and one
    # sits at 0.17 m, within a bounding height of the support but too high for a resting bowl's centre (a mug's
    # rim 7 cm above the table seen as a bowl).
    score = (blob((0.3, 0.3, 0.14), 0.6) + blob((0.7, 0.3, 0.05), 1.0) + blob((0.5, 0.7, 0.30), 0.9)
             + blob((0.2, 0.8, 0.17), 0.8))
    sizes = {"bowl": (0.1, 0.1, 0.08)}
    assert len(extract_all({"bowl": score}, grid, sizes, 0.5)) == 4
    (found,) = extract_all({"bowl": score}, grid, sizes, 0.5, support_z=0.1)
    assert np.linalg.norm(found.position - [0.3, 0.3, 0.14]) < 0.01
    with pytest.raises(ValueError, match="support_z"):
        ExtractionConfig(support_z=float("nan"))


@pytest.mark.parametrize("height", [0.06, 0.12, 0.28])
def test_resting_objects_are_centred_between_the_support_and_their_regions_top(height):
    # A box resting on the support at 0.10 m whose score is strongest on its upper part (a template answering on
    # a cereal box's printed face, a cap's crown): the score mass - and its centroid - lies high, the region
    # above half the peak spans the object from the support to its top.
    grid = VoxelGrid.from_bounds([0, 0, 0.08], [0.6, 0.6, 0.5], 0.01)
    z, y, x = (grid.axis_centres(a) for a in (2, 1, 0))
    inside_xy = (np.abs(x[None, :] - 0.3) < 0.04) & (np.abs(y[:, None] - 0.3) < 0.04)
    profile = np.where((z > 0.10) & (z < 0.10 + height), 0.6 + 0.4 * (z - 0.10) / height, 0.0)
    score = (profile[:, None, None] * inside_xy[None]).astype(np.float32)
    sizes = {"cereal_box": (0.2, 0.2, 0.3)}
    (centroid,) = extract_all({"cereal_box": score}, grid, sizes, 0.5, support_z=0.10, position="centroid")
    (resting,) = extract_all({"cereal_box": score}, grid, sizes, 0.5, support_z=0.10, position="centroid",
                             resting=True)
    centre = 0.10 + height / 2
    assert centroid.position[2] - centre > 0.05 * height  # the mass lies high
    assert abs(resting.position[2] - centre) <= 0.005  # half a voxel: the region's top is quantised
    np.testing.assert_allclose(resting.position[:2], centroid.position[:2])  # only the height changes
    with pytest.raises(ValueError, match="support_z"):
        ExtractionConfig(resting=True)


def test_surprisal_is_the_frames_own_p_value_per_class():
    heat = np.array([[[0.0, 0.0], [0.5, 1.0]], [[0.2, 0.2], [0.2, 0.2]]], np.float32)
    s = heat_surprisal(heat)
    # Class 0: 4 cells; at least 0.0: all 4, at least 0.5: 2, at least 1.0: 1. Class 1 is flat: no surprise.
    np.testing.assert_allclose(s[0], np.log([[1.0, 1.0], [2.0, 4.0]]), rtol=1e-6)
    np.testing.assert_array_equal(s[1], 0.0)
    # Only the order of a frame's heat counts: a class-specific gain and floor change nothing.
    rng = np.random.default_rng(3)
    h = rng.uniform(0, 1, (2, 12, 16)).astype(np.float32)
    np.testing.assert_allclose(heat_surprisal(0.3 * h + 0.6), heat_surprisal(h), rtol=1e-6)
    # Background mean 1 (the mean of -log U over a frame of distinct values, up to the 1/N discretisation).
    assert abs(float(heat_surprisal(h).mean()) - 1.0) < 0.05


@pytest.mark.parametrize("dtype, levels", [(np.uint8, 1), (np.uint8, 3), (np.uint16, 1)])
def test_surprisal_of_quantised_codes_is_that_of_their_values(dtype, levels):
    # The detector publishes code · scale: counted from the codes' histogram, the same float32 surprisals as
    # sorting the values (ties included: a third of the cells share one code).
    rng = np.random.default_rng(5)
    codes = rng.integers(0, np.iinfo(dtype).max, (2 * levels, 30, 40)).astype(dtype)
    codes[:, :10] = 7
    values = codes.astype(np.float32) * np.float32(1 / np.iinfo(dtype).max)
    np.testing.assert_array_equal(level_surprisal(codes, levels), level_surprisal(values, levels))


def test_mapper_given_codes_builds_the_map_of_their_values(camera, objects, poses):
    heat = [np.clip(render_heatmaps(camera, T, objects, len(CLASSES), peak=0.8) + 0.1, 0, 1) for T in poses[:6]]
    scale = np.float32(1 / 255)
    maps = {}
    for kind in ("codes", "values"):
        mapper = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_background="surprisal"))
        for h, T in zip(heat, poses):
            codes = np.round(h / scale).astype(np.uint8)
            mapper.integrate(codes if kind == "codes" else codes.astype(np.float32) * scale, T, camera)
        maps[kind] = mapper.snapshot()
    for name in maps["values"]:
        np.testing.assert_array_equal(maps["codes"][name], maps["values"][name])
    assert maps["codes"]["acc_0"].max() > 1  # the objects did get heat


def test_surprisal_puts_every_class_and_frame_on_one_scale(camera, objects, poses):
    # The bowl detector answers 0.4 on the lower half of every image (the table it mistakes for a bowl), the
    # others 0.05; the objects add a blob on top whose strength varies from frame to frame (lighting) and class
    # to class. Raw heat needs a threshold per class; surprisal needs one.
    rng = np.random.default_rng(4)
    raw = VoxelMapper(GRID, CLASSES)
    normalised = VoxelMapper(GRID, CLASSES, MapperConfig(heatmap_background="surprisal"))
    for T in poses:
        gain = rng.uniform(0.2, 0.6, (len(CLASSES), 1, 1)).astype(np.float32)
        blobs = render_heatmaps(camera, T, objects, len(CLASSES), peak=1.0) * gain
        floor = np.full(blobs.shape, 0.05, np.float32)
        floor[0, camera.height // 2:] = 0.4
        heat = np.clip(np.maximum(floor + rng.uniform(-0.05, 0.05, blobs.shape), blobs + 0.05), 0, 1)
        raw.integrate(heat.astype(np.float32), T, camera)
        normalised.integrate(heat.astype(np.float32), T, camera)
    sizes = {name: tuple(o.size) for name, o in zip(CLASSES, objects)}
    # Raw: at the threshold that keeps the weakest object, the bowl's plateau adds candidates.
    config = ExtractionConfig(threshold=0.3, class_sizes=sizes)
    assert len(raw.extract(config)) > len(objects)
    # Background averages 1 per view (noise over 13 views reaches ~4 somewhere in the grid); the objects more.
    found = normalised.extract(ExtractionConfig(threshold=5.0, class_sizes=sizes))
    assert sorted(f.class_name for f in found) == sorted(CLASSES)
    for f in found:
        truth = objects[CLASSES.index(f.class_name)]
        assert np.linalg.norm(f.position - truth.centre) < 0.02, (f.class_name, f.position, truth.centre)
