"""The localization experiment: the particle filter against a dataset's object map (thesis ch. 4).

For perception model A (eq. 4.6) and B (eq. 4.27), soft and hard (§4.5.2) heatlines, and three heatline sources -
``synthetic`` (synthetic scores from the ground-truth boxes, §4.8.3), ``dpm`` (simulated DPM, eq. 4.29, scores
drawn from the calibrated likelihoods) and ``detector`` (the §4.3 template detector run on the rendered images) -
it reports the position error over time and its running RMSE, the time to converge from global initialisation
(first frame after which the error stays under the filter preset's threshold for 10 frames), the RMSE after
convergence, the heading error, and with ``kidnap`` the frames needed to recover.

DATASET: a dataset folder (``semloc sim``) or ``sim:NAME`` to simulate in memory (``scenario``: a tabletop along a
real RGB-D Scenes trajectory, the world's seed, the hall's camera). Details: docs/localization.md.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Annotated, Literal

import numpy as np
from pydantic import BeforeValidator, Field, ValidationInfo, field_validator, model_validator

from semloc_core.experiments import heatline_cache as cache
from semloc_core.experiments import localization_calibration as calibrating
from semloc_core.experiments.localization_detector import DETECTOR_MIN_PIXELS
from semloc_core.experiments.spec import DataPath, DataPaths, Spec
from semloc_core.experiments.tabletop import simulated_scenario

SOURCES = ("synthetic", "dpm", "detector")


def _listed(value):
    """``"A,B"`` (as typed on a command line) -> ``["A", "B"]``; lists as they are."""
    return [v.strip() for v in value.split(",") if v.strip()] if isinstance(value, str) else value


class ScenarioSpec(Spec):
    """The world of a ``sim:NAME`` dataset."""

    seed: int = Field(0, description="the world's seed")
    trajectory: DataPath | None = Field(None, description="sim:tabletop: an RGB-D Scenes v2 .pose (or TUM) file")
    exemplars: str = Field("auto", description="sim:tabletop: real object crops folder, auto or none")
    camera: str | None = Field(None, description="sim:hall: the robot's camera (panorama = 1024x256, "
                                                 "panorama:WxH, rig, pinhole); the calibration world gets it too")


class PerceptionSpec(Spec):
    """How heatlines are weighed."""

    view: bool = Field(True, description="expect only objects inside the image and not hidden (ViewGeometry); "
                                         "false: the thesis's bearing-only field of view")
    peak: float = Field(1.0, gt=0, le=1, description="model B: p(d) at an object's bearing")
    exponent: float | Literal["auto"] = Field("auto", description="model B's likelihood exponent; auto: 1 / the "
                                                                  "source's bin correlation length on the "
                                                                  "calibration frames")
    sigma: float | Literal["auto"] = Field("auto", description="bearing spread of eq. 4.7 / 4.26 (degrees); auto: "
                                                               "the maximum-likelihood value on the calibration "
                                                               "frames (sim:NAME; otherwise the filter preset's)")
    hit_rate: float = Field(0.5, gt=0, lt=1, description="model B on hard heatlines: P(z=1|d) per bin")
    false_alarm_rate: float = Field(0.02, gt=0, lt=1, description="... and P(z=1|no object)")
    hard_width_deg: float = Field(5.0, gt=0, description="width of a hard detection (degrees)")


class LocalizationCalibrationSpec(Spec):
    """Where the detector's score likelihoods come from."""

    file: DataPath | None = Field(None, description="score likelihoods (semloc calibrate); 'self': fitted on every "
                                                    "3rd evaluated frame (an upper bound, not a fair figure); "
                                                    "default: fitted on another seed of the simulated scenario")
    frames: int = Field(360, ge=1, description="frames of the calibration scenario (every 3rd is used); not with "
                                               "trajectories, whose files are used whole")
    trajectories: DataPaths = Field([], description="sim:tabletop: calibrate on tabletops along these files "
                                                    "instead (the thesis: scenes 6, 7, 11, 12, §4.8.2), samples "
                                                    "pooled; their worlds use scenario.seed + 1000")
    bandwidth: Literal["robust_std", "normal_reference"] = Field(
        "robust_std", description="KDE bandwidth: the robust standard deviation (thesis §4.8.2) or the "
                                  "normal-reference rule")

    @model_validator(mode="after")
    def _frames_or_trajectories(self):
        # The trajectory files are used whole: a frame count given beside them would be silently ignored.
        if self.trajectories and "frames" in self.model_fields_set:
            raise ValueError("calibration.frames does nothing with calibration.trajectories (their files are used "
                             "whole): leave it out, or name fewer trajectories")
        return self


