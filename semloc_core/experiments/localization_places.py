"""Recognised places in the localization experiment (issue 34): the loop-closure engine runs on the sequence's own
rendered frames, beside the filter, as the loop-closure worker runs beside the localizer.

Each frame the engine decides whether it closes loops with earlier frames (its own decisions: no ground-truth loops);
each frame records the pose the filter estimated while the health monitor judged it ``localized``, by the loop-closure
worker's rule (``semloc_core.localization.place_poses.PoseRecorder``: committed late, withdrawn when the filter
abandons the stretch; the hybrid map). A frame that closes loops while the monitor says ``lost`` injects the poses the
recognised places propose (``semloc_core.localization.proposals``); while it says otherwise the places are the
monitor's opinion at the next frame. While it says ``lost`` or ``uncertain``, the places also weigh the particles by
their agreement with them. The kidnapped sequence is the one the filter sees, so the engine sees the teleport too.

A prior lap (``LocalizationSpec.prior_lap``): the engine and a filter of its own first go over the whole sequence,
unkidnapped, recording places as above; the measured run's frames then continue the same engine
(``RecognisedPlaces.next_traversal``), their images degraded (``sequence_features``'s ``degradation``) so that a
place is recognised from another traversal's view, never from the same pixels.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from semloc_core.localization.filter import Status
from semloc_core.localization.health import LocalizationState, confident_places, hypothesis_spreads
from semloc_core.localization.place_poses import PlacePoseConfig, PoseRecorder
from semloc_core.localization.proposals import PlaceProposalConfig, PlaceProposer

Log = Callable[[str], None]


def sequence_features(dataset, indices, cache_file: Path | None, log: Log, degradation=None) -> list:
    """SIFT features (the loop-closure worker's defaults, on the frame as rendered) of each of ``indices``' frames.
    Each frame is computed once (a sequence carried back goes over frames twice) and cached by frame index: a cache
    holding every frame asked for serves it, and frames it lacks are added to it. ``degradation``
    (``semloc_core.sim.degrade.Degradation``): the frames as a second traversal sees them."""
    from semloc_core.experiments.heatline_cache import looks
    from semloc_core.io.loopclosure import load_features, save_features
    from semloc_core.loopclosure import FeatureParams, extract_features
    from semloc_core.sim.degrade import degrade

    params = FeatureParams()
    known: dict[int, object] = {}
    described = {"sift": params.__dict__, "looks": looks(dataset)}
    if degradation is not None:
        described["degradation"] = {k: list(v) if isinstance(v, tuple) else v for k, v in degradation.__dict__.items()}
    if cache_file is not None and cache_file.exists():
        frames, stored = load_features(cache_file)
        if all(stored.get(k) == v for k, v in described.items()) and len(stored.get("indices", ())) == len(frames):
            known = dict(zip((int(i) for i in stored["indices"]), frames))
    missing = sorted({int(i) for i in indices} - set(known))
    start = time.perf_counter()
    for k, index in enumerate(missing):
        image = dataset.image(index)
        if degradation is not None:  # numbered after a first traversal of the whole sequence: its second half
            image = degrade(image, len(dataset) + index, 2 * len(dataset), degradation)
        known[index] = extract_features(image, dataset.camera, params, dataset.T_body_cam_at(index))
        if (k + 1) % 100 == 0:
            log(f"  loop-closure features: {k + 1}/{len(missing)} ({(time.perf_counter() - start) / (k + 1):.2f} s "
                "a frame)")
    if cache_file is not None and missing:
        order = sorted(known)
        save_features(cache_file, [known[i] for i in order], {"indices": order, **described})
    return [known[int(i)] for i in indices]


def traversal_degradation(name: str):
    """The named degradation (``semloc_core.sim.degrade.PRESETS``) of a second traversal's images, checked: it must
    keep the camera model (no downscale or fisheye warp), so the features' bearings stay the camera's. None for
    ``none``: the lap's own pixels, an upper bound (recognition is trivial), not a fair figure."""
    from semloc_core.sim.degrade import PRESETS

    if name not in PRESETS:
        raise ValueError(f"unknown degradation {name!r}: one of {', '.join(PRESETS)}")
    degradation = PRESETS[name]
    if degradation.size is not None or degradation.fisheye:
        raise ValueError(f"degradation {name!r} changes the camera model (size or fisheye): not for a second traversal")
    return None if degradation.is_identity else degradation


def reentry_figures(errors, start: int, recognised, thresholds=(0.5, 1.0, 2.0), hold: int = 10) -> dict:
    """How soon a filter re-initialised (or kidnapped) at step ``start`` settles, per error threshold (m): the first
    step from which the error stays under it for ``hold`` steps (``first_settled``), counted from ``start`` and from
    the first step at or after ``start`` that recognised a place with recorded poses (``recognised``, ascending)."""
    from semloc_core.localization.evaluation import first_settled

    entered = next((int(s) for s in recognised if s >= start), None)
    figures = {"start": int(start), "recognised_at": entered, "thresholds": {}}
    for threshold in thresholds:
        settled = first_settled(np.asarray(errors, float), threshold, hold, start)
        figures["thresholds"][str(threshold)] = {
            "settled_at": settled,
            "frames_from_start": None if settled is None else settled - start,
            "frames_from_recognised": None if settled is None or entered is None else settled - entered}
    return figures


def prior_lap_figures(lap: dict, estimates, ground_truth, preset) -> dict:
    """What a prior lap left (``lap``: ``RecognisedPlaces.next_traversal``'s figures; ``estimates`` and
    ``ground_truth`` its filter's and the true planar poses): its loops, the frames it recorded and their recorded
    poses' position errors (the hybrid map's), and its own filter's convergence."""
    from semloc_core.localization.evaluation import localization_metrics

    metrics = localization_metrics(estimates, ground_truth, preset.converge_threshold, preset.hold)
    return {"frames": len(lap["recorded"]), "loops_found": len(lap["loop_steps"]),
            **recorded_figures(lap["recorded"], ground_truth, lap["backfilled"], lap["smoothed"]),
            "smoothing_refused": lap["smoothing_refused"],
            "time_to_converge_frames": metrics["time_to_converge_frames"],
            "rmse_after_convergence_m": metrics["rmse_after_convergence_m"]}


def recorded_figures(recorded, ground_truth, backfilled, smoothed=()) -> dict:
    """The recorded poses (T, 3; NaN rows: none) against the true planar poses: how many, their position errors,
    and those of the ones carried back along the odometry (``backfilled``: their steps) and of those a backward
    filter pass gave (``smoothed``)."""
    kept = np.isfinite(recorded).all(axis=1)
    errors = np.hypot(*(recorded[kept, :2] - np.asarray(ground_truth)[kept, :2]).T)
    figures = {"recorded": int(kept.sum()),
               "recorded_error_median_m": float(np.median(errors)) if errors.size else None,
               "recorded_error_p90_m": float(np.quantile(errors, 0.9)) if errors.size else None,
               "recorded_over_0_5_m": int((errors > 0.5).sum()),
               "recorded_steps": np.flatnonzero(kept).tolist(), "recorded_errors_m": errors.tolist()}
    for name, steps in (("backfilled", backfilled), ("smoothed", smoothed)):
        chosen = np.zeros(len(recorded), bool)
        chosen[list(steps)] = True
        chosen_errors = errors[chosen[kept]]
        figures.update({name: int(chosen_errors.size), f"{name}_over_0_5_m": int((chosen_errors > 0.5).sum()),
                        f"{name}_steps": np.flatnonzero(chosen & kept).tolist()})
    return figures


def earlier_recognitions(places, lap_ground_truth, ground_truth) -> dict:
    """The steps of the measured run (``places`` after ``next_traversal``) that recognised a place the prior lap
    recorded, judged by the simulator: how far (m) the step's true position is from the nearest true position of
    the lap frames it closed loops with (a right recognition is within the engine's view overlap, a wrong one far)."""
    distances = []
    for step in places.earlier_recognised:
        partners = [f for f in places.partners[step] if f < places.offset]
        distances.append(float(np.hypot(*(np.asarray(lap_ground_truth)[partners, :2]
                                          - np.asarray(ground_truth)[step, :2]).T).min()))
    return {"steps": list(places.earlier_recognised), "true_distance_m": distances}


class RecognisedPlaces:
    """The loop-closure engine over ``features`` (one per step of the sequence) with the places' recorded poses;
    called after each filter step with the estimate and the monitor's state. ``injections``: steps at which a
    recognised place proposed particles; ``weighed``: steps at which it weighed them (``PlaceProposer.weigh``);
    ``loops``: steps at which the engine found a loop. ``min_log_odds``: the loops that are the monitor's opinion
    (``HealthMonitor.place_opinion``; its convergence odds); ``place_std``: ``HealthMonitor.place_std``.
    ``recognised``: steps at which a loop closed with at least one frame whose pose was recorded;
    ``earlier_recognised``: those of them closing with a recorded frame of an earlier traversal (``next_traversal``,
    whose frames come first in the engine: ``offset``); ``partners``: per loop step, the engine frames it closed
    with. ``wrong_places``:
    every loop brings the recorded poses of the frames that many steps before those it closes with (a wrong
    recognition at the loop's own belief; 0: the true ones). ``recording``: which estimates the places keep, at the
    scale of ``monitor`` (the run's ``HealthMonitor``: its ``rival_frames`` and 'elsewhere'), carried back along the
    odometry with the noise the filter's motion model gave each increment, as the localizer worker sends it."""

    def __init__(self, features: list, config: PlaceProposalConfig, rng: np.random.Generator, engine_params=None,
                 min_log_odds: float = math.log(9.0), wrong_places: int = 0, place_std: float = 0.5,
                 recording: PlacePoseConfig | None = None, monitor=None):
        from semloc_core.loopclosure import EngineParams, LoopClosureEngine

        self.features = features
        self.engine = LoopClosureEngine(engine_params or EngineParams())
        self.proposer = PlaceProposer(config)
        self.rng = rng
        self.min_log_odds = min_log_odds
        self.wrong_places = int(wrong_places)
        self.place_std = float(place_std)
        # the monitor's window and 'elsewhere' (None: their defaults) decide which estimates the places keep
        self.recording = recording or PlacePoseConfig()
        self.recorder_scale = (None, None, None) if monitor is None else (
            monitor.config.rival_frames, monitor.elsewhere_xy, monitor.elsewhere_theta)
        self.recorder = PoseRecorder(self.recording, *self.recorder_scale)
        self.recorded = np.full((len(features), 3), np.nan)  # per engine frame
        self.offset = 0  # engine frames of the earlier traversals
        self.opinion: np.ndarray | None = None  # recorded poses of a place recognised at the last step
        self.injections: list[int] = []
        self.weighed: list[int] = []
        self.loops: list[int] = []
        self.partners: dict[int, list[int]] = {}  # step -> the engine frames it closed loops with
        self.earlier_recognised: list[int] = []  # steps closing a loop with an earlier traversal's recorded frame
        self.recognised: list[int] = []
        self.backfilled: set[int] = set()  # engine frames holding a pose carried back along the odometry
        self.smoothed: set[int] = set()  # engine frames holding a pose from a backward filter pass
        self.smoothing_refused: dict[str, int] = {}  # a pass's poses the recorder refused, by reason

    def next_traversal(self, features: list) -> dict:
        """The engine goes on over another traversal's ``features`` (one per step, steps counted from 0 again) with
        the places and poses this one recorded; the proposer may propose at once. Returns this traversal's figures
        (its steps' lists, the frames it recorded)."""
        done = {"loop_steps": self.loops, "partners": self.partners, "recognised_steps": self.recognised,
                "injections": self.injections, "weighed": self.weighed, "recorded": self.recorded[self.offset:].copy(),
                "backfilled": sorted(f - self.offset for f in self.backfilled if f >= self.offset),
                "smoothed": sorted(f - self.offset for f in self.smoothed if f >= self.offset),
                "smoothing_refused": dict(self.smoothing_refused)}
        self.smoothing_refused = {}
        self.offset = len(self.features)
        self.features = list(self.features) + list(features)
        self.recorded = np.vstack([self.recorded, np.full((len(features), 3), np.nan)])
        self.loops, self.recognised, self.injections, self.weighed = [], [], [], []
        self.partners, self.earlier_recognised = {}, []
        self.recorder = PoseRecorder(self.recording, *self.recorder_scale)  # the lap's pending: never
        # confirmed
        self.proposer.restart()
        return done

    def fill_past(self, anchor: int, poses: list) -> None:
        """A backward pass's (step, pose, covariance) anchored at step ``anchor`` (``smoothing.BackwardSmoother``)
        into the frames that hold no pose, by the recorder's rule (``PoseRecorder.fill``)."""
        given = {self.offset + int(step): pose for step, pose, _ in poses}
        accepted, refused = self.recorder.fill(self.offset + int(anchor), given)
        for key in accepted:
            self.recorded[key] = given[key]
        self.smoothed.update(accepted)
        for reason, count in refused.items():
            self.smoothing_refused[reason] = self.smoothing_refused.get(reason, 0) + count

    def restart(self) -> None:
        """The localizer restarted without its pose (``semloc localize --global``): the places keep their poses, and
        the proposer may propose again at once."""
        self.proposer.restart()

    def after_step(self, step: int, estimate, state: LocalizationState, particle_filter, odometry=None) -> None:
        """``odometry``: the motion since the last step (``semloc_core.localization.Odometry``; None: none)."""
        frame = self.offset + step
        result = self.engine.add_frame(self.features[frame])
        moved = None if odometry is None else (odometry.dx, odometry.dy, odometry.dtheta)
        committed, retracted = self.recorder.update(frame, estimate.pose, state is LocalizationState.LOCALIZED,
                                                    estimate.status in (Status.UNINITIALIZED, Status.LOCALIZING),
                                                    moved, hypothesis_spreads(estimate.covariance),
                                                    None if odometry is None else odometry.dt,
                                                    None if odometry is None else
                                                    particle_filter.motion.increment_std(odometry))
        for key, pose in committed:
            self.recorded[key] = pose
        self.recorded[retracted] = np.nan
        self.backfilled.update(self.recorder.last_backfilled)
        self.backfilled.difference_update(retracted)
        self.smoothed.difference_update(retracted)
        self.opinion = None
        if result.loops.size == 0:
            return
        self.loops.append(step)
        self.partners[step] = [int(f) for f in result.loops]
        poses = self.recorded[np.maximum(result.loops - self.wrong_places, 0)]
        recorded = np.isfinite(poses).all(axis=1)
        if recorded.any():
            self.recognised.append(step)
        if (recorded & (result.loops < self.offset)).any():
            self.earlier_recognised.append(step)
        if state is not LocalizationState.LOST:
            self.opinion = confident_places(poses, result.loop_beliefs, self.min_log_odds)
        injected, weighed = self.proposer.recognised(step, particle_filter, poses, result.loop_beliefs, state,
                                                     self.rng, self.place_std, estimate.pose)
        if injected:
            self.injections.append(step)
        if weighed:
            self.weighed.append(step)
