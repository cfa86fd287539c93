"""Template matching (eq. 4.3-4.4): the fast detector against the direct equations and against known scenes."""

from __future__ import annotations

import multiprocessing

import cv2
import numpy as np
import pytest

from semloc_core.detection.features import FeatureParams
from semloc_core.detection.templates import (MatchParams, TemplateDetector, build_templates, mask_uniform_background,
                                             template_grid)
from tests.detection.reference import heatmaps_reference, template_reference
from tests.detection.synthetic import make_object, paste, textured_background

KINDS = ("clock", "machine", "can")


def _detector(params=FeatureParams(), scales=(1.0, 0.75, 0.5), template_cells=9, mirror=True):
    templates = []
    for kind in KINDS:
        templates += build_templates(make_object(kind, 120), kind, params, template_cells, mirror=mirror)
    return TemplateDetector(templates, params, MatchParams(scales))


def _peak_pixel(heatmap: np.ndarray, image_shape) -> tuple[float, float]:
    rows, cols = heatmap.shape
    r, q = np.unravel_index(np.argmax(heatmap), heatmap.shape)
    return (q + 0.5) * image_shape[1] / cols - 0.5, (r + 0.5) * image_shape[0] / rows - 0.5


def test_templates_match_reference_construction():
    params = FeatureParams()
    exemplar = make_object("machine", 130)
    fast = build_templates(exemplar, "machine", params, 9)
    slow = template_reference(exemplar, "machine", params, 9)
    for a, b in zip(fast, slow):
        assert a.mirrored == b.mirrored
        np.testing.assert_allclose(a.hoge_root, b.hoge_root, atol=1e-5)
        np.testing.assert_allclose(a.hqc_root, b.hqc_root, atol=1e-6)


@pytest.mark.parametrize("masked, color_space", [(False, "rgb"), (True, "rgb"), (True, "hsv")])
def test_fast_heatmaps_equal_the_direct_equations(masked, color_space):
    """Same numbers as the straightforward implementation: max abs difference <= 1e-4."""
    params = FeatureParams(color_space=color_space)
    templates = []
    for kind in ("clock", "can"):
        exemplar = make_object(kind, 100)
        mask = mask_uniform_background(exemplar) if masked else None
        templates += build_templates(exemplar, kind, params, 7, mask=mask)
    detector = TemplateDetector(templates, params, MatchParams((1.0, 0.6)))
    scene = textured_background(160, 200, seed=5)
    paste(scene, make_object("clock"), (60, 70), 50)
    paste(scene, make_object("can"), (150, 90), 70)
    fast = detector.heatmaps(scene)
    slow = heatmaps_reference(scene, list(detector.templates), params, detector.match.scales)
    assert fast.shape == slow.shape == (2, 20, 25)
    assert np.abs(fast - slow).max() <= 1e-4


