"""A discriminatively trained window detector on the §4.3 cell features (the thesis's DPM heatmaps, §4.6.2, root
filter only).

The template detector correlates one exemplar's histograms with the image; its answer is wherever the image looks
like the exemplar - a cap's crown, a red box for a red mug - and its maximum lies where the exemplar's texture
lies, not at the object's centre. This detector keeps the same cell features (square-rooted HOGE and HQC
histograms, one feature pyramid per frame) and learns, per class, a linear filter ``w`` over a window of cells and
a bias ``b`` from frames with known objects (a simulator's calibration worlds): positives are windows centred on
an object's projected centre at the pyramid level where the object fills the window, negatives are windows
anywhere else (already a cell off the centre), first drawn at random and then the filter's own strongest mistakes
(hard negatives, as DPM's training). The heatmap of a class is

    H_c(I)(u) = max_s sigma(w_c . F(I^s)[window at u] + b_c)

- a logistic regression's probability that a window centred at ``u`` is centred on an object of class ``c``, max
over the pyramid levels, never thresholded. Where the training put the positives (the projected 3-D centre of the
object's bounding box) is where the heat is meant to peak, so that back-projected heat meets at the object's
centre; how near it comes (a cap's heat still leans towards its crown) is measured in docs/mapping.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.detection.correlation import Correlator
from semloc_core.detection.features import FeatureParams, Workspace, fit_to_cells, hoge, hqc
from semloc_core.detection.templates import WARM_UP_IMAGE, _check_image, resample_maps


def feature_dim(params: FeatureParams) -> int:
    return params.hoge_bins + params.hqc_bins


def cell_features(level: np.ndarray, params: FeatureParams, workspace: Workspace | None = None) -> np.ndarray:
    """(rows, cols, D) float32: square-rooted HOGE and HQC histograms of a pyramid level (sizes a multiple of the
    cell). The square root makes a dot product of two cells their Bhattacharyya coefficient, as in eq. 4.3."""
    return np.concatenate([np.sqrt(hoge(level, params, workspace)), np.sqrt(hqc(level, params, workspace=workspace))],
                          axis=2).astype(np.float32)


@dataclass(frozen=True, eq=False)
class LinearWindowModel:
    """Per-class linear window filters over the cell features, and the pyramid they are applied on."""

    classes: tuple[str, ...]
    weights: tuple[np.ndarray, ...]          # per class (rows, cols, D) float32, odd sides (a centre cell)
    biases: np.ndarray                       # (classes,) float32
    params: FeatureParams = FeatureParams()
    scales: tuple[float, ...] = (1.0,)
    info: dict = field(default_factory=dict)  # how it was trained (free-form, JSON-serialisable)

    def __post_init__(self) -> None:
        classes = tuple(str(c) for c in self.classes)
        if not classes or len(set(classes)) != len(classes):
            raise ValueError(f"need distinct class names, got {self.classes}")
        weights = tuple(np.asarray(w, np.float32) for w in self.weights)
        if len(weights) != len(classes):
            raise ValueError(f"{len(weights)} filters for {len(classes)} classes")
        dim = feature_dim(self.params)
        for name, w in zip(classes, weights):
            if w.ndim != 3 or w.shape[0] % 2 == 0 or w.shape[1] % 2 == 0 or w.shape[2] != dim:
                raise ValueError(f"filter of {name!r} must be (odd rows, odd cols, {dim}), got {w.shape}")
            if not np.isfinite(w).all():
                raise ValueError(f"filter of {name!r} is not finite")
        biases = np.asarray(self.biases, np.float32).reshape(-1)
        if biases.shape != (len(classes),) or not np.isfinite(biases).all():
            raise ValueError(f"need one finite bias per class, got {self.biases}")
        scales = tuple(float(s) for s in self.scales)
        if not scales or any(not (0.01 <= s <= 8.0) for s in scales):
            raise ValueError(f"scales must be a non-empty list in [0.01, 8], got {self.scales}")
        object.__setattr__(self, "classes", classes)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "biases", biases)
        object.__setattr__(self, "scales", scales)

    def subset(self, classes) -> "LinearWindowModel":
        index = [self.classes.index(c) for c in classes]
        return LinearWindowModel(tuple(classes), tuple(self.weights[k] for k in index), self.biases[index],
                                 self.params, self.scales, self.info)


class LinearWindowDetector:
    """Soft detector: per-class heatmaps in [0, 1] on the base cell grid (``round(H / cell)`` x ``round(W / cell)``),
    as the template detector's. One instance per stream (it keeps DFT plans and scratch buffers)."""

    def __init__(self, model: LinearWindowModel):
        if not isinstance(model, LinearWindowModel):
            raise TypeError(f"expected LinearWindowModel, got {type(model)}")
        self.model = model
        self.params = model.params
        self.classes = model.classes
        self._correlator = Correlator(feature_dim(model.params),
                                      [(np.arange(w.shape[2]), np.moveaxis(w, 2, 0)) for w in model.weights])
        self._workspace = Workspace()
        self.heatmaps(WARM_UP_IMAGE)   # numba compiles (or loads) its kernels now, not on the first camera frame

    def output_shape(self, image_shape) -> tuple[int, int]:
        height, width = image_shape[:2]
        cell = self.params.cell
        return max(1, int(round(height / cell))), max(1, int(round(width / cell)))

    def level_features(self, image: np.ndarray, scale: float) -> np.ndarray:
        level = fit_to_cells(image, scale, self.params.cell, self._workspace)
        return cell_features(level, self.params, self._workspace)

    def feature_scores(self, features: np.ndarray) -> np.ndarray:
        """(classes, rows, cols) raw scores ``w_c . window + b_c`` of windows centred on each cell of a feature
        map; cells outside the map count as zero features."""
        scores = self._correlator.correlate(np.moveaxis(features, 2, 0))
        return (scores + self.model.biases[:, None, None]).astype(np.float32)

    def level_scores(self, image: np.ndarray, scale: float) -> np.ndarray:
        return self.feature_scores(self.level_features(image, scale))

    def _resampled_level_scores(self, image: np.ndarray):
        """Each level's raw scores (classes, h, w) on the base cell grid, in ``model.scales`` order."""
        image = _check_image(image)
        out_rows, out_cols = self.output_shape(image.shape)
        for scale in self.model.scales:
            yield resample_maps(self.level_scores(image, scale), out_rows, out_cols)

    def level_heatmaps(self, image: np.ndarray) -> np.ndarray:
        """Per-level class heatmaps (classes, levels, h, w) float32 in [0, 1], levels in ``model.scales`` order:
        each level's window probabilities on the base cell grid. A window answers for objects of one apparent
        size, so the level says how far the object is (semloc_core.mapping.scale_depth)."""
        return _probability(np.stack(list(self._resampled_level_scores(image)), axis=1))

    def heatmaps(self, image: np.ndarray) -> np.ndarray:
        """Class heatmaps (classes, h, w) float32 in [0, 1]: the max over levels of the windows' probabilities
        (the max of ``level_heatmaps``, the logistic being monotonic)."""
        best = None
        for scores in self._resampled_level_scores(image):
            best = scores if best is None else np.maximum(best, scores, out=best)
        return _probability(best)


