"""ROS 2 messages <-> semloc: CDR (de)serialisation through rosbags' typestore, checked at the boundary, and the
conversions to and from semloc's frames and core types (docs/ros2.md).

Everything decoded here is untrusted: :func:`decode_cdr` raises :class:`schemas.FrameError` (reason ``cdr`` or
``size``) for bytes that are not the message, and the converters raise it (reason ``invalid``, ``encoding`` or
``frame_id``) for values outside physical ranges: non-finite numbers, quaternions that are not unit, images whose
data does not match their size, camera intrinsics that cannot be a camera.
"""

from __future__ import annotations

import bisect
import math
from functools import lru_cache

import numpy as np

from schemas import FrameError
from schemas.camera import compressed_size
from semloc_core.camera import FisheyeCamera, PinholeCamera
from semloc_core.geometry import (invert_transform, make_transform, quaternion_to_rotation, rotation_about_z,
                                  rotation_to_quaternion, transform_to_pose2d)
from semloc_core.io.camera_model import LENS_OF_DISTORTION_MODEL
from semloc_core.io.dataset import increment_to_twist, relative_increments

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

# Largest CDR payload accepted per type (an uncompressed 4K RGB image is 25 MB).
MAX_BYTES = {IMAGE: 64 << 20, COMPRESSED_IMAGE: 32 << 20, CAMERA_INFO: 64 << 10, ODOMETRY: 64 << 10,
             TF_MESSAGE: 4 << 20, POSE_WITH_COVARIANCE_STAMPED: 64 << 10, POSE_STAMPED: 64 << 10}
MAX_IMAGE_SIDE = 16384
# CDR encapsulation identifiers (first two bytes, big-endian): plain CDR, big- and little-endian.
CDR_BE, CDR_LE = b"\x00\x00", b"\x00\x01"
UNIT_QUATERNION_TOLERANCE = 1e-3
DISTORTION_MODELS = {"plumb_bob": (5,), "rational_polynomial": (8,), "equidistant": (4,), "": (0,), "none": (0,)}


@lru_cache(maxsize=None)
def typestore(distro: str = "jazzy"):
    """rosbags' typestore of a ROS 2 distribution (``humble``, ``jazzy``, ``kilted``): its message definitions
    (type hashes differ between distributions where a message changed, e.g. visualization_msgs/Marker)."""
    from rosbags.typesys import Stores, get_typestore

    stores = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED}
    if distro not in stores:
        raise ValueError(f"ROS 2 distribution must be one of {sorted(stores)}, got {distro!r}")
    return get_typestore(stores[distro])


def decode_cdr(store, payload: bytes, msgtype: str):
    """The message of type ``msgtype`` in CDR ``payload`` (with its 4-byte encapsulation header); FrameError if not."""
    limit = MAX_BYTES.get(msgtype, 16 << 20)
    if len(payload) > limit:
        raise FrameError(f"{msgtype}: {len(payload)} bytes, more than {limit}", reason="size")
    if len(payload) < 4 or bytes(payload[:2]) not in (CDR_BE, CDR_LE):
        raise FrameError(f"{msgtype}: not a CDR payload (encapsulation {bytes(payload[:2]).hex()})", reason="cdr")
    try:
        return store.deserialize_cdr(payload, msgtype)
    except Exception as error:  # rosbags raises SerdeError, struct.error, UnicodeDecodeError, ...
        raise FrameError(f"{msgtype}: undecodable CDR: {type(error).__name__}: {error}", reason="cdr") from None


def encode_cdr(store, msg, msgtype: str) -> bytes:
    """CDR bytes (little-endian, with the encapsulation header) of a message."""
    return bytes(store.serialize_cdr(msg, msgtype))


# ---------------------------------------------------------------------------------------------------- time, frames
def stamp_ns(stamp) -> int:
    """builtin_interfaces/Time (or ROS 1 time) -> integer ns; FrameError if negative or out of range."""
    seconds = getattr(stamp, "sec", getattr(stamp, "secs", 0))
    nanos = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
    if not 0 <= int(nanos) < 1_000_000_000 or int(seconds) < 0:
        raise FrameError(f"bad time stamp {seconds} s {nanos} ns", reason="invalid")
    return int(seconds) * 1_000_000_000 + int(nanos)


def ros_time(store, ns: int):
    Time = store.types["builtin_interfaces/msg/Time"]
    ns = max(0, int(ns))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def ros_header(store, ns: int, frame_id: str):
    return store.types["std_msgs/msg/Header"](stamp=ros_time(store, ns), frame_id=frame_id)


