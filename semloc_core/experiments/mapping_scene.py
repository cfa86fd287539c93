"""One scene of the mapping experiment: heatmaps back-projected into a voxel map, objects extracted with an
extraction configuration, and scored against the scene's ground-truth objects (thesis ch. 5)."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from semloc_core.experiments.heatmap_sources import depth_image
from semloc_core.experiments.tabletop import TABLETOP_SIZES

# Uncalibrated thresholds: oracle heat is 0..1 with objects near 1; detector heat as surprisal averages 1 per view
# on background and 4-7 on objects (docs/mapping.md).
DEFAULT_THRESHOLDS = {"oracle": 0.5, "detector": 3.0}
DETECTOR_BACKGROUND = "surprisal"
MODES = {"normalised": True, "sum": False}


def map_scene(dataset, source, grid, frames, downsample: int, background: str,
              log: Callable[[str], None] = lambda _: None, llr: dict | None = None, scale_depth: dict | None = None,
              level_reach: int = 0, occlusion_margin: float | None = None) -> tuple[object, dict]:
    """Map ``frames`` of a scene; ``scale_depth`` (from ``mapping_fits.fit_scale_depth``): the source gives
    per-level maps, back-projected scale-selected. ``occlusion_margin``: integrate each frame with its depth image
    (hidden voxels unseen)."""
    from semloc_core.mapping import MapperConfig, VoxelMapper
    from semloc_core.mapping.scale_depth import calibration_mismatch, level_depths

    mapper = VoxelMapper(grid, source.classes, MapperConfig(heatmap_downsample=downsample,
                                                            heatmap_background=background, heatmap_llr=llr or {},
                                                            level_reach=level_reach,
                                                            **({} if occlusion_margin is None else
                                                               {"occlusion_margin": occlusion_margin})))
    depths = None
    if scale_depth is not None:
        problem = calibration_mismatch(scale_depth["scales"], scale_depth["classes"], source.scales, source.classes)
        if problem:
            raise ValueError(f"the scale-depth calibration does not fit this detector: {problem}")
        depths = level_depths([scale_depth["classes"][c]["depth_per_scale"] for c in source.classes],
                              source.scales, dataset.camera.K[0, 0])
    T_world_cam = dataset.T_world_cam
    heat_seconds, map_seconds = 0.0, 0.0
    for n, i in enumerate(frames):
        start = time.perf_counter()
        heatmaps = source(i)
        middle = time.perf_counter()
        depth = None if occlusion_margin is None else depth_image(dataset, i)
        mapper.integrate(heatmaps, T_world_cam[i], dataset.camera, level_depths=depths, depth=depth)
        map_seconds += time.perf_counter() - middle
        heat_seconds += middle - start
        if (n + 1) % 50 == 0:
            log(f"  {n + 1}/{len(frames)} frames")
    timing = {"frames": len(frames), "heatmap_s_per_frame": heat_seconds / max(len(frames), 1),
              "integrate_s_per_frame": map_seconds / max(len(frames), 1),
              "heatmap_shape": list(np.asarray(heatmaps).shape)}
    return mapper, timing


def extraction_for(calibration: dict, source: str, mode: str, extraction, support: tuple | None = None
                   ) -> tuple[object, dict]:
    """The ExtractionConfig of one heatmap source and score mode (``extraction``: the spec's extraction settings):
    calibrated values, else the defaults; and the settings as reported."""
    from semloc_core.mapping import ExtractionConfig
    from semloc_core.mapping.existence import ExistenceCurve

    entry = calibration.get(source, {}).get(mode, {})
    threshold = extraction.threshold if extraction.threshold is not None else entry.get(
        "threshold", DEFAULT_THRESHOLDS[source])
    settings = {"threshold": float(threshold), "class_scales": entry.get("class_scales", {}),
                "cross_class": bool(entry.get("cross_class", False)), "tophat": float(entry.get("tophat", 0.0)),
                "min_views": extraction.min_views, "calibrated": bool(entry)}
    support_z, support_polygon = support or (None, None)
    settings["support_z"] = support_z
    settings["support_polygon"] = None if support_polygon is None else np.asarray(support_polygon).tolist()
    settings["position"] = extraction.position
    settings["resting"] = bool(entry.get("resting", False)) and support_z is not None
    settings["prominence"] = extraction.prominence
    existence = ExistenceCurve.from_document(entry["existence"]) if "existence" in entry else None
    settings["existence"] = None if existence is None else existence.to_document()
    return ExtractionConfig(threshold=settings["threshold"], normalise=MODES[mode], min_views=extraction.min_views,
                            class_sizes=TABLETOP_SIZES, class_scales=settings["class_scales"],
                            cross_class=settings["cross_class"], tophat=settings["tophat"],
                            support_z=support_z, support_polygon=support_polygon, position=extraction.position,
                            mode_bandwidth=extraction.mode_bandwidth, resting=settings["resting"],
                            prominence=extraction.prominence, existence=existence), settings


def score_scene(mapper, truth, extraction, distance: float, min_size: float, objects=None) -> dict:
    """Figures of one extracted map against the ground truth (``objects``: already extracted with
    ``extraction``); ``predicted_map`` is the extracted SemanticMap."""
    from semloc_core.eval.objects import object_map_figures
    from semloc_core.mapping.extraction import objects_to_semantic_map

    objects = mapper.extract(extraction) if objects is None else objects
    sizes = ({name: extraction.size_of(name) for name in mapper.class_names}
             if extraction.export_size == "bounding_volume" else None)
    predicted = objects_to_semantic_map(objects, mapper.class_names, mapper.grid, sizes, extraction.existence)
    pred_classes = [predicted.class_names[k] for k in predicted.class_index]
    gt_classes = [truth.class_names[k] for k in truth.class_index]
    figures = object_map_figures(pred_classes, predicted.positions, gt_classes, truth.positions, distance,
                                 predicted.scores, planar=False)
    planar = object_map_figures(pred_classes, predicted.positions, gt_classes, truth.positions, distance,
                                predicted.scores, planar=True)
    matches = np.asarray(figures["matches"], int)
    large = np.max(truth.sizes, axis=1) >= min_size
    found = np.zeros(len(truth), bool)
    found[matches[matches >= 0]] = True
    # Every class mapped or present: a false positive of a class the scene does not hold counts against it too.
    per_class_large = {name: {"objects": 0, "found": 0} for name in dict.fromkeys([*truth.class_names,
                                                                                   *mapper.class_names])}
    for c, name in enumerate(truth.class_names):
        mine = (truth.class_index == c) & large
        per_class_large[name] = {"objects": int(mine.sum()), "found": int((found & mine).sum())}
    errors_3d = [float(np.linalg.norm(predicted.positions[p] - truth.positions[g])) for p, g in enumerate(matches)
                 if g >= 0]
    errors_2d = [float(np.linalg.norm(predicted.positions[p, :2] - truth.positions[g, :2]))
                 for p, g in enumerate(matches) if g >= 0]
    return {
        "objects_predicted": len(predicted), "objects_truth": len(truth),
        "tp": figures["tp"], "fp": figures["fp"], "fn": figures["fn"],
        "precision": figures["precision"], "recall": figures["recall"],
        "large_objects": int(large.sum()), "large_found": int((found & large).sum()),
        "recall_large": float((found & large).sum() / large.sum()) if large.any() else None,
        "mean_error_3d_m": float(np.mean(errors_3d)) if errors_3d else None,
        "max_error_3d_m": float(np.max(errors_3d)) if errors_3d else None,
        "mean_error_planar_m": float(np.mean(errors_2d)) if errors_2d else None,
        "planar": {k: planar[k] for k in ("tp", "fp", "fn", "precision", "recall")},
        "per_class": {name: {**{k: figures["per_class"].get(name, {}).get(k) for k in
                                ("tp", "fp", "fn", "precision", "recall", "mean_position_error")},
                             "large_objects": per_class_large[name]["objects"],
                             "large_found": per_class_large[name]["found"]}
                      for name in per_class_large},
        "predicted": [{"class": o.class_name, "position": o.position.tolist(), "extent": o.extent.tolist(),
                       "score": o.score, "existence": float(e), "match": int(m)}
                      for o, e, m in zip(objects, predicted.existence, matches)],
        "predicted_map": predicted,
    }


def summarise(report: dict, sources, key: str) -> dict:
    """Totals over the scenes of one score mode, per heatmap source."""
    summary = {}
    for source_name in sources:
        scenes = [s["sources"][source_name][key] for s in report["scenes"].values()]
        per_class: dict = {}
        for scene in scenes:
            for name, figures in scene["per_class"].items():
                entry = per_class.setdefault(name, {"tp": 0, "fp": 0, "fn": 0, "large_objects": 0, "large_found": 0})
                for k in entry:
                    entry[k] += figures[k] or 0
        summary[source_name] = {
            "scenes": len(scenes),
            "scenes_all_large_found": sum(s["large_found"] == s["large_objects"] for s in scenes),
            "scenes_at_most_one_fp": sum(s["fp"] <= 1 for s in scenes),
            "large_found": sum(s["large_found"] for s in scenes),
            "large_objects": sum(s["large_objects"] for s in scenes),
            "fp": sum(s["fp"] for s in scenes),
            "per_class": per_class,
        }
    return summary
