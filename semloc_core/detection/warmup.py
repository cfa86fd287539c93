"""Compiling a detector worker's numba kernels before the first real frame.

numba compiles a kernel on its first call (cached on disk afterwards). The template and window detectors already
run once on a tiny image when built, but a worker's frames take paths that tiny image does not: the pruned levels
(``heatmaps(image, rows=...)``: ``_kernels.lerp_rows_max``) and the heatlines' projection (``_kernels.scatter_max``).
``warm_up`` runs the caller's own detector over a small synthetic scene along every path the worker will take, and
a throwaway projector over its heatmaps. The detector keeps no state between frames but its buffers.
"""

from __future__ import annotations

import numpy as np

from semloc_core.bearing import BearingGrid
from semloc_core.camera import PinholeCamera
from semloc_core.detection.heatlines import HeatlineProjector

WIDTH, HEIGHT = 320, 240  # the synthetic image: a pyramid level a band is cut from needs some rows (~5 ms a pass)


def synthetic_scene(width: int = WIDTH, height: int = HEIGHT, seed: int = 0) -> np.ndarray:
    """A BGR uint8 image of random blocks: edges and colours for every feature to respond to."""
    rng = np.random.default_rng(seed)
    blocks = rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
    return np.ascontiguousarray(np.repeat(np.repeat(blocks, 8, axis=0), 8, axis=1)[:height, :width])


def warm_up(detector, levels: bool = False, prune: bool = False, bins: int = 360) -> int:
    """Run ``detector`` once on a synthetic scene as a worker does: ``level_heatmaps`` with ``levels`` (a window
    detector publishing its levels), else ``heatmaps``; with ``prune`` also on one band of rows per level
    (``heatmaps(image, rows=...)``, a template detector); the heatmaps projected to ``bins`` heatlines by a
    throwaway projector. Returns the passes run."""
    image = synthetic_scene()
    heatmaps = detector.level_heatmaps(image).max(axis=1) if levels else detector.heatmaps(image)
    passes = 1
    if prune:
        rows = detector.output_shape(image.shape)[0]
        band = (rows // 2 - 1, rows // 2 + 1)   # narrow: each level matched on a band, not the whole of it
        detector.heatmaps(image, rows={scale: band for scale in detector.match.scales})
        passes += 1
    camera = PinholeCamera.from_fov(WIDTH, HEIGHT, 60.0)
    HeatlineProjector(camera, tuple(detector.classes), BearingGrid(bins)).project(heatmaps)
    return passes
