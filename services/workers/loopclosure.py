"""Loop closure: Image (or LoopFeatures) in; LoopClosure decisions, SimilarityRow and TopoMapUpdate out; the
topological map by request/reply (thesis ch. 3, computed incrementally; docs/loopclosure.md).

Camera images are gated (``keyframes``; semloc_core.loopclosure.keyframes): SIFT and the DP run only on key-frames,
chosen by the odometry's distance and turn since the last one (subscribed; as AMCL gates its updates) or the
image's change, at most one per ``min_interval_s``, and the first after time no odometry message covers
(``_note_odometry``); other images cost a thumbnail. LoopFeatures are taken as sent.

Bearings need the camera model: from ``calibration`` (a YAML file) or the camera worker's ``CameraModel``
(subscribed, and queried at start). The camera publishes it before its first image, but on another key: a worker
that met the camera later gets it from its query's reply, after the image. The newest image without a model waits
for it; an older one is skipped (``no camera model yet``).
With ``state_dir`` the engine keeps the frames' descriptors and the lattice's final cells in files
(``<state_dir>/<robot>/<name>.store/<generation>/``, FileStorage) and its snapshot holds the index, the map and the
lengths of those files; each frame's features are journaled, so a restarted worker (after a crash too) continues the
same map with the same frame numbering.
Each frame carries its pose as the localizer estimated it (PoseEstimate at the frame's stamp) while the localizer was
localized (its ``state``; a localizer without one: ``converged``), kept by ``place_poses``' ``PoseRecorder``
(committed once ``commit_after`` further estimates stayed localized; a stretch the localizer abandons for another
hypothesis, by the odometry, withdrawn; a stretch's first pose carried back along the odometry to the frames before
it, within the motion noise the localizer sends with its estimates), so the saved map (``semloc map save``: GraphML, JSON) has node positions and
each LoopClosure the poses of the places it recognises (``loop_poses``, which the localizer draws particles around
when lost: the hybrid map); NaN while no such estimate has that stamp. A frame the engine does not keep (its view is
held by an earlier frame: ``engine.cull_redundant``) gives its pose to that frame when that one has none. The
localizer's backward filter passes (``PastPoses``) give poses to frames that hold none, withdrawn with the stretch
each pass started from (``PoseRecorder.fill``). The estimates, the passes and the odometry are journaled with the
frames, in the order they changed the state, and the snapshot holds the estimates waiting for their odometry and the
odometry since the last one judged: a restarted worker (after a crash too) ends where it was, and asks the
localizer's and the odometry's caches for what they sent meanwhile (recoverable streams; a pass is not recovered).
The key-frame gate starts over (its last key-frame's thumbnail is not kept): the first image after a restart is a
key-frame. The snapshot also holds the pairing of a session's runs (``_new_run``:
which stream has started over, the first frame answering to its stamp): a worker restarted in a second run gives the
old run's frames none of the new run's estimates.
The engine's two one-off steps (the calibration on its first frames, the vocabulary's k-means: seconds each on the
demo, where a frame takes milliseconds) run on a helper thread (``LoopClosureEngine.prepare``): meanwhile images are
still taken, gated and given SIFT, and their features wait in order (``engine_backlog`` in the status) for the
engine, which then continues exactly as it would have: each image taken feeds it the two oldest waiting frames,
and more while no image waits. A frame in that backlog is not yet in the state or the journal (a crash loses it, as
one in the image queue); a graceful stop finishes them.
"""

from __future__ import annotations

import collections
import errno
import math
import os
import shutil
import threading
import time
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from schemas import CameraModel, FrameError, Image, Odometry, decode, encode, keys
from schemas.localization import PastPoses, PoseEstimate
from schemas.loopclosure import MAX_REVISIONS, LoopClosure, LoopFeatures, SimilarityRow, TopoMap, TopoMapUpdate
from semloc_core.camera import members
from semloc_core.io.camera_model import load_camera
from semloc_core.io.loopclosure import FileStorage
from semloc_core.localization.motion import Odometry as Increment
from semloc_core.localization.motion import compose
from semloc_core.localization.health import hypothesis_spreads
from semloc_core.localization.place_poses import PlacePoseConfig, PoseRecorder
from semloc_core.loopclosure import EngineParams, FeatureParams, FeatureSequence, LoopClosureEngine, extract_features
from semloc_core.loopclosure.keyframes import KeyframeParams, appearance_change, keyframe_reason, thumbnail
from semloc_core.loopclosure.topomap import TopoMapUpdate as MapUpdate
from semloc_core.loopclosure.warmup import warm_up
from services.frames import (DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_ODOMETRY_DT, DEFAULT_MAX_SPEED,
                             DEFAULT_MAX_TURN_RATE, ImagePixelLimit, OdometryDtLimit, PeerStream, SpeedLimit,
                             TurnRateLimit, bgr_images, camera_from_frame, check_clock, check_image,
                             check_odometry_limits, extrinsic_overrides, features_from_frame, loop_closure_frame,
                             loop_features_frame, odometry_buffer, restarted, similarity_row_frame, take_revisions,
                             topomap_frame, topomap_update_frame)
from services.runtime import Worker, WorkerConfig, check_robot
from services.state import REFUSED_WRITES, State


UNKNOWN_POSE = (float("nan"),) * 3
EARLY_POSES = 1024  # estimates kept for frames this worker has not processed yet (it may lag the localizer)
RECENT_FRAMES = 1024  # frames a late estimate is still matched to by its stamp
NO_MODEL = "no camera model yet"  # the reason an image without the camera model is skipped under
ODOMETRY_HOLES = 64  # spans of time no odometry covers kept for the key-frame gate (a flapping link: the latest)
POSE_QUEUE = 64  # estimates waiting for the odometry to reach their stamps (odometry that stops lets them through)
BACKLOG = 256  # frames' features waiting for the engine (~70 KB each); a full backlog is fed at once
FEED_S = 0.05  # the backlog is fed this often, and at most this long at a time


