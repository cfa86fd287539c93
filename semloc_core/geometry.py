"""Rigid transforms, quaternions and angles.

Conventions (docs/conventions.md):

* World frame W: right-handed, z up, metres.
* Body frame B (a robot base, or the gravity-levelled frame under a hand-held camera): x forward, y left, z up.
  A planar pose (x, y, theta) places B in W; theta is counter-clockwise from the world x axis.
* Camera frame C: OpenCV (x right, y down, z forward).
* ``T_a_b`` is a 4x4 homogeneous matrix mapping coordinates in frame b to frame a (the pose of b in a).
* Quaternions are stored (x, y, z, w), as in TUM trajectory files.
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi

# Rotation taking camera-frame coordinates (OpenCV: x right, y down, z forward) to body-frame coordinates
# (x forward, y left, z up) for a level camera looking along the body's x axis.
R_BODY_CAM_FORWARD = np.array(
    [
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
    ]
)


def wrap_angle(angle):
    """Wrap angles (radians) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % TWO_PI - np.pi


def angle_diff(a, b):
    """Signed smallest difference a - b, in [-pi, pi)."""
    return wrap_angle(np.asarray(a) - np.asarray(b))


def make_transform(rotation: np.ndarray, translation) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return transform


def look_at(eye, target, roll: float = 0.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``, its x axis
    level with respect to ``up`` (world z), then rolled by ``roll`` about its axis. Looking along ``up``, x is the
    world's -y."""
    eye = np.asarray(eye, float)
    forward = np.asarray(target, float) - eye
    norm = np.linalg.norm(forward)
    if norm == 0:
        raise ValueError("eye and target coincide")
    forward /= norm
    right = np.cross(forward, np.asarray(up, float))
    if np.linalg.norm(right) < 1e-9:
        right = np.array([0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward], axis=1)
    if roll:
        R = R @ np.array([[np.cos(roll), -np.sin(roll), 0.0], [np.sin(roll), np.cos(roll), 0.0], [0.0, 0.0, 1.0]])
    return make_transform(R, eye)


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (or a stack of them, shape (..., 4, 4))."""
    transform = np.asarray(transform, dtype=float)
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    inverse = np.zeros_like(transform)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def check_rigid_transform(transform, name: str = "transform", atol: float = 1e-6) -> np.ndarray:
    """``transform`` as a float 4x4 array if it is a finite rigid transform - a proper rotation (R R^T = I within
    ``atol``, det R > 0) and last row (0, 0, 0, 1) - else ValueError naming ``name`` and what is wrong."""
    T = np.asarray(transform, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} contains non-finite values")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation is not a proper rotation matrix")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def rotation_about_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_about_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_about_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def quaternion_to_rotation(quaternion_xyzw) -> np.ndarray:
    """Rotation matrix (or stack) from unit quaternion(s) in (x, y, z, w) order."""
    q = np.asarray(quaternion_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rotation = np.empty(q.shape[:-1] + (3, 3))
    rotation[..., 0, 0] = 1 - 2 * (y * y + z * z)
    rotation[..., 0, 1] = 2 * (x * y - z * w)
    rotation[..., 0, 2] = 2 * (x * z + y * w)
    rotation[..., 1, 0] = 2 * (x * y + z * w)
    rotation[..., 1, 1] = 1 - 2 * (x * x + z * z)
    rotation[..., 1, 2] = 2 * (y * z - x * w)
    rotation[..., 2, 0] = 2 * (x * z - y * w)
    rotation[..., 2, 1] = 2 * (y * z + x * w)
    rotation[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return rotation


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, from a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=float)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose2d_to_transform(x: float, y: float, theta: float, z: float = 0.0) -> np.ndarray:
    """4x4 transform T_world_body of a planar pose (body at height z)."""
    return make_transform(rotation_about_z(theta), (x, y, z))


def transform_to_pose2d(transform: np.ndarray) -> np.ndarray:
    """Planar pose (x, y, theta) of a 4x4 T_world_body: position projected on the floor, heading = yaw of body x."""
    heading = np.arctan2(transform[1, 0], transform[0, 0])
    return np.array([transform[0, 3], transform[1, 3], heading])


def level_frame_of_camera(T_world_cam: np.ndarray) -> np.ndarray:
    """T_world_body of the gravity-levelled body frame under a camera with arbitrary attitude.

    The body origin is the camera centre, x is the camera's optical axis projected on the horizontal plane, z is
    up. Used for hand-held cameras: the planar pose of this frame is what the localizer estimates, and the
    camera's extrinsic rotation in it (its pitch and roll) is what an IMU would report.
    """
    optical_axis = T_world_cam[:3, 2]
    heading = np.arctan2(optical_axis[1], optical_axis[0])
    return make_transform(rotation_about_z(heading), T_world_cam[:3, 3])


def inside_polygon(x, y, polygon) -> np.ndarray:
    """Whether each point (x, y) lies inside ``polygon`` ((n, 2) vertices, either orientation; even-odd rule)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    polygon = np.asarray(polygon, dtype=float)
    inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    for ax, ay, bx, by in zip(x0, y0, x1, y1):
        # count crossings of a ray towards +x with each edge
        straddles = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            crossing_x = ax + (y - ay) * (bx - ax) / (by - ay)
        inside ^= straddles & (x < crossing_x)
    return inside
