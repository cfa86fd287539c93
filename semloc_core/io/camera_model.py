"""Camera models on disk: JSON documents (a data set's ``camera.json``) and calibration YAML files.

Calibration YAML (OpenCV / ROS ``camera_info`` style; matrices as ``{rows, cols, data}``)::

    model: pinhole                 # pinhole (default) | fisheye | equirectangular | rig
    camera_name: front
    image_width: 640
    image_height: 480
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob    # plumb_bob, rational_polynomial or none: the coefficient count (0, 4, 5, 8, 12, 14)
                                   # decides; equidistant or fisheye: a fisheye camera; any other name is refused
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    T_body_cam: {rows: 4, cols: 4, data: [...]}   # optional; default: level camera looking along body x

    model: fisheye                 # OpenCV's fisheye (equidistant) model: camera_matrix and 4 coefficients k1..k4
    distortion_model: equidistant  # (a pinhole mapping with distortion_model: equidistant, as ROS writes, is one too)

    model: equirectangular         # + image_width, image_height, optional lat_top / lat_bottom (radians), T_body_cam

    model: rig
    cameras: [ {<pinhole or equirectangular mapping>}, ... ]

Files written by OpenCV's ``cv2.FileStorage`` (YAML ``%YAML:1.0`` with ``!!opencv-matrix``, XML or JSON; keys
``camera_matrix`` or ``K``, ``distortion_coefficients`` / ``dist_coeffs`` / ``D``, ``image_width`` / ``image_height``,
and ``model`` / ``distortion_model`` as above or OpenCV's calibration sample's ``fisheye_model: 1``) are read too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from semloc_core.camera import (MAX_IMAGE_SIDE, CameraRig, EquirectangularCamera, FisheyeCamera, PinholeCamera,
                                forward_extrinsic, members, resized, same_aspect)
from semloc_core.io.errors import FileFormatError


class CameraFormatError(FileFormatError):
    """A camera document that does not describe a valid camera model."""


def camera_to_document(camera) -> dict:
    if isinstance(camera, (PinholeCamera, FisheyeCamera)):
        return {"model": "pinhole" if isinstance(camera, PinholeCamera) else "fisheye", "width": int(camera.width), "height": int(camera.height),
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
        if model == "fisheye":
            return FisheyeCamera(int(document["width"]), int(document["height"]), np.asarray(document["K"], float),
                                 np.asarray(document.get("dist", np.zeros(4)), float),
                                 np.asarray(document.get("T_body_cam", np.eye(4)), float))
        if model == "equirectangular":
            return EquirectangularCamera(int(document["width"]), int(document["height"]),
                                         np.asarray(document.get("T_body_cam", np.eye(4)), float),
                                         document.get("lat_top"), document.get("lat_bottom"))
        if model == "rig":
            return CameraRig(tuple(camera_from_document(c) for c in document["cameras"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CameraFormatError(f"invalid {model} camera: {error}") from None
    raise CameraFormatError(f"unknown camera model {model!r} (pinhole, fisheye, equirectangular, rig)")


# ---------------------------------------------------------------------------------------------- calibration YAML
class CalibrationError(CameraFormatError):
    """A calibration file or model is malformed (the message names the file, the field and what is wrong)."""


def _matrix(value, rows: int | None, cols: int | None, what: str) -> np.ndarray:
    try:
        if isinstance(value, dict):
            data = np.asarray(value.get("data", []), dtype=float)
            r, c = int(value.get("rows", 1)), int(value.get("cols", data.size))
        else:
            matrix = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what}: not a matrix of numbers: {value!r:.80}") from None
    if isinstance(value, dict):
        if data.size != r * c:
            raise CalibrationError(f"{what}: {r}x{c} matrix needs {r * c} values, has {data.size}")
        matrix = data.reshape(r, c)
    if rows is not None and cols is not None:
        if matrix.size != rows * cols:
            raise CalibrationError(f"{what}: expected {rows}x{cols}, got shape {matrix.shape}")
        matrix = matrix.reshape(rows, cols)
    if not np.all(np.isfinite(matrix)):
        raise CalibrationError(f"{what}: non-finite values")
    return matrix


def _as_yaml_matrix(matrix: np.ndarray) -> dict:
    matrix = np.atleast_2d(np.asarray(matrix, dtype=float))
    return {"rows": int(matrix.shape[0]), "cols": int(matrix.shape[1]), "data": [float(v) for v in matrix.ravel()]}


def _field(where: str, name: str) -> str:
    """``file: field.sub`` - where a value is, for messages (``where`` is the file, or the file and a field)."""
    return f"{where}.{name}" if ": " in where else f"{where}: {name}"


# The distortion model names of ROS camera_info (and OpenCV's "fisheye") -> the lens they describe. Why refuse the
# others: a name semloc does not know (kannala_brandt, double_sphere, ...) with 4 or 5 coefficients would otherwise
# be read as plumb_bob and give bearings tens of degrees off, without a word.
LENS_OF_DISTORTION_MODEL = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole", "none": "pinhole",
                            "": "pinhole", "equidistant": "fisheye", "fisheye": "fisheye"}


def _lens_kind(kind, distortion_model, where: str):
    """The camera model of a mapping whose ``model`` is ``kind`` and ``distortion_model`` is given: a pinhole
    mapping with a fisheye distortion model is a fisheye (as ROS writes it); an unknown or contradicting name is a
    CalibrationError."""
    if distortion_model is None or kind not in ("pinhole", "fisheye"):
        return kind
    lens = LENS_OF_DISTORTION_MODEL.get(str(distortion_model).strip().lower())
    if lens is None:
        raise CalibrationError(f"{_field(where, 'distortion_model')}: {distortion_model!r} is not a model semloc "
                               f"reads ({', '.join(name for name in LENS_OF_DISTORTION_MODEL if name)})")
    if kind == "fisheye" and lens == "pinhole":
        raise CalibrationError(f"{_field(where, 'distortion_model')}: {distortion_model!r} is a pinhole lens's, the "
                               f"model is fisheye")
    return lens


def _single_from_mapping(data: dict, where: str):
    if not isinstance(data, dict):
        raise CalibrationError(f"{where}: expected a mapping, got {type(data).__name__}")
    kind = data.get("model", "pinhole")
    try:
        width, height = int(data["image_width"]), int(data["image_height"])
    except (KeyError, TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{where}: image_width and image_height are required integers") from None
    for name, side in (("image_width", width), ("image_height", height)):
        if not 1 <= side <= MAX_IMAGE_SIDE:
            raise CalibrationError(f"{_field(where, name)}: {side} is outside [1, {MAX_IMAGE_SIDE}] pixels")
    T = forward_extrinsic() if "T_body_cam" not in data else _matrix(data["T_body_cam"], 4, 4,
                                                                     _field(where, "T_body_cam"))
    kind = _lens_kind(kind, data.get("distortion_model"), where)
    try:
        if kind in ("pinhole", "fisheye"):
            if "camera_matrix" not in data:
                raise CalibrationError(f"{where}: camera_matrix is required for a {kind} camera")
            K = _matrix(data["camera_matrix"], 3, 3, _field(where, "camera_matrix"))
            dist = data.get("distortion_coefficients")
            if dist is not None:
                dist = _matrix(dist, None, None, _field(where, "distortion_coefficients")).ravel()
            if kind == "fisheye":
                return FisheyeCamera(width, height, K, np.zeros(4) if dist is None else dist, T)
            dist = np.zeros(0) if dist is None else dist
            return PinholeCamera(width, height, K, dist, T)
        if kind == "equirectangular":
            return EquirectangularCamera(width, height, T, data.get("lat_top"), data.get("lat_bottom"))
    except (TypeError, ValueError) as error:
        if isinstance(error, CalibrationError):
            raise
        raise CalibrationError(f"{where}: {error}") from None
    raise CalibrationError(f"{where}: unknown camera model {kind!r} (pinhole, fisheye, equirectangular or rig)")


def camera_from_mapping(data: dict, where: str = "calibration"):
    if not isinstance(data, dict):
        raise CalibrationError(f"{where}: expected a mapping")
    if data.get("model") == "rig":
        cameras = data.get("cameras")
        if not isinstance(cameras, list) or not cameras:
            raise CalibrationError(f"{where}: a rig needs a non-empty 'cameras' list")
        return CameraRig(tuple(_single_from_mapping(c, _field(where, f"cameras[{i}]")) for i, c in enumerate(cameras)))
    return _single_from_mapping(data, where)


def _read_opencv_storage(path: Path) -> dict:
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as error:
        raise CalibrationError(f"{path}: OpenCV cannot read it: {error}") from None
    try:
        def node(*names):
            for name in names:
                n = storage.getNode(name)
                if not n.empty():
                    return n
            return None

        K, dist = node("camera_matrix", "K", "cameraMatrix"), node("distortion_coefficients", "dist_coeffs", "D",
                                                                    "distCoeffs")
        width, height = node("image_width", "width"), node("image_height", "height")
        if K is None or width is None or height is None:
            raise CalibrationError(f"{path}: an OpenCV file needs camera_matrix, image_width and image_height")
        data = {"image_width": int(width.real()), "image_height": int(height.real()), "camera_matrix": K.mat()}
        for name in ("model", "distortion_model"):
            if (text := node(name)) is not None:
                data[name] = text.string()
        fisheye = node("fisheye_model")  # OpenCV's calibration sample (tutorial_code/calib3d/camera_calibration)
        if fisheye is not None and fisheye.real() and "model" not in data:
            data["model"] = "fisheye"
        if dist is not None:
            data["distortion_coefficients"] = dist.mat()
        T = node("T_body_cam")
        if T is not None:
            data["T_body_cam"] = T.mat()
        return data
    finally:
        storage.release()


def _written_by_opencv(text: str) -> bool:
    """Whether a file is ``cv2.FileStorage``'s: its YAML header, XML, or JSON with OpenCV's matrices."""
    start = text.lstrip()
    return start.startswith(("%YAML", "<?xml", "<opencv_storage")) or (start.startswith("{") and
                                                                        '"opencv-matrix"' in text)


def load_camera(path: str | Path):
    """A ``PinholeCamera``, ``EquirectangularCamera`` or ``CameraRig`` from a calibration YAML file."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise CalibrationError(f"{path}: cannot read it: {error}") from None
    if _written_by_opencv(text):
        return camera_from_mapping(_read_opencv_storage(path), str(path))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise CalibrationError(f"{path}: not valid YAML: {error}") from None
    return camera_from_mapping(data, str(path))


