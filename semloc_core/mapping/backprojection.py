"""Back-projection of per-class heatmaps into a voxel grid, plane by plane (thesis §5.4).

A horizontal slice ``z = z_k`` of the grid is a plane, and a pinhole camera maps a plane to its image by a
homography. With ``T_world_cam = [R | t]``, intrinsics ``K`` and voxel ``(i, j, k)`` at
``c0 + s·(i, j, k)`` (``c0`` the centre of voxel 0, ``s`` the voxel size), the homogeneous pixel is::

    p(i, j, k) = K Rᵀ (c0 + s·(i, j, k) − t) = A · (i, j, 1) + k · d,
    A = K Rᵀ [s·e_x | s·e_y | c0 − t],   d = s · K Rᵀ e_z

so every slice's homography ``H_k = A + d·e_3ᵀ`` differs from the others only in its last column, and the third
coordinate of ``p`` is the voxel's depth along the optical axis. Each voxel samples the heatmap there.

Sampling rule, identical in the fast path and the per-voxel reference: **bilinear interpolation of the heatmap
padded with zeros** (pixel centres at integer coordinates). A voxel whose centre projects to ``u ∈ [-1, W)``,
``v ∈ [-1, H)`` with depth in ``[min_depth, max_depth]`` receives the interpolated value (which fades to 0 over
the half pixel outside the image, so the volume is a continuous function of the pose); it counts as *in view* when
its centre falls on the image itself - counted with the same bilinear weights (the *coverage*: the weight falling
on real pixels rather than on the zero border, 1 inside, fading to 0 across the border half-pixel), so that the
view-normalised score ``sum / views`` is continuous too and has no spurious peaks along the edges of a view.

The fast path is a numba kernel that walks each slice row by row: the visible span of a row is solved in closed
form (six linear constraints on ``i``); each voxel of the span computes its sampling position and bilinear weights
once and gathers every class with them (classes interleaved, so one tap is one cache line). The slices are dealt
to a few threads (the kernel releases the GIL; the bytes do not depend on the split). OpenCV's ``warpPerspective``
per slice is the obvious alternative; it rounds sampling positions to 1/32 pixel (fixed point), so its volumes
differ from an exact per-voxel projection by more than 1e-4 of the maximum, and it is not faster here
(benchmarks/mapper.py measures both).
"""

from __future__ import annotations

import itertools
import os
import threading

import cv2
import numpy as np
from numba import njit

from semloc_core.camera import PinholeCamera
from semloc_core.geometry import check_rigid_transform
from semloc_core.mapping.grid import VoxelGrid


_UNLIMITED_DEPTH = 1e30


def check_pose(T_world_cam) -> np.ndarray:
    """A camera pose as a float 4x4 rigid transform (rotation orthonormal within 1e-5), or ValueError with the
    reason."""
    return check_rigid_transform(T_world_cam, "T_world_cam", atol=1e-5)


def check_heatmaps(heatmaps, num_classes: int | None = None, codes: bool = False) -> np.ndarray:
    """Heatmaps as a float32 (C, H, W) array of finite values, or ValueError with the reason. ``codes``: uint8 or
    uint16 maps (a detector's quantised scores) are returned as they are."""
    h = np.asarray(heatmaps)
    if h.ndim == 2:
        h = h[None]
    if h.ndim != 3:
        raise ValueError(f"heatmaps must be (classes, height, width), got shape {h.shape}")
    if not (np.issubdtype(h.dtype, np.floating) or np.issubdtype(h.dtype, np.integer) or h.dtype == bool):
        raise ValueError(f"heatmaps must be numeric, got dtype {h.dtype}")
    if num_classes is not None and h.shape[0] != num_classes:
        raise ValueError(f"expected {num_classes} heatmaps (one per class), got {h.shape[0]}")
    if h.shape[1] < 2 or h.shape[2] < 2:
        raise ValueError(f"heatmaps must be at least 2x2 pixels, got {h.shape[1]}x{h.shape[2]}")
    if codes and h.dtype in (np.uint8, np.uint16):
        return h
    h = h.astype(np.float32, copy=False)
    if not np.all(np.isfinite(h)):
        raise ValueError("heatmaps contain non-finite values")
    return h


