"""Datasets: one reader for simulated worlds and real recordings.

``open_dataset(path)`` returns a :class:`Dataset` for

* a dataset written by ``semloc sim`` (a folder with ``dataset.json``; layout in docs/datasets.md),
* an image folder with a loop ground-truth matrix (the layout of ``rtabmap_loop_samples``: ``images/1.jpg ..`` and
  ``*GT*.bmp``; the matrix's row = later frame, column = earlier frame, 255 = loop),
* a TUM trajectory file (``t x y z qx qy qz qw``, T_world_cam), or a folder with ``groundtruth.txt``,
* an RGB-D Scenes v2 ``.pose`` file (placed in a z-up world around its table, see
  ``trajectory.level_real_trajectory``).

Whatever is not in the source is ``None`` (e.g. no images in a trajectory file, no poses in an image folder).
``semloc_core.sim.make_scenario`` returns a subclass that renders its frames on demand, so algorithms take either.

Conventions: ``T_world_body`` (N, 4, 4) poses of the body frame (a robot base on the floor, or the levelled frame
under a hand-held camera); ``T_body_cam`` (N, 4, 4) per-frame camera extrinsics (static for robots, the attitude an
IMU reports for hand-held cameras; ``None`` for rigs, whose members keep their own); ``T_world_cam`` their product
(for a rig: camera 0). Odometry row i is the motion from frame i-1 to frame i (row 0 is zero).
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from semloc_core.camera import CameraRig, PinholeCamera
from semloc_core.geometry import invert_transform, level_frame_of_camera, transform_to_pose2d, wrap_angle
from semloc_core.io.atomic import replace_text
from semloc_core.io.camera_model import camera_from_document, camera_to_document
from semloc_core.io.errors import FileFormatError
from semloc_core.io.semantic_map import SemanticMap, load_semantic_map, save_semantic_map
from semloc_core.io.trajectory import (level_real_trajectory, read_rgbd_scenes_poses, read_tum, write_planar_tum,
                                       write_tum)

FORMAT_NAME = "semloc.dataset"
FORMAT_VERSION = 1
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".tif", ".tiff")


class DatasetError(FileFormatError):
    """A dataset that cannot be opened or lacks what was asked of it."""


# ----------------------------------------------------------------------------------------------- records

@dataclass(frozen=True, eq=False)
class Odometry:
    """Per-frame body-frame motion: the constant twist (v forward, v_lateral left, omega) that carries the body from
    frame i-1 to frame i in ``dt`` seconds (SE(2) log; exact before noise). Row 0 is zero."""

    v: np.ndarray
    v_lateral: np.ndarray
    omega: np.ndarray
    dt: np.ndarray

    def __len__(self) -> int:
        return int(self.v.shape[0])

    def as_array(self) -> np.ndarray:
        """(N, 4) columns v, v_lateral, omega, dt."""
        return np.stack([self.v, self.v_lateral, self.omega, self.dt], axis=1)

    def increments(self) -> np.ndarray:
        """(N, 3) body-frame increments (dx, dy, dtheta) from frame i-1 to frame i (SE(2) exp of the twist)."""
        return twist_to_increment(self.v * self.dt, self.v_lateral * self.dt, self.omega * self.dt)

    def integrate(self, start_pose) -> np.ndarray:
        """Planar poses (N, 3) obtained by chaining the increments from ``start_pose`` (x, y, theta) at frame 0."""
        inc = self.increments()
        poses = np.empty((len(self), 3))
        poses[0] = start_pose
        for i in range(1, len(self)):
            x, y, th = poses[i - 1]
            c, s = np.cos(th), np.sin(th)
            poses[i] = (x + c * inc[i, 0] - s * inc[i, 1], y + s * inc[i, 0] + c * inc[i, 1], th + inc[i, 2])
        poses[:, 2] = wrap_angle(poses[:, 2])
        return poses


def twist_to_increment(dx_twist, dy_twist, dtheta) -> np.ndarray:
    """SE(2) exponential: body increment (dx, dy, dtheta) of a constant twist integrated over one step."""
    dx_twist, dy_twist, dtheta = (np.asarray(a, float) for a in (dx_twist, dy_twist, dtheta))
    small = np.abs(dtheta) < 1e-9
    safe = np.where(small, 1.0, dtheta)
    a = np.where(small, 1.0 - dtheta ** 2 / 6, np.sin(safe) / safe)
    b = np.where(small, dtheta / 2, (1 - np.cos(safe)) / safe)
    return np.stack([a * dx_twist - b * dy_twist, b * dx_twist + a * dy_twist, dtheta], axis=-1)


def increment_to_twist(increment) -> np.ndarray:
    """SE(2) logarithm: the twist displacement (dx, dy, dtheta) whose exponential is ``increment``."""
    inc = np.asarray(increment, float)
    dtheta = inc[..., 2]
    small = np.abs(dtheta) < 1e-9
    safe = np.where(small, 1.0, dtheta)
    a = np.where(small, 1.0 - dtheta ** 2 / 6, np.sin(safe) / safe)
    b = np.where(small, dtheta / 2, (1 - np.cos(safe)) / safe)
    det = a * a + b * b
    dx = (a * inc[..., 0] + b * inc[..., 1]) / det
    dy = (-b * inc[..., 0] + a * inc[..., 1]) / det
    return np.stack([dx, dy, dtheta], axis=-1)


def relative_increments(poses2d: np.ndarray) -> np.ndarray:
    """(N, 3) body-frame increments between consecutive planar poses (row 0 zero)."""
    poses2d = np.asarray(poses2d, float)
    out = np.zeros_like(poses2d)
    d = poses2d[1:, :2] - poses2d[:-1, :2]
    c, s = np.cos(poses2d[:-1, 2]), np.sin(poses2d[:-1, 2])
    out[1:, 0] = c * d[:, 0] + s * d[:, 1]
    out[1:, 1] = -s * d[:, 0] + c * d[:, 1]
    out[1:, 2] = wrap_angle(poses2d[1:, 2] - poses2d[:-1, 2])
    return out


@dataclass(frozen=True)
class VisibleObject:
    """One object seen in one frame (one camera of a rig).

    Boxes are ``[x_min, y_min, x_max, y_max]`` in pixel-edge coordinates (a single pixel (u, v) spans
    ``[u - 0.5, v - 0.5, u + 0.5, v + 0.5]``): ``box`` bounds the whole object as if nothing hid it (clipped to the
    image), ``visible_box`` its visible pixels (in a panorama, an object across the left/right seam has
    ``x_min < -0.5``: columns left of 0 continue from the right edge). ``bearing`` (rad, docs/conventions.md) and ``elevation`` of its centre
    in the body frame, ``distance`` from the camera centre (m). ``occluded_fraction`` = 1 - visible / unoccluded
    pixels inside the image; ``truncated`` when part of it falls outside the image.
    """

    object_index: int
    class_name: str
    camera: int
    box: tuple[float, float, float, float]
    visible_box: tuple[float, float, float, float]
    pixels: int
    visible_pixels: int
    occluded_fraction: float
    bearing: float
    elevation: float
    distance: float
    truncated: bool

    def to_dict(self) -> dict:
        d = asdict(self)
        d["box"] = list(self.box)
        d["visible_box"] = list(self.visible_box)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VisibleObject":
        d = dict(d)
        d["box"] = tuple(float(x) for x in d["box"])
        d["visible_box"] = tuple(float(x) for x in d["visible_box"])
        return cls(**d)


@dataclass(frozen=True)
class ViewExemplar:
    """A rendered view of a class's object: ``azimuth`` counter-clockwise from the object's front, ``elevation``
    above its horizontal plane (radians), from ``distance`` metres."""

    class_name: str
    image: np.ndarray
    mask: np.ndarray
    azimuth: float
    elevation: float
    distance: float


# ----------------------------------------------------------------------------------------------- the dataset

class Dataset:
    """Frames, camera model and ground truth of a recording (real or simulated); see the module docstring."""

    def __init__(self, name: str, n_frames: int, camera=None, stamps_ns=None, T_world_body=None, T_body_cam=None,
                 semantic_map: SemanticMap | None = None, odometry: Odometry | None = None, loop_gt=None,
                 loop_gt_soft=None, image_source: Callable[[int], object] | None = None,
                 visible_source: Callable[[int], list[VisibleObject]] | None = None,
                 exemplar_dir: Path | None = None, multiview_dir: Path | None = None, metadata: dict | None = None,
                 path: Path | None = None, extra_gt: dict | None = None) -> None:
        self.name = name
        self._n = int(n_frames)
        if self._n < 0:
            raise DatasetError("a dataset cannot have a negative frame count")
        self.camera = camera
        self.stamps_ns = (np.arange(self._n, dtype=np.int64) * 33_333_333 if stamps_ns is None
                          else np.asarray(stamps_ns, np.int64))
        self.T_world_body = None if T_world_body is None else np.asarray(T_world_body, float)
        self.T_body_cam = None if T_body_cam is None else np.asarray(T_body_cam, float)
        self.semantic_map = semantic_map
        self.odometry = odometry
        self.loop_gt = None if loop_gt is None else np.asarray(loop_gt, bool)
        self.loop_gt_soft = None if loop_gt_soft is None else np.asarray(loop_gt_soft, bool)
        self._image_source = image_source
        self._visible_source = visible_source
        self.exemplar_dir = exemplar_dir
        self.multiview_dir = multiview_dir
        self.metadata = dict(metadata or {})
        self.path = path
        # Further (N, N) bool pair matrices, e.g. "aliased_gt": same place on another floor.
        self.extra_gt = {k: np.asarray(v, bool) for k, v in (extra_gt or {}).items()}
        self._check()

    def _check(self) -> None:
        n = self._n
        if self.stamps_ns.shape != (n,):
            raise DatasetError(f"{self.name}: {self.stamps_ns.shape[0]} stamps for {n} frames")
        for label, value in (("T_world_body", self.T_world_body), ("T_body_cam", self.T_body_cam)):
            if value is not None and value.shape != (n, 4, 4):
                raise DatasetError(f"{self.name}: {label} has shape {value.shape}, expected ({n}, 4, 4)")
        for label, value in (("loop_gt", self.loop_gt), ("loop_gt_soft", self.loop_gt_soft)):
            if value is not None and value.shape != (n, n):
                raise DatasetError(f"{self.name}: {label} has shape {value.shape}, expected ({n}, {n})")
        for label, value in self.extra_gt.items():
            if value.shape != (n, n):
                raise DatasetError(f"{self.name}: {label} has shape {value.shape}, expected ({n}, {n})")
        if self.odometry is not None and len(self.odometry) != n:
            raise DatasetError(f"{self.name}: odometry has {len(self.odometry)} rows for {n} frames")

    def __len__(self) -> int:
        return self._n

    def __repr__(self) -> str:
        have = [k for k in ("camera", "T_world_body", "odometry", "semantic_map", "loop_gt")
                if getattr(self, k) is not None]
        return f"Dataset({self.name!r}, {self._n} frames, with {', '.join(have) or 'nothing else'})"

    # ------------------------------------------------------------------ frames

    @property
    def has_images(self) -> bool:
        return self._image_source is not None

    def image(self, i: int):
        """Frame i as BGR uint8 (H, W, 3); for a rig, a tuple with one image per camera."""
        if self._image_source is None:
            raise DatasetError(f"{self.name} has no images")
        i = self._index(i)
        return self._image_source(i)

    def _index(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < self._n:
            raise IndexError(f"frame {i} out of range [0, {self._n})")
        return i

    # ------------------------------------------------------------------ poses

    @property
    def has_poses(self) -> bool:
        return self.T_world_body is not None

    def _require_poses(self) -> None:
        if self.T_world_body is None:
            raise DatasetError(f"{self.name} has no ground-truth poses")

    @property
    def T_world_cam(self) -> np.ndarray:
        """(N, 4, 4) camera poses (camera 0 for a rig)."""
        self._require_poses()
        if self.T_body_cam is not None:
            return self.T_world_body @ self.T_body_cam
        if isinstance(self.camera, CameraRig):
            return self.T_world_body @ self.camera.cameras[0].T_body_cam
        return self.T_world_body @ (self.camera.T_body_cam if self.camera is not None else np.eye(4))

    @property
    def poses2d(self) -> np.ndarray:
        """(N, 3) planar poses (x, y, theta) of the body frame."""
        self._require_poses()
        return np.stack([transform_to_pose2d(T) for T in self.T_world_body])

    def T_body_cam_at(self, i: int) -> np.ndarray | None:
        """The camera's extrinsic at frame i (None for a rig)."""
        if self.T_body_cam is not None:
            return self.T_body_cam[self._index(i)]
        if isinstance(self.camera, CameraRig) or self.camera is None:
            return None
        return self.camera.T_body_cam

    # ------------------------------------------------------------------ ground truth

    def visible_objects(self, i: int) -> list[VisibleObject]:
        if self._visible_source is None:
            raise DatasetError(f"{self.name} has no per-frame object ground truth")
        return self._visible_source(self._index(i))

    def loop_gt_at(self, distance: float, soft_distance: float | None = None, max_angle: float | None = None):
        """Loop ground truth recomputed from the poses at another threshold: (hard, soft) (N, N) bool."""
        from semloc_core.eval.loops import loop_ground_truth

        self._require_poses()
        T = self.T_world_cam
        return loop_ground_truth(T[:, :3, 3], T[:, :3, 2], distance, soft_distance, max_angle)

    def exemplars(self) -> dict[str, list[np.ndarray]]:
        """One or more exemplar images per class (BGR), read from the exemplar folder."""
        if self.exemplar_dir is None:
            raise DatasetError(f"{self.name} has no exemplars")
        return read_exemplar_folder(self.exemplar_dir)

    def exemplar_masks(self) -> dict[str, list[np.ndarray]]:
        """The masks (uint8, 255 = object) of ``exemplars()``, same order, from ``<exemplars>_masks/<class>/``;
        classes without masks are left out."""
        if self.exemplar_dir is None:
            raise DatasetError(f"{self.name} has no exemplars")
        folder = Path(self.exemplar_dir)
        masks_dir = folder.parent / (folder.name + "_masks")
        out: dict[str, list[np.ndarray]] = {}
        for class_dir in sorted(p for p in folder.iterdir() if p.is_dir()):
            files = [p for p in sorted(class_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]
            masks = [cv2.imread(str(masks_dir / class_dir.name / (p.stem + ".png")), cv2.IMREAD_GRAYSCALE)
                     for p in files]
            if files and all(m is not None for m in masks):
                out[class_dir.name] = masks
        return out

    def multiview_exemplars(self) -> dict[str, list[ViewExemplar]]:
        if self.multiview_dir is None:
            raise DatasetError(f"{self.name} has no multi-view exemplars")
        return read_multiview_folder(self.multiview_dir)


# ----------------------------------------------------------------------------------------------- exemplar folders

def read_exemplar_folder(folder) -> dict[str, list[np.ndarray]]:
    """``folder/<class>/*.png|jpg`` -> {class: [BGR images]} (the detector's template-library layout)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"exemplar folder {folder} does not exist")
    out: dict[str, list[np.ndarray]] = {}
    for class_dir in sorted(p for p in folder.iterdir() if p.is_dir()):
        images = [_read_image(p) for p in sorted(class_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]
        if images:
            out[class_dir.name] = images
    return out


def write_exemplar_folder(folder, exemplars: dict[str, list[np.ndarray]], masks: dict | None = None) -> None:
    folder = Path(folder)
    for class_name, images in exemplars.items():
        (folder / class_name).mkdir(parents=True, exist_ok=True)
        for k, image in enumerate(images):
            _write_png(folder / class_name / f"{class_name}_{k:02d}.png", image)
    for class_name, class_masks in (masks or {}).items():
        (folder.parent / (folder.name + "_masks") / class_name).mkdir(parents=True, exist_ok=True)
        for k, mask in enumerate(class_masks):
            _write_png(folder.parent / (folder.name + "_masks") / class_name / f"{class_name}_{k:02d}.png", mask)


def write_multiview_folder(folder, views: dict[str, list[ViewExemplar]]) -> None:
    """``folder/<class>/<class>_az<deg>_el<deg>.png``, masks in ``folder/<class>/masks/``, and ``views.json``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    index = []
    for class_name, class_views in views.items():
        (folder / class_name / "masks").mkdir(parents=True, exist_ok=True)
        for view in class_views:
            stem = f"{class_name}_az{round(np.degrees(view.azimuth)) % 360:03d}_el{round(np.degrees(view.elevation)):02d}"
            _write_png(folder / class_name / f"{stem}.png", view.image)
            _write_png(folder / class_name / "masks" / f"{stem}.png", view.mask)
            index.append({"class": class_name, "file": f"{class_name}/{stem}.png",
                          "mask": f"{class_name}/masks/{stem}.png", "azimuth_deg": float(np.degrees(view.azimuth)),
                          "elevation_deg": float(np.degrees(view.elevation)), "distance_m": float(view.distance)})
    (folder / "views.json").write_text(json.dumps({"format": "semloc.multiview_exemplars", "version": 1,
                                                   "views": index}, indent=1))


def read_multiview_folder(folder) -> dict[str, list[ViewExemplar]]:
    folder = Path(folder)
    try:
        document = json.loads((folder / "views.json").read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"cannot read {folder / 'views.json'}: {error}") from None
    out: dict[str, list[ViewExemplar]] = {}
    for entry in document.get("views", []):
        image = _read_image(folder / entry["file"])
        mask_path = folder / entry.get("mask", "")
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) if entry.get("mask") else None
        if mask is None:
            mask = np.full(image.shape[:2], 255, np.uint8)
        out.setdefault(entry["class"], []).append(ViewExemplar(
            entry["class"], image, mask, np.radians(entry["azimuth_deg"]), np.radians(entry["elevation_deg"]),
            float(entry["distance_m"])))
    return out


