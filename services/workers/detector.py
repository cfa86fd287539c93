"""Detector: Image in; per-class Heatmaps and Heatlines out (thesis §4.3, §4.4.2, §4.6, §5.3).

With ``prune`` a template detector matches each pyramid level only on the image rows where an object of that
level's size can stand (semloc_core.detection.pruning), from the localizer's latest localized PoseEstimate, the
image's attitude, the camera's height (a 3-D pose stream's, ``height_pose``, else the configured one) and the
configured support plane; without such a pose every level runs everywhere.

With ``publish_levels`` a window detector with a pyramid (kind: linear) also publishes its per-level maps
(HeatmapLevels), whose max over levels is the Heatmaps frame: the mapper's scale-selected back-projection reads them.

The detector itself is configured in a few lines (docs/detection.md): template library, OpenCV's shipped
detectors, the user's ONNX model or Python box detector. Heatlines need the camera model: from ``calibration``
(a YAML file) or the camera worker's ``CameraModel`` (subscribed, and queried at start). The camera publishes its
model before its first image, but on another key: a detector that met the camera after the model went out gets it
from its query's reply, after the first image. The newest image without a model waits (its heatmaps published) and
gets its heatlines when the model comes; an older one is skipped (``no camera model yet``, degraded).
"""

from __future__ import annotations

from collections import deque
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas import CameraModel, FrameError, Image, Pose3D, keys
from schemas.detection import HeatmapLevels, Heatlines, Heatmaps
from schemas.localization import PoseEstimate
from semloc_core import bearing
from semloc_core.camera import PinholeCamera, members
from semloc_core.detection.config import build_detector
from semloc_core.detection.heatlines import HeatlineProjector
from semloc_core.detection.heatmaps import overlay
from semloc_core.detection.pruning import PruneParams, build_pruner, height_from_pose
from semloc_core.detection.warmup import warm_up
from semloc_core.io.camera_model import load_camera
from semloc_core.io.semantic_map import load_semantic_map
from services.frames import (DEFAULT_MAX_IMAGE_PIXELS, ImagePixelLimit, bgr_images, camera_from_frame,
                             camera_heatmap_levels, camera_heatmaps, check_image, extrinsic_overrides,
                             heatlines_frame)
from services.runtime import Worker, WorkerConfig


HEIGHT_POSES = 16   # the 3-D poses kept to find the one nearest an image's stamp


class PruneSettings(BaseModel):
    """Where objects can be, for ``prune`` (docs/detection.md, "Pruning levels"); the last three are
    ``semloc_core.detection.pruning.PruneParams``."""

    model_config = ConfigDict(extra="forbid")
    map: str = Field(description="object map (semloc.semantic_map) whose objects' extents give each class's sizes")
    support_z: float = Field(ge=-100.0, le=100.0, description="height of the plane the objects stand on (m)")
    support_polygon: list[tuple[float, float]] | None = Field(
        None, min_length=3, max_length=1000, description="its outline, world (x, y) (m); none: unbounded")
    camera_height: float = Field(ge=-100.0, le=100.0, description="camera centre above the floor (m)")
    camera_height_tolerance: float = Field(PruneParams.camera_height_tolerance, ge=0.0, le=5.0,
                                           description="the camera's height is known to within this (m)")
    height_pose: bool = Field(False, description="the camera's height for each image from the body's Pose3D (input "
                                                 "height_pose: ground truth; rewire inputs.height_pose.key to a "
                                                 "visual-inertial odometry's) instead of camera_height")
    pose_height_tolerance: float = Field(PruneParams.pose_height_tolerance, ge=0.0, le=5.0,
                                         description="that pose's height is right to within this (m)")
    vertical_speed: float = Field(PruneParams.vertical_speed, ge=0.0, le=10.0,
                                  description="the camera moves up and down at most this fast (m/s): the tolerance "
                                              "grows with the time between the pose and the image")
    size_factor: float = Field(PruneParams.size_factor, ge=1.0, le=4.0,
                               description="a level runs where the expected size is within this factor of its own")
    polygon_margin: float = Field(PruneParams.polygon_margin, ge=0.0, le=10.0,
                                  description="the outline grown by this (m): the pose's error and lag")
    max_pose_age_s: float = Field(2.0, gt=0.0, le=60.0,
                                  description="a pose older than this before the image is not used (every level runs)")
    max_pose_distance: float = Field(100.0, gt=0.0, le=1e6,
                                     description="a pose farther than this from the outline (or the origin) is "
                                                 "rejected (m)")

    def params(self) -> PruneParams:
        return PruneParams(size_factor=self.size_factor, polygon_margin=self.polygon_margin,
                           camera_height_tolerance=self.camera_height_tolerance,
                           pose_height_tolerance=self.pose_height_tolerance, vertical_speed=self.vertical_speed)


