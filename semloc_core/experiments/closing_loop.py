"""Closing the loop: another real trajectory placed around a mapped table and localized twice with the same
observations and filter seeds, once with the mapped objects and once with the ground-truth map; the ratio of the
two RMSEs after convergence says what the map's errors cost the localizer.

The observations are synthetic heatlines from the ground-truth boxes (§4.8.3: only the map's errors count), or the
localizer's template detector's heatlines with its score likelihoods and bearing model fitted on calibration worlds
(the loop as a robot runs it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from semloc_core.experiments.spec import DataPath, DataPaths, Spec
from semloc_core.experiments.tabletop import scenario_along

Log = Callable[[str], None]


class LocalizeSpec(Spec):
    """The mapping experiment's ``localize`` settings (off without a trajectory)."""

    trajectory: DataPath | None = Field(None, description="a real trajectory to localize in the mapped world")
    frames: int | None = Field(None, ge=1, description="at most this many poses of it")
    stride: int = Field(2, ge=1, description="localize every n-th frame")
    seeds: int = Field(5, ge=1, description="filter seeds (each run with both maps)")
    noise_draws: int = Field(0, ge=0, description="also localize with N copies of the ground-truth map whose "
                                                  "objects are moved at random (planar, Gaussian) by as much as "
                                                  "the mapped objects are off")
    source: Literal["detector", "oracle"] | None = Field(None, description="whose map is localized against "
                                                                           "(default: the first heatmap source)")
    observations: Literal["synthetic", "detector"] = Field(
        "synthetic", description="what the localizer observes: synthetic heatlines from the ground-truth boxes, or "
                                 "the localizer's template detector's heatlines (calibrated on "
                                 "calibration_trajectories' worlds)")
    calibration_trajectories: DataPaths | None = Field(
        None, description="observations detector: trajectories of the calibration worlds (default: RGB-D Scenes "
                          "v2 06, 11 and 12 beside the localized trajectory)")


def calibration_trajectories(localize: LocalizeSpec) -> list[str]:
    """The calibration worlds' trajectories of detector observations: the spec's, else RGB-D Scenes v2 06, 11 and
    12 beside the localized trajectory (the worlds the localization experiment's table-top figures are calibrated
    on; docs/localization.md)."""
    return list(localize.calibration_trajectories or [
        str(Path(localize.trajectory).with_name(f"{scene}.pose")) for scene in ("06", "11", "12")])


class _WithMap:
    """A dataset whose object map is replaced (the localizer reads ``semantic_map``)."""

    def __init__(self, dataset, semantic_map):
        self._dataset = dataset
        self.semantic_map = semantic_map

    def __getattr__(self, name):
        return getattr(self._dataset, name)

    def __len__(self) -> int:
        return len(self._dataset)


def detector_observations(other, world: str, indices, localize: LocalizeSpec, seed: int, cache: str | None,
                          log: Log) -> dict:
    """The template detector's heatlines of ``other``'s ``indices``, the score likelihoods (model B) and bearing
    model (σ, exponent) fitted on simulated calibration worlds, and what the detector can see (``view_geometry``
    down to its usable size): exactly what the localization experiment's sim:tabletop detector source uses, so the
    two experiments' detector runs are comparable. Calibration and heatlines are kept in ``cache``."""
    from semloc_core.detection.calibration import decision_threshold
    from semloc_core.experiments import heatline_cache
    from semloc_core.experiments import localization_calibration as calibrating
    from semloc_core.experiments.localization import (LocalizationCalibrationSpec, LocalizationSpec,
                                                      ScenarioSpec)
    from semloc_core.experiments.localization_detector import (DETECTOR_MIN_PIXELS, DETECTOR_SETTINGS,
                                                               detector_heatlines)
    from semloc_core.localization import ScoreLikelihood
    from semloc_core.localization.experiment import view_geometry

    spec = LocalizationSpec(dataset="sim:tabletop", sources=["detector"], seed=seed, cache=cache,
                            scenario=ScenarioSpec(seed=seed),
                            calibration=LocalizationCalibrationSpec(trajectories=calibration_trajectories(localize)))
    calibration, description = calibrating.detector_calibration(spec, log, None)
    if missing := sorted(set(other.semantic_map.class_names) - set(calibration.classes)):
        raise ValueError(f"the calibration worlds hold no {missing}: give localize.calibration_trajectories whose "
                         f"worlds do")
    likelihood = ScoreLikelihood.from_calibration(calibration)
    thresholds = {c: decision_threshold(calibration, c) for c in calibration.classes}
    bearing = calibrating.fitted_bearing_model(spec, "detector", likelihood, thresholds, log, None)
    path = (Path(cache) / f"loop_{Path(localize.trajectory).stem}_in_{world}_seed{seed}"
            f"_detector_heatlines.npz") if cache else None
    key = f"{heatline_cache.fingerprint(other)} {sorted(DETECTOR_SETTINGS.items())}"
    heatlines = heatline_cache.cached_heatlines(path, indices, lambda: detector_heatlines(other, indices, log, None),
                                                key)
    views = {i: view_geometry(other, i, 360, DETECTOR_MIN_PIXELS) for i in indices}
    return {"heatlines": heatlines, "likelihood": likelihood, "bearing": bearing, "views": views,
            "calibration": description}