# ----------------------------------------------------------------------------------------------- file helpers

def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DatasetError(f"cannot read image {path}")
    return image


def _write_png(path: Path, image: np.ndarray, compression: int = 1) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, compression]):
        raise DatasetError(f"cannot write {path}")


def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def _list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=_natural_key)


def _symmetric(matrix: np.ndarray) -> np.ndarray:
    m = np.asarray(matrix, bool)
    m = m | m.T
    np.fill_diagonal(m, False)
    return m


# ----------------------------------------------------------------------------------------------- writing

def write_dataset(dataset: Dataset, path, progress: Callable[[int, int], None] | None = None,
                  extra: dict | None = None, exemplars=None, exemplar_masks=None, multiview=None,
                  visible: bool = True) -> Path:
    """Write any Dataset (typically a simulated scenario) in the semloc layout; returns the folder.

    ``exemplars`` {class: [BGR]} and ``multiview`` {class: [ViewExemplar]} are written when given; ``progress``
    is called as ``progress(done, total)`` after every frame.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    n = len(dataset)
    rig = isinstance(dataset.camera, CameraRig)
    files: dict = {}
    if dataset.has_images:
        if rig:
            for k in range(len(dataset.camera.cameras)):
                (path / "images" / f"cam{k}").mkdir(parents=True, exist_ok=True)
            files["images"] = "images/cam{camera}/{frame:06d}.png"
        else:
            (path / "images").mkdir(exist_ok=True)
            files["images"] = "images/{frame:06d}.png"
    visible_lines = []
    with_visible = visible and dataset._visible_source is not None
    for i in range(n):
        if dataset.has_images:
            image = dataset.image(i)
            if rig:
                for k, img in enumerate(image):
                    _write_png(path / files["images"].format(camera=k, frame=i), img)
            else:
                _write_png(path / files["images"].format(frame=i), image)
        if with_visible:
            visible_lines.append(json.dumps({"frame": i, "objects": [o.to_dict() for o in dataset.visible_objects(i)]}))
        if progress is not None:
            progress(i + 1, n)
    if with_visible:
        (path / "visible_objects.jsonl").write_text("\n".join(visible_lines) + "\n")
        files["visible_objects"] = "visible_objects.jsonl"
    if dataset.camera is not None:
        (path / "camera.json").write_text(json.dumps(camera_to_document(dataset.camera), indent=1))
        files["camera"] = "camera.json"
    arrays = {"stamps_ns": dataset.stamps_ns}
    if dataset.has_poses:
        arrays["T_world_body"] = dataset.T_world_body
        arrays["poses2d"] = dataset.poses2d
        write_tum(path / "groundtruth.txt", np.asarray(dataset.stamps_ns, np.int64), dataset.T_world_cam)
        files["groundtruth"] = "groundtruth.txt"
        # the planar body pose, the localizer's frame: `evo_ape tum groundtruth_body.tum trajectory.tum` compares
        # like with like (docs/conventions.md, "Files and their frames")
        write_planar_tum(path / "groundtruth_body.tum", np.asarray(dataset.stamps_ns, np.int64), dataset.poses2d)
        files["groundtruth_body"] = "groundtruth_body.tum"
    if dataset.T_body_cam is not None:
        arrays["T_body_cam"] = dataset.T_body_cam
    if dataset.odometry is not None:
        arrays["odometry"] = dataset.odometry.as_array()
        rows = ["frame,stamp_ns,v,v_lateral,omega,dt"]
        for i, (v, vl, w, dt) in enumerate(dataset.odometry.as_array()):
            rows.append(f"{i},{dataset.stamps_ns[i]},{v:.9g},{vl:.9g},{w:.9g},{dt:.9g}")
        (path / "odometry.csv").write_text("\n".join(rows) + "\n")
        files["odometry"] = "odometry.csv"
    np.savez(path / "poses.npz", **arrays)
    files["poses"] = "poses.npz"
    if dataset.semantic_map is not None:
        save_semantic_map(dataset.semantic_map, path / "semantic_map.json")
        files["semantic_map"] = "semantic_map.json"
    for label in ("loop_gt", "loop_gt_soft"):
        matrix = getattr(dataset, label)
        if matrix is not None:
            np.save(path / f"{label}.npy", matrix.astype(bool), allow_pickle=False)
            # The same matrix as an image, lower triangle (row = later frame), like rtabmap's samples_GT.bmp.
            _write_png(path / f"{label}.png", (np.tril(matrix, -1) * 255).astype(np.uint8))
            files[label] = f"{label}.npy"
    for label, matrix in dataset.extra_gt.items():
        np.save(path / f"{label}.npy", matrix.astype(bool), allow_pickle=False)
        files.setdefault("extra_gt", {})[label] = f"{label}.npy"
    if exemplars is not None:
        write_exemplar_folder(path / "exemplars", exemplars, exemplar_masks)
        files["exemplars"] = "exemplars"
    if multiview is not None:
        write_multiview_folder(path / "exemplars_multiview", multiview)
        files["multiview_exemplars"] = "exemplars_multiview"
    document = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "name": dataset.name, "frames": n,
                "files": files, "metadata": _jsonable(dataset.metadata)}
    document.update(_jsonable(extra or {}))
    replace_text(path / "dataset.json", json.dumps(document, indent=1))
    return path


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


# ----------------------------------------------------------------------------------------------- reading

def open_dataset(path) -> Dataset:
    """Open a semloc dataset folder, an image folder with loop ground truth, a TUM file or an RGB-D Scenes pose
    file (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path} does not exist")
    if path.is_file():
        if path.suffix == ".pose":
            return _open_rgbd_scenes(path)
        return _open_tum(path)
    if (path / "dataset.json").is_file():
        return _open_semloc(path)
    return _open_image_folder(path)