def _finite(values, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise FrameError(f"{what} is not finite", reason="invalid")
    return array


def _rotation(q, what: str) -> np.ndarray:
    quaternion = _finite([q.x, q.y, q.z, q.w], f"{what} orientation")
    if abs(float(np.linalg.norm(quaternion)) - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise FrameError(f"{what} orientation is not a unit quaternion (norm {np.linalg.norm(quaternion):.4f})",
                         reason="invalid")
    return quaternion_to_rotation(quaternion)


def pose_matrix(pose, what: str = "pose") -> np.ndarray:
    """4x4 transform of a geometry_msgs/Pose (checked)."""
    return make_transform(_rotation(pose.orientation, what),
                          _finite([pose.position.x, pose.position.y, pose.position.z], f"{what} position"))


def transform_matrix(transform, what: str = "transform") -> np.ndarray:
    """4x4 transform of a geometry_msgs/Transform (checked)."""
    t = transform.translation
    return make_transform(_rotation(transform.rotation, what), _finite([t.x, t.y, t.z], f"{what} translation"))


def ros_pose(store, T: np.ndarray):
    types = store.types
    x, y, z, w = rotation_to_quaternion(T[:3, :3])
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)))


def planar_twist(T_from: np.ndarray, T_to: np.ndarray, dt: float) -> tuple[float, float, float]:
    """(v, v_lateral, omega) of the constant body twist taking planar pose ``T_from`` to ``T_to`` in ``dt`` s (the
    SE(2) logarithm; semloc's Odometry frame, which the localizer integrates back exactly)."""
    poses = np.stack([transform_to_pose2d(T_from), transform_to_pose2d(T_to)])
    twist = increment_to_twist(relative_increments(poses)[1])
    return float(twist[0] / dt), float(twist[1] / dt), float(twist[2] / dt)


# ---------------------------------------------------------------------------------------------------- transforms
class TransformBuffer:
    """A small tf2: stamped transforms per (parent, child) edge, static ones, and lookups along the tree with
    interpolation (linear translation, spherical rotation) - never extrapolation. ``history_ns``: how much of each
    dynamic edge is kept (None: everything, for reading a whole log)."""

    def __init__(self, history_ns: int | None = 10_000_000_000):
        self.history_ns = history_ns
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}  # child -> T_parent_child
        self.dynamic: dict[str, tuple[list[int], list[np.ndarray]]] = {}  # child -> (stamps, transforms)

    def add(self, parent: str, child: str, stamp: int, T: np.ndarray, static: bool = False) -> None:
        if not parent or not child or parent == child:
            raise FrameError(f"transform {parent!r} -> {child!r} does not link two frames", reason="frame_id")
        self.parent[child] = parent
        if static:
            self.static[child] = T
            self.dynamic.pop(child, None)
            return
        stamps, transforms = self.dynamic.setdefault(child, ([], []))
        index = bisect.bisect_left(stamps, stamp)
        if index < len(stamps) and stamps[index] == stamp:
            transforms[index] = T
        else:
            stamps.insert(index, stamp)
            transforms.insert(index, T)
        if self.history_ns is not None and stamps[-1] - stamps[0] > self.history_ns:
            cut = bisect.bisect_left(stamps, stamps[-1] - self.history_ns)
            del stamps[:cut], transforms[:cut]

    def add_message(self, msg, static: bool = False) -> int:
        """Every TransformStamped of a tf2_msgs/TFMessage; returns how many were added."""
        for transform in msg.transforms:
            self.add(transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/"),
                     stamp_ns(transform.header.stamp), transform_matrix(transform.transform), static)
        return len(msg.transforms)

    def _edge(self, child: str, stamp: int) -> np.ndarray | None:
        if child in self.static:
            return self.static[child]
        stamps, transforms = self.dynamic.get(child, ([], []))
        index = bisect.bisect_left(stamps, stamp)
        if index < len(stamps) and stamps[index] == stamp:
            return transforms[index]
        if index == 0 or index == len(stamps):
            return None  # outside the edge's history: tf2 does not extrapolate either
        a, b = stamps[index - 1], stamps[index]
        return interpolate(transforms[index - 1], transforms[index], (stamp - a) / (b - a))

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.parent and len(chain) < 64:
            chain.append(self.parent[chain[-1]])
        return chain

    def lookup(self, parent: str, child: str, stamp: int) -> np.ndarray | None:
        """T_parent_child at ``stamp`` (ns), or None when the tree does not connect them at that time."""
        if parent == child:
            return np.eye(4)
        up_child, up_parent = self._chain(child), self._chain(parent)
        common = next((f for f in up_child if f in up_parent), None)
        if common is None:
            return None

        def to_common(chain: list[str]) -> np.ndarray | None:
            T = np.eye(4)
            for frame in chain[: chain.index(common)]:
                edge = self._edge(frame, stamp)
                if edge is None:
                    return None
                T = edge @ T
            return T

        T_common_child, T_common_parent = to_common(up_child), to_common(up_parent)
        if T_common_child is None or T_common_parent is None:
            return None
        return invert_transform(T_common_parent) @ T_common_child

    def edges(self, parent: str, child: str) -> list[str]:
        """The edges from ``child`` up to ``parent`` (each named by its child frame); empty unless ``parent`` is
        above ``child`` in the tree."""
        chain = self._chain(child)
        return chain[: chain.index(parent)] if parent in chain else []

    def forget(self, parent: str, child: str) -> None:
        """Drop the stamped history of the edges from ``child`` up to ``parent``: a restarted source's transforms
        before the restart belong to another run (interpolating across it, or its history cut by the new stamps
        when its clock restarted behind, would mix the two)."""
        for frame in self.edges(parent, child):
            self.dynamic.pop(frame, None)

    def latest_stamp(self, child: str) -> int | None:
        stamps = self.dynamic.get(child, ([], []))[0]
        return stamps[-1] if stamps else None


