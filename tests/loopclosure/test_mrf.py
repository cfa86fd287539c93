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
    params = MrfParams(sigma=rng.uniform(0.1, 0.4), coupling=coupling, damping=0.0, iterations=60)
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
    params = MrfParams(offset=-2.0)
    result = infer_batch(M, params)
    rows, cols = np.nonzero(np.isfinite(M))
    cell_beliefs, F = infer_cells(rows, cols, M[rows, cols], 80, params)
    assert F == pytest.approx(np.max(M[np.isfinite(M)]))
    assert np.allclose(np.where(np.isfinite(cell_beliefs), cell_beliefs, -1e9),
                       np.where(np.isfinite(result.beliefs[rows, cols]), result.beliefs[rows, cols], -1e9))
    assert np.all(np.isneginf(result.beliefs[M <= -2.0]))


@pytest.mark.parametrize("band", [5, 30])
def test_incremental_equals_batch(band):
    n, window = 200, 10
    M = banded_scores(n, window, 1)
    params = MrfParams()
    batch = infer_batch(M, params)
    incremental = IncrementalMrf(params, band=band, normalizer=batch.normalizer)
    for j in range(n):
        rows = np.arange(max(0, j - window))
        incremental.add_column(rows, M[rows, j])
    decisions = incremental.dense().decisions
    assert batch.decisions.sum() > 100
    assert np.mean(decisions == batch.decisions) >= 0.995
    both = np.sum(decisions & batch.decisions)
    assert both / np.sum(decisions | batch.decisions) > 0.95


def test_running_normalizer_reaches_the_batch_value():
    n, window = 200, 10
    M = banded_scores(n, window, 2)
    incremental = IncrementalMrf(MrfParams(), band=30)
    for j in range(n):
        rows = np.arange(max(0, j - window))
        incremental.add_column(rows, M[rows, j])
    assert incremental.normalizer == pytest.approx(np.max(M[np.isfinite(M)]))
    batch = infer_batch(M, MrfParams())
    assert np.mean(incremental.dense().decisions == batch.decisions) >= 0.995


def test_state_round_trip_continues_identically():
    n, window = 120, 10
    M = banded_scores(n, window, 3)
    params = MrfParams()
    a = IncrementalMrf(params, band=20)
    for j in range(70):
        rows = np.arange(max(0, j - window))
        a.add_column(rows, M[rows, j])
    b = IncrementalMrf.from_state(a.state(), params, 20, None)
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
    params = MrfParams(sigma=0.5)
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
    thesis = infer_batch(M, MrfParams(coupling="thesis"))
    attractive = infer_batch(M, MrfParams(coupling="attractive"))
    assert thesis.decisions[2, 7] and not attractive.decisions[2, 7]


def test_input_validation():
    with pytest.raises(ValueError):
        MrfParams(coupling="potts")
    with pytest.raises(ValueError):
        infer_batch(np.zeros((3, 4)))
    mrf = IncrementalMrf()
    mrf.add_column([], [])
    with pytest.raises(ValueError, match="earlier"):
        mrf.add_column([1], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        mrf.add_column([0], [np.nan])
