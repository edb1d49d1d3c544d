"""Compiled inner loops (numba) of association: the per-pair statistics of the named markers' distances.

Why compiled: a frame of L markers has L^2 / 2 pairs; numpy would hold every frame's pair distances at once
(F x L x L, 40 MB for 160 frames of 180 markers, and sort them along a strided axis), where a loop over pairs
needs one frame column at a time. Arithmetic is numpy's, in numpy's order (the answers are bit-identical).
Compiled on first use and cached on disk beside this file (``cache=True``). Imports only numpy and numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def pair_distance_medians(X):  # pragma: no cover  (compiled)
    """Per marker pair of X (L, F, 3) [m] (NaN where unnamed), over the frames where both are named: the count
    n (L, L), the median distance med (L, L) [m] and the median absolute deviation from it mad (L, L) [m] (NaN
    where n is 0). Symmetric; the distance as np.linalg.norm's sqrt((dx^2 + dy^2) + dz^2), the median as
    np.nanmedian's mean of the two middle values."""
    L, F = X.shape[0], X.shape[1]
    n = np.zeros((L, L), np.int64)
    med = np.full((L, L), np.nan)
    mad = np.full((L, L), np.nan)
    d = np.empty(F)
    for a in range(L):
        for b in range(a, L):
            k = 0
            for f in range(F):
                dx, dy, dz = X[a, f, 0] - X[b, f, 0], X[a, f, 1] - X[b, f, 1], X[a, f, 2] - X[b, f, 2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if np.isfinite(r):
                    d[k] = r
                    k += 1
            n[a, b] = n[b, a] = k
            if k == 0:
                continue
            s = np.sort(d[:k])
            m = 0.5 * (s[(k - 1) // 2] + s[k // 2])
            w = np.sort(np.abs(s - m))
            med[a, b] = med[b, a] = m
            mad[a, b] = mad[b, a] = 0.5 * (w[(k - 1) // 2] + w[k // 2])
    return n, med, mad
