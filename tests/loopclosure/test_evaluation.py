"""Evaluation helpers: the descriptor-distance study behind t_match, and the batch map from beliefs."""

from __future__ import annotations

import numpy as np

from semloc_core.camera import PinholeCamera
from semloc_core.loopclosure.evaluation import descriptor_distances, distance_summary
from semloc_core.loopclosure.features import FeatureSequence, normalize_descriptors
from semloc_core.loopclosure.topomap import build_topological_map, map_from_beliefs

from .synthetic import sift_like


def _view(camera: PinholeCamera, points_world: np.ndarray, x: float):
    """Pixel coordinates of world points (camera axes: x right, y down, z forward) from a camera at (x, 0, 0)."""
    uv, inside = camera.project_cam(points_world - np.array([x, 0.0, 0.0]))
    assert inside.all()
    return uv


def test_descriptor_distances_keep_epipolar_correspondences_and_drop_chance_matches():
    rng = np.random.default_rng(0)
    camera = PinholeCamera.from_fov(640, 480, 60.0)
    points = np.column_stack([rng.uniform(-1, 1, 80), rng.uniform(-0.9, 0.9, 80), rng.uniform(3, 8, 80)])
    base = sift_like(80, rng)
    first = normalize_descriptors(base)
    # The second view moved 0.5 m sideways: the same 80 points, descriptors slightly perturbed ...
    second = normalize_descriptors(base + 0.02 * np.abs(rng.normal(0, 1, base.shape)))
    p1, p2 = _view(camera, points, 0.0), _view(camera, points, 0.5)
    # ... except 15 features whose descriptors match a first-view feature but which sit 20-80 px off their epipolar
    # line (a sideways motion: the lines are the image rows): a descriptor match that geometry rejects.
    fake = rng.choice(80, 15, replace=False)
    p2[fake, 1] += rng.choice([-1, 1], 15) * rng.uniform(20, 80, 15)
    a = FeatureSequence(np.linspace(-0.5, 0.5, 80), first, points=p1)
    b = FeatureSequence(np.linspace(-0.5, 0.5, 80), second, points=p2)
    unrelated = FeatureSequence(np.linspace(-0.5, 0.5, 40), normalize_descriptors(sift_like(40, rng)))
    verified, nearest = descriptor_distances([a, b, unrelated], [(0, 1)], [(0, 2)])
    true = np.setdiff1d(np.arange(80), fake)
    expected = np.abs(second[true].astype(int) - first[true].astype(int)).sum(axis=1)
    assert np.array_equal(np.sort(verified), np.sort(expected))
    # Nearest neighbours of the unrelated frame's features among the first frame's: exact L1.
    brute = np.abs(unrelated.descriptors[:, None].astype(int) - first[None].astype(int)).sum(axis=2).min(axis=1)
    assert np.array_equal(nearest, brute)
    summary = distance_summary(verified, nearest, [float(np.median(expected)), 1e6])
    assert summary["verified_correspondences"]["count"] == 65
    assert summary["accepted"][1] == {"t_match": 1e6, "verified": 1.0, "unrelated": 1.0}
    assert abs(summary["accepted"][0]["verified"] - 0.5) < 0.05


def test_map_from_beliefs_is_the_map_of_the_sure_loops_with_their_strengths():
    rng = np.random.default_rng(1)
    n = 60
    beliefs = np.full((n, n), -np.inf)
    later = rng.integers(20, n, 80)
    earlier = later - rng.integers(10, 20, 80)
    beliefs[earlier, later] = rng.uniform(-5, 30, 80)
    sure = np.argwhere(beliefs >= 12.0)
    expected = build_topological_map(n, sure, 2, strengths=beliefs[sure[:, 0], sure[:, 1]])
    got = map_from_beliefs(beliefs, 12.0, 2)
    assert np.array_equal(got.frame_node, expected.frame_node) and np.array_equal(got.edges, expected.edges)
    d = np.argwhere(beliefs > 0)  # no threshold: D itself
    assert np.array_equal(map_from_beliefs(beliefs, None, 2).frame_node,
                          build_topological_map(n, d, 2, strengths=beliefs[d[:, 0], d[:, 1]]).frame_node)
