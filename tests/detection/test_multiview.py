"""Multi-view dominant-orientation templates (§5.3, eq. 5.1)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.detection.multiview import (MultiViewDetector, OrientationParams, build_view_template,
                                             quantised_orientations, similarity_tables, spread_orientations)
from tests.detection.synthetic import make_object, paste, textured_background


def test_similarity_table_is_max_abs_cosine_over_present_orientations():
    tables = similarity_tables(8)
    assert tables[3, 0] == 0.0                                  # nothing present
    assert tables[3, 1 << 3] == pytest.approx(1.0)              # the same orientation
    assert tables[0, 1 << 4] == pytest.approx(0.0, abs=1e-7)    # perpendicular
    assert tables[0, (1 << 4) | (1 << 2)] == pytest.approx(np.cos(np.pi / 4))
    assert tables[0, 1 << 7] == pytest.approx(np.cos(np.pi / 8))   # orientation wraps at pi


def test_spreading_ors_the_neighbourhood():
    bins = np.full((9, 9), -1)
    bins[4, 4] = 2
    bins[4, 5] = 5
    spread = spread_orientations(bins, 3)
    assert spread[4, 4] == (1 << 2) | (1 << 5)
    assert spread[3, 3] == 1 << 2 and spread[3, 6] == 1 << 5
    assert spread[0, 0] == 0 and spread[4, 7] == 0


def test_orientation_ignores_gradient_polarity():
    params = OrientationParams()
    image = np.zeros((32, 32), np.uint8)
    image[:, 16:] = 200
    dark_to_light, _ = quantised_orientations(image, params)
    light_to_dark, _ = quantised_orientations(255 - image, params)
    np.testing.assert_array_equal(dark_to_light, light_to_dark)
    assert set(np.unique(dark_to_light[:, 15:17])) == {0}   # vertical edge: horizontal gradient, bin 0


def test_view_matches_itself_with_score_one():
    params = OrientationParams(scales=(1.0,))
    view = make_object("machine", 160)
    template = build_view_template(view, "machine", params)
    assert 1 <= len(template.offsets) <= params.max_features
    image = np.full((160, 160, 3), 128, np.uint8)
    resized = cv2.resize(view, template.size, interpolation=cv2.INTER_AREA)
    top, left = 60, 64
    image[top:top + template.size[1], left:left + template.size[0]] = resized
    heatmap = MultiViewDetector([template], params).heatmaps(image)[0]
    centre_u = left + (template.size[0] - 1) // 2
    centre_v = top + (template.size[1] - 1) // 2
    r, q = np.unravel_index(np.argmax(heatmap), heatmap.shape)
    assert heatmap.max() == pytest.approx(1.0, abs=1e-6)
    assert abs(q * params.spread + (params.spread - 1) // 2 - centre_u) < params.spread
    assert abs(r * params.spread + (params.spread - 1) // 2 - centre_v) < params.spread


def test_multiview_peaks_at_each_object_across_views_and_sizes():
    params = OrientationParams()
    views = [build_view_template(make_object(kind, 120), kind, params) for kind in ("clock", "machine", "can")]
    # A second view of the machine (mirrored) must not hurt: the class score is the max over views.
    views.append(build_view_template(make_object("machine", 120)[:, ::-1].copy(), "machine", params))
    detector = MultiViewDetector(views, params)
    scene = textured_background(480, 640, seed=1)
    centres = {"clock": (150, 200), "machine": (420, 260), "can": (560, 150)}
    for (kind, centre), height in zip(centres.items(), (64, 85, 120)):
        paste(scene, make_object(kind, 120), centre, height)
    heatmaps = detector.heatmaps(scene)
    assert heatmaps.shape == (3, 120, 160) and heatmaps.min() >= 0 and heatmaps.max() <= 1.0 + 1e-6
    for k, kind in enumerate(detector.classes):
        r, q = np.unravel_index(np.argmax(heatmaps[k]), heatmaps[k].shape)
        u, v = (q + 0.5) * 4 - 0.5, (r + 0.5) * 4 - 0.5
        assert np.hypot(u - centres[kind][0], v - centres[kind][1]) < 10, kind


def test_view_without_gradients_is_rejected():
    with pytest.raises(ValueError, match="no gradient"):
        build_view_template(np.full((40, 40, 3), 90, np.uint8), "flat")
