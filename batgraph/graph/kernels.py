"""Compiled inner loops (numba): the fast smoother's projection sums and block-tridiagonal solves, the pixel
noise's weighted triangulation and the fast filter's per-marker updates.

Why compiled code and not numpy: both loops are small dense work repeated many times. In numpy, the
projection sums make ~20 temporary arrays of the observation rows per evaluation, and the
block-tridiagonal recursion is a Python loop over frames of batched 6 x 6 inverses, which is overhead-bound
when few markers share a frame (issue "Speed a user feels": 5 x 24 x 160 is 2.5 ms per evaluation and 6 ms
per solve in numpy, 0.3 ms and 3 ms here). The arithmetic is the numpy version's, in the same order where
it matters (the sums over a cell's rows run in row order, as ``np.bincount`` does), so the answers agree to
rounding; tests/test_kernels.py checks them against plain numpy on random systems.

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside this file, or numba's
user-wide cache when that is not writable), so only the first run after an install pays the compile.

Threads: each compiled loop releases the GIL (``nogil``) and works on a range of markers, frames or row
chunks, so the public functions here split their work into :func:`threads` contiguous parts run on a
thread pool (the calling thread takes the first). Why Python threads and not numba's ``parallel=True``:
the same speed-up here, and numba's parallel compile made the first run after an install ~45 s longer.
The parts never change an answer: markers and points are independent, and the projection sums are added
per chunk of rows whose boundaries depend on the number of rows only, then over chunks in order.
``BATGRAPH_THREADS`` (environment) or :func:`set_threads` sets the number (default: the cores this
process may use); batgraph.batch gives each worker process its share of the cores.
Arithmetic follows numpy's error model (``error_model="numpy"``): a division by zero gives inf or NaN,
as in the numpy code these loops replace, instead of raising (e.g. a singular 3 x 3 block, whose
Gauss-Newton step is then rejected). This module imports only numpy and numba.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

from ..forked import usable_cores

ROBUST_CODE = {"none": 0, "huber": 1, "cauchy": 2}  # the ``robust`` argument of :func:`projection_sums`

# Rows per chunk of the projection sums (at least), and the most chunks: a function of the number of rows
# only, so that the sums (per chunk, then over chunks in order) do not depend on the number of threads.
MIN_CHUNK_ROWS = 2048
MAX_CHUNKS = 64


def _default_threads() -> int:
    text = os.environ.get("BATGRAPH_THREADS", "").strip()
    if text.isdigit() and int(text) > 0:
        return int(text)
    return usable_cores()


_threads = _default_threads()
_pool: ThreadPoolExecutor | None = None


def _forget_pool() -> None:
    """In a forked child the pool's threads do not exist (fork copies only the calling thread): start afresh."""
    global _pool
    _pool = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def needs_compiling() -> bool:
    """Whether the next run compiles the kernels (~1-2 min on a 2-core machine; the first run after an install
    or an update): numba's on-disk cache holds no compiled copy of the projection sums for this source.
    Reads numba's cache index through its internals; False where that fails (a newer numba: no note, no harm)."""
    try:
        return len(_projection_chunks._cache._cache_file._load_index()) == 0
    except Exception:  # noqa: BLE001  (private numba API: say nothing rather than fail)
        return False


def threads() -> int:
    """How many threads the kernels use (>= 1)."""
    return _threads


def set_threads(n: int) -> None:
    """Use ``n`` (>= 1) threads from now on (e.g. a batch worker's share of the cores)."""
    global _threads, _pool
    if n != _threads and _pool is not None:
        _pool.shutdown()
        _pool = None
    _threads = max(1, int(n))