def _probability(scores: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-np.clip(scores, -30.0, 30.0)))).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- training


def window_at(features: np.ndarray, row: int, col: int, shape: tuple[int, int]) -> np.ndarray:
    """The (rows, cols, D) window of ``features`` centred on cell (row, col), zero outside the map (as the FFT
    correlation sees it)."""
    h, w = shape
    out = np.zeros((h, w, features.shape[2]), np.float32)
    r0, c0 = row - h // 2, col - w // 2
    rs, re = max(r0, 0), min(r0 + h, features.shape[0])
    cs, ce = max(c0, 0), min(c0 + w, features.shape[1])
    if rs < re and cs < ce:
        out[rs - r0:re - r0, cs - c0:ce - c0] = features[rs:re, cs:ce]
    return out


def window_shape(aspect: float, window_cells: int) -> tuple[int, int]:
    """(rows, cols) of a window whose longer side spans ``window_cells`` cells with height / width ``aspect``,
    both odd."""
    def odd(value: float) -> int:
        return max(1, int(2 * round((value - 1) / 2.0) + 1))

    if aspect >= 1.0:
        return odd(window_cells), odd(window_cells / aspect)
    return odd(window_cells * aspect), odd(window_cells)


@dataclass(frozen=True)
class TrainingObject:
    """An object in a training frame: class index, the pixel (x, y, pixel-centre coordinates) its 3-D centre
    projects to, its box's width and height in pixels, and whether it may serve as a positive (unoccluded, inside
    the image). Every object of a class, positive or not, keeps the windows around its centre out of the
    negatives."""

    class_index: int
    centre: tuple[float, float]
    size: tuple[float, float]
    positive: bool = True


def best_level(size_px: tuple[float, float], shape: tuple[int, int], scales, cell: int,
               tolerance: float = 1.3) -> int | None:
    """Index of the pyramid level where a (width, height) box fills a window of ``shape`` best (None if no level
    is within ``tolerance`` of it)."""
    # At level scale s the box spans fit * s window lengths along its tighter side: 1 fills the window.
    fit = max(size_px[0] / shape[1], size_px[1] / shape[0]) / cell
    ratios = [abs(np.log(fit * s)) for s in scales]
    k = int(np.argmin(ratios))
    return k if ratios[k] <= np.log(tolerance) else None


