"""Block features for template matching (thesis §4.3.1 HOGE, §4.3.2 HQC).

Both features are histograms over non-overlapping square cells of ``cell`` pixels (the thesis's blocks
Omega_i). The image given to these functions must have a height and width that are multiples of ``cell``
(``fit_to_cells`` resizes an image so); the result is ``(rows, cols, bins)`` float32 with each cell's histogram
summing to 1.

HOGE uses second derivatives of a Gaussian, which are exactly steerable (Freeman & Adelson 1991): the response at
orientation theta is ``c^2 Gxx + 2cs Gxy + s^2 Gyy`` (c = cos theta, s = sin theta). Squaring and pooling over a
cell are linear in the six products of the three basis responses, so the fast path pools the products once per
cell and steers the pooled energies to every orientation with one small matrix product — the same numbers as
filtering with each oriented kernel, squaring per pixel and summing (eq. 4.1), at a fraction of the cost.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from semloc_core.cache import BoundedCache
from semloc_core.detection import _kernels


# The "hsv" colour model (§4.3.2: "different color models can also be considered"): a pixel with enough
# saturation and brightness for its hue to mean something votes for hue x saturation chromatic bins, which ignore
# brightness so that the same paint under dimmer light keeps its bin (its vote is split between the two nearest hue
# bins, see hsv_colour_votes); any other pixel is a grey, binned by brightness. With the default 6 hue x 4
# saturation levels: 8 + 24 = 32 colours.
HSV_GREY_LEVELS = 8
HSV_MIN_SATURATION = 48   # of 255
HSV_MIN_VALUE = 32        # of 255


@dataclass(frozen=True)
class FeatureParams:
    """Parameters shared by the image and template features."""

    cell: int = 8                 # block size n in pixels (§4.3.2 "blocks of n x n pixels")
    orientations: int = 8         # oriented energies in [0, pi) (Fig. 4.2b uses 8)
    sigma: float = 1.0            # Gaussian scale of the derivative filters, pixels
    epsilon_fraction: float = 0.01  # eq. 4.2 noise floor: 1 % of the expected maximum response
    color_levels: int = 4         # k levels per channel -> k^3 colours (§4.3.2, k = 4)
    min_contrast: float = 4.0     # grey levels: the weakest edge that still counts as structure in a flat image
    color_space: str = "rgb"      # "rgb" (the thesis's k^3 cube) or "hsv" (hue x saturation + greys, see hqc)
    hue_levels: int = 6           # hsv: hue bins (60 degrees each, centred on red, yellow, green, ...)
    saturation_levels: int = 4    # hsv: saturation bins of the chromatic colours

    def __post_init__(self) -> None:
        if int(self.cell) < 1:
            raise ValueError(f"cell must be >= 1 pixel, got {self.cell}")
        if int(self.orientations) < 2:
            raise ValueError(f"need at least 2 orientations, got {self.orientations}")
        if not self.sigma > 0:
            raise ValueError(f"sigma must be positive, got {self.sigma}")
        if not 0 < self.epsilon_fraction < 1:
            raise ValueError(f"epsilon_fraction must be in (0, 1), got {self.epsilon_fraction}")
        if not 2 <= int(self.color_levels) <= 16:
            raise ValueError(f"color_levels must be in [2, 16], got {self.color_levels}")
        if not self.min_contrast > 0:
            raise ValueError(f"min_contrast must be positive, got {self.min_contrast}")
        if self.color_space not in ("rgb", "hsv"):
            raise ValueError(f"color_space must be 'rgb' or 'hsv', got {self.color_space!r}")
        if not 2 <= int(self.hue_levels) <= 60 or not 1 <= int(self.saturation_levels) <= 8:
            raise ValueError(f"need 2..60 hue levels and 1..8 saturation levels, got {self.hue_levels}, "
                             f"{self.saturation_levels}")
        if HSV_GREY_LEVELS + self.hue_levels * self.saturation_levels > 256:
            raise ValueError("the hsv model is limited to 256 colours")

    @property
    def hoge_bins(self) -> int:
        """Oriented energies plus the normalised-epsilon "no structure" bin."""
        return self.orientations + 1

    @property
    def hqc_bins(self) -> int:
        if self.color_space == "hsv":
            return HSV_GREY_LEVELS + self.hue_levels * self.saturation_levels
        return self.color_levels ** 3

    @property
    def orientation_angles(self) -> np.ndarray:
        return np.arange(self.orientations) * (np.pi / self.orientations)


# ---------------------------------------------------------------------------------------------------- HOGE


def gaussian_derivative_kernels(sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D Gaussian g, first derivative g' and second derivative g'' (float64, truncated at 4 sigma).

    g'' is made exactly zero-sum (by removing a multiple of g, which keeps its shape symmetric) so that the
    band-pass filters ignore an additive brightness offset exactly — the invariance §4.3.1 claims.
    """
    radius = max(1, int(np.ceil(4.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1.0 / sigma**2) * g
    g2 -= g * (g2.sum() / g.sum())
    g1 = 0.5 * (g1 - g1[::-1])  # antisymmetric already; exactly so despite rounding (the filtering pairs its taps)
    return g, g1, g2


def steering_weights(angles: np.ndarray) -> np.ndarray:
    """(orientations, 3) weights of the basis (Gxx, Gxy, Gyy) for the directional second derivative."""
    c, s = np.cos(angles), np.sin(angles)
    return np.stack([c * c, 2.0 * c * s, s * s], axis=1)


def _energy_weights(angles: np.ndarray) -> np.ndarray:
    """(6, orientations): squared steered response as a combination of the pooled basis products.

    (a A + b B + c C)^2 = a^2 AA + b^2 BB + c^2 CC + 2ab AB + 2ac AC + 2bc BC, order [AA, BB, CC, AB, AC, BC].
    """
    w = steering_weights(angles)
    a, b, c = w[:, 0], w[:, 1], w[:, 2]
    return np.stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c], axis=0)


