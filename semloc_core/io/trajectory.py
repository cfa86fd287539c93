"""Trajectory files: TUM (``t x y z qx qy qz qw``) and RGB-D Scenes v2 pose files (``qw qx qy qz x y z``).

TUM files store a pose per stamp: timestamp in seconds, translation, quaternion x, y, z, w (readable by evo). A
camera trajectory is ``T_world_cam``; a planar body pose (the localizer's, ``planar_tum_line``,
``write_planar_tum``) is ``(x, y, 0)`` with a rotation about z (docs/conventions.md, "Files and their frames").

RGB-D Scenes v2 ``NN.pose`` files (Lai et al. 2014) store, one line per frame, the Kinect's pose in the first
frame's coordinates as quaternion (w, x, y, z) then translation; they carry no time (the Kinect ran at 30 Hz).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from semloc_core.geometry import pose2d_to_transform, quaternion_to_rotation, rotation_to_quaternion
from semloc_core.io.atomic import replace_text


class TrajectoryFormatError(ValueError):
    """A trajectory file that cannot be read."""


def _load_rows(path: Path, columns: int, on_cut: Callable[[str], None] | None = None) -> np.ndarray:
    """The rows of numbers of a trajectory file. With ``on_cut``, a file whose writer was cut off (killed, or the
    power cut) is read up to its last line end: a last line without one may have lost digits and still parse, so it
    is dropped whatever it holds, and ``on_cut`` says so once."""
    path = Path(path)
    rows = []
    try:
        text = path.read_text(errors="replace")
    except OSError as error:
        raise TrajectoryFormatError(f"cannot read trajectory {path}: {error}") from None
    lines = text.splitlines()
    if on_cut is not None and lines and not text.endswith(("\n", "\r")):
        on_cut(f"{path} was cut short: its last line ({len(lines)}) has no line end, {lines[-1][:40]!r}: dropped, "
               f"read the lines before it")
        lines.pop()
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != columns:
            raise TrajectoryFormatError(f"{path}:{number}: expected {columns} numbers, got {len(fields)}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            raise TrajectoryFormatError(f"{path}:{number}: not a number in {line!r}") from None
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses")
    data = np.asarray(rows)
    if not np.all(np.isfinite(data)):
        raise TrajectoryFormatError(f"{path}: non-finite values")
    return data


def _poses(quaternion_xyzw: np.ndarray, translation: np.ndarray, path) -> np.ndarray:
    norms = np.linalg.norm(quaternion_xyzw, axis=1)
    if np.any(norms < 1e-6):
        raise TrajectoryFormatError(f"{path}: zero quaternion")
    R = quaternion_to_rotation(quaternion_xyzw)
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = translation
    return T


def read_tum(path, on_cut: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (s, float64) and poses (N, 4, 4) from a TUM file; ``on_cut``: a file whose writer may have been
    cut off (the saver's, a power cut) is read up to its last line end and ``on_cut`` says so (``_load_rows``)."""
    data = _load_rows(path, 8, on_cut)
    return data[:, 0], _poses(data[:, 4:8], data[:, 1:4], path)


TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


def tum_line(stamp, T) -> str:
    """One TUM line of the pose ``T`` (4, 4): an integer ``stamp`` is nanoseconds (written exactly, as seconds with
    nine decimals), a float one seconds."""
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"a TUM pose is a finite (4, 4) transform, got {T.shape}")
    if isinstance(stamp, (int, np.integer)):
        sign, magnitude = ("-" if stamp < 0 else ""), abs(int(stamp))
        time = f"{sign}{magnitude // 1_000_000_000}.{magnitude % 1_000_000_000:09d}"
    else:
        time = f"{float(stamp):.9f}"
    q = rotation_to_quaternion(T[:3, :3])
    return f"{time} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"


def planar_tum_line(stamp, x: float, y: float, theta: float) -> str:
    """The TUM line of a planar pose of the body (docs/conventions.md): z = 0, a rotation about z only."""
    return tum_line(stamp, pose2d_to_transform(x, y, theta))


def write_tum(path, stamps_s, poses: np.ndarray) -> None:
    """Write poses (N, 4, 4) with timestamps in seconds (or integer nanoseconds) as a TUM file (atomically)."""
    path = Path(path)
    stamps = np.asarray(stamps_s)
    stamps = stamps.astype(np.int64) if np.issubdtype(stamps.dtype, np.integer) else stamps.astype(float)
    lines = [TUM_HEADER] + [tum_line(t, T) for t, T in zip(stamps.tolist(), np.asarray(poses, float))]
    replace_text(path, "\n".join(lines) + "\n")


def write_planar_tum(path, stamps, poses2d) -> None:
    """Write planar body poses (N, 3) = (x, y, theta) as a TUM file (z = 0, yaw only), atomically."""
    poses2d = np.asarray(poses2d, float).reshape(-1, 3)
    write_tum(path, stamps, np.stack([pose2d_to_transform(*p) for p in poses2d]) if len(poses2d)
              else np.zeros((0, 4, 4)))


