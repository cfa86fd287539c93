"""Heatmaps -> heatlines over bearing (thesis §4.4.2), and the hard variant (§4.5.2, Fig. 4.8).

The thesis takes the maximum along each image column of an upright camera. Here every heatmap cell is sent through
the camera model (and the per-frame ``T_body_cam``, so a tilted hand-held camera still maps correctly) to the
bearings its area covers; a heatline bin takes the maximum over the cells that reach it. For an upright pinhole
camera this is exactly the column maximum; for a rig it is also the maximum across cameras; for a panorama, the
column -> longitude map.

The cells' rays are computed once per (camera, heatmap shape); the cell -> bin map once per attitude (cached: a
camera on a fixed mount pays it once, a hand-held one a rotation and an arctangent per cell a frame). Projecting is
one scatter of the maxima.
"""

from __future__ import annotations

import numpy as np

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.camera import CameraRig, EquirectangularCamera, FisheyeCamera, PinholeCamera, members
from semloc_core.detection._kernels import scatter_max
from semloc_core.geometry import check_rigid_transform


class _CellSamples:
    """Sub-sample points of every heatmap cell of one camera, and their rays in the camera frame.

    They depend on the camera and the heatmap's shape only, so they are computed once; a frame's attitude then costs
    a rotation and an arctangent per sample (``bins``), not the lens model again.
    """

    def __init__(self, camera, grid: BearingGrid, shape: tuple[int, int], samples: int | None = None):
        rows, cols = int(shape[0]), int(shape[1])
        if rows < 1 or cols < 1:
            raise ValueError(f"heatmap shape must be positive, got {shape}")
        if samples is None:
            samples = _samples_per_cell(camera, cols, rows, grid)
        # Sub-sample each cell so that no bin inside the field of view is skipped even when a cell spans several
        # bins (a coarse heatmap of a panorama); every sample carries its cell's score (nearest neighbour).
        sx, sy = camera.width / cols, camera.height / rows
        offsets = (np.arange(samples) + 0.5) / samples
        u = ((np.arange(cols)[:, None] + offsets[None, :]) * sx - 0.5).reshape(-1)
        v = ((np.arange(rows)[:, None] + offsets[None, :]) * sy - 0.5).reshape(-1)
        uu, vv = np.meshgrid(u, v)
        self.rays_cam = camera.rays_cam(uu, vv).reshape(-1, 3)
        cell_row = np.repeat(np.arange(rows), samples)
        cell_col = np.repeat(np.arange(cols), samples)
        self.cells = (cell_row[:, None] * cols + cell_col[None, :]).reshape(-1)
        self.samples, self.shape, self.grid = samples, (rows, cols), grid

    def bins(self, camera, T_body_cam=None) -> "_CellBins":
        """Which bins the cells reach under this attitude (``T_body_cam`` overrides the camera's extrinsic)."""
        T = camera.T_body_cam if T_body_cam is None else check_rigid_transform(T_body_cam, "T_body_cam")
        R = np.asarray(T, float)[:3, :3]
        # The bearing of a body-frame ray R r is atan2((R r)_y, (R r)_x): two rows of R, no normalisation needed.
        bins = self.grid.index(np.arctan2(self.rays_cam @ R[1], self.rays_cam @ R[0]))
        cells = self.cells
        if self.samples > 1:  # several samples of a cell in one bin: keep one (pairs of a fine map are unique)
            n_cells = self.shape[0] * self.shape[1]
            pairs = np.unique(bins * n_cells + cells)
            bins, cells = pairs // n_cells, pairs % n_cells
        return _CellBins(cells, bins, self.grid.n_bins)