def _split(n_items: int, min_part: int, run) -> None:
    """Call ``run(lo, hi)`` on contiguous parts of range(n_items), at most :func:`threads` of them and none
    under ``min_part`` items unless there is one part, in parallel (the first on the calling thread)."""
    global _pool
    k = max(1, min(_threads, n_items // max(min_part, 1)))
    if k == 1:
        run(0, n_items)
        return
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=_threads - 1, thread_name_prefix="batgraph-kernel")
    cuts = [(j * n_items) // k for j in range(k + 1)]
    futures = [_pool.submit(run, cuts[j], cuts[j + 1]) for j in range(1, k)]
    run(cuts[0], cuts[1])
    for f in futures:
        f.result()


def projection_sums(pt, cell, col, cam, P, uv, Linv, behind_px, robust, k, jacobian, total, closest,
                    Hw, Hc, g, rr) -> None:
    """Add every observation row's robust cost and Gauss-Newton terms into its (frame, marker) cell, in place.

    pt (3, n_cells) positions [m]; per row (n,): cell (int, f * M' + m, non-decreasing), col (int, marker
    column m), cam (int), uv (2, n) ideal pixels, Linv (3, n) the whitening (a, b, c) of L^-1 = [[a, 0], [b, c]];
    P (12, C) projection matrices row-major; behind_px (C,) the residual [px] of a point behind its camera
    (zero Jacobian; GTSAM's cheirality exception); robust ROBUST_CODE; k the loss's threshold [sigmas].
    Outputs (added to): total (M',) robust cost per marker; closest (M',) largest inverse depth [1/m]
    (max); and if ``jacobian``: Hw, Hc (n_cells, 6) upper-triangle entries of sum w Jw^T Jw and of the
    robust-curvature correction sum w a (Jw^T r)(Jw^T r)^T / |r|^2, g (n_cells, 3) sum w Jw^T r, rr
    (n_cells,) sum w |r|^2 (batgraph.graph.fast._Problem.evaluate defines each).
    """
    n = len(cell)
    n_chunks = min(MAX_CHUNKS, max(1, n // MIN_CHUNK_ROWS))
    bounds = np.empty(n_chunks + 1, np.int64)
    bounds[0], bounds[-1] = 0, n
    if n_chunks > 1:  # each cut moved back to the first row of its cell: a cell's rows stay in one chunk
        bounds[1:-1] = np.searchsorted(cell, cell[(np.arange(1, n_chunks) * n) // n_chunks])
    part, near = np.zeros((n_chunks, len(total))), np.zeros((n_chunks, len(total)))
    _split(n_chunks, 1, lambda j0, j1: _projection_chunks(
        j0, j1, bounds, pt, cell, col, cam, P, uv, Linv, behind_px, robust, k, jacobian, part, near, Hw, Hc, g, rr))
    total += part.sum(axis=0)
    np.maximum(closest, near.max(axis=0), out=closest)


@njit(cache=True, nogil=True, error_model="numpy")
def _projection_chunks(j0, j1, bounds, pt, cell, col, cam, P, uv, Linv, behind_px, robust, k, jacobian, part, near,
                       Hw, Hc, g, rr):  # pragma: no cover  (compiled)
    """:func:`projection_sums` over the row chunks j0..j1-1 (rows bounds[j]..bounds[j+1]-1), chunk j's cost
    and closest inverse depth per marker into part[j], near[j] (n_chunks, M')."""
    for j in range(j0, j1):
        _projection_rows(bounds[j], bounds[j + 1], pt, cell, col, cam, P, uv, Linv, behind_px, robust, k, jacobian,
                         part[j], near[j], Hw, Hc, g, rr)


@njit(cache=True, nogil=True, error_model="numpy")
def _projection_rows(lo, hi, pt, cell, col, cam, P, uv, Linv, behind_px, robust, k, jacobian, total, closest,
                     Hw, Hc, g, rr):  # pragma: no cover  (compiled)
    """:func:`projection_sums` over rows lo..hi-1, into total and closest (M',). The row arithmetic is
    :func:`_row_residual`'s, :func:`_rho_w`'s, :func:`_row_jacobian`'s and :func:`_curvature_a`'s (the fast
    filter's), written out here: calling them measured 6 % slower in this, the smoother's hottest loop."""
    kk = k * k
    for i in range(lo, hi):
        c, cm, mk = cell[i], cam[i], col[i]
        x, y, z = pt[0, c], pt[1, c], pt[2, c]
        depth = P[8, cm] * x + P[9, cm] * y + P[10, cm] * z + P[11, cm]
        inv = 1.0 / depth if depth != 0.0 else np.inf
        front = inv > 0.0 and inv < np.inf
        u = v = 0.0
        if front:
            u = (P[0, cm] * x + P[1, cm] * y + P[2, cm] * z + P[3, cm]) * inv
            v = (P[4, cm] * x + P[5, cm] * y + P[6, cm] * z + P[7, cm]) * inv
            e0, e1 = u - uv[0, i], v - uv[1, i]
        else:
            inv = 0.0
            e0 = e1 = behind_px[cm]
        if inv > closest[mk]:
            closest[mk] = inv
        a, b, cc = Linv[0, i], Linv[1, i], Linv[2, i]
        r0, r1 = a * e0, b * e0 + cc * e1
        d2 = r0 * r0 + r1 * r1
        if robust == 0:
            rho, w = 0.5 * d2, 1.0
        elif robust == 1:
            rn = np.sqrt(d2)
            if rn <= k:
                rho, w = 0.5 * d2, 1.0
            else:
                rho, w = k * rn - 0.5 * kk, k / rn
        else:
            rho, w = 0.5 * kk * np.log1p(d2 / kk), kk / (kk + d2)
        total[mk] += rho
        if not jacobian:
            continue
        J00 = J01 = J02 = J10 = J11 = J12 = 0.0
        if front:
            J00, J01 = (P[0, cm] - u * P[8, cm]) * inv, (P[1, cm] - u * P[9, cm]) * inv
            J02, J10 = (P[2, cm] - u * P[10, cm]) * inv, (P[4, cm] - v * P[8, cm]) * inv
            J11, J12 = (P[5, cm] - v * P[9, cm]) * inv, (P[6, cm] - v * P[10, cm]) * inv
        W00, W01, W02 = a * J00, a * J01, a * J02
        W10, W11, W12 = b * J00 + cc * J10, b * J01 + cc * J11, b * J02 + cc * J12
        jr0, jr1, jr2 = W00 * r0 + W10 * r1, W01 * r0 + W11 * r1, W02 * r0 + W12 * r1
        g[c, 0] += w * jr0
        g[c, 1] += w * jr1
        g[c, 2] += w * jr2
        rr[c] += w * d2
        Hw[c, 0] += w * (W00 * W00 + W10 * W10)
        Hw[c, 1] += w * (W00 * W01 + W10 * W11)
        Hw[c, 2] += w * (W00 * W02 + W10 * W12)
        Hw[c, 3] += w * (W01 * W01 + W11 * W11)
        Hw[c, 4] += w * (W01 * W02 + W11 * W12)
        Hw[c, 5] += w * (W02 * W02 + W12 * W12)
        if robust == 0 or d2 <= 0.0 or (robust == 1 and d2 <= kk):
            continue
        wa = w * (1.0 if robust == 1 else min(1.0, 2 * d2 / (kk + d2))) / d2
        Hc[c, 0] += wa * jr0 * jr0
        Hc[c, 1] += wa * jr0 * jr1
        Hc[c, 2] += wa * jr0 * jr2
        Hc[c, 3] += wa * jr1 * jr1
        Hc[c, 4] += wa * jr1 * jr2
        Hc[c, 5] += wa * jr2 * jr2


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _row_residual(P, cm, x, y, z, u_obs, v_obs, a, b, cc, behind):  # pragma: no cover  (compiled)
    """One projection row at the point (x, y, z) [m] seen by camera cm (P (12, C) as in projection_sums):
    (r0, r1, inv, u, v), the whitened residual r = L^-1 (pi(p) - uv) with L^-1 = [[a, 0], [b, cc]], the inverse
    depth [1/m] (0 behind the camera) and the projection (u, v) [px]. Behind the camera (depth <= 0, or not a
    number) r = L^-1 (behind, behind) (GTSAM's cheirality exception; :func:`_row_jacobian` is then zero)."""
    depth = P[8, cm] * x + P[9, cm] * y + P[10, cm] * z + P[11, cm]
    inv = 1.0 / depth if depth != 0.0 else np.inf
    u = v = 0.0
    if inv > 0.0 and inv < np.inf:
        u = (P[0, cm] * x + P[1, cm] * y + P[2, cm] * z + P[3, cm]) * inv
        v = (P[4, cm] * x + P[5, cm] * y + P[6, cm] * z + P[7, cm]) * inv
        e0, e1 = u - u_obs, v - v_obs
    else:
        inv = 0.0
        e0 = e1 = behind
    return a * e0, b * e0 + cc * e1, inv, u, v


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _row_jacobian(P, cm, u, v, inv, a, b, cc):  # pragma: no cover  (compiled)
    """The whitened Jacobian L^-1 d pi / dp [1/m] of a row (:func:`_row_residual`'s u, v, inv), row-major
    (W00, W01, W02, W10, W11, W12); zero behind the camera (inv = 0)."""
    J00 = J01 = J02 = J10 = J11 = J12 = 0.0
    if inv > 0.0:
        J00, J01 = (P[0, cm] - u * P[8, cm]) * inv, (P[1, cm] - u * P[9, cm]) * inv
        J02, J10 = (P[2, cm] - u * P[10, cm]) * inv, (P[4, cm] - v * P[8, cm]) * inv
        J11, J12 = (P[5, cm] - v * P[9, cm]) * inv, (P[6, cm] - v * P[10, cm]) * inv
    return a * J00, a * J01, a * J02, b * J00 + cc * J10, b * J01 + cc * J11, b * J02 + cc * J12


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rho_w(d2, robust, k, kk):  # pragma: no cover  (compiled)
    """(rho, w): the robust loss (ROBUST_CODE ``robust``, threshold k, kk = k^2) of a squared whitened norm
    d2 and its IRLS weight (batgraph.graph.cost.robust_loss)."""
    if robust == 0:
        return 0.5 * d2, 1.0
    if robust == 1:
        rn = np.sqrt(d2)
        if rn <= k:
            return 0.5 * d2, 1.0
        return k * rn - 0.5 * kk, k / rn
    return 0.5 * kk * np.log1p(d2 / kk), kk / (kk + d2)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _curvature_a(d2, robust, kk):  # pragma: no cover  (compiled)
    """a of the robust loss's curvature term w a (Jw^T r)(Jw^T r)^T / |r|^2 (0 where there is none: no
    robust loss, |r| = 0, or inside Huber's k): a = 1 beyond Huber's k, Cauchy's a = min(1, 2 d2 / (k^2 + d2))
    (clamped so that the block stays positive semi-definite)."""
    if robust == 0 or d2 <= 0.0 or (robust == 1 and d2 <= kk):
        return 0.0
    return 1.0 if robust == 1 else min(1.0, 2 * d2 / (kk + d2))


# Blocks up to this size are multiplied and inverted by plain loops (a BLAS / LAPACK call costs more than
# a 6 x 6 product); larger ones (segment groups: 6 x members) go to BLAS and LAPACK through numba.
SMALL_BLOCK = 12


# Blocks larger than SMALL_BLOCK and up to this size (the oscillating model's 18) are inverted by
# :func:`_cholesky_inverse` when positive definite: 3.5 us against 9.1 us for LAPACK's inverse and log det
# through numba at 18 x 18 (one LAPACK call costs more than the arithmetic there); larger, or indefinite, by LAPACK.
CHOLESKY_BLOCK = 36


@njit(cache=True, nogil=True, error_model="numpy")
def _cholesky_inverse(A, out, work):  # pragma: no cover  (compiled)
    """out = A^-1 (d, d) of a symmetric positive definite A (its lower triangle read) by Cholesky, A = L L^T
    (L in work's lower triangle), then L^-1 (in out) and A^-1 = L^-T L^-1; returns log det A, or NaN (out
    undefined) when a pivot is not positive (A not positive definite: the caller inverts it otherwise)."""
    d = A.shape[0]
    for j in range(d):
        s = A[j, j]
        for k in range(j):
            s -= work[j, k] * work[j, k]
        if not s > 0.0:
            return np.nan
        ljj = np.sqrt(s)
        work[j, j] = ljj
        for i in range(j + 1, d):
            t = A[i, j]
            for k in range(j):
                t -= work[i, k] * work[j, k]
            work[i, j] = t / ljj
    logdet = 0.0
    for j in range(d):
        logdet += 2.0 * np.log(work[j, j])
        out[j, j] = 1.0 / work[j, j]
        for i in range(j + 1, d):
            t = 0.0
            for k in range(j, i):
                t -= work[i, k] * out[k, j]
            out[i, j] = t / work[i, i]
    for i in range(d):  # (L^-T L^-1)[i, j] = sum_{k >= i} L^-1[k, i] L^-1[k, j] for j <= i, into work
        for j in range(i + 1):
            t = 0.0
            for k in range(i, d):
                t += out[k, i] * out[k, j]
            work[i, j] = t
    for i in range(d):
        for j in range(i + 1):
            out[i, j] = out[j, i] = work[i, j]
    return logdet


@njit(cache=True, nogil=True, error_model="numpy")
def _inverse(A, out, work, want_logdet=True):  # pragma: no cover  (compiled)
    """out = A^-1 (d, d) by Gauss-Jordan elimination with partial pivoting (LAPACK getri's answer to
    rounding); returns log |det A| (-inf for a singular A, whose out is then inf / NaN). work: (d, d).
    A block larger than SMALL_BLOCK: by :func:`_cholesky_inverse` (A symmetric; up to CHOLESKY_BLOCK and
    positive definite), else LAPACK, whose log det is a second factorisation: skipped (0 returned) unless
    ``want_logdet``."""
    d = A.shape[0]
    if d > SMALL_BLOCK:
        if d <= CHOLESKY_BLOCK:
            logdet = _cholesky_inverse(A, out, work)
            if not np.isnan(logdet):
                return logdet
        out[:] = np.linalg.inv(A)
        return np.linalg.slogdet(A)[1] if want_logdet else 0.0
    return _gauss_jordan(A, out, work)


@njit(cache=True, nogil=True, error_model="numpy")
def _gauss_jordan(A, out, work):  # pragma: no cover  (compiled)
    """:func:`_inverse` of a small block (plain loops, no LAPACK: quick to compile): out = A^-1, returns
    log |det A| (-inf for a singular A)."""
    d = A.shape[0]
    for i in range(d):
        for j in range(d):
            work[i, j] = A[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    logdet = 0.0
    for c in range(d):
        p, big = c, abs(work[c, c])
        for r in range(c + 1, d):
            if abs(work[r, c]) > big:
                p, big = r, abs(work[r, c])
        if p != c:
            for j in range(d):
                work[c, j], work[p, j] = work[p, j], work[c, j]
                out[c, j], out[p, j] = out[p, j], out[c, j]
        piv = work[c, c]
        logdet += np.log(abs(piv))
        inv_piv = 1.0 / piv
        for j in range(d):
            work[c, j] *= inv_piv
            out[c, j] *= inv_piv
        for r in range(d):
            if r == c:
                continue
            f = work[r, c]
            if f == 0.0:
                continue
            for j in range(d):
                work[r, j] -= f * work[c, j]
                out[r, j] -= f * out[c, j]
    return logdet


@njit(cache=True, nogil=True, error_model="numpy")
def _matmul(A, B, out):  # pragma: no cover  (compiled)
    """out = A @ B for (a, q) and (q, b) arrays (either may be a transposed view)."""
    if A.shape[1] > SMALL_BLOCK:
        out[:] = np.dot(A, B)
        return
    _loop_matmul(A, B, out)


@njit(cache=True, nogil=True, error_model="numpy")
def _loop_matmul(A, B, out):  # pragma: no cover  (compiled)
    """:func:`_matmul` by plain loops (no BLAS: quick to compile)."""
    a, q = A.shape
    b = B.shape[1]
    for i in range(a):
        for j in range(b):
            t = 0.0
            for l in range(q):
                t += A[i, l] * B[l, j]
            out[i, j] = t


@njit(cache=True, nogil=True, error_model="numpy")
def _left(Bb, X, out, transpose):  # pragma: no cover  (compiled)
    """out = B X (or B^T X) for the block-diagonal B = diag(Bb[0], ..., Bb[g-1]) (Bb (g, b, b)) and X (g b, r)."""
    g, b = Bb.shape[0], Bb.shape[1]
    for j in range(g):
        _matmul(Bb[j].T if transpose else Bb[j], X[j * b:(j + 1) * b], out[j * b:(j + 1) * b])


@njit(cache=True, nogil=True, error_model="numpy")
def _forward_sweep(D, B, m, Sinv, L, S, work, rhs, y, Ly, want_logdet):  # pragma: no cover  (compiled)
    """The forward sweep of marker m: Sinv[k] = S_k^-1 (F, d, d) with S_0 = D_0, S_k = D_k - L_k B^T,
    L_k = B S_{k-1}^-1; and when rhs (F, M, d, r) has frames, y[k] = rhs_k - L_k y_{k-1} (F, d, r).
    B (M, g, b, b): each marker's sub-diagonal block, block-diagonal with g blocks of b x b (d = g b; g > 1 for
    a segment group, whose members' motions are independent): products with it cost g b^2 d, not d^3, and
    S_k = (B L_k^T)^T (S_{k-1}^-1 is symmetric). Returns sum_k log |det S_k| (0 for large blocks unless
    ``want_logdet``). L, S, work: (d, d) scratch; Ly (d, r) scratch."""
    F, d = D.shape[0], D.shape[2]
    with_rhs = rhs.shape[0] > 0
    Bm = B[m]
    g = Bm.shape[0]
    logdet = _inverse(D[0, m], Sinv[0], work, want_logdet)
    if with_rhs:
        y[0] = rhs[0, m]
    for k in range(1, F):
        _left(Bm, Sinv[k - 1], L, False)
        if g == 1:
            _matmul(L, Bm[0].T, S)
            for i in range(d):
                for j in range(d):
                    S[i, j] = D[k, m, i, j] - S[i, j]
            logdet += _inverse(S, Sinv[k], work, want_logdet)
        else:
            for i in range(d):
                for j in range(d):
                    work[i, j] = L[j, i]
            _left(Bm, work, S, False)  # B L^T = (L B^T)^T
            for i in range(d):
                for j in range(d):
                    work[i, j] = D[k, m, i, j] - S[j, i]
            logdet += _inverse(work, Sinv[k], S, want_logdet)
        if with_rhs:
            _matmul(L, y[k - 1], Ly)
            for i in range(d):
                for c in range(y.shape[2]):
                    y[k, i, c] = rhs[k, m, i, c] - Ly[i, c]
    return logdet


_NO_RHS = np.empty((0, 1, 1, 1))  # the rhs argument of _forward_sweep when there is none


# The fewest (frame, marker) blocks of a tridiagonal system worth handing to another thread.
MIN_PART_BLOCKS = 2048


def _markers_split(D: np.ndarray, run) -> None:
    """run(m0, m1) over contiguous ranges of the markers of D (F, M, d, d), in parallel (see :func:`_split`)."""
    F, M = D.shape[:2]
    _split(M, -(-MIN_PART_BLOCKS // max(F, 1)), run)


def _typed(a: np.ndarray) -> np.ndarray:
    """``a`` C-contiguous and writeable (copied if not): numba compiles a kernel once per layout and
    read-only flag of its arguments, so a read-only view (np.broadcast_to of one marker) or a fancy-indexed
    (Fortran-ordered) array would compile a second copy of it on a first run (~10 s for the tridiagonal solve)."""
    return np.require(a, requirements="CW")


def _blocks(B: np.ndarray) -> np.ndarray:
    """The sub-diagonal blocks as (M, g, b, b) C-contiguous: (M, d, d) is one block (g = 1); (M, g, b, b) is a
    block-diagonal B of g blocks (a segment group's members, batgraph.graph.rigid)."""
    return _typed(B[:, None] if B.ndim == 3 else B)


def tridiagonal_solve(D: np.ndarray, B: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """dx (F, M, d, r) solving H dx = rhs for every marker's block-tridiagonal H (batgraph.graph.fast._solve).

    D (F, M, d, d) diagonal blocks; B (M, d, d) the sub-diagonal block H[k+1, k] of each marker, constant
    over frames, or (M, g, b, b) the blocks of a block-diagonal one (d = g b); rhs (F, M, d, r); D and rhs
    C-contiguous. Forward: S_k and y_k = rhs_k - B S_{k-1}^-1 y_{k-1}; back:
    dx_{F-1} = S^-1 y, dx_k = S_k^-1 (y_k - B^T dx_{k+1}).
    """
    out = np.empty_like(rhs)
    B = _blocks(B)
    _markers_split(D, lambda m0, m1: _solve_markers(m0, m1, D, B, rhs, out))
    return out


def tridiagonal_logdet(D: np.ndarray, B: np.ndarray) -> np.ndarray:
    """log det H (M,) of every marker's block-tridiagonal H (D (F, M, d, d), B as tridiagonal_solve's): sum_k
    log det S_k."""
    out = np.empty(D.shape[1])
    B = _blocks(B)
    _markers_split(D, lambda m0, m1: _logdet_markers(m0, m1, D, B, out))
    return out


def tridiagonal_marginals(D: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks Sigma (F, M, d, d) of H^-1 and log det H (M,) (batgraph.graph.fast.marginals):
    Sigma_{F-1} = S_{F-1}^-1, Sigma_k = S_k^-1 + G_k Sigma_{k+1} G_k^T with G_k = S_k^-1 B^T, symmetrised."""
    Sigma, ld = np.empty_like(D), np.empty(D.shape[1])
    B = _blocks(B)
    _markers_split(D, lambda m0, m1: _marginals_markers(m0, m1, D, B, Sigma, ld))
    return Sigma, ld


def tridiagonal_motion_trace(D: np.ndarray, B: np.ndarray, AtQiA: np.ndarray, Qi: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """log det H (M,) and tr(H^-1 H_m) (M,) of every marker's block-tridiagonal H, where H_m is its motion part:
    the block-tridiagonal matrix with diagonal blocks AtQiA (frames 0..F-2) plus Qi (frames 1..F-1) and
    sub-diagonal blocks B (batgraph.graph.fast.motion_trace, the gradient of the evidence in the noise level).

    D (F, M, d, d); B, AtQiA, Qi (M, d, d). With Sigma = H^-1 from the backward recursion (as
    :func:`tridiagonal_marginals`) and the lag-one blocks Sigma_{k,k+1} = -G_k Sigma_{k+1}, the trace is
    sum_k tr(Sigma_k M_k) + 2 sum_k tr(Sigma_{k,k+1} B); only two frames' Sigma are kept (memory O(F d^2) per
    thread for the forward sweep's inverses).
    """
    if B.ndim != 3:  # a block-diagonal B (segment groups) is not supported here: the search runs without them
        raise ValueError(f"B must be one (d, d) block per marker, shape (M, d, d), got {B.shape}")
    ld, tr = np.empty(D.shape[1]), np.empty(D.shape[1])
    Bb = _blocks(B)
    AtQiA, Qi = _typed(AtQiA), _typed(Qi)
    _markers_split(D, lambda m0, m1: _motion_trace_markers(m0, m1, D, Bb, AtQiA, Qi, ld, tr))
    return ld, tr


def tridiagonal_solve_motion_trace(D: np.ndarray, B: np.ndarray, AtQiA: np.ndarray, Qi: np.ndarray,
                                   rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`tridiagonal_solve` and :func:`tridiagonal_motion_trace` of the same H in one forward sweep:
    (dx (F, M, d, r), log det H (M,), tr(H^-1 H_m) (M,)); arguments as theirs (B (M, d, d))."""
    if B.ndim != 3:
        raise ValueError(f"B must be one (d, d) block per marker, shape (M, d, d), got {B.shape}")
    out, ld, tr = np.empty_like(rhs), np.empty(D.shape[1]), np.empty(D.shape[1])
    Bb = _blocks(B)
    AtQiA, Qi = _typed(AtQiA), _typed(Qi)
    _markers_split(D, lambda m0, m1: _solve_trace_markers(m0, m1, D, Bb, AtQiA, Qi, rhs, out, ld, tr))
    return out, ld, tr


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_markers(m0, m1, D, B, rhs, out):  # pragma: no cover  (compiled)
    """:func:`tridiagonal_solve` for markers m0..m1-1, into out (F, M, d, r)."""
    F, M, d, r = rhs.shape
    Sinv = np.empty((F, d, d))
    y = np.empty((F, d, r))
    L, S, work = np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    Ly, t_ = np.empty((d, r)), np.empty((d, r))
    for m in range(m0, m1):
        _forward_sweep(D, B, m, Sinv, L, S, work, rhs, y, Ly, False)
        _matmul(Sinv[F - 1], y[F - 1], out[F - 1, m])
        for k in range(F - 2, -1, -1):
            _back_step(B[m], Sinv[k], y[k], out[k + 1, m], out[k, m], Ly, t_)


@njit(cache=True, nogil=True, error_model="numpy")
def _back_step(Bm, Sinv_k, y_k, dx_next, dx_k, Ly, t_):  # pragma: no cover  (compiled)
    """One back-substitution step: dx_k = S_k^-1 (y_k - B^T dx_{k+1}) into dx_k (d, r); Ly, t_ (d, r) scratch."""
    _left(Bm, dx_next, Ly, True)
    for i in range(t_.shape[0]):
        for c in range(t_.shape[1]):
            t_[i, c] = y_k[i, c] - Ly[i, c]
    _matmul(Sinv_k, t_, dx_k)


@njit(cache=True, nogil=True, error_model="numpy")
def _logdet_markers(m0, m1, D, B, out):  # pragma: no cover  (compiled)
    """:func:`tridiagonal_logdet` for markers m0..m1-1, into out (M,)."""
    F, d = D.shape[0], D.shape[2]
    Sinv = np.empty((F, d, d))
    L, S, work = np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    for m in range(m0, m1):
        out[m] = _forward_sweep(D, B, m, Sinv, L, S, work, _NO_RHS, Sinv, L, True)


@njit(cache=True, nogil=True, error_model="numpy")
def _marginals_markers(m0, m1, D, B, Sigma, ld):  # pragma: no cover  (compiled)
    """:func:`tridiagonal_marginals` for markers m0..m1-1, into Sigma (F, M, d, d) and ld (M,)."""
    F, d = D.shape[0], D.shape[2]
    Sinv = np.empty((F, d, d))
    L, S, work = np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    G, GS = np.empty((d, d)), np.empty((d, d))
    for m in range(m0, m1):
        ld[m] = _forward_sweep(D, B, m, Sinv, L, S, work, _NO_RHS, Sinv, L, True)
        Sigma[F - 1, m] = Sinv[F - 1]
        for k in range(F - 2, -1, -1):
            if B.shape[1] == 1:
                _matmul(Sinv[k], B[m, 0].T, G)
            else:  # G = S_k^-1 B^T = (B S_k^-1)^T
                _left(B[m], Sinv[k], GS, False)
                for i in range(d):
                    for j in range(d):
                        G[i, j] = GS[j, i]
            _matmul(G, Sigma[k + 1, m], GS)
            _matmul(GS, G.T, S)
            for i in range(d):
                for j in range(d):
                    Sigma[k, m, i, j] = Sinv[k, i, j] + S[i, j]
        for k in range(F):
            for i in range(d):
                for j in range(i + 1, d):
                    s = 0.5 * (Sigma[k, m, i, j] + Sigma[k, m, j, i])
                    Sigma[k, m, i, j] = Sigma[k, m, j, i] = s


@njit(cache=True, nogil=True, error_model="numpy")
def _motion_trace_markers(m0, m1, D, B, AtQiA, Qi, ld, tr):  # pragma: no cover  (compiled)
    """:func:`tridiagonal_motion_trace` for markers m0..m1-1 (B (M, 1, d, d)), into ld and tr (M,)."""
    F, d = D.shape[0], D.shape[2]
    Sinv = np.empty((F, d, d))
    L, S, work = np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    G, GS, nxt, cur = np.empty((d, d)), np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    for m in range(m0, m1):
        ld[m] = _forward_sweep(D, B, m, Sinv, L, S, work, _NO_RHS, Sinv, L, True)
        nxt[:] = Sinv[F - 1]
        t = _trace_last(nxt, Qi[m]) if F > 1 else 0.0
        for k in range(F - 2, -1, -1):
            t = _trace_step(Sinv[k], B[m, 0], nxt, AtQiA[m], Qi[m], k > 0, G, GS, S, cur, t)
            nxt[:] = cur
        tr[m] = t


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_last(Sigma_last, Qi_m):  # pragma: no cover  (compiled)
    """The last frame's term of tr(H^-1 H_m): tr(Sigma_{F-1} Qi)."""
    t = 0.0
    for i in range(Qi_m.shape[0]):
        for j in range(Qi_m.shape[0]):
            t += Sigma_last[i, j] * Qi_m[j, i]
    return t


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_step(Sinv_k, Bm, nxt, AtQiA_m, Qi_m, with_qi, G, GS, S, cur, t):  # pragma: no cover  (compiled)
    """One step of the backward recursion: Sigma_k into cur from Sigma_{k+1} (nxt) and S_k^-1; returns the
    running trace t plus frame k's terms of tr(H^-1 H_m): tr(Sigma_k AtQiA) (+ tr(Sigma_k Qi) where ``with_qi``,
    k > 0) + 2 tr(Sigma_{k,k+1} B), added term by term. G, GS, S: (d, d) scratch."""
    d = Qi_m.shape[0]
    _matmul(Sinv_k, Bm.T, G)
    _matmul(G, nxt, GS)  # -Sigma_{k,k+1}
    _matmul(GS, G.T, S)
    for i in range(d):
        for j in range(d):
            cur[i, j] = Sinv_k[i, j] + S[i, j]
    for i in range(d):
        for j in range(d):
            t -= 2.0 * GS[i, j] * Bm[j, i]
            t += cur[i, j] * AtQiA_m[j, i]
            if with_qi:
                t += cur[i, j] * Qi_m[j, i]
    return t


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_trace_markers(m0, m1, D, B, AtQiA, Qi, rhs, out, ld, tr):  # pragma: no cover  (compiled)
    """:func:`tridiagonal_solve_motion_trace` for markers m0..m1-1: :func:`_solve_markers`' back-substitution
    and :func:`_motion_trace_markers`' backward recursion in one loop after one forward sweep."""
    F, M, d, r = rhs.shape
    Sinv = np.empty((F, d, d))
    y = np.empty((F, d, r))
    L, S, work = np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    Ly, t_ = np.empty((d, r)), np.empty((d, r))
    G, GS, nxt, cur = np.empty((d, d)), np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    for m in range(m0, m1):
        ld[m] = _forward_sweep(D, B, m, Sinv, L, S, work, rhs, y, Ly, True)
        _matmul(Sinv[F - 1], y[F - 1], out[F - 1, m])
        nxt[:] = Sinv[F - 1]
        t = _trace_last(nxt, Qi[m]) if F > 1 else 0.0
        for k in range(F - 2, -1, -1):
            _back_step(B[m], Sinv[k], y[k], out[k + 1, m], out[k, m], Ly, t_)
            t = _trace_step(Sinv[k], B[m, 0], nxt, AtQiA[m], Qi[m], k > 0, G, GS, S, cur, t)
            nxt[:] = cur
        tr[m] = t


@njit(cache=True, nogil=True, error_model="numpy")
def _observe(P, c, x, y, z, u_obs, v_obs, J):  # pragma: no cover  (compiled)
    """Residual (u_obs - u, v_obs - v) [px] of camera c (P (C, 3, 4)) at (x, y, z) [m] and J = d(u, v)/dp
    (2, 3) into J; (0, 0) and J = 0 for a point within 1e-9 m of the camera plane or behind it."""
    depth = P[c, 2, 0] * x + P[c, 2, 1] * y + P[c, 2, 2] * z + P[c, 2, 3]
    if not depth > 1e-9:
        J[:] = 0.0
        return 0.0, 0.0
    inv = 1.0 / depth
    u = (P[c, 0, 0] * x + P[c, 0, 1] * y + P[c, 0, 2] * z + P[c, 0, 3]) * inv
    v = (P[c, 1, 0] * x + P[c, 1, 1] * y + P[c, 1, 2] * z + P[c, 1, 3]) * inv
    for j in range(3):
        J[0, j] = (P[c, 0, j] - u * P[c, 2, j]) * inv
        J[1, j] = (P[c, 1, j] - v * P[c, 2, j]) * inv
    return u_obs - u, v_obs - v


def weighted_triangulation(P, uv, W, use, xyz, iters, r_out, h_out, Sigma) -> None:
    """Weighted Gauss-Newton triangulation of every (frame, marker) point (batgraph.pixel_noise.estimate_pixel_sigma).

    P (C, 3, 4) projection matrices to ideal pixels; uv (C, F, M, 2) ideal pixels; W (C, F, M, 2, 2) each
    observation's information [1/px^2]; use (C, F, M) bool; xyz (F, M, 3) [m], refined in place where
    finite (``iters`` steps, each kept only where it lowers the point's cost sum r^T W r; a point whose
    residuals all vanish, i.e. behind every camera, keeps its start). Writes r_out (C, F, M, 2) = uv - pi(p)
    at the final points, Sigma (F, M, 3, 3) = (sum_c J^T W J)^-1 where it is invertible (left as given
    elsewhere) and h_out (C, F, M) = sum(A * Sigma'), each used observation's leverage with A = J^T W J
    (zero behind the camera) and Sigma' = Sigma with its non-finite entries as 0 (left as given where not used).
    The sum runs in numpy's order for ``np.sum(A * Sigma', axis=(-2, -1))`` (:func:`_leverage`), so h_out is
    that expression's, bit for bit, without its (C, F, M, 3, 3) arrays (62 MB each at 30 x 180 x 160).
    """
    F, M = use.shape[1:]
    _split(F, -(-MIN_PART_BLOCKS // max(M, 1)),
           lambda f0, f1: _triangulate_frames(f0, f1, P, uv, W, use, xyz, iters, r_out, h_out, Sigma))


@njit(cache=True, nogil=True, error_model="numpy")
def _leverage(A, S):  # pragma: no cover  (compiled)
    """sum(A * S') over the 9 entries of 3x3 A and S (S' = S, non-finite entries as 0), added in numpy's
    pairwise order for a contiguous 9-element sum: ((p0 + p1) + (p2 + p3)) + ((p4 + p5) + (p6 + p7)), then p8."""
    p0, p1, p2 = _entry(A, S, 0, 0), _entry(A, S, 0, 1), _entry(A, S, 0, 2)
    p3, p4, p5 = _entry(A, S, 1, 0), _entry(A, S, 1, 1), _entry(A, S, 1, 2)
    p6, p7, p8 = _entry(A, S, 2, 0), _entry(A, S, 2, 1), _entry(A, S, 2, 2)
    return (((p0 + p1) + (p2 + p3)) + ((p4 + p5) + (p6 + p7))) + p8


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _entry(A, S, i, j):  # pragma: no cover  (compiled)
    """A[i, j] * S[i, j], with a non-finite S[i, j] as 0."""
    return A[i, j] * (S[i, j] if np.isfinite(S[i, j]) else 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _triangulate_frames(f0, f1, P, uv, W, use, xyz, iters, r_out, h_out, Sigma):  # pragma: no cover  (compiled)
    """:func:`weighted_triangulation` of frames f0..f1-1."""
    C, F, M = use.shape
    J = np.empty((2, 3))
    H, Hr, work = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    g, step, trial = np.empty(3), np.empty(3), np.empty(3)
    A = np.empty((C, 3, 3))  # each camera's J^T W J at the final point
    for f in range(f0, f1):
        for m in range(M):
            if not (np.isfinite(xyz[f, m, 0]) and np.isfinite(xyz[f, m, 1]) and np.isfinite(xyz[f, m, 2])):
                continue
            for it in range(iters + 1):
                H[:] = 0.0
                g[:] = 0.0
                cost = 0.0
                for c in range(C):
                    if not use[c, f, m]:
                        continue
                    r0, r1 = _observe(P, c, xyz[f, m, 0], xyz[f, m, 1], xyz[f, m, 2], uv[c, f, m, 0], uv[c, f, m, 1], J)
                    w00, w01, w11 = W[c, f, m, 0, 0], W[c, f, m, 0, 1], W[c, f, m, 1, 1]
                    cost += w00 * r0 * r0 + 2 * w01 * r0 * r1 + w11 * r1 * r1
                    for i in range(3):
                        a0 = w00 * J[0, i] + w01 * J[1, i]  # (W J)^T row i
                        a1 = w01 * J[0, i] + w11 * J[1, i]
                        g[i] += a0 * r0 + a1 * r1
                        for j in range(3):
                            H[i, j] += a0 * J[0, j] + a1 * J[1, j]
                    if it == iters:  # the final point: per-observation outputs
                        r_out[c, f, m, 0], r_out[c, f, m, 1] = r0, r1
                        for i in range(3):
                            a0 = w00 * J[0, i] + w01 * J[1, i]
                            a1 = w01 * J[0, i] + w11 * J[1, i]
                            for j in range(3):
                                A[c, i, j] = a0 * J[0, j] + a1 * J[1, j]
                if it == iters:
                    if abs(np.linalg.det(H)) > 0:
                        _inverse(H, Sigma[f, m], work)
                    for c in range(C):
                        if use[c, f, m]:
                            h_out[c, f, m] = _leverage(A[c], Sigma[f, m])
                    break
                for i in range(3):
                    for j in range(3):
                        Hr[i, j] = H[i, j] + (1e-12 if i == j else 0.0)
                _inverse(Hr, work, H)  # H is free now: used as scratch
                for i in range(3):
                    step[i] = work[i, 0] * g[0] + work[i, 1] * g[1] + work[i, 2] * g[2]
                    trial[i] = xyz[f, m, i] + step[i]
                new_cost, nonzero = 0.0, False
                for c in range(C):
                    if not use[c, f, m]:
                        continue
                    r0, r1 = _observe(P, c, trial[0], trial[1], trial[2], uv[c, f, m, 0], uv[c, f, m, 1], J)
                    nonzero = nonzero or r0 != 0.0 or r1 != 0.0
                    new_cost += W[c, f, m, 0, 0] * r0 * r0 + 2 * W[c, f, m, 0, 1] * r0 * r1 + W[c, f, m, 1, 1] * r1 * r1
                if new_cost < cost and nonzero:
                    xyz[f, m] = trial


# ----- the fast filter (batgraph.graph.fast_filter) ---------------------------------------------------------
# Markers per thread at least: a marker's whole filter (every frame's update) is ~10-100 us.
MIN_FILTER_MARKERS = 16


def filter_markers(f0, f1, join, tri, A, Q, P0, bounds, cam, P, uv, Linv, behind_px, robust, k, max_iterations,
                   step_tol, rel_tol, mean, cov, xyz, cov_out, iterations, discarded) -> None:
    """Frames f0..f1-1 of the fast filter (batgraph.graph.fast_filter), every marker independently, in place.

    join (M,) int: each marker's joining frame (-1: never); tri (M, 3) [m] its triangulation there. A, Q,
    P0 (d, d): transition, process noise and joining prior (fast_filter.motion_matrices). The rows (camera
    cam, ideal pixels uv (2, n), whitening Linv (3, n) as (a, b, c) of [[a, 0], [b, c]]; P (12, C) and
    behind_px (C,) as in :func:`projection_sums`) are sorted by (marker, frame): those of marker m on frame
    f are bounds[m F + f]..bounds[m F + f + 1]-1 (bounds (M F + 1,)). robust ROBUST_CODE, k its threshold.
    mean (M, d), cov (M, d, d): each joined marker's state after frame f0 - 1 (the joining prior at its
    joining frame replaces it), updated to after frame f1 - 1. Writes xyz (F, M, 3) and cov_out (F, M, 3, 3)
    of frames f0..f1-1 from each marker's joining frame on (left as given before it), raises
    iterations (M,) to the most Levenberg-Marquardt iterations a marker's update took and adds to
    discarded (M,) its updates discarded because their posterior information is singular to rounding
    (:func:`_filter_update`: the marker keeps its prediction on that frame).
    Each update is batgraph.graph.fast_filter's (its module docstring); tests/test_fast_filter.py checks it
    against a textbook iterated extended Kalman filter and against iSAM2.
    """
    _split(len(join), MIN_FILTER_MARKERS, lambda m0, m1: _filter_markers(
        m0, m1, f0, f1, join, tri, A, Q, P0, bounds, cam, P, uv, Linv, behind_px, robust, k, max_iterations,
        step_tol, rel_tol, mean, cov, xyz, cov_out, iterations, discarded))


@njit(cache=True, nogil=True, error_model="numpy")
def _filter_markers(m0, m1, f0, f1, join, tri, A, Q, P0, bounds, cam, P, uv, Linv, behind_px, robust, k,
                    max_iterations, step_tol, rel_tol, mean, cov, xyz, cov_out, iterations,
                    discarded):  # pragma: no cover  (compiled)
    """:func:`filter_markers` of markers m0..m1-1 (compiled; plain loops throughout, which compile quickly)."""
    F, d = xyz.shape[0], A.shape[0]
    rows = np.empty((2, 10, max(behind_px.shape[0], 1)))  # two buffers of rows: r0, r1, inv, W (6), d2
    AP, scratch = np.empty((d, d)), np.empty((d, d))
    AT = np.ascontiguousarray(A.T)
    x = np.empty(d)
    for m in range(m0, m1):
        j = join[m]
        if j < 0:
            continue
        for f in range(max(f0, j), f1):
            if f == j:
                for i in range(d):
                    mean[m, i] = tri[m, i] if i < 3 else 0.0
                    for q in range(d):
                        cov[m, i, q] = P0[i, q]
            else:  # predict: A mean, A cov A^T + Q
                for i in range(d):
                    t = 0.0
                    for q in range(d):
                        t += A[i, q] * mean[m, q]
                    x[i] = t
                mean[m] = x
                _loop_matmul(A, cov[m], AP)
                _loop_matmul(AP, AT, scratch)
                for i in range(d):
                    for q in range(d):
                        cov[m, i, q] = scratch[i, q] + Q[i, q]
            lo, hi = bounds[m * F + f], bounds[m * F + f + 1]
            it, dropped = _filter_update(mean[m], cov[m], lo, hi, cam, P, uv, Linv, behind_px, robust, k,
                                         max_iterations, step_tol, rel_tol, rows)
            iterations[m] = max(iterations[m], it)
            discarded[m] += dropped
            for i in range(3):
                xyz[f, m, i] = mean[m, i]
                for q in range(3):
                    cov_out[f, m, i, q] = cov[m, i, q]


@njit(cache=True, nogil=True, error_model="numpy")
def _filter_cost(p, mu, Lp, lo, hi, cam, P, uv, Linv, behind_px, robust, k, out):  # pragma: no cover
    """0.5 (p - mu)^T Lp (p - mu) + sum rho over rows lo..hi-1 at p (inf if not a number), with each row's
    r0, r1, inverse depth, whitened Jacobian (6) and d2 into out[:, i - lo] (10, n)."""
    kk = k * k
    total = 0.0
    for i in range(3):
        for q in range(3):
            total += 0.5 * (p[i] - mu[i]) * Lp[i, q] * (p[q] - mu[q])
    for i in range(lo, hi):
        cm = cam[i]
        a, b, cc = Linv[0, i], Linv[1, i], Linv[2, i]
        r0, r1, inv, u, v = _row_residual(P, cm, p[0], p[1], p[2], uv[0, i], uv[1, i], a, b, cc, behind_px[cm])
        W00, W01, W02, W10, W11, W12 = _row_jacobian(P, cm, u, v, inv, a, b, cc)
        n = i - lo
        out[0, n], out[1, n], out[2, n] = r0, r1, inv
        out[3, n], out[4, n], out[5, n], out[6, n], out[7, n], out[8, n] = W00, W01, W02, W10, W11, W12
        d2 = r0 * r0 + r1 * r1
        out[9, n] = d2
        total += _rho_w(d2, robust, k, kk)[0]
    return np.inf if np.isnan(total) else total


@njit(cache=True, nogil=True, error_model="numpy")
def _filter_system(rows, n, robust, k, curvature, g, H):  # pragma: no cover  (compiled)
    """The observations' part of the update's Gauss-Newton system from rows (10, n) (:func:`_filter_cost`'s):
    g = sum w Jw^T r and H = sum w (Jw^T Jw - curvature a (Jw^T r)(Jw^T r)^T / |r|^2), w the IRLS weights,
    a the robust loss's curvature (:func:`_curvature_a`); curvature 1.0 (a Newton-type step) or 0.0 (IRLS)."""
    kk = k * k
    jr = np.empty(3)
    g[:] = 0.0
    H[:] = 0.0
    for i in range(n):
        r0, r1, d2 = rows[0, i], rows[1, i], rows[9, i]
        w = _rho_w(d2, robust, k, kk)[1]
        for q in range(3):
            jr[q] = rows[3 + q, i] * r0 + rows[6 + q, i] * r1
            g[q] += w * jr[q]
        a = curvature * _curvature_a(d2, robust, kk)
        wa = w * a / d2 if a != 0.0 else 0.0
        for q in range(3):
            for s in range(q, 3):
                H[q, s] += w * (rows[3 + q, i] * rows[3 + s, i] + rows[6 + q, i] * rows[6 + s, i]) - wa * jr[q] * jr[s]
    for q in range(3):
        for s in range(q):
            H[q, s] = H[s, q]


@njit(cache=True, nogil=True, error_model="numpy")
def _filter_update(mean, cov, lo, hi, cam, P, uv, Linv, behind_px, robust, k, max_iterations, step_tol, rel_tol,
                   rows):  # pragma: no cover  (compiled)
    """The update of one marker (batgraph.graph.fast_filter's module docstring; state mean (d,), cov (d, d),
    updated in place) with its
    rows lo..hi-1; rows (2, 10, >= hi - lo) scratch (the current point's rows and a trial's). Returns the
    iterations taken and whether the update was discarded (state left as given): its posterior information
    is singular to rounding, so that its inverse is not finite. Met where mislabels drove a point to within
    1e-10 m of a camera centre: that camera's Jacobian, ~1e11 px/m, makes the information ~1e23 1/m^2 along
    its rows and the rest is lost to rounding."""
    d = mean.shape[0]
    n = hi - lo
    mu, p, g, dp, trial = mean[:3].copy(), mean[:3].copy(), np.empty(3), np.empty(3), np.empty(3)
    Ppp, Lp, S, work, H = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    for i in range(3):
        for q in range(3):
            Ppp[i, q] = cov[i, q]
    _gauss_jordan(Ppp, Lp, work)
    cur = 0
    c = _filter_cost(p, mu, Lp, lo, hi, cam, P, uv, Linv, behind_px, robust, k, rows[cur])
    lam, newton, it = 0.0, False, 0
    for _ in range(max_iterations):
        _filter_system(rows[cur], n, robust, k, 1.0 if newton else 0.0, g, H)
        for i in range(3):  # + the prior's terms, then Levenberg-Marquardt's damping
            for q in range(3):
                g[i] += Lp[i, q] * (p[q] - mu[q])
                H[i, q] += Lp[i, q]
        for i in range(3):
            H[i, i] *= 1.0 + lam
        singular = _gauss_jordan(H, S, work) == -np.inf  # a zero pivot: a NaN step, rejected and damped further
        step, finite = 0.0, True
        for i in range(3):
            dp[i] = np.nan if singular else -(S[i, 0] * g[0] + S[i, 1] * g[1] + S[i, 2] * g[2])
            trial[i] = p[i] + dp[i]
            if np.isnan(dp[i]):
                finite = False
            elif abs(dp[i]) > step:
                step = abs(dp[i])
        c_new = _filter_cost(trial, mu, Lp, lo, hi, cam, P, uv, Linv, behind_px, robust, k, rows[1 - cur])
        ok = c_new <= c
        rel = (c - c_new) / max(c, 2.2250738585072014e-308)  # the smallest normal double
        done = (ok and rel < rel_tol) or (finite and step < step_tol) or lam > 1e12  # 1e12: stuck
        it += 1
        if ok:
            p[:] = trial
            cur = 1 - cur
            c = c_new
            lam = lam / 10 if lam > 1e-9 else 0.0
        elif not newton:  # a rejected curvature step is retried as an IRLS step before damping grows
            lam = max(lam * 10, 1e-6)
        newton = ok
        if done:
            break
    # the covariance: (Lp + sum w Jw^T Jw)^-1 at the final point with the IRLS weights
    _filter_system(rows[cur], n, robust, k, 0.0, g, H)
    for i in range(3):
        for q in range(3):
            H[i, q] += Lp[i, q]
    _gauss_jordan(H, S, work)
    if not np.isfinite(S).all():  # information singular to rounding: the update is discarded
        return it, True
    for i in range(3):
        for q in range(i):
            S[i, q] = S[q, i] = 0.5 * (S[i, q] + S[q, i])
    if d > 3:  # the rest of the state from the prior's conditional
        e = d - 3
        G, GS, Puu = np.zeros((e, 3)), np.zeros((e, 3)), np.empty((e, e))
        for i in range(e):  # G = P_up Lp, GS = G S
            for j in range(3):
                for q in range(3):
                    G[i, j] += cov[3 + i, q] * Lp[q, j]
        for i in range(e):
            for j in range(3):
                for q in range(3):
                    GS[i, j] += G[i, q] * S[q, j]
        for i in range(e):  # Puu = P_uu - G P_pu + GS G^T
            for j in range(e):
                t = cov[3 + i, 3 + j]
                for q in range(3):
                    t += GS[i, q] * G[j, q] - G[i, q] * cov[q, 3 + j]
                Puu[i, j] = t
        for i in range(e):
            mean[3 + i] += G[i, 0] * (p[0] - mu[0]) + G[i, 1] * (p[1] - mu[1]) + G[i, 2] * (p[2] - mu[2])
            for j in range(3):
                cov[3 + i, j] = cov[j, 3 + i] = GS[i, j]
        for i in range(e):
            for j in range(e):
                cov[3 + i, 3 + j] = 0.5 * (Puu[i, j] + Puu[j, i])
    for i in range(3):
        mean[i] = p[i]
        for q in range(3):
            cov[i, q] = S[i, q]
    return it, False

