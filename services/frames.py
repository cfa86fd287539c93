"""Every conversion between the wire's frames (``schemas``) and semloc_core's objects, both ways, and the checks
that a frame fits the core object it meets (an image and the camera model).

A worker decodes a frame, turns it into core objects here, calls the core, turns the result into a frame here and
publishes it: no worker converts frames itself, and no worker imports another to read that one's frames. The
frames themselves, with their physical ranges, are in ``schemas``; ROS 2 messages, another wire, are converted in
``services/ros2/``.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Annotated

import cv2
import numpy as np
from pydantic import Field

from schemas import (CameraImage, CameraModel, EquirectangularSpec, FisheyeSpec, FrameError, Header, Image, Odometry,
                     PinholeSpec, Pose2D, Pose3D, camera_image)
from schemas.camera import MAX_SIDE
from schemas.detection import CameraHeatmapLevels, CameraHeatmaps, Heatlines, Heatmaps
from schemas.limits import MAX_CLOCK_AHEAD, MAX_ODOMETRY_DT, MAX_SPEED, MAX_TURN_RATE
from schemas.localization import PastPoses, PoseEstimate
from schemas.loopclosure import LoopClosure, LoopFeatures, Revision, SimilarityRow, TopoMap, TopoMapUpdate
from schemas.mapping import ObjectMap, ObjectMapV1, VoxelMap
from semloc_core import bearing
from semloc_core.camera import CameraRig, EquirectangularCamera, FisheyeCamera, PinholeCamera, members
from semloc_core.detection.heatmaps import max_pool, quantise_unit
from semloc_core.geometry import pose2d_to_transform, transform_to_pose2d
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization.motion import OdometryBuffer
from semloc_core.loopclosure.topomap import TopologicalMap
from semloc_core.mapping.grid import VoxelGrid

if TYPE_CHECKING:
    from semloc_core.localization import PoseEstimate as CorePoseEstimate
    from semloc_core.loopclosure import FeatureSequence
    from semloc_core.loopclosure import FrameResult
    from semloc_core.loopclosure.topomap import IncrementalTopoMap, TopoMapUpdate as MapUpdate
    from services.camera_sources import Capture


# ---------------------------------------------------------------------------------------------------- cameras
def camera_model_frame(camera, header: Header, name: str = "") -> CameraModel:
    """The ``CameraModel`` frame of a semloc_core camera or rig."""
    specs = []
    for member in members(camera):
        if isinstance(member, PinholeCamera):
            specs.append(PinholeSpec(width=member.width, height=member.height, K=member.K, dist=member.dist,
                                     T_body_cam=member.T_body_cam))
        elif isinstance(member, FisheyeCamera):
            specs.append(FisheyeSpec(width=member.width, height=member.height, K=member.K, dist=member.dist,
                                     T_body_cam=member.T_body_cam))
        else:
            specs.append(EquirectangularSpec(width=member.width, height=member.height, T_body_cam=member.T_body_cam,
                                             lat_top=member.lat_top, lat_bottom=member.lat_bottom))
    return CameraModel(header=header, name=name, cameras=specs)


def camera_from_frame(model: CameraModel):
    """The semloc_core camera of a ``CameraModel`` frame (a ``CameraRig`` when it has several cameras)."""
    cameras = []
    for spec in model.cameras:
        if isinstance(spec, PinholeSpec):
            cameras.append(PinholeCamera(spec.width, spec.height, np.array(spec.K), np.array(spec.dist),
                                         np.array(spec.T_body_cam)))
        elif isinstance(spec, FisheyeSpec):
            cameras.append(FisheyeCamera(spec.width, spec.height, np.array(spec.K), np.array(spec.dist),
                                         np.array(spec.T_body_cam)))
        else:
            cameras.append(EquirectangularCamera(spec.width, spec.height, np.array(spec.T_body_cam), spec.lat_top,
                                                 spec.lat_bottom))
    return cameras[0] if len(cameras) == 1 else CameraRig(tuple(cameras))


# The largest image (pixels per camera) a worker decodes unless configured otherwise: a 4K frame (8.3 M) fits.
DEFAULT_MAX_IMAGE_PIXELS = 1 << 23
ImagePixelLimit = Annotated[int, Field(ge=1, le=MAX_SIDE * MAX_SIDE, description="an image of more pixels (per "
                                       "camera) is rejected before it is decoded ('size')")]


def check_image(frame: Image, max_pixels: int, camera) -> None:
    """An image frame within ``max_pixels`` per camera (FrameError ``size``) that fits ``camera`` (a camera model
    or rig, or None: FrameError ``calibration``) - checked before any pixel is decoded."""
    for image in frame.images:
        if image.width * image.height > max_pixels:
            raise FrameError(f"camera {image.camera}: a {image.width}x{image.height} image, over the configured "
                             f"{max_pixels} pixels", reason="size")
    if camera is None:
        return
    cameras = members(camera)
    if len(frame.images) != len(cameras):
        raise FrameError(f"image has {len(frame.images)} camera(s), the camera model {len(cameras)}",
                         reason="calibration")
    for image in frame.images:
        check_fits(cameras, image.camera, image.width, image.height, "image")


def check_fits(cameras, index: int, width: int, height: int, what: str) -> None:
    """FrameError ``calibration`` unless member ``index`` of ``cameras`` (``members(camera)``) takes ``width`` x
    ``height`` images (``what`` came from one: an image, heatmaps)."""
    if index >= len(cameras):
        raise FrameError(f"{what} of camera {index}, the camera model has {len(cameras)}", reason="calibration")
    model = cameras[index]
    if (width, height) != (model.width, model.height):
        raise FrameError(f"camera {index}: {what} of a {width}x{height} image, calibration {model.width}x"
                         f"{model.height}", reason="calibration")


def bgr_images(frame: Image) -> tuple[list[CameraImage], list[np.ndarray]]:
    """An image frame's member images ordered by camera index, and their pixels as BGR (grey images expanded)."""
    images = sorted(frame.images, key=lambda image: image.camera)
    pixels = []
    for image in images:
        bgr = image.bgr()
        pixels.append(bgr if bgr.ndim == 3 else cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR))
    return images, pixels


