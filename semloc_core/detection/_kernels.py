"""numba kernels of the §4.3 detector's fast path (the equations are in features.py and templates.py).

* ``pooled_energies``: the six products of the steerable basis responses summed over each cell and steered to
  every orientation (eq. 4.1), in one pass over the three response images instead of six multiplies, six block
  means and a matrix product (``normalised_energies``: eq. 4.2);
* ``rgb_histograms`` / ``hsv_histograms``: HQC cell histograms (§4.3.2) counted straight from the pixels (palette
  index or hsv votes looked up per pixel and added to its cell), instead of a full-resolution index image and
  ``bincount``; like ``normalised_energies`` they write histograms or, for the detector, the square roots of the
  bins it uses as channel planes;
* ``multiply_accumulate``: the channel sum of eq. 4.3 in the frequency domain, out[t] = sum over template t's
  channels of K[p] x I[channel p], on split real / imaginary planes (``ccs_to_split`` / ``split_to_ccs`` convert
  from and to OpenCV's packed real spectra, see ``cv2.dft``).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, fastmath=True)
def pooled_energies(gxx, gxy, gyy, cell, steering, out):
    """out[r, c, o] = oriented energy o pooled over cell (r, c) (eq. 4.1), from the six products of the steerable
    basis responses [gxx^2, gxy^2, gyy^2, gxx gxy, gxx gyy, gxy gyy] summed over the cell and steered by
    ``steering`` (6, orientations); clamped at 0 (float32 rounding of the expansion)."""
    rows, cols, orientations = out.shape
    width = cols * cell
    band = np.zeros((6, width), np.float32)
    pooled = np.zeros(6, np.float32)
    for r in range(rows):
        band[:] = 0.0
        for y in range(r * cell, (r + 1) * cell):
            for x in range(width):
                a = gxx[y, x]
                b = gxy[y, x]
                c = gyy[y, x]
                band[0, x] += a * a
                band[1, x] += b * b
                band[2, x] += c * c
                band[3, x] += a * b
                band[4, x] += a * c
                band[5, x] += b * c
        for col in range(cols):
            for k in range(6):
                total = np.float32(0.0)
                for x in range(col * cell, (col + 1) * cell):
                    total += band[k, x]
                pooled[k] = total
            for o in range(orientations):
                energy = np.float32(0.0)
                for k in range(6):
                    energy += pooled[k] * steering[k, o]
                out[r, col, o] = max(energy, np.float32(0.0))


@numba.njit(cache=True, nogil=True)
def normalised_energies(energies, totals, epsilon, root, out):
    """out[o, r, c] = energies[r, c, o] / (epsilon + totals[r, c]) and out[-1, r, c] = epsilon / (epsilon +
    totals[r, c]) (eq. 4.2), square-rooted when ``root`` (eq. 4.3's sqrt F). ``out`` is (bins, rows, cols): channel
    planes, or a histogram's (rows, cols, bins) seen through ``transpose(2, 0, 1)``."""
    rows, cols, orientations = energies.shape
    for r in range(rows):
        for c in range(cols):
            scale = np.float32(1.0) / (epsilon + totals[r, c])
            for o in range(orientations):
                value = energies[r, c, o] * scale
                out[o, r, c] = np.sqrt(value) if root else value
            value = epsilon * scale
            out[orientations, r, c] = np.sqrt(value) if root else value


@numba.njit(inline="always")
def _write_cell(counts, slot, root, out, r, c):
    for colour in range(counts.shape[0]):
        k = slot[colour]
        if k >= 0:
            out[k, r, c] = np.sqrt(counts[colour]) if root else counts[colour]


@numba.njit(cache=True, nogil=True)
def rgb_histograms(bgr, weighted_lut, cell, bins, slot, root, out):
    """HQC cell histograms (§4.3.2) of the palette colours: out[slot[colour], r, c] = share of cell (r, c)'s pixels
    of that colour (square-rooted when ``root``; colours whose slot is -1 are left out). ``weighted_lut`` (3, 256)
    gives each channel's level already weighted (B * k^2, G * k, R). ``out`` as in ``normalised_energies``."""
    rows, cols = out.shape[1], out.shape[2]
    unit = np.float32(1.0 / (cell * cell))
    counts = np.zeros(bins, np.float32)
    for r in range(rows):
        for c in range(cols):
            counts[:] = 0.0
            for y in range(r * cell, (r + 1) * cell):
                for x in range(c * cell, (c + 1) * cell):
                    colour = (weighted_lut[0, bgr[y, x, 0]] + weighted_lut[1, bgr[y, x, 1]]
                              + weighted_lut[2, bgr[y, x, 2]])
                    counts[colour] += unit
            _write_cell(counts, slot, root, out, r, c)


@numba.njit(cache=True, nogil=True)
def hsv_histograms(hsv, lower_bin, upper_bin, upper_share, saturation_bin, grey_bin, min_saturation, min_value,
                   cell, bins, slot, root, out):
    """HQC cell histograms of the hsv model (see features.hsv_colour_votes), written as ``rgb_histograms``: a grey
    pixel (saturation < ``min_saturation`` or value < ``min_value``) votes for ``grey_bin[value]``, a chromatic one
    splits its vote between ``lower_bin[hue]`` and ``upper_bin[hue]`` (+ its saturation bin), the upper one getting
    ``upper_share[hue]``."""
    rows, cols = out.shape[1], out.shape[2]
    unit = np.float32(1.0 / (cell * cell))
    one = np.float32(1.0)
    counts = np.zeros(bins, np.float32)
    for r in range(rows):
        for c in range(cols):
            counts[:] = 0.0
            for y in range(r * cell, (r + 1) * cell):
                for x in range(c * cell, (c + 1) * cell):
                    hue = hsv[y, x, 0]
                    saturation = hsv[y, x, 1]
                    value = hsv[y, x, 2]
                    if saturation < min_saturation or value < min_value:
                        counts[grey_bin[value]] += unit
                    else:
                        share = upper_share[hue]
                        level = saturation_bin[saturation]
                        counts[lower_bin[hue] + level] += unit * (one - share)
                        counts[upper_bin[hue] + level] += unit * share
            _write_cell(counts, slot, root, out, r, c)


@numba.njit(cache=True, nogil=True)
def ccs_to_split(ccs, real, imag):
    """Unpack OpenCV's packed real 2-D spectra (C, M, N), M and N even, into the half-plane (C, M, N/2 + 1) of
    ``numpy.fft.rfft2``'s layout as separate real and imaginary parts.

    CCS: columns 1 .. N - 2 hold (Re, Im) pairs of every row; columns 0 and N - 1 hold the Hermitian columns j = 0
    and j = N/2 packed as [Re 0, Re 1, Im 1, ..., Re M/2 - 1, Im M/2 - 1, Re M/2]."""
    channels, m, n = ccs.shape
    half = n // 2
    for c in range(channels):
        for i in range(m):
            for j in range(1, half):
                real[c, i, j] = ccs[c, i, 2 * j - 1]
                imag[c, i, j] = ccs[c, i, 2 * j]
        for j, column in ((0, 0), (half, n - 1)):
            real[c, 0, j] = ccs[c, 0, column]
            imag[c, 0, j] = 0.0
            real[c, m // 2, j] = ccs[c, m - 1, column]
            imag[c, m // 2, j] = 0.0
            for i in range(1, m // 2):
                re = ccs[c, 2 * i - 1, column]
                im = ccs[c, 2 * i, column]
                real[c, i, j] = re
                imag[c, i, j] = im
                real[c, m - i, j] = re      # Hermitian: Y(M - i, j) = conj(Y(i, j)) for j = 0, N/2
                imag[c, m - i, j] = -im


@numba.njit(cache=True, nogil=True)
def split_to_ccs(real, imag, ccs):
    """The inverse of ``ccs_to_split`` (for spectra of real maps: the Hermitian columns' lower half is implied)."""
    channels, m, n = ccs.shape
    half = n // 2
    for c in range(channels):
        for i in range(m):
            for j in range(1, half):
                ccs[c, i, 2 * j - 1] = real[c, i, j]
                ccs[c, i, 2 * j] = imag[c, i, j]
        for j, column in ((0, 0), (half, n - 1)):
            ccs[c, 0, column] = real[c, 0, j]
            ccs[c, m - 1, column] = real[c, m // 2, j]
            for i in range(1, m // 2):
                ccs[c, 2 * i - 1, column] = real[c, i, j]
                ccs[c, 2 * i, column] = imag[c, i, j]


@numba.njit(cache=True, nogil=True, fastmath=True)
def multiply_accumulate(image_real, image_imag, kernel_real, kernel_imag, pair_channel, pair_start, out_real,
                        out_imag):
    """out[t] = sum over p in pair_start[t] .. pair_start[t + 1] - 1 of kernel[p] * image[pair_channel[p]], complex
    spectra given as flat real and imaginary parts (one row per spectrum): contiguous planes, so the loop runs in
    SIMD."""
    n = out_real.shape[1]
    for t in range(out_real.shape[0]):
        o_re = out_real[t]
        o_im = out_imag[t]
        o_re[:] = 0.0
        o_im[:] = 0.0
        for p in range(pair_start[t], pair_start[t + 1]):
            a_re = image_real[pair_channel[p]]
            a_im = image_imag[pair_channel[p]]
            k_re = kernel_real[p]
            k_im = kernel_imag[p]
            for i in range(n):
                o_re[i] += a_re[i] * k_re[i] - a_im[i] * k_im[i]
                o_im[i] += a_re[i] * k_im[i] + a_im[i] * k_re[i]
