"""Learned affine neighbours: a marker that stays a fixed affine combination of three other markers, ``x_m = x_a +
w_b (x_b - x_a) + w_c (x_c - x_a)`` (a point on the wing membrane moves with the wrist and digits around it), learned
from the named points as steady pairs are (batgraph.associate.segments), to check a named path that has no segment.

Learned only for markers without a declared segment: the candidates are its NEIGHBOURS nearest markers (by median
distance), the relation the triple with the smallest spread of the four named together on LEARN_MIN_FRAMES frames
or more, kept when that spread is at most MAX_SIGMA_M (a membrane that billows, or a marker that is not on one, gets
none). The spread is measured, not assumed: a relation is as strict as the named points show it to be.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from . import kernels

LEARN_MIN_FRAMES = 40
NEIGHBOURS = 6
MAX_SIGMA_M = 0.003
CHI3_MEDIAN = 1.5382  # the median of the length of a standard normal 3-vector


@dataclass
class Relations:
    """Per marker (L,) its three reference markers (L, 3) (-1: no relation), weights (L, 2) of the second and
    third, and the residual's per-axis std sigma (L,) [m]."""

    refs: np.ndarray
    weights: np.ndarray
    sigma: np.ndarray

    def residual(self, X: np.ndarray, m: int) -> np.ndarray:
        """Marker m's distance (F,) [m] from its relation's prediction on each frame of X (F, L, 3); NaN where
        any of the four is not named or m has no relation."""
        a, b, c = self.refs[m]
        if a < 0:
            return np.full(len(X), np.nan)
        wb, wc = self.weights[m]
        pred = X[:, a] + wb * (X[:, b] - X[:, a]) + wc * (X[:, c] - X[:, a])
        return np.linalg.norm(X[:, m] - pred, axis=-1)


def learn(X: np.ndarray, declared: set[int], noise_m: float = 0.0) -> Relations:
    """Relations (see module docstring) from named positions X (F, L, 3) [m] (NaN where unnamed) for the markers
    not in ``declared`` (the markers with a declared segment); noise_m [m]: the floor of a relation's std."""
    F, L = X.shape[:2]
    out = Relations(np.full((L, 3), -1, np.int64), np.zeros((L, 2)), np.full(L, np.nan))
    named = np.isfinite(X).all(axis=-1)
    n, med, _ = kernels.pair_distance_medians(np.ascontiguousarray(X.transpose(1, 0, 2), dtype=np.float64))
    for m in range(L):
        if m in declared or named[:, m].sum() < LEARN_MIN_FRAMES:
            continue
        ok = (n[m] >= LEARN_MIN_FRAMES) & (np.arange(L) != m)
        near = np.flatnonzero(ok)[np.argsort(med[m][ok], kind="stable")][:NEIGHBOURS]
        best = (np.inf, None, None)
        for a, b, c in combinations(near.tolist(), 3):
            on = named[:, m] & named[:, a] & named[:, b] & named[:, c]
            if on.sum() < LEARN_MIN_FRAMES:
                continue
            w, sigma = _fit(X[on, m], X[on, a], X[on, b], X[on, c])
            if sigma < best[0]:
                best = (sigma, (a, b, c), w)
        if best[1] is not None and best[0] <= MAX_SIGMA_M:
            out.refs[m], out.weights[m], out.sigma[m] = best[1], best[2], max(best[0], noise_m)
    return out


def _fit(xm: np.ndarray, xa: np.ndarray, xb: np.ndarray, xc: np.ndarray) -> tuple[np.ndarray, float]:
    """Weights (2,) by least squares, refitted once without the frames beyond 4 stds, and the per-axis robust std
    of the residual [m]."""
    A = np.stack([xb - xa, xc - xa], axis=-1).reshape(-1, 2)  # (n * 3, 2)
    y = (xm - xa).reshape(-1)
    keep = np.ones(len(xm), bool)
    w, sigma = np.zeros(2), np.inf
    for _ in range(2):
        rows = np.repeat(keep, 3)
        w = np.linalg.lstsq(A[rows], y[rows], rcond=None)[0]
        r = np.linalg.norm((y - A @ w).reshape(-1, 3), axis=1)
        sigma = float(np.median(r[keep])) / CHI3_MEDIAN
        keep = r <= 4 * sigma
        if keep.sum() < LEARN_MIN_FRAMES:
            break
    return w, sigma
