"""The demo's world: a simulated table top, generated once and cached, plus what the workers need to run on it.

``semloc demo`` plays a ``tabletop`` scenario (docs/demo.md explains the choice): a hand-held camera walks round a
table with bowls, caps, cereal boxes, mugs and soda cans, more than once, so that

* loop closure has revisits (every lap passes the places of the previous one),
* localization has labelled objects to see and a map of them (the simulator's object map),
* mapping has objects to find in 3-D, with exact ground truth for all three.

The frame rate of the generated orbit is chosen so that ``frames`` frames cover ``laps`` laps: the walker keeps its
natural speed (0.3 m/s) and the demo plays fewer, farther-apart frames, the way a robot samples keyframes.

A world is cached under ``<cache>/worlds/<key>/`` (:func:`default_cache_dir` by default): the data set
(docs/datasets.md), the detector configuration built from its exemplars, and the detector's score likelihoods
calibrated on a second, smaller world of another seed (so nothing is fitted on the frames being evaluated), and
the mapper's extraction (class scales, threshold, top-hat, cross-class, resting heights) fitted on the same
calibration scenes as the mapping experiment fits it (``calibration.fit``). Object
appearances are the real RGB-D Object crops of the data folder (docs/datasets.md) when present, generated textures
otherwise; the key says which, so both kinds can sit in one cache.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml

WORLD_FORMAT = "semloc.demo_world"
WORLD_VERSION = 4  # 2: three calibration scenes showing the world's own objects; 3: the mapper's fitted extraction;
# 4: its threshold halfway across the gap the best F1 leaves (mapping_fits.plateau_gap)
ORBIT_SPEED = 0.3  # m/s: semloc_core.sim.trajectories.orbit_trajectory's default walking speed
CALIBRATION_SEED_OFFSET = 1000
# The score likelihoods are fitted on this many other scenes (seeds seed + 1000, + 1001, ...) with the same objects
# (design seed = the world's): with one scene, what the fit gets right depended on that scene - over calibration
# seeds the localizer's median error on the --fast world (sigma 5 deg) ranged 0.13-0.18 m, and scenes with other
# objects' designs (generated looks) gave 2 m; pooled over three, 0.10-0.13 m (docs/demo.md).
CALIBRATION_SCENES = 3
# The demo mapper's settings its extraction is fitted with: deploy/demo.yaml's mapper runs with these (a test
# checks), and the fitted file (mapper_extraction.json) sets the rest. Matched within 5 cm as semloc eval mapping.
MAPPER_SETTINGS = {"voxel_size": 0.02, "heatmap_background": "surprisal", "min_views": 5, "position": "centroid"}
MAPPER_FIT_DISTANCE = 0.05



@dataclass(frozen=True)
class WorldSpec:
    """What defines a demo world; equal specs give byte-identical worlds (the simulator is deterministic)."""

    frames: int = 300
    laps: float = 3.0
    seed: int = 0
    appearance: str = "auto"  # auto | real | generated
    calibration_frames: int = 90

    def __post_init__(self) -> None:
        if self.frames < 20:
            raise ValueError(f"a demo world needs at least 20 frames, got {self.frames}")
        if not 0.5 <= self.laps <= 20:
            raise ValueError(f"laps must be within [0.5, 20], got {self.laps}")
        if self.appearance not in ("auto", "real", "generated"):
            raise ValueError(f"appearance must be auto, real or generated, got {self.appearance!r}")
        if self.calibration_frames < 10:
            raise ValueError("calibration_frames must be at least 10")


@dataclass(frozen=True)
class World:
    """A generated world on disk and the files the graph's workers read."""

    path: Path                 # the world's folder
    dataset: Path              # the data set played by the camera (docs/datasets.md)
    detector: Path             # detector configuration YAML (templates from the data set's exemplars)
    score_likelihood: Path     # the detector's calibrated p(z|d), p(z|not d) (localizer, model B)
    mapper_extraction: Path    # the mapper's extraction fitted on the calibration scenes (its extraction_file)
    semantic_map: Path         # the ground-truth object map (the localizer's map)
    spec: WorldSpec
    appearance: str            # real | generated
    fps: float
    info: dict                 # laps, loop pairs, objects, table: what the demo prints about the world


