"""Detector configuration (a few lines of YAML) -> a heatmap detector.

Every detector semloc builds answers ``classes`` and ``heatmaps(image) -> (classes, rows, cols)`` float32 in [0, 1]
on a grid covering the image uniformly (docs/detection.md). ``kind`` selects it:

* ``templates`` — §4.3 single-exemplar HOGE x HQC templates from a template library folder;
* ``multiview`` — §5.3 dominant-orientation templates, several views per class from a template library folder;
* ``linear`` — per-class linear window filters on the §4.3 cell features, trained on frames with known objects
  (``semloc train-detector``; the thesis's DPM heatmaps, §4.6.2, root filter only);
* ``hog_people`` — OpenCV's HOG people detector made soft (§4.6.2);
* ``haar`` — an OpenCV cascade made soft (§4.6.2);
* ``dnn`` — the user's own model file run by ``cv2.dnn`` (SSD or YOLO outputs), made soft (§4.6.2);
* ``python`` — the user's own Python box detector: ``factory: "package.module:function"`` returning an object with
  ``classes`` and ``detect(image) -> [(boxes, scores) per class]``.
"""

from __future__ import annotations

import importlib
from typing import Annotated, Literal, Protocol, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from semloc_core.detection.boxes import (BoxHeatmapDetector, DnnDetector, HaarCascadeDetector, HogPeopleDetector,
                                         ScoreSquash)
from semloc_core.detection.features import FeatureParams
from semloc_core.detection.linear import LinearWindowDetector, LinearWindowModel
from semloc_core.detection.multiview import MultiViewDetector, OrientationParams, build_view_template
from semloc_core.detection.templates import (MatchParams, TemplateDetector, build_templates,
                                             mask_uniform_background)
from semloc_core.io.detector_models import (DetectorModelError, load_cascade, load_dnn, load_detector_config,
                                            load_template_library, read_linear_model)
from semloc_core.validation import describe_validation


class HeatmapDetector(Protocol):
    classes: tuple[str, ...]

    def heatmaps(self, image: np.ndarray) -> np.ndarray: ...


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SquashConfig(_Strict):
    kind: Literal["logistic", "clip"] = "logistic"
    centre: float = 0.0
    width: float = Field(1.0, gt=0)


class _Library(_Strict):
    templates: str = Field(description="template library folder: one sub-folder of exemplar images per class")
    classes: list[str] | None = Field(None, description="use only these classes (default: every sub-folder)")
    files: str | None = Field(None, description="use only exemplar files matching this glob, e.g. '*_el35.png'")
    mask: Literal["alpha", "auto", "none"] = Field(
        "alpha", description="object masks: PNG alpha only; alpha else plain-background detection; none")


class TemplatesConfig(_Library):
    kind: Literal["templates"]
    cell: int = Field(8, ge=1)
    orientations: int = Field(8, ge=2)
    sigma: float = Field(1.0, gt=0)
    epsilon_fraction: float = Field(0.01, gt=0, lt=1)
    color_levels: int = Field(4, ge=2, le=16)
    color_space: Literal["rgb", "hsv"] = Field("rgb", description="HQC colour model (hsv: brightness-invariant)")
    hue_levels: int = Field(6, ge=2, le=60, description="hsv: hue bins")
    saturation_levels: int = Field(4, ge=1, le=8, description="hsv: saturation bins")
    template_cells: int = Field(9, ge=1)
    scales: list[float] = Field(default_factory=lambda: [1.0, 0.75, 0.5], min_length=1)
    mirror: bool = True
    threads: int = Field(1, ge=1, le=16, description="pyramid levels matched on this many threads at once (the same "
                                                     "heatmaps; less wall time, not less CPU time)")


class MultiViewConfig(_Library):
    kind: Literal["multiview"]
    orientations: int = Field(8, ge=2, le=8)
    spread: int = Field(4, ge=1)
    magnitude_threshold: float = Field(10.0, ge=0)
    max_features: int = Field(63, ge=1)
    template_px: int = Field(64, ge=8)
    scales: list[float] = Field(default_factory=lambda: [1.0, 0.75, 0.5], min_length=1)
    mirror: bool = False