def interpolate(Ta: np.ndarray, Tb: np.ndarray, alpha: float) -> np.ndarray:
    """The pose a fraction ``alpha`` of the way from Ta to Tb (slerp of the rotations, lerp of the positions)."""
    qa, qb = rotation_to_quaternion(Ta[:3, :3]), rotation_to_quaternion(Tb[:3, :3])
    dot = float(np.dot(qa, qb))
    if dot < 0:
        qb, dot = -qb, -dot
    if dot > 0.9995:
        q = qa + alpha * (qb - qa)
    else:
        angle = math.acos(min(1.0, dot))
        q = (math.sin((1 - alpha) * angle) * qa + math.sin(alpha * angle) * qb) / math.sin(angle)
    T = make_transform(quaternion_to_rotation(q / np.linalg.norm(q)), Ta[:3, 3] + alpha * (Tb[:3, 3] - Ta[:3, 3]))
    return T


# ---------------------------------------------------------------------------------------------------- inputs
def image_pixels(msgtype: str, msg, grayscale: bool = False) -> np.ndarray:
    """BGR (or grey) uint8 pixels of a sensor_msgs Image / CompressedImage; FrameError if they cannot be read."""
    from services.camera_sources import ros_image_to_bgr

    if msgtype == IMAGE:
        width, height = int(msg.width), int(msg.height)
    else:  # read the size from the file's header first: a small PNG may claim gigapixels
        width, height = encoded_size(bytes(np.asarray(msg.data, dtype=np.uint8)[:65536]))
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        raise FrameError(f"image size {width}x{height} out of range", reason="invalid")
    try:
        return ros_image_to_bgr(msgtype, msg, grayscale)
    except ValueError as error:
        raise FrameError(f"{msgtype}: {error}", reason="encoding") from None


