"""Perception (sensor) models: how likely a heatline observation is from each particle's pose.

Two interchangeable models, both ``model.weigh(states, heatlines) -> Weighing``:

* ``InnerProductModel`` - model A (§4.4.2): the weight is the sum over classes of the inner product of the observed
  heatline with the expected one (eq. 4.6); the expected heatline is the max over the class's instances within the
  visibility radius ``dist_v`` of a Gaussian at the instance's bearing (eq. 4.7-4.8).
* ``GenerativeScoreModel`` - model B (§4.7): the generative score likelihood of eq. 4.27, a product over classes and
  over the observed bearing bins of p(z|d) p(d|Y) + p(z|d̄) p(d̄|Y), with p(d(θ)|Y) the max over instances of a
  Gaussian in bearing (eq. 4.26, σ = 5°). Computed in log space.

Bearings follow docs/conventions.md: bin i of an n-bin heatline covers [-π + iΔ, -π + (i+1)Δ); the expected bearing
of an object from pose (x, y, θ) is atan2(dy, dx) - θ. Only bins marked ``observed`` carry evidence.

The fast paths run in numba (``_kernels``); ``expected_heatlines``, ``log_likelihood_reference`` and
``inner_product_reference`` evaluate the same equations densely in numpy, for tests, plots and the benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from semloc_core.bearing import Heatlines
from semloc_core.cache import BoundedCache
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import _kernels
from semloc_core.localization.score_likelihood import ScoreLikelihood

DEFAULT_SIGMA = math.radians(5.0)  # §4.7.3: "σ is a field of view threshold (in this case 5°)"
DEFAULT_VISIBILITY_RADIUS = 20.0  # eq. 4.8: dist_v = 20 (metres)
# The view's occlusion test looks up which objects can hide another in a grid of the map (_kernels.occluder_cells):
# its cells are as fine as this many (cell, object pair) tests allow (~0.1 s to build), and no finer than this (m)
OCCLUDER_GRID_TESTS = 2e6
MIN_OCCLUDER_CELL = 0.01
_NO_GRID = (0.0, 0.0, 1.0, 0, 0, np.zeros(2, np.int32), np.zeros(0, np.int32))  # weighing without a view


@dataclass(frozen=True)
class Weighing:
    """Result of weighing particles against one observation.

    ``log_likelihood`` (N,): log of each particle's weight factor (eq. 4.28 for model B, log of eq. 4.6 for A).
    ``fit`` (N,): how well each particle explains the observation, in [0, 1] whatever was observed, for recovery
    (augmented MCL) and status. Model B: exp(-(ℓ* - ℓ_i) / n_bins), where ℓ_i is the particle's log-likelihood
    ratio against a pose expecting no object, ℓ* the largest ratio any detection probability could reach on this
    observation, n_bins the observed bins. Model A: the share of the observed heatline mass that the expected
    heatline explains. ``informative`` is False when the observation carries no evidence (no observed bin of a
    mapped class).
    """

    log_likelihood: np.ndarray
    fit: np.ndarray
    informative: bool


@dataclass(frozen=True, eq=False)
class ViewGeometry:
    """What the camera can see beyond the bearing bins, for one frame (optional; an extension of the thesis).

    ``camera_height``: the camera centre's height above the floor (world z, metres); ``elevation_low/high`` (bins,):
    per bearing bin, the span of elevations (radians, up positive) the image covers there (from the camera model
    and the frame's attitude; an empty span, low > high, where the image does not reach). With it, an object is
    expected only if its centre lies inside the image, it looks at least ``min_angular_height`` tall (what the source
    can detect), and no nearer mapped object hides it: the core of the nearer one's footprint (half its radius: a
    map's sizes are axis-aligned boxes) covers at least half of its width at its centre's elevation (thesis §4.8.4,
    "Occlusions": "expanded to explicitly discount objects that should not be visible even though they're in the
    field of view ... modelling occlusions between objects, measuring object sizes and distances").
    """

    camera_height: float
    elevation_low: np.ndarray
    elevation_high: np.ndarray
    min_angular_height: float = 0.0  # objects that look shorter than this (radians) are not expected

    def __post_init__(self) -> None:
        low = np.ascontiguousarray(self.elevation_low, dtype=np.float64).reshape(-1)
        high = np.ascontiguousarray(self.elevation_high, dtype=np.float64).reshape(-1)
        if low.shape != high.shape or low.size < 4:
            raise ValueError(f"elevation spans must be two (bins,) arrays, got {low.shape} and {high.shape}")
        if not (math.isfinite(self.camera_height) and np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError("view geometry must be finite")
        object.__setattr__(self, "elevation_low", low)
        object.__setattr__(self, "elevation_high", high)
        object.__setattr__(self, "camera_height", float(self.camera_height))
        if not (math.isfinite(self.min_angular_height) and self.min_angular_height >= 0):
            raise ValueError(f"min_angular_height must be >= 0, got {self.min_angular_height}")
        object.__setattr__(self, "min_angular_height", float(self.min_angular_height))

    @classmethod
    def from_camera(cls, camera, n_bins: int, camera_height: float, T_body_cam=None, min_pixels: float = 0.0,
                    step: float = 0.5) -> "ViewGeometry":
        """Elevation spans per bin of a camera, rig or panorama (``T_body_cam``: the frame's attitude for a single
        camera). ``min_pixels``: the smallest object height (pixels, at the image centre) the heatline source
        detects - a detector's smallest template, a ground-truth box filter.

        The rays of a bearing form a meridian from the nadir to the zenith, along which elevation is monotone; the
        part of a bin's wedge inside an image is therefore bounded by the image's border, and its highest and lowest
        rays lie on that border (or at the zenith / nadir when the image holds them). So the spans are traced along
        the border of each image (``step`` pixels apart, linear between samples), each border segment giving the
        elevations where it enters and leaves every bin it crosses: every bin the image reaches gets its span, however
        narrow the bins are against the pixels."""
        from semloc_core.camera import CameraRig, EquirectangularCamera, members, rays_body

        n_bins = int(n_bins)
        if n_bins < 4:
            raise ValueError(f"need at least 4 bearing bins, got {n_bins}")
        if not (math.isfinite(step) and 0 < step <= 8):
            raise ValueError(f"step must be in (0, 8] pixels, got {step}")
        low = np.full(n_bins, np.pi / 2)
        high = np.full(n_bins, -np.pi / 2)
        single = not isinstance(camera, CameraRig)
        for member in members(camera):
            T = member.T_body_cam if not single or T_body_cam is None else np.asarray(T_body_cam, dtype=float)
            for u, v in _image_border(member.width, member.height, step):
                rays = rays_body(member, u, v, T_body_cam=T)
                _spans_along(rays, n_bins, low, high)
            # a pole inside the image: every meridian reaches it
            poles = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]) @ T[:3, :3]
            _, inside = member.project_cam(poles)
            if inside[0]:
                high[:] = np.pi / 2
                low[:] = np.minimum(low, np.pi / 2)
            if inside[1]:
                low[:] = -np.pi / 2
                high[:] = np.maximum(high, -np.pi / 2)
        first = members(camera)[0]
        pixel = ((first.lat_top - first.lat_bottom) / first.height if isinstance(first, EquirectangularCamera)
                 else 1.0 / first.K[1, 1])
        return cls(camera_height, low, high, float(min_pixels) * pixel)


def _image_border(width: int, height: int, step: float):
    """The four sides of an image's border [-0.5, width - 0.5] x [-0.5, height - 0.5] as (u, v) samples at most
    ``step`` pixels apart, each side from corner to corner."""
    columns = np.linspace(-0.5, width - 0.5, int(math.ceil(width / step)) + 1)
    rows = np.linspace(-0.5, height - 0.5, int(math.ceil(height / step)) + 1)
    return ((columns, np.full_like(columns, -0.5)), (columns, np.full_like(columns, height - 0.5)),
            (np.full_like(rows, -0.5), rows), (np.full_like(rows, width - 0.5), rows))


def _spans_along(rays: np.ndarray, n_bins: int, low: np.ndarray, high: np.ndarray) -> None:
    """Widen ``low``/``high`` (per bin) by a polyline of rays (body frame, in order): each segment, linear in
    (bearing, elevation), gives the elevations where it enters and leaves each bin it crosses (bin i covers
    [-π + iΔ, -π + (i+1)Δ), docs/conventions.md)."""
    bearing = np.arctan2(rays[:, 1], rays[:, 0])
    elevation = np.arctan2(rays[:, 2], np.hypot(rays[:, 0], rays[:, 1]))
    width = 2 * np.pi / n_bins
    start = (bearing[:-1] + np.pi) / width  # in bins
    turn = (np.diff(bearing) + np.pi) % (2 * np.pi) - np.pi  # the short way round (a segment is a fraction of a bin)
    end = start + turn / width
    e0, e1 = elevation[:-1], elevation[1:]
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    first = np.floor(lo).astype(np.int64)
    count = np.floor(hi).astype(np.int64) - first + 1
    segment = np.repeat(np.arange(start.size), count)
    bins = first[segment] + (np.arange(segment.size) - np.repeat(np.cumsum(count) - count, count))
    span = end - start
    safe = np.where(span != 0, span, 1.0)
    # the segment's ends inside the bin, as fractions along the segment; its elevation there
    a = np.clip(bins, lo[segment], hi[segment])
    b = np.clip(bins + 1, lo[segment], hi[segment])
    flat = span[segment] == 0
    ta = np.where(flat, 0.0, (a - start[segment]) / safe[segment])
    tb = np.where(flat, 0.0, (b - start[segment]) / safe[segment])
    ea = e0[segment] + (e1[segment] - e0[segment]) * ta
    eb = e0[segment] + (e1[segment] - e0[segment]) * tb
    wrapped = np.mod(bins, n_bins)
    np.minimum.at(low, wrapped, np.minimum(ea, eb))
    np.maximum.at(high, wrapped, np.maximum(ea, eb))


def _check_states(states) -> np.ndarray:
    states = np.ascontiguousarray(states, dtype=np.float64)
    if states.ndim != 2 or states.shape[1] != 3:
        raise ValueError(f"particle states must be (N, 3) [x, y, theta], got shape {states.shape}")
    return states


def _check_heatlines(heatlines) -> Heatlines:
    if not isinstance(heatlines, Heatlines):
        raise TypeError(f"expected semloc_core.bearing.Heatlines, got {type(heatlines).__name__}")
    return heatlines


class _BearingModel:
    """Shared machinery: the map's objects grouped by class and aligned with an observation's classes."""

    kind: int

    def __init__(self, semantic_map: SemanticMap, sigma: float, visibility_radius: float, peak: float,
                 window_sigmas: float, subdivisions: int):
        if not isinstance(semantic_map, SemanticMap):
            raise TypeError(f"expected a SemanticMap, got {type(semantic_map).__name__}")
        if not (np.isfinite(sigma) and 0 < sigma < math.pi):
            raise ValueError(f"sigma must be in (0, pi) radians, got {sigma}")
        if not visibility_radius > 0:
            raise ValueError(f"visibility radius must be positive (inf for no limit), got {visibility_radius}")
        if not 0 < peak <= 1:
            raise ValueError(f"peak detection probability must be in (0, 1], got {peak}")
        if not window_sigmas >= 3:
            raise ValueError(f"window_sigmas must be at least 3, got {window_sigmas}")
        if int(subdivisions) < 1:
            raise ValueError(f"subdivisions must be >= 1, got {subdivisions}")
        self.semantic_map = semantic_map
        self._object_xy = np.ascontiguousarray(semantic_map.positions[:, :2], dtype=np.float64)
        self.sigma = float(sigma)
        self.visibility_radius = float(visibility_radius)
        self.peak = float(peak)
        self.window_sigmas = float(window_sigmas)
        self.subdivisions = int(subdivisions)
        self._layouts = BoundedCache(8)  # per class tuple of the heatlines
        self._windows = BoundedCache(8)  # per bin count
        self._tables = None  # (heatlines, prefix tables) of the last observation weighed (its classes fix the layout)
        self._detection_cache = None  # (heatlines, settings, detections) of the last observation drawn from
        self._terms = None  # (heatlines, the model's per-bin terms) of the last observation weighed
        self._class_members = BoundedCache(8)  # per class tuple of the heatlines: its mapped rows and their objects
        self._occluder_grids = BoundedCache(8)  # per class tuple of the heatlines: which objects can hide another

    def _layout(self, classes: tuple[str, ...]):
        """Objects sorted by observed class: (heatline rows used, x, y, start, stop, view geometry, tables).
        Cached per class tuple. ``tables``: (class of each prefix table, its existence, each object's table, each
        object's ln existence, whether each class's objects share one existence) - one table per class and distinct
        existence (see _kernels)."""
        layout = self._layouts.get(classes)
        if layout is None:
            rows, order, starts, stops = [], [], [], []
            table_of: dict = {}  # (class, existence) -> prefix table
            object_table = []
            m = self.semantic_map
            for row, name in enumerate(classes):
                members = self.semantic_map.objects_of(name)
                if members.size == 0:
                    continue
                c = len(rows)
                rows.append(row)
                starts.append(len(order))
                order.extend(members.tolist())
                stops.append(len(order))
                for existence in m.existence[members]:
                    object_table.append(table_of.setdefault((c, float(existence)), len(table_of)))
            order = np.array(order, dtype=np.int64)
            known = m.has_height[order] & (m.sizes[order, 2] > 0)
            half_height = 0.5 * m.sizes[order, 2]
            layout = (np.array(rows, dtype=np.int64), np.ascontiguousarray(m.positions[order, 0]),
                      np.ascontiguousarray(m.positions[order, 1]), np.array(starts, dtype=np.int64),
                      np.array(stops, dtype=np.int64),
                      (np.ascontiguousarray(known), np.ascontiguousarray(m.positions[order, 2]),
                       np.ascontiguousarray(m.positions[order, 2] - half_height),
                       np.ascontiguousarray(m.positions[order, 2] + half_height),
                       np.ascontiguousarray(0.5 * m.sizes[order, :2].max(axis=1))),
                      (np.array([c for c, _ in table_of], dtype=np.int64),
                       np.array([e for _, e in table_of], dtype=float),
                       np.array(object_table, dtype=np.int64), np.ascontiguousarray(np.log(m.existence[order])),
                       np.array([np.unique(m.existence[order[a:b]]).size == 1 for a, b in zip(starts, stops)],
                                dtype=np.bool_)))
            self._layouts[classes] = layout
        return layout

    def _window(self, n_bins: int):
        """Cached (weights, half_bins) of the Gaussian window on an n-bin grid (see _kernels)."""
        layout = self._windows.get(n_bins)
        if layout is None:
            sigma_bins = self.sigma / (2 * math.pi / n_bins)
            half_bins = int(math.ceil(self.window_sigmas * sigma_bins))
            if 2 * half_bins + 2 > n_bins:
                raise ValueError(f"a {n_bins}-bin heatline is too coarse for sigma = {math.degrees(self.sigma):.1f} "
                                 f"deg: the Gaussian window would wrap around the circle")
            weights = _kernels.window_layout(n_bins, self.subdivisions, half_bins, sigma_bins, self.peak)
            layout = (weights, half_bins)
            self._windows[n_bins] = layout
        return layout

    def _score(self, states: np.ndarray, heatlines: Heatlines, coefficients: np.ndarray, layout,
               view: ViewGeometry | None) -> np.ndarray:
        _, xs, ys, starts, stops, geometry, (table_class, table_existence, object_table, log_existence, alike) = layout
        n_bins = heatlines.scores.shape[1]
        weights, half_bins = self._window(n_bins)
        # once per observation: the filter weighs its particles and then its recovery probes on the same heatlines
        cached = self._tables
        if cached is not None and cached[0] is heatlines:
            tables = cached[1]
        else:
            # an object that exists with probability π is expected with π g: its class's coefficients scaled by π
            tables = _kernels.prefix_tables(coefficients[table_class] * table_existence[:, None], heatlines.observed,
                                            weights, half_bins, self.kind)
            self._tables = (heatlines, tables)
        out = np.empty(states.shape[0])
        if view is not None:
            if not isinstance(view, ViewGeometry):
                raise TypeError(f"view must be a ViewGeometry, got {type(view).__name__}")
            if view.elevation_low.shape != (n_bins,):
                raise ValueError(f"view geometry has {view.elevation_low.size} bins, the heatlines {n_bins}")
            camera_height, low, high = view.camera_height, view.elevation_low, view.elevation_high
            min_height = view.min_angular_height
            grid = self._occluder_grid(heatlines.classes, layout)
        else:
            camera_height, low, high, min_height = 0.0, np.zeros(n_bins), np.zeros(n_bins), 0.0
            grid = _NO_GRID
        if states.shape[0]:
            sigma_bins = self.sigma / (2 * math.pi / n_bins)
            _kernels.score_particles(states, xs, ys, starts, stops, tables, object_table, log_existence, alike,
                                     sigma_bins * sigma_bins, n_bins, self.subdivisions, half_bins,
                                     self.visibility_radius, view is not None, *geometry, camera_height, low, high,
                                     min_height, *grid, out)
        return out

    def _occluder_grid(self, classes: tuple[str, ...], layout):
        """(x0, y0, cell size, columns, rows, offsets, occluders) of ``_kernels.occluder_cells`` over the map's
        bounds for the layout's objects, once per class tuple: which objects can hide another from each cell. The
        cells are as fine as ``OCCLUDER_GRID_TESTS`` pair tests allow, at least ``MIN_OCCLUDER_CELL``."""
        grid = self._occluder_grids.get(classes)
        if grid is None:
            _, xs, ys, _, _, (known, _, _, _, radius), _ = layout
            low, high = self.semantic_map.bounds
            n_known = int(known.sum())
            cell = max(math.sqrt(float(np.prod(high - low)) * n_known * n_known / OCCLUDER_GRID_TESTS),
                       MIN_OCCLUDER_CELL)
            # fewer than two objects of known height: nothing can hide anything, no grid
            columns, rows = (int(v) for v in np.ceil((high - low) / cell)) if n_known > 1 else (0, 0)
            offsets, occluders = _kernels.occluder_cells(xs, ys, radius, known, self.visibility_radius,
                                                         float(low[0]), float(low[1]), cell, columns, rows)
            grid = self._occluder_grids[classes] = (float(low[0]), float(low[1]), cell, columns, rows, offsets,
                                                    occluders)
        return grid

    def sample_poses(self, heatlines: Heatlines, n: int, free_space, rng: np.random.Generator,
                     peaks_per_class: int = 3, min_separation_deg: float = 5.0) -> np.ndarray:
        """``n`` poses that would see the observation's detections where they are (sensor-resetting proposals for
        global localization, recovery and the recovery reference).

        Detections are the strongest ``peaks_per_class`` peaks of each mapped class's heatline, drawn in proportion
        to their score above the class's median. A pose is drawn from two detections at different bearings, each
        paired with a random mapped instance of its class: the positions that see the two instances that far
        apart form an arc through them (resection), and a uniform heading picks a point on it; the heading then puts
        the instances at the peaks' bearings (± sigma / 2). With a single detection (or when the pair has no valid
        pose) it is a random free-space position within the visibility radius, turned to put the instance at the
        peak. Returns an empty (0, 3) array when no mapped class has a peak."""
        detections = self._detections(heatlines, peaks_per_class, min_separation_deg)
        n = int(n)
        if detections is None or n <= 0:
            return np.zeros((0, 3))
        cdf, peak_bearing, counts, offsets, flat = detections
        first = np.empty(n, dtype=np.int64)
        first_xy = np.empty((n, 2))
        out = np.empty((n, 3))
        done = np.zeros(n, dtype=bool)
        _kernels.aligned_poses(rng, cdf, peak_bearing, counts, offsets, flat, self._object_xy,
                               math.radians(min_separation_deg), self.visibility_radius, *free_space.arrays, first,
                               first_xy, out, done)
        rest = np.flatnonzero(~done)
        if rest.size:
            targets = first_xy[rest]
            positions = free_space.sample(rest.size, rng)
            if math.isfinite(self.visibility_radius):
                for _ in range(20):  # keep the instance within reach
                    far = np.flatnonzero(np.hypot(*(targets - positions).T) > self.visibility_radius)
                    if far.size == 0:
                        break
                    positions[far] = free_space.sample(far.size, rng)
            out[rest, :2] = positions
            out[rest, 2] = (np.arctan2(targets[:, 1] - positions[:, 1], targets[:, 0] - positions[:, 0])
                            - peak_bearing[first[rest]])
        out[:, 2] += rng.normal(0.0, self.sigma / 2, n)
        out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return out

    def _detections(self, heatlines: Heatlines, peaks_per_class: int, min_separation_deg: float):
        """The strongest ``peaks_per_class`` peaks of each mapped class's heatline (each suppressing its neighbours
        within ``min_separation_deg``) and the mapped instances they may be: (cumulative distribution of their
        weights, peak bearings, instances per peak, offsets into ``flat``, flat instance indices), or None without a
        peak. Once per observation: the
        filter draws poses several times from the same heatlines."""
        key = (int(peaks_per_class), float(min_separation_deg))
        cached = self._detection_cache
        if cached is not None and cached[0] is heatlines and cached[1] == key:
            return cached[2]
        n_bins = heatlines.scores.shape[1]
        grid_centres = -np.pi + (np.arange(n_bins) + 0.5) * (2 * np.pi / n_bins)
        separation = max(1, int(round(math.radians(min_separation_deg) / (2 * np.pi / n_bins))))
        observed = heatlines.observed
        rows, members_of = self._mapped_rows(heatlines.classes)
        detections = None
        if rows.size and observed.any() and peaks_per_class > 0:
            # every mapped class at once: its strongest bins, each suppressing its neighbours, while above the
            # class's median
            scores = heatlines.scores[rows][:, observed]
            middle = scores.shape[1] // 2  # the class's median, as np.median (the mean of two in float32), faster
            if scores.shape[1] % 2:
                floor = np.partition(scores, middle, axis=1)[:, middle].astype(np.float64)
            else:
                ordered = np.partition(scores, [middle - 1, middle], axis=1)
                floor = ((ordered[:, middle - 1] + ordered[:, middle]) / np.float32(2)).astype(np.float64)
            found = np.zeros((rows.size, peaks_per_class), dtype=bool)
            weight = np.zeros((rows.size, peaks_per_class))
            index = np.zeros((rows.size, peaks_per_class), dtype=np.int64)
            _kernels.strongest_peaks(heatlines.scores[rows], observed, separation, floor, found, weight, index)
            if found.any():  # in class order, strongest first within a class
                weights = weight[found]
                weights = weights / weights.sum()
                cdf = weights.cumsum()
                cdf /= cdf[-1]   # as Generator.choice(p=weights) computes it
                members = [members_of[r] for r in np.repeat(np.arange(rows.size), found.sum(axis=1))]
                counts = np.array([m.size for m in members])
                detections = (cdf, grid_centres[index[found]], counts, np.concatenate([[0], np.cumsum(counts)])[:-1],
                              np.concatenate(members))
        self._detection_cache = (heatlines, key, detections)
        return detections

    def _mapped_rows(self, classes: tuple[str, ...]) -> tuple[np.ndarray, list]:
        """The rows of the heatlines' classes that the map holds, and each one's objects (cached per class tuple:
        the map does not change)."""
        mapped = self._class_members.get(classes)
        if mapped is None:
            members = [self.semantic_map.objects_of(name) for name in classes]
            rows = np.array([row for row, objects in enumerate(members) if objects.size], dtype=np.int64)
            mapped = self._class_members[classes] = (rows, [members[row] for row in rows])
        return mapped

    def expected(self, pose, heatlines: Heatlines, view: ViewGeometry | None = None) -> np.ndarray:
        """The expected heatline / detection probability (C, B) of each observed class from one pose (for plots)."""
        return expected_heatlines(np.asarray(pose, dtype=float)[None], self.semantic_map, heatlines.classes,
                                  heatlines.scores.shape[1], self.sigma, self.peak, self.visibility_radius, view)[0]


class GenerativeScoreModel(_BearingModel):
    """Model B: generative score likelihood (eq. 4.17-4.28), in log space.

    ``likelihood`` gives p(z|d), p(z|d̄) for every class that the observations carry and the map holds.
    ``peak`` scales the Gaussian of eq. 4.26 (1.0 = an object exactly at a bearing is certainly detected there;
    below 1 it tolerates misses). ``visibility_radius`` ignores objects farther than that (the thesis's model B has
    no such limit: the default is inf). ``exponent`` tempers the likelihood (log-likelihood x exponent; 1 = eq. 4.27):
    eq. 4.18 treats neighbouring bins as independent although a detection spans several, which makes the product
    overconfident; an exponent near bin width / σ keeps a global initialisation from collapsing on one particle.
    """

    kind = _kernels.KIND_LOG_RATIO

    def __init__(self, semantic_map: SemanticMap, likelihood: ScoreLikelihood, sigma: float = DEFAULT_SIGMA,
                 visibility_radius: float = math.inf, peak: float = 1.0, exponent: float = 1.0,
                 window_sigmas: float = 5.0, subdivisions: int = 4):
        super().__init__(semantic_map, sigma, visibility_radius, peak, window_sigmas, subdivisions)
        if not isinstance(likelihood, ScoreLikelihood):
            raise TypeError(f"expected a ScoreLikelihood, got {type(likelihood).__name__}")
        if not 0 < exponent <= 1:
            raise ValueError(f"exponent must be in (0, 1], got {exponent}")
        self.likelihood = likelihood
        self.exponent = float(exponent)

    def log_densities(self, heatlines: Heatlines, rows: np.ndarray):
        names = [heatlines.classes[r] for r in rows]
        missing = [n for n in names if n not in self.likelihood.classes]
        if missing:
            raise ValueError(f"no score likelihood for observed class(es) {missing} "
                             f"(calibrated: {list(self.likelihood.classes)})")
        return self.likelihood.log_densities(heatlines.scores[rows], [self.likelihood.index(n) for n in names])

    def weigh(self, states, heatlines: Heatlines, view: ViewGeometry | None = None) -> Weighing:
        states = _check_states(states)
        heatlines = _check_heatlines(heatlines)
        layout = self._layout(heatlines.classes)
        rows = layout[0]
        terms = self._observation_terms(heatlines, rows)
        if terms is None:
            zeros = np.zeros(states.shape[0])
            return Weighing(zeros, zeros.copy(), False)
        ratio_minus_one, background, best, n_observed = terms
        log_ratio = self._score(states, heatlines, ratio_minus_one, layout, view)
        # What a particle leaves unexplained, per observed bin, is its fit (1 = explains everything, smaller = worse).
        fit = np.exp(np.minimum(log_ratio - best, 0.0) / n_observed)
        return Weighing(self.exponent * (background + log_ratio), fit, True)

    def _observation_terms(self, heatlines: Heatlines, rows: np.ndarray):
        """(p(z|d)/p(z|d̄) - 1 per class and bin, the background sum, the best sum, observed bins) of one
        observation, or None when it has no term; once per observation (the filter weighs its particles and then
        its probes on the same heatlines)."""
        cached = self._terms
        if cached is not None and cached[0] is heatlines:
            return cached[1]
        terms = None
        n_observed = int(heatlines.observed.sum())
        if n_observed * len(rows):
            log_d, log_b = self.log_densities(heatlines, rows)
            # eq. 4.27 in log space: log Π_c Π_θ [p(z|d) P + p(z|d̄)(1 - P)]
            #   = Σ_c Σ_θ log p(z|d̄) + Σ_c Σ_θ log(1 + (p(z|d)/p(z|d̄) - 1) P);
            # the first sum does not depend on the pose, the second is zero wherever no object is expected.
            ratio_minus_one = np.expm1(log_d - log_b)
            observed = heatlines.observed
            background = float(log_b[:, observed].sum())
            # The best any pose could do: P = peak wherever the score favours an object, 0 elsewhere.
            best = float(np.log1p(self.peak * ratio_minus_one[:, observed]).clip(min=0.0).sum())
            terms = (ratio_minus_one, background, best, n_observed)
        self._terms = (heatlines, terms)
        return terms


class InnerProductModel(_BearingModel):
    """Model A: w = Σ_c <z_c, ẑ_c> (eq. 4.6), ẑ from eq. 4.7-4.8 (Gaussians within ``visibility_radius``).

    ``exponent`` raises the weight to a power (1 = the thesis); the log-likelihood returned is
    ``exponent * log(w + floor)`` so that a particle that explains nothing keeps a small non-zero weight.
    """

    kind = _kernels.KIND_INNER_PRODUCT

    def __init__(self, semantic_map: SemanticMap, sigma: float = DEFAULT_SIGMA,
                 visibility_radius: float = DEFAULT_VISIBILITY_RADIUS, exponent: float = 1.0, floor: float = 1e-6,
                 window_sigmas: float = 5.0, subdivisions: int = 4):
        super().__init__(semantic_map, sigma, visibility_radius, 1.0, window_sigmas, subdivisions)
        if not exponent > 0:
            raise ValueError(f"exponent must be positive, got {exponent}")
        if not floor > 0:
            raise ValueError(f"floor must be positive, got {floor}")
        self.exponent = float(exponent)
        self.floor = float(floor)

    def weigh(self, states, heatlines: Heatlines, view: ViewGeometry | None = None) -> Weighing:
        states = _check_states(states)
        heatlines = _check_heatlines(heatlines)
        layout = self._layout(heatlines.classes)
        rows = layout[0]
        cached = self._terms
        if cached is not None and cached[0] is heatlines:  # once per observation, as model B's terms
            scores, mass = cached[1]
        else:
            scores = np.where(heatlines.observed[None], heatlines.scores[rows].astype(np.float64), 0.0)
            mass = float(np.clip(scores, 0, None).sum())
            self._terms = (heatlines, (scores, mass))
        if rows.size == 0 or mass <= 0:
            zeros = np.zeros(states.shape[0])
            return Weighing(zeros, zeros.copy(), False)
        weights = self._score(states, heatlines, scores, layout, view)
        return Weighing(self.exponent * np.log(np.maximum(weights, 0.0) + self.floor), weights / mass, True)


# ---------------------------------------------------------------------------------------------- dense references
def object_visibility(states, semantic_map: SemanticMap, visibility_radius: float = math.inf,
                      view: ViewGeometry | None = None) -> np.ndarray:
    """(N, objects) bool: within the visibility radius (eq. 4.8) and, with ``view``, inside the image vertically and
    not hidden behind a nearer object (see ``ViewGeometry``). Plain numpy, object by object."""
    states = _check_states(states)
    m = semantic_map
    delta = m.positions[None, :, :2] - states[:, None, :2]
    distance = np.hypot(delta[..., 0], delta[..., 1])
    visible = distance <= visibility_radius
    if view is None:
        return visible
    n_bins = view.elevation_low.size
    bearing = (np.arctan2(delta[..., 1], delta[..., 0]) - states[:, 2:3] + np.pi) % (2 * np.pi) - np.pi
    known = m.has_height & (m.sizes[:, 2] > 0)
    elevation = np.arctan2(m.positions[None, :, 2] - view.camera_height, distance)
    bins = np.round((bearing + np.pi) / (2 * np.pi / n_bins) - 0.5).astype(np.int64) % n_bins
    inside = (elevation >= view.elevation_low[bins]) & (elevation <= view.elevation_high[bins])
    radius = 0.5 * m.sizes[:, :2].max(axis=1)
    bottom = m.positions[:, 2] - 0.5 * m.sizes[:, 2]
    top = m.positions[:, 2] + 0.5 * m.sizes[:, 2]
    # the box's elevation span: lowest of the bottom's near and far edges to the highest of the top's (seen from
    # above, a bowl's image box covers its far rim; _kernels._apparent_height)
    near = np.maximum(distance - radius[None, :], 1e-3)
    far = distance + radius[None, :]
    top_rel = top[None, :] - view.camera_height
    bottom_rel = bottom[None, :] - view.camera_height
    apparent = (np.maximum(np.arctan2(top_rel, near), np.arctan2(top_rel, far))
                - np.minimum(np.arctan2(bottom_rel, near), np.arctan2(bottom_rel, far)))
    inside &= apparent >= view.min_angular_height
    visible &= inside | ~known[None, :]
    hidden = np.zeros_like(visible)
    for k in np.flatnonzero(known):
        own = np.arctan2(radius[k], distance[:, k])
        for o in np.flatnonzero(known):
            if o == k:
                continue
            gap = np.abs((bearing[:, k] - bearing[:, o] + np.pi) % (2 * np.pi) - np.pi)
            width = np.arctan2(_kernels.OCCLUDER_CORE * radius[o], distance[:, o])
            covered = np.minimum(gap + own, width) - np.maximum(gap - own, -width)  # of k's bearing span
            behind = (visible[:, o] & (distance[:, o] < distance[:, k])
                      & (covered >= 2 * _kernels.OCCLUDED_SHARE * own)
                      & (elevation[:, k] >= np.arctan2(bottom[o] - view.camera_height, distance[:, o]))
                      & (elevation[:, k] <= np.arctan2(top[o] - view.camera_height, distance[:, o])))
            hidden[:, k] |= behind & visible[:, k]
    return visible & ~hidden


def expected_heatlines(states, semantic_map: SemanticMap, classes, n_bins: int, sigma: float = DEFAULT_SIGMA,
                       peak: float = 1.0, visibility_radius: float = math.inf,
                       view: ViewGeometry | None = None) -> np.ndarray:
    """(N, C, B): max over each class's visible instances of π_k·peak·exp(-(θ - θ_k)² / 2σ²) (eq. 4.7, 4.26; π_k
    the object's existence probability, 1 in a surveyed map)."""
    states = _check_states(states)
    centres = -np.pi + (np.arange(n_bins) + 0.5) * (2 * np.pi / n_bins)
    out = np.zeros((states.shape[0], len(classes), n_bins))
    visibility = object_visibility(states, semantic_map, visibility_radius, view)  # eq. 4.8 (+ view)
    for c, name in enumerate(classes):
        for k in semantic_map.objects_of(name):
            dx = semantic_map.positions[k, 0] - states[:, 0]
            dy = semantic_map.positions[k, 1] - states[:, 1]
            bearing = np.arctan2(dy, dx) - states[:, 2]
            difference = (centres[None, :] - bearing[:, None] + np.pi) % (2 * np.pi) - np.pi
            gaussian = semantic_map.existence[k] * peak * np.exp(-0.5 * (difference / sigma) ** 2)
            np.maximum(out[:, c], gaussian * visibility[:, k, None], out=out[:, c])
    return out


