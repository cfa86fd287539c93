"""The mapping experiment: the voxel mapper's object map against ground truth (thesis ch. 5).

Heatmaps of every ``stride``-th frame are back-projected along the ground-truth camera poses into a voxel grid over
the table (from the dataset's ``metadata["table"]``, or ``mapper.grid_min`` / ``grid_max``), objects are extracted
and matched to the ground-truth object map: per class and per scene, precision, recall (also restricted to objects
of at least ``scoring.min_size``), false positives and position error (3-D and on the floor plane).

DATASET is a ``semloc sim`` folder (anything ``open_dataset`` reads that has images, poses and a map), or
``tabletop`` to render scenes on the fly: one per entry of ``trajectories`` (RGB-D Scenes ``.pose`` files, or
``orbit:SEED`` for the simulator's own walk), objects textured with the data folder's real crops when present.

Heatmaps: ``detector`` (a semloc_core.detection detector, ``detector`` names the configuration) or ``oracle`` (a
Gaussian at each visible object's projected centre, size ∝ its projected size), or ``both``. ``calibration.fit``
fits the extraction on these scenes (calibration scenes); ``localize`` closes the loop (closing_loop.py).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from semloc_core.experiments import mapping_fits as fits
from semloc_core.experiments.closing_loop import LocalizeSpec, calibration_trajectories, close_the_loop
from semloc_core.experiments.heatmap_sources import (CachedHeatmaps, DetectorHeatmaps, OracleHeatmaps,
                                                     detector_cache_name, detector_config)
from semloc_core.experiments.mapping_scene import (DETECTOR_BACKGROUND, MODES, extraction_for, map_scene,
                                                   score_scene, summarise)
from semloc_core.experiments.spec import DataPath, DataPaths, Spec
from semloc_core.experiments.tabletop import TABLETOP_SIZES, table_grid, table_support, tabletop_scenes

Log = Callable[[str], None]
Vector3 = tuple[float, float, float]


class MapperSpec(Spec):
    """How heatmaps are accumulated."""

    voxel_size: float = Field(0.01, gt=0, description="metres (thesis: 0.01)")
    grid_min: Vector3 | None = Field(None, description="grid box (default: over the table)")
    grid_max: Vector3 | None = None
    heatmap_downsample: int = Field(1, ge=1)
    background: Literal["none", "median", "surprisal"] | None = Field(
        None, description="how each frame's background heat is discounted (default: surprisal for the detector)")
    accumulate: Literal["heat", "llr"] = Field("heat", description="raw heat (thesis §5.4) or per-class "
                                                                   "log-likelihood ratios of the heat (calibrated)")
    scale_depth: bool = Field(False, description="a trained window detector's level chooses each vote's depth "
                                                 "(depth per scale from the calibration)")
    level_reach: int = Field(0, ge=0, description="scale_depth: the max over the levels within this many steps")
    occlusion: bool = Field(False, description="a voxel counts as seen only where the frame's depth image shows it "
                                               "unoccluded (scenes rendered on the fly)")
    occlusion_margin: float = Field(0.15, ge=0, allow_inf_nan=False,
                                    description="occlusion: metres behind the seen surface a voxel still counts")


class ExtractionSpec(Spec):
    """How objects are extracted from the volumes."""

    position: Literal["peak", "centroid", "mode"] = Field("peak", description="object position (docs/mapping.md)")
    mode_bandwidth: float = Field(0.02, gt=0, description="position mode: the smoothing Gaussian's std, metres")
    prominence: float = Field(0.8, ge=0, lt=1, description="shoulder rule: a candidate joined to a stronger object "
                                                           "of its class above this fraction of its peak (0: off)")
    threshold: float | None = Field(None, description="on the score (default: calibrated, else per heatmap source)")
    normalise: bool = Field(True, description="score = mean per view (false: sum / frames)")
    min_views: int = Field(10, ge=1)
    support: Literal["none", "table"] = Field("none", description="table: objects rest on the table top")


class ScoringSpec(Spec):
    distance: float = Field(0.05, gt=0, description="match radius, metres (3-D)")
    min_size: float = Field(0.10, ge=0, description="recall counts objects whose largest extent is at least this")


class MappingCalibrationSpec(Spec):
    file: DataPath | None = Field(None, description="a fitted calibration (JSON): scales, threshold, cross-class, "
                                                    "existence, llr, scale_depth")
    fit: bool = Field(False, description="fit the extraction (and llr / scale_depth) on these scenes")
    leave_one_out: bool = Field(False, description="fit each scene's extraction on the other scenes of the run")


class MappingSpec(Spec):
    """``semloc eval mapping``."""

    dataset: str | None = Field(None, description="a semloc sim dataset folder, or 'tabletop'")
    seed: int = Field(0, description="tabletop: scenario seed; the closing loop's first filter seed")
    cache: str | None = Field(None, description="folder keeping each scene's detector heatmaps (float16 npz)")
    trajectories: DataPaths = Field([], description="tabletop: real trajectories (.pose, TUM), one scene each; "
                                                    "'orbit' or 'orbit:SEED' for the simulator's own walk (default)")
    frames: int | None = Field(None, ge=1, description="at most this many frames of each scene")
    stride: int = Field(3, ge=1, description="map every n-th frame")
    heatmaps: Literal["detector", "oracle", "both"] = "detector"
    detector: str = Field("templates-hsv", description="a named configuration (heatmap_sources.DETECTORS) or a "
                                                       "YAML/JSON detector configuration file")
    mapper: MapperSpec = MapperSpec()
    extraction: ExtractionSpec = ExtractionSpec()
    scoring: ScoringSpec = ScoringSpec()
    calibration: MappingCalibrationSpec = MappingCalibrationSpec()
    localize: LocalizeSpec = LocalizeSpec()
    save_volumes: bool = Field(False, description="write each scene's voxel map (.npz) and PLY")
    prune_levels: bool = Field(False, description="the template detector's levels pruned as the detector worker's "
                                                  "prune does, by the previous frame's true pose and the frame's "
                                                  "true camera height (table-top data)")

    @model_validator(mode="after")
    def _consistent(self):
        tabletop = self.dataset == "tabletop"
        if self.mapper.occlusion and not tabletop:
            raise ValueError("mapper.occlusion needs depth images: here only DATASET 'tabletop' (rendered on the "
                             "fly) has them")
        if not tabletop and (self.trajectories or self.localize.trajectory):
            raise ValueError("trajectories and localize need DATASET 'tabletop'")
        if self.mapper.scale_depth and self.heatmaps == "oracle":
            raise ValueError("mapper.scale_depth needs detector heatmaps")
        if self.mapper.scale_depth and self.mapper.accumulate == "llr":
            raise ValueError("mapper.scale_depth and accumulate llr do not combine (the ratios are fitted on single "
                             "maps)")
        return self

    @property
    def sources(self) -> list[str]:
        return ["detector", "oracle"] if self.heatmaps == "both" else [self.heatmaps]


@dataclass
class MappedScene:
    """One scene mapped with one heatmap source."""

    name: str
    dataset: object
    source: str
    mapper: object
    results: dict
    support: tuple | None
    fits: dict
    predicted_map: object = None    # the primary score mode's extracted SemanticMap
    predicted: list = field(default_factory=list)


@dataclass
class MappingResult:
    report: dict
    rows: list[dict]                # the Markdown table's rows
    scenes: list[MappedScene]
    calibration: dict | None        # what calibration.fit fitted
    spec: MappingSpec


def check(spec: MappingSpec) -> None:
    """What the spec names must exist and fit: raises ValueError."""
    from semloc_core.io.detector_models import DetectorModelError

    if spec.dataset is None:
        raise ValueError("no dataset given")
    if spec.localize.trajectory and spec.localize.observations == "detector":
        missing = [t for t in calibration_trajectories(spec.localize) if not Path(t).is_file()]
        if missing:
            raise ValueError(f"localize.observations detector: calibration trajectories not found: {missing} "
                             f"(localize.calibration_trajectories)")
    if spec.mapper.scale_depth:
        try:
            kind = detector_config(spec.detector).get("kind")
        except (OSError, ValueError, DetectorModelError) as error:
            raise ValueError(f"cannot read detector {spec.detector}: {error}") from None
        if kind != "linear":
            raise ValueError(f"mapper.scale_depth needs a trained window detector (kind: linear), {spec.detector} "
                             f"is {kind!r}")


def open_scenes(spec: MappingSpec, log: Log) -> list[tuple[str, object]]:
    """(name, Dataset) per scene."""
    from semloc_core.io.dataset import open_dataset

    if spec.dataset != "tabletop":
        return [(Path(spec.dataset).name, open_dataset(spec.dataset))]
    return tabletop_scenes(spec.trajectories, spec.seed, spec.frames, log=log)


def run(spec: MappingSpec, log: Log = lambda _: None) -> MappingResult:
    """Map, extract and score every scene of the spec (and fit, and close the loop, when asked). Raises ValueError
    (and OSError) for inputs it cannot use."""
    check(spec)
    calibration = {}
    if spec.calibration.file:
        try:
            calibration = json.loads(Path(spec.calibration.file).read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise ValueError(f"cannot read calibration {spec.calibration.file}: {error}") from None
    scenes = open_scenes(spec, log)
    sources = spec.sources
    primary = "normalised" if spec.extraction.normalise else "sum"
    report: dict = {"dataset": spec.dataset, "seed": spec.seed, "stride": spec.stride,
                    "voxel_size_m": spec.mapper.voxel_size, "distance_m": spec.scoring.distance,
                    "min_size_m": spec.scoring.min_size, "min_views": spec.extraction.min_views,
                    "detector": spec.detector if "detector" in sources else None,
                    "calibration_file": spec.calibration.file, "primary_mode": primary,
                    "occlusion_margin_m": spec.mapper.occlusion_margin if spec.mapper.occlusion else None,
                    "bounding_volumes": TABLETOP_SIZES, "scenes": {}, "summary": {}}
    with tempfile.TemporaryDirectory(prefix="semloc-eval-mapping-") as tmp:
        mapped, fitted = _map_scenes(spec, scenes, calibration, report, Path(tmp), log)
    rows, for_localization = _score(spec, mapped, calibration, report, primary)
    report["summary"] = {mode: summarise(report, sources, mode) for mode in MODES}
    merged = None
    if spec.calibration.fit:
        merged = _merged_calibration(spec, mapped, fitted, log)
        report["calibration_fitted"] = merged
    if spec.localize.trajectory:
        map_from = spec.localize.source or ("oracle" if spec.heatmaps == "oracle" else "detector")
        report["closing_the_loop"] = close_the_loop(for_localization, spec.localize, map_from, spec.seed,
                                                    spec.scoring.distance, spec.cache, log)
    return MappingResult(report, rows, mapped, merged, spec)


def _map_scenes(spec: MappingSpec, scenes, calibration: dict, report: dict, tmp: Path, log: Log):
    """Every scene mapped with every heatmap source (and the extraction fitted on each, when asked)."""
    mapper_spec, sources = spec.mapper, spec.sources
    fitted: dict = {}

    def detector_source(name, dataset, frames):
        workdir = tmp / name
        workdir.mkdir(exist_ok=True)
        make = lambda: DetectorHeatmaps(dataset, spec.detector, workdir, levels=mapper_spec.scale_depth,  # noqa: E731
                                        prune=spec.prune_levels)
        if not spec.cache and mapper_spec.accumulate == "heat" and not mapper_spec.scale_depth:
            return make()
        # Fitting likelihood ratios reads every frame's heatmaps before mapping: keep them (in the temporary
        # folder unless a cache is given) rather than running the detector twice.
        key = (f"{name}_seed{dataset.metadata.get('seed_used')}_{detector_cache_name(spec.detector)}"
               f"_stride{spec.stride}_{len(frames)}frames{'_levels' if mapper_spec.scale_depth else ''}"
               f"{'_pruned_by_pose' if spec.prune_levels else ''}.npz")
        return CachedHeatmaps(make, Path(spec.cache or tmp) / key, frames, log)

    llr = None
    if "detector" in sources and mapper_spec.accumulate == "llr":
        llr = calibration.get("detector", {}).get("llr")
        if spec.calibration.fit:
            llr = fits.fit_scene_llr(scenes, spec.stride, detector_source, log)
        if not llr:
            raise ValueError("accumulate llr needs calibration.fit or a calibration.file with 'llr'")
        fitted["llr"] = llr
    scale_depth = None
    if "detector" in sources and mapper_spec.scale_depth:
        scale_depth = calibration.get("detector", {}).get("scale_depth")
        if spec.calibration.fit:
            scale_depth = fits.fit_scale_depth(scenes, spec.stride, detector_source, log)
        if not scale_depth:
            raise ValueError("mapper.scale_depth needs calibration.fit or a calibration.file with 'scale_depth'")
        fitted["scale_depth"] = scale_depth
        report["scale_depth"] = scale_depth
    mapped = []
    for name, dataset in scenes:
        if dataset.semantic_map is None or not dataset.has_poses or not dataset.has_images:
            raise ValueError(f"{name} lacks images, poses or a ground-truth map")
        grid = table_grid(dataset, mapper_spec.voxel_size, mapper_spec.grid_min, mapper_spec.grid_max)
        frames = list(range(0, len(dataset), spec.stride))
        support = table_support(dataset) if spec.extraction.support == "table" else None
        report["scenes"][name] = {"frames_total": len(dataset), "frames_used": len(frames),
                                  "grid": grid.to_document(), "seed": dataset.metadata.get("seed_used"),
                                  "sources": {}}
        for source_name in sources:
            if source_name == "detector":
                source = detector_source(name, dataset, frames)
                report["scenes"][name]["detector_config"] = source.config
            else:
                source = OracleHeatmaps(dataset, dataset.semantic_map.class_names)
            scene_llr = llr if source_name == "detector" else None
            background = mapper_spec.background or (DETECTOR_BACKGROUND if source_name == "detector"
                                                    and not scene_llr else "none")
            log(f"scene {name}: mapping {len(frames)} frames with {source_name} heatmaps into {grid}")
            mapper, timing = map_scene(dataset, source, grid, frames, mapper_spec.heatmap_downsample, background,
                                       log, scene_llr, scale_depth if source_name == "detector" else None,
                                       mapper_spec.level_reach,
                                       mapper_spec.occlusion_margin if mapper_spec.occlusion else None)
            results = {"timing": timing, "background": background, "accumulate": "llr" if scene_llr else "heat"}
            scene_fits = {}
            if spec.calibration.fit or spec.calibration.leave_one_out:
                scene_fits = {mode: fits.fit_extraction(
                    mapper, dataset.semantic_map, normalise=normalise, min_views=spec.extraction.min_views,
                    distance=spec.scoring.distance, min_size=spec.scoring.min_size, position=spec.extraction.position,
                    mode_bandwidth=spec.extraction.mode_bandwidth, support=support,
                    prominence=spec.extraction.prominence) for mode, normalise in MODES.items()}
                for mode, fit in scene_fits.items():
                    fitted.setdefault(source_name, {}).setdefault(mode, []).append(fit)
            mapped.append(MappedScene(name, dataset, source_name, mapper, results, support, scene_fits))
    return mapped, fitted


def _score(spec: MappingSpec, mapped: list[MappedScene], calibration: dict, report: dict, primary: str):
    """Each mapped scene extracted and scored in both score modes; the table's rows and the map to localize in."""
    rows, for_localization = [], None
    for scene in mapped:
        for mode in MODES:
            scene_calibration = calibration
            if spec.calibration.leave_one_out:
                # Fitted on every other scene of this run, never on the one evaluated.
                others = [s.fits[mode] for s in mapped if s.source == scene.source and s.name != scene.name]
                scene_calibration = {scene.source: {mode: fits.merge_extraction_fits(others)}}
            extraction, settings = extraction_for(scene_calibration, scene.source, mode, spec.extraction,
                                                  scene.support)
            scored = score_scene(scene.mapper, scene.dataset.semantic_map, extraction, spec.scoring.distance,
                                 spec.scoring.min_size)
            predicted_map = scored.pop("predicted_map")
            scene.results[mode] = {"extraction": settings, **scored}
            if mode != primary:
                continue
            scene.predicted_map, scene.predicted = predicted_map, scored["predicted"]
            rows.append({"scene": scene.name, "heatmaps": scene.source, "score": mode,
                         "large found": f"{scored['large_found']}/{scored['large_objects']}",
                         "FP": scored["fp"], "precision": round(scored["precision"], 3),
                         "recall": round(scored["recall"], 3),
                         "mean err 3-D (cm)": None if scored["mean_error_3d_m"] is None else
                         round(100 * scored["mean_error_3d_m"], 1)})
            if scene.source == (spec.localize.source or spec.sources[0]) and for_localization is None:
                for_localization = (scene.name, scene.dataset, predicted_map)
        report["scenes"][scene.name]["sources"][scene.source] = scene.results
    return rows, for_localization


def _merged_calibration(spec: MappingSpec, mapped: list[MappedScene], fitted: dict, log: Log) -> dict:
    """The scenes' fits merged per source and score mode, with each mode's existence curve."""
    merged = {source: {mode: fits.merge_extraction_fits(mode_fits) for mode, mode_fits in modes.items()}
              for source, modes in fitted.items() if source not in ("llr", "scale_depth")}
    for source, modes in merged.items():
        for mode in modes:
            curve = fits.fit_scene_existence(
                [(s.dataset, s.mapper, s.support) for s in mapped if s.source == source],
                merged, source, mode, spec.extraction, spec.scoring.distance, spec.scoring.min_size, log)
            if curve is not None:
                modes[mode]["existence"] = curve.to_document()
    for key in ("llr", "scale_depth"):
        if key in fitted:
            merged.setdefault("detector", {})[key] = fitted[key]
    return merged