CACHE_DIR_ENV = "SEMLOC_CACHE_DIR"


def default_cache_dir() -> Path:
    """``$SEMLOC_CACHE_DIR``, else the platform's user cache folder for semloc (``$XDG_CACHE_HOME/semloc`` or
    ``~/.cache/semloc`` on Linux, ``~/Library/Caches/semloc`` on macOS, ``%LOCALAPPDATA%\\semloc\\Cache``)."""
    import platformdirs

    return Path(os.environ.get(CACHE_DIR_ENV) or platformdirs.user_cache_path("semloc", appauthor=False))


def _crops(appearance: str):
    """(crops, clutter crops, resolved appearance) for the scenario."""
    from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops

    if appearance == "generated":
        return None, None, "generated"
    folder = default_exemplar_dir()
    if folder is None:
        if appearance == "real":
            raise FileNotFoundError("appearance 'real' needs the data folder's rgbd_object_exemplars "
                                    "(or SEMLOC_SHARED_DATA); use 'auto' or 'generated'")
        return None, None, "generated"
    crops, clutter = load_exemplar_crops(folder)
    return crops, clutter, "real"


def _resolved_appearance(appearance: str) -> str:
    from semloc_core.io.exemplars import default_exemplar_dir

    if appearance != "auto":
        return appearance
    return "real" if default_exemplar_dir() is not None else "generated"


def _orbit_radius(scenario) -> float:
    positions = scenario.poses2d[:, :2]
    centre = np.asarray(scenario.metadata["table"]["centre"], float)
    return float(np.median(np.linalg.norm(positions - centre, axis=1)))


def laps_of(poses2d: np.ndarray, centre) -> float:
    """How many times the camera went round ``centre`` (unwrapped angle / 2 pi)."""
    angle = np.unwrap(np.arctan2(poses2d[:, 1] - centre[1], poses2d[:, 0] - centre[0]))
    return float(abs(angle[-1] - angle[0]) / (2 * math.pi))


def _make(seed: int, frames: int, crops, clutter, laps: float | None = None, fps: float | None = None,
          design_seed: int | None = None):
    """A tabletop scenario whose orbit covers ``laps`` laps in ``frames`` frames (or is sampled at ``fps``), its
    objects designed by ``design_seed`` (default: ``seed``)."""
    from semloc_core.sim import make_scenario

    options = {} if crops is None else {"crops": crops, "clutter_crops": clutter}
    if design_seed is not None:
        options["design_seed"] = design_seed
    if fps is None:
        # The orbit's radius depends on the table the seed draws: build once at 30 fps to read it (cheap: frames
        # render on demand), then pick the frame rate that spreads the frames over the laps at walking speed.
        probe = make_scenario("tabletop", seed=seed, frames=frames, **options)
        lap_time = 2 * math.pi * _orbit_radius(probe) / ORBIT_SPEED
        fps = round(frames / (laps * lap_time), 3)
    return make_scenario("tabletop", seed=seed, frames=frames, fps=fps, **options), fps


def _write_scenario(scenario, folder: Path, progress: Callable[[int, int], None] | None) -> None:
    scenario.write(folder, progress=progress, multiview=False)


# The demo's detector: the thesis's single-exemplar HOGE x HQC templates (§4.3) built from the world's own
# exemplars: 4-px blocks, 9-block templates, a 4-level pyramid matching objects of 30, 42, 60 and 86 px, HSV colour.
# The finest level (an upsampled image) is half a frame's time, but the far side of the table shows objects 21-30 px
# tall: pyramids from 1.0 lost the localizer's track there, and 1.2 / 0.6 alone (0.65 of the time) found fewer
# objects on the real table-top trajectories (docs/results/2026-12-05-detector-levels.md). ``semloc calibrate``'s
# default (6-px blocks, 7-block templates, 3 scales) is ~4x faster, but on this world the localizer fed by it was
# about twice as far off (docs/demo.md).
DETECTOR = {"kind": "templates", "cell": 4, "template_cells": 9, "scales": [1.2, 0.85, 0.6, 0.42],
            "color_space": "hsv"}


