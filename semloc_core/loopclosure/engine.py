"""Incremental loop-closure engine: one frame's features in, its loop decision and the map update out.

Per frame (all in the caller's thread, no I/O; the two one-off steps, the calibration and the vocabulary, may be
computed ahead on any thread: :meth:`LoopClosureEngine.prepare`):

1. TF-IDF retrieval over an inverted index returns the best earlier frames outside the window w (plus the
   neighbours of the previous frame's loop partners, which keeps a loop band continuous in the lattice).
2. The cyclic DP scores the frame against those candidates only: a sparse column of M. Its correspondences are
   searched through the vocabulary (``match_words``, :mod:`.matching`): only features filed under a common visual
   word are compared, with the exact match threshold. Once the sequence's calibration gives a bearing band, the
   score's count is the band count U of those correspondences rather than the DP's k (:mod:`.similarity`).
3. The MRF gains that column and re-runs loopy BP on the last ``band`` columns, warm-started.
4. The new column's decisions (and any revised decisions inside the band) update the topological map.

Without a vocabulary the engine learns one from its first ``bootstrap_frames`` frames (k-means, no download); until
then every frame outside the window is a candidate. ``exhaustive=True`` scores every frame outside the window
(the thesis's full M), for reference runs.

What grows with the map - every frame's descriptors and words, and the lattice's final cells - lives in a
``storage`` (:mod:`.storage`): memory by default, or files (``semloc_core.io.loopclosure.FileStorage``), whose
pages the engine lets go of every ``RELEASE_EVERY`` frames, or sooner once it has aligned ``RELEASE_ALIGNED``
candidates (what it touches grows with them). The engine's own memory per frame is then a few
numbers, its inverted index and its topological map; :meth:`LoopClosureEngine.state` holds those and the lengths
of what is stored, so with files its size and restore time barely grow with the map.

Redundant frames (``cull_redundant``; RTAB-Map's rehearsal, ORB-SLAM's key-frame culling): a frame whose loop at
least ``map_min_belief`` sure is with a frame that already holds its view - the alignment matched a majority of the
larger frame's features, and at least as large a share as any two successive frames of the map matched - is reported
as usual (loops, revisions, status, node) but leaves the map: its features are taken out of the store and the index
(it is never aligned again), the topological map records it as a visit of the holder's place, and its lattice
column, once final, joins a bounded sample of final cells (``mrf.RETAINED_CELLS``) rather than the archive. The
decision's null is spread over the pairs whose earlier frame is kept. A camera going over the same images matches
them all; real revisits are not that close (docs/loopclosure.md).

Robot cameras (issue 33): with ``calibration.mode`` ``"sequence"`` the engine holds its first ``calibration.frames``
frames in memory, derives the match threshold, the repeated-texture threshold, the static-region mask and the
bearing band from them (:mod:`.calibration`), and only then stores them (calibrated) and aligns anything; loops are
reported at the belief threshold expected to reach ``target_precision`` (:mod:`.decision`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from enum import Enum

import numpy as np
from pydantic import Field

from semloc_core.loopclosure.bow import BowVector, InvertedIndex, Vocabulary, train_vocabulary
from semloc_core.loopclosure.calibration import Calibration, CalibrationParams, calibrate
from semloc_core.loopclosure.decision import MIN_NULL_SAMPLE, Decision, NullFit, decide
from semloc_core.loopclosure.features import DESCRIPTOR_SIZE, FeatureSequence
from semloc_core.loopclosure.matching import FrameStore
from semloc_core.loopclosure.mrf import ARCHIVE_DTYPE, IncrementalMrf, MrfParams, background_normalization
from semloc_core.loopclosure.similarity import AlignmentParams, alignment_matches, alignment_score, pair_count
from semloc_core.loopclosure.storage import MemoryStorage, RecentRecords
from semloc_core.loopclosure.topomap import IncrementalTopoMap, TopoMapUpdate
from semloc_core.settings import settings

STATE_FORMAT = "semloc.loopclosure_state"
# 5: the calibration from the sequence, the frames held for it and the decision threshold (issue 33);
# 4: descriptors, words and final lattice cells in a storage, the state holds the index
# 6: redundant frames (cull_redundant) and the closest successive frames
# 7: the decision's off-place partners (decision_places)
# 8: the background sample's frames (the decision's null is fitted to their beliefs)
# 9: every stored frame's bearings (the bearing-band count) and the calibration's band tau and L
STATE_VERSION = 9
_BACKGROUND_KEPT = 20_000
# A background score, how many pairs it stands for, its two frames' feature counts and the two frames.
_BACKGROUND_DTYPE = np.dtype([("score", np.float64), ("weight", np.float64), ("count_a", np.int64),
                              ("count_b", np.int64), ("earlier", np.int64), ("later", np.int64)])
_DECISION_CELLS = 200  # scored pairs before the decision threshold is estimated
# Growth of the lattice between two estimates of the decision threshold. Each estimate costs 1-2 ms at 6,000-18,000
# cells, and at 5 % they made up the slowest 5 % of a route's frames. At 10 % there are half as many; the decisions
# are barely affected (results/2026-12-06-loop-engine-p95.md).
_DECISION_GROWTH = 0.10
RELEASE_EVERY = 32  # frames between letting go of resident pages of a file storage ...
RELEASE_ALIGNED = 1024  # ... at most: also once this many candidates were aligned since
INDEX_BLOCK_FRAMES = 1024  # frames of the inverted index frozen into one block of the storage


class FrameStatus(str, Enum):
    LOOP_FOUND = "loop_found"
    TOO_FEW_FRAMES = "too_few_frames"  # nothing outside the window yet
    NO_CANDIDATE = "no_candidate"  # retrieval found no earlier frame worth aligning (or the frame has no features)
    REJECTED = "rejected"  # candidates were aligned but inference found no loop


@settings
class EngineParams:
    """Engine settings.

    ``window`` w (frames closer in time are never candidates), ``band`` (columns re-inferred per frame);
    candidates per frame: the ``candidates`` best TF-IDF matches outside the window with a score above
    ``min_retrieval_score``, every frame within ``neighbour_candidates`` of a loop partner (D) of the previous frame,
    and ``background_samples`` frames drawn at random (``seed``), whose scores calibrate the node potential;
    ``exhaustive`` aligns every frame outside the window instead, as the engine does until its vocabulary exists
    and until the lattice holds ``bootstrap_pairs`` pairs (so the background estimate starts from every pair rather
    than from a handful). The vocabulary, when none is given, is learnt (``vocabulary_words``) from the first
    ``bootstrap_frames`` frames. The map: ``temporal_radius`` r, and loops
    join places only when at least ``map_min_belief`` sure (log-odds). Frames with fewer than ``min_features``
    features are not aligned. ``match_words``: each feature is filed under its ``match_words`` nearest visual words
    and the DP compares only features sharing one (:mod:`.matching`); 0 compares every pair of features, as the
    thesis does (and the engine does until it has a vocabulary).

    ``calibration`` (issue 33): with mode ``"sequence"`` the engine derives the match threshold, the repeated-texture
    threshold and the static-region mask from its first ``calibration.frames`` frames (:mod:`.calibration`; give it
    unsuppressed features) and aligns nothing before; ``"fixed"`` uses ``alignment.t_match`` and the features as
    given. ``target_precision``: loops are reported at the belief threshold whose expected precision reaches it
    (:mod:`.decision`), re-estimated as the lattice grows. ``cull_redundant``: a frame whose view a sure loop
    partner already holds is reported but not kept (module docstring), so a camera going over the same places again
    and again does not grow the map.
    """

    window: int = Field(30, ge=0, description="w: frames closer in time are never loop candidates")
    band: int = Field(30, ge=1, le=10000, description="columns re-inferred by loopy BP per frame")
    candidates: int = Field(10, ge=1, le=1000, description="earlier frames retrieved per frame (TF-IDF) for the DP")
    background_samples: int = Field(2, ge=0, description="frames drawn at random per frame, scored as the background "
                                    "of the calibrated potential")
    seed: int = Field(0, description="seed of those draws")
    neighbour_candidates: int = Field(3, ge=0, le=100, description="also align frames this close to the previous "
                                      "frame's loop partners")
    min_retrieval_score: float = Field(0.0, description="retrieved candidates need a TF-IDF score above this")
    exhaustive: bool = Field(False, description="align every frame outside the window (the thesis's full M)")
    vocabulary_words: int = Field(500, ge=8, le=100000, description="words of a vocabulary learnt on the fly")
    bootstrap_frames: int = Field(60, ge=1, description="frames to learn the vocabulary from")
    bootstrap_pairs: int = Field(500, ge=0, description="align exhaustively until the lattice holds this many pairs")
    temporal_radius: int = Field(2, ge=0, le=100, description="r: frames <= r apart are one place in the map")
    map_min_belief: float = Field(12.0, description="log-odds a loop needs to join places in the map")
    min_features: int = Field(8, ge=0, description="frames with fewer features are not aligned")
    match_words: int = Field(2, ge=0, description="each feature is filed under its match_words nearest words and "
                             "the DP compares features sharing one (0: every pair)")
    alignment: AlignmentParams = Field(default_factory=AlignmentParams, description="the cyclic DP alignment")
    mrf: MrfParams = Field(default_factory=MrfParams, description="the MRF and its inference")
    calibration: CalibrationParams = Field(default_factory=CalibrationParams, description="t_match, repeated "
                                           "texture and static regions from the first frames, or fixed")
    target_precision: float = Field(0.95, gt=0, le=1, description="loops are reported at the belief threshold "
                                    "expected to reach this precision")
    decision_places: bool = Field(True, description="the expected precision also counts as false the decided "
                                  "partners more than temporal_radius frames from their visit's strongest one")
    cull_redundant: bool = Field(True, description="a frame whose sure loop partner already holds its view (most "
                                 "features of both matched, and at least as closely as successive frames match) "
                                 "is reported but not kept: no features stored, indexed or aligned later")

    def __post_init__(self) -> None:
        if self.match_words > self.vocabulary_words:
            raise ValueError("match_words cannot exceed vocabulary_words")

    def to_json_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json_dict(cls, data: dict) -> "EngineParams":
        data = dict(data)
        alignment = AlignmentParams(**data.pop("alignment", {}))
        mrf = MrfParams(**data.pop("mrf", {}))
        calibration = CalibrationParams(**data.pop("calibration", {}))
        return cls(alignment=alignment, mrf=mrf, calibration=calibration, **data)


@dataclass
class FrameResult:
    """The engine's answer for one frame.

    ``candidates`` the earlier frames aligned (retrieved, best first, then a few drawn at random to track the
    background level) with their ``retrieval_scores`` and DP
    ``similarity`` (this frame's row of M); ``loops``/``loop_beliefs`` the earlier frames it closes a loop with (belief
    at least the decision threshold) and the max-marginal log-odds; ``revised`` earlier frames whose loops changed
    (inside the band: by inference; any frame: by a new decision threshold); ``decision`` the threshold in force and the precision expected of it. The map joins
    places only on loops at least ``map_min_belief`` sure (spatial distinctiveness is a must, compactness a should,
    §3.1): ``map_update`` and ``node``.
    """

    frame: int
    status: FrameStatus
    candidates: np.ndarray
    retrieval_scores: np.ndarray
    similarity: np.ndarray
    loops: np.ndarray
    loop_beliefs: np.ndarray
    revised: dict[int, np.ndarray]
    map_update: TopoMapUpdate
    node: int
    decision: Decision | None = None
    redundant_with: int = -1  # the frame holding this one's view, when this one was not kept (cull_redundant)


@dataclass(frozen=True)
class Prepared:
    """The one-off work of frame ``frame``'s :meth:`LoopClosureEngine.add_frame`, done ahead
    (:meth:`LoopClosureEngine.prepare`): the calibration (``calibrate``'s result, None when it found nothing) when
    ``calibrated``, the vocabulary (None: too little texture to learn one yet) when ``trained``."""

    frame: int
    calibrated: bool = False
    calibration: Calibration | None = None
    trained: bool = False
    vocabulary: Vocabulary | None = None


class LoopClosureEngine:
    def __init__(self, params: EngineParams = EngineParams(), vocabulary: Vocabulary | None = None,
                 storage=None) -> None:
        self.params = params
        self.vocabulary = vocabulary
        self.storage = storage if storage is not None else MemoryStorage()
        self.mrf = IncrementalMrf(params.mrf, params.band, window=params.window,
                                  archive=self.storage.log("mrf_cells", ARCHIVE_DTYPE))
        # Scores of pairs drawn at random (the calibrated potential's reference), how many pairs each stands for and
        # the feature counts of its two frames: the latest _BACKGROUND_KEPT.
        self._background = RecentRecords(_BACKGROUND_DTYPE, _BACKGROUND_KEPT)
        self._normalized_at = 0  # background samples drawn when the normalization was last estimated
        self._drawn = 0
        self._norm = None
        self._rng = np.random.default_rng(params.seed)
        self.topomap = IncrementalTopoMap(params.temporal_radius)
        self.calibration: Calibration | None = None  # from the sequence (calibration mode "sequence")
        self.alignment = params.alignment  # the DP's parameters in force (t_match from the calibration)
        self.decision: Decision | None = None
        self._decided_at = 0  # lattice cells when the decision threshold was last estimated
        self._pending: list[FeatureSequence] = []  # the first frames, held (unstored) until the calibration
        self._sizes = np.zeros(64, np.int64)  # features per frame (stored: 0 for a redundant frame)
        self._redundant = np.zeros(64, bool)  # frames not kept (cull_redundant)
        self._n_redundant = 0
        # The closest two successive stored frames came (matched features over the larger count): a redundant frame
        # is at least this close to its partner; and the pairs outside the window whose earlier frame is kept.
        self._closest_successive = -np.inf
        self._pairs = 0
        self._kept_outside = 0  # kept frames outside the newest frame's window
        # Descriptors live in the store's chunks with the words they are filed under (its first word is the one
        # the frame's TF-IDF vector counts).
        self._store = FrameStore(max(1, params.match_words), self.storage)
        self._indexed = 0  # frames in the inverted index
        self._query: BowVector | None = None  # the TF-IDF vector of the newest indexed frame
        self._since_release = [0, 0]  # frames and aligned candidates since the storage last let go of its pages
        self._index: InvertedIndex | None = None
        if vocabulary is not None:
            self._check_vocabulary(vocabulary)
            self._index = InvertedIndex(vocabulary.size, self.storage, INDEX_BLOCK_FRAMES)

    @property
    def n_frames(self) -> int:
        return len(self._store) + len(self._pending)

    @property
    def n_kept(self) -> int:
        """Frames the map holds the view of (not redundant)."""
        return self.n_frames - self._n_redundant

    def descriptors(self, frame: int) -> np.ndarray:
        """The stored descriptors of ``frame`` (read-only; a frame held for the calibration: as it came)."""
        stored = len(self._store)
        return self._store.descriptors(frame) if frame < stored else self._pending[frame - stored].descriptors

    # --- one frame ------------------------------------------------------------------------------------------

    def prepare(self, features: FeatureSequence) -> Callable[[], Prepared] | None:
        """The one-off work ``add_frame(features)`` would do - the calibration on the calibration's last frame, the
        vocabulary's k-means at ``bootstrap_frames``: seconds each, where a frame takes milliseconds - as a function
        of copies of its inputs, to be run on any thread (a worker's helper, so that its frames keep coming
        meanwhile); ``add_frame(features, prepared=its result)`` then uses it, with the same result as computing it
        there. None when that frame has no such work. The engine must not change in between."""
        if not isinstance(features, FeatureSequence):
            raise TypeError(f"expected a FeatureSequence, got {type(features).__name__}")
        t, p = self.n_frames, self.params
        calibrates = self.calibrating and len(self._pending) + 1 >= p.calibration.frames
        if self.calibrating and not calibrates:
            return None  # (no index while calibrating: no vocabulary either)
        trains = self.vocabulary is None and t + 1 >= p.bootstrap_frames
        if not (calibrates or trains):
            return None
        stored = [np.array(self._store.descriptors(f)) for f in range(len(self._store)) if self._sizes[f]]
        pending, calibration, frames = [*self._pending, features] if calibrates else [features], self.calibration, t + 1

        def work() -> Prepared:
            found = _calibration_or_fallback(pending, p, frames) if calibrates else calibration
            vocabulary = None
            if trains:
                new = [found.apply(f) if found is not None else f for f in pending]
                vocabulary = _learn_vocabulary(stored + [f.descriptors for f in new if len(f)], p)
            return Prepared(t, calibrates, found if calibrates else None, trains, vocabulary)

        return work

    def add_frame(self, features: FeatureSequence, prepared: Prepared | None = None) -> FrameResult:
        """Frame ``features``'s loops and map update; ``prepared``: what :meth:`prepare` computed for it."""
        if not isinstance(features, FeatureSequence):
            raise TypeError(f"expected a FeatureSequence, got {type(features).__name__}")
        t = self.n_frames
        if prepared is not None and prepared.frame != t:
            raise ValueError(f"work prepared for frame {prepared.frame} given to frame {t}")
        calibrated = False
        if self.calibrating:
            self._pending.append(features)
            self._append_size(len(features))
            if len(self._pending) >= self.params.calibration.frames:
                features = self._calibrate(prepared)
                calibrated = True
        else:
            if self.calibration is not None:
                features = self.calibration.apply(features)
            self._store.add(features.descriptors, features.bearings)
            self._append_size(len(features))
        self._count_pairs(t)
        successive = False  # frame t's match with the frame before it is to be noted (with the candidates' below)
        if not self.calibrating:
            self._index_frame(t, prepared)
            if self.params.cull_redundant:
                for frame in range(1, t) if calibrated else ():  # (the calibration stores every frame)
                    self._note_successive(frame)
                successive = self._successive_applies(t)
        retrieved, retrieval_all, exhaustive = self._candidates(t)
        enough = len(features) >= self.params.min_features
        drawn = self._background_draw(t) if enough and not exhaustive else np.zeros(0, np.int64)
        retrieved_set = set(retrieved.tolist())  # (a set: np.isin costs more than a frame's few draws)
        fresh = np.array([frame for frame in drawn.tolist() if frame not in retrieved_set], np.int64)
        candidates = np.concatenate([retrieved, fresh]).astype(np.int64)
        retrieval = retrieval_all[candidates] if retrieval_all is not None else np.ones(candidates.size)
        if successive:  # one alignment call for both (each candidate is aligned on its own)
            matched = self._matched(t, np.append(candidates, t - 1))
            self._note_match(t, matched[-1])
            matched = matched[:-1]
        else:
            matched = self._matched(t, candidates)
        similarity = self._similarity(t, candidates, matched)
        # The background sample: pairs drawn uniformly (whether retrieval picked them too or not, so the sample is
        # that of all pairs, as the batch's statistics of M are), or every pair of an exhaustive column.
        if exhaustive:
            sampled = similarity
        else:
            position = {frame: k for k, frame in enumerate(candidates.tolist())}
            sampled = similarity[[position[frame] for frame in drawn.tolist()]]
        sampled_frames = candidates if exhaustive else drawn
        # A pair drawn from this column stands for the column's pairs, so the sample weighs every pair ever scored
        # alike, as the batch's statistics of the whole M do (an unweighted sample overweights the early columns,
        # whose pairs - frames of one stretch of route - are not representative: median -14.5 vs -27.5 on seed 1).
        if sampled.size:
            records = np.empty(sampled.size, _BACKGROUND_DTYPE)
            records["score"], records["weight"] = sampled, max(1.0, (t - self.params.window) / sampled.size)
            records["count_a"], records["count_b"] = self._sizes[sampled_frames], len(features)
            records["earlier"], records["later"] = sampled_frames, t
            self._background.append(records)
        self._drawn += sampled.size
        band_first = max(0, t - self.params.band + 1)
        before = self.mrf.cells_from(band_first)[2]  # what was reported and linked for the band's frames so far
        self.mrf.add_column(candidates, similarity, self._normalization(), count=len(features))
        reported = self.decision_threshold  # what the band's frames were reported at
        cells = self._decide()
        revised, relinked = self._revisions(band_first, t, before, reported, cells)
        revision = TopoMapUpdate()  # what the revisions changed in the map goes out with this frame's change
        for frame, (partners, strengths) in sorted(relinked.items()):
            revision = revision.then(self.topomap.revise(frame, partners, strengths))
        rows, _, beliefs = self.mrf.column(t)
        loop_mask = beliefs >= self.decision_threshold
        loops, loop_beliefs = rows[loop_mask], beliefs[loop_mask]
        # The map links the places of sure loops only; among them a frame joins its strongest one (topomap). A
        # frame whose view one of them already holds is a visit of that frame's place and leaves the map.
        linked = beliefs >= self.params.map_min_belief
        holder = -1
        if self.params.cull_redundant and not self.calibrating:
            holder = self._holder(t, rows[linked], candidates, matched)
        if holder >= 0:
            update = revision.then(self.topomap.add_visit(holder, rows[linked], beliefs[linked]))
            self._drop_newest(t)
        else:
            update = revision.then(self.topomap.add_frame(rows[linked], beliefs[linked]))
        if loops.size:
            status = FrameStatus.LOOP_FOUND
        elif t <= self.params.window:
            status = FrameStatus.TOO_FEW_FRAMES
        elif retrieved.size == 0:
            status = FrameStatus.NO_CANDIDATE
        else:
            status = FrameStatus.REJECTED
        self._since_release[0] += 1
        self._since_release[1] += candidates.size
        if self._since_release[0] >= RELEASE_EVERY or self._since_release[1] >= RELEASE_ALIGNED:
            self.storage.release()
            self._since_release = [0, 0]
        return FrameResult(t, status, candidates, retrieval, similarity, loops, loop_beliefs, revised, update,
                           self.topomap.node_of(t), self.decision, holder)

    # --- redundant frames ------------------------------------------------------------------------------------

    def _match_fraction(self, a: int, b: np.ndarray, matched: np.ndarray) -> np.ndarray:
        """Matched features over the larger of the two frames' counts (1: the same features, 0: nothing shared)."""
        return matched / np.maximum(np.maximum(self._sizes[a], self._sizes[b]), 1)

    def _successive_applies(self, frame: int) -> bool:
        previous = frame - 1
        return previous >= 0 and not self._redundant[previous] and bool(self._sizes[frame]) and bool(
            self._sizes[previous])

    def _note_successive(self, frame: int) -> None:
        """How closely ``frame`` and the stored frame before it match: the spacing of the map's own frames."""
        if self._successive_applies(frame):
            self._note_match(frame, self._matched(frame, np.array([frame - 1], np.int64))[0])

    def _note_match(self, frame: int, matched) -> None:
        """``matched``: features of ``frame`` and the frame before it paired by their alignment."""
        fraction = float(self._match_fraction(frame, np.array([frame - 1], np.int64), np.array([matched]))[0])
        self._closest_successive = max(self._closest_successive, fraction)

    def _holder(self, t: int, partners: np.ndarray, candidates: np.ndarray, matched: np.ndarray) -> int:
        """The sure loop partner (``partners``: belief at least ``map_min_belief``) that already holds frame t's view,
        or -1. It does when the alignment matched most features of both frames (a majority of the larger count) and
        at least as large a share as any two successive frames of the map matched: the revisit adds nothing the
        map's own spacing of frames would not hold. On real sequences a revisit is rarely that close (the closest
        of RTAB-Map's loop samples: 0.52 of the features; the demo's table top: 0.34, successive frames 0.38); a
        camera going over the same images again matches them all."""
        if not partners.size:
            return -1
        position = {frame: k for k, frame in enumerate(candidates.tolist())}
        fraction = self._match_fraction(t, partners, matched[[position[p] for p in partners.tolist()]])
        best = int(np.argmax(fraction))
        if fraction[best] > 0.5 and fraction[best] >= self._closest_successive:
            return int(partners[best])
        return -1

    def _drop_newest(self, t: int) -> None:
        """Frame t (the newest) leaves the map: its features are taken out of the store and the index, it is never
        a candidate again, and its lattice column is dropped once final. Its decisions and place stand."""
        self._store.retract_last()
        if self._index is not None and self._indexed > t:
            self._index.retract_last(self._query)
        self._sizes[t] = 0
        self._redundant[t] = True
        self._n_redundant += 1
        self.mrf.release_column(t)

    def _count_pairs(self, t: int) -> None:
        """Pairs (i, t) outside the window with i kept: the pairs the decision's null is spread over."""
        entered = t - self.params.window - 1  # the frame leaving the window now
        if entered >= 0 and not self._redundant[entered]:
            self._kept_outside += 1
        self._pairs += self._kept_outside

    # --- calibration and decisions ---------------------------------------------------------------------------

    @property
    def calibrating(self) -> bool:
        """Whether the engine is still collecting its first frames to calibrate on (it aligns nothing meanwhile)."""
        return self.params.calibration.mode == "sequence" and self.calibration is None

    def _calibrate(self, prepared: Prepared | None) -> FeatureSequence:
        """Calibrate on the frames held so far (none aligned yet), store them calibrated; the newest one's features
        as calibrated."""
        if prepared is not None and prepared.calibrated:
            found = prepared.calibration
        else:
            found = _calibration_or_fallback(self._pending, self.params, self.n_frames)
        self._use_calibration(found)
        first = len(self._store)
        frames = [found.apply(f) for f in self._pending]
        self._pending = []
        for frame, f in enumerate(frames, start=first):
            self._store.add(f.descriptors, f.bearings)
            self._sizes[frame] = len(f)
            if frame < self.mrf.n_columns:  # the newest frame gets its column after this, with its new count
                self.mrf.set_count(frame, len(f))
        return frames[-1]

    def _use_calibration(self, calibration: Calibration) -> None:
        self.calibration = calibration
        self.alignment = replace(self.params.alignment, t_match=calibration.t_match,
                                 band_half_width=calibration.band_half_width,
                                 band_max_log_scale=calibration.band_max_log_scale)

    @property
    def decision_threshold(self) -> float:
        """Loops are pairs with a belief at least this (+inf until the lattice can tell a target precision)."""
        return self.decision.threshold if self.decision is not None else np.inf

    @property
    def decision_state(self) -> str:
        """Whether loops are reported: ``waiting`` (the lattice is too small to fit a null yet), ``unreachable`` (no
        belief threshold is expected to reach the target precision: no loops until a re-estimate finds one) or
        ``reporting``."""
        if self.decision is None or self.decision.null is None:
            return "waiting"
        return "reporting" if np.isfinite(self.decision.threshold) else "unreachable"

    def _decide(self) -> tuple[np.ndarray, ...] | None:
        """Re-estimate the decision threshold once the lattice has grown by _DECISION_GROWTH; the
        lattice's cells it was estimated on (None when it was not)."""
        count = self.mrf.n_cells
        grown = count - self._decided_at >= max(1.0, _DECISION_GROWTH * self._decided_at)
        if count < _DECISION_CELLS or (self.decision is not None and not grown):
            return None
        cells = self.mrf.cells()
        self.decision = self.decision_at(self.params.target_precision, cells)
        self._decided_at = count
        return cells

    def decision_at(self, target_precision: float, cells: tuple[np.ndarray, ...] | None = None) -> Decision:
        """The decision the lattice as it stands gives at ``target_precision`` (the engine's own is at its
        ``target_precision``; others are for reports); ``cells``: the lattice's, when already read."""
        rows, cols, _, beliefs = self.mrf.cells() if cells is None else cells
        # Every pair outside the window could be a loop, aligned or not: the pairs retrieval left out count among
        # the pairs the null's false decisions are spread over (the batch's lattice holds them all), which keeps
        # the expected precision of a lattice of retrieved candidates - loops and their near misses - honest. Not
        # the pairs of frames that left the map: they are never aligned again. The null itself is that of those
        # pairs: fitted to the beliefs of the pairs drawn at random (the background sample, weighted as it is),
        # not to the retrieved candidates', the best-looking of the unrelated pairs.
        sample, weights = self._background_beliefs(rows, cols, beliefs)
        # A decided partner beyond the temporal radius of its visit's strongest one is another place: a near miss.
        radius = self.params.temporal_radius if self.params.decision_places else None
        return decide(beliefs, target_precision, max(beliefs.size, self._pairs), (rows, cols), radius, sample, weights,
                      self.mrf.sorted_beliefs(beliefs))

    def _background_beliefs(self, rows: np.ndarray, cols: np.ndarray, beliefs: np.ndarray):
        """The beliefs of the background sample's pairs still in the lattice, and how many pairs each stands for
        (None, None: too few to fit a null to)."""
        sample = self._background.read()
        n = max(self.n_frames, 1)
        # Keys in column-major order: the lattice's cells come column by column, rows ascending in each, so they
        # are sorted already (sorting 18,000 keys was half of a late decision's own cost).
        keys = cols.astype(np.int64) * n + rows
        if np.any(keys[1:] <= keys[:-1]):
            order = np.argsort(keys)
            keys, beliefs = keys[order], beliefs[order]
        wanted = sample["later"] * n + sample["earlier"]
        at = np.minimum(np.searchsorted(keys, wanted), max(keys.size - 1, 0))
        found = keys.size > 0
        found = (keys[at] == wanted) if found else np.zeros(wanted.size, bool)
        if np.count_nonzero(found) < MIN_NULL_SAMPLE:  # (no draws: background_samples = 0) the lattice's own
            return None, None
        return beliefs[at][found], sample["weight"][found]

    def _append_size(self, size: int) -> None:
        t = self.n_frames - 1
        if t == self._sizes.size:
            self._sizes = np.concatenate([self._sizes, np.zeros_like(self._sizes)])
            self._redundant = np.concatenate([self._redundant, np.zeros_like(self._redundant)])
        self._sizes[t] = size

    def _normalization(self):
        if self.params.mrf.potential == "thesis":
            return None  # the running maximum score, as F = max(M)
        # Re-estimated once the sample has grown by 5 %: a median and deviation from N samples are uncertain by
        # ~1/sqrt(N) of the spread, more than 5 % more samples move them (and each change re-weights the band).
        if self._norm is None or self._drawn - self._normalized_at >= max(1, 0.05 * len(self._background)):
            sample = self._background.read()
            background = self.params.mrf.background
            by_count = background != "global"
            counts = [sample[k].astype(np.float64) if by_count else None for k in ("count_a", "count_b")]
            self._norm = background_normalization(sample["score"], sample["weight"], *counts,
                                                  background == "features_spread")
            self._normalized_at = self._drawn
        return self._norm

    def _background_draw(self, t: int) -> np.ndarray:
        """``background_samples`` earlier frames outside the window, drawn uniformly (those with features)."""
        limit = t - self.params.window
        if limit <= 0 or not self.params.background_samples or self.calibrating:
            return np.zeros(0, np.int64)
        drawn = self._rng.choice(limit, size=min(self.params.background_samples, limit), replace=False)
        keep = (self._sizes[drawn] >= self.params.min_features) & ~self._redundant[drawn]
        return np.sort(drawn[keep]).astype(np.int64)

    def _matched(self, query: int, candidates: np.ndarray) -> np.ndarray:
        """The count k of frame ``query`` (the later frame) against each candidate - the DP's matched pairs, or the
        bearing-band count once the calibration gave its band (similarity.pair_count): through the vocabulary's
        direct index once there is one, comparing every pair of features before (or with ``match_words`` = 0)."""
        if not candidates.size:  # (a frame held for the calibration is not stored yet)
            return np.zeros(0, np.int64)
        a = self.alignment
        if self.params.match_words and self._index is not None and a.match == "threshold":
            return self._store.align(query, candidates, a)
        # The ratio test needs each feature's nearest and second-nearest neighbour among all the candidate's.
        q, bearings = self._store.descriptors(query), self._store.bearings(query)
        return np.array([pair_count(alignment_matches(q, self._store.descriptors(i), a), bearings,
                                    self._store.bearings(i), a) for i in candidates.tolist()], np.int64)

    def _similarity(self, query: int, candidates: np.ndarray, matched: np.ndarray) -> np.ndarray:
        """DP scores M of frame ``query`` against each candidate, from the matched pairs (§3.3.2)."""
        if not candidates.size:
            return np.zeros(0, np.float64)
        return np.asarray(alignment_score(int(self._sizes[query]), self._sizes[candidates], matched, self.alignment),
                          np.float64)

    def _check_vocabulary(self, vocabulary: Vocabulary) -> None:
        if self.params.match_words > vocabulary.size:
            raise ValueError(f"match_words ({self.params.match_words}) exceeds the vocabulary's {vocabulary.size} "
                             "words")

    def _index_frame(self, t: int, prepared: Prepared | None = None) -> None:
        if self.vocabulary is None:
            if t + 1 < self.params.bootstrap_frames:
                return
            if prepared is not None and prepared.trained:
                self.vocabulary = prepared.vocabulary
            else:
                self.vocabulary = _learn_vocabulary(
                    [self._store.descriptors(f) for f in range(t + 1) if self._sizes[f]], self.params)
            if self.vocabulary is None:
                return  # not enough texture yet: keep scoring every candidate
            self._index = InvertedIndex(self.vocabulary.size, self.storage, INDEX_BLOCK_FRAMES)
        assert self._index is not None
        while self._indexed <= t:
            frame = self._indexed
            descriptors = self._store.descriptors(frame)
            words = self.vocabulary.nearest_words(descriptors, max(1, self.params.match_words))
            self._store.set_words(frame, words)
            self._add_to_index(frame)

    def _add_to_index(self, frame: int) -> None:
        """File the next frame (its words set) in the inverted index."""
        vector = self.vocabulary.vector(self._store.descriptors(frame), self._store.words(frame)[:, 0])
        self._index.add(vector)
        self._indexed += 1
        self._query = vector

    def _candidates(self, t: int) -> tuple[np.ndarray, np.ndarray | None, bool]:
        """Earlier frames to align with frame t (best first), every earlier frame's retrieval score (None without
        retrieval), and whether the candidates are all the frames outside the window."""
        p = self.params
        limit = t - p.window  # frames 0..limit-1 lie outside the window
        if limit <= 0 or self._sizes[t] < p.min_features or self.calibrating:
            return np.zeros(0, np.int64), None, False
        earlier_pairs = (limit - 1) * limit // 2  # pairs outside the window among the frames before t
        if p.exhaustive or self._index is None or earlier_pairs < p.bootstrap_pairs:
            frames = np.flatnonzero((self._sizes[:limit] >= p.min_features) & ~self._redundant[:limit])
            return frames.astype(np.int64), None, True
        scores = self._index.scores(self._query, limit)
        keep = np.flatnonzero(scores > p.min_retrieval_score)
        if keep.size > p.candidates:
            keep = keep[np.argpartition(-scores[keep], p.candidates - 1)[: p.candidates]]
        chosen = set(keep.tolist())
        if p.neighbour_candidates and t > 0:
            # Loops come in bands (a revisit is a diagonal of M, an intersection an ellipse, §3.4): the frames next
            # to the previous frame's loop partners (D) are the likeliest partners of this one, whether the
            # revisit runs in the same or the opposite direction. Following the band from D, not from retrieval
            # alone, is what lets the engine score as much of each band as the exhaustive M does.
            rows, _, beliefs = self.mrf.column(t - 1)
            partners = rows[beliefs > 0]
            if partners.size:  # (most frames have none)
                near = (partners[:, None] + np.arange(-p.neighbour_candidates, p.neighbour_candidates + 1)).ravel()
                chosen.update(near[(near >= 0) & (near < limit)].tolist())
        frames = np.array(sorted(chosen), dtype=np.int64)
        frames = frames[np.argsort(-scores[frames], kind="stable")]  # best first, ties by frame
        return frames[(self._sizes[frames] >= p.min_features) & ~self._redundant[frames]], scores, False

    def _revisions(self, first: int, t: int, before: np.ndarray, reported: float, cells: tuple | None
                   ) -> tuple[dict[int, np.ndarray], dict[int, tuple[np.ndarray, np.ndarray]]]:
        """Earlier frames in the band (columns ``first``..t-1) whose loops (at the decision threshold) or map links
        (loops at least ``map_min_belief`` sure, with their beliefs) changed with this frame's inference.
        ``before``: those cells' beliefs before it, reported as loops at ``reported`` - what was last reported and
        linked, since every frame reports its whole band; ``cells``: the whole lattice's as :meth:`_decide` read it
        (None when it did not re-estimate the threshold, which then is what it was)."""
        rows, cols, beliefs = self.mrf.cells_from(first)
        earlier = cols < t
        rows, cols, beliefs = rows[earlier], cols[earlier], beliefs[earlier]
        sure = self.params.map_min_belief
        threshold = self.decision_threshold
        loops, links = {}, {}
        for j in np.unique(cols[(beliefs >= threshold) != (before >= reported)]).tolist():
            loops[j] = rows[(cols == j) & (beliefs >= threshold)]
        for j in np.unique(cols[(beliefs >= sure) != (before >= sure)]).tolist():
            mine = (cols == j) & (beliefs >= sure)
            links[j] = rows[mine], beliefs[mine]
        if threshold != reported:
            loops.update(self._threshold_revisions(first, reported, cells))
        return loops, links

    def _threshold_revisions(self, first: int, reported: float, cells: tuple) -> dict[int, np.ndarray]:
        """Frames before column ``first`` whose loops a new decision threshold changed (their beliefs are final,
        but what they were reported at is not): their loops at the new threshold. Without this a frame kept the
        loops of the threshold in force while it was in the band - on the demo's table top that rose from -7.5 to
        1.9 log-odds over 190 frames, and the early frames' loops made the worker's reported set 0.74 precise where
        the final threshold's was 0.82."""
        rows, cols, _, beliefs = cells
        threshold = self.decision_threshold
        low, high = min(threshold, reported), max(threshold, reported)
        changed = np.unique(cols[(cols < first) & (beliefs >= low) & (beliefs < high)])
        if not changed.size:
            return {}
        above = np.flatnonzero(beliefs >= threshold)  # (the few decided cells first: isin over all costs more)
        mine = above[np.isin(cols[above], changed)]
        order = np.argsort(cols[mine], kind="stable")
        partners, owners = rows[mine][order], cols[mine][order]
        bounds = np.searchsorted(owners, changed, "left"), np.searchsorted(owners, changed, "right")
        return {int(j): partners[a:b] for j, a, b in zip(changed.tolist(), *(x.tolist() for x in bounds))}

    # --- results --------------------------------------------------------------------------------------------

    def similarity_cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(earlier, later, M, belief) of every scored pair with a positive potential."""
        return self.mrf.cells()

    # --- state ----------------------------------------------------------------------------------------------

    def flush(self) -> None:
        """Make what the storage holds durable (before a snapshot of :meth:`state` is written)."""
        self.storage.flush()

    def state(self) -> tuple[dict[str, np.ndarray], dict]:
        """Arrays (npz-ready, no objects) and a JSON-ready dict that restore the engine exactly: with a persistent
        storage together with it (the state then holds its index and lengths), else on their own (the state then
        also holds the descriptors and the lattice's final cells)."""
        n = self.n_frames
        arrays = {"feature_lengths": self._sizes[:n].copy()}
        persistent = bool(self.storage.persistent)
        arrays.update(_pending_arrays(self._pending))
        if not persistent:
            parts = [self._store.descriptors(f) for f in range(len(self._store))]
            arrays["descriptors"] = (np.concatenate(parts) if parts else np.zeros((0, DESCRIPTOR_SIZE), np.uint8))
            parts = [self._store.bearings(f) for f in range(len(self._store))]
            arrays["bearings"] = np.concatenate(parts) if parts else np.zeros(0)
        if self.vocabulary is not None:
            arrays["vocabulary_centers"] = self.vocabulary.centers
            arrays["vocabulary_idf"] = self.vocabulary.idf
        if self._index is not None and persistent:
            arrays["index_blocks"] = self._index.block_postings()
            arrays["index_block_frames"] = np.array(self._index.block_frames, np.int64)
        arrays.update({f"mrf_{k}": v for k, v in self.mrf.state().items()})
        sample = self._background.read()
        arrays["background"], arrays["background_weights"] = sample["score"], sample["weight"]
        arrays["background_counts"] = np.stack([sample["count_a"], sample["count_b"]], axis=1)
        arrays["background_frames"] = np.stack([sample["earlier"], sample["later"]], axis=1)
        arrays["background_drawn"] = np.array([self._drawn, self._normalized_at], np.int64)
        arrays["redundant"] = np.packbits(self._redundant[:n])
        arrays["redundancy"] = np.array([self._closest_successive, self._pairs], np.float64)
        arrays["calibration"] = self.calibration.to_array() if self.calibration is not None else np.zeros(0)
        arrays["decision"] = _decision_array(self.decision, self._decided_at)
        arrays.update({f"topomap_{k}": v for k, v in self.topomap.state().items()})
        meta = {"format": STATE_FORMAT, "version": STATE_VERSION, "frames": n, "storage": persistent,
                "params": self.params.to_json_dict(), "rng": self._rng.bit_generator.state}
        return arrays, meta

    @classmethod
    def from_state(cls, arrays: dict, meta: dict, storage=None) -> "LoopClosureEngine":
        """The engine of :meth:`state`; ``storage``: the persistent storage it was saved with (what it wrote after
        the state is dropped)."""
        if meta.get("format") != STATE_FORMAT:
            raise ValueError(f"not a {STATE_FORMAT} (format {meta.get('format')!r})")
        if meta.get("version") != STATE_VERSION:
            raise ValueError(f"engine state version {meta.get('version')!r} cannot be read: this engine reads only "
                             f"v{STATE_VERSION} (start from an empty state or use the version that wrote it)")
        persistent = bool(meta.get("storage", False))
        if persistent != bool(storage is not None and storage.persistent):
            raise ValueError("engine state: saved with a persistent storage, which must be given" if persistent
                             else "engine state: saved on its own; give no persistent storage")
        params = EngineParams.from_json_dict(meta["params"])
        vocabulary = None
        if "vocabulary_centers" in arrays:
            vocabulary = Vocabulary(arrays["vocabulary_centers"], arrays["vocabulary_idf"])
        lengths = np.asarray(arrays["feature_lengths"], np.int64)
        if lengths.ndim != 1 or np.any(lengths < 0) or lengths.size != int(meta["frames"]):
            raise ValueError("engine state: bad feature lengths")
        engine = cls(params, vocabulary, storage if persistent else None)
        n = lengths.size
        engine._pending = _pending_from_arrays(arrays, lengths)
        stored = lengths[: n - len(engine._pending)]
        if persistent:
            engine._store = FrameStore.reopen(max(1, params.match_words), storage, stored, vocabulary is not None)
        else:
            ends = np.cumsum(stored)
            descriptors = np.asarray(arrays["descriptors"], np.uint8)
            features = int(ends[-1]) if stored.size else 0
            if descriptors.shape != (features, DESCRIPTOR_SIZE):
                raise ValueError("engine state: descriptors do not match the feature lengths")
            bearings = np.asarray(arrays["bearings"], np.float64)
            if bearings.shape != (features,) or not np.all(np.abs(bearings) <= np.pi):
                raise ValueError("engine state: bearings must be radians in [-pi, pi], one per stored feature")
            for a, b in zip((ends - stored).tolist(), ends.tolist()):
                engine._store.add(descriptors[a:b], bearings[a:b])
        engine._sizes = np.concatenate([lengths, np.zeros(max(64, n), np.int64)])
        engine._redundant = np.zeros(engine._sizes.size, bool)
        if vocabulary is not None and stored.size:
            if persistent:  # the frozen index blocks and the words are stored: only the open block is rebuilt
                engine._index = InvertedIndex.reopen(vocabulary.size, storage, arrays.get("index_blocks", []),
                                                     int(arrays.get("index_block_frames", INDEX_BLOCK_FRAMES)))
                if engine._index.frozen_frames > n:
                    raise ValueError("engine state: more indexed frames than frames")
                engine._indexed = engine._index.frozen_frames
                for frame in range(engine._indexed, stored.size):
                    engine._add_to_index(frame)
            else:
                engine._index_frame(stored.size - 1)  # words and TF-IDF vectors of every frame, as they were
        mrf_state = {k[4:]: v for k, v in arrays.items() if k.startswith("mrf_")}
        archive = storage.log("mrf_cells", ARCHIVE_DTYPE) if persistent else None
        engine.mrf = IncrementalMrf.from_state(mrf_state, params.mrf, params.band, params.window, archive=archive)
        scores = np.asarray(arrays["background"], np.float64).reshape(-1)
        weights = np.asarray(arrays["background_weights"], np.float64).reshape(-1)
        counts = np.asarray(arrays["background_counts"], np.int64)
        frames = np.asarray(arrays["background_frames"], np.int64)
        if frames.shape != (scores.size, 2) or (frames.size and (frames.min() < 0 or np.any(frames[:, 0] >= frames[:, 1])
                                                                or frames.max() >= lengths.size)):
            raise ValueError("engine state: one pair of frames (earlier, later) per background score")
        if weights.shape != scores.shape or counts.shape != (scores.size, 2) or scores.size > _BACKGROUND_KEPT:
            raise ValueError("engine state: one weight and one pair of feature counts per background score")
        records = np.empty(scores.size, _BACKGROUND_DTYPE)
        records["score"], records["weight"], records["count_a"], records["count_b"] = scores, weights, *counts.T
        records["earlier"], records["later"] = frames.T
        engine._background.append(records)
        redundant = np.unpackbits(np.asarray(arrays["redundant"], np.uint8), count=n).astype(bool)
        if redundant.size != n or np.any(lengths[redundant] != 0):
            raise ValueError("engine state: redundant frames hold no features")
        engine._redundant[:n] = redundant
        engine._n_redundant = int(redundant.sum())
        closest, pairs = (float(v) for v in np.asarray(arrays["redundancy"], np.float64).reshape(2))
        engine._closest_successive, engine._pairs = closest, int(pairs)
        outside = n - 1 - params.window  # frames outside the newest frame's window
        engine._kept_outside = int(np.count_nonzero(~redundant[:outside])) if outside > 0 else 0
        engine._drawn, engine._normalized_at = (int(v) for v in arrays["background_drawn"])
        if engine._drawn:
            # The estimate in use when the state was saved (from the sample as it was then).
            engine._norm = engine.mrf.normalization
        if "rng" in meta:
            engine._rng.bit_generator.state = meta["rng"]
        calibration = np.asarray(arrays["calibration"], np.float64)
        if calibration.size:
            engine._use_calibration(Calibration.from_array(calibration))
        if engine._pending and not engine.calibrating:
            raise ValueError("engine state: frames held for a calibration that is done")
        engine.decision, engine._decided_at = _decision_from_array(arrays["decision"])
        topo_state = {k[8:]: v for k, v in arrays.items() if k.startswith("topomap_")}
        engine.topomap = IncrementalTopoMap.from_state(topo_state, params.temporal_radius)
        if engine.mrf.n_columns != engine.n_frames or engine.topomap.n_frames != engine.n_frames:
            raise ValueError("engine state: MRF, map and features disagree on the number of frames")
        return engine


def _calibration_or_fallback(frames: list[FeatureSequence], params: EngineParams, n_frames: int) -> Calibration:
    """The calibration of the frames held for it; too few correspondences to say anything: the configured
    constants, and the status says so."""
    found = calibrate(frames, params.calibration, alignment=params.alignment)
    if found is None:
        t = params.alignment.t_match
        found = Calibration(t, t, frames=n_frames, stats={"fallback": "no correspondences between consecutive frames"})
    return found


def _learn_vocabulary(training: list[np.ndarray], params: EngineParams) -> Vocabulary | None:
    """The vocabulary learnt from the frames' descriptors; None while they hold fewer than its words."""
    if sum(d.shape[0] for d in training) < params.vocabulary_words:
        return None
    return train_vocabulary(training, words=params.vocabulary_words)


def _pending_arrays(pending: list[FeatureSequence]) -> dict[str, np.ndarray]:
    """The frames held for the calibration, whole (the calibration needs their pixels, not only descriptors)."""
    def joined(field, empty):
        return np.concatenate([getattr(f, field) for f in pending]) if pending else empty

    return {"pending_frames": np.array(len(pending), np.int64),
            "pending_bearings": joined("bearings", np.zeros(0)),
            "pending_descriptors": joined("descriptors", np.zeros((0, DESCRIPTOR_SIZE), np.uint8)),
            "pending_camera_index": joined("camera_index", np.zeros(0, np.int16)),
            "pending_points": joined("points", np.zeros((0, 2), np.float32))}


def _pending_from_arrays(arrays: dict, lengths: np.ndarray) -> list[FeatureSequence]:
    """The frames of :func:`_pending_arrays`: the last ``pending_frames`` of ``lengths``, checked as any features."""
    count = int(arrays["pending_frames"])
    if not 0 <= count <= lengths.size:
        raise ValueError("engine state: bad number of frames held for the calibration")
    sizes = lengths[lengths.size - count:]
    ends = np.cumsum(sizes)
    fields = [np.asarray(arrays[f"pending_{k}"]) for k in ("bearings", "descriptors", "camera_index", "points")]
    if any(len(a) != (int(ends[-1]) if count else 0) for a in fields):
        raise ValueError("engine state: the frames held for the calibration do not match their lengths")
    # FeatureSequence checks each frame as it checks one from the bus (sorted finite bearings, uint8 descriptors).
    return [FeatureSequence(*(a[b - n:b] for a in fields)) for n, b in zip(sizes.tolist(), ends.tolist())]


def _decision_array(decision: Decision | None, decided_at: int) -> np.ndarray:
    if decision is None:
        return np.zeros(0)
    null = decision.null
    return np.array([decision.threshold, np.nan if decision.expected_precision is None else decision.expected_precision,
                     decision.decided, decision.pairs, decision.target_precision,
                     *((null.location, null.scale) if null is not None else (np.nan,) * 2), decided_at,
                     decision.off_place])


def _decision_from_array(values) -> tuple[Decision | None, int]:
    v = np.asarray(values, np.float64).reshape(-1)
    if not v.size:
        return None, 0
    if v.size != 9:
        raise ValueError("engine state: bad decision")
    null = None if np.isnan(v[5]) else NullFit(float(v[5]), float(v[6]))
    expected = None if np.isnan(v[1]) else float(v[1])
    return Decision(float(v[0]), expected, int(v[2]), int(v[3]), float(v[4]), null, int(v[8])), int(v[7])
