"""`semloc eval localization DATASET --json OUT`: particle-filter localization against the dataset's object map.

For perception model A (eq. 4.6) and B (eq. 4.27), soft and hard (§4.5.2) heatlines, and three heatline sources -
``synthetic`` (synthetic scores from the ground-truth boxes, §4.8.3), ``dpm`` (simulated DPM, eq. 4.29, scores
drawn from the calibrated likelihoods) and ``detector`` (the §4.3 template detector run on the rendered images) -
it reports the position error over time and its running RMSE, the time to converge from global initialisation
(first frame after which the error stays under the preset's threshold for 10 frames), the RMSE after convergence,
the heading error, and with ``--kidnap`` the frames needed to recover. Estimated trajectories are written as TUM
files, error and trajectory plots as PNG and a Markdown table next to the JSON.

DATASET: a dataset folder (``semloc sim``) or ``sim:NAME`` to simulate in memory (``--trajectory`` for a tabletop
along a real RGB-D Scenes trajectory, ``--scenario-seed``, ``--frames``). Details: docs/localization.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SOURCES = ("synthetic", "dpm", "detector")
# Thesis Table 4.1: objects per RGB-D Scenes v2 scene (bowl, cap, cereal box, coffee mug, soda can). A tabletop
# driven by scene NN's real trajectory gets that scene's objects.
SCENE_OBJECTS = {
    1: (2, 1, 0, 1, 1), 2: (1, 0, 1, 1, 2), 3: (2, 1, 0, 1, 1), 4: (2, 0, 1, 1, 1), 5: (1, 1, 1, 1, 0),
    6: (1, 0, 0, 2, 2), 7: (1, 1, 1, 1, 1), 8: (0, 2, 0, 0, 1), 9: (1, 0, 1, 0, 1), 10: (1, 1, 0, 1, 0),
    11: (0, 0, 1, 0, 2), 12: (0, 2, 0, 1, 0), 13: (1, 0, 1, 1, 1), 14: (1, 1, 0, 1, 1),
}
TABLETOP_CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")
# The configuration whose accuracy docs/detection.md reports (benchmarks/detection_accuracy.py "templates-hsv",
# the default of both scenes): 6-px blocks, 7-block templates, 3-level pyramid, hue x saturation colours.
DETECTOR_SETTINGS = {"cell": 6, "template_cells": 7, "scales": (1.0, 0.7, 0.5), "color_space": "hsv"}
# Calibration training data as ``semloc calibrate``: objects down to 20 px and 30 % occluded are positives.
CALIBRATION_CRITERIA = {"min_height_px": 20.0, "max_occluded_fraction": 0.3}
# Model B expects (ViewGeometry) exactly the objects p(z|d) was fitted on: those at least as tall as the calibration's
# positives. (30 px, the accuracy table's "usable" size, left 20-30 px objects that the detector does respond to
# unexpected, which pulled the estimate to poses where they fall out of view: scene 01, 0.24 m against 0.11 m.)
DETECTOR_MIN_PIXELS = CALIBRATION_CRITERIA["min_height_px"]
# --templates: the thesis's one exemplar per class, or views chosen on the calibration worlds as
# `semloc select-templates` chooses them (its criteria: objects >= 30 px, <= 10 % occluded, hit within 5 deg).
TEMPLATE_CHOICES = ("front", "selected")
SELECTION_CRITERIA = {"min_height_px": 30.0, "max_occluded_fraction": 0.1}
SELECTION_MAX_PER_CLASS = 4
SELECTION_TOLERANCE_DEG = 5.0

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (semloc sim) or sim:NAME (tabletop, hall) made in memory")
    parser.add_argument("--json", required=True, help="report file (JSON); TUM files, plots and a table go next to it")
    parser.add_argument("--models", default="A,B", help="perception models to run (A, B)")
    parser.add_argument("--variants", default="soft,hard", help="soft and/or hard (thresholded) heatlines")
    parser.add_argument("--sources", default="synthetic,dpm,detector", help=f"heatline sources {SOURCES}")
    parser.add_argument("--preset", default="auto", choices=("auto", "tabletop", "hall"),
                        help="scale of filter and thresholds (auto: hall for panoramas and maps over 30 m)")
    parser.add_argument("--init", default="global", choices=("global", "gt"), help="global or ground-truth start")
    parser.add_argument("--kidnap", type=int, default=None, help="teleport the ground truth at this position")
    parser.add_argument("--jump", type=int, default=None, help="frames skipped by the kidnapping (default N/3)")
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--frames", type=int, default=None, help="at most this many frames (after the stride)")
    parser.add_argument("--view", action=argparse.BooleanOptionalAction, default=True,
                        help="expect only objects inside the image and not hidden (ViewGeometry; --no-view: the "
                             "thesis's bearing-only field of view)")
    parser.add_argument("--particles", type=int, default=None, help="max particles (default: the preset's)")
    parser.add_argument("--filter", action="append", default=[], metavar="KEY=VALUE",
                        help="override a FilterConfig field of the preset (e.g. history_frames=0); repeatable")
    parser.add_argument("--peak", type=float, default=1.0, help="model B: p(d) at an object's bearing")
    parser.add_argument("--exponent", default="auto",
                        help="model B: likelihood exponent; auto: 1 / the heatline source's bin correlation length "
                             "measured on the calibration frames (assumption 4 of §4.7.2 made true on average)")
    parser.add_argument("--sigma", default="auto",
                        help="bearing spread of eq. 4.7 / 4.26 (degrees); auto: the maximum-likelihood value on the "
                             "calibration frames (sim:NAME; otherwise the preset's)")
    parser.add_argument("--hit-rate", type=float, default=0.5, help="model B on hard heatlines: P(z=1|d) per bin")
    parser.add_argument("--false-alarm-rate", type=float, default=0.02, help="... and P(z=1|no object)")
    parser.add_argument("--hard-width-deg", type=float, default=5.0, help="width of a hard detection (degrees)")
    parser.add_argument("--calibration", help="score likelihoods of the detector (semloc calibrate); 'self': fitted "
                                              "on every 3rd evaluated frame (an upper bound, not a fair figure); "
                                              "default: calibrated on another seed of the simulated scenario")
    parser.add_argument("--calibration-frames", type=int, default=360,
                        help="frames of the calibration scenario (every 3rd is used)")
    parser.add_argument("--calibration-trajectories",
                        help="sim:tabletop: calibrate on tabletops along these .pose files instead (comma-separated; "
                             "the thesis fits its likelihoods on scenes 6, 7, 11 and 12, §4.8.2), samples pooled; "
                             "their worlds use --scenario-seed + 1000, so no evaluated world is a training world")
    parser.add_argument("--bandwidth", default="robust_std", choices=("robust_std", "normal_reference"),
                        help="KDE bandwidth of the fitted likelihoods: the robust standard deviation (thesis §4.8.2) "
                             "or the normal-reference rule (narrow with many samples; see docs/localization.md)")
    parser.add_argument("--seed", type=int, default=0, help="filter and simulated-DPM seed")
    parser.add_argument("--scenario-seed", type=int, default=0, help="sim:NAME: the world's seed")
    parser.add_argument("--trajectory", help="sim:tabletop: an RGB-D Scenes v2 .pose (or TUM) file to follow")
    parser.add_argument("--exemplars", default="auto", help="sim:tabletop: real object crops folder, auto or none")
    parser.add_argument("--templates", default="front", choices=TEMPLATE_CHOICES,
                        help="the detector's exemplar views: front = each class's canonical view and its mirror "
                             "(thesis §4.5.1); selected = up to 4 views per class chosen on the calibration worlds "
                             "among the front and multi-view exemplars (semloc select-templates), rendered of the "
                             "evaluated world's objects")
    parser.add_argument("--camera", default=None,
                        help="sim:hall: the robot's camera (panorama = 1024x256, panorama:WxH, rig, pinhole); the "
                             "calibration world gets the same one")
    parser.add_argument("--cache", help="folder keeping each source's heatlines (and the calibration) between runs")
    parser.add_argument("--quiet", action="store_true")


# ---------------------------------------------------------------------------------------------------- datasets
def _scenario(name: str, seed: int, frames, trajectory, exemplars: str, camera: str | None = None):
    from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops
    from semloc_core.io.trajectory import read_trajectory
    from semloc_core.sim import make_scenario

    options = {}
    if name == "tabletop" and exemplars != "none":
        folder = default_exemplar_dir() if exemplars == "auto" else Path(exemplars)
        if folder is not None:
            options["crops"], options["clutter_crops"] = load_exemplar_crops(folder)
    if camera:
        if name == "tabletop":
            raise ValueError("--camera is for sim:hall (the tabletop's camera is the Kinect of its trajectory)")
        options["camera"] = camera
    path = None
    if trajectory:
        if name != "tabletop":
            raise ValueError("--trajectory is for sim:tabletop")
        path = read_trajectory(Path(trajectory))[1]
        scene = Path(trajectory).stem
        if scene.isdigit() and int(scene) in SCENE_OBJECTS:
            options["instances"] = dict(zip(TABLETOP_CLASSES, SCENE_OBJECTS[int(scene)]))
    return make_scenario(name, seed=seed, frames=frames, trajectory=path, **options)


def _open(args):
    from semloc_core.io.dataset import open_dataset

    if args.dataset.startswith("sim:"):
        return _scenario(args.dataset[4:], args.scenario_seed, None, args.trajectory, args.exemplars, args.camera)
    if args.camera:
        raise ValueError("--camera is for sim:NAME datasets")
    return open_dataset(args.dataset)


def candidate_views(dataset) -> dict[str, list[tuple[str, np.ndarray, np.ndarray | None]]]:
    """Each class's exemplar views in ``dataset``: ``(key, image, mask)``, its canonical exemplars (``front<k>``)
    then its multi-view exemplars (``az<deg>_el<deg>``, if the dataset has them). A key names a viewpoint, so a view
    chosen on one world is found again among another world's renders of its own objects."""
    from semloc_core.io.dataset import DatasetError

    masks = dataset.exemplar_masks() if hasattr(dataset, "exemplar_masks") else {}
    out: dict[str, list] = {}
    for name, images in dataset.exemplars().items():
        class_masks = masks.get(name) or [None] * len(images)
        out[name] = [(f"front{k}", image, mask) for k, (image, mask) in enumerate(zip(images, class_masks))]
    try:
        multiview = dataset.multiview_exemplars() if hasattr(dataset, "multiview_exemplars") else {}
    except DatasetError:
        multiview = {}
    for name, views in multiview.items():
        out.setdefault(name, []).extend(
            (f"az{math.degrees(v.azimuth):.0f}_el{math.degrees(v.elevation):.0f}", v.image, v.mask) for v in views)
    return out


