"""Non-maximum suppression, class scales, cross-class suppression and their calibration on hand-made volumes."""

import numpy as np
import pytest

from semloc_core.io.semantic_map import SemanticMap
from semloc_core.mapping import ExtractionConfig, VoxelGrid
from semloc_core.mapping.backprojection import remove_background
from semloc_core.mapping.extraction import calibrate_class_scales, extract_all, extract_objects

GRID = VoxelGrid.from_bounds([0, 0, 0], [1.0, 1.0, 0.4], 0.02)


def _blob(centre, peak=1.0, sigma=0.03):
    z, y, x = (GRID.axis_centres(a) for a in (2, 1, 0))
    d2 = ((x[None, None, :] - centre[0]) ** 2 + (y[None, :, None] - centre[1]) ** 2
          + (z[:, None, None] - centre[2]) ** 2)
    return (peak * np.exp(-d2 / (2 * sigma**2))).astype(np.float32)


def test_peaks_found_suppressed_and_refined():
    centres = [(0.305, 0.41, 0.15), (0.70, 0.62, 0.2)]
    score = _blob(centres[0]) + _blob(centres[1], 0.8)
    # A weaker bump 6 cm from the first object: inside its 20 cm bounding volume, so suppressed.
    score += _blob((0.365, 0.41, 0.15), 0.6, 0.01)
    found = extract_objects(score, GRID, "bowl", (0.2, 0.2, 0.2), threshold=0.5)
    # Peaks sampled at voxel centres up to 1 cm (half a voxel per axis) from the blob centres.
    assert [o.score for o in found] == pytest.approx([1.0, 0.8 * np.exp(-3 * 0.01**2 / (2 * 0.03**2))], abs=0.02)
    for obj, centre in zip(found, centres):
        assert np.linalg.norm(obj.position - centre) < 0.004  # sub-voxel (voxel = 2 cm)
        assert np.all(obj.extent > 0.04) and np.all(obj.extent < 0.2)
    # With a small bounding volume the bump is an object of its own.
    assert len(extract_objects(score, GRID, "bowl", (0.04, 0.04, 0.04), threshold=0.5)) == 3
    assert extract_objects(score, GRID, "bowl", (0.2, 0.2, 0.2), threshold=1.1) == []


def test_peak_on_the_border_is_rejected():
    score = _blob((0.99, 0.5, 0.2))  # the true peak lies outside the box: only its flank is inside
    assert extract_objects(score, GRID, "cap", (0.1, 0.1, 0.1), threshold=0.1) == []
    assert len(extract_objects(score, GRID, "cap", (0.1, 0.1, 0.1), threshold=0.1, reject_border=False)) == 1


def test_cross_class_suppression_keeps_the_stronger_class():
    mug = (0.5, 0.5, 0.1)
    scores = {"coffee_mug": _blob(mug, 0.9), "bowl": _blob((0.51, 0.5, 0.1), 0.7) + _blob((0.2, 0.2, 0.1), 0.7)}
    sizes = {"coffee_mug": (0.12, 0.12, 0.12), "bowl": (0.18, 0.18, 0.08)}
    separate = extract_all(scores, GRID, sizes, 0.5)
    assert sorted(o.class_name for o in separate) == ["bowl", "bowl", "coffee_mug"]
    joint = extract_all(scores, GRID, sizes, 0.5, cross_class=True)
    assert sorted((o.class_name, round(o.position[0], 1)) for o in joint) == [("bowl", 0.2), ("coffee_mug", 0.5)]


def test_class_scales_calibrated_from_truth():
    # Positions on voxel centres, so that the blobs' peaks are sampled exactly.
    truth = SemanticMap.from_objects([{"class": "bowl", "position": [0.31, 0.31, 0.11]},
                                      {"class": "bowl", "position": [0.71, 0.71, 0.11]},
                                      {"class": "cap", "position": [0.51, 0.21, 0.11]}], bounds=[[0, 0], [1, 1]])
    scores = {"bowl": _blob((0.31, 0.31, 0.11), 0.4) + _blob((0.71, 0.71, 0.11), 0.6),
              "cap": _blob((0.53, 0.21, 0.11), 0.2), "soda_can": _blob((0.51, 0.51, 0.11), 0.9)}
    scales = calibrate_class_scales(scores, GRID, truth, radius=0.05)
    assert set(scales) == {"bowl", "cap"}  # no soda can in the truth: no scale
    assert scales["bowl"] == pytest.approx(0.5, abs=0.01)  # median of 0.4 and 0.6
    assert scales["cap"] == pytest.approx(0.2, abs=0.01)


