"""One block-tridiagonal system with large dense blocks, a segment group's (batgraph.graph.rigid), by LAPACK.

A group of g markers joined by segment-length factors is one block-tridiagonal system over frames whose
n x n blocks (n = g d: 14 markers x 18 values of the "oscillating" model = 252) are dense, and whose
sub-diagonal block B = diag(B_1, ..., B_g) is block diagonal (each member's own motion). The recursion is
batgraph.graph.kernels' (forward: S_0 = D_0, S_k = D_k - B S_{k-1}^-1 B^T, y_k = rhs_k - B S_{k-1}^-1 y_{k-1};
back: dx_{F-1} = S^-1 y, dx_k = S_k^-1 (y_k - B^T dx_{k+1}); marginals Sigma_k = S_k^-1 + G_k Sigma_{k+1} G_k^T,
G_k = S_k^-1 B^T), but each S_k^-1 comes from LAPACK's symmetric inverse: Cholesky (potrf + potri, ~n^3
flops, log det from the factor's diagonal), or LU (getrf + getri, ~2 n^3, and a second factorisation for
the log det) where S_k is not positive definite (an exact-curvature step with a robust loss can make it
indefinite). The kernels invert blocks this wide by LU (their compiled Cholesky is for blocks of at most
kernels.CHOLESKY_BLOCK values): a 252-wide inverse took 1.87 ms by LU and 1.08 ms by Cholesky on the 2-core
machine (one thread). Products with B are per member (g b^2 n, not n^3).

The loop over frames is Python: a few numpy / LAPACK calls a frame, tens of microseconds beside one
large inverse. :data:`MIN_DENSE` is where this beats the compiled kernels (BENCHMARKS.md).

Shapes: D (F, n, n) diagonal blocks, symmetric; Bb (g, b, b) the blocks of B (n = g b); rhs (F, n, r).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.linalg import lapack

#: The smallest block (n values per frame) solved here rather than by batgraph.graph.kernels.
MIN_DENSE = 64


@njit(cache=True, nogil=True)
def _mirror_lower(a):  # pragma: no cover  (compiled)
    """a[i, j] = a[j, i] for j > i, in place (np.tril and fancy indexing cost 10-20 times as much at n = 252)."""
    n = a.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            a[i, j] = a[j, i]


@njit(cache=True, nogil=True)
def _symmetrise(a):  # pragma: no cover  (compiled)
    """Each (n, n) matrix of a (F, n, n) replaced by 0.5 (A + A^T), in place (numpy's takes ~10 times as long)."""
    for f in range(a.shape[0]):
        for i in range(a.shape[1]):
            for j in range(i + 1, a.shape[1]):
                a[f, i, j] = a[f, j, i] = 0.5 * (a[f, i, j] + a[f, j, i])


def _symmetric_inverse(S: np.ndarray) -> tuple[np.ndarray, float]:
    """(S^-1 (n, n), log |det S|) of a symmetric S (only its lower triangle is read by Cholesky)."""
    c, info = lapack.dpotrf(S.T, lower=1, clean=0)  # S.T: the same matrix, Fortran-ordered (no copy)
    if info == 0:
        inv, info = lapack.dpotri(c, lower=1)
        if info == 0:
            _mirror_lower(inv)  # potri fills the lower triangle
            return inv, 2.0 * float(np.log(np.diagonal(c)).sum())
    return np.linalg.inv(S), float(np.linalg.slogdet(S)[1])


def _left(Bb: np.ndarray, X: np.ndarray, transpose: bool = False) -> np.ndarray:
    """B X (or B^T X) for the block-diagonal B of blocks Bb (g, b, b) and X (g b, r)."""
    g, b = Bb.shape[:2]
    blocks = np.swapaxes(Bb, -1, -2) if transpose else Bb
    return (blocks @ X.reshape(g, b, -1)).reshape(X.shape)


def _forward(D: np.ndarray, Bb: np.ndarray, rhs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """The forward sweep: S_k^-1 (F, n, n), y (F, n, r) (None without rhs) and log det H = sum_k log |det S_k|."""
    F = D.shape[0]
    Sinv = np.empty_like(D)
    y = None if rhs is None else np.empty_like(rhs)
    Sinv[0], logdet = _symmetric_inverse(D[0])
    if y is not None:
        y[0] = rhs[0]
    for k in range(1, F):
        L = _left(Bb, Sinv[k - 1])  # B S_{k-1}^-1
        Sinv[k], ld = _symmetric_inverse(D[k] - _left(Bb, L.T))  # B S^-1 B^T = B (B S^-1)^T, S^-1 symmetric
        logdet += ld
        if y is not None:
            y[k] = rhs[k] - L @ y[k - 1]
    return Sinv, y, logdet


def solve_and_marginals(D: np.ndarray, Bb: np.ndarray, rhs: np.ndarray, covariances: bool = True
                        ) -> tuple[np.ndarray, np.ndarray | None, float]:
    """One forward sweep for all three: dx (F, n, r) solving H dx = rhs, the diagonal blocks Sigma (F, n, n) of
    H^-1, symmetrised (None unless ``covariances``), and log det H (log |det| where H is indefinite)."""
    Sinv, y, ld = _forward(D, Bb, rhs)
    dx = np.empty_like(rhs)
    dx[-1] = Sinv[-1] @ y[-1]
    for k in range(D.shape[0] - 2, -1, -1):
        dx[k] = Sinv[k] @ (y[k] - _left(Bb, dx[k + 1], transpose=True))
    if not covariances:
        return dx, None, ld
    Sigma = np.empty_like(D)
    Sigma[-1] = Sinv[-1]
    for k in range(D.shape[0] - 2, -1, -1):
        G = _left(Bb, Sinv[k]).T  # S_k^-1 B^T = (B S_k^-1)^T
        Sigma[k] = Sinv[k] + (G @ Sigma[k + 1]) @ G.T
    _symmetrise(Sigma)
    return dx, Sigma, ld


def solve(D: np.ndarray, Bb: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """dx (F, n, r) solving H dx = rhs (module docstring)."""
    return solve_and_marginals(D, Bb, rhs, covariances=False)[0]


def logdet(D: np.ndarray, Bb: np.ndarray) -> float:
    """log det H (log |det| where H is indefinite): the forward sweep only."""
    return _forward(D, Bb, None)[2]


def marginals(D: np.ndarray, Bb: np.ndarray) -> tuple[np.ndarray, float]:
    """The diagonal blocks Sigma (F, n, n) of H^-1, symmetrised, and log det H (module docstring)."""
    _, Sigma, ld = solve_and_marginals(D, Bb, np.zeros(D.shape[:2] + (0,)))
    return Sigma, ld
