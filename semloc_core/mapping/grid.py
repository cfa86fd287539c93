"""The voxel grid: an axis-aligned box of the world frame cut into cubic voxels (thesis §5.4).

Indices ``(i, j, k)`` run along world ``x, y, z``; the centre of voxel ``(i, j, k)`` is
``origin + (i + 0.5, j + 0.5, k + 0.5) * voxel_size``. Every volume over the grid is stored ``[k, j, i]``
(z-slices of ``(ny, nx)`` images, rows along y), so one horizontal slice is one contiguous image - the plane the
back-projection warps a heatmap into.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    origin: np.ndarray  # (3,) world coordinates of the box's minimum corner, metres
    voxel_size: float  # edge of a cubic voxel, metres
    shape: tuple[int, int, int]  # (nx, ny, nz) voxels along world x, y, z

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=float).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"grid origin must be 3 finite coordinates, got {self.origin!r}")
        size = float(self.voxel_size)
        if not np.isfinite(size) or size <= 0:
            raise ValueError(f"voxel size must be a positive number of metres, got {self.voxel_size!r}")
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"grid shape must be three positive voxel counts (nx, ny, nz), got {self.shape!r}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "voxel_size", size)
        object.__setattr__(self, "shape", shape)

    @classmethod
    def from_bounds(cls, minimum, maximum, voxel_size: float) -> "VoxelGrid":
        """The grid covering the box [minimum, maximum] (metres), rounded up to whole voxels."""
        lo = np.asarray(minimum, dtype=float).reshape(-1)
        hi = np.asarray(maximum, dtype=float).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("grid bounds must be two finite 3-vectors")
        if np.any(hi <= lo):
            raise ValueError(f"grid bounds min {lo.tolist()} must be below max {hi.tolist()} on every axis")
        if not np.isfinite(voxel_size) or voxel_size <= 0:
            raise ValueError(f"voxel size must be a positive number of metres, got {voxel_size!r}")
        # The tolerance keeps 2.0 / 0.01 at 200 voxels instead of 201 from floating-point noise.
        shape = np.ceil((hi - lo) / voxel_size - 1e-9).astype(int)
        return cls(lo, voxel_size, tuple(int(n) for n in shape))

    @property
    def nx(self) -> int:
        return self.shape[0]

    @property
    def ny(self) -> int:
        return self.shape[1]

    @property
    def nz(self) -> int:
        return self.shape[2]

    @property
    def num_voxels(self) -> int:
        return self.nx * self.ny * self.nz

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        """Shape of one volume over the grid: (nz, ny, nx)."""
        return (self.nz, self.ny, self.nx)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3): minimum and maximum corner of the box actually covered (whole voxels)."""
        return np.stack([self.origin, self.origin + np.asarray(self.shape) * self.voxel_size])

    def axis_centres(self, axis: int) -> np.ndarray:
        """Centre coordinates of the voxels along world axis 0 (x), 1 (y) or 2 (z)."""
        return self.origin[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_size

    def centres(self, indices) -> np.ndarray:
        """World coordinates of voxel centres for integer or fractional indices (..., 3) ordered (i, j, k)."""
        return self.origin + (np.asarray(indices, dtype=float) + 0.5) * self.voxel_size

    def indices_of(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Voxel indices (..., 3) containing world points (..., 3), and a mask of the points inside the grid."""
        p = np.asarray(points, dtype=float)
        idx = np.floor((p - self.origin) / self.voxel_size).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.asarray(self.shape)), axis=-1)
        return idx, inside

    def bytes_per_voxel(self, num_classes: int) -> int:
        """Memory of one voxel: a float32 accumulator per class plus a float32 view count."""
        return 4 * int(num_classes) + 4

    def to_document(self) -> dict:
        return {"origin": self.origin.tolist(), "voxel_size": self.voxel_size, "shape": list(self.shape)}

    @classmethod
    def from_document(cls, document: dict) -> "VoxelGrid":
        try:
            return cls(document["origin"], document["voxel_size"], tuple(document["shape"]))
        except (KeyError, TypeError) as error:
            raise ValueError(f"invalid voxel grid description {document!r}: {error}") from None

    def __str__(self) -> str:
        # For progress lines: millimetres are the most a voxel grid's corners need (repr keeps every digit).
        def point(p) -> str:
            return "(" + ", ".join(f"{v:.3f}" for v in p) + ")"

        return (f"{' x '.join(map(str, self.shape))} voxels of {self.voxel_size * 100:g} cm from {point(self.origin)} "
                f"to {point(self.bounds[1])} m")

    def __repr__(self) -> str:
        return (f"VoxelGrid(origin={self.origin.tolist()}, voxel_size={self.voxel_size}, shape={self.shape}, "
                f"bounds_max={self.bounds[1].tolist()})")