class LocalizationSpec(Spec):
    """``semloc eval localization``."""

    dataset: str | None = Field(None, description="dataset folder (semloc sim) or sim:NAME (tabletop, hall)")
    seed: int = Field(0, description="filter and simulated-DPM seed")
    cache: str | None = Field(None, description="folder keeping each source's heatlines and the calibration")
    scenario: ScenarioSpec = ScenarioSpec()
    models: Annotated[list[Literal["A", "B"]], BeforeValidator(_listed)] = ["A", "B"]
    variants: Annotated[list[Literal["soft", "hard"]], BeforeValidator(_listed)] = ["soft", "hard"]
    sources: Annotated[list[Literal[SOURCES]], BeforeValidator(_listed)] = list(SOURCES)
    filter_preset: Literal["auto", "tabletop", "hall"] = Field(
        "auto", description="scale of filter and thresholds (auto: hall for panoramas and maps over 30 m)")
    init: Literal["global", "gt"] = Field("global", description="global or ground-truth start")
    kidnap: int | None = Field(None, ge=0, description="teleport the ground truth at this position")
    jump: int | None = Field(None, description="frames skipped by the kidnapping (default N/3); negative: carried "
                                               "back to where it was that many frames before (a recorded place)")
    reinit: int | None = Field(None, ge=1, description="re-initialise the filter globally at this position (a restart "
                                                     "without its pose; recognised places keep what they recorded); "
                                                     "with kidnap at the same position, a restart elsewhere")
    stride: int = Field(1, ge=1, description="use every n-th frame")
    frames: int | None = Field(None, ge=1, description="at most this many frames (after the stride)")
    particles: int | None = Field(None, ge=1, description="max particles (default: the filter preset's)")
    filter: dict[str, float | bool] = Field({}, description="FilterConfig fields over the preset's, e.g. "
                                                            "{history_frames: 0}")
    places: bool = Field(False, description="run the loop-closure engine on the sequence's rendered frames: places "
                                            "record the estimate while localized, and a place recognised while "
                                            "lost proposes particles around its recorded poses (issue 34)")
    prior_lap: bool = Field(False, description="places: first go over the whole sequence once, unkidnapped, a "
                                               "filter of its own recording places while localized (a mapping "
                                               "lap); the measured run continues that loop-closure engine")
    lap_init: Literal["global", "gt"] | None = Field(
        None, description="prior_lap: the mapping lap's start (gt: the pose an operator gives a robot that records a "
                          "map); default: init. The measured run starts by init")
    second_traversal: str = Field("sensor", description="prior_lap: the measured run's images as the loop-closure "
                                                        "engine sees them, degraded so (semloc_core.sim.degrade "
                                                        "PRESETS; the camera model kept; none: the lap's "
                                                        "pixels, an upper bound, not a fair figure)")
    place_proposals: dict[str, float] = Field({}, description="PlaceProposalConfig fields, e.g. "
                                                              "{position_std: 0.1}")
    place_poses: dict[str, bool | int | float] = Field({}, description="PlacePoseConfig fields (which localized estimates "
                                                               "the places record), e.g. {commit_after: 0}")
    smoothing: dict[str, bool | int] = Field({}, description="SmoothingConfig fields (places: a backward filter "
                                                             "pass from each localized stretch fills the frames "
                                                             "before it), e.g. {enabled: false}")
    wrong_places: int = Field(0, ge=0, description="a wrong recognition, for measuring what one costs: every loop "
                                                   "brings the recorded poses of the frames this many steps before "
                                                   "those it closes with, at its own belief (0: the true ones)")
    health: dict[str, float | bool] = Field({}, description="HealthConfig fields (the monitor judging each "
                                                            "estimate localized / uncertain / lost), e.g. "
                                                            "{rival_frames: 5, second_model: true}")
    perception: PerceptionSpec = PerceptionSpec()
    calibration: LocalizationCalibrationSpec = LocalizationCalibrationSpec()
    estimate: DataPath | None = Field(
        None, description="a TUM trajectory of the body (semloc up --save's trajectory.tum) to evaluate instead of "
                          "running the filter: its figures against the dataset's ground truth, frames matched by stamp")
    templates: Literal["front", "selected"] = Field(
        "front", description="the detector's exemplar views: front = each class's canonical view and its mirror "
                             "(thesis §4.5.1); selected = up to 4 views per class chosen on the calibration worlds")

    @field_validator("filter")
    @classmethod
    def _known_filter_fields(cls, values: dict) -> dict:
        from semloc_core.localization import FilterConfig

        filter_with(FilterConfig(), values)  # raises for an unknown field or a bad value
        return values

    @field_validator("place_proposals", "place_poses", "smoothing")
    @classmethod
    def _known_config_fields(cls, values: dict, info: ValidationInfo) -> dict:
        from semloc_core.localization.place_poses import PlacePoseConfig
        from semloc_core.localization.proposals import PlaceProposalConfig
        from semloc_core.localization.smoothing import SmoothingConfig

        config = {"place_proposals": PlaceProposalConfig, "place_poses": PlacePoseConfig,
                  "smoothing": SmoothingConfig}[info.field_name]
        config(**values)  # raises for an unknown field or a bad value
        return values

    @field_validator("health")
    @classmethod
    def _known_health_fields(cls, values: dict) -> dict:
        health_config(values)  # raises for an unknown field or a bad value
        return values

    @model_validator(mode="after")
    def _consistent(self):
        if self.scenario.camera and not (self.dataset or "").startswith("sim:"):
            raise ValueError("scenario.camera is for sim:NAME datasets")
        if self.reinit is not None and self.frames is not None and self.reinit >= self.frames:
            raise ValueError(f"reinit {self.reinit} is past the last of {self.frames} frames")
        if self.calibration.file == "self" and "detector" not in self.sources:
            raise ValueError("calibration.file 'self' needs the detector source")
        if self.prior_lap:
            from semloc_core.experiments.localization_places import traversal_degradation

            if not self.places:
                raise ValueError("prior_lap records places: it needs places: true")
            traversal_degradation(self.second_traversal)  # raises for an unknown or unsuitable one
        elif self.lap_init is not None:
            raise ValueError("lap_init is the start of the prior lap: it needs prior_lap: true")
        return self


