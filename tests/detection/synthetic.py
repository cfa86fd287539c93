"""Hand-made test scenes: distinctive objects pasted on textured backgrounds at known positions and sizes."""

from __future__ import annotations

import cv2
import numpy as np


def make_object(kind: str, height: int = 96) -> np.ndarray:
    """A synthetic exemplar (uint8 BGR) of one of a few visually distinct kinds."""
    if kind == "clock":
        size = height
        image = np.full((size, size, 3), (40, 60, 70), np.uint8)
        centre = (size // 2, size // 2)
        cv2.circle(image, centre, size // 2 - 2, (245, 245, 245), -1, cv2.LINE_AA)
        cv2.circle(image, centre, size // 2 - 2, (20, 20, 20), max(2, size // 16), cv2.LINE_AA)
        for k in range(12):
            angle = k * np.pi / 6
            inner = (int(centre[0] + 0.33 * size * np.cos(angle)), int(centre[1] + 0.33 * size * np.sin(angle)))
            outer = (int(centre[0] + 0.42 * size * np.cos(angle)), int(centre[1] + 0.42 * size * np.sin(angle)))
            cv2.line(image, inner, outer, (20, 20, 20), max(1, size // 32), cv2.LINE_AA)
        cv2.line(image, centre, (centre[0], int(size * 0.2)), (10, 10, 10), max(2, size // 20), cv2.LINE_AA)
        cv2.line(image, centre, (int(size * 0.72), centre[1]), (10, 10, 10), max(2, size // 20), cv2.LINE_AA)
        return image
    if kind == "machine":
        width = int(height * 0.55)
        image = np.full((height, width, 3), (150, 60, 20), np.uint8)   # blue body (BGR)
        cv2.rectangle(image, (width // 6, height // 8), (5 * width // 6, height // 3), (30, 230, 240), -1)
        for row in range(4):
            for col in range(3):
                x = width // 6 + col * width // 4
                y = int(height * 0.45) + row * height // 12
                cv2.rectangle(image, (x, y), (x + width // 8, y + height // 20), (230, 230, 230), -1)
        cv2.rectangle(image, (width // 4, int(height * 0.85)), (3 * width // 4, int(height * 0.93)), (0, 0, 0), -1)
        return image
    if kind == "can":
        width = int(height * 0.5)
        image = np.zeros((height, width, 3), np.uint8)
        shade = 0.55 + 0.45 * np.sin(np.linspace(0.2, np.pi - 0.2, width))
        image[:] = (np.array([30, 30, 220]) * shade[:, None]).astype(np.uint8)[None, :, :]
        image[: height // 10] = (190, 190, 190)
        image[-height // 10:] = (190, 190, 190)
        cv2.putText(image, "S", (width // 5, int(height * 0.65)), cv2.FONT_HERSHEY_SIMPLEX, width / 30.0,
                    (255, 255, 255), max(1, width // 12), cv2.LINE_AA)
        return image
    if kind == "arrow":   # strongly asymmetric left/right: for mirror tests
        width = int(height * 0.8)
        image = np.full((height, width, 3), (200, 200, 200), np.uint8)
        image[:, : width // 3] = (20, 20, 200)
        tip = np.array([[width // 3, height // 5], [width - 4, height // 2], [width // 3, 4 * height // 5]])
        cv2.fillPoly(image, [tip], (200, 90, 10))
        return image
    raise ValueError(f"unknown kind {kind!r}")


def textured_background(height: int, width: int, seed: int = 0) -> np.ndarray:
    """Smooth random colour texture with some edges (walls, panels) — clutter for the matcher."""
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
    background = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    background = cv2.GaussianBlur(background, (0, 0), 3)
    background = (background.astype(np.float32) * 0.5 + 64).astype(np.uint8)
    for _ in range(12):
        x0, y0 = int(rng.integers(0, width)), int(rng.integers(0, height))
        x1, y1 = x0 + int(rng.integers(20, 120)), y0 + int(rng.integers(20, 120))
        colour = tuple(int(c) for c in rng.integers(40, 200, 3))
        cv2.rectangle(background, (x0, y0), (x1, y1), colour, 2)
    return background


def paste(scene: np.ndarray, obj: np.ndarray, centre_xy, height: int) -> tuple[float, float, float, float]:
    """Paste ``obj`` resized to ``height`` px tall, centred at ``centre_xy``; returns its box (x, y, w, h)."""
    width = max(1, int(round(obj.shape[1] * height / obj.shape[0])))
    resized = cv2.resize(obj, (width, height), interpolation=cv2.INTER_AREA)
    x0 = int(round(centre_xy[0] - width / 2))
    y0 = int(round(centre_xy[1] - height / 2))
    xs0, ys0 = max(0, x0), max(0, y0)
    xs1, ys1 = min(scene.shape[1], x0 + width), min(scene.shape[0], y0 + height)
    scene[ys0:ys1, xs0:xs1] = resized[ys0 - y0:ys1 - y0, xs0 - x0:xs1 - x0]
    return float(x0), float(y0), float(width), float(height)


class SyntheticDataset:
    """A tiny dataset with exact object ground truth, duck-typed like ``semloc_core.io.dataset.Dataset``.

    Level pinhole camera; every frame pastes each class's object at a random column and height on clutter, so the
    ground-truth bearing is the bearing of the object's centre column.
    """

    def __init__(self, n_frames: int = 8, width: int = 320, height: int = 240, fov_deg: float = 60.0,
                 kinds=("clock", "machine"), seed: int = 0):
        from semloc_core.camera import PinholeCamera

        self.camera = PinholeCamera.from_fov(width, height, fov_deg)
        self.kinds = tuple(kinds)
        self._n = n_frames
        self._seed = seed
        self._frames: dict[int, tuple] = {}

    def __len__(self) -> int:
        return self._n

    def _frame(self, i: int):
        if i not in self._frames:
            from semloc_core.camera import pixel_bearings

            rng = np.random.default_rng([self._seed, i])
            width, height = self.camera.width, self.camera.height
            scene = textured_background(height, width, seed=1000 * self._seed + i)
            bearings = pixel_bearings(self.camera)
            objects = []
            columns = rng.permutation(np.arange(40, width - 40, 60))[: len(self.kinds)]
            for index, (kind, column) in enumerate(zip(self.kinds, columns)):
                object_height = int(rng.integers(50, 110))
                centre = (int(column), int(rng.integers(object_height // 2 + 2, height - object_height // 2 - 2)))
                x, y, w, h = paste(scene, make_object(kind, 120), centre, object_height)
                objects.append(SimpleVisible(index, kind, (x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5),
                                             float(bearings[centre[1], centre[0]])))
            self._frames[i] = (scene, objects)
        return self._frames[i]

    def image(self, i: int) -> np.ndarray:
        return self._frame(i)[0]

    def visible_objects(self, i: int):
        return self._frame(i)[1]

    def T_body_cam_at(self, i: int):
        return self.camera.T_body_cam


class SimpleVisible:
    """The fields of ``semloc_core.io.dataset.VisibleObject`` the detection evaluation reads."""

    def __init__(self, object_index, class_name, box, bearing, occluded_fraction=0.0, truncated=False,
                 visible_pixels=1):
        self.object_index = object_index
        self.class_name = class_name
        self.box = box
        self.bearing = bearing
        self.occluded_fraction = occluded_fraction
        self.truncated = truncated
        self.visible_pixels = visible_pixels
