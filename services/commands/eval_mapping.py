"""`semloc eval mapping DATASET --json OUT`: the voxel mapper's object map against ground truth (thesis ch. 5).

Heatmaps of every ``--stride``-th frame are back-projected along the ground-truth camera poses into a voxel grid
over the table (from the dataset's ``metadata["table"]``, or ``--grid-min/--grid-max``), objects are extracted,
and matched to the ground-truth object map: per class and per scene, precision, recall (also restricted to objects
of at least ``--min-size``), false positives and position error (3-D and on the floor plane).

DATASET is a ``semloc sim`` folder (anything ``open_dataset`` reads that has images, poses and a map), or the name
``tabletop`` to render scenes on the fly: one per ``--trajectory`` (RGB-D Scenes ``.pose`` files), seed ``--seed``,
objects textured with ../shared/data's real crops when present.

Heatmaps (``--heatmaps``): ``detector`` (a semloc_core.detection detector built from the dataset's exemplars,
``--detector`` names the configuration) or ``oracle`` (a Gaussian at each visible object's projected centre, size
∝ its projected size - isolates the mapper from the detector), or both.

``--localize TRAJECTORY`` closes the loop (tabletop only): another real trajectory is placed around the same table
and localized twice with the same observations and seeds, once with the mapped objects and once with the
ground-truth map; the report gives both RMSEs after convergence and their ratio. The observations are synthetic
heatlines from the ground-truth boxes (only the map's errors count), or with ``--localize-observations detector``
the template detector's heatlines (the loop as a robot runs it).
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

# Bounding volumes (x, y, z metres) of the tabletop classes: the thesis's "approximate bounding volume of the
# object" given to non-maximum suppression - class priors, not measured on the evaluated scenes.
TABLETOP_SIZES = {"bowl": (0.18, 0.18, 0.08), "cap": (0.26, 0.26, 0.10), "cereal_box": (0.20, 0.20, 0.30),
                  "coffee_mug": (0.12, 0.12, 0.12), "soda_can": (0.08, 0.08, 0.14)}

# Named detector configurations; ``templates`` is a folder of the dataset (or of the exemplars rendered for a
# scenario). Same parameters as benchmarks/detection_accuracy.py.
DETECTORS = {
    "templates-hsv": {"kind": "templates", "templates": "exemplars", "cell": 4, "template_cells": 9,
                      "scales": [1.2, 0.85, 0.6, 0.42], "color_space": "hsv"},
    "templates-rgb": {"kind": "templates", "templates": "exemplars", "cell": 4, "template_cells": 9,
                      "scales": [1.2, 0.85, 0.6, 0.42]},
    "multiview-templates-hsv": {"kind": "templates", "templates": "exemplars_multiview", "cell": 4,
                                "template_cells": 9, "scales": [1.2, 0.85, 0.6, 0.42], "color_space": "hsv",
                                "mirror": False},
    "multiview-dot": {"kind": "multiview", "templates": "exemplars_multiview", "spread": 4,
                      "scales": [1.2, 0.85, 0.6, 0.42]},
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="a semloc sim dataset folder, or 'tabletop' to render scenes on the fly")
    parser.add_argument("--json", required=True, help="report file (JSON); Markdown table and PNG plots next to it")
    parser.add_argument("--trajectory", nargs="+", default=[],
                        help="tabletop: real trajectories (.pose, TUM), one scene each; 'orbit' or 'orbit:SEED' for "
                             "the simulator's own walk around the table (default)")
    parser.add_argument("--seed", type=int, default=0, help="tabletop: scenario seed")
    parser.add_argument("--frames", type=int, default=None, help="use at most this many frames of each scene")
    parser.add_argument("--stride", type=int, default=3, help="map every n-th frame")
    parser.add_argument("--heatmaps", choices=["detector", "oracle", "both"], default="detector")
    parser.add_argument("--detector", default="templates-hsv",
                        help=f"one of {sorted(DETECTORS)} or a YAML/JSON detector configuration file")
    parser.add_argument("--voxel-size", type=float, default=0.01, help="metres (thesis: 0.01)")
    parser.add_argument("--grid-min", type=float, nargs=3, default=None, help="grid box (default: over the table)")
    parser.add_argument("--grid-max", type=float, nargs=3, default=None)
    parser.add_argument("--heatmap-downsample", type=int, default=1)
    parser.add_argument("--background", choices=["none", "median", "surprisal"], default=None,
                        help="how each frame's background heat is discounted: median subtraction, or surprisal "
                             "(-log of the frame's fraction of cells at least as hot; the default for the detector)")
    parser.add_argument("--position", choices=["peak", "centroid", "mode"], default="peak",
                        help="object position: the refined score maximum, the centroid of the score above half "
                             "the peak around it, or the maximum of that score smoothed at --mode-bandwidth "
                             "(docs/mapping.md)")
    parser.add_argument("--mode-bandwidth", type=float, default=0.02,
                        help="--position mode: the smoothing Gaussian's standard deviation, metres")
    parser.add_argument("--prominence", type=float, default=0.8,
                        help="a candidate joined to a stronger object of its class by voxels above this fraction of "
                             "its peak is that object's shoulder, not an object (0: off; docs/mapping.md)")
    parser.add_argument("--threshold", type=float, default=None,
                        help="extraction threshold on the score (default: per heatmap source, see docs/mapping.md)")
    parser.add_argument("--no-normalise", action="store_true", help="score = sum / frames instead of mean per view")
    parser.add_argument("--min-views", type=int, default=10)
    parser.add_argument("--distance", type=float, default=0.05, help="match radius, metres (3-D)")
    parser.add_argument("--min-size", type=float, default=0.10,
                        help="recall counts ground-truth objects whose largest extent is at least this (m)")
    parser.add_argument("--localize", default=None, help="tabletop: a trajectory to localize in the mapped world")
    parser.add_argument("--localize-frames", type=int, default=None, help="at most this many poses of it")
    parser.add_argument("--localize-stride", type=int, default=2, help="localize every n-th frame")
    parser.add_argument("--localize-seeds", type=int, default=5, help="filter seeds (each run with both maps)")
    parser.add_argument("--localize-noise-draws", type=int, default=0,
                        help="also localize with N copies of the ground-truth map whose objects are moved at random "
                             "(planar, Gaussian) by as much as the mapped objects are off: what the ratio would be "
                             "for errors of that size without their pattern")
    parser.add_argument("--localize-source", choices=["detector", "oracle"], default=None,
                        help="whose map is localized against (default: the first heatmap source)")
    parser.add_argument("--localize-observations", choices=["synthetic", "detector"], default="synthetic",
                        help="what the localizer observes: synthetic heatlines from the ground-truth boxes (only the "
                             "map's errors count), or the localizer's template detector's heatlines (the loop as a "
                             "robot runs it: the same exemplars as the mapping detector; its settings, score "
                             "likelihoods and bearing model as semloc eval localization --sources detector, fitted "
                             "on the --localize-calibration-trajectories worlds)")
    parser.add_argument("--localize-calibration-trajectories", nargs="+", default=None,
                        help="--localize-observations detector: trajectories of the calibration worlds (default: "
                             "RGB-D Scenes v2 06, 11 and 12 beside the --localize trajectory)")
    parser.add_argument("--save-volumes", action="store_true", help="write each scene's voxel map (.npz) and PLY")
    parser.add_argument("--accumulate", choices=["heat", "llr"], default="heat",
                        help="detector: back-project raw heat (thesis §5.4) or per-class log-likelihood ratios of "
                             "the heat (fitted with --calibrate-out, read from --calibration)")
    parser.add_argument("--support", choices=["none", "table"], default="none",
                        help="table: objects rest on the table top the grid is placed on (centre over the "
                             "table, within the class's bounding height above its top; the calibration may also "
                             "choose resting heights, docs/mapping.md)")
    parser.add_argument("--scale-depth", action="store_true",
                        help="detector (a trained window detector): scale-selected back-projection - each voxel "
                             "takes the pyramid level whose apparent size matches its depth; the depth per scale "
                             "is fitted with --calibrate-out and read from --calibration (docs/mapping.md)")
    parser.add_argument("--level-reach", type=int, default=0,
                        help="--scale-depth: a voxel takes the max over the levels within this many steps of the "
                             "one its depth stands for (0: that level only)")
    parser.add_argument("--occlusion", action="store_true",
                        help="count a voxel as seen by a frame only where the frame's depth image (the simulator's "
                             "render) shows it unoccluded: hidden voxels get neither a view nor heat")
    parser.add_argument("--occlusion-margin", type=float, default=0.15,
                        help="--occlusion: metres behind the seen surface a voxel still counts as seen (0.15)")
    parser.add_argument("--heatmap-cache", default=None,
                        help="folder: store each scene's detector heatmaps there (float16 npz) and reuse them")
    parser.add_argument("--calibration", default=None,
                        help="JSON from --calibrate-out: per-class score scales, threshold, cross-class suppression")
    parser.add_argument("--leave-one-out", action="store_true",
                        help="fit each scene's extraction (scales, threshold, top-hat, cross-class) on the other "
                             "scenes of the run; heat likelihood ratios still come from --calibration")
    parser.add_argument("--calibrate-out", default=None,
                        help="fit the extraction on THESE scenes (a calibration scene) and write it here")


# ---------------------------------------------------------------------------------------------------- scenes


def _tabletop_options() -> dict:
    from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops

    folder = default_exemplar_dir()
    if folder is None:
        return {}
    crops, others = load_exemplar_crops(folder)
    return {"crops": crops, "clutter_crops": others}


def open_scenes(args, log) -> list[tuple[str, object]]:
    """(name, Dataset) per scene."""
    from semloc_core.io.dataset import open_dataset

    if args.dataset != "tabletop":
        return [(Path(args.dataset).name, open_dataset(args.dataset))]
    from semloc_core.io.trajectory import read_trajectory
    from semloc_core.sim import make_scenario

    from services.commands.eval_localization import SCENE_OBJECTS, TABLETOP_CLASSES

    options = _tabletop_options()
    scenes = []
    for path in args.trajectory or ["orbit"]:
        # "orbit" or "orbit:SEED": the simulator's own walk around the table (calibration scenes).
        base_seed = args.seed
        if path == "orbit" or path.startswith("orbit:"):
            trajectory, name = None, path.replace(":", "")
            base_seed = int(path.split(":")[1]) if ":" in path else args.seed
        else:
            trajectory, name = read_trajectory(Path(path))[1], Path(path).stem
        scene_options = dict(options)
        if getattr(args, "clutter", None) is not None:  # semloc train-detector --clutter
            scene_options["clutter"] = args.clutter
        if name.isdigit() and int(name) in SCENE_OBJECTS:
            # The objects of RGB-D Scenes v2 scene NN (thesis Table 4.1), as semloc eval localization does.
            scene_options["instances"] = dict(zip(TABLETOP_CLASSES, SCENE_OBJECTS[int(name)]))
        # Some seeds draw more objects than a small table holds (the simulator then refuses): take the next seed
        # and say so in the report.
        for seed in range(base_seed, base_seed + 10):
            try:
                scenario = make_scenario("tabletop", seed=seed, frames=args.frames, trajectory=trajectory,
                                         **scene_options)
            except ValueError as error:
                log(f"scene {name}: seed {seed}: {error}")
                continue
            log(f"scene {name}: tabletop seed {seed}, {len(scenario)} frames, {len(scenario.semantic_map)} objects")
            scenario.metadata["seed_used"] = seed
            scenes.append((name, scenario))
            break
        else:
            raise ValueError(f"scene {name}: no seed in [{base_seed}, {base_seed + 10}) builds a tabletop world")
    return scenes


def table_grid(dataset, voxel_size: float, grid_min=None, grid_max=None, margin: float = 0.1, height: float = 0.7):
    """The grid over the table: its axis-aligned footprint plus ``margin``, from just below the surface up to
    ``height`` above it (the thesis: 2 x 2 x 0.7 m at 1 cm)."""
    from semloc_core.mapping import VoxelGrid

    if grid_min is not None and grid_max is not None:
        return VoxelGrid.from_bounds(grid_min, grid_max, voxel_size)
    surface_z, corners = table_support(dataset)
    lo = np.r_[corners.min(axis=0) - margin, surface_z - 0.02]
    hi = np.r_[corners.max(axis=0) + margin, surface_z - 0.02 + height]
    return VoxelGrid.from_bounds(lo, hi, voxel_size)


def table_support(dataset) -> tuple[float, np.ndarray]:
    """The table top the objects rest on: its height and its (4, 2) corners (x, y), from the dataset's metadata."""
    table = dataset.metadata.get("table")
    if not table:
        raise ValueError("the dataset has no table metadata: give --grid-min and --grid-max, and --support none")
    centre = np.asarray(table["centre"], float)
    axes = np.asarray(table["axes"], float)
    half = np.asarray(table["half_extent"], float)
    corners = np.array([centre + axes @ (half * s) for s in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
    return float(table["surface_z"]), corners


# ---------------------------------------------------------------------------------------------------- heatmaps


class OracleHeatmaps:
    """Gaussians at the projected centres of the objects visible in the frame (the ideal detector)."""

    def __init__(self, dataset, classes, rows: int = 120, cols: int = 160):
        from semloc_core.mapping.synthetic import SyntheticObject

        gt = dataset.semantic_map
        self.classes = tuple(classes)
        self.objects = [SyntheticObject(self.classes.index(gt.class_names[c]), gt.positions[k], gt.sizes[k])
                        for k, c in enumerate(gt.class_index)]
        self.dataset, self.rows, self.cols = dataset, rows, cols

    def __call__(self, i: int) -> np.ndarray:
        from semloc_core.mapping.synthetic import render_heatmaps

        visible = {v.object_index for v in self.dataset.visible_objects(i) if v.visible_pixels > 0}
        objects = [o for k, o in enumerate(self.objects) if k in visible]
        return render_heatmaps(self.dataset.camera, self.dataset.T_world_cam[i], objects, len(self.classes),
                               height=self.rows, width=self.cols)


class DetectorHeatmaps:
    """A detector's heatmaps of a dataset's frames; ``levels``: its per-level maps (classes, levels, h, w), for
    scale-selected back-projection (a detector with a pyramid of window filters: ``level_heatmaps``)."""

    def __init__(self, dataset, spec: str, workdir: Path, levels: bool = False):
        from semloc_core.detection.config import build_detector
        from semloc_core.io.detector_models import load_detector_config

        config = dict(DETECTORS[spec]) if spec in DETECTORS else dict(load_detector_config(spec))
        if "templates" in config:   # a template library of the dataset (a trained model brings its own)
            root = Path(dataset.path) if getattr(dataset, "path", None) else self._write_exemplars(dataset, workdir)
            config["templates"] = str(root / config["templates"])
        self.detector = build_detector(config)
        self.classes = tuple(self.detector.classes)
        self.dataset = dataset
        self.config = config
        self.levels = levels
        self.scales = None
        if levels:
            if not hasattr(self.detector, "level_heatmaps"):
                raise ValueError(f"--scale-depth needs a detector with pyramid levels (kind: linear), not {spec!r}")
            self.scales = tuple(self.detector.model.scales)

    @staticmethod
    def _write_exemplars(dataset, workdir: Path) -> Path:
        from semloc_core.io.dataset import write_exemplar_folder, write_multiview_folder

        write_exemplar_folder(workdir / "exemplars", dataset.exemplars(), dataset.exemplar_masks())
        write_multiview_folder(workdir / "exemplars_multiview", dataset.multiview_exemplars())
        return workdir

    def __call__(self, i: int) -> np.ndarray:
        image = self.dataset.image(i)
        return self.detector.level_heatmaps(image) if self.levels else self.detector.heatmaps(image)


def detector_cache_name(spec: str) -> str:
    """The heatmap cache's name for a detector: a named configuration's name; for a configuration file, its stem
    and a digest of its bytes and of the model file it names, so that two trained models' ``detector.yaml`` (or
    a retrained model) never share cached heatmaps."""
    if spec in DETECTORS:
        return spec
    from semloc_core.io.detector_models import load_detector_config

    path = Path(spec)
    digest = hashlib.sha1(path.read_bytes())
    model = load_detector_config(path).get("model")
    if isinstance(model, str) and Path(model).is_file():
        digest.update(Path(model).read_bytes())
    return f"{path.stem}-{digest.hexdigest()[:10]}"


class CachedHeatmaps:
    """A heatmap source's frames computed once, stored as float16 ``.npz`` (no pickle) and replayed. The detector
    takes most of an evaluation's time; with the cache every accumulation and extraction setting is compared on
    the very same heatmaps. ``make_source()`` builds the real source only when the file is missing or was made
    for other frames."""

    def __init__(self, make_source, path: Path, frames: list[int], log):
        self.frames = {int(i): n for n, i in enumerate(frames)}
        self.config = None
        if path.exists():
            with np.load(path, allow_pickle=False) as data:
                if [int(i) for i in data["frames"]] == [int(i) for i in frames]:
                    self.stack = data["heatmaps"]
                    self.classes = tuple(str(c) for c in data["classes"])
                    self.config = json.loads(str(data["config"]))
                    self.scales = tuple(float(s) for s in data["scales"]) if "scales" in data else None
                    log(f"  heatmaps from the cache {path}")
                    return
        source = make_source()
        self.classes, self.config = source.classes, getattr(source, "config", None)
        self.scales = getattr(source, "scales", None)
        start = time.perf_counter()
        self.stack = np.stack([np.asarray(source(i), np.float32).astype(np.float16) for i in frames])
        self.seconds_per_frame = (time.perf_counter() - start) / max(len(frames), 1)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(path.name + ".part.npz")
        np.savez(partial, heatmaps=self.stack, frames=np.asarray(frames, np.int64),
                 classes=np.asarray(self.classes), config=json.dumps(self.config),
                 **({} if self.scales is None else {"scales": np.asarray(self.scales, np.float64)}))
        partial.replace(path)

    def __call__(self, i: int) -> np.ndarray:
        return self.stack[self.frames[int(i)]].astype(np.float32)


# ---------------------------------------------------------------------------------------------------- one scene


# Uncalibrated thresholds: oracle heat is 0..1 with objects near 1; detector heat as surprisal averages 1 per view
# on background and 4-7 on objects (docs/mapping.md).
DEFAULT_THRESHOLDS = {"oracle": 0.5, "detector": 3.0}
DETECTOR_BACKGROUND = "surprisal"


def map_scene(dataset, source, grid, frames, downsample: int, background: str, log, llr: dict | None = None,
              scale_depth: dict | None = None, level_reach: int = 0,
              occlusion_margin: float | None = None) -> tuple[object, dict]:
    """Map ``frames`` of a scene; ``scale_depth`` (from ``fit_scale_depth``): the source gives per-level maps,
    back-projected scale-selected. ``occlusion_margin``: integrate each frame with its depth image (hidden voxels
    unseen)."""
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


def depth_image(dataset, i: int) -> np.ndarray:
    """Frame ``i``'s depth along the optical axis (H, W) float32, from a scene rendered on the fly (its render gives
    the range along each pixel's ray); dataset folders hold no depth."""
    render = getattr(dataset, "render", None)
    if render is None:
        raise ValueError("--occlusion needs depth images: here only DATASET 'tabletop' (rendered on the fly) has them")
    from semloc_core.camera import pixel_grid

    rays = dataset.camera.rays_cam(*pixel_grid(dataset.camera))  # unit rays: range x their z = depth along the axis
    return (render(i)[0].depth * rays[..., 2]).astype(np.float32)


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


def score_scene(mapper, truth, extraction, distance: float, min_size: float, objects=None) -> dict:
    """Figures of one extracted map against the ground truth (``objects``: already extracted with
    ``extraction``)."""
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


def top_view_png(mapper, truth, predicted, title: str) -> bytes:
    """Per class: max over height of the score volume, ground truth (circles) and extracted objects (crosses)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classes = mapper.class_names
    fig, axes = plt.subplots(1, len(classes), figsize=(3.2 * len(classes), 3.4), squeeze=False)
    lo, hi = mapper.grid.bounds
    for c, (name, ax) in enumerate(zip(classes, axes[0])):
        score = mapper.score_volume(c, normalise=True, min_views=10).max(axis=0)
        ax.imshow(score, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="magma")
        gt = truth.positions[truth.class_index == truth.class_names.index(name)] if name in truth.class_names else []
        for p in gt:
            ax.add_patch(plt.Circle(p[:2], 0.05, fill=False, color="cyan", lw=1.2))
        for o in predicted:
            if o["class"] == name:
                ax.plot(*o["position"][:2], "x", color="lime" if o["match"] >= 0 else "red", ms=8, mew=2)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()


# ---------------------------------------------------------------------------------------------------- run


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


MODES = {"normalised": True, "sum": False}
SWEEP = np.round(np.arange(0.3, 1.21, 0.05), 2)


def extraction_for(calibration: dict, source: str, mode: str, args, support: tuple | None = None
                   ) -> tuple[object, dict]:
    """The ExtractionConfig of one heatmap source and score mode: calibrated values, else the defaults."""
    from semloc_core.mapping import ExtractionConfig
    from semloc_core.mapping.existence import ExistenceCurve

    entry = calibration.get(source, {}).get(mode, {})
    threshold = args.threshold if args.threshold is not None else entry.get("threshold", DEFAULT_THRESHOLDS[source])
    settings = {"threshold": float(threshold), "class_scales": entry.get("class_scales", {}),
                "cross_class": bool(entry.get("cross_class", False)), "tophat": float(entry.get("tophat", 0.0)),
                "min_views": args.min_views, "calibrated": bool(entry)}
    support_z, support_polygon = support or (None, None)
    settings["support_z"] = support_z
    settings["support_polygon"] = None if support_polygon is None else np.asarray(support_polygon).tolist()
    settings["position"] = args.position
    settings["resting"] = bool(entry.get("resting", False)) and support_z is not None
    settings["prominence"] = args.prominence
    existence = ExistenceCurve.from_document(entry["existence"]) if "existence" in entry else None
    settings["existence"] = None if existence is None else existence.to_document()
    return ExtractionConfig(threshold=settings["threshold"], normalise=MODES[mode], min_views=args.min_views,
                            class_sizes=TABLETOP_SIZES, class_scales=settings["class_scales"],
                            cross_class=settings["cross_class"], tophat=settings["tophat"],
                            support_z=support_z, support_polygon=support_polygon, position=args.position,
                            mode_bandwidth=args.mode_bandwidth, resting=settings["resting"],
                            prominence=args.prominence, existence=existence), settings


def fit_extraction(mapper, truth, *, normalise: bool, min_views: int, distance: float, min_size: float,
                   position: str, mode_bandwidth: float = 0.02, support: tuple | None = None,
                   class_sizes: dict = TABLETOP_SIZES, prominence: float = 0.0) -> dict:
    """Class scales, threshold, top-hat, cross-class suppression and resting heights that maximise F1 (then
    fewest false positives) on this scene - run it on a calibration scene, never on the scenes evaluated. Used by
    ``--calibrate-out`` and by the demo's world (services/demo_world.py); ``support`` = (height, outline)."""
    from semloc_core.mapping import ExtractionConfig
    from semloc_core.mapping.extraction import calibrate_class_scales, extract_with, white_tophat

    support_z, support_polygon = support or (None, None)
    raw = {name: mapper.score_volume(name, normalise=normalise, min_views=min_views)
           for name in mapper.class_names}
    results = []
    for tophat in (0.0, 2.0):
        scores = raw if not tophat else {name: white_tophat(volume, class_sizes[name], mapper.grid.voxel_size,
                                                            tophat) for name, volume in raw.items()}
        scales = calibrate_class_scales(scores, mapper.grid, truth, radius=distance)
        scaled = {name: volume / np.float32(scales.get(name, 1.0)) for name, volume in scores.items()}
        for cross_class, resting in itertools.product((False, True), (False, True) if support_z is not None
                                                      else (False,)):
            for threshold in SWEEP:
                config = ExtractionConfig(threshold=float(threshold), normalise=normalise,
                                          min_views=min_views, class_sizes=class_sizes, class_scales=scales,
                                          cross_class=cross_class, tophat=tophat, support_z=support_z,
                                          support_polygon=support_polygon, position=position,
                                          mode_bandwidth=mode_bandwidth, resting=resting, prominence=prominence)
                # The same objects as mapper.extract(config), from the volumes computed once per top-hat.
                objects = extract_with(scaled, mapper.grid, config)
                scored = score_scene(mapper, truth, config, distance, min_size, objects)
                f1 = 2 * scored["tp"] / max(2 * scored["tp"] + scored["fp"] + scored["fn"], 1)
                results.append(((round(f1, 9), -scored["fp"]), (tophat, cross_class, resting), float(threshold),
                                scored, scales))
    best = max(r[0] for r in results)
    # Several thresholds often tie: take the middle of the best plateau, not its edge, so that the choice
    # carries over to other scenes; of the settings reaching the best, the one with the widest plateau, then the
    # smallest mean position error at the plateau's middle (resting heights or not, when both find the same).
    plateaus = {k: [r for r in results if r[0] == best and r[1] == k] for k in {r[1] for r in results if r[0] == best}}

    def mean_error(plateau: list) -> float:
        error = plateau[len(plateau) // 2][3]["mean_error_3d_m"]
        return math.inf if error is None else error

    setting = max(sorted(plateaus), key=lambda k: (len(plateaus[k]), -mean_error(plateaus[k])))
    plateau = plateaus[setting]
    chosen = plateau[len(plateau) // 2]
    scored = chosen[3]
    return {"threshold": chosen[2], "tophat": setting[0], "cross_class": setting[1], "resting": setting[2],
            "class_scales": chosen[4], "class_sizes": {name: list(size) for name, size in class_sizes.items()},
            "f1": best[0], "tp": scored["tp"], "fp": scored["fp"], "fn": scored["fn"],
            "mean_error_3d_m": scored["mean_error_3d_m"], "plateau": [r[2] for r in plateau]}


def run(args: argparse.Namespace) -> int:
    from semloc_core.eval.report import json_text, markdown_table
    from semloc_core.io.semantic_map import save_semantic_map

    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.stride < 1 or args.voxel_size <= 0:
        _log("semloc eval mapping: --stride must be >= 1 and --voxel-size > 0")
        return 2
    if not 0 <= args.prominence < 1:
        _log("semloc eval mapping: --prominence must be a fraction in [0, 1)")
        return 2
    if args.level_reach < 0:
        _log("semloc eval mapping: --level-reach must be >= 0")
        return 2
    if not (np.isfinite(args.occlusion_margin) and args.occlusion_margin >= 0):
        _log("semloc eval mapping: --occlusion-margin must be a finite distance >= 0 (metres)")
        return 2
    if args.localize_seeds < 1 or args.localize_noise_draws < 0:
        _log("semloc eval mapping: --localize-seeds must be >= 1 and --localize-noise-draws >= 0")
        return 2
    if args.dataset != "tabletop" and args.occlusion:
        _log("semloc eval mapping: --occlusion needs depth images: here only DATASET 'tabletop' (rendered on the "
             "fly) has them")
        return 2
    if args.dataset != "tabletop" and (args.trajectory or args.localize):
        _log("semloc eval mapping: --trajectory and --localize need DATASET 'tabletop'")
        return 2
    if args.localize and args.localize_observations == "detector":
        missing = [t for t in localization_calibration_trajectories(args) if not Path(t).is_file()]
        if missing:
            _log(f"semloc eval mapping: --localize-observations detector: calibration trajectories not found: "
                 f"{missing} (--localize-calibration-trajectories)")
            return 2
    if args.scale_depth:
        problem = None
        if args.heatmaps == "oracle":
            problem = "--scale-depth needs detector heatmaps"
        elif args.accumulate == "llr":
            problem = "--scale-depth and --accumulate llr do not combine (the ratios are fitted on single maps)"
        else:
            try:
                from semloc_core.io.detector_models import load_detector_config

                kind = (DETECTORS.get(args.detector) or load_detector_config(args.detector)).get("kind")
            except (OSError, ValueError) as error:
                kind, problem = None, f"cannot read --detector {args.detector}: {error}"
            if problem is None and kind != "linear":
                problem = f"--scale-depth needs a trained window detector (kind: linear), {args.detector} is {kind!r}"
        if problem:
            _log(f"semloc eval mapping: {problem}")
            return 2
    calibration = {}
    if args.calibration:
        try:
            calibration = json.loads(Path(args.calibration).read_text())
        except (OSError, json.JSONDecodeError) as error:
            _log(f"semloc eval mapping: cannot read calibration {args.calibration}: {error}")
            return 2
    try:
        scenes = open_scenes(args, _log)
    except (OSError, ValueError, TypeError) as error:
        _log(f"semloc eval mapping: {error}")
        return 2
    sources = ["detector", "oracle"] if args.heatmaps == "both" else [args.heatmaps]
    primary = "sum" if args.no_normalise else "normalised"
    report: dict = {"dataset": args.dataset, "seed": args.seed, "stride": args.stride,
                    "voxel_size_m": args.voxel_size, "distance_m": args.distance, "min_size_m": args.min_size,
                    "min_views": args.min_views, "detector": args.detector if "detector" in sources else None,
                    "calibration_file": args.calibration, "primary_mode": primary,
                    "occlusion_margin_m": args.occlusion_margin if args.occlusion else None,
                    "bounding_volumes": TABLETOP_SIZES, "scenes": {}, "summary": {}}
    rows = []
    fitted: dict = {}
    mapped_for_localization = None
    stem = out.with_suffix("").name
    with tempfile.TemporaryDirectory(prefix="semloc-eval-mapping-") as tmp:
        def detector_source(name, dataset, frames):
            workdir = Path(tmp) / name
            workdir.mkdir(exist_ok=True)
            make = lambda: DetectorHeatmaps(dataset, args.detector, workdir, levels=args.scale_depth)  # noqa: E731
            if not args.heatmap_cache and args.accumulate == "heat" and not args.scale_depth:
                return make()
            # Fitting likelihood ratios reads every frame's heatmaps before mapping: keep them (in the temporary
            # folder unless a cache is given) rather than running the detector twice.
            key = (f"{name}_seed{dataset.metadata.get('seed_used')}_{detector_cache_name(args.detector)}"
                   f"_stride{args.stride}_{len(frames)}frames{'_levels' if args.scale_depth else ''}.npz")
            return CachedHeatmaps(make, Path(args.heatmap_cache or tmp) / key, frames, _log)

        llr = None
        if "detector" in sources and args.accumulate == "llr":
            llr = calibration.get("detector", {}).get("llr")
            if args.calibrate_out:
                llr = fit_scene_llr(scenes, args, detector_source)
            if not llr:
                _log("semloc eval mapping: --accumulate llr needs --calibrate-out or a --calibration with 'llr'")
                return 2
            fitted["llr"] = llr
        scale_depth = None
        if "detector" in sources and args.scale_depth:
            scale_depth = calibration.get("detector", {}).get("scale_depth")
            try:
                if args.calibrate_out:
                    scale_depth = fit_scale_depth(scenes, args, detector_source)
            except ValueError as error:
                _log(f"semloc eval mapping: {error}")
                return 2
            if not scale_depth:
                _log("semloc eval mapping: --scale-depth needs --calibrate-out or a --calibration with 'scale_depth'")
                return 2
            fitted["scale_depth"] = scale_depth
            report["scale_depth"] = scale_depth
        mapped = []  # (name, dataset, source name, mapper, results, support, fits per mode)
        for name, dataset in scenes:
            if dataset.semantic_map is None or not dataset.has_poses or not dataset.has_images:
                _log(f"semloc eval mapping: {name} lacks images, poses or a ground-truth map")
                return 2
            grid = table_grid(dataset, args.voxel_size, args.grid_min, args.grid_max)
            frames = list(range(0, len(dataset), args.stride))
            support = table_support(dataset) if args.support == "table" else None
            report["scenes"][name] = {"frames_total": len(dataset), "frames_used": len(frames),
                                      "grid": grid.to_document(), "seed": dataset.metadata.get("seed_used"),
                                      "sources": {}}
            save_semantic_map(dataset.semantic_map, out.with_name(f"{stem}_{name}_truth.json"))
            for source_name in sources:
                if source_name == "detector":
                    source = detector_source(name, dataset, frames)
                    report["scenes"][name]["detector_config"] = source.config
                else:
                    source = OracleHeatmaps(dataset, dataset.semantic_map.class_names)
                scene_llr = llr if source_name == "detector" else None
                background = args.background or (DETECTOR_BACKGROUND if source_name == "detector" and not scene_llr
                                                 else "none")
                _log(f"scene {name}: mapping {len(frames)} frames with {source_name} heatmaps into {grid}")
                try:
                    mapper, timing = map_scene(dataset, source, grid, frames, args.heatmap_downsample, background,
                                               _log, scene_llr, scale_depth if source_name == "detector" else None,
                                               args.level_reach,
                                               args.occlusion_margin if args.occlusion else None)
                except ValueError as error:  # a calibration of another detector, no depth images
                    _log(f"semloc eval mapping: {error}")
                    return 2
                results = {"timing": timing, "background": background, "accumulate": "llr" if scene_llr else "heat"}
                fits = {}
                if args.calibrate_out or args.leave_one_out:
                    fits = {mode: fit_extraction(mapper, dataset.semantic_map, normalise=normalise,
                                                 min_views=args.min_views, distance=args.distance,
                                                 min_size=args.min_size, position=args.position,
                                                 mode_bandwidth=args.mode_bandwidth, support=support,
                                                 prominence=args.prominence)
                            for mode, normalise in MODES.items()}
                    for mode, fit in fits.items():
                        fitted.setdefault(source_name, {}).setdefault(mode, []).append(fit)
                mapped.append((name, dataset, source_name, mapper, results, support, fits))
                if args.save_volumes:
                    from semloc_core.io.voxel_map import save_ply, save_voxel_snapshot

                    save_voxel_snapshot(out.with_name(f"{stem}_{name}_{source_name}.npz"), mapper.snapshot())
                    cloud = mapper.hot_voxels(0.5, min_views=args.min_views)
                    save_ply(out.with_name(f"{stem}_{name}_{source_name}_hot.ply"), cloud["points"], cloud["colors"],
                             {"score": cloud["score"], "class_index": cloud["class_index"]})
        for name, dataset, source_name, mapper, results, support, _ in mapped:
            for mode in MODES:
                scene_calibration = calibration
                if args.leave_one_out:
                    # Fitted on every other scene of this run, never on the one evaluated.
                    others = [fits[mode] for other, _, s, _, _, _, fits in mapped if s == source_name and other != name]
                    scene_calibration = {source_name: {mode: merge_extraction_fits(others)}}
                extraction, settings = extraction_for(scene_calibration, source_name, mode, args, support)
                scored = score_scene(mapper, dataset.semantic_map, extraction, args.distance, args.min_size)
                predicted_map = scored.pop("predicted_map")
                results[mode] = {"extraction": settings, **scored}
                if mode != primary:
                    continue
                save_semantic_map(predicted_map, out.with_name(f"{stem}_{name}_{source_name}_objects.json"))
                out.with_name(f"{stem}_{name}_{source_name}.png").write_bytes(
                    top_view_png(mapper, dataset.semantic_map, scored["predicted"],
                                 f"{name}, {source_name} heatmaps ({mode})"))
                rows.append({"scene": name, "heatmaps": source_name, "score": mode,
                             "large found": f"{scored['large_found']}/{scored['large_objects']}",
                             "FP": scored["fp"], "precision": round(scored["precision"], 3),
                             "recall": round(scored["recall"], 3),
                             "mean err 3-D (cm)": None if scored["mean_error_3d_m"] is None else
                             round(100 * scored["mean_error_3d_m"], 1)})
                if source_name == (args.localize_source or sources[0]) and mapped_for_localization is None:
                    mapped_for_localization = (name, dataset, predicted_map)
            report["scenes"][name]["sources"][source_name] = results
    report["summary"] = {mode: summarise(report, sources, mode) for mode in MODES}
    if args.calibrate_out:
        merged = {source: {mode: merge_extraction_fits(fits) for mode, fits in modes.items()}
                  for source, modes in fitted.items()
                  if source not in ("llr", "scale_depth")}
        for source, modes in merged.items():
            for mode in modes:
                curve = fit_scene_existence(
                    [(dataset, mapper, support) for _, dataset, s, mapper, _, support, _ in mapped if s == source],
                    merged, source, mode, args)
                if curve is not None:
                    modes[mode]["existence"] = curve.to_document()
        for key in ("llr", "scale_depth"):
            if key in fitted:
                merged.setdefault("detector", {})[key] = fitted[key]
        Path(args.calibrate_out).write_text(json.dumps(merged, indent=2) + "\n")
        report["calibration_fitted"] = merged
    if args.localize:
        report["closing_the_loop"] = close_the_loop(mapped_for_localization, args, _log)
    out.write_text(json_text(report))
    table = markdown_table(rows, ["scene", "heatmaps", "score", "large found", "FP", "precision", "recall",
                                  "mean err 3-D (cm)"])
    out.with_suffix(".md").write_text(table + "\n")
    print(table)
    return 0


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


def fit_scale_depth(scenes, args, detector_source) -> dict:
    """Each class's depth per scale (semloc_core.mapping.scale_depth) pooled over ``scenes`` (calibration
    scenes)."""
    from semloc_core.mapping.scale_depth import fit_depth_per_scale

    pooled: dict = {}
    scales = None
    for name, dataset in scenes:
        frames = list(range(0, len(dataset), args.stride))
        source = detector_source(name, dataset, frames)
        scales = source.scales
        for key, values in scale_depth_samples(dataset, source, frames).items():
            pooled.setdefault(key, []).extend(values)
        _log(f"scene {name}: scale-depth samples " + ", ".join(f"{k} {len(v)}" for k, v in pooled.items()))
    empty = [k for k, v in pooled.items() if not v]
    if empty:
        raise ValueError(f"no well-seen object of {empty} answered on the calibration scenes: cannot fit their "
                         f"depth per scale")
    return {"scales": list(scales), "classes": {k: fit_depth_per_scale(*zip(*v)) for k, v in pooled.items()}}


def fit_scene_llr(scenes, args, detector_source) -> dict:
    """Per-class heat log-likelihood ratios pooled over ``scenes`` (calibration scenes)."""
    from semloc_core.mapping.likelihood import fit_heat_llr

    positives: dict = {}
    negatives: dict = {}
    for name, dataset in scenes:
        frames = list(range(0, len(dataset), args.stride))
        pos, neg = llr_samples(dataset, detector_source(name, dataset, frames), frames)
        for key, samples in pos.items():
            positives.setdefault(key, []).extend(samples)
        for key, samples in neg.items():
            negatives.setdefault(key, []).extend(samples)
        _log(f"scene {name}: heat samples " + ", ".join(f"{k} {sum(map(len, v))}+/{sum(map(len, negatives[k]))}-"
                                                         for k, v in pos.items()))
    return fit_heat_llr(positives, negatives)


def fit_scene_existence(scenes, calibration: dict, source: str, mode: str, args):
    """The existence curve (semloc_core.mapping.existence) of the merged extraction: every candidate down to
    SAMPLE_FLOOR of its threshold in the calibration scenes, real when it matches a ground-truth object (None
    without any candidate)."""
    from semloc_core.mapping.existence import SAMPLE_FLOOR, fit_existence

    scores, real, threshold = [], [], None
    for dataset, mapper, support in scenes:
        extraction, settings = extraction_for(calibration, source, mode, args, support)
        threshold = settings["threshold"]
        scored = score_scene(mapper, dataset.semantic_map, replace(extraction, threshold=SAMPLE_FLOOR * threshold),
                             args.distance, args.min_size)
        scores += [p["score"] for p in scored["predicted"]]
        real += [p["match"] >= 0 for p in scored["predicted"]]
    if not scores:
        _log(f"existence ({source}, {mode}): no candidate in the calibration scenes - objects stay certain")
        return None
    curve = fit_existence(scores, real, threshold)
    _log(f"existence ({source}, {mode}): {curve.samples} candidates >= {SAMPLE_FLOOR} x threshold, {curve.real} "
         f"real; p(real) = {curve(threshold)[()]:.2f} at the threshold, {curve(1.25 * threshold)[()]:.2f} at 1.25 x")
    return curve


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


def scenario_along(scene, trajectory, frames: int | None = None, margin: float = 0.15):
    """The world of ``scene`` (a tabletop Scenario) seen along another real hand-held ``trajectory`` (N, 4, 4):
    levelled as the simulator levels it, then turned and moved so that the table it looked at lands on this
    scene's table. Of the two orientations (a table's axes have no sign) the one keeping every camera outside the
    table by ``margin`` and farthest from it is taken; ValueError when neither does."""
    from semloc_core.geometry import invert_transform, level_frame_of_camera, make_transform, rotation_about_z
    from semloc_core.io.trajectory import level_real_trajectory
    from semloc_core.sim.scenario import Scenario

    table = scene.metadata["table"]
    T_cam, own = level_real_trajectory(np.asarray(trajectory, float), float(table["surface_z"]))
    if frames is not None:
        T_cam = T_cam[:frames]
    heading = lambda axes: float(np.arctan2(axes[1, 0], axes[0, 0]))  # noqa: E731
    centre, axes, half = (np.asarray(table[k], float) for k in ("centre", "axes", "half_extent"))
    best = None
    for flip in (0.0, np.pi):
        turn = rotation_about_z(heading(axes) - heading(np.asarray(own["axes"], float)) + flip)
        move = make_transform(turn, np.r_[centre, 0.0]) @ make_transform(np.eye(3), np.r_[-np.asarray(own["centre"]),
                                                                                              0.0])
        placed = move @ T_cam
        local = np.abs((placed[:, :2, 3] - centre) @ axes) - half
        clearance = float(np.max(local, axis=1).min())
        if best is None or clearance > best[0]:
            best = (clearance, placed)
    if best[0] < margin:
        raise ValueError(f"the trajectory passes {best[0]:.2f} m from this table's edge (needs {margin} m)")
    T_world_cam = best[1]
    T_world_body = np.stack([level_frame_of_camera(T) for T in T_world_cam])
    T_body_cam = invert_transform(T_world_body) @ T_world_cam
    stamps = np.round(np.arange(len(T_world_cam)) / 30.0 * 1e9).astype(np.int64)
    return Scenario("tabletop", scene.world, scene.camera, T_world_body, T_body_cam, stamps, scene.seed,
                    options=dict(scene.options), realism=scene.realism, loop=scene.loop_settings,
                    odometry_noise=scene.odometry_noise, lighting=scene.base_lighting,
                    exemplar_settings=scene.exemplar_settings, exemplar_builders=scene._exemplar_builders,
                    metadata={**scene.metadata, "placed_clearance_m": best[0]})


class _WithMap:
    """A dataset whose object map is replaced (the localizer reads ``semantic_map``)."""

    def __init__(self, dataset, semantic_map):
        self._dataset = dataset
        self.semantic_map = semantic_map

    def __getattr__(self, name):
        return getattr(self._dataset, name)

    def __len__(self) -> int:
        return len(self._dataset)


def localization_calibration_trajectories(args) -> list[str]:
    """The calibration worlds' trajectories of ``--localize-observations detector``: the option's, else RGB-D
    Scenes v2 06, 11 and 12 beside the ``--localize`` trajectory (the worlds semloc eval localization's table-top
    figures are calibrated on; docs/localization.md)."""
    return list(args.localize_calibration_trajectories or [
        str(Path(args.localize).with_name(f"{scene}.pose")) for scene in ("06", "11", "12")])


def detector_observations(other, world: str, indices, args, log) -> dict:
    """The template detector's heatlines of ``other``'s ``indices``, the score likelihoods (model B) and bearing
    model (σ, exponent) fitted on simulated calibration worlds, and what the detector can see (``view_geometry``
    down to its usable size): exactly what ``semloc eval localization sim:tabletop --sources detector`` uses, so the
    two evaluations' detector runs are comparable. Calibration and heatlines are cached in ``--heatmap-cache``."""
    from semloc_core.detection.calibration import decision_threshold
    from semloc_core.localization import ScoreLikelihood
    from semloc_core.localization.experiment import view_geometry
    from services.commands import eval_localization as localization

    trajectories = localization_calibration_trajectories(args)
    parser = argparse.ArgumentParser()
    localization.add_arguments(parser)
    options = parser.parse_args(["sim:tabletop", "--json", "-", "--sources", "detector", "--seed", str(args.seed),
                                 "--scenario-seed", str(args.seed), "--calibration-trajectories",
                                 ",".join(trajectories)] + (["--cache", args.heatmap_cache] if args.heatmap_cache
                                                            else []))
    calibration, description = localization.detector_calibration(options, log, None)
    if missing := sorted(set(other.semantic_map.class_names) - set(calibration.classes)):
        raise ValueError(f"the calibration worlds hold no {missing}: give --localize-calibration-trajectories whose "
                         f"worlds do")
    likelihood = ScoreLikelihood.from_calibration(calibration)
    thresholds = {c: decision_threshold(calibration, c) for c in calibration.classes}
    bearing = localization.fitted_bearing_model(options, "detector", likelihood, thresholds, log, None)
    cache = (Path(args.heatmap_cache) / f"loop_{Path(args.localize).stem}_in_{world}_seed{args.seed}"
             f"_detector_heatlines.npz") if args.heatmap_cache else None
    key = f"{localization.fingerprint(other)} {sorted(localization.DETECTOR_SETTINGS.items())}"
    heatlines = localization.cached_heatlines(
        cache, indices, lambda: localization.detector_heatlines(other, indices, log, None), key)
    views = {i: view_geometry(other, i, 360, localization.DETECTOR_MIN_PIXELS) for i in indices}
    return {"heatlines": heatlines, "likelihood": likelihood, "bearing": bearing, "views": views,
            "calibration": description}


def close_the_loop(mapped, args, log) -> dict:
    """Localize another trajectory in the mapped world with the mapped objects and with the ground-truth map: the
    same observations (synthetic heatlines from the ground-truth boxes, §4.8.3, or with ``--localize-observations
    detector`` the template detector's heatlines, ``detector_observations``), sequence and filter seeds."""
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
        other = scenario_along(scene, read_trajectory(Path(args.localize))[1], args.localize_frames)
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
    sequence = make_sequence(other, args.localize_stride)
    indices = [int(i) for i in sequence.indices]
    log(f"closing the loop: localizing {Path(args.localize).stem} ({len(indices)} frames) in the world of {name}")
    classes = truth.class_names
    if args.localize_observations == "detector":
        try:
            observed = detector_observations(other, name, indices, args, log)
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
    map_from = args.localize_source or ("oracle" if args.heatmaps == "oracle" else "detector")
    result = {"mapped_scene": name, "map_from": map_from, "trajectory": Path(args.localize).stem,
              "frames": len(indices),
              "stride": args.localize_stride, "observations": observations, "bearing_model": bearing_model,
              "placed_clearance_m": other.metadata["placed_clearance_m"], "objects_truth": len(truth),
              "objects_mapped": len(mapped_map), "runs": {}}
    maps = {"truth": truth, "mapped": mapped_map}
    if args.localize_noise_draws > 0:
        # Random planar errors with the mapped objects' RMS error (matched within --distance), one map per draw.
        figures = object_map_figures(
            [mapped_map.class_names[k] for k in mapped_map.class_index], mapped_map.positions,
            [truth.class_names[k] for k in truth.class_index], truth.positions, args.distance, planar=False)
        matched = [(p, g) for p, g in enumerate(figures["matches"]) if g >= 0]
        rms = float(np.sqrt(np.mean([np.sum((mapped_map.positions[p, :2] - truth.positions[g, :2]) ** 2)
                                     for p, g in matched]))) if matched else 0.0
        result["noise_reference"] = {"planar_rms_error_m": rms, "draws": args.localize_noise_draws}
        rng = np.random.default_rng(args.seed)
        for draw in range(args.localize_noise_draws):
            moved = truth.positions.copy()
            moved[:, :2] += rng.normal(0.0, rms / np.sqrt(2.0), (len(truth), 2))  # per axis: planar RMS / sqrt 2
            maps[f"noise{draw}"] = room_map(truth, moved)
    for model in ("A", "B"):
        likelihood = likelihood_b if model == "B" else None
        for map_name, semantic_map in maps.items():
            runs = []
            for seed in range(args.seed, args.seed + args.localize_seeds):
                spec = RunSpec(model, likelihood, init="global", seed=seed,
                               exponent=exponent_b if model == "B" else 1.0, view=True)
                trace = run_sequence(_WithMap(other, semantic_map), sequence, heatlines, preset, spec,
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
        if args.localize_noise_draws > 0:
            result["noise_reference"][f"ratios_{model}"] = [ratio(f"noise{d}") for d in
                                                            range(args.localize_noise_draws)]
    return result


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="semloc eval mapping", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
