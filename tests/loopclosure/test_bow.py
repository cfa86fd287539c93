"""Vocabulary learning, TF-IDF vectors and the inverted index."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.loopclosure.bow import InvertedIndex, Vocabulary, train_vocabulary

from .synthetic import sift_like


def clustered(centres: np.ndarray, per_frame: int, frames: int, rng, spread: float = 2.0):
    """Frames of descriptors drawn around known centres (each frame uses a random subset of the words)."""
    out = []
    for _ in range(frames):
        words = rng.choice(len(centres), per_frame)
        out.append(np.clip(centres[words] + rng.normal(0, spread, (per_frame, 128)), 0, 255).astype(np.uint8))
    return out


def test_kmeans_recovers_well_separated_words():
    rng = np.random.default_rng(0)
    centres = (sift_like(12, rng) * 512).astype(np.float32)
    frames = clustered(centres, 30, 20, rng)
    vocabulary = train_vocabulary(frames, words=12, seed=1)
    distance = np.linalg.norm(vocabulary.centers[:, None, :] - centres[None], axis=2)
    # Every true centre found (the noise is clipped at 0, which biases the means by a few units; centres are ~500 apart).
    assert np.all(distance.min(axis=0) < 20.0)
    labels = vocabulary.quantize(centres.astype(np.uint8))
    assert np.unique(labels).size == 12


def test_training_is_deterministic():
    rng = np.random.default_rng(1)
    frames = [(sift_like(40, rng) * 512).astype(np.uint8) for _ in range(5)]
    a = train_vocabulary(frames, words=16, seed=3)
    b = train_vocabulary(frames, words=16, seed=3)
    assert np.array_equal(a.centers, b.centers) and np.array_equal(a.idf, b.idf)


def test_idf_counts_training_frames():
    centres = np.zeros((3, 128), np.float32)
    centres[0, 0] = centres[1, 1] = centres[2, 2] = 500
    frames = [centres[[0, 1]].astype(np.uint8), centres[[0]].astype(np.uint8), centres[[0, 2]].astype(np.uint8),
              centres[[0]].astype(np.uint8)]
    trained = train_vocabulary(frames, words=3, iterations=0, seed=0)
    order = trained.quantize(centres.astype(np.uint8))
    idf = trained.idf[order]
    assert idf[0] == pytest.approx(0.0)  # in every frame
    assert idf[1] == pytest.approx(np.log(4)) and idf[2] == pytest.approx(np.log(4))


def dense(vector, size):
    out = np.zeros(size)
    out[vector.words] = vector.weights
    return out


def test_cosine_similarity_and_inverted_index_agree_with_dense_vectors():
    rng = np.random.default_rng(2)
    vocabulary = Vocabulary((sift_like(50, rng) * 512).astype(np.float32), rng.uniform(0.1, 3.0, 50))
    frames = [(sift_like(int(rng.integers(5, 40)), rng) * 512).astype(np.uint8) for _ in range(30)]
    vectors = [vocabulary.vector(d) for d in frames]
    matrix = np.array([dense(v, 50) for v in vectors])
    assert np.allclose(np.linalg.norm(matrix, axis=1), 1.0)
    index = InvertedIndex(50)
    for v in vectors:
        index.add(v)
    query = vectors[7]
    assert query.similarity(query) == pytest.approx(1.0)
    assert np.allclose(index.scores(query), matrix @ matrix[7])
    assert np.allclose(index.scores(query, limit=12), (matrix @ matrix[7])[:12])
    frames_found, scores = index.query(query, limit=30, top=5)
    assert frames_found[0] == 7 and np.all(np.diff(scores) <= 0)
    assert set(frames_found.tolist()) == set(np.argsort(-(matrix @ matrix[7]))[:5].tolist())
    assert vectors[3].similarity(vectors[9]) == pytest.approx(matrix[3] @ matrix[9])


def test_vocabulary_validation():
    with pytest.raises(ValueError):
        Vocabulary(np.zeros((4, 64)), np.zeros(4))
    with pytest.raises(ValueError):
        Vocabulary(np.zeros((4, 128)), np.zeros(3))
    with pytest.raises(ValueError, match="too few"):
        train_vocabulary([np.zeros((3, 128), np.uint8)], words=10)
