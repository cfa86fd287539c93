"""Numba kernel of the simulator's renderer: per-pixel ray casting of analytic primitives with a depth buffer.

Every primitive lives in its own orthonormal local frame (``R`` maps local axes to the camera frame, ``o`` is the
local origin in the camera frame). Rays are the camera model's unit rays through pixel centres, so one kernel
renders pinhole (with or without distortion), equirectangular and rig cameras alike: the camera model only decides
the ray of each pixel, never the geometry.

Shapes (``kind``), in local coordinates:

* QUAD: the rectangle ``0 <= x <= sx, 0 <= y <= sy`` of the plane ``z = 0``; texture column along x, row along y.
  Front side = seen from ``z < 0`` (local z points into the surface, like a camera looking at it).
* FRUSTUM: the side of a cone frustum around the z axis, radius ``r0`` at ``z = 0`` and ``r1`` at ``z = h``,
  azimuth limited to ``[phi0, phi1]``; texture column = azimuth (phi = 0 at the texture centre), row = down from
  the top. Both sides are drawn (the inside of a bowl, of a trash can).
* DISC: the annulus ``r_in <= r <= r_out`` of the plane ``z = 0``, azimuth in ``[phi0, phi1]``; texture spans the
  square ``[-r_out, r_out]^2`` (row along -y).
* DOME: the part ``z >= z_cut`` of the ellipsoid with semi-axes ``a, b, c``; column = azimuth, row = down from
  the top to ``z_cut``.

Texture sampling: bilinear inside one mip level chosen per pixel from the pixel's footprint on the surface (so
distant or grazing walls do not alias into noise that SIFT would pick up).
"""

from __future__ import annotations

import math

import numba
import numpy as np

QUAD = 0
FRUSTUM = 1
DISC = 2
DOME = 3

FLAG_TWO_SIDED = 1
FLAG_REPEAT = 2
FLAG_ALPHA = 4

_TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, inline="always")
def _sample(atlas, alpha_atlas, levels, tex, level, s, t, repeat, out):
    """Bilinear sample of texture ``tex`` at mip ``level``; writes BGR floats into ``out``, returns alpha (0..255)."""
    # Unsigned subscripts throughout the per-pixel code: numba adds a negative-index wrap-around to every signed
    # one (the indices are never negative). With the single modulo below, the exponent-based mip level and the
    # in-place quad hit in _render_rows: the kernel is 1.5-1.6x faster than without them, same bytes.
    entry = levels[np.uint64(tex), np.uint64(level)]
    offset = entry[0]
    height = entry[1]
    width = entry[2]
    x = s * width - 0.5
    y = t * height - 0.5
    x0f = math.floor(x)
    y0f = math.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = int(x0f)
    y0 = int(y0f)
    x1 = x0 + 1
    y1 = y0 + 1
    if repeat:
        # One modulo per axis (an integer division is the dearest step of a sample); x1 is x0's right neighbour.
        x0 %= width
        y0 %= height
        x1 = x0 + 1 if x0 + 1 < width else 0
        y1 = y0 + 1 if y0 + 1 < height else 0
    else:
        x0 = min(max(x0, 0), width - 1)
        x1 = min(max(x1, 0), width - 1)
        y0 = min(max(y0, 0), height - 1)
        y1 = min(max(y1, 0), height - 1)
    i00 = np.uint64(offset + y0 * width + x0)
    i01 = np.uint64(offset + y0 * width + x1)
    i10 = np.uint64(offset + y1 * width + x0)
    i11 = np.uint64(offset + y1 * width + x1)
    w00 = (1.0 - fx) * (1.0 - fy)
    w01 = fx * (1.0 - fy)
    w10 = (1.0 - fx) * fy
    w11 = fx * fy
    for c in range(np.uint64(3)):
        out[c] = (w00 * atlas[i00, c] + w01 * atlas[i01, c] + w10 * atlas[i10, c] + w11 * atlas[i11, c])
    return w00 * alpha_atlas[i00] + w01 * alpha_atlas[i01] + w10 * alpha_atlas[i10] + w11 * alpha_atlas[i11]


