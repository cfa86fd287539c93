"""Reading what the detectors need from disk: template libraries, exemplar images, cascades, DNN models, configs.

A **template library** is a folder with one sub-folder of exemplar images per class::

    library/
      clock/      front.png  side.jpg ...
      trashcan/   a.png
      ...

Each image is one exemplar (a single view for the §4.3 templates; several views of a class for the §5.3 multi-view
templates). An exemplar's object mask, optional, comes from a PNG alpha channel (alpha >= 128), or from a grey image
of the same name in ``<class>/masks/`` or in a sibling folder ``<library>_masks/<class>/`` (the simulator's layout);
non-zero = object. Files whose names start with '.' are skipped; so are sub-folders without images.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from semloc_core.io.atomic import replacing
from semloc_core.io.errors import FileFormatError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


class DetectorModelError(FileFormatError):
    """A template library, model or detector configuration that cannot be used."""


@dataclass(frozen=True, eq=False)
class Exemplar:
    class_name: str
    image: np.ndarray            # uint8 BGR (H, W, 3)
    mask: np.ndarray | None      # (H, W) bool from the alpha channel, or None
    path: str


def _mask_file(path: Path) -> Path | None:
    """A separate mask for exemplar ``path``: ``<class>/masks/<name>`` or ``<library>_masks/<class>/<name>``."""
    class_dir = path.parent
    sibling = class_dir.parent.parent / f"{class_dir.parent.name}_masks" / class_dir.name
    for folder in (class_dir / "masks", sibling):
        for name in (path.name, path.stem + ".png"):
            if (folder / name).is_file():
                return folder / name
    return None


def load_exemplar(path, class_name: str | None = None) -> Exemplar:
    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DetectorModelError(f"{path}: not a readable image")
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(1.0, float(image.max())))
    mask = None
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        mask = image[..., 3] >= 128
        image = np.ascontiguousarray(image[..., :3])
        if not mask.any():
            raise DetectorModelError(f"{path}: the alpha channel masks out every pixel")
    mask_path = _mask_file(path) if mask is None else None
    if mask_path is not None:
        grey = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if grey is None or grey.shape != image.shape[:2]:
            raise DetectorModelError(f"{mask_path}: not a mask of the size of {path.name} ({image.shape[1]}x"
                                     f"{image.shape[0]})")
        mask = grey > 0
        if not mask.any():
            raise DetectorModelError(f"{mask_path}: the mask is empty")
    return Exemplar(class_name or path.parent.name, image, mask, str(path))


def load_template_library(folder, pattern: str | None = None) -> dict[str, list[Exemplar]]:
    """Class name -> its exemplars, classes and files in sorted order (deterministic).

    ``pattern`` (a glob such as ``"*_el35.png"``) keeps only the exemplar files whose name matches it.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DetectorModelError(f"template library {folder} is not a folder")
    library: dict[str, list[Exemplar]] = {}
    for class_dir in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        files = sorted(p for p in class_dir.iterdir()
                       if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES
                       and (pattern is None or fnmatch.fnmatch(p.name, pattern)))
        if files:
            library[class_dir.name] = [load_exemplar(p, class_dir.name) for p in files]
    if not library:
        raise DetectorModelError(f"template library {folder} has no class folder with images "
                                 f"({', '.join(IMAGE_SUFFIXES)}{'' if pattern is None else ' matching ' + pattern})")
    return library


def load_cascade(name_or_path: str) -> cv2.CascadeClassifier:
    """A Haar/LBP cascade: a file path, or the name of one shipped in ``cv2.data.haarcascades``."""
    path = Path(name_or_path)
    if not path.is_file():
        shipped = Path(cv2.data.haarcascades) / name_or_path
        if not shipped.is_file():
            available = sorted(p.name for p in Path(cv2.data.haarcascades).glob("*.xml"))
            raise DetectorModelError(f"cascade {name_or_path!r} is neither a file nor shipped with OpenCV "
                                     f"(shipped: {', '.join(available)})")
        path = shipped
    cascade = cv2.CascadeClassifier(str(path))
    if cascade.empty():
        raise DetectorModelError(f"{path}: OpenCV could not load the cascade")
    return cascade


def load_dnn(model, config=None):
    """A ``cv2.dnn.Net`` from a model file (ONNX, TensorFlow .pb, Caffe .caffemodel + .prototxt, Darknet...)."""
    model = Path(model)
    if not model.is_file():
        raise DetectorModelError(f"DNN model {model} does not exist")
    try:
        net = cv2.dnn.readNet(str(model), "" if config is None else str(config))
    except cv2.error as error:
        raise DetectorModelError(f"{model}: OpenCV dnn could not read the model: {error}") from error
    if net.empty():
        raise DetectorModelError(f"{model}: OpenCV dnn loaded an empty network")
    return net


def load_detector_config(path) -> dict:
    """A detector configuration file (YAML or JSON) as a dict; relative paths in it are made absolute."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise DetectorModelError(f"{path}: cannot read the detector configuration: {error}") from error
    if not isinstance(document, dict):
        raise DetectorModelError(f"{path}: a detector configuration must be a mapping")
    for key in ("templates", "model", "model_config", "cascade"):
        value = document.get(key)
        if isinstance(value, str) and not Path(value).is_absolute() and (path.parent / value).exists():
            document[key] = str((path.parent / value).resolve())
    return document


LINEAR_MODEL_FORMAT = "semloc-linear-window-detector"
LINEAR_MODEL_VERSION = 1


def save_linear_model(path, model) -> Path:
    """Write a ``LinearWindowModel`` as ``.npz`` (no pickle), atomically: ``meta`` (UTF-8 JSON: format, version,
    classes, feature parameters, scales, training info) and ``weights_<k>`` / ``biases``."""
    import json
    from dataclasses import asdict

    path = Path(path)
    meta = {"format": LINEAR_MODEL_FORMAT, "version": LINEAR_MODEL_VERSION, "classes": list(model.classes),
            "params": asdict(model.params), "scales": list(model.scales), "info": model.info}
    arrays = {f"weights_{k}": w for k, w in enumerate(model.weights)}
    arrays["biases"] = model.biases
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with replacing(path) as stream:
        np.savez(stream, **arrays)
    return path


def read_linear_model(path) -> dict:
    """The parts of a model ``save_linear_model`` wrote, as ``LinearWindowModel``'s fields: ``classes``, ``weights``,
    ``biases``, ``params`` (a mapping of the feature parameters), ``scales``, ``info``; a file that is not one gets a
    ``DetectorModelError`` saying why (``semloc_core.detection.config.load_linear_model`` builds the model)."""
    import json

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise DetectorModelError(f"{path}: not a readable linear detector model: {error}") from error
    try:
        meta = json.loads(arrays["meta"].tobytes().decode())
        if meta.get("format") != LINEAR_MODEL_FORMAT:
            raise DetectorModelError(f"{path}: not a {LINEAR_MODEL_FORMAT} file (format {meta.get('format')!r})")
        if meta.get("version") != LINEAR_MODEL_VERSION:
            raise DetectorModelError(f"{path}: model version {meta.get('version')}, this semloc reads "
                                     f"{LINEAR_MODEL_VERSION}")
        classes = meta["classes"]
        return {"classes": tuple(classes), "weights": tuple(arrays[f"weights_{k}"] for k in range(len(classes))),
                "biases": arrays["biases"], "params": dict(meta["params"]), "scales": tuple(meta["scales"]),
                "info": meta.get("info", {})}
    except DetectorModelError:
        raise
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as error:
        raise DetectorModelError(f"{path}: invalid linear detector model: {error!r}") from error
