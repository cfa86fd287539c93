"""Localizer: Heatlines (+ Odometry) in, PoseEstimate out - particle-filter localization against a map of labelled
objects (thesis ch. 4; docs/localization.md).

Map: a semantic map file (``--map``) and/or the mapper's ``ObjectMap`` stream (``--map-from-mapper``). Start: the
restored snapshot if there is one, else ``initial_pose``, else a global localization. Queries, as nav2 AMCL's
services: ``set_initial_pose`` (a Pose2D with covariance -> Ack), ``relocalize`` (global localization -> Ack), and
the latest estimate on the pose key. Odometry is buffered by stamp and integrated exactly up to each heatline's
capture stamp, then applied as one motion update;
without odometry the particles diffuse by a random walk over the time between heatlines, and over the time the
odometry leaves uncovered within it (a rebooted robot, a link gap beyond the publishers' cache, a refused message).

State (``state_dir``): the snapshot holds the whole filter (particles, recovery averages, random generator, the
history-checked proposals' window of heatlines), the buffered odometry and what the next verdict weighs (a place
recognised since the last one, the motion since); each odometry message and each update is journaled, so a restarted
worker replays them and continues draw for draw: the same inputs give the same poses and states
(tests/localization/test_localizer_restore.py). The backward passes are not kept (best-effort): they change no pose.
The particles drawn for display come from their own generator, so neither display nor
rerun output changes the filter's course.
"""

from __future__ import annotations

import collections
import math
import time
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from schemas import Ack, CameraModel, FrameError, Odometry, Pose2D, keys
from schemas.detection import Heatlines
from schemas.localization import PastPoses, PoseEstimate
from schemas.loopclosure import LoopClosure
from schemas.mapping import ANY_OBJECT_MAP, ObjectMap, ObjectMapV1
from semloc_core import bearing
from semloc_core.cache import BoundedCache
from semloc_core.io.camera_model import load_camera
from semloc_core.io.semantic_map import SemanticMap, load_semantic_map
from semloc_core.localization.filter import Status, compose_motion
from semloc_core.localization.health import HealthConfig, HealthMonitor, LocalizationState, estimate_margin
from semloc_core.localization.motion import Odometry as OdometryIncrement
from semloc_core.localization.proposals import PlaceProposalConfig, PlaceProposer
from semloc_core.localization.smoothing import BackwardSmoother, PastFrame, SmoothingConfig
from semloc_core.localization import (DifferentialDriveModel, FilterConfig, FreeSpace, GenerativeScoreModel,
                                      InnerProductModel, NonFiniteStepError, OmniDriveModel,
                                      ParticleFilter, RandomWalkModel, ScoreLikelihood, ViewGeometry,
                                      load_score_likelihood, synthetic_scores_likelihood)
from services.frames import (DEFAULT_MAX_ODOMETRY_DT, DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE, OdometryDtLimit,
                             PeerStream, SpeedLimit, TurnRateLimit, camera_from_frame, check_clock,
                             check_odometry_limits, heatlines_from_frame, odometry_buffer, past_poses_frame,
                             pose_estimate_frame, semantic_map_from_frame)
from services.runtime import Worker, WorkerConfig
from services.state import State, StateError

WARM_UP_BINS = 360  # the detector's default heatline bins; the kernels do not depend on the count

NO_MODEL = "view geometry on but no camera model yet"  # the reason heatlines without it are skipped under

STATE_LEVELS = {LocalizationState.LOCALIZED: 0, LocalizationState.UNCERTAIN: 1, LocalizationState.LOST: 2}