def _single_to_mapping(camera, name: str = "") -> dict:
    data: dict = {}
    if isinstance(camera, PinholeCamera):
        data = {"model": "pinhole", "image_width": camera.width, "image_height": camera.height,
                "camera_matrix": _as_yaml_matrix(camera.K),
                "distortion_model": "plumb_bob" if camera.dist.size in (0, 5) else "rational_polynomial",
                "distortion_coefficients": _as_yaml_matrix(camera.dist.reshape(1, -1))}
    elif isinstance(camera, FisheyeCamera):
        data = {"model": "fisheye", "image_width": camera.width, "image_height": camera.height,
                "camera_matrix": _as_yaml_matrix(camera.K), "distortion_model": "equidistant",
                "distortion_coefficients": _as_yaml_matrix(camera.dist.reshape(1, -1))}
    elif isinstance(camera, EquirectangularCamera):
        data = {"model": "equirectangular", "image_width": camera.width, "image_height": camera.height,
                "lat_top": float(camera.lat_top), "lat_bottom": float(camera.lat_bottom)}
    else:
        raise CalibrationError(f"cannot write a {type(camera).__name__}")
    if name:
        data["camera_name"] = name
    data["T_body_cam"] = _as_yaml_matrix(camera.T_body_cam)
    return data


def camera_to_mapping(camera, name: str = "") -> dict:
    if isinstance(camera, CameraRig):
        return {"model": "rig", "camera_name": name, "cameras": [_single_to_mapping(c) for c in camera.cameras]}
    return _single_to_mapping(camera, name)