def _open_semloc(path: Path) -> Dataset:
    try:
        document = json.loads((path / "dataset.json").read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"cannot read {path / 'dataset.json'}: {error}") from None
    if document.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: not a {FORMAT_NAME} folder (format {document.get('format')!r})")
    if document.get("version") != FORMAT_VERSION:
        raise DatasetError(f"{path}: unsupported dataset version {document.get('version')}")
    files = document.get("files", {})
    n = int(document["frames"])
    camera = camera_from_document(json.loads((path / files["camera"]).read_text())) if "camera" in files else None
    with np.load(path / files.get("poses", "poses.npz"), allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    odometry = None
    if "odometry" in arrays:
        o = arrays["odometry"]
        odometry = Odometry(o[:, 0], o[:, 1], o[:, 2], o[:, 3])
    semantic_map = load_semantic_map(path / files["semantic_map"]) if "semantic_map" in files else None
    loops = {k: np.load(path / files[k], allow_pickle=False) if k in files else None
             for k in ("loop_gt", "loop_gt_soft")}
    image_source = None
    if "images" in files:
        pattern = files["images"]
        if isinstance(camera, CameraRig):
            count = len(camera.cameras)

            def image_source(i, pattern=pattern, count=count):
                return tuple(_read_image(path / pattern.format(camera=k, frame=i)) for k in range(count))
        else:
            def image_source(i, pattern=pattern):
                return _read_image(path / pattern.format(frame=i))
    visible_source = None
    if "visible_objects" in files:
        cache: dict[str, list] = {}

        def visible_source(i):
            if "rows" not in cache:
                rows = [json.loads(line) for line in (path / files["visible_objects"]).read_text().splitlines()
                        if line.strip()]
                cache["rows"] = [[VisibleObject.from_dict(o) for o in r["objects"]] for r in rows]
            return cache["rows"][i]
    return Dataset(
        name=document.get("name", path.name), n_frames=n, camera=camera, stamps_ns=arrays.get("stamps_ns"),
        T_world_body=arrays.get("T_world_body"), T_body_cam=arrays.get("T_body_cam"), semantic_map=semantic_map,
        odometry=odometry, loop_gt=loops["loop_gt"], loop_gt_soft=loops["loop_gt_soft"], image_source=image_source,
        visible_source=visible_source,
        exemplar_dir=path / files["exemplars"] if "exemplars" in files else None,
        multiview_dir=path / files["multiview_exemplars"] if "multiview_exemplars" in files else None,
        metadata={**document.get("metadata", {}), **{k: v for k, v in document.items()
                                                      if k not in ("files", "metadata")}},
        path=path, extra_gt={k: np.load(path / f, allow_pickle=False) for k, f in files.get("extra_gt", {}).items()})


def _open_image_folder(path: Path) -> Dataset:
    image_dir = path / "images" if (path / "images").is_dir() else path
    images = _list_images(image_dir)
    gt_files = [p for p in sorted(path.iterdir()) if p.is_file() and "gt" in p.stem.lower()
                and p.suffix.lower() in (".bmp", ".png", ".npy") and p.stem.lower() != "groundtruth"]
    if not images and not (path / "groundtruth.txt").is_file():
        raise DatasetError(f"{path}: no images, no dataset.json, no groundtruth.txt")
    if images:
        # A loop matrix image can sit next to the images: never take it for a frame.
        images = [p for p in images if p not in gt_files]
    loop_gt = None
    if gt_files:
        gt = gt_files[0]
        matrix = np.load(gt, allow_pickle=False) if gt.suffix == ".npy" else cv2.imread(str(gt), cv2.IMREAD_GRAYSCALE)
        if matrix is None:
            raise DatasetError(f"cannot read loop ground truth {gt}")
        loop_gt = _symmetric(np.asarray(matrix) > (127 if gt.suffix != ".npy" else 0))
    stamps = T_world_cam = None
    if (path / "groundtruth.txt").is_file():
        stamps_s, T_world_cam = read_tum(path / "groundtruth.txt")
        stamps = np.round(stamps_s * 1e9).astype(np.int64)
    n = len(images) if images else len(T_world_cam)
    if loop_gt is not None and loop_gt.shape[0] != n:
        raise DatasetError(f"{path}: loop matrix {loop_gt.shape} does not match {n} images")
    if T_world_cam is not None and len(T_world_cam) != n:
        raise DatasetError(f"{path}: {len(T_world_cam)} poses for {n} images")
    camera = None
    metadata: dict = {"source": "image_folder"}
    if (path / "camera.json").is_file():
        camera = camera_from_document(json.loads((path / "camera.json").read_text()))
    elif images:
        first = _read_image(images[0])
        # Unknown intrinsics: a nominal 60-degree pinhole, flagged so nobody mistakes it for a calibration.
        camera = PinholeCamera.from_fov(first.shape[1], first.shape[0], 60.0)
        metadata["camera_assumed"] = True
    T_world_body = T_body_cam = None
    if T_world_cam is not None:
        T_world_body = np.stack([level_frame_of_camera(T) for T in T_world_cam])
        T_body_cam = invert_transform(T_world_body) @ T_world_cam
    image_source = (lambda i: _read_image(images[i])) if images else None
    return Dataset(name=path.name, n_frames=n, camera=camera, stamps_ns=stamps, T_world_body=T_world_body,
                   T_body_cam=T_body_cam, loop_gt=loop_gt, image_source=image_source, metadata=metadata, path=path)


def _open_tum(path: Path) -> Dataset:
    stamps_s, T_world_cam = read_tum(path)
    T_world_body = np.stack([level_frame_of_camera(T) for T in T_world_cam])
    return Dataset(name=path.stem, n_frames=len(T_world_cam), stamps_ns=np.round(stamps_s * 1e9).astype(np.int64),
                   T_world_body=T_world_body, T_body_cam=invert_transform(T_world_body) @ T_world_cam,
                   metadata={"source": "tum"}, path=path)


def _open_rgbd_scenes(path: Path, surface_z: float = 0.75) -> Dataset:
    T_ref_cam = read_rgbd_scenes_poses(path)
    T_world_cam, table = level_real_trajectory(T_ref_cam, surface_z)
    T_world_body = np.stack([level_frame_of_camera(T) for T in T_world_cam])
    return Dataset(name=path.stem, n_frames=len(T_world_cam),
                   stamps_ns=np.arange(len(T_world_cam), dtype=np.int64) * 33_333_333, T_world_body=T_world_body,
                   T_body_cam=invert_transform(T_world_body) @ T_world_cam,
                   metadata={"source": "rgbd_scenes_v2", "table": _jsonable(table)}, path=path)
