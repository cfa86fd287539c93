"""Mapper: Heatmaps + camera poses in; the semantic object map (ObjectMap) out (thesis ch. 5, docs/mapping.md).

With ``scale_depth_file`` it takes the detector's HeatmapLevels instead and back-projects each level only into the
depth band where the detector's window fits the class (scale-selected back-projection, docs/mapping.md).

Every Heatmaps frame is matched by capture stamp to a pose (Pose3D of the body - ground truth, odometry - or a
planar Pose2D, e.g. the localizer's), back-projected into the voxel grid with the camera model (the camera
worker's CameraModel, or a calibration YAML), and the extracted objects are published periodically and on request.
On ``mapper/save`` it answers with the whole map, objects and score volumes (VoxelMap), for ``semloc map save``
and ``semloc up --save``.
State (``--state-dir``): the snapshot holds the voxel volumes, the buffered poses, the heatmaps waiting for theirs
and the bus's camera model in use; every pose and heatmaps frame and each new camera model is journaled, so a
restarted worker replays what came after the snapshot, and maps at once with the model it had, whether the camera
worker answers or not (a link cut); a model from the bus in this run replaces it.

Settings: the worker's own (camera, poses, classes, grid), and the core's ``volume`` (``MapperConfig``: how heat
accumulates) and ``extraction`` (``ExtractionConfig``: how objects are extracted) as they are; a fitted
``extraction_file`` (semloc_core/io/mapping_calibration.py) replaces the extraction settings it fitted.
"""

from __future__ import annotations

from collections import deque
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from schemas import CameraModel, FrameError, Pose2D, Pose3D, decode, encode, keys
from schemas.detection import HeatmapLevels, Heatmaps
from schemas.limits import MAX_COORDINATE
from schemas.mapping import ObjectMap, VoxelMap
from semloc_core.camera import PinholeCamera, members
from semloc_core.detection.config import detector_classes
from semloc_core.io.camera_model import load_camera
from semloc_core.io.mapping_calibration import extraction_fit, scale_depth_fit
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.mapping import (ExtractionConfig, MapperConfig, MapperMemoryError, VoxelGrid, VoxelMapper,
                                 first_allocation_bytes)
from semloc_core.mapping.poses import Match, PoseBuffer
from semloc_core.mapping.scale_depth import calibration_mismatch, level_depths
from semloc_core.mapping.warmup import warm_up
from semloc_core.settings import updated
from services.config import ConfigError
from services.frames import camera_from_frame, check_clock, check_fits, objectmap_frame, pose_matrix, voxel_map_frame
from services.runtime import Worker, WorkerConfig
from services.state import State

# The reason a camera model is refused (voxel back-projection is written for pinhole rays), and the status says.
NOT_PINHOLE = "the mapper needs pinhole cameras"
MODEL_REFUSED = f"camera model refused ({NOT_PINHOLE})"
# Heatmap frames never integrated, by reason (the status's details, the snapshot): no pose within pose_tolerance_s of
# its stamp once a later one came, or dropped, the oldest, when more than ``pending`` waited for theirs.
WITHOUT_POSE, OVER_PENDING = "heatmaps_without_pose", "heatmaps_over_pending"


def pinhole(camera):
    """``camera`` if every member is a pinhole camera, else FrameError."""
    for member in members(camera):
        if not isinstance(member, PinholeCamera):
            raise FrameError(f"{NOT_PINHOLE}, got {type(member).__name__}")
    return camera