class _CellBins:
    """Which bin each heatmap cell of one camera reaches (a cell spanning several bins appears once per bin)."""

    def __init__(self, cells: np.ndarray, bins: np.ndarray, n_bins: int):
        self.cells = np.ascontiguousarray(cells, np.int64)
        self.bins = np.ascontiguousarray(bins, np.int64)
        self.n_bins = int(n_bins)
        self.bins_hit = np.flatnonzero(np.bincount(self.bins, minlength=self.n_bins))

    def project(self, heatmaps: np.ndarray) -> np.ndarray:
        """(classes, rows, cols) -> (classes, n_bins) max per bin (§4.4.2); unobserved bins 0."""
        flat = np.ascontiguousarray(heatmaps.reshape(heatmaps.shape[0], -1), np.float32)
        out = np.full((flat.shape[0], self.n_bins), -np.inf, np.float32)
        scatter_max(flat, self.cells, self.bins, out)
        out[~np.isfinite(out)] = 0.0  # bins no cell reaches (heatmaps are finite: checked in _per_camera)
        return out


def _samples_per_cell(camera, cols: int, rows: int, grid: BearingGrid) -> int:
    """Sub-samples per cell side so that neighbouring samples are at most one bin apart in bearing.

    Samples at most one bin width apart cannot jump over a bin, so no bin inside the field of view is left empty;
    a fine heatmap (a cell narrower than a bin) is sampled at its cell centres only.
    """
    if isinstance(camera, EquirectangularCamera):
        cell_angle = 2.0 * np.pi / cols
    else:
        # Widest angular pixel is at the image centre for a pinhole, and 1 / f everywhere across the radius of an
        # equidistant fisheye (its coefficients are small corrections); a tilt adds little at these sizes.
        fx = camera.K[0, 0]
        cell_angle = max(camera.width / cols, camera.height / rows) / fx
    return int(np.clip(np.ceil(cell_angle / grid.bin_width - 1e-9), 1, 32))


class HeatlineProjector:
    """Turns per-class heatmaps of a camera (or rig) into ``Heatlines``.

    ``project(heatmaps, T_body_cam=None)``: ``heatmaps`` is (classes, rows, cols) for a single camera, or a
    sequence of those (one per rig member, same classes). ``T_body_cam`` overrides the extrinsic for this frame: a
    4x4 for a single camera, or one 4x4-or-None per rig member. Maps are cached per distinct attitude; an attitude
    that changes every frame costs a rotation of the cached rays per frame (0.7 ms for a 160 x 120 heatmap).
    """

    def __init__(self, camera, classes, grid: BearingGrid = BearingGrid(), cache_size: int = 8):
        if not isinstance(camera, (PinholeCamera, FisheyeCamera, EquirectangularCamera, CameraRig)):
            raise TypeError(f"unsupported camera model {type(camera)}")
        self.camera = camera
        self.classes = tuple(classes)
        if not self.classes:
            raise ValueError("need at least one class")
        self.grid = grid
        self._samples: dict = {}  # (member, shape) -> _CellSamples
        self._cache: dict = {}
        self._cache_size = int(cache_size)

    def _maps(self, shapes, overrides):
        key = (tuple(shapes), tuple(None if T is None else np.asarray(T, float).round(9).tobytes() for T in overrides))
        maps = self._cache.get(key)
        if maps is None:
            maps = [self._cell_samples(i, camera, shape).bins(camera, T)
                    for i, (camera, shape, T) in enumerate(zip(members(self.camera), shapes, overrides))]
            if len(self._cache) >= self._cache_size:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = maps
        return maps

    def _cell_samples(self, member: int, camera, shape) -> _CellSamples:
        key = (member, tuple(shape))
        if key not in self._samples:
            self._samples[key] = _CellSamples(camera, self.grid, shape)
        return self._samples[key]

    def project(self, heatmaps, T_body_cam=None) -> Heatlines:
        cameras = members(self.camera)
        per_camera = _per_camera(heatmaps, len(cameras), len(self.classes))
        if T_body_cam is None:
            overrides = [None] * len(cameras)
        elif isinstance(T_body_cam, np.ndarray) and T_body_cam.shape == (4, 4):
            if len(cameras) != 1:
                raise ValueError("a rig takes one T_body_cam override per member camera (or None)")
            overrides = [T_body_cam]
        else:
            overrides = list(T_body_cam)
            if len(overrides) != len(cameras):
                raise ValueError(f"expected {len(cameras)} T_body_cam overrides, got {len(overrides)}")
        maps = self._maps([h.shape[1:] for h in per_camera], overrides)
        scores = np.zeros((len(self.classes), self.grid.n_bins), np.float32)
        observed = np.zeros(self.grid.n_bins, bool)
        for cell_bins, maps_of_camera in zip(maps, per_camera):
            np.maximum(scores, cell_bins.project(maps_of_camera), out=scores)   # rig: max across cameras
            observed[cell_bins.bins_hit] = True
        return Heatlines(self.classes, scores, observed)


