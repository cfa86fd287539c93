"""Training the linear window detector (``semloc_core.detection.linear``) on frames with known objects.

Per class a linear filter over the §4.3 cell features whose heat peaks where an object's 3-D centre projects,
learnt from a training world: a ``semloc sim`` folder with per-frame object ground truth, or ``tabletop`` with
``trajectories`` (``orbit:SEED``, the simulator's calibration walks). :func:`write_model` writes
``model.npz``, ``detector.yaml`` (``kind: linear``, ready as a detector configuration) and ``training.json``. Use
worlds other than the ones you evaluate on: this is training.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from pydantic import Field

from semloc_core.experiments.spec import DataPaths, Spec

DEFAULT_SCALES = [1.2, 0.85, 0.6, 0.42, 0.3, 0.21]
DEFAULT_TRAINING_SEEDS = range(200, 206)  # tabletop walks of their own: not the mapping calibration's orbits


class TrainingSpec(Spec):
    """``semloc train-detector``."""

    dataset: str | None = Field(None, description="a semloc dataset folder with per-frame object ground truth, or "
                                                   "'tabletop'")
    trajectories: DataPaths | None = Field(None, description="tabletop: orbit:SEED (the simulator's walk) or a pose "
                                                             "file, one world each (default: orbit:200 ... "
                                                             "orbit:205)")
    frames: int = Field(600, ge=1, description="tabletop: frames per world")
    seed: int = 0
    stride: int = Field(4, ge=1, description="every n-th frame")
    classes: list[str] | None = Field(None, description="default: every class of the ground truth")
    cell: int = Field(4, ge=1, description="feature cell, pixels")
    window_cells: int = Field(9, ge=1, description="window's longer side, cells")
    scales: list[float] = Field(DEFAULT_SCALES, min_length=1, description="pyramid levels")
    color_space: Literal["rgb", "hsv"] = "hsv"
    l2: float = Field(1e-3, gt=0, description="L2 weight of the logistic regression")
    rounds: int = Field(2, ge=0, description="hard-negative mining rounds")
    random_negatives: int = Field(40, ge=0, description="random negatives per frame and class")
    hard_negatives: int = Field(20, ge=0, description="hard negatives per frame, class and round")
    clutter: int | None = Field(None, ge=0, description="tabletop: distractor objects per world (the simulator's "
                                                         "default, 3)")
    ignore_radius: float = Field(0.1, ge=0, le=2, description="windows centred within this fraction of an object's "
                                                              "box size of its centre are neither positives nor "
                                                              "negatives")
    max_occluded: float = Field(0.2, ge=0, le=1, description="objects more occluded than this (or cut by the image "
                                                             "edge) are not positives")


def training_objects(dataset, i: int, classes: tuple[str, ...], max_occluded: float) -> list:
    """The frame's objects of ``classes`` as ``TrainingObject``: the pixel their 3-D centre projects to, their
    unoccluded box's size; positives unless occluded or truncated."""
    from semloc_core.detection.linear import TrainingObject

    T = dataset.T_world_cam[i]
    positions = dataset.semantic_map.positions
    out = []
    for seen in dataset.visible_objects(i):
        if seen.class_name not in classes or seen.camera != 0:
            continue
        centre_cam = (positions[seen.object_index] - T[:3, 3]) @ T[:3, :3]
        if centre_cam[2] <= 0:
            continue
        uv = dataset.camera.project_cam(centre_cam[None])[0][0]
        x0, y0, x1, y1 = seen.box
        positive = seen.occluded_fraction <= max_occluded and not seen.truncated
        out.append(TrainingObject(classes.index(seen.class_name), (float(uv[0]), float(uv[1])),
                                  (float(x1 - x0), float(y1 - y0)), positive))
    return out


def training_scenes(spec: TrainingSpec, log: Callable[[str], None]) -> list[tuple[str, object]]:
    from semloc_core.experiments.tabletop import tabletop_scenes
    from semloc_core.io.dataset import open_dataset

    if spec.dataset != "tabletop":
        return [(Path(spec.dataset).name, open_dataset(spec.dataset))]
    trajectories = spec.trajectories
    if trajectories is None:
        trajectories = [f"orbit:{seed}" for seed in DEFAULT_TRAINING_SEEDS]
    return tabletop_scenes(trajectories, spec.seed, spec.frames, spec.clutter, log)


def run(spec: TrainingSpec, log: Callable[[str], None] = lambda _: None):
    """The trained ``LinearWindowModel`` (its ``info`` says what it was trained on). ValueError for unusable
    inputs."""
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.linear import train_linear_model

    if spec.dataset is None:
        raise ValueError("no dataset given")
    scenes = training_scenes(spec, log)
    classes = tuple(spec.classes or sorted({c for _, d in scenes for c in d.semantic_map.class_names}))
    params = FeatureParams(cell=spec.cell, color_space=spec.color_space)
    total = sum(len(range(0, len(d), spec.stride)) for _, d in scenes)
    start = time.perf_counter()

    def frames():
        for name, dataset in scenes:
            for i in range(0, len(dataset), spec.stride):
                yield dataset.image(i), training_objects(dataset, i, classes, spec.max_occluded)

    def progress(stage: str, count: int) -> None:
        if stage == "features":
            if count % 25 == 0 or count == total:
                log(f"  features {count} / {total} frames ({time.perf_counter() - start:.0f} s)")
        else:
            log(f"  {stage}: {count} negatives ({time.perf_counter() - start:.0f} s)")

    model = train_linear_model(frames(), classes, params, spec.scales, spec.window_cells, spec.l2,
                               spec.random_negatives, spec.hard_negatives, spec.rounds, radius=spec.ignore_radius,
                               seed=spec.seed, progress=progress)
    trajectories = spec.trajectories
    if trajectories is None and spec.dataset == "tabletop":
        trajectories = [f"orbit:{seed}" for seed in DEFAULT_TRAINING_SEEDS]
    model.info.update({"dataset": spec.dataset, "trajectory": trajectories, "stride": spec.stride,
                       "clutter": spec.clutter, "seconds": round(time.perf_counter() - start, 1)})
    return model


def write_model(model, folder: Path) -> Path:
    """``folder/model.npz``, ``folder/detector.yaml`` and ``folder/training.json``; returns the YAML's path."""
    import yaml

    from semloc_core.io.detector_models import save_linear_model

    folder = Path(folder)
    save_linear_model(folder / "model.npz", model)
    (folder / "detector.yaml").write_text(yaml.safe_dump({"kind": "linear", "model": "model.npz"}))
    (folder / "training.json").write_text(json.dumps(model.info, indent=2))
    return folder / "detector.yaml"