def remove_background(heatmaps: np.ndarray) -> np.ndarray:
    """Subtract each class's median heat from its heatmap and clip at zero.

    Real detectors answer everywhere: a template matcher scores 0.05-0.2 on plain table and floor, differently per
    class. Summed over hundreds of views that floor swamps the Hough volume with a class-dependent offset and makes
    one threshold meaningless across classes; objects cover a small part of an image, so the median is the floor.
    """
    h = np.asarray(heatmaps, dtype=np.float32)
    floor = np.median(h.reshape(h.shape[0], -1), axis=1).astype(np.float32)
    return np.maximum(h - floor[:, None, None], np.float32(0.0))


def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """Intrinsics of an image resampled from ``from_size`` (W, H) to ``to_size`` covering the same field of view.

    Pixel centres stay at integer coordinates: ``u' = (u + 0.5)·W'/W − 0.5``.
    """
    sx = to_size[0] / from_size[0]
    sy = to_size[1] / from_size[1]
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=float)


def heatmap_camera(camera: PinholeCamera, height: int, width: int) -> PinholeCamera:
    """The camera model of a heatmap of (height, width) pixels covering ``camera``'s image."""
    if (width, height) == (camera.width, camera.height):
        return camera
    K = scale_intrinsics(camera.K, (camera.width, camera.height), (width, height))
    return PinholeCamera(width, height, K, camera.dist, camera.T_body_cam)


def downsample_heatmaps(heatmaps: np.ndarray, camera: PinholeCamera, factor: int):
    """Area-average (C, H, W) heatmaps by an integer factor; returns (heatmaps, camera of the smaller image).

    Averaging first is a low-pass filter: a voxel a few heatmap pixels wide then samples the mean response over its
    footprint instead of one aliased pixel, and the kernel gathers from a cache-sized image.
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"downsample factor must be a positive integer, got {factor}")
    h = check_heatmaps(heatmaps)
    cam = heatmap_camera(camera, h.shape[1], h.shape[2])
    if factor == 1:
        return h, cam
    width, height = h.shape[2] // factor, h.shape[1] // factor
    if width < 2 or height < 2:
        raise ValueError(f"downsampling {h.shape[2]}x{h.shape[1]} heatmaps by {factor} leaves nothing")
    # Crop to a multiple of the factor so INTER_AREA is an exact box average.
    cropped = h[:, : height * factor, : width * factor]
    small = cv2.resize(np.ascontiguousarray(cropped.transpose(1, 2, 0)), (width, height), interpolation=cv2.INTER_AREA)
    small = small.reshape(height, width, -1).transpose(2, 0, 1)
    K = scale_intrinsics(cam.K, (width * factor, height * factor), (width, height))
    return np.ascontiguousarray(small, dtype=np.float32), PinholeCamera(width, height, K, cam.dist, cam.T_body_cam)


def undistorted_camera(camera: PinholeCamera, max_growth: float = 2.0) -> PinholeCamera:
    """The distortion-free pinhole (same focal lengths) whose image holds all of ``camera``'s distorted image.

    Barrel distortion pushes the image border outwards once undistorted; keeping the original size would crop
    it away. The canvas is limited to ``max_growth`` times the original size per axis.
    """
    n = 64
    edge = np.linspace(-0.5, 1.0, n, endpoint=False)
    w, h = camera.width - 0.5, camera.height - 0.5
    border = np.concatenate([
        np.c_[edge * (w + 0.5), np.full(n, -0.5)], np.c_[edge * (w + 0.5), np.full(n, h)],
        np.c_[np.full(n, -0.5), edge * (h + 0.5)], np.c_[np.full(n, w), edge * (h + 0.5)]])
    ideal = cv2.undistortPointsIter(border.reshape(-1, 1, 2), camera.K, camera.dist, None, camera.K,
                                    (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)).reshape(-1, 2)
    lo = np.maximum(ideal.min(axis=0), [-(max_growth - 1) / 2 * camera.width, -(max_growth - 1) / 2 * camera.height])
    hi = np.minimum(ideal.max(axis=0), [(max_growth + 1) / 2 * camera.width, (max_growth + 1) / 2 * camera.height])
    lo = np.floor(np.minimum(lo + 0.5, 0.0))  # pixel edges -> the canvas never shrinks below the original
    hi = np.ceil(np.maximum(hi + 0.5, [camera.width, camera.height]))
    K = camera.K.copy()
    K[0, 2] -= lo[0]
    K[1, 2] -= lo[1]
    width, height = int(hi[0] - lo[0]), int(hi[1] - lo[1])
    return PinholeCamera(width, height, K, T_body_cam=camera.T_body_cam)


def undistortion_maps(camera: PinholeCamera) -> tuple[PinholeCamera, tuple[np.ndarray, np.ndarray]]:
    """The ideal camera of ``undistorted_camera`` and the cv2.remap maps resampling ``camera``'s image onto it."""
    ideal = undistorted_camera(camera)
    maps = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, ideal.K, (ideal.width, ideal.height),
                                       cv2.CV_32FC1)
    return ideal, maps


