"""CPU renderer: culls primitives to pixel boxes, then ray-casts them with a depth buffer (``_raycast``).

``Renderer(world).render(camera, T_world_cam)`` returns linear BGR floats (0..255 before exposure and effects),
the range of the first hit along each pixel's ray (metres, ``inf`` for none) and the id of the object seen at each
pixel (-1 for none). The camera is any single model of ``semloc_core.camera``; rigs are rendered member by member by
the scenario. Pixel rays come from the camera model itself, so lens distortion and the equirectangular mapping are
exact, and geometry never depends on the texture resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semloc_core.camera import EquirectangularCamera, PinholeCamera, pixel_grid
from semloc_core.geometry import invert_transform
from semloc_core.sim import _raycast
from semloc_core.sim.world import World

_EDGES = np.array([(a, b) for a in range(8) for b in range(8) if a < b and bin(a ^ b).count("1") == 1])
_PAIRS = np.array([(a, b) for a in range(8) for b in range(8) if a < b])
NEAR = 0.02  # metres: nothing closer than this to the camera centre is drawn


@dataclass(frozen=True)
class Lighting:
    """A directional light plus ambient; ``direction`` points from the scene towards the light (world frame)."""

    direction: tuple[float, float, float] = (0.35, 0.25, 0.9)

    def unit(self) -> np.ndarray:
        d = np.asarray(self.direction, float)
        return d / np.linalg.norm(d)


@dataclass(frozen=True, eq=False)
class RenderOutput:
    colour: np.ndarray  # (H, W, 3) float32 BGR, linear 0..255 before exposure
    depth: np.ndarray  # (H, W) float32 range along the ray, inf where nothing was hit
    ids: np.ndarray  # (H, W) int32 object id, -1 for background


@dataclass(frozen=True, eq=False)
class _CameraCache:
    rays: np.ndarray
    pixel_angle: float
    max_normalized: float
    projection: np.ndarray  # (fx, fy, cx, cy) of an undistorted pinhole, else empty


class Renderer:
    """Renders one world for any number of cameras; caches each camera's pixel rays."""

    def __init__(self, world: World, parallel: bool = False) -> None:
        """``parallel`` renders bands of rows on numba's threads (same bytes; faster on an idle multi-core
        machine, slower when the cores are shared, e.g. under pytest-xdist)."""
        self.world = world
        self.parallel = bool(parallel)
        self._cameras: dict[int, tuple[object, _CameraCache]] = {}
        a = world.atlas
        self._atlas = (a.texels, a.alpha, a.levels, a.n_levels)

    # ------------------------------------------------------------------ cameras

    def _camera(self, camera) -> _CameraCache:
        key = id(camera)
        cached = self._cameras.get(key)
        if cached is not None and cached[0] is camera:
            return cached[1]
        if not isinstance(camera, (PinholeCamera, EquirectangularCamera)):
            raise TypeError(f"render one camera model at a time (pinhole or equirectangular), got {type(camera)}")
        u, v = pixel_grid(camera)
        rays = np.ascontiguousarray(camera.rays_cam(u, v), dtype=np.float32)
        if isinstance(camera, PinholeCamera):
            pixel_angle = 1.0 / float(np.mean(np.diag(camera.K)[:2]))
            border = np.concatenate([rays[0], rays[-1], rays[:, 0], rays[:, -1]])
            max_normalized = float(np.max(np.abs(border[:, :2] / border[:, 2:3])))
        else:
            pixel_angle = 2.0 * np.pi / camera.width
            max_normalized = np.inf
        if isinstance(camera, PinholeCamera) and camera.dist.size == 0 and abs(camera.K[0, 1]) < 1e-12:
            projection = np.array([camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]])
        else:
            projection = np.zeros(0)
        cache = _CameraCache(rays, pixel_angle, max_normalized, projection)
        self._cameras[key] = (camera, cache)
        return cache

    # ------------------------------------------------------------------ culling

    def _rois_pinhole(self, camera: PinholeCamera, corners: np.ndarray, max_normalized: float):
        """Pixel boxes of the primitives' boxes clipped to the near plane; (P, 2, 4) and counts (P,)."""
        P = corners.shape[0]
        z = corners[..., 2]
        a = corners[:, _EDGES[:, 0]]
        b = corners[:, _EDGES[:, 1]]
        za, zb = a[..., 2], b[..., 2]
        crosses = (za - NEAR) * (zb - NEAR) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(crosses, (NEAR - za) / (zb - za), 0.0)
        cut = a + s[..., None] * (b - a)
        points = np.concatenate([corners, cut], axis=1)
        valid = np.concatenate([z >= NEAR, crosses], axis=1)
        if camera.dist.size:
            # Distortion bends straight edges: the outline's extremes may lie between the corners.
            f = np.linspace(0.0, 1.0, 9)[1:-1]
            along = a[:, :, None, :] + f[None, None, :, None] * (b - a)[:, :, None, :]
            along = along.reshape(P, -1, 3)
            points = np.concatenate([points, along], axis=1)
            valid = np.concatenate([valid, along[..., 2] >= NEAR], axis=1)
        safe_z = np.where(valid, points[..., 2], 1.0)
        normalized = points[..., :2] / safe_z[..., None]
        rois = np.zeros((P, 2, 4), np.int32)
        counts = np.zeros(P, np.int32)
        any_valid = valid.any(axis=1)
        full = np.zeros(P, bool)
        if camera.dist.size:
            too_wide = np.where(valid, np.abs(normalized).max(axis=-1) > 1.3 * max_normalized, False).any(axis=1)
            full |= too_wide & any_valid
            import cv2

            flat = np.concatenate([normalized.reshape(-1, 2), np.ones((P * normalized.shape[1], 1))], axis=1)
            uv, _ = cv2.projectPoints(flat, np.zeros(3), np.zeros(3), camera.K, camera.dist)
            uv = uv.reshape(P, -1, 2)
        else:
            uv = normalized * np.diag(camera.K)[:2] + camera.K[:2, 2]
        big = 1e9
        umin = np.where(valid, uv[..., 0], big).min(axis=1)
        umax = np.where(valid, uv[..., 0], -big).max(axis=1)
        vmin = np.where(valid, uv[..., 1], big).min(axis=1)
        vmax = np.where(valid, uv[..., 1], -big).max(axis=1)
        W, H = camera.width, camera.height
        u0 = np.clip(np.floor(umin) - 1, 0, W).astype(np.int64)
        u1 = np.clip(np.ceil(umax) + 2, 0, W).astype(np.int64)
        v0 = np.clip(np.floor(vmin) - 1, 0, H).astype(np.int64)
        v1 = np.clip(np.ceil(vmax) + 2, 0, H).astype(np.int64)
        u0[full], u1[full], v0[full], v1[full] = 0, W, 0, H
        visible = any_valid & (u1 > u0) & (v1 > v0)
        rois[:, 0] = np.stack([u0, u1, v0, v1], axis=1)
        counts[visible] = 1
        return rois, counts

    def _rois_equirect(self, camera: EquirectangularCamera, corners: np.ndarray):
        P = corners.shape[0]
        W, H = camera.width, camera.height
        x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
        up = -y
        horizontal = np.hypot(x, z)
        # Smallest horizontal distance from the panorama's vertical axis to the box (over all corner pairs, which
        # include the edges of the footprint's convex hull).
        pa = corners[:, _PAIRS[:, 0]][..., [0, 2]]
        pb = corners[:, _PAIRS[:, 1]][..., [0, 2]]
        d = pb - pa
        length2 = np.einsum("...i,...i->...", d, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.clip(np.where(length2 > 0, -np.einsum("...i,...i->...", pa, d) / length2, 0.0), 0, 1)
        closest = pa + s[..., None] * d
        d_min = np.minimum(np.linalg.norm(closest, axis=-1).min(axis=1), horizontal.min(axis=1))
        d_max = horizontal.max(axis=1)
        # Longitude arc: the complement of the largest gap between the corners' sorted longitudes. An arc wider
        # than a half turn means the footprint surrounds the vertical axis (distance 0, every longitude).
        lon = np.sort(np.arctan2(x, z), axis=1)
        gaps = np.diff(np.concatenate([lon, lon[:, :1] + 2 * np.pi], axis=1), axis=1)
        g = np.argmax(gaps, axis=1)
        arc = 2 * np.pi - gaps[np.arange(P), g]
        start = lon[np.arange(P), (g + 1) % 8]
        surrounds = arc > np.pi - 1e-3
        d_min = np.where(surrounds, 0.0, d_min)
        up_max, up_min = up.max(axis=1), up.min(axis=1)
        lat_hi = np.where(up_max >= 0, np.arctan2(up_max, np.maximum(d_min, 1e-9)), np.arctan2(up_max, d_max))
        lat_lo = np.where(up_min <= 0, np.arctan2(up_min, np.maximum(d_min, 1e-9)), np.arctan2(up_min, d_max))
        span = camera.lat_top - camera.lat_bottom
        v0 = np.clip(np.floor((camera.lat_top - lat_hi) / span * H - 0.5) - 1, 0, H).astype(np.int64)
        v1 = np.clip(np.ceil((camera.lat_top - lat_lo) / span * H - 0.5) + 2, 0, H).astype(np.int64)
        full = surrounds | (d_min < 1e-6)
        u_start = np.floor((start + np.pi) / (2 * np.pi) * W - 0.5).astype(np.int64) - 1
        u_end = np.ceil((start + arc + np.pi) / (2 * np.pi) * W - 0.5).astype(np.int64) + 2
        rois = np.zeros((P, 2, 4), np.int32)
        counts = np.zeros(P, np.int32)
        for p in np.flatnonzero(v1 > v0):
            if full[p] or u_end[p] - u_start[p] >= W:
                rois[p, 0] = (0, W, v0[p], v1[p])
                counts[p] = 1
                continue
            a0, a1 = u_start[p], u_end[p]
            if a0 < 0:
                rois[p, 0] = (0, a1, v0[p], v1[p])
                rois[p, 1] = (W + a0, W, v0[p], v1[p])
                counts[p] = 2
            elif a1 > W:
                rois[p, 0] = (a0, W, v0[p], v1[p])
                rois[p, 1] = (0, a1 - W, v0[p], v1[p])
                counts[p] = 2
            else:
                rois[p, 0] = (a0, a1, v0[p], v1[p])
                counts[p] = 1
        return rois, counts

    # ------------------------------------------------------------------ rendering

    def _frame_arrays(self, T_world_cam: np.ndarray, subset: np.ndarray | None):
        world = self.world
        T_cam_world = invert_transform(np.asarray(T_world_cam, float))
        R_cw, t_cw = T_cam_world[:3, :3], T_cam_world[:3, 3]
        index = np.arange(world.n_primitives) if subset is None else np.asarray(subset, np.int64)
        R_wl = world.R_world_local[index].copy()
        o_w = world.origin_world[index].copy()
        bill = world.billboard[index]
        if bill.any():
            # Billboards turn about world z so that their front faces the camera centre.
            centre = o_w[bill]
            cam = np.asarray(T_world_cam, float)[:3, 3]
            into = centre - cam
            into[:, 2] = 0.0
            norm = np.linalg.norm(into, axis=1, keepdims=True)
            into = np.where(norm > 1e-9, into / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0]))
            down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), into.shape)
            right = np.cross(down, into)
            R_b = np.stack([right, down, into], axis=2)
            size = world.shape[index][bill, :2]
            R_wl[bill] = R_b
            o_w[bill] = centre - right * size[:, :1] / 2 - down * size[:, 1:2] / 2
        R_cl = np.einsum("ij,pjk->pik", R_cw, R_wl)
        o_c = o_w @ R_cw.T + t_cw
        corners = world.bbox_world[index] @ R_cw.T + t_cw
        return index, R_wl, R_cl, o_c, corners

    def render(self, camera, T_world_cam: np.ndarray, lighting: Lighting | None = None, subset=None,
               colour: bool = True) -> RenderOutput:
        """Render the world (or the primitives ``subset``) seen by ``camera`` at pose ``T_world_cam``."""
        T_world_cam = np.asarray(T_world_cam, float)
        if T_world_cam.shape != (4, 4) or not np.all(np.isfinite(T_world_cam)):
            raise ValueError(f"T_world_cam must be a finite 4x4 matrix, got shape {T_world_cam.shape}")
        cache = self._camera(camera)
        world = self.world
        index, R_wl, R_cl, o_c, corners = self._frame_arrays(T_world_cam, subset)
        if isinstance(camera, PinholeCamera):
            rois, counts = self._rois_pinhole(camera, corners, cache.max_normalized)
        else:
            rois, counts = self._rois_equirect(camera, corners)
        # Front to back: later primitives fail the depth test early and skip texture sampling.
        centre_distance = np.linalg.norm(corners.mean(axis=1), axis=1)
        drawn = np.flatnonzero(counts > 0)
        order = drawn[np.argsort(centre_distance[drawn], kind="stable")].astype(np.int64)
        light = (lighting or Lighting()).unit()
        light_local = np.einsum("pji,j->pi", R_wl, light)
        H, W = camera.height, camera.width
        out_colour = np.zeros((H, W, 3) if colour else (1, 1, 3), np.float32)
        depth = np.full((H, W), np.inf, np.float32)
        ids = np.full((H, W), -1, np.int32)
        if order.size:
            texels, alpha, levels, n_levels = self._atlas
            kernel = _raycast.render_primitives_parallel if self.parallel and subset is None else \
                _raycast.render_primitives
            kernel(
                cache.rays, order, world.kind[index], world.flags[index], np.ascontiguousarray(R_cl),
                np.ascontiguousarray(o_c), np.ascontiguousarray(world.shape[index]), world.texture[index],
                np.ascontiguousarray(world.tex_scale[index]), np.ascontiguousarray(world.texel_density[index]),
                np.ascontiguousarray(light_local), np.ascontiguousarray(world.material[index]),
                world.object_id[index], rois, counts, texels, alpha, levels, n_levels, cache.pixel_angle, NEAR,
                colour, out_colour, depth, ids, cache.projection)
        return RenderOutput(out_colour, depth, ids)