def _level_cell(uv: tuple[float, float], scale_rc: tuple[float, float], cell: int) -> tuple[int, int]:
    """The cell of a level containing base pixel ``uv`` (x, y, pixel-centre coordinates: pixel 0 spans [-0.5, 0.5]);
    ``scale_rc`` = the level's (row, col) scales."""
    return int(np.floor((uv[1] + 0.5) * scale_rc[0] / cell)), int(np.floor((uv[0] + 0.5) * scale_rc[1] / cell))


def ignored_cells(objects, class_index: int, base_shape, level_shape, cell: int, radius: float) -> np.ndarray:
    """(rows, cols) bool over a level's cells: the cells within ``radius`` x box size (base pixels) of an object of
    the class's centre - neither positives nor negatives. At the positive's level the box spans the window (about
    ``window_cells`` cells), so 0.1 leaves out the positive's own cell (and a neighbour when the centre lies near a
    cell's edge) and makes a window one cell off a negative: the filter learns to answer on the centre, not on the
    most textured part (with 0.25 a cap's heat sat between crown and centre; docs/mapping.md)."""
    rows, cols = level_shape
    sy, sx = rows * cell / base_shape[0], cols * cell / base_shape[1]
    ys = (np.arange(rows) + 0.5) * cell / sy - 0.5   # cell centres in pixel-centre coordinates
    xs = (np.arange(cols) + 0.5) * cell / sx - 0.5
    mask = np.zeros((rows, cols), bool)
    for obj in objects:
        if obj.class_index != class_index:
            continue
        r = radius * max(obj.size)
        mask |= ((ys[:, None] - obj.centre[1]) ** 2 + (xs[None, :] - obj.centre[0]) ** 2) <= r * r
    return mask


def fit_logistic(positives: np.ndarray, negatives: np.ndarray, l2: float, positive_weight: float | None = None
                 ) -> tuple[np.ndarray, float]:
    """L2-regularised logistic regression: (w, b) minimising the weighted log-loss + l2/2 |w|^2 (L-BFGS). The
    positives are weighted to the negatives' total unless ``positive_weight`` says otherwise."""
    x = np.concatenate([positives, negatives]).astype(np.float32)
    y = np.concatenate([np.ones(len(positives)), -np.ones(len(negatives))]).astype(np.float32)
    if positive_weight is None:
        positive_weight = len(negatives) / max(len(positives), 1)
    c = np.where(y > 0, positive_weight, 1.0).astype(np.float32)
    c /= c.sum()

    def loss(theta):
        w, b = theta[:-1].astype(np.float32), np.float32(theta[-1])
        margin = y * (x @ w + b)
        value = float(np.sum(c * np.logaddexp(0.0, -margin))) + 0.5 * l2 * float(w @ w)
        g = (-y * c / (1.0 + np.exp(np.clip(margin, -50, 50)))).astype(np.float32)
        grad = np.r_[x.T @ g + l2 * w, g.sum()]
        return value, grad.astype(np.float64)

    import scipy.optimize  # training only: not imported by every detector's and mapper's start

    theta0 = np.zeros(x.shape[1] + 1)
    result = scipy.optimize.minimize(loss, theta0, jac=True, method="L-BFGS-B", options={"maxiter": 500})
    return result.x[:-1].astype(np.float32), float(result.x[-1])


def _pyramid(detector: LinearWindowDetector, image: np.ndarray) -> list[np.ndarray]:
    return [detector.level_features(image, s).astype(np.float16) for s in detector.model.scales]


