"""Camera and robot trajectories: hand-held orbits and smooth robot paths (real hand-held trajectories are placed
in a world by ``semloc_core.io.trajectory.level_real_trajectory``).

All functions are deterministic given their ``numpy.random.Generator``. Poses are 4x4 ``T_world_x`` stacks (N, 4, 4).
"""

from __future__ import annotations

import numpy as np

from semloc_core.geometry import look_at, make_transform, rotation_about_z


def smooth_noise(rng: np.random.Generator, t: np.ndarray, period: float, amplitude: float, terms: int = 3):
    """A smooth random signal: a sum of sinusoids with random phases near ``period`` (seconds or metres)."""
    out = np.zeros_like(t, dtype=float)
    for k in range(terms):
        p = period * rng.uniform(0.6, 1.6) / (k + 1)
        out += amplitude / (k + 1) * np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi))
    return out


def orbit_trajectory(rng: np.random.Generator, frames: int, fps: float, centre, surface_z: float,
                     radius: float = 1.15, height_above: float = 0.45, speed: float = 0.3) -> np.ndarray:
    """A hand-held camera walking around a table and looking at it, like the RGB-D Scenes recordings.

    The walker's angular speed varies and sometimes stalls; distance, height and gaze wander smoothly; a small roll
    and high-frequency shake are added (what a hand holds).
    """
    t = np.arange(frames) / fps
    omega = speed / radius
    phase0 = rng.uniform(-np.pi, np.pi)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    angle = phase0 + direction * (omega * t + smooth_noise(rng, t, 9.0, 0.35))
    r = radius + smooth_noise(rng, t, 7.0, 0.18)
    z = surface_z + height_above + smooth_noise(rng, t, 5.0, 0.06)
    centre = np.asarray(centre, float)
    gaze = np.stack([centre[0] + smooth_noise(rng, t, 6.0, 0.18), centre[1] + smooth_noise(rng, t, 6.0, 0.18),
                     np.full_like(t, surface_z + 0.05)], axis=1)
    roll = np.radians(smooth_noise(rng, t, 4.0, 1.5) + smooth_noise(rng, t, 0.6, 0.3))
    shake = smooth_noise(rng, t, 0.5, 0.004)
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        eye = (centre[0] + r[i] * np.cos(angle[i]), centre[1] + r[i] * np.sin(angle[i]), z[i] + shake[i])
        poses[i] = look_at(eye, gaze[i], roll[i])
    return poses


def resample_polyline(points: np.ndarray, spacing: float, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` metres along a polyline (N, 2) and the tangent heading at each."""
    points = np.asarray(points, float)
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg, axis=1)
    keep = np.concatenate([[True], length > 1e-9])
    points = points[keep]
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg, axis=1)
    cumulative = np.concatenate([[0.0], np.cumsum(length)])
    total = cumulative[-1]
    n = int(np.floor(total / spacing)) + 1 if count is None else count
    s = np.arange(n) * spacing
    if s[-1] > total + 1e-9:
        raise ValueError(f"path of {total:.1f} m is too short for {n} samples every {spacing} m")
    x = np.interp(s, cumulative, points[:, 0])
    y = np.interp(s, cumulative, points[:, 1])
    idx = np.clip(np.searchsorted(cumulative, s, side="right") - 1, 0, len(seg) - 1)
    heading = np.arctan2(seg[idx, 1], seg[idx, 0])
    return np.stack([x, y], axis=1), heading


def round_corners(waypoints: np.ndarray, radius: float, step: float = 0.1) -> np.ndarray:
    """A dense polyline through waypoints with circular fillets of ``radius`` at each corner."""
    wp = np.asarray(waypoints, float)
    out = [wp[0]]
    for k in range(1, len(wp) - 1):
        a, b, c = wp[k - 1], wp[k], wp[k + 1]
        d0 = b - a
        d1 = c - b
        l0, l1 = np.linalg.norm(d0), np.linalg.norm(d1)
        if l0 < 1e-9 or l1 < 1e-9:
            continue
        u0, u1 = d0 / l0, d1 / l1
        turn = np.arctan2(u0[0] * u1[1] - u0[1] * u1[0], np.dot(u0, u1))
        if abs(turn) < 1e-3:
            out.append(b)
            continue
        if abs(abs(turn) - np.pi) < 1e-3:
            # A U-turn: a semicircle to the left.
            normal = np.array([-u0[1], u0[0]])
            r = min(radius, 0.45 * l0, 0.45 * l1, 1.0)
            centre = b + normal * r
            start = np.arctan2(-normal[1], -normal[0])
            angles = start + np.linspace(0, np.pi, 16)
            out.extend(centre + r * np.stack([np.cos(angles), np.sin(angles)], axis=1))
            continue
        r = min(radius, 0.45 * min(l0, l1) / max(np.tan(abs(turn) / 2), 1e-6))
        tangent = r * np.tan(abs(turn) / 2)
        p0 = b - u0 * tangent
        normal = np.array([-u0[1], u0[0]]) * np.sign(turn)
        centre = p0 + normal * r
        start = np.arctan2(p0[1] - centre[1], p0[0] - centre[0])
        n = max(2, int(abs(turn) * r / step) + 2)
        angles = start + np.linspace(0, turn, n)
        out.extend(centre + r * np.stack([np.cos(angles), np.sin(angles)], axis=1))
    out.append(wp[-1])
    return np.asarray(out)


def robot_poses(xy: np.ndarray, heading: np.ndarray, rng: np.random.Generator | None = None,
                yaw_jitter_deg: float = 0.0, lateral_jitter: float = 0.0) -> np.ndarray:
    """T_world_body (N, 4, 4) of a ground robot (body on the floor) along sampled points, with optional wander."""
    n = len(xy)
    xy = np.asarray(xy, float).copy()
    heading = np.asarray(heading, float).copy()
    if rng is not None and (yaw_jitter_deg or lateral_jitter):
        s = np.arange(n, dtype=float)
        lateral = smooth_noise(rng, s, 40.0, lateral_jitter)
        xy += lateral[:, None] * np.stack([-np.sin(heading), np.cos(heading)], axis=1)
        heading = heading + np.radians(smooth_noise(rng, s, 12.0, yaw_jitter_deg))
    poses = np.empty((n, 4, 4))
    for i in range(n):
        poses[i] = make_transform(rotation_about_z(heading[i]), (xy[i, 0], xy[i, 1], 0.0))
    return poses
