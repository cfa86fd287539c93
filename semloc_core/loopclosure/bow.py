"""Bag of visual words: vocabulary, TF-IDF vectors and an inverted index.

Two uses: the BoW TF-IDF similarity baseline standing in for FAB-MAP (§3.6), and candidate retrieval in the
incremental engine (only the best-scoring earlier frames are aligned with the DP).

The vocabulary is learnt here, without downloads: k-means (k-means++ seeding, Lloyd iterations) on SIFT
descriptors of training frames; the inverse document frequencies come from the same frames and stay fixed, so a
frame's vector - and every pair's score - does not change as the database grows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numba.typed import List

from semloc_core.loopclosure.features import DESCRIPTOR_SIZE
from semloc_core.loopclosure.storage import MemoryStorage


@njit(cache=True)
def _keep_nearest(distances, count, out_row) -> None:
    """Indices of the ``count`` smallest distances into out_row, nearest first (ties: lower index first)."""
    best = np.empty(count, np.float32)
    filled = 0
    for c in range(distances.shape[0]):
        d = distances[c]
        if filled < count or d < best[filled - 1]:
            slot = filled if filled < count else count - 1
            while slot > 0 and d < best[slot - 1]:
                best[slot] = best[slot - 1]
                out_row[slot] = out_row[slot - 1]
                slot -= 1
            best[slot] = d
            out_row[slot] = c
            if filled < count:
                filled += 1


@njit(cache=True, fastmath=True)
def _nearest_centres(x: np.ndarray, centers: np.ndarray, squared_norms: np.ndarray, count: int) -> np.ndarray:
    """Indices of each row's ``count`` nearest centres (squared L2 = |c|^2 - 2 x.c + |x|^2), nearest first.

    One frame's few hundred descriptors against the vocabulary is a small product: through BLAS it costs 0.3 ms
    on one thread but 8 ms when OpenBLAS spreads it over threads on a busy machine (measured here), so it is
    computed here, in blocks of four descriptors by two centres (eight dot products share each load: 0.3 ms per
    route frame, against 0.6 ms one dot product at a time), independent of the BLAS threading."""
    n, k, dims = x.shape[0], centers.shape[0], x.shape[1]
    out = np.empty((n, count), np.int64)
    dist = np.empty((4, k), np.float32)
    for first in range(0, n, 4):
        rows = min(4, n - first)
        a, b, c_, d_ = first, min(first + 1, n - 1), min(first + 2, n - 1), min(first + 3, n - 1)
        for c in range(0, k, 2):
            e = c + 1 if c + 1 < k else c  # an odd last centre is computed twice
            s0 = np.float32(0.0)
            s1 = np.float32(0.0)
            s2 = np.float32(0.0)
            s3 = np.float32(0.0)
            u0 = np.float32(0.0)
            u1 = np.float32(0.0)
            u2 = np.float32(0.0)
            u3 = np.float32(0.0)
            for t in range(dims):
                v = centers[c, t]
                w = centers[e, t]
                xa, xb, xc, xd = x[a, t], x[b, t], x[c_, t], x[d_, t]
                s0 += xa * v
                s1 += xb * v
                s2 += xc * v
                s3 += xd * v
                u0 += xa * w
                u1 += xb * w
                u2 += xc * w
                u3 += xd * w
            dist[0, c] = squared_norms[c] - 2 * s0
            dist[1, c] = squared_norms[c] - 2 * s1
            dist[2, c] = squared_norms[c] - 2 * s2
            dist[3, c] = squared_norms[c] - 2 * s3
            dist[0, e] = squared_norms[e] - 2 * u0
            dist[1, e] = squared_norms[e] - 2 * u1
            dist[2, e] = squared_norms[e] - 2 * u2
            dist[3, e] = squared_norms[e] - 2 * u3
        for r in range(rows):
            _keep_nearest(dist[r], count, out[first + r])
    return out


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """``centers`` (K, 128) float32 word centres; ``idf`` (K,) float64 inverse document frequencies."""

    centers: np.ndarray
    idf: np.ndarray

    def __post_init__(self) -> None:
        centers = np.ascontiguousarray(self.centers, dtype=np.float32)
        idf = np.asarray(self.idf, dtype=np.float64).reshape(-1)
        if centers.ndim != 2 or centers.shape[1] != DESCRIPTOR_SIZE or centers.shape[0] < 1:
            raise ValueError(f"vocabulary centres must have shape (K, {DESCRIPTOR_SIZE}), got {centers.shape}")
        if idf.shape != (centers.shape[0],) or not np.all(np.isfinite(idf)) or np.any(idf < 0):
            raise ValueError("idf must be finite, non-negative, one value per word")
        if not np.all(np.isfinite(centers)):
            raise ValueError("vocabulary centres must be finite")
        object.__setattr__(self, "centers", centers)
        object.__setattr__(self, "idf", idf)
        object.__setattr__(self, "_squared_norms", (centers.astype(np.float64) ** 2).sum(axis=1).astype(np.float32))

    @property
    def size(self) -> int:
        return int(self.centers.shape[0])

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Word index of each descriptor (nearest centre in L2)."""
        return self.nearest_words(descriptors, 1)[:, 0]

    def nearest_words(self, descriptors: np.ndarray, count: int) -> np.ndarray:
        """(n, count) indices of each descriptor's ``count`` nearest words, nearest first."""
        d = np.asarray(descriptors)
        if d.ndim != 2 or d.shape[1] != DESCRIPTOR_SIZE:
            raise ValueError(f"descriptors must have shape (n, {DESCRIPTOR_SIZE}), got {d.shape}")
        if not 1 <= count <= self.size:
            raise ValueError(f"count must be in 1..{self.size}, got {count}")
        if d.shape[0] == 0:
            return np.zeros((0, count), np.int64)
        return _nearest_centres(np.ascontiguousarray(d, dtype=np.float32), self.centers, self._squared_norms,
                                int(count))

    def vector(self, descriptors: np.ndarray, words: np.ndarray | None = None) -> "BowVector":
        """L2-normalised TF-IDF vector of one frame, stored sparsely (``words``: its descriptors' nearest words, if
        already known)."""
        words = self.quantize(descriptors) if words is None else np.asarray(words, np.int64).reshape(-1)
        if words.size == 0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        counts = np.bincount(words, minlength=self.size)
        unique = np.flatnonzero(counts)
        weights = counts[unique] / words.size * self.idf[unique]
        norm = float(np.linalg.norm(weights))
        if norm == 0.0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        return BowVector(unique.astype(np.int64), weights / norm)


