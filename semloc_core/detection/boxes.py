"""Heatmaps from box detectors (thesis §4.6.2), the shipped OpenCV detectors, and a plug-in for a user's own model.

§4.6.2 turns a box detector into a soft one: run it with a threshold of -inf and no non-maximum suppression so that
it scores windows all over the image; give each heatmap cell the maximum score of the boxes centred in it; fill the
cells that no box is centred in from their nearest scored cell.

Shipped detectors whose models come inside the installed ``opencv-python-headless`` (< 5):

* ``HogPeopleDetector`` — Dalal-Triggs HOG + linear SVM for pedestrians; every window is returned with its SVM
  margin (``hitThreshold`` very negative, ``groupThreshold=0``).
* ``HaarCascadeDetector`` — Viola-Jones cascades in ``cv2.data.haarcascades`` (faces, bodies, plates...);
  ``detectMultiScale3(minNeighbors=0, outputRejectLevels=True)`` returns the windows that reach the last stages with
  their stage weight.

and ``DnnDetector`` runs a model the user supplies through ``cv2.dnn`` (ONNX, TensorFlow, Caffe, Darknet) with
SSD-style or YOLO-style outputs. Scores are raw (SVM margins, stage sums, logits or probabilities); ``ScoreSquash``
maps them monotonically into [0, 1] so that every heatmap in semloc shares one range.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from scipy import ndimage


# ---------------------------------------------------------------------------------------------------- adapter


def box_centres(boxes: np.ndarray) -> np.ndarray:
    """Centre pixel (u, v) of integer-pixel boxes (x, y, w, h) that cover columns x .. x+w-1 and rows y .. y+h-1."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return np.stack([boxes[:, 0] + (boxes[:, 2] - 1) / 2.0, boxes[:, 1] + (boxes[:, 3] - 1) / 2.0], axis=1)


def boxes_to_heatmap(boxes, scores, image_size: tuple[int, int], out_shape: tuple[int, int] | None = None,
                     empty_value: float = 0.0) -> np.ndarray:
    """Dense heatmap (rows, cols) float32 from every scored box of one class (§4.6.2).

    ``image_size`` is (width, height) of the image the boxes live in; ``out_shape`` (rows, cols) the heatmap grid
    covering that image uniformly (default: one cell per pixel). Each cell takes the maximum score of the boxes
    whose centre pixel (rounded half up) falls in it; every other cell takes the score of the nearest such cell
    (Euclidean, in cells). Boxes centred outside the image are ignored. With no box at all the heatmap is
    ``empty_value`` everywhere.
    """
    width, height = int(image_size[0]), int(image_size[1])
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {image_size}")
    rows, cols = (height, width) if out_shape is None else (int(out_shape[0]), int(out_shape[1]))
    if rows < 1 or cols < 1:
        raise ValueError(f"heatmap shape must be positive, got {out_shape}")
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if boxes.shape[0] != scores.shape[0]:
        raise ValueError(f"{boxes.shape[0]} boxes but {scores.shape[0]} scores")
    finite = np.all(np.isfinite(boxes), axis=1) & np.isfinite(scores)
    centres = box_centres(boxes[finite])
    scores = scores[finite]
    # Round half up to a pixel, then to the cell holding that pixel (cells cover W/cols pixels each).
    u = np.floor(centres[:, 0] + 0.5)
    v = np.floor(centres[:, 1] + 0.5)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    q = np.floor((u[inside] + 0.5) * cols / width).astype(np.int64)
    r = np.floor((v[inside] + 0.5) * rows / height).astype(np.int64)
    q = np.minimum(q, cols - 1)
    r = np.minimum(r, rows - 1)
    heatmap = np.full(rows * cols, -np.inf)
    np.maximum.at(heatmap, r * cols + q, scores[inside])
    heatmap = heatmap.reshape(rows, cols)
    scored = np.isfinite(heatmap)
    if not scored.any():
        return np.full((rows, cols), empty_value, np.float32)
    if not scored.all():
        nearest = ndimage.distance_transform_edt(~scored, return_distances=False, return_indices=True)
        heatmap = heatmap[nearest[0], nearest[1]]
    return heatmap.astype(np.float32)


@dataclass(frozen=True)
class ScoreSquash:
    """Monotone map of raw detector scores into [0, 1]: logistic((s - centre) / width), or identity clipped."""

    kind: str = "logistic"
    centre: float = 0.0
    width: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("logistic", "clip"):
            raise ValueError(f"score squash kind must be 'logistic' or 'clip', got {self.kind!r}")
        if not self.width > 0:
            raise ValueError(f"squash width must be positive, got {self.width}")

    def __call__(self, scores) -> np.ndarray:
        scores = np.asarray(scores, dtype=np.float64)
        if self.kind == "clip":
            return np.clip(scores, 0.0, 1.0)
        return 0.5 * (1.0 + np.tanh(0.5 * (scores - self.centre) / self.width))   # overflow-free logistic