class MapperWorkerConfig(WorkerConfig):
    camera: str = Field("front", description="camera whose CameraModel is used (keys semloc/<robot>/camera/<camera>)")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    pose_key: str | None = Field(None, description="Pose3D/Pose2D stream (default: semloc/<robot>/groundtruth/pose)")
    pose_frame: Literal["body", "camera"] = Field("body", description="'body': poses are T_world_body; 'camera': "
                                                  "T_world_cam directly")
    pose_tolerance_s: float = Field(0.05, ge=0, description="largest pose gap a heatmap stamp is interpolated over")
    pending: int = Field(64, ge=1, description="heatmap frames waiting for their pose, at most")
    classes: list[str] | None = Field(None, description="classes to map; heatmaps of another class set are rejected "
                                      "('classes'). Give them, or detector_file")
    detector_file: str | None = Field(None, description="the detector configuration whose classes are mapped (the "
                                      "detector's detector_file), instead of classes")
    world_extent: float = Field(1000.0, gt=0, le=MAX_COORDINATE, description="poses farther than this from the "
                                "world origin (m, along any axis) are rejected ('range')")
    grid_min: list[float] = Field([-1.0, -1.0, 0.0], min_length=3, max_length=3,
                                  description="grid box minimum corner (world, metres)")
    grid_max: list[float] = Field([1.0, 1.0, 0.7], min_length=3, max_length=3,
                                  description="grid box maximum corner (world, metres)")
    voxel_size: float = Field(0.01, gt=0, description="voxel edge, metres")
    volume: MapperConfig = Field(default_factory=MapperConfig, description="how heat accumulates in the voxel "
                                 "volumes (semloc_core.mapping.MapperConfig)")
    extraction: ExtractionConfig = Field(default_factory=ExtractionConfig, description="how objects are extracted "
                                         "(semloc_core.mapping.ExtractionConfig)")
    extraction_file: str | None = Field(
        None, description="a fitted calibration (`semloc eval mapping`'s calibration.fit, a demo world's mapper_extraction.json): "
                          "its detector entry for this score mode replaces extraction's threshold, class_scales, "
                          "tophat, cross_class, resting, class_sizes and existence (semloc_core/io/"
                          "mapping_calibration.py)")
    scale_depth_file: str | None = Field(
        None, description="a fitted calibration with a depth per scale (what `semloc eval mapping` fits with mapper.scale_depth): map the "
                          "detector's HeatmapLevels (detector publish_levels) scale-selected instead of its Heatmaps")
    publish_period_s: float = Field(2.0, gt=0, description="ObjectMap publication period (when the map changed)")
    rerun_hot_fraction: float = Field(0.6, gt=0, le=1, description="hot voxels logged: >= this of the class max")
    rerun_max_points: int = Field(50_000, ge=0)

    @model_validator(mode="after")
    def _check(self):
        if self.classes is not None and self.detector_file is not None:
            raise ValueError("give the classes to map either as classes or as detector_file, not both")
        if self.detector_file is not None:
            self.classes = list(detector_classes(self.detector_file))
            self.detector_file = None  # resolved: the config snapshot of the run lists the classes
        if self.classes is not None and (not self.classes or len(set(self.classes)) != len(self.classes)):
            raise ValueError(f"classes must be distinct names, at least one, got {self.classes}")
        VoxelGrid.from_bounds(self.grid_min, self.grid_max, self.voxel_size)  # raises with the reason
        if self.extraction_file:
            fitted = extraction_fit(self.extraction_file, self.extraction.normalise)
            if fitted.get("resting") and self.extraction.support_z is None:
                raise ValueError(f"extraction_file {self.extraction_file} was fitted with resting heights: give "
                                 f"extraction.support_z, the height of the surface the objects rest on")
            mode = "normalised" if self.extraction.normalise else "sum"
            self.extraction = updated(self.extraction, fitted, f"extraction_file {self.extraction_file}: {mode}.")
        if self.scale_depth_file:
            self.scale_depth()
            if self.volume.heatmap_llr:
                raise ValueError("scale_depth_file and volume.heatmap_llr do not combine (the ratios are fitted on "
                                 "single maps)")
        return self

    def memory_needs(self) -> dict[str, int]:
        grid = VoxelGrid.from_bounds(self.grid_min, self.grid_max, self.voxel_size)
        classes = len(self.classes or ()) or 1
        what = "the first tile's" if self.volume.tile_size else "the"
        return {f"{what} voxel volumes of {grid.nx} x {grid.ny} x {grid.nz} voxels x {classes} classes (grid_min, "
                f"grid_max, voxel_size, classes, volume.tile_size)": first_allocation_bytes(grid, classes, self.volume)}

    def scale_depth(self) -> dict | None:
        """The fitted depth per scale of ``scale_depth_file``: {"scales": [...], "classes": {name: metres per
        focal pixel per unit scale}}, or None without the file."""
        return None if not self.scale_depth_file else scale_depth_fit(self.scale_depth_file)


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
            self.mapper = VoxelMapper(self.grid, self.classes, c.volume)
        except (ValueError, MapperMemoryError) as error:  # e.g. ratios lacking a class; over volume.memory_limit_mb
            raise ConfigError(f"cannot map classes {list(self.classes)}: {error}") from None
        self.logger.info("mapping classes %s over %s (%.0f MB)", ", ".join(self.classes), self.grid,
                         self.mapper.memory_bytes / 2**20)
        # numba compiles on a kernel's first call: now, on a throwaway mapper, not on the first heatmaps
        self.compile_kernels(warm_up, self.classes, c.volume, c.voxel_size, self.scale_depth)
        self.poses = PoseBuffer(tolerance_ns=int(c.pose_tolerance_s * 1e9))
        self.waiting: deque[Heatmaps | HeatmapLevels] = deque()
        self.camera = None
        self.model: CameraModel | None = None  # the bus's model in use (snapshotted)
        # The newest model from the bus in this run: one answered while the state is restored replaces the state's
        # once they are replayed (run)
        self.live_model: CameraModel | None = None
        # The model the journal (or the snapshot it follows) holds: a model is journaled before the first heatmaps
        # integrated with it (not at arrival: the model answered at start comes before the journal is open).
        self.journaled_model: CameraModel | None = None
        self.unmatched = dict.fromkeys((WITHOUT_POSE, OVER_PENDING), 0)
        self.integrated_since_publish = 0
        self._cached_map: SemanticMap | None = None
        if c.calibration:
            self._set_camera(load_camera(c.calibration))
        self.objects_out = self.output("objects", keys.mapper_objects(self.robot), ObjectMap)
        self.queryable("map", keys.mapper_map(self.robot), self.on_map_query)
        self.queryable("save", keys.mapper_save(self.robot), self.on_save_query)
        model_key = keys.camera_model(self.robot, c.camera)
        self.model_input = None if c.calibration else self.latest_input("camera_model", model_key, CameraModel,
                                                                        self.on_camera_model)
        # Poses are small and must not be lost (a heatmap without its pose is wasted): lossless.
        poses = self.input("pose", c.pose_key or keys.groundtruth_pose(self.robot), (Pose3D, Pose2D), self.on_pose,
                           policy="lossless", depth=1024, check=self.check_pose, raw=True)
        poses.drives_output = False  # a pose integrates the heatmaps waiting for it; alone it asks for no map
        self.heatmaps_type = Heatmaps if self.scale_depth is None else HeatmapLevels
        heatmaps_key = (keys.detector_heatmaps if self.scale_depth is None
                        else keys.detector_heatmap_levels)(self.robot)
        heatmaps = self.input("heatmaps", heatmaps_key, self.heatmaps_type, self.on_heatmaps, policy="lossless",
                              depth=16, check=self.check_heatmaps, raw=True)
        if self.scale_depth is not None:
            self.logger.info("scale-selected: mapping HeatmapLevels with the depth per scale of %s",
                             c.scale_depth_file)
        self.every(c.publish_period_s, self.publish_if_changed)
        self.journal_stream("pose", poses, self.apply_pose)
        self.journal_stream("heatmaps", heatmaps, self.apply_heatmaps)
        if self.model_input is not None:
            self.journal_stream("camera_model", self.model_input, self.apply_camera_model)

    # ------------------------------------------------------------------ boundary checks (zenoh's thread)
    def check_pose(self, frame: Pose3D | Pose2D) -> None:
        check_clock(frame)  # the pose buffer orders by stamp
        position = frame.position if isinstance(frame, Pose3D) else (frame.x, frame.y)
        farthest = float(np.max(np.abs(position)))
        if farthest > self.config.world_extent:
            raise FrameError(f"pose {farthest:.6g} m from the origin, beyond the world extent "
                             f"{self.config.world_extent:g}", reason="range")

    def check_heatmaps(self, frame: Heatmaps | HeatmapLevels) -> None:
        check_clock(frame)  # heatmaps wait in stamp order for their poses
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
        self.camera = pinhole(camera)

    def on_camera_model(self, frame: CameraModel) -> None:
        # The camera republishes its model every second: the same model is kept (journaled once)
        if self.model is None or encode(frame.model_copy(update={"header": self.model.header})) != encode(self.model):
            try:
                self._use_model(frame)
            except FrameError:
                # Counted as rejected by the runtime; and the status says so for as long as models are refused (a
                # fisheye camera feeds the rest of the graph while this map stays empty).
                self.skipped(MODEL_REFUSED)
                raise
        self.resumed(MODEL_REFUSED)
        self.live_model = frame
        self._drain()
        self.resumed("no camera model yet: heatmaps wait")

    def apply_camera_model(self, frame: CameraModel) -> None:
        """A journaled model, replayed as it came: the frames journaled after it were mapped with it."""
        self._use_model(frame)
        self.journaled_model = frame
        self._drain()

    def run(self) -> None:
        # The state restored: a model the camera worker answered meanwhile is the camera's now (another camera since
        # the crash: the frames still to come are of that one), whatever the state's was.
        if self.live_model is not None and self.model is not self.live_model:
            self._use_model(self.live_model)
            self._drain()
        super().run()

    def _use_model(self, frame: CameraModel) -> None:
        first = self.camera is None
        self._set_camera(camera_from_frame(frame))
        self.model = frame
        if first:
            self.logger.info("camera model %s: %d camera(s)", "replayed" if self.replaying else "received",
                             len(members(self.camera)))

    def on_pose(self, frame: Pose3D | Pose2D, payload: bytes) -> None:
        try:
            self.apply_pose(frame)
        finally:  # a frame integrated before another was refused changed the state all the same
            self.journal_write("pose", payload)

    def on_heatmaps(self, frame: Heatmaps | HeatmapLevels, payload: bytes) -> None:
        if self.model is not self.journaled_model:
            self.journal_write("camera_model", self.model)
            self.journaled_model = self.model
        try:
            self.apply_heatmaps(frame)
        finally:
            self.journal_write("heatmaps", payload)

    def apply_pose(self, frame: Pose3D | Pose2D) -> None:
        self.poses.add(frame.header.stamp_ns, pose_matrix(frame))
        self._drain()

    def apply_heatmaps(self, frame: Heatmaps | HeatmapLevels) -> None:
        if self.camera is None and not self.replaying:
            self.skipped("no camera model yet: heatmaps wait")
        self.waiting.append(frame)
        while len(self.waiting) > self.config.pending:
            self.waiting.popleft()
            self._unmatched(OVER_PENDING, f"more than pending={self.config.pending} waited for their pose: the oldest "
                                          "dropped")
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
                self._unmatched(WITHOUT_POSE, f"no pose within pose_tolerance_s={self.config.pose_tolerance_s:g} s")
                continue
            self._integrate(frame, T_world)

    def _unmatched(self, reason: str, why: str) -> None:
        """One more heatmap frame never integrated, for ``reason`` (logged at the 1st, 10th, 100th, 1000th)."""
        self.unmatched[reason] += 1
        if self.unmatched[reason] in (1, 10, 100, 1000):
            self.logger.warning("%d heatmap frame(s) not integrated: %s", self.unmatched[reason], why)

    def status_details(self) -> dict:
        """Heatmap frames waiting for their pose now, and those never integrated, by reason."""
        waiting = getattr(self, "waiting", ())  # the status thread may ask before setup
        return {"heatmaps_waiting": len(waiting), **getattr(self, "unmatched", {})}

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
                self.mapper.integrate(self._heat(entry)[order], T_world_cam, camera, level_depths=depths)
            except (ValueError, TypeError) as error:
                raise FrameError(str(error)) from None
            self._log_frustum(frame, entry.camera, camera, T_world_cam)
        self.integrated_since_publish += 1
        self._cached_map = None

    def _heat(self, entry) -> np.ndarray:
        """An entry's maps as the mapper takes them. Surprisal ranks a frame's heat, so quantised scores go as their
        codes (value = code · scale: the same order when scale > 0), which the mapper counts without sorting."""
        if (self.config.volume.heatmap_background == "surprisal" and entry.scores.dtype == np.uint8
                and entry.scale > 0):
            return entry.scores
        return entry.values()

    # ------------------------------------------------------------------ outputs
    def current_map(self) -> SemanticMap | None:
        """The extracted map; None before the first frame is integrated (nothing mapped yet)."""
        if self.mapper.frames == 0:
            return None
        if self._cached_map is None:
            self._cached_map = self.mapper.semantic_map(self.config.extraction)
        return self._cached_map

    def _frame(self, semantic_map: SemanticMap) -> ObjectMap:
        header = self.objects_out.header(stamp_ns=self.poses.newest_stamp or 0, frame_id="world")
        return objectmap_frame(header, semantic_map, frames=self.mapper.frames)

    def on_map_query(self, _request) -> ObjectMap | None:
        semantic_map = self.current_map()
        return None if semantic_map is None else self._frame(semantic_map)

    def on_save_query(self, _request) -> VoxelMap:
        """The whole map (objects and score volumes) for whoever saves it (``semloc map save``, ``up --save``);
        empty before the first frame."""
        semantic_map = self.current_map() or self.mapper.semantic_map(self.config.extraction)
        extraction = self.config.extraction
        return voxel_map_frame(self._frame(semantic_map), self.grid,
                               self.mapper.score_volumes(extraction.normalise, extraction.min_views),
                               self.mapper.view_count())

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
            return None  # nothing mapped: no snapshot (the journal holds the poses and heatmaps until then)
        arrays = dict(self.mapper.snapshot())
        poses = self.poses.snapshot()
        arrays["pose_stamps"], arrays["pose_matrices"] = poses["stamps"], poses["poses"]
        # Heatmaps still waiting for their pose, as the frames they arrived as.
        waiting = [np.frombuffer(encode(frame), np.uint8) for frame in self.waiting]
        arrays["waiting_lengths"] = np.array([w.size for w in waiting], np.int64)
        arrays["waiting_frames"] = np.concatenate(waiting) if waiting else np.zeros(0, np.uint8)
        if self.model is not None:  # a restarted mapper maps with it before the camera answers (a cut link)
            arrays["camera_model"] = np.frombuffer(encode(self.model), np.uint8)
        return State(arrays=arrays, meta={"unmatched": dict(self.unmatched),
                                          "scale_selected": self.scale_depth is not None,
                                          "integrated_since_publish": self.integrated_since_publish})

    def restore(self, state: State) -> None:
        arrays = dict(state.arrays)
        poses = PoseBuffer(tolerance_ns=self.poses.tolerance_ns)
        poses.restore({"stamps": arrays.pop("pose_stamps", np.zeros(0, np.int64)),
                       "poses": arrays.pop("pose_matrices", np.zeros((0, 4, 4)))})
        lengths = np.asarray(arrays.pop("waiting_lengths", np.zeros(0, np.int64)), np.int64)
        data = np.asarray(arrays.pop("waiting_frames", np.zeros(0, np.uint8)), np.uint8)
        if lengths.sum() != data.size or np.any(lengths < 0):
            raise ValueError("snapshot: waiting heatmaps do not match their lengths")
        ends = np.cumsum(lengths)
        waiting = deque(decode(data[a:b].tobytes(), expected=self.heatmaps_type)
                        for a, b in zip((ends - lengths).tolist(), ends.tolist()))
        model = arrays.pop("camera_model", None)
        if model is not None:  # a file: decoded and checked as the bus's model is (its robot, pinhole members)
            model = decode(np.asarray(model, np.uint8).tobytes(), expected=CameraModel)
            if self.model_input is None:
                model = None  # a calibration file is the camera
            else:
                self.model_input.accept(model)
                camera = pinhole(camera_from_frame(model))
        restored = VoxelMapper.from_snapshot(arrays)
        if model is not None:  # whatever becomes of the map: the model is the camera's
            self.camera, self.model, self.journaled_model = camera, model, model
            self.logger.info("camera model restored: %d camera(s)", len(members(camera)))
        if restored.grid.shape != self.grid.shape or not np.allclose(restored.grid.origin, self.grid.origin) \
                or restored.grid.voxel_size != self.grid.voxel_size:
            self.logger.warning("snapshot grid %s differs from the configured %s: starting a new map",
                                restored.grid, self.grid)
            return
        if self.config.classes and tuple(self.config.classes) != restored.class_names:
            self.logger.warning("snapshot classes %s differ from the configured %s: starting a new map",
                                restored.class_names, self.config.classes)
            return
        wanted = self.config.volume
        if (restored.config.heatmap_llr, restored.config.heatmap_background, restored.config.level_reach,
                bool(state.meta.get("scale_selected", False))) != (
                wanted.heatmap_llr, wanted.heatmap_background, wanted.level_reach, self.scale_depth is not None):
            self.logger.warning("snapshot accumulated heat differently (likelihood ratios, background removal or "
                                "scale-selected levels): starting a new map")
            return
        self.mapper = restored
        self.poses, self.waiting = poses, waiting
        counts = state.meta.get("unmatched")
        counts = counts if isinstance(counts, dict) else {}  # a file is untrusted
        self.unmatched = {reason: max(0, int(counts.get(reason, 0))) for reason in self.unmatched}
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
            cloud = self.mapper.hot_voxels(self.config.rerun_hot_fraction, self.config.extraction.normalise,
                                           self.config.extraction.min_views, self.config.rerun_max_points)
            self.rerun_log("hot_voxels", rr.Points3D(cloud["points"], colors=cloud["colors"],
                                                     radii=self.grid.voxel_size / 2), header=header)


WORKER = Mapper