def filter_with(config, overrides: dict):
    """``config`` (a FilterConfig) with ``overrides`` applied (numbers or booleans; ValueError for an unknown
    field or a bad value)."""
    values = config.to_dict()
    for key, value in overrides.items():
        if key not in values:
            raise ValueError(f"unknown filter parameter {key!r}; known: {sorted(values)}")
        if not isinstance(value, (int, float)):
            raise ValueError(f"filter {key}: {value!r} is not a number or true/false")
        values[key] = type(values[key])(value)
    return type(config).from_dict(values)


def health_config(overrides: dict):
    """The monitor's ``HealthConfig`` with ``overrides`` (ValueError for an unknown field or a bad value)."""
    from semloc_core.localization.health import HealthConfig

    known = HealthConfig().to_dict()
    unknown = sorted(set(overrides) - set(known))
    if unknown:
        raise ValueError(f"unknown health parameter {unknown[0]!r}; known: {sorted(known)}")
    return HealthConfig(**{**known, **overrides})


@dataclass
class LocalizationResult:
    """The report (every figure, JSON-ready), and what the written report draws from."""

    report: dict
    semantic_map: object
    ground_truth: np.ndarray
    stamps_s: np.ndarray


def open_dataset_of(spec: LocalizationSpec):
    """The spec's dataset: made in memory for sim:NAME, else read."""
    from semloc_core.io.dataset import open_dataset

    if spec.dataset.startswith("sim:"):
        s = spec.scenario
        return simulated_scenario(spec.dataset[4:], s.seed, None, s.trajectory, s.exemplars, s.camera)
    return open_dataset(spec.dataset)


