"""Fast evaluation of the perception models (the equations are in perception.py, the dense versions too).

Both models score a particle by summing, per class c and per observed bin j, a term of the detection probability
(or expected heatline) P[c, j] = max_k g(j - u_k), where g is a Gaussian of the bearing difference and u_k the bearing
(in bins) at which the particle expects instance k of class c (eq. 4.7, 4.26):

* model B (eq. 4.27 in log space, minus its pose-independent part): ``log(1 + a[c, j] P[c, j])`` with
  ``a = p(z|d)/p(z|d̄) - 1``;
* model A (eq. 4.6): ``z[c, j] P[c, j]``.

Two facts make this cheap:

1. All Gaussians share one σ, so the max over instances at bin j is the Gaussian of the *nearest* instance: the
   circle of bins splits at the midpoints between consecutive instances, and each instance contributes the sum of
   its own terms over its share of bins.
2. An instance's terms depend only on its continuous bearing and on the observation. So once per observation we
   tabulate, for bearings on a grid of ``sub`` steps per bin, the running sum of the terms over the ``K`` bins
   around that bearing (``prefix_tables``). A share of bins is then a difference of two table entries, linearly
   interpolated between the two neighbouring grid bearings.

An object that exists only with probability π_k (a mapped object, ``SemanticMap.existence``) is expected with
π_k g: P[c, j] = max_k π_k g(j - u_k). Same-width Gaussians scaled differently still split the circle into one
share per instance, in bearing order: instance a beats its neighbour b at distance D where
ln π_a - x² / 2σ² = ln π_b - (D - x)² / 2σ², i.e. up to x = D / 2 + σ² ln(π_a / π_b) / D (a weak instance next
to a strong one can own nothing). Its terms come from the table of its class scaled by π_k (one table per class
and distinct π; one per class when every π is 1).

The Gaussian is truncated beyond ``H`` bins (H >= 5σ, where it is below 4e-6). This avoids the dense
(particles x classes x bins) pass of the reference implementation: per particle and object the cost is one bearing
and four table reads.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

KIND_LOG_RATIO = 0  # model B
KIND_INNER_PRODUCT = 1  # model A
OCCLUDED_SHARE = 0.5  # an object at least this share of whose width a nearer object covers is not expected ...
OCCLUDER_CORE = 0.5  # ... by the inner part of the nearer one's footprint radius: a map's size is the axis-aligned
# box of the object (no yaw), which for a rotated box (a cereal box 45 degrees off the axes) is up to 2-3 times as
# wide as what the camera sees of it; the full box hid objects next to it that were in plain view
TARGET_SLACK = max(1.0 - 2.0 * OCCLUDED_SHARE, 0.0)  # how far a target's width widens the pair test (_apply_view)


@intrinsic
def _prefetch(typingctx, array, index):
    """Ask for the cache line of array.flat[index] (LLVM's prefetch: read, high locality), without waiting for it."""
    signature = types.void(array, index)

    def codegen(context, builder, sig, args):
        view = context.make_array(sig.args[0])(context, builder, args[0])
        pointer = builder.bitcast(cgutils.get_item_pointer(context, builder, sig.args[0], view, [args[1]]),
                                  ir.IntType(8).as_pointer())
        int32 = ir.IntType(32)
        function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [pointer.type, int32, int32, int32]), "llvm.prefetch.p0")
        builder.call(function, [pointer, int32(0), int32(3), int32(1)])
        return context.get_dummy_value()

    return signature, codegen


