"""What the localization experiment fits on simulated calibration worlds (seed + 1000, never the evaluated world):
the detector's exemplar views (``templates: selected``), its score likelihoods p(z|d), p(z|not d) (§4.8.2), and
each heatline source's bearing model (σ of eq. 4.26 and model B's likelihood exponent). Each is cached in the
spec's ``cache`` folder.

The functions take the experiment's spec (``localization.LocalizationSpec``).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from semloc_core.experiments.heatline_cache import cached_heatlines, fingerprint, views_key
from semloc_core.experiments.localization_detector import (CALIBRATION_CRITERIA, DETECTOR_MIN_PIXELS,
                                                           DETECTOR_SETTINGS, SELECTION_CRITERIA,
                                                           SELECTION_MAX_PER_CLASS, SELECTION_TOLERANCE_DEG,
                                                           candidate_views, scene_detector)
from semloc_core.experiments.tabletop import simulated_scenario

Log = Callable[[str], None]


def calibration_worlds(spec):
    """(name, seed, trajectory files, label) of the worlds a sim:NAME evaluation calibrates on: seed + 1000, the
    same scenario or tabletops along ``calibration.trajectories``."""
    name, seed = spec.dataset[4:], spec.scenario.seed + 1000
    files = [Path(f) for f in spec.calibration.trajectories]
    if files and name != "tabletop":
        raise ValueError("calibration.trajectories is for sim:tabletop")
    return name, seed, files, "+".join(f.stem for f in files) if files else "default"


def calibration_scenarios(spec) -> list:
    name, seed, files, _ = calibration_worlds(spec)
    exemplars = spec.scenario.exemplars
    return ([simulated_scenario(name, seed, None, str(f), exemplars) for f in files] if files
            else [simulated_scenario(name, seed, spec.calibration.frames, None, exemplars, spec.scenario.camera)])


def calibration_stem(spec) -> Path | None:
    """Where the calibration's cached files go (None without a cache folder)."""
    name, seed, _, label = calibration_worlds(spec)
    config = "c{cell}t{template_cells}{color_space}_allclasses".format(**DETECTOR_SETTINGS)
    if spec.templates != "front":
        config += f"_{spec.templates}"
    if not spec.cache:
        return None
    Path(spec.cache).mkdir(parents=True, exist_ok=True)
    camera = f"_{spec.scenario.camera.replace(':', '-')}" if spec.scenario.camera else ""
    return Path(spec.cache) / f"calibration_{name}{camera}_{label}_s{seed}_{config}"


def template_views(spec, log: Log) -> dict | None:
    """``templates: selected``: per class the exemplar views chosen on the calibration worlds (greedy forward
    selection, ``semloc_core.detection.selection``, on every 3rd frame), cached next to the calibration; None for
    ``front``. A class without a usable object in the calibration worlds keeps its canonical view."""
    from semloc_core.detection.evaluation import UsableCriteria
    from semloc_core.detection.selection import select_exemplars
    from semloc_core.experiments.template_selection import exemplar_heatlines

    if spec.templates == "front":
        return None
    if not spec.dataset.startswith("sim:"):
        raise ValueError("templates: selected chooses views on simulated calibration worlds: use a sim:NAME dataset")
    stem = calibration_stem(spec)
    cached = stem.with_name(f"{stem.name}_views.json") if stem else None
    if cached is not None and cached.exists():
        return json.loads(cached.read_text())["chosen"]
    start = time.perf_counter()
    scenarios = calibration_scenarios(spec)
    candidates = scene_detector(*scenarios, chosen={name: [v[0] for v in views] for dataset in scenarios
                                                    for name, views in candidate_views(dataset).items()})
    lines, observed, objects = [], [], []
    for scenario in scenarios:
        indices = list(range(0, len(scenario), 3))

        def done(n: int, total: int = len(indices)) -> None:
            if n % 20 == 0:
                log(f"  view selection: {n}/{total} frames, {len(candidates.templates)} templates")

        world_lines, world_observed, world_objects, exemplars = exemplar_heatlines(
            scenario, candidates, indices, UsableCriteria(**SELECTION_CRITERIA), done)
        lines.append(world_lines)
        observed.append(world_observed)
        objects += world_objects
    steps = select_exemplars(np.concatenate(lines), np.concatenate(observed), [name for name, _ in exemplars],
                             objects, SELECTION_MAX_PER_CLASS, SELECTION_TOLERANCE_DEG)
    chosen = {name: [exemplars[step.exemplar][1].split("/", 1)[1] for step in steps.get(name, [])] or ["front0"]
              for name in candidates.classes}
    # what the canonical view alone scores on the same frames, for comparison
    front = [k for k, (_, source) in enumerate(exemplars) if source.split("/", 1)[1] == "front0"]
    front_steps = select_exemplars(np.concatenate(lines)[:, front], np.concatenate(observed),
                                   [exemplars[k][0] for k in front], objects, 1, SELECTION_TOLERANCE_DEG)

    def described(class_steps):
        return [{"view": exemplars[s.exemplar][1], "hits": s.hits,
                 "misses": s.misses, "hallucinations": s.hallucinations} for s in class_steps]

    record = {"chosen": chosen, "frames": len(objects), "criteria": SELECTION_CRITERIA,
              "steps": {name: described(class_steps) for name, class_steps in steps.items()},
              "front_only": {name: {"hits": s[0].hits, "misses": s[0].misses, "hallucinations": s[0].hallucinations}
                             for name, s in front_steps.items()}}
    log(f"exemplar views chosen on {len(objects)} calibration frames ({time.perf_counter() - start:.0f} s): "
        + "; ".join(f"{name} {', '.join(keys)}" for name, keys in chosen.items()))
    if cached is not None:
        cached.write_text(json.dumps(record, indent=1))
    return chosen


