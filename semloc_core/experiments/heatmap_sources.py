"""Heatmap sources of the mapping experiments: a frame index in, (classes, h, w) heat out.

* :class:`OracleHeatmaps`: a Gaussian at each visible object's projected centre (the ideal detector - isolates the
  mapper from the detector);
* :class:`DetectorHeatmaps`: a semloc_core.detection detector run on the frame's image;
* :class:`CachedHeatmaps`: a source's frames computed once, kept as float16 ``.npz`` and replayed.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

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


def detector_config(name: str) -> dict:
    """A named configuration (:data:`DETECTORS`) or the configuration file at ``name``."""
    from semloc_core.io.detector_models import load_detector_config

    return dict(DETECTORS[name]) if name in DETECTORS else dict(load_detector_config(name))


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

    def __init__(self, dataset, name: str, workdir: Path, levels: bool = False, prune: bool = False):
        from semloc_core.detection.config import build_detector

        config = detector_config(name)
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
                raise ValueError(f"scale_depth needs a detector with pyramid levels (kind: linear), not {name!r}")
            self.scales = tuple(self.detector.model.scales)
        self.pruner = self._pruner(dataset) if prune else None

    def _pruner(self, dataset):
        """The detector worker's ``prune`` on a table-top dataset: its table, object map and median camera height,
        each frame pruned by the previous frame's true pose (the detector lags the localizer by a frame) and the
        camera's height from the frame's own (the 3-D pose the mapper maps with: ``height_pose``)."""
        from semloc_core.detection.pruning import build_pruner
        from semloc_core.experiments.tabletop import pruning_support

        if not hasattr(self.detector, "level_object_px") or self.levels:
            raise ValueError("prune_levels needs a template detector (kind: templates) without scale_depth")
        support_z, corners, camera_height = pruning_support(dataset)
        return build_pruner(self.detector, dataset.camera, dataset.semantic_map, support_z, camera_height, corners)

    @staticmethod
    def _write_exemplars(dataset, workdir: Path) -> Path:
        from semloc_core.io.dataset import write_exemplar_folder, write_multiview_folder

        write_exemplar_folder(workdir / "exemplars", dataset.exemplars(), dataset.exemplar_masks())
        write_multiview_folder(workdir / "exemplars_multiview", dataset.multiview_exemplars())
        return workdir

    def __call__(self, i: int) -> np.ndarray:
        image = self.dataset.image(i)
        if self.pruner is not None:
            from semloc_core.detection.pruning import height_from_pose
            from semloc_core.geometry import transform_to_pose2d

            previous = self.dataset.T_world_body[max(0, i - 1)]
            T_body_cam = self.dataset.T_body_cam_at(i)
            height = height_from_pose(self.dataset.T_world_body[i],
                                      self.pruner.camera.T_body_cam if T_body_cam is None else T_body_cam, 0.0,
                                      self.pruner.params)
            rows = self.pruner.rows(transform_to_pose2d(previous), T_body_cam, height)
            return self.detector.heatmaps(image, rows=rows)
        return self.detector.level_heatmaps(image) if self.levels else self.detector.heatmaps(image)


def detector_cache_name(name: str) -> str:
    """The heatmap cache's name for a detector: a named configuration's name; for a configuration file, its stem
    and a digest of its bytes and of the model file it names, so that two trained models' ``detector.yaml`` (or
    a retrained model) never share cached heatmaps."""
    if name in DETECTORS:
        return name
    from semloc_core.io.detector_models import load_detector_config

    path = Path(name)
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

    def __init__(self, make_source: Callable[[], object], path: Path, frames: list[int],
                 log: Callable[[str], None]):
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
        self.stack = np.stack([np.asarray(source(i), np.float32).astype(np.float16) for i in frames])
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(path.name + ".part.npz")
        np.savez(partial, heatmaps=self.stack, frames=np.asarray(frames, np.int64),
                 classes=np.asarray(self.classes), config=json.dumps(self.config),
                 **({} if self.scales is None else {"scales": np.asarray(self.scales, np.float64)}))
        partial.replace(path)

    def __call__(self, i: int) -> np.ndarray:
        return self.stack[self.frames[int(i)]].astype(np.float32)


def depth_image(dataset, i: int) -> np.ndarray:
    """Frame ``i``'s depth along the optical axis (H, W) float32, from a scene rendered on the fly (its render gives
    the range along each pixel's ray); dataset folders hold no depth."""
    render = getattr(dataset, "render", None)
    if render is None:
        raise ValueError("occlusion needs depth images: here only DATASET 'tabletop' (rendered on the fly) has them")
    from semloc_core.camera import pixel_grid

    rays = dataset.camera.rays_cam(*pixel_grid(dataset.camera))  # unit rays: range x their z = depth along the axis
    return (render(i)[0].depth * rays[..., 2]).astype(np.float32)
