"""The semantic object map: the format the localizer reads and the voxel mapper and simulator write.

On disk (JSON, or YAML by file extension)::

    format: semloc.semantic_map
    version: 1
    frame_id: world
    bounds: {min: [x, y], max: [x, y]}          # metres; the region particles may occupy
    free_space: [[[x, y], ...], ...]             # optional polygons; particles are initialised inside them
    objects:
      - {class: bowl, position: [x, y, z], size: [sx, sy, sz], score: 1.0, existence: 1.0, id: 0}
        # z, size, score, existence, id optional

Positions are object centres in the world frame (z up). A missing z means "unknown height" (stored as 0 with
``has_height`` False); a missing size means unknown extent (stored as 0). ``score`` is what made the object (a
mapper's extraction score; 1 for a drawn map) and is not read by the localizer; ``existence`` in (0, 1] is the
probability that the object is really there (1, the default, for a surveyed map; a mapper fits it from its
calibration scenes): the perception models expect an object's detections only with that probability.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from semloc_core.io.errors import FileFormatError
from semloc_core.io.atomic import replace_text
from semloc_core.validation import describe_validation

FORMAT_NAME = "semloc.semantic_map"
FORMAT_VERSION = 1


class MapFormatError(FileFormatError):
    """A semantic map file or object that does not follow the format."""


FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class _ObjectModel(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)
    class_name: str = Field(alias="class", min_length=1)
    position: list[FiniteFloat] = Field(min_length=2, max_length=3)
    size: list[Annotated[float, Field(ge=0, allow_inf_nan=False)]] | None = Field(default=None, min_length=3, max_length=3)
    score: FiniteFloat = 1.0
    existence: float = Field(default=1.0, gt=0.0, le=1.0, allow_inf_nan=False)
    id: int | None = None


class _BoundsModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min: list[FiniteFloat] = Field(min_length=2, max_length=2)
    max: list[FiniteFloat] = Field(min_length=2, max_length=2)

    @model_validator(mode="after")
    def _ordered(self):
        if not (self.min[0] < self.max[0] and self.min[1] < self.max[1]):
            raise ValueError(f"bounds min {self.min} must be below max {self.max} on both axes")
        return self


class _MapModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: str = FORMAT_NAME
    version: int = FORMAT_VERSION
    frame_id: str = "world"
    bounds: _BoundsModel | None = None
    free_space: list[list[list[FiniteFloat]]] | None = None
    objects: list[_ObjectModel]

    @field_validator("format")
    @classmethod
    def _format(cls, value: str) -> str:
        if value != FORMAT_NAME:
            raise ValueError(f"expected format {FORMAT_NAME!r}, got {value!r}")
        return value

    @field_validator("version")
    @classmethod
    def _version(cls, value: int) -> int:
        if value != FORMAT_VERSION:
            raise ValueError(f"unsupported version {value} (this semloc reads version {FORMAT_VERSION})")
        return value

    @field_validator("free_space")
    @classmethod
    def _polygons(cls, value):
        for polygon in value or []:
            if len(polygon) < 3 or any(len(point) != 2 for point in polygon):
                raise ValueError("each free-space polygon needs at least 3 points of 2 coordinates")
        return value


@dataclass(frozen=True, eq=False)
class SemanticMap:
    """Objects as arrays: ``class_index`` (N,) into ``class_names``; ``positions`` (N, 3); ``sizes`` (N, 3);
    ``existence`` (N,) in (0, 1], ones when not given."""

    class_names: tuple[str, ...]
    class_index: np.ndarray
    positions: np.ndarray
    sizes: np.ndarray
    scores: np.ndarray
    has_height: np.ndarray
    bounds: np.ndarray  # (2, 2): [[xmin, ymin], [xmax, ymax]]
    free_space: tuple[np.ndarray, ...] = field(default_factory=tuple)
    frame_id: str = "world"
    existence: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self)
        existence = np.ones(n) if self.existence is None else np.asarray(self.existence, dtype=float)
        if existence.shape != (n,) or not np.all((existence > 0) & (existence <= 1)):
            raise MapFormatError(f"existence must be {n} probabilities in (0, 1], got {existence!r}")
        object.__setattr__(self, "existence", existence)

    def __len__(self) -> int:
        return int(self.class_index.shape[0])

    def objects_of(self, class_name: str) -> np.ndarray:
        """Indices of the objects of one class (empty if the class is absent)."""
        if class_name not in self.class_names:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.class_index == self.class_names.index(class_name))

    def labels(self) -> list[str]:
        """Each object's class name, with its existence probability when it is not certain ("mug p=0.87")."""
        return [self.class_names[c] + ("" if p >= 1.0 else f" p={p:.2f}")
                for c, p in zip(self.class_index, self.existence)]

    @classmethod
    def from_objects(cls, objects: list[dict], bounds=None, free_space=None, frame_id: str = "world",
                     class_names: tuple[str, ...] | None = None, margin: float = 1.0) -> "SemanticMap":
        """Build from dicts ``{"class", "position", "size"?, "score"?}``; bounds default to the objects' extent."""
        document = {"objects": objects, "frame_id": frame_id}
        if bounds is not None:
            b = np.asarray(bounds, dtype=float)
            document["bounds"] = {"min": b[0].tolist(), "max": b[1].tolist()}
        if free_space is not None:
            document["free_space"] = [np.asarray(p, dtype=float).tolist() for p in free_space]
        return _from_model(_validate(document), class_names=class_names, margin=margin)

    def to_document(self) -> dict:
        objects = []
        for i in range(len(self)):
            position = self.positions[i].tolist() if self.has_height[i] else self.positions[i, :2].tolist()
            obj = {"id": i, "class": self.class_names[self.class_index[i]], "position": position,
                   "score": float(self.scores[i])}
            if self.existence[i] < 1.0:
                obj["existence"] = float(self.existence[i])
            if np.any(self.sizes[i] > 0):
                obj["size"] = self.sizes[i].tolist()
            objects.append(obj)
        document = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "frame_id": self.frame_id,
            "bounds": {"min": self.bounds[0].tolist(), "max": self.bounds[1].tolist()},
            "objects": objects,
        }
        if self.free_space:
            document["free_space"] = [np.asarray(p).tolist() for p in self.free_space]
        return document


