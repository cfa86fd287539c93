"""Mapper: Heatmaps + camera poses in; the semantic object map (ObjectMap) out (thesis ch. 5, docs/mapping.md).

With ``scale_depth_file`` it takes the detector's HeatmapLevels instead and back-projects each level only into the
depth band where the detector's window fits the class (scale-selected back-projection, docs/mapping.md).

Every Heatmaps frame is matched by capture stamp to a pose (Pose3D of the body - ground truth, odometry - or a
planar Pose2D, e.g. the localizer's), back-projected into the voxel grid with the camera model (the camera
worker's CameraModel, or a calibration YAML), and the extracted objects are published periodically and on request.
The voxel state is snapshotted (``--state-dir``) and restored on start.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from pydantic import Field, field_validator, model_validator

from schemas import CameraModel, FrameError, Pose2D, Pose3D, keys
from schemas.detection import HeatmapLevels, Heatmaps
from schemas.limits import MAX_COORDINATE
from schemas.mapping import ObjectMap
from semloc_core.camera import PinholeCamera, members
from semloc_core.detection.config import detector_classes
from semloc_core.io.camera_model import load_camera
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.mapping import ExtractionConfig, MapperConfig, VoxelGrid, VoxelMapper
from semloc_core.mapping.poses import Match, PoseBuffer
from semloc_core.mapping.existence import ExistenceCurve
from semloc_core.mapping.scale_depth import calibration_mismatch, level_depths
from services.config import ConfigError
from services.frames import camera_from_frame, check_fits, objectmap_frame, pose_matrix
from services.runtime import Worker, WorkerConfig
from services.state import State


class MapperWorkerConfig(WorkerConfig):
    camera: str = Field("front", description="camera whose CameraModel is used (keys semloc/<robot>/camera/<camera>)")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    pose_key: str | None = Field(None, description="Pose3D/Pose2D stream (default: semloc/<robot>/groundtruth/pose)")
    pose_frame: str = Field("body", description="'body': poses are T_world_body; 'camera': T_world_cam directly")
    pose_tolerance_s: float = Field(0.05, ge=0, description="largest pose gap a heatmap stamp is interpolated over")
    pending: int = Field(64, ge=1, description="heatmap frames waiting for their pose, at most")
    classes: list[str] | None = Field(None, description="classes to map; heatmaps of another class set are rejected "
                                      "('classes'). Give them, or detector_file")
    detector_file: str | None = Field(None, description="the detector configuration whose classes are mapped (the "
                                      "detector's detector_file), instead of classes")
    world_extent: float = Field(1000.0, gt=0, le=MAX_COORDINATE, description="poses farther than this from the "
                                "world origin (m, along any axis) are rejected ('range')")
    grid_min: list[float] = Field([-1.0, -1.0, 0.0], description="grid box minimum corner (world, metres)")
    grid_max: list[float] = Field([1.0, 1.0, 0.7], description="grid box maximum corner (world, metres)")
    voxel_size: float = Field(0.01, gt=0, description="voxel edge, metres")
    heatmap_downsample: int = Field(1, ge=1, description="area-average heatmaps by this factor first")
    min_depth: float = Field(0.05, gt=0)
    max_depth: float | None = Field(None, gt=0, description="metres along the optical axis (None: unlimited)")
    tile_size: int | None = Field(None, ge=1, description="lazily allocated column tiles (large spaces)")
    memory_limit_mb: float = Field(4096.0, gt=0)
    heatmap_background: str = Field("none", description="'median': subtract each class's per-frame median heat; "
                                                         "'surprisal': -log of the frame's fraction of cells as hot")
    heatmap_llr: dict[str, list[float]] = Field(
        default_factory=dict, description="per-class heat log-likelihood ratios over scores 0..1: accumulate evidence "
                                          "('llr' a semloc eval mapping calibration fits with accumulate llr)")
    scale_depth_file: str | None = Field(
        None, description="JSON with a fitted scale-depth calibration (what `semloc eval mapping` "
                          "fits with mapper.scale_depth): map the detector's HeatmapLevels (detector publish_levels) "
                          "scale-selected instead of its Heatmaps")
    level_reach: int = Field(0, ge=0, description="scale-selected: each level also takes the max of the levels "
                                                  "within this many steps of it")
    support_z: float | None = Field(None, description="height of the surface objects rest on (e.g. the table top)")
    support_polygon: list[list[float]] | None = Field(
        None, description="(x, y) outline of that surface: object centres lie over it")
    resting: bool = Field(False, description="objects rest on the support: centre height halfway between "
                                             "support_z and the top of the object's score region")
    threshold: float = Field(0.5, description="extraction threshold on the score volume")
    normalise: bool = Field(True, description="score = mean heat over the frames that saw a voxel")
    min_views: int = Field(5, ge=1)
    object_size: list[float] = Field([0.2, 0.2, 0.2], description="default bounding volume (x, y, z), metres")
    class_sizes: dict[str, list[float]] = Field(default_factory=dict, description="per-class bounding volumes")
    extent_fraction: float = Field(0.5, gt=0, lt=1)
    class_scales: dict[str, float] = Field(default_factory=dict,
                                           description="per-class score divisors (a semloc eval mapping calibration)")
    cross_class: bool = Field(False, description="an object suppresses other classes' candidates on its core")
    tophat: float = Field(0.0, ge=0, description="> 0: white top-hat by this many bounding volumes before NMS")
    existence: dict | None = Field(None, description="p(real | score) of the objects (an existence curve of "
                                                     "a semloc eval mapping calibration: reference, intercept, "
                                                     "slope); none: every object certain")
    extraction_file: str | None = Field(
        None, description="JSON of a fitted extraction (`semloc eval mapping`'s calibration.fit, a demo world's "
                          "mapper_extraction.json): its detector entry for this score mode replaces threshold, "
                          "class_scales, tophat, cross_class, resting, class_sizes and existence")
    position: str = Field("peak", description="object position: 'peak' (refined maximum), 'centroid' (of the "
                                              "score above extent_fraction of the peak) or 'mode' (maximum of that "
                                              "score smoothed at mode_bandwidth)")
    mode_bandwidth: float = Field(0.02, gt=0, description="position 'mode': smoothing standard deviation, metres")
    prominence: float = Field(0.0, ge=0, lt=1, description="> 0: a candidate joined to a stronger object of its "
                                                           "class by voxels above this fraction of its peak is "
                                                           "that object's shoulder (docs/mapping.md)")
    publish_period_s: float = Field(2.0, gt=0, description="ObjectMap publication period (when the map changed)")
    rerun_hot_fraction: float = Field(0.6, gt=0, le=1, description="hot voxels logged: >= this of the class max")
    rerun_max_points: int = Field(50_000, ge=0)

    @field_validator("grid_min", "grid_max", "object_size")
    @classmethod
    def _three(cls, value):
        if len(value) != 3:
            raise ValueError("needs 3 values (x, y, z)")
        return value

    @model_validator(mode="after")
    def _check(self):
        if self.pose_frame not in ("body", "camera"):
            raise ValueError("pose_frame must be 'body' or 'camera'")
        if self.classes is not None and self.detector_file is not None:
            raise ValueError("give the classes to map either as classes or as detector_file, not both")
        if self.detector_file is not None:
            self.classes = list(detector_classes(self.detector_file))
            self.detector_file = None  # resolved: the config snapshot of the run lists the classes
        if self.classes is not None and (not self.classes or len(set(self.classes)) != len(self.classes)):
            raise ValueError(f"classes must be distinct names, at least one, got {self.classes}")
        VoxelGrid.from_bounds(self.grid_min, self.grid_max, self.voxel_size)  # raises with the reason
        if self.extraction_file:
            for name, value in fitted_extraction(self.extraction_file, self.normalise).items():
                setattr(self, name, value)
            if self.resting and self.support_z is None:
                raise ValueError(f"extraction_file {self.extraction_file} was fitted with resting heights: give "
                                 f"support_z, the height of the surface the objects rest on")
        if self.scale_depth_file:
            self.scale_depth()
            if self.heatmap_llr:
                raise ValueError("scale_depth_file and heatmap_llr do not combine (the ratios are fitted on "
                                 "single maps)")
        self.extraction()
        self.mapper_config()
        return self

    def scale_depth(self) -> dict | None:
        """The fitted depth per scale of ``scale_depth_file``: {"scales": [...], "classes": {name: metres per
        focal pixel per unit scale}}, or None without the file."""
        return None if not self.scale_depth_file else fitted_scale_depth(self.scale_depth_file)

    def mapper_config(self) -> MapperConfig:
        return MapperConfig(heatmap_downsample=self.heatmap_downsample, min_depth=self.min_depth,
                            max_depth=math.inf if self.max_depth is None else self.max_depth,
                            tile_size=self.tile_size, memory_limit_mb=self.memory_limit_mb,
                            heatmap_background=self.heatmap_background, heatmap_llr=dict(self.heatmap_llr),
                            level_reach=self.level_reach)

    def extraction(self) -> ExtractionConfig:
        return ExtractionConfig(threshold=self.threshold, normalise=self.normalise, min_views=self.min_views,
                                object_size=tuple(self.object_size),
                                class_sizes={k: tuple(v) for k, v in self.class_sizes.items()},
                                extent_fraction=self.extent_fraction, class_scales=dict(self.class_scales),
                                cross_class=self.cross_class, tophat=self.tophat, support_z=self.support_z,
                                support_polygon=(None if self.support_polygon is None
                                                 else tuple(tuple(v) for v in self.support_polygon)),
                                position=self.position, mode_bandwidth=self.mode_bandwidth, resting=self.resting,
                                prominence=self.prominence,
                                existence=None if self.existence is None else ExistenceCurve.from_document(
                                    self.existence))


# The fitted settings a calibration file sets, and their types (semloc eval mapping's calibration.fit writes them).
FITTED_EXTRACTION = {"threshold": float, "class_scales": dict, "tophat": float, "cross_class": bool,
                     "resting": bool, "class_sizes": dict, "existence": ExistenceCurve}


def _positive(value, count: int) -> bool:
    """``value`` is one positive finite number (count 1) or a list of ``count`` of them."""
    values = [value] if count == 1 else value
    return (isinstance(values, list) and len(values) == count
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                    for v in values))


def fitted_extraction(path: str, normalise: bool) -> dict:
    """The extraction settings fitted in ``path`` for the detector's score mode (normalised or sum)."""
    import json
    from pathlib import Path

    mode = "normalised" if normalise else "sum"
    try:
        document = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"extraction_file {path}: cannot read it ({error})") from None
    source = document.get("detector") if isinstance(document, dict) else None
    entry = source.get(mode) if isinstance(source, dict) else None
    if not isinstance(entry, dict):
        raise ValueError(f"extraction_file {path}: no 'detector' -> '{mode}' entry (is it from semloc eval mapping's "
                         f"calibration.fit with detector heatmaps?)")
    settings = {}
    for name, kind in FITTED_EXTRACTION.items():
        if name not in entry:
            continue
        value = entry[name]
        if kind is ExistenceCurve:
            try:
                settings[name] = ExistenceCurve.from_document(value).to_document()
            except ValueError as error:
                raise ValueError(f"extraction_file {path}: {mode}.{name}: {error}") from None
        elif kind is float and isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            settings[name] = float(value)
        elif kind is bool and isinstance(value, bool):
            settings[name] = value
        elif kind is dict and isinstance(value, dict) and all(_positive(v, 1 if name == "class_scales" else 3)
                                                               for v in value.values()):
            settings[name] = value
        else:
            what = {"class_scales": "{class: positive number}", "class_sizes": "{class: [x, y, z] > 0}"}.get(
                name, kind.__name__)
            raise ValueError(f"extraction_file {path}: {mode}.{name} = {value!r} is not a {what}")
    if "threshold" not in settings:
        raise ValueError(f"extraction_file {path}: {mode} has no threshold")
    return settings