def test_background_removal_subtracts_each_class_median():
    rng = np.random.default_rng(0)
    heat = np.stack([np.full((20, 30), 0.2), np.full((20, 30), 0.05)]).astype(np.float32)
    heat[0, 5:8, 5:8] = 0.9
    heat[1] += rng.uniform(0, 0.01, (20, 30)).astype(np.float32)
    out = remove_background(heat)
    assert out[0, 6, 6] == pytest.approx(0.7) and out[0, 0, 0] == 0
    assert out.min() >= 0 and np.mean(out[1] == 0) >= 0.5  # half the pixels are at or below the median


def test_tophat_removes_plateaus_and_keeps_object_sized_bumps():
    from semloc_core.mapping.extraction import white_tophat

    plateau = np.zeros(GRID.volume_shape, np.float32)
    plateau[:8, 10:40, 5:45] = 0.6  # a table-wide response 60 x 80 cm
    plateau += np.random.default_rng(1).uniform(0, 0.02, plateau.shape).astype(np.float32)
    score = plateau + _blob((0.31, 0.71, 0.11), 0.5)
    flat = white_tophat(score, (0.12, 0.12, 0.12), GRID.voxel_size, 2.0)
    assert flat.min() >= 0
    assert flat[3, 20:30, 15:35].max() < 0.1  # the plateau's inside is gone
    found = extract_objects(flat, GRID, "bowl", (0.12, 0.12, 0.12), threshold=0.3)
    assert len(found) == 1 and np.linalg.norm(found[0].position - (0.31, 0.71, 0.11)) < 0.01
    assert len(extract_objects(score, GRID, "bowl", (0.12, 0.12, 0.12), threshold=0.3)) > 3


@pytest.mark.parametrize("position", ["centroid", "mode"])
def test_mass_positions_are_sub_voxel_on_peaks_and_centred_on_plateaus(position):
    centres = [(0.305, 0.41, 0.15), (0.70, 0.62, 0.2)]
    score = _blob(centres[0]) + _blob(centres[1], 0.8)
    for obj, centre in zip(extract_all({"bowl": score}, GRID, {"bowl": (0.2, 0.2, 0.2)}, 0.5, position=position),
                           centres):
        assert np.linalg.norm(obj.position - centre) < 0.004  # as the parabola, on a symmetric peak
    # A template answering on a large uniform face: a flat top 12 cm wide with a small bump on one side. The
    # maximum sits on the bump, 5 cm from the object's centre; the centroid of the mass above half the peak, and
    # the maximum of that mass smoothed at 2 cm (one voxel here), stay within 1 cm.
    centre = np.array([0.5, 0.5, 0.1])
    z, y, x = (GRID.axis_centres(a) for a in (2, 1, 0))
    inside = ((np.abs(x[None, None, :] - centre[0]) <= 0.06) & (np.abs(y[None, :, None] - centre[1]) <= 0.06)
              & (np.abs(z[:, None, None] - centre[2]) <= 0.04))
    flat = np.where(inside, 0.9, 0.0).astype(np.float32) + _blob(centre + [0.05, 0.0, 0.0], 0.1, 0.01)
    (peak,) = extract_all({"cap": flat}, GRID, {"cap": (0.26, 0.26, 0.1)}, 0.5)
    (mass,) = extract_all({"cap": flat}, GRID, {"cap": (0.26, 0.26, 0.1)}, 0.5, position=position)
    assert np.linalg.norm(peak.position - centre) > 0.04
    assert np.linalg.norm(mass.position - centre) < 0.01


def test_unknown_position_estimators_and_bad_supports_are_refused():
    with pytest.raises(ValueError, match="position"):
        extract_all({"cap": _blob((0.5, 0.5, 0.1))}, GRID, {"cap": (0.26, 0.26, 0.1)}, 0.5, position="middle")
    with pytest.raises(ValueError, match="position"):
        ExtractionConfig(position="middle")
    with pytest.raises(ValueError, match="mode_bandwidth"):
        ExtractionConfig(position="mode", mode_bandwidth=0.0)
    with pytest.raises(ValueError, match="support_polygon"):
        ExtractionConfig(support_polygon=[(0, 0), (1, 1)])
    with pytest.raises(ValueError, match="support_polygon"):
        ExtractionConfig(support_polygon=[(0, 0), (1, 0), (np.nan, 1)])