def fit_likelihoods(frames, bandwidth: str):
    """Score likelihoods (§4.8.2) from ``(heatlines, [GroundTruthObject])`` pairs, samples pooled over them."""
    from semloc_core.detection.calibration import fit_score_likelihoods, heatline_samples

    positives: dict = {}
    negatives: dict = {}
    for heatlines, objects in frames:
        found, absent = heatline_samples(heatlines, [(o.class_name, o.bearing, o.usable) for o in objects])
        for name in found:
            positives.setdefault(name, []).append(found[name])
            negatives.setdefault(name, []).append(absent[name])
    samples_d = {name: np.concatenate(v) for name, v in positives.items()}
    samples_not_d = {name: np.concatenate(v) for name, v in negatives.items()}
    usable = [n for n in samples_d if samples_d[n].size >= 2 and samples_not_d[n].size >= 2]
    if not usable:
        raise ValueError("no class has calibration samples")
    return fit_score_likelihoods({n: samples_d[n] for n in usable}, {n: samples_not_d[n] for n in usable},
                                 detector=dict(DETECTOR_SETTINGS, scales=list(DETECTOR_SETTINGS["scales"])),
                                 bandwidth=bandwidth)


def detector_calibration(spec, log: Log, chosen: dict | None):
    """Score likelihoods of the detector and where they come from: the spec's file, or fitted on other simulated
    worlds (seed + 1000): the same scenario, or tabletops along ``calibration.trajectories``. Cached per
    configuration. ``(None, "self")`` for ``file: self`` (fitted later on the evaluated frames)."""
    from semloc_core.io.calibration import load_score_likelihoods, save_score_likelihoods

    file, bandwidth = spec.calibration.file, spec.calibration.bandwidth
    if file == "self":
        return None, "self"
    if file:
        return load_score_likelihoods(file), str(Path(file).resolve())
    if not spec.dataset.startswith("sim:"):
        return None, None
    name, seed, files, label = calibration_worlds(spec)
    stem = calibration_stem(spec)
    cached = stem.with_name(f"{stem.name}_{bandwidth}.json") if stem else None
    description = (f"sim:{name} seed {seed}" + (f" along {label}" if files else f", {spec.calibration.frames} frames")
                   + f", bandwidth {bandwidth}")
    if cached is not None and cached.exists():
        return load_score_likelihoods(cached), description
    start = time.perf_counter()

    def frames():
        for scenario, _, heatlines, objects in calibration_detector_frames(spec, log, chosen):
            yield heatlines, objects
        log(f"calibration samples from {description}: {time.perf_counter() - start:.0f} s")

    likelihoods = fit_likelihoods(frames(), bandwidth)
    if cached is not None:
        save_score_likelihoods(likelihoods, cached)
    return likelihoods, description


def calibration_detector_frames(spec, log: Log, chosen: dict | None):
    """(scenario, frame index, detector heatlines, ground-truth objects) of every 3rd frame of the calibration
    worlds; the heatlines are cached with the calibration (the bearing model is fitted on them too)."""
    from semloc_core.bearing import BearingGrid
    from semloc_core.detection.evaluation import UsableCriteria, frame_objects, run_detector

    criteria = UsableCriteria(**CALIBRATION_CRITERIA)
    stem = calibration_stem(spec)
    scenarios = calibration_scenarios(spec)
    # Every class's detector runs on every calibration world, as the thesis evaluates every DPM model on every image
    # (§4.8.2): a world without the class gives p(z|d̄) its negatives too. With only the worlds holding the class
    # (one world for the cap, bowl and cereal box here), p(z|d̄) ended where that world's background ended (cap:
    # zero above 0.55) and a world with a brighter background scored log p(z|d)/p(z|d̄) = +14 per bin wherever a
    # pose expected the class (tabletop 05: the true pose 35 nats a frame below a wrong one for 250 frames).
    detector = scene_detector(*scenarios, chosen=chosen)
    for k, scenario in enumerate(scenarios):
        indices = list(range(0, len(scenario), 3))
        path = stem.with_name(f"{stem.name}_world{k}_detector.npz") if stem else None
        key = f"{fingerprint(scenario)} {sorted(DETECTOR_SETTINGS.items())} {list(detector.classes)}{views_key(chosen)}"
        lines = cached_heatlines(path, indices, lambda: {int(i): h for i, h, _ in run_detector(
            scenario, detector, indices, BearingGrid(360), criteria)}, key)
        for i in indices:
            yield scenario, i, lines[i], frame_objects(scenario.visible_objects(i), criteria)


