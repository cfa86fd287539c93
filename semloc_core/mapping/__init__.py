"""Semantic voxel mapping from heatmaps (thesis ch. 5): back-projection into per-class Hough volumes, object
extraction by non-maximum suppression, export as the localizer's object map. See docs/mapping.md."""

from __future__ import annotations

from semloc_core.lazy import lazy_exports

# name -> the module defining it, imported on first use (semloc_core.lazy)
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
    "first_allocation_bytes": "volume",
    "objects_to_semantic_map": "extraction",
    "slice_homography": "backprojection",
}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