@numba.njit(cache=True, inline="always")
def _quad_hit(shape, ox, oy, dx, dy, dz, t, hit):
    """The QUAD case of ``_intersect`` once the plane's ray parameter ``t`` (> near) is known."""
    x = ox + t * dx
    y = oy + t * dy
    if x < 0.0 or x > shape[0] or y < 0.0 or y > shape[1]:
        return False
    hit[0] = t
    hit[1] = x / shape[0]
    hit[2] = y / shape[1]
    hit[3] = 0.0
    hit[4] = 0.0
    hit[5] = 1.0
    hit[6] = abs(dz)
    return True


@numba.njit(cache=True, inline="always")
def _intersect(kind, shape, ox, oy, oz, dx, dy, dz, near, hit):
    """Nearest valid intersection in local coordinates; fills hit = [t, s, tt, nx, ny, nz, cos_incidence].

    Returns False on a miss. ``(s, tt)`` are texture coordinates in [0, 1] before repetition; the normal is the
    geometric one (not yet turned towards the viewer).
    """
    if kind == QUAD:
        if abs(dz) < 1e-12:
            return False
        t = -oz / dz
        if t <= near:
            return False
        return _quad_hit(shape, ox, oy, dx, dy, dz, t, hit)
    if kind == DISC:
        if abs(dz) < 1e-12:
            return False
        t = -oz / dz
        if t <= near:
            return False
        x = ox + t * dx
        y = oy + t * dy
        r2 = x * x + y * y
        r_out = shape[0]
        r_in = shape[1]
        if r2 > r_out * r_out or r2 < r_in * r_in:
            return False
        phi = math.atan2(y, x)
        if phi < shape[2] or phi > shape[3]:
            return False
        hit[0] = t
        hit[1] = (x + r_out) / (2.0 * r_out)
        hit[2] = (r_out - y) / (2.0 * r_out)
        hit[3] = 0.0
        hit[4] = 0.0
        hit[5] = 1.0
        hit[6] = abs(dz)
        return True
    if kind == FRUSTUM:
        r0 = shape[0]
        h = shape[2]
        k = (shape[1] - r0) / h
        rz = r0 + k * oz
        a = dx * dx + dy * dy - k * k * dz * dz
        b = 2.0 * (ox * dx + oy * dy - k * rz * dz)
        c = ox * ox + oy * oy - rz * rz
        if abs(a) < 1e-14:
            if abs(b) < 1e-14:
                return False
            roots0 = -c / b
            roots1 = roots0
        else:
            disc = b * b - 4.0 * a * c
            if disc < 0.0:
                return False
            sq = math.sqrt(disc)
            q = -0.5 * (b + sq) if b >= 0.0 else -0.5 * (b - sq)
            roots0 = q / a
            roots1 = c / q if q != 0.0 else roots0
            if roots1 < roots0:
                roots0, roots1 = roots1, roots0
        for j in range(2):
            t = roots0 if j == 0 else roots1
            if t <= near:
                continue
            z = oz + t * dz
            if z < 0.0 or z > h:
                continue
            r = r0 + k * z
            if r < 0.0:
                continue
            x = ox + t * dx
            y = oy + t * dy
            phi = math.atan2(y, x)
            if phi < shape[3] or phi > shape[4]:
                continue
            nx = x
            ny = y
            nz = -k * r
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            if norm < 1e-15:
                continue
            nx /= norm
            ny /= norm
            nz /= norm
            hit[0] = t
            hit[1] = (phi + math.pi) / _TWO_PI
            hit[2] = (h - z) / h
            hit[3] = nx
            hit[4] = ny
            hit[5] = nz
            hit[6] = abs(nx * dx + ny * dy + nz * dz)
            return True
        return False
    if kind == DOME:
        sa = shape[0]
        sb = shape[1]
        sc = shape[2]
        z_cut = shape[3]
        px = ox / sa
        py = oy / sb
        pz = oz / sc
        qx = dx / sa
        qy = dy / sb
        qz = dz / sc
        a = qx * qx + qy * qy + qz * qz
        b = 2.0 * (px * qx + py * qy + pz * qz)
        c = px * px + py * py + pz * pz - 1.0
        disc = b * b - 4.0 * a * c
        if disc < 0.0:
            return False
        sq = math.sqrt(disc)
        for j in range(2):
            t = (-b - sq) / (2.0 * a) if j == 0 else (-b + sq) / (2.0 * a)
            if t <= near:
                continue
            z = oz + t * dz
            if z < z_cut:
                continue
            x = ox + t * dx
            y = oy + t * dy
            nx = x / (sa * sa)
            ny = y / (sb * sb)
            nz = z / (sc * sc)
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx /= norm
            ny /= norm
            nz /= norm
            hit[0] = t
            hit[1] = (math.atan2(y, x) + math.pi) / _TWO_PI
            hit[2] = (sc - z) / (sc - z_cut)
            hit[3] = nx
            hit[4] = ny
            hit[5] = nz
            hit[6] = abs(nx * dx + ny * dy + nz * dz)
            return True
        return False
    return False