def _template_detector(views: dict, settings: dict = DETECTOR_SETTINGS):
    """The template detector of ``{class: [(key, image, mask)]}``; each view with its mirror, ``source``
    ``class/key``."""
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.templates import MatchParams, TemplateDetector, build_templates, mask_uniform_background

    params = FeatureParams(cell=settings["cell"], color_space=settings["color_space"])
    templates = []
    for name, class_views in sorted(views.items()):
        for key, image, mask in class_views:
            mask = mask_uniform_background(image) if mask is None else np.asarray(mask) > 0
            templates += build_templates(image, name, params, settings["template_cells"], mask=mask, mirror=True,
                                         source=f"{name}/{key}")
    return TemplateDetector(templates, params, MatchParams(tuple(settings["scales"])))


def _scene_detector(*datasets, chosen: dict | None = None):
    """The template detector of every class of ``datasets`` (views of a class shared by several: the first's):
    each class's canonical exemplars, or with ``chosen`` (``{class: [view key]}``, ``_template_views``) those
    views."""
    views: dict = {}
    for dataset in datasets:
        for name, class_views in candidate_views(dataset).items():
            if name in views:
                continue
            keys = (chosen or {}).get(name)
            if keys is None:
                views[name] = [v for v in class_views if v[0].startswith("front")]
                continue
            by_key = {v[0]: v for v in class_views}
            if missing := [k for k in keys if k not in by_key]:
                raise ValueError(f"{getattr(dataset, 'name', 'the dataset')} has no exemplar view {missing} of "
                                 f"{name!r} (chosen on the calibration worlds); it needs multi-view exemplars")
            views[name] = [by_key[k] for k in keys]
    return _template_detector(views)


