"""Compiling the engine's numba kernels before the first real frame.

numba compiles a kernel on its first call (about 20 s of CPU for the engine's on a fresh install, cached on disk
afterwards). A worker that reports running and then compiles stalls its first real frames: on a fresh install the
demo's loop-closure worker dropped half its images that way. ``warm_up`` runs a throwaway engine of the caller's
settings, scaled down, over a synthetic wall seen twice - the calibration, the bootstrap alignments, the
vocabulary, retrieval, the lattice, the decisions and the map all run - and leaves nothing behind.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from semloc_core.camera import PinholeCamera
from semloc_core.loopclosure.engine import EngineParams, LoopClosureEngine
from semloc_core.loopclosure.features import FeatureParams, extract_features

WIDTH, HEIGHT = 160, 120  # the synthetic camera: small, so the warm-up's own work is a fraction of a second
STEP = 24  # pixels the camera pans between frames
PASS = 24  # frames per pass along the wall; the wall is seen twice
WARM_UP_FEATURES = 200  # at most, per frame (the DP's and k-means' work grow with it; the kernels' types do not)


def synthetic_wall(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A grey wall (height x width x 3, uint8) with a random blob or box per 120 pixels: texture for SIFT."""
    rng = np.random.default_rng(seed)
    wall = np.full((height, width, 3), 120, np.uint8)
    for _ in range(width * height // 120):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        if rng.random() < 0.5:
            cv2.circle(wall, (x, y), int(rng.integers(2, 8)), colour, -1)
        else:
            cv2.rectangle(wall, (x, y), (x + int(rng.integers(3, 14)), y + int(rng.integers(3, 14))), colour, -1)
    return wall


def warm_up(params: EngineParams = EngineParams(), features: FeatureParams = FeatureParams()) -> int:
    """Compile every kernel an engine of ``params`` calls on its frames (feature extraction with ``features``
    included) by running a scaled-down copy over two passes along a synthetic wall. Returns the frames run.

    Scaled down: a short window and band; the calibration over the first 8 frames and the vocabulary from the
    first 16, so some frames are aligned before it exists (every feature pair compared) and the rest through it;
    at most 64 words (some must be rare: a word in every frame has IDF 0 and retrieval would score nothing). The
    decision's threshold is estimated once the lattice holds a few hundred cells, as it comes to. The kinds of
    everything (calibration mode, potential, coupling, decisions) are the caller's, so the same kernels run with
    the same types."""
    calibration = replace(params.calibration, frames=min(params.calibration.frames, 8))
    small = replace(params, window=2, band=min(params.band, 8), bootstrap_frames=16, bootstrap_pairs=20,
                    vocabulary_words=min(params.vocabulary_words, 64), calibration=calibration)
    engine = LoopClosureEngine(small)
    camera = PinholeCamera.from_fov(WIDTH, HEIGHT, 60.0)
    wall = synthetic_wall(STEP * PASS + WIDTH, HEIGHT)
    features = replace(features, max_features=min(features.max_features or WARM_UP_FEATURES, WARM_UP_FEATURES))
    one_pass = [extract_features(np.ascontiguousarray(wall[:, x:x + WIDTH]), camera, features)
                for x in range(0, STEP * PASS, STEP)]
    for sequence in one_pass + one_pass:  # the second pass sees the same views: loops, and redundant frames culled
        engine.add_frame(sequence)
    engine.topomap.flush()
    return 2 * PASS