class DetectorConfig(WorkerConfig):
    camera: str = Field("front", description="camera whose images are processed")
    detector: dict = Field(default_factory=dict, description="detector configuration (docs/detection.md)")
    detector_file: str | None = Field(None, description="YAML file with the detector configuration")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    bins: int = Field(360, ge=4, le=36000, description="bearing bins of the heatlines over the full turn")
    heatmap_dtype: Literal["uint8", "float16", "float32"] = Field("uint8", description="heatmap values on the wire")
    heatmap_pool: int = Field(1, ge=1, le=64, description="max-pool heatmaps by this factor before publishing")
    rerun_every: int = Field(1, ge=0, description="log heatmap overlays every n-th frame (0: never)")
    overlay_width: int = Field(320, ge=0, le=16384,
                               description="heatmap overlays are logged at most this wide (pixels; 0: the image's "
                                           "width); the heatmaps' own grid is coarser than the image")
    publish_levels: bool = Field(False, description="also publish a window detector's per-level heatmaps "
                                                    "(HeatmapLevels, for the mapper's scale_depth_file)")
    max_image_pixels: ImagePixelLimit = DEFAULT_MAX_IMAGE_PIXELS
    prune: PruneSettings | None = Field(None, description="match each pyramid level only where objects of its size "
                                                          "can be, from the localizer's pose (template detector)")

    @model_validator(mode="after")
    def _one_detector(self):
        if bool(self.detector) == bool(self.detector_file):
            raise ValueError("give exactly one of 'detector' (a mapping) or 'detector_file' (a YAML path)")
        return self


NO_MODEL = "no camera model yet: no heatlines"  # the reason an image without the camera model is skipped under


