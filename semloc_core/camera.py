"""Camera models: pixel <-> ray <-> bearing.

Four models, all with an extrinsic ``T_body_cam`` (camera pose in the body frame, see ``geometry``):

* ``PinholeCamera`` - intrinsics K and OpenCV distortion coefficients (0, 4, 5, 8, 12 or 14 of them).
* ``FisheyeCamera`` - intrinsics K and OpenCV's fisheye (equidistant) coefficients k1..k4.
* ``EquirectangularCamera`` - a 360-degree panorama: column -> longitude, row -> latitude.
* ``CameraRig`` - several cameras fired together (a Ladybug-style ring); images are processed per camera and merged
  in bearing.

The camera frame is OpenCV's for every model (x right, y down, z forward). For the panorama, longitude 0 is the
camera's z axis and positive longitude turns right (towards +x), so column u grows to the right as in a pinhole
image; latitude is positive upwards (towards -y).

Bearing = azimuth of a ray in the body frame, counter-clockwise from body x, in [-pi, pi). With the default
extrinsic (level camera looking along body x) a pixel right of centre has a negative bearing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from semloc_core.geometry import (R_BODY_CAM_FORWARD, check_rigid_transform, make_transform, rotation_about_z,
                                  wrap_angle)

_VALID_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)
# The longest image side a camera model may have, in pixels (the wire's limit too: schemas.camera.MAX_SIDE, which
# stands alone as the wire contract does; tests/contract check that the two agree).
MAX_IMAGE_SIDE = 16384


def forward_extrinsic(height: float = 0.0) -> np.ndarray:
    """T_body_cam of a level camera at ``height`` metres above the body origin, looking along body x."""
    return make_transform(R_BODY_CAM_FORWARD, (0.0, 0.0, height))


def _check_size(width: int, height: int) -> None:
    if not (0 < int(width) <= MAX_IMAGE_SIDE and 0 < int(height) <= MAX_IMAGE_SIDE):
        raise ValueError(f"image sides must be positive and at most {MAX_IMAGE_SIDE} pixels, got {width}x{height}")


def _check_lens(camera, distortion_lengths: tuple[int, ...]) -> None:
    """Check and store (as float arrays) a frozen camera's size, K, distortion and extrinsic."""
    _check_size(camera.width, camera.height)
    K = np.asarray(camera.K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite 3x3 matrix with positive focal lengths, got {K!r}")
    dist = np.asarray(camera.dist, dtype=float).reshape(-1)
    if dist.size not in distortion_lengths or not np.all(np.isfinite(dist)):
        raise ValueError(f"a {type(camera).__name__} has one of {distortion_lengths} finite distortion coefficients, "
                         f"got {dist.size}")
    object.__setattr__(camera, "K", K)
    object.__setattr__(camera, "dist", dist)
    object.__setattr__(camera, "T_body_cam", check_rigid_transform(camera.T_body_cam, "T_body_cam"))


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_body_cam: np.ndarray = field(default_factory=forward_extrinsic)

    def __post_init__(self) -> None:
        _check_lens(self, _VALID_DISTORTION_LENGTHS)

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov_deg: float, T_body_cam=None) -> "PinholeCamera":
        """Distortion-free camera with square pixels and the principal point at the image centre."""
        if not 0.0 < horizontal_fov_deg < 180.0:
            raise ValueError("horizontal field of view must be in (0, 180) degrees")
        f = 0.5 * width / np.tan(np.radians(horizontal_fov_deg) / 2.0)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, K, T_body_cam=forward_extrinsic() if T_body_cam is None else T_body_cam)

    @property
    def horizontal_fov(self) -> float:
        fx, cx = self.K[0, 0], self.K[0, 2]
        return float(np.arctan2(cx, fx) + np.arctan2(self.width - cx, fx))

    def rays_cam(self, u, v) -> np.ndarray:
        """Unit rays in the camera frame through pixel coordinates (u, v) (pixel centres at integers)."""
        uv = np.stack(np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float)), axis=-1)
        flat = uv.reshape(-1, 1, 2)
        if self.dist.size:
            # The default 5 iterations leave ~0.1 px error at the corners of a strongly distorted lens.
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
            normalized = cv2.undistortPointsIter(flat, self.K, self.dist, None, None, criteria).reshape(-1, 2)
        else:
            normalized = (flat.reshape(-1, 2) - self.K[:2, 2]) / np.diag(self.K)[:2]
        rays = np.concatenate([normalized, np.ones((normalized.shape[0], 1))], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays.reshape(uv.shape[:-1] + (3,))

    def project_cam(self, points_cam) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) of camera-frame points and a mask of those in front and inside the image."""
        p = np.asarray(points_cam, dtype=float)
        flat = p.reshape(-1, 3)
        in_front = flat[:, 2] > 1e-9
        safe = np.where(in_front[:, None], flat, np.array([0.0, 0.0, 1.0]))
        if self.dist.size:
            uv, _ = cv2.projectPoints(safe, np.zeros(3), np.zeros(3), self.K, self.dist)
            uv = uv.reshape(-1, 2)
        else:
            uv = safe[:, :2] / safe[:, 2:3] * np.diag(self.K)[:2] + self.K[:2, 2]
        inside = in_front & _inside_image(uv, self.width, self.height)
        return uv.reshape(p.shape[:-1] + (2,)), inside.reshape(p.shape[:-1])


@dataclass(frozen=True, eq=False)
class FisheyeCamera:
    """OpenCV's fisheye (equidistant) model: r = f * theta_d with theta_d = theta (1 + k1 theta^2 + k2 theta^4 +
    k3 theta^6 + k4 theta^8), ``dist`` = (k1, k2, k3, k4) (``cv2.fisheye``; ROS ``equidistant``). Rays reach
    up to 90 degrees off axis; points behind the camera plane are not projected."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(4))
    T_body_cam: np.ndarray = field(default_factory=forward_extrinsic)

    def __post_init__(self) -> None:
        _check_lens(self, (4,))

    @property
    def horizontal_fov(self) -> float:
        rays = self.rays_cam(np.array([-0.5, self.width - 0.5]), np.full(2, self.K[1, 2]))
        return float(np.arctan2(-rays[0, 0], rays[0, 2]) + np.arctan2(rays[1, 0], rays[1, 2]))

    def rays_cam(self, u, v) -> np.ndarray:
        uv = np.stack(np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float)), axis=-1)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        normalized = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist,
                                                 criteria=criteria).reshape(-1, 2)
        # undistortPoints gives tan(theta) (x, y): a ray past 90 degrees has none; rebuild the ray from theta.
        distorted = (uv.reshape(-1, 2) - self.K[:2, 2]) / np.diag(self.K)[:2]
        theta = np.arctan(np.hypot(*normalized.T))
        direction = np.arctan2(distorted[:, 1], distorted[:, 0])
        rays = np.stack([np.sin(theta) * np.cos(direction), np.sin(theta) * np.sin(direction), np.cos(theta)], -1)
        return rays.reshape(uv.shape[:-1] + (3,))

    def project_cam(self, points_cam) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(points_cam, dtype=float)
        flat = p.reshape(-1, 3)
        in_front = flat[:, 2] > 1e-9
        safe = np.where(in_front[:, None], flat, np.array([0.0, 0.0, 1.0]))
        uv, _ = cv2.fisheye.projectPoints(safe.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        uv = uv.reshape(-1, 2)
        inside = in_front & _inside_image(uv, self.width, self.height)
        return uv.reshape(p.shape[:-1] + (2,)), inside.reshape(p.shape[:-1])


@dataclass(frozen=True, eq=False)
class EquirectangularCamera:
    width: int
    height: int
    T_body_cam: np.ndarray = field(default_factory=forward_extrinsic)
    lat_top: float | None = None
    lat_bottom: float | None = None

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        # Square pixels by default: the vertical span is height/width of the full 2*pi turn, centred on the horizon.
        half_span = np.pi * self.height / self.width
        lat_top = half_span if self.lat_top is None else float(self.lat_top)
        lat_bottom = -half_span if self.lat_bottom is None else float(self.lat_bottom)
        if not (-np.pi / 2 <= lat_bottom < lat_top <= np.pi / 2):
            raise ValueError(f"need -pi/2 <= lat_bottom < lat_top <= pi/2, got {lat_bottom}, {lat_top}")
        object.__setattr__(self, "lat_top", lat_top)
        object.__setattr__(self, "lat_bottom", lat_bottom)
        object.__setattr__(self, "T_body_cam", check_rigid_transform(self.T_body_cam, "T_body_cam"))

    @property
    def horizontal_fov(self) -> float:
        return float(2.0 * np.pi)

    def column_longitude(self, u) -> np.ndarray:
        return (np.asarray(u, float) + 0.5) / self.width * 2.0 * np.pi - np.pi

    def row_latitude(self, v) -> np.ndarray:
        return self.lat_top - (np.asarray(v, float) + 0.5) / self.height * (self.lat_top - self.lat_bottom)

    def rays_cam(self, u, v) -> np.ndarray:
        lon = self.column_longitude(u)
        lat = self.row_latitude(v)
        lon, lat = np.broadcast_arrays(lon, lat)
        return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)

    def project_cam(self, points_cam) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(points_cam, dtype=float)
        lon = np.arctan2(p[..., 0], p[..., 2])
        lat = np.arctan2(-p[..., 1], np.hypot(p[..., 0], p[..., 2]))
        # Longitude wraps: the seam behind the camera maps to the first column, not past the last.
        u = np.mod((lon + np.pi) / (2.0 * np.pi) * self.width, self.width) - 0.5
        v = (self.lat_top - lat) / (self.lat_top - self.lat_bottom) * self.height - 0.5
        uv = np.stack([u, v], axis=-1)
        nonzero = np.linalg.norm(p, axis=-1) > 1e-9
        return uv, nonzero & _inside_image(uv, self.width, self.height)