def filter_preset_of(spec: LocalizationSpec, dataset):
    from semloc_core.localization.experiment import PRESETS, preset_for

    preset = preset_for(dataset) if spec.filter_preset == "auto" else PRESETS[spec.filter_preset]
    if spec.particles:
        preset = preset.with_filter(max_particles=spec.particles, min_particles=min(preset.filter.min_particles,
                                                                                     spec.particles))
    if spec.filter:
        preset = replace(preset, filter=filter_with(preset.filter, spec.filter))
    return preset


def run_summary(name: str, metrics: dict, seconds: float) -> str:
    """One run's progress line: convergence, RMSE after it, recoveries, and on how many frames the monitor's state
    said "not localized" among those far off and those close (counts: a share read as a count misleads)."""
    rmse = metrics["rmse_after_convergence_m"]
    detection = metrics["state_detection"]
    return (f"{name:>22}: converged at {metrics['time_to_converge_frames']}, RMSE after "
            f"{'-' if rmse is None else f'{rmse:.3f} m'}, recoveries {metrics['recoveries']} ({seconds:.1f} s); "
            f"not localized on {detection['flagged_far_frames']} of {detection['far_frames']} frames > "
            f"{detection['far_m']:g} m off, {detection['flagged_near_frames']} of {detection['near_frames']} "
            f"< {detection['near_m']:g} m")