def _detector_config(exemplars: Path) -> dict:
    return {**DETECTOR, "templates": str(exemplars.resolve())}


def _world_key(spec: WorldSpec, appearance: str) -> str:
    laps = f"{spec.laps:g}".replace(".", "p")
    # The detector's settings are part of the key: its calibrated likelihoods belong to them.
    settings = {k: v for k, v in _detector_config(Path(".")).items() if k != "templates"}
    digest = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:6]
    return (f"tabletop-s{spec.seed}-f{spec.frames}-l{laps}-c{spec.calibration_frames}-{appearance}-d{digest}"
            f"-v{WORLD_VERSION}")


def load_world(folder: Path) -> World:
    """A world written by :func:`ensure_world` (raises FileNotFoundError / ValueError when incomplete)."""
    meta_path = folder / "world.json"
    meta = json.loads(meta_path.read_text())
    if meta.get("format") != WORLD_FORMAT or meta.get("version") != WORLD_VERSION:
        raise ValueError(f"{meta_path}: not a {WORLD_FORMAT} v{WORLD_VERSION} file")
    world = World(path=folder, dataset=folder / "dataset", detector=folder / "detector.yaml",
                  score_likelihood=folder / "score_likelihood.json",
                  mapper_extraction=folder / "mapper_extraction.json",
                  semantic_map=folder / "dataset" / "semantic_map.json", spec=WorldSpec(**meta["spec"]),
                  appearance=meta["appearance"], fps=float(meta["fps"]), info=meta["info"])
    for path in (world.dataset / "dataset.json", world.detector, world.score_likelihood, world.mapper_extraction,
                 world.semantic_map):
        if not path.is_file():
            raise FileNotFoundError(f"incomplete world {folder}: {path.name} is missing")
    # The detector file names the exemplar folder by absolute path: follow the world if the cache moved.
    config = yaml.safe_load(world.detector.read_text())
    if Path(config.get("templates", "")) != (world.dataset / "exemplars").resolve():
        world.detector.write_text(yaml.safe_dump(_detector_config(world.dataset / "exemplars"), sort_keys=False))
    return world


def ensure_world(spec: WorldSpec, cache_dir: Path | None = None,
                 log: Callable[[str], None] = print,
                 progress: Callable[[str, int, int], None] | None = None) -> World:
    """The world of ``spec``: from the cache if it is there, else generated (data set, detector, calibration)."""
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    appearance = _resolved_appearance(spec.appearance)
    folder = cache_dir / "worlds" / _world_key(spec, appearance)
    if (folder / "world.json").is_file():
        try:
            world = load_world(folder)
            log(f"world: {folder} (cached)")
            return world
        except (OSError, ValueError, KeyError, TypeError) as error:
            log(f"world: cache entry {folder} unusable ({error}); generating it again")
            shutil.rmtree(folder, ignore_errors=True)
    started = time.monotonic()
    crops, clutter, appearance = _crops(appearance)
    log(f"world: generating {spec.frames} frames of tabletop (seed {spec.seed}, {appearance} object appearances) "
        f"into {folder}")
    # Written into a temporary sibling and renamed at the end: an interrupted run never leaves a half world that a
    # later run would take for complete.
    folder.parent.mkdir(parents=True, exist_ok=True)
    partial = folder.parent / f".{folder.name}.{os.getpid()}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        scenario, fps = _make(spec.seed, spec.frames, crops, clutter, laps=spec.laps)
        _write_scenario(scenario, partial / "dataset",
                        None if progress is None else (lambda done, total: progress("render", done, total)))
        calibration_seeds = [spec.seed + CALIBRATION_SEED_OFFSET + k for k in range(CALIBRATION_SCENES)]
        likelihoods, extraction = _calibrate(partial, calibration_seeds, spec, crops, clutter, fps, progress)
        from semloc_core.io.calibration import save_score_likelihoods

        save_score_likelihoods(likelihoods, partial / "score_likelihood.json")
        (partial / "mapper_extraction.json").write_text(json.dumps(extraction, indent=2) + "\n")
        fitted = extraction["detector"]["normalised"]
        log(f"world: mapper extraction fitted on {len(fitted['fits'])} calibration scenes: threshold "
            f"{fitted['threshold']:g}, top-hat {fitted['tophat']:g}, cross-class {fitted['cross_class']}, resting "
            f"{fitted['resting']} (F1 per scene " + ", ".join(f"{f['f1']:.2f}" for f in fitted["fits"]) + ")")
        (partial / "detector.yaml").write_text(yaml.safe_dump(_detector_config(folder / "dataset" / "exemplars"),
                                                              sort_keys=False))
        info = _world_info(scenario, fps, calibration_seeds)
        meta = {"format": WORLD_FORMAT, "version": WORLD_VERSION, "spec": asdict(spec), "appearance": appearance,
                "fps": fps, "info": info, "generated_s": round(time.monotonic() - started, 1)}
        (partial / "world.json").write_text(json.dumps(meta, indent=2) + "\n")
        if folder.exists():  # another process finished the same world meanwhile: keep theirs
            shutil.rmtree(partial, ignore_errors=True)
        else:
            partial.rename(folder)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    world = load_world(folder)
    log(f"world: ready in {time.monotonic() - started:.0f} s")
    return world


