"""Simulated table tops for the experiments: the RGB-D Scenes v2 scenes' objects, worlds along real trajectories,
the grid over a table and the table top the objects rest on.

A table top is the simulator's ``tabletop`` scenario (semloc_core.sim), its objects textured with the real RGB-D
Object crops of the data folder when present (``exemplars: auto``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

TABLETOP_CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")
# Thesis Table 4.1: objects per RGB-D Scenes v2 scene (bowl, cap, cereal box, coffee mug, soda can). A tabletop
# driven by scene NN's real trajectory gets that scene's objects.
SCENE_OBJECTS = {
    1: (2, 1, 0, 1, 1), 2: (1, 0, 1, 1, 2), 3: (2, 1, 0, 1, 1), 4: (2, 0, 1, 1, 1), 5: (1, 1, 1, 1, 0),
    6: (1, 0, 0, 2, 2), 7: (1, 1, 1, 1, 1), 8: (0, 2, 0, 0, 1), 9: (1, 0, 1, 0, 1), 10: (1, 1, 0, 1, 0),
    11: (0, 0, 1, 0, 2), 12: (0, 2, 0, 1, 0), 13: (1, 0, 1, 1, 1), 14: (1, 1, 0, 1, 1),
}
# Bounding volumes (x, y, z metres) of the tabletop classes: the thesis's "approximate bounding volume of the
# object" given to non-maximum suppression - class priors, not measured on the evaluated scenes.
TABLETOP_SIZES = {"bowl": (0.18, 0.18, 0.08), "cap": (0.26, 0.26, 0.10), "cereal_box": (0.20, 0.20, 0.30),
                  "coffee_mug": (0.12, 0.12, 0.12), "soda_can": (0.08, 0.08, 0.14)}


def crop_options(exemplars: str = "auto") -> dict:
    """The scenario options texturing a tabletop's objects with real crops: ``auto`` (the data folder's, when
    present), ``none`` (generated looks) or a folder."""
    from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops

    if exemplars == "none":
        return {}
    folder = default_exemplar_dir() if exemplars == "auto" else Path(exemplars)
    if folder is None:
        return {}
    crops, others = load_exemplar_crops(folder)
    return {"crops": crops, "clutter_crops": others}


def scene_instances(trajectory: str | Path) -> dict | None:
    """The objects of RGB-D Scenes v2 scene NN for a trajectory file named ``NN.pose`` (None for another name)."""
    scene = Path(trajectory).stem
    if scene.isdigit() and int(scene) in SCENE_OBJECTS:
        return dict(zip(TABLETOP_CLASSES, SCENE_OBJECTS[int(scene)]))
    return None


def simulated_scenario(name: str, seed: int, frames: int | None = None, trajectory: str | None = None,
                       exemplars: str = "auto", camera: str | None = None):
    """A scenario made in memory: ``tabletop`` (along a real trajectory file when given, with that scene's
    objects) or another simulator scenario (``camera``: its camera model, e.g. ``panorama:4096x1024``)."""
    from semloc_core.io.trajectory import read_trajectory
    from semloc_core.sim import make_scenario

    options = crop_options(exemplars) if name == "tabletop" else {}
    if camera:
        if name == "tabletop":
            raise ValueError("camera is for sim:hall (the tabletop's camera is the Kinect of its trajectory)")
        options["camera"] = camera
    path = None
    if trajectory:
        if name != "tabletop":
            raise ValueError("a trajectory is for sim:tabletop")
        path = read_trajectory(Path(trajectory))[1]
        if instances := scene_instances(trajectory):
            options["instances"] = instances
    return make_scenario(name, seed=seed, frames=frames, trajectory=path, **options)


def tabletop_scenes(trajectories: list[str], seed: int, frames: int | None = None, clutter: int | None = None,
                    log: Callable[[str], None] = lambda _: None) -> list[tuple[str, object]]:
    """(name, Scenario) per trajectory: a real trajectory file (``NN.pose`` gets scene NN's objects), or ``orbit``
    / ``orbit:SEED``, the simulator's own walk around the table (the calibration scenes). Some seeds draw more
    objects than a small table holds (the simulator then refuses): the next seed is taken, and the scenario's
    ``metadata["seed_used"]`` says which."""
    from semloc_core.io.trajectory import read_trajectory
    from semloc_core.sim import make_scenario

    options = crop_options("auto")
    scenes = []
    for path in trajectories or ["orbit"]:
        base_seed = seed
        if path == "orbit" or path.startswith("orbit:"):
            trajectory, name = None, path.replace(":", "")
            base_seed = int(path.split(":")[1]) if ":" in path else seed
        else:
            trajectory, name = read_trajectory(Path(path))[1], Path(path).stem
        scene_options = dict(options)
        if clutter is not None:
            scene_options["clutter"] = clutter
        if instances := scene_instances(name + ".pose"):
            scene_options["instances"] = instances
        for candidate in range(base_seed, base_seed + 10):
            try:
                scenario = make_scenario("tabletop", seed=candidate, frames=frames, trajectory=trajectory,
                                         **scene_options)
            except ValueError as error:
                log(f"scene {name}: seed {candidate}: {error}")
                continue
            log(f"scene {name}: tabletop seed {candidate}, {len(scenario)} frames, {len(scenario.semantic_map)} "
                f"objects")
            scenario.metadata["seed_used"] = candidate
            scenes.append((name, scenario))
            break
        else:
            raise ValueError(f"scene {name}: no seed in [{base_seed}, {base_seed + 10}) builds a tabletop world")
    return scenes


def table_support(dataset) -> tuple[float, np.ndarray]:
    """The table top the objects rest on: its height and its (4, 2) corners (x, y), from the dataset's metadata."""
    table = dataset.metadata.get("table")
    if not table:
        raise ValueError("the dataset has no table metadata: give grid.min and grid.max, and extraction.support none")
    centre = np.asarray(table["centre"], float)
    axes = np.asarray(table["axes"], float)
    half = np.asarray(table["half_extent"], float)
    corners = np.array([centre + axes @ (half * s) for s in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
    return float(table["surface_z"]), corners



def pruning_support(dataset) -> tuple[float, np.ndarray, float]:
    """What the detector's level pruning takes of a table-top dataset: the table top's height and corners
    (``table_support``) and the camera's median height above the floor over the sequence."""
    support_z, corners = table_support(dataset)
    return support_z, corners, float(np.median(dataset.T_world_cam[:, 2, 3]))

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