@dataclass(frozen=True, eq=False)
class CameraRig:
    """Cameras fired together; each keeps its own extrinsic in the common body frame."""

    cameras: tuple

    def __post_init__(self) -> None:
        cameras = tuple(self.cameras)
        if not cameras:
            raise ValueError("a camera rig needs at least one camera")
        for camera in cameras:
            if not isinstance(camera, (PinholeCamera, FisheyeCamera, EquirectangularCamera)):
                raise TypeError(f"rig members must be pinhole, fisheye or equirectangular cameras, got {type(camera)}")
        object.__setattr__(self, "cameras", cameras)

    @classmethod
    def ring(cls, count: int, width: int, height: int, horizontal_fov_deg: float, height_m: float = 0.0):
        """``count`` identical pinhole cameras evenly spaced in yaw, the first looking along body x."""
        cameras = []
        for k in range(count):
            yaw = 2.0 * np.pi * k / count
            T = make_transform(rotation_about_z(yaw) @ R_BODY_CAM_FORWARD, (0.0, 0.0, height_m))
            cameras.append(PinholeCamera.from_fov(width, height, horizontal_fov_deg, T_body_cam=T))
        return cls(tuple(cameras))


Camera = PinholeCamera | FisheyeCamera | EquirectangularCamera


def members(camera) -> tuple:
    """The single cameras of a model: the rig's members, or the camera itself."""
    return camera.cameras if isinstance(camera, CameraRig) else (camera,)


