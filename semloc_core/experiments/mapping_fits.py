"""What the mapping experiment fits on calibration scenes (never on the scenes it evaluates): the extraction (class
scales, threshold, top-hat, cross-class suppression, resting heights), merged over scenes; the heat's
log-likelihood ratios; each class's depth per pyramid scale; and the existence curve of extracted objects."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from semloc_core.experiments.mapping_scene import extraction_for, score_scene
from semloc_core.experiments.tabletop import TABLETOP_SIZES

SWEEP = np.round(np.arange(0.3, 1.21, 0.05), 2)
Log = Callable[[str], None]


def fit_extraction(mapper, truth, *, normalise: bool, min_views: int, distance: float, min_size: float,
                   position: str, mode_bandwidth: float = 0.02, support: tuple | None = None,
                   class_sizes: dict = TABLETOP_SIZES, prominence: float = 0.0) -> dict:
    """Class scales, threshold, top-hat, cross-class suppression and resting heights that maximise F1 (then
    fewest false positives) on this scene - run it on a calibration scene, never on the scenes evaluated. Used by
    the mapping experiment's calibration and by the demo's world; ``support`` = (height, outline)."""
    from semloc_core.mapping import ExtractionConfig
    from semloc_core.mapping.extraction import calibrate_class_scales, extract_with, white_tophat

    support_z, support_polygon = support or (None, None)
    raw = {name: mapper.score_volume(name, normalise=normalise, min_views=min_views)
           for name in mapper.class_names}

    def config_for(threshold: float, setting: tuple, scales: dict):
        tophat, cross_class, resting = setting
        return ExtractionConfig(threshold=float(threshold), normalise=normalise, min_views=min_views,
                                class_sizes=class_sizes, class_scales=scales, cross_class=cross_class, tophat=tophat,
                                support_z=support_z, support_polygon=support_polygon, position=position,
                                mode_bandwidth=mode_bandwidth, resting=resting, prominence=prominence)

    def evaluate(scaled: dict, config) -> tuple[tuple, dict]:
        # The same objects as mapper.extract(config), from the volumes computed once per top-hat.
        scored = score_scene(mapper, truth, config, distance, min_size, extract_with(scaled, mapper.grid, config))
        f1 = 2 * scored["tp"] / max(2 * scored["tp"] + scored["fp"] + scored["fn"], 1)
        return (round(f1, 9), -scored["fp"]), scored

    results, scaled_volumes = [], {}
    for tophat in (0.0, 2.0):
        scores = raw if not tophat else {name: white_tophat(volume, class_sizes[name], mapper.grid.voxel_size,
                                                            tophat) for name, volume in raw.items()}
        scales = calibrate_class_scales(scores, mapper.grid, truth, radius=distance)
        scaled_volumes[tophat] = {name: volume / np.float32(scales.get(name, 1.0)) for name, volume in scores.items()}
        for cross_class, resting in itertools.product((False, True), (False, True) if support_z is not None
                                                      else (False,)):
            for threshold in SWEEP:
                key, scored = evaluate(scaled_volumes[tophat], config_for(threshold, (tophat, cross_class, resting),
                                                                          scales))
                results.append((key, (tophat, cross_class, resting), float(threshold), scored, scales))
    best = max(r[0] for r in results)
    # Several thresholds often tie: of the settings reaching the best, the one with the widest plateau, then the
    # smallest mean position error at the plateau's middle (resting heights or not, when both find the same).
    plateaus = {k: [r for r in results if r[0] == best and r[1] == k] for k in {r[1] for r in results if r[0] == best}}

    def mean_error(plateau: list) -> float:
        error = plateau[len(plateau) // 2][3]["mean_error_3d_m"]
        return math.inf if error is None else error

    setting = max(sorted(plateaus), key=lambda k: (len(plateaus[k]), -mean_error(plateaus[k])))
    plateau = plateaus[setting]
    chosen = plateau[len(plateau) // 2]
    threshold, scored, scales = chosen[2], chosen[3], chosen[4]
    # The threshold: not the plateau's middle step, which is only as fine as the sweep and of two tied steps the
    # upper (0.65 and 0.7 tied: 0.7, with a demo calibration scene's weakest real object at 0.717 and strongest
    # false one at 0.624), but the middle of the gap where the best F1 holds, from the strongest candidate it
    # rejects to the weakest object it keeps: the same margin on both sides for the scenes the fit is used on.
    scaled = scaled_volumes[setting[0]]
    candidates = [o.score for o in extract_with(scaled, mapper.grid, config_for(SWEEP[0], setting, scales))]
    gap = plateau_gap(candidates, plateau[0][2], plateau[-1][2])
    middle = round(sum(gap) / 2, 4)
    key, middle_scored = evaluate(scaled, config_for(middle, setting, scales))
    if key == best:  # always, unless extraction is not nested in the threshold
        threshold, scored = middle, middle_scored
    return {"threshold": threshold, "tophat": setting[0], "cross_class": setting[1], "resting": setting[2],
            "class_scales": scales, "class_sizes": {name: list(size) for name, size in class_sizes.items()},
            "f1": best[0], "tp": scored["tp"], "fp": scored["fp"], "fn": scored["fn"],
            "mean_error_3d_m": scored["mean_error_3d_m"], "plateau": [r[2] for r in plateau],
            "gap": [round(v, 4) for v in gap]}


def plateau_gap(scores, low: float, high: float) -> tuple[float, float]:
    """The thresholds that keep exactly what thresholds ``low`` to ``high`` keep: (the strongest of ``scores``
    below ``low``, the weakest at or above ``high``), an object being kept when its score is at least the threshold
    (greedy suppression in decreasing score keeps, at any threshold, the objects of a lower threshold that score
    at least as much). Without a score on a side, that side is the given bound."""
    below = [float(s) for s in scores if s < low]
    above = [float(s) for s in scores if s >= high]
    return (max(below) if below else float(low)), (min(above) if above else float(high))


def merge_extraction_fits(fits: list[dict]) -> dict:
    """One calibration from several calibration scenes: the most common top-hat setting (a tie goes to the setting
    whose scenes fit better - mean F1 - then to the smaller factor), then median scales (over the scenes that chose
    it) and threshold, majority cross-class and resting heights."""
    tophats = [f["tophat"] for f in fits]

    def preference(factor: float) -> tuple:
        f1 = [f.get("f1", 0.0) for f in fits if f["tophat"] == factor]
        return tophats.count(factor), sum(f1) / len(f1), -factor

    tophat = max(sorted(set(tophats)), key=preference)
    chosen = [f for f in fits if f["tophat"] == tophat]
    scales: dict = {}
    for fit in chosen:
        for name, value in fit["class_scales"].items():
            scales.setdefault(name, []).append(value)
    return {"class_scales": {k: float(np.median(v)) for k, v in scales.items()}, "tophat": tophat,
            **({"class_sizes": chosen[0]["class_sizes"]} if "class_sizes" in chosen[0] else {}),
            "threshold": float(np.median([f["threshold"] for f in chosen])),
            "cross_class": sum(f["cross_class"] for f in chosen) * 2 > len(chosen),
            "resting": sum(f.get("resting", False) for f in chosen) * 2 > len(chosen),
            "fits": fits}


def well_seen_centres(dataset, i: int, classes, max_occluded: float = 0.3, min_height_px: float = 20.0):
    """The objects of ``classes`` in frame ``i`` at least ``min_height_px`` tall, untruncated, at most
    ``max_occluded`` hidden, whose centre projects into the image: (class index, depth of the centre along the
    optical axis, u, v) each."""
    from semloc_core.geometry import invert_transform

    truth, camera = dataset.semantic_map, dataset.camera
    T_cam_world = invert_transform(dataset.T_world_cam[i])
    for seen in dataset.visible_objects(i):
        if (seen.class_name not in classes or seen.truncated or seen.occluded_fraction > max_occluded
                or seen.box[3] - seen.box[1] < min_height_px):
            continue
        centre = T_cam_world[:3, :3] @ truth.positions[seen.object_index] + T_cam_world[:3, 3]
        (u, v), inside = camera.project_cam(centre)
        if inside:
            yield classes.index(seen.class_name), float(centre[2]), float(u), float(v)


def llr_samples(dataset, source, frames, max_occluded: float = 0.3, min_height_px: float = 20.0):
    """Positive and negative heat samples of one scene (semloc_core.mapping.likelihood.heat_samples): positives at
    the projected centres of objects at least ``min_height_px`` tall, untruncated, at most ``max_occluded``
    hidden; negatives outside every box of the class."""
    from semloc_core.mapping.likelihood import heat_samples

    camera = dataset.camera
    positives = {name: [] for name in source.classes}
    negatives = {name: [] for name in source.classes}
    for i in frames:
        heat = source(i)
        boxes = [(source.classes.index(seen.class_name), seen.box) for seen in dataset.visible_objects(i)
                 if seen.class_name in source.classes]
        centres = [(c, u, v) for c, _, u, v in well_seen_centres(dataset, i, source.classes, max_occluded,
                                                                  min_height_px)]
        pos, neg = heat_samples(heat, (camera.width, camera.height), centres, boxes)
        for c, name in enumerate(source.classes):
            positives[name].append(pos[c])
            # Every 7th background cell is plenty (a scene has millions) and keeps the pooled samples small.
            negatives[name].append(neg[c][::7])
    return positives, negatives


def scale_depth_samples(dataset, source, frames, max_occluded: float = 0.3, min_height_px: float = 20.0,
                        min_heat: float = 0.5) -> dict:
    """Per class, (depth, focal, scale) of every well-seen object (as ``llr_samples``' positives) whose strongest
    level at its projected centre answers at least ``min_heat``: the level's scale and the centre's depth."""
    camera = dataset.camera
    samples = {name: [] for name in source.classes}
    for i in frames:
        levels = source(i)  # (classes, levels, h, w)
        rows, cols = levels.shape[2:]
        for c, depth, u, v in well_seen_centres(dataset, i, source.classes, max_occluded, min_height_px):
            x = min(max(int(round((u + 0.5) * cols / camera.width - 0.5)), 0), cols - 1)
            y = min(max(int(round((v + 0.5) * rows / camera.height - 0.5)), 0), rows - 1)
            heat = levels[c, :, y, x]
            best = int(np.argmax(heat))
            if heat[best] >= min_heat:
                samples[source.classes[c]].append((depth, float(camera.K[0, 0]), source.scales[best]))
    return samples


def fit_scale_depth(scenes, stride: int, detector_source, log: Log) -> dict:
    """Each class's depth per scale (semloc_core.mapping.scale_depth) pooled over ``scenes`` (calibration
    scenes); ``detector_source(name, dataset, frames)`` gives a scene's per-level heatmaps."""
    from semloc_core.mapping.scale_depth import fit_depth_per_scale

    pooled: dict = {}
    scales = None
    for name, dataset in scenes:
        frames = list(range(0, len(dataset), stride))
        source = detector_source(name, dataset, frames)
        scales = source.scales
        for key, values in scale_depth_samples(dataset, source, frames).items():
            pooled.setdefault(key, []).extend(values)
        log(f"scene {name}: scale-depth samples " + ", ".join(f"{k} {len(v)}" for k, v in pooled.items()))
    empty = [k for k, v in pooled.items() if not v]
    if empty:
        raise ValueError(f"no well-seen object of {empty} answered on the calibration scenes: cannot fit their "
                         f"depth per scale")
    return {"scales": list(scales), "classes": {k: fit_depth_per_scale(*zip(*v)) for k, v in pooled.items()}}


