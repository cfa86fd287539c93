"""Mapping frames: ``ObjectMap``, the semantic object map (the mapper's output and the localizer's map input).

Column-wise, mirroring the semantic map file format (``semloc.semantic_map`` v1, docs/conventions.md): object ``n``
is class ``class_names[class_index[n]]`` with centre ``positions[n]`` (world frame, z up, metres; ``has_height[n]``
false means the z is unknown and stored as 0), extent ``sizes[n]`` (0 = unknown), ``scores[n]`` and (version 2)
``existence[n]``, the probability that the object is there (``SemanticMap.existence``). ``bounds`` is
the floor box ``[[xmin, ymin], [xmax, ymax]]`` the map covers; ``free_space`` optional polygons (N, 2).
``header.frame_id`` is the world frame's name (``"world"``). ``frames`` counts the camera frames integrated into
the map so far (0 for a map that was not built by the mapper).

Converters to and from ``semloc_core.io.semantic_map.SemanticMap`` live in ``services.workers.mapper`` (schemas
depend on nothing of ours).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from schemas.base import Array, Frame, FrameError
from schemas.limits import MAX_COORDINATE, MAX_OBJECT_SIZE

MAX_OBJECTS = 100_000
_WORLD = (-MAX_COORDINATE, MAX_COORDINATE)
MAX_CLASSES = 4096
ClassName = Annotated[str, Field(min_length=1, max_length=128)]


class _ObjectMapFields(Frame):
    # the fields and checks of every ObjectMap version (no schema: not a frame type of its own)
    class_names: tuple[ClassName, ...] = Field(max_length=MAX_CLASSES)
    class_index: Array("int32", ndim=1, max_elements=MAX_OBJECTS)
    positions: Array("float64", shape=(None, 3), finite=True, max_elements=3 * MAX_OBJECTS, bounds=_WORLD)
    has_height: Array("bool", ndim=1, max_elements=MAX_OBJECTS)
    sizes: Array("float64", shape=(None, 3), finite=True, max_elements=3 * MAX_OBJECTS,
                 bounds=(0.0, MAX_OBJECT_SIZE))
    scores: Array("float64", ndim=1, finite=True, max_elements=MAX_OBJECTS)
    bounds: Array("float64", shape=(2, 2), finite=True, bounds=_WORLD)
    free_space: list[Array("float64", shape=(None, 2), finite=True, max_elements=2 * MAX_OBJECTS, bounds=_WORLD)] = (
        Field(default_factory=list, max_length=1024))
    frames: Annotated[int, Field(ge=0, lt=2**63)] = 0

    @field_validator("class_names")
    @classmethod
    def _distinct(cls, names):
        if len(set(names)) != len(names):
            raise ValueError(f"class names must be distinct, got {list(names)}")
        return names

    @field_validator("free_space")
    @classmethod
    def _polygons(cls, polygons):
        for polygon in polygons:
            if len(polygon) < 3:
                raise ValueError("each free-space polygon needs at least 3 points")
        return polygons

    @model_validator(mode="after")
    def _consistent(self):
        n = len(self.class_index)
        for name in ("positions", "has_height", "sizes", "scores"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} has {len(getattr(self, name))} rows for {n} objects")
        if n and (self.class_index.min() < 0 or self.class_index.max() >= len(self.class_names)):
            raise ValueError(f"class_index must lie in [0, {len(self.class_names)})")
        if not (self.bounds[0, 0] < self.bounds[1, 0] and self.bounds[0, 1] < self.bounds[1, 1]):
            raise ValueError(f"bounds min {self.bounds[0].tolist()} must be below max {self.bounds[1].tolist()}")
        return self

    def __len__(self) -> int:
        return int(len(self.class_index))


class ObjectMapV1(_ObjectMapFields, schema="semloc.ObjectMap", version=1, max_bytes=32 << 20):
    """Objects of known classes with positions in the world frame (the localizer's map; the mapper's output)."""


class ObjectMap(_ObjectMapFields, schema="semloc.ObjectMap", version=2, max_bytes=32 << 20):
    """Objects of known classes with positions in the world frame (the localizer's map; the mapper's output);
    ``existence[n]`` in (0, 1]: the probability that object n is really there (v2; v1 frames have none: 1)."""

    existence: Array("float64", ndim=1, finite=True, max_elements=MAX_OBJECTS, description="each in (0, 1]")

    @model_validator(mode="after")
    def _probabilities(self):
        if len(self.existence) != len(self.class_index):
            raise ValueError(f"existence has {len(self.existence)} rows for {len(self.class_index)} objects")
        if len(self.existence) and not np.all((self.existence > 0) & (self.existence <= 1)):
            raise FrameError("existence must lie in (0, 1]", reason="range")
        return self


# What a reader of object maps accepts: the current version and the one before it (read as certain objects).
ANY_OBJECT_MAP = (ObjectMap, ObjectMapV1)


MAX_VOXELS = 64 << 20  # 64 M scores: a 2.6 m x 2.6 m x 0.5 m table top at 2 cm holds 0.4 M per class


class VoxelMap(ObjectMap, schema="semloc.VoxelMap", version=1, max_bytes=256 << 20):
    """The mapper's whole map at one moment (its answer on ``mapper/save``): the extracted objects (every field of
    ``ObjectMap``) and the per-class score volumes they were extracted from, over the grid of ``voxel_size``
    cubes whose minimum corner is ``origin`` (world frame). ``score_volumes`` (C, nz, ny, nx) is indexed ``[class,
    k, j, i]`` like ``class_names`` (``scores`` are the objects'); ``views`` (nz, ny, nx) how many frames saw each
    voxel (summed coverage)."""

    origin: Array("float64", shape=(3,), finite=True, bounds=_WORLD)
    voxel_size: Annotated[float, Field(gt=0.0, le=100.0)]
    score_volumes: Array("float32", ndim=4, finite=True, max_elements=MAX_VOXELS)
    views: Array("float32", ndim=3, finite=True, max_elements=MAX_VOXELS, bounds=(0.0, float(2**63)))

    @model_validator(mode="after")
    def _volumes(self):
        volumes = self.score_volumes.shape
        if volumes[0] != len(self.class_names) or self.views.shape != volumes[1:]:
            raise ValueError(f"score_volumes {volumes} must be (classes={len(self.class_names)}, nz, ny, nx) and "
                             f"views {self.views.shape} (nz, ny, nx)")
        return self