def run(spec: LocalizationSpec, log: Callable[[str], None] = lambda _: None) -> LocalizationResult:
    """Every run of the spec. Raises ValueError (and DatasetError, OSError) for inputs it cannot use."""
    from semloc_core.detection.calibration import decision_threshold
    from semloc_core.localization import ScoreLikelihood, synthetic_scores_likelihood
    from semloc_core.localization.experiment import (frame_observations, ground_truth_heatlines, make_sequence,
                                                     view_geometry)

    if spec.dataset is None:
        raise ValueError("no dataset given")
    dataset = open_dataset_of(spec)
    if spec.estimate is not None:
        return evaluate_estimate(spec, dataset, log)
    if dataset.semantic_map is None or dataset.poses2d is None or dataset.odometry is None:
        raise ValueError("the dataset needs an object map, poses and odometry")
    preset = filter_preset_of(spec, dataset)
    sources = spec.sources
    sequence = make_sequence(dataset, spec.stride, spec.frames, spec.kidnap, spec.jump)
    classes = dataset.semantic_map.class_names
    indices = [int(i) for i in sequence.indices]
    if spec.reinit is not None and spec.reinit >= len(indices):
        raise ValueError(f"reinit {spec.reinit} is past the last of {len(indices)} steps")
    lap = make_sequence(dataset, spec.stride, spec.frames) if spec.prior_lap else None
    # a sequence carried back goes over some frames twice: each is seen once; a prior lap sees every frame
    frames = sorted(set(indices) | (set(int(i) for i in lap.indices) if lap is not None else set()))
    log(f"{spec.dataset}: {len(dataset)} frames, {len(indices)} used, preset {preset.name}, classes {list(classes)}")

    calibration, calibration_source, chosen = None, None, None
    if "dpm" in sources or "detector" in sources:
        try:
            chosen = calibrating.template_views(spec, log) if "detector" in sources else None
            calibration, calibration_source = calibrating.detector_calibration(spec, log, chosen)
        except (OSError, ValueError) as error:
            raise ValueError(f"calibration failed: {error}") from None
    if "detector" in sources and calibration is None and calibration_source != "self":
        # Only a simulated scenario (sim:NAME) has other seeds to fit them on: a dataset folder needs a file.
        raise ValueError("the detector source needs calibration.file: the score likelihoods, e.g. `semloc calibrate "
                         "DATASET -o FILE` on a recording of your classes (or 'self', fitted on the evaluated "
                         "frames), or leave the detector out: --set sources=[synthetic,dpm]")
    if calibration is not None and (missing := sorted(set(classes) - set(calibration.classes))):
        raise ValueError(f"the calibration has no score likelihood of {missing} (calibrated: "
                         f"{list(calibration.classes)}); give more calibration.frames or a calibration.file")
    calibrated = ScoreLikelihood.from_calibration(calibration) if calibration is not None else None

    # what each source can see: ground-truth boxes down to the preset's size, the detector down to its usable size
    minimum_pixels = {"synthetic": preset.min_box_px, "dpm": preset.min_box_px, "detector": DETECTOR_MIN_PIXELS}
    views = {source: {i: view_geometry(dataset, i, 360, minimum_pixels[source]) for i in frames}
             for source in sources} if spec.perception.view else None
    key = cache.heatline_key(spec, dataset, preset)
    observations = {}

    def observed():
        if not observations:
            start = time.perf_counter()
            observations.update(frame_observations(dataset, frames, classes, 360, preset.min_box_px))
            log(f"ground truth views of {len(frames)} frames: {time.perf_counter() - start:.0f} s")
        return observations

    heatlines, likelihoods, thresholds = {}, {}, {}
    if "synthetic" in sources:
        heatlines["synthetic"] = cache.cached_heatlines(cache.cache_path(spec, "synthetic"), frames,
                                                        lambda: ground_truth_heatlines(observed(), "synthetic"), key)
        likelihoods["synthetic"] = synthetic_scores_likelihood(classes)
        thresholds["synthetic"] = 0.5  # where N(0.75, 0.25) and N(0.25, 0.25) cross
    if "dpm" in sources:
        likelihoods["dpm"] = calibrated if calibrated is not None else synthetic_scores_likelihood(classes)
        heatlines["dpm"] = cache.cached_heatlines(
            cache.cache_path(spec, f"dpm{spec.seed}"), frames,
            lambda: ground_truth_heatlines(observed(), "dpm", likelihoods["dpm"], seed=spec.seed),
            key + str(calibration_source))
        thresholds["dpm"] = ({c: decision_threshold(calibration, c) for c in calibration.classes}
                             if calibration is not None else 0.5)
    if "detector" in sources:
        start = time.perf_counter()
        heatlines["detector"] = cache.cached_detector_heatlines(spec, dataset, frames, key, chosen, log)
        log(f"detector heatlines: {time.perf_counter() - start:.0f} s")
        if calibration_source == "self":
            calibration = calibrating.self_calibration(dataset, heatlines["detector"], frames[::3],
                                                       spec.calibration.bandwidth)
            calibrated = ScoreLikelihood.from_calibration(calibration)
        likelihoods["detector"] = calibrated
        thresholds["detector"] = {c: decision_threshold(calibration, c) for c in calibration.classes}

    bearing_models = {}
    for source in sources:
        try:
            bearing_models[source] = calibrating.fitted_bearing_model(spec, source, likelihoods[source],
                                                                      thresholds[source], log, chosen)
        except (OSError, ValueError) as error:
            raise ValueError(f"calibrating the bearing model failed: {error}") from None

    report = {
        "dataset": spec.dataset, "frames": len(indices), "stride": spec.stride, "init": spec.init,
        "lap_init": (spec.lap_init or spec.init) if spec.prior_lap else None, "view": bool(spec.perception.view),
        "seed": spec.seed, "kidnap": spec.kidnap, "reinit": spec.reinit,
        "teleports": list(sequence.teleports), "trajectory": spec.scenario.trajectory, "camera": spec.scenario.camera,
        "scenario_seed": spec.scenario.seed if spec.dataset.startswith("sim:") else None,
        "calibration": calibration_source, "templates": spec.templates, "template_views": chosen,
        "preset": {"name": preset.name, "converge_threshold_m": preset.converge_threshold,
                   "recover_threshold_m": preset.recover_threshold, "hold_frames": preset.hold,
                   "filter": preset.filter.to_dict(), "motion": preset.motion, "alphas": list(preset.alphas),
                   "sigma_deg": math.degrees(preset.sigma), "visibility_radius_m": preset.visibility_radius
                   if math.isfinite(preset.visibility_radius) else None},
        "runs": {},
        "bearing_models": bearing_models,
    }
    ground_truth = np.asarray(dataset.poses2d)[sequence.indices]
    features, lap_features = None, None
    if spec.places:
        from semloc_core.experiments.localization_places import sequence_features, traversal_degradation

        start = time.perf_counter()
        if lap is None:
            features = sequence_features(dataset, indices, cache.cache_path(spec, "loopfeatures"), log)
        else:  # the lap sees the frames as rendered, the measured run as a second traversal
            lap_features = sequence_features(dataset, lap.indices, cache.cache_path(spec, "loopfeatures"), log)
            degradation = traversal_degradation(spec.second_traversal)
            features = sequence_features(dataset, indices, cache.cache_path(
                spec, "loopfeatures" if degradation is None else f"loopfeatures-{spec.second_traversal}"), log,
                degradation)
        log(f"loop-closure features of {len(frames)} frames: {time.perf_counter() - start:.0f} s")
    _run_filters(spec, dataset, sequence, preset, heatlines, likelihoods, thresholds, views, report, log, features,
                 (lap, lap_features) if lap is not None else None)
    report["ground_truth"] = ground_truth.tolist()
    return LocalizationResult(report, dataset.semantic_map, ground_truth,
                              np.asarray(dataset.stamps_ns)[sequence.indices] * 1e-9)