class LoopClosureConfig(WorkerConfig):
    camera: str = Field("front", description="camera whose images are processed")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    vocabulary: str | None = Field(None, description="vocabulary .npz (default: learnt from the first frames)")
    features: FeatureParams = Field(default_factory=FeatureParams, description="SIFT features "
                                    "(semloc_core.loopclosure.FeatureParams)")
    engine: EngineParams = Field(default_factory=EngineParams, description="retrieval, alignment, MRF and map "
                                 "(semloc_core.loopclosure.EngineParams)")
    image_policy: Literal["latest", "lossless"] = Field("latest", description="image queue policy")
    keyframes: KeyframeParams = Field(default_factory=KeyframeParams, description="which images are processed "
                                      "(semloc_core.loopclosure.keyframes.KeyframeParams)")
    max_image_pixels: ImagePixelLimit = DEFAULT_MAX_IMAGE_PIXELS
    max_speed: SpeedLimit = DEFAULT_MAX_SPEED  # the localizer's: the places carry its poses along the same odometry
    max_turn_rate: TurnRateLimit = DEFAULT_MAX_TURN_RATE
    max_odometry_dt: OdometryDtLimit = DEFAULT_MAX_ODOMETRY_DT
    place_poses: PlacePoseConfig = Field(default_factory=PlacePoseConfig, description="which localized estimates "
                                         "the frames keep (semloc_core.localization.place_poses.PlacePoseConfig; "
                                         "same_track_* default to three of the converged spread the "
                                         "localizer's estimates carry, the back-fill uses the motion noise they "
                                         "carry; the stretches are judged on the odometry, with keyframes "
                                         "enabled)")
    store_min_free_mb: float = Field(64.0, ge=0, description="frames go to the engine only while the file system of "
                                     "its store (state_dir) has this much free (MiB) and is writable; meanwhile they "
                                     "wait (the oldest dropped beyond the backlog, counted) and the status says why")
    rerun_every: int = Field(10, ge=0, description="log the matrices and the graph every n-th frame (0: never)")
    rerun_matrix_px: int = Field(512, ge=16, le=4096, description="logged matrices are max-pooled to this size")


