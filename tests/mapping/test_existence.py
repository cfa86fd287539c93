"""Existence probability of mapped objects: the logistic fit on calibration candidates, its file form, and the
exported map carrying it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.io.semantic_map import MapFormatError, SemanticMap, load_semantic_map, save_semantic_map
from semloc_core.mapping.existence import ExistenceCurve, fit_existence
from semloc_core.mapping.extraction import ExtractionConfig, MappedObject, objects_to_semantic_map
from semloc_core.mapping.grid import VoxelGrid


@pytest.mark.parametrize("intercept, slope", [(0.5, 4.0), (2.0, 8.0), (-1.0, 3.0)])
def test_the_fit_recovers_the_curve_that_drew_the_labels(intercept, slope):
    rng = np.random.default_rng(int(10 * slope))
    reference = 0.65
    scores = reference * np.exp(rng.uniform(-0.7, 0.7, 4000))
    truth = ExistenceCurve(reference, intercept, slope)
    real = rng.random(scores.size) < truth(scores)
    curve = fit_existence(scores, real, reference)
    assert curve.samples == 4000 and curve.real == int(real.sum())
    assert curve.intercept == pytest.approx(intercept, abs=0.25)
    assert curve.slope == pytest.approx(slope, rel=0.15)
    grid = reference * np.exp(np.linspace(-0.7, 0.7, 50))
    assert np.abs(curve(grid) - truth(grid)).max() < 0.05


def test_a_separating_calibration_stays_finite_and_ordered():
    """Every candidate above the threshold real, every one below false: the prior keeps the slope finite, the
    curve rises through the threshold and never reaches 0 or exceeds 1."""
    scores = np.array([0.35, 0.4, 0.45, 0.5, 0.55, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2])
    real = scores > 0.65
    curve = fit_existence(scores, real, 0.65)
    assert math.isfinite(curve.slope) and curve.slope > 5
    probabilities = curve(np.array([0.3, 0.5, 0.65, 0.8, 1.3, 1e6, 0.0]))
    assert np.all(np.diff(probabilities[:6]) >= 0)
    assert probabilities[1] < 0.5 < probabilities[3]
    assert np.all((probabilities > 0) & (probabilities <= 1))


def test_a_look_alike_above_the_threshold_lowers_the_curve_there():
    rng = np.random.default_rng(3)
    scores = 0.65 * np.exp(rng.uniform(-0.6, 0.6, 200))
    clean = fit_existence(scores, scores > 0.65, 0.65)
    noisy_labels = (scores > 0.65) & (rng.random(200) > 0.3)  # 30 % of those above are look-alikes
    noisy = fit_existence(scores, noisy_labels, 0.65)
    assert noisy(0.8)[()] < clean(0.8)[()] - 0.1


@pytest.mark.parametrize("scores, real, reference, message", [
    ([], [], 0.5, "no candidates"),
    ([0.5, -1.0], [True, False], 0.5, "positive and finite"),
    ([0.5, np.nan], [True, False], 0.5, "positive and finite"),
    ([0.5, 0.6], [True], 0.5, "alike"),
    ([0.5, 0.6], [True, False], 0.0, "positive"),
])
def test_bad_samples_are_refused(scores, real, reference, message):
    with pytest.raises(ValueError, match=message):
        fit_existence(scores, real, reference)


def test_the_curve_round_trips_and_bad_documents_are_refused():
    curve = ExistenceCurve(0.65, 1.2, 9.5, samples=69, real=57)
    again = ExistenceCurve.from_document(curve.to_document())
    assert again == curve
    for document in ({"reference": 0.65, "intercept": 1.0}, {"reference": 0.65, "intercept": 1.0, "slope": "x"},
                     {"reference": 0.0, "intercept": 1.0, "slope": 1.0},
                     {"reference": 0.65, "intercept": 1.0, "slope": -1.0}, [1, 2, 3]):
        with pytest.raises(ValueError):
            ExistenceCurve.from_document(document)
    # The extraction reads a curve's document as the curve, checked as the curve checks it.
    assert ExtractionConfig(existence=curve.to_document()).existence == curve
    with pytest.raises(ValueError, match="existence.intercept: Field required"):
        ExtractionConfig(existence={"reference": 0.65})


def test_the_exported_map_carries_each_objects_existence(tmp_path):
    grid = VoxelGrid.from_bounds([0, 0, 0], [1, 1, 0.5], 0.05)
    objects = [MappedObject("mug", np.array([0.2, 0.3, 0.1]), np.full(3, 0.1), 1.3),
               MappedObject("mug", np.array([0.7, 0.6, 0.1]), np.full(3, 0.1), 0.7)]
    curve = ExistenceCurve(0.65, 1.0, 9.5)
    semantic_map = objects_to_semantic_map(objects, ("mug",), grid, existence=curve)
    np.testing.assert_allclose(semantic_map.existence, curve(np.array([1.3, 0.7])))
    assert semantic_map.existence[1] < semantic_map.existence[0] < 1.0
    path = tmp_path / "map.json"
    save_semantic_map(semantic_map, path)
    np.testing.assert_allclose(load_semantic_map(path).existence, semantic_map.existence)
    certain = objects_to_semantic_map(objects, ("mug",), grid)
    np.testing.assert_array_equal(certain.existence, [1.0, 1.0])
    save_semantic_map(certain, path)
    assert "existence" not in path.read_text()  # a certain object is written as before


@pytest.mark.parametrize("existence", [0.0, 1.5, -0.2, float("nan")])
def test_maps_refuse_existence_outside_0_1(existence):
    with pytest.raises(MapFormatError, match="existence"):
        SemanticMap.from_objects([{"class": "mug", "position": [0, 0], "existence": existence}])


def test_the_wire_map_carries_existence_and_a_version_1_map_is_certain():
    from schemas import Header, decode, encode
    from schemas.mapping import ANY_OBJECT_MAP, ObjectMapV1
    from services.frames import objectmap_frame, semantic_map_from_frame

    semantic_map = SemanticMap.from_objects(
        [{"class": "mug", "position": [0.2, 0.3, 0.8], "existence": 0.4},
         {"class": "bowl", "position": [0.6, -0.1, 0.78], "size": [0.18, 0.18, 0.08]}], bounds=[[-1, -1], [1, 1]])
    frame = decode(encode(objectmap_frame(Header(robot="r1", stream="mapper/objects"), semantic_map, 7)),
                   expected=ANY_OBJECT_MAP)
    np.testing.assert_array_equal(semantic_map_from_frame(frame).existence, [0.4, 1.0])
    old = ObjectMapV1(**{name: getattr(frame, name) for name in ObjectMapV1.model_fields})
    again = semantic_map_from_frame(decode(encode(old), expected=ANY_OBJECT_MAP))
    np.testing.assert_array_equal(again.existence, [1.0, 1.0])
    np.testing.assert_array_equal(again.positions, semantic_map.positions)


def test_labels_show_the_existence_of_uncertain_objects():
    semantic_map = SemanticMap.from_objects([{"class": "mug", "position": [0, 0], "existence": 0.874},
                                             {"class": "bowl", "position": [1, 0]}])
    assert semantic_map.labels() == ["mug p=0.87", "bowl"]
