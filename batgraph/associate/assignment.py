"""Least-cost assignment with a measure of how sure each link is: the margin by which the best assignment
without that link costs more (another link, or none: a weak link is not sure either). Rows and columns may stay
unassigned (half the gate each), so a link is made only when it costs less than the gate; solved per connected
group of gated pairs with scipy's linear_sum_assignment.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

BIG = 1e9
EXACT_UP_TO = 16  # rows + columns of a group whose margins are found exactly (one assignment per link)
LARGE = 64  # rows + columns beyond which links are the mutual choices (:func:`_mutual_best`)


def _components(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int) -> np.ndarray:
    """Connected component label of every row node then every column node of a bipartite graph of edges."""
    n = n_rows + n_cols
    g = coo_matrix((np.ones(len(rows)), (rows, n_rows + cols)), shape=(n, n))
    return connected_components(g, directed=False)[1]


def assign(cost: np.ndarray, gate: float, ambiguity: float, compete_only: bool = False
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-cost links of rows to columns (cost (R, K), inf beyond the gate; leaving a row or a column out costs
    gate / 2 each). Returns (rows, cols, margin): the links and, for each, how much more the best assignment
    without it costs (:func:`_margin`; with ``compete_only``, inf where that assignment just leaves both out: the
    link's own strength is then the caller's to judge). Solved per connected group of gated pairs."""
    R, K = cost.shape
    if R + K > LARGE:
        return _mutual_best(cost, gate, compete_only)
    r_idx, c_idx = np.nonzero(np.isfinite(cost))
    if not len(r_idx):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    comp = _components(r_idx, c_idx, R, K)
    out_r, out_c, out_m = [], [], []
    for g in np.unique(comp[r_idx]):
        rows = np.flatnonzero(comp[:R] == g)
        cols = np.flatnonzero(comp[R:] == g)
        sub = cost[np.ix_(rows, cols)]
        links, total = _solve(sub, gate)
        exact = sum(sub.shape) <= EXACT_UP_TO
        for a, b in links:
            out_r.append(rows[a])
            out_c.append(cols[b])
            if ambiguity <= 0:
                out_m.append(np.inf)
            elif exact:
                out_m.append(_margin(sub, gate, a, b, total, compete_only))
            else:
                out_m.append(_local_margin(sub, gate, a, b, compete_only))
    return np.asarray(out_r, np.int64), np.asarray(out_c, np.int64), np.asarray(out_m)


def _margin(sub: np.ndarray, gate: float, a: int, b: int, total: float, compete_only: bool) -> float:
    """How much more the best assignment without the link (a, b) costs: against another link for row a or column
    b, or against leaving both out (gate - cost: the link's own evidence; inf with ``compete_only``)."""
    if sub.shape == (1, 1):
        return np.inf if compete_only else gate - float(sub[0, 0])
    forbidden = sub.copy()
    forbidden[a, b] = np.inf
    links, alt = _solve(forbidden, gate)
    if compete_only and not any(x == a or y == b for x, y in links):
        return np.inf
    return alt - total


def _local_margin(sub: np.ndarray, gate: float, a: int, b: int, compete_only: bool) -> float:
    """:func:`_margin` for a large group, from the link's row and column alone: how much more row a's next-best
    column or column b's next-best row costs (or leaving the link out, gate - cost, unless ``compete_only``). A lower
    bound of the exact margin's competition (an alternative may be taken by another link)."""
    c = float(sub[a, b])
    row = np.r_[sub[a, :b], sub[a, b + 1:]]
    col = np.r_[sub[:a, b], sub[a + 1:, b]]
    alt = min(float(row.min()) if len(row) else np.inf, float(col.min()) if len(col) else np.inf)
    if not compete_only:
        alt = min(alt, gate)
    return alt - c


def _mutual_best(cost: np.ndarray, gate: float, compete_only: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For large matrices (more than LARGE rows and columns, a big rig's frame): the links each row and column
    choose mutually (each the other's least cost, below the gate), with :func:`_local_margin`'s margins, all at
    once. Not the least-cost assignment where choices chain, but where a link's row and column agree."""
    R, K = cost.shape
    C = np.where(np.isfinite(cost), cost, np.inf)
    if R == 0 or K == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    rb, cb = np.argmin(C, axis=1), np.argmin(C, axis=0)
    r = np.arange(R)
    c = C[r, rb]
    ok = (cb[rb] == r) & (c < gate)
    rows, cols, c = r[ok], rb[ok], c[ok]
    row2 = np.partition(C, 1, axis=1)[:, 1] if K >= 2 else np.full(R, np.inf)
    col2 = np.partition(C, 1, axis=0)[1] if R >= 2 else np.full(K, np.inf)
    alt = np.minimum(row2[rows], col2[cols])
    if not compete_only:
        alt = np.minimum(alt, gate)
    return rows.astype(np.int64), cols.astype(np.int64), alt - c


def _solve(sub: np.ndarray, gate: float) -> tuple[list[tuple[int, int]], float]:
    """Least-cost assignment with a miss / birth of cost gate / 2 for each row / column left out."""
    from scipy.optimize import linear_sum_assignment  # 40 ms to import: only associate needs it

    R, K = sub.shape
    full = np.full((R + K, K + R), BIG)
    full[:R, :K] = np.where(np.isfinite(sub), sub, BIG)
    full[np.arange(R), K + np.arange(R)] = gate / 2
    full[R + np.arange(K), np.arange(K)] = gate / 2
    full[R:, K:] = 0.0
    r, c = linear_sum_assignment(full)
    links = [(int(a), int(b)) for a, b in zip(r, c, strict=True) if a < R and b < K]
    return links, float(full[r, c].sum())


def mahalanobis(diff: np.ndarray, S: np.ndarray) -> np.ndarray:
    """diff^T S^-1 diff for diff (..., d) and S (..., d, d)."""
    return np.einsum("...i,...i->...", diff, np.linalg.solve(S, diff[..., None])[..., 0])


def mahalanobis_within(diff: np.ndarray, S: np.ndarray, gate: float, want: np.ndarray | None = None) -> np.ndarray:
    """:func:`mahalanobis` for diff (..., 2) and S (..., 2, 2) where it may be below ``gate`` (and ``want``, a
    mask of diff's leading shape), inf elsewhere: where S is positive definite and |diff|^2 > 2 gate tr(S), the
    distance is at least 2 gate (S's largest eigenvalue is at most its trace), so it is not solved for."""
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    tr = S[..., 0, 0] + S[..., 1, 1]
    near = ~((det > 0) & (tr > 0) & (np.einsum("...i,...i->...", diff, diff) > 2 * gate * tr))
    if want is not None:
        near &= want
    m = np.full(diff.shape[:-1], np.inf)
    m[near] = mahalanobis(diff[near], S[near])
    return m
