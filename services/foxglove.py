"""semloc frames as messages Foxglove decodes, for ``semloc record --foxglove`` (docs/ros2.md, "Foxglove").

Foxglove's own schemas (protobuf, from the ``foxglove-sdk`` package: the schema of each channel is the
FileDescriptorSet it ships): images as ``foxglove.RawImage`` or ``foxglove.CompressedImage``, poses (the
localizer's estimate, ground truth) as ``foxglove.PoseInFrame``, the mapper's object map as ``foxglove.SceneUpdate``
(a cube and a label per object). Heatlines have no Foxglove schema: they go as JSON (``semloc.HeatlinesPlot``,
schema in JSON Schema) with each class's peak score and its bearing, plot-able over time, and the whole line per
class, plot-able against its index.

A channel's topic is the frame's key with a leading ``/`` (and ``/<camera>`` for each camera of a rig).
"""

from __future__ import annotations

import json
import warnings

import numpy as np

from semloc_core.bearing import BearingGrid
from semloc_core.geometry import make_transform, rotation_about_z, rotation_to_quaternion

PROTOBUF = "protobuf"
JSON = "json"
HEATLINES_SCHEMA = {
    "title": "semloc.HeatlinesPlot",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
                      "required": ["sec", "nsec"]},
        "classes": {"type": "array", "items": {"type": "string"}},
        "peak": {"type": "object", "additionalProperties": {"type": "number"},
                 "description": "highest score of each class"},
        "peak_bearing_deg": {"type": "object", "additionalProperties": {"type": "number"},
                             "description": "bearing of that score (degrees, counter-clockwise from body x)"},
        "scores": {"type": "object", "additionalProperties": {"type": "array", "items": {"type": "number"}},
                   "description": "the heatline of each class, one score per bearing bin"},
    },
    "required": ["timestamp", "classes", "peak", "peak_bearing_deg", "scores"],
}


def _messages():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import foxglove.messages as messages
    return messages


def _timestamp(m, stamp_ns: int):
    return m.Timestamp(int(stamp_ns) // 1_000_000_000, int(stamp_ns) % 1_000_000_000)


def _pose(m, T: np.ndarray):
    x, y, z, w = rotation_to_quaternion(T[:3, :3])
    return m.Pose(position=m.Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                  orientation=m.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


def _planar(x: float, y: float, theta: float) -> np.ndarray:
    return make_transform(rotation_about_z(theta), (x, y, 0.0))


def foxglove_messages(key: str, frame) -> list[tuple[str, object]]:
    """(topic, message) pairs of one semloc frame: a foxglove-sdk message (``.encode()``, ``.get_schema()``) or a
    :class:`JsonMessage`; empty for frame types without a Foxglove form."""
    m = _messages()
    name = type(frame).schema_name
    stamp, frame_id = frame.header.stamp_ns, frame.header.frame_id or "world"
    topic = "/" + key
    if name == "semloc.Image":
        out = []
        for index, image in enumerate(frame.images):
            where = topic if len(frame.images) == 1 else f"{topic}/{index}"
            data = np.asarray(image.data)
            if image.compression == "none":
                channels = 1 if data.ndim == 2 else 3
                out.append((where, m.RawImage(timestamp=_timestamp(m, stamp), frame_id=frame_id, width=image.width,
                                              height=image.height, encoding=image.encoding,
                                              step=image.width * channels, data=data.tobytes())))
            else:
                out.append((where, m.CompressedImage(timestamp=_timestamp(m, stamp), frame_id=frame_id,
                                                     data=data.tobytes(), format=image.compression)))
        return out
    if name in ("semloc.PoseEstimate", "semloc.Pose2D"):
        return [(topic, m.PoseInFrame(timestamp=_timestamp(m, stamp), frame_id=frame_id,
                                      pose=_pose(m, _planar(frame.x, frame.y, frame.theta))))]
    if name == "semloc.Pose3D":
        return [(topic, m.PoseInFrame(timestamp=_timestamp(m, stamp), frame_id=frame_id,
                                      pose=_pose(m, frame.matrix())))]
    if name == "semloc.ObjectMap":
        return [(topic, _scene(m, frame, stamp, frame_id))]
    if name == "semloc.Heatlines":
        return [(topic, _heatlines(frame, stamp))]
    return []


def _scene(m, frame, stamp: int, frame_id: str):
    from services.ros2.messages import class_color

    cubes, texts = [], []
    for cls, position, size in zip(frame.class_index, frame.positions, frame.sizes):
        r, g, b = class_color(int(cls))
        T = make_transform(np.eye(3), position)
        cubes.append(m.CubePrimitive(pose=_pose(m, T), size=m.Vector3(x=float(size[0]), y=float(size[1]),
                                                                        z=float(size[2])),
                                     color=m.Color(r=r, g=g, b=b, a=0.8)))
        label = make_transform(np.eye(3), np.asarray(position, float) + [0.0, 0.0, 0.5 * float(size[2]) + 0.05])
        texts.append(m.TextPrimitive(pose=_pose(m, label), billboard=True, font_size=14.0, scale_invariant=True,
                                     color=m.Color(r=1.0, g=1.0, b=1.0, a=1.0), text=frame.class_names[int(cls)]))
    entity = m.SceneEntity(timestamp=_timestamp(m, stamp), frame_id=frame_id, id="objects", cubes=cubes,
                           texts=texts)
    return m.SceneUpdate(entities=[entity])


class JsonMessage:
    """A JSON message with its JSON Schema, shaped like the foxglove-sdk messages (``encode``, ``get_schema``)."""

    def __init__(self, value: dict, schema: dict):
        self.value, self.schema = value, schema

    def encode(self) -> bytes:
        return json.dumps(self.value, separators=(",", ":")).encode()

    def get_schema(self):
        from types import SimpleNamespace

        return SimpleNamespace(name=self.schema["title"], encoding="jsonschema",
                               data=json.dumps(self.schema).encode())


def _heatlines(frame, stamp: int) -> JsonMessage:
    scores = frame.values()
    bearings = np.degrees(BearingGrid(scores.shape[1]).centers)
    peak = scores.argmax(axis=1)
    return JsonMessage({
        "timestamp": {"sec": int(stamp) // 1_000_000_000, "nsec": int(stamp) % 1_000_000_000},
        "classes": list(frame.classes),
        "peak": {c: float(scores[i, peak[i]]) for i, c in enumerate(frame.classes)},
        "peak_bearing_deg": {c: float(bearings[peak[i]]) for i, c in enumerate(frame.classes)},
        "scores": {c: [round(float(v), 4) for v in scores[i]] for i, c in enumerate(frame.classes)},
    }, HEATLINES_SCHEMA)


def message_encoding(schema_encoding: str) -> str:
    return PROTOBUF if schema_encoding == PROTOBUF else JSON