def save_camera(camera, path: str | Path, name: str = "") -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(camera_to_mapping(camera, name), sort_keys=False))
    return path


def fit_to_frames(camera, sizes: list[tuple[int, int]], where: str) -> tuple[object, list[str]]:
    """``camera`` (a model or rig) made to fit a source whose member cameras give ``sizes`` (width, height) frames,
    and a warning per member it had to change: a member calibrated at another size with the same aspect ratio is
    scaled (:func:`semloc_core.camera.resized`); any other difference raises CalibrationError naming ``where`` (the
    calibration file, or "of <the source>") and both sizes."""
    cameras = members(camera)
    if len(sizes) != len(cameras):
        raise CalibrationError(f"the calibration {where} has {len(cameras)} camera(s), the source gives {len(sizes)} "
                               f"image(s) per frame")
    fitted, warnings = [], []
    for index, (model, (width, height)) in enumerate(zip(cameras, sizes)):
        name = f"camera {index}: " if len(cameras) > 1 else ""
        if (model.width, model.height) == (width, height):
            fitted.append(model)
        elif same_aspect(width, height, model.width, model.height):
            fitted.append(resized(model, width, height))
            warnings.append(f"{name}the source's frames are {width}x{height}, the calibration {where} is "
                            f"{model.width}x{model.height}: intrinsics scaled by {width / model.width:.4g} (same "
                            f"aspect ratio); calibrate this camera for best results (semloc calibrate-camera)")
        else:
            raise CalibrationError(f"{name}the calibration {where} is for {model.width}x{model.height} images, the "
                                   f"source gives {width}x{height} (another aspect ratio): calibrate this camera "
                                   f"(semloc calibrate-camera) or give its calibration")
    return (fitted[0] if not isinstance(camera, CameraRig) else CameraRig(tuple(fitted))), warnings
