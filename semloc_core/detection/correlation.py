"""Dense "same" correlation of a multi-channel cell map with a fixed bank of small multi-channel kernels, summed over
each kernel's channels, in the frequency domain (eq. 4.3's sum over template blocks and histogram bins; the linear
window filters' dot products).

    out_k(x) = sum_{c in channels_k} sum_b K_k[c, b] F[c, x + b - centre_k]       (cells outside F count as zero)

One forward DFT per input channel and map size, the products summed over channels in the frequency domain (one numba
pass over split real / imaginary half-planes, ``_kernels.multiply_accumulate``), one inverse DFT per kernel. The
DFTs are OpenCV's complex ones, two real maps per transform (a + ib in, a + ib out): on these sizes that is about
three times as fast as ``scipy.fft``'s real transforms and twice OpenCV's own real ones. Everything that depends only
on the map's size (DFT size, the kernels' spectra, buffers) is planned once per size.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from semloc_core.cache import BoundedCache
from semloc_core.detection import _kernels


def even_dft_size(n: int) -> int:
    """The smallest even size >= n that OpenCV's DFT handles fast (a product of 2, 3 and 5)."""
    size = cv2.getOptimalDFTSize(max(int(n), 2))
    while size % 2:
        size = cv2.getOptimalDFTSize(size + 1)
    return size


@dataclass
class _Plan:
    shape: tuple[int, int]      # DFT size (even, even)
    kernel_real: np.ndarray     # (pairs, M * (N/2 + 1)) float32: spectra of each (kernel, channel) pair, flipped (a
    kernel_imag: np.ndarray     # convolution), as flat half-plane real and imaginary parts
    packed: np.ndarray          # (channel pairs, M, N, 2) float32 complex DFT input, zero outside the map: channel
    # k at [k % pairs, ..., k // pairs]; transformed in place (its spectra)
    image_real: np.ndarray      # (channels, M, N/2 + 1) each channel's half-plane
    image_imag: np.ndarray
    reversed_real: np.ndarray   # the same with the rows reversed, for mirrored kernels ((0, ...) without any)
    reversed_imag: np.ndarray
    product_real: np.ndarray    # (kernels, M, N/2 + 1)
    product_imag: np.ndarray
    products: np.ndarray        # (kernel pairs, M, N, 2) complex inverse DFT input, transformed in place: kernel
    # j's map in [..., 0], kernel j + pairs's in [..., 1]


