"""Where the robot may be: the map's bounds, optionally narrowed to free-space polygons.

Global initialisation and recovery draw particles uniformly from this region; the filter can also give no weight
to particles that drift out of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import _kernels


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """``bounds`` [[xmin, ymin], [xmax, ymax]]; ``polygons`` (each (P, 2)): if any, the region is their union
    (clipped to the bounds)."""

    bounds: np.ndarray
    polygons: tuple[np.ndarray, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        bounds = np.asarray(self.bounds, dtype=float)
        if bounds.shape != (2, 2) or not np.all(np.isfinite(bounds)) or not np.all(bounds[0] < bounds[1]):
            raise ValueError(f"bounds must be [[xmin, ymin], [xmax, ymax]] with min < max, got {bounds.tolist()}")
        polygons = []
        for polygon in self.polygons:
            polygon = np.asarray(polygon, dtype=float)
            if polygon.ndim != 2 or polygon.shape[1] != 2 or polygon.shape[0] < 3 or not np.all(np.isfinite(polygon)):
                raise ValueError(f"a free-space polygon must be (P >= 3, 2) finite points, got {polygon.shape}")
            polygons.append(polygon)
        object.__setattr__(self, "bounds", bounds)
        object.__setattr__(self, "polygons", tuple(polygons))
        vertices = np.concatenate(polygons) if polygons else np.zeros((0, 2))
        starts = np.concatenate([[0], np.cumsum([len(p) for p in polygons])]) if polygons else np.zeros(0)
        object.__setattr__(self, "_arrays", (bounds, np.ascontiguousarray(vertices), starts.astype(np.int64)))

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bounds, polygon vertices concatenated, each polygon's first vertex then the end) for the numba kernels."""
        return self._arrays

    @classmethod
    def from_map(cls, semantic_map: SemanticMap) -> "FreeSpace":
        return cls(semantic_map.bounds, tuple(semantic_map.free_space))

    @property
    def sampling_box(self) -> np.ndarray:
        """The box that rejection sampling draws from: bounds ∩ the polygons' bounding box."""
        if not self.polygons:
            return self.bounds
        points = np.concatenate(self.polygons)
        low = np.maximum(self.bounds[0], points.min(0))
        high = np.minimum(self.bounds[1], points.max(0))
        if np.any(low >= high):
            raise ValueError("the free-space polygons lie outside the map bounds")
        return np.array([low, high])

    def contains(self, xy) -> np.ndarray:
        """Boolean mask of the points (..., 2) inside the region (even-odd rule in the polygons, as
        ``geometry.inside_polygon``)."""
        xy = np.asarray(xy, dtype=float)
        points = np.ascontiguousarray(xy.reshape(-1, 2))
        inside = np.empty(points.shape[0], dtype=bool)
        _kernels.inside_free_space(points, *self._arrays, inside)
        return inside.reshape(xy.shape[:-1])

    def area(self, rng: np.random.Generator | None = None, samples: int = 20000) -> float:
        """Area of the region (exact without polygons, Monte Carlo estimate with them)."""
        box = self.sampling_box
        box_area = float(np.prod(box[1] - box[0]))
        if not self.polygons:
            return box_area
        rng = rng or np.random.default_rng(0)
        points = box[0] + rng.random((samples, 2)) * (box[1] - box[0])
        return box_area * float(self.contains(points).mean())

    def sample(self, n: int, rng: np.random.Generator, max_rounds: int = 100) -> np.ndarray:
        """n points (n, 2) uniform over the region (rejection sampling from ``sampling_box``)."""
        n = int(n)
        box = self.sampling_box
        out = np.empty((n, 2))
        filled = 0
        for _ in range(max_rounds):
            if filled >= n:
                break
            batch = max(2 * (n - filled), 64)
            points = box[0] + rng.random((batch, 2)) * (box[1] - box[0])
            points = points[self.contains(points)][: n - filled]
            out[filled:filled + len(points)] = points
            filled += len(points)
        if filled < n:
            raise ValueError("could not sample the free space: its polygons cover almost none of the bounds")
        return out

    def sample_poses(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n poses (n, 3): positions uniform over the region, headings uniform over [-pi, pi)."""
        xy = self.sample(n, rng)
        return np.column_stack([xy, rng.uniform(-np.pi, np.pi, int(n))])