class Workspace:
    """Scratch buffers reused from frame to frame (owned by one detector; not shared between threads).

    Full-resolution temporaries allocated afresh on every frame cost as much as the filtering itself here: each
    megabyte comes from the kernel as new zeroed pages. Keeping them lets a 640x480 frame run about twice as fast.
    Every feature function takes an optional workspace; without one it allocates as usual.
    """

    def __init__(self) -> None:
        self._buffers: BoundedCache = BoundedCache(512)  # a frame size uses ~40-60, its levels' bands more

    def get(self, name: str, shape: tuple[int, ...], dtype, init=None) -> np.ndarray:
        """The buffer called ``name`` with this shape and dtype; ``init(buffer)`` fills a newly made one."""
        key = (name, tuple(int(n) for n in shape), np.dtype(dtype).str)
        buffer = self._buffers.get(key)
        if buffer is None:
            buffer = self._buffers[key] = np.empty(shape, dtype)
            if init is not None:
                init(buffer)
        return buffer


def _check_grey(image: np.ndarray, cell: int, workspace: Workspace) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        if image.dtype != np.uint8:
            raise ValueError(f"a colour image must be uint8 BGR, got {image.dtype}")
        grey = workspace.get("grey", image.shape[:2], np.uint8)
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY, dst=grey)
    if image.ndim != 2:
        raise ValueError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")
    if image.shape[0] % cell or image.shape[1] % cell or image.shape[0] < cell or image.shape[1] < cell:
        raise ValueError(f"image size {image.shape[1]}x{image.shape[0]} is not a positive multiple of cell={cell}")
    if image.dtype not in (np.uint8, np.float32):
        image = image.astype(np.float32)   # _kernels.pooled_energies reads uint8 and float32
    return np.ascontiguousarray(image)


def _energies_and_totals(grey: np.ndarray, params: FeatureParams, workspace: Workspace):
    """(oriented energies E_theta per cell (eq. 4.1), their sum per cell), workspace buffers (filtered and pooled
    in one pass: _kernels.pooled_energies)."""
    grey = _check_grey(grey, params.cell, workspace)
    cell = params.cell
    rows, cols = grey.shape[0] // cell, grey.shape[1] // cell
    energies = workspace.get("energies", (rows, cols, params.orientations), np.float32)
    totals = workspace.get("energy_total", (rows, cols), np.float32)
    _kernels.pooled_energies(grey, *_basis_kernels(params.sigma), cell, _steering(params.orientations), energies,
                             totals)
    return energies, totals


