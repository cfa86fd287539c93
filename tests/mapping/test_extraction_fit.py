"""The extraction fitted on a calibration scene (`mapping_fits.fit_extraction`, what `semloc eval mapping`'s
calibration.fit and every demo world use): its threshold lies halfway between the strongest false candidate it
rejects and the weakest real object it keeps, whatever step the threshold sweep has."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from semloc_core.eval.objects import object_map_figures
from semloc_core.experiments.mapping_fits import fit_extraction
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.mapping import ExtractionConfig, VoxelGrid, VoxelMapper
from semloc_core.mapping.synthetic import SyntheticObject, orbit_poses, render_heatmaps

from .conftest import CLASSES

GRID = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [1.1, 1.2, 0.4], 0.02)
SIZES = {name: (0.12, 0.12, 0.12) for name in CLASSES}
# Bowls: three real ones (the last weak) and a look-alike the truth does not have, 0.35 m or more apart.
CENTRES = [(0.3, 0.3, 0.1), (0.8, 0.3, 0.1), (0.3, 0.85, 0.1), (0.8, 0.85, 0.1)]


def _truth() -> SemanticMap:
    real = np.array(CENTRES[:3])
    return SemanticMap(class_names=CLASSES, class_index=np.zeros(3, np.int64), positions=real,
                       sizes=np.full((3, 3), 0.12), scores=np.ones(3), has_height=np.ones(3, bool),
                       bounds=np.array([[0.0, 0.0], [1.1, 1.2]]))


def _mapper(camera, weak: float, false: float) -> VoxelMapper:
    mapper = VoxelMapper(GRID, CLASSES)
    bowls = [SyntheticObject(0, np.array(c), np.full(3, 0.12)) for c in CENTRES]
    for T in orbit_poses([0.55, 0.6, 0.1], 1.0, 0.6, 12) + orbit_poses([0.55, 0.6, 0.1], 0.8, 0.9, 6, 0.3):
        heat = sum(render_heatmaps(camera, T, [bowl], len(CLASSES), peak=peak)
                   for bowl, peak in zip(bowls, (1.0, 1.0, weak, false)))
        mapper.integrate(heat, T, camera)
    return mapper


@pytest.mark.parametrize("weak, false", [(0.72, 0.6), (0.9, 0.52)])
def test_the_fitted_threshold_is_halfway_between_the_weakest_real_object_and_the_strongest_false_one(
        camera, weak, false):
    # (0.72, 0.6): the sweep's thresholds 0.65 and 0.7 tie, and 0.7 was taken, 0.02 under the weak bowl's score;
    # (0.9, 0.52): eight tie (docs/results/2026-12-06-demo-mapping.md).
    mapper, truth = _mapper(camera, weak, false), _truth()
    fit = fit_extraction(mapper, truth, normalise=True, min_views=5, distance=0.05, min_size=0.1,
                         position="centroid", class_sizes=SIZES)
    assert (fit["tp"], fit["fp"], fit["fn"]) == (3, 0, 0)
    # Every candidate with the fit's settings, each scored and told real or false by the ground truth.
    every = ExtractionConfig(threshold=0.1, min_views=5, class_sizes=SIZES, class_scales=fit["class_scales"],
                             cross_class=fit["cross_class"], tophat=fit["tophat"], position="centroid")
    found = mapper.semantic_map(every)
    names = [found.class_names[k] for k in found.class_index]
    matches = object_map_figures(names, found.positions, ["bowl"] * 3, truth.positions, 0.05, found.scores,
                                 planar=False)["matches"]
    real = [s for s, m in zip(found.scores, matches) if m >= 0]
    rejected = [s for s, m in zip(found.scores, matches) if m < 0]
    assert len(real) == 3 and rejected
    weakest, strongest_false = min(real), max(rejected)
    assert strongest_false < fit["threshold"] < weakest
    assert fit["threshold"] == pytest.approx((weakest + strongest_false) / 2, abs=1e-3)
    kept = mapper.semantic_map(dataclasses.replace(every, threshold=fit["threshold"]))
    assert len(kept) == 3
