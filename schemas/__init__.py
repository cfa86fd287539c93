"""semloc's wire contract: frame models, the msgpack codec, key expressions, JSON Schema export.

    from schemas import Header, Image, encode, decode, FrameError, keys

Depends on nothing else of semloc. Format and how to add a frame type: docs/wire.md.
"""

from schemas import keys
from schemas.base import WIRE_DTYPES, Array, Frame, FrameError, Header, Sub, frame_types, lookup
from schemas.camera import (CameraImage, CameraModel, EquirectangularSpec, FisheyeSpec, Image, PinholeSpec,
                            camera_image)
from schemas.codec import decode, encode, peek_header, peek_schema
from schemas.motion import Odometry, Pose2D, Pose3D
from schemas.status import Ack, InputStats, MemoryStats, OutputStats, PersistenceStats, Status

__all__ = [
    "WIRE_DTYPES",
    "Ack",
    "Array",
    "CameraImage",
    "CameraModel",
    "EquirectangularSpec",
    "FisheyeSpec",
    "Frame",
    "FrameError",
    "Header",
    "Image",
    "InputStats",
    "MemoryStats",
    "Odometry",
    "OutputStats",
    "PersistenceStats",
    "PinholeSpec",
    "Pose2D",
    "Pose3D",
    "Status",
    "Sub",
    "camera_image",
    "decode",
    "encode",
    "frame_types",
    "keys",
    "lookup",
    "peek_header",
    "peek_schema",
]