def _per_camera(heatmaps, n_cameras: int, n_classes: int) -> list[np.ndarray]:
    if isinstance(heatmaps, np.ndarray) and heatmaps.ndim == 3:
        heatmaps = [heatmaps]
    heatmaps = [np.asarray(h, dtype=np.float32) for h in heatmaps]
    if len(heatmaps) != n_cameras:
        raise ValueError(f"expected heatmaps for {n_cameras} camera(s), got {len(heatmaps)}")
    for h in heatmaps:
        if h.ndim != 3 or h.shape[0] != n_classes:
            raise ValueError(f"heatmaps must be (classes={n_classes}, rows, cols), got {h.shape}")
        if not np.all(np.isfinite(h)):
            raise ValueError("heatmaps contain non-finite values")
    return heatmaps


# ---------------------------------------------------------------------------------------------------- peaks, hard


def heatline_peaks(scores: np.ndarray, observed: np.ndarray, min_separation: int, threshold: float = -np.inf,
                   max_peaks: int | None = None) -> np.ndarray:
    """Greedy non-maximum suppression on one heatline: bins of the strongest peaks, strongest first.

    A peak suppresses every bin within ``min_separation`` bins of it (circularly: the bins cover the full turn).
    Only observed bins with a score above ``threshold`` are candidates.
    """
    scores = np.asarray(scores, dtype=np.float64)
    n = scores.shape[0]
    candidates = np.flatnonzero(np.asarray(observed, bool) & (scores > threshold))
    # Stable sort on the negated score: ties go to the lower bin, deterministically.
    order = candidates[np.argsort(-scores[candidates], kind="stable")]
    suppressed = np.zeros(n, bool)
    peaks = []
    for b in order:
        if suppressed[b]:
            continue
        peaks.append(b)
        if max_peaks is not None and len(peaks) >= max_peaks:
            break
        suppressed[(b + np.arange(-min_separation, min_separation + 1)) % n] = True
    return np.asarray(peaks, dtype=np.int64)


def hard_heatlines(heatlines: Heatlines, thresholds, nms_deg: float = 5.0, width_deg: float = 1.0) -> Heatlines:
    """The "hardened" detector of §4.5.2 (Fig. 4.8): threshold, non-maximum suppression, binary heatline.

    ``thresholds`` is one value for every class or a mapping class -> value. Each surviving peak becomes a detection
    of fixed angular width ``width_deg`` (value 1 over it, 0 elsewhere).
    """
    grid = heatlines.grid
    if isinstance(thresholds, dict):
        missing = [c for c in heatlines.classes if c not in thresholds]
        if missing:
            raise ValueError(f"no threshold for classes {missing}")
        per_class = [float(thresholds[c]) for c in heatlines.classes]
    else:
        per_class = [float(thresholds)] * len(heatlines.classes)
    separation = max(1, int(round(np.radians(nms_deg) / grid.bin_width)))
    half_width = max(0, int(round(np.radians(width_deg) / grid.bin_width / 2.0 - 0.5)))
    binary = np.zeros_like(heatlines.scores)
    for k, threshold in enumerate(per_class):
        for peak in heatline_peaks(heatlines.scores[k], heatlines.observed, separation, threshold):
            binary[k, (peak + np.arange(-half_width, half_width + 1)) % grid.n_bins] = 1.0
    binary *= heatlines.observed
    return Heatlines(heatlines.classes, binary, heatlines.observed)
