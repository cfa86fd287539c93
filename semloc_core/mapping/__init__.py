"""Semantic voxel mapping from heatmaps (thesis ch. 5): back-projection into per-class Hough volumes, object
extraction by non-maximum suppression, export as the localizer's object map. See docs/mapping.md."""

from semloc_core.mapping.backprojection import backproject_reference, downsample_heatmaps, slice_homography
from semloc_core.mapping.extraction import ExtractionConfig, MappedObject, extract_objects, objects_to_semantic_map
from semloc_core.mapping.grid import VoxelGrid
from semloc_core.mapping.volume import FrameStats, MapperConfig, MapperMemoryError, VoxelMapper

__all__ = [
    "ExtractionConfig",
    "FrameStats",
    "MappedObject",
    "MapperConfig",
    "MapperMemoryError",
    "VoxelGrid",
    "VoxelMapper",
    "backproject_reference",
    "downsample_heatmaps",
    "extract_objects",
    "objects_to_semantic_map",
    "slice_homography",
]
