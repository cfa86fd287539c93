"""Exemplar-view selection on a training world (semloc_core.detection.selection, `semloc select-templates`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid
from semloc_core.detection.evaluation import GroundTruthObject
from semloc_core.detection.features import FeatureParams
from semloc_core.detection.selection import exemplar_of_templates, per_exemplar, select_exemplars
from semloc_core.detection.templates import build_templates

GRID = BearingGrid()


def _line(peaks: dict[float, float], floor: float = 0.1) -> np.ndarray:
    """A heatline with a narrow peak of the given height at each bearing (degrees)."""
    line = np.full(GRID.n_bins, floor, np.float32)
    for bearing_deg, height in peaks.items():
        line[GRID.index(np.radians(bearing_deg))] = height
    return line


def _object(class_name: str, bearing_deg: float, usable: bool = True) -> GroundTruthObject:
    return GroundTruthObject(class_name, float(np.radians(bearing_deg)), usable, 40.0, 0)


def test_greedy_selection_keeps_the_views_that_find_objects_and_drops_background_answers():
    # Three training frames with one mug each, at 10, -40 and 100 degrees.
    bearings = [10.0, -40.0, 100.0]
    objects = [[_object("mug", b)] for b in bearings]
    front = [_line({10.0: 0.9}), _line({-40.0: 0.9}), _line({-150.0: 0.8})]    # finds frames 0 and 1
    side = [_line({}), _line({}), _line({100.0: 0.95})]                       # finds frame 2 only
    background = [_line({60.0: 0.99}), _line({60.0: 0.99}), _line({60.0: 0.99})]  # answers elsewhere, always
    lines = np.stack([np.stack([background[f], front[f], side[f]]) for f in range(3)])
    observed = np.ones((3, GRID.n_bins), bool)
    chosen = select_exemplars(lines, observed, ["mug", "mug", "mug"], objects)
    steps = chosen["mug"]
    assert [s.exemplar for s in steps] == [1, 2]
    assert [(s.hits, s.misses) for s in steps] == [(2, 1), (3, 0)]
    assert select_exemplars(lines, observed, ["mug"] * 3, objects, max_per_class=1)["mug"][0].exemplar == 1


def test_ties_prefer_fewer_hallucinations_and_classes_without_objects_get_nothing():
    observed = np.ones((1, GRID.n_bins), bool)
    false_peak = _line({0.0: 0.9, 150.0: 0.5})     # its second peak is near no cup
    near_a_cup = _line({0.0: 0.9, 120.0: 0.5})     # its second peak is on a cup too small to count
    lines = np.stack([np.stack([false_peak, near_a_cup, _line({90.0: 0.9})])])
    one_cup = [[_object("cup", 0.0), _object("bowl", 90.0, usable=False)]]
    chosen = select_exemplars(lines, observed, ["cup", "cup", "bowl"], one_cup)
    assert [s.exemplar for s in chosen["cup"]] == [0]       # equal in every count: the lower index
    assert "bowl" not in chosen                             # its only object is not usable
    two_cups = [[_object("cup", 0.0), _object("cup", -90.0), _object("cup", 120.0, usable=False)]]
    steps = select_exemplars(lines, observed, ["cup", "cup", "bowl"], two_cups)["cup"]
    assert steps[0].exemplar == 1 and (steps[0].hits, steps[0].misses, steps[0].hallucinations) == (1, 1, 0)
    assert len(steps) == 1                                  # the other view adds no hit


@pytest.mark.parametrize("bad", ["lines", "observed", "objects", "max"])
def test_bad_input_is_rejected(bad):
    lines = np.zeros((2, 3, GRID.n_bins), np.float32)
    observed = np.ones((2, GRID.n_bins), bool)
    objects = [[], []]
    kwargs = {}
    if bad == "lines":
        lines = lines[:, :2]
    elif bad == "observed":
        observed = observed[:1]
    elif bad == "objects":
        objects = [[]]
    else:
        kwargs["max_per_class"] = 0
    with pytest.raises(ValueError):
        select_exemplars(lines, observed, ["a", "a", "b"], objects, **kwargs)


def test_an_exemplar_and_its_mirror_are_one_candidate():
    image = np.zeros((60, 40, 3), np.uint8)
    image[10:50, 5:20] = (0, 0, 255)
    templates = build_templates(image, "can", FeatureParams(cell=4), 5, source="can_00.png") + \
        build_templates(image[::-1].copy(), "can", FeatureParams(cell=4), 5, source="can_01.png")
    index, exemplars = exemplar_of_templates(templates)
    assert index.tolist() == [0, 0, 1, 1] and exemplars == [("can", "can_00.png"), ("can", "can_01.png")]
    maps = np.arange(4 * 6, dtype=np.float32).reshape(4, 2, 3)
    np.testing.assert_array_equal(per_exemplar(maps, index, 2), maps[[1, 3]])


def test_semloc_select_templates_writes_a_library_the_detector_loads(tmp_path, sim_dataset, capsys):
    from semloc_core.detection.config import build_detector
    from services.cli import main

    dataset = sim_dataset("tabletop", frames=6, seed=3)
    output = tmp_path / "library"
    assert main(["select-templates", str(dataset), "-o", str(output), "--quiet", "--set", "max_per_class=2"]) == 0
    record = json.loads((output / "selection.json").read_text())
    detector = build_detector(output / "detector.yaml")
    assert set(detector.classes) == set(record["classes"]) and len(record["classes"]) == 5
    for class_name, steps in record["classes"].items():
        assert 1 <= len(steps) <= 2
        assert [s["hits"] for s in steps] == sorted(s["hits"] for s in steps)        # each step adds hits
        assert all((output / s["file"]).is_file() for s in steps)
        assert len([t for t in detector.templates if t.class_name == class_name]) == 2 * len(steps)  # + mirrors
    assert "found on the training frames" in capsys.readouterr().out
    assert main(["select-templates", str(tmp_path / "missing"), "-o", str(output)]) == 2