@dataclass(frozen=True, eq=False)
class BowVector:
    """Sparse TF-IDF vector: sorted unique ``words`` and their L2-normalised ``weights``."""

    words: np.ndarray
    weights: np.ndarray

    def similarity(self, other: "BowVector") -> float:
        """Cosine similarity of two TF-IDF vectors, in [0, 1] (the BoW baseline score)."""
        common, ia, ib = np.intersect1d(self.words, other.words, assume_unique=True, return_indices=True)
        if common.size == 0:
            return 0.0
        return float(np.dot(self.weights[ia], other.weights[ib]))


def _squared_distances(x: np.ndarray, centers: np.ndarray, x_sq: np.ndarray) -> np.ndarray:
    c_sq = (centers.astype(np.float64) ** 2).sum(1).astype(np.float32)
    return np.maximum(x_sq[:, None] + c_sq[None, :] - 2.0 * (x @ centers.T), 0.0)


def _assign(x: np.ndarray, centers: np.ndarray, x_sq: np.ndarray, chunk: int = 4096):
    """Nearest centre of every row and its squared distance, in row chunks (the full N x K matrix is large)."""
    c_sq = (centers.astype(np.float64) ** 2).sum(1).astype(np.float32)
    labels = np.empty(x.shape[0], np.int64)
    best = np.empty(x.shape[0], np.float32)
    for start in range(0, x.shape[0], chunk):
        part = c_sq[None, :] - 2.0 * (x[start : start + chunk] @ centers.T)
        labels[start : start + chunk] = np.argmin(part, axis=1)
        best[start : start + chunk] = part[np.arange(part.shape[0]), labels[start : start + chunk]]
    return labels, np.maximum(best + x_sq, 0.0)