def undistort_heatmaps(heatmaps: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Resample (C, H, W) heatmaps onto the distortion-free canvas of ``maps`` (bilinear, zero outside)."""
    out = cv2.remap(np.ascontiguousarray(heatmaps.transpose(1, 2, 0)), maps[0], maps[1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.ascontiguousarray(out.reshape(maps[0].shape[0], maps[0].shape[1], -1).transpose(2, 0, 1))


def pad_heatmaps(heatmaps: np.ndarray) -> np.ndarray:
    """(H + 2, W + 2, C) float32 copy, classes interleaved, with a one-pixel zero border: every bilinear tap of a
    sample at ``u ∈ [-1, W)`` then lands inside the array (no per-tap bounds test), and the classes of one tap
    share a cache line."""
    c, h, w = heatmaps.shape
    padded = np.zeros((h + 2, w + 2, c), dtype=np.float32)
    padded[1:-1, 1:-1] = heatmaps.transpose(1, 2, 0)
    return padded


def surface_depths(depth: np.ndarray, height: int, width: int, maps=None) -> np.ndarray:
    """The padded (height + 2, width + 2) float32 surface depths the kernel's occlusion test reads, from a depth
    image (metres along the optical axis, any resolution; NaN, inf or <= 0 = no return).

    Each heatmap pixel takes the farthest surface within its footprint (a max filter, then nearest resampling): a
    voxel counts as hidden only where every depth pixel it could be seen through is nearer, so the edges of an
    occluder hide nothing behind them. No return and the border hide nothing. ``maps``: ``undistortion_maps`` of
    the heatmaps' camera, applied (nearest) after the resampling."""
    z = np.asarray(depth, dtype=np.float32)
    if z.ndim != 2 or min(z.shape) < 1:
        raise ValueError(f"depth must be a (H, W) image, got shape {z.shape}")
    z = np.where(np.isfinite(z) & (z > 0), z, np.float32(_UNLIMITED_DEPTH)).astype(np.float32)
    ky, kx = -(-z.shape[0] // height), -(-z.shape[1] // width)
    if ky > 1 or kx > 1:
        z = cv2.dilate(z, np.ones((ky, kx), np.uint8), anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    if z.shape != (height, width):
        # Pixel (r, c) of the heatmap covers depth rows from r * H0 / height: the dilation anchored at the
        # top-left corner makes that first pixel hold the max over the footprint.
        rows = (np.arange(height) * z.shape[0]) // height
        cols = (np.arange(width) * z.shape[1]) // width
        z = z[rows[:, None], cols[None, :]]
    if maps is not None:
        z = cv2.remap(np.ascontiguousarray(z), maps[0], maps[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=_UNLIMITED_DEPTH)
    out = np.full((z.shape[0] + 2, z.shape[1] + 2), _UNLIMITED_DEPTH, np.float32)
    out[1:-1, 1:-1] = z
    return out


def slice_homography_terms(grid: VoxelGrid, K: np.ndarray, T_world_cam: np.ndarray,
                           offset=(0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (3x3) and ``d`` (3,) with ``p(i, j, k) = A·(i, j, 1) + k·d`` the homogeneous pixel of voxel
    ``offset + (i, j, k)``; slice k's homography (voxel (i, j) -> pixel) is ``A + d·e_3ᵀ``."""
    R = T_world_cam[:3, :3]
    t = T_world_cam[:3, 3]
    M = np.asarray(K, dtype=float) @ R.T
    s = grid.voxel_size
    first_centre = grid.origin + (np.asarray(offset, dtype=float) + 0.5) * s
    A = np.empty((3, 3))
    A[:, 0] = M[:, 0] * s
    A[:, 1] = M[:, 1] * s
    A[:, 2] = M @ (first_centre - t)
    return A, M[:, 2] * s


def slice_homography(grid: VoxelGrid, K: np.ndarray, T_world_cam: np.ndarray, k: int) -> np.ndarray:
    """3x3 homography taking voxel coordinates (i, j, 1) of slice k to homogeneous pixels."""
    A, d = slice_homography_terms(grid, K, T_world_cam)
    H = A.copy()
    H[:, 2] += k * d
    return H


def frustum_constraints(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int, min_depth: float,
                        max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces ``G·X + h >= 0`` (world points X) containing every voxel centre the kernel may write:
    depth in [min_depth, max_depth] and the sample inside the zero-padded image. Rows: near, far, left, right,
    top, bottom (the far row is dropped when max_depth is infinite)."""
    R = T_world_cam[:3, :3]
    t = T_world_cam[:3, 3]
    M = np.asarray(K, dtype=float) @ R.T  # homogeneous pixel = M·(X − t)
    pu, pv, pw = M
    rows = [pw, -pw, pu + pw, width * pw - pu, pv + pw, height * pw - pv]
    offsets = [-min_depth, max_depth, 0.0, 0.0, 0.0, 0.0]
    if not np.isfinite(max_depth):
        del rows[1], offsets[1]
    G = np.array(rows)
    h = np.array(offsets) - G @ t
    return G, h


def box_in_frustum(G: np.ndarray, h: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Conservative test: False only when the box [lo, hi] lies entirely outside one of the half-spaces."""
    # The box corner that maximises G·X picks hi where the coefficient is positive.
    best = np.where(G > 0, hi, lo)
    return bool(np.all(np.einsum("ij,ij->i", G, best) + h >= 0))


@njit(cache=True, nogil=True, fastmath=True)
def _row(i0, i1, au, av, aw, bu, bv, bw, min_depth, max_depth, width, height, padded_width, flat, acc_row,
         views_row, num_channels, edges, channels, surface, margin):
    """Voxels i0..i1-1 of one row: acc_row[c, i] += bilinear sample of class c's channel, views_row[i] += coverage
    (the bilinear weight falling on real pixels). Returns the summed coverage.

    With depth bands (``edges`` (C, L + 1), ``channels`` (C, L)), class c samples channel ``channels[c, r]`` where
    its band r, ``edges[c, r] <= depth < edges[c, r + 1]``, holds the voxel's depth (a window detector's levels,
    semloc_core.mapping.scale_depth); a voxel outside every band of a class gets nothing from it. Without
    (``edges`` None) class c samples channel c: numba compiles that case separately, the band search pruned, so
    single maps pay nothing for it.

    With a ``surface`` (padded (H + 2, W + 2) depths of the nearest surface seen through each heatmap pixel, see
    ``surface_depths``) a voxel deeper than ``surface + margin`` at its nearest pixel is hidden from this frame:
    neither a view nor any heat (None: compiled without the test).

    One pass per voxel, its tap and weights kept in registers (an earlier version stored them in per-row
    temporaries for a second pass). Indices are unsigned on purpose: numba then skips the negative-index
    wrap-around it adds to every signed subscript. Together: 1.6x faster, measured by benchmarks/mapper.py."""
    num_classes = acc_row.shape[0]
    stride = np.uint64(padded_width)
    row_stride = stride * num_channels
    covered = 0.0
    last_x = width - 1.0  # last tap index, in padded coordinates, that is a real pixel
    last_y = height - 1.0
    for i in range(np.uint64(i0), np.uint64(i1)):
        x = np.float64(i)
        w = aw + bw * x
        inv = 1.0 / w
        u = (au + bu * x) * inv + 1.0  # +1: coordinates in the zero-padded heatmap
        v = (av + bv * x) * inv + 1.0
        if not (w >= min_depth and w <= max_depth and u >= 0.0 and u < width + 1.0 and v >= 0.0
                and v < height + 1.0):
            continue
        if surface is not None and w > surface[np.uint64(v + 0.5), np.uint64(u + 0.5)] + margin:
            continue
        x0 = np.uint64(u)
        y0 = np.uint64(v)
        fx = u - x0
        fy = v - y0
        a00 = np.float32((1.0 - fx) * (1.0 - fy))
        a01 = np.float32(fx * (1.0 - fy))
        a10 = np.float32((1.0 - fx) * fy)
        a11 = np.float32(fx * fy)
        # Taps x0 >= 1 and x0 + 1 <= width are real pixels (index 0 and width + 1 are the zero border).
        cover_x = (1.0 - fx if x0 >= 1 else 0.0) + (fx if x0 <= last_x else 0.0)
        cover_y = (1.0 - fy if y0 >= 1 else 0.0) + (fy if y0 <= last_y else 0.0)
        coverage = cover_x * cover_y
        views_row[i] += np.float32(coverage)
        covered += coverage
        b = (y0 * stride + x0) * num_channels  # channels interleaved: one tap is one or two cache lines
        for c in range(num_classes):
            k = b + np.uint64(c)
            if edges is not None:
                band = 0
                while band < channels.shape[1] - 1 and w >= edges[c, band + 1]:
                    band += 1
                if w < edges[c, band] or w > edges[c, band + 1]:
                    continue
                k = b + np.uint64(channels[c, band])
            acc_row[c, i] += (a00 * flat[k] + a01 * flat[k + num_channels]
                              + a10 * flat[k + row_stride] + a11 * flat[k + row_stride + num_channels])
    return covered


@njit(cache=True, nogil=True)
def _row_span(au, av, aw, bu, bv, bw, n, min_depth, max_depth, width, height):
    """[i0, i1) containing every voxel of the row that can pass the sampling test (a superset by one voxel)."""
    lo = 0.0
    hi = n - 1.0
    for c in range(6):
        if c == 0:
            alpha, beta = aw - min_depth, bw
        elif c == 1:
            alpha, beta = max_depth - aw, -bw
        elif c == 2:
            alpha, beta = au + aw, bu + bw
        elif c == 3:
            alpha, beta = width * aw - au, width * bw - bu
        elif c == 4:
            alpha, beta = av + aw, bv + bw
        else:
            alpha, beta = height * aw - av, height * bw - bv
        # alpha + beta·i >= 0
        if beta > 0.0:
            lo = max(lo, -alpha / beta)
        elif beta < 0.0:
            hi = min(hi, alpha / -beta)
        elif alpha < 0.0:
            return 0, 0
    if hi < lo:
        return 0, 0
    return max(int(np.floor(lo)) - 1, 0), min(int(np.ceil(hi)) + 2, n)


@njit(cache=True, nogil=True)
def _backproject_slices(acc, views, padded, A, d, min_depth, max_depth, width, height, edges, channels, surface,
                        margin, k_begin, k_end, coverage):
    """acc[c, k, j, i] += bilinear(padded[..., channel of c at the voxel's depth], p(i, j, k)); views[k, j, i] +=
    coverage, for slices k_begin <= k < k_end; coverage[k] = the slice's summed coverage (see ``_row``)."""
    _, nz, ny, nx = acc.shape
    padded_width = padded.shape[1]
    num_channels = np.uint64(padded.shape[2])
    flat = padded.reshape(-1)
    bu, bv, bw = A[0, 0], A[1, 0], A[2, 0]
    for k in range(k_begin, k_end):
        in_view = 0.0
        for j in range(ny):
            au = A[0, 1] * j + A[0, 2] + d[0] * k
            av = A[1, 1] * j + A[1, 2] + d[1] * k
            aw = A[2, 1] * j + A[2, 2] + d[2] * k
            i0, i1 = _row_span(au, av, aw, bu, bv, bw, nx, min_depth, max_depth, width, height)
            if i1 > i0:
                in_view += _row(i0, i1, au, av, aw, bu, bv, bw, min_depth, max_depth, width, height, padded_width,
                                flat, acc[:, k, j], views[k, j], num_channels, edges, channels, surface, margin)
        coverage[k] = in_view


# By default a block is split over threads only above this many voxels per thread (starting a thread costs
# ~0.1 ms; a dense 200x200x70 block takes ~20 ms on one core).
_MIN_VOXELS_PER_THREAD = 1 << 18
_MAX_THREADS = 4  # beyond this the gather is bound by memory, not by cores
_SLICES_PER_TASK = 4


def default_threads() -> int:
    """Threads :func:`backproject_block` uses by default: the CPUs this process may run on (at most 4)."""
    try:
        available = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        available = os.cpu_count() or 1
    return max(1, min(available, _MAX_THREADS))


def _band_tables(level_bands, num_classes: int, min_depth: float, max_depth: float):
    """The kernel's per-class depth-band tables: ``edges`` (C, L + 1) ascending, ``channels`` (C, L) the padded
    channel of each band. Single maps: one band per class, [min_depth, max_depth], channel c. Per-level bands
    (C, L, 2) are sorted by depth and must meet (``scale_depth.depth_bands`` makes them so); an unlimited far end
    becomes the kernel's huge finite one."""
    far = float(max_depth) if np.isfinite(max_depth) else _UNLIMITED_DEPTH
    if level_bands is None:
        edges = np.tile(np.array([float(min_depth), far]), (num_classes, 1))
        return edges, np.arange(num_classes, dtype=np.int64).reshape(num_classes, 1)
    bands = np.asarray(level_bands, dtype=float)
    if bands.ndim != 3 or bands.shape[0] != num_classes or bands.shape[2] != 2 or np.any(np.isnan(bands)):
        raise ValueError(f"level_bands must be finite ({num_classes} classes, levels, 2) [near, far) depths, got "
                         f"shape {bands.shape}")
    bands = np.minimum(bands, far)
    levels = bands.shape[1]
    edges = np.zeros((num_classes, levels + 1))
    channels = np.zeros((num_classes, levels), np.int64)
    for c in range(num_classes):
        order = np.argsort(bands[c, :, 0], kind="stable")
        near, far_edges = bands[c, order, 0], bands[c, order, 1]
        if np.any(far_edges < near) or np.any(near[1:] < far_edges[:-1] - 1e-12):
            raise ValueError(f"level_bands of class {c} overlap or are reversed: {bands[c].tolist()}")
        if np.any(near[1:] > far_edges[:-1] + 1e-12):
            raise ValueError(f"level_bands of class {c} leave a gap between levels: {bands[c].tolist()}")
        edges[c, :-1], edges[c, -1] = near, far_edges[-1]
        channels[c] = c * levels + order
    return edges, channels


def backproject_block(acc: np.ndarray, views: np.ndarray, padded: np.ndarray, A: np.ndarray, d: np.ndarray,
                      min_depth: float, max_depth: float, width: int, height: int,
                      threads: int | None = None, level_bands: np.ndarray | None = None,
                      surface: np.ndarray | None = None, occlusion_margin: float = 0.0) -> float:
    """Add one frame to a block of voxels (fast path). ``acc`` (C, nz, ny, nx) and ``views`` (nz, ny, nx), both
    float32, are updated in place; ``padded`` from ``pad_heatmaps``; ``A, d`` from ``slice_homography_terms`` for
    the block's first voxel. Returns the frame's summed coverage (≈ the number of voxels in view).

    ``level_bands`` (C, L, 2): scale-selected back-projection (semloc_core.mapping.scale_depth). ``padded`` then
    holds C·L maps, class c's level l at channel ``c·L + l``, and a voxel takes, per class, the level whose
    [near, far) depth band holds its depth (bands of one class must not overlap; a depth in no band adds nothing
    to that class). The view count is the same as with single maps. One pass whatever the number of levels.

    ``surface`` (H + 2, W + 2) float32 from ``surface_depths``: occlusion. A voxel more than ``occlusion_margin``
    behind the surface its nearest heatmap pixel sees is hidden - the frame neither views it nor gives it heat.

    ``threads``: that many threads take groups of slices from a shared counter until none is left (the kernel
    releases the GIL). A thread whose core is busy with other work simply takes fewer groups, so a loaded
    machine costs no more than one thread would. Each voxel is computed the same way whatever the split: the
    result is the same bytes with any number of threads. Default: :func:`default_threads`, but at most one thread
    per 2^18 voxels (small tiles stay on the calling thread)."""
    if not (acc.flags.c_contiguous and views.flags.c_contiguous and padded.flags.c_contiguous):
        raise ValueError("accumulator, view counts and padded heatmaps must be C-contiguous")
    if acc.ndim != 4 or views.shape != acc.shape[1:] or padded.ndim != 3:
        raise ValueError(f"shapes do not match: accumulator {acc.shape}, view counts {views.shape}, "
                         f"padded heatmaps {padded.shape}")
    edges, channels = _band_tables(level_bands, acc.shape[0], min_depth, max_depth)
    if padded.shape[2] != channels.size:
        raise ValueError(f"shapes do not match: accumulator {acc.shape}, padded heatmaps {padded.shape}"
                         + ("" if level_bands is None else f", {channels.shape[1]} levels per class"))
    if surface is not None:
        if surface.dtype != np.float32 or not surface.flags.c_contiguous or surface.shape != padded.shape[:2]:
            raise ValueError(f"surface depths must be C-contiguous float32 of the padded heatmaps' size "
                             f"{padded.shape[:2]}, got {surface.dtype} {surface.shape}")
        if not (np.isfinite(occlusion_margin) and occlusion_margin >= 0):
            raise ValueError(f"occlusion_margin must be a finite distance >= 0, got {occlusion_margin!r}")
    if threads is None:
        threads = min(default_threads(), views.size // _MIN_VOXELS_PER_THREAD)
    elif int(threads) != threads or threads < 1:
        raise ValueError(f"threads must be a positive integer, got {threads!r}")
    nz = acc.shape[1]
    # The kernel is compiled with fastmath (no infinities assumed): an unlimited range becomes a huge finite one.
    far = float(max_depth) if np.isfinite(max_depth) else _UNLIMITED_DEPTH
    args = (acc, views, padded, np.ascontiguousarray(A, dtype=float), np.ascontiguousarray(d, dtype=float),
            float(min_depth), far, float(width), float(height), *((None, None) if level_bands is None else
                                                                   (edges, channels)),
            surface, float(occlusion_margin))
    coverage = np.zeros(nz)
    tasks = -(-nz // _SLICES_PER_TASK)
    threads = max(1, min(int(threads), tasks))
    if threads == 1:
        _backproject_slices(*args, 0, nz, coverage)
        return float(coverage.sum())
    counter = itertools.count()  # next() is atomic under the GIL

    def work():
        while (task := next(counter)) < tasks:
            begin = task * _SLICES_PER_TASK
            _backproject_slices(*args, begin, min(begin + _SLICES_PER_TASK, nz), coverage)

    helpers = [threading.Thread(target=work, daemon=True) for _ in range(threads - 1)]
    for helper in helpers:
        helper.start()
    try:
        work()
    finally:
        for helper in helpers:
            helper.join()
    return float(coverage.sum())


def backproject_reference(grid: VoxelGrid, heatmaps: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray,
                          min_depth: float = 0.05, max_depth: float = np.inf, surface: np.ndarray | None = None,
                          occlusion_margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-voxel projection, the slow reference: every voxel centre is transformed into the camera and projected
    with ``camera.project_cam`` (distortion included), then sampled with the same rule as the fast path
    (``surface``: the same occlusion test, on the nearest pixel).

    Returns the frame's contribution (C, nz, ny, nx) and its coverage (nz, ny, nx), both float32.
    """
    h = check_heatmaps(heatmaps)
    cam = heatmap_camera(camera, h.shape[1], h.shape[2])
    T = check_pose(T_world_cam)
    # An extra all-ones channel sampled by the same rule is the coverage.
    padded = pad_heatmaps(np.concatenate([h, np.ones_like(h[:1])])).transpose(2, 0, 1).astype(np.float64)
    height, width = h.shape[1:]
    values = np.zeros((h.shape[0] + 1,) + grid.volume_shape, dtype=np.float32)
    ii, jj = np.meshgrid(np.arange(grid.nx), np.arange(grid.ny))
    for k in range(grid.nz):  # one slice at a time keeps the temporaries small
        indices = np.stack([ii, jj, np.full_like(ii, k)], axis=-1)
        points_cam = (grid.centres(indices) - T[:3, 3]) @ T[:3, :3]
        depth = points_cam[..., 2]
        uv, _ = cam.project_cam(points_cam)
        u = uv[..., 0] + 1.0
        v = uv[..., 1] + 1.0
        ok = (depth >= min_depth) & (depth <= max_depth) & (u >= 0) & (u < width + 1) & (v >= 0) & (v < height + 1)
        if surface is not None:
            seen = np.zeros_like(ok)
            seen[ok] = depth[ok] <= surface[np.floor(v[ok] + 0.5).astype(np.int64),
                                            np.floor(u[ok] + 0.5).astype(np.int64)] + occlusion_margin
            ok &= seen
        uo, vo = u[ok], v[ok]
        x0 = np.floor(uo).astype(np.int64)
        y0 = np.floor(vo).astype(np.int64)
        fx, fy = uo - x0, vo - y0
        sample = ((1 - fx) * (1 - fy) * padded[:, y0, x0] + fx * (1 - fy) * padded[:, y0, x0 + 1]
                  + (1 - fx) * fy * padded[:, y0 + 1, x0] + fx * fy * padded[:, y0 + 1, x0 + 1])
        values[:, k][:, ok] = sample
    return values[:-1], values[-1]