class LocalizerConfig(WorkerConfig):
    map: str | None = Field(None, description="semantic map file (.json/.yaml, format semloc.semantic_map)")
    map_from_mapper: bool = Field(False, description="take the map from the mapper's ObjectMap stream (and query)")
    model: Literal["A", "B"] = Field("B", description="perception model: A inner product (eq. 4.6), B generative "
                                     "score likelihood (eq. 4.27)")
    score_likelihood: str = Field("synthetic", description="model B's p(z|d), p(z|not d): 'synthetic' "
                                  "(N(0.75,0.25) / N(0.25,0.25)) or a semloc.score_likelihood JSON file")
    hard_hit_rate: float = Field(0.9, gt=0, lt=1, description="model B on hard (0/1) heatlines: P(z=1 | object)")
    hard_false_alarm_rate: float = Field(0.05, gt=0, lt=1, description="... and P(z=1 | no object)")
    sigma_deg: float = Field(5.0, gt=0, lt=90, description="bearing spread of an expected detection (degrees)")
    visibility_radius: float | None = Field(None, gt=0, description="ignore objects farther than this (m); "
                                            "default 20 for model A (dist_v), none for model B")
    peak_detection_probability: float = Field(1.0, gt=0, le=1, description="model B: p(d) at an object's bearing")
    likelihood_exponent: float = Field(1.0, gt=0, le=1, description="model B: temper the log-likelihood")
    motion: Literal["diff_drive", "omni", "random_walk"] = Field("diff_drive", description="motion model: "
                                                                 "diff_drive (eq. 4.5), omni (sideways motion too: "
                                                                 "hand-held cameras), random_walk (no odometry)")
    odom_alpha1: float = Field(0.2, ge=0, description="rotation noise from rotation (AMCL alpha1)")
    odom_alpha2: float = Field(0.2, ge=0, description="rotation noise from translation (AMCL alpha2)")
    odom_alpha3: float = Field(0.2, ge=0, description="translation noise from translation (AMCL alpha3)")
    odom_alpha4: float = Field(0.2, ge=0, description="translation noise from rotation (AMCL alpha4)")
    random_walk_translation_std: float = Field(0.2, ge=0, description="diffusion without odometry (m per sqrt s)")
    random_walk_rotation_std: float = Field(0.2, ge=0, description="diffusion without odometry (rad per sqrt s)")
    max_dt: float = Field(1.0, gt=0, description="longest gap (s) a random-walk step covers")
    classes: list[str] | None = Field(None, description="the classes heatlines and maps may name (the detector's); "
                                      "default: the map's. A frame naming another class is rejected ('classes')")
    max_speed: SpeedLimit = DEFAULT_MAX_SPEED
    max_turn_rate: TurnRateLimit = DEFAULT_MAX_TURN_RATE
    max_odometry_dt: OdometryDtLimit = DEFAULT_MAX_ODOMETRY_DT
    odometry_wait_s: float = Field(0.5, ge=0, description="once odometry flows, hold heatlines up to this long for "
                                   "the odometry that reaches their capture stamp (0: never wait)")
    filter: FilterConfig = Field(default_factory=FilterConfig, description="the particle filter "
                                 "(semloc_core.localization.FilterConfig; angles in radians)")
    health: HealthConfig = Field(default_factory=HealthConfig, description="the monitor judging each estimate "
                                 "localized / uncertain / lost (semloc_core.localization.health.HealthConfig)")
    places: bool = Field(True, description="take the loop-closure worker's recognised places (LoopClosure with "
                         "loop_poses): while lost or initialising, draw particles around their recorded poses; "
                         "while localized, a place that puts the robot elsewhere makes the state uncertain")
    place_proposals: PlaceProposalConfig = Field(default_factory=PlaceProposalConfig, description="how many "
                                                 "particles a recognised place proposes, and how far from its "
                                                 "recorded poses (semloc_core.localization.proposals)")
    smoothing: SmoothingConfig = Field(default_factory=SmoothingConfig, description="a backward filter pass from "
                                       "each localized stretch over the frames before it, a few steps per frame; "
                                       "its poses go out as PastPoses (semloc_core.localization.smoothing; "
                                       "best-effort: a restart drops the frames and passes)")
    initial_pose: list[float] | None = Field(None, description="[x, y, theta] to start from (default: global)")
    initial_covariance: list[float] = Field([0.25, 0.25, 0.0685], description="variances of the initial pose "
                                            "(x m², y m², theta rad²; AMCL initial_cov_xx/yy/aa)")
    global_localization_at_start: bool = Field(True, description="without initial pose or snapshot: global "
                                               "localization as soon as a map is there")
    view: bool = Field(False, description="expect only objects inside the image and not hidden behind nearer ones "
                       "(needs the camera model and camera_height; an extension of the thesis's model)")
    camera: str = Field("front", description="camera whose CameraModel gives the view geometry")
    calibration: str | None = Field(None, description="camera calibration YAML (default: CameraModel from the bus)")
    camera_height: float | None = Field(None, description="camera centre above the floor (m), for the view")
    sample_size: int = Field(200, ge=0, le=100_000, description="particles sent with each PoseEstimate (0: none)")
    ground_truth: bool = Field(True, description="subscribe to the ground-truth pose (rerun: estimate vs truth)")
    rerun_every: int = Field(1, ge=0, description="log to rerun every n-th update (0: never)")
    rerun_particles: int = Field(2000, ge=0, description="particles drawn in rerun")
    seed: int | None = Field(None, description="random seed (reproducible runs)")

    def memory_needs(self) -> dict[str, int]:
        n = self.filter.max_particles  # all of them at a global initialisation
        return {f"the particle filter's {n} particles at least (filter.max_particles)":
                n * ParticleFilter.KEPT_BYTES_PER_PARTICLE}

    @field_validator("initial_pose")
    @classmethod
    def _three(cls, value):
        if value is not None and (len(value) != 3 or not all(math.isfinite(v) for v in value)):
            raise ValueError("initial_pose must be three finite numbers [x, y, theta]")
        return value

    @field_validator("initial_covariance")
    @classmethod
    def _variances(cls, value):
        if len(value) != 3 or not all(math.isfinite(v) and v >= 0 for v in value):
            raise ValueError("initial_covariance must be three non-negative variances")
        return value