class LinearConfig(_Strict):
    kind: Literal["linear"]
    model: str = Field(description="model file written by semloc train-detector (.npz)")
    classes: list[str] | None = Field(None, description="use only these classes (default: every class of the model)")
    model_config = ConfigDict(extra="forbid", protected_namespaces=())


class _Boxes(_Strict):
    squash: SquashConfig = Field(default_factory=SquashConfig)
    heatmap_cell: int = Field(4, ge=1, description="heatmap grid step in pixels")


class HogPeopleConfig(_Boxes):
    kind: Literal["hog_people"]
    class_name: str = "person"
    win_stride: tuple[int, int] = (8, 8)
    scale: float = Field(1.05, gt=1.0)
    upscale: float = Field(1.0, gt=0)


class HaarConfig(_Boxes):
    kind: Literal["haar"]
    cascade: str = "haarcascade_frontalface_default.xml"
    class_name: str = "face"
    scale_factor: float = Field(1.1, gt=1.0)
    min_size: tuple[int, int] = (0, 0)


class DnnConfig(_Boxes):
    kind: Literal["dnn"]
    model: str
    model_config_file: str | None = Field(None, alias="model_config")
    classes: dict[int, str] = Field(min_length=1, description="model class index -> semloc class name")
    input_size: tuple[int, int] = (300, 300)
    output: Literal["ssd", "yolo"] = "ssd"
    scale: float = 1.0 / 255.0
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    swap_rb: bool = True
    objectness: bool = False
    yolo_layout: Literal["auto", "rows", "columns"] = "auto"
    squash: SquashConfig = Field(default_factory=lambda: SquashConfig(kind="clip"))
    model_config = ConfigDict(extra="forbid", populate_by_name=True, protected_namespaces=())


class PythonConfig(_Boxes):
    kind: Literal["python"]
    factory: str = Field(pattern=r"^[\w.]+:[\w]+$", description="module:function returning a box detector")
    options: dict = Field(default_factory=dict)


DetectorConfig = Annotated[
    Union[TemplatesConfig, MultiViewConfig, LinearConfig, HogPeopleConfig, HaarConfig, DnnConfig, PythonConfig],
    Field(discriminator="kind"),
]
_ADAPTER = TypeAdapter(DetectorConfig)


def parse_detector_config(document: dict):
    """Validate a configuration mapping; raises ``DetectorModelError`` with pydantic's explanation."""
    try:
        return _ADAPTER.validate_python(document)
    except ValidationError as error:
        raise DetectorModelError(f"invalid detector configuration: {describe_validation(error)}") from None


def _exemplar_mask(exemplar, mode: str):
    if mode == "none":
        return None
    if exemplar.mask is not None or mode == "alpha":
        return exemplar.mask
    return mask_uniform_background(exemplar.image)


def _library(config):
    try:
        library = load_template_library(config.templates, config.files)
    except DetectorModelError as error:
        raise DetectorModelError(f"templates: {error}") from None
    if config.classes is not None:
        missing = [c for c in config.classes if c not in library]
        if missing:
            raise DetectorModelError(f"classes: {missing} have no folder in {config.templates}")
        library = {c: library[c] for c in config.classes}
    return library


def detector_classes(config) -> tuple[str, ...]:
    """The classes (in order) of the detector a config (parsed, a mapping or a file) builds, without building it
    when its classes can be read off (template libraries, trained models) - what a consumer of its heatmaps, such
    as the mapper, takes as its configured class set."""
    if isinstance(config, (str, bytes)) or hasattr(config, "__fspath__"):
        path = config
        try:
            return detector_classes(load_detector_config(path))
        except DetectorModelError as error:
            raise DetectorModelError(f"{path}: {error}") from None
    if isinstance(config, dict):
        config = parse_detector_config(config)
    if isinstance(config, (TemplatesConfig, MultiViewConfig)):
        return tuple(_library(config))
    if isinstance(config, LinearConfig):
        model = load_linear_model(config.model)
        return tuple(config.classes) if config.classes is not None else tuple(model.classes)
    return tuple(build_detector(config).classes)


