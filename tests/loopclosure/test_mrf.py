"""The MRF on the similarity matrix: exact on trees, batch = incremental, state round trip, smoothing."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from semloc_core.loopclosure.mrf import (
    COUPLINGS,
    DIRECTIONS,
    IncrementalMrf,
    MrfParams,
    Normalization,
    infer_batch,
    infer_cells,
)


def brute_force_max_marginals(M: np.ndarray, params: MrfParams) -> dict:
    """Exact max-marginal log-odds of every live cell of the lattice (eqs. 3.1-3.3), by enumeration."""
    n = M.shape[0]
    F = M.max()
    p = np.clip((M - params.offset) / (F - params.offset), 0, 1)
    live = list(zip(*np.nonzero(np.triu(p > 0, 1))))

    def log_psi_equal(a, b):
        j = np.log(params.alpha) - ((p[a] - p[b]) / params.sigma) ** 2
        return max(j, 0.0) if params.coupling == "attractive" else j

    edges = set()
    for a in live:
        for dk, dl in DIRECTIONS:
            b = (a[0] + dk, a[1] + dl)
            if 0 <= b[0] < n and 0 <= b[1] < n:
                edges.add(tuple(sorted((a, b))))
    states, scores = [], []
    for labels in itertools.product((0, 1), repeat=len(live)):
        label = dict(zip(live, labels))
        total = 0.0
        for cell, x in label.items():
            q = min(p[cell], 1 - 1e-6)
            total += np.log(q) if x else np.log1p(-q)
        for a, b in edges:
            if label.get(a, 0) == label.get(b, 0):
                total += log_psi_equal(a, b)
        states.append(labels)
        scores.append(total)
    states, scores = np.array(states), np.array(scores)
    return {cell: scores[states[:, k] == 1].max() - scores[states[:, k] == 0].max() for k, cell in enumerate(live)}


@pytest.mark.parametrize("coupling", COUPLINGS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bp_is_exact_on_a_tree(coupling, seed):
    """On a tree-structured set of live cells max-product BP converges to the exact max-marginals."""
    rng = np.random.default_rng(seed)
    n = 8
    M = np.zeros((n, n))
    # A diagonal chain and a branch off it: the live cells' neighbourhood graph is a tree.
    for cell in [(0, 3), (1, 4), (2, 5), (3, 6), (4, 7), (0, 5)]:
        M[cell] = rng.uniform(0.05, 1.0)
    params = MrfParams(potential="thesis", sigma=rng.uniform(0.1, 0.4), coupling=coupling, damping=0.0,
                       iterations=60)
    exact = brute_force_max_marginals(M, params)
    result = infer_batch(M, params)
    for cell, value in exact.items():
        assert result.beliefs[cell] == pytest.approx(value, abs=1e-6)
    assert np.all(np.isneginf(result.beliefs[M <= 0]))


def banded_scores(n: int, window: int, seed: int) -> np.ndarray:
    """A similarity matrix with a parallel and an inverse revisit band in noise, like Figure 3.2."""
    rng = np.random.default_rng(seed)
    M = rng.normal(-5.0, 4.0, (n, n))
    bands = ((0.30, 0.55, lambda col: col - int(0.27 * n)), (0.65, 0.85, lambda col: int(1.2 * n) - col))
    for start, end, row_of in bands:
        for col in range(int(start * n), int(end * n)):
            for width in range(-2, 3):
                M[row_of(col) + width, col] = rng.normal(30.0 - 6 * abs(width), 4.0)
    M[np.tril_indices(n, window)] = -np.inf
    return M


def test_batch_matches_cell_form_and_clamps_at_the_offset():
    M = banded_scores(80, 10, 0)
    params = MrfParams(potential="thesis", offset=-2.0)
    result = infer_batch(M, params, window=10)
    rows, cols = np.nonzero(np.isfinite(M))
    cell_beliefs, norm = infer_cells(rows, cols, M[rows, cols], 80, params, window=10)
    assert norm.location + norm.scale == pytest.approx(np.max(M[np.isfinite(M)]))
    assert np.allclose(np.where(np.isfinite(cell_beliefs), cell_beliefs, -1e9),
                       np.where(np.isfinite(result.beliefs[rows, cols]), result.beliefs[rows, cols], -1e9))
    assert np.all(np.isneginf(result.beliefs[M <= -2.0]))


@pytest.mark.parametrize("potential", ["calibrated", "thesis"])
@pytest.mark.parametrize("band", [5, 30])
def test_incremental_equals_batch(band, potential):
    n, window = 200, 10
    M = banded_scores(n, window, 1)
    params = MrfParams(potential=potential, sigma=0.05 if potential == "thesis" else 100.0,
                       alpha=2.0 if potential == "thesis" else 8.0)
    batch = infer_batch(M, params, window=window)
    incremental = IncrementalMrf(params, band=band, normalization=batch.normalization, window=window)
    for j in range(n):
        rows = np.arange(max(0, j - window))
        incremental.add_column(rows, M[rows, j])
    decisions = incremental.dense().decisions
    assert batch.decisions.sum() > 100
    assert np.mean(decisions == batch.decisions) >= 0.995
    both = np.sum(decisions & batch.decisions)
    assert both / np.sum(decisions | batch.decisions) > 0.95


@pytest.mark.parametrize("potential", ["calibrated", "thesis"])
def test_running_normalization_reaches_the_batch_value(potential):
    n, window = 200, 10
    M = banded_scores(n, window, 2)
    params = MrfParams(potential=potential)
    incremental = IncrementalMrf(params, band=30, window=window)
    for j in range(n):
        rows = np.arange(max(0, j - window))
        incremental.add_column(rows, M[rows, j])
    batch = infer_batch(M, params, window=window)
    assert incremental.normalization.location == pytest.approx(batch.normalization.location)
    assert incremental.normalization.scale == pytest.approx(batch.normalization.scale)
    assert np.mean(incremental.dense().decisions == batch.decisions) >= 0.995


def test_state_round_trip_continues_identically():
    n, window = 120, 10
    M = banded_scores(n, window, 3)
    params = MrfParams()
    a = IncrementalMrf(params, band=20, window=window)
    for j in range(70):
        rows = np.arange(max(0, j - window))
        a.add_column(rows, M[rows, j])
    b = IncrementalMrf.from_state(a.state(), params, 20, window)
    for j in range(70, n):
        rows = np.arange(max(0, j - window))
        a.add_column(rows, M[rows, j])
        b.add_column(rows, M[rows, j])
    for x, y in zip(a.cells(), b.cells()):
        assert np.array_equal(x, y)


def test_attractive_coupling_fills_a_gap_in_a_band_but_not_an_isolated_cell():
    """Temporal consistency (§3.4): a weak cell inside a band of similar scores is pulled up by its neighbours;
    the same weak score alone stays below the decision threshold."""
    n = 30
    M = np.zeros((n, n))
    for col in range(10, 25):
        M[col - 8, col] = 0.55
    M[16 - 8, 16] = 0.42  # the gap
    M[2, 28] = 0.42  # isolated
    M[0, 29] = 1.0  # sets F
    params = MrfParams(potential="thesis", sigma=0.5)
    result = infer_batch(M, params)
    assert result.decisions[8, 16]
    assert not result.decisions[2, 28]
    assert all(result.decisions[col - 8, col] for col in range(10, 25))


def test_thesis_coupling_pushes_apart_dissimilar_neighbours():
    """With the coupling as written, alpha*G < 1 rewards different labels: a strong cell next to clamped cells is
    pushed to 1 even when its own potential says 0."""
    n = 10
    M = np.zeros((n, n))
    M[2, 7] = 0.3  # p = 0.3 / 1.0 -> its own log-odds favour 0
    M[0, 9] = 1.0
    thesis = infer_batch(M, MrfParams(potential="thesis", coupling="thesis"))
    attractive = infer_batch(M, MrfParams(potential="thesis", coupling="attractive"))
    assert thesis.decisions[2, 7] and not attractive.decisions[2, 7]


@pytest.mark.parametrize("scale, shift", [(3.0, -40.0), (0.25, 7.0)])
def test_calibrated_potential_ignores_the_units_of_the_score(scale, shift):
    """The calibrated potential sees scores in background deviations: any affine change of the score's units gives
    the same beliefs."""
    M = banded_scores(120, 10, 4)
    params = MrfParams(sigma=3.0, alpha=8.0)
    a = infer_batch(M, params, window=10)
    b = infer_batch(M * scale + shift, params, window=10)
    finite = np.isfinite(a.beliefs)
    assert np.array_equal(finite, np.isfinite(b.beliefs))
    assert np.allclose(a.beliefs[finite], b.beliefs[finite])
    assert a.decisions.sum() > 50


def test_calibrated_band_support_beats_an_isolated_outlier():
    """A long band of moderately high scores (a revisit) is labelled a loop and, after inference, ranks above an
    isolated pair whose raw score is higher."""
    rng = np.random.default_rng(5)
    n = 120
    M = rng.normal(0.0, 1.0, (n, n))
    M[np.tril_indices(n, 10)] = -np.inf
    for col in range(40, 100):
        M[col - 36 : col - 33, col] = 3.5  # 3.5 deviations above the background, 3 wide, over 60 frames
    M[5, 110] = 4.0  # an isolated outlier
    result = infer_batch(M, MrfParams(), window=10)
    band = [result.beliefs[col - 35, col] for col in range(45, 95)]
    assert min(band) > 0
    assert min(band) > result.beliefs[5, 110] + 2.0


def test_unscored_pairs_count_as_background():
    """Engine columns hold only some pairs: an unscored neighbour acts as a background pair (z = 0), a structural
    one (inside the window) as a certain non-loop."""
    params = MrfParams(sigma=100.0, alpha=8.0)
    norm = Normalization(0.0, 1.0)
    lone, _ = infer_cells([10], [40], [2.0], 60, params, norm, window=5)
    theta = params.kappa * (2.0 - params.z0)
    j = np.log(params.alpha) - (2.0 / params.sigma) ** 2  # G(z = 2, z = 0)
    prior = params.prior_theta
    assert lone[0] == pytest.approx(theta + 8 * (max(0.0, prior + j) - max(j, prior)))


def test_input_validation():
    with pytest.raises(ValueError):
        MrfParams(coupling="potts")
    with pytest.raises(ValueError):
        MrfParams(potential="linear")
    with pytest.raises(ValueError):
        infer_batch(np.zeros((3, 4)))
    mrf = IncrementalMrf()
    mrf.add_column([], [])
    with pytest.raises(ValueError, match="earlier"):
        mrf.add_column([1], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        mrf.add_column([0], [np.nan])


@pytest.mark.parametrize("released", [(), (60, 61, 90)])
def test_sorted_beliefs_are_the_lattices_beliefs_sorted(released):
    """What the decision threshold is estimated on, with the archived beliefs kept sorted as they come: at every
    column, np.sort of the finite beliefs of every cell (with released columns' cells held among them too)."""
    n, window = 160, 10
    M = banded_scores(n, window, 4)
    mrf = IncrementalMrf(MrfParams(), band=20, window=window)
    archived = []
    for j in range(n):
        rows = np.arange(max(0, j - window))
        mrf.add_column(rows, M[rows, j])
        if j in released:
            mrf.release_column(j)
        beliefs = mrf.cells()[3]
        assert np.array_equal(mrf.sorted_beliefs(beliefs), np.sort(beliefs[np.isfinite(beliefs)]))
        archived.append(mrf._base)
    assert archived[-1] > 1000  # the archive was merged into the sorted beliefs, many times over
    assert len(set(archived)) > 3


def _lad_line_in_numpy(x, y, w, iterations=60):
    """The reweighted least-squares iterations of the LAD line written with numpy (its sums pairwise)."""
    floor = 1e-6 * max(float(np.ptp(y)), 1e-12)
    x0 = float(np.average(x, weights=w))
    xc, u, a, b = x - x0, w, 0.0, 0.0
    for _ in range(iterations + 1):
        s0, s1, s2 = u.sum(), (u * xc).sum(), (u * xc * xc).sum()
        t0, t1 = (u * y).sum(), (u * xc * y).sum()
        det = s0 * s2 - s1 * s1
        if not det > 0:
            break
        a, b = (s2 * t0 - s1 * t1) / det, (s0 * t1 - s1 * t0) / det
        u = w / np.maximum(np.abs(y - a - b * xc), floor)
    return float(a - b * x0), float(b)


@pytest.mark.parametrize("size", [5, 100, 1000, 40_000])
def test_lad_line_is_the_numpy_iteration_to_the_bit(size):
    """The background's line through (feature count, score), in numba, is the numpy iteration's to the last bit
    (the engine's beliefs, and so its decisions, stay those of the loop it replaced), on lines with outliers."""
    from semloc_core.loopclosure.mrf import _lad_line

    rng = np.random.default_rng(size)
    x = rng.integers(50, 500, size).astype(np.float64)
    y = -20.0 + 0.02 * x + rng.standard_normal(size) * 3.0
    y[rng.random(size) < 0.1] += 40.0  # loops among the background
    w = rng.uniform(1.0, 50.0, size)
    line = _lad_line(x, y, w)
    assert line == _lad_line_in_numpy(x, y, w)
    if size >= 100:
        assert abs(line[1] - 0.02) < 0.01  # the outliers do not pull the line
