"""Compiling a mapper's numba kernels before the first real frame.

numba compiles the back-projection kernels on their first call (1-1.6 s of CPU on a fresh install, cached on
disk afterwards): a mapper worker that compiles on its first heatmaps stalls them while it already reports running.
``warm_up`` integrates one synthetic frame into a throwaway mapper of the caller's settings over a small grid, so
the same kernels run with the same types; the caller's own mapper is not touched.
"""

from __future__ import annotations

import numpy as np

from semloc_core.camera import PinholeCamera
from semloc_core.mapping.grid import VoxelGrid
from semloc_core.mapping.scale_depth import level_depths
from semloc_core.mapping.volume import MapperConfig, VoxelMapper

VOXELS = 16  # the throwaway grid's side (voxels; a quarter as high): the kernels' work is a fraction of a frame's
WIDTH, HEIGHT = 64, 48  # the synthetic heatmaps


def warm_up(classes, config: MapperConfig, voxel_size: float, scale_depth: dict | None = None) -> int:
    """Integrate one frame of random heat into a throwaway ``VoxelMapper(classes, config)`` whose grid has the
    caller's ``voxel_size``, seen from in front by a synthetic camera; with ``scale_depth`` (a fitted depth per
    scale, ``{"scales": [...], "classes": {name: ...}}``) per-level maps, scale-selected as the mapper worker
    integrates a detector's HeatmapLevels. The heat comes as a detector's wire sends it:
    quantised codes where the background is surprisal (they are ranked as they are), else floats in [0, 1].
    Returns the voxel blocks the frame reached (0 only if the configured depth range excludes the grid)."""
    side = VOXELS * voxel_size
    grid = VoxelGrid.from_bounds([0.0, 0.0, 0.0], [side, side, side / 4], voxel_size)
    mapper = VoxelMapper(grid, tuple(classes), config)
    camera = PinholeCamera.from_fov(WIDTH, HEIGHT, 60.0)
    depths = None if scale_depth is None else level_depths(
        [scale_depth["classes"][name] for name in mapper.class_names], scale_depth["scales"], camera.K[0, 0])
    levels = () if depths is None else (depths.shape[1],)
    rng = np.random.default_rng(0)
    heat = rng.random((len(classes),) + levels + (HEIGHT, WIDTH), dtype=np.float32)
    if config.heatmap_background == "surprisal":
        heat = (heat * 255).astype(np.uint8)
    # The camera looks along +x at the grid's middle from twice its side (plus the nearest depth mapped).
    distance = config.min_depth + 2 * side
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]   # columns: x_cam, y_cam, z_cam
    T_world_cam[:3, 3] = [-distance, side / 2, side / 8]
    stats = mapper.integrate(heat, T_world_cam, camera, level_depths=depths)
    return stats.blocks_updated