def fitted_scale_depth(path: str) -> dict:
    """The scale-depth calibration in ``path`` (its ``detector.scale_depth``, as semloc eval mapping writes it with
    mapper.scale_depth and calibration.fit), checked: {"scales": [...], "classes": {name: depth_per_scale}}."""
    import json
    from pathlib import Path

    try:
        document = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"scale_depth_file {path}: cannot read it ({error})") from None
    source = document.get("detector") if isinstance(document, dict) else None
    entry = source.get("scale_depth") if isinstance(source, dict) else None
    if not isinstance(entry, dict):
        raise ValueError(f"scale_depth_file {path}: no 'detector' -> 'scale_depth' entry (is it from semloc eval "
                         f"mapping with mapper.scale_depth and calibration.fit?)")
    scales, classes = entry.get("scales"), entry.get("classes")
    if not (isinstance(scales, list) and scales and all(_positive(v, 1) for v in scales)):
        raise ValueError(f"scale_depth_file {path}: scales = {scales!r} is not a list of positive numbers")
    if not (isinstance(classes, dict) and classes):
        raise ValueError(f"scale_depth_file {path}: classes = {classes!r} is not a mapping of classes")
    depth_per_scale = {}
    for name, fit in classes.items():
        value = fit.get("depth_per_scale") if isinstance(fit, dict) else None
        if not _positive(value, 1):
            raise ValueError(f"scale_depth_file {path}: {name}.depth_per_scale = {value!r} is not a positive number")
        depth_per_scale[name] = float(value)
    return {"scales": [float(v) for v in scales], "classes": depth_per_scale}


