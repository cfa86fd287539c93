"""Heatmaps with exact ground truth: known 3-D objects projected into known camera poses.

Used by the mapping tests and benchmark before (and besides) the simulator and the detector: a heatmap here is a
Gaussian blob centred on each object's projected centre, its width proportional to the object's projected size -
the response of an ideal sliding-window detector, whose score peaks where the window is centred on the object.
The back-projected rays of the blob centres all pass through the object's centre, so the Hough peak is there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semloc_core.camera import PinholeCamera, pixel_grid
from semloc_core.geometry import look_at


@dataclass(frozen=True, eq=False)
class SyntheticObject:
    class_index: int
    centre: np.ndarray  # (3,) world, metres
    size: np.ndarray  # (3,) metres


def orbit_poses(target, radius: float, height: float, count: int, start_angle: float = 0.0,
                sweep: float = 2 * np.pi) -> list[np.ndarray]:
    """``count`` cameras on a horizontal circle around ``target`` at ``height`` above it, all looking at it."""
    target = np.asarray(target, dtype=float)
    poses = []
    for a in start_angle + sweep * np.arange(count) / count:
        eye = target + np.array([radius * np.cos(a), radius * np.sin(a), height])
        poses.append(look_at(eye, target))
    return poses


def render_heatmaps(camera: PinholeCamera, T_world_cam: np.ndarray, objects, num_classes: int,
                    spread: float = 0.5, peak: float = 1.0, background: float = 0.0,
                    height: int | None = None, width: int | None = None) -> np.ndarray:
    """(num_classes, H, W) float32 heatmaps: per object, a Gaussian of standard deviation ``spread`` times its
    projected radius, peaking at ``peak`` on its projected centre; ``background`` is added everywhere.

    Objects behind the camera or projecting outside the image contribute only their blob's part that falls inside.
    Occlusion is ignored. Distortion-free projection with ``camera.K`` (scaled to ``width x height`` if given).
    """
    height = camera.height if height is None else int(height)
    width = camera.width if width is None else int(width)
    sx, sy = width / camera.width, height / camera.height
    K = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]]) @ camera.K
    heat = np.full((num_classes, height, width), background, dtype=np.float32)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    blobs = np.zeros((num_classes, height, width), dtype=np.float32)
    for obj in objects:
        p = R.T @ (np.asarray(obj.centre, dtype=float) - t)
        if p[2] <= 0.05:
            continue
        cu, cv = (K @ p)[:2] / p[2]
        radius = K[0, 0] * 0.5 * float(np.max(obj.size)) / p[2]
        sigma = max(spread * radius, 0.5)
        if not (-4 * sigma < cu < width + 4 * sigma and -4 * sigma < cv < height + 4 * sigma):
            continue
        blob = peak * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2))
        np.maximum(blobs[obj.class_index], blob, out=blobs[obj.class_index])
    return heat + blobs


def render_level_heatmaps(camera: PinholeCamera, T_world_cam: np.ndarray, objects, num_classes: int,
                          level_depths: np.ndarray, depth_factor: dict | None = None, **kwargs) -> np.ndarray:
    """(num_classes, levels, H, W) per-level heatmaps of an ideal window detector: each object's blob
    (``render_heatmaps``) on the level whose depth (``level_depths`` (classes, levels), metres) is nearest, in
    log, to the object's depth along the optical axis. ``depth_factor`` {object index: f} makes the detector
    misjudge an object's size: it answers at the level of depth ``f`` x the true depth (a look-alike of the wrong
    size)."""
    depths = np.asarray(level_depths, dtype=float)
    maps = None
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    for k, obj in enumerate(objects):
        heat = render_heatmaps(camera, T_world_cam, [obj], num_classes, **kwargs)
        if maps is None:
            maps = np.zeros((num_classes, depths.shape[1]) + heat.shape[1:], np.float32)
        z = float((R.T @ (np.asarray(obj.centre, dtype=float) - t))[2])
        if z <= 0.05:
            continue
        z *= (depth_factor or {}).get(k, 1.0)
        level = int(np.argmin(np.abs(np.log(depths[obj.class_index] / z))))
        np.maximum(maps[obj.class_index, level], heat[obj.class_index], out=maps[obj.class_index, level])
    if maps is None:
        height = kwargs.get("height") or camera.height
        width = kwargs.get("width") or camera.width
        maps = np.zeros((num_classes, depths.shape[1], height, width), np.float32)
    return maps


def plane_depth(camera: PinholeCamera, T_world_cam: np.ndarray, point, normal) -> np.ndarray:
    """(H, W) float32 depth along the optical axis of the infinite plane through ``point`` with ``normal`` (world),
    inf where a pixel's ray does not meet it in front of the camera: a depth image with exact ground truth (a table
    top, a wall) for the occlusion test."""
    rays = camera.rays_cam(*pixel_grid(camera))
    normal = np.asarray(normal, float)
    along = (rays @ T_world_cam[:3, :3].T) @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(point, float) - T_world_cam[:3, 3]) @ normal) / along
    return np.where(t > 0, t * rays[..., 2], np.inf).astype(np.float32)