def _kmeans_pp(x: np.ndarray, x_sq: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (Arthur & Vassilvitskii, 2007)."""
    centers = np.empty((k, x.shape[1]), np.float32)
    centers[0] = x[rng.integers(x.shape[0])]
    closest = _squared_distances(x, centers[:1], x_sq)[:, 0].astype(np.float64)
    for c in range(1, k):
        total = closest.sum()
        index = int(rng.choice(x.shape[0], p=closest / total)) if total > 0 else int(rng.integers(x.shape[0]))
        centers[c] = x[index]
        closest = np.minimum(closest, _squared_distances(x, centers[c : c + 1], x_sq)[:, 0])
    return centers


def train_vocabulary(
    descriptor_sets,
    words: int = 500,
    iterations: int = 15,
    seed: int = 0,
    max_descriptors: int = 60_000,
) -> Vocabulary:
    """Learn a vocabulary from training frames (one uint8 descriptor array per frame).

    k-means with k-means++ seeding on at most ``max_descriptors`` descriptors (a random subset), ``iterations``
    Lloyd steps; empty clusters are re-seeded with the worst-fitted descriptors. ``idf_w = log(N / n_w)`` over the
    N training frames (``n_w`` frames contain word w; unseen words get ``log(N)``).
    """
    sets = [np.asarray(d) for d in descriptor_sets]
    for index, d in enumerate(sets):
        if d.ndim != 2 or d.shape[1] != DESCRIPTOR_SIZE:
            raise ValueError(f"training frame {index}: descriptors must have shape (n, {DESCRIPTOR_SIZE})")
    if words < 1 or iterations < 0:
        raise ValueError("need words >= 1 and iterations >= 0")
    rng = np.random.default_rng(seed)
    x = np.concatenate(sets).astype(np.float32) if sets else np.zeros((0, DESCRIPTOR_SIZE), np.float32)
    if x.shape[0] < words:
        raise ValueError(f"{x.shape[0]} training descriptors are too few for {words} words")
    if x.shape[0] > max_descriptors:
        x = x[rng.choice(x.shape[0], max_descriptors, replace=False)]
    x_sq = (x.astype(np.float64) ** 2).sum(1).astype(np.float32)
    from scipy.sparse import csr_matrix  # training only: not imported by every loop-closure worker's start

    centers = _kmeans_pp(x, x_sq, words, rng)
    for _ in range(iterations):
        labels, fit = _assign(x, centers, x_sq)
        counts = np.bincount(labels, minlength=words)
        # Per-cluster sums as a sparse (words x N) one-hot product: np.add.at is ~50x slower here.
        onehot = csr_matrix((np.ones(labels.size, np.float32), (labels, np.arange(labels.size))),
                            shape=(words, labels.size))
        moved = np.asarray(onehot @ x, dtype=np.float64) / np.maximum(counts, 1)[:, None]
        empty = np.flatnonzero(counts == 0)
        if empty.size:
            worst = np.argsort(-fit)[: empty.size]
            moved[empty] = x[worst]
        centers = moved.astype(np.float32)
    vocabulary = Vocabulary(centers, np.zeros(words))
    df = np.zeros(words)
    for d in sets:
        if d.shape[0]:
            df[np.unique(vocabulary.quantize(d))] += 1
    n_docs = max(len(sets), 1)
    idf = np.log(n_docs / np.maximum(df, 1.0))
    return Vocabulary(centers, idf)


@njit(cache=True)
def _new_postings(words: int):
    frames, weights = List(), List()
    for _ in range(words):
        frames.append(np.zeros(4, np.int64))
        weights.append(np.zeros(4))
    return frames, weights


@njit(cache=True)
def _add_postings(frames, weights, lengths, frame, words, values) -> None:
    for t in range(words.shape[0]):
        w = words[t]
        length = lengths[w]
        if length == frames[w].shape[0]:
            grown_f = np.zeros(2 * length, np.int64)
            grown_w = np.zeros(2 * length)
            grown_f[:length] = frames[w]
            grown_w[:length] = weights[w]
            frames[w] = grown_f
            weights[w] = grown_w
        frames[w][length] = frame
        weights[w][length] = values[t]
        lengths[w] = length + 1


@njit(cache=True)
def _retract_postings(frames, lengths, frame, words) -> None:
    """Drop ``frame``'s postings, each the last of its word's list (the frame was the last one added)."""
    for t in range(words.shape[0]):
        w = words[t]
        length = lengths[w]
        if length == 0 or frames[w][length - 1] != frame:
            raise ValueError("the frame's postings are not the last ones")
        lengths[w] = length - 1


@njit(cache=True)
def _posting_scores(frames, weights, lengths, words, values, limit, out):
    """Add the open block's scores of frames < limit into ``out``."""
    for t in range(words.shape[0]):
        w = words[t]
        f, x = frames[w], weights[w]
        for p in range(lengths[w]):
            if f[p] >= limit:
                break  # postings are in frame order
            out[f[p]] += values[t] * x[p]


@njit(cache=True)
def _block_scores(offsets, frames, weights, words, values, limit, out):
    """Add a frozen block's scores of frames < limit into ``out`` (postings word by word, each in frame order)."""
    for t in range(words.shape[0]):
        w = words[t]
        for p in range(offsets[w], offsets[w + 1]):
            if frames[p] >= limit:
                break
            out[frames[p]] += values[t] * weights[p]


@njit(cache=True)
def _freeze_postings(frames, weights, lengths, offsets, out_frames, out_weights) -> None:
    for w in range(lengths.shape[0]):
        start = offsets[w]
        for p in range(lengths[w]):
            out_frames[start + p] = frames[w][p]
            out_weights[start + p] = weights[w][p]


class InvertedIndex:
    """Word -> (frame, weight) postings for TF-IDF retrieval; cost per query grows with the postings touched.

    Postings live in compiled lists (one per word): adding a frame and scoring a query are single compiled calls
    (a Python loop over a frame's ~100 words cost ~1 ms per query, a quarter of the engine's per-frame upkeep).
    Every ``block_frames`` frames the lists are frozen into one word-ordered block of a ``storage``
    (:mod:`.storage`): memory by default, or mapped files, so a long run's index need not stay in the process's
    memory. A frame's score sums its words in the query's word order either way: blocks change no score.
    """

    def __init__(self, vocabulary_size: int, storage=None, block_frames: int = 1024) -> None:
        if vocabulary_size < 1 or block_frames < 1:
            raise ValueError("vocabulary_size and block_frames must be >= 1")
        self.vocabulary_size = int(vocabulary_size)
        self.block_frames = int(block_frames)
        self._storage = storage if storage is not None else MemoryStorage()
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # frozen: offsets, frames, weights
        self._open()
        self._count = 0

    def _open(self) -> None:
        self._frames, self._weights = _new_postings(self.vocabulary_size)
        self._length = np.zeros(self.vocabulary_size, np.int64)

    @classmethod
    def reopen(cls, vocabulary_size: int, storage, block_postings, block_frames: int = 1024) -> "InvertedIndex":
        """The index whose frozen blocks (``block_postings``: their sizes, :meth:`block_postings`) ``storage``
        holds; the open block's frames are to be added again."""
        index = cls(vocabulary_size, storage, block_frames)
        for postings in np.asarray(block_postings, np.int64).reshape(-1).tolist():
            index._blocks.append(index._block_arrays(len(index._blocks), postings))
            index._count += index.block_frames
        return index

    def _block_arrays(self, k: int, postings: int):
        size = max(1, postings)  # an empty block still has its (empty) arrays
        return (self._storage.chunk("index_offsets", k, (self.vocabulary_size + 1,), np.int64),
                self._storage.chunk("index_frames", k, (size,), np.int32),
                self._storage.chunk("index_weights", k, (size,), np.float64))

    def block_postings(self) -> np.ndarray:
        """Postings of each frozen block (what :meth:`reopen` needs besides the storage)."""
        return np.array([int(offsets[-1]) for offsets, _, _ in self._blocks], np.int64)

    @property
    def frozen_frames(self) -> int:
        return len(self._blocks) * self.block_frames

    def __len__(self) -> int:
        return self._count

    def add(self, vector: BowVector) -> int:
        """Index the next frame; returns its id (frames are numbered 0, 1, ... in insertion order)."""
        if self._count - self.frozen_frames == self.block_frames:
            self._freeze()
        frame = self._count
        if vector.words.size:
            _add_postings(self._frames, self._weights, self._length, frame, vector.words, vector.weights)
        self._count += 1
        return frame

    def retract_last(self, vector: BowVector) -> None:
        """Take the newest frame's postings (``vector``, as it was added) out again; the frame keeps its number and
        scores 0 from then on (a redundant frame)."""
        frame = self._count - 1
        if frame < self.frozen_frames:
            raise ValueError("no frame of the open block to retract")
        if vector.words.size:
            _retract_postings(self._frames, self._length, frame, vector.words)

    def _freeze(self) -> None:
        offsets = np.concatenate([[0], np.cumsum(self._length)]).astype(np.int64)
        stored_offsets, frames, weights = self._block_arrays(len(self._blocks), int(offsets[-1]))
        stored_offsets[:] = offsets
        _freeze_postings(self._frames, self._weights, self._length, offsets, frames, weights)
        self._blocks.append((stored_offsets, frames, weights))
        self._open()

    def scores(self, vector: BowVector, limit: int | None = None) -> np.ndarray:
        """Cosine similarity of ``vector`` to every indexed frame (or to frames ``< limit``)."""
        limit = self._count if limit is None else max(0, min(int(limit), self._count))
        out = np.zeros(limit)
        if limit == 0 or vector.words.size == 0:
            return out
        for k, (offsets, frames, weights) in enumerate(self._blocks):
            if k * self.block_frames >= limit:
                break
            _block_scores(offsets, frames, weights, vector.words, vector.weights, limit, out)
        if limit > self.frozen_frames:
            _posting_scores(self._frames, self._weights, self._length, vector.words, vector.weights, limit, out)
        return out

    def query(self, vector: BowVector, limit: int, top: int, min_score: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The ``top`` frames ``< limit`` with the highest scores above ``min_score``, best first."""
        scores = self.scores(vector, limit)
        keep = np.flatnonzero(scores > min_score)
        if keep.size > top:
            keep = keep[np.argpartition(-scores[keep], top - 1)[:top]]
        order = keep[np.lexsort((keep, -scores[keep]))]
        return order, scores[order]