ESTIMATE_STAMP_TOLERANCE_NS = 1_000  # TUM stamps have nine decimals: a frame's own stamp comes back exactly


def evaluate_estimate(spec: LocalizationSpec, dataset, log: Callable[[str], None] = lambda _: None) \
        -> LocalizationResult:
    """The figures of a trajectory computed elsewhere (``spec.estimate``, a TUM file of the body's planar pose: a
    live run's ``trajectory.tum``) against the dataset's ground truth, on the frames whose stamps it has. The same
    formulas as the filter runs (``localization_metrics``); the frames are the matched ones."""
    from semloc_core.geometry import transform_to_pose2d
    from semloc_core.io.trajectory import read_tum
    from semloc_core.localization.evaluation import localization_metrics

    if dataset.semantic_map is None or dataset.poses2d is None:
        raise ValueError("the dataset needs an object map and poses")
    stamps_s, transforms = read_tum(spec.estimate, on_cut=log)  # a live run's file cut short: up to the cut
    stamps = np.asarray(dataset.stamps_ns, np.int64)
    wanted = np.round(stamps_s * 1e9).astype(np.int64)
    nearest = np.clip(np.searchsorted(stamps, wanted), 0, len(stamps) - 1)
    nearest = np.where((nearest > 0) & (np.abs(stamps[nearest - 1] - wanted) < np.abs(stamps[nearest] - wanted)),
                       nearest - 1, nearest)
    matched = np.abs(stamps[nearest] - wanted) <= ESTIMATE_STAMP_TOLERANCE_NS
    if not matched.any():
        raise ValueError(f"no stamp of {spec.estimate} is a frame of {spec.dataset}")
    latest = {int(frame): transform_to_pose2d(T) for frame, T in zip(nearest[matched], transforms[matched])}
    frames = np.array(sorted(latest), np.int64)  # one estimate per frame: the file's last for that stamp
    estimates = np.array([latest[int(f)] for f in frames])
    ground_truth = np.asarray(dataset.poses2d)[frames]
    preset = filter_preset_of(spec, dataset)
    metrics = localization_metrics(estimates, ground_truth, preset.converge_threshold, preset.hold)
    log(f"{spec.estimate}: {len(frames)} frames of {len(stamps)} matched ({int((~matched).sum())} stamps not "
        f"frames), RMSE {metrics['rmse_m']:.4f} m")
    report = {
        "dataset": spec.dataset, "estimate": spec.estimate, "frames": len(frames), "init": "estimate", "view": False,
        "unmatched_stamps": int((~matched).sum()), "frame_indices": frames.tolist(),
        "preset": {"name": preset.name, "converge_threshold_m": preset.converge_threshold,
                   "hold_frames": preset.hold},
        "runs": {"estimate": {"model": None, "variant": "soft", "source": "estimate", "metrics": metrics,
                              "ms_per_step": None, "estimates": estimates.tolist()}},
        "ground_truth": ground_truth.tolist(),
    }
    return LocalizationResult(report, dataset.semantic_map, ground_truth, stamps[frames] * 1e-9)


