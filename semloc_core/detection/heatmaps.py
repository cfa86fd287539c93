"""Small heatmap utilities shared by the detector worker, the evaluation and the mapper: pooling, quantising,
overlays."""

from __future__ import annotations

import cv2
import numpy as np


def max_pool(heatmaps: np.ndarray, factor: int) -> np.ndarray:
    """Downsample (classes, rows, cols) by an integer ``factor`` keeping each block's maximum (peaks survive).

    Trailing rows/columns that do not fill a block are pooled into the last block, so the result still covers the
    whole image uniformly: shape (classes, ceil(rows / factor), ceil(cols / factor)).
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"pooling factor must be >= 1, got {factor}")
    heatmaps = np.asarray(heatmaps, dtype=np.float32)
    if factor == 1:
        return heatmaps
    classes, rows, cols = heatmaps.shape
    out_rows, out_cols = -(-rows // factor), -(-cols // factor)
    padded = np.full((classes, out_rows * factor, out_cols * factor), -np.inf, np.float32)
    padded[:, :rows, :cols] = heatmaps
    pooled = padded.reshape(classes, out_rows, factor, out_cols, factor).max(axis=(2, 4))
    return pooled


def quantise_unit(scores: np.ndarray, dtype: str = "uint8") -> tuple[np.ndarray, float]:
    """Scores in [0, 1] for the wire: (values, scale) with score = values * scale. uint8 rounds to 1/255."""
    scores = np.clip(np.asarray(scores, dtype=np.float32), 0.0, 1.0)
    if dtype == "uint8":
        return np.rint(scores * 255.0).astype(np.uint8), 1.0 / 255.0
    if dtype in ("float16", "float32"):
        return scores.astype(dtype), 1.0
    raise ValueError(f"heatmap dtype must be uint8, float16 or float32, got {dtype!r}")


def overlay(image: np.ndarray, heatmap: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """The image with one class's heatmap (any grid covering it, values in [0, 1]) blended on top in turbo."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    height, width = image.shape[:2]
    upsampled = cv2.resize(np.asarray(heatmap, np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    colours = cv2.applyColorMap(np.rint(np.clip(upsampled, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return cv2.addWeighted(image, 1.0 - alpha, colours, alpha, 0.0)