def window_layout(n_bins: int, sub: int, half_bins: int, sigma_bins: float, peak: float) -> np.ndarray:
    """(K, F) float32: g of the k-th of the K bins around the bearing at fine step f (bins f // sub - half_bins
    .. f // sub - half_bins + K - 1, modulo n_bins)."""
    n_fine = n_bins * sub
    k = 2 * half_bins + 2
    fine = np.arange(n_fine)
    unwrapped = (fine // sub - half_bins)[None, :] + np.arange(k)[:, None]
    offset = unwrapped - fine[None, :] / sub
    return (peak * np.exp(-0.5 * (offset / sigma_bins) ** 2)).astype(np.float32)


def prefix_tables(coefficients: np.ndarray, observed: np.ndarray, weights: np.ndarray, half_bins: int,
                  kind: int) -> np.ndarray:
    """(C, K + 1, F) running sums over the K bins around each fine bearing f of the per-bin term, from 0 (column k
    of bearing f at [c, k, f]: the bearings side by side, so that the table is filled in SIMD across bearings and
    an instance's two neighbouring bearings are read from one cache line). In float32, as the terms are: the tables
    are written once per observation and read at random per particle, and at half the size (1.5 MB at 5 classes,
    360 bins) they are filled and read ~1.4x faster; a particle's log-likelihood moves by < 1e-4 (the sums of its
    shares, against float64 tables)."""
    masked = np.where(observed[None, :], coefficients, 0.0).astype(np.float32)
    k_count, n_fine = weights.shape
    sub = n_fine // masked.shape[1]
    # each bin repeated for its sub fine bearings and the rows wrapped around by the window's reach on either side:
    # the k-th bin of bearing f's window is then entry f + k sub, for every f at once
    repeated = np.repeat(np.take(masked, np.arange(-half_bins, masked.shape[1] + k_count - half_bins), axis=1,
                                 mode="wrap"), sub, axis=1)
    tables = np.empty((masked.shape[0], k_count + 1, n_fine), np.float32)
    _fill_prefix_tables(repeated, weights, sub, kind, tables)
    return tables


@numba.njit(cache=True, fastmath=True, nogil=True)
def _fill_prefix_tables(repeated, weights, sub, kind, tables):
    n_classes = repeated.shape[0]
    k_count, n_fine = weights.shape
    terms = np.empty(n_fine, np.float32)
    exponent = np.empty(n_fine, np.int32)
    for c in range(n_classes):
        tables[c, 0, :] = 0.0
        for k in range(k_count):
            row = repeated[c, k * sub:k * sub + n_fine]
            for f in range(n_fine):
                terms[f] = row[f] * weights[k, f]
            if kind == KIND_LOG_RATIO:
                _log1p_f32(terms, exponent)
            for f in range(n_fine):
                tables[c, k + 1, f] = tables[c, k, f] + terms[f]


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _log1p_f32(values, exponent):
    """values <- log(1 + values) in float32, for 1 + values > 0 (normal floats), in two branch-free passes that
    run in SIMD (a libm call per element does not): the exponent and mantissa split on the bits, then Cephes'
    ``logf`` polynomial (within an ulp or two of libm's logf). ``exponent``: int32 scratch of the same size."""
    one = np.float32(1.0)
    for k in range(values.shape[0]):
        values[k] = one + values[k]
    bits = values.view(np.int32)
    for k in range(values.shape[0]):  # x = m 2^e with m in [0.5, 1)
        exponent[k] = ((bits[k] >> 23) & 0xFF) - 126
        bits[k] = (bits[k] & 0x807FFFFF) | 0x3F000000
    half_sqrt2 = np.float32(0.707106781186547524)
    for k in range(values.shape[0]):
        m = values[k]
        e = np.float32(exponent[k])
        small = m < half_sqrt2  # m in [sqrt(1/2), sqrt(2)): x = m - 1 near 0
        e = e - one if small else e
        x = (m + m - one) if small else (m - one)
        z = x * x
        y = np.float32(7.0376836292e-2)
        y = y * x - np.float32(1.1514610310e-1)
        y = y * x + np.float32(1.1676998740e-1)
        y = y * x - np.float32(1.2420140846e-1)
        y = y * x + np.float32(1.4249322787e-1)
        y = y * x - np.float32(1.6668057665e-1)
        y = y * x + np.float32(2.0000714765e-1)
        y = y * x - np.float32(2.4999993993e-1)
        y = y * x + np.float32(3.3333331174e-1)
        y = y * x * z
        y += np.float32(-2.12194440e-4) * e
        y -= np.float32(0.5) * z
        values[k] = x + y + np.float32(0.693359375) * e


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _atan2(y, x):
    # Minimax polynomial for atan on [0, 1] (max error 4e-8 rad); written without branches so that the loop over
    # objects vectorises: ~40x faster than libm's atan2 here.
    ax = abs(x)
    ay = abs(y)
    a = min(ax, ay) / max(max(ax, ay), 1e-300)
    s = a * a
    r = ((((((((-0.0040540580 * s + 0.0218612288) * s - 0.0559098861) * s + 0.0964200441) * s - 0.1390853351) * s
            + 0.1994653599) * s - 0.3332985605) * s + 0.9999993329) * a)
    r = 1.5707963267948966 - r if ay > ax else r
    r = 3.141592653589793 - r if x < 0.0 else r
    return -r if y < 0.0 else r


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _apparent_height(top, bottom, distance, radius):
    """Elevation span (radians) of an object's box seen from ``distance`` (top and bottom relative to the camera):
    from the lowest of its bottom's near and far edges to the highest of its top's. Seen from above, a bowl's box in
    the image covers its rim's far side too - what a ground-truth box (and the calibration's "20 px tall") measures;
    the vertical side alone made 28-px bowls and 26-px caps "too small to detect" (tabletop 05)."""
    near = max(distance - radius, 1e-3)
    far = distance + radius
    return max(_atan2(top, near), _atan2(top, far)) - min(_atan2(bottom, near), _atan2(bottom, far))


# rows of the per-object terms of the view's occlusion test (_apply_view)
_BEARING, _OCCLUDER_DISTANCE, _TARGET_DISTANCE, _REACH, _SLACK, _OWN, _SLOPE, _HALF_WIDTH, _BOTTOM, _TOP = range(10)


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _apply_view(n_objects, terms, visible, distance, object_known, object_z, object_bottom, object_top, object_radius,
                camera_z, slope_low, slope_high, min_height, n_bins, inv_bin, occluders, hidden):
    """Clear ``visible`` for the ``n_objects`` objects outside the image vertically or hidden behind a nearer one.
    ``slope_low``, ``slope_high`` (bins,): the tangents of the image's elevation span at each bearing bin.
    ``terms`` (10, padded): row ``_BEARING`` the objects' bearings, the others scratch; ``distance`` (squared on
    entry, the distance on return), ``visible``, ``hidden`` (scratch) and the objects' ``object_*``: padded to whole
    vectors (bearing, distance and radius 0, not known). ``occluders``: the objects that can hide another from the
    particle's position, ascending (``occluder_cells``: those of its cell, a superset of the ones that pass the pair
    test below, so that the result is that of testing every object).

    Every loop runs over whole vectors without a branch (SIMD): branches on random bearings mispredict, and a
    panorama sees nearly every object. One short loop per term, and the occluder loop reads one array and writes one:
    LLVM vectorises a loop only while it needs few run-time alias checks (one loop filling every term ran scalar, its
    selects as mispredicted branches, ~4x slower).
    """
    padded = terms.shape[1]
    bearing = terms[_BEARING]
    for k in range(padded):
        distance[k] = math.sqrt(distance[k])
    for k in range(n_objects):  # used only for the objects whose height is known
        b = int(bearing[k] + 0.5)
        b = b - n_bins if b >= n_bins else b
        # its centre's elevation atan(rise / distance) within the span iff its slope is within the span's tangents
        rise = object_z[k] - camera_z
        inside = (rise >= slope_low[b] * distance[k]) & (rise <= slope_high[b] * distance[k])
        visible[k] = visible[k] & (inside | ~object_known[k])
    if min_height > 0.0:
        for k in range(n_objects):
            if visible[k] and object_known[k] and _apparent_height(
                    object_top[k] - camera_z, object_bottom[k] - camera_z, distance[k], object_radius[k]) < min_height:
                visible[k] = False
    # only objects in view hide or are hidden: one not in view is farther than every target as an occluder (finite:
    # fastmath assumes no inf) and nearer than every occluder as a target
    occluder_distance = terms[_OCCLUDER_DISTANCE]
    for k in range(padded):
        occluder_distance[k] = distance[k] if visible[k] & object_known[k] else 1e300
    target_distance = terms[_TARGET_DISTANCE]
    for k in range(padded):
        target_distance[k] = distance[k] if visible[k] & object_known[k] else -1.0
    # A nearer object o hides k only if their bearings' gap d is at most h + (1 - 2 s) own, h o's core half-width, s
    # OCCLUDED_SHARE (covered below >= 2 s own: covered <= h - d + own when d - own >= -h, else covered <= 2 h and
    # d < own - h); h and own are at most their bounds r / distance in bins (atan x <= x; the margin covers _atan2's
    # error). With s = 1/2: k's centre lies within o's core.
    reach = terms[_REACH]
    for k in range(padded):
        reach[k] = OCCLUDER_CORE * (object_radius[k] / max(distance[k], 1e-300) * inv_bin) + 1e-5
    slack = terms[_SLACK]
    for k in range(padded):
        slack[k] = TARGET_SLACK * (object_radius[k] / max(distance[k], 1e-300) * inv_bin)
    # as a target: its half-width (bins) and its centre's elevation as a slope (tan); as an occluder: its core
    # half-width (bins) and its bottom's and top's elevations as slopes (an elevation is inside iff its slope is,
    # which spares two arctangents)
    own = terms[_OWN]
    for k in range(padded):
        own[k] = _atan2(object_radius[k], distance[k]) * inv_bin
    slope = terms[_SLOPE]
    for k in range(padded):
        slope[k] = (object_z[k] - camera_z) / max(distance[k], 1e-300)
    half_width = terms[_HALF_WIDTH]
    for k in range(padded):
        half_width[k] = _atan2(OCCLUDER_CORE * object_radius[k], distance[k]) * inv_bin
    bottom = terms[_BOTTOM]
    for k in range(padded):
        bottom[k] = (object_bottom[k] - camera_z) * (1.0 / max(distance[k], 1e-300))
    top = terms[_TOP]
    for k in range(padded):
        top[k] = (object_top[k] - camera_z) * (1.0 / max(distance[k], 1e-300))
    for k in range(padded):
        hidden[k] = False
    for q in range(occluders.shape[0]):
        o = occluders[q]
        distance_o = terms[_OCCLUDER_DISTANCE, o]
        bearing_o = terms[_BEARING, o]
        reach_o = terms[_REACH, o]
        half_width_o = terms[_HALF_WIDTH, o]
        bottom_o = terms[_BOTTOM, o]
        top_o = terms[_TOP, o]
        for k in range(padded):
            # the pair test, then: hidden when a nearer object covers at least half of its width (OCCLUDED_SHARE)
            # at its centre's elevation - a can in front of a bowl leaves most of the bowl in view
            d = abs(terms[_BEARING, k] - bearing_o)
            d = min(d, n_bins - d)
            own_k = terms[_OWN, k]
            slope_k = terms[_SLOPE, k]
            covered = min(d + own_k, half_width_o) - max(d - own_k, -half_width_o)
            hidden[k] |= ((distance_o < terms[_TARGET_DISTANCE, k]) & (d < reach_o + terms[_SLACK, k])
                          & (covered >= 2.0 * OCCLUDED_SHARE * own_k) & (bottom_o <= slope_k) & (slope_k <= top_o))
    for k in range(n_objects):
        visible[k] = visible[k] & ~hidden[k]


@numba.njit(cache=True, nogil=True)
def occluder_cells(object_x, object_y, object_radius, object_known, max_range, x0, y0, cell_size, cells_x, cells_y):
    """(offsets, occluders): the objects that can hide another from somewhere in each cell of a grid of ``cells_x``
    x ``cells_y`` cells of ``cell_size`` from (x0, y0), cells in rows of x (score_particles' view): cell c's are
    ``occluders[offsets[c]:offsets[c + 1]]``, ascending; after the last cell, every object whose height is known
    (for positions beyond the grid).

    Object o is listed when a position p in the cell may pass ``_apply_view``'s pair test with some target j: both
    known and within ``max_range``, o nearer, and j's bearing within o's core reach plus j's slack. Over the cell
    (centre c, circumradius ρ) |p - k| lies within D_k ± ρ and the direction to k within asin(ρ / D_k) of c's, so o
    is left out only when for every j D_o - ρ > D_j + ρ or the gap seen from c, less both angles, exceeds the reach
    at distances D_o - ρ and D_j - ρ (plus a margin over the kernel's 1e-5 bins, < 2e-5 rad, and its arctangents'
    error, < 1e-7 rad). The lists then hold every object that passes the pair test, and the kernel's result is that
    of testing them all (tests/localization/test_perception_fast.py checks both).
    """
    n = object_x.shape[0]
    n_cells = cells_x * cells_y
    # ρ widened for the rounding of a position into its cell
    scale = abs(x0) + abs(y0) + (cells_x + cells_y) * cell_size + 1.0
    rho = cell_size * math.sqrt(0.5) * (1.0 + 1e-9) + 1e-9 * scale
    margin = 1e-4
    known = np.empty(n, np.int64)
    n_known = 0
    for k in range(n):
        known[n_known] = k
        n_known += object_known[k]
    offsets = np.empty(n_cells + 2, np.int32)
    occluders = np.empty(n_cells * n_known + n_known, np.int32)
    reach_distance = np.empty(n)
    angle = np.empty(n)
    spread = np.empty(n)
    in_range = np.empty(n, np.bool_)
    total = 0
    for cell in range(n_cells):
        offsets[cell] = total
        cx = x0 + (cell % cells_x + 0.5) * cell_size
        cy = y0 + (cell // cells_x + 0.5) * cell_size
        for a in range(n_known):
            k = known[a]
            dx = object_x[k] - cx
            dy = object_y[k] - cy
            distance = math.sqrt(dx * dx + dy * dy)
            angle[k] = math.atan2(dy, dx)
            near = distance <= rho
            spread[k] = math.pi if near else math.asin(rho / distance)
            reach_distance[k] = distance - rho  # <= 0: the object may be right there
            in_range[k] = distance - rho <= max_range
        for a in range(n_known):
            o = known[a]
            if not in_range[o]:
                continue
            listed = reach_distance[o] <= 0.0
            for b in range(n_known):
                j = known[b]
                if listed:
                    break
                if j == o or not in_range[j] or reach_distance[o] > reach_distance[j] + 2.0 * rho:
                    continue
                gap = abs(angle[o] - angle[j])
                gap = min(gap, 2.0 * math.pi - gap) - spread[o] - spread[j]
                reach = OCCLUDER_CORE * object_radius[o] / reach_distance[o] + margin
                if TARGET_SLACK > 0.0:
                    reach += (TARGET_SLACK * object_radius[j] / reach_distance[j] if reach_distance[j] > 0.0
                              else np.inf)
                listed = gap <= reach
            if listed:
                occluders[total] = o
                total += 1
    offsets[n_cells] = total
    for a in range(n_known):
        occluders[total] = known[a]
        total += 1
    offsets[n_cells + 1] = total
    return offsets, occluders[:total].copy()


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _share(distance, log_ratio, sigma2):
    """How far (bins) an instance's share reaches towards a neighbour ``distance`` bins away, ``log_ratio`` =
    ln(π_self / π_neighbour): where the two scaled Gaussians cross. Coincident instances: the likelier owns all,
    equal ones split at the shared bearing."""
    if log_ratio == 0.0:  # equally likely (every object of a surveyed map): halfway
        return 0.5 * distance
    if distance > 0.0:
        return 0.5 * distance + sigma2 * log_ratio / distance
    if log_ratio > 0.0:
        return np.inf
    return -np.inf


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _share_entries(table, u, left, right, sub, inv_sub, half_bins, n_fine, k_count, entries):
    """Where the terms of the bins (u - left, u + right] that an instance at continuous bin ``u`` owns are read in
    the flattened tables (laid out (table, column, bearing)), and how they combine: entries = the flat indices of
    [bearing f0 at its first and last column, bearing f1 at its first and last column] for the two tabulated
    bearings f0, f1 = f0 + 1 around u; returns the interpolation weight of f1. Column 0 of a table is a zero, so a
    bearing's range sum is one difference of clamped columns; ``base`` is the unwrapped bin of a bearing's first
    column; ``k_count``: the columns (K + 1)."""
    first_bin = int(math.floor(u - left)) + 1
    last_bin = int(math.floor(u + right))
    fine = u * sub
    f0 = int(fine)
    f1 = f0 + 1
    base0 = int((f0 + 0.5) * inv_sub) - half_bins
    base1 = int((f1 + 0.5) * inv_sub) - half_bins
    if f1 == n_fine:
        f1 = 0
    k_max = k_count - 1
    low0 = min(max(first_bin - base0, 0), k_max)
    high0 = min(max(last_bin - base0 + 1, low0), k_max)
    low1 = min(max(first_bin - base1, 0), k_max)
    high1 = min(max(last_bin - base1 + 1, low1), k_max)
    start = table * k_count
    entries[0] = (start + low0) * n_fine + f0
    entries[1] = (start + high0) * n_fine + f0
    entries[2] = (start + low1) * n_fine + f1
    entries[3] = (start + high1) * n_fine + f1
    return fine - f0


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _cell_of(x, y, x0, y0, inv_cell, cells_x, cells_y):
    """The grid cell of (x, y) (score_particles' occluder_cells grid), cells_x * cells_y beyond the grid."""
    column = (x - x0) * inv_cell
    row = (y - y0) * inv_cell
    inside = (column >= 0.0) & (column < cells_x) & (row >= 0.0) & (row < cells_y)
    return (int(row) * cells_x + int(column)) if inside else cells_x * cells_y


@numba.njit(cache=True, fastmath=True, nogil=True)
def score_particles(states, object_x, object_y, class_start, class_stop, tables, object_table, object_log_existence,
                    class_alike, sigma2, n_bins, sub, half_bins, max_range, view, object_known, object_z, object_bottom,
                    object_top, object_radius, camera_z, elevation_low, elevation_high, min_height, cell_x0,
                    cell_y0, cell_size, cells_x, cells_y, cell_offsets, cell_occluders, out):
    """For each particle, Σ_c Σ_j term(c, j) with the max over instances by nearest instance. Writes ``out[i]``.

    Objects are sorted by class: class c holds objects class_start[c] .. class_stop[c] - 1; object k's terms are
    ``tables[object_table[k]]`` and its existence ln π_k ``object_log_existence[k]`` (``sigma2``: σ² in bins²,
    where scaled Gaussians cross; ``class_alike[c]``: class c's objects share one existence, so the split is
    halfway). With ``view``, an object
    is expected only if its centre's elevation seen from the camera (at height ``camera_z``) lies within the image's
    elevation span at its bearing bin (``elevation_low/high``), and no nearer object hides it: the core of the
    nearer one's bearing span (``OCCLUDER_CORE`` x ``object_radius``) covers at least ``OCCLUDED_SHARE`` of its own and its centre ray passes between
    the nearer one's ``object_bottom`` and ``object_top`` (elevation); objects that look shorter than ``min_height``
    (radians) are not expected either. Objects whose height is unknown (``object_known`` False) are neither checked nor hide anything.
    The objects that can hide another are looked up in a grid of the map's cells (``occluder_cells``: ``cells_x`` x
    ``cells_y`` cells of ``cell_size`` from (``cell_x0``, ``cell_y0``), the list of cell c ``cell_occluders
    [cell_offsets[c]:cell_offsets[c + 1]]``, cells in rows of x; beyond the grid, the list after the last cell).
    """
    n_particles = states.shape[0]
    n_classes = class_start.shape[0]
    n_objects = object_x.shape[0]
    n_fine = n_bins * sub
    inv_bin = n_bins / (2.0 * math.pi)
    inv_n_bins = 1.0 / n_bins
    inv_sub = 1.0 / sub
    range2 = max_range * max_range if math.isfinite(max_range) else np.inf
    padded = (n_objects + 7) & ~7  # the view's tests run over whole vectors: what follows stays finite
    terms = np.zeros((10, padded))
    bearing = terms[_BEARING]
    visible = np.zeros(padded, dtype=np.bool_)
    distance = np.zeros(padded)
    known = np.zeros(padded, dtype=np.bool_)
    z = np.zeros(padded)
    bottom = np.zeros(padded)
    top = np.zeros(padded)
    radius = np.zeros(padded)
    known[:n_objects] = object_known
    z[:n_objects] = object_z
    bottom[:n_objects] = object_bottom
    top[:n_objects] = object_top
    radius[:n_objects] = object_radius
    hidden = np.zeros(padded, dtype=np.bool_)
    # the spans' tangents (tan(±π/2) is finite in float64: 1.6e16), so that an elevation test is a product
    slope_low = np.tan(elevation_low) if view else elevation_low
    slope_high = np.tan(elevation_high) if view else elevation_high
    inv_cell = 1.0 / cell_size
    positions = np.empty(max(n_objects, 1))
    members = np.empty(max(n_objects, 1), dtype=np.int64)
    reach = 0.5 * n_bins  # a share never reaches further than half the circle (nor, in effect, beyond the window)
    # Each particle's shares are located first and their table entries prefetched, all together, then read while
    # the next particle's shares are located: the tables (MBs) do not stay in cache, and misses issued back to back
    # overlap where reads interleaved with the geometry wait one by one (the same sums in the same order).
    k_count = tables.shape[1]
    flat = tables.reshape(-1)
    buffered_entries = np.empty((2, max(n_objects, 1), 4), dtype=np.int64)
    buffered_weight = np.empty((2, max(n_objects, 1)))
    values = np.empty((max(n_objects, 1), 4))
    pending = 0  # shares of the previous particle, located and prefetched, not yet read
    for i in range(n_particles):
        entries = buffered_entries[i & 1]
        weight = buffered_weight[i & 1]
        x = states[i, 0]
        y = states[i, 1]
        heading = states[i, 2]
        # every object's continuous bin coordinate (bin j's centre at u = j, u in [0, n_bins)); no branches here
        for k in range(n_objects):
            dx = object_x[k] - x
            dy = object_y[k] - y
            u = (_atan2(dy, dx) - heading + math.pi) * inv_bin - 0.5
            u -= n_bins * math.floor(u * inv_n_bins)
            bearing[k] = min(max(u, 0.0), n_bins - 1e-9)
            distance[k] = dx * dx + dy * dy
            visible[k] = distance[k] <= range2
        if view:
            # the grid's entries of the next two particles asked for ahead (random cells of a fine grid miss)
            if i + 2 < n_particles:
                _prefetch(cell_offsets, _cell_of(states[i + 2, 0], states[i + 2, 1], cell_x0, cell_y0, inv_cell,
                                                 cells_x, cells_y))
            if i + 1 < n_particles:
                _prefetch(cell_occluders, cell_offsets[_cell_of(states[i + 1, 0], states[i + 1, 1], cell_x0, cell_y0,
                                                                inv_cell, cells_x, cells_y)])
            cell = _cell_of(x, y, cell_x0, cell_y0, inv_cell, cells_x, cells_y)
            _apply_view(n_objects, terms, visible, distance, known, z, bottom, top, radius, camera_z, slope_low,
                        slope_high, min_height, n_bins, inv_bin,
                        cell_occluders[cell_offsets[cell]:cell_offsets[cell + 1]], hidden)
        n_shares = 0
        for c in range(n_classes):
            alike = class_alike[c]
            m = 0
            for k in range(class_start[c], class_stop[c]):  # no branches: visibility is random along a cloud
                positions[m] = bearing[k]
                members[m] = k
                m += visible[k]
            if alike:  # one existence for the whole class (every surveyed map): halfway to the nearest
                table = object_table[class_start[c]]
                for a in range(m):
                    u = positions[a]
                    # distances to the nearest instance on either side (ties between coincident ones by index)
                    left = float(n_bins)
                    right = float(n_bins)
                    # (d + 0 is d, bit for bit, but for -0: then d <= 0 and the circle is added; the wrap as
                    # arithmetic, not a branch: random signs mispredicted it, ~30 % of weighing without a view)
                    for b in range(a):
                        d = positions[b] - u
                        d += n_bins * (d <= 0.0)
                        right = min(right, d)
                        left = min(left, n_bins - d)
                    for b in range(a + 1, m):
                        d = positions[b] - u
                        d += n_bins * (d < 0.0)
                        right = min(right, d)
                        left = min(left, n_bins - d)
                    weight[n_shares] = _share_entries(table, u, 0.5 * left, 0.5 * right, sub, inv_sub, half_bins,
                                                      n_fine, k_count, entries[n_shares])
                    n_shares += 1
            else:
                for a in range(m):
                    u = positions[a]
                    log_a = object_log_existence[members[a]]
                    # how far this instance's share reaches on either side: to where the next instance's scaled
                    # Gaussian takes over (ties between coincident equally likely ones by index)
                    left = reach
                    right = reach
                    for b in range(m):
                        if b == a:
                            continue
                        d = positions[b] - u
                        if d < 0.0 or (d == 0.0 and b < a):
                            d += n_bins
                        log_ratio = log_a - object_log_existence[members[b]]
                        right = min(right, _share(d, log_ratio, sigma2))
                        left = min(left, _share(n_bins - d, log_ratio, sigma2))
                    weight[n_shares] = _share_entries(object_table[members[a]], u, max(left, -reach),
                                                      max(right, -reach), sub, inv_sub, half_bins, n_fine, k_count,
                                                      entries[n_shares])
                    n_shares += 1
        for s in range(n_shares):
            for q in range(4):
                _prefetch(flat, entries[s, q])
        if i:
            out[i - 1] = _sum_shares(flat, buffered_entries[(i - 1) & 1], buffered_weight[(i - 1) & 1], pending,
                                     values)
        pending = n_shares
    if n_particles:
        last = (n_particles - 1) & 1
        out[n_particles - 1] = _sum_shares(flat, buffered_entries[last], buffered_weight[last], pending, values)
    return out


@numba.njit(cache=True, fastmath=True, nogil=True, inline="always")
def _sum_shares(flat, entries, weight, n_shares, values):
    """A particle's log-likelihood from its shares (score_particles): each share's sum at its two tabulated bearings
    f0, f1 (differences of the entries' table values), interpolated by its weight. ``values``: scratch."""
    for s in range(n_shares):
        for q in range(4):
            values[s, q] = flat[entries[s, q]]
    total = 0.0
    for s in range(n_shares):
        v0 = values[s, 1] - values[s, 0]
        v1 = values[s, 3] - values[s, 2]
        total += v0 + (v1 - v0) * weight[s]
    return total


@numba.njit(cache=True, nogil=True, inline="always")
def _wrap_angle(angle):
    """(angle + π) % 2π - π with the bits of numpy's and Python's floor modulo, without its fmod (~20 ns) for the
    angles the filter wraps (|angle + π| < 4π): fmod(a, 2π) is a itself on [0, 2π) and a - 2π exactly on [2π, 4π)
    (Sterbenz), and on [-2π, 0) the floor modulo adds 2π to a, rounded, as here. Others take the modulo."""
    two_pi = 2.0 * math.pi
    shifted = angle + math.pi
    if shifted >= 0.0 and shifted < two_pi:
        wrapped = shifted
    elif shifted >= two_pi and shifted < 2.0 * two_pi:
        wrapped = shifted - two_pi
    elif shifted < 0.0 and shifted >= -two_pi:
        wrapped = shifted + two_pi
    else:
        wrapped = shifted % two_pi
    return wrapped - math.pi


@numba.njit(cache=True, nogil=True)
def differential_drive(states, speed_noise, turn_noise, v, omega, dt, out):
    """Eq. 4.5 for each particle (motion.DifferentialDriveModel) in one pass, with the noise drawn by numpy: the
    same operations in the same order as the numpy expressions, so the same bits (no fastmath)."""
    for i in range(states.shape[0]):
        speed = v + speed_noise[i]
        turn = (omega + turn_noise[i]) * dt
        heading = states[i, 2] + turn / 2
        out[i, 0] = states[i, 0] + speed * dt * math.cos(heading)
        out[i, 1] = states[i, 1] + speed * dt * math.sin(heading)
        out[i, 2] = _wrap_angle(states[i, 2] + turn)


@numba.njit(cache=True, nogil=True)
def omni_drive(states, dx, dy, dtheta, dx_noise, dy_noise, dtheta_noise, out):
    """Body-frame increments with noise for each particle (motion.OmniDriveModel) in one pass, as
    ``differential_drive``."""
    for i in range(states.shape[0]):
        step_x = dx + dx_noise[i]
        step_y = dy + dy_noise[i]
        c = math.cos(states[i, 2])
        s = math.sin(states[i, 2])
        out[i, 0] = states[i, 0] + c * step_x - s * step_y
        out[i, 1] = states[i, 1] + s * step_x + c * step_y
        out[i, 2] = _wrap_angle(states[i, 2] + (dtheta + dtheta_noise[i]))


@numba.njit(cache=True, nogil=True)
def outlier_mixture(log_likelihood, log_inlier, log_outlier, out):
    """out = logaddexp(``log_inlier`` + ℓ - max ℓ, ``log_outlier``) where ℓ is finite, ℓ elsewhere (filter.
    outlier_mixture) in one pass after the max, the same bits as numpy's (its logaddexp: libm's exp and log1p, as
    here). Returns whether any ℓ was finite (out untouched otherwise)."""
    top = -np.inf
    found = False
    for i in range(log_likelihood.shape[0]):
        value = log_likelihood[i]
        if math.isfinite(value):
            top = max(top, value)
            found = True
    if not found:
        return False
    # below this, exp(x - b) < |b| e^-40: log1p of it is ~50x below half an ulp of b, so the sum is b (no exp, no log)
    negligible = log_outlier + math.log(abs(log_outlier)) - 40.0 if log_outlier != 0.0 else -np.inf
    for i in range(log_likelihood.shape[0]):
        value = log_likelihood[i]
        if not math.isfinite(value):
            out[i] = value
            continue
        x = log_inlier + (value - top)
        if x < negligible:
            out[i] = log_outlier
        elif x == log_outlier:
            out[i] = x + math.log(2.0)
        elif x > log_outlier:
            out[i] = x + math.log1p(math.exp(log_outlier - x))
        else:
            out[i] = log_outlier + math.log1p(math.exp(x - log_outlier))
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _inside(x, y, bounds, vertices, starts):
    """Whether (x, y) lies in the free space (``FreeSpace.contains``): inside the bounds and, when there are
    polygons (``starts``: each polygon's first vertex, then the end), inside one of them (even-odd rule, crossings
    of a ray towards +x, as ``geometry.inside_polygon``)."""
    if not (x >= bounds[0, 0] and x <= bounds[1, 0] and y >= bounds[0, 1] and y <= bounds[1, 1]):
        return False
    if starts.shape[0] < 2:
        return True
    for polygon in range(starts.shape[0] - 1):
        first, stop = starts[polygon], starts[polygon + 1]
        odd = False
        for e in range(first, stop):
            f = e + 1 if e + 1 < stop else first
            ax, ay, bx, by = vertices[e, 0], vertices[e, 1], vertices[f, 0], vertices[f, 1]
            if (ay > y) != (by > y) and x < ax + (y - ay) * (bx - ax) / (by - ay):
                odd = not odd
        if odd:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def inside_free_space(points, bounds, vertices, starts, out):
    """out[i] = whether points[i] (x, y) lies in the free space (see ``_inside``)."""
    if starts.shape[0] < 2:  # the bounds alone: without a branch (SIMD), 30x faster than through _inside
        for i in range(points.shape[0]):
            x = points[i, 0]
            y = points[i, 1]
            out[i] = (x >= bounds[0, 0]) & (x <= bounds[1, 0]) & (y >= bounds[0, 1]) & (y <= bounds[1, 1])
        return
    for i in range(points.shape[0]):
        out[i] = _inside(points[i, 0], points[i, 1], bounds, vertices, starts)


@numba.njit(cache=True, nogil=True)
def resect(first_xy, delta, first, second, peak_cos, peak_sin, todo, heading, max_range, bounds, vertices, starts, out,
           done):
    """One round of resection for ``perception.sample_poses``: for each i with j = todo[i], the position p that sees
    the instances A = first_xy[j] and B = A - delta[j] at the bearings b1, b2 of peaks first[j] and second[j] (of
    cosines ``peak_cos``, sines ``peak_sin``) from heading[i]: p + t1 u1 = A, p + t2 u2 = B (u = the rays at heading +
    bearing, by the angle-sum identities), a 2 x 2 system with det = sin(alpha). A solution with both instances ahead
    (t > 0), within ``max_range`` and in the free space is accepted: out[j] = (p, heading[i]), done[j] = True. The
    others stay in ``todo``, compacted in order; returns their count."""
    remaining = 0
    for i in range(todo.shape[0]):
        j = todo[i]
        ch = math.cos(heading[i])
        sh = math.sin(heading[i])
        c1 = peak_cos[first[j]]
        s1 = peak_sin[first[j]]
        c2 = peak_cos[second[j]]
        s2 = peak_sin[second[j]]
        u1x = ch * c1 - sh * s1
        u1y = sh * c1 + ch * s1
        u2x = ch * c2 - sh * s2
        u2y = sh * c2 + ch * s2
        dx = delta[j, 0]
        dy = delta[j, 1]
        det = -u1x * u2y + u1y * u2x
        safe = det if abs(det) > 1e-9 else 1.0
        t1 = (-dx * u2y + dy * u2x) / safe
        t2 = (u1x * dy - u1y * dx) / safe
        x = first_xy[j, 0] - t1 * u1x
        y = first_xy[j, 1] - t1 * u1y
        if (abs(det) > 1e-9 and t1 > 0 and t2 > 0 and t1 <= max_range and t2 <= max_range
                and _inside(x, y, bounds, vertices, starts)):
            out[j, 0] = x
            out[j, 1] = y
            out[j, 2] = heading[i]
            done[j] = True
        else:
            todo[remaining] = j
            remaining += 1
    return remaining


@numba.njit(cache=True, nogil=True)
def resect_rounds(rng, rounds, first_xy, delta, first, second, peak_cos, peak_sin, todo, max_range, bounds, vertices,
                  starts, out, done):
    """Up to ``rounds`` rounds of ``resect`` on ``todo``, each with headings drawn uniformly in [-π, π) by ``rng``
    (numba's Generator draws what numpy's would, from the same state); returns how many stay undone (at the front
    of ``todo``)."""
    remaining = todo.shape[0]
    for _ in range(rounds):
        if remaining == 0:
            break
        heading = rng.uniform(-np.pi, np.pi, remaining)
        remaining = resect(first_xy, delta, first, second, peak_cos, peak_sin, todo[:remaining], heading, max_range,
                           bounds, vertices, starts, out, done)
    return remaining


@numba.njit(cache=True, nogil=True, inline="always")
def _draw_peaks(cdf, uniform, out):
    """out[i] = the first index whose cumulative weight exceeds uniform[i] (np.searchsorted(cdf, uniform, "right"):
    rng.choice's draws by weight)."""
    for i in range(uniform.shape[0]):
        low = 0
        high = cdf.shape[0]
        while low < high:
            middle = (low + high) // 2
            if cdf[middle] <= uniform[i]:
                low = middle + 1
            else:
                high = middle
        out[i] = low


@numba.njit(cache=True, nogil=True, inline="always")
def _draw_instances(rng, choice, counts, offsets, flat, object_xy, objects, xy):
    """A random mapped instance of each chosen peak's class (``rng.integers(0, counts[choice])`` element by element:
    numpy's draws for an array of bounds), its index into ``objects`` and its position into ``xy``."""
    for i in range(choice.shape[0]):
        c = choice[i]
        objects[i] = flat[offsets[c] + rng.integers(0, counts[c])]
        xy[i, 0] = object_xy[objects[i], 0]
        xy[i, 1] = object_xy[objects[i], 1]


@numba.njit(cache=True, nogil=True)
def aligned_poses(rng, cdf, peak_bearing, counts, offsets, flat, object_xy, min_separation, max_range, bounds,
                  vertices, starts, first, first_xy, out, done):
    """The draws and the resection of ``perception.sample_poses`` for ``first.shape[0]`` poses (see there), drawn
    by ``rng`` in numpy's order (numba's Generator draws numpy's numbers from the same state): the first peak of
    each pose (``first``, by the peaks' cumulative weights ``cdf``) and its instance's position (``first_xy``), a
    second peak other than the first (8 tries), its instance, and for the pairs at least ``min_separation`` apart
    (radians) on two different instances, up to 8 rounds of ``resect``: out[j], done[j] for the poses found."""
    n = first.shape[0]
    _draw_peaks(cdf, rng.random(n), first)
    first_object = np.empty(n, np.int64)
    _draw_instances(rng, first, counts, offsets, flat, object_xy, first_object, first_xy)
    if cdf.shape[0] < 2:
        return
    second = np.empty(n, np.int64)
    _draw_peaks(cdf, rng.random(n), second)
    same = np.empty(n, np.int64)
    redrawn = np.empty(n, np.int64)
    for _ in range(8):  # another detection than the first
        n_same = 0
        for i in range(n):
            same[n_same] = i
            n_same += second[i] == first[i]
        if n_same == 0:
            break
        _draw_peaks(cdf, rng.random(n_same), redrawn[:n_same])
        for q in range(n_same):
            second[same[q]] = redrawn[q]
    second_object = np.empty(n, np.int64)
    second_xy = np.empty((n, 2))
    _draw_instances(rng, second, counts, offsets, flat, object_xy, second_object, second_xy)
    todo = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        alpha = (peak_bearing[first[i]] - peak_bearing[second[i]] + np.pi) % (2 * np.pi) - np.pi
        todo[count] = i
        count += (abs(alpha) >= min_separation) & (first_object[i] != second_object[i])
    delta = first_xy - second_xy  # t1 u1 - t2 u2 = A - B
    # Resection: with a heading h, the rays at h + bearing reach both instances (resect); up to 8 headings until
    # the position lies ahead of both rays, in the free space
    resect_rounds(rng, 8, first_xy, delta, first, second, np.cos(peak_bearing), np.sin(peak_bearing), todo[:count],
                  max_range, bounds, vertices, starts, out, done)


@numba.njit(cache=True, nogil=True)
def strongest_peaks(scores, observed, separation, floor, found, weight, index):
    """For ``perception._detections``: per row of ``scores`` (classes x bins), up to ``found.shape[1]`` peaks,
    strongest first, while above ``floor[r]``: the first maximum over the observed bins not yet suppressed (found,
    value - floor, its bin), each suppressing the bins within ``separation`` of it."""
    n_rows, n_bins = scores.shape
    row = np.empty(n_bins)
    for r in range(n_rows):
        for b in range(n_bins):
            row[b] = scores[r, b] if observed[b] else -np.inf
        for peak in range(found.shape[1]):
            best = 0
            for b in range(1, n_bins):  # the first maximum, as np.argmax
                if row[b] > row[best]:
                    best = b
            value = row[best]
            if not value > floor[r]:
                break
            found[r, peak] = True
            weight[r, peak] = value - floor[r]
            index[r, peak] = best
            for offset in range(-separation, separation + 1):
                row[(best + offset) % n_bins] = -np.inf


@numba.njit(cache=True, nogil=True)
def sines_cosines(theta, sines, cosines):
    """sines, cosines = np.sin(theta), np.cos(theta), the same bits (both are libm's here, checked in
    tests/localization/test_kernels_exact.py) in one pass, 1.6x faster than numpy's two."""
    for i in range(theta.shape[0]):
        sines[i] = math.sin(theta[i])
        cosines[i] = math.cos(theta[i])


@numba.njit(cache=True, nogil=True)
def pose_moments(states, weights, sin_theta, cos_theta, labels, label, mean, covariance):
    """Weighted mean (circular for θ) and covariance of the poses (N, 3) whose ``labels`` equal ``label`` (all of them
    when ``label`` < 0), into ``mean`` (3,) and ``covariance`` (3, 3); θ residuals wrapped to [-π, π). ``sin_theta``,
    ``cos_theta``: of each pose's θ (numpy's are SIMD). Returns the total weight (0: nothing written)."""
    total = 0.0
    sx = 0.0
    sy = 0.0
    ss = 0.0
    sc = 0.0
    for i in range(states.shape[0]):
        if label >= 0 and labels[i] != label:
            continue
        w = weights[i]
        total += w
        sx += w * states[i, 0]
        sy += w * states[i, 1]
        ss += w * sin_theta[i]
        sc += w * cos_theta[i]
    if not total > 0.0:
        return 0.0
    mean[0] = sx / total
    mean[1] = sy / total
    mean[2] = math.atan2(ss / total, sc / total)
    cxx = cxy = cxt = cyy = cyt = ctt = 0.0
    for i in range(states.shape[0]):
        if label >= 0 and labels[i] != label:
            continue
        w = weights[i] / total
        rx = states[i, 0] - mean[0]
        ry = states[i, 1] - mean[1]
        rt = _wrap_angle(states[i, 2] - mean[2])
        cxx += w * rx * rx
        cxy += w * rx * ry
        cxt += w * rx * rt
        cyy += w * ry * ry
        cyt += w * ry * rt
        ctt += w * rt * rt
    covariance[0, 0] = cxx
    covariance[0, 1] = covariance[1, 0] = cxy
    covariance[0, 2] = covariance[2, 0] = cxt
    covariance[1, 1] = cyy
    covariance[1, 2] = covariance[2, 1] = cyt
    covariance[2, 2] = ctt
    return total


@numba.njit(cache=True, nogil=True)
def cluster_labels(states, cell, max_cells, labels):
    """Each pose's hypothesis: the 8-connected occupied cells of an xy grid of ``cell`` metres, numbered in raster
    order of their first cell (as ``scipy.ndimage.label`` numbers them), into ``labels``; returns their count. A
    cloud spread over more than ``max_cells`` cells is one hypothesis."""
    n = states.shape[0]
    if n == 0:
        return 0
    cells = np.empty((n, 2), np.int64)
    low_i = low_j = np.iinfo(np.int64).max
    high_i = high_j = np.iinfo(np.int64).min
    for p in range(n):
        i = int(math.floor(states[p, 0] / cell))
        j = int(math.floor(states[p, 1] / cell))
        cells[p, 0] = i
        cells[p, 1] = j
        low_i = min(low_i, i)
        low_j = min(low_j, j)
        high_i = max(high_i, i)
        high_j = max(high_j, j)
    rows = high_i - low_i + 1
    cols = high_j - low_j + 1
    if rows * cols > max_cells:
        labels[:] = 0
        return 1
    grid = np.zeros((rows, cols), np.int64)  # 0 empty, -1 occupied, > 0 its label
    for p in range(n):
        grid[cells[p, 0] - low_i, cells[p, 1] - low_j] = -1
    count = 0
    stack = np.empty(rows * cols, np.int64)
    for start in range(rows * cols):
        if grid.flat[start] != -1:
            continue
        count += 1
        grid.flat[start] = count
        stack[0] = start
        top = 1
        while top:
            top -= 1
            i = stack[top] // cols
            j = stack[top] - i * cols
            for a in range(max(i - 1, 0), min(i + 2, rows)):
                for b in range(max(j - 1, 0), min(j + 2, cols)):
                    if grid[a, b] == -1:
                        grid[a, b] = count
                        stack[top] = a * cols + b
                        top += 1
    for p in range(n):
        labels[p] = grid[cells[p, 0] - low_i, cells[p, 1] - low_j] - 1
    return count
