"""Loop closure and the topological map (thesis chapter 3), computed incrementally.

* :mod:`.features` - bearing-sorted SIFT feature sequences (§3.3.1).
* :mod:`.similarity` - the cyclic DP similarity (§3.3.2) and the SIFT-count baselines M^SIFT, M^SYM.
* :mod:`.bow` - vocabulary, TF-IDF baseline and the inverted index used for candidate retrieval.
* :mod:`.mrf` - the MRF on the similarity matrix and generalised max-product loopy BP (§3.4), batch and incremental.
* :mod:`.topomap` - dominating-set topological map (§3.5), batch and incremental.
* :mod:`.engine` - the streaming engine tying them together.
* :mod:`.evaluation` - similarity matrices for whole sequences (reference runs and the baselines).
"""

from __future__ import annotations

from semloc_core.lazy import lazy_exports

# name -> the module defining it, imported on first use (semloc_core.lazy)
_EXPORTS = {
    "AlignmentParams": "similarity",
    "BowVector": "bow",
    "DESCRIPTOR_SCALE": "features",
    "EngineParams": "engine",
    "FeatureParams": "features",
    "FeatureSequence": "features",
    "FrameResult": "engine",
    "FrameStatus": "engine",
    "IncrementalMrf": "mrf",
    "IncrementalTopoMap": "topomap",
    "InvertedIndex": "bow",
    "LoopClosureEngine": "engine",
    "MrfParams": "mrf",
    "MrfResult": "mrf",
    "TopoMapUpdate": "topomap",
    "TopologicalMap": "topomap",
    "Vocabulary": "bow",
    "build_topological_map": "topomap",
    "dominating_set": "topomap",
    "dp_similarity": "similarity",
    "extract_features": "features",
    "infer_batch": "mrf",
    "infer_cells": "mrf",
    "normalize_descriptors": "features",
    "pair_scores": "similarity",
    "sift_match_count": "similarity",
    "symmetric_match_count": "similarity",
    "train_vocabulary": "bow",
}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