def _validate(document) -> _MapModel:
    if not isinstance(document, dict):
        raise MapFormatError(f"a semantic map must be a mapping, got {type(document).__name__}")
    try:
        return _MapModel.model_validate(document)
    except ValidationError as error:
        raise MapFormatError(describe_validation(error)) from None


def _from_model(model: _MapModel, class_names=None, margin: float = 1.0) -> SemanticMap:
    names = list(class_names or [])
    for obj in model.objects:
        if obj.class_name not in names:
            if class_names is not None:
                raise MapFormatError(f"object class {obj.class_name!r} not among {list(class_names)}")
            names.append(obj.class_name)
    n = len(model.objects)
    positions = np.zeros((n, 3))
    has_height = np.zeros(n, dtype=bool)
    sizes = np.zeros((n, 3))
    for i, obj in enumerate(model.objects):
        positions[i, : len(obj.position)] = obj.position
        has_height[i] = len(obj.position) == 3
        if obj.size is not None:
            sizes[i] = obj.size
    if model.bounds is not None:
        bounds = np.array([model.bounds.min, model.bounds.max], dtype=float)
    elif n:
        bounds = np.array([positions[:, :2].min(0) - margin, positions[:, :2].max(0) + margin])
    else:
        raise MapFormatError("a map without objects must declare its bounds")
    return SemanticMap(
        class_names=tuple(names),
        class_index=np.array([names.index(o.class_name) for o in model.objects], dtype=np.int64),
        positions=positions,
        sizes=sizes,
        scores=np.array([o.score for o in model.objects], dtype=float),
        has_height=has_height,
        bounds=bounds,
        free_space=tuple(np.asarray(p, dtype=float) for p in (model.free_space or [])),
        frame_id=model.frame_id,
        existence=np.array([o.existence for o in model.objects], dtype=float),
    )


def load_semantic_map(path, class_names: tuple[str, ...] | None = None) -> SemanticMap:
    """Read and validate a map file (.json, .yaml or .yml); raises MapFormatError with the reason."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise MapFormatError(f"cannot read semantic map {path}: {error}") from None
    try:
        document = yaml.safe_load(text) if path.suffix.lower() in (".yaml", ".yml") else json.loads(text)
    except (yaml.YAMLError, json.JSONDecodeError) as error:
        raise MapFormatError(f"{path} is not valid {path.suffix.lstrip('.') or 'JSON'}: {error}") from None
    try:
        return _from_model(_validate(document), class_names=class_names)
    except MapFormatError as error:
        raise MapFormatError(f"{path}: {error}") from None


def save_semantic_map(semantic_map: SemanticMap, path) -> None:
    """Write a map as JSON or YAML (by extension), atomically."""
    path = Path(path)
    document = semantic_map.to_document()
    text = yaml.safe_dump(document, sort_keys=False) if path.suffix.lower() in (".yaml", ".yml") else json.dumps(
        document, indent=2)
    replace_text(path, text)
