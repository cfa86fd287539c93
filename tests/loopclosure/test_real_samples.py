"""The real rtabmap loop samples (84 indoor frames, hand-labelled loops): scores against their ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.camera import PinholeCamera
from semloc_core.io.loopclosure import read_loop_samples
from semloc_core.loopclosure.evaluation import scored_pairs, similarity_matrices
from semloc_core.loopclosure.features import FeatureParams, extract_features

from ..conftest import shared_path

pytestmark = pytest.mark.shared_data


def average_precision(score, y):
    order = np.argsort(-score, kind="stable")
    hits = y[order]
    return float((np.cumsum(hits) / np.arange(1, hits.size + 1))[hits].mean())


@pytest.fixture(scope="module")
def samples():
    images, gt = read_loop_samples(shared_path("rtabmap_loop_samples"))
    camera = PinholeCamera.from_fov(512, 384, 60.0)
    frames = [extract_features(cv2.imread(str(p)), camera, FeatureParams(max_features=300)) for p in images]
    return frames, gt


def test_reader_gives_the_documented_ground_truth(samples):
    frames, gt = samples
    assert len(frames) == 84 and gt.shape == (84, 84)
    assert gt.sum() == 228 and not np.tril(gt).any()


def test_dp_ranks_real_revisits_above_chance_and_above_sift_counts(samples):
    frames, gt = samples
    window = 30
    matrices = similarity_matrices(frames, window)
    earlier, later = scored_pairs(len(frames), window)
    y = gt[earlier, later]
    base_rate = y.mean()
    dp = average_precision(matrices["dp"][earlier, later], y)
    sift = average_precision(matrices["sift"][earlier, later], y)
    assert dp > max(0.5, 3 * base_rate)
    assert dp > sift
