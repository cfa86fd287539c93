"""Heat as evidence: per-class log-likelihood ratios of heatmap scores, accumulated instead of raw scores.

The thesis sums raw detector scores (§5.4). A real detector answers everywhere (a template scores 0.05-0.3 on plain
table), differently per class, so summed along hundreds of rays the background dominates the volume and one
threshold cannot fit every class. The soft localizer already models scores by their likelihoods, p(z|d) at an
object and p(z|d̄) elsewhere (§4.7.3, eq. 4.23-4.27); the mapper can do the same per heatmap cell:

    L_c(z) = log p(z | d_c) − log p(z | d̄_c)

replaces the score ``z`` of class ``c`` before back-projection. Summed over the frames that saw a voxel this is the
voxel's log-odds under the (naive) independence of views; divided by the view count (the mapper's normalised
score) it is the mean evidence per view: > 0 where the detector answered as it does on objects, < 0 where it
answered as it does on background - a voxel seen often is not favoured, and background heat pulls a voxel down
instead of up. The ratio is in the same unit for every class, the global normalisation §5.3 asks for.

Samples (``heat_samples``): ``d`` = the class's heat at the projection of an object's centre (the cell a voxel at
the object samples), ``d̄`` = heat at cells outside every projected box of the class (grown by ``margin``).
Densities are the same reflected Gaussian KDEs as the localizer's calibration (semloc_core.detection.calibration).
Fit them on calibration scenes, never on the scenes evaluated.
"""

from __future__ import annotations

import numpy as np

from semloc_core.detection.calibration import kde_on_grid, robust_bandwidth

LLR_GRID_POINTS = 101  # ratio table over scores [0, 1]; step 0.01, finer than any bandwidth that matters