class _RecordingDetector:
    """The detector, keeping every frame's heatmaps in call order: the calibration's detector run also feeds the
    mapper's fit, so the detector runs once per calibration frame. Called with a frame index it replays that
    frame's heatmaps (a heatmap source for ``mapping_scene.map_scene``)."""

    def __init__(self, detector):
        self.detector = detector
        self.classes = detector.classes
        self.recorded: list[np.ndarray] = []

    def heatmaps(self, image) -> np.ndarray:
        heatmaps = self.detector.heatmaps(image)
        self.recorded.append(heatmaps)
        return heatmaps

    def __call__(self, i: int) -> np.ndarray:
        return self.recorded[i]


def _calibrate(partial: Path, seeds: list[int], spec: WorldSpec, crops, clutter, fps: float, progress):
    """Score likelihoods of the demo's detector (the world's exemplars) fitted on scenes of other seeds showing the
    world's objects elsewhere (thesis §4.8.2: fitted on other scenes of the same objects), samples pooled; and the
    mapper's extraction fitted on the same scenes' heatmaps (the mapping experiment's ``calibration.fit``, merged
    over the scenes), in that command's file format."""
    from semloc_core.detection.config import build_detector
    from semloc_core.io.dataset import open_dataset
    from semloc_core.experiments.detector_calibration import calibration_samples, fit_pooled
    from semloc_core.experiments.mapping_fits import merge_extraction_fits

    detector = _RecordingDetector(build_detector(_detector_config(partial / "dataset" / "exemplars")))
    frames = spec.calibration_frames
    steps = 2 * frames * len(seeds)  # per scene: render its frames, then run the detector on them

    def report(base: int):
        return None if progress is None else (lambda done, *_: progress("calibration", base + done, steps))

    samples, fits = [], []
    for k, seed in enumerate(seeds):
        folder = partial / f"calibration{k}"
        scene, _ = _make(seed, frames, crops, clutter, fps=fps, design_seed=spec.seed)
        _write_scenario(scene, folder, report(2 * k * frames))
        dataset = open_dataset(folder)
        detector.recorded = []
        samples.append(calibration_samples(dataset, detector, list(range(len(dataset))),
                                           progress=report((2 * k + 1) * frames)))
        fits.append(_fit_mapper_extraction(scene, detector))
        shutil.rmtree(folder, ignore_errors=True)  # only its samples and fit are needed
    return fit_pooled(detector, samples), {"detector": {"normalised": merge_extraction_fits(fits)},
                                           "mapper_settings": MAPPER_SETTINGS}