@numba.njit(cache=True)
def _quad_polygon(R, origin, p, sx, sy, proj, poly) -> int:
    """The quad's outline clipped to z > 0 and projected with an undistorted pinhole (fx, fy, cx, cy): writes up to
    8 pixel vertices into ``poly`` and returns their count (0 when the quad is behind the camera)."""
    corners = np.empty((4, 3))
    for c in range(4):
        x = sx if c == 1 or c == 2 else 0.0
        y = sy if c >= 2 else 0.0
        for a in range(3):
            corners[c, a] = origin[p, a] + R[p, a, 0] * x + R[p, a, 1] * y
    z_min = 1e-6
    count = 0
    for c in range(4):
        a = corners[c]
        b = corners[(c + 1) % 4]
        a_in = a[2] >= z_min
        b_in = b[2] >= z_min
        if a_in:
            poly[count, 0] = proj[0] * a[0] / a[2] + proj[2]
            poly[count, 1] = proj[1] * a[1] / a[2] + proj[3]
            count += 1
        if a_in != b_in:
            f = (z_min - a[2]) / (b[2] - a[2])
            x = a[0] + f * (b[0] - a[0])
            y = a[1] + f * (b[1] - a[1])
            poly[count, 0] = proj[0] * x / z_min + proj[2]
            poly[count, 1] = proj[1] * y / z_min + proj[3]
            count += 1
    return count


@numba.njit(cache=True, inline="always")
def _row_span(poly, count, v):
    """Columns where the row through pixel centres ``v`` crosses the convex polygon: (x_min, x_max), empty if
    x_min > x_max."""
    x_min = 1e300
    x_max = -1e300
    for e in range(count):
        x0 = poly[e, 0]
        y0 = poly[e, 1]
        x1 = poly[(e + 1) % count, 0]
        y1 = poly[(e + 1) % count, 1]
        if (v < y0 and v < y1) or (v > y0 and v > y1):
            continue
        if y1 == y0:
            lo = min(x0, x1)
            hi = max(x0, x1)
        else:
            x = x0 + (v - y0) * (x1 - x0) / (y1 - y0)
            lo = x
            hi = x
        x_min = min(x_min, lo)
        x_max = max(x_max, hi)
    return x_min, x_max


