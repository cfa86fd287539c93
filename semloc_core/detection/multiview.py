"""Multi-view dominant-orientation templates (thesis §5.3, eq. 5.1), in the spirit of DOT / LINE-2D.

    s(x) = sum_{r in Omega} max_{x' in R(x + r)} S(T(r), I(x'))                                     (eq. 5.1)

* I(x'): the quantised gradient orientation at x' (``orientations`` bins over [0, pi): the sign of the gradient is
  ignored so an object reads the same on dark and light backgrounds), only where the gradient is strong enough.
* T(r): the template's features — the strongest, well-spread gradient locations r of an exemplar view, relative to
  its centre, each with its orientation.
* S(o, o') = |cos(o - o')|; R(x) = the ``spread`` x ``spread`` neighbourhood of x. The max over R is taken once per
  image by OR-ing the orientation bit masks over the neighbourhood ("spreading"), then a 256-entry table per template
  orientation gives max |cos| over the orientations present: the response map of that orientation.
* s is divided by |Omega| so it lies in [0, 1]. It is evaluated on a grid of step ``spread`` (the spreading covers
  the positions in between), with the response maps stored decimated per offset ("linearised memories", Hinterstoisser
  et al. 2012) so each feature costs one strided slice-add. Pyramid levels handle scale; the class score map is the
  max over views and levels. The output grid is ``round(H / spread)`` x ``round(W / spread)``, covering the image
  uniformly like every semloc heatmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from semloc_core.detection.features import fit_to_cells
from semloc_core.detection.templates import resample_maps


@dataclass(frozen=True)
class OrientationParams:
    orientations: int = 8          # bins over [0, pi); at most 8 (one byte of bits)
    spread: int = 4                # T: neighbourhood of the max in eq. 5.1, and the output grid step, pixels
    magnitude_threshold: float = 10.0   # gradient magnitude (grey levels per pixel) below which no orientation
    max_features: int = 63
    min_feature_distance: float = 3.0   # pixels between selected template features
    template_px: int = 64          # longer side of a view once resized for feature selection
    scales: tuple[float, ...] = (1.0, 0.75, 0.5)

    def __post_init__(self) -> None:
        if not 2 <= int(self.orientations) <= 8:
            raise ValueError(f"orientations must be in [2, 8], got {self.orientations}")
        if int(self.spread) < 1:
            raise ValueError(f"spread must be >= 1, got {self.spread}")
        if not self.magnitude_threshold >= 0:
            raise ValueError("magnitude_threshold must be >= 0")
        if int(self.max_features) < 1 or int(self.template_px) < 8:
            raise ValueError("need max_features >= 1 and template_px >= 8")
        if not self.scales or any(not 0.01 <= s <= 8 for s in self.scales):
            raise ValueError(f"scales must be a non-empty list in [0.01, 8], got {self.scales}")
        object.__setattr__(self, "scales", tuple(float(s) for s in self.scales))


def quantised_orientations(image: np.ndarray, params: OrientationParams) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: orientation bin (int, -1 where the gradient is too weak) and gradient magnitude."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    grey = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0   # grey levels per pixel
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    magnitude = cv2.magnitude(gx, gy)
    angle = np.mod(np.arctan2(gy, gx), np.pi)   # polarity ignored
    n = params.orientations
    bins = np.floor(angle / (np.pi / n) + 0.5).astype(np.int32) % n
    bins[magnitude < params.magnitude_threshold] = -1
    return bins, magnitude


def spread_orientations(bins: np.ndarray, spread: int) -> np.ndarray:
    """uint8 bit mask per pixel: the orientations present in the spread x spread window around it (OR)."""
    bits = np.where(bins >= 0, np.left_shift(1, np.maximum(bins, 0)), 0).astype(np.uint8)
    height, width = bits.shape
    low = spread // 2
    padded = np.zeros((height + spread - 1, width + spread - 1), np.uint8)
    padded[low:low + height, low:low + width] = bits
    out = np.zeros_like(bits)
    for dy in range(spread):
        for dx in range(spread):
            np.bitwise_or(out, padded[dy:dy + height, dx:dx + width], out=out)
    return out


def similarity_tables(orientations: int) -> np.ndarray:
    """(orientations, 256) float32: for template orientation o and a bit mask, max |cos(o - o')| over its bits."""
    tables = np.zeros((orientations, 256), np.float32)
    masks = np.arange(256)
    for o in range(orientations):
        for o2 in range(orientations):
            similarity = abs(np.cos((o - o2) * np.pi / orientations))
            present = (masks >> o2) & 1 == 1
            tables[o, present] = np.maximum(tables[o, present], similarity)
    return tables


@dataclass(frozen=True, eq=False)
class ViewTemplate:
    """Features of one exemplar view: offsets (dx, dy) from the view centre in pixels and orientation bins."""

    class_name: str
    offsets: np.ndarray       # (n, 2) int (dx, dy)
    orientation: np.ndarray   # (n,) int
    size: tuple[int, int]     # (width, height) of the resized view
    source: str = ""


def build_view_template(view: np.ndarray, class_name: str, params: OrientationParams = OrientationParams(),
                        mask: np.ndarray | None = None, source: str = "") -> ViewTemplate:
    """Select up to ``max_features`` strong, spread-out gradient features of one exemplar view (uint8 BGR)."""
    view = np.asarray(view)
    if view.ndim != 3 or view.shape[2] != 3 or view.dtype != np.uint8:
        raise ValueError(f"view must be a uint8 BGR (H, W, 3) image, got {view.dtype} {view.shape}")
    height, width = view.shape[:2]
    factor = params.template_px / max(width, height)
    size = (max(1, int(round(width * factor))), max(1, int(round(height * factor))))
    resized = cv2.resize(view, size, interpolation=cv2.INTER_AREA)
    bins, magnitude = quantised_orientations(resized, params)
    allowed = bins >= 0
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (height, width):
            raise ValueError(f"mask shape {mask.shape} does not match the view {(height, width)}")
        small = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        # The silhouette's own edge is the most telling feature: keep a 2-pixel band outside the mask too.
        allowed &= cv2.dilate(small, np.ones((5, 5), np.uint8)) > 0
    ys, xs = np.nonzero(allowed)
    if ys.size == 0:
        raise ValueError(f"view {source or class_name!r} has no gradient above the magnitude threshold")
    order = np.argsort(-magnitude[ys, xs], kind="stable")
    chosen: list[int] = []
    min_sq = params.min_feature_distance**2
    picked_x = np.empty(params.max_features)
    picked_y = np.empty(params.max_features)
    for index in order:
        x, y = xs[index], ys[index]
        n = len(chosen)
        if n and np.min((picked_x[:n] - x) ** 2 + (picked_y[:n] - y) ** 2) < min_sq:
            continue
        picked_x[n], picked_y[n] = x, y
        chosen.append(index)
        if len(chosen) == params.max_features:
            break
    chosen = np.asarray(chosen)
    centre = np.array([(size[0] - 1) // 2, (size[1] - 1) // 2])
    offsets = np.stack([xs[chosen], ys[chosen]], axis=1) - centre
    return ViewTemplate(class_name, offsets.astype(np.int64), bins[ys[chosen], xs[chosen]].astype(np.int64),
                        size, source)


class MultiViewDetector:
    """Dense eq. 5.1 score maps per class: max over each class's views and the pyramid levels.

    ``heatmaps(image)`` -> (classes, round(H / spread), round(W / spread)) float32 in [0, 1].
    """

    def __init__(self, views, params: OrientationParams = OrientationParams()):
        views = list(views)
        if not views:
            raise ValueError("need at least one view template")
        self.params = params
        self.views = tuple(views)
        self.classes = tuple(dict.fromkeys(v.class_name for v in views))
        self._view_class = np.array([self.classes.index(v.class_name) for v in views])
        self._tables = similarity_tables(params.orientations)

    def output_shape(self, image_shape) -> tuple[int, int]:
        step = self.params.spread
        return max(1, int(round(image_shape[0] / step))), max(1, int(round(image_shape[1] / step)))

    def level_scores(self, image: np.ndarray, scale: float) -> np.ndarray:
        """(views, rows, cols) eq. 5.1 scores on the level's grid of step ``spread``."""
        step = self.params.spread
        level = fit_to_cells(image, scale, step)
        height, width = level.shape[:2]
        rows, cols = height // step, width // step
        bins, _ = quantised_orientations(level, self.params)
        spread = spread_orientations(bins, step)
        # Response map per template orientation, stored padded and decimated by offset residue: feature r of a
        # grid position x = step * i reads response[(y + r_y)] for every i at once with one strided slice.
        margin = max(int(np.abs(v.offsets).max()) for v in self.views) + step
        responses = np.zeros((self.params.orientations, height + 2 * margin, width + 2 * margin), np.float32)
        responses[:, margin:margin + height, margin:margin + width] = self._tables[:, spread]
        # Evaluate at the grid cell centres (pixel step * i + centre_offset) so levels resample consistently.
        centre_offset = (step - 1) // 2
        scores = np.zeros((len(self.views), rows, cols), np.float32)
        for k, view in enumerate(self.views):
            acc = scores[k]
            for (dx, dy), o in zip(view.offsets, view.orientation):
                y0 = margin + centre_offset + dy
                x0 = margin + centre_offset + dx
                acc += responses[o, y0:y0 + rows * step:step, x0:x0 + cols * step:step]
            acc /= len(view.offsets)
        return scores

    def heatmaps(self, image: np.ndarray) -> np.ndarray:
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected a uint8 BGR (H, W, 3) image, got {image.dtype} {image.shape}")
        rows, cols = self.output_shape(image.shape)
        best = None
        for scale in self.params.scales:
            level = resample_maps(self.level_scores(image, scale), rows, cols)
            best = level if best is None else np.maximum(best, level)
        out = np.zeros((len(self.classes), rows, cols), np.float32)
        for k in range(len(self.classes)):
            out[k] = best[self._view_class == k].max(axis=0)
        return out