def test_objects_rest_over_the_support_polygon():
    # A table 60 x 40 cm; one object on it, a stronger answer beyond its edge (the floor, a chair).
    table = [(0.2, 0.3), (0.8, 0.3), (0.8, 0.7), (0.2, 0.7)]
    score = _blob((0.5, 0.5, 0.1), 0.8) + _blob((0.9, 0.5, 0.1), 1.0)
    sizes = {"bowl": (0.18, 0.18, 0.08)}
    assert len(extract_all({"bowl": score}, GRID, sizes, 0.5)) == 2
    (on_table,) = extract_all({"bowl": score}, GRID, sizes, 0.5, support_polygon=table)
    assert np.linalg.norm(on_table.position - (0.5, 0.5, 0.1)) < 0.004
    # The polygon's orientation does not matter.
    assert len(extract_all({"bowl": score}, GRID, sizes, 0.5, support_polygon=table[::-1])) == 1


def test_centroid_suppression_takes_a_flat_top_with_two_maxima_as_one_object():
    # A cap's crown: a flat top 24 cm wide whose two ends answer a little more strongly, 16 cm apart - more than
    # half the 26 cm bounding volume, so suppression around the first maximum leaves the second one.
    centre = np.array([0.5, 0.5, 0.1])
    z, y, x = (GRID.axis_centres(a) for a in (2, 1, 0))
    inside = ((np.abs(x[None, None, :] - centre[0]) <= 0.12) & (np.abs(y[None, :, None] - centre[1]) <= 0.05)
              & (np.abs(z[:, None, None] - centre[2]) <= 0.04))
    score = (np.where(inside, 0.8, 0.0) + _blob(centre - [0.08, 0, 0], 0.2, 0.02)
             + _blob(centre + [0.08, 0, 0], 0.19, 0.02)).astype(np.float32)
    sizes = {"cap": (0.26, 0.26, 0.1)}
    assert len(extract_all({"cap": score}, GRID, sizes, 0.5)) == 2
    (one,) = extract_all({"cap": score}, GRID, sizes, 0.5, position="centroid")
    assert np.linalg.norm(one.position - centre) < 0.015


def _cone(apex, direction, length, peak, sigma=0.03):
    """A ridge of score from ``apex`` along ``direction`` (a back-projected object seen from one side), falling to
    0.85 of ``peak`` at ``length``."""
    z, y, x = (GRID.axis_centres(a) for a in (2, 1, 0))
    points = np.stack(np.broadcast_arrays(x[None, None, :], y[None, :, None], z[:, None, None]), axis=-1)
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    along = np.clip((points - apex) @ direction, 0.0, length)
    off = np.linalg.norm(points - (np.asarray(apex) + along[..., None] * direction), axis=-1)
    return (peak * (1.0 - 0.15 * along / length) * np.exp(-off**2 / (2 * sigma**2))).astype(np.float32)


@pytest.mark.parametrize("position", ["peak", "centroid"])
def test_a_shoulder_on_an_objects_cone_is_not_a_second_object(position):
    can = np.array([0.40, 0.50, 0.10])
    # The cone behind the can holds a second maximum 18 cm along it (the view rays' far end), a soda can's
    # bounding volume (8 x 8 x 14 cm) away from the can: without prominence it is a second can.
    score = _cone(can, (1.0, -0.8, 0.0), 0.2, 1.0) + _blob(can + [0.14, -0.112, 0.0], 0.1, 0.012)
    size = {"soda_can": (0.08, 0.08, 0.14)}
    assert len(extract_all({"soda_can": score}, GRID, size, 0.5, position=position)) == 2
    (only,) = extract_all({"soda_can": score}, GRID, size, 0.5, position=position, prominence=0.8)
    assert np.linalg.norm(only.position[:2] - can[:2]) < 0.05
    # Two cans 18 cm apart with a dip between them stay two cans.
    pair = _blob(can, 1.0, 0.02) + _blob(can + [0.14, -0.112, 0.0], 0.9, 0.02)
    assert len(extract_all({"soda_can": pair}, GRID, size, 0.5, position=position, prominence=0.8)) == 2
    with pytest.raises(ValueError, match="prominence"):
        ExtractionConfig(prominence=1.0)


@pytest.mark.parametrize("size", [(3, 3, 3), (11, 27, 27), (1, 5, 3), (41, 41, 41)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_box_filter_is_scipys_min_and_max_filter(size, dtype):
    from scipy import ndimage

    from semloc_core.mapping.extraction import box_filter

    rng = np.random.default_rng(1)
    volume = rng.normal(size=(9, 30, 25)).astype(dtype)
    volume[:, :, :2] = -np.inf  # what the candidates' band and footprint set outside them
    volume.flat[::7] = volume.flat[3]  # plateaus
    for kind, reference in (("min", ndimage.minimum_filter), ("max", ndimage.maximum_filter)):
        out = box_filter(volume, size, kind)
        assert out.dtype == dtype
        np.testing.assert_array_equal(out, reference(volume, size=size, mode="nearest"))
