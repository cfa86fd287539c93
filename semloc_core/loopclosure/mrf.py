"""Loop-closure detection with an MRF on the similarity matrix (thesis §3.4).

The lattice H has one binary node per image pair (i, j), i earlier than j: 1 = the two images close a loop. Node
potentials come from the normalised similarity p = M_ij / F: phi(1) = p, phi(0) = 1 - p. Each node is tied to its 8
neighbours (i +- 1, j +- 1) by psi(0,0) = psi(1,1) = alpha * G(M_ij, M_kl), psi(0,1) = psi(1,0) = 1, with
G(x, y) = exp(-(x - y)^2 / sigma^2), sigma = 0.05 F (eqs. 3.1-3.2). Generalised max-product belief propagation on
the node/edge cluster graph, damped (lambda = 0.5) for 20 iterations, gives max-marginals whose argmax is D.

Implementation notes.

* Binary max-product runs in the log domain with one number per message: mu = log m(1) - log m(0). For pairwise
  factors the cluster-graph schedule (node clusters, then edge clusters) is the synchronous pairwise update
  mu_{c->e} = max(0, a + J) - max(J, a), with a the log-odds at c without e's message and J = log(alpha G).
  Damping mixes the new log message with the previous one.
* ``coupling="thesis"`` uses J = log(alpha G) as written: when neighbouring scores differ by more than
  sigma * sqrt(ln alpha) the factor *rewards* different labels. ``coupling="attractive"`` (the default, see
  docs/loopclosure.md for the measurements behind it) uses J = max(0, log(alpha G)): similar neighbours still pull
  towards the same label, dissimilar ones are left independent instead of being pushed apart.
* Cells with p = 0 (a score at or below the offset, the window |i - j| <= w, the lower triangle, and pairs that
  were never scored) have phi(1) = 0: their label is fixed at 0, so the message they send is the constant -J(p_c, 0)
  whatever they receive. Only cells with p > 0 are stored ("live"), which makes the lattice sparse when only
  retrieved candidates are scored.
* ``phi(0) = 0`` (p = 1, the maximum of M) would be an infinite log-odds: p is clipped to ``1 - 1e-6``.

Two drivers share one numba kernel: :func:`infer_batch` (every cell, zero messages, 20 synchronous iterations:
the thesis) and :class:`IncrementalMrf`, which adds one column per new frame and re-runs the iterations only on the
last ``band`` columns, warm-started from the stored messages, holding the messages older cells send fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

# Neighbour directions (d_row, d_col); direction 7 - d is the opposite of d.
DIRECTIONS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64)
_D_ROW = np.ascontiguousarray(DIRECTIONS[:, 0])
_D_COL = np.ascontiguousarray(DIRECTIONS[:, 1])
_MAX_P = 1.0 - 1e-6
COUPLINGS = ("attractive", "thesis")


@dataclass(frozen=True)
class MrfParams:
    """Thesis §3.6.2: sigma = 0.05 F (the fraction of F), alpha = 2, damping 0.5, 20 iterations.

    ``offset``: the score that maps to p = 0 (the thesis's phi(1) = M / F assumes M >= 0, i.e. offset 0); ``p = (M -
    offset) / (F - offset)`` clipped to [0, 1]. ``coupling``: see the module docstring.
    """

    sigma: float = 0.05
    alpha: float = 2.0
    damping: float = 0.5
    iterations: int = 20
    offset: float = 0.0
    coupling: str = "attractive"

    def __post_init__(self) -> None:
        if not (self.sigma > 0 and self.alpha >= 1.0 and 0.0 <= self.damping < 1.0 and self.iterations >= 1):
            raise ValueError(f"need sigma > 0, alpha >= 1, 0 <= damping < 1, iterations >= 1; got {self}")
        if self.coupling not in COUPLINGS:
            raise ValueError(f"coupling must be one of {COUPLINGS}, got {self.coupling!r}")
        if not np.isfinite(self.offset):
            raise ValueError("offset must be finite")

    @property
    def attractive(self) -> bool:
        return self.coupling == "attractive"


def normalized_potential(M, normalizer: float, offset: float = 0.0) -> np.ndarray:
    """phi(1) = p = (M - offset) / (F - offset), clipped to [0, 1] (§3.4; offset 0 is the thesis's M / F)."""
    if not normalizer > offset:
        raise ValueError(f"normalizer F ({normalizer}) must exceed the offset ({offset})")
    p = (np.asarray(M, dtype=np.float64) - offset) / (normalizer - offset)
    return np.clip(np.nan_to_num(p, nan=0.0, neginf=0.0, posinf=1.0), 0.0, 1.0)


def _log_odds(p: np.ndarray) -> np.ndarray:
    p = np.minimum(p, _MAX_P)
    return np.log(p) - np.log1p(-p)


@njit(cache=True)
def _coupling(p_a: float, p_b: float, sigma: float, log_alpha: float, attractive: bool) -> float:
    """J = log(alpha * G(M_a, M_b)) (eq. 3.1), floored at 0 for the attractive variant."""
    z = (p_a - p_b) / sigma
    j = log_alpha - z * z
    if attractive and j < 0.0:
        return 0.0
    return j


@njit(cache=True)
def _run_bp(theta, value, nbr, fixed_in, msg, sources, sigma, log_alpha, attractive, damping, iterations):
    """Synchronous damped max-product iterations; only messages sent by ``sources`` are recomputed.

    theta (C,) log-odds of phi; value (C,) p; nbr (C, 8) live neighbour index or -1; fixed_in (C,) sum of the
    constant messages from clamped neighbours; msg (C, 8) incoming messages (msg[c, d] comes from direction d),
    updated in place.
    """
    count = sources.shape[0]
    new = np.empty((count, 8))
    for _ in range(iterations):
        for s in range(count):
            c = sources[s]
            total = theta[c] + fixed_in[c]
            for d in range(8):
                total += msg[c, d]
            for d in range(8):
                e = nbr[c, d]
                if e < 0:
                    new[s, d] = 0.0
                    continue
                cavity = total - msg[c, d]  # everything c knows except what e told it
                coupling = _coupling(value[c], value[e], sigma, log_alpha, attractive)
                mu = max(0.0, cavity + coupling) - max(coupling, cavity)
                new[s, d] = damping * msg[e, 7 - d] + (1.0 - damping) * mu
        for s in range(count):
            c = sources[s]
            for d in range(8):
                e = nbr[c, d]
                if e >= 0:
                    msg[e, 7 - d] = new[s, d]


@njit(cache=True)
def _beliefs(theta, fixed_in, msg, cells):
    out = np.empty(cells.shape[0])
    for s in range(cells.shape[0]):
        c = cells[s]
        total = theta[c] + fixed_in[c]
        for d in range(8):
            total += msg[c, d]
        out[s] = total
    return out


@njit(cache=True)
def _find_row(rows, start, stop, row):
    """Index of ``row`` in the sorted rows[start:stop], or -1."""
    lo, hi = start, stop
    while lo < hi:
        mid = (lo + hi) // 2
        if rows[mid] < row:
            lo = mid + 1
        else:
            hi = mid
    if lo < stop and rows[lo] == row:
        return lo
    return -1


@njit(cache=True)
def _link(rows, cols, col_start, n_cols, first, stop, value, sigma, log_alpha, attractive, nbr, fixed_in):
    """Neighbour table and summed clamped-neighbour messages of cells ``first..stop-1``.

    Cells are stored column by column (column l occupies col_start[l]..col_start[l+1]-1, rows ascending); the
    lattice is n_cols x n_cols. A neighbour outside it has no factor; one inside but not stored is clamped at 0.
    """
    for c in range(first, stop):
        i, j = rows[c], cols[c]
        acc = 0.0
        for d in range(8):
            k = i + _D_ROW[d]
            l_ = j + _D_COL[d]
            if k < 0 or l_ < 0 or k >= n_cols or l_ >= n_cols:
                nbr[c, d] = -1
                continue
            e = _find_row(rows, col_start[l_], col_start[l_ + 1], k)
            nbr[c, d] = e
            if e < 0:
                # A clamped neighbour (label 0, value 0) sends -J(p_c, 0) whatever it receives.
                acc -= _coupling(value[c], 0.0, sigma, log_alpha, attractive)
        fixed_in[c] = acc


@dataclass(frozen=True)
class MrfResult:
    """(n, n) max-marginal log-odds (``-inf`` where phi(1) = 0) and the MAP labelling D = belief > 0."""

    beliefs: np.ndarray
    decisions: np.ndarray
    normalizer: float


def _columnwise(rows: np.ndarray, cols: np.ndarray, n: int):
    order = np.lexsort((rows, cols))
    rows, cols = rows[order], cols[order]
    col_start = np.zeros(n + 1, np.int64)
    np.add.at(col_start, cols + 1, 1)
    return order, rows, cols, np.cumsum(col_start)


def infer_cells(
    rows,
    cols,
    scores,
    n: int,
    params: MrfParams = MrfParams(),
    normalizer: float | None = None,
) -> tuple[np.ndarray, float]:
    """Batch inference on scored cells of an (n, n) lattice; every other cell has M = 0 (clamped).

    Returns the max-marginal log-odds of each given cell (``-inf`` where p = 0) and the normaliser F used
    (default: the maximum score, the thesis's F = max(M)).
    """
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    cols = np.asarray(cols, dtype=np.int64).reshape(-1)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if not (rows.shape == cols.shape == scores.shape):
        raise ValueError("rows, cols and scores must have the same length")
    if np.any(np.isnan(scores)):
        raise ValueError("scores contain NaN")
    if rows.size and (rows.min() < 0 or cols.min() < 0 or rows.max() >= n or cols.max() >= n):
        raise ValueError(f"cells must lie inside the {n}x{n} lattice")
    finite = scores[np.isfinite(scores)]
    F = float(finite.max()) if normalizer is None and finite.size else float(normalizer if normalizer else 0.0)
    beliefs = np.full(rows.size, -np.inf)
    if finite.size == 0 or F <= params.offset:
        return beliefs, F
    p = normalized_potential(scores, F, params.offset)
    live = np.flatnonzero(p > 0)
    if np.unique(rows[live] * n + cols[live]).size != live.size:
        raise ValueError("duplicate cells")
    order, r, c, col_start = _columnwise(rows[live], cols[live], n)
    value = p[live][order]
    log_alpha = float(np.log(params.alpha))
    nbr = np.empty((r.size, 8), np.int64)
    fixed_in = np.empty(r.size)
    _link(r, c, col_start, n, 0, r.size, value, params.sigma, log_alpha, params.attractive, nbr, fixed_in)
    theta = _log_odds(value)
    msg = np.zeros((r.size, 8))
    cells = np.arange(r.size, dtype=np.int64)
    _run_bp(theta, value, nbr, fixed_in, msg, cells, params.sigma, log_alpha, params.attractive, params.damping,
            params.iterations)
    beliefs[live[order]] = _beliefs(theta, fixed_in, msg, cells)
    return beliefs, F


def infer_batch(M, params: MrfParams = MrfParams(), normalizer: float | None = None) -> MrfResult:
    """The thesis's batch inference on a full (n, n) similarity matrix (upper triangle = scored pairs).

    Entries that are not loop candidates (the window, the lower triangle, unscored pairs) must be ``<=
    params.offset`` (0 or ``-inf`` will do). ``normalizer`` defaults to max(M), the thesis's F.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(f"M must be square, got shape {M.shape}")
    n = M.shape[0]
    # Only the strict upper triangle holds scored pairs (i earlier than j).
    rows, cols = np.nonzero(np.triu(M > params.offset, 1))
    cell_beliefs, F = infer_cells(rows, cols, M[rows, cols], n, params, normalizer)
    beliefs = np.full((n, n), -np.inf)
    beliefs[rows, cols] = cell_beliefs
    return MrfResult(beliefs, beliefs > 0, F)


class IncrementalMrf:
    """The lattice grown one column (frame) at a time, with inference on the last ``band`` columns only.

    ``add_column(scores)`` appends column j = number of columns so far, with the scores of pairs (i, j), i < j; it
    re-runs ``params.iterations`` synchronous iterations on the messages sent by cells of columns j-band+1..j,
    warm-started from the stored messages; messages sent by older cells stay as they were. A column's decisions
    are final once it leaves the band. ``normalizer=None`` keeps F = the running maximum score (then, as the thesis's
    F is the maximum over the whole sequence, decisions made before F reached its final value can differ from the
    batch result); a fixed F makes the result independent of arrival order.
    """

    def __init__(self, params: MrfParams = MrfParams(), band: int = 30, normalizer: float | None = None) -> None:
        if band < 1:
            raise ValueError("band must be >= 1")
        if normalizer is not None and not normalizer > params.offset:
            raise ValueError("a fixed normalizer must exceed params.offset")
        self.params = params
        self.band = int(band)
        self.fixed_normalizer = normalizer
        self.normalizer = float(normalizer) if normalizer is not None else -np.inf
        self._log_alpha = float(np.log(params.alpha))
        self._size = 0
        capacity = 64
        self._rows = np.zeros(capacity, np.int64)
        self._cols = np.zeros(capacity, np.int64)
        self._scores = np.zeros(capacity)
        self._value = np.zeros(capacity)
        self._theta = np.zeros(capacity)
        self._fixed_in = np.zeros(capacity)
        self._nbr = np.full((capacity, 8), -1, np.int64)
        self._msg = np.zeros((capacity, 8))
        self._beliefs = np.zeros(capacity)
        self._col_start = [0]

    # --- growth ---------------------------------------------------------------------------------------------

    @property
    def n_columns(self) -> int:
        return len(self._col_start) - 1

    @property
    def n_cells(self) -> int:
        return self._size

    def _reserve(self, extra: int) -> None:
        need = self._size + extra
        capacity = self._rows.size
        if need <= capacity:
            return
        while capacity < need:
            capacity *= 2
        for name in ("_rows", "_cols", "_scores", "_value", "_theta", "_fixed_in", "_beliefs"):
            old = getattr(self, name)
            new = np.zeros(capacity, old.dtype)
            new[: self._size] = old[: self._size]
            setattr(self, name, new)
        for name, fill in (("_nbr", -1), ("_msg", 0.0)):
            old = getattr(self, name)
            new = np.full((capacity, 8), fill, old.dtype)
            new[: self._size] = old[: self._size]
            setattr(self, name, new)

    def _renormalize(self) -> None:
        s = self._size
        self._value[:s] = normalized_potential(self._scores[:s], self.normalizer, self.params.offset)
        self._theta[:s] = _log_odds(np.maximum(self._value[:s], 1e-300))

    def add_column(self, rows, scores) -> None:
        """Append the next column: scores of pairs (rows[k], j) for the new frame j; unlisted pairs have M = 0."""
        j = self.n_columns
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if rows.shape != scores.shape:
            raise ValueError("rows and scores must have the same length")
        if rows.size and (rows.min() < 0 or rows.max() >= j):
            raise ValueError(f"rows of column {j} must be earlier frames (0..{j - 1})")
        if np.unique(rows).size != rows.size:
            raise ValueError("duplicate rows in one column")
        if np.any(np.isnan(scores)):
            raise ValueError("scores contain NaN")
        finite = scores[np.isfinite(scores)]
        renormalized = False
        if self.fixed_normalizer is None and finite.size and finite.max() > self.normalizer:
            self.normalizer = float(finite.max())
            renormalized = self._size > 0
            if renormalized:
                self._renormalize()
        live = scores > self.params.offset
        if self.normalizer <= self.params.offset:
            live[:] = False
        order = np.argsort(rows[live], kind="stable")
        rows, scores = rows[live][order], scores[live][order]
        count = rows.size
        self._reserve(count)
        first = self._size
        stop = first + count
        self._rows[first:stop] = rows
        self._cols[first:stop] = j
        self._scores[first:stop] = scores
        self._msg[first:stop] = 0.0
        self._size = stop
        self._col_start.append(stop)
        if count:
            value = normalized_potential(scores, self.normalizer, self.params.offset)
            self._value[first:stop] = value
            self._theta[first:stop] = _log_odds(value)
        # A new F changes every clamped-neighbour message; otherwise only columns j-1 and j gain neighbours.
        self._relink(0 if renormalized else max(0, j - 1), j)
        self._infer()

    def _relink(self, first_col: int, last_col: int) -> None:
        starts = np.asarray(self._col_start, dtype=np.int64)
        first, stop = int(starts[first_col]), int(starts[last_col + 1])
        s = self._size
        _link(self._rows[:s], self._cols[:s], starts, self.n_columns, first, stop, self._value[:s],
              self.params.sigma, self._log_alpha, self.params.attractive, self._nbr[:s], self._fixed_in[:s])

    def band_cells(self) -> np.ndarray:
        first_col = max(0, self.n_columns - self.band)
        return np.arange(self._col_start[first_col], self._size, dtype=np.int64)

    def _infer(self) -> None:
        cells = self.band_cells()
        if cells.size == 0:
            return
        s = self._size
        p = self.params
        _run_bp(self._theta[:s], self._value[:s], self._nbr[:s], self._fixed_in[:s], self._msg[:s], cells, p.sigma,
                self._log_alpha, p.attractive, p.damping, p.iterations)
        self._beliefs[cells] = _beliefs(self._theta[:s], self._fixed_in[:s], self._msg[:s], cells)

    # --- results --------------------------------------------------------------------------------------------

    def column(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, scores, beliefs) of the live cells of column j; belief > 0 is a loop closure."""
        if not 0 <= j < self.n_columns:
            raise IndexError(f"column {j} out of range 0..{self.n_columns - 1}")
        a, b = self._col_start[j], self._col_start[j + 1]
        return self._rows[a:b].copy(), self._scores[a:b].copy(), self._beliefs[a:b].copy()

    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, scores, beliefs) of every live cell."""
        s = self._size
        return self._rows[:s].copy(), self._cols[:s].copy(), self._scores[:s].copy(), self._beliefs[:s].copy()

    def dense(self) -> MrfResult:
        n = self.n_columns
        beliefs = np.full((n, n), -np.inf)
        rows, cols, _, b = self.cells()
        beliefs[rows, cols] = b
        return MrfResult(beliefs, beliefs > 0, self.normalizer)

    # --- state ----------------------------------------------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        s = self._size
        return {
            "rows": self._rows[:s].copy(),
            "cols": self._cols[:s].copy(),
            "scores": self._scores[:s].copy(),
            "messages": self._msg[:s].copy(),
            "beliefs": self._beliefs[:s].copy(),
            "col_start": np.asarray(self._col_start, np.int64),
            "normalizer": np.array([self.normalizer]),
        }

    @classmethod
    def from_state(cls, state: dict, params: MrfParams, band: int, normalizer: float | None) -> "IncrementalMrf":
        mrf = cls(params, band, normalizer)
        rows = np.asarray(state["rows"], np.int64)
        cols = np.asarray(state["cols"], np.int64)
        col_start = np.asarray(state["col_start"], np.int64)
        count = rows.size
        if not (cols.shape == (count,) and np.shape(state["scores"]) == (count,)
                and np.shape(state["messages"]) == (count, 8) and np.shape(state["beliefs"]) == (count,)):
            raise ValueError("inconsistent MRF state arrays")
        if col_start.ndim != 1 or col_start.size < 1 or col_start[0] != 0 or col_start[-1] != count \
                or np.any(np.diff(col_start) < 0):
            raise ValueError("inconsistent MRF column index")
        mrf._reserve(count)
        mrf._size = count
        mrf._rows[:count] = rows
        mrf._cols[:count] = cols
        mrf._scores[:count] = state["scores"]
        mrf._msg[:count] = state["messages"]
        mrf._beliefs[:count] = state["beliefs"]
        mrf._col_start = col_start.tolist()
        mrf.normalizer = float(np.asarray(state["normalizer"]).reshape(-1)[0])
        if count:
            mrf._renormalize()
            mrf._relink(0, mrf.n_columns - 1)
        return mrf