def close_the_loop(mapped, localize: LocalizeSpec, map_from: str, seed: int, distance: float, cache: str | None,
                   log: Log) -> dict:
    """Localize ``localize.trajectory`` in the world of ``mapped`` = (scene name, scene, predicted map) with the
    mapped objects and with the ground-truth map: the same observations, sequence and filter seeds (``seed`` ...).
    ``distance``: the match radius of the random-error reference."""
    from semloc_core.eval.objects import object_map_figures
    from semloc_core.io.semantic_map import SemanticMap
    from semloc_core.io.trajectory import read_trajectory
    from semloc_core.localization import synthetic_scores_likelihood
    from semloc_core.localization.evaluation import localization_metrics
    from semloc_core.localization.experiment import (PRESETS, RunSpec, frame_observations, ground_truth_heatlines,
                                                     make_sequence, run_sequence, view_geometry)

    if mapped is None:
        return {"error": "no mapped scene"}
    name, scene, predicted = mapped
    truth = scene.semantic_map
    try:
        other = scenario_along(scene, read_trajectory(Path(localize.trajectory))[1], localize.frames)
    except (OSError, ValueError) as error:
        log(f"closing the loop: {error}")
        return {"error": str(error)}

    # The localizer's region is the room (the ground truth's bounds and free space); only the objects differ.
    def room_map(objects: SemanticMap, positions: np.ndarray) -> SemanticMap:
        """``objects`` (those of the truth's classes) at ``positions``, in the truth's room."""
        keep = [k for k in range(len(objects)) if objects.class_names[objects.class_index[k]] in truth.class_names]
        return SemanticMap.from_objects(
            [{"class": objects.class_names[objects.class_index[k]], "position": positions[k].tolist(),
              "size": objects.sizes[k].tolist(), "score": float(objects.scores[k]),
              "existence": float(objects.existence[k])} for k in keep],
            bounds=truth.bounds, free_space=truth.free_space or None, class_names=truth.class_names)

    mapped_map = room_map(predicted, predicted.positions)
    preset = PRESETS["tabletop"]
    sequence = make_sequence(other, localize.stride)
    indices = [int(i) for i in sequence.indices]
    log(f"closing the loop: localizing {Path(localize.trajectory).stem} ({len(indices)} frames) in the world of "
        f"{name}")
    classes = truth.class_names
    if localize.observations == "detector":
        try:
            observed = detector_observations(other, name, indices, localize, seed, cache, log)
        except (OSError, ValueError) as error:
            log(f"closing the loop: {error}")
            return {"error": str(error)}
        heatlines, likelihood_b, views = observed["heatlines"], observed["likelihood"], observed["views"]
        preset = replace(preset, sigma=math.radians(observed["bearing"]["sigma_deg"]))
        exponent_b = observed["bearing"]["exponent"]
        observations = f"template detector heatlines (calibrated on {observed['calibration']})"
        bearing_model = {"sigma_deg": observed["bearing"]["sigma_deg"], "exponent_model_b": exponent_b}
    else:
        heatlines = ground_truth_heatlines(frame_observations(other, indices, classes, 360, preset.min_box_px),
                                           "synthetic")
        views = {i: view_geometry(other, i, 360) for i in indices}
        likelihood_b, exponent_b = synthetic_scores_likelihood(classes), 1.0
        observations = "synthetic heatlines from ground-truth boxes"
        bearing_model = {"sigma_deg": math.degrees(preset.sigma), "exponent_model_b": exponent_b}
    ground_truth = np.asarray(other.poses2d)[sequence.indices]
    result = {"mapped_scene": name, "map_from": map_from, "trajectory": Path(localize.trajectory).stem,
              "frames": len(indices),
              "stride": localize.stride, "observations": observations, "bearing_model": bearing_model,
              "placed_clearance_m": other.metadata["placed_clearance_m"], "objects_truth": len(truth),
              "objects_mapped": len(mapped_map), "runs": {}}
    maps = {"truth": truth, "mapped": mapped_map}
    if localize.noise_draws > 0:
        # Random planar errors with the mapped objects' RMS error (matched within distance), one map per draw.
        figures = object_map_figures(
            [mapped_map.class_names[k] for k in mapped_map.class_index], mapped_map.positions,
            [truth.class_names[k] for k in truth.class_index], truth.positions, distance, planar=False)
        matched = [(p, g) for p, g in enumerate(figures["matches"]) if g >= 0]
        rms = float(np.sqrt(np.mean([np.sum((mapped_map.positions[p, :2] - truth.positions[g, :2]) ** 2)
                                     for p, g in matched]))) if matched else 0.0
        result["noise_reference"] = {"planar_rms_error_m": rms, "draws": localize.noise_draws}
        rng = np.random.default_rng(seed)
        for draw in range(localize.noise_draws):
            moved = truth.positions.copy()
            moved[:, :2] += rng.normal(0.0, rms / np.sqrt(2.0), (len(truth), 2))  # per axis: planar RMS / sqrt 2
            maps[f"noise{draw}"] = room_map(truth, moved)
    for model in ("A", "B"):
        likelihood = likelihood_b if model == "B" else None
        for map_name, semantic_map in maps.items():
            runs = []
            for filter_seed in range(seed, seed + localize.seeds):
                run_spec = RunSpec(model, likelihood, init="global", seed=filter_seed,
                                   exponent=exponent_b if model == "B" else 1.0, view=True)
                trace = run_sequence(_WithMap(other, semantic_map), sequence, heatlines, preset, run_spec,
                                     views=views).arrays()
                metrics = localization_metrics(trace["poses"], ground_truth, preset.converge_threshold, preset.hold)
                runs.append({key: metrics[key] for key in ("time_to_converge_frames", "rmse_after_convergence_m",
                                                           "rmse_m", "heading_rmse_after_convergence_deg")})
            after = [r["rmse_after_convergence_m"] for r in runs]
            converged = [a for a in after if a is not None]
            summary = {"seeds": len(runs), "converged_runs": len(converged),
                       "median_rmse_after_convergence_m": float(np.median(converged)) if converged else None,
                       "median_rmse_m": float(np.median([r["rmse_m"] for r in runs])), "per_seed": runs}
            result["runs"][f"{model}-{map_name}"] = summary
            log(f"  model {model}, {map_name} map: {len(converged)}/{len(runs)} runs converged, median RMSE after "
                f"convergence {summary['median_rmse_after_convergence_m']}, median RMSE {summary['median_rmse_m']:.3f}")
        truth_rmse = result["runs"][f"{model}-truth"]["median_rmse_after_convergence_m"]

        def ratio(map_name: str) -> float | None:
            rmse = result["runs"][f"{model}-{map_name}"]["median_rmse_after_convergence_m"]
            return rmse / truth_rmse if truth_rmse and rmse is not None else None

        result[f"ratio_{model}"] = ratio("mapped")
        if localize.noise_draws > 0:
            result["noise_reference"][f"ratios_{model}"] = [ratio(f"noise{d}") for d in range(localize.noise_draws)]
    return result