def extrinsic_overrides(images: list[CameraImage]) -> list[np.ndarray | None]:
    """Each member image's own T_body_cam (a hand-held camera's attitude), None where it carries none."""
    return [None if image.T_body_cam is None else np.asarray(image.T_body_cam) for image in images]


def capture_frames(capture: Capture, stamp: int, header, *, jpeg_quality: int | None = None,
                   frame_id: str = "camera") -> list[tuple[str, object]]:
    """The frames a capture of a camera source becomes, as (output, frame): ``image`` always; ``groundtruth_pose``
    and ``groundtruth_pose2d`` with ground truth; ``odometry`` with motion. ``header(output, stamp_ns, frame_id)``
    gives each frame's header (the camera worker's outputs number them; a replay numbers its own). The image comes
    last: a worker that takes the image's pose from the ground truth (the detector's ``height_pose``) has it
    by the time the image arrives."""
    overrides = capture.T_body_cam or [None] * len(capture.images)
    images = [camera_image(pixels, jpeg_quality=jpeg_quality, T_body_cam=override, camera=index)
              for index, (pixels, override) in enumerate(zip(capture.images, overrides))]
    frames = []
    if capture.T_world_body is not None:
        frames.append(("groundtruth_pose", Pose3D.from_matrix(header("groundtruth_pose", stamp, "world"),
                                                              capture.T_world_body, child_frame_id="body")))
        x, y, theta = transform_to_pose2d(capture.T_world_body)
        frames.append(("groundtruth_pose2d", Pose2D(header=header("groundtruth_pose2d", stamp, "world"), x=float(x),
                                                    y=float(y), theta=float(theta))))
    if capture.odometry is not None:
        v, v_lateral, omega, dt = capture.odometry
        frames.append(("odometry", Odometry(header=header("odometry", stamp, "body"), v=v, v_lateral=v_lateral,
                                            omega=omega, dt=dt)))
    return frames + [("image", Image(header=header("image", stamp, frame_id), images=images))]


def pose_matrix(frame: Pose3D | Pose2D) -> np.ndarray:
    """The 4x4 transform of a pose frame (a planar Pose2D stands on the floor: z 0, level)."""
    if isinstance(frame, Pose3D):
        return frame.matrix()
    return pose2d_to_transform(frame.x, frame.y, frame.theta)


