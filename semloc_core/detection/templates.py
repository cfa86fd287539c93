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
  template shares them; HOGE pooling is done on the six products of the three steerable basis responses, and both
  features are pooled per cell in one pass over the pixels (``features``, numba);
* the correlation is done in the frequency domain (``correlation.Correlator``): one forward DFT per feature channel
  and level, the channel sum taken in the frequency domain, one inverse DFT per template, feature and level;
* HQC channels that a template never uses are skipped (their products are zero);
* nothing of a frame's size is allocated per frame (scratch buffers are kept per image size).
"""

from __future__ import annotations

import math
import os
from fractions import Fraction
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from semloc_core.detection import _kernels
from semloc_core.detection.correlation import Correlator
from semloc_core.detection.features import FeatureParams, Workspace, fit_to_cells, hoge, hqc, root_features


# A detector runs this once when built, so that a worker's first frame does not wait for numba's compiler.
WARM_UP_IMAGE = np.zeros((32, 32, 3), np.uint8)


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
    resized = cv2.resize(np.ascontiguousarray(exemplar), size, interpolation=cv2.INTER_AREA)
    if mask is None:
        pixel_mask = None
        block_mask = np.ones((rows, cols), bool)
    else:
        coverage = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        pixel_mask = coverage >= 0.5
        block_mask = coverage.reshape(rows, cell, cols, cell).mean(axis=(1, 3)) >= min_block_coverage
        if not block_mask.any():
            raise ValueError(f"exemplar {source or class_name!r}: no block is {min_block_coverage:.0%} object")
    template = Template(class_name=class_name, hoge_root=np.sqrt(hoge(resized, params)),
                        hqc_root=np.sqrt(hqc(resized, params, mask=pixel_mask)), block_mask=block_mask,
                        source=source)
    return [template, mirrored_template(template)] if mirror else [template]


def mirrored_template(template: Template) -> Template:
    """The template of the exemplar's horizontal flip: its blocks in reverse column order, each HOGE orientation
    theta counted as pi - theta (bin k of N as bin (N - k) mod N; the noise bin stays), colours unchanged.

    That is what the features of the flipped image are (the flipped exemplar's HOGE computed afresh differs by
    float rounding only, at most 3e-7 on the demo's exemplars), and exactly mirrored kernels share their spectra in
    the correlator (``correlation._mirror_pairs``): a frame reads half as many."""
    orientations = template.hoge_root.shape[2] - 1
    order = np.r_[(orientations - np.arange(orientations)) % orientations, orientations]
    return Template(class_name=template.class_name, hoge_root=template.hoge_root[:, ::-1][..., order],
                    hqc_root=template.hqc_root[:, ::-1], block_mask=template.block_mask[:, ::-1],
                    mirrored=not template.mirrored, source=template.source)


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


class TemplateDetector:
    """Soft detector of §4.3: per-class heatmaps in [0, 1] on the base cell grid of the image.

    The output grid has ``round(H / cell)`` x ``round(W / cell)`` cells covering the image uniformly (see
    docs/detection.md). The object holds per-image-size DFT plans and scratch buffers, so reuse one instance per
    stream (and one per thread).

    ``threads`` > 1 matches the pyramid levels concurrently, the levels split into that many groups of about equal
    pixel counts, one group on the calling thread and the others on the detector's own worker threads (every kernel
    releases the GIL). The heatmaps are the same to the bit (a max is taken in any order); only the wall time
    drops, not the CPU time a frame costs.
    """

    def __init__(self, templates, params: FeatureParams = FeatureParams(), match: MatchParams = MatchParams(),
                 threads: int = 1):
        templates = list(templates)
        if not templates:
            raise ValueError("a template detector needs at least one template")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or not 1 <= threads <= 16:
            raise ValueError(f"threads must be an integer in [1, 16], got {threads!r}")
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
        self._class_members = [np.flatnonzero([t.class_name == name for t in templates]) for name in self.classes]
        # One correlation per template and feature over the level's HOGE bins and the colours any template uses
        # (a colour no template uses contributes zero); each divided by the template's b_T (eq. 4.3).
        used = [np.flatnonzero(t.hqc_root.reshape(-1, t.hqc_root.shape[2]).any(axis=0)) for t in templates]
        self._hqc_channels = np.unique(np.concatenate(used))
        hoge_bins = params.hoge_bins
        kernels = [(np.arange(hoge_bins), np.moveaxis(t.hoge_root, 2, 0) / np.float32(t.blocks)) for t in templates]
        kernels += [(hoge_bins + np.searchsorted(self._hqc_channels, channels),
                     np.moveaxis(t.hqc_root[..., channels], 2, 0) / np.float32(t.blocks))
                    for t, channels in zip(templates, used)]
        self._correlator = Correlator(hoge_bins + self._hqc_channels.size, kernels)
        self.threads = int(threads)
        self.band_steps = 16   # a level matched on some rows runs on a whole number of 16ths of its height
        # One workspace per group of levels: groups run concurrently, each in its own buffers.
        self._workspaces = [Workspace() for _ in range(self.threads)]
        self._workspace = self._workspaces[0]
        self._pool, self._pool_pid = None, None   # made on first use, again in a forked child (threads do not fork)
        self.heatmaps(WARM_UP_IMAGE)   # numba compiles (or loads) its kernels now, not on the first camera frame

    def output_shape(self, image_shape) -> tuple[int, int]:
        height, width = image_shape[:2]
        cell = self.params.cell
        return max(1, int(round(height / cell))), max(1, int(round(width / cell)))

    # ---- matching
    def _level_maps(self, image: np.ndarray, scale: float, workspace: Workspace | None = None,
                    band: tuple[int, int] | None = None) -> np.ndarray:
        """(templates, rows, cols, 2): every template's H^HOGE in [..., 0] and H^HQC in [..., 1] on the level's own
        cell grid (a view of a buffer that the next call overwrites); with ``band`` (``_level_band``) only on the
        level's cell rows [first, last)."""
        cell = self.params.cell
        workspace = workspace or self._workspace
        level = fit_to_cells(image, scale, cell, workspace) if band is None else self._band_image(
            image, scale, band, workspace)
        rows, cols = level.shape[0] // cell, level.shape[1] // cell
        # Features are computed once per frame and level and shared by every template (square roots: eq. 4.3's
        # correlation of sqrt F then sums the Bhattacharyya coefficients of the block pairs).
        root_features(level, self.params, self._hqc_channels, self._correlator.input(rows, cols), workspace)
        return self._correlator.run(rows, cols)   # kernel t (HOGE) and t + templates (HQC) share a pair

    def _band_alignment(self, image_shape, scale: float) -> int | None:
        """The level's cell rows at which a band can start so that resizing its source rows alone samples them as
        resizing the whole image does (the source row ratio a whole number there), or None when that step is
        coarser than an eighth of the level (then the whole level is resized and cut)."""
        cell = self.params.cell
        level_rows = self._level_size(image_shape, scale)[0]
        ratio = Fraction(int(image_shape[0]), level_rows * cell)   # source rows per level row
        step = ratio.denominator // math.gcd(ratio.denominator, cell)
        return step if step * 8 <= level_rows else None

    def _band_image(self, image: np.ndarray, scale: float, band: tuple[int, int], workspace: Workspace) -> np.ndarray:
        """The level's image on its cell rows ``band`` only: resized from the source rows that cover them where the
        band is aligned (``_band_alignment``; the whole level resized costs a fifth of its matching), else cut from
        the whole level. Either way the same pixels as the whole level's but for a band's first and last rows (the
        crop's edge replicated, inside the template's reach)."""
        cell = self.params.cell
        if self._band_alignment(image.shape, scale) is None:
            return fit_to_cells(image, scale, cell, workspace)[band[0] * cell:band[1] * cell]
        level_rows, level_cols = self._level_size(image.shape, scale)
        ratio = Fraction(int(image.shape[0]), level_rows * cell)
        first, last = band[0] * cell * ratio, band[1] * cell * ratio   # whole numbers: the band is aligned
        size = (level_cols * cell, (band[1] - band[0]) * cell)
        out = workspace.get(f"band_{size}", (size[1], size[0], 3), np.uint8)
        # as fit_to_cells: INTER_AREA where OpenCV has its integer-factor path
        whole = (level_cols * cell, level_rows * cell)
        integer = image.shape[1] * whole[1] == image.shape[0] * whole[0] and ratio.denominator == 1 and ratio > 1
        return cv2.resize(image[int(first):int(last)], size, dst=out,
                          interpolation=cv2.INTER_AREA if integer else cv2.INTER_LINEAR)

    def _level_band(self, level_rows: int, out_total: int, out_rows: tuple[int, int],
                    alignment: int | None = None) -> tuple[int, int]:
        """The level's cell rows [first, last) matched for output rows ``out_rows``: widened by the template's
        half-height and a cell for the resampling, its height rounded up to a whole number of ``1 / band_steps`` of
        the level (a few buffer and DFT sizes a stream) and of ``alignment``, starting on a multiple of
        ``alignment``, kept inside the level."""
        alignment = alignment or 1
        reach = max(t.shape[0] for t in self.templates) // 2 + 1
        first = max(0, math.floor(out_rows[0] * level_rows / out_total) - reach) // alignment * alignment
        last = min(level_rows, math.ceil(out_rows[1] * level_rows / out_total) + reach)
        step = alignment * max(1, math.ceil(level_rows / self.band_steps / alignment))
        height = min(level_rows, math.ceil((last - first) / step) * step)
        first = min(first, (level_rows - height) // alignment * alignment)
        return first, min(level_rows, first + height)

    def level_similarities(self, image: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """Per-template H^HOGE and H^HQC (eq. 4.3 before the max over scales) on the level's own cell grid.

        Returns two (templates, rows, cols) float32 arrays.
        """
        maps = self._level_maps(_check_image(image), scale)
        return np.ascontiguousarray(maps[..., 0]), np.ascontiguousarray(maps[..., 1])

    def _best_over_scales(self, image: np.ndarray, scales=None, rows=None) -> np.ndarray:
        """(templates, h, w, 2): the max over scales of every template's H^HOGE ([..., 0]) and H^HQC ([..., 1]) on
        the output grid (a workspace buffer, overwritten by the next call)."""
        image = _check_image(image)
        out_rows, out_cols = self.output_shape(image.shape)
        if rows is not None:
            rows = self._check_rows(rows, out_rows)
            scales = tuple(s for s in self.match.scales if s in rows)
            if not scales:   # no level sees an object anywhere: no heat
                best = self._workspace.get("best", (len(self.templates), out_rows, out_cols, 2), np.float32)
                best.fill(0.0)
                return best
        scales = self.match.scales if scales is None else self._check_scales(scales)
        groups = _level_groups(scales, self.threads)
        if len(groups) > 1 and len({self._correlator.dft_shape(*self._matched_size(image.shape, s, out_rows, rows))
                                    for s in scales}) < len(scales):
            groups = [sorted(scales, reverse=True)]   # two levels of one DFT size would share the correlator's buffers
        shape = (len(self.templates), out_rows, out_cols, 2)
        if len(groups) > 1 and self._pool_pid != os.getpid():
            self._pool, self._pool_pid = ThreadPoolExecutor(self.threads - 1, "semloc-detector"), os.getpid()
        futures = [self._pool.submit(self._best_of_levels, image, group, self._workspaces[k], shape, rows)
                   for k, group in enumerate(groups[1:], start=1)]
        best = self._best_of_levels(image, groups[0], self._workspace, shape, rows)
        for future in futures:
            np.maximum(best, future.result(), out=best)
        return best

    def _matched_size(self, image_shape, scale: float, out_rows: int, rows=None) -> tuple[int, int]:
        """The cell grid a level is matched on: the whole level's, or its band's."""
        level_rows, level_cols = self._level_size(image_shape, scale)
        if rows is None:
            return level_rows, level_cols
        first, last = self._level_band(level_rows, out_rows, rows[scale], self._band_alignment(image_shape, scale))
        return last - first, level_cols

    def _level_size(self, image_shape, scale: float) -> tuple[int, int]:
        """A level's cell grid (as ``fit_to_cells`` sizes it)."""
        return self.output_shape((image_shape[0] * scale, image_shape[1] * scale))

    def _best_of_levels(self, image: np.ndarray, scales, workspace: Workspace, shape, rows=None) -> np.ndarray:
        """The max over these levels of every template's maps on the output grid (``_best_over_scales``), in
        ``workspace``'s buffers; with ``rows`` each level on its band only, 0 where no level runs."""
        out_rows, out_cols = shape[1:3]
        best = workspace.get("best", shape, np.float32)
        resampled = workspace.get("resampled", shape, np.float32)
        if rows is not None:
            best.fill(0.0)
        for k, scale in enumerate(scales):
            level_rows = self._level_size(image.shape, scale)[0]
            band = None if rows is None else self._level_band(level_rows, out_rows, rows[scale],
                                                              self._band_alignment(image.shape, scale))
            if band == (0, level_rows):
                band = None
            level = self._level_maps(image, scale, workspace, band)
            if band is not None:
                _resample_band(level, band, level_rows, best, workspace)
                continue
            target = best if k == 0 and rows is None else resampled   # the first level straight into the max
            if level.shape[1:3] == (out_rows, out_cols):
                np.copyto(target, level)
            else:
                for maps, out in zip(level, target):   # both features of a template at once (2 channels)
                    cv2.resize(maps, (out_cols, out_rows), dst=out, interpolation=cv2.INTER_LINEAR)
            if target is resampled:
                np.maximum(best, resampled, out=best)
        return best

    def _check_scales(self, scales) -> tuple[float, ...]:
        scales = tuple(float(s) for s in scales)
        unknown = [s for s in scales if s not in self.match.scales]
        if not scales or unknown:
            raise ValueError(f"scales must be a non-empty subset of the detector's {self.match.scales}, got {scales}")
        return scales

    def _check_rows(self, rows, out_rows: int) -> dict[float, tuple[int, int]]:
        checked = {}
        for scale, band in dict(rows).items():
            scale = float(scale)
            first, last = (int(v) for v in band)
            if scale not in self.match.scales or not 0 <= first < last <= out_rows:
                raise ValueError(f"rows: level {scale} must be one of {self.match.scales} with 0 <= first < last <= "
                                 f"{out_rows}, got {band}")
            checked[scale] = (first, last)
        return checked

    def level_object_px(self) -> dict[float, float]:
        """Each level's matched object size: the longer side, in image pixels, of an object as long as a template
        (``template_cells x cell / s``)."""
        template_px = max(max(t.shape) for t in self.templates) * self.params.cell
        return {s: template_px / s for s in self.match.scales}

    def levels_for(self, smallest_px: float, largest_px: float) -> tuple[float, ...]:
        """The pyramid levels that answer for objects whose longer side spans [smallest_px, largest_px] pixels in the
        image, for ``heatmaps(image, scales=...)`` when the distance to the objects is known (a map and a pose, a
        depth grid: longer side ~ focal length x object size / distance).

        Level s matches objects about as long as a template, ``template_cells x cell / s`` pixels; each object size
        is answered best by the level nearest to it (in log scale), so the levels kept are those whose share of the
        size axis (up to the geometric midpoints with their neighbours) meets the range. An object size outside every
        share keeps the nearest level.
        """
        if not (0 < smallest_px <= largest_px and math.isfinite(largest_px)):
            raise ValueError(f"need 0 < smallest_px <= largest_px < inf, got {smallest_px}, {largest_px}")
        low, high = math.log(smallest_px), math.log(largest_px)
        kept = [s for s, (a, b) in level_shares(self.level_object_px()).items() if a <= high and b >= low]
        return tuple(s for s in self.match.scales if s in kept)

    def template_heatmaps(self, image: np.ndarray, scales=None) -> tuple[np.ndarray, np.ndarray]:
        """(H^HOGE, H^HQC) per template after the max over scales, each (templates, h, w) on the output grid."""
        best = self._best_over_scales(image, scales)
        return np.ascontiguousarray(best[..., 0]), np.ascontiguousarray(best[..., 1])

    def heatmaps(self, image: np.ndarray, scales=None, rows=None) -> np.ndarray:
        """Class heatmaps (classes, h, w) float32 in [0, 1]: eq. 4.4, max over each class's templates.

        ``scales``: match only these levels (a subset of ``match.scales``, e.g. ``levels_for`` the expected object
        sizes); all by default. Fewer levels are proportionally faster; a level left out is one the objects are not
        expected at, so the class heatmaps keep their peaks but lose that level's background response.
        ``rows``: {level: (first, last + 1)} on the output grid (``pruning.level_rows``): match each level only on
        those rows (plus a template's reach; levels not named not at all); elsewhere the heatmap is the max over the
        other levels (0 where none runs). Overrides ``scales``.
        """
        best = self._best_over_scales(image, scales, rows)
        product = self._workspace.get("product", best.shape[:3], np.float32)
        np.multiply(best[..., 0], best[..., 1], out=product)   # eq. 4.4
        np.clip(product, 0.0, 1.0, out=product)   # removes DFT round-off only
        out = np.empty((len(self.classes),) + best.shape[1:3], np.float32)
        for k, members in enumerate(self._class_members):
            np.max(product[members], axis=0, out=out[k])
        return out



def level_shares(level_px) -> dict[float, tuple[float, float]]:
    """Each level's share of the log object-size axis, {level: (low, high)}: up to the geometric midpoints with its
    neighbours (``level_px``: each level's matched object size, ``TemplateDetector.level_object_px``). An object is
    answered best by the level nearest to it in log size."""
    order = sorted(level_px, key=lambda s: level_px[s])
    sizes = np.log([level_px[s] for s in order])
    bounds = np.concatenate([[-np.inf], (sizes[1:] + sizes[:-1]) / 2, [np.inf]])
    return {s: (bounds[k], bounds[k + 1]) for k, s in enumerate(order)}

def _level_groups(scales, threads: int) -> list[list[float]]:
    """The levels split into at most ``threads`` groups of about equal work (a level's work is about its pixel
    count, scale^2): each level, largest first, joins the least loaded group."""
    groups, loads = [[] for _ in range(min(threads, len(scales)))], [0.0] * min(threads, len(scales))
    for scale in sorted(scales, reverse=True):
        k = loads.index(min(loads))
        groups[k].append(scale)
        loads[k] += scale * scale
    return groups


def _resample_band(level: np.ndarray, band: tuple[int, int], level_rows: int, best: np.ndarray,
                   workspace: Workspace) -> None:
    """Max ``level``'s maps (templates, rows of ``band``, cols, 2) of a level ``level_rows`` high into ``best`` on
    the output grid, on the output rows whose samples lie within the band: sampled as ``cv2.resize`` samples the
    whole level (bilinear, pixel centres; columns by ``cv2.resize`` with the band's height kept, rows and the max in
    one pass, ``_kernels.lerp_rows_max``)."""
    out_rows, out_cols = best.shape[1:3]
    below, above, weight = _bilinear_taps(level_rows, out_rows)
    inside = np.flatnonzero((below >= band[0]) & (above < band[1]))
    if inside.size == 0:
        return
    widened = workspace.get("band_columns", (level.shape[0], level.shape[1], out_cols, 2), np.float32)
    if level.shape[2] == out_cols:
        np.copyto(widened, level)
    else:
        for maps, out in zip(level, widened):
            cv2.resize(maps, (out_cols, level.shape[1]), dst=out, interpolation=cv2.INTER_LINEAR)
    first, last = inside[0], inside[-1] + 1   # contiguous: the sample positions grow with the row
    flat = lambda a: a.reshape(a.shape[0], a.shape[1], -1)  # noqa: E731 - (templates, rows, cols x 2)
    _kernels.lerp_rows_max(flat(widened), first, below[first:last] - band[0], above[first:last] - band[0],
                           weight[first:last], flat(best))


def _bilinear_taps(source: int, target: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cv2.resize's INTER_LINEAR taps from ``source`` rows onto ``target``: each target row's source row below, above
    and the weight of the one above (pixel centres aligned; beyond the edges the edge row)."""
    position = np.clip((np.arange(target) + 0.5) * source / target - 0.5, 0.0, source - 1)
    below = np.floor(position).astype(np.int64)
    return below, np.minimum(below + 1, source - 1), (position - below).astype(np.float32)


def resample_maps(maps: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Resample (n, r, c) maps covering the image uniformly onto a new (n, rows, cols) array (bilinear, cv2
    centres)."""
    maps = np.asarray(maps, dtype=np.float32)
    if maps.shape[1:] == (rows, cols):
        return maps.copy()   # callers may pass a view of a reused buffer
    out = np.empty((maps.shape[0], rows, cols), np.float32)
    for plane, resampled in zip(maps, out):
        cv2.resize(plane, (cols, rows), dst=resampled, interpolation=cv2.INTER_LINEAR)
    return out


def _check_image(image) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 BGR (H, W, 3) image, got {image.dtype} {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"image {image.shape[1]}x{image.shape[0]} is too small")
    return image