def log_likelihood_reference(states, heatlines: Heatlines, semantic_map: SemanticMap, likelihood: ScoreLikelihood,
                             sigma: float = DEFAULT_SIGMA, peak: float = 1.0, visibility_radius: float = math.inf,
                             view: ViewGeometry | None = None) -> np.ndarray:
    """Eq. 4.27 term by term (dense numpy): Σ_c Σ_{θ observed} log[p(z|d) P + p(z|d̄) (1 - P)]."""
    classes = [c for c in heatlines.classes if semantic_map.objects_of(c).size]
    rows = [heatlines.classes.index(c) for c in classes]
    if not rows:
        return np.zeros(_check_states(states).shape[0])
    log_d, log_b = likelihood.log_densities(heatlines.scores[rows], [likelihood.index(c) for c in classes])
    detection = expected_heatlines(states, semantic_map, classes, heatlines.scores.shape[1], sigma, peak,
                                   visibility_radius, view)  # p(d(θ)|Y), eq. 4.26
    per_bin = np.log(np.exp(log_d)[None] * detection + np.exp(log_b)[None] * (1.0 - detection))
    return per_bin[:, :, heatlines.observed].sum(axis=(1, 2))


def inner_product_reference(states, heatlines: Heatlines, semantic_map: SemanticMap, sigma: float = DEFAULT_SIGMA,
                            visibility_radius: float = DEFAULT_VISIBILITY_RADIUS,
                            view: ViewGeometry | None = None) -> np.ndarray:
    """Eq. 4.6 with eq. 4.7-4.8 (dense numpy): Σ_c Σ_{θ observed} z_c(θ) ẑ_c(θ)."""
    classes = [c for c in heatlines.classes if semantic_map.objects_of(c).size]
    rows = [heatlines.classes.index(c) for c in classes]
    if not rows:
        return np.zeros(_check_states(states).shape[0])
    expected = expected_heatlines(states, semantic_map, classes, heatlines.scores.shape[1], sigma, 1.0,
                                  visibility_radius, view)
    observed = np.where(heatlines.observed[None], heatlines.scores[rows], 0.0)
    return np.einsum("ncb,cb->n", expected, observed)
