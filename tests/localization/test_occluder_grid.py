"""The view's occlusion test looks up which objects can hide another in a grid of the map's cells
(``_kernels.occluder_cells``): the lists must hold every object that passes the kernel's pair test from anywhere in
the cell, so that weighing with the grid is bit for bit weighing with every object tested."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.bearing import Heatlines
from semloc_core.camera import EquirectangularCamera, PinholeCamera, forward_extrinsic
from semloc_core.geometry import make_transform, rotation_about_y
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import (GenerativeScoreModel, InnerProductModel, ViewGeometry, _kernels,
                                      synthetic_scores_likelihood)

CLASSES = ("a", "b", "c", "d", "e")


def _world(kind: str, rng) -> SemanticMap:
    """The benchmark's room (20 objects of 0.3 m in 10 m x 10 m), a cluttered table top (40 small objects in 2 m x
    1.5 m, some touching) and a map with objects of unknown height and some off its bounds."""
    if kind == "room":
        objects = [{"class": CLASSES[k % 5], "position": [*rng.uniform(0.5, 9.5, 2), 0.4], "size": [0.3, 0.3, 0.5]}
                   for k in range(20)]
        return SemanticMap.from_objects(objects, bounds=[[0, 0], [10, 10]])
    if kind == "table":
        objects = [{"class": CLASSES[k % 5], "position": [*rng.uniform([0, 0], [2, 1.5]), rng.uniform(0.7, 0.9)],
                    "size": rng.uniform(0.04, 0.3, 3).tolist()} for k in range(36)]
        for k in range(4):  # pairs side by side
            x, y = rng.uniform([0.2, 0.2], [1.8, 1.3])
            objects += [{"class": "a", "position": [x, y, 0.8], "size": [0.1, 0.1, 0.2]},
                        {"class": "b", "position": [x + 0.12, y + 0.01, 0.8], "size": [0.1, 0.1, 0.2]}]
        return SemanticMap.from_objects(objects, bounds=[[0, 0], [2, 1.5]])
    objects = [{"class": CLASSES[k % 5], "position": [*rng.uniform(-1, 7, 2), 0.5],
                **({"size": rng.uniform(0.1, 0.8, 3).tolist()} if k % 4 else {})} for k in range(24)]
    return SemanticMap.from_objects(objects, bounds=[[0, 0], [6, 6]])


def _poses(semantic_map: SemanticMap, rng, n: int) -> np.ndarray:
    """Uniform over the bounds and a little beyond, next to objects, and on cell corners of every grid size."""
    low, high = semantic_map.bounds
    span = high - low
    uniform = rng.uniform(low - 0.1 * span, high + 0.1 * span, (n, 2))
    near = semantic_map.positions[rng.integers(0, len(semantic_map), n), :2] + rng.normal(0, 0.3, (n, 2))
    corners = low + np.round(rng.uniform(0, 1, (n, 2)) * span / 0.01) * 0.01
    xy = np.concatenate([uniform, near, corners])
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, xy.shape[0])])


def _passing_occluders(model, layout, xy, n_bins: int) -> list[set]:
    """Per position: the objects that pass the kernel's pair test with some target (both known and within range,
    the occluder nearer, the target's bearing within its core reach plus the target's slack), in numpy, with
    exact arctangents."""
    _, xs, ys, _, _, (known, _, _, _, radius), _ = layout
    inv_bin = n_bins / (2 * math.pi)
    out = []
    for x, y in xy:
        distance = np.hypot(xs - x, ys - y)
        angle = np.arctan2(ys - y, xs - x)
        usable = known & (distance <= model.visibility_radius)
        gap = np.abs((angle[:, None] - angle[None, :] + np.pi) % (2 * np.pi) - np.pi) * inv_bin
        reach = (_kernels.OCCLUDER_CORE * radius / np.maximum(distance, 1e-300) * inv_bin)[:, None] + 1e-5
        slack = (_kernels.TARGET_SLACK * radius / np.maximum(distance, 1e-300) * inv_bin)[None, :]
        passes = ((distance[:, None] < distance[None, :]) & (gap < reach + slack) & usable[:, None]
                  & usable[None, :])
        np.fill_diagonal(passes, False)
        out.append(set(np.flatnonzero(passes.any(axis=1)).tolist()))
    return out


@pytest.mark.parametrize("kind", ["room", "table", "unknown_heights"])
@pytest.mark.parametrize("visibility_radius", [math.inf, 2.0])
def test_every_occluder_that_passes_the_pair_test_is_listed_in_its_cell(kind, visibility_radius):
    rng = np.random.default_rng(len(kind) + int(visibility_radius if math.isfinite(visibility_radius) else 0))
    semantic_map = _world(kind, rng)
    model = GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(CLASSES),
                                 visibility_radius=visibility_radius)
    layout = model._layout(CLASSES)
    x0, y0, cell, columns, rows, offsets, occluders = model._occluder_grid(CLASSES, layout)
    assert columns * rows > 100  # a real grid, not one cell
    poses = _poses(semantic_map, rng, 600)
    listed_total = passing_total = inside_total = 0
    for (x, y), passing in zip(poses[:, :2], _passing_occluders(model, layout, poses[:, :2], 360)):
        column, row = (x - x0) / cell, (y - y0) / cell
        inside = 0 <= column < columns and 0 <= row < rows
        c = int(row) * columns + int(column) if inside else columns * rows
        listed = occluders[offsets[c]:offsets[c + 1]]
        assert np.all(np.diff(listed) > 0)  # ascending, each once
        assert passing <= set(listed.tolist()), (x, y, passing - set(listed.tolist()))
        if inside:
            listed_total += listed.size
            passing_total += len(passing)
            inside_total += 1
    # ... and the lists are shorter than every object (in the room ~6 of 20, where ~3 pass)
    n_known = int(layout[5][0].sum())
    assert passing_total > 0 and listed_total < (0.4 if kind == "room" else 0.85) * n_known * inside_total


def _pitched_camera(pitch_deg: float):
    T = make_transform(rotation_about_y(math.radians(pitch_deg)), (0, 0, 0)) @ forward_extrinsic()
    return PinholeCamera.from_fov(640, 480, 60.0, T_body_cam=T)


@pytest.mark.parametrize("kind", ["room", "table", "unknown_heights"])
def test_weighing_with_the_grid_is_weighing_with_every_object_tested(kind):
    """Bit for bit, models A and B, a panorama and a pitched pinhole with a minimum size, and the weighing does hide
    objects (the view changes the log-likelihoods)."""
    rng = np.random.default_rng(7 + len(kind))
    semantic_map = _world(kind, rng)
    height = 0.9 if kind == "table" else 1.2
    views = [ViewGeometry.from_camera(EquirectangularCamera(1024, 256, forward_extrinsic(height)), 360,
                                      camera_height=height),
             ViewGeometry.from_camera(_pitched_camera(20.0), 360, camera_height=height, min_pixels=20)]
    observed = np.ones(360, dtype=bool)
    scores = rng.uniform(0.0, 1.0, (len(CLASSES), 360)).astype(np.float32)
    heatlines = Heatlines(CLASSES, scores, observed)
    poses = _poses(semantic_map, rng, 1500)
    every_object = (0.0, 0.0, 1.0, 0, 0, np.zeros(2, np.int32), np.flatnonzero(
        GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(CLASSES))._layout(CLASSES)[5][0]
    ).astype(np.int32))
    every_object[5][1] = every_object[6].size
    for model in (GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(CLASSES)),
                  InnerProductModel(semantic_map)):
        for view in views:
            with_grid = model.weigh(poses, heatlines, view).log_likelihood
            model._occluder_grids[CLASSES] = every_object  # every position beyond the grid: every object tested
            exhaustive = model.weigh(poses, heatlines, view).log_likelihood
            model._occluder_grids.clear()
            np.testing.assert_array_equal(with_grid, exhaustive)
            assert np.abs(with_grid - model.weigh(poses, heatlines).log_likelihood).max() > 0.1