# ---------------------------------------------------------------------------------------------------- detection
def camera_heatmaps(image: CameraImage, heatmaps: np.ndarray, dtype: str, pool: int = 1) -> CameraHeatmaps:
    """The wire entry of one member camera's heatmaps (classes, rows, cols) in [0, 1]: max-pooled by ``pool``,
    quantised to ``dtype``, sized and posed as ``image``."""
    values, scale = quantise_unit(max_pool(heatmaps, pool), dtype)
    return CameraHeatmaps(camera=image.camera, image_width=image.width, image_height=image.height, scores=values,
                          scale=scale, T_body_cam=image.T_body_cam)


def camera_heatmap_levels(image: CameraImage, levels: np.ndarray, dtype: str, pool: int = 1) -> CameraHeatmapLevels:
    """:func:`camera_heatmaps` of a window detector's per-level maps (classes, levels, rows, cols)."""
    classes, count = levels.shape[:2]
    pooled = max_pool(levels.reshape((classes * count,) + levels.shape[2:]), pool)
    values, scale = quantise_unit(pooled.reshape((classes, count) + pooled.shape[1:]), dtype)
    return CameraHeatmapLevels(camera=image.camera, image_width=image.width, image_height=image.height,
                               scores=values, scale=scale, T_body_cam=image.T_body_cam)


def heatmaps_from_frame(frame: Heatmaps) -> list[np.ndarray]:
    """Per member camera (ordered by camera index): (classes, rows, cols) float32 scores."""
    return [entry.values() for entry in sorted(frame.maps, key=lambda e: e.camera)]


def heatlines_frame(header, heatlines: bearing.Heatlines, hard: bool = False) -> Heatlines:
    """The wire frame of a ``semloc_core.bearing.Heatlines`` (float32 scores)."""
    return Heatlines(header=header, classes=heatlines.classes, scores=heatlines.scores.astype(np.float32),
                     observed=heatlines.observed, hard=hard)


def heatlines_from_frame(frame: Heatlines) -> bearing.Heatlines:
    """The ``semloc_core.bearing.Heatlines`` of a wire frame (dequantised)."""
    return bearing.Heatlines(frame.classes, frame.values(), np.asarray(frame.observed, bool))


# ---------------------------------------------------------------------------------------------------- maps
def objectmap_frame(header, semantic_map: SemanticMap, frames: int = 0) -> ObjectMap:
    """The wire frame of a ``SemanticMap``."""
    return ObjectMap(header=header, class_names=semantic_map.class_names,
                     class_index=semantic_map.class_index.astype(np.int32),
                     positions=semantic_map.positions.astype(np.float64), has_height=semantic_map.has_height,
                     sizes=semantic_map.sizes.astype(np.float64), scores=semantic_map.scores.astype(np.float64),
                     existence=semantic_map.existence.astype(np.float64), bounds=semantic_map.bounds.astype(np.float64),
                     free_space=[np.asarray(p, np.float64) for p in semantic_map.free_space], frames=frames)


def voxel_map_frame(objects: ObjectMap, grid: VoxelGrid, score_volumes: np.ndarray, views: np.ndarray) -> VoxelMap:
    """The mapper's whole map: its objects' frame and the score volumes (C, nz, ny, nx) and view counts over
    ``grid`` they were extracted from."""
    return VoxelMap(**{name: getattr(objects, name) for name in ObjectMap.model_fields}, origin=grid.origin,
                    voxel_size=grid.voxel_size, score_volumes=np.asarray(score_volumes, np.float32),
                    views=np.asarray(views, np.float32))


def grid_of(frame: VoxelMap) -> VoxelGrid:
    """The voxel grid a VoxelMap's volumes lie on."""
    return VoxelGrid(np.asarray(frame.origin), frame.voxel_size, frame.score_volumes.shape[:0:-1])


def semantic_map_from_frame(frame: ObjectMap | ObjectMapV1) -> SemanticMap:
    """The ``SemanticMap`` of a wire frame (what a localizer fed by the mapper reads); a version-1 frame's objects
    are certain."""
    return SemanticMap(class_names=tuple(frame.class_names), class_index=np.asarray(frame.class_index, np.int64),
                       positions=np.array(frame.positions, float), sizes=np.array(frame.sizes, float),
                       scores=np.array(frame.scores, float), has_height=np.array(frame.has_height, bool),
                       bounds=np.array(frame.bounds, float),
                       free_space=tuple(np.array(p, float) for p in frame.free_space),
                       frame_id=frame.header.frame_id or "world",
                       existence=np.array(frame.existence, float) if isinstance(frame, ObjectMap) else None)