def encoded_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame marker, without decoding
    (``schemas.camera.compressed_size``); FrameError for anything else."""
    return compressed_size(data)


def camera_from_info(msg, T_body_cam: np.ndarray) -> PinholeCamera | FisheyeCamera:
    """The camera of a sensor_msgs/CameraInfo: a pinhole (``plumb_bob``, ``rational_polynomial`` or no distortion)
    or a fisheye (``equidistant``, OpenCV's fisheye model); the optical frame is OpenCV's, as semloc's camera frame;
    mounted at ``T_body_cam``."""
    width, height = int(msg.width), int(msg.height)
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        raise FrameError(f"camera size {width}x{height} out of range", reason="invalid")
    model = str(msg.distortion_model)
    # ROS 1 bags keep their message definitions' upper-case names (D, K)
    d, k = (getattr(msg, name, None) if hasattr(msg, name) else getattr(msg, name.upper()) for name in ("d", "k"))
    dist = _finite(d, "distortion").reshape(-1)
    if model not in DISTORTION_MODELS:
        raise FrameError(f"unsupported distortion model {model!r} (plumb_bob, rational_polynomial, equidistant)",
                         reason="invalid")
    fisheye = LENS_OF_DISTORTION_MODEL[model] == "fisheye"
    if dist.size and not np.any(dist) and not fisheye:
        dist = np.zeros(0)
    if dist.size not in DISTORTION_MODELS[model] + (0,):
        raise FrameError(f"{model} with {dist.size} coefficients", reason="invalid")
    K = _finite(k, "K").reshape(3, 3) if np.asarray(k).size == 9 else None
    if K is None or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[1, 0] or K[2, 0] or K[2, 1]:
        raise FrameError(f"K is not a camera matrix: {None if K is None else K.tolist()}", reason="invalid")
    try:
        if fisheye:
            return FisheyeCamera(width, height, K, dist if dist.size else np.zeros(4), T_body_cam)
        return PinholeCamera(width, height, K, dist, T_body_cam)
    except ValueError as error:
        raise FrameError(f"camera_info: {error}", reason="invalid") from None


def initial_pose(msg, map_frame: str) -> tuple[float, float, float, np.ndarray]:
    """(x, y, theta, 3x3 covariance over x, y, yaw) of a PoseWithCovarianceStamped as RViz's "2D Pose Estimate"
    tool sends it on /initialpose; FrameError unless it is in ``map_frame`` with a sane covariance."""
    frame = str(msg.header.frame_id).lstrip("/")
    if frame != map_frame:
        raise FrameError(f"initial pose in frame {frame!r}, expected {map_frame!r}", reason="frame_id")
    x, y, theta = transform_to_pose2d(pose_matrix(msg.pose.pose, "initial pose"))
    full = _finite(msg.pose.covariance, "covariance")
    if full.size != 36:
        raise FrameError(f"covariance has {full.size} entries, expected 36", reason="invalid")
    full = full.reshape(6, 6)
    covariance = full[np.ix_([0, 1, 5], [0, 1, 5])]
    if not np.allclose(covariance, covariance.T, atol=1e-9) or np.any(np.linalg.eigvalsh(covariance) < -1e-12):
        raise FrameError("initial pose covariance is not symmetric positive semi-definite", reason="invalid")
    return float(x), float(y), float(theta), covariance


# ---------------------------------------------------------------------------------------------------- outputs
def pose_with_covariance_stamped(store, stamp: int, frame_id: str, x: float, y: float, theta: float,
                                 covariance: np.ndarray):
    """geometry_msgs/PoseWithCovarianceStamped of a planar pose; covariance 3x3 over (x, y, yaw) placed in ROS's
    6x6 row-major (x, y, z, rotation about x, y, z), as nav2 AMCL fills it (z, roll, pitch zero)."""
    types = store.types
    full = np.zeros((6, 6))
    index = [0, 1, 5]
    full[np.ix_(index, index)] = np.asarray(covariance, float)
    pose = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=ros_pose(store, make_transform(rotation_about_z(theta), (x, y, 0.0))), covariance=full.reshape(-1))
    return types[POSE_WITH_COVARIANCE_STAMPED](header=ros_header(store, stamp, frame_id), pose=pose)


def tf_message(store, transforms: list[tuple[int, str, str, np.ndarray]]):
    """tf2_msgs/TFMessage of (stamp, parent, child, T_parent_child) tuples."""
    types = store.types
    stamped = []
    for stamp, parent, child, T in transforms:
        x, y, z, w = rotation_to_quaternion(T[:3, :3])
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)))
        stamped.append(types["geometry_msgs/msg/TransformStamped"](
            header=ros_header(store, stamp, parent), child_frame_id=child, transform=transform))
    return types[TF_MESSAGE](transforms=stamped)


def path_message(store, stamp: int, frame_id: str, poses: list[tuple[int, float, float, float]]):
    """nav_msgs/Path of planar poses (stamp, x, y, theta)."""
    types = store.types
    stamped = [types[POSE_STAMPED](header=ros_header(store, s, frame_id),
                                   pose=ros_pose(store, make_transform(rotation_about_z(t), (x, y, 0.0))))
               for s, x, y, t in poses]
    return types[PATH](header=ros_header(store, stamp, frame_id), poses=stamped)


# A colour per class (tab10), cycling.
_PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                     [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]]) / 255.0


def class_color(index: int) -> tuple[float, float, float]:
    return tuple(float(c) for c in _PALETTE[int(index) % len(_PALETTE)])


def _marker(store, header, ns: str, marker_id: int, kind: int, **fields):
    types = store.types
    Marker = types["visualization_msgs/msg/Marker"]
    values = dict(header=header, ns=ns, id=int(marker_id), type=int(kind), action=Marker.ADD,
                  pose=ros_pose(store, np.eye(4)), scale=types["geometry_msgs/msg/Vector3"](x=1.0, y=1.0, z=1.0),
                  color=types["std_msgs/msg/ColorRGBA"](r=1.0, g=1.0, b=1.0, a=1.0),
                  lifetime=types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False,
                  points=[], colors=[], text="", mesh_resource="", mesh_use_embedded_materials=False)
    fields_of_type = Marker.__dataclass_fields__
    if "texture" in fields_of_type:  # Iron and later: texture and mesh file fields
        values.update(texture_resource="", uv_coordinates=[],
                      texture=types[COMPRESSED_IMAGE](header=ros_header(store, 0, ""), format="",
                                                      data=np.zeros(0, np.uint8)),
                      mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)))
    values.update(fields)
    return Marker(**values)


def _delete_all(store, header, ns: str):
    Marker = store.types["visualization_msgs/msg/Marker"]
    return _marker(store, header, ns, 0, Marker.CUBE, action=Marker.DELETEALL)


def object_markers(store, stamp: int, frame_id: str, class_names, class_index, positions, sizes, scores=None):
    """visualization_msgs/MarkerArray of an object map: a box per object (its size, its class's colour, opacity
    from its score) and a text label above it; a DELETEALL first so that removed objects disappear."""
    types = store.types
    Marker = types["visualization_msgs/msg/Marker"]
    header = ros_header(store, stamp, frame_id)
    markers = [_delete_all(store, header, "semloc_objects")]
    for n, (cls, position, size) in enumerate(zip(class_index, positions, sizes)):
        r, g, b = class_color(int(cls))
        alpha = 0.8 if scores is None else float(np.clip(0.3 + 0.7 * scores[n], 0.3, 1.0))
        T = make_transform(np.eye(3), position)
        extent = np.maximum(np.asarray(size, float), 0.01)
        markers.append(_marker(store, header, "semloc_objects", n, Marker.CUBE, pose=ros_pose(store, T),
                               scale=types["geometry_msgs/msg/Vector3"](x=extent[0], y=extent[1], z=extent[2]),
                               color=types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=alpha)))
        label = make_transform(np.eye(3), np.asarray(position, float) + [0.0, 0.0, 0.5 * extent[2] + 0.05])
        markers.append(_marker(store, header, "semloc_labels", n, Marker.TEXT_VIEW_FACING,
                               pose=ros_pose(store, label), text=str(class_names[int(cls)]),
                               scale=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.06)))
    return types[MARKER_ARRAY](markers=markers)


def topomap_markers(store, stamp: int, frame_id: str, node_positions: dict[int, tuple[float, float]],
                    edges) -> object:
    """visualization_msgs/MarkerArray of the topological map: its nodes (a sphere list at each node's key-frame
    pose) and the edges between placed nodes (a line list)."""
    types = store.types
    Marker = types["visualization_msgs/msg/Marker"]
    Point = types["geometry_msgs/msg/Point"]
    header = ros_header(store, stamp, frame_id)
    points = [Point(x=float(x), y=float(y), z=0.0) for x, y in node_positions.values()]
    lines = []
    for a, b in edges:
        if int(a) in node_positions and int(b) in node_positions:
            lines += [Point(x=float(node_positions[int(n)][0]), y=float(node_positions[int(n)][1]), z=0.0)
                      for n in (a, b)]
    blue = types["std_msgs/msg/ColorRGBA"](r=0.1, g=0.4, b=1.0, a=1.0)
    return types[MARKER_ARRAY](markers=[
        _delete_all(store, header, "semloc_topomap"),
        _marker(store, header, "semloc_topomap", 0, Marker.SPHERE_LIST, points=points, color=blue,
                scale=types["geometry_msgs/msg/Vector3"](x=0.05, y=0.05, z=0.05)),
        _marker(store, header, "semloc_topomap", 1, Marker.LINE_LIST, points=lines, color=blue,
                scale=types["geometry_msgs/msg/Vector3"](x=0.01, y=0.0, z=0.0)),
    ])
