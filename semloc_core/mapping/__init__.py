"""Semantic voxel mapping from heatmaps (thesis ch. 5): back-projection into per-class Hough volumes, object
extraction by non-maximum suppression, export as the localizer's object map. See docs/mapping.md."""

from __future__ import annotations

import importlib

# name -> the module defining it, imported on first use (PEP 562): importing one module of this package (a
# worker needs a frame type's helpers) must not import them all (numba kernels, SciPy), which made every
# worker's start, and so every restart, slower.
_EXPORTS = {
    "ExtractionConfig": "extraction",
    "FrameStats": "volume",
    "MappedObject": "extraction",
    "MapperConfig": "volume",
    "MapperMemoryError": "volume",
    "VoxelGrid": "grid",
    "VoxelMapper": "volume",
    "backproject_reference": "backprojection",
    "downsample_heatmaps": "backprojection",
    "extract_objects": "extraction",
    "objects_to_semantic_map": "extraction",
    "slice_homography": "backprojection",
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
