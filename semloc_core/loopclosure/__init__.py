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

import importlib

# name -> the module defining it, imported on first use (PEP 562): importing one module of this package (a
# worker needs a frame type's helpers) must not import them all (numba kernels, SciPy), which made every
# worker's start, and so every restart, slower.
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


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