class LoopClosureWorker(Worker):
    """Incremental loop closure and the topological map (thesis ch. 3)."""

    Config = LoopClosureConfig

    def setup(self) -> None:
        c = self.config
        self.vocabulary = None
        if c.vocabulary:
            from semloc_core.io.loopclosure import load_vocabulary

            self.vocabulary = load_vocabulary(c.vocabulary)
        self.params = c.engine
        self.engine: LoopClosureEngine | None = None  # made at the first frame, unless a snapshot is restored
        self.stamps = np.zeros(64, np.int64)  # capture stamp of each frame
        self.frame_poses = np.full((64, 3), np.nan)  # the localizer's estimate per frame (NaN: none)
        self.pose_changes: dict[int, tuple] = {}  # frame -> its new pose, not yet published (TopoMapUpdate)
        self.frame_of_stamp: dict[int, int] = {}  # of the latest RECENT_FRAMES frames
        self.holder_of: dict[int, int] = {}  # the frame holding the view of each of those the engine did not keep
        self.revisions_due: dict[int, np.ndarray] = {}  # frame -> its loops now, not yet published
        self.early_poses: dict[int, tuple[float, float, float]] = {}  # estimates of frames not processed yet
        # A session replayed again starts the images and the estimates over on the same stamps (_new_run): each
        # stream's latest stamp, and which one has started a new run the other has not reached yet
        self.last_estimate_ns: int | None = None
        self.images_ahead = self.estimates_ahead = False
        self.recorder = PoseRecorder(c.place_poses)  # commits an estimate once the localizer has stayed localized
        # Calibrating, the engine suppresses repeated texture itself (at the threshold it derives).
        sequence = c.engine.calibration.mode == "sequence"
        self.feature_params = replace(c.features, repeated_threshold=0.0) if sequence else c.features
        self.camera = load_camera(c.calibration) if c.calibration else None
        self.waiting_for_model: Image | None = None  # the newest image without a camera model (the module's docstring)
        robot = self.robot
        self.events_out = self.output("events", keys.loopclosure_events(robot), LoopClosure)
        self.similarity_out = self.output("similarity", keys.loopclosure_similarity(robot), SimilarityRow)
        self.topomap_out = self.output("topomap", keys.loopclosure_topomap(robot), TopoMapUpdate)
        # The whole map answers queries on the same key its updates are published on.
        self.queryable("topomap", keys.loopclosure_topomap(robot), self.on_map_query)
        model_key = keys.camera_model(robot, c.camera)
        if not c.calibration:
            self.latest_input("camera_model", model_key, CameraModel, self.on_camera_model)
        self.image_input = self.input("image", keys.camera_image(robot, c.camera), Image, self.on_image,
                                      policy=c.image_policy, check=self.check_image)
        features = self.input("features", keys.loopclosure_features(robot), LoopFeatures, self.on_features,
                              policy="lossless", check=check_clock)
        # The localizer's estimates go to the recorder in its order: a stale or repeated one is refused (``order``)
        # in the handler, not at the boundary, so that one a restored worker's state holds already, which the
        # localizer's cache sends again (keys.RECOVERABLE_STREAMS), is counted as that (``already_held``).
        self.estimates_order = PeerStream()
        pose_input = self.input("pose", keys.localizer_pose(robot), PoseEstimate, self.on_pose, policy="lossless",
                                depth=1024, check=check_clock, raw=True)
        pose_input.drives_output = False  # node positions only: a pose asks for no output
        past = self.input("past_poses", keys.localizer_past_poses(robot), PastPoses, self.on_past_poses,
                          policy="lossless", depth=16, check=check_clock, raw=True)
        past.drives_output = False
        self.past_filled = 0
        self.dropped_no_room = 0  # frames dropped from a full backlog while the store had no room
        # A store restored read-only (its disk refused writes): the engine's state, to open it writable again later
        self.read_only_state: tuple[dict, dict] | None = None
        self.replayed_waiting = 0  # the journal's frames at the head of the backlog (journaled already)
        self.past_refused: collections.Counter[str] = collections.Counter()  # a pass's poses not taken, by reason
        # What changes the places is journaled in the order it changed the state (the frames, the estimates and
        # the odometry judging them, the backward passes): a restarted worker replays it exactly, and asks the
        # localizer's and the odometry's caches for what came while it was down (the runtime's CacheHistory).
        self.journal_stream("features", features, self.on_features)
        self.journal_stream("pose", pose_input, self.apply_pose)
        self.journal_stream("past_poses", past, self.apply_past_poses)
        if c.keyframes.enabled:
            odometry = self.input("odom", keys.odometry(robot), Odometry, self.on_odometry, policy="lossless",
                                  depth=1024, check=self.check_odometry, raw=True)
            odometry.drives_output = False  # motion feeds the gate; only images call for an output
            self.journal_stream("odom", odometry, self.apply_odometry)
        self.odometry = odometry_buffer()
        self.pose_motion = odometry_buffer()  # the odometry between the localizer's estimates (PoseRecorder)
        self.pose_queue: collections.deque[PoseEstimate] = collections.deque()  # estimates awaiting their odometry
        self.odometry_seen = False
        self.motion: Increment | None = None  # since the last key-frame
        self.odometry_end: int | None = None  # the latest stamp an odometry message reached (this run of the stream)
        self.odometry_holes: list[tuple[int, int]] = []  # (start, end) ns no message covers, not yet behind a key-frame
        self.last_key: tuple[int, np.ndarray] | None = None  # (stamp_ns, thumbnail) of the last key-frame
        self.gated: collections.Counter[str] = collections.Counter()  # images per key-frame reason ("": skipped)
        # numba compiles the engine's kernels on first use (~15 s of CPU on a fresh install): done here, before the
        # worker reports running, or the first real frames stall and the image queue drops them.
        self.compile_kernels(warm_up, c.engine, self.feature_params)
        # Frames waiting for the engine while its one-off step runs on the helper thread (module docstring).
        self.backlog: collections.deque[tuple[FeatureSequence, object, np.ndarray | None]] = collections.deque()
        self.one_off: Future | None = None
        self.helper = ThreadPoolExecutor(1, thread_name_prefix="loopclosure-one-off", initializer=_lowest_priority)
        self.every(FEED_S, self._feed_idle)

    def _engine(self) -> LoopClosureEngine:
        if self.engine is None:
            root = self.state_store_dir
            generation = f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
            storage = FileStorage(root / generation) if root is not None else None
            self.engine = LoopClosureEngine(self.params, self.vocabulary, storage)
        return self.engine

    # --- inputs ---------------------------------------------------------------------------------------------

    def check_image(self, frame: Image) -> None:
        """Before anything is decoded (zenoh's thread): the size limit, and the camera model when there is one."""
        check_clock(frame)  # the key-frame gate and the places' poses go by its stamp
        check_image(frame, self.config.max_image_pixels, self.camera)

    def check_odometry(self, frame: Odometry) -> None:
        check_odometry_limits(frame, self.config)

    def on_camera_model(self, frame: CameraModel) -> None:
        camera = camera_from_frame(frame)
        if self.camera is None:
            self.logger.info("camera model received: %d camera(s)", len(members(camera)))
        self.camera = camera
        self.resumed(NO_MODEL)
        if self.waiting_for_model is not None:
            image, self.waiting_for_model = self.waiting_for_model, None
            try:
                self.on_image(image)
            except FrameError as error:  # taken before there was a model to check it against
                self.logger.warning("the image that waited for the camera model does not fit it: %s", error)
                self.skipped(NO_MODEL)

    def on_odometry(self, frame: Odometry, payload: bytes) -> None:
        try:
            self.apply_odometry(frame)
        finally:  # (a message that failed half-way changed the state all the same: replayed, it fails the same)
            self.journal_write("odom", payload)
        self._publish_pose_changes()

    def apply_odometry(self, frame: Odometry) -> None:
        """An odometry message to the key-frame gate and the estimates' motion (journaled: replayed after a
        restart)."""
        self._note_odometry(frame)
        self.odometry.add(frame.header.stamp_ns, frame.v, frame.v_lateral, frame.omega, frame.dt)
        self.pose_motion.add(frame.header.stamp_ns, frame.v, frame.v_lateral, frame.omega, frame.dt)
        self.odometry_seen = True
        self._record_poses()

    def _note_odometry(self, frame: Odometry) -> None:
        """Time no odometry message covers, for the key-frame gate: a message starting after the latest one ended
        leaves a hole; one arriving late fills what it covers. Noted as the messages come rather than asked of the
        buffer (``uncovered_until``): the gate integrates up to each image even when its odometry is still to come,
        and the buffer then drops what a later message covers before that image, so it could not tell a gap from
        a message's latency. A message more than STREAM_RESTART_S back starts the stream over, as in the buffer."""
        end = int(frame.header.stamp_ns)
        start = end - int(round(frame.dt * 1e9))  # (the buffer's own interval of it)
        if self.odometry_end is None or restarted(self.odometry_end, end):
            self.odometry_end, self.odometry_holes = end, []
            return
        self.odometry_holes = [part for a, b in self.odometry_holes
                               for part in ((a, min(b, start)), (max(a, end), b)) if part[0] < part[1]]
        if start > self.odometry_end:
            self.odometry_holes = [*self.odometry_holes, (self.odometry_end, start)][-ODOMETRY_HOLES:]
        self.odometry_end = max(self.odometry_end, end)

    def is_keyframe(self, stamp_ns: int, image: np.ndarray) -> bool:
        """The key-frame gate on one camera image (counted per reason; the state moves on to it when it is one)."""
        thumb = thumbnail(image)
        if self.odometry_seen:
            step = self.odometry.integrate_until(stamp_ns)
            if step is not None:
                self.motion = compose(self.motion, step)
        motion = (self.motion or Increment(0.0, 0.0, 0.0, 0.0)) if self.odometry_seen else None
        since = change = None
        gap = 0.0
        if self.last_key is not None and restarted(self.last_key[0], stamp_ns):
            # a new run of the images (a session replayed again) starts over
            self.last_key, self.motion, self.odometry_holes = None, None, []
        if self.last_key is not None:
            since = max(0.0, (stamp_ns - self.last_key[0]) * 1e-9)
            change = appearance_change(thumb, self.last_key[1])
            # the holes between the last key-frame and this image: motion the odometry leaves out
            gap = 1e-9 * sum(min(b, stamp_ns) - max(a, self.last_key[0]) for a, b in self.odometry_holes
                             if a < stamp_ns and b > self.last_key[0])
        # at most what the odometry's limits allow in that time: a source whose dt leaves a few microseconds between
        # its messages does not make every image a key-frame
        uncovered = (gap * self.config.max_speed, gap * self.config.max_turn_rate) if gap else None
        reason = keyframe_reason(self.config.keyframes, since, motion, change, uncovered)
        self.gated[reason or ""] += 1
        if reason is None:
            return False
        if reason == "odometry_gap":
            self.logger.info("key-frame at %d: no odometry covers %.2f s since the last one, the motion is unknown",
                             stamp_ns, gap)
        # the motion counts afresh from here; a hole reaching past it is still ahead of the next key-frame
        self.odometry_holes = [(a, b) for a, b in self.odometry_holes if b > stamp_ns]
        self.last_key, self.motion = (int(stamp_ns), thumb), None
        kept = sum(self.gated.values()) - self.gated[""]
        if kept in (1, 10, 100) or kept % 500 == 0:
            held = f"; the map holds {self.engine.n_kept}" if self.engine is not None else ""
            self.logger.info("key-frames: %d of %d images (%s)%s", kept, sum(self.gated.values()),
                             ", ".join(f"{k} {v}" for k, v in sorted(self.gated.items()) if k), held)
        return True

    def on_image(self, frame: Image) -> None:
        if self.camera is None:
            if self.waiting_for_model is not None:  # a newer image replaces it
                self.skipped(NO_MODEL)
            self.waiting_for_model = frame
            return
        cameras = members(self.camera)
        check_image(frame, self.config.max_image_pixels, self.camera)  # again: the camera model may have changed
        images, pixels = bgr_images(frame)
        if self.config.keyframes.enabled and not self.is_keyframe(frame.header.stamp_ns, pixels[0]):
            self.answered()  # no key-frame: nothing to publish, and that is the answer
            return  # (a rig is gated on its first camera's view)
        if len(cameras) == 1:
            features = extract_features(pixels[0], self.camera, self.feature_params, extrinsic_overrides(images)[0])
        else:
            features = extract_features(pixels, self.camera, self.feature_params)
        self.process(features, frame.header, pixels[0])

    def on_features(self, frame: LoopFeatures) -> None:
        self.process(features_from_frame(frame), frame.header, None)

    def on_pose(self, frame: PoseEstimate, payload: bytes) -> None:
        self.estimates_order.check(frame)  # (FrameError: refused, the state unchanged, nothing journaled)
        try:
            self.apply_pose(frame, checked=True)
        finally:
            self.journal_write("pose", payload)
        self._publish_pose_changes()

    def apply_pose(self, frame: PoseEstimate, checked: bool = False) -> None:
        """One of the localizer's estimates, in its order (journaled: replayed after a restart, where the order
        check goes on from it)."""
        if not checked:
            self.estimates_order.check(frame)
        stamp_ns = int(frame.header.stamp_ns)
        if restarted(self.last_estimate_ns, stamp_ns):
            self._new_run("estimates", stamp_ns)
        self.last_estimate_ns = stamp_ns
        if self.images_ahead:  # an estimate of the old run: its frames no longer answer to their stamps
            return
        self.pose_queue.append(frame)
        self._record_poses()

    def _new_run(self, stream: str, stamp_ns: int) -> None:
        """A new run of the images or the estimates (their stamps more than STREAM_RESTART_S back: a session
        replayed again), which names frames by the old run's stamps again. The frames keep the poses they recorded
        (the map); the old run's estimates do nothing more: its stretch ends unjudged and what it had not committed
        is dropped (``PoseRecorder.restart``), with the estimates waiting for their odometry and those kept for
        frames not processed yet. Until the other stream starts its new run too, the one behind is the old run's:
        its estimates are ignored, its frames answer to no stamp (both streams start over together: the localizer
        stamps its estimates with the images')."""
        if stream == "images":
            behind = not self.estimates_ahead and restarted(self.last_estimate_ns, stamp_ns)
            self._forget_frame_stamps()
            if behind:
                self._end_estimates_run()
            self.images_ahead, self.estimates_ahead = behind, False
        else:
            newest = self.engine.n_frames if self.engine is not None else 0
            behind = not self.images_ahead and newest > 0 and restarted(int(self.stamps[newest - 1]), stamp_ns)
            self._end_estimates_run()
            if behind:
                self._forget_frame_stamps()
            self.estimates_ahead, self.images_ahead = behind, False
        self.logger.info("a new run of the %s (stamp %d)%s", stream, stamp_ns,
                         "; the other stream's are the old run's until it starts over too" if behind else "")

    def _end_estimates_run(self) -> None:
        self.recorder.restart()
        self.pose_queue.clear()
        self.early_poses.clear()

    def _forget_frame_stamps(self) -> None:
        self.frame_of_stamp.clear()
        self.holder_of.clear()

    def _record_poses(self) -> None:
        """The localizer's estimates go to the recorder in order once the odometry reaches their stamps (it may
        arrive after the estimate), at once while no odometry is subscribed or seen; at most POSE_QUEUE wait."""
        covered = self.pose_motion.covered_until_ns if self.odometry_seen else None
        while self.pose_queue and (covered is None or covered >= self.pose_queue[0].header.stamp_ns
                                   or len(self.pose_queue) > POSE_QUEUE):
            self._record_pose(self.pose_queue.popleft())

    def _record_pose(self, frame: PoseEstimate) -> None:
        stamp_ns = int(frame.header.stamp_ns)
        moved = None
        if self.odometry_seen:
            # odometry for part of the span only (a rebooted robot, a link gap): the robot may have moved in the
            # rest, so the motion is unknown, as with none - nothing carried or judged across it (the localizer
            # diffuses its particles over that time)
            uncovered = self.pose_motion.uncovered_until(stamp_ns)
            moved = self.pose_motion.integrate_until(stamp_ns)
            if uncovered > 0:
                moved = None
        if frame.converged_std is not None:  # the localizer's own scale (a localizer without it: the defaults)
            self.recorder.follow_scale(frame.converged_std)
        committed, retracted = self.recorder.update(stamp_ns, (float(frame.x), float(frame.y), float(frame.theta)),
                                                    frame.localized(), frame.status == "localizing",
                                                    None if moved is None else (moved.dx, moved.dy, moved.dtheta),
                                                    hypothesis_spreads(frame.covariance),
                                                    None if moved is None else moved.dt, frame.motion_std)
        for stamp in retracted:
            index = self.frame_of_stamp.get(stamp)
            if index is not None:
                self._retract_pose(index)
            self.early_poses.pop(stamp, None)
        for stamp, pose in committed:
            self._commit_pose(stamp, pose)

    def _commit_pose(self, stamp: int, pose) -> None:
        """The frame with capture stamp ``stamp`` keeps ``pose`` (kept for it while it has not come yet)."""
        index = self.frame_of_stamp.get(stamp)
        if index is not None:
            self._set_pose(index, tuple(pose))
            return
        self.early_poses[stamp] = tuple(pose)
        while len(self.early_poses) > EARLY_POSES:
            self.early_poses.pop(next(iter(self.early_poses)))

    def on_past_poses(self, frame: PastPoses, payload: bytes) -> None:
        try:
            self.apply_past_poses(frame)
        finally:
            self.journal_write("past_poses", payload)
        self._publish_pose_changes()

    def apply_past_poses(self, frame: PastPoses) -> None:
        """A backward filter pass's poses of earlier frames (the localizer's ``smoothing``): those of frames
        holding no pose are kept as back-filled ones (``PoseRecorder.fill``: withdrawn with the stretch the pass
        started from); the others are counted by reason (``past_poses_refused_<reason>`` in the status).
        Journaled: replayed after a restart."""
        self._record_poses()  # the estimates the odometry has reached first: the pass's anchor among them
        poses = {int(stamp): tuple(float(v) for v in pose) for stamp, pose in zip(frame.stamps_ns, frame.poses)}
        accepted, refused = self.recorder.fill(int(frame.anchor_stamp_ns), poses)
        newest = int(self.stamps[self.engine.n_frames - 1]) if self.engine is not None and self.engine.n_frames else -1
        for stamp in accepted:  # a stamp no frame has and none will (the images are past) needs no pose kept
            if stamp in self.frame_of_stamp or stamp > newest:
                self._commit_pose(stamp, poses[stamp])
        self.past_filled += len(accepted)
        self.past_refused.update(refused)

    def _retract_pose(self, index: int) -> None:
        """Frame ``index`` forgets its pose, and so does the frame holding its view when it had it from this one."""
        holder = self.holder_of.get(index)
        if holder is not None and np.array_equal(self.frame_poses[holder], self.frame_poses[index]):
            self._write_pose(holder, UNKNOWN_POSE)
        self._write_pose(index, UNKNOWN_POSE)

    def _set_pose(self, index: int, pose) -> None:
        """Frame ``index``'s pose; a frame not kept gives it to the frame holding its view when that has none."""
        self._write_pose(index, pose)
        holder = self.holder_of.get(index)
        if holder is not None and np.all(np.isfinite(pose)) and np.isnan(self.frame_poses[holder, 0]):
            self._write_pose(holder, pose)

    def _write_pose(self, index: int, pose) -> None:
        """Every change of a frame's pose goes out with the next TopoMapUpdate (replayed, they rebuild the poses:
        ``semloc export``)."""
        pose = tuple(float(v) for v in pose)
        if not np.array_equal(self.frame_poses[index], pose, equal_nan=True):
            self.frame_poses[index] = pose
            self.pose_changes[index] = pose

    def _publish_pose_changes(self) -> None:
        """The frames' pose changes made outside a frame's processing (estimates, odometry, a backward pass)."""
        engine = self.engine
        if self.pose_changes and engine is not None:
            header = self.topomap_out.header(stamp_ns=int(self.stamps[engine.n_frames - 1]))
            self.topomap_out.publish(topomap_update_frame(header, MapUpdate(), engine.n_frames,
                                                          engine.topomap.n_nodes, self._take_pose_changes()))

    def _take_pose_changes(self) -> dict[int, tuple]:
        changes, self.pose_changes = self.pose_changes, {}
        return changes

    def _add_frame_record(self, index: int, stamp_ns: int, holder: int) -> None:
        """Frame ``index``'s stamp (and the frame holding its view, -1: kept), the stamp matched to late poses
        for the latest RECENT_FRAMES frames."""
        if index >= self.stamps.size:
            self.stamps = np.concatenate([self.stamps, np.zeros_like(self.stamps)])
            self.frame_poses = np.concatenate([self.frame_poses, np.full_like(self.frame_poses, np.nan)])
        self.stamps[index] = stamp_ns
        if self.estimates_ahead:  # a frame of the old run: the estimates' stamps name the new run's
            return
        self.frame_of_stamp[stamp_ns] = index
        if holder >= 0:
            self.holder_of[index] = holder
        while len(self.frame_of_stamp) > RECENT_FRAMES:
            self.holder_of.pop(self.frame_of_stamp.pop(next(iter(self.frame_of_stamp))), None)

    # --- one frame ------------------------------------------------------------------------------------------

    def process(self, features: FeatureSequence, source_header, thumbnail) -> None:
        """A frame's features to the engine, behind those waiting for it (module docstring): each frame taken feeds
        the two oldest waiting (one in, two out: a backlog shrinks even while the images come as fast as SIFT takes
        them, at a few milliseconds a frame once the vocabulary is there), and more while no image waits
        (``_feed_idle``)."""
        if self.replaying:
            if not self.backlog and self._store_ready():
                self._add(features, source_header, thumbnail, None)
            else:  # a store that refuses writes: the journal's frames wait for it first (they are journaled)
                self.backlog.append((features, source_header, thumbnail))
                self.replayed_waiting += 1
            return
        self.backlog.append((features, source_header, thumbnail))
        if self._feed() and self.backlog:
            self._feed()
        self._feed_idle()
        # (a one-off step far behind: waited for, and the images wait)
        while len(self.backlog) >= BACKLOG + self.replayed_waiting:
            if not self._feed(wait=True):  # the store has no room: the oldest frame taken live is given up
                del self.backlog[self.replayed_waiting]
                self.dropped_no_room += 1

    def _feed_idle(self) -> None:
        """The backlog to the engine, in order, while no image waits (an image waiting is dropped when the next
        comes), for up to FEED_S at a time."""
        if self.write_failing("store") and not self.backlog:  # (no frame to find out that the store takes them again)
            self._store_ready()
        started = time.monotonic()
        while (self.backlog and not self.image_input.waiting and time.monotonic() - started < FEED_S
               and self._feed()):
            pass

    def _store_refusal(self) -> OSError | None:
        """Why the engine's store cannot take a frame now (None: it can): its file system read-only, or with less
        than ``store_min_free_mb`` free. Checked before each frame, so that a disk filling up stops the frames
        before the engine's files refuse one halfway through (its state would then be half changed)."""
        root = self.state_store_dir
        if root is None:
            return None
        where = self.engine.storage.directory if self.engine is not None else root
        try:
            stat = os.statvfs(next(p for p in (where, *where.parents) if p.exists()))  # (a store still to make)
        except OSError as error:
            return OSError(error.errno, error.strerror, str(where))
        if stat.f_flag & os.ST_RDONLY:
            return OSError(errno.EROFS, os.strerror(errno.EROFS), str(where))
        free_mb = stat.f_bavail * stat.f_frsize / 2**20
        if free_mb < self.config.store_min_free_mb:
            return OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {free_mb:.0f} MiB free, under "
                           f"store_min_free_mb {self.config.store_min_free_mb:g}; frames wait", str(where))
        return None

    def _store_ready(self) -> bool:
        """Whether the store takes a frame now (``_store_refusal``): an outage is reported once (degraded until it
        ends), and a store restored read-only is opened writable again once it can be."""
        refusal = self._store_refusal()
        if refusal is not None:
            if not self.write_failing("store"):  # (counted once per outage, not at every frame it holds back)
                self.write_failed("store", refusal)
            return False
        if self.read_only_state is not None:
            # No frame went to the engine meanwhile: the same state, its files now open for writing.
            arrays, meta = self.read_only_state
            read_only = self.engine.storage
            try:
                self.engine = LoopClosureEngine.from_state(arrays, meta, FileStorage(read_only.directory))
            except OSError as error:  # (a file of it still refused: tried again at the next frame)
                self.write_failed("store", error, "restored read-only; frames wait until it is writable")
                return False
            read_only.close()
            self.read_only_state = None
            self.logger.info("store %s writable again: frames go to the engine", read_only.directory)
        self.write_succeeded("store")
        return True

    def _feed(self, wait: bool = False) -> bool:
        """The oldest waiting frame to the engine; False when its one-off step runs on the helper thread (started
        here when the engine names one) and ``wait`` is not set, or when the store has no room
        (``_store_ready``: the frames wait, the status is degraded until it has)."""
        if not self._store_ready():
            return False
        if self.one_off is None:
            work = self._engine().prepare(self.backlog[0][0])
            if work is not None:
                self.one_off = self.helper.submit(work)
        prepared = None
        if self.one_off is not None:
            if not (wait or self.one_off.done()):
                return False
            job, self.one_off = self.one_off, None
            try:
                prepared = job.result()
            except Exception:
                self._take()  # its frame fails as it would have in the engine
                raise
        journaled = self.replayed_waiting > 0
        self._add(*self._take(), prepared, journaled=journaled)
        return True

    def _take(self) -> tuple:
        """The oldest frame waiting."""
        self.replayed_waiting = max(0, self.replayed_waiting - 1)
        return self.backlog.popleft()

    def _add(self, features: FeatureSequence, source_header, thumbnail, prepared, journaled: bool = False) -> None:
        engine = self._engine()
        started = time.monotonic()
        result = engine.add_frame(features, prepared)
        n = engine.n_frames
        stamp_ns = int(source_header.stamp_ns)
        if n > 1 and restarted(int(self.stamps[n - 2]), stamp_ns):
            self._new_run("images", stamp_ns)
        self._add_frame_record(n - 1, stamp_ns, result.redundant_with)
        # (a frame of the old run while the estimates are the new one's: an early pose at its stamp is of another)
        self._set_pose(n - 1, UNKNOWN_POSE if self.estimates_ahead else self.early_poses.pop(stamp_ns, UNKNOWN_POSE))
        # Journaled once the state holds the frame, before its outputs: a frame published is never lost.
        if not journaled:  # (one from the journal is there still: no snapshot holds it yet, see snapshot())
            self.journal_write("features", loop_features_frame(source_header, features),
                               replay_s=time.monotonic() - started)  # SIFT is not replayed
        stamps = self.stamps[:n]
        stamp = source_header.stamp_ns
        self.similarity_out.publish(similarity_row_frame(self.similarity_out.header(stamp_ns=stamp), result,
                                                         len(features)))
        event_header = self.events_out.header(stamp_ns=stamp)
        loop_poses = self.frame_poses[result.loops]
        # A new decision threshold may revise more earlier frames than one frame carries: the rest go with the next.
        revised = take_revisions(self.revisions_due, result.revised, MAX_REVISIONS)
        self.events_out.publish(loop_closure_frame(event_header, result, stamps, loop_poses, revised))
        update = result.map_update
        if update or self.pose_changes:
            self.topomap_out.publish(topomap_update_frame(self.topomap_out.header(stamp_ns=stamp), update,
                                                          engine.n_frames, engine.topomap.n_nodes,
                                                          self._take_pose_changes()))
        if self.rerun is not None:
            self._log(result, event_header, thumbnail)

    def status_details(self) -> dict:
        """Calibration and decision figures: what the engine derived from the sequence and the precision it
        expects of the loops it reports."""
        engine = getattr(self, "engine", None)  # the status thread may ask before setup
        if engine is None:  # no frame yet (or none the store had room for)
            params = getattr(self, "params", None)
            return {"calibration": "waiting for frames",
                    "target_precision": None if params is None else params.target_precision,
                    "engine_backlog": len(getattr(self, "backlog", ())),
                    "frames_dropped_no_store_room": getattr(self, "dropped_no_room", 0), **self._keyframe_counts()}
        calibration = engine.calibration
        decision = engine.decision
        return {
            "calibration": ("calibrating" if engine.calibrating else
                            "fixed" if calibration is None else calibration.stats.get("fallback", "sequence")),
            "t_match": engine.alignment.t_match,
            "static_area": None if calibration is None else calibration.summary()["static_area"],
            # the bearing band whose count U scores pairs (tau 0: the DP's k)
            "band_half_width_deg": float(np.degrees(engine.alignment.band_half_width)),
            "band_max_log_scale": engine.alignment.band_max_log_scale,
            "target_precision": engine.params.target_precision,
            "decisions": engine.decision_state,  # 'unreachable': no threshold reaches the target, no loops reported
            "expected_precision": None if decision is None else decision.expected_precision,
            "decision_threshold": (None if decision is None or not np.isfinite(decision.threshold)
                                   else decision.threshold),
            "off_place_partners": None if decision is None else decision.off_place,  # near misses counted false
            "decided_pairs": None if decision is None else decision.decided,  # 1: next to no loops at a finite threshold
            "map_frames": engine.n_kept,  # frames whose view the map keeps; the others were visits of them
            "frames": engine.n_frames,
            "past_poses_filled": self.past_filled,  # poses a backward pass of the localizer gave
            "engine_backlog": len(self.backlog),  # frames waiting for the engine's one-off step, or store room
            "frames_dropped_no_store_room": self.dropped_no_room,
            **{f"past_poses_refused_{reason}": count for reason, count in self.past_refused.items()},
            **self._keyframe_counts(),
        }

    def _keyframe_counts(self) -> dict[str, int]:
        """The images the gate took, per reason (``keyframes_<reason>``; the status thread may ask before setup)."""
        gated = dict(getattr(self, "gated", {}))  # (a copy: the handler thread may add a reason meanwhile)
        return {f"keyframes_{reason}": count for reason, count in gated.items() if reason}

    def on_map_query(self, _request) -> TopoMap:
        engine = self._engine()
        stamps = self.stamps[:engine.n_frames]
        header = self.topomap_out.header(stamp_ns=int(stamps[-1]) if stamps.size else 0)
        return topomap_frame(header, engine.topomap, stamps, self.frame_poses[:engine.n_frames])

    # --- state ----------------------------------------------------------------------------------------------

    def snapshot(self) -> State | None:
        # The frames taken are finished first at the stop (the one-off step waited for), and the journal's always:
        # a snapshot ends their journal segments.
        while (self.stopping or self.replayed_waiting) and self.backlog:
            try:
                fed = self._feed(wait=True)
            except Exception as error:  # (that frame is lost, as in a handler; the others and the state are not)
                self.logger.error("a frame waiting for the engine failed: %s", error)
                continue
            if not fed and self.replayed_waiting:  # no snapshot: the journal keeps them for the next attempt
                raise self._store_refusal() or OSError(errno.EAGAIN, "the journal's frames wait for the store",
                                                       str(self.state_store_dir))
            if not fed:
                self.logger.error("%d frame(s) waiting for store room lost at the stop", len(self.backlog))
                self.backlog.clear()
        if self.engine is None:
            return None
        self.engine.flush()  # the store's files hold what the snapshot indexes before the snapshot is written
        arrays, meta = self.engine.state()
        arrays["stamps_ns"] = self.stamps[: self.engine.n_frames].copy()
        arrays["frame_poses"] = self.frame_poses[: self.engine.n_frames].copy()
        meta["pose_recorder"] = self.recorder.snapshot()
        # Which run each stream is in (_new_run) and the first frame answering to its stamp (none: the frame count)
        meta["runs"] = {"last_estimate_ns": self.last_estimate_ns, "images_ahead": self.images_ahead,
                        "estimates_ahead": self.estimates_ahead,
                        "stamped_from": min(self.frame_of_stamp.values(), default=self.engine.n_frames)}
        # Poses committed for frames still to come (the localizer ahead of this worker): the recorder has moved on.
        meta["early_poses"] = [[stamp, *pose] for stamp, pose in self.early_poses.items()]
        # The estimates waiting for their odometry and the odometry since the last one judged (the recorder's
        # motion): the journal after this snapshot replays onto them as they were (services/journal.py).
        motion = self.pose_motion.snapshot()
        queued = [encode(estimate) for estimate in self.pose_queue]
        arrays["pose_motion_spans"], arrays["pose_motion_twists"] = motion["spans"], motion["twists"]
        arrays["pose_queue"] = np.frombuffer(b"".join(queued), np.uint8)
        meta["motion"] = {"consumed_ns": motion["consumed_ns"], "odometry_seen": self.odometry_seen,
                          "pose_queue_bytes": [len(payload) for payload in queued]}
        if self.engine.storage.persistent:
            meta["generation"] = self.engine.storage.directory.name
            self._drop_other_generations()
        return State(arrays=arrays, meta=meta)

    def restore(self, state: State) -> None:
        arrays = dict(state.arrays)
        stamps = np.asarray(arrays.pop("stamps_ns", np.zeros(0, np.int64)), np.int64)
        poses = arrays.pop("frame_poses", np.full((len(stamps), 3), np.nan))
        motion, pose_queue = _motion(state.meta.get("motion"), arrays, self.robot)
        generation = state.meta.get("generation")
        storage = refused = None
        if generation is not None:
            root = self.state_store_dir
            if root is None or not isinstance(generation, str) or not (root / generation).is_dir():
                raise ValueError(f"the snapshot's store {generation!r} is not in {root}")
            storage = FileStorage(root / generation)
        try:
            engine = LoopClosureEngine.from_state(arrays, state.meta, storage)
        except OSError as error:
            if storage is None or error.errno not in REFUSED_WRITES:
                raise
            # The disk refuses writes (read-only, full): the state is good. Read-only, the map answers and the
            # frames wait (_store_ready) until the store can be opened for writing again.
            storage.close()
            storage = FileStorage(storage.directory, read_only=True)
            engine = LoopClosureEngine.from_state(arrays, state.meta, storage)
            refused = error
        if storage is not None and storage.made:
            raise ValueError(f"the snapshot's store {storage.directory} lacks {', '.join(storage.made[:5])}")
        if engine.params != self.params:
            self.logger.warning("the saved map was built with other parameters; continuing with the saved ones")
        if len(stamps) != engine.n_frames or np.shape(poses) != (len(stamps), 3):
            raise ValueError("saved state: stamps or poses do not match the frames")
        runs = _runs(state.meta.get("runs", {}), engine.n_frames)
        early_poses = _early_poses(state.meta.get("early_poses", []))
        self.recorder.restore(state.meta.get("pose_recorder", {}))
        self.engine = engine
        if refused is not None:
            self.read_only_state = (arrays, state.meta)
            self.write_failed("store", refused, "restored read-only; frames wait until it is writable")
        self.last_estimate_ns, self.images_ahead, self.estimates_ahead = (
            runs["last_estimate_ns"], runs["images_ahead"], runs["estimates_ahead"])
        self.stamps = np.concatenate([stamps, np.zeros(max(64, stamps.size), np.int64)])
        self.frame_poses = np.concatenate([np.asarray(poses, np.float64), np.full((max(64, stamps.size), 3), np.nan)])
        first = max(runs["stamped_from"], stamps.size - RECENT_FRAMES)  # (the old run's frames reuse the stamps)
        self.frame_of_stamp = {int(stamp): index for index, stamp in enumerate(stamps[first:].tolist(), first)}
        self.holder_of = {}  # (a pose arriving after a restart stays with its own frame)
        self.early_poses = early_poses
        self.pose_motion.restore(motion)
        self.odometry_seen = motion["odometry_seen"]
        self.pose_queue = collections.deque(pose_queue)
        self._drop_other_generations()
        self.logger.info("restored %d frames, %d nodes", engine.n_frames, engine.topomap.n_nodes)

    def teardown(self) -> None:
        self.helper.shutdown(wait=False, cancel_futures=True)

    def _drop_other_generations(self) -> None:
        """Delete the stores no snapshot refers to (a run that crashed before its first snapshot, or the one this
        run started before restoring): only the engine's own is referred to, or will be by the next snapshot."""
        root, current = self.state_store_dir, self.engine.storage
        if root is None or not root.is_dir() or not current.persistent:
            return
        for child in root.iterdir():
            if child.is_dir() and child != current.directory:
                shutil.rmtree(child, ignore_errors=True)

    # --- rerun ----------------------------------------------------------------------------------------------

    def _log(self, result, header, thumbnail) -> None:
        import rerun as rr

        self.rerun_log("status", rr.TextLog(f"frame {result.frame}: {result.status.value}"
                                            + (f" with {result.loops.tolist()}" if result.loops.size else "")
                                            + (f"; a visit of frame {result.redundant_with}"
                                               if result.redundant_with >= 0 else "")),
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
        decided = (beliefs >= self.engine.decision_threshold).astype(np.float32)
        self.rerun_log("decisions", rr.DepthImage(_pooled(n, rows, cols, decided, self.config.rerun_matrix_px),
                                                  colormap="turbo"), header=header)
        snapshot = self.engine.topomap.snapshot()
        ids = [str(k) for k in snapshot.node_ids.tolist()]
        self.rerun_log("graph", rr.GraphNodes(ids, labels=[f"{k}:{f}" for k, f in zip(ids, snapshot.keyframes.tolist())]),
                       header=header)
        self.rerun_log("graph", rr.GraphEdges([(str(a), str(b)) for a, b in snapshot.edges.tolist()],
                                              graph_type="undirected"), header=header)


def _runs(saved, n_frames: int) -> dict:
    """The snapshot's pairing of the image and estimate runs (``snapshot``), checked; a snapshot without it (saved
    before it was kept) pairs as one run of each stream, all frames answering to their stamps."""
    runs = {"last_estimate_ns": None, "images_ahead": False, "estimates_ahead": False, "stamped_from": 0}
    if not isinstance(saved, dict) or set(saved) - set(runs):
        raise ValueError("saved state: runs must be a mapping of " + ", ".join(runs))
    runs.update(saved)
    last, first = runs["last_estimate_ns"], runs["stamped_from"]
    ahead = runs["images_ahead"], runs["estimates_ahead"]
    if (not all(isinstance(flag, bool) for flag in ahead) or all(ahead)
            or not (last is None or type(last) is int) or type(first) is not int or not 0 <= first <= n_frames):
        raise ValueError("saved state: runs has a bad flag, stamp or frame index")
    return runs


def _early_poses(saved) -> dict[int, tuple[float, float, float]]:
    """The snapshot's poses of frames not processed yet (``snapshot``), checked: at most EARLY_POSES rows of an
    integer stamp and a finite x, y, theta."""
    if not isinstance(saved, list) or len(saved) > EARLY_POSES or not all(
            isinstance(row, list) and len(row) == 4 and type(row[0]) is int
            and all(isinstance(v, (int, float)) and math.isfinite(v) for v in row[1:]) for row in saved):
        raise ValueError(f"saved state: early_poses must be at most {EARLY_POSES} rows of a stamp and a finite pose")
    return {row[0]: (float(row[1]), float(row[2]), float(row[3])) for row in saved}


def _motion(saved, arrays: dict, robot: str) -> tuple[dict, list[PoseEstimate]]:
    """The snapshot's odometry buffer of the estimates' motion and the estimates waiting for it (``snapshot``; its
    arrays taken out of ``arrays``), checked: each estimate decoded and of this robot. A snapshot without them (saved
    before they were kept) restores none, as then."""
    spans, twists, queue = (arrays.pop(name, None) for name in ("pose_motion_spans", "pose_motion_twists",
                                                                "pose_queue"))
    empty = {"spans": np.zeros((0, 2), np.int64), "twists": np.zeros((0, 3)), "consumed_ns": None,
             "odometry_seen": False}
    if saved is None:
        return empty, []
    fields = {"consumed_ns", "odometry_seen", "pose_queue_bytes"}
    if not isinstance(saved, dict) or set(saved) != fields:
        raise ValueError("saved state: motion must be a mapping of " + ", ".join(sorted(fields)))
    consumed, seen, sizes = saved["consumed_ns"], saved["odometry_seen"], saved["pose_queue_bytes"]
    if (spans is None or twists is None or queue is None or not (consumed is None or type(consumed) is int)
            or not isinstance(seen, bool) or not isinstance(sizes, list) or len(sizes) > POSE_QUEUE
            or not all(type(n) is int and n > 0 for n in sizes) or sum(sizes) != np.size(queue)):
        raise ValueError("saved state: motion has a bad stamp, flag or waiting estimates")
    payload, offsets = np.asarray(queue, np.uint8).tobytes(), np.cumsum([0, *sizes]).tolist()
    estimates = []
    for start, end in zip(offsets, offsets[1:]):
        estimate = decode(payload[start:end], expected=PoseEstimate)  # (FrameError: a ValueError)
        check_robot(estimate, robot)
        estimates.append(estimate)
    buffer = odometry_buffer()
    buffer.restore({"spans": spans, "twists": twists, "consumed_ns": consumed})  # (checks its arrays)
    return buffer.snapshot() | {"odometry_seen": seen}, estimates


def _lowest_priority() -> None:
    """The helper thread yields the cores to SIFT and the other workers (on Linux a thread has its own nice value):
    its step may take longer, the images do not wait for it. Its kernels release the GIL (features.py)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (OSError, AttributeError):  # (elsewhere: the process's priority, as before)
        pass


def _pooled(n: int, rows, cols, values, size: int) -> np.ndarray:
    """An (n, n) sparse matrix drawn into at most size x size pixels (max over each block)."""
    scale = max(1, int(np.ceil(n / size)))
    side = max(1, int(np.ceil(n / scale)))
    image = np.zeros((side, side), np.float32)
    if len(rows):
        np.maximum.at(image, (np.asarray(rows) // scale, np.asarray(cols) // scale), np.asarray(values, np.float32))
    return image


WORKER = LoopClosureWorker