def read_rgbd_scenes_poses(path) -> np.ndarray:
    """Poses (N, 4, 4) T_first_cam from an RGB-D Scenes v2 ``.pose`` file (quaternion w x y z, translation)."""
    data = _load_rows(path, 7)
    return _poses(data[:, [1, 2, 3, 0]], data[:, 4:7], path)


def read_trajectory(path) -> tuple[np.ndarray | None, np.ndarray]:
    """Read a TUM file (8 columns) or an RGB-D Scenes pose file (7 columns); stamps are None for the latter."""
    path = Path(path)
    data = None
    try:
        first = next(line for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))
    except StopIteration:
        raise TrajectoryFormatError(f"{path}: no poses") from None
    except OSError as error:
        raise TrajectoryFormatError(f"cannot read trajectory {path}: {error}") from None
    columns = len(first.replace(",", " ").split())
    if columns == 8:
        stamps, poses = read_tum(path)
        return stamps, poses
    if columns == 7:
        return data, read_rgbd_scenes_poses(path)
    raise TrajectoryFormatError(f"{path}: {columns} columns; expected 8 (TUM) or 7 (RGB-D Scenes .pose)")


# ----------------------------------------------------------------------------------------------- hand-held trajectories

def gravity_from_camera_poses(T_ref_cam: np.ndarray) -> np.ndarray:
    """Unit 'up' direction in the reference frame of a hand-held camera trajectory.

    A hand-held camera is held with little roll, so its x axis (OpenCV: right) stays nearly horizontal: up is the
    direction most orthogonal to all x axes (smallest eigenvector of sum x x^T); its sign makes the cameras' y
    axes (down) point mostly against it. On the RGB-D Scenes v2 trajectories this agrees within 1-6 degrees with
    the normal of the plane the camera centres move in.
    """
    x_axes = np.asarray(T_ref_cam, float)[:, :3, 0]
    _, vectors = np.linalg.eigh(x_axes.T @ x_axes)
    up = vectors[:, 0]
    if np.mean(np.asarray(T_ref_cam)[:, :3, 1] @ up) > 0:
        up = -up
    return up / np.linalg.norm(up)


def gaze_centre(T_ref_cam: np.ndarray) -> np.ndarray:
    """Least-squares point closest to every optical axis: where the camera keeps looking (the table's middle)."""
    T_ref_cam = np.asarray(T_ref_cam, float)
    z = T_ref_cam[:, :3, 2]
    c = T_ref_cam[:, :3, 3]
    P = np.eye(3)[None] - z[:, :, None] * z[:, None, :]
    A = P.sum(axis=0)
    b = np.einsum("nij,nj->i", P, c)
    return np.linalg.solve(A, b)


def level_real_trajectory(T_ref_cam: np.ndarray, surface_z: float = 0.75, surface_below_gaze: float = 0.05):
    """Place a hand-held trajectory recorded around a table in a z-up world.

    Returns ``(T_world_cam, table)``. The world has z up (from :func:`gravity_from_camera_poses`), the table
    surface at ``surface_z`` (``surface_below_gaze`` below the point the camera keeps looking at), that point
    above the origin, and x along the first camera's horizontal heading. ``table`` holds ``centre`` (x, y) and
    ``half_extent`` (2,) along ``axes`` (2x2, columns) of the area the optical axes meet on the surface, and
    ``surface_z``.
    """
    T_ref_cam = np.asarray(T_ref_cam, float)
    if T_ref_cam.ndim != 3 or T_ref_cam.shape[1:] != (4, 4) or len(T_ref_cam) < 3:
        raise ValueError(f"need at least 3 poses of shape (4, 4), got {T_ref_cam.shape}")
    up = gravity_from_camera_poses(T_ref_cam)
    target = gaze_centre(T_ref_cam)
    forward = T_ref_cam[0, :3, 2] - np.dot(T_ref_cam[0, :3, 2], up) * up
    if np.linalg.norm(forward) < 1e-6:
        forward = T_ref_cam[0, :3, 0] - np.dot(T_ref_cam[0, :3, 0], up) * up
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    R_world_ref = np.stack([forward, left, up], axis=0)
    T_world_ref = np.eye(4)
    T_world_ref[:3, :3] = R_world_ref
    T_world_ref[:3, 3] = -R_world_ref @ target
    T_world_ref[2, 3] += surface_z + surface_below_gaze
    T_world_cam = np.einsum("ij,njk->nik", T_world_ref, T_ref_cam)
    origin = T_world_cam[:, :3, 3]
    axis = T_world_cam[:, :3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (surface_z - origin[:, 2]) / axis[:, 2]
    ok = (s > 0) & np.isfinite(s)
    hits = origin[ok, :2] + s[ok, None] * axis[ok, :2]
    if len(hits) < 3:
        hits = np.zeros((3, 2))
    centre = np.median(hits, axis=0)
    spread = hits - centre
    _, vectors = np.linalg.eigh(spread.T @ spread)
    axes = vectors[:, ::-1].copy()
    half = np.percentile(np.abs(spread @ axes), 85, axis=0)
    table = {"centre": centre, "surface_z": float(surface_z), "axes": axes, "half_extent": half}
    return T_world_cam, table