def _inside_image(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    return (uv[..., 0] >= -0.5) & (uv[..., 0] < width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] < height - 0.5)


def pixel_grid(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel-centre coordinates (u, v), each of shape (height, width)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    return u.astype(float), v.astype(float)


def rays_body(camera: Camera, u, v, T_body_cam: np.ndarray | None = None) -> np.ndarray:
    """Unit rays in the body frame through pixels (u, v); ``T_body_cam`` overrides the static extrinsic.

    The override carries a per-frame attitude, e.g. the pitch and roll of a hand-held camera from its IMU.
    """
    T = camera.T_body_cam if T_body_cam is None else check_rigid_transform(T_body_cam, "T_body_cam")
    return camera.rays_cam(u, v) @ T[:3, :3].T


def pixel_bearings(camera: Camera, T_body_cam: np.ndarray | None = None) -> np.ndarray:
    """Bearing of every pixel's ray, shape (height, width)."""
    rays = rays_body(camera, *pixel_grid(camera), T_body_cam=T_body_cam)
    return wrap_angle(np.arctan2(rays[..., 1], rays[..., 0]))


def column_bearings(camera: Camera, T_body_cam: np.ndarray | None = None) -> np.ndarray:
    """Bearing of each column's centre-row ray, shape (width,) - the thesis's column -> bearing map (§4.4.2)."""
    u = np.arange(camera.width, dtype=float)
    v = np.full_like(u, (camera.height - 1) / 2.0)
    rays = rays_body(camera, u, v, T_body_cam=T_body_cam)
    return wrap_angle(np.arctan2(rays[:, 1], rays[:, 0]))


def project_body(camera: Camera, points_body, T_body_cam: np.ndarray | None = None):
    """Project body-frame points into the camera: pixel coordinates (..., 2), visibility mask (...)."""
    T = camera.T_body_cam if T_body_cam is None else check_rigid_transform(T_body_cam, "T_body_cam")
    p = np.asarray(points_body, dtype=float)
    points_cam = (p - T[:3, 3]) @ T[:3, :3]
    return camera.project_cam(points_cam)


def same_aspect(width: int, height: int, other_width: int, other_height: int, tolerance: float = 0.01) -> bool:
    """Whether two image sizes have the same aspect ratio within ``tolerance`` (relative): 640x480 and 512x384 do,
    640x480 and 640x360 do not."""
    return abs((width * other_height) / (height * other_width) - 1.0) <= tolerance


def resized(camera: Camera, width: int, height: int) -> Camera:
    """The camera seeing its image resized to ``width`` x ``height``: the intrinsics scaled about
    pixel centres (u' = (u + 0.5) s - 0.5, as ``cv2.resize`` maps pixels), distortion and extrinsic unchanged (they
    act on normalised coordinates)."""
    _check_size(width, height)
    if isinstance(camera, EquirectangularCamera):
        return EquirectangularCamera(width, height, camera.T_body_cam, camera.lat_top, camera.lat_bottom)
    sx, sy = width / camera.width, height / camera.height
    K = camera.K.copy()
    K[0, :] *= sx
    K[1, :] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    return type(camera)(width, height, K, camera.dist, camera.T_body_cam)
