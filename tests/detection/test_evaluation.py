"""Hit / miss / hallucination scoring of heatlines against ground-truth bearings (hand-computed cases)."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.detection.evaluation import (GroundTruthObject, UsableCriteria, frame_objects, run_detector,
                                              score_hard, score_soft)
from semloc_core.detection.heatlines import hard_heatlines
from tests.detection.synthetic import SimpleVisible, SyntheticDataset


def _line(peaks: dict[float, float]) -> np.ndarray:
    centres = np.degrees(BearingGrid().centers)
    line = np.zeros(360)
    for bearing_deg, height in peaks.items():
        line = np.maximum(line, height * np.exp(-0.5 * ((centres - bearing_deg) / 2.0) ** 2))
    return line


def _obj(name, bearing_deg, usable=True, height=50.0, index=0):
    return GroundTruthObject(name, np.radians(bearing_deg), usable, height, index)


def test_soft_scoring_takes_the_n_strongest_peaks():
    observed = np.ones(360, bool)
    scores = np.stack([_line({10.5: 0.9, -40.5: 0.7, 80.5: 0.8}), _line({0.5: 0.3})]).astype(np.float32)
    heatlines = Heatlines(("cup", "bowl"), scores, observed)
    objects = [_obj("cup", 12.0, index=0), _obj("cup", -40.0, index=1), _obj("cup", 79.0, usable=False, index=2)]
    counts = score_soft(heatlines, objects)
    # Two usable cups -> the two strongest peaks (10.5 and 80.5): 10.5 hits, 80.5 lies at the unusable cup (not a
    # hallucination), the cup at -40 is missed.
    assert (counts["cup"].hits, counts["cup"].misses, counts["cup"].hallucinations) == (1, 1, 0)
    assert counts["cup"].peak_errors_deg == pytest.approx([-1.5])
    # No usable bowl: a soft heatline makes no claim, nothing is counted.
    assert (counts["bowl"].hits, counts["bowl"].misses, counts["bowl"].hallucinations) == (0, 0, 0)


def test_hard_scoring_counts_every_detection():
    observed = np.ones(360, bool)
    scores = np.stack([_line({10.5: 0.9, -40.5: 0.3, 80.5: 0.8}), _line({0.5: 0.6})]).astype(np.float32)
    hard = hard_heatlines(Heatlines(("cup", "bowl"), scores, observed), 0.5, width_deg=3.0)
    objects = [_obj("cup", 12.0, index=0), _obj("cup", -40.0, index=1)]
    counts = score_hard(hard, objects)
    assert (counts["cup"].hits, counts["cup"].misses, counts["cup"].hallucinations) == (1, 1, 1)
    assert (counts["bowl"].hits, counts["bowl"].misses, counts["bowl"].hallucinations) == (0, 0, 1)


def test_frame_objects_apply_the_usable_criteria_and_merge_rig_views():
    visible = [SimpleVisible(0, "cup", (0, 0, 10, 40), 0.1),
               SimpleVisible(1, "cup", (0, 0, 10, 20), 0.2),                       # too short
               SimpleVisible(2, "cup", (0, 0, 10, 40), 0.3, occluded_fraction=0.5),  # occluded
               SimpleVisible(3, "cup", (0, 0, 10, 40), 0.4, truncated=True),
               SimpleVisible(4, "cup", (0, 0, 10, 20), 0.5),                       # seen by two rig cameras:
               SimpleVisible(4, "cup", (0, 0, 10, 45), 0.5)]                       # the better view counts
    objects = {o.object_index: o for o in frame_objects(visible, UsableCriteria(min_height_px=30))}
    assert len(objects) == 5
    assert [objects[i].usable for i in range(5)] == [True, False, False, False, True]


def test_template_detector_finds_the_synthetic_objects():
    """End to end on the hand-made dataset: every object >= 50 px tall is a soft hit within 5 degrees."""
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.templates import TemplateDetector, build_templates
    from semloc_core.detection.evaluation import accumulate
    from tests.detection.synthetic import make_object

    dataset = SyntheticDataset(6, seed=7)
    params = FeatureParams()
    templates = [t for kind in dataset.kinds for t in build_templates(make_object(kind, 120), kind, params)]
    total: dict = {}
    for _, heatlines, objects in run_detector(dataset, TemplateDetector(templates, params), range(len(dataset))):
        accumulate(total, score_soft(heatlines, objects))
    for name in dataset.kinds:
        assert total[name].hits == len(dataset) and total[name].misses == 0
        assert np.max(np.abs(total[name].peak_errors_deg)) < 2.0
