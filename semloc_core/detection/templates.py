"""Single-exemplar object templates and their dense matching (thesis §4.3.3, §4.5.1, eq. 4.3–4.4).

A template is the HOGE and HQC cell histograms of one exemplar image, resized so that its longer side spans
``template_cells`` cells (an odd number, so that the template has a centre cell). Each exemplar also yields its
mirror image (§4.5.1: "compute heatmaps using flipped templates and select the maximal response").

``TemplateDetector.heatmaps`` computes, for every class, the heatmap

    H_T^F(I) = max_s Corr(sqrt F(I^s), sqrt F(T)) / b_T          (eq. 4.3, F = HOGE or HQC)
    H_T      = H_T^HOGE(I) * H_T^HQC(I)                             (eq. 4.4)

and the class heatmap is the maximum over the class's templates (exemplars and mirrors). The correlation of the
square-rooted histograms, summed over the bins, is the Bhattacharyya coefficient of each block pair; summed over
the template blocks and divided by their number b_T it lies in [0, 1]. The template is centred on each output cell
("same" correlation); blocks falling outside the image contribute nothing, so an object half out of view scores at
most about one half.

How it is fast (the reference in tests/detection/reference.py computes the same equations directly):

* features are computed once per frame and pyramid level (the image is rescaled, not the templates), so every
  template shares them;
* HOGE pooling is done on the six products of the three steerable basis responses (see ``features``);
* the correlation is done in the Fourier domain: one forward FFT per feature channel and level, the channel sum
  taken in the frequency domain, one inverse FFT per template, feature and level;
* HQC channels that a template never uses are skipped (their products are zero).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft

from semloc_core.cache import BoundedCache
from semloc_core.detection.features import FeatureParams, Workspace, fit_to_cells, hoge, hqc


@dataclass(frozen=True, eq=False)
class Template:
    """One exemplar view of a class: square-rooted cell histograms, zero outside the object's blocks."""

    class_name: str
    hoge_root: np.ndarray   # (rows, cols, orientations + 1) float32
    hqc_root: np.ndarray    # (rows, cols, levels^3) float32
    block_mask: np.ndarray  # (rows, cols) bool: the blocks that count in b_T
    mirrored: bool = False
    source: str = ""

    def __post_init__(self) -> None:
        mask = np.asarray(self.block_mask, dtype=bool)
        if mask.ndim != 2 or mask.shape[0] % 2 == 0 or mask.shape[1] % 2 == 0:
            raise ValueError(f"template block grid must be 2-D with odd sides, got {mask.shape}")
        if not mask.any():
            raise ValueError(f"template {self.class_name!r} has no object block")
        for name in ("hoge_root", "hqc_root"):
            value = np.asarray(getattr(self, name), dtype=np.float32)
            if value.shape[:2] != mask.shape or value.ndim != 3:
                raise ValueError(f"{name} shape {value.shape} does not match the block grid {mask.shape}")
            object.__setattr__(self, name, np.where(mask[..., None], value, np.float32(0.0)))
        object.__setattr__(self, "block_mask", mask)

    @property
    def shape(self) -> tuple[int, int]:
        return self.block_mask.shape

    @property
    def blocks(self) -> int:
        """b_T of eq. 4.3."""
        return int(self.block_mask.sum())


def _nearest_odd(value: float) -> int:
    return max(1, int(2 * round((value - 1) / 2.0) + 1))


def template_grid(width: int, height: int, template_cells: int) -> tuple[int, int]:
    """(rows, cols) of a template whose longer side spans ``template_cells`` cells, both odd (a centre block)."""
    longer = max(width, height)
    return _nearest_odd(template_cells * height / longer), _nearest_odd(template_cells * width / longer)


