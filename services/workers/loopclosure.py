"""Loop closure: Image (or LoopFeatures) in; LoopClosure decisions, SimilarityRow and TopoMapUpdate out; the
topological map by request/reply (thesis ch. 3, computed incrementally; docs/loopclosure.md).

Bearings need the camera model: from ``calibration`` (a YAML file) or the camera worker's ``CameraModel``
(subscribed, and queried at start). The engine's whole state (features, vocabulary, lattice, map) is snapshotted
with the runtime's state mechanism, so a restarted worker continues the same map with the same frame numbering.
Each node carries its key-frame's pose as the localizer estimated it (PoseEstimate at the key-frame's stamp), so
the saved map (``semloc map save``: GraphML, JSON) has node positions; NaN while no estimate has that stamp.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from schemas import CameraModel, Image, keys
from schemas.localization import PoseEstimate
from schemas.loopclosure import LoopClosure, LoopFeatures, SimilarityRow, TopoMap, TopoMapUpdate
from semloc_core.camera import members
from semloc_core.io.camera_model import load_camera
from semloc_core.loopclosure import EngineParams, FeatureParams, FeatureSequence, LoopClosureEngine, extract_features
from services.frames import (DEFAULT_MAX_IMAGE_PIXELS, ImagePixelLimit, bgr_images, camera_from_frame, check_image,
                             extrinsic_overrides, features_from_frame, loop_closure_frame, similarity_row_frame,
                             topomap_frame, topomap_update_frame)
from services.runtime import Worker, WorkerConfig
from services.state import State


UNKNOWN_POSE = (float("nan"),) * 3
EARLY_POSES = 1024  # estimates kept for frames this worker has not processed yet (it may lag the localizer)


class LoopClosureConfig(WorkerConfig):
    camera: str = Field("front", description="camera whose images are processed")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    vocabulary: str | None = Field(None, description="vocabulary .npz (default: learnt from the first frames)")
    features: FeatureParams = Field(default_factory=FeatureParams, description="SIFT features "
                                    "(semloc_core.loopclosure.FeatureParams)")
    engine: EngineParams = Field(default_factory=EngineParams, description="retrieval, alignment, MRF and map "
                                 "(semloc_core.loopclosure.EngineParams)")
    image_policy: Literal["latest", "lossless"] = Field("latest", description="image queue policy")
    max_image_pixels: ImagePixelLimit = DEFAULT_MAX_IMAGE_PIXELS
    rerun_every: int = Field(10, ge=0, description="log the matrices and the graph every n-th frame (0: never)")
    rerun_matrix_px: int = Field(512, ge=16, le=4096, description="logged matrices are max-pooled to this size")


class LoopClosureWorker(Worker):
    """Incremental loop closure and the topological map (thesis ch. 3)."""

    Config = LoopClosureConfig

    def setup(self) -> None:
        c = self.config
        vocabulary = None
        if c.vocabulary:
            from semloc_core.io.loopclosure import load_vocabulary

            vocabulary = load_vocabulary(c.vocabulary)
        self.engine = LoopClosureEngine(c.engine, vocabulary)
        self.stamps: list[int] = []
        self.frame_poses: list[tuple[float, float, float]] = []  # the localizer's estimate per frame (NaN: none)
        self.frame_of_stamp: dict[int, int] = {}
        self.early_poses: dict[int, tuple[float, float, float]] = {}  # estimates of frames not processed yet
        self.feature_params = c.features
        self.camera = load_camera(c.calibration) if c.calibration else None
        robot = self.robot
        self.events_out = self.output("events", keys.loopclosure_events(robot), LoopClosure)
        self.similarity_out = self.output("similarity", keys.loopclosure_similarity(robot), SimilarityRow)
        self.topomap_out = self.output("topomap", keys.loopclosure_topomap(robot), TopoMapUpdate)
        # The whole map answers queries on the same key its updates are published on.
        self.queryable("topomap", keys.loopclosure_topomap(robot), self.on_map_query)
        model_key = keys.camera_model(robot, c.camera)
        if not c.calibration:
            self.latest_input("camera_model", model_key, CameraModel, self.on_camera_model)
        self.input("image", keys.camera_image(robot, c.camera), Image, self.on_image, policy=c.image_policy,
                   check=self.check_image)
        self.input("features", keys.loopclosure_features(robot), LoopFeatures, self.on_features,
                   policy="lossless")
        pose_input = self.input("pose", keys.localizer_pose(robot), PoseEstimate, self.on_pose, policy="lossless",
                                depth=1024)
        pose_input.drives_output = False  # node positions only: a pose asks for no output
        self.frames_without_model = 0

    # --- inputs ---------------------------------------------------------------------------------------------

    def check_image(self, frame: Image) -> None:
        """Before anything is decoded (zenoh's thread): the size limit, and the camera model when there is one."""
        check_image(frame, self.config.max_image_pixels, self.camera)

    def on_camera_model(self, frame: CameraModel) -> None:
        camera = camera_from_frame(frame)
        if self.camera is None:
            self.logger.info("camera model received: %d camera(s)", len(members(camera)))
        self.camera = camera

    def on_image(self, frame: Image) -> None:
        if self.camera is None:
            self.frames_without_model += 1
            if self.frames_without_model in (1, 100, 1000):
                self.logger.warning("no camera model yet: %d image(s) skipped", self.frames_without_model)
            return
        cameras = members(self.camera)
        check_image(frame, self.config.max_image_pixels, self.camera)  # again: the camera model may have changed
        images, pixels = bgr_images(frame)
        if len(cameras) == 1:
            features = extract_features(pixels[0], self.camera, self.feature_params, extrinsic_overrides(images)[0])
        else:
            features = extract_features(pixels, self.camera, self.feature_params)
        self.process(features, frame.header, pixels[0])

    def on_features(self, frame: LoopFeatures) -> None:
        self.process(features_from_frame(frame), frame.header, None)

    def on_pose(self, frame: PoseEstimate) -> None:
        pose = (float(frame.x), float(frame.y), float(frame.theta))
        index = self.frame_of_stamp.get(int(frame.header.stamp_ns))
        if index is not None:
            self.frame_poses[index] = pose
            return
        self.early_poses[int(frame.header.stamp_ns)] = pose
        while len(self.early_poses) > EARLY_POSES:
            self.early_poses.pop(next(iter(self.early_poses)))

    # --- one frame ------------------------------------------------------------------------------------------

    def process(self, features: FeatureSequence, source_header, thumbnail) -> None:
        result = self.engine.add_frame(features)
        self.stamps.append(int(source_header.stamp_ns))
        self.frame_of_stamp[self.stamps[-1]] = len(self.stamps) - 1
        self.frame_poses.append(self.early_poses.pop(self.stamps[-1], UNKNOWN_POSE))
        stamps = np.asarray(self.stamps, np.int64)
        stamp = source_header.stamp_ns
        self.similarity_out.publish(similarity_row_frame(self.similarity_out.header(stamp_ns=stamp), result,
                                                         len(features)))
        event_header = self.events_out.header(stamp_ns=stamp)
        self.events_out.publish(loop_closure_frame(event_header, result, stamps))
        update = result.map_update
        if update:
            self.topomap_out.publish(topomap_update_frame(self.topomap_out.header(stamp_ns=stamp), update,
                                                          self.engine.n_frames, self.engine.topomap.n_nodes))
        if self.rerun is not None:
            self._log(result, event_header, thumbnail)

    def on_map_query(self, _request) -> TopoMap:
        header = self.topomap_out.header(stamp_ns=self.stamps[-1] if self.stamps else 0)
        return topomap_frame(header, self.engine.topomap, np.asarray(self.stamps, np.int64),
                             np.asarray(self.frame_poses, np.float64))

    # --- state ----------------------------------------------------------------------------------------------

    def snapshot(self) -> State:
        arrays, meta = self.engine.state()
        arrays["stamps_ns"] = np.asarray(self.stamps, np.int64)
        arrays["frame_poses"] = np.asarray(self.frame_poses, np.float64).reshape(-1, 3)
        return State(arrays=arrays, meta=meta)

    def restore(self, state: State) -> None:
        arrays = dict(state.arrays)
        stamps = arrays.pop("stamps_ns", np.zeros(0, np.int64))
        poses = arrays.pop("frame_poses", np.full((len(stamps), 3), np.nan))
        engine = LoopClosureEngine.from_state(arrays, state.meta)
        if engine.params != self.engine.params:
            self.logger.warning("the saved map was built with other parameters; continuing with the saved ones")
        if len(stamps) != engine.n_frames or np.shape(poses) != (len(stamps), 3):
            raise ValueError("saved state: stamps or poses do not match the frames")
        self.engine = engine
        self.stamps = [int(s) for s in stamps]
        self.frame_poses = [tuple(p) for p in np.asarray(poses, float).tolist()]
        self.frame_of_stamp = {stamp: index for index, stamp in enumerate(self.stamps)}
        self.logger.info("restored %d frames, %d nodes", engine.n_frames, engine.topomap.n_nodes)

    # --- rerun ----------------------------------------------------------------------------------------------

    def _log(self, result, header, thumbnail) -> None:
        import rerun as rr

        self.rerun_log("status", rr.TextLog(f"frame {result.frame}: {result.status.value}"
                                            + (f" with {result.loops.tolist()}" if result.loops.size else "")),
                       header=header)
        for node, keyframe in result.map_update.new_nodes:
            if thumbnail is not None and keyframe == result.frame:
                small = cv2.resize(thumbnail, (max(1, thumbnail.shape[1] // 4), max(1, thumbnail.shape[0] // 4)))
                ok, buffer = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
                if ok:
                    self.rerun_log("keyframes", rr.EncodedImage(contents=buffer.tobytes(), media_type="image/jpeg"),
                                   header=header)
            self.rerun_log("keyframe", rr.TextLog(f"node {node}: key-frame {keyframe}"), header=header)
        every = self.config.rerun_every
        if not every or result.frame % every:
            return
        n = self.engine.n_frames
        rows, cols, scores, beliefs = self.engine.similarity_cells()
        norm = self.engine.mrf.normalization
        # Scores as seen by the MRF: phi(1) for the thesis potential, background deviations otherwise (clipped).
        potential = (np.clip((scores - norm.location) / norm.scale, 0, 10) if norm is not None
                     else np.zeros_like(scores))
        self.rerun_log("similarity", rr.DepthImage(_pooled(n, rows, cols, potential, self.config.rerun_matrix_px),
                                                   colormap="turbo"), header=header)
        self.rerun_log("decisions", rr.DepthImage(_pooled(n, rows, cols, (beliefs > 0).astype(np.float32),
                                                          self.config.rerun_matrix_px), colormap="turbo"),
                       header=header)
        snapshot = self.engine.topomap.snapshot()
        ids = [str(k) for k in snapshot.node_ids.tolist()]
        self.rerun_log("graph", rr.GraphNodes(ids, labels=[f"{k}:{f}" for k, f in zip(ids, snapshot.keyframes.tolist())]),
                       header=header)
        self.rerun_log("graph", rr.GraphEdges([(str(a), str(b)) for a, b in snapshot.edges.tolist()],
                                              graph_type="undirected"), header=header)


def _pooled(n: int, rows, cols, values, size: int) -> np.ndarray:
    """An (n, n) sparse matrix drawn into at most size x size pixels (max over each block)."""
    scale = max(1, int(np.ceil(n / size)))
    side = max(1, int(np.ceil(n / scale)))
    image = np.zeros((side, side), np.float32)
    if len(rows):
        np.maximum.at(image, (np.asarray(rows) // scale, np.asarray(cols) // scale), np.asarray(values, np.float32))
    return image


WORKER = LoopClosureWorker