class Localizer(Worker):
    """Particle-filter localization against a map of labelled objects (thesis ch. 4)."""

    Config = LocalizerConfig

    def setup(self) -> None:
        c = self.config
        if not c.map and not c.map_from_mapper:
            raise ValueError("give a map file (--map) or --map-from-mapper")
        self.rng = np.random.default_rng(c.seed)  # the filter's
        self.display_rng = np.random.default_rng(None if c.seed is None else [c.seed, 1])  # samples published
        self.health_rng = np.random.default_rng(None if c.seed is None else [c.seed, 34])  # the monitor's probes
        self.monitor = HealthMonitor.for_filter(c.filter, c.health)
        self.past_published = self.past_out_of_bounds = 0
        # the backward passes draw from their own generator: the filter's course is the same with or without them
        self.smoother = BackwardSmoother(c.smoothing, self._pass_filter,
                                         lambda: HealthMonitor.for_filter(c.filter, c.health), c.health.rival_frames,
                                         np.random.default_rng(None if c.seed is None else [c.seed, 37]))
        self.health_since_ns = 0
        self.health_changes = 0
        self.place_poses: np.ndarray | None = None  # a recognised place's poses, for the next verdict
        self.moved_since_judged: np.ndarray | None = np.zeros(3)  # odometry since the last verdict (None: unknown)
        self.motion_std: tuple[float, float] | None = None  # the last prediction's increment noise (PoseEstimate)
        self.place_injections = 0
        self.proposer = PlaceProposer(c.place_proposals)
        self.pending_replay: list[tuple[str, object]] = []  # journal records that came before the map
        self.semantic_map: SemanticMap | None = None
        self.filter: ParticleFilter | None = None
        self.models = BoundedCache(4)  # perception models per (model, classes, hard)
        self.odometry = odometry_buffer()
        self.odometry_seen = False
        # heatlines ahead of the odometry: (frame, its heatlines, held since (monotonic))
        # heatlines held for their odometry, in order: (frame, heatlines, when it arrived)
        self.waiting: collections.deque[tuple[Heatlines, bearing.Heatlines, float]] = collections.deque()
        self.last_stamp_ns: int | None = None
        self.ground_truth: np.ndarray | None = None
        self.updates = 0
        self.pending_restore: State | None = None
        self.likelihood = self._load_likelihood() if "B" in (c.model, self._second_model()) else None
        self.pose_out = self.output("pose", keys.localizer_pose(self.robot), PoseEstimate)
        self.past_out = self.output("past_poses", keys.localizer_past_poses(self.robot), PastPoses)
        self.last_estimate: PoseEstimate | None = None
        self.camera_model = None  # before the map: the kernels' warm-up uses the view geometry
        # with view on, the newest heatlines before the camera model, neither predicted nor weighed yet:
        # (frame, its heatlines), updated when the model comes
        self.held_for_model: tuple[Heatlines, bearing.Heatlines] | None = None
        self.views = BoundedCache(4)  # view geometry per heatline bin count
        if c.view:
            if c.camera_height is None:
                raise ValueError("view: true needs camera_height (metres above the floor)")
            if c.calibration:
                self.camera_model = load_camera(c.calibration)
            else:
                model_key = keys.camera_model(self.robot, c.camera)
                self.latest_input("camera_model", model_key, CameraModel, self.on_camera_model)
        if c.map:
            self._set_map(load_semantic_map(c.map))
        if c.map_from_mapper:
            self.latest_input("map", keys.mapper_objects(self.robot), ANY_OBJECT_MAP, self.on_map,
                              query_key=keys.mapper_map(self.robot), check=self.check_map)
        heatlines = self.input("heatlines", keys.detector_heatlines(self.robot), Heatlines, self.on_heatlines,
                               policy="latest", depth=2, check=self.check_heatlines)
        # The odometry and heatlines of a link gap arrive when the link returns (keys.RECOVERABLE_STREAMS), in order
        # and beyond the queues' depths; a heatline waits up to odometry_wait_s for the odometry reaching its stamp.
        odometry = self.input("odom", keys.odometry(self.robot), Odometry, self.on_odometry, policy="lossless",
                              depth=4096, check=self.check_odometry, raw=True)
        odometry.drives_output = False  # motion waits for the next heatlines: only heatlines are owed a pose
        self.journal_stream("odom", odometry, self._apply_odometry)
        self.journal_stream("update", heatlines, self._apply_update)
        # a frame replaced while it waited for the camera model: its prediction only (see _hold_for_model)
        self.journal_stream("predict", heatlines, self._apply_prediction)
        # (stamp_ns, seq) of the last decision handled: in the snapshot, so that a restarted localizer's order check
        # goes on from it (a decision re-delivered after a restart would weigh and inject its place a second time)
        self.last_loop: tuple[int, int] | None = None
        if c.places:
            self.loop_stream = PeerStream()  # a decision applied twice injects twice
            loops = self.input("loops", keys.loopclosure_events(self.robot), LoopClosure, self.on_loop,
                               policy="latest", depth=4, check=self.check_loop)
            loops.drives_output = False  # a place changes the particles; the next heatlines publish the pose
            self.journal_stream("loop", loops, self._apply_loop)
        if c.odometry_wait_s > 0:
            self.every(min(0.05, c.odometry_wait_s / 2), self._flush_waiting)
        if c.ground_truth:
            self.input("ground_truth", keys.groundtruth_pose2d(self.robot), Pose2D, self.on_ground_truth,
                       policy="latest", depth=4)
        self.queryable("set_initial_pose", keys.localizer_set_initial_pose(self.robot), self.on_set_initial_pose,
                       request=Pose2D, check=self.check_pose_request)
        self.queryable("relocalize", keys.localizer_relocalize(self.robot), self.on_relocalize)
        self.queryable("pose", keys.localizer_pose(self.robot), self.on_pose_query)

    # ------------------------------------------------------------------ boundary checks (zenoh's thread)
    def _known_classes(self) -> tuple[str, ...] | None:
        if self.config.classes is not None:
            return tuple(self.config.classes)
        semantic_map = self.semantic_map  # one read: the main thread may replace it
        return None if semantic_map is None else semantic_map.class_names

    def check_heatlines(self, frame: Heatlines) -> None:
        check_clock(frame)  # the odometry is integrated up to its stamp
        known = self._known_classes()
        if known is not None:
            unknown = [name for name in frame.classes if name not in known]
            if unknown:
                raise FrameError(f"heatlines of {len(unknown)} class(es) outside the configured set, e.g. "
                                 f"{unknown[0][:40]!r}", reason="classes")

    def check_loop(self, frame: LoopClosure) -> None:
        """Recorded place poses inside the map's bounds (when there is a map), then this robot's decisions in order
        (``PeerStream``: last, as it takes the frame's stamp as the last accepted)."""
        semantic_map = self.semantic_map
        if frame.loop_poses is not None and semantic_map is not None:
            known = frame.loop_poses[np.isfinite(frame.loop_poses).all(axis=1)]
            (x_min, y_min), (x_max, y_max) = semantic_map.bounds
            if known.size and not ((known[:, 0] >= x_min) & (known[:, 0] <= x_max) & (known[:, 1] >= y_min)
                                   & (known[:, 1] <= y_max)).all():
                raise FrameError(f"a recognised place's pose outside the map's bounds "
                                 f"{semantic_map.bounds.tolist()}", reason="range")
        self.loop_stream.check(frame)

    def check_map(self, frame: ObjectMap | ObjectMapV1) -> None:
        if self.config.classes is not None:
            unknown = [name for name in frame.class_names if name not in self.config.classes]
            if unknown:
                raise FrameError(f"a map of {len(unknown)} class(es) outside the configured set, e.g. "
                                 f"{unknown[0][:40]!r}", reason="classes")

    def check_odometry(self, frame: Odometry) -> None:
        check_odometry_limits(frame, self.config)

    def check_pose_request(self, request: Pose2D) -> None:
        """A set_initial_pose request inside the map (when there is one), with a covariance (positive semi-definite,
        checked on decode) no wider than the map: checked before anything is touched."""
        semantic_map = self.semantic_map
        if semantic_map is None:
            return
        (x_min, y_min), (x_max, y_max) = semantic_map.bounds
        if not (x_min <= request.x <= x_max and y_min <= request.y <= y_max):
            raise FrameError(f"initial pose ({request.x:.6g}, {request.y:.6g}) outside the map's bounds "
                             f"{semantic_map.bounds.tolist()}", reason="range")
        if request.covariance is not None:
            extent = float(np.max(semantic_map.bounds[1] - semantic_map.bounds[0]))
            spread = float(max(request.covariance[0][0], request.covariance[1][1]))
            if spread > extent**2 or request.covariance[2][2] > (2 * math.pi) ** 2:
                raise FrameError(f"initial covariance wider than the map ({extent:.3g} m) or a full turn",
                                 reason="range")

    # ------------------------------------------------------------------ models and map
    def _second_model(self) -> str | None:
        """The monitor's second perception model (the other one), when ``health.second_model``."""
        c = self.config
        return ("A" if c.model == "B" else "B") if c.health.second_model and c.health.rivals else None

    def _load_likelihood(self) -> ScoreLikelihood | None:
        source = self.config.score_likelihood
        if source == "synthetic":
            return None  # built per class set once the classes are known
        return load_score_likelihood(source)

    def _likelihood_for(self, classes: tuple[str, ...], hard: bool) -> ScoreLikelihood:
        c = self.config
        if hard:
            return ScoreLikelihood.binary(classes, c.hard_hit_rate, c.hard_false_alarm_rate)
        return self.likelihood if self.likelihood is not None else synthetic_scores_likelihood(classes)

    def _perception(self, classes: tuple[str, ...], hard: bool, which: str | None = None):
        """The perception model ``which`` (default: the configured one; the other one is the monitor's second)."""
        c = self.config
        which = which or c.model
        key = ("A",) if which == "A" else ("B", classes if (hard or self.likelihood is None) else None, hard)
        model = self.models.get(key)
        if model is None:
            sigma = math.radians(c.sigma_deg)
            if which == "A":
                model = InnerProductModel(self.semantic_map, sigma=sigma,
                                          visibility_radius=c.visibility_radius or 20.0)
            else:
                model = GenerativeScoreModel(self.semantic_map, self._likelihood_for(classes, hard), sigma=sigma,
                                             visibility_radius=c.visibility_radius or math.inf,
                                             peak=c.peak_detection_probability, exponent=c.likelihood_exponent)
            self.models[key] = model
        return model

    def _walk(self) -> RandomWalkModel:
        """The diffusion over time without odometry (the motion models' fallback)."""
        return RandomWalkModel(self.config.random_walk_translation_std, self.config.random_walk_rotation_std)

    def _motion(self):
        c = self.config
        walk = self._walk()
        if c.motion == "random_walk":
            return walk
        alphas = dict(alpha1=c.odom_alpha1, alpha2=c.odom_alpha2, alpha3=c.odom_alpha3, alpha4=c.odom_alpha4)
        if c.motion == "omni":
            return OmniDriveModel(**alphas, fallback=walk)
        return DifferentialDriveModel(**alphas, fallback=walk)

    def _set_map(self, semantic_map: SemanticMap) -> None:
        self.semantic_map = semantic_map
        self.models.clear()
        free_space = FreeSpace.from_map(semantic_map)
        self.logger.info("map: %d objects of %d classes, bounds %s", len(semantic_map), len(semantic_map.class_names),
                         semantic_map.bounds.tolist())
        if self.filter is None:
            placeholder = GenerativeScoreModel(semantic_map, synthetic_scores_likelihood(("_",)))
            self.filter = ParticleFilter(self._motion(), placeholder, free_space, self.config.filter,
                                         rng=self.rng)
            if self.pending_restore is not None:
                self._restore_filter(self.pending_restore)
                self.pending_restore = None
                if self.pending_replay:
                    for stream, frame in self.pending_replay:
                        if stream == "odom":
                            self._apply_odometry(frame)
                        elif stream == "predict":
                            self._predict_only(frame, replayed=True)
                        else:
                            self._replay_update(frame, replayed=True)
                    self.pending_replay = []
                    self.save_state_now()  # those records are now in the state, not in the journal
            elif self.config.initial_pose is not None:
                self._start_at(self.config.initial_pose, np.diag(self.config.initial_covariance))
            elif self.config.global_localization_at_start:
                self.filter.initialize_global()
            self.compile_kernels(self._warm_up)
        else:
            self.filter.free_space = free_space  # the particles stay: same world frame
        self._log_map()

    def _warm_up(self) -> None:
        """Two throwaway corrections and verdicts by a filter and a monitor of the worker's settings, on random
        heatlines of the map's classes: numba compiles the kernels on their first call (about 15 s of CPU on a fresh
        install, cached on disk afterwards), which would otherwise stall the first real frames while the worker
        already reports running. The worker's own filter, monitor and generators are untouched."""
        classes = self.semantic_map.class_names
        noise = np.random.default_rng(0)
        filter_copy = ParticleFilter(self._motion(), self._perception(classes, hard=False), self.filter.free_space,
                                     self.config.filter, rng=noise)
        filter_copy.initialize_global()
        monitor = HealthMonitor.for_filter(self.config.filter, self.config.health)
        heatlines = bearing.Heatlines(classes, noise.random((len(classes), WARM_UP_BINS)),
                                      np.ones(WARM_UP_BINS, bool))
        view = self._view(WARM_UP_BINS)
        # the second pass: a filter with weights and rivals, motion without odometry (the random-walk fallback)
        for odometry in (OdometryIncrement(0.05, 0.01, 0.02, 0.1), None):
            filter_copy.predict(odometry, 0.1)
            filter_copy.correct(heatlines, view=view)
            estimate = filter_copy.estimate()
            margin = estimate_margin(filter_copy.perception, heatlines, estimate.pose, filter_copy.free_space, noise,
                                     monitor.config.probes, view, monitor.rivals)
            monitor.update(estimate, margin, lost_ratio=filter_copy.config.lost_ratio)

    def on_map(self, frame: ObjectMap | ObjectMapV1) -> None:
        if len(frame) == 0:
            self.logger.info("ignoring an empty object map")
            return
        self._set_map(semantic_map_from_frame(frame))

    # ------------------------------------------------------------------ inputs
    def on_odometry(self, frame: Odometry, payload: bytes) -> None:
        self._apply_odometry(frame)
        if self.filter is not None and self.filter.initialized:
            self.journal_write("odom", payload)
        self._release_waiting()

    def _apply_odometry(self, frame: Odometry) -> None:
        if self.replaying and self.filter is None:
            self.pending_replay.append(("odom", frame))
            return
        self.odometry.add(frame.header.stamp_ns, frame.v, frame.v_lateral, frame.omega, frame.dt)
        self.odometry_seen = True

    def _apply_update(self, frame: Heatlines) -> None:
        """A journaled update (the held-back release decided then is not decided again)."""
        if self.filter is None:
            self.pending_replay.append(("update", frame))
            return
        self._replay_update(frame)

    def _apply_prediction(self, frame: Heatlines) -> None:
        """A journaled prediction without its correction (a frame replaced while it waited for the camera model)."""
        if self.filter is None:
            self.pending_replay.append(("predict", frame))
            return
        self._predict_only(frame, replayed=True)

    def _replay_update(self, frame: Heatlines, replayed: bool = False) -> None:
        try:
            self._update(frame, heatlines_from_frame(frame), replayed=replayed)
        except FrameError as error:
            if error.reason != "nonfinite_state":
                raise
            # refused again, as it was the first time (the same draws and odometry): that too is the state

    def on_loop(self, frame: LoopClosure) -> None:
        if self._apply_loop(frame):
            self.journal_write("loop", frame)  # the proposals drew from the filter's generator: part of the state

    def _apply_loop(self, frame: LoopClosure) -> bool:
        """A recognised place (issue 34): while lost or initialising, particles drawn around the poses its frames
        were seen at (a minority, weighed by the next heatlines like any particle); otherwise its poses are the
        place's opinion at the next verdict. While not localized the particles are also weighed by their agreement
        with it (``PlaceProposer.weigh``). Returns whether the particle set changed."""
        self.last_loop = (int(frame.header.stamp_ns), int(frame.header.seq))
        if self.filter is None or not self.filter.initialized or frame.loop_poses is None or not len(frame.loops):
            return False
        recorded = frame.loop_poses[np.isfinite(frame.loop_poses).all(axis=1)]
        if recorded.shape[0] == 0:
            return False
        if self.monitor.state is not LocalizationState.LOST:
            self.place_poses = self.monitor.place_opinion(frame.loop_poses, frame.beliefs)
        injected, weighed = self.proposer.recognised(self.updates, self.filter, frame.loop_poses, frame.beliefs,
                                                     self.monitor.state, self.rng, self.monitor.place_std,
                                                     self.filter.estimate().pose)
        if injected:
            self.place_injections += 1
            if not self.replaying:
                self.logger.info("recognised place (frame %d, loops %s): %d particles around its poses",
                                 frame.frame, frame.loops.tolist()[:5], injected)
        return injected > 0 or weighed

    def _release_waiting(self, waited_s: float | None = None) -> None:
        """The held heatlines, in order, that the odometry reaches (or held ``waited_s`` and more: with the odometry
        there is)."""
        while self.waiting:
            frame, heatlines, arrived = self.waiting[0]
            if not self._odometry_reaches(frame.header.stamp_ns) and (
                    waited_s is None or time.monotonic() - arrived < waited_s):
                return
            self.waiting.popleft()
            self._update(frame, heatlines)

    def _odometry_reaches(self, stamp_ns: int) -> bool:
        covered = self.odometry.covered_until_ns
        return covered is not None and covered >= stamp_ns

    def _flush_waiting(self) -> None:
        """Heatlines held longer than odometry_wait_s go ahead with the motion there is."""
        self._release_waiting(self.config.odometry_wait_s)

    def on_camera_model(self, frame: CameraModel) -> None:
        self.camera_model = camera_from_frame(frame)
        self.views.clear()
        self.resumed(NO_MODEL)
        if self.held_for_model is not None:
            held, heatlines = self.held_for_model
            self.held_for_model = None
            try:
                self._update(held, heatlines)
            except FrameError as error:  # the held frame's, not the model's: the model stays
                self.logger.warning("the heatlines that waited for the camera model: %s", error)

    def _view(self, n_bins: int) -> ViewGeometry | None:
        if not self.config.view or self.camera_model is None:
            return None
        view = self.views.get(n_bins)
        if view is None:
            view = ViewGeometry.from_camera(self.camera_model, n_bins, self.config.camera_height)
            self.views[n_bins] = view
        return view

    def on_ground_truth(self, frame: Pose2D) -> None:
        self.ground_truth = np.array([frame.x, frame.y, frame.theta])

    def on_heatlines(self, frame: Heatlines) -> None:
        if self.filter is None or not self.filter.initialized:
            self.updates += 1
            if self.updates in (1, 100, 1000):
                self.logger.warning("heatlines but no map / no initial pose yet (%d dropped)", self.updates)
            return
        heatlines = heatlines_from_frame(frame)
        # Motion up to the capture stamp first: odometry that has not reached it yet (another process, another
        # machine) would otherwise be cut at the stamp and its part before it lost.
        stamp = frame.header.stamp_ns
        if self.config.odometry_wait_s > 0 and self.odometry_seen and (self.waiting or
                                                                       not self._odometry_reaches(stamp)):
            # behind those held (a link gap's, recovered in a burst ahead of their odometry): each waits its turn
            self.waiting.append((frame, heatlines, time.monotonic()))
            self._release_waiting()
            return
        self._update(frame, heatlines)

    def _update(self, frame: Heatlines, heatlines: bearing.Heatlines, replayed: bool = False) -> None:
        """Predict with the odometry up to the frame's capture stamp, correct with its heatlines, journal, publish
        (``replayed``: a journal record applied late, neither journaled nor published again). With view on and no
        camera model yet, the frame waits for it (``_hold_for_model``)."""
        view = self._view(heatlines.scores.shape[1])
        if self.config.view and view is None and not (replayed or self.replaying):
            self._hold_for_model(frame, heatlines)
            return
        stamp = frame.header.stamp_ns
        try:
            known, dt = self._predict(frame, heatlines)
            if self.config.view and view is None:
                # a journal replayed before the camera model came back: its correction cannot be made (a snapshot
                # written after this replay differs from the run that wrote the journal)
                self.updates += 1
                self.skipped(NO_MODEL)
                return
            self.filter.correct(heatlines, view=view)
        except NonFiniteStepError as error:  # the filter kept its state; the frame is counted as rejected
            if not replayed:  # its random draws and the odometry it consumed are part of the state: replay them
                self.journal_write("update", frame)
            raise FrameError(f"{error} ({self.filter.refused_steps} refused so far)", reason="nonfinite_state") \
                from None
        self._judge(heatlines, view, stamp, bool(frame.hard))
        self.updates += 1
        if replayed:
            return
        self._smooth(heatlines, view, known, dt, stamp)
        self.journal_write("update", frame)
        self._publish(frame.header.stamp_ns)
        if (self.rerun is not None and not self.replaying and self.config.rerun_every
                and self.updates % self.config.rerun_every == 0):
            self._log_update(heatlines)

    def _hold_for_model(self, frame: Heatlines, heatlines: bearing.Heatlines) -> None:
        """The camera publishes its model before its first image, but on another key: a localizer that met the camera
        after the model went out gets it from its query's reply, after the first heatlines. The newest such frame
        waits for it, unpredicted (the filter's first observation); an older one gets its prediction only, in order,
        and is skipped. Not in the state: a restart drops a waiting frame, as the odometry wait's."""
        if self.held_for_model is not None:
            self._predict_only(self.held_for_model[0])
        self.held_for_model = (frame, heatlines)

    def _predict_only(self, frame: Heatlines, replayed: bool = False) -> None:
        """The prediction of a frame whose correction cannot be made (view on, no camera model), journaled as such:
        replayed, it predicts only, whether the model is there by then or not."""
        try:
            self._predict(frame, heatlines_from_frame(frame))
        except NonFiniteStepError as error:  # the filter kept its state; its draws are part of it all the same
            self.logger.warning("prediction of heatlines without a camera model refused: %s", error)
        self.updates += 1
        if not replayed:
            self.journal_write("predict", frame)
            self.skipped(NO_MODEL)

    def _predict(self, frame: Heatlines, heatlines: bearing.Heatlines):
        """The motion since the previous frame up to this one's capture stamp; returns (the motion, if odometry has
        all of it; the time step)."""
        stamp = frame.header.stamp_ns
        dt = 0.0 if self.last_stamp_ns is None else min(max((stamp - self.last_stamp_ns) * 1e-9, 0.0),
                                                        self.config.max_dt)
        self.last_stamp_ns = stamp
        self.filter.perception = self._perception(heatlines.classes, bool(frame.hard))
        # exactly the motion up to the capture stamp: odometry newer than the image waits for the next heatlines
        uncovered = self.odometry.uncovered_until(stamp)
        motion = self.odometry.integrate_until(stamp)
        self.filter.predict(motion, dt)
        # the places carry poses back with the noise this prediction added (loop-closure worker's recorder)
        self.motion_std = None if motion is None else self.filter.motion.increment_std(motion)
        gap = 0.0 if motion is None else min(uncovered, self.config.max_dt)
        if gap > 0:
            # odometry for part of the span only: the robot may have moved in the rest, as without odometry
            self.filter.predict(None, gap)
            walk_std = self._walk().increment_std(OdometryIncrement(0.0, 0.0, 0.0, gap))
            self.motion_std = tuple(math.hypot(a, b) for a, b in zip(self.motion_std, walk_std))
        known = None if gap > 0 else motion  # the motion since the previous frame, if odometry has all of it
        self.moved_since_judged = (None if known is None or self.moved_since_judged is None else compose_motion(
            self.moved_since_judged, np.array([known.dx, known.dy, known.dtheta])))
        return known, dt

    def _pass_filter(self, rng: np.random.Generator) -> ParticleFilter:
        """A filter like the live one (motion, perception, free space, settings) for a backward pass, drawing from
        ``rng``."""
        return ParticleFilter(self.filter.motion, self.filter.perception, self.filter.free_space, self.config.filter,
                              rng=rng)

    def _smooth(self, heatlines: bearing.Heatlines, view, motion, dt: float, stamp_ns: int) -> None:
        """The frame into the backward smoother, a few steps of its passes, and the poses of those that ended out
        (off the journal: a restart drops them)."""
        estimate = self.filter.estimate()
        moved = None if motion is None else (motion.dx, motion.dy, motion.dtheta)
        self.smoother.record(PastFrame(stamp_ns, heatlines, view, moved, dt, self.filter.perception),
                             self.monitor.state is LocalizationState.LOCALIZED,
                             estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING), self.filter.snapshot)
        for anchor, reason, poses in self.smoother.advance():
            header = self.past_out.header(stamp_ns=stamp_ns, frame_id=self.semantic_map.frame_id)
            frame, outside = past_poses_frame(header, anchor, poses, self.semantic_map.bounds)
            self.past_out_of_bounds += outside
            if frame is not None:
                self.past_out.publish(frame)
                self.past_published += len(frame.stamps_ns)
            self.logger.info("backward pass from %d ended (%s): %d earlier poses, %d outside the map", anchor, reason,
                             len(poses) - outside, outside)

    def _judge(self, heatlines: bearing.Heatlines, view, stamp_ns: int, hard: bool) -> None:
        """The monitor's verdict on the estimate after this correction (its own probes: the filter's course is the
        same without it)."""
        estimate = self.filter.estimate()
        second = self._second_model()
        if second is not None:  # the other model weighs the same estimate and probes (the models' agreement)
            second = (self._perception(heatlines.classes, hard, second), self.monitor.second_rivals)
        margin = estimate_margin(self.filter.perception, heatlines, estimate.pose, self.filter.free_space,
                                 self.health_rng, self.monitor.config.probes, view, self.monitor.rivals, second)
        before = self.monitor.state
        verdict = self.monitor.update(estimate, margin, place_poses=self.place_poses,
                                      lost_ratio=self.filter.config.lost_ratio, moved=self.moved_since_judged)
        self.place_poses, self.moved_since_judged = None, np.zeros(3)
        if verdict.state is not before:
            self.health_since_ns, self.health_changes = stamp_ns, self.health_changes + 1
            if not self.replaying:
                self.logger.info("localization %s -> %s: %s", before.value, verdict.state.value, verdict.reason)

    def _start_at(self, pose, covariance) -> None:
        """The filter initialised at a pose no frame has weighed, configured (``initial_pose``: the robot may have
        been moved while off, the config copied from another site) or given (``set_initial_pose``): a hypothesis, not
        localized until the heatlines have weighed it. A restored snapshot is not one: its state comes with it."""
        self.filter.initialize_pose(pose, covariance)
        self._reset_health(given=True)

    def _reset_health(self, given: bool = False) -> None:
        """A new initialisation: the state starts again (lost; ``given``: from a given pose, held as a jump)."""
        if self.monitor.state is not LocalizationState.LOST:
            self.health_changes += 1
        self.monitor.reset(given)
        self.health_since_ns = self.last_stamp_ns or 0

    def status_details(self) -> dict:
        """The monitor's state in the status (``semloc status``): state, why, since when, how often it changed."""
        monitor = getattr(self, "monitor", None)  # the status thread may ask before setup
        smoother = getattr(self, "smoother", None)
        if monitor is None or smoother is None:
            return {}
        return {"localization_state": monitor.state.value, "localization_reason": monitor.last.reason,
                "localization_since_ns": self.health_since_ns, "localization_changes": self.health_changes,
                "place_injections": self.place_injections, "backward_passes": smoother.started,
                "backward_passes_dropped": smoother.dropped, "past_poses": self.past_published,
                "past_poses_out_of_bounds": self.past_out_of_bounds}

    def _publish(self, stamp_ns: int) -> None:
        self._set_last_estimate(stamp_ns)
        self.pose_out.publish(self.last_estimate)

    def _set_last_estimate(self, stamp_ns: int) -> None:
        """The estimate the pose query answers with (and publications send)."""
        estimate = self.filter.estimate()
        sample = weights = None
        if self.config.sample_size:
            sample, weights = self._sample(self.config.sample_size)
        header = self.pose_out.header(stamp_ns=stamp_ns, frame_id=self.semantic_map.frame_id)
        config = self.filter.config
        self.last_estimate = pose_estimate_frame(header, estimate, self.filter.last_injected, sample, weights,
                                                 state=self.monitor.state.value,
                                                 converged_std=(config.converged_xy_std, config.converged_theta_std),
                                                 motion_std=self.motion_std)

    def _sample(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        states, weights = self.filter.states, self.filter.weights
        if states.shape[0] > count:
            chosen = self.display_rng.choice(states.shape[0], count, replace=False)
            states, weights = states[chosen], weights[chosen]
        return states.astype(np.float32), weights.astype(np.float32)

    # ------------------------------------------------------------------ queries
    def on_set_initial_pose(self, request: Pose2D) -> Ack:
        header = self.pose_out.header()
        if self.filter is None:
            return Ack(header=header, ok=False, message="no map yet")
        self.check_pose_request(request)  # again, on this thread: the map may have changed since it arrived
        covariance = (np.asarray(request.covariance) if request.covariance is not None
                      else np.diag(self.config.initial_covariance))
        self._start_at([request.x, request.y, request.theta], covariance)
        self.smoother.reset()
        self.odometry.reset()  # the new pose is now: motion buffered so far is before it
        self.waiting.clear()
        self.held_for_model = None
        self.motion_std = None  # announced without a prediction
        self.logger.info("initial pose set to (%.3f, %.3f, %.3f): not localized before %d frames weigh it",
                         request.x, request.y, request.theta, self.monitor.config.rival_frames)
        self._publish(self.last_stamp_ns or 0)  # as AMCL: the new pose is announced at once
        self.save_state_now()
        return Ack(header=header, ok=True, message="initial pose set")

    def on_relocalize(self, _request) -> Ack:
        header = self.pose_out.header()
        if self.filter is None:
            return Ack(header=header, ok=False, message="no map yet")
        self.filter.initialize_global()
        self._reset_health()
        self.smoother.reset()
        self.proposer.restart()
        self.odometry.reset()  # the new pose is now: motion buffered so far is before it
        self.waiting.clear()
        self.held_for_model = None
        self.motion_std = None  # announced without a prediction
        self.logger.info("global relocalization: %d particles", self.filter.states.shape[0])
        self._publish(self.last_stamp_ns or 0)
        self.save_state_now()
        return Ack(header=header, ok=True, message="global relocalization started")

    def on_pose_query(self, _request):
        return self.last_estimate

    # ------------------------------------------------------------------ state
    def snapshot(self) -> State | None:
        if self.filter is None or not self.filter.initialized:
            return None
        filter_state = self.filter.snapshot()
        arrays = {k: v for k, v in filter_state.items() if isinstance(v, np.ndarray)}
        odometry = self.odometry.snapshot()
        arrays["odometry_spans"], arrays["odometry_twists"] = odometry["spans"], odometry["twists"]
        history = self.filter.history  # the history-checked proposals' window: their draws depend on it
        for index, (heatlines, _, _) in enumerate(history):
            arrays[f"history_scores_{index}"] = heatlines.scores
            arrays[f"history_observed_{index}"] = heatlines.observed
        estimate = self.filter.estimate()
        meta = {"filter": {k: (v.item() if isinstance(v, np.generic) else v) for k, v in filter_state.items()
                           if k not in arrays},
                "history": [{"classes": list(heatlines.classes), "view": view is not None, "motion": motion.tolist()}
                            for heatlines, view, motion in history],
                "odometry_consumed_ns": odometry["consumed_ns"], "odometry_seen": self.odometry_seen,
                "last_stamp_ns": self.last_stamp_ns, "updates": self.updates,
                "last_loop": None if self.last_loop is None else list(self.last_loop),
                "pose": [float(v) for v in estimate.pose], "status": estimate.status.value,
                "health": {**self.monitor.snapshot(), "since_ns": self.health_since_ns, "changes": self.health_changes,
                           "place_injections": self.place_injections, "last_place_step": self.proposer.last_step,
                           "rng": self.health_rng.bit_generator.state,
                           # what the next verdict weighs: a place recognised since the last one, the motion since
                           "place_poses": None if self.place_poses is None else self.place_poses.tolist(),
                           "moved": None if self.moved_since_judged is None else self.moved_since_judged.tolist()},
                "motion_std": None if self.motion_std is None else list(self.motion_std)}
        return State(arrays=arrays, meta=meta)

    def restore(self, state: State) -> None:
        last_loop = self._last_loop_of(state.meta)  # checked before anything changes
        if self.filter is None:
            self.pending_restore = state  # applied when the map arrives
        else:
            self._restore_filter(state)
        self.last_loop = last_loop
        if last_loop is not None and self.config.places:
            self.loop_stream.last = last_loop  # the decisions go on in order from the last one handled

    @staticmethod
    def _last_loop_of(meta: dict) -> tuple[int, int] | None:
        """The snapshot's last decision handled (None: none, or a snapshot from before it was kept)."""
        value = meta.get("last_loop")
        if value is None:
            return None
        if not (isinstance(value, list) and len(value) == 2 and all(isinstance(v, int) and v >= 0 for v in value)):
            raise StateError(f"last_loop: expected [stamp_ns, seq], got {str(value)[:60]}")
        return int(value[0]), int(value[1])

    def _restore_filter(self, state: State) -> None:
        meta = state.meta
        filter_state = {**meta.get("filter", {}), **{k: v for k, v in state.arrays.items()
                                                     if not k.startswith(("odometry_", "history_"))}}
        history = self._history_of(state)
        odometry = odometry_buffer()
        if "odometry_spans" in state.arrays:
            odometry.restore({"spans": state.arrays["odometry_spans"], "twists": state.arrays["odometry_twists"],
                              "consumed_ns": meta.get("odometry_consumed_ns")})
        health = dict(meta.get("health") or {})
        health_rng = health.pop("rng", None)
        place_poses = _finite_rows(health.pop("place_poses", None), "place_poses", 3)
        moved = _finite_rows(health.pop("moved", [0.0, 0.0, 0.0]), "moved", 3)
        motion_std = _finite_rows(meta.get("motion_std"), "motion_std", 2)
        if health_rng is not None:
            np.random.default_rng().bit_generator.state = health_rng  # raises on another generator's state
        self.filter.restore(filter_state)  # checks everything before changing anything
        if history is not None:
            self.filter.restore_history(history)
        if health:
            self.monitor.restore(health)
            self.health_since_ns = int(health.get("since_ns", 0))
            self.health_changes = int(health.get("changes", 0))
            self.place_injections = int(health.get("place_injections", 0))
            last = health.get("last_place_step")
            self.proposer.last_step = None if last is None else int(last)
        if health_rng is not None:
            self.health_rng.bit_generator.state = health_rng
        self.place_poses, self.moved_since_judged = place_poses, None if moved is None else moved.reshape(3)
        self.motion_std = None if motion_std is None else tuple(float(v) for v in motion_std.reshape(2))
        self.odometry = odometry
        self.odometry_seen = bool(meta.get("odometry_seen", False))
        last = meta.get("last_stamp_ns")
        self.last_stamp_ns = None if last is None else int(last)
        self.updates = int(meta.get("updates", 0))
        if self.last_stamp_ns is not None:
            self._set_last_estimate(self.last_stamp_ns)  # the pose query answers at once after a restart
        self.logger.info("restored %d particles, pose %s (%s)", self.filter.states.shape[0], meta.get("pose"),
                         meta.get("status"))

    def _history_of(self, state: State) -> list[tuple] | None:
        """The snapshot's history window (``filter.history_frames``), checked as heatlines from the bus are; None
        when a frame was weighed with the view geometry and there is no camera model yet (the window starts anew)."""
        entries = state.meta.get("history") or []
        if not isinstance(entries, list):
            raise StateError(f"history: expected a list of observations, got {str(entries)[:60]}")
        known, history = self._known_classes(), []
        kept = self.config.filter.history_frames  # the window may have been made shorter since: its newest frames
        for index in range(max(len(entries) - kept, 0) if kept else len(entries), len(entries)):
            entry = entries[index]
            scores = state.arrays.get(f"history_scores_{index}")
            observed = state.arrays.get(f"history_observed_{index}")
            if not isinstance(entry, dict) or scores is None or observed is None:
                raise StateError(f"history: observation {index} incomplete")
            classes = tuple(str(name) for name in entry.get("classes", []))
            if known is not None and not set(classes) <= set(known):
                raise StateError(f"history: observation {index} names a class outside {list(known)}")
            try:
                heatlines = bearing.Heatlines(classes, scores, observed)
            except ValueError as error:
                raise StateError(f"history: observation {index}: {error}") from None
            if not np.all(np.isfinite(heatlines.scores)):
                raise StateError(f"history: observation {index} has non-finite scores")
            view = self._view(heatlines.scores.shape[1]) if entry.get("view") else None
            if entry.get("view") and view is None:
                self.logger.warning("history window not restored: no camera model yet for its view geometry")
                return None
            motion = np.asarray(entry.get("motion"), dtype=np.float64).reshape(-1)
            if motion.shape != (3,) or not np.all(np.isfinite(motion)):
                raise StateError(f"history: observation {index}'s motion must be 3 finite numbers")
            history.append((heatlines, view, motion))
        return history

    # ------------------------------------------------------------------ rerun
    def _log_map(self) -> None:
        if self.rerun is None:
            return
        import rerun as rr

        m = self.semantic_map
        self.rerun_log("map/objects", rr.Points2D(m.positions[:, :2], radii=0.05, class_ids=m.class_index,
                                                  labels=m.labels()), static=True)
        self.rerun_log("map/bounds", rr.Boxes2D(mins=m.bounds[0], sizes=m.bounds[1] - m.bounds[0]), static=True)

    def _log_update(self, heatlines) -> None:
        import rerun as rr

        header = self.last_estimate.header
        estimate = self.filter.estimate()
        states, weights = self._sample(self.config.rerun_particles)
        if states.shape[0]:
            shade = (255 * weights / max(float(weights.max()), 1e-12)).astype(np.uint8)
            colors = np.stack([np.full_like(shade, 255), 255 - shade, 255 - shade], axis=1)
            self.rerun_log("particles", rr.Points2D(states[:, :2], radii=0.01, colors=colors), header=header)
        pose = estimate.pose
        # the monitor's state as a level (0 localized, 1 uncertain, 2 lost) beside the error, and why, as text
        self.rerun_log("state", rr.Scalars(float(STATE_LEVELS[self.monitor.state])), header=header)
        if self.health_since_ns == header.stamp_ns:
            self.rerun_log("state_changes", rr.TextLog(f"{self.monitor.state.value}: {self.monitor.last.reason}"),
                           header=header)
        self.rerun_log("estimate/position", rr.Points2D([pose[:2]], radii=0.04, colors=[[0, 120, 255]]),
                       header=header)
        self.rerun_log("estimate/heading", rr.Arrows2D(origins=[pose[:2]], vectors=[[0.3 * math.cos(pose[2]),
                                                                                     0.3 * math.sin(pose[2])]],
                                                       colors=[[0, 120, 255]]), header=header)
        self.rerun_log("estimate/covariance", rr.LineStrips2D([_ellipse(pose[:2], estimate.covariance[:2, :2])],
                                                              colors=[[0, 120, 255]]), header=header)
        if self.ground_truth is not None:
            truth = self.ground_truth
            self.rerun_log("ground_truth/position", rr.Points2D([truth[:2]], radii=0.04, colors=[[0, 200, 0]]),
                           header=header)
            self.rerun_log("ground_truth/heading", rr.Arrows2D(origins=[truth[:2]], vectors=[[
                0.3 * math.cos(truth[2]), 0.3 * math.sin(truth[2])]], colors=[[0, 200, 0]]), header=header)
            self.rerun_log("error_m", rr.Scalars(float(np.hypot(*(pose[:2] - truth[:2])))), header=header)
        expected = self.filter.perception.expected(pose, heatlines, self._view(heatlines.scores.shape[1]))
        for row, name in enumerate(heatlines.classes):
            observed = np.where(heatlines.observed, heatlines.scores[row], 0.0)
            self.rerun_log(f"heatlines/observed/{name}", rr.BarChart(observed), header=header)
            self.rerun_log(f"heatlines/expected/{name}", rr.BarChart(expected[row]), header=header)


def _finite_rows(value, name: str, columns: int) -> np.ndarray | None:
    """A snapshot's rows of ``columns`` finite numbers (None stays None); StateError otherwise: a file is untrusted."""
    if value is None:
        return None
    try:
        rows = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        rows = None
    if rows is None or rows.size == 0 or rows.size % columns or not np.all(np.isfinite(rows)):
        raise StateError(f"{name}: expected rows of {columns} finite numbers, got {str(value)[:60]}")
    return rows.reshape(-1, columns)


def _ellipse(centre, covariance, sigmas: float = 2.0, points: int = 48) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    radii = sigmas * np.sqrt(np.clip(values, 0.0, None))
    angle = np.linspace(0, 2 * np.pi, points)
    circle = np.stack([np.cos(angle) * radii[0], np.sin(angle) * radii[1]], axis=1)
    return centre + circle @ vectors.T


WORKER = Localizer