def build_templates(exemplar: np.ndarray, class_name: str, params: FeatureParams = FeatureParams(),
                    template_cells: int = 9, mask: np.ndarray | None = None, mirror: bool = True,
                    min_block_coverage: float = 0.5, source: str = "") -> list[Template]:
    """Templates of one exemplar (uint8 BGR) and, if ``mirror``, of its horizontal flip.

    ``mask`` (H, W) bool marks the object's pixels (e.g. from a PNG alpha channel); blocks covered less than
    ``min_block_coverage`` are left out of the template, and colours are counted on object pixels only, so the
    exemplar's background does not have to match the scene's. Without a mask the whole rectangle is the template,
    as in the thesis.
    """
    exemplar = np.asarray(exemplar)
    if exemplar.ndim != 3 or exemplar.shape[2] != 3 or exemplar.dtype != np.uint8:
        raise ValueError(f"exemplar must be a uint8 BGR (H, W, 3) image, got {exemplar.dtype} {exemplar.shape}")
    if int(template_cells) < 1 or int(template_cells) % 2 == 0:
        raise ValueError(f"template_cells must be a positive odd number, got {template_cells}")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != exemplar.shape[:2]:
            raise ValueError(f"mask shape {mask.shape} does not match the exemplar {exemplar.shape[:2]}")
        if not mask.any():
            raise ValueError(f"the mask of exemplar {source or class_name!r} is empty")
    rows, cols = template_grid(exemplar.shape[1], exemplar.shape[0], template_cells)
    cell = params.cell
    size = (cols * cell, rows * cell)
    views = [(exemplar, mask, False)]
    if mirror:
        views.append((exemplar[:, ::-1], None if mask is None else mask[:, ::-1], True))
    templates = []
    for image, view_mask, mirrored in views:
        resized = cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)
        if view_mask is None:
            pixel_mask = None
            block_mask = np.ones((rows, cols), bool)
        else:
            coverage = cv2.resize(view_mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
            pixel_mask = coverage >= 0.5
            block_mask = coverage.reshape(rows, cell, cols, cell).mean(axis=(1, 3)) >= min_block_coverage
            if not block_mask.any():
                raise ValueError(f"exemplar {source or class_name!r}: no block is {min_block_coverage:.0%} object")
        templates.append(Template(
            class_name=class_name,
            hoge_root=np.sqrt(hoge(resized, params)),
            hqc_root=np.sqrt(hqc(resized, params, mask=pixel_mask)),
            block_mask=block_mask,
            mirrored=mirrored,
            source=source,
        ))
    return templates


def mask_uniform_background(bgr: np.ndarray, tolerance: int = 24) -> np.ndarray:
    """Object mask of an exemplar shot on a plain background (e.g. RGB-D Object crops on a white turntable).

    The background colour is the median of the image border; pixels within ``tolerance`` of it (max over channels)
    and connected to the border are background.
    """
    bgr = np.asarray(bgr)
    border = np.concatenate([bgr[0], bgr[-1], bgr[:, 0], bgr[:, -1]]).astype(np.int32)
    background = np.median(border, axis=0)
    close = (np.abs(bgr.astype(np.int32) - background).max(axis=2) <= tolerance).astype(np.uint8)
    # Non-background pixels are label 0; every component of background-coloured pixels touching the border is
    # background (a white label in the middle of the object is not).
    _, labels = cv2.connectedComponents(close, connectivity=4)
    edge_labels = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    is_background = np.isin(labels, edge_labels[edge_labels > 0])
    return ~is_background


# ---------------------------------------------------------------------------------------------------- matching


@dataclass(frozen=True)
class MatchParams:
    """Which pyramid levels the image is matched at (I^s of eq. 4.3) and what the output grid is."""

    scales: tuple[float, ...] = (1.0, 0.75, 0.5)

    def __post_init__(self) -> None:
        scales = tuple(float(s) for s in self.scales)
        if not scales or any(not (0.01 <= s <= 8.0) for s in scales):
            raise ValueError(f"scales must be a non-empty list in [0.01, 8], got {self.scales}")
        object.__setattr__(self, "scales", scales)


def scales_for_object_sizes(smallest_px: float, largest_px: float, count: int, template_cells: int,
                            cell: int) -> tuple[float, ...]:
    """Geometric pyramid so that objects whose longer side spans [smallest_px, largest_px] meet the template size."""
    if not 0 < smallest_px <= largest_px or count < 1:
        raise ValueError("need 0 < smallest_px <= largest_px and count >= 1")
    template_px = template_cells * cell
    sizes = np.geomspace(largest_px, smallest_px, count) if count > 1 else np.array([np.sqrt(smallest_px * largest_px)])
    return tuple(float(template_px / size) for size in sizes)


@dataclass
class _LevelPlan:
    """Everything that depends only on the level's size: FFT shape and the templates' spectra."""

    rows: int
    cols: int
    fft_shape: tuple[int, int]
    hoge_spectra: np.ndarray            # (hoge_bins, templates, P0, P1//2+1) complex64, conjugated
    hqc_channels: np.ndarray            # union of the colours any template uses
    hqc_spectra: list = field(default_factory=list)   # per template: (its channels as positions in the union, spectra)


def _centred_spectrum(blocks: np.ndarray, fft_shape: tuple[int, int]) -> np.ndarray:
    """conj(FFT) of (channels, rows, cols) placed with its centre block at the origin (for "same" correlation)."""
    channels, rows, cols = blocks.shape
    padded = np.zeros((channels,) + fft_shape, np.float32)
    padded[:, :rows, :cols] = blocks
    padded = np.roll(padded, (-(rows // 2), -(cols // 2)), axis=(1, 2))
    return np.conj(scipy.fft.rfft2(padded)).astype(np.complex64)


class TemplateDetector:
    """Soft detector of §4.3: per-class heatmaps in [0, 1] on the base cell grid of the image.

    The output grid has ``round(H / cell)`` x ``round(W / cell)`` cells covering the image uniformly (see
    docs/detection.md). The object holds per-image-size FFT plans (its only state), so reuse one instance per
    stream (and one per thread: it also keeps scratch buffers).
    """

    def __init__(self, templates, params: FeatureParams = FeatureParams(), match: MatchParams = MatchParams()):
        templates = list(templates)
        if not templates:
            raise ValueError("a template detector needs at least one template")
        bins = (params.hoge_bins, params.hqc_bins)
        for template in templates:
            if not isinstance(template, Template):
                raise TypeError(f"expected Template, got {type(template)}")
            if (template.hoge_root.shape[2], template.hqc_root.shape[2]) != bins:
                raise ValueError(f"template {template.class_name!r} was built with other feature parameters")
        self.params = params
        self.match = match
        self.templates = tuple(templates)
        self.classes = tuple(dict.fromkeys(t.class_name for t in templates))
        self._template_class = np.array([self.classes.index(t.class_name) for t in templates])
        self._plans: BoundedCache = BoundedCache(16)  # per pyramid level size (rows, cols)
        self._workspace = Workspace()

    # ---- planning
    def output_shape(self, image_shape) -> tuple[int, int]:
        height, width = image_shape[:2]
        cell = self.params.cell
        return max(1, int(round(height / cell))), max(1, int(round(width / cell)))

    def _plan(self, rows: int, cols: int) -> _LevelPlan:
        plan = self._plans.get((rows, cols))
        if plan is not None:
            return plan
        half_rows = max(t.shape[0] for t in self.templates) // 2
        half_cols = max(t.shape[1] for t in self.templates) // 2
        fft_shape = (scipy.fft.next_fast_len(rows + half_rows, real=True),
                     scipy.fft.next_fast_len(cols + half_cols, real=True))
        # Stored (channels, templates, ...) so that each channel's slice is contiguous for the multiply-add loop.
        hoge_spectra = np.ascontiguousarray(np.stack([
            _centred_spectrum(np.moveaxis(t.hoge_root, 2, 0), fft_shape) / np.float32(t.blocks)
            for t in self.templates], axis=1))
        used = [np.flatnonzero(t.hqc_root.reshape(-1, t.hqc_root.shape[2]).any(axis=0)) for t in self.templates]
        union = np.unique(np.concatenate(used))
        hqc_spectra = []
        for template, channels in zip(self.templates, used):
            blocks = np.moveaxis(template.hqc_root[..., channels], 2, 0)
            hqc_spectra.append((np.searchsorted(union, channels),
                                _centred_spectrum(blocks, fft_shape) / np.float32(template.blocks)))
        plan = _LevelPlan(rows, cols, fft_shape, hoge_spectra, union, hqc_spectra)
        self._plans[(rows, cols)] = plan
        return plan

    # ---- matching
    def level_similarities(self, image: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """Per-template H^HOGE and H^HQC (eq. 4.3 before the max over scales) on the level's own cell grid.

        Returns two (templates, rows, cols) float32 arrays.
        """
        cell = self.params.cell
        level = fit_to_cells(image, scale, cell, self._workspace)
        rows, cols = level.shape[0] // cell, level.shape[1] // cell
        plan = self._plan(rows, cols)
        hoge_root = np.sqrt(hoge(level, self.params, self._workspace))
        hqc_root = np.sqrt(hqc(level, self.params, workspace=self._workspace)[..., plan.hqc_channels])
        hoge_spectrum = scipy.fft.rfft2(np.moveaxis(hoge_root, 2, 0), s=plan.fft_shape)
        hqc_spectrum = scipy.fft.rfft2(np.moveaxis(hqc_root, 2, 0), s=plan.fft_shape)
        # Channel sum in the frequency domain: one inverse FFT per template and feature. Explicit multiply-add
        # loops over channels into preallocated spectra beat einsum on complex64 by about 3x here.
        shape = hoge_spectrum.shape[1:]
        templates = len(self.templates)
        hoge_product = self._workspace.get(f"hoge_product_{shape}", (templates,) + shape, np.complex64)
        hqc_product = self._workspace.get(f"hqc_product_{shape}", (templates,) + shape, np.complex64)
        scratch = self._workspace.get(f"spectrum_scratch_{shape}", (templates,) + shape, np.complex64)
        np.multiply(plan.hoge_spectra[0], hoge_spectrum[0], out=hoge_product)
        for channel in range(1, hoge_spectrum.shape[0]):
            np.multiply(plan.hoge_spectra[channel], hoge_spectrum[channel], out=scratch)
            hoge_product += scratch
        for k, (positions, spectra) in enumerate(plan.hqc_spectra):
            np.multiply(spectra[0], hqc_spectrum[positions[0]], out=hqc_product[k])
            for j in range(1, len(positions)):
                np.multiply(spectra[j], hqc_spectrum[positions[j]], out=scratch[0])
                hqc_product[k] += scratch[0]
        hoge_similarity = scipy.fft.irfft2(hoge_product, s=plan.fft_shape)[:, :rows, :cols]
        hqc_similarity = scipy.fft.irfft2(hqc_product, s=plan.fft_shape)[:, :rows, :cols]
        return hoge_similarity.astype(np.float32), hqc_similarity.astype(np.float32)

    def template_heatmaps(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(H^HOGE, H^HQC) per template after the max over scales, each (templates, h, w) on the output grid."""
        image = _check_image(image)
        out_rows, out_cols = self.output_shape(image.shape)
        best_hoge = best_hqc = None
        for scale in self.match.scales:
            level_hoge, level_hqc = self.level_similarities(image, scale)
            level_hoge = resample_maps(level_hoge, out_rows, out_cols)
            level_hqc = resample_maps(level_hqc, out_rows, out_cols)
            if best_hoge is None:
                best_hoge, best_hqc = level_hoge, level_hqc
            else:
                np.maximum(best_hoge, level_hoge, out=best_hoge)
                np.maximum(best_hqc, level_hqc, out=best_hqc)
        return best_hoge, best_hqc

    def heatmaps(self, image: np.ndarray) -> np.ndarray:
        """Class heatmaps (classes, h, w) float32 in [0, 1]: eq. 4.4, max over each class's templates."""
        best_hoge, best_hqc = self.template_heatmaps(image)
        product = np.clip(best_hoge * best_hqc, 0.0, 1.0)   # eq. 4.4; clip removes FFT round-off only
        return combine_templates(product, self._template_class, len(self.classes))


def combine_templates(per_template: np.ndarray, template_class: np.ndarray, classes: int) -> np.ndarray:
    """Max over the templates of each class: (templates, h, w) -> (classes, h, w)."""
    out = np.zeros((classes,) + per_template.shape[1:], np.float32)
    for k in range(classes):
        members = per_template[template_class == k]
        if len(members):
            out[k] = members.max(axis=0)
    return out


def resample_maps(maps: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Resample (n, r, c) maps covering the image uniformly onto an (n, rows, cols) grid (bilinear, cv2 centres)."""
    if maps.shape[1:] == (rows, cols):
        return np.ascontiguousarray(maps, dtype=np.float32)
    out = np.empty((maps.shape[0], rows, cols), np.float32)
    # cv2.resize takes at most 512 channels at once; templates rarely come near that.
    for start in range(0, maps.shape[0], 512):
        chunk = np.ascontiguousarray(np.moveaxis(maps[start:start + 512], 0, 2), dtype=np.float32)
        resized = cv2.resize(chunk, (cols, rows), interpolation=cv2.INTER_LINEAR)
        out[start:start + 512] = resized.reshape(rows, cols, -1).transpose(2, 0, 1)
    return out


def _check_image(image) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 BGR (H, W, 3) image, got {image.dtype} {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"image {image.shape[1]}x{image.shape[0]} is too small")
    return image