# ---------------------------------------------------------------------------------------------------- peers
# The odometry a worker takes unless configured otherwise: a robot's, not a car's. The localizer moves its particles
# by it, the loop-closure worker its key-frame gate and recorded poses: the same limits, or the two follow different
# motions.
DEFAULT_MAX_SPEED = 10.0
DEFAULT_MAX_TURN_RATE = 10.0
DEFAULT_MAX_ODOMETRY_DT = 10.0
SpeedLimit = Annotated[float, Field(gt=0, le=MAX_SPEED, description="odometry faster than this (m/s, |v| or "
                                    "|v_lateral|) is rejected ('range')")]
TurnRateLimit = Annotated[float, Field(gt=0, le=MAX_TURN_RATE, description="odometry turning faster than this "
                                       "(rad/s) is rejected ('range')")]
OdometryDtLimit = Annotated[float, Field(gt=0, le=MAX_ODOMETRY_DT, description="odometry covering a longer "
                                         "interval (s) is rejected ('range')")]


def check_odometry_limits(frame: Odometry, config) -> None:
    """Odometry within ``config``'s ``max_speed``, ``max_turn_rate`` and ``max_odometry_dt``, stamped within
    ``check_clock`` (FrameError ``range``): every consumer buffers it by stamp."""
    check_clock(frame)
    for name, value, limit in (("v", frame.v, config.max_speed), ("v_lateral", frame.v_lateral, config.max_speed),
                               ("omega", frame.omega, config.max_turn_rate), ("dt", frame.dt, config.max_odometry_dt)):
        if abs(value) > limit:
            raise FrameError(f"odometry {name} = {value:.6g} beyond the configured {limit:g}", reason="range")


# An ordered peer stream (one publisher, in order) is out of order only by a re-delivery: a frame further back than
# this is a new run of the stream, not a stale frame.
STREAM_RESTART_S = 1.0


def odometry_buffer() -> OdometryBuffer:
    """A worker's buffer of its odometry stream: a message more than STREAM_RESTART_S before the latest one starts
    it over (a session replayed again), rather than being dropped as motion already applied."""
    return OdometryBuffer(restart_after_ns=int(STREAM_RESTART_S * 1e9))


def restarted(last_stamp_ns: int | None, stamp_ns: int) -> bool:
    """Whether ``stamp_ns`` starts a stream over: more than STREAM_RESTART_S before the last stamp taken."""
    return last_stamp_ns is not None and last_stamp_ns - stamp_ns > STREAM_RESTART_S * 1e9


def check_clock(frame) -> None:
    """FrameError ``range`` for a frame stamped more than MAX_CLOCK_AHEAD past this machine's clock (zenoh's
    thread): no clock stamped it yet. Every input that orders its frames by stamp checks it (an odometry buffer, a
    pose buffer, a key-frame gate, an ordered stream): such a frame would be the newest for good, holding every later
    frame back behind it or making it look stale."""
    ahead_s = (frame.header.stamp_ns - time.time_ns()) * 1e-9
    if ahead_s > MAX_CLOCK_AHEAD:
        raise FrameError(f"stamped {ahead_s:.3g} s ahead of this clock (at most {MAX_CLOCK_AHEAD:g} s)",
                         reason="range")


class PeerStream:
    """The boundary check of an ordered stream another worker of this robot publishes (the localizer's estimates,
    the loop-closure worker's decisions; its robot the runtime checks on every input): ``check(frame)`` (zenoh's
    thread) refuses a frame stamped too far ahead (``check_clock``), and one that does not come after the last one
    accepted (``order``: stale or delivered twice); the same stamp again only as another frame of the stream
    (another ``seq``: the localizer announces a new initial pose at its last stamp). A frame more than
    STREAM_RESTART_S before the last one starts the stream over (a replay of an earlier recording, a source
    restarted, a clock set back); refusing it would refuse the whole new run, and let one frame stamped ahead silence
    the input until the robot's clock caught up with it."""

    def __init__(self):
        self.last: tuple[int, int] | None = None  # (stamp_ns, seq) of the last frame accepted
        self.lock = threading.Lock()  # zenoh may deliver on several threads

    def check(self, frame) -> None:
        check_clock(frame)
        header = frame.header
        with self.lock:
            last = self.last
            if last is not None and not restarted(last[0], header.stamp_ns) and (
                    header.stamp_ns < last[0] or (header.stamp_ns, header.seq) == last):
                raise FrameError(f"stamp {header.stamp_ns} (seq {header.seq}) not after the last frame's {last[0]} "
                                 f"(seq {last[1]})", reason="order")
            self.last = (header.stamp_ns, header.seq)


