"""Straightforward implementation of the §4.3 detector, written directly from the equations.

It shares nothing with the fast path but the glue both must agree on (resizing the image to a pyramid level and
resampling level maps onto the output grid): every oriented kernel is built and applied on its own, energies are
squared per pixel and summed per block (eq. 4.1), normalised (eq. 4.2), colours are mapped to the nearest of the
k^3 palette colours by distance, and the correlation of eq. 4.3 is a plain sum over the template's blocks. Used by
tests/detection and benchmarks/detector.py to check the fast detector; far too slow for the product path.
"""

from __future__ import annotations

import cv2
import numpy as np

from semloc_core.detection.features import FeatureParams, fit_to_cells
from semloc_core.detection.templates import Template, resample_maps


def _kernels_1d(sigma: float):
    radius = max(1, int(np.ceil(4.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1.0 / sigma**2) * g
    g2 -= g * (g2.sum() / g.sum())
    return g, g1, g2


def oriented_kernel(theta: float, sigma: float) -> np.ndarray:
    """2-D second derivative of a Gaussian along direction theta (x right, y down): d^2/dn^2 G."""
    g, g1, g2 = _kernels_1d(sigma)
    kxx, kxy, kyy = np.outer(g, g2), np.outer(g1, g1), np.outer(g2, g)
    c, s = np.cos(theta), np.sin(theta)
    return c * c * kxx + 2 * c * s * kxy + s * s * kyy


def hoge_reference(image: np.ndarray, params: FeatureParams) -> np.ndarray:
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    grey = grey.astype(np.float64)
    cell = params.cell
    rows, cols = grey.shape[0] // cell, grey.shape[1] // cell
    energies = np.zeros((rows, cols, params.orientations))
    for i, theta in enumerate(params.orientation_angles):
        response = cv2.filter2D(grey, cv2.CV_64F, oriented_kernel(theta, params.sigma),
                                borderType=cv2.BORDER_REFLECT_101)
        squared = response**2                                                        # eq. 4.1
        energies[..., i] = squared.reshape(rows, cell, cols, cell).sum(axis=(1, 3))  # sum over Omega
    total = energies.sum(axis=-1)
    # Expected maximum: the image's 99th-percentile block energy, at least that of a min_contrast step edge
    # (measured here by filtering an actual edge rather than by the closed form the fast path uses).
    edge = np.zeros((3 * cell, 3 * cell))
    edge[:, int(1.5 * cell):] = params.min_contrast
    edge_energies = []
    for theta in params.orientation_angles:
        response = cv2.filter2D(edge, cv2.CV_64F, oriented_kernel(theta, params.sigma), borderType=cv2.BORDER_REPLICATE)
        edge_energies.append((response[cell:2 * cell] ** 2).sum())
    epsilon = params.epsilon_fraction * max(np.percentile(total, 99.0), sum(edge_energies))
    histogram = np.concatenate([energies, np.full((rows, cols, 1), epsilon)], axis=-1)
    return histogram / (epsilon + total)[..., None]                                  # eq. 4.2


def hsv_votes_reference(bgr: np.ndarray, params: FeatureParams) -> list[tuple[np.ndarray, np.ndarray]]:
    """The hsv colour model written out: greys by brightness; chromatic pixels split between the two hue bins
    whose centres (every 360 / hue_levels degrees from red) bracket their hue, at their saturation bin."""
    from semloc_core.detection import features as f

    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV).astype(np.float64)
    hue, saturation, value = hsv[..., 0] * 2.0, hsv[..., 1], hsv[..., 2]       # hue in degrees
    chromatic = (saturation >= f.HSV_MIN_SATURATION) & (value >= f.HSV_MIN_VALUE)
    hue_levels, saturation_levels = params.hue_levels, params.saturation_levels
    position = hue / (360.0 / hue_levels)
    lower = np.floor(position).astype(np.int64) % hue_levels
    upper = (lower + 1) % hue_levels
    share = position - np.floor(position)
    saturation_bin = np.clip((saturation.astype(np.int64) - f.HSV_MIN_SATURATION) * saturation_levels
                             // (256 - f.HSV_MIN_SATURATION), 0, saturation_levels - 1)
    grey_bin = value.astype(np.int64) * f.HSV_GREY_LEVELS // 256
    first = np.where(chromatic, f.HSV_GREY_LEVELS + lower * saturation_levels + saturation_bin, grey_bin)
    second = np.where(chromatic, f.HSV_GREY_LEVELS + upper * saturation_levels + saturation_bin, grey_bin)
    share = np.where(chromatic, share, 0.0)
    return [(first, 1.0 - share), (second, share)]


def hqc_reference(bgr: np.ndarray, params: FeatureParams, mask: np.ndarray | None = None) -> np.ndarray:
    if params.color_space == "hsv":
        votes = hsv_votes_reference(bgr, params)
    else:
        k = params.color_levels
        palette_values = np.linspace(0.0, 255.0, k)
        b, g, r = np.meshgrid(palette_values, palette_values, palette_values, indexing="ij")
        palette = np.stack([b.ravel(), g.ravel(), r.ravel()], axis=1)      # index = (b * k + g) * k + r
        pixels = bgr.reshape(-1, 3).astype(np.float64)
        distances = ((pixels[:, None, :] - palette[None, :, :]) ** 2).sum(axis=2)
        votes = [(distances.argmin(axis=1).reshape(bgr.shape[:2]), np.ones(bgr.shape[:2]))]
    bins = params.hqc_bins
    cell = params.cell
    rows, cols = bgr.shape[0] // cell, bgr.shape[1] // cell
    histogram = np.zeros((rows, cols, bins))
    for r in range(rows):
        for c in range(cols):
            pixels = (slice(r * cell, (r + 1) * cell), slice(c * cell, (c + 1) * cell))
            inside = np.ones((cell, cell), bool) if mask is None else mask[pixels]
            if not inside.any():
                continue
            for index, weight in votes:
                histogram[r, c] += np.bincount(index[pixels][inside], weights=weight[pixels][inside], minlength=bins)
            histogram[r, c] /= inside.sum()
    return histogram


def correlate_reference(features_root: np.ndarray, template_root: np.ndarray, block_mask: np.ndarray) -> np.ndarray:
    """eq. 4.3 for one level: sum over template blocks of the Bhattacharyya coefficient, divided by b_T."""
    rows, cols, _ = features_root.shape
    t_rows, t_cols = block_mask.shape
    half_r, half_c = t_rows // 2, t_cols // 2
    padded = np.zeros((rows + 2 * half_r, cols + 2 * half_c, features_root.shape[2]))
    padded[half_r:half_r + rows, half_c:half_c + cols] = features_root
    out = np.zeros((rows, cols))
    for a in range(t_rows):
        for b in range(t_cols):
            if block_mask[a, b]:
                out += padded[a:a + rows, b:b + cols] @ template_root[a, b]
    return out / block_mask.sum()


def template_reference(exemplar: np.ndarray, class_name: str, params: FeatureParams, template_cells: int,
                       mask=None) -> list[Template]:
    """Original + mirrored template, built with the reference features (mirror = flipped exemplar)."""
    from semloc_core.detection.templates import template_grid

    rows, cols = template_grid(exemplar.shape[1], exemplar.shape[0], template_cells)
    size = (cols * params.cell, rows * params.cell)
    out = []
    for mirrored in (False, True):
        image = exemplar[:, ::-1] if mirrored else exemplar
        resized = cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)
        pixel_mask, block_mask = None, np.ones((rows, cols), bool)
        if mask is not None:
            view_mask = mask[:, ::-1] if mirrored else mask
            coverage = cv2.resize(view_mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
            pixel_mask = coverage >= 0.5
            block_mask = coverage.reshape(rows, params.cell, cols, params.cell).mean(axis=(1, 3)) >= 0.5
        out.append(Template(class_name, np.sqrt(hoge_reference(resized, params)),
                            np.sqrt(hqc_reference(resized, params, pixel_mask)), block_mask, mirrored))
    return out


def heatmaps_reference(image: np.ndarray, templates, params: FeatureParams, scales) -> np.ndarray:
    """Class heatmaps (classes, h, w): eq. 4.3 (max over scales per feature), eq. 4.4, max over templates."""
    classes = list(dict.fromkeys(t.class_name for t in templates))
    out_rows = max(1, int(round(image.shape[0] / params.cell)))
    out_cols = max(1, int(round(image.shape[1] / params.cell)))
    best_hoge = np.zeros((len(templates), out_rows, out_cols), np.float32)
    best_hqc = np.zeros_like(best_hoge)
    for scale in scales:
        level = fit_to_cells(image, scale, params.cell)
        hoge_root = np.sqrt(hoge_reference(level, params))
        hqc_root = np.sqrt(hqc_reference(level, params))
        level_hoge = np.stack([correlate_reference(hoge_root, t.hoge_root, t.block_mask) for t in templates])
        level_hqc = np.stack([correlate_reference(hqc_root, t.hqc_root, t.block_mask) for t in templates])
        best_hoge = np.maximum(best_hoge, resample_maps(level_hoge.astype(np.float32), out_rows, out_cols))
        best_hqc = np.maximum(best_hqc, resample_maps(level_hqc.astype(np.float32), out_rows, out_cols))
    product = best_hoge * best_hqc                                                   # eq. 4.4
    heatmaps = np.zeros((len(classes), out_rows, out_cols), np.float32)
    for k, name in enumerate(classes):
        heatmaps[k] = np.max([product[i] for i, t in enumerate(templates) if t.class_name == name], axis=0)
    return heatmaps