def test_exemplar_matches_itself_perfectly():
    """A scene that is exactly the template's view: both features agree block for block, H = 1 at the centre."""
    params = FeatureParams()
    exemplar = make_object("machine", 200)
    rows, cols = template_grid(exemplar.shape[1], exemplar.shape[0], 9)
    view = cv2.resize(exemplar, (cols * params.cell, rows * params.cell), interpolation=cv2.INTER_AREA)
    detector = TemplateDetector(build_templates(exemplar, "machine", params, 9, mirror=False), params,
                                MatchParams((1.0,)))
    heatmap = detector.heatmaps(view)[0]
    assert heatmap[rows // 2, cols // 2] == pytest.approx(1.0, abs=1e-4)
    assert heatmap.max() == pytest.approx(1.0, abs=1e-4)
    assert heatmap.min() >= 0.0


@pytest.mark.parametrize("heights", [(100, 130, 90), (60, 80, 150)])
def test_each_class_peaks_on_its_object(heights):
    """Objects of different sizes on clutter: each class's heatmap peaks within 1.5 cells of its object centre."""
    detector = _detector()
    scene = textured_background(480, 640, seed=1)
    centres = {"clock": (150, 200), "machine": (420, 260), "can": (560, 150)}
    for kind, height in zip(KINDS, heights):
        paste(scene, make_object(kind, 120), centres[kind], height)
    heatmaps = detector.heatmaps(scene)
    assert heatmaps.dtype == np.float32 and heatmaps.shape == (3, 60, 80)
    assert heatmaps.min() >= 0.0 and heatmaps.max() <= 1.0
    for k, kind in enumerate(detector.classes):
        u, v = _peak_pixel(heatmaps[k], scene.shape)
        assert np.hypot(u - centres[kind][0], v - centres[kind][1]) <= 1.5 * 8 * np.sqrt(2), kind
        # Peaky: the peak stands well above the class's typical response.
        assert heatmaps[k].max() > 3 * np.median(heatmaps[k])


def test_mirrored_template_finds_the_flipped_object():
    params = FeatureParams()
    exemplar = make_object("arrow", 120)
    scene = textured_background(240, 320, seed=2)
    paste(scene, exemplar[:, ::-1], (160, 120), 110)
    with_mirror = TemplateDetector(build_templates(exemplar, "arrow", params, 9, mirror=True), params)
    without = TemplateDetector(build_templates(exemplar, "arrow", params, 9, mirror=False), params)
    assert with_mirror.heatmaps(scene).max() > without.heatmaps(scene).max() + 0.1


def test_levels_for_object_sizes_and_heatmaps_on_those_levels():
    """A level answers objects about a template long (template_cells x cell / scale pixels); matching only the
    levels kept is the max over those levels, as a detector built with just them."""
    detector = _detector(scales=(1.2, 0.85, 0.6, 0.42))
    template_px = 9 * detector.params.cell
    assert detector.levels_for(template_px / 1.2, template_px / 1.2) == (1.2,)
    assert detector.levels_for(template_px / 0.85 * 0.99, template_px / 0.6 * 1.01) == (0.85, 0.6)
    assert detector.levels_for(1.0, 1e4) == detector.match.scales
    assert detector.levels_for(1e4, 2e4) == (0.42,)   # larger than every level: the nearest one
    scene = textured_background(240, 320, seed=2)
    paste(scene, make_object("clock"), (160, 120), 90)
    only = TemplateDetector(detector.templates, detector.params, MatchParams((0.85, 0.42)))
    np.testing.assert_allclose(detector.heatmaps(scene, scales=(0.85, 0.42)), only.heatmaps(scene), atol=1e-6)
    assert np.all(detector.heatmaps(scene) >= detector.heatmaps(scene, scales=(0.85,)) - 1e-6)
    with pytest.raises(ValueError, match="subset"):
        detector.heatmaps(scene, scales=(0.5,))
    with pytest.raises(ValueError, match="smallest_px"):
        detector.levels_for(50, 10)


@pytest.mark.parametrize("threads", [2, 3])
def test_levels_on_threads_give_the_same_heatmaps(threads):
    """Levels matched concurrently (groups of about equal pixel counts) give the serial heatmaps to the bit, on every
    level and on a subset, frame after frame (each group keeps its own buffers)."""
    serial = _detector(scales=(1.2, 0.85, 0.6, 0.42))
    threaded = TemplateDetector(serial.templates, serial.params, serial.match, threads=threads)
    for seed in (3, 4):
        scene = textured_background(240, 320, seed=seed)
        paste(scene, make_object("clock"), (100 + 40 * seed, 120), 90)
        paste(scene, make_object("can"), (80, 60), 60)
        np.testing.assert_array_equal(threaded.heatmaps(scene), serial.heatmaps(scene))
        np.testing.assert_array_equal(threaded.heatmaps(scene, scales=(0.85, 0.42)),
                                      serial.heatmaps(scene, scales=(0.85, 0.42)))
        for a, b in zip(threaded.template_heatmaps(scene), serial.template_heatmaps(scene)):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="threads"):
        TemplateDetector(serial.templates, serial.params, serial.match, threads=0)
    # two levels of one cell grid (1.0 and 1.01 of 240 x 320 on 8-px cells) share buffers: they run on one thread
    close = MatchParams((1.0, 1.01, 0.5))
    np.testing.assert_array_equal(TemplateDetector(serial.templates, serial.params, close, threads=threads)
                                  .heatmaps(scene), TemplateDetector(serial.templates, serial.params, close)
                                  .heatmaps(scene))


def _heatmaps_to_file(detector, scene, path):
    np.save(path, detector.heatmaps(scene))


def test_levels_on_threads_in_a_forked_child(tmp_path):
    """A process forked from one whose detector already ran its threads (the fork copies no thread) still gets its
    heatmaps: the detector starts its threads again."""
    serial = _detector(scales=(1.0, 0.6))
    threaded = TemplateDetector(serial.templates, serial.params, serial.match, threads=2)
    scene = textured_background(160, 200, seed=6)
    paste(scene, make_object("machine"), (100, 80), 70)
    expected = serial.heatmaps(scene)
    np.testing.assert_array_equal(threaded.heatmaps(scene), expected)
    child = multiprocessing.get_context("fork").Process(target=_heatmaps_to_file,
                                                        args=(threaded, scene, tmp_path / "child.npy"))
    child.start()
    child.join(120)
    assert child.exitcode == 0
    np.testing.assert_array_equal(np.load(tmp_path / "child.npy"), expected)


def test_mask_from_plain_background_keeps_white_parts_inside_the_object():
    exemplar = np.full((60, 40, 3), 250, np.uint8)
    cv2.rectangle(exemplar, (10, 10), (30, 50), (20, 40, 200), -1)
    cv2.rectangle(exemplar, (15, 20), (25, 30), (250, 250, 250), -1)   # a white label on the object
    mask = mask_uniform_background(exemplar)
    assert mask[25, 20] and mask[12, 12] and not mask[2, 2] and not mask[55, 35]


def test_bad_inputs_raise_clear_errors():
    params = FeatureParams()
    with pytest.raises(ValueError, match="uint8 BGR"):
        build_templates(np.zeros((20, 20), np.uint8), "x", params)
    with pytest.raises(ValueError, match="odd"):
        build_templates(make_object("can"), "x", params, template_cells=8)
    detector = TemplateDetector(build_templates(make_object("can"), "can", params), params)
    with pytest.raises(ValueError, match="uint8 BGR"):
        detector.heatmaps(np.zeros((100, 100, 3), np.float32))
    with pytest.raises(ValueError):
        MatchParams(())