def train_linear_model(frames, classes, params: FeatureParams = FeatureParams(), scales=(1.0, 0.75, 0.5),
                       window_cells: int = 9, l2: float = 1e-3, random_negatives: int = 40, hard_negatives: int = 20,
                       rounds: int = 2, radius: float = 0.1, level_tolerance: float = 1.3, seed: int = 0,
                       progress=None) -> LinearWindowModel:
    """Fit one window filter per class on ``frames`` = iterable of (BGR image, [TrainingObject]).

    Per class: the window's aspect is the median of its positives' boxes; positives are the windows centred on the
    cell holding each positive object's projected centre, at the level where its box fills the window best;
    ``random_negatives`` windows per frame are drawn at random levels and cells outside ``radius`` x box size of
    every object of the class; then ``rounds`` of hard-negative mining add each frame's ``hard_negatives``
    highest-scoring such windows and refit (logistic regression, ``fit_logistic``).
    """
    classes = tuple(classes)
    scales = tuple(float(s) for s in scales)
    rng = np.random.default_rng(seed)
    cell = params.cell
    dim = feature_dim(params)
    pyramids, objects_per_frame, shapes = [], [], []
    boxes = {k: [] for k in range(len(classes))}
    probe = LinearWindowDetector(LinearWindowModel(classes, [np.zeros((1, 1, dim), np.float32)] * len(classes),
                                                   np.zeros(len(classes)), params, scales))
    for n, (image, objects) in enumerate(frames):
        image = _check_image(image)
        objects = list(objects)
        pyramids.append(_pyramid(probe, image))
        objects_per_frame.append(objects)
        shapes.append(image.shape[:2])
        for obj in objects:
            if obj.positive:
                boxes[obj.class_index].append(obj.size)
        if progress:
            progress("features", n + 1)
    missing = [classes[k] for k, b in boxes.items() if not b]
    if missing:
        raise ValueError(f"no positive example of {missing} in the training frames")
    shapes_c = {k: window_shape(float(np.median([h / w for w, h in b])), window_cells) for k, b in boxes.items()}

    def level_geometry(n, k):
        rows, cols = pyramids[n][k].shape[:2]
        return rows, cols, (rows * cell / shapes[n][0], cols * cell / shapes[n][1])

    weights, biases, info = [], [], {"classes": {}}
    for c, name in enumerate(classes):
        shape = shapes_c[c]
        positives, negatives = [], []
        ignored = {}
        for n, objects in enumerate(objects_per_frame):
            for obj in objects:
                if obj.class_index != c or not obj.positive:
                    continue
                k = best_level(obj.size, shape, scales, cell, level_tolerance)
                if k is None:
                    continue
                rows, cols, scale_rc = level_geometry(n, k)
                r, q = _level_cell(obj.centre, scale_rc, cell)
                if 0 <= r < rows and 0 <= q < cols:
                    positives.append(window_at(pyramids[n][k], r, q, shape).ravel())
            free = []
            for k in range(len(scales)):
                rows, cols, _ = level_geometry(n, k)
                ignored[n, k] = ignored_cells(objects, c, shapes[n], (rows, cols), cell, radius)
                free.append(np.flatnonzero(~ignored[n, k].ravel()))
            for _ in range(random_negatives):
                k = int(rng.integers(len(scales)))
                if len(free[k]):
                    r, q = divmod(int(rng.choice(free[k])), ignored[n, k].shape[1])
                    negatives.append(window_at(pyramids[n][k], r, q, shape).ravel())
        if not positives:
            raise ValueError(f"no positive of {name!r} fits a pyramid level (scales {scales})")
        positives, negatives = np.asarray(positives, np.float32), np.asarray(negatives, np.float32)
        w, b = fit_logistic(positives, negatives, l2)
        for round_ in range(rounds):
            single = LinearWindowDetector(LinearWindowModel((name,), [w.reshape(shape + (dim,))], [b], params, scales))
            mined = []
            for n in range(len(pyramids)):
                candidates = []
                for k in range(len(scales)):
                    scores = single.feature_scores(pyramids[n][k].astype(np.float32))[0]
                    scores[ignored[n, k]] = -np.inf
                    top = np.argsort(scores, axis=None)[::-1][:hard_negatives]
                    candidates += [(scores.flat[t], k, t) for t in top if scores.flat[t] > -1.0]
                candidates.sort(key=lambda item: -item[0])
                for _, k, t in candidates[:hard_negatives]:
                    r, q = divmod(int(t), pyramids[n][k].shape[1])
                    mined.append(window_at(pyramids[n][k], r, q, shape).ravel())
            if mined:
                negatives = np.concatenate([negatives, np.asarray(mined, np.float32)])
            w, b = fit_logistic(positives, negatives, l2)
            if progress:
                progress(f"{name}: round {round_ + 1}, {len(mined)} hard negatives", len(negatives))
        margins_pos = positives @ w + b
        margins_neg = negatives @ w + b
        info["classes"][name] = {"window": list(shape), "positives": int(len(positives)),
                                 "negatives": int(len(negatives)),
                                 "train_positive_recall": float(np.mean(margins_pos > 0)),
                                 "train_negative_false": float(np.mean(margins_neg > 0))}
        weights.append(w.reshape(shape + (dim,)))
        biases.append(b)
    info.update({"frames": len(pyramids), "l2": l2, "rounds": rounds, "window_cells": window_cells,
                 "radius": radius})
    return LinearWindowModel(classes, weights, np.asarray(biases, np.float32), params, scales, info)