class Detector(Worker):
    """Soft object detection: per-class heatmaps and heatlines for every image."""

    Config = DetectorConfig

    def setup(self) -> None:
        c = self.config
        self.detector = build_detector(c.detector_file or c.detector)
        self.classes = tuple(self.detector.classes)
        self.detector_kind = str(c.detector.get("kind", "")) if c.detector else "file"
        self.logger.info("detector %s: classes %s", self.detector_kind, ", ".join(self.classes))
        self.camera = None
        self.projector = None
        # the newest image without a camera model: (the frame, its heatmaps, extrinsics), its heatlines to come
        self.waiting_for_model = None
        if c.calibration:
            self._set_camera(load_camera(c.calibration))
        self.heatmaps_out = self.output("heatmaps", keys.detector_heatmaps(self.robot), Heatmaps, bulk=True)
        self.heatlines_out = self.output("heatlines", keys.detector_heatlines(self.robot), Heatlines)
        self.levels_out = None
        if c.publish_levels:
            if not hasattr(self.detector, "level_heatmaps"):
                raise ValueError(f"publish_levels needs a window detector with pyramid levels (kind: linear); "
                                 f"{self.detector_kind} has none")
            self.level_scales = tuple(float(s) for s in self.detector.model.scales)
            self.levels_out = self.output("heatmap_levels", keys.detector_heatmap_levels(self.robot),
                                          HeatmapLevels, bulk=True)
        self.pruner, self.pose, self.prune_counts, self.prune_last = None, None, [0, 0, 0], ""
        if c.prune is not None:
            if not hasattr(self.detector, "level_object_px"):
                raise ValueError(f"prune needs a template detector (kind: templates); {self.detector_kind} has no "
                                 f"pyramid levels to prune")
            self.prune_map = load_semantic_map(c.prune.map)
            anchor = np.asarray(c.prune.support_polygon or [(0.0, 0.0)], float)
            self.prune_anchor = anchor.mean(axis=0)
            # the latest pose prunes: none of a link gap's (recover=False)
            pose_input = self.input("pose", keys.localizer_pose(self.robot), PoseEstimate, self.on_pose,
                                    policy="latest", depth=1, check=self.check_pose, recover=False)
            pose_input.drives_output = False  # a pose asks for no heatmaps: only images are owed an output
            self.height_poses = deque(maxlen=HEIGHT_POSES)   # (stamp, T_world_body, height sigma), newest last
            if c.prune.height_pose:
                height_input = self.input("height_pose", keys.groundtruth_pose(self.robot), Pose3D,
                                          self.on_height_pose, policy="latest", depth=HEIGHT_POSES,
                                          check=self.check_pose, recover=False)
                height_input.drives_output = False
            if self.camera is not None:
                self._set_pruner()
        model_key = keys.camera_model(self.robot, c.camera)
        if not c.calibration:
            self.latest_input("camera_model", model_key, CameraModel, self.on_camera_model)
        self.input("image", keys.camera_image(self.robot, c.camera), Image, self.on_image, policy="latest", depth=2,
                   check=self.check_image)
        self.frames = 0
        # numba compiles on a kernel's first call: now, not on the first frames while the worker reports running
        self.compile_kernels(warm_up, self.detector, levels=self.levels_out is not None, prune=c.prune is not None,
                             bins=c.bins)

    def _set_camera(self, camera) -> None:
        self.camera = camera
        self.projector = HeatlineProjector(camera, self.classes, bearing.BearingGrid(self.config.bins))
        if self.config.prune is not None and hasattr(self, "prune_map"):
            self._set_pruner()

    def _set_pruner(self) -> None:
        p = self.config.prune
        if not isinstance(self.camera, PinholeCamera):
            self.pruner = None
            self.logger.warning("prune: needs a single pinhole camera, not %s: every level runs everywhere",
                                type(self.camera).__name__)
            return
        self.pruner = build_pruner(self.detector, self.camera, self.prune_map, p.support_z, p.camera_height,
                                   p.support_polygon, p.params())

    def check_pose(self, frame: PoseEstimate | Pose3D) -> None:
        """A pose to prune by must be near the support polygon (a pose elsewhere is another map's). No
        ``check_clock``: neither input orders its poses by stamp. The latest pose replaces the last whatever its
        stamp and serves only images within ``max_pose_age_s`` of it; a height pose serves only as the nearest in
        time of the last HEIGHT_POSES arrivals. A pose stamped ahead serves no image and is gone with the next ones."""
        x, y = (frame.position[:2] if isinstance(frame, Pose3D) else (frame.x, frame.y))
        distance = float(np.hypot(x - self.prune_anchor[0], y - self.prune_anchor[1]))
        if distance > self.config.prune.max_pose_distance:
            raise FrameError(f"pose {distance:.6g} m from the support polygon, beyond max_pose_distance "
                             f"{self.config.prune.max_pose_distance:g} m", reason="pose_range")

    def on_pose(self, frame: PoseEstimate) -> None:
        self.pose = frame if frame.localized() else None   # not localized: prune by nothing

    def on_height_pose(self, frame: Pose3D) -> None:
        sigma = 0.0 if frame.covariance is None else float(np.sqrt(frame.covariance[2, 2]))
        self.height_poses.append((frame.header.stamp_ns, frame.matrix(), sigma))

    def _height(self, stamp_ns: int, T_body_cam) -> tuple[float, float] | None:
        """(camera height, tolerance) from the 3-D pose nearest the image in time, or None without one."""
        if not self.height_poses:
            return None
        pose_stamp, T_world_body, sigma = min(self.height_poses, key=lambda entry: abs(entry[0] - stamp_ns))
        T_body_cam = self.camera.T_body_cam if T_body_cam is None else T_body_cam
        height = height_from_pose(T_world_body, T_body_cam, (stamp_ns - pose_stamp) * 1e-9, self.pruner.params, sigma)
        if not self.pruner.agrees(height):   # counted; the configured height is used
            self.prune_counts[2] += 1
            return None
        return height

    def _rows(self, frame: Image, images):
        """The levels' rows for this image, or None (every level everywhere): a localized pose no older than
        ``max_pose_age_s`` before the image (one frame behind it: the localizer waits for these heatlines)."""
        pose = self.pose
        if self.pruner is None or pose is None or len(images) != 1:
            return None
        age_s = (frame.header.stamp_ns - pose.header.stamp_ns) * 1e-9
        if not -self.config.prune.max_pose_age_s <= age_s <= self.config.prune.max_pose_age_s:
            return None
        T_body_cam = extrinsic_overrides(images)[0]
        return self.pruner.rows((pose.x, pose.y, pose.theta), T_body_cam, self._height(frame.header.stamp_ns,
                                                                                         T_body_cam))

    def status_details(self) -> dict:
        """With ``prune``: frames pruned and matched in full, height poses not used (the camera's height they give
        disagrees with the configured one), and the last frame's levels and rows with their share of the full
        work."""
        counts = getattr(self, "prune_counts", None)   # the status thread may ask before setup
        if self.config.prune is None or counts is None:
            return {}
        return {"prune_frames": counts[0], "prune_full_frames": counts[1], "prune_height_disagreed": counts[2],
                "prune_last": self.prune_last}

    def on_camera_model(self, frame: CameraModel) -> None:
        camera = camera_from_frame(frame)
        if self.camera is None or not _same_camera(camera, self.camera):
            self.logger.info("camera model received: %d camera(s)", len(members(camera)))
            self._set_camera(camera)
            self.resumed(NO_MODEL)
        if self.waiting_for_model is not None:
            image, per_camera, extrinsics = self.waiting_for_model
            self.waiting_for_model = None
            try:
                check_image(image, self.config.max_image_pixels, self.camera)
            except FrameError as error:  # taken before there was a model to check it against
                self.logger.warning("the image that waited for the camera model does not fit it: %s", error)
                self.skipped(NO_MODEL)
            else:
                self._publish_heatlines(image.header.stamp_ns, per_camera, extrinsics)

    def check_image(self, frame: Image) -> None:
        """Before anything is decoded (zenoh's thread): the size limit, and the camera model when there is one."""
        check_image(frame, self.config.max_image_pixels, self.camera)

    def on_image(self, frame: Image) -> None:
        check_image(frame, self.config.max_image_pixels, self.camera)  # again: the camera model may have changed
        images, pixels = bgr_images(frame)
        per_camera, per_camera_levels = [], []
        rows = None if self.config.prune is None else self._rows(frame, images)
        if self.config.prune is not None:
            self.prune_counts[rows is None] += 1
            self.prune_last = "all levels" if rows is None else f"share {self.pruner.share(rows):.2f}: " + " ".join(
                f"{scale:g}:{first}-{last}" for scale, (first, last) in rows.items())
        for bgr in pixels:
            if rows is not None:
                per_camera.append(self.detector.heatmaps(bgr, rows=rows))
            elif self.levels_out is None:
                per_camera.append(self.detector.heatmaps(bgr))
            else:  # one pass: the heatmap is the max of the level maps (the logistic is monotonic)
                levels = self.detector.level_heatmaps(bgr)
                per_camera_levels.append(levels)
                per_camera.append(levels.max(axis=1))
        stamp, frame_id = frame.header.stamp_ns, frame.header.frame_id
        c = self.config
        maps = [camera_heatmaps(image, heatmaps, c.heatmap_dtype, c.heatmap_pool)
                for image, heatmaps in zip(images, per_camera)]
        self.heatmaps_out.publish(Heatmaps(header=self.heatmaps_out.header(stamp_ns=stamp, frame_id=frame_id),
                                           classes=self.classes, detector=self.detector_kind[:64], maps=maps))
        if self.levels_out is not None:
            maps = [camera_heatmap_levels(image, levels, c.heatmap_dtype, c.heatmap_pool)
                    for image, levels in zip(images, per_camera_levels)]
            self.levels_out.publish(HeatmapLevels(header=self.levels_out.header(stamp_ns=stamp, frame_id=frame_id),
                                                  classes=self.classes, detector=self.detector_kind[:64],
                                                  level_scales=self.level_scales, maps=maps))
        heatlines = None
        if self.projector is not None:
            heatlines = self._publish_heatlines(stamp, per_camera, extrinsic_overrides(images))
        else:
            if self.waiting_for_model is not None:  # a newer image replaces it: its heatlines are lost
                self.skipped(NO_MODEL)
            self.waiting_for_model = (frame, per_camera, extrinsic_overrides(images))
        if self.rerun is not None and self.config.rerun_every and self.frames % self.config.rerun_every == 0:
            self._log(frame.header, images, pixels, per_camera, heatlines)
        self.frames += 1

    def _publish_heatlines(self, stamp_ns: int, per_camera, extrinsics):
        heatlines = self.projector.project(per_camera, T_body_cam=extrinsics)
        self.heatlines_out.publish(heatlines_frame(self.heatlines_out.header(stamp_ns=stamp_ns, frame_id="body"),
                                                   heatlines))
        return heatlines

    def _log(self, header, images, pixels, per_camera, heatlines) -> None:
        import rerun as rr

        quality = self.config.rerun.jpeg_quality or 80
        for image, bgr, heatmaps in zip(images, pixels, per_camera):
            prefix = "heatmap" if len(images) == 1 else f"heatmap/camera{image.camera}"
            bgr = _shrunk(bgr, self.config.overlay_width)
            for name, heatmap in zip(self.classes, heatmaps):
                ok, buffer = cv2.imencode(".jpg", overlay(bgr, heatmap), [cv2.IMWRITE_JPEG_QUALITY, quality])
                if ok:
                    self.rerun_log(f"{prefix}/{name}", rr.EncodedImage(contents=buffer.tobytes(),
                                                                       media_type="image/jpeg"), header=header)
        if heatlines is not None:
            for name, scores in zip(self.classes, heatlines.scores):
                self.rerun_log(f"heatlines/{name}", rr.BarChart(np.where(heatlines.observed, scores, 0.0)),
                               header=header)


def _shrunk(image: np.ndarray, width: int) -> np.ndarray:
    """The image at most ``width`` pixels wide (0: as it is). Why: five JPEG overlays a frame cost ~15 ms of CPU at
    640 x 480, about as much as the detection; at 320 wide ~3 ms, and a 4-pixel-block heatmap loses nothing."""
    height, full = image.shape[:2]
    if width == 0 or full <= width:
        return image
    return cv2.resize(image, (width, max(1, round(height * width / full))), interpolation=cv2.INTER_AREA)


def _same_camera(a, b) -> bool:
    first, second = members(a), members(b)
    if len(first) != len(second):
        return False
    for x, y in zip(first, second):
        if type(x) is not type(y) or (x.width, x.height) != (y.width, y.height):
            return False
        if not np.allclose(x.T_body_cam, y.T_body_cam):
            return False
        if hasattr(x, "K") and not (np.allclose(x.K, y.K) and np.array_equal(x.dist, y.dist)):
            return False
        if hasattr(x, "lat_top") and (x.lat_top, x.lat_bottom) != (y.lat_top, y.lat_bottom):
            return False
    return True


WORKER = Detector