def fitted_bearing_model(spec, source: str, likelihood, thresholds, log: Log, chosen: dict | None) -> dict:
    """σ (eq. 4.26) and the likelihood exponent of one heatline source (``bearing_model``), fitted on the
    calibration worlds' frames of that source (sim:NAME), cached; the spec's values when given."""
    from semloc_core.detection.heatlines import hard_heatlines
    from semloc_core.localization.bearing_model import correlation_bins, fit_sigma
    from semloc_core.localization.experiment import (PRESETS, frame_observations, ground_truth_heatlines,
                                                     preset_for, view_geometry)

    perception = spec.perception
    fixed = {"sigma_deg": None if perception.sigma == "auto" else float(perception.sigma),
             "exponent": None if perception.exponent == "auto" else float(perception.exponent)}
    if all(v is not None for v in fixed.values()) or not spec.dataset.startswith("sim:"):
        return {"sigma_deg": fixed["sigma_deg"], "exponent": fixed["exponent"] or 1.0, "exponent_hard": None,
                "source": "options"}

    def preset_of(scenario):
        return preset_for(scenario) if spec.filter_preset == "auto" else PRESETS[spec.filter_preset]

    stem = calibration_stem(spec)
    view_label = "view" if perception.view else "noview"
    cached = stem.with_name(f"{stem.name}_bearing_{source}_{view_label}.json") if stem else None
    if cached is not None and cached.exists():
        fitted = json.loads(cached.read_text())
    else:
        start = time.perf_counter()
        frames = []  # (scenario, index, heatlines)
        if source == "detector":
            frames = [(sc, i, h) for sc, i, h, _ in calibration_detector_frames(spec, log, chosen)]
        else:
            scenarios = calibration_scenarios(spec)
            if source == "synthetic":
                from semloc_core.localization import synthetic_scores_likelihood

                likelihood = synthetic_scores_likelihood(sorted({c for sc in scenarios
                                                                 for c in sc.semantic_map.class_names}))
            for sc in scenarios:
                indices = list(range(0, len(sc), 3))
                observations = frame_observations(sc, indices, sc.semantic_map.class_names, 360,
                                                  preset_of(sc).min_box_px)
                lines = ground_truth_heatlines(observations, source, likelihood, seed=spec.seed + 1000)
                frames += [(sc, i, lines[i]) for i in indices]
        minimum = DETECTOR_MIN_PIXELS if source == "detector" else None
        triples = []
        for sc, i, h in frames:
            view = view_geometry(sc, i, h.scores.shape[1], minimum if minimum is not None
                                 else preset_of(sc).min_box_px) if perception.view else None
            triples.append((sc.semantic_map, sc.poses2d[i], h, view))
        sigma, totals = fit_sigma(triples, likelihood)
        tau = correlation_bins(h for _, _, h in frames)
        tau_hard = correlation_bins(hard_heatlines(h, thresholds, nms_deg=5.0, width_deg=perception.hard_width_deg)
                                    for _, _, h in frames)
        fitted = {"sigma_deg": math.degrees(sigma), "correlation_bins": tau, "correlation_bins_hard": tau_hard,
                  "log_likelihood_by_sigma_deg": totals, "frames": len(frames)}
        log(f"{source}: bearing model on {len(frames)} calibration frames: sigma {fitted['sigma_deg']:.1f} deg, "
            f"correlation {tau:.1f} bins ({time.perf_counter() - start:.0f} s)")
        if cached is not None:
            cached.write_text(json.dumps(fitted, indent=1))
    return {"sigma_deg": fixed["sigma_deg"] if fixed["sigma_deg"] is not None else fitted["sigma_deg"],
            "exponent": fixed["exponent"] if fixed["exponent"] is not None else 1.0 / max(
                fitted["correlation_bins"], 1.0),
            "exponent_hard": None if fixed["exponent"] is not None else 1.0 / max(
                fitted["correlation_bins_hard"], 1.0),
            "source": "calibration", "fitted": fitted}


def self_calibration(dataset, heatlines: dict, frames, bandwidth: str):
    """Likelihoods fitted on the evaluated frames' own detector heatlines (diagnostic upper bound)."""
    from semloc_core.detection.evaluation import UsableCriteria, frame_objects

    criteria = UsableCriteria(**CALIBRATION_CRITERIA)
    return fit_likelihoods(((heatlines[int(i)], frame_objects(dataset.visible_objects(int(i)), criteria))
                            for i in frames), bandwidth)