# ---------------------------------------------------------------------------------------------------- localization
def pose_estimate_frame(header, estimate: CorePoseEstimate, injected: int = 0, sample=None,
                        sample_weights=None, state: str | None = None, converged_std=None,
                        motion_std=None) -> PoseEstimate:
    """The wire frame of a ``semloc_core.localization.PoseEstimate`` (an initialised filter's); ``state``: the
    health monitor's judgement (``LocalizationState`` value); ``converged_std``, ``motion_std``: the filter's
    converged spread and the noise of the increment it predicted with (schemas.localization)."""
    sym = lambda m: 0.5 * (np.asarray(m, float) + np.asarray(m, float).T)  # noqa: E731 - rounding asymmetries
    return PoseEstimate(header=header, x=float(estimate.pose[0]), y=float(estimate.pose[1]),
                        theta=float(estimate.pose[2]), covariance=sym(estimate.covariance), status=estimate.status.value,
                        state=state,
                        particles=int(estimate.n_particles), effective_sample_size=float(estimate.effective_sample_size),
                        clusters=max(1, int(estimate.n_clusters)), cluster_weight=min(1.0, float(estimate.cluster_weight)),
                        recovery_ratio=float(estimate.recovery_ratio), injected=int(injected),
                        mean=np.asarray(estimate.mean_pose, float), mean_covariance=sym(estimate.mean_covariance),
                        sample=sample, sample_weights=sample_weights, converged_std=_pair(converged_std),
                        motion_std=_pair(motion_std))


def _pair(values) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=np.float64).reshape(2)


def past_poses_frame(header, anchor_stamp_ns: int, poses: list, bounds) -> tuple[PastPoses | None, int]:
    """The wire frame of a backward pass's (stamp, pose, covariance), newest first, anchored at ``anchor_stamp_ns``;
    poses outside the map's ``bounds`` ((2, 2): min, max of x, y) are left out. Returns the frame (None: no pose
    left) and how many were left out."""
    bounds = np.asarray(bounds, float)
    inside = [(s, p, c) for s, p, c in poses if np.all(bounds[0] <= p[:2]) and np.all(p[:2] <= bounds[1])]
    if not inside:
        return None, len(poses)
    sym = lambda m: 0.5 * (np.asarray(m, float) + np.asarray(m, float).T)  # noqa: E731 - rounding asymmetries
    frame = PastPoses(header=header, anchor_stamp_ns=int(anchor_stamp_ns),
                      stamps_ns=np.array([s for s, _, _ in inside], np.int64),
                      poses=np.array([p for _, p, _ in inside], float),
                      covariances=np.array([sym(c) for _, _, c in inside], float))
    return frame, len(poses) - len(inside)


# ---------------------------------------------------------------------------------------------------- loop closure
def loop_features_frame(header, features: FeatureSequence) -> LoopFeatures:
    """The wire frame of one frame's ``FeatureSequence`` (bearings, descriptors, pixels and rig members)."""
    return LoopFeatures(header=header, bearings=features.bearings, descriptors=features.descriptors,
                        points=features.points, camera_index=features.camera_index)


def features_from_frame(frame: LoopFeatures) -> FeatureSequence:
    """The ``FeatureSequence`` of a ``LoopFeatures`` frame (FrameError when the features are not in bearing
    order)."""
    from semloc_core.loopclosure.features import FeatureSequence  # its numba kernels: only where features are read

    try:
        return FeatureSequence(np.asarray(frame.bearings), np.asarray(frame.descriptors), frame.camera_index,
                               frame.points)
    except ValueError as error:
        raise FrameError(str(error)) from None


def _pairs(rows) -> np.ndarray:
    return np.array(rows, np.int64).reshape(-1, 2)


