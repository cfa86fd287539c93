"""The SeqSLAM baseline finds a route driven again, in either direction, under other light and noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.eval.pr import average_precision, pr_curve
from semloc_core.loopclosure.evaluation import scored_pairs
from semloc_core.loopclosure.seqslam import SeqSlamParams, enhance, similarity_matrix, thumbnail


def route_images(places: int, seed: int = 0) -> list[np.ndarray]:
    """A corridor of ``places`` views: a long random texture seen through a sliding 160x120 window."""
    rng = np.random.default_rng(seed)
    strip = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160 + 12 * places)).astype(np.float32), (0, 0), 3)
    return [strip[:, 12 * k:12 * k + 160] for k in range(places)]


def revisit(images, rng, gain: float) -> list[np.ndarray]:
    return [np.clip(gain * im + rng.normal(0, 6, im.shape), 0, 255).astype(np.uint8) for im in images]


@pytest.mark.parametrize("backwards", [False, True])
def test_revisits_rank_first(backwards):
    rng = np.random.default_rng(1)
    first = route_images(40)
    second = first[::-1] if backwards else first
    images = revisit(first, rng, 1.0) + revisit(second, rng, 0.6)  # the second pass under dimmer light
    thumbs = np.stack([thumbnail(im) for im in images])
    M = similarity_matrix(thumbs, window=10)
    n = len(images)
    gt = np.zeros((n, n), bool)
    for k in range(40):
        place = 39 - k if backwards else k
        for d in (-1, 0, 1):
            if 0 <= place + d < 40:
                gt[place + d, 40 + k] = True
    earlier, later = scored_pairs(n, 10)
    assert average_precision(pr_curve(M[earlier, later], gt[earlier, later])) > 0.8
    assert np.all(np.isneginf(M[np.tril_indices(n)]))


def test_thumbnail_is_patch_normalised_and_light_invariant():
    image = route_images(1)[0].astype(np.uint8)
    a, b = thumbnail(image), thumbnail((0.5 * image + 20).astype(np.uint8))
    assert a.shape == (32, 64)
    assert abs(a[:8, :8].mean()) < 1e-4 and abs(a[:8, :8].std() - 1) < 1e-3
    assert np.mean(np.abs(a - b)) < 0.15


def test_enhancement_is_local_standardisation():
    d = np.arange(30, dtype=float)[:, None] * np.ones((1, 4))
    e = enhance(d, 3)
    assert np.allclose(e[15], 0.0)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError):
        SeqSlamParams(width=4, patch=8)