def heat_samples(heatmaps: np.ndarray, image_size: tuple[int, int], centres, boxes, margin: float = 0.25
                 ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per class, (positive, negative) heat samples of one frame.

    ``heatmaps`` (C, h, w) cover an image of ``image_size`` = (W, H) uniformly (docs/detection.md). ``centres``:
    (class index, u, v) pixel projections of object centres that count as seen (visible, not truncated);
    ``boxes``: (class index, [x0, y0, x1, y1]) of every object in view, whatever its visibility - no negative is
    taken inside one of its class's boxes grown by ``margin`` of its size on each side.
    """
    h = np.asarray(heatmaps, dtype=np.float32)
    num_classes, rows, cols = h.shape
    width, height = image_size
    # Cell (r, q) centre in pixels: u = (q + 0.5)·W/w − 0.5 (docs/detection.md), so q = (u + 0.5)·w/W − 0.5.
    qs = (np.arange(cols) + 0.5) * width / cols - 0.5
    rs = (np.arange(rows) + 0.5) * height / rows - 0.5
    positives: list[list[float]] = [[] for _ in range(num_classes)]
    background = np.ones((num_classes, rows, cols), bool)
    for c, box in boxes:
        x0, y0, x1, y1 = (float(v) for v in box)
        gx, gy = margin * (x1 - x0), margin * (y1 - y0)
        inside_cols = (qs >= x0 - gx) & (qs <= x1 + gx)
        inside_rows = (rs >= y0 - gy) & (rs <= y1 + gy)
        background[c][np.ix_(inside_rows, inside_cols)] = False
    for c, u, v in centres:
        q = (u + 0.5) * cols / width - 0.5
        r = (v + 0.5) * rows / height - 0.5
        if not (0 <= q <= cols - 1 and 0 <= r <= rows - 1):
            continue
        q0, r0 = min(int(q), cols - 2), min(int(r), rows - 2)
        fq, fr = q - q0, r - r0
        patch = h[c, r0:r0 + 2, q0:q0 + 2]
        positives[c].append(float((1 - fr) * ((1 - fq) * patch[0, 0] + fq * patch[0, 1])
                                  + fr * ((1 - fq) * patch[1, 0] + fq * patch[1, 1])))
    negatives = [h[c][background[c]] for c in range(num_classes)]
    return [np.asarray(p, np.float32) for p in positives], negatives


def increasing_fit(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The non-decreasing sequence closest to ``values`` in weighted least squares (pool adjacent violators)."""
    blocks: list[list[float]] = []  # [weighted mean, weight, length]
    for value, weight in zip(np.asarray(values, float), np.asarray(weights, float)):
        blocks.append([value, weight, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            v2, w2, n2 = blocks.pop()
            v1, w1, n1 = blocks[-1]
            total = w1 + w2
            blocks[-1] = [(v1 * w1 + v2 * w2) / total if total > 0 else 0.5 * (v1 + v2), total, n1 + n2]
    return np.concatenate([np.full(n, v) for v, _, n in blocks])


def fit_heat_llr(samples_d: dict, samples_not_d: dict, clip: float = 4.0, points: int = LLR_GRID_POINTS) -> dict:
    """{class: list of ``points`` log-likelihood ratios over scores 0..1} from pooled samples.

    The ratio is clipped to ±``clip`` (the tails of both densities rest on a handful of samples) and made
    non-decreasing in the score - a stronger detector answer is never weaker evidence for the object - by a
    least-squares fit weighted with the samples' density: where no sample fell the ratio says nothing and takes
    its populated neighbours' value instead of a KDE's tail wiggles.
    """
    z = np.linspace(0.0, 1.0, points)
    step = z[1] - z[0]
    tables = {}
    for name in samples_d:
        d = np.concatenate([np.ravel(s) for s in samples_d[name]]) if len(samples_d[name]) else np.zeros(0)
        nd = (np.concatenate([np.ravel(s) for s in samples_not_d[name]]) if samples_not_d.get(name)
              else np.zeros(0))
        if d.size < 10 or nd.size < 10:
            continue  # too few samples for a density: left out (check_llr_tables names the class)
        pdf_d = kde_on_grid(d, z, robust_bandwidth(d, step))
        pdf_nd = kde_on_grid(nd, z, robust_bandwidth(nd, step))
        floor = 1e-6
        ratio = np.clip(np.log(pdf_d + floor) - np.log(pdf_nd + floor), -clip, clip)
        # Each class's samples weigh equally (negatives outnumber positives a thousandfold).
        tables[name] = [float(v) for v in increasing_fit(ratio, pdf_d + pdf_nd + floor)]
    return tables


def check_llr_tables(tables: dict, class_names) -> np.ndarray:
    """The tables of ``class_names`` as a (C, points) float32 array, or ValueError naming what is wrong."""
    missing = [name for name in class_names if name not in tables]
    if missing:
        raise ValueError(f"heat likelihood ratios lack classes {missing}; they have {sorted(tables)}")
    rows = [np.asarray(tables[name], dtype=np.float64) for name in class_names]
    lengths = {row.shape for row in rows}
    if len(lengths) != 1 or rows[0].ndim != 1 or rows[0].size < 2:
        raise ValueError(f"heat likelihood ratio tables must be 1-D and of one length, got shapes {sorted(lengths)}")
    if not all(np.all(np.isfinite(row)) for row in rows):
        raise ValueError("heat likelihood ratio tables must be finite")
    return np.stack(rows).astype(np.float32)


def heat_surprisal(heatmaps: np.ndarray) -> np.ndarray:
    """Each cell's heat replaced by its surprisal within the frame: ``-log q``, ``q`` the fraction of the frame's
    cells of that class whose heat is at least the cell's (``q`` = 1 at the frame's floor, 1/N at its maximum).

    ``q`` is the empirical p-value of the cell's heat under the hypothesis that it is background, the frame's own
    heat being the background's distribution (objects cover a small part of an image). Averaged over the frames
    that saw a voxel (the mapper's normalised score) it is 1 for background whatever the class, template, scene or
    lighting - only the order of a frame's heat counts, so a dim scene where every template answers weakly and a
    template answering 0.3 on the whole table are put on one scale (the global normalisation §5.3 asks for) - and
    large only where the detector answered among its strongest, view after view.
    """
    return level_surprisal(heatmaps, 1)  # one level per class: each map judged against itself


def level_surprisal(level_maps: np.ndarray, levels: int) -> np.ndarray:
    """``heat_surprisal`` of per-level maps ((classes · levels), H, W), class-major: every level of a class is
    judged against the frame's max-over-levels heat of that class (the single-map heatmap), so a level's answer
    is as surprising as the same heat in the single map.

    Only the order of a frame's heat counts, so quantised maps (uint8 or uint16 codes, as the detector publishes
    them: value = code · scale, scale > 0) may be given as their codes: the same surprisals, counted from the
    codes' histogram in one pass instead of sorting every cell (5 maps of 160x120: 0.3 ms against 5 ms)."""
    h = np.asarray(level_maps)
    if h.ndim != 3 or levels < 1 or h.shape[0] % levels:
        raise ValueError(f"need (classes x {levels} levels, H, W) maps, got shape {h.shape}")
    codes = h.dtype in (np.uint8, np.uint16)
    if not codes:
        h = h.astype(np.float32, copy=False)
    out = np.empty(h.shape, np.float32)
    for c in range(h.shape[0] // levels):
        group = h[c * levels:(c + 1) * levels]
        background = group.max(axis=0).ravel()
        total = np.float32(background.size)
        if codes:
            # at_least[v] = cells of the class's max map whose code is >= v (a suffix sum of the histogram).
            at_least = np.cumsum(np.bincount(background, minlength=np.iinfo(h.dtype).max + 1)[::-1])[::-1]
            at_least = np.maximum(at_least, 1).astype(np.float32)
            out[c * levels:(c + 1) * levels] = np.log(total / at_least)[group]
            continue
        background = np.sort(background)
        at_least = background.size - np.searchsorted(background, group.ravel(), side="left")
        # A level never exceeds its class's max map, so at_least >= 1 (the clamp only guards rounding); heat below
        # the frame's floor counts as the whole frame: surprisal 0.
        at_least = np.maximum(at_least, 1).astype(np.float32)
        out[c * levels:(c + 1) * levels] = np.log(total / at_least).reshape(group.shape)
    return out


def heat_to_llr(heatmaps: np.ndarray, tables: np.ndarray) -> np.ndarray:
    """Each class's scores replaced by its log-likelihood ratio (linear interpolation over scores 0..1; scores
    outside take the end values)."""
    h = np.asarray(heatmaps, dtype=np.float32)
    z = np.linspace(0.0, 1.0, tables.shape[1])
    return np.stack([np.interp(h[c], z, tables[c]).astype(np.float32) for c in range(h.shape[0])])