def similarity_row_frame(header, result: FrameResult, features: int) -> SimilarityRow:
    """The similarity of a new frame to its candidates (one ``LoopClosureEngine.add_frame`` result)."""
    return SimilarityRow(header=header, frame=result.frame, candidates=result.candidates,
                         retrieval_scores=result.retrieval_scores.astype(np.float32),
                         similarity=result.similarity.astype(np.float32), features=features)


def loop_closure_frame(header, result: FrameResult, stamps_ns: np.ndarray,
                       loop_poses: np.ndarray | None = None, revised: dict | None = None) -> LoopClosure:
    """The loop-closure decision of one ``add_frame`` result; ``stamps_ns`` each frame's capture stamp. The
    precision the engine expects of its loops and their belief threshold go with it; ``loop_poses`` (loops, 3) the
    pose each loop's frame was seen at while the localizer was localized (NaN: not); ``revised`` replaces the
    result's revisions (frame -> its loops now)."""
    revised = result.revised if revised is None else revised
    decision = result.decision
    poses = None if loop_poses is None else np.asarray(loop_poses, np.float64).reshape(-1, 3)
    return LoopClosure(header=header, frame=result.frame, status=result.status.value, loops=result.loops,
                       loop_stamps_ns=stamps_ns[result.loops], beliefs=result.loop_beliefs.astype(np.float32),
                       node=result.node, revised=[Revision(frame=f, loops=np.asarray(l, np.int64))
                                                  for f, l in sorted(revised.items())],
                       expected_precision=None if decision is None else decision.expected_precision,
                       decision_threshold=(decision.threshold if decision is not None
                                           and np.isfinite(decision.threshold) else None), loop_poses=poses)


def take_revisions(due: dict, revised: dict, limit: int) -> dict:
    """The revisions one LoopClosure carries: ``revised`` (frame -> its loops now) joins those ``due`` from earlier
    frames (a newer revision of a frame replaces the older), and the ``limit`` earliest frames leave ``due``."""
    due.update(revised)
    return {frame: due.pop(frame) for frame in sorted(due)[:limit]}


def topomap_update_frame(header, update: MapUpdate, frames: int, nodes: int,
                         poses: dict[int, tuple] | None = None) -> TopoMapUpdate:
    """The change one frame made to the topological map (of ``frames`` frames and ``nodes`` places now); ``poses``:
    frame -> its new pose (NaN: withdrawn), the frames whose pose changed."""
    posed = sorted(poses) if poses else []
    return TopoMapUpdate(header=header, frames=frames, nodes=nodes, assigned=_pairs(update.assigned),
                         new_nodes=_pairs(update.new_nodes), edges_added=_pairs(update.edges_added),
                         edges_removed=_pairs(update.edges_removed),
                         posed_frames=np.array(posed, np.int64) if posed else None,
                         frame_poses=np.array([poses[f] for f in posed], np.float64).reshape(-1, 3) if posed else None)


def topomap_frame(header, topomap: IncrementalTopoMap, stamps_ns: np.ndarray,
                  frame_poses: np.ndarray | None = None) -> TopoMap:
    """The whole topological map; ``stamps_ns`` each frame's capture stamp, ``frame_poses`` (frames, 3) each frame's
    estimated planar pose (NaN rows: none) when known."""
    snapshot = topomap.snapshot()
    poses = None if frame_poses is None else np.asarray(frame_poses, np.float64).reshape(-1, 3)[snapshot.keyframes]
    return TopoMap(header=header, keyframes=snapshot.keyframes, keyframe_stamps_ns=stamps_ns[snapshot.keyframes],
                   frame_node=snapshot.frame_node, edges=snapshot.edges, transitions=snapshot.transitions,
                   keyframe_poses=poses)


def topological_map_from_frame(frame: TopoMap) -> tuple[TopologicalMap, np.ndarray]:
    """The core map of a TopoMap frame (node ids 0..n-1) and its key-frames' poses (n, 3), NaN where unknown."""
    topomap = TopologicalMap(np.arange(len(frame.keyframes)), frame.keyframes, frame.frame_node, frame.edges,
                             frame.transitions)
    poses = frame.keyframe_poses if frame.keyframe_poses is not None else np.full((len(frame.keyframes), 3), np.nan)
    return topomap, np.asarray(poses, np.float64)