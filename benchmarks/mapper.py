"""Voxel mapper throughput: 640x480 heatmaps x 5 classes into 200x200x70 voxels (the thesis's 2 x 2 x 0.7 m at 1 cm).

Compares, in the same process and on the same frames:

* ``fast``      - VoxelMapper.integrate (plane-by-plane homographies, numba row kernel), full pipeline per frame
                  (input checks, optional downsampling, padding, back-projection, view coverage), with the
                  kernel's default threads (one per CPU, at most 4) and again pinned to one CPU (``1 core``);
* ``reference`` - per-voxel projection (every voxel centre through camera.project_cam, bilinear sample), numpy;
* ``cv2-warp``  - cv2.warpPerspective per slice with the same homographies (5 classes as channels), for scale.

and checks the volumes are equal: max |fast - reference| <= 1e-4 of the maximum.

Times are medians per frame: wall clock, and CPU time of the process (all threads). On a machine shared with other
work the wall clock includes waiting for a core; the 1-core CPU time is what an idle core would give.

Heatmaps are dense (a Gaussian per object on top of uniform noise, never exactly zero), so nothing can be skipped.
Poses: hand-held-like views around a 1.4 m table, 0.6-1.2 m from its centre, 0.35-0.8 m above it.

``--occlusion``: every frame also brings its depth image (the table top's plane, which hides what is under it)
and both paths apply the occlusion test (``integrate(..., depth=)``, ``backproject_reference(..., surface=)``).

    .venv/bin/python benchmarks/mapper.py [--frames 60] [--reference-frames 4] [--downsample 1 4] [--occlusion]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.camera import PinholeCamera  # noqa: E402
from semloc_core.mapping import MapperConfig, VoxelGrid, VoxelMapper, backproject_reference  # noqa: E402
from semloc_core.mapping.backprojection import (downsample_heatmaps, slice_homography_terms,  # noqa: E402
                                                surface_depths)
from semloc_core.mapping.synthetic import SyntheticObject, look_at, plane_depth, render_heatmaps  # noqa: E402

CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")
KINECT = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def scene(frames: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    grid = VoxelGrid.from_bounds([-1.0, -1.0, 0.7], [1.0, 1.0, 1.4], 0.01)  # table top at z = 0.7 m
    objects = [SyntheticObject(c, np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.78]),
                               np.array([0.12, 0.12, 0.16])) for c in range(len(CLASSES))]
    poses = []
    for a in np.linspace(0, 2 * np.pi, frames, endpoint=False) + rng.normal(0, 0.05, frames):
        r, h = rng.uniform(0.6, 1.2), rng.uniform(0.35, 0.8)
        eye = np.array([r * np.cos(a), r * np.sin(a), 0.7 + h])
        poses.append(look_at(eye, [rng.normal(0, 0.15), rng.normal(0, 0.15), 0.75]))
    camera = PinholeCamera(640, 480, KINECT)
    heatmaps = [render_heatmaps(camera, T, objects, len(CLASSES)) + rng.uniform(0.01, 0.05, (5, 480, 640)).astype(
        np.float32) for T in poses]
    return grid, camera, poses, heatmaps


def warp_per_slice(acc_zyxc: np.ndarray, grid: VoxelGrid, heat: np.ndarray, camera: PinholeCamera, T, min_depth):
    """The cv2 alternative: one warpPerspective per slice (classes as channels), depth-masked, accumulated."""
    A, d = slice_homography_terms(grid, camera.K, T)
    src = np.ascontiguousarray(heat.transpose(1, 2, 0))
    jj, ii = np.mgrid[0:grid.ny, 0:grid.nx]
    for k in range(grid.nz):
        H = A.copy()
        H[:, 2] += k * d
        depth = H[2, 0] * ii + H[2, 1] * jj + H[2, 2]
        warped = cv2.warpPerspective(src, H, (grid.nx, grid.ny), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        acc_zyxc[k] += warped * (depth >= min_depth)[..., None]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--reference-frames", type=int, default=4)
    parser.add_argument("--downsample", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--repeats", type=int, default=3, help="passes over the frames for the fast path")
    parser.add_argument("--occlusion", action="store_true", help="frames with depth images: the occlusion test on")
    args = parser.parse_args()

    grid, camera, poses, heatmaps = scene(args.frames)
    # The table top's plane (z = 0.7 m) hides what is under it.
    depths = [plane_depth(camera, T, (0.0, 0.0, 0.7), (0.0, 0.0, 1.0)) if args.occlusion else None for T in poses]
    print(f"grid {grid.shape} = {grid.num_voxels / 1e6:.2f} M voxels x {len(CLASSES)} classes; "
          f"{args.frames} frames of {heatmaps[0].shape} heatmaps" + (", with depth (occlusion)" if args.occlusion
                                                                     else ""))
    warm = VoxelMapper(grid, CLASSES)
    # Compile / load the numba kernel outside the timings.
    warm.integrate(heatmaps[0], poses[0], camera, depth=depths[0])
    in_view = []

    rows = []
    all_cpus = os.sched_getaffinity(0)
    for factor in args.downsample:
        config = MapperConfig(heatmap_downsample=factor)
        timings = {}
        for label, cpus in (("default", all_cpus), ("1 core", {min(all_cpus)})):
            os.sched_setaffinity(0, cpus)  # the kernel's default thread count follows the affinity
            try:
                wall, cpu = [], []
                for _ in range(args.repeats):
                    mapper = VoxelMapper(grid, CLASSES, config)
                    for heat, T, depth in zip(heatmaps, poses, depths):
                        t0, c0 = time.perf_counter(), time.process_time()
                        stats = mapper.integrate(heat, T, camera, depth=depth)
                        wall.append(time.perf_counter() - t0)
                        cpu.append(time.process_time() - c0)
                        if factor == args.downsample[0] and label == "default":
                            in_view.append(stats.voxels_in_view / grid.num_voxels)
            finally:
                os.sched_setaffinity(0, all_cpus)
            timings[label] = (1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu)))

        # The same first frames through the per-voxel reference and through a fresh fast mapper.
        n = args.reference_frames
        ref = np.zeros((len(CLASSES),) + grid.volume_shape, np.float32)
        ref_times, ref_cpu = [], []
        for heat, T, depth in zip(heatmaps[:n], poses[:n], depths[:n]):
            small, cam = downsample_heatmaps(heat, camera, factor)
            t0, c0 = time.perf_counter(), time.process_time()
            surface = None if depth is None else surface_depths(depth, cam.height, cam.width)
            values, _ = backproject_reference(grid, small, cam, T, min_depth=config.min_depth, surface=surface,
                                              occlusion_margin=config.occlusion_margin)
            ref += values
            ref_times.append(time.perf_counter() - t0)
            ref_cpu.append(time.process_time() - c0)
        fast = VoxelMapper(grid, CLASSES, config)
        for heat, T, depth in zip(heatmaps[:n], poses[:n], depths[:n]):
            fast.integrate(heat, T, camera, depth=depth)
        got = np.stack([fast.hough_volume(c) for c in CLASSES])
        diff = float(np.abs(got - ref).max() / ref.max())

        # cv2.warpPerspective per slice on the same (downsampled) heatmaps, same frames.
        warp = np.zeros(grid.volume_shape + (len(CLASSES),), np.float32)
        warp_times = []
        for heat, T in zip(heatmaps[:n], poses[:n]):
            small, cam = downsample_heatmaps(heat, camera, factor)
            t0 = time.perf_counter()
            warp_per_slice(warp, grid, small, cam, T, config.min_depth)
            warp_times.append(time.perf_counter() - t0)
        warp_diff = float(np.abs(np.moveaxis(warp, -1, 0) - ref).max() / ref.max())

        ref_ms, ref_cpu_ms, warp_ms = (1e3 * float(np.median(t)) for t in (ref_times, ref_cpu, warp_times))
        rows.append((factor, timings, (ref_ms, ref_cpu_ms), warp_ms, diff, warp_diff))

    print(f"median fraction of the grid in view per frame: {np.median(in_view):.2f}; "
          f"{len(all_cpus)} CPUs, load average {os.getloadavg()[0]:.1f}")
    print()
    print("| heatmap px | fast ms/frame wall (CPU) | fast frames/s | 1 core ms/frame wall (CPU) | "
          "1 core frames/s (CPU) | reference ms/frame wall (CPU) | speed-up (CPU, 1 core) | max diff / max | "
          "cv2-warp ms/frame | cv2-warp diff / max |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for factor, timings, (ref_ms, ref_cpu_ms), warp_ms, diff, warp_diff in rows:
        size = f"{640 // factor}x{480 // factor}"
        (fast_ms, fast_cpu), (one_ms, one_cpu) = timings["default"], timings["1 core"]
        print(f"| {size} | {fast_ms:.1f} ({fast_cpu:.1f}) | {1e3 / fast_ms:.1f} | {one_ms:.1f} ({one_cpu:.1f}) | "
              f"{1e3 / one_ms:.1f} ({1e3 / one_cpu:.1f}) | {ref_ms:.0f} ({ref_cpu_ms:.0f}) | {ref_cpu_ms / one_cpu:.0f}x | "
              f"{diff:.1e} {'ok' if diff <= 1e-4 else 'FAIL'} | {warp_ms:.1f} | {warp_diff:.1e} |")
    return 0 if all(r[4] <= 1e-4 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
