"""Recognised places in the localization experiment (issue 34): the loop-closure engine runs on the sequence's own
rendered frames, beside the filter, as the loop-closure worker runs beside the localizer.

Each frame the engine decides whether it closes loops with earlier frames (its own decisions: no ground-truth
loops); each frame records the pose the filter estimated while the health monitor judged it ``localized`` (the hybrid
map). A frame that closes loops while the monitor says ``lost`` injects the poses the recognised places propose
(``semloc_core.localization.proposals``); while it says otherwise the places are the monitor's opinion at the next
frame. While it says ``lost`` or ``uncertain``, the places also weigh the particles by their agreement with them.
The kidnapped sequence is the one the filter sees, so the engine sees the teleport too.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from semloc_core.localization.health import LocalizationState, confident_places
from semloc_core.localization.proposals import PlaceProposalConfig, PlaceProposer

Log = Callable[[str], None]


def sequence_features(dataset, indices, cache_file: Path | None, log: Log) -> list:
    """SIFT features (the loop-closure worker's defaults, on the frame as rendered) of each of ``indices``' frames.
    Each frame is computed once (a sequence carried back goes over frames twice) and cached by frame index: a cache
    holding every frame asked for serves it, and frames it lacks are added to it."""
    from semloc_core.io.loopclosure import load_features, save_features
    from semloc_core.loopclosure import FeatureParams, extract_features

    params = FeatureParams()
    known: dict[int, object] = {}
    if cache_file is not None and cache_file.exists():
        frames, stored = load_features(cache_file)
        if stored.get("sift") == params.__dict__ and len(stored.get("indices", ())) == len(frames):
            known = dict(zip((int(i) for i in stored["indices"]), frames))
    missing = sorted({int(i) for i in indices} - set(known))
    start = time.perf_counter()
    for k, index in enumerate(missing):
        known[index] = extract_features(dataset.image(index), dataset.camera, params, dataset.T_body_cam_at(index))
        if (k + 1) % 100 == 0:
            log(f"  loop-closure features: {k + 1}/{len(missing)} ({(time.perf_counter() - start) / (k + 1):.2f} s "
                "a frame)")
    if cache_file is not None and missing:
        order = sorted(known)
        save_features(cache_file, [known[i] for i in order], {"indices": order, "sift": params.__dict__})
    return [known[int(i)] for i in indices]


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


class RecognisedPlaces:
    """The loop-closure engine over ``features`` (one per step of the sequence) with the places' recorded poses;
    called after each filter step with the estimate and the monitor's state. ``injections``: steps at which a
    recognised place proposed particles; ``weighed``: steps at which it weighed them (``PlaceProposer.weigh``);
    ``loops``: steps at which the engine found a loop. ``min_log_odds``: the loops that are the monitor's opinion
    (``HealthMonitor.place_opinion``; its convergence odds); ``place_std``: ``HealthMonitor.place_std``.
    ``recognised``: steps at which a loop closed with at least one frame whose pose was recorded. ``wrong_places``:
    every loop brings the recorded poses of the frames that many steps before those it closes with (a wrong
    recognition at the loop's own belief; 0: the true ones)."""

    def __init__(self, features: list, config: PlaceProposalConfig, rng: np.random.Generator, engine_params=None,
                 min_log_odds: float = math.log(9.0), wrong_places: int = 0, place_std: float = 0.5):
        from semloc_core.loopclosure import EngineParams, LoopClosureEngine

        self.features = features
        self.engine = LoopClosureEngine(engine_params or EngineParams())
        self.proposer = PlaceProposer(config)
        self.rng = rng
        self.min_log_odds = min_log_odds
        self.wrong_places = int(wrong_places)
        self.place_std = float(place_std)
        self.recorded = np.full((len(features), 3), np.nan)
        self.opinion: np.ndarray | None = None  # recorded poses of a place recognised at the last step
        self.injections: list[int] = []
        self.weighed: list[int] = []
        self.loops: list[int] = []
        self.recognised: list[int] = []

    def restart(self) -> None:
        """The localizer restarted without its pose (``semloc localize --global``): the places keep their poses, and
        the proposer may propose again at once."""
        self.proposer.restart()

    def after_step(self, step: int, estimate, state: LocalizationState, particle_filter) -> None:
        result = self.engine.add_frame(self.features[step])
        if state is LocalizationState.LOCALIZED:
            self.recorded[step] = estimate.pose
        self.opinion = None
        if result.loops.size == 0:
            return
        self.loops.append(step)
        poses = self.recorded[np.maximum(result.loops - self.wrong_places, 0)]
        if np.isfinite(poses).all(axis=1).any():
            self.recognised.append(step)
        if state is not LocalizationState.LOST:
            self.opinion = confident_places(poses, result.loop_beliefs, self.min_log_odds)
        injected, weighed = self.proposer.recognised(step, particle_filter, poses, result.loop_beliefs, state,
                                                     self.rng, self.place_std, estimate.pose)
        if injected:
            self.injections.append(step)
        if weighed:
            self.weighed.append(step)