@numba.njit(cache=True)
def _render_rows(rays, order, kind, flags, R, origin, shape, tex, tex_scale, texel_density, light, material,
                object_id, rois, n_rois, atlas, alpha_atlas, levels, n_levels, pixel_angle, near, shade_colour,
                colour, depth, ids, proj, band_v0, band_v1):
    """Draw primitives ``order`` into rows [band_v0, band_v1) of the buffers with a depth test.

    rays (H, W, 3) float32 camera-frame unit rays; R (P, 3, 3) local->camera rotations; origin (P, 3) local origins
    in the camera frame; light (P, 3) unit direction towards the light, in each primitive's local frame;
    material (P, 3) = ambient, diffuse, back-side factor; rois (P, 2, 4) pixel boxes [u0, u1, v0, v1] (end
    exclusive), n_rois (P,) how many are used. With ``shade_colour`` False only depth and ids are written.
    ``proj`` = (fx, fy, cx, cy) of an undistorted pinhole: each quad is then scanned only over its outline's span
    on each row (its exact test still decides); empty for other camera models.
    """
    hit = np.empty(7)
    poly = np.empty((8, 2))
    spans = proj.shape[0] == 4
    sample = np.empty(3)
    for oi in range(order.shape[0]):
        p = order[oi]
        k = kind[p]
        two_sided = (flags[p] & FLAG_TWO_SIDED) != 0
        repeat = (flags[p] & FLAG_REPEAT) != 0
        has_alpha = (flags[p] & FLAG_ALPHA) != 0
        r00 = R[p, 0, 0]
        r01 = R[p, 0, 1]
        r02 = R[p, 0, 2]
        r10 = R[p, 1, 0]
        r11 = R[p, 1, 1]
        r12 = R[p, 1, 2]
        r20 = R[p, 2, 0]
        r21 = R[p, 2, 1]
        r22 = R[p, 2, 2]
        # Ray origin (the camera centre) in local coordinates: -R^T o.
        ox = -(r00 * origin[p, 0] + r10 * origin[p, 1] + r20 * origin[p, 2])
        oy = -(r01 * origin[p, 0] + r11 * origin[p, 1] + r21 * origin[p, 2])
        oz = -(r02 * origin[p, 0] + r12 * origin[p, 1] + r22 * origin[p, 2])
        lx = light[p, 0]
        ly = light[p, 1]
        lz = light[p, 2]
        ambient = material[p, 0]
        diffuse = material[p, 1]
        back = material[p, 2]
        ti = tex[p]
        nl = n_levels[ti]
        density = texel_density[p]
        scale_s = tex_scale[p, 0]
        scale_t = tex_scale[p, 1]
        oid = object_id[p]
        planar = k == QUAD or k == DISC
        single_sided = k == QUAD and not two_sided
        shp = shape[p]
        n_poly = -1
        if spans and k == QUAD:
            n_poly = _quad_polygon(R, origin, p, shp[0], shp[1], proj, poly)
            if n_poly < 3:
                continue
        for ri in range(n_rois[p]):
            v0 = max(rois[p, ri, 2], band_v0)
            v1 = min(rois[p, ri, 3], band_v1)
            for row in range(v0, v1):
                u0 = rois[p, ri, 0]
                u1 = rois[p, ri, 1]
                if n_poly > 0:
                    x_min, x_max = _row_span(poly, n_poly, float(row))
                    if x_min > x_max:
                        continue
                    u0 = max(u0, int(math.floor(x_min)) - 1)
                    u1 = min(u1, int(math.ceil(x_max)) + 2)
                v = np.uint64(row)  # rois and bands are clipped to the image: never negative
                for u in range(np.uint64(u0), np.uint64(max(u0, u1))):
                    cx = rays[v, u, 0]
                    cy = rays[v, u, 1]
                    cz = rays[v, u, 2]
                    dz = r02 * cx + r12 * cy + r22 * cz
                    if planar:
                        # Planes first test the depth (cheap), then the outline: hidden pixels cost little.
                        if (single_sided and dz <= 0.0) or abs(dz) < 1e-12:
                            continue
                        t = -oz / dz
                        if t <= near or t >= depth[v, u]:
                            continue
                    dx = r00 * cx + r10 * cy + r20 * cz
                    dy = r01 * cx + r11 * cy + r21 * cz
                    if k == QUAD:
                        # t and its tests are done above: no second division.
                        if not _quad_hit(shp, ox, oy, dx, dy, dz, t, hit):
                            continue
                    else:
                        if not _intersect(k, shp, ox, oy, oz, dx, dy, dz, near, hit):
                            continue
                        t = hit[0]
                        if t >= depth[v, u]:
                            continue
                    s = hit[1] * scale_s
                    tt = hit[2] * scale_t
                    if not shade_colour and not has_alpha:
                        depth[v, u] = t
                        ids[v, u] = oid
                        continue
                    # Mip level from the pixel's footprint on the surface (texels covered by one pixel).
                    footprint = t * pixel_angle / max(hit[6], 0.15) * density
                    level = 0
                    if footprint > 1.0:
                        # floor(log2(footprint)) from the exponent, without a log per pixel; just below a power
                        # of two log2 may round up, so there the log decides (the same level as always).
                        mantissa, exponent = math.frexp(footprint)
                        level = exponent - 1 if mantissa <= 0.99999 else int(math.log2(footprint))
                        level = min(level, nl - 1)
                    a = _sample(atlas, alpha_atlas, levels, ti, level, s, tt, repeat, sample)
                    if has_alpha and a < 128.0:
                        continue
                    depth[v, u] = t
                    ids[v, u] = oid
                    if not shade_colour:
                        continue
                    nx = hit[3]
                    ny = hit[4]
                    nz = hit[5]
                    facing = nx * dx + ny * dy + nz * dz
                    factor = 1.0
                    if facing > 0.0:
                        # The ray meets the surface's back: shade with the normal turned to the viewer.
                        nx = -nx
                        ny = -ny
                        nz = -nz
                        if k != QUAD:
                            factor = back
                    lambert = nx * lx + ny * ly + nz * lz
                    if lambert < 0.0:
                        lambert = 0.0
                    gain = (ambient + diffuse * lambert) * factor
                    colour[v, u, 0] = sample[0] * gain
                    colour[v, u, 1] = sample[1] * gain
                    colour[v, u, 2] = sample[2] * gain