class BoxDetector(Protocol):
    """What a box detector plug-in provides: class names and, per image, (boxes, scores) for each class."""

    classes: tuple[str, ...]

    def detect(self, image: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """For each class in ``classes`` order: boxes (N, 4) as (x, y, w, h) pixels and raw scores (N,)."""
        ...


class BoxHeatmapDetector:
    """A ``BoxDetector`` made soft (§4.6.2): ``heatmaps(image)`` -> (classes, rows, cols) float32 in [0, 1].

    The output grid has ``round(H / cell)`` x ``round(W / cell)`` cells, like the template detector's.
    """

    def __init__(self, detector: BoxDetector, squash: ScoreSquash = ScoreSquash(), cell: int = 4):
        if int(cell) < 1:
            raise ValueError(f"cell must be >= 1, got {cell}")
        self.detector = detector
        self.squash = squash
        self.cell = int(cell)
        self.classes = tuple(detector.classes)

    def output_shape(self, image_shape) -> tuple[int, int]:
        return max(1, int(round(image_shape[0] / self.cell))), max(1, int(round(image_shape[1] / self.cell)))

    def heatmaps(self, image: np.ndarray) -> np.ndarray:
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected a uint8 BGR (H, W, 3) image, got {image.dtype} {image.shape}")
        detections = self.detector.detect(image)
        if len(detections) != len(self.classes):
            raise ValueError(f"detector returned {len(detections)} classes, expected {len(self.classes)}")
        shape = self.output_shape(image.shape)
        size = (image.shape[1], image.shape[0])
        # The squash is monotone, so squashing before the max gives the same heatmap as after.
        return np.stack([boxes_to_heatmap(boxes, self.squash(scores), size, shape)
                         for boxes, scores in detections]).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- shipped


@dataclass
class HogPeopleDetector:
    """OpenCV's default HOG people detector, every window scored (class ``person``).

    ``upscale`` > 1 enlarges the image first so people shorter than the 128-pixel window are still scored.
    """

    class_name: str = "person"
    win_stride: tuple[int, int] = (8, 8)
    scale: float = 1.05
    upscale: float = 1.0
    _hog: object = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self._hog = cv2.HOGDescriptor()
        self._hog.setSVMDetector(cv2.HOGDescriptor_getDefaultPeopleDetector())
        self.classes = (self.class_name,)

    def detect(self, image: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        work = image if self.upscale == 1.0 else cv2.resize(image, None, fx=self.upscale, fy=self.upscale)
        # The pyramid of HOGDescriptor.detectMultiScale, walked here one level at a time: detectMultiScale scans
        # the levels in parallel threads that append a level's boxes and its weights to the outputs under two
        # separate locks, so two threads can interleave and pair boxes with another level's weights (OpenCV 4.x;
        # measured here: 1 call in 300 under load, enough to move the best box). Level by level (the same sizes,
        # INTER_LINEAR_EXACT and box rounding) the result equals a single-threaded detectMultiScale exactly.
        win_w, win_h = self._hog.winSize
        height, width = work.shape[:2]
        boxes, weights = [], []
        scale = 1.0
        for _ in range(64):  # detectMultiScale's nlevels
            size = (int(round(width / scale)), int(round(height / scale)))
            if size[0] < win_w or size[1] < win_h:
                break
            level = work if scale == 1.0 else cv2.resize(work, size, interpolation=cv2.INTER_LINEAR_EXACT)
            found, found_weights = self._hog.detect(level, hitThreshold=-1e9, winStride=self.win_stride,
                                                    padding=(0, 0))
            found = np.asarray(found, dtype=np.float64).reshape(-1, 2)
            window = np.full((len(found), 2), [round(win_w * scale), round(win_h * scale)], dtype=np.float64)
            boxes.append(np.column_stack([np.round(found * scale), window]))
            weights.append(np.asarray(found_weights, dtype=np.float64).reshape(-1))
            scale *= self.scale
        boxes = np.concatenate(boxes) if boxes else np.zeros((0, 4))
        return [(boxes / self.upscale, np.concatenate(weights) if weights else np.zeros(0))]


@dataclass
class HaarCascadeDetector:
    """A Viola-Jones cascade; ``cascade`` is a ``cv2.CascadeClassifier`` (see ``io.detector_models``).

    Score = stage weight + ``stage_step`` x (reject level - deepest level): windows that get further through the
    cascade always outscore those rejected earlier; within a level the stage weight orders them.
    """

    cascade: object
    class_name: str = "face"
    scale_factor: float = 1.1
    min_size: tuple[int, int] = (0, 0)
    stage_step: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.cascade, cv2.CascadeClassifier) or self.cascade.empty():
            raise ValueError("HaarCascadeDetector needs a loaded cv2.CascadeClassifier")
        self.classes = (self.class_name,)

    def detect(self, image: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        rects, levels, weights = self.cascade.detectMultiScale3(
            grey, scaleFactor=self.scale_factor, minNeighbors=0, minSize=self.min_size, outputRejectLevels=True)
        boxes = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
        if boxes.shape[0] == 0:
            return [(boxes, np.zeros(0))]
        levels = np.asarray(levels, dtype=np.float64).reshape(-1)
        scores = np.asarray(weights, dtype=np.float64).reshape(-1) + self.stage_step * (levels - levels.max())
        return [(boxes, scores)]


@dataclass
class DnnDetector:
    """A user's model run by ``cv2.dnn`` (``net`` from ``io.detector_models.load_dnn``).

    ``output``: ``"ssd"`` — one blob (1, 1, N, 7) of [image, class, score, x1, y1, x2, y2] with corners in [0, 1];
    ``"yolo"`` — one blob (1, N, 4 + C) or (1, 4 + C, N) (``yolo_layout``) of [cx, cy, w, h, class scores...] in input pixels
    (YOLOv5 with an objectness column: ``objectness=True``, scores = objectness x class score).
    ``class_ids`` maps the model's class index to our class name; other classes are ignored. The input is resized
    to ``input_size`` (width, height) and scaled as ``(pixel - mean) * scale`` (``swap_rb`` for RGB models).
    """

    net: object
    class_ids: dict
    input_size: tuple[int, int] = (300, 300)
    output: str = "ssd"
    scale: float = 1.0 / 255.0
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    swap_rb: bool = True
    objectness: bool = False
    yolo_layout: str = "auto"   # "rows" (N, 4 + C), "columns" (4 + C, N), or "auto": the longer axis is N

    def __post_init__(self) -> None:
        if self.output not in ("ssd", "yolo"):
            raise ValueError(f"output must be 'ssd' or 'yolo', got {self.output!r}")
        if self.yolo_layout not in ("auto", "rows", "columns"):
            raise ValueError(f"yolo_layout must be 'auto', 'rows' or 'columns', got {self.yolo_layout!r}")
        if not self.class_ids:
            raise ValueError("class_ids must map at least one model class index to a class name")
        self.class_ids = {int(k): str(v) for k, v in self.class_ids.items()}
        self.classes = tuple(dict.fromkeys(self.class_ids.values()))

    def detect(self, image: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        height, width = image.shape[:2]
        blob = cv2.dnn.blobFromImage(image, float(self.scale), tuple(self.input_size), tuple(self.mean),
                                     swapRB=self.swap_rb, crop=False)
        self.net.setInput(blob)
        raw = np.asarray(self.net.forward(), dtype=np.float64)
        if self.output == "ssd":
            rows = raw.reshape(-1, 7)
            model_class = rows[:, 1].astype(np.int64)
            scores = rows[:, 2]
            x1, y1 = rows[:, 3] * width, rows[:, 4] * height
            x2, y2 = rows[:, 5] * width, rows[:, 6] * height
        else:
            table = raw.reshape(raw.shape[-2], raw.shape[-1])
            columns = table.shape[0] < table.shape[1] if self.yolo_layout == "auto" else self.yolo_layout == "columns"
            if columns:
                table = table.T   # (4 + C, N) layout (YOLOv8) -> (N, 4 + C)
            class_scores = table[:, 5:] * table[:, 4:5] if self.objectness else table[:, 4:]
            model_class = class_scores.argmax(axis=1)
            scores = class_scores[np.arange(table.shape[0]), model_class]
            sx, sy = width / self.input_size[0], height / self.input_size[1]
            x1 = (table[:, 0] - table[:, 2] / 2) * sx
            y1 = (table[:, 1] - table[:, 3] / 2) * sy
            x2 = (table[:, 0] + table[:, 2] / 2) * sx
            y2 = (table[:, 1] + table[:, 3] / 2) * sy
        boxes = np.stack([x1, y1, x2 - x1, y2 - y1], axis=1)
        out = []
        for name in self.classes:
            ids = [k for k, v in self.class_ids.items() if v == name]
            keep = np.isin(model_class, ids)
            out.append((boxes[keep], scores[keep]))
        return out


