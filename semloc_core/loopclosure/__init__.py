"""Loop closure and the topological map (thesis chapter 3), computed incrementally.

* :mod:`.features` - bearing-sorted SIFT feature sequences (§3.3.1).
* :mod:`.similarity` - the cyclic DP similarity (§3.3.2) and the SIFT-count baselines M^SIFT, M^SYM.
* :mod:`.bow` - vocabulary, TF-IDF baseline and the inverted index used for candidate retrieval.
* :mod:`.mrf` - the MRF on the similarity matrix and generalised max-product loopy BP (§3.4), batch and incremental.
* :mod:`.topomap` - dominating-set topological map (§3.5), batch and incremental.
* :mod:`.engine` - the streaming engine tying them together.
* :mod:`.evaluation` - similarity matrices for whole sequences (reference runs and the baselines).
"""

from semloc_core.loopclosure.bow import BowVector, InvertedIndex, Vocabulary, train_vocabulary
from semloc_core.loopclosure.engine import EngineParams, FrameResult, FrameStatus, LoopClosureEngine
from semloc_core.loopclosure.features import (
    DESCRIPTOR_SCALE,
    FeatureParams,
    FeatureSequence,
    extract_features,
    normalize_descriptors,
)
from semloc_core.loopclosure.mrf import IncrementalMrf, MrfParams, MrfResult, infer_batch, infer_cells
from semloc_core.loopclosure.similarity import (
    AlignmentParams,
    dp_similarity,
    pair_scores,
    sift_match_count,
    symmetric_match_count,
)
from semloc_core.loopclosure.topomap import (
    IncrementalTopoMap,
    TopologicalMap,
    TopoMapUpdate,
    build_topological_map,
    dominating_set,
)

__all__ = [
    "AlignmentParams",
    "BowVector",
    "DESCRIPTOR_SCALE",
    "EngineParams",
    "FeatureParams",
    "FeatureSequence",
    "FrameResult",
    "FrameStatus",
    "IncrementalMrf",
    "IncrementalTopoMap",
    "InvertedIndex",
    "LoopClosureEngine",
    "MrfParams",
    "MrfResult",
    "TopoMapUpdate",
    "TopologicalMap",
    "Vocabulary",
    "build_topological_map",
    "dominating_set",
    "dp_similarity",
    "extract_features",
    "infer_batch",
    "infer_cells",
    "normalize_descriptors",
    "pair_scores",
    "sift_match_count",
    "symmetric_match_count",
    "train_vocabulary",
]