@numba.njit(cache=True)
def render_primitives(rays, order, kind, flags, R, origin, shape, tex, tex_scale, texel_density, light, material,
                      object_id, rois, n_rois, atlas, alpha_atlas, levels, n_levels, pixel_angle, near,
                      shade_colour, colour, depth, ids, proj):
    """Draw primitives ``order`` into the whole image, on one thread (see ``_render_rows``)."""
    _render_rows(rays, order, kind, flags, R, origin, shape, tex, tex_scale, texel_density, light, material,
                 object_id, rois, n_rois, atlas, alpha_atlas, levels, n_levels, pixel_angle, near, shade_colour,
                 colour, depth, ids, proj, 0, rays.shape[0])


@numba.njit(cache=True, parallel=True)
def render_primitives_parallel(rays, order, kind, flags, R, origin, shape, tex, tex_scale, texel_density, light,
                               material, object_id, rois, n_rois, atlas, alpha_atlas, levels, n_levels, pixel_angle,
                               near, shade_colour, colour, depth, ids, proj):
    """Same as ``render_primitives`` with bands of rows on parallel threads. Every pixel is written by one thread
    in primitive order, so the result is identical to the serial kernel's."""
    height = rays.shape[0]
    band_rows = 16
    n_bands = (height + band_rows - 1) // band_rows
    for band in numba.prange(n_bands):
        v0 = band * band_rows
        v1 = min(height, v0 + band_rows)
        _render_rows(rays, order, kind, flags, R, origin, shape, tex, tex_scale, texel_density, light, material,
                     object_id, rois, n_rois, atlas, alpha_atlas, levels, n_levels, pixel_angle, near, shade_colour,
                     colour, depth, ids, proj, v0, v1)