class Mapper(Worker):
    """Semantic voxel mapping: heatmaps back-projected along known poses into per-class Hough volumes."""

    Config = MapperWorkerConfig

    def setup(self) -> None:
        c = self.config
        self.grid = VoxelGrid.from_bounds(c.grid_min, c.grid_max, c.voxel_size)
        self.scale_depth = c.scale_depth()
        if c.classes is None:
            raise ConfigError("the mapper needs its classes: set classes (a list) or detector_file (the detector's "
                              "configuration)")
        self.classes = tuple(c.classes)
        try:
            self.mapper = VoxelMapper(self.grid, self.classes, c.mapper_config())
        except ValueError as error:  # e.g. heat likelihood ratios lacking one of the classes
            raise ConfigError(f"cannot map classes {list(self.classes)}: {error}") from None
        self.logger.info("mapping classes %s over %s (%.0f MB)", ", ".join(self.classes), self.grid,
                         self.mapper.memory_bytes / 2**20)
        self.poses = PoseBuffer(tolerance_ns=int(c.pose_tolerance_s * 1e9))
        self.waiting: deque[Heatmaps | HeatmapLevels] = deque()
        self.camera = None
        self.unmatched = 0
        self.integrated_since_publish = 0
        self._cached_map: SemanticMap | None = None
        if c.calibration:
            self._set_camera(load_camera(c.calibration))
        self.objects_out = self.output("objects", keys.mapper_objects(self.robot), ObjectMap)
        self.queryable("map", keys.mapper_map(self.robot), self.on_map_query)
        model_key = keys.camera_model(self.robot, c.camera)
        if not c.calibration:
            self.latest_input("camera_model", model_key, CameraModel, self.on_camera_model)
        # Poses are small and must not be lost (a heatmap without its pose is wasted): lossless.
        self.input("pose", c.pose_key or keys.groundtruth_pose(self.robot), (Pose3D, Pose2D), self.on_pose,
                   policy="lossless", depth=1024, check=self.check_pose)
        if self.scale_depth is None:
            self.input("heatmaps", keys.detector_heatmaps(self.robot), Heatmaps, self.on_heatmaps,
                       policy="lossless", depth=16, check=self.check_heatmaps)
        else:
            self.input("heatmaps", keys.detector_heatmap_levels(self.robot), HeatmapLevels, self.on_heatmaps,
                       policy="lossless", depth=16, check=self.check_heatmaps)
            self.logger.info("scale-selected: mapping HeatmapLevels with the depth per scale of %s",
                             c.scale_depth_file)
        self.every(c.publish_period_s, self.publish_if_changed)

    # ------------------------------------------------------------------ boundary checks (zenoh's thread)
    def check_pose(self, frame: Pose3D | Pose2D) -> None:
        position = frame.position if isinstance(frame, Pose3D) else (frame.x, frame.y)
        farthest = float(np.max(np.abs(position)))
        if farthest > self.config.world_extent:
            raise FrameError(f"pose {farthest:.6g} m from the origin, beyond the world extent "
                             f"{self.config.world_extent:g}", reason="range")

    def check_heatmaps(self, frame: Heatmaps | HeatmapLevels) -> None:
        if set(frame.classes) != set(self.classes):
            unknown = sorted(set(frame.classes) - set(self.classes))
            missing = sorted(set(self.classes) - set(frame.classes))
            raise FrameError(f"heatmaps of another class set: {len(unknown)} unknown (e.g. "
                             f"{(unknown or [''])[0][:40]!r}), {len(missing)} of the map missing", reason="classes")
        if self.scale_depth is not None:
            self._check_levels(frame)
        camera = self.camera  # one read: the main thread may replace it
        if camera is not None:
            self._check_cameras(frame, members(camera))

    def _check_cameras(self, frame: Heatmaps | HeatmapLevels, cameras) -> None:
        for entry in frame.maps:
            check_fits(cameras, entry.camera, entry.image_width, entry.image_height, "heatmaps")

    # ------------------------------------------------------------------ inputs
    def _set_camera(self, camera) -> None:
        for member in members(camera):
            if not isinstance(member, PinholeCamera):
                raise FrameError(f"the mapper needs pinhole cameras, got {type(member).__name__}")
        self.camera = camera

    def on_camera_model(self, frame: CameraModel) -> None:
        first = self.camera is None
        self._set_camera(camera_from_frame(frame))
        if first:
            self.logger.info("camera model received: %d camera(s)", len(members(self.camera)))
        self._drain()

    def on_pose(self, frame: Pose3D | Pose2D) -> None:
        self.poses.add(frame.header.stamp_ns, pose_matrix(frame))
        self._drain()

    def on_heatmaps(self, frame: Heatmaps | HeatmapLevels) -> None:
        self.waiting.append(frame)
        while len(self.waiting) > self.config.pending:
            self.waiting.popleft()
            self.unmatched += 1
        self._drain()

    def _check_levels(self, frame: HeatmapLevels) -> None:
        problem = calibration_mismatch(self.scale_depth["scales"], self.scale_depth["classes"], frame.level_scales,
                                       self.classes)
        if problem:
            raise FrameError(f"{problem} ({self.config.scale_depth_file}; another detector?)", reason="calibration")

    def _drain(self) -> None:
        """Integrate every waiting frame whose pose is known; drop those that can never get one."""
        if self.camera is None:
            return
        while self.waiting:
            frame = self.waiting[0]
            match, T_world = self.poses.lookup(frame.header.stamp_ns)
            if match is Match.WAIT:
                return
            self.waiting.popleft()
            if match is Match.MISSING:
                self.unmatched += 1
                if self.unmatched in (1, 10, 100, 1000):
                    self.logger.warning("%d heatmap frame(s) without a pose within %.3f s", self.unmatched,
                                        self.config.pose_tolerance_s)
                continue
            self._integrate(frame, T_world)

    def _integrate(self, frame: Heatmaps | HeatmapLevels, T_world: np.ndarray) -> None:
        cameras = members(self.camera)
        self._check_cameras(frame, cameras)  # again: the camera model may have changed since the frame arrived
        order = [frame.classes.index(name) for name in self.mapper.class_names]
        per_scale = (None if self.scale_depth is None else
                     [self.scale_depth["classes"][name] for name in self.mapper.class_names])
        for entry in frame.maps:
            camera = cameras[entry.camera]
            if self.config.pose_frame == "camera":
                T_world_cam = T_world
            else:
                T_body_cam = camera.T_body_cam if entry.T_body_cam is None else np.asarray(entry.T_body_cam)
                T_world_cam = T_world @ T_body_cam
            # A level's depth follows the focal length of the image the detector saw (the camera's own K).
            depths = None if per_scale is None else level_depths(per_scale, frame.level_scales, camera.K[0, 0])
            try:
                self.mapper.integrate(entry.values()[order], T_world_cam, camera, level_depths=depths)
            except (ValueError, TypeError) as error:
                raise FrameError(str(error)) from None
            self._log_frustum(frame, entry.camera, camera, T_world_cam)
        self.integrated_since_publish += 1
        self._cached_map = None

    # ------------------------------------------------------------------ outputs
    def current_map(self) -> SemanticMap | None:
        """The extracted map; None before the first frame is integrated (nothing mapped yet)."""
        if self.mapper.frames == 0:
            return None
        if self._cached_map is None:
            self._cached_map = self.mapper.semantic_map(self.config.extraction())
        return self._cached_map

    def _frame(self, semantic_map: SemanticMap) -> ObjectMap:
        header = self.objects_out.header(stamp_ns=self.poses.newest_stamp or 0, frame_id="world")
        return objectmap_frame(header, semantic_map, frames=self.mapper.frames)

    def on_map_query(self, _request) -> ObjectMap | None:
        semantic_map = self.current_map()
        return None if semantic_map is None else self._frame(semantic_map)

    def publish_if_changed(self) -> None:
        if self.integrated_since_publish == 0:
            return
        semantic_map = self.current_map()
        frame = self._frame(semantic_map)
        self.objects_out.publish(frame)
        self.integrated_since_publish = 0
        self._log_map(frame.header, semantic_map)

    # ------------------------------------------------------------------ state
    def snapshot(self) -> State | None:
        if self.mapper.frames == 0:
            return None  # nothing mapped: no snapshot (a restart starts empty all the same)
        return State(arrays=self.mapper.snapshot(), meta={"unmatched": self.unmatched,
                                                          "scale_selected": self.scale_depth is not None})

    def restore(self, state: State) -> None:
        restored = VoxelMapper.from_snapshot(state.arrays)
        if restored.grid.shape != self.grid.shape or not np.allclose(restored.grid.origin, self.grid.origin) \
                or restored.grid.voxel_size != self.grid.voxel_size:
            self.logger.warning("snapshot grid %s differs from the configured %s: starting a new map",
                                restored.grid, self.grid)
            return
        if self.config.classes and tuple(self.config.classes) != restored.class_names:
            self.logger.warning("snapshot classes %s differ from the configured %s: starting a new map",
                                restored.class_names, self.config.classes)
            return
        wanted = self.config.mapper_config()
        if (restored.config.heatmap_llr, restored.config.heatmap_background, restored.config.level_reach,
                bool(state.meta.get("scale_selected", False))) != (
                wanted.heatmap_llr, wanted.heatmap_background, wanted.level_reach, self.scale_depth is not None):
            self.logger.warning("snapshot accumulated heat differently (likelihood ratios, background removal or "
                                "scale-selected levels): starting a new map")
            return
        self.mapper = restored
        self.unmatched = int(state.meta.get("unmatched", 0))
        self.integrated_since_publish = 1  # publish the restored map at the next period
        self.logger.info("restored a map of %d frame(s)", restored.frames)

    # ------------------------------------------------------------------ rerun
    def _log_frustum(self, frame: Heatmaps | HeatmapLevels, index: int, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        if self.rerun is None:
            return
        import rerun as rr

        path = "camera" if len(members(self.camera)) == 1 else f"camera{index}"
        self.rerun_log(path, rr.Transform3D(translation=T_world_cam[:3, 3], mat3x3=T_world_cam[:3, :3]),
                       header=frame.header)
        self.rerun_log(path, rr.Pinhole(image_from_camera=camera.K, resolution=[camera.width, camera.height],
                                        image_plane_distance=0.1), header=frame.header)

    def _log_map(self, header, semantic_map: SemanticMap) -> None:
        if self.rerun is None:
            return
        import rerun as rr

        from semloc_core.mapping.volume import class_colors

        colors = class_colors(len(semantic_map.class_names))
        self.rerun_log("objects", rr.Boxes3D(
            centers=semantic_map.positions, sizes=np.maximum(semantic_map.sizes, self.grid.voxel_size),
            labels=semantic_map.labels(),
            colors=colors[semantic_map.class_index]), header=header)
        if self.config.rerun_max_points:
            cloud = self.mapper.hot_voxels(self.config.rerun_hot_fraction, self.config.normalise,
                                           self.config.min_views, self.config.rerun_max_points)
            self.rerun_log("hot_voxels", rr.Points3D(cloud["points"], colors=cloud["colors"],
                                                     radii=self.grid.voxel_size / 2), header=header)


WORKER = Mapper