def _template_views(args, log) -> dict | None:
    """``--templates selected``: per class the exemplar views chosen on the calibration worlds (greedy forward
    selection, ``semloc_core.detection.selection``, on every 3rd frame), cached next to the calibration; None for
    ``front``. A class without a usable object in the calibration worlds keeps its canonical view."""
    from semloc_core.detection.evaluation import UsableCriteria
    from semloc_core.detection.selection import select_exemplars
    from services.commands.select_templates import exemplar_heatlines

    if args.templates == "front":
        return None
    if not args.dataset.startswith("sim:"):
        raise ValueError("--templates selected chooses views on simulated calibration worlds: use a sim:NAME dataset")
    stem = _calibration_stem(args)
    cached = stem.with_name(f"{stem.name}_views.json") if stem else None
    if cached is not None and cached.exists():
        return json.loads(cached.read_text())["chosen"]
    start = time.perf_counter()
    scenarios = _calibration_scenarios(args)
    candidates = _scene_detector(*scenarios, chosen={name: [v[0] for v in views] for dataset in scenarios
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


def _fit_likelihoods(frames, bandwidth: str):
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


def _calibration_worlds(args):
    """(name, seed, trajectory files, label) of the worlds a sim:NAME evaluation calibrates on: seed + 1000, the
    same scenario or tabletops along ``--calibration-trajectories``."""
    name, seed = args.dataset[4:], args.scenario_seed + 1000
    files = [Path(f) for f in (args.calibration_trajectories or "").split(",") if f.strip()]
    if files and name != "tabletop":
        raise ValueError("--calibration-trajectories is for sim:tabletop")
    return name, seed, files, "+".join(f.stem for f in files) if files else "default"


def _calibration_scenarios(args) -> list:
    name, seed, files, _ = _calibration_worlds(args)
    return ([_scenario(name, seed, None, str(f), args.exemplars) for f in files] if files
            else [_scenario(name, seed, args.calibration_frames, None, args.exemplars, args.camera)])


def _calibration_stem(args) -> Path | None:
    name, seed, _, label = _calibration_worlds(args)
    config = "c{cell}t{template_cells}{color_space}_allclasses".format(**DETECTOR_SETTINGS)
    if args.templates != "front":
        config += f"_{args.templates}"
    if not args.cache:
        return None
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    camera = f"_{args.camera.replace(':', '-')}" if args.camera else ""
    return Path(args.cache) / f"calibration_{name}{camera}_{label}_s{seed}_{config}"


def detector_calibration(args, log, chosen: dict | None):
    """Score likelihoods of the detector: the given file, or fitted on other simulated worlds (seed + 1000): the
    same scenario, or tabletops along ``--calibration-trajectories``. Cached per configuration."""
    from semloc_core.io.calibration import load_score_likelihoods, save_score_likelihoods

    if args.calibration == "self":
        return None, "self"
    if args.calibration:
        return load_score_likelihoods(args.calibration), str(Path(args.calibration).resolve())
    if not args.dataset.startswith("sim:"):
        return None, None
    name, seed, files, label = _calibration_worlds(args)
    stem = _calibration_stem(args)
    cached = stem.with_name(f"{stem.name}_{args.bandwidth}.json") if stem else None
    description = (f"sim:{name} seed {seed}" + (f" along {label}" if files else f", {args.calibration_frames} frames")
                   + f", bandwidth {args.bandwidth}")
    if cached is not None and cached.exists():
        return load_score_likelihoods(cached), description
    start = time.perf_counter()

    def frames():
        for scenario, _, heatlines, objects in _calibration_detector_frames(args, log, chosen):
            yield heatlines, objects
        log(f"calibration samples from {description}: {time.perf_counter() - start:.0f} s")

    likelihoods = _fit_likelihoods(frames(), args.bandwidth)
    if cached is not None:
        save_score_likelihoods(likelihoods, cached)
    return likelihoods, description


def _calibration_detector_frames(args, log, chosen: dict | None):
    """(scenario, frame index, detector heatlines, ground-truth objects) of every 3rd frame of the calibration
    worlds; the heatlines are cached with the calibration (the bearing model is fitted on them too)."""
    from semloc_core.bearing import BearingGrid
    from semloc_core.detection.evaluation import UsableCriteria, frame_objects, run_detector

    criteria = UsableCriteria(**CALIBRATION_CRITERIA)
    stem = _calibration_stem(args)
    scenarios = _calibration_scenarios(args)
    # Every class's detector runs on every calibration world, as the thesis evaluates every DPM model on every image
    # (§4.8.2): a world without the class gives p(z|d̄) its negatives too. With only the worlds holding the class
    # (one world for the cap, bowl and cereal box here), p(z|d̄) ended where that world's background ended (cap:
    # zero above 0.55) and a world with a brighter background scored log p(z|d)/p(z|d̄) = +14 per bin wherever a
    # pose expected the class (tabletop 05: the true pose 35 nats a frame below a wrong one for 250 frames).
    detector = _scene_detector(*scenarios, chosen=chosen)
    for k, scenario in enumerate(scenarios):
        indices = list(range(0, len(scenario), 3))
        path = stem.with_name(f"{stem.name}_world{k}_detector.npz") if stem else None
        key = f"{fingerprint(scenario)} {sorted(DETECTOR_SETTINGS.items())} {list(detector.classes)}{_views_key(chosen)}"
        lines = cached_heatlines(path, indices, lambda: {int(i): h for i, h, _ in run_detector(
            scenario, detector, indices, BearingGrid(360), criteria)}, key)
        for i in indices:
            yield scenario, i, lines[i], frame_objects(scenario.visible_objects(i), criteria)


def fitted_bearing_model(args, source: str, likelihood, thresholds, log, chosen: dict | None) -> dict:
    """σ (eq. 4.26) and the likelihood exponent of one heatline source (``bearing_model``), fitted on the
    calibration worlds' frames of that source (sim:NAME), cached; the options' values when given."""
    from semloc_core.detection.heatlines import hard_heatlines
    from semloc_core.localization.bearing_model import correlation_bins, fit_sigma
    from semloc_core.localization.experiment import (PRESETS, frame_observations, ground_truth_heatlines,
                                                     preset_for, view_geometry)

    fixed = {"sigma_deg": None if args.sigma == "auto" else float(args.sigma),
             "exponent": None if args.exponent == "auto" else float(args.exponent)}
    if all(v is not None for v in fixed.values()) or not args.dataset.startswith("sim:"):
        return {"sigma_deg": fixed["sigma_deg"], "exponent": fixed["exponent"] or 1.0, "exponent_hard": None,
                "source": "options"}
    stem = _calibration_stem(args)
    cached = stem.with_name(f"{stem.name}_bearing_{source}_{'view' if args.view else 'noview'}.json") if stem else None
    if cached is not None and cached.exists():
        fitted = json.loads(cached.read_text())
    else:
        start = time.perf_counter()
        frames = []  # (scenario, index, heatlines)
        if source == "detector":
            frames = [(sc, i, h) for sc, i, h, _ in _calibration_detector_frames(args, log, chosen)]
        else:
            scenarios = _calibration_scenarios(args)
            if source == "synthetic":
                from semloc_core.localization import synthetic_scores_likelihood

                likelihood = synthetic_scores_likelihood(sorted({c for sc in scenarios
                                                                 for c in sc.semantic_map.class_names}))
            for sc in scenarios:
                preset = preset_for(sc) if args.preset == "auto" else PRESETS[args.preset]
                indices = list(range(0, len(sc), 3))
                observations = frame_observations(sc, indices, sc.semantic_map.class_names, 360, preset.min_box_px)
                lines = ground_truth_heatlines(observations, source, likelihood, seed=args.seed + 1000)
                frames += [(sc, i, lines[i]) for i in indices]
        minimum = DETECTOR_MIN_PIXELS if source == "detector" else None
        triples = []
        for sc, i, h in frames:
            preset = preset_for(sc) if args.preset == "auto" else PRESETS[args.preset]
            view = view_geometry(sc, i, h.scores.shape[1], minimum if minimum is not None else preset.min_box_px) \
                if args.view else None
            triples.append((sc.semantic_map, sc.poses2d[i], h, view))
        sigma, totals = fit_sigma(triples, likelihood)
        tau = correlation_bins(h for _, _, h in frames)
        tau_hard = correlation_bins(hard_heatlines(h, thresholds, nms_deg=5.0, width_deg=args.hard_width_deg)
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


def _self_calibration(dataset, heatlines: dict, frames, bandwidth: str):
    """Likelihoods fitted on the evaluated frames' own detector heatlines (diagnostic upper bound)."""
    from semloc_core.detection.evaluation import UsableCriteria, frame_objects

    criteria = UsableCriteria(**CALIBRATION_CRITERIA)
    return _fit_likelihoods(((heatlines[int(i)], frame_objects(dataset.visible_objects(int(i)), criteria))
                             for i in frames), bandwidth)


def detector_heatlines(dataset, indices, log, chosen: dict | None) -> dict:
    from semloc_core.detection.evaluation import run_detector

    detector = _scene_detector(dataset, chosen=chosen)
    out = {}
    start = time.perf_counter()
    for done, (i, heatlines, _) in enumerate(run_detector(dataset, detector, [int(i) for i in indices]), start=1):
        out[int(i)] = heatlines
        if done % 50 == 0:
            log(f"  detector: {done}/{len(indices)} frames ({done / (time.perf_counter() - start):.1f} frames/s)")
    return out


def heatline_cache_name(dataset: str, scenario_seed: int, trajectory: str | None, camera: str | None,
                        what: str) -> str:
    """The file name of one dataset's heatlines of one source in a ``--cache`` folder."""
    parts = [dataset.replace("/", "_").replace(":", "-"), f"s{scenario_seed}",
             *([camera.replace(":", "-")] if camera else []), Path(trajectory).stem if trajectory else "orbit", what]
    return "_".join(parts) + ".npz"


def _views_key(chosen: dict | None) -> str:
    """What the chosen exemplar views add to a detector cache's key (nothing for the front views)."""
    return f" {sorted(chosen.items())}" if chosen else ""


def filter_overrides(config, assignments: list[str]):
    """``config`` (a FilterConfig) with ``KEY=VALUE`` assignments applied; values are JSON numbers or booleans."""
    values = config.to_dict()
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        if not sep or not key:
            raise SystemExit(f"--filter wants KEY=VALUE, got {assignment!r}")
        if key not in values:
            raise SystemExit(f"--filter: unknown filter parameter {key!r}; known: {sorted(values)}")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            raise SystemExit(f"--filter {key}: {text!r} is not a number or true/false") from None
        if not isinstance(value, (int, float)):
            raise SystemExit(f"--filter {key}: {text!r} is not a number or true/false")
        values[key] = type(values[key])(value)
    try:
        return type(config).from_dict(values)
    except ValueError as error:
        raise SystemExit(f"--filter: {error}") from None


def heatline_key(args, dataset, preset) -> str:
    """The key a dataset's cached heatlines are stored under (empty without ``--cache``)."""
    return f"{fingerprint(dataset)} min_box_px={preset.min_box_px}" if args.cache else ""


def cached_detector_heatlines(args, dataset, indices, key: str, chosen: dict | None, log) -> dict:
    """The detector's heatlines of ``indices``: from the ``--cache`` (one file per ``--templates`` choice) when it
    holds them for this ``key`` and these views, else computed and stored."""
    return cached_heatlines(_cache_path(args, detector_cache_what(args.templates)), indices,
                             lambda: detector_heatlines(dataset, indices, log, chosen),
                             f"{key} {sorted(DETECTOR_SETTINGS.items())}{_views_key(chosen)}")


def detector_cache_what(templates: str) -> str:
    """The detector source's part of a heatline cache name, per ``--templates`` choice."""
    return "detector" if templates == "front" else f"detector_{templates}"


def _cache_path(args, what: str) -> Path | None:
    """One file per dataset and source; a run whose frames are a subset of a cached run's reuses it."""
    if not args.cache:
        return None
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    return folder / heatline_cache_name(args.dataset, args.scenario_seed, args.trajectory, args.camera, what)


def fingerprint(dataset) -> str:
    """A digest of what a cached heatline depends on: the map, the poses and the first frame's visible boxes (a
    simulator that changed its scenes must not be served stale heatlines)."""
    import hashlib

    digest = hashlib.sha256()
    semantic_map = dataset.semantic_map
    for array in (semantic_map.positions, semantic_map.sizes, semantic_map.class_index, np.asarray(dataset.poses2d)):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    digest.update(repr(semantic_map.class_names).encode())
    for obj in dataset.visible_objects(0):
        digest.update(repr((obj.object_index, tuple(float(v) for v in obj.visible_box))).encode())
    return digest.hexdigest()[:16]


def cached_heatlines(path: Path | None, indices, compute, key: str = "") -> dict:
    """Heatlines per frame index, from ``path`` when it holds these frames of this ``key``, else computed (and
    stored)."""
    from semloc_core.bearing import Heatlines

    if path is not None and path.exists():
        with np.load(path, allow_pickle=False) as data:
            stored = {int(i): k for k, i in enumerate(data["indices"])}
            if str(data["key"]) == key and all(int(i) in stored for i in indices):
                classes = tuple(str(c) for c in data["classes"])
                return {int(i): Heatlines(classes, data["scores"][stored[int(i)]], data["observed"][stored[int(i)]])
                        for i in indices}
    heatlines = compute()
    if path is not None:
        first = heatlines[int(indices[0])]
        np.savez_compressed(path, indices=np.asarray(indices), key=np.asarray(key), classes=np.asarray(first.classes),
                            scores=np.stack([heatlines[int(i)].scores for i in indices]),
                            observed=np.stack([heatlines[int(i)].observed for i in indices]))
    return heatlines


# ---------------------------------------------------------------------------------------------------- report
def _plots(report: dict, sequence, ground_truth, semantic_map, stem: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    figure, axis = plt.subplots(figsize=(9, 4.5))
    for name, run in report["runs"].items():
        errors = np.array([np.nan if e is None else e for e in run["metrics"]["errors_m"]])
        axis.plot(errors, label=name, lw=1)
    axis.axhline(report["preset"]["converge_threshold_m"], color="k", ls=":", lw=1)
    axis.set_yscale("log")
    axis.set_xlabel("frame")
    axis.set_ylabel("position error (m)")
    axis.legend(fontsize=7, ncol=2)
    axis.set_title(f"{report['dataset']}: localization error")
    figure.tight_layout()
    path = stem.with_name(stem.name + "_errors.png")
    figure.savefig(path, dpi=110)
    plt.close(figure)
    written.append(path.name)

    figure, axis = plt.subplots(figsize=(7, 7))
    positions = semantic_map.positions
    axis.scatter(positions[:, 0], positions[:, 1], c=semantic_map.class_index, cmap="tab10", marker="s", s=30,
                 label="objects")
    axis.plot(ground_truth[:, 0], ground_truth[:, 1], "k-", lw=1.5, label="ground truth")
    for name, run in report["runs"].items():
        if run["variant"] == "soft":
            estimate = np.asarray(run["estimates"])
            axis.plot(estimate[:, 0], estimate[:, 1], lw=0.8, label=name)
    span = np.ptp(ground_truth[:, :2], axis=0).max() * 0.6 + 0.5
    centre = ground_truth[:, :2].mean(axis=0)
    axis.set_xlim(centre[0] - span, centre[0] + span)
    axis.set_ylim(centre[1] - span, centre[1] + span)
    axis.set_aspect("equal")
    axis.legend(fontsize=7)
    axis.set_title(f"{report['dataset']}: trajectories (soft)")
    figure.tight_layout()
    path = stem.with_name(stem.name + "_trajectories.png")
    figure.savefig(path, dpi=110)
    plt.close(figure)
    written.append(path.name)
    return written


def _markdown(report: dict) -> str:
    lines = [f"# Localization: {report['dataset']}", "",
             f"preset {report['preset']['name']}, init {report['init']}, {report['frames']} frames, "
             f"view geometry {'on' if report['view'] else 'off'}", "",
             "| run | time to converge (frames) | RMSE after convergence (m) | heading RMSE (deg) | RMSE all (m) "
             "| recovery (frames) | ms/step |", "|---|---|---|---|---|---|---|"]
    fmt = lambda v, f="{:.3f}": "-" if v is None else f.format(v)  # noqa: E731
    for name, run in report["runs"].items():
        m = run["metrics"]
        recovery = ", ".join(fmt(r["frames_to_recover"], "{}") for r in m["recoveries"]) or "-"
        lines.append(f"| {name} | {fmt(m['time_to_converge_frames'], '{}')} | {fmt(m['rmse_after_convergence_m'])} "
                     f"| {fmt(m['heading_rmse_after_convergence_deg'], '{:.1f}')} | {fmt(m['rmse_m'])} | {recovery} "
                     f"| {run['ms_per_step']:.1f} |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    from semloc_core.detection.calibration import decision_threshold
    from semloc_core.detection.heatlines import hard_heatlines
    from semloc_core.geometry import pose2d_to_transform
    from semloc_core.io.dataset import DatasetError
    from semloc_core.io.trajectory import write_tum
    from semloc_core.localization import ScoreLikelihood, synthetic_scores_likelihood
    from semloc_core.localization.evaluation import localization_metrics
    from semloc_core.localization.experiment import (PRESETS, RunSpec, frame_observations, ground_truth_heatlines,
                                                     make_sequence, preset_for, run_sequence, view_geometry)

    log = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    sources = [s.strip() for s in args.sources.split(",") if s.strip()]
    bad = [m for m in models if m not in ("A", "B")] + [v for v in variants if v not in ("soft", "hard")] + [
        s for s in sources if s not in SOURCES]
    if bad:
        print(f"semloc eval localization: unknown model/variant/source {bad}", file=sys.stderr)
        return 2
    try:
        dataset = _open(args)
    except (DatasetError, OSError, ValueError, TypeError) as error:
        print(f"semloc eval localization: {error}", file=sys.stderr)
        return 2
    if dataset.semantic_map is None or dataset.poses2d is None or dataset.odometry is None:
        print("semloc eval localization: the dataset needs an object map, poses and odometry", file=sys.stderr)
        return 2
    preset = preset_for(dataset) if args.preset == "auto" else PRESETS[args.preset]
    if args.particles:
        preset = preset.with_filter(max_particles=args.particles, min_particles=min(preset.filter.min_particles,
                                                                                     args.particles))
    if args.filter:
        preset = replace(preset, filter=filter_overrides(preset.filter, args.filter))
    try:
        sequence = make_sequence(dataset, args.stride, args.frames, args.kidnap, args.jump)
    except ValueError as error:
        print(f"semloc eval localization: {error}", file=sys.stderr)
        return 2
    classes = dataset.semantic_map.class_names
    indices = [int(i) for i in sequence.indices]
    log(f"{args.dataset}: {len(dataset)} frames, {len(indices)} used, preset {preset.name}, classes {list(classes)}")

    calibration, calibration_source, chosen = None, None, None
    if "dpm" in sources or "detector" in sources:
        try:
            chosen = _template_views(args, log) if "detector" in sources else None
            calibration, calibration_source = detector_calibration(args, log, chosen)
        except (OSError, ValueError) as error:
            print(f"semloc eval localization: calibration failed: {error}", file=sys.stderr)
            return 2
    if "detector" in sources and calibration is None and calibration_source != "self":
        print("semloc eval localization: the detector source needs --calibration (score likelihoods)",
              file=sys.stderr)
        return 2
    if calibration_source == "self" and "detector" not in sources:
        print("semloc eval localization: --calibration self needs the detector source", file=sys.stderr)
        return 2
    if calibration is not None and (missing := sorted(set(classes) - set(calibration.classes))):
        print(f"semloc eval localization: the calibration has no score likelihood of {missing} (calibrated: "
              f"{list(calibration.classes)}); give more --calibration-frames or a --calibration file",
              file=sys.stderr)
        return 2
    calibrated = ScoreLikelihood.from_calibration(calibration) if calibration is not None else None

    # what each source can see: ground-truth boxes down to the preset's size, the detector down to its usable size
    minimum_pixels = {"synthetic": preset.min_box_px, "dpm": preset.min_box_px, "detector": DETECTOR_MIN_PIXELS}
    views = {source: {i: view_geometry(dataset, i, 360, minimum_pixels[source]) for i in indices}
             for source in sources} if args.view else None
    key = heatline_key(args, dataset, preset)
    observations = {}

    def observed():
        if not observations:
            start = time.perf_counter()
            observations.update(frame_observations(dataset, indices, classes, 360, preset.min_box_px))
            log(f"ground truth views of {len(indices)} frames: {time.perf_counter() - start:.0f} s")
        return observations

    heatlines = {}
    likelihoods = {}
    thresholds = {}
    if "synthetic" in sources:
        heatlines["synthetic"] = cached_heatlines(_cache_path(args, "synthetic"), indices, lambda: ground_truth_heatlines(
            observed(), "synthetic"), key)
        likelihoods["synthetic"] = synthetic_scores_likelihood(classes)
        thresholds["synthetic"] = 0.5  # where N(0.75, 0.25) and N(0.25, 0.25) cross
    if "dpm" in sources:
        likelihoods["dpm"] = calibrated if calibrated is not None else synthetic_scores_likelihood(classes)
        heatlines["dpm"] = cached_heatlines(_cache_path(args, f"dpm{args.seed}"), indices, lambda: ground_truth_heatlines(
            observed(), "dpm", likelihoods["dpm"], seed=args.seed), key + str(calibration_source))
        thresholds["dpm"] = ({c: decision_threshold(calibration, c) for c in calibration.classes}
                             if calibration is not None else 0.5)
    if "detector" in sources:
        start = time.perf_counter()
        heatlines["detector"] = cached_detector_heatlines(args, dataset, indices, key, chosen, log)
        log(f"detector heatlines: {time.perf_counter() - start:.0f} s")
        if calibration_source == "self":
            calibration = _self_calibration(dataset, heatlines["detector"], indices[::3], args.bandwidth)
            calibrated = ScoreLikelihood.from_calibration(calibration)
        likelihoods["detector"] = calibrated
        thresholds["detector"] = {c: decision_threshold(calibration, c) for c in calibration.classes}

    bearing_models = {}
    for source in sources:
        try:
            bearing_models[source] = fitted_bearing_model(args, source, likelihoods[source], thresholds[source],
                                                          log, chosen)
        except (OSError, ValueError) as error:
            print(f"semloc eval localization: calibrating the bearing model failed: {error}", file=sys.stderr)
            return 2

    ground_truth = np.asarray(dataset.poses2d)[sequence.indices]
    stamps = np.asarray(dataset.stamps_ns)[sequence.indices] * 1e-9
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("")
    report = {
        "dataset": args.dataset, "frames": len(indices), "stride": args.stride, "init": args.init,
        "view": bool(args.view), "seed": args.seed, "kidnap": args.kidnap, "teleports": list(sequence.teleports),
        "trajectory": args.trajectory, "camera": args.camera,
        "scenario_seed": args.scenario_seed if args.dataset.startswith("sim:") else None,
        "calibration": calibration_source, "templates": args.templates, "template_views": chosen,
        "preset": {"name": preset.name, "converge_threshold_m": preset.converge_threshold,
                   "recover_threshold_m": preset.recover_threshold, "hold_frames": preset.hold,
                   "filter": preset.filter.to_dict(), "motion": preset.motion, "alphas": list(preset.alphas),
                   "sigma_deg": math.degrees(preset.sigma), "visibility_radius_m": preset.visibility_radius
                   if math.isfinite(preset.visibility_radius) else None},
        "runs": {},
    }
    report["bearing_models"] = bearing_models
    for source in sources:
        bearing = bearing_models[source]
        source_preset = preset if bearing["sigma_deg"] is None else replace(preset,
                                                                            sigma=math.radians(bearing["sigma_deg"]))
        for variant in variants:
            lines = heatlines[source]
            if variant == "hard":
                lines = {i: hard_heatlines(h, thresholds[source], nms_deg=5.0, width_deg=args.hard_width_deg)
                         for i, h in lines.items()}
            for model in models:
                name = f"{model}-{variant}-{source}"
                likelihood = None
                if model == "B":
                    likelihood = (ScoreLikelihood.binary(classes, args.hit_rate, args.false_alarm_rate)
                                  if variant == "hard" else likelihoods[source])
                exponent = (bearing["exponent_hard"] or bearing["exponent"]) if variant == "hard" \
                    else bearing["exponent"]
                spec = RunSpec(model, likelihood, init=args.init, seed=args.seed,
                               exponent=exponent if model == "B" else 1.0, peak=args.peak, view=args.view)
                start = time.perf_counter()
                trace = run_sequence(dataset, sequence, lines, source_preset, spec,
                                     views=views[source] if views else None).arrays()
                seconds = time.perf_counter() - start
                metrics = localization_metrics(trace["poses"], ground_truth, preset.converge_threshold, preset.hold,
                                               sequence.teleports, preset.recover_threshold)
                tum = stem.with_name(f"{stem.name}_{name}.tum")
                write_tum(tum, stamps, np.stack([pose2d_to_transform(*p) for p in trace["poses"]]))
                report["runs"][name] = {
                    "model": model, "variant": variant, "source": source, "metrics": metrics,
                    "sigma_deg": math.degrees(source_preset.sigma), "exponent": spec.exponent,
                    "ms_per_step": 1e3 * float(np.median(trace["seconds"])), "seconds": seconds,
                    "statuses": trace["statuses"], "particles": trace["particles"].tolist(),
                    "estimates": trace["poses"].tolist(), "tum": tum.name}
                log(f"{name:>22}: converged at {metrics['time_to_converge_frames']}, RMSE after "
                    f"{metrics['rmse_after_convergence_m']}, recoveries {metrics['recoveries']} ({seconds:.1f} s)")
    report["ground_truth"] = ground_truth.tolist()
    report["plots"] = _plots(report, sequence, ground_truth, dataset.semantic_map, stem)
    table = stem.with_name(stem.name + ".md")
    table.write_text(_markdown(report))
    out.write_text(json.dumps(report, allow_nan=False))
    print(_markdown(report))
    return 0