@functools.lru_cache(maxsize=8)
def _basis_kernels(sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gaussian_derivative_kernels as float32 (once per sigma, not per image): g and g'' symmetric, g' antisymmetric,
    exactly (_kernels.pooled_energies adds the mirrored taps before multiplying)."""
    kernels = tuple(k.astype(np.float32) for k in gaussian_derivative_kernels(sigma))
    g, g1, g2 = kernels
    if not (np.array_equal(g, g[::-1]) and np.array_equal(g2, g2[::-1]) and np.array_equal(g1, -g1[::-1])):
        raise ValueError(f"the Gaussian derivative kernels of sigma={sigma} are not (anti)symmetric")
    for kernel in kernels:
        kernel.flags.writeable = False
    return kernels


@functools.lru_cache(maxsize=8)
def _steering(orientations: int) -> np.ndarray:
    weights = _energy_weights(np.arange(orientations) * (np.pi / orientations)).astype(np.float32)
    weights.flags.writeable = False
    return weights


@functools.lru_cache(maxsize=32)
def edge_energy(contrast: float, params: FeatureParams) -> float:
    """Pooled energy, summed over orientations, of one cell crossed by a straight step edge of ``contrast``.

    Across the edge the Gxx response is the step response of g'' (the cumulative sum of its taps); each of the
    ``cell`` rows along the edge contributes the sum of its squares, and steering spreads it as cos^4 over the
    orientations, whose sum is 3N/8 for N >= 3 evenly spaced orientations.
    """
    _, _, g2 = gaussian_derivative_kernels(params.sigma)
    step_response = np.cumsum(g2)
    n = params.orientations
    spread = np.sum(np.cos(np.arange(n) * np.pi / n) ** 4)
    return float(spread * params.cell * contrast**2 * np.sum(step_response**2))


def noise_floor(total_energy: np.ndarray, params: FeatureParams) -> float:
    """epsilon of eq. 4.2: ``epsilon_fraction`` of the expected maximum pooled energy.

    The expected maximum is the 99th percentile of the per-cell energy sum of the image itself, so that epsilon
    scales with contrast and HOGE is invariant to a multiplicative brightness change. It never drops below the
    energy of a ``min_contrast`` edge: in a (nearly) flat image rounding noise is not blown up into structure, and
    the normalised epsilon approaches one as §4.3.1 says it should.
    """
    expected_max = _percentile(total_energy, 99.0) if total_energy.size else 0.0
    return params.epsilon_fraction * max(expected_max, edge_energy(params.min_contrast, params))


def _percentile(values: np.ndarray, q: float) -> float:
    """np.percentile(values, q) (its default, linear interpolation between the two closest ranks) from a partial
    sort of those two ranks only: a third of the time on a level's cells."""
    flat = np.asarray(values).ravel()
    position = q / 100.0 * (flat.size - 1)
    low = int(position)
    high = min(low + 1, flat.size - 1)
    ranked = np.partition(flat, (low, high))
    below, above = float(ranked[low]), float(ranked[high])
    return below + (above - below) * (position - low)


def _normalise_into(energies: np.ndarray, totals: np.ndarray, params: FeatureParams, root: bool,
                    out: np.ndarray) -> None:
    """eq. 4.2 (square-rooted when ``root``) into ``out`` (see _kernels.normalised_energies)."""
    _kernels.normalised_energies(energies, totals, np.float32(noise_floor(totals, params)), root, out)


def hoge(image: np.ndarray, params: FeatureParams = FeatureParams(), workspace: Workspace | None = None) -> np.ndarray:
    """Histograms of normalised gradient energies per cell (§4.3.1), (rows, cols, orientations + 1), float32 (with a
    ``workspace``, one of its buffers, overwritten by the next call)."""
    workspace = workspace or Workspace()
    energies, totals = _energies_and_totals(image, params, workspace)
    shape = energies.shape[:-1] + (energies.shape[-1] + 1,)
    histogram = workspace.get("hoge", shape, np.float32)
    _normalise_into(energies, totals, params, False, histogram.transpose(2, 0, 1)[..., None])
    return histogram


# ---------------------------------------------------------------------------------------------------- HQC


def colour_lut(levels: int) -> np.ndarray:
    """uint8 -> level index of the nearest of ``levels`` values spread uniformly over [0, 255] (§4.3.2)."""
    palette = np.linspace(0.0, 255.0, levels)
    values = np.arange(256, dtype=np.float64)
    return np.abs(values[:, None] - palette[None, :]).argmin(axis=1).astype(np.uint8)


def quantise_colours(bgr: np.ndarray, levels: int, workspace: Workspace | None = None) -> np.ndarray:
    """Index of each pixel's nearest of the ``levels``^3 palette colours sampled uniformly over the RGB cube (B most
    significant), as in §4.3.2: (H, W), uint8 when there are at most 256 colours, else int32."""
    bgr = np.asarray(bgr)
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise ValueError(f"HQC needs a uint8 BGR (H, W, 3) image, got {bgr.dtype} {bgr.shape}")
    workspace = workspace or Workspace()
    lut = colour_lut(levels)
    if levels**3 <= 256:
        # One per-channel table that already weights each channel's level (B * k^2, G * k, R), then one
        # channel sum: two passes over the image, all in uint8.
        weighted = np.stack([lut * levels * levels, lut * levels, lut], axis=-1).astype(np.uint8).reshape(1, 256, 3)
        parts = cv2.LUT(np.ascontiguousarray(bgr), weighted, dst=workspace.get("levels", bgr.shape, np.uint8))
        index = workspace.get("index", bgr.shape[:2], np.uint8)
        cv2.transform(parts, np.ones((1, 3), np.float32), dst=index)
        return index
    q = cv2.LUT(np.ascontiguousarray(bgr), lut).astype(np.int32)
    return (q[..., 0] * levels + q[..., 1]) * levels + q[..., 2]


@functools.lru_cache(maxsize=8)
def _hsv_lookup(hue_levels: int, saturation_levels: int) -> tuple[np.ndarray, ...]:
    """The hsv model's per-channel lookups, each (256,): hue -> HSV_GREY_LEVELS + lower hue bin * saturation_levels,
    hue -> the same for the upper bin (the lower one's neighbour on the hue circle), hue -> the upper bin's share
    in 1/HUE_WEIGHT (int32: a whole number, OpenCV's hue being degrees / 2), saturation -> saturation bin, value ->
    grey bin. Hue bin k is centred on hue k * 360 / hue_levels degrees, so pure red sits on a bin centre."""
    values = np.arange(256)
    position = values * hue_levels // _kernels.HUE_WEIGHT    # OpenCV hue is degrees / 2
    lower = position % hue_levels
    upper = (lower + 1) % hue_levels
    weight = (values * hue_levels % _kernels.HUE_WEIGHT).astype(np.int32)
    saturation = np.clip((values - HSV_MIN_SATURATION) * saturation_levels // (256 - HSV_MIN_SATURATION),
                         0, saturation_levels - 1)
    grey = values * HSV_GREY_LEVELS // 256
    tables = ((HSV_GREY_LEVELS + lower * saturation_levels).astype(np.uint8),
              (HSV_GREY_LEVELS + upper * saturation_levels).astype(np.uint8), weight, saturation.astype(np.uint8),
              grey.astype(np.uint8))
    for table in tables:
        table.flags.writeable = False
    return tables


def _hsv_tables(hue_levels: int, saturation_levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lookups as per-channel tables of cv2.LUT, each (1, 256, 3) for a (H, S, V) image:

    * ``first`` (uint8): H -> 8 + lower hue bin * 4, S -> saturation bin, V -> grey bin;
    * ``second`` (uint8): H -> 8 + upper hue bin * 4;
    * ``weight`` (float32): H -> the share of the upper bin.
    """
    lower, upper, weight, saturation, grey = _hsv_lookup(hue_levels, saturation_levels)
    share = weight / np.float32(_kernels.HUE_WEIGHT)
    first = np.stack([lower, saturation, grey], axis=-1)
    second = np.stack([upper, saturation, grey], axis=-1)
    weight = np.stack([share, np.zeros(256), np.zeros(256)], axis=-1)
    return (first.astype(np.uint8)[None], second.astype(np.uint8)[None], weight.astype(np.float32)[None])


def hsv_colour_votes(bgr: np.ndarray, workspace: Workspace | None = None, hue_levels: int = 6,
                     saturation_levels: int = 4):
    """The ``hsv`` model's votes: [(bin image uint8, weight image float32), (bin image, weight image)].

    A pixel is chromatic when its saturation >= HSV_MIN_SATURATION and value >= HSV_MIN_VALUE (below either, hue
    is noise). A chromatic pixel's unit vote is split linearly between the two hue bins whose centres bracket its
    hue (same saturation bin), so a small hue shift between an exemplar and the scene, or red straddling 0/360,
    moves weight gradually instead of flipping bins; brightness plays no part. A grey pixel votes fully for its
    brightness bin.
    """
    workspace = workspace or Workspace()
    shape = bgr.shape[:2]
    first_table, second_table, weight_table = _hsv_tables(hue_levels, saturation_levels)
    hsv = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2HSV, dst=workspace.get("hsv", bgr.shape, np.uint8))
    parts = cv2.LUT(hsv, first_table, dst=workspace.get("hsv_parts", bgr.shape, np.uint8))
    grey = workspace.get("hsv_grey", shape, np.uint8)
    cv2.inRange(hsv, (0, 0, 0), (255, HSV_MIN_SATURATION - 1, 255), dst=grey)   # low saturation ...
    dark = workspace.get("hsv_dark", shape, np.uint8)
    cv2.inRange(hsv, (0, 0, 0), (255, 255, HSV_MIN_VALUE - 1), dst=dark)        # ... or too dark: grey
    cv2.bitwise_or(grey, dark, dst=grey)
    is_grey = grey.view(bool)   # 0 / 255 -> False / True
    first = workspace.get("hsv_first", shape, np.uint8)
    np.add(parts[..., 0], parts[..., 1], out=first)
    np.copyto(first, parts[..., 2], where=is_grey)
    hue = np.ascontiguousarray(hsv[..., 0])
    second = workspace.get("hsv_second", shape, np.uint8)
    np.add(cv2.LUT(hue, second_table[..., 0].reshape(1, 256)), parts[..., 1], out=second)
    np.copyto(second, first, where=is_grey)
    share = workspace.get("hsv_share", shape, np.float32)
    np.take(weight_table[0, :, 0], hue, out=share)
    share[is_grey] = 0.0
    rest = workspace.get("hsv_rest", shape, np.float32)
    np.subtract(np.float32(1.0), share, out=rest)
    return [(first, rest), (second, share)]


def colour_votes(bgr: np.ndarray, params: FeatureParams, workspace: Workspace | None = None):
    """[(colour index image, weight image or None)]: every pixel's vote(s) for the HQC histogram."""
    if params.color_space == "hsv":
        bgr = np.asarray(bgr)
        if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
            raise ValueError(f"HQC needs a uint8 BGR (H, W, 3) image, got {bgr.dtype} {bgr.shape}")
        return hsv_colour_votes(bgr, workspace, params.hue_levels, params.saturation_levels)
    return [(quantise_colours(bgr, params.color_levels, workspace), None)]


def hqc(bgr: np.ndarray, params: FeatureParams = FeatureParams(), mask: np.ndarray | None = None,
        workspace: Workspace | None = None) -> np.ndarray:
    """Histograms of quantised colours per cell (§4.3.2), (rows, cols, bins) float32 summing to 1 per cell.

    ``mask`` (H, W) bool restricts the counts to object pixels (a template's silhouette); a cell without any
    masked pixel gets an all-zero histogram. With a ``workspace`` and no mask the result is one of its buffers,
    overwritten by the next call.
    """
    bgr = np.asarray(bgr)
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise ValueError(f"HQC needs a uint8 BGR (H, W, 3) image, got {bgr.dtype} {bgr.shape}")
    workspace = workspace or Workspace()
    cell = params.cell
    height, width = bgr.shape[:2]
    if height % cell or width % cell or height < cell or width < cell:
        raise ValueError(f"image size {width}x{height} is not a positive multiple of cell={cell}")
    rows, cols = height // cell, width // cell
    bins = params.hqc_bins
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (height, width):
            raise ValueError(f"mask shape {mask.shape} does not match the image {(height, width)}")
        cell_of_pixel = (np.arange(height)[:, None] // cell) * cols + (np.arange(width)[None, :] // cell)
        counts = np.zeros(rows * cols * bins)
        for index, weight in colour_votes(bgr, params, workspace):
            counts += np.bincount(cell_of_pixel[mask] * bins + index[mask],
                                  weights=None if weight is None else weight[mask], minlength=rows * cols * bins)
        counts = counts.astype(np.float32).reshape(rows, cols, bins)
        totals = counts.sum(axis=-1, keepdims=True)
        return np.divide(counts, totals, out=np.zeros_like(counts), where=totals > 0)
    histogram = workspace.get("hqc", (rows, cols, bins), np.float32)
    _count_colours(bgr, params, workspace, _all_bins(bins), False, histogram.transpose(2, 0, 1)[..., None])
    return histogram


def _count_colours(bgr: np.ndarray, params: FeatureParams, workspace: Workspace, slot: np.ndarray, root: bool,
                   out: np.ndarray) -> None:
    """HQC bins of every cell into channel ``slot[bin]`` of ``out`` (bins whose slot is -1 left out; square-rooted
    when ``root``; layout of _kernels.normalised_energies): each pixel's vote(s) looked up and added to its cell in
    one pass, with no full-size index image."""
    bgr = np.ascontiguousarray(bgr)
    if params.color_space == "hsv":
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV, dst=workspace.get("hsv", bgr.shape, np.uint8))
        _kernels.hsv_histograms(hsv, *_hsv_lookup(params.hue_levels, params.saturation_levels), HSV_MIN_SATURATION,
                                HSV_MIN_VALUE, params.cell, params.hqc_bins, slot, root, out)
    else:
        _kernels.rgb_histograms(bgr, _weighted_colour_lut(params.color_levels), params.cell, params.hqc_bins, slot,
                                root, out)


@functools.lru_cache(maxsize=8)
def _all_bins(bins: int) -> np.ndarray:
    slots = np.arange(bins)
    slots.flags.writeable = False
    return slots


def root_features(image: np.ndarray, params: FeatureParams, hqc_channels: np.ndarray, out: np.ndarray,
                  workspace: Workspace | None = None) -> None:
    """The square-rooted cell features that eq. 4.3 correlates: channels 0 .. hoge_bins - 1 are sqrt HOGE, the next
    ones sqrt of the HQC bins ``hqc_channels`` (ascending), of a uint8 BGR image whose sides are multiples of the
    cell. ``out`` (P, rows, cols, parts) receives channel k at ``[k % P, ..., k // P]`` (the correlator's input)."""
    workspace = workspace or Workspace()
    _normalise_into(*_energies_and_totals(image, params, workspace), params, True, out)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"HQC needs a uint8 BGR (H, W, 3) image, got {image.dtype} {image.shape}")
    slot = np.full(params.hqc_bins, -1, np.int64)
    slot[np.asarray(hqc_channels)] = params.hoge_bins + np.arange(len(hqc_channels))
    _count_colours(image, params, workspace, slot, True, out)


@functools.lru_cache(maxsize=8)
def _weighted_colour_lut(levels: int) -> np.ndarray:
    """(3, 256) int32: each channel's palette level weighted by its place in the colour index (B k^2, G k, R)."""
    lut = colour_lut(levels).astype(np.int32)
    table = np.stack([lut * levels * levels, lut * levels, lut])
    table.flags.writeable = False
    return table


def fit_to_cells(image: np.ndarray, scale: float, cell: int, workspace: Workspace | None = None) -> np.ndarray:
    """Resize ``image`` by about ``scale`` to the nearest size that is a whole number of cells (at least one)."""
    height, width = image.shape[:2]
    cols = max(1, int(round(width * scale / cell)))
    rows = max(1, int(round(height * scale / cell)))
    size = (cols * cell, rows * cell)
    if size == (width, height):
        return image
    # INTER_AREA only where OpenCV has its fast integer-factor path (it costs ~5x INTER_LINEAR otherwise); a
    # 0.7x bilinear reduction aliases little at the block scale the features pool over.
    integer_reduction = width % size[0] == 0 and height % size[1] == 0 and width // size[0] == height // size[1] > 1
    interpolation = cv2.INTER_AREA if integer_reduction else cv2.INTER_LINEAR
    if workspace is None:
        return cv2.resize(image, size, interpolation=interpolation)
    out = workspace.get(f"level_{size}", (size[1], size[0]) + image.shape[2:], image.dtype)
    return cv2.resize(image, size, dst=out, interpolation=interpolation)
