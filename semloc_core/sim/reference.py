"""A slow, independent numpy ray caster of the same worlds: the reference for tests and benchmarks.

Every primitive is intersected with every pixel's ray (no culling), vectorised over pixels; the nearest hit wins.
Colours are the level-0 texel nearest to the hit (no mip-mapping, no shading), so only ``depth`` and ``ids`` are
meant to agree with :class:`~semloc_core.sim.renderer.Renderer`; the colour is there so the benchmark compares like
work (a full frame with texture lookups).
"""

from __future__ import annotations

import numpy as np

from semloc_core.camera import pixel_grid
from semloc_core.sim import _raycast
from semloc_core.sim.renderer import NEAR, RenderOutput
from semloc_core.sim.world import World


def _billboard_frames(world: World, T_world_cam: np.ndarray):
    R = world.R_world_local.copy()
    o = world.origin_world.copy()
    bill = world.billboard
    if bill.any():
        centre = o[bill]
        into = centre - T_world_cam[:3, 3]
        into[:, 2] = 0
        into /= np.linalg.norm(into, axis=1, keepdims=True)
        down = np.broadcast_to([0.0, 0.0, -1.0], into.shape)
        right = np.cross(down, into)
        R[bill] = np.stack([right, down, into], axis=2)
        size = world.shape[bill, :2]
        o[bill] = centre - right * size[:, :1] / 2 - down * size[:, 1:2] / 2
    return R, o


def render_reference(world: World, camera, T_world_cam) -> RenderOutput:
    T_world_cam = np.asarray(T_world_cam, float)
    u, v = pixel_grid(camera)
    rays_cam = camera.rays_cam(u, v).reshape(-1, 3)
    rays = rays_cam @ T_world_cam[:3, :3].T  # world directions
    eye = T_world_cam[:3, 3]
    n = rays.shape[0]
    depth = np.full(n, np.inf)
    ids = np.full(n, -1, np.int32)
    colour = np.zeros((n, 3), np.float32)
    R_all, o_all = _billboard_frames(world, T_world_cam)
    atlas = world.atlas
    for p in range(world.n_primitives):
        R, o = R_all[p], o_all[p]
        d = rays @ R  # local directions
        oc = (eye - o) @ R  # camera centre in local coordinates
        kind = world.kind[p]
        shape = world.shape[p]
        t = np.full(n, np.inf)
        s_tex = np.zeros(n)
        t_tex = np.zeros(n)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if kind in (_raycast.QUAD, _raycast.DISC):
                tt = -oc[2] / d[:, 2]
                x = oc[0] + tt * d[:, 0]
                y = oc[1] + tt * d[:, 1]
                if kind == _raycast.QUAD:
                    ok = (x >= 0) & (x <= shape[0]) & (y >= 0) & (y <= shape[1])
                    if not world.flags[p] & _raycast.FLAG_TWO_SIDED:
                        ok &= d[:, 2] > 0
                    s_tex, t_tex = x / shape[0], y / shape[1]
                else:
                    r2 = x * x + y * y
                    phi = np.arctan2(y, x)
                    ok = (r2 <= shape[0] ** 2) & (r2 >= shape[1] ** 2) & (phi >= shape[2]) & (phi <= shape[3])
                    s_tex, t_tex = (x + shape[0]) / (2 * shape[0]), (shape[0] - y) / (2 * shape[0])
                ok &= np.isfinite(tt) & (tt > NEAR)
                t = np.where(ok, tt, np.inf)
            elif kind == _raycast.FRUSTUM:
                r0, r1, h, phi0, phi1 = shape[:5]
                k = (r1 - r0) / h
                rz = r0 + k * oc[2]
                a = d[:, 0] ** 2 + d[:, 1] ** 2 - k * k * d[:, 2] ** 2
                b = 2 * (oc[0] * d[:, 0] + oc[1] * d[:, 1] - k * rz * d[:, 2])
                c = oc[0] ** 2 + oc[1] ** 2 - rz ** 2
                disc = b * b - 4 * a * c
                sq = np.sqrt(np.maximum(disc, 0))
                for sign in (1.0, -1.0):  # the nearer root last so it overrides
                    root = (-b + sign * sq) / (2 * a)
                    z = oc[2] + root * d[:, 2]
                    x = oc[0] + root * d[:, 0]
                    y = oc[1] + root * d[:, 1]
                    phi = np.arctan2(y, x)
                    ok = (disc >= 0) & (root > NEAR) & (z >= 0) & (z <= h) & (r0 + k * z >= 0) & (phi >= phi0) & (
                        phi <= phi1)
                    better = ok & (root < t)
                    t = np.where(better, root, t)
                    s_tex = np.where(better, (phi + np.pi) / (2 * np.pi), s_tex)
                    t_tex = np.where(better, (h - z) / h, t_tex)
            elif kind == _raycast.DOME:
                sa, sb, sc, z_cut = shape[:4]
                scale = np.array([sa, sb, sc])
                po = oc / scale
                q = d / scale
                a = np.einsum("ij,ij->i", q, q)
                b = 2 * q @ po
                c = po @ po - 1
                disc = b * b - 4 * a * c
                sq = np.sqrt(np.maximum(disc, 0))
                for sign in (1.0, -1.0):
                    root = (-b + sign * sq) / (2 * a)
                    z = oc[2] + root * d[:, 2]
                    x = oc[0] + root * d[:, 0]
                    y = oc[1] + root * d[:, 1]
                    ok = (disc >= 0) & (root > NEAR) & (z >= z_cut)
                    better = ok & (root < t)
                    t = np.where(better, root, t)
                    s_tex = np.where(better, (np.arctan2(y, x) + np.pi) / (2 * np.pi), s_tex)
                    t_tex = np.where(better, (sc - z) / (sc - z_cut), t_tex)
        hit = t < depth
        if not hit.any():
            continue
        offset, height, width = atlas.levels[world.texture[p], 0]
        scale_s, scale_t = world.tex_scale[p]
        col = np.floor(s_tex[hit] * scale_s * width).astype(np.int64)
        row = np.floor(t_tex[hit] * scale_t * height).astype(np.int64)
        if world.flags[p] & _raycast.FLAG_REPEAT:
            col %= width
            row %= height
        col = np.clip(col, 0, width - 1)
        row = np.clip(row, 0, height - 1)
        index = offset + row * width + col
        if world.flags[p] & _raycast.FLAG_ALPHA:
            opaque = atlas.alpha[index] >= 128
            sel = np.flatnonzero(hit)
            hit = np.zeros(n, bool)
            hit[sel[opaque]] = True
            index = index[opaque]
        depth[hit] = t[hit]
        ids[hit] = world.object_id[p]
        colour[hit] = atlas.texels[index]
    shape2 = (camera.height, camera.width)
    return RenderOutput(colour.reshape(shape2 + (3,)), depth.reshape(shape2).astype(np.float32), ids.reshape(shape2))
