"""numba kernels of the §4.3 detector's fast path (the equations are in features.py and templates.py).

* ``pooled_energies``: the steerable basis responses filtered a row at a time, their six products summed over each
  cell and steered to every orientation (eq. 4.1), in one pass over the image instead of three filtered images, six
  multiplies, six block means and a matrix product (``normalised_energies``: eq. 4.2);
* ``rgb_histograms`` / ``hsv_histograms``: HQC cell histograms (§4.3.2) counted straight from the pixels (palette
  index or hsv votes looked up per pixel and added to its cell), instead of a full-resolution index image and
  ``bincount``; like ``normalised_energies`` they write histograms or, for the detector, the square roots of the
  bins it uses as channel planes;
* ``multiply_accumulate``: the channel sum of eq. 4.3 in the frequency domain, out[t] = sum over template t's
  channels of K[p] x I[channel p], on split real / imaginary half-planes; ``unpack_spectra`` / ``pack_spectra``
  let one complex DFT transform two real maps at a time (OpenCV's complex DFT is about twice as
  fast per map as its real one here).
"""

from __future__ import annotations

import numba
import numpy as np

# OpenCV's 8-bit hue is degrees / 2: a hue bin boundary falls on a multiple of 1/180 of the circle for any number of
# hue bins, so the hsv model's split votes are whole multiples of 1/HUE_WEIGHT.
HUE_WEIGHT = 180


@numba.njit(inline="always")
def _reflect_101(p, n):
    """OpenCV's BORDER_REFLECT_101 index (cv2.borderInterpolate): ... 2 1 | 0 1 2 ... n-1 | n-2 ..."""
    if n == 1:
        return 0
    while p < 0 or p >= n:
        p = -p if p < 0 else 2 * n - 2 - p
    return p


@numba.njit(cache=True, nogil=True, fastmath=True)
def pooled_energies(grey, g, g1, g2, cell, steering, out, totals):
    """out[r, c, o] = oriented energy o pooled over cell (r, c) (eq. 4.1) of a grey image (uint8 or float32), and
    totals[r, c] their sum.

    The steerable basis Gxx = g'' (x) g (y), Gxy = g' (x) g' (y), Gyy = g (x) g'' (y) (correlations with OpenCV's
    BORDER_REFLECT_101, as cv2.sepFilter2D; g and g'' symmetric, g' antisymmetric, so mirrored taps are added or
    subtracted before one multiply) is filtered along the rows once per image row, kept in a ring of the rows in
    reach, and along the columns per output row; the six products [Gxx^2, Gxy^2, Gyy^2, Gxx Gxy, Gxx Gyy,
    Gxy Gyy] are summed over the cell and steered by ``steering`` (6, orientations), clamped at 0 (float32 rounding
    of the expansion). The responses are never stored whole: three full-size images written and read again cost
    more, among the detector's other buffers, than the filtering."""
    height, width = grey.shape
    rows, cols, orientations = out.shape
    taps = g.shape[0]
    radius = taps // 2
    padded = np.empty(width + 2 * radius, np.float32)
    column = np.empty(width + 2 * radius, np.int64)
    for i in range(column.shape[0]):
        column[i] = _reflect_101(i - radius, width)
    # ring[p % taps]: image row p filtered along the row by g'', g' and g; the rows a column filter reads (row y's
    # reflected neighbours) are within radius of y, so a row is dropped only once no later output row needs it
    ring = np.empty((taps, 3, width), np.float32)
    done = -1
    gxx = np.empty(width, np.float32)
    gxy = np.empty(width, np.float32)
    gyy = np.empty(width, np.float32)
    band = np.zeros((6, width), np.float32)
    pooled = np.zeros(6, np.float32)
    for r in range(rows):
        band[:] = 0.0
        for y in range(r * cell, (r + 1) * cell):
            while done < min(y + radius, height - 1):
                done += 1
                source = grey[done]
                for i in range(padded.shape[0]):
                    padded[i] = source[column[i]]
                slot = ring[done % taps]
                xx, xy, yy = slot[0], slot[1], slot[2]
                centre = padded[radius:radius + width]
                a, c = g2[radius], g[radius]
                for x in range(width):
                    xx[x] = a * centre[x]
                    xy[x] = 0.0
                    yy[x] = c * centre[x]
                for j in range(radius):   # taps j and taps - 1 - j: equal (g, g''), opposite (g')
                    a, b, c = g2[j], g1[j], g[j]
                    left = padded[j:j + width]
                    right = padded[taps - 1 - j:taps - 1 - j + width]
                    for x in range(width):
                        both = left[x] + right[x]
                        xx[x] += a * both
                        xy[x] += b * (left[x] - right[x])
                        yy[x] += c * both
            centre = ring[y % taps]
            a, c = g[radius], g2[radius]
            for x in range(width):
                gxx[x] = a * centre[0, x]
                gxy[x] = 0.0
                gyy[x] = c * centre[2, x]
            for i in range(radius):
                above = ring[_reflect_101(y + i - radius, height) % taps]
                below = ring[_reflect_101(y + radius - i, height) % taps]
                a, b, c = g[i], g1[i], g2[i]
                for x in range(width):
                    gxx[x] += a * (above[0, x] + below[0, x])
                    gxy[x] += b * (above[1, x] - below[1, x])
                    gyy[x] += c * (above[2, x] + below[2, x])
            for x in range(width):
                a = gxx[x]
                b = gxy[x]
                c = gyy[x]
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
            total = np.float32(0.0)
            for o in range(orientations):
                energy = np.float32(0.0)
                for k in range(6):
                    energy += pooled[k] * steering[k, o]
                energy = max(energy, np.float32(0.0))
                out[r, col, o] = energy
                total += energy
            totals[r, col] = total