def load_linear_model(path) -> LinearWindowModel:
    """The linear window model in ``path`` (written by ``semloc_core.io.detector_models.save_linear_model``); a file
    that is not one, or whose filters do not fit its feature parameters, gets a ``DetectorModelError`` saying why."""
    parts = read_linear_model(path)
    try:
        return LinearWindowModel(**{**parts, "params": FeatureParams(**parts["params"])})
    except (TypeError, ValueError) as error:
        raise DetectorModelError(f"{path}: invalid linear detector model: {error!r}") from error


def build_detector(config) -> HeatmapDetector:
    """A heatmap detector from a parsed config, a mapping, or a path to a YAML/JSON file (whose errors name it)."""
    if isinstance(config, (str, bytes)) or hasattr(config, "__fspath__"):
        path = config
        document = load_detector_config(path)
        try:
            return build_detector(document)
        except DetectorModelError as error:
            raise DetectorModelError(f"{path}: {error}") from None
    if isinstance(config, dict):
        config = parse_detector_config(config)
    if isinstance(config, TemplatesConfig):
        params = FeatureParams(config.cell, config.orientations, config.sigma, config.epsilon_fraction,
                               config.color_levels, color_space=config.color_space, hue_levels=config.hue_levels,
                               saturation_levels=config.saturation_levels)
        templates = []
        for name, exemplars in _library(config).items():
            for exemplar in exemplars:
                templates += build_templates(exemplar.image, name, params, config.template_cells,
                                             mask=_exemplar_mask(exemplar, config.mask), mirror=config.mirror,
                                             source=exemplar.path)
        return TemplateDetector(templates, params, MatchParams(tuple(config.scales)), threads=config.threads)
    if isinstance(config, MultiViewConfig):
        params = OrientationParams(config.orientations, config.spread, config.magnitude_threshold,
                                   config.max_features, template_px=config.template_px, scales=tuple(config.scales))
        views = []
        for name, exemplars in _library(config).items():
            for exemplar in exemplars:
                mask = _exemplar_mask(exemplar, config.mask)
                views.append(build_view_template(exemplar.image, name, params, mask, exemplar.path))
                if config.mirror:
                    views.append(build_view_template(exemplar.image[:, ::-1].copy(), name, params,
                                                     None if mask is None else mask[:, ::-1], exemplar.path))
        return MultiViewDetector(views, params)
    if isinstance(config, LinearConfig):
        model = load_linear_model(config.model)
        if config.classes is not None:
            missing = [c for c in config.classes if c not in model.classes]
            if missing:
                raise DetectorModelError(f"classes {missing} are not in the model {config.model} ({model.classes})")
            model = model.subset(config.classes)
        return LinearWindowDetector(model)
    squash = ScoreSquash(config.squash.kind, config.squash.centre, config.squash.width)
    if isinstance(config, HogPeopleConfig):
        boxes = HogPeopleDetector(config.class_name, tuple(config.win_stride), config.scale, config.upscale)
    elif isinstance(config, HaarConfig):
        boxes = HaarCascadeDetector(load_cascade(config.cascade), config.class_name, config.scale_factor,
                                    tuple(config.min_size))
    elif isinstance(config, DnnConfig):
        boxes = DnnDetector(load_dnn(config.model, config.model_config_file), config.classes,
                            tuple(config.input_size), config.output, config.scale, tuple(config.mean),
                            config.swap_rb, config.objectness, config.yolo_layout)
    elif isinstance(config, PythonConfig):
        module_name, function_name = config.factory.split(":")
        try:
            factory = getattr(importlib.import_module(module_name), function_name)
        except (ImportError, AttributeError) as error:
            raise DetectorModelError(f"cannot import detector factory {config.factory!r}: {error}") from error
        boxes = factory(**config.options)
        if not hasattr(boxes, "classes") or not callable(getattr(boxes, "detect", None)):
            raise DetectorModelError(f"{config.factory} must return an object with 'classes' and 'detect(image)'")
    else:
        raise DetectorModelError(f"unsupported detector configuration {type(config).__name__}")
    return BoxHeatmapDetector(boxes, squash, config.heatmap_cell)