class Correlator:
    """``kernels``: one ``(channels, blocks)`` per output map: the input channels it reads (int array) and its
    weights over them, (len(channels), rows, cols) with odd sides (the centre block sits on the output cell).

    ``input(rows, cols)`` is where to write the map (see there); ``run(rows, cols)`` returns the
    correlations as (P, rows, cols, 2) with P = ceil(kernels / 2): kernel k's map is ``[k % P, ..., k // P]`` (two
    maps per complex inverse DFT). Both are views of buffers that the next call overwrites; ``correlate`` returns a
    plain (kernels, rows, cols) copy. One instance per stream: it keeps buffers per map size, so calls for different
    sizes may run on different threads at once (a pyramid's levels), never two of the same DFT size (``dft_shape``).
    """

    def __init__(self, n_channels: int, kernels):
        self.n_channels = int(n_channels)
        self._channels, self._blocks = [], []
        for channels, blocks in kernels:
            channels = np.asarray(channels, dtype=np.int64).reshape(-1)
            blocks = np.asarray(blocks, dtype=np.float32)
            if blocks.ndim != 3 or blocks.shape[0] != channels.size or not blocks.shape[1] % 2 == blocks.shape[2] % 2 == 1:
                raise ValueError(f"kernel blocks must be (channels, odd rows, odd cols), got {blocks.shape} for "
                                 f"{channels.size} channels")
            if channels.size and (channels.min() < 0 or channels.max() >= self.n_channels):
                raise ValueError(f"kernel channels must be in [0, {self.n_channels}), got {channels}")
            self._channels.append(channels)
            self._blocks.append(blocks)
        if not self._blocks:
            raise ValueError("a correlator needs at least one kernel")
        # A kernel that is another's mirror image (a template's mirrored view, §4.5.1) is not stored: its output
        # comes from the other's spectra (``_kernels.multiply_accumulate``), which halves what a frame reads.
        mirrors = _mirror_pairs(self._channels, self._blocks)
        self._stored = [k for k in range(len(self._blocks)) if k not in mirrors]
        mirror_of = {source: (k, channels) for k, (source, channels) in mirrors.items()}
        self._pair_channel = np.concatenate([self._channels[k] for k in self._stored])
        self._pair_start = np.concatenate([[0], np.cumsum([self._channels[k].size for k in self._stored])]
                                          ).astype(np.int64)
        self._kernel_out = np.array(self._stored, np.int64)
        self._mirror_out = np.array([mirror_of[k][0] if k in mirror_of else -1 for k in self._stored], np.int64)
        self._mirror_channel = np.concatenate([mirror_of[k][1] if k in mirror_of else self._channels[k]
                                               for k in self._stored]).astype(np.int64)
        self._reversed_rows = np.array([k in mirrors for k in range(len(self._blocks))])
        self._half = (max(b.shape[1] for b in self._blocks) // 2, max(b.shape[2] for b in self._blocks) // 2)
        self._plans = BoundedCache(48)  # per DFT size: a stream's pyramid levels and their bands
        self._plans_lock = threading.Lock()   # levels planned from several threads

    @property
    def n_kernels(self) -> int:
        return len(self._blocks)

    @property
    def output_pairs(self) -> int:
        return (self.n_kernels + 1) // 2

    def dft_shape(self, rows: int, cols: int) -> tuple[int, int]:
        """The DFT size a map of this size is correlated at: maps of one DFT size share buffers (a plan), so two
        of them must not run at once."""
        # circular correlation equals the zero-padded one when the template's half-size fits in the padding (and
        # the whole flipped kernel fits in it)
        return (even_dft_size(max(rows + self._half[0], 2 * self._half[0] + 1)),
                even_dft_size(max(cols + self._half[1], 2 * self._half[1] + 1)))

    def _plan(self, rows: int, cols: int) -> _Plan:
        with self._plans_lock:
            return self._plan_locked(rows, cols)

    def _plan_locked(self, rows: int, cols: int) -> _Plan:
        shape = self.dft_shape(rows, cols)   # maps of sizes with one DFT size (a level's bands) share a plan
        plan = self._plans.get(shape)
        if plan is None:
            half_plane = (shape[0], shape[1] // 2 + 1)
            spectra = []
            for blocks in (self._blocks[k] for k in self._stored):
                _, krows, kcols = blocks.shape
                # correlation = convolution with the kernel flipped about its centre, centre at the origin
                flipped = np.zeros((blocks.shape[0],) + shape)
                flipped[:, :krows, :kcols] = blocks[:, ::-1, ::-1]
                spectra.append(np.fft.rfft2(np.roll(flipped, (-(krows // 2), -(kcols // 2)), axis=(1, 2))))
            spectra = np.concatenate(spectra).reshape(len(self._pair_channel), -1)
            channel_pairs, kernel_pairs = (self.n_channels + 1) // 2, self.output_pairs
            plan = _Plan(shape, np.ascontiguousarray(spectra.real, np.float32),
                         np.ascontiguousarray(spectra.imag, np.float32),
                         np.zeros((channel_pairs,) + shape + (2,), np.float32),
                         np.empty((self.n_channels,) + half_plane, np.float32),
                         np.empty((self.n_channels,) + half_plane, np.float32),
                         np.empty((self.n_channels if self._reversed_rows.any() else 0,) + half_plane, np.float32),
                         np.empty((self.n_channels if self._reversed_rows.any() else 0,) + half_plane, np.float32),
                         np.empty((self.n_kernels,) + half_plane, np.float32),
                         np.empty((self.n_kernels,) + half_plane, np.float32),
                         np.empty((kernel_pairs,) + shape + (2,), np.float32))
            self._plans[shape] = plan
        return plan

    def input(self, rows: int, cols: int) -> np.ndarray:
        """The (P, rows, cols, 2) view to write a map of this size into before each ``run``, P = ceil(channels / 2):
        channel k at ``[k % P, ..., k // P]`` (two real maps per complex DFT; ``run`` zeroes what lies outside)."""
        return self._plan(rows, cols).packed[:, :rows, :cols]

    def run(self, rows: int, cols: int) -> np.ndarray:
        """(P, rows, cols, 2) correlations of what was written into ``input(rows, cols)`` (see the class)."""
        plan = self._plan(rows, cols)
        packed = plan.packed
        # The DFTs run in place (a fifth less time than into another buffer: less memory to touch), so the padding
        # holds the last map's spectra: zero it, and a pair's second map when the channels are odd.
        packed[:, rows:] = 0.0
        packed[:, :rows, cols:] = 0.0
        for k in range(self.n_channels, 2 * packed.shape[0]):
            packed[k % packed.shape[0], :rows, :cols, k // packed.shape[0]] = 0.0
        for pair in range(packed.shape[0]):
            cv2.dft(packed[pair], dst=packed[pair])
        _kernels.unpack_spectra(packed, plan.image_real, plan.image_imag, plan.reversed_real,
                                plan.reversed_imag)
        kernels = self.n_kernels
        flat = lambda a: a.reshape(a.shape[0], a.shape[1] * a.shape[2])  # noqa: E731 - (0, ...) when no mirror
        _kernels.multiply_accumulate(flat(plan.image_real), flat(plan.image_imag), flat(plan.reversed_real),
                                     flat(plan.reversed_imag), plan.kernel_real, plan.kernel_imag, self._pair_channel,
                                     self._pair_start, self._kernel_out, self._mirror_out, self._mirror_channel,
                                     plan.product_real.reshape(kernels, -1), plan.product_imag.reshape(kernels, -1))
        _kernels.pack_spectra(plan.product_real, plan.product_imag, self._reversed_rows, plan.products)
        for pair in range(plan.products.shape[0]):
            cv2.dft(plan.products[pair], dst=plan.products[pair], flags=cv2.DFT_INVERSE | cv2.DFT_SCALE)
        return plan.products[:, :rows, :cols]

    def correlate(self, features: np.ndarray) -> np.ndarray:
        """Correlations (kernels, rows, cols) of a (channels, rows, cols) map, as a new array."""
        features = np.asarray(features)
        if features.ndim != 3 or features.shape[0] != self.n_channels:
            raise ValueError(f"expected a ({self.n_channels}, rows, cols) map, got {features.shape}")
        rows, cols = features.shape[1:]
        view = self.input(rows, cols)
        pairs = view.shape[0]
        for k, channel in enumerate(features):
            view[k % pairs, :, :, k // pairs] = channel
        out = self.run(rows, cols)
        return np.concatenate([out[..., 0], out[..., 1]])[:self.n_kernels]


def _mirror_pairs(channels: list, blocks: list) -> dict:
    """{kernel j: (kernel i, channels)} for kernels that are an earlier kernel's mirror image left-right: each of
    j's channel blocks is one of i's flipped (columns reversed), ``channels[b]`` the input channel j reads with the
    flip of i's block b. Blocks are compared exactly (equal blocks are interchangeable: the sums are the same)."""
    def signature(k, flip):
        return blocks[k].shape, tuple(sorted((b[:, ::-1] if flip else b).tobytes() for b in blocks[k]))

    plain = {}
    for k in range(len(blocks)):
        plain.setdefault(signature(k, False), []).append(k)
    mirrors, sources = {}, set()
    for j in range(len(blocks)):
        if j in sources:
            continue
        candidates = [i for i in plain.get(signature(j, True), []) if i < j and i not in mirrors and i not in sources]
        if not candidates:
            continue
        i = candidates[0]
        unused = {}
        for a, block in enumerate(blocks[j]):
            unused.setdefault(np.ascontiguousarray(block[:, ::-1]).tobytes(), []).append(a)
        order = [unused[block.tobytes()].pop() for block in blocks[i]]
        mirrors[j] = (i, channels[j][np.array(order, np.int64)])
        sources.add(i)
    return mirrors