def fit_scene_llr(scenes, stride: int, detector_source, log: Log) -> dict:
    """Per-class heat log-likelihood ratios pooled over ``scenes`` (calibration scenes)."""
    from semloc_core.mapping.likelihood import fit_heat_llr

    positives: dict = {}
    negatives: dict = {}
    for name, dataset in scenes:
        frames = list(range(0, len(dataset), stride))
        pos, neg = llr_samples(dataset, detector_source(name, dataset, frames), frames)
        for key, samples in pos.items():
            positives.setdefault(key, []).extend(samples)
        for key, samples in neg.items():
            negatives.setdefault(key, []).extend(samples)
        log(f"scene {name}: heat samples " + ", ".join(f"{k} {sum(map(len, v))}+/{sum(map(len, negatives[k]))}-"
                                                        for k, v in pos.items()))
    return fit_heat_llr(positives, negatives)


def fit_scene_existence(scenes, calibration: dict, source: str, mode: str, extraction, distance: float,
                        min_size: float, log: Log):
    """The existence curve (semloc_core.mapping.existence) of the merged extraction: every candidate down to
    SAMPLE_FLOOR of its threshold in the calibration scenes ``(dataset, mapper, support)``, real when it matches a
    ground-truth object (None without any candidate)."""
    from semloc_core.mapping.existence import SAMPLE_FLOOR, fit_existence

    scores, real, threshold = [], [], None
    for dataset, mapper, support in scenes:
        config, settings = extraction_for(calibration, source, mode, extraction, support)
        threshold = settings["threshold"]
        scored = score_scene(mapper, dataset.semantic_map, replace(config, threshold=SAMPLE_FLOOR * threshold),
                             distance, min_size)
        scores += [p["score"] for p in scored["predicted"]]
        real += [p["match"] >= 0 for p in scored["predicted"]]
    if not scores:
        log(f"existence ({source}, {mode}): no candidate in the calibration scenes - objects stay certain")
        return None
    curve = fit_existence(scores, real, threshold)
    log(f"existence ({source}, {mode}): {curve.samples} candidates >= {SAMPLE_FLOOR} x threshold, {curve.real} "
        f"real; p(real) = {curve(threshold)[()]:.2f} at the threshold, {curve(1.25 * threshold)[()]:.2f} at 1.25 x")
    return curve