@numba.njit(cache=True, nogil=True, fastmath=True)
def normalised_energies(energies, totals, epsilon, root, out):
    """Channel o (and the last, ``orientations``) of every cell: energies[r, c, o] / (epsilon + totals[r, c]) and
    epsilon / (epsilon + totals[r, c]) (eq. 4.2), square-rooted when ``root`` (eq. 4.3's sqrt F).

    ``out`` (P, rows, cols, parts) receives channel k at ``[k % P, ..., k // P]``: a histogram (rows, cols, bins)
    seen through ``transpose(2, 0, 1)[..., None]``, or the correlator's complex DFT input (two channels a pair).
    A channel's row is computed in a contiguous buffer (so that the division and square root run in SIMD) and then
    copied to its strided place."""
    rows, cols, orientations = energies.shape
    scale = np.empty(cols, np.float32)
    row = np.empty(cols, np.float32)
    for r in range(rows):
        for c in range(cols):
            scale[c] = np.float32(1.0) / (epsilon + totals[r, c])
        for o in range(orientations + 1):
            if o < orientations:
                for c in range(cols):
                    row[c] = energies[r, c, o] * scale[c]
            else:
                for c in range(cols):
                    row[c] = epsilon * scale[c]
            _store_row(row, root, out, o, r)


@numba.njit(inline="always")
def _store_row(row, root, out, k, r):
    """Channel k's row r of ``out`` (layout of ``normalised_energies``) from a contiguous row, square-rooted when
    ``root``."""
    if root:
        for c in range(row.shape[0]):
            row[c] = np.sqrt(row[c])
    pairs = out.shape[0]
    target = out[k % pairs, r, :, k // pairs]
    for c in range(row.shape[0]):
        target[c] = row[c]


@numba.njit(inline="always")
def _write_rows(counts, unit, slot, root, out, r, row):
    """Row r of the channels slot[colour] (colours whose slot is -1 left out) from counts (colours, cols) x unit."""
    for colour in range(counts.shape[0]):
        k = slot[colour]
        if k >= 0:
            for c in range(counts.shape[1]):
                row[c] = counts[colour, c] * unit
            _store_row(row, root, out, k, r)


@numba.njit(cache=True, nogil=True, fastmath=True)
def rgb_histograms(bgr, weighted_lut, cell, bins, slot, root, out):
    """HQC cell histograms (§4.3.2) of the palette colours: channel slot[colour] = share of cell (r, c)'s pixels of
    that colour (square-rooted when ``root``; colours whose slot is -1 are left out), written into ``out`` as in
    ``normalised_energies``, a row of cells at a time. ``weighted_lut`` (3, 256) gives each channel's level already
    weighted (B * k^2, G * k, R). Pixels are counted as integers (exact)."""
    rows, cols = out.shape[1], out.shape[2]
    unit = np.float32(1.0 / (cell * cell))
    counts = np.zeros((bins, cols), np.int32)
    row = np.empty(cols, np.float32)
    for r in range(rows):
        counts[:] = 0
        for y in range(r * cell, (r + 1) * cell):
            pixels = bgr[y]
            for c in range(cols):
                for x in range(c * cell, (c + 1) * cell):
                    colour = (weighted_lut[0, pixels[x, 0]] + weighted_lut[1, pixels[x, 1]]
                              + weighted_lut[2, pixels[x, 2]])
                    counts[colour, c] += 1
        _write_rows(counts, unit, slot, root, out, r, row)


@numba.njit(cache=True, nogil=True, fastmath=True)
def hsv_histograms(hsv, lower_bin, upper_bin, upper_weight, saturation_bin, grey_bin, min_saturation, min_value,
                   cell, bins, slot, root, out):
    """HQC cell histograms of the hsv model (see features.hsv_colour_votes), written as ``rgb_histograms``: a grey
    pixel (saturation < ``min_saturation`` or value < ``min_value``) votes for ``grey_bin[value]``, a chromatic one
    splits its vote between ``lower_bin[hue]`` and ``upper_bin[hue]`` (+ its saturation bin), the upper one getting
    ``upper_weight[hue]`` / HUE_WEIGHT (a whole number: the hue's place between the two bin centres, in 180ths, so
    the votes are counted exactly as integers)."""
    rows, cols = out.shape[1], out.shape[2]
    unit = np.float32(1.0 / (HUE_WEIGHT * cell * cell))
    counts = np.zeros((bins, cols), np.int32)
    row = np.empty(cols, np.float32)
    for r in range(rows):
        counts[:] = 0
        for y in range(r * cell, (r + 1) * cell):
            pixels = hsv[y]
            for c in range(cols):
                for x in range(c * cell, (c + 1) * cell):
                    hue = pixels[x, 0]
                    saturation = pixels[x, 1]
                    value = pixels[x, 2]
                    if saturation < min_saturation or value < min_value:
                        counts[grey_bin[value], c] += HUE_WEIGHT
                    else:
                        share = upper_weight[hue]
                        level = saturation_bin[saturation]
                        counts[lower_bin[hue] + level, c] += HUE_WEIGHT - share
                        counts[upper_bin[hue] + level, c] += share
        _write_rows(counts, unit, slot, root, out, r, row)


@numba.njit(inline="always")
def _first_spectrum_row(out_re, out_im, z, w, n, half, h):
    """One row of the first map's half-plane spectrum A = (Z + conj W(-v)) / 2 from a packed pair's rows z and w
    (row -u); swapping z and w gives the row -u (a mirrored kernel's)."""
    out_re[0] = h * (z[0, 0] + w[0, 0])
    out_im[0] = h * (z[0, 1] - w[0, 1])
    for v in range(1, half):
        out_re[v] = h * (z[v, 0] + w[n - v, 0])
        out_im[v] = h * (z[v, 1] - w[n - v, 1])


@numba.njit(inline="always")
def _second_spectrum_row(out_re, out_im, z, w, n, half, h):
    """The same for the second map, B = (Z - conj W(-v)) / 2i."""
    out_re[0] = h * (z[0, 1] + w[0, 1])
    out_im[0] = h * (w[0, 0] - z[0, 0])
    for v in range(1, half):
        out_re[v] = h * (z[v, 1] + w[n - v, 1])
        out_im[v] = h * (w[n - v, 0] - z[v, 0])


@numba.njit(cache=True, nogil=True)
def unpack_spectra(spectra, real, imag, reversed_real, reversed_imag):
    """Separate the spectra of two real maps transformed together (Z = DFT(a + i b), (P, M, N, 2)): the half-planes
    (v <= N/2) of A = (Z(u, v) + conj Z(-u, -v)) / 2 into channel j and of B = (Z(u, v) - conj Z(-u, -v)) / 2i into
    channel j + P of ``real`` and ``imag`` (C, M, N/2 + 1). ``reversed_real`` / ``reversed_imag``: the same
    half-planes with the rows in reverse order (row u holds row -u, what a mirrored kernel multiplies, see
    ``multiply_accumulate``), from the same two rows of Z; (0, M, N/2 + 1) arrays when no kernel is mirrored."""
    n_pairs, m, n = spectra.shape[0], spectra.shape[1], spectra.shape[2]
    n_channels, half = real.shape[0], real.shape[2]
    mirrored = reversed_real.shape[0] > 0
    h = np.float32(0.5)
    for j in range(n_pairs):
        second = j + n_pairs
        for u in range(m):
            z = spectra[j, u]
            w = spectra[j, m - u if u else 0]   # row -u; column -v is n - v (0 for v = 0)
            _first_spectrum_row(real[j, u], imag[j, u], z, w, n, half, h)
            if mirrored:   # A(-u, v): z and w swap roles
                _first_spectrum_row(reversed_real[j, u], reversed_imag[j, u], w, z, n, half, h)
            if second < n_channels:
                _second_spectrum_row(real[second, u], imag[second, u], z, w, n, half, h)
                if mirrored:
                    _second_spectrum_row(reversed_real[second, u], reversed_imag[second, u], w, z, n, half, h)


@numba.njit(cache=True, nogil=True)
def pack_spectra(real, imag, reversed_rows, packed):
    """The inverse of ``unpack_spectra`` for the outputs: packed[j] = the full spectrum of map j + i map j + P (P =
    packed.shape[0]), from their half-planes (the rest by Hermitian symmetry, X(u, v) = conj X(-u, N - v)), so that
    one complex inverse DFT gives map j in its real part and map j + P in its imaginary part. A map whose
    ``reversed_rows`` is set holds its rows in reverse order (row u is row -u: a mirrored kernel's output)."""
    n_pairs, m, n = packed.shape[0], packed.shape[1], packed.shape[2]
    n_maps, half = real.shape[0], real.shape[2]
    for j in range(n_pairs):
        second = j + n_pairs
        has_second = second < n_maps
        for u in range(m):
            mirror = m - u if u else 0
            a_row, c_row = (mirror, u) if reversed_rows[j] else (u, mirror)
            a_re, a_im = real[j, a_row], imag[j, a_row]
            c_re, c_im = real[j, c_row], imag[j, c_row]
            target = packed[j, u]
            if has_second:   # W = A + iB: (A_re - B_im, A_im + B_re); beyond N/2, A = conj A(-u, N - v)
                b_row, d_row = (mirror, u) if reversed_rows[second] else (u, mirror)
                b_re, b_im = real[second, b_row], imag[second, b_row]
                d_re, d_im = real[second, d_row], imag[second, d_row]
                for v in range(half):
                    target[v, 0] = a_re[v] - b_im[v]
                    target[v, 1] = a_im[v] + b_re[v]
                for v in range(half, n):
                    target[v, 0] = c_re[n - v] + d_im[n - v]
                    target[v, 1] = d_re[n - v] - c_im[n - v]
            else:
                for v in range(half):
                    target[v, 0] = a_re[v]
                    target[v, 1] = a_im[v]
                for v in range(half, n):
                    target[v, 0] = c_re[n - v]
                    target[v, 1] = -c_im[n - v]


@numba.njit(cache=True, nogil=True, fastmath=True)
def multiply_accumulate(image_real, image_imag, reversed_real, reversed_imag, kernel_real, kernel_imag,
                        pair_channel, pair_start, kernel_out, mirror_out, mirror_channel, out_real, out_imag):
    """out[kernel_out[s]] = sum over p in pair_start[s] .. pair_start[s + 1] - 1 of kernel[p] * image[pair_channel[p]]
    for every stored kernel s, complex spectra given as flat real and imaginary parts (one row per spectrum): long
    contiguous loops, which run in SIMD (per-row loops of the half-plane, or blocks of rows, measured slower).

    A stored kernel whose ``mirror_out[s]`` is >= 0 also gives its mirror image's output there, from the same
    kernel spectra read once: a kernel mirrored left-right (its channels mapped to ``mirror_channel[p]``) has the
    spectrum conj K(-u, v), so its output at row -u is the sum of conj K(u, v) x image[mirror_channel[p]](-u, v) -
    the row-reversed image half-planes (``unpack_spectra``) - and is written row-reversed (``pack_spectra``).

    Two (kernel, channel) pairs are summed per pass over the outputs (an odd first one alone): a quarter less
    time than one per pass, which reads and writes the outputs twice as often (four per pass, measured slower)."""
    n = out_real.shape[1]
    for s in range(kernel_out.shape[0]):
        o_re = out_real[kernel_out[s]]
        o_im = out_imag[kernel_out[s]]
        o_re[:] = 0.0
        o_im[:] = 0.0
        first, end = pair_start[s], pair_start[s + 1]
        if mirror_out[s] < 0:
            if (end - first) % 2:
                a_re, a_im = image_real[pair_channel[first]], image_imag[pair_channel[first]]
                k_re, k_im = kernel_real[first], kernel_imag[first]
                for i in range(n):
                    o_re[i] += a_re[i] * k_re[i] - a_im[i] * k_im[i]
                    o_im[i] += a_re[i] * k_im[i] + a_im[i] * k_re[i]
                first += 1
            for p in range(first, end, 2):
                a_re, a_im = image_real[pair_channel[p]], image_imag[pair_channel[p]]
                c_re, c_im = image_real[pair_channel[p + 1]], image_imag[pair_channel[p + 1]]
                k_re, k_im, l_re, l_im = kernel_real[p], kernel_imag[p], kernel_real[p + 1], kernel_imag[p + 1]
                for i in range(n):
                    o_re[i] += a_re[i] * k_re[i] - a_im[i] * k_im[i] + c_re[i] * l_re[i] - c_im[i] * l_im[i]
                    o_im[i] += a_re[i] * k_im[i] + a_im[i] * k_re[i] + c_re[i] * l_im[i] + c_im[i] * l_re[i]
            continue
        m_re = out_real[mirror_out[s]]
        m_im = out_imag[mirror_out[s]]
        m_re[:] = 0.0
        m_im[:] = 0.0
        if (end - first) % 2:
            a_re, a_im = image_real[pair_channel[first]], image_imag[pair_channel[first]]
            b_re, b_im = reversed_real[mirror_channel[first]], reversed_imag[mirror_channel[first]]
            k_re, k_im = kernel_real[first], kernel_imag[first]
            for i in range(n):
                kr = k_re[i]
                ki = k_im[i]
                o_re[i] += a_re[i] * kr - a_im[i] * ki
                o_im[i] += a_re[i] * ki + a_im[i] * kr
                m_re[i] += b_re[i] * kr + b_im[i] * ki
                m_im[i] += b_im[i] * kr - b_re[i] * ki
            first += 1
        for p in range(first, end, 2):
            a_re, a_im = image_real[pair_channel[p]], image_imag[pair_channel[p]]
            b_re, b_im = reversed_real[mirror_channel[p]], reversed_imag[mirror_channel[p]]
            c_re, c_im = image_real[pair_channel[p + 1]], image_imag[pair_channel[p + 1]]
            d_re, d_im = reversed_real[mirror_channel[p + 1]], reversed_imag[mirror_channel[p + 1]]
            k_re, k_im, l_re, l_im = kernel_real[p], kernel_imag[p], kernel_real[p + 1], kernel_imag[p + 1]
            for i in range(n):
                kr, ki, lr, li = k_re[i], k_im[i], l_re[i], l_im[i]
                o_re[i] += a_re[i] * kr - a_im[i] * ki + c_re[i] * lr - c_im[i] * li
                o_im[i] += a_re[i] * ki + a_im[i] * kr + c_re[i] * li + c_im[i] * lr
                m_re[i] += b_re[i] * kr + b_im[i] * ki + d_re[i] * lr + d_im[i] * li
                m_im[i] += b_im[i] * kr - b_re[i] * ki + d_im[i] * lr - d_re[i] * li



@numba.njit(cache=True, nogil=True)
def scatter_max(values, cells, bins, out):
    """out[c, bins[k]] = max(out[c, bins[k]], values[c, cells[k]]) for every pair k: a heatline bin is the maximum
    over the heatmap cells that reach it (§4.4.2), without sorting the pairs by bin."""
    for k in range(cells.shape[0]):
        cell, b = cells[k], bins[k]
        for c in range(values.shape[0]):
            v = values[c, cell]
            if v > out[c, b]:
                out[c, b] = v


@numba.njit(cache=True, nogil=True, fastmath=True)
def lerp_rows_max(rows, first, below, above, weight, best):
    """best[t, first + i] = max(itself, rows[t, below[i]] + weight[i] (rows[t, above[i]] - rows[t, below[i]])):
    maps (templates, rows, n) resampled along their rows onto the output rows (bilinear) and maxed into ``best``
    (templates, output rows, n) in one pass, instead of two gathers, three arithmetic passes and a max."""
    for t in range(rows.shape[0]):
        for i in range(below.shape[0]):
            lower, upper, out = rows[t, below[i]], rows[t, above[i]], best[t, first + i]
            w = weight[i]
            for k in range(out.shape[0]):
                value = lower[k] + w * (upper[k] - lower[k])
                out[k] = max(out[k], value)
