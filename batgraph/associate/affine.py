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

from .segments import pair_stats

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

    def residual(self, X: np.ndarray, have: np.ndarray, m: int) -> np.ndarray:
        """Marker m's distance (F,) [m] from its relation's prediction on each frame of X (F, L, 3); NaN where
        any of the four is not named (have (F, L)) or m has no relation."""
        a, b, c = self.refs[m]
        if a < 0:
            return np.full(len(X), np.nan)
        wb, wc = self.weights[m]
        pred = X[:, a] + wb * (X[:, b] - X[:, a]) + wc * (X[:, c] - X[:, a])
        return np.where(have[:, [m, a, b, c]].all(axis=1), np.linalg.norm(X[:, m] - pred, axis=-1), np.nan)


def learn(X: np.ndarray, declared: set[int], noise_m: float = 0.0, stats: tuple | None = None) -> Relations:
    """Relations (see module docstring) from named positions X (F, L, 3) [m] (NaN where unnamed) for the markers
    not in ``declared`` (the markers with a declared segment); noise_m [m]: the floor of a relation's std; stats:
    segments.pair_stats(X) where the caller has it."""
    L = X.shape[1]
    out = Relations(np.full((L, 3), -1, np.int64), np.zeros((L, 2)), np.full(L, np.nan))
    named = np.isfinite(X).all(axis=-1)
    n, med, _ = stats if stats is not None else pair_stats(X)
    for m in range(L):
        if m in declared or named[:, m].sum() < LEARN_MIN_FRAMES:
            continue
        ok = (n[m] >= LEARN_MIN_FRAMES) & (np.arange(L) != m)
        near = np.flatnonzero(ok)[np.argsort(med[m][ok], kind="stable")][:NEIGHBOURS]
        trip = np.array(list(combinations(near.tolist(), 3)), np.int64).reshape(-1, 3)
        if not len(trip):
            continue
        w, sigma = _fit(X[:, m], X[:, trip[:, 0]].transpose(1, 0, 2), X[:, trip[:, 1]].transpose(1, 0, 2),
                        X[:, trip[:, 2]].transpose(1, 0, 2))
        best = int(np.argmin(sigma))
        if sigma[best] <= MAX_SIGMA_M:
            out.refs[m], out.weights[m], out.sigma[m] = trip[best], w[best], max(float(sigma[best]), noise_m)
    return out


def _fit(xm: np.ndarray, xa: np.ndarray, xb: np.ndarray, xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triple (T): weights (T, 2) by least squares over the frames where all four are named, refitted once
    without the frames beyond 4 stds, and the residual's robust per-axis std (T,) [m] (inf with fewer than
    LEARN_MIN_FRAMES frames). xm (F, 3), xa, xb, xc (T, F, 3), NaN where not named."""
    y, db, dc = xm[None] - xa, xb - xa, xc - xa
    keep = np.isfinite(y).all(axis=-1) & np.isfinite(db).all(axis=-1) & np.isfinite(dc).all(axis=-1)  # (T, F)
    enough = keep.sum(axis=1) >= LEARN_MIN_FRAMES
    y, db, dc = (np.nan_to_num(a) for a in (y, db, dc))
    dot = {name: np.einsum("tfi,tfi->tf", p, q) for name, (p, q) in
           {"bb": (db, db), "cc": (dc, dc), "bc": (db, dc), "by": (db, y), "cy": (dc, y), "yy": (y, y)}.items()}
    w, sigma = np.zeros((len(xa), 2)), np.full(len(xa), np.inf)
    for _ in range(2):
        bb, cc, bc, by, cy = ((keep * dot[k]).sum(axis=1) for k in ("bb", "cc", "bc", "by", "cy"))
        det = bb * cc - bc * bc
        good = enough & (det > 1e-12 * np.maximum(bb * cc, 1e-300))
        w = np.where(good[:, None], np.stack([cc * by - bc * cy, bb * cy - bc * by], axis=1)
                     / np.where(good, det, 1.0)[:, None], 0.0)
        wb, wc = w[:, :1], w[:, 1:]
        r2 = (dot["yy"] - 2 * (wb * dot["by"] + wc * dot["cy"]) + wb * wb * dot["bb"] + 2 * wb * wc * dot["bc"]
              + wc * wc * dot["cc"])
        r = np.sqrt(np.maximum(r2, 0.0))  # (T, F) the residuals' lengths
        sigma = np.where(good, _median(r, keep) / CHI3_MEDIAN, np.inf)
        keep = keep & (r <= 4 * sigma[:, None])
        enough = enough & (keep.sum(axis=1) >= LEARN_MIN_FRAMES)
    return w, np.where(enough, sigma, np.inf)


def _median(r: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Per row (T,) the median of r (T, F) over the kept entries (NaN where none): np.nanmedian's value, by one
    sort (nanmedian loops over the rows)."""
    n = keep.sum(axis=1)
    s = np.sort(np.where(keep, r, np.inf), axis=1)
    lo, hi = np.maximum((n - 1) // 2, 0), np.maximum(n // 2, 0)
    mid = 0.5 * (np.take_along_axis(s, lo[:, None], 1)[:, 0] + np.take_along_axis(s, hi[:, None], 1)[:, 0])
    return np.where(n > 0, mid, np.nan)
