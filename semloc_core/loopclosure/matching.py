"""Correspondence search through the vocabulary for the DP (a direct index, as DBoW2 uses for matching).

The DP similarity (§3.3.2) needs the pairs of features whose descriptors match (L1 distance below ``t_match``).
Testing every descriptor pair costs n x m 128-byte distances (~0.36 ms for two route frames of 150 features), and
only about 10 of those ~22,000 pairs match. Here every feature is filed under its ``words_per_feature`` nearest
visual words and only features sharing a word are tested - with the exact L1 threshold, so every match found is a
true match and the DP runs on a subset of the exhaustive match matrix. On `route` (500 words, 3 words per feature)
that subset holds 98 % of the matches, a pair of frames costs 2-3 % of the exhaustive test, and M computed this way
has correlation 0.999 with the exhaustive M and the same AP (docs/loopclosure.md). With the vocabulary's whole size
as ``words_per_feature`` every pair shares a word and the result is the exhaustive one (tested).

:class:`FrameStore` keeps the frames' descriptors and words one after the other in growing arrays of a storage
(:mod:`.storage`: memory, or files the process maps) and aligns one stored frame against many others in one
compiled call.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from semloc_core.loopclosure.features import DESCRIPTOR_SIZE
from semloc_core.loopclosure.similarity import (AlignmentParams, _align_match_list, _band_count, _check_lengths, _units,
                                                band_log_scales)
from semloc_core.loopclosure.storage import MemoryStorage

_HALF = DESCRIPTOR_SIZE // 2


@njit(cache=True)
def _shares_lower_word(query_words, q, reference_words, r, word) -> bool:
    """Whether features q and r share a word below ``word`` (then the pair was tested there already)."""
    for a in range(query_words.shape[1]):
        w = query_words[q, a]
        if w < word:
            for b in range(reference_words.shape[1]):
                if reference_words[r, b] == w:
                    return True
    return False


@njit(cache=True)
def _indexed_match_list(qd, qw, q_post_words, q_post_features, rd, rw, r_post_words, r_post_features, t_match,
                        out_q, out_r):
    """Exact matches (L1 < t_match) among feature pairs sharing a word: a merge of the two frames' postings (each
    sorted by word). Writes (query, reference) indices into out_q/out_r (grown when full); returns them and the
    count."""
    count = 0
    a, b = 0, 0
    na, nb = q_post_words.shape[0], r_post_words.shape[0]
    while a < na and b < nb:
        wa, wb = q_post_words[a], r_post_words[b]
        if wa < wb:
            a += 1
            continue
        if wb < wa:
            b += 1
            continue
        a_end = a
        while a_end < na and q_post_words[a_end] == wa:
            a_end += 1
        b_end = b
        while b_end < nb and r_post_words[b_end] == wa:
            b_end += 1
        for x in range(a, a_end):
            q = q_post_features[x]
            for y in range(b, b_end):
                r = r_post_features[y]
                if _shares_lower_word(qw, q, rw, r, wa):
                    continue
                # In two halves of constant length, each a loop that vectorises in full: most pairs are past
                # t_match after the first (the store holds DESCRIPTOR_SIZE dimensions).
                total = 0
                for d in range(_HALF):
                    total += abs(np.int32(qd[q, d]) - np.int32(rd[r, d]))
                if total >= t_match:
                    continue
                for d in range(_HALF, DESCRIPTOR_SIZE):
                    total += abs(np.int32(qd[q, d]) - np.int32(rd[r, d]))
                if total < t_match:
                    if count == out_q.shape[0]:
                        grown_q = np.empty(2 * count, np.int64)
                        grown_r = np.empty(2 * count, np.int64)
                        grown_q[:count] = out_q
                        grown_r[:count] = out_r
                        out_q, out_r = grown_q, grown_r
                    out_q[count] = q
                    out_r[count] = r
                    count += 1
        a, b = a_end, b_end
    return out_q, out_r, count


@njit(cache=True)
def _align_stored(query, candidates, descriptors, words, post_words, post_features, offset_of, length_of, t_match,
                  s_match, s_miss, s_gap, bearings, half_width, log_scales):
    """The count k of stored frame ``query`` against each candidate frame: the matched pairs of the optimal cyclic
    alignment, or with ``half_width`` > 0 the bearing-band count U of the matches (similarity.band_count)."""
    qo, n = offset_of[query], length_of[query]
    band = half_width > 0
    qb = bearings[qo:qo + n]
    most = 0
    for c in range(candidates.shape[0]):
        most = max(most, length_of[candidates[c]])
    residual = np.empty(max(16, 4 * n) if band else 0)
    order = np.empty(residual.shape[0], np.int64)
    row_hits = np.zeros(n if band else 0, np.int64)
    col_hits = np.zeros(most if band else 0, np.int64)
    per = words.shape[1]
    qd = descriptors[qo:qo + n]
    qw = words[qo:qo + n]
    qpw = post_words[qo * per:(qo + n) * per]
    qpf = post_features[qo * per:(qo + n) * per]
    out_q = np.empty(max(16, 4 * n), np.int64)
    out_r = np.empty(max(16, 4 * n), np.int64)
    k = np.zeros(candidates.shape[0], np.int64)
    for c in range(candidates.shape[0]):
        f = candidates[c]
        ro, m = offset_of[f], length_of[f]
        if n == 0 or m == 0:
            continue
        out_q, out_r, count = _indexed_match_list(
            qd, qw, qpw, qpf, descriptors[ro:ro + m], words[ro:ro + m], post_words[ro * per:(ro + m) * per],
            post_features[ro * per:(ro + m) * per], t_match, out_q, out_r)
        if not band:
            k[c] = _align_match_list(out_q, out_r, count, n, m, s_match, s_miss, s_gap)[1]
            continue
        if count > residual.shape[0]:
            residual = np.empty(out_q.shape[0])
            order = np.empty(out_q.shape[0], np.int64)
        k[c] = _band_count(out_q, out_r, count, qb, bearings[ro:ro + m], half_width, log_scales, residual, order,
                           row_hits, col_hits)
    return k


def _postings(words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(word, feature) entries of a frame sorted by word."""
    flat = words.reshape(-1)
    order = np.argsort(flat, kind="stable")
    return flat[order].astype(np.int32), (order // words.shape[1]).astype(np.int32)


class FrameStore:
    """Descriptors and visual words of a growing sequence of frames, for indexed alignment.

    ``add(descriptors)`` stores a frame; ``set_words(frame, words)`` files its features under their (n,
    ``words_per_feature``) nearest words, which the frame needs before :meth:`align` may use it (the vocabulary can
    come later than the frame). The arrays live in ``storage`` (default: memory); :meth:`reopen` finds the frames of
    a persistent storage again from their lengths.
    """

    def __init__(self, words_per_feature: int, storage=None) -> None:
        if words_per_feature < 1:
            raise ValueError("words_per_feature must be >= 1")
        self.words_per_feature = int(words_per_feature)
        self.storage = storage if storage is not None else MemoryStorage()
        per = self.words_per_feature
        self._desc = self.storage.array("descriptors", np.uint8, (DESCRIPTOR_SIZE,))
        self._bearings = self.storage.array("bearings", np.float64)  # for the bearing-band count
        self._words = self.storage.array("words", np.int32, (per,))
        self._post_words = self.storage.array("post_words", np.int32)
        self._post_features = self.storage.array("post_features", np.int32)
        self._offset_of = np.zeros(64, np.int64)
        self._length_of = np.zeros(64, np.int64)
        self._has_words = np.zeros(64, bool)
        self._frames = 0
        self._used = 0  # features stored

    @classmethod
    def reopen(cls, words_per_feature: int, storage, lengths, has_words: bool) -> "FrameStore":
        """The store of frames with these feature counts, already written to ``storage`` (a persistent one)."""
        store = cls(words_per_feature, storage)
        lengths = np.asarray(lengths, np.int64).reshape(-1)
        if np.any(lengths < 0):
            raise ValueError("feature counts must be >= 0")
        for n in lengths.tolist():
            store._place(n)
        per = store.words_per_feature
        for array, rows in ((store._desc, store._used), (store._bearings, store._used), (store._words, store._used),
                            (store._post_words, store._used * per), (store._post_features, store._used * per)):
            if array.data.shape[0] < rows:
                raise ValueError(f"the storage holds {array.data.shape[0]} of the {rows} stored rows")
        store._has_words[: store._frames] = has_words
        return store

    def __len__(self) -> int:
        return self._frames

    def has_words(self, frame: int) -> bool:
        return bool(self._has_words[frame])

    def _place(self, n: int) -> int:
        """Reserve the next frame's n feature slots; returns its first."""
        f = self._frames
        if f == self._offset_of.size:
            for name in ("_offset_of", "_length_of", "_has_words"):
                old = getattr(self, name)
                setattr(self, name, np.concatenate([old, np.zeros_like(old)]))
        self._offset_of[f], self._length_of[f] = self._used, n
        self._used += n
        self._frames += 1
        return self._used - n

    def add(self, descriptors: np.ndarray, bearings: np.ndarray) -> None:
        """Store a frame: its (n, DESCRIPTOR_SIZE) uint8 descriptors and n bearings (radians, in [-pi, pi])."""
        d = np.asarray(descriptors)
        if d.ndim != 2 or d.shape[1] != DESCRIPTOR_SIZE or d.dtype != np.uint8:
            raise ValueError(f"descriptors must be uint8 of shape (n, {DESCRIPTOR_SIZE})")
        b = np.asarray(bearings, np.float64)
        if b.shape != (d.shape[0],) or not np.all(np.abs(b) <= np.pi):  # (NaN fails too)
            raise ValueError(f"a frame of {d.shape[0]} descriptors needs as many bearings in [-pi, pi], got shape "
                             f"{b.shape}")
        n, per = d.shape[0], self.words_per_feature
        used = self._used + n
        # Every array's rows first: a storage that cannot hold them (a full disk) raises with the store unchanged.
        for array, rows in ((self._desc, used), (self._bearings, used), (self._words, used),
                            (self._post_words, used * per), (self._post_features, used * per)):
            array.reserve(rows)
        offset = self._place(n)
        self._desc.data[offset:offset + n] = d
        self._bearings.data[offset:offset + n] = b

    def retract_last(self) -> None:
        """Keep the newest frame's number but none of its features (a redundant frame: its slots go to the next
        frame); it then aligns as a frame without features."""
        f = self._frames - 1
        if f < 0:
            raise IndexError("no frame to retract")
        self._used -= int(self._length_of[f])
        self._length_of[f] = 0
        self._has_words[f] = True

    def descriptors(self, frame: int) -> np.ndarray:
        """The stored descriptors of ``frame`` (a read-only view)."""
        offset, n = int(self._offset_of[frame]), int(self._length_of[frame])
        view = self._desc.data[offset:offset + n]
        view.flags.writeable = False
        return view

    def bearings(self, frame: int) -> np.ndarray:
        """The stored bearings of ``frame`` (a read-only view)."""
        offset, n = int(self._offset_of[frame]), int(self._length_of[frame])
        view = self._bearings.data[offset:offset + n]
        view.flags.writeable = False
        return view

    def words(self, frame: int) -> np.ndarray:
        """The (n, words_per_feature) words ``frame`` is filed under (set_words)."""
        if not self._has_words[frame]:
            raise ValueError(f"frame {frame} has no words yet")
        offset, n = int(self._offset_of[frame]), int(self._length_of[frame])
        return self._words.data[offset:offset + n].copy()

    def set_words(self, frame: int, words: np.ndarray) -> None:
        per = self.words_per_feature
        words = np.asarray(words)
        n = int(self._length_of[frame])
        if words.shape != (n, per):
            raise ValueError(f"frame {frame}: expected ({n}, {per}) words, got {words.shape}")
        offset = int(self._offset_of[frame])
        self._words.data[offset:offset + n] = words
        post_words, post_features = _postings(words)
        self._post_words.data[offset * per:(offset + n) * per] = post_words
        self._post_features.data[offset * per:(offset + n) * per] = post_features
        self._has_words[frame] = True

    def align(self, query: int, candidates, params: AlignmentParams = AlignmentParams()) -> np.ndarray:
        """k of frame ``query`` against each candidate frame, on the matches among features that share a word: the
        matched pairs of the optimal cyclic alignment, or the bearing-band count (``params.band_half_width`` > 0)."""
        candidates = np.ascontiguousarray(candidates, np.int64).reshape(-1)
        frames = np.concatenate([[query], candidates])
        if frames.size and (frames.min() < 0 or frames.max() >= self._frames):
            raise IndexError("frame out of range")
        if not self._has_words[frames].all():
            raise ValueError("every frame aligned needs its words (set_words)")
        if candidates.size:
            _check_lengths(int(self._length_of[query]), int(self._length_of[candidates].max()))
        return _align_stored(query, candidates, self._desc.data, self._words.data, self._post_words.data,
                             self._post_features.data, self._offset_of, self._length_of, float(params.t_match),
                             _units(params.s_match), _units(params.s_miss), _units(params.s_gap),
                             self._bearings.data, float(params.band_half_width),
                             band_log_scales(params.band_max_log_scale))