def _fit_mapper_extraction(scene, recorded: _RecordingDetector) -> dict:
    """The demo mapper's extraction fitted on one calibration scene: its frames' recorded heatmaps back-projected
    with the mapper's settings into its grid over the table, then the mapping experiment's fit against the scene's
    objects."""
    from semloc_core.mapping import VoxelGrid
    from semloc_core.experiments.mapping_fits import fit_extraction
    from semloc_core.experiments.mapping_scene import map_scene
    from semloc_core.experiments.tabletop import table_support

    table = scene.metadata["table"]
    low, high = table_box(table["centre"], table["half_extent"], table["surface_z"])
    grid = VoxelGrid.from_bounds(low, high, MAPPER_SETTINGS["voxel_size"])
    mapper, _ = map_scene(scene, recorded, grid, range(len(recorded.recorded)), 1,
                          MAPPER_SETTINGS["heatmap_background"], log=lambda _: None)
    return fit_extraction(mapper, scene.semantic_map, normalise=True, min_views=MAPPER_SETTINGS["min_views"],
                          distance=MAPPER_FIT_DISTANCE, min_size=0.10, position=MAPPER_SETTINGS["position"],
                          support=table_support(scene))


def _world_info(scenario, fps: float, calibration_seeds: list[int]) -> dict:
    from semloc_core.eval.pr import loop_pairs
    from semloc_core.experiments.tabletop import table_support

    table = scenario.metadata["table"]
    centre = np.asarray(table["centre"], float)
    semantic_map = scenario.semantic_map
    window = 30
    _, labels, _ = loop_pairs(np.zeros(scenario.loop_gt.shape), scenario.loop_gt, scenario.loop_gt_soft, window=window)
    counts = {name: int(np.sum(semantic_map.class_index == k)) for k, name in enumerate(semantic_map.class_names)}
    return {
        "scenario": "tabletop", "seed": int(scenario.seed), "frames": len(scenario), "fps": fps,
        "laps": round(laps_of(scenario.poses2d, centre), 2),
        "path_m": round(float(np.linalg.norm(np.diff(scenario.poses2d[:, :2], axis=0), axis=1).sum()), 1),
        "orbit_radius_m": round(_orbit_radius(scenario), 2),
        "loop_pairs": int(np.sum(labels)), "loop_window": window,
        "objects": counts, "object_count": len(semantic_map),
        "table": {"centre": [float(v) for v in centre], "half_extent": [float(v) for v in table["half_extent"]],
                  "surface_z": float(table["surface_z"]),
                  "corners": [[float(v) for v in corner] for corner in table_support(scenario)[1]]},
        "calibration_seeds": calibration_seeds,
    }


def mapper_grid(world: World, margin: float = 0.15) -> tuple[list[float], list[float]]:
    """The mapper's voxel box: the table's footprint (any orientation) plus a margin, from its surface to 0.45 m
    above it (the tallest class, a cereal box, stands ~0.3 m)."""
    table = world.info["table"]
    return table_box(table["centre"], table["half_extent"], table["surface_z"], margin)


def table_box(centre, half_extent, surface_z: float, margin: float = 0.15) -> tuple[list[float], list[float]]:
    """The box over a table of any orientation (see :func:`mapper_grid`)."""
    centre = np.asarray(centre, float)
    reach = float(np.linalg.norm(half_extent)) + margin
    z0 = float(surface_z) - 0.05
    low = [centre[0] - reach, centre[1] - reach, z0]
    high = [centre[0] + reach, centre[1] + reach, z0 + 0.45]
    return [round(float(v), 3) for v in low], [round(float(v), 3) for v in high]


def pruning_settings(world: World) -> dict:
    """The detector worker's ``prune`` settings for this world (docs/detection.md, "Pruning levels"): the table the
    objects stand on, the object map whose classes' sizes are expected, and the camera's height above the floor
    (the walk's median; the hand-held camera's varies within ``PruneParams.camera_height_tolerance``)."""
    from semloc_core.experiments.tabletop import pruning_support
    from semloc_core.io.dataset import open_dataset

    support_z, corners, camera_height = pruning_support(open_dataset(world.dataset))
    return {"map": str(world.semantic_map), "support_z": support_z,
            "support_polygon": [[float(v) for v in corner] for corner in corners],
            "camera_height": round(camera_height, 3)}