def _run_filters(spec, dataset, sequence, preset, heatlines, likelihoods, thresholds, views, report, log,
                 features=None, lap=None) -> None:
    """Every model x variant x source run into ``report["runs"]``; with ``features`` (one per step) the
    loop-closure engine's recognised places run beside each filter; with ``lap`` (a Sequence and its features) they
    first record a lap of their own filter (``spec.prior_lap``)."""
    from semloc_core.detection.heatlines import hard_heatlines
    from semloc_core.localization import ScoreLikelihood
    from semloc_core.localization.evaluation import localization_metrics, state_metrics
    from semloc_core.localization.experiment import RunSpec, run_sequence
    from semloc_core.localization.health import HealthMonitor, hypothesis_spreads
    from semloc_core.localization.smoothing import SmoothingConfig

    perception = spec.perception
    classes = dataset.semantic_map.class_names
    ground_truth = np.asarray(dataset.poses2d)[sequence.indices]
    for source in spec.sources:
        bearing = report["bearing_models"][source]
        source_preset = preset if bearing["sigma_deg"] is None else replace(preset,
                                                                            sigma=math.radians(bearing["sigma_deg"]))
        for variant in spec.variants:
            lines = heatlines[source]
            if variant == "hard":
                lines = {i: hard_heatlines(h, thresholds[source], nms_deg=5.0, width_deg=perception.hard_width_deg)
                         for i, h in lines.items()}
            for model in spec.models:
                name = f"{model}-{variant}-{source}"
                # model B's (and, for model A, the monitor's second model's)
                likelihood = (ScoreLikelihood.binary(classes, perception.hit_rate, perception.false_alarm_rate)
                              if variant == "hard" else likelihoods.get(source))
                exponent = (bearing["exponent_hard"] or bearing["exponent"]) if variant == "hard" \
                    else bearing["exponent"]
                run_spec = RunSpec(model, likelihood, init=spec.init, seed=spec.seed,
                                   exponent=exponent if model == "B" else 1.0, peak=perception.peak,
                                   view=perception.view, health=health_config(spec.health),
                                   smoothing=SmoothingConfig(**spec.smoothing))
                places = None
                if features is not None:
                    from semloc_core.experiments.localization_places import RecognisedPlaces
                    from semloc_core.localization.place_poses import PlacePoseConfig
                    from semloc_core.localization.proposals import PlaceProposalConfig

                    monitor = HealthMonitor.for_filter(source_preset.filter, run_spec.health)  # the run's
                    places = RecognisedPlaces(features if lap is None else lap[1],
                                              PlaceProposalConfig(**spec.place_proposals),
                                              np.random.default_rng([spec.seed, 35]),
                                              min_log_odds=monitor.rival_lost, wrong_places=spec.wrong_places,
                                              place_std=monitor.place_std,
                                              recording=PlacePoseConfig(**spec.place_poses),
                                              monitor=monitor)
                lap_figures = None
                if lap is not None:
                    from semloc_core.experiments.localization_places import prior_lap_figures

                    lap_spec = replace(run_spec, init=spec.lap_init or spec.init)
                    lap_trace = run_sequence(dataset, lap[0], lines, source_preset, lap_spec,
                                             views=views[source] if views else None, places=places).arrays()
                    lap_figures = prior_lap_figures(places.next_traversal(features), lap_trace["poses"],
                                                    np.asarray(dataset.poses2d)[lap[0].indices], preset)
                    lap_figures["trace"] = {  # the lap's own course, per step: where its poses came from
                        "states": lap_trace["states"], "state_reasons": lap_trace["reasons"],
                        "rival_log_odds": lap_trace["rivals"], "estimates": lap_trace["poses"].tolist(),
                        "spreads": hypothesis_spreads(lap_trace["covariances"]).tolist(),
                        "cluster_weights": lap_trace["cluster_weights"].tolist()}
                start = time.perf_counter()
                trace = run_sequence(dataset, sequence, lines, source_preset, run_spec,
                                     views=views[source] if views else None, places=places,
                                     reinit_at=spec.reinit).arrays()
                seconds = time.perf_counter() - start
                metrics = localization_metrics(trace["poses"], ground_truth, preset.converge_threshold, preset.hold,
                                               sequence.teleports, preset.recover_threshold)
                if places is not None:
                    from semloc_core.experiments.localization_places import recorded_figures

                    recorded = recorded_figures(places.recorded[places.offset:], ground_truth,
                                                [f - places.offset for f in places.backfilled if f >= places.offset],
                                                [f - places.offset for f in places.smoothed if f >= places.offset])
                    metrics["places"] = {"loops_found": len(places.loops), "loop_steps": places.loops,
                                         "recognised_steps": places.recognised, "injections": places.injections,
                                         "weighed": places.weighed,
                                         **{k: recorded[k] for k in ("recorded", "recorded_over_0_5_m", "backfilled",
                                                                     "backfilled_over_0_5_m", "smoothed",
                                                                     "smoothed_over_0_5_m")},
                                         "smoothing_refused": dict(places.smoothing_refused)}
                    if lap_figures is not None:
                        from semloc_core.experiments.localization_places import earlier_recognitions

                        metrics["places"]["prior_lap"] = lap_figures
                        metrics["places"]["lap_recognised"] = earlier_recognitions(
                            places, np.asarray(dataset.poses2d)[lap[0].indices], ground_truth)
                restart = spec.reinit if spec.reinit is not None else (sequence.teleports or (None,))[0]
                if restart is not None:
                    from semloc_core.experiments.localization_places import reentry_figures

                    metrics["reentry"] = reentry_figures(metrics["errors_m"], restart,
                                                         places.recognised if places is not None else [],
                                                         hold=preset.hold)
                metrics["state_detection"] = state_metrics(trace["states"], metrics["errors_m"],
                                                           preset.recover_threshold, preset.converge_threshold)
                report["runs"][name] = {
                    "model": model, "variant": variant, "source": source, "metrics": metrics,
                    "sigma_deg": math.degrees(source_preset.sigma), "exponent": run_spec.exponent,
                    "ms_per_step": 1e3 * float(np.median(trace["seconds"])), "seconds": seconds,
                    "statuses": trace["statuses"], "states": trace["states"], "fit_margins": trace["margins"],
                    "state_reasons": trace["reasons"], "rival_log_odds": trace["rivals"],
                    "second_rival_log_odds": trace["second_rivals"],
                    "particles": trace["particles"].tolist(), "cluster_weights": trace["cluster_weights"].tolist(),
                    "spreads": hypothesis_spreads(trace["covariances"]).tolist(),
                    "estimates": trace["poses"].tolist()}
                log(run_summary(name, metrics, seconds))
