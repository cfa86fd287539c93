"""The template detector's fast path as it was before the numba / OpenCV-DFT path (main at 45ac78f), kept only as
the in-process speed reference of benchmarks/detector.py ("today's path" of issue 35).

Same equations as semloc_core.detection.templates: per pyramid level, the steerable basis filtered by OpenCV into
three full-size images, HOGE pooled with six cv2.multiply + INTER_AREA block means and a matrix product, HQC counted
with ``bincount`` over bands of cells, the correlation with ``scipy.fft`` (one forward transform per channel, complex
multiply-adds in numpy, one inverse per template and feature). It shares the unchanged helpers (kernels, noise
floor, colour votes, resizing) with the product code.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.fft

from semloc_core.detection import features as f
from semloc_core.detection.templates import TemplateDetector, _check_image


def _basis_responses(image, params: f.FeatureParams, workspace: f.Workspace):
    """The steerable basis (Gxx, Gxy, Gyy), three OpenCV separable filters into full-size images."""
    grey = f._check_grey(image, params.cell, workspace)
    g, g1, g2 = (k.astype(np.float32) for k in f.gaussian_derivative_kernels(params.sigma))
    border = cv2.BORDER_REFLECT_101
    shape = grey.shape
    gxx = cv2.sepFilter2D(grey, cv2.CV_32F, g2, g, dst=workspace.get("gxx", shape, np.float32), borderType=border)
    gxy = cv2.sepFilter2D(grey, cv2.CV_32F, g1, g1, dst=workspace.get("gxy", shape, np.float32), borderType=border)
    gyy = cv2.sepFilter2D(grey, cv2.CV_32F, g, g2, dst=workspace.get("gyy", shape, np.float32), borderType=border)
    return gxx, gxy, gyy


def _hoge(image, params: f.FeatureParams, workspace: f.Workspace) -> np.ndarray:
    gxx, gxy, gyy = _basis_responses(image, params, workspace)
    shape = gxx.shape
    cell = params.cell
    rows, cols = shape[0] // cell, shape[1] // cell
    product = workspace.get("product", shape, np.float32)
    pooled = np.empty((6, rows, cols), np.float32)
    for k, (a, b) in enumerate(((gxx, gxx), (gxy, gxy), (gyy, gyy), (gxx, gxy), (gxx, gyy), (gxy, gyy))):
        cv2.multiply(a, b, dst=product)
        cv2.resize(product, (cols, rows), dst=pooled[k], interpolation=cv2.INTER_AREA)
    pooled *= np.float32(cell * cell)
    energies = (pooled.reshape(6, -1).T @ f._energy_weights(params.orientation_angles).astype(np.float32))
    energies = np.maximum(energies.reshape(rows, cols, -1), 0.0)
    total = energies.sum(axis=-1, keepdims=True, dtype=np.float32)
    epsilon = np.float32(f.noise_floor(total, params))
    denominator = total + epsilon
    histogram = np.empty(energies.shape[:-1] + (energies.shape[-1] + 1,), np.float32)
    np.divide(energies, denominator, out=histogram[..., :-1])
    np.divide(epsilon, denominator[..., 0], out=histogram[..., -1])
    return histogram


def _hqc(bgr, params: f.FeatureParams, workspace: f.Workspace) -> np.ndarray:
    cell = params.cell
    votes = f.colour_votes(bgr, params, workspace)
    height, width = votes[0][0].shape
    rows, cols = height // cell, width // cell
    bins = params.hqc_bins
    band_rows = max(1, 16384 // (cols * bins))
    band_height = band_rows * cell

    def band_keys(buffer: np.ndarray) -> None:
        buffer[:] = ((np.arange(band_height)[:, None] // cell) * cols + (np.arange(width)[None, :] // cell)) * bins

    base = workspace.get(f"hqc_base_{cell}_{bins}", (band_height, width), np.int64, init=band_keys)
    keys = workspace.get("hqc_keys", (band_height, width), np.int64)
    histogram = np.zeros((rows, cols, bins), np.float32)
    for row in range(0, rows, band_rows):
        count = min(band_rows, rows - row)
        pixels = slice(row * cell, (row + count) * cell)
        for index, weight in votes:
            np.add(base[:count * cell], index[pixels], out=keys[:count * cell])
            counts = np.bincount(keys[:count * cell].ravel(), minlength=count * cols * bins,
                                 weights=None if weight is None else weight[pixels].ravel())
            histogram[row:row + count] += counts.reshape(count, cols, bins)
    histogram *= np.float32(1.0 / (cell * cell))
    return histogram


def _resample(maps: np.ndarray, rows: int, cols: int) -> np.ndarray:
    if maps.shape[1:] == (rows, cols):
        return np.ascontiguousarray(maps, dtype=np.float32)
    chunk = np.ascontiguousarray(np.moveaxis(maps, 0, 2), dtype=np.float32)
    resized = cv2.resize(chunk, (cols, rows), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(resized.reshape(rows, cols, -1).transpose(2, 0, 1))


def _centred_spectrum(blocks: np.ndarray, fft_shape: tuple[int, int]) -> np.ndarray:
    channels, rows, cols = blocks.shape
    padded = np.zeros((channels,) + fft_shape, np.float32)
    padded[:, :rows, :cols] = blocks
    padded = np.roll(padded, (-(rows // 2), -(cols // 2)), axis=(1, 2))
    return np.conj(scipy.fft.rfft2(padded)).astype(np.complex64)


class PreviousTemplateDetector:
    """``heatmaps(image)`` of the previous fast path, for the templates, features and scales of ``detector``."""

    def __init__(self, detector: TemplateDetector):
        self.detector = detector
        self.params = detector.params
        self._plans: dict = {}
        self._workspace = f.Workspace()

    def _plan(self, rows: int, cols: int):
        plan = self._plans.get((rows, cols))
        if plan is None:
            templates = self.detector.templates
            fft_shape = (scipy.fft.next_fast_len(rows + max(t.shape[0] for t in templates) // 2, real=True),
                         scipy.fft.next_fast_len(cols + max(t.shape[1] for t in templates) // 2, real=True))
            hoge_spectra = np.ascontiguousarray(np.stack([
                _centred_spectrum(np.moveaxis(t.hoge_root, 2, 0), fft_shape) / np.float32(t.blocks)
                for t in templates], axis=1))
            used = [np.flatnonzero(t.hqc_root.reshape(-1, t.hqc_root.shape[2]).any(axis=0)) for t in templates]
            union = np.unique(np.concatenate(used))
            hqc_spectra = [(np.searchsorted(union, channels),
                            _centred_spectrum(np.moveaxis(t.hqc_root[..., channels], 2, 0), fft_shape)
                            / np.float32(t.blocks)) for t, channels in zip(templates, used)]
            plan = self._plans[(rows, cols)] = (fft_shape, hoge_spectra, union, hqc_spectra)
        return plan

    def level_similarities(self, image: np.ndarray, scale: float):
        cell = self.params.cell
        level = f.fit_to_cells(image, scale, cell, self._workspace)
        rows, cols = level.shape[0] // cell, level.shape[1] // cell
        fft_shape, hoge_spectra, union, hqc_spectra = self._plan(rows, cols)
        hoge_spectrum = scipy.fft.rfft2(np.moveaxis(np.sqrt(_hoge(level, self.params, self._workspace)), 2, 0),
                                        s=fft_shape)
        hqc_root = np.sqrt(_hqc(level, self.params, self._workspace)[..., union])
        hqc_spectrum = scipy.fft.rfft2(np.moveaxis(hqc_root, 2, 0), s=fft_shape)
        shape = hoge_spectrum.shape[1:]
        templates = len(self.detector.templates)
        hoge_product = self._workspace.get(f"hoge_product_{shape}", (templates,) + shape, np.complex64)
        hqc_product = self._workspace.get(f"hqc_product_{shape}", (templates,) + shape, np.complex64)
        scratch = self._workspace.get(f"spectrum_scratch_{shape}", (templates,) + shape, np.complex64)
        np.multiply(hoge_spectra[0], hoge_spectrum[0], out=hoge_product)
        for channel in range(1, hoge_spectrum.shape[0]):
            np.multiply(hoge_spectra[channel], hoge_spectrum[channel], out=scratch)
            hoge_product += scratch
        for k, (positions, spectra) in enumerate(hqc_spectra):
            np.multiply(spectra[0], hqc_spectrum[positions[0]], out=hqc_product[k])
            for j in range(1, len(positions)):
                np.multiply(spectra[j], hqc_spectrum[positions[j]], out=scratch[0])
                hqc_product[k] += scratch[0]
        hoge_similarity = scipy.fft.irfft2(hoge_product, s=fft_shape)[:, :rows, :cols]
        hqc_similarity = scipy.fft.irfft2(hqc_product, s=fft_shape)[:, :rows, :cols]
        return hoge_similarity.astype(np.float32), hqc_similarity.astype(np.float32)

    def heatmaps(self, image: np.ndarray) -> np.ndarray:
        image = _check_image(image)
        out_rows, out_cols = self.detector.output_shape(image.shape)
        best_hoge = best_hqc = None
        for scale in self.detector.match.scales:
            level_hoge, level_hqc = self.level_similarities(image, scale)
            level_hoge = _resample(level_hoge, out_rows, out_cols)
            level_hqc = _resample(level_hqc, out_rows, out_cols)
            if best_hoge is None:
                best_hoge, best_hqc = level_hoge, level_hqc
            else:
                np.maximum(best_hoge, level_hoge, out=best_hoge)
                np.maximum(best_hqc, level_hqc, out=best_hqc)
        product = np.clip(best_hoge * best_hqc, 0.0, 1.0)
        classes = self.detector.classes
        template_class = np.array([classes.index(t.class_name) for t in self.detector.templates])
        out = np.zeros((len(classes),) + product.shape[1:], np.float32)
        for k in range(len(classes)):
            out[k] = product[template_class == k].max(axis=0)
        return out
