"""Box detectors made soft (§4.6.2): the adapter on hand-made boxes, the shipped OpenCV detectors, the plug-ins."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.detection.boxes import (BoxHeatmapDetector, HaarCascadeDetector, HogPeopleDetector, ScoreSquash,
                                         box_centres, boxes_to_heatmap)
from semloc_core.detection.config import build_detector
from semloc_core.io.detector_models import DetectorModelError, load_cascade
from tests.detection.onnx_builder import constant_detections_model
from tests.detection.synthetic import textured_background


def _nearest_neighbour_check(heatmap, scored_cells: dict):
    """Every scored cell holds its max score; every other cell the score of one of its nearest scored cells."""
    rows, cols = heatmap.shape
    cells = np.array(list(scored_cells))
    values = np.array([scored_cells[c] for c in scored_cells], np.float32)
    rr, qq = np.mgrid[0:rows, 0:cols]
    distance = (rr[..., None] - cells[:, 0]) ** 2 + (qq[..., None] - cells[:, 1]) ** 2
    nearest = distance == distance.min(axis=-1, keepdims=True)
    assert np.all(np.any(nearest & (values == heatmap[..., None]), axis=-1))
    for (r, q), value in scored_cells.items():
        assert heatmap[r, q] == pytest.approx(value)


def test_box_centres_of_integer_pixel_boxes():
    np.testing.assert_allclose(box_centres([[10, 20, 5, 7], [0, 0, 4, 4]]), [[12, 23], [1.5, 1.5]])


def test_adapter_is_exact_on_hand_made_boxes():
    """Centre pixel takes the max of the boxes centred on it; everything else its nearest scored pixel."""
    boxes = np.array([[10, 10, 5, 5],     # centre (12, 12)
                      [8, 8, 9, 9],       # centre (12, 12) too, lower score: the max wins
                      [30, 5, 11, 3],     # centre (35, 6)
                      [0, 25, 4, 6],      # centre (1.5, 27.5) -> rounds half up to pixel (2, 28)
                      [70, 70, 5, 5]])    # centred outside the 40 x 32 image: ignored
    scores = np.array([0.9, 0.3, 0.5, 0.7, 5.0])
    heatmap = boxes_to_heatmap(boxes, scores, (40, 32))
    assert heatmap.shape == (32, 40) and heatmap.dtype == np.float32
    _nearest_neighbour_check(heatmap, {(12, 12): 0.9, (6, 35): 0.5, (28, 2): 0.7})


def test_adapter_on_a_coarser_grid():
    heatmap = boxes_to_heatmap([[10, 10, 5, 5], [30, 5, 11, 3]], [0.9, 0.5], (40, 32), out_shape=(8, 10))
    _nearest_neighbour_check(heatmap, {(3, 3): 0.9, (1, 8): 0.5})   # pixel (12,12) -> cell (3,3); (35,6) -> (1,8)


def test_adapter_without_boxes_and_with_bad_input():
    np.testing.assert_array_equal(boxes_to_heatmap(np.zeros((0, 4)), [], (8, 6), empty_value=0.25),
                                  np.full((6, 8), 0.25, np.float32))
    with pytest.raises(ValueError, match="2 boxes but 1 scores"):
        boxes_to_heatmap([[0, 0, 2, 2], [1, 1, 2, 2]], [0.5], (8, 6))
    assert boxes_to_heatmap([[0, 0, 2, 2], [np.nan, 0, 2, 2]], [0.5, 0.9], (8, 6)).max() == pytest.approx(0.5)


def test_squash_is_monotone_into_the_unit_interval():
    squash = ScoreSquash("logistic", centre=1.0, width=0.5)
    values = squash(np.array([-1e6, -3.0, 1.0, 2.0, 1e6]))
    assert np.all(np.diff(values) >= 0) and values[0] == 0.0 and values[-1] == 1.0 and values[2] == 0.5


def _person_scene() -> np.ndarray:
    image = (textured_background(240, 320, seed=4) * 0.3 + 150).astype(np.uint8)
    cx, top, h, dark = 200, 60, 110, (30, 30, 30)
    cv2.circle(image, (cx, top + h // 10), h // 10, dark, -1)
    cv2.ellipse(image, (cx, top + int(h * 0.38)), (h // 8, int(h * 0.2)), 0, 0, 360, dark, -1)
    for side in (-1, 1):
        cv2.line(image, (cx + side * h // 20, top + int(h * 0.55)), (cx + side * h // 10, top + h), dark, h // 14)
        cv2.line(image, (cx + side * h // 8, top + int(h * 0.22)), (cx + side * h // 6, top + int(h * 0.55)), dark,
                 h // 20)
    return image


@pytest.mark.parametrize("make", [
    lambda: HogPeopleDetector(),
    lambda: HaarCascadeDetector(load_cascade("haarcascade_fullbody.xml"), "person", scale_factor=1.05),
])
def test_shipped_detector_heatmap_peaks_at_its_best_box(make):
    detector = make()
    image = _person_scene()
    boxes, scores = detector.detect(image)[0]
    assert len(boxes) > 0
    best = np.argmax(scores)
    squash = ScoreSquash("logistic", 0.0, 1.0)
    heatmap = BoxHeatmapDetector(detector, squash, cell=1).heatmaps(image)[0]
    u, v = np.floor(box_centres(boxes[best])[0] + 0.5).astype(int)
    # The best box's centre pixel holds the maximum, which is the best box's own (squashed) score ...
    assert heatmap[v, u] == heatmap.max() == pytest.approx(float(squash(scores[best])), rel=1e-6)
    # ... and the maximum spreads by nearest-neighbour fill only over pixels closer to that centre than to any
    # other scored centre (the plateau is the centre's own Voronoi cell).
    centres = np.floor(box_centres(boxes) + 0.5)
    others = centres[np.any(centres != (u, v), axis=1)]
    vv, uu = np.nonzero(heatmap == heatmap.max())
    to_best = (uu - u) ** 2 + (vv - v) ** 2
    to_others = ((uu[:, None] - others[:, 0]) ** 2 + (vv[:, None] - others[:, 1]) ** 2).min(axis=1)
    assert np.all(to_best <= to_others)


def test_hog_people_detector_scores_the_person_highest():
    image = _person_scene()
    boxes, scores = HogPeopleDetector().detect(image)[0]
    assert len(scores) > 1000   # dense: threshold -inf, no grouping
    u, v = box_centres(boxes[np.argmax(scores)])[0]
    assert abs(u - 200) < 16 and abs(v - 115) < 16


def test_dnn_plugin_runs_a_user_onnx_model(tmp_path):
    """SSD-style model file -> config in a few lines -> heatmaps; the image really flows through the network."""
    table = np.array([[[[0, 1, 0.2, 0.10, 0.20, 0.30, 0.60],    # class 1, box (0.1..0.3, 0.2..0.6)
                        [0, 2, 0.1, 0.50, 0.50, 0.70, 0.90],
                        [0, 1, 0.05, 0.60, 0.10, 0.80, 0.30]]]], np.float32)
    model = tmp_path / "toy.onnx"
    model.write_bytes(constant_detections_model(table, (64, 64), score_column=2))
    config = {"kind": "dnn", "model": str(model), "classes": {1: "cup", 2: "bowl"}, "input_size": [64, 64],
              "output": "ssd", "heatmap_cell": 1}
    detector = build_detector(config)
    assert detector.classes == ("cup", "bowl")
    dark = np.zeros((100, 200, 3), np.uint8)
    heatmaps = detector.heatmaps(dark)
    u, v = np.floor(box_centres([[0.1 * 200, 0.2 * 100, 0.2 * 200, 0.4 * 100]])[0] + 0.5).astype(int)
    assert heatmaps[0, v, u] == heatmaps[0].max() == pytest.approx(0.2, abs=1e-6)
    u2, v2 = np.floor(box_centres([[0.6 * 200, 0.1 * 100, 0.2 * 200, 0.2 * 100]])[0] + 0.5).astype(int)
    assert heatmaps[0, v2, u2] == pytest.approx(0.05, abs=1e-6)
    grey = np.full((100, 200, 3), 255, np.uint8)   # mean input 1.0 after scaling: every score + 1, clipped to 1
    assert build_detector(config).heatmaps(grey)[1].max() == pytest.approx(1.0)


def test_yolo_output_layout(tmp_path):
    rows = np.array([[[32, 16, 8, 8, 0.1, 0.7], [10, 40, 4, 4, 0.6, 0.2]]], np.float32)   # (1, N, 4 + C)
    model = tmp_path / "yolo.onnx"
    model.write_bytes(constant_detections_model(rows, (64, 64), score_column=0))
    config = {"kind": "dnn", "model": str(model), "classes": {0: "a", 1: "b"}, "input_size": [64, 64],
              "output": "yolo", "yolo_layout": "rows", "heatmap_cell": 1}
    heatmaps = build_detector(config).heatmaps(np.zeros((64, 64, 3), np.uint8))
    u, v = np.floor(box_centres([[28, 12, 8, 8]])[0] + 0.5).astype(int)
    assert heatmaps[1, v, u] == heatmaps[1].max() == pytest.approx(0.7)
    assert heatmaps[0, 40, 10] == heatmaps[0].max() == pytest.approx(0.6)   # box (8, 38, 4, 4) -> pixel (10, 40)


class _FixedBoxes:
    classes = ("thing",)

    def __init__(self, x: int = 5):
        self.x = x

    def detect(self, image):
        return [(np.array([[self.x, 5, 4, 4]]), np.array([3.0]))]


def make_fixed_boxes(x: int = 5):
    return _FixedBoxes(x)


def test_python_plugin_from_config():
    detector = build_detector({"kind": "python", "factory": f"{__name__}:make_fixed_boxes", "options": {"x": 9},
                               "heatmap_cell": 1, "squash": {"kind": "logistic", "centre": 3.0}})
    heatmap = detector.heatmaps(np.zeros((20, 20, 3), np.uint8))[0]
    np.testing.assert_allclose(heatmap, 0.5)   # one box: NN fill everywhere with its squashed score
    with pytest.raises(DetectorModelError, match="cannot import"):
        build_detector({"kind": "python", "factory": "no_such_module_xyz:make"})


def test_unknown_cascade_and_missing_model_are_clear_errors(tmp_path):
    with pytest.raises(DetectorModelError, match="shipped"):
        load_cascade("no_such_cascade.xml")
    with pytest.raises(DetectorModelError, match="does not exist"):
        build_detector({"kind": "dnn", "model": str(tmp_path / "missing.onnx"), "classes": {0: "x"}})
    with pytest.raises(DetectorModelError, match="invalid detector configuration"):
        build_detector({"kind": "haar", "scale_factor": 0.5})


def test_hog_people_detector_pairs_every_box_with_its_own_weight():
    # OpenCV's parallel detectMultiScale can pair boxes with another pyramid level's weights; the detector walks
    # the levels itself and must give exactly what a single-threaded detectMultiScale gives, call after call.
    detector = HogPeopleDetector()
    image = _person_scene()
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rects, weights = detector._hog.detectMultiScale(image, hitThreshold=-1e9, winStride=detector.win_stride,
                                                        padding=(0, 0), scale=detector.scale, groupThreshold=0)
    finally:
        cv2.setNumThreads(previous)
    expected = {(*map(float, r), float(w)) for r, w in zip(np.asarray(rects).reshape(-1, 4), np.ravel(weights))}
    for _ in range(20):
        boxes, scores = detector.detect(image)[0]
        assert {(*map(float, b), float(w)) for b, w in zip(boxes, scores)} == expected
