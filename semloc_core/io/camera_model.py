"""Camera models as JSON documents (``camera.json`` of a dataset, camera-model frames)."""

from __future__ import annotations

import numpy as np

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera
from semloc_core.io.errors import FileFormatError


class CameraFormatError(FileFormatError):
    """A camera document that does not describe a valid camera model."""


def camera_to_document(camera) -> dict:
    if isinstance(camera, PinholeCamera):
        return {"model": "pinhole", "width": int(camera.width), "height": int(camera.height),
                "K": camera.K.tolist(), "dist": camera.dist.tolist(), "T_body_cam": camera.T_body_cam.tolist()}
    if isinstance(camera, EquirectangularCamera):
        return {"model": "equirectangular", "width": int(camera.width), "height": int(camera.height),
                "lat_top": float(camera.lat_top), "lat_bottom": float(camera.lat_bottom),
                "T_body_cam": camera.T_body_cam.tolist()}
    if isinstance(camera, CameraRig):
        return {"model": "rig", "cameras": [camera_to_document(c) for c in camera.cameras]}
    raise TypeError(f"not a camera model: {type(camera)}")


def camera_from_document(document) -> PinholeCamera | EquirectangularCamera | CameraRig:
    if not isinstance(document, dict) or "model" not in document:
        raise CameraFormatError("a camera document is a mapping with a 'model' key")
    model = document["model"]
    try:
        if model == "pinhole":
            return PinholeCamera(int(document["width"]), int(document["height"]), np.asarray(document["K"], float),
                                 np.asarray(document.get("dist", []), float),
                                 np.asarray(document.get("T_body_cam", np.eye(4)), float))
        if model == "equirectangular":
            return EquirectangularCamera(int(document["width"]), int(document["height"]),
                                         np.asarray(document.get("T_body_cam", np.eye(4)), float),
                                         document.get("lat_top"), document.get("lat_bottom"))
        if model == "rig":
            return CameraRig(tuple(camera_from_document(c) for c in document["cameras"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CameraFormatError(f"invalid {model} camera: {error}") from None
    raise CameraFormatError(f"unknown camera model {model!r} (pinhole, equirectangular, rig)")
