"""Compiled inner loops (numba): the projection rows and the block-tridiagonal sweeps of every marker's chain.

Why compiled: both are small dense work repeated many times (a row is a 2 x 3 Jacobian; a sweep step a few
6 x 6 products), which numpy can only do through many temporary arrays or a Python loop over frames. Each
loop works on a range of markers and releases the GIL, so batgraph.solver.threads runs ranges side by side;
markers are independent, so the split never changes an answer. Arithmetic follows numpy's error model (a
division by zero gives inf or NaN, e.g. a singular block, whose step is then rejected).
Compiled on first use and cached on disk beside this file (``cache=True``). Imports only numpy and numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .threads import split

ROBUST_CODE = {"none": 0, "huber": 1, "cauchy": 2}
MIN_PART_ROWS = 1024  # the fewest observation rows worth handing to another thread
MIN_PART_BLOCKS = 512  # the fewest (frame, marker) blocks of a sweep worth handing to another thread


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def rho_w(d2, robust, k):  # pragma: no cover  (compiled)
    """GTSAM's m-estimators on |r| = sqrt(d2): (rho, IRLS weight rho'(|r|) / |r|, curvature factor a). Huber:
    0.5 d2 inside k, k |r| - k^2 / 2 beyond (w = k / |r|, a = 1); Cauchy: 0.5 k^2 log(1 + d2 / k^2)
    (w = k^2 / (k^2 + d2), a = min(1, 2 d2 / (k^2 + d2))); none: 0.5 d2. The robust loss's own curvature in
    the whitened residual is w (I - a r r^T / |r|^2) (a clamped so that it stays positive semi-definite)."""
    kk = k * k
    if robust == 0:
        return 0.5 * d2, 1.0, 0.0
    if robust == 1:
        rn = np.sqrt(d2)
        if rn <= k:
            return 0.5 * d2, 1.0, 0.0
        return k * rn - 0.5 * kk, k / rn, 1.0
    return 0.5 * kk * np.log1p(d2 / kk), kk / (kk + d2), min(1.0, 2.0 * d2 / (kk + d2))


@njit(cache=True, nogil=True, error_model="numpy")
def robust_loss(d2, robust, k):  # pragma: no cover  (compiled)
    """:func:`rho_w` over an array d2 (n,): (rho (n,), w (n,))."""
    rho, w = np.empty_like(d2), np.empty_like(d2)
    for i in range(d2.shape[0]):
        rho[i], w[i], _ = rho_w(d2[i], robust, k)
    return rho, w


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _position(x, kf, mk, W, i, pair, out):  # pragma: no cover  (compiled)
    """out (3,) = sum_j W[i, 0, j] x[kf, mk, block j] (+ W[i, 1, j] x[kf + 1, ...] when ``pair``)."""
    nb = x.shape[2] // 3
    for q in range(3):
        t = 0.0
        for j in range(nb):
            t += W[i, 0, j] * x[kf, mk, 3 * j + q]
            if pair:
                t += W[i, 1, j] * x[kf + 1, mk, 3 * j + q]
        out[q] = t


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _project(P, cm, p, u_obs, v_obs, a, b, c, behind, J):  # pragma: no cover  (compiled)
    """Whitened residual r = L^-1 (pi(p) - uv) of camera cm (P (12, C) row-major K [R | t]) with L^-1 = [[a, 0],
    [b, c]], and its whitened Jacobian J (2, 3) [1/m]: (r0, r1, inverse depth). Behind the camera (depth <= 0)
    r = L^-1 (behind, behind) with J = 0, GTSAM's answer to a cheirality exception."""
    x, y, z = p[0], p[1], p[2]
    depth = P[8, cm] * x + P[9, cm] * y + P[10, cm] * z + P[11, cm]
    inv = 1.0 / depth if depth != 0.0 else np.inf
    if not (inv > 0.0 and inv < np.inf):
        J[:] = 0.0
        return a * behind, (b + c) * behind, 0.0
    u = (P[0, cm] * x + P[1, cm] * y + P[2, cm] * z + P[3, cm]) * inv
    v = (P[4, cm] * x + P[5, cm] * y + P[6, cm] * z + P[7, cm]) * inv
    for j in range(3):
        ju = (P[j, cm] - u * P[8 + j, cm]) * inv
        jv = (P[4 + j, cm] - v * P[8 + j, cm]) * inv
        J[0, j] = a * ju
        J[1, j] = b * ju + c * jv
    e0, e1 = u - u_obs, v - v_obs
    return a * e0, b * e0 + c * e1, inv


@njit(cache=True, nogil=True, error_model="numpy")
def _rows(m0, m1, starts, x, kf_, W, cam, P, uv, Linv, behind, robust, k, exact, jacobian,
          cost, near, D, B, g):  # pragma: no cover  (compiled)
    """:func:`rows_system` for markers m0..m1-1."""
    F, nb = x.shape[0], x.shape[2] // 3
    p, J, gw, H = np.empty(3), np.empty((2, 3)), np.empty(3), np.empty((3, 3))
    for mk in range(m0, m1):
        for i in range(starts[mk], starts[mk + 1]):
            kf, cm = kf_[i], cam[i]
            pair = kf + 1 < F and (W[i, 1, 0] != 0.0 or W[i, 1, 1] != 0.0 or W[i, 1, 2] != 0.0)
            _position(x, kf, mk, W, i, pair, p)
            r0, r1, inv = _project(P, cm, p, uv[0, i], uv[1, i], Linv[0, i], Linv[1, i], Linv[2, i], behind[cm], J)
            if inv > near[mk]:
                near[mk] = inv
            d2 = r0 * r0 + r1 * r1
            rho, w, a = rho_w(d2, robust, k)
            cost[mk] += rho
            if not jacobian:
                continue
            for q in range(3):
                gw[q] = w * (J[0, q] * r0 + J[1, q] * r1)
            wa = w * a * exact[mk] / d2 if a != 0.0 and exact[mk] != 0.0 and d2 > 0.0 else 0.0
            for q in range(3):
                for s in range(3):
                    jr_q, jr_s = J[0, q] * r0 + J[1, q] * r1, J[0, s] * r0 + J[1, s] * r1
                    H[q, s] = w * (J[0, q] * J[0, s] + J[1, q] * J[1, s]) - wa * jr_q * jr_s
            for ea in range(2 if pair else 1):
                for ja in range(nb):
                    wa_ = W[i, ea, ja]
                    if wa_ == 0.0:
                        continue
                    for q in range(3):
                        g[kf + ea, mk, 3 * ja + q] += wa_ * gw[q]
                    for eb in range(2 if pair else 1):
                        for jb in range(nb):
                            wb_ = W[i, eb, jb]
                            if wb_ == 0.0 or eb > ea:
                                continue
                            f = wa_ * wb_
                            for q in range(3):
                                for s in range(3):
                                    if ea == eb:
                                        D[kf + ea, mk, 3 * ja + q, 3 * jb + s] += f * H[q, s]
                                    else:  # H[k + 1, k]: rows of frame k + 1, columns of frame k
                                        B[kf, mk, 3 * ja + q, 3 * jb + s] += f * H[q, s]


def rows_system(x, rows, cams, loss, exact, cost, near, system=None) -> None:
    """Add every projection row's robust cost and Gauss-Newton terms into its marker's system, in place.

    x (F, M, d) states [m]; rows: batgraph.solver.problem.Rows (sorted by marker, ``starts`` (M + 1,) their
    ranges, ``k`` (n,) the interval's first frame, ``W`` (n, 2, 3) the weights of the position on the states of
    frames k and k + 1); cams: problem.Cameras (P (12, C), behind (C,)); loss: problem.Loss; exact (M,) 1.0 where
    the Hessian takes the robust loss's own curvature, 0.0 for IRLS's. Adds to cost (M,) and sets near (M,) to
    each marker's largest inverse depth; with system = (D (F, M, d, d), B (F - 1, M, d, d) (H[k + 1, k]),
    g (F, M, d)) adds the Gauss-Newton terms to them.
    """
    jacobian = system is not None
    D, B, g = system if jacobian else (_NONE4, _NONE4, _NONE3)
    split(len(rows.starts) - 1, max(1, MIN_PART_ROWS * (len(rows.starts) - 1) // max(len(rows.k), 1)),
          lambda m0, m1: _rows(m0, m1, rows.starts, x, rows.k, rows.W, rows.cam, cams.P, rows.uv, rows.Linv,
                               cams.behind, loss.code, float(loss.k), exact, jacobian, cost, near, D, B, g))


_NONE3, _NONE4 = np.zeros((1, 1, 1)), np.zeros((1, 1, 1, 1))  # unused when no system is asked for


@njit(cache=True, nogil=True, error_model="numpy")
def _row_terms(lo, hi, x, mrk, kf_, W, dW, cam, P, uv, Linv, behind, robust, k, r, J, w, a, p, dp,
               inv):  # pragma: no cover
    """:func:`row_terms` for rows lo..hi-1."""
    F = x.shape[0]
    Jr = np.empty((2, 3))
    for i in range(lo, hi):
        kf, mk = kf_[i], mrk[i]
        pair = kf + 1 < F and (W[i, 1, 0] != 0.0 or W[i, 1, 1] != 0.0 or W[i, 1, 2] != 0.0)
        _position(x, kf, mk, W, i, pair, p[i])
        _position(x, kf, mk, dW, i, pair, dp[i])
        r[i, 0], r[i, 1], inv[i] = _project(P, cam[i], p[i], uv[0, i], uv[1, i], Linv[0, i], Linv[1, i],
                                            Linv[2, i], behind[cam[i]], Jr)
        J[i] = Jr
        _, w[i], a[i] = rho_w(r[i, 0] ** 2 + r[i, 1] ** 2, robust, k)


def row_terms(x, rows, cams, loss) -> dict:
    """Per row (n rows): the whitened residual r (n, 2), its whitened Jacobian in the world point J (n, 2, 3)
    [1/m], the IRLS weight w (n,) and curvature factor a (n,) (:func:`rho_w`) of ``loss``, the point p (n, 3) [m],
    dp/ds (n, 3) [m per frame] along its time, and the inverse depth inv (n,) [1/m] (0 behind the camera).
    Arguments as :func:`rows_system`'s (rows placed, with ``dW``)."""
    n = len(rows.k)
    out = {"r": np.empty((n, 2)), "J": np.empty((n, 2, 3)), "w": np.empty(n), "a": np.empty(n), "p": np.empty((n, 3)),
           "dp": np.empty((n, 3)), "inv": np.empty(n)}
    split(n, MIN_PART_ROWS, lambda lo, hi: _row_terms(
        lo, hi, x, rows.marker, rows.k, rows.W, rows.dW, rows.cam, cams.P, rows.uv, rows.Linv, cams.behind, loss.code,
        float(loss.k), out["r"], out["J"], out["w"], out["a"], out["p"], out["dp"], out["inv"]))
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def shared_terms(k, marker, W, r, J, w, a, Jt, cols, exact, F, M, d, n):  # pragma: no cover  (compiled)
    """The rows' part of the shared variables' system: g_t (n,), H_tt (n, n) and the coupling with the states H_xt
    (F, M, d, n). Row i (placed: k, W as :func:`rows_system`'s; marker (n_rows,)) has whitened residual r (2,),
    Jacobians J (2, 3) in its point and Jt (2, p) in its theta columns cols (p,) (-1: none), IRLS weight w and
    curvature factor a (:func:`rho_w`); its curvature in r is Wr = w I, less w a r r^T / |r|^2 with ``exact`` (the
    robust loss's own). H_xt gets W[i, e, j] (J^T Wr Jt)[q, a] at (k_i + e, marker_i, 3 j + q, cols[a]) for each of
    the row's two states e within the frames."""
    g, H, Hxt = np.zeros(n), np.zeros((n, n)), np.zeros((F, M, d, n))
    p = cols.shape[1]
    WJt, jw = np.empty((2, p)), np.empty((3, p))
    for i in range(k.shape[0]):
        r0, r1 = r[i, 0], r[i, 1]
        w00, w01, w11 = w[i], 0.0, w[i]
        d2 = r0 * r0 + r1 * r1
        if exact and d2 > 0:
            f = w[i] * a[i] / d2
            w00, w01, w11 = w00 - f * r0 * r0, -f * r0 * r1, w11 - f * r1 * r1
        for b in range(p):
            WJt[0, b] = w00 * Jt[i, 0, b] + w01 * Jt[i, 1, b]
            WJt[1, b] = w01 * Jt[i, 0, b] + w11 * Jt[i, 1, b]
            for q in range(3):
                jw[q, b] = J[i, 0, q] * WJt[0, b] + J[i, 1, q] * WJt[1, b]
        for c in range(p):
            ca = cols[i, c]
            if ca < 0:
                continue
            g[ca] += w[i] * (Jt[i, 0, c] * r0 + Jt[i, 1, c] * r1)
            for b in range(p):
                if cols[i, b] >= 0:
                    H[ca, cols[i, b]] += Jt[i, 0, c] * WJt[0, b] + Jt[i, 1, c] * WJt[1, b]
            for e in range(2):
                if k[i] + e < F:
                    for j in range(d // 3):
                        for q in range(3):
                            Hxt[k[i] + e, marker[i], 3 * j + q, ca] += W[i, e, j] * jw[q, c]
    return g, H, Hxt


# ----- block-tridiagonal sweeps ----------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def mirror_lower(a):  # pragma: no cover  (compiled)
    """a (n, n) with its upper triangle set from its lower one, in place; returns a (LAPACK's potri fills one)."""
    n = a.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            a[i, j] = a[j, i]
    return a


@njit(cache=True, nogil=True, error_model="numpy")
def _inverse(A, out, work):  # pragma: no cover  (compiled)
    """out = A^-1 by Gauss-Jordan with partial pivoting (small blocks; LAPACK beyond 12); returns log |det A|
    (-inf for a singular A, whose out is then inf / NaN)."""
    d = A.shape[0]
    if d > 12:
        out[:] = np.linalg.inv(A)
        return np.linalg.slogdet(A)[1]
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
        for j in range(d):
            work[c, j] /= piv
            out[c, j] /= piv
        for r in range(d):
            f = work[r, c]
            if r == c or f == 0.0:
                continue
            for j in range(d):
                work[r, j] -= f * work[c, j]
                out[r, j] -= f * out[c, j]
    return logdet


@njit(cache=True, nogil=True, error_model="numpy")
def _mul(A, B, out, trans_b):  # pragma: no cover  (compiled)
    """out = A @ B (or A @ B^T); BLAS beyond 12 wide."""
    if A.shape[1] > 12:
        out[:] = np.dot(np.ascontiguousarray(A), np.ascontiguousarray(B.T if trans_b else B))
        return
    n, q = A.shape
    c = B.shape[0] if trans_b else B.shape[1]
    for i in range(n):
        for j in range(c):
            t = 0.0
            for l in range(q):
                t += A[i, l] * (B[j, l] if trans_b else B[l, j])
            out[i, j] = t


@njit(cache=True, nogil=True, error_model="numpy")
def _bmul(Bk, X, out, trans):  # pragma: no cover  (compiled)
    """out = B X (or B^T X) for the block-diagonal B = diag(Bk[0], .., Bk[g - 1]) (Bk (g, b, b)), X (g b, r)."""
    g, b = Bk.shape[0], Bk.shape[1]
    for j in range(g):
        _mul(Bk[j].T if trans else Bk[j], X[j * b:(j + 1) * b], out[j * b:(j + 1) * b], False)


@njit(cache=True, nogil=True, error_model="numpy")
def _forward(D, B, m, Sinv, L, S, work, rhs, y, Ly):  # pragma: no cover  (compiled)
    """Forward sweep of chain m: Sinv[k] = S_k^-1 with S_0 = D_0, S_k = D_k - L_k B_{k-1}^T, L_k = B_{k-1}
    S_{k-1}^-1 (B[k-1, m] = H[k, k-1], block diagonal (g, b, b)); with rhs frames, y_k = rhs_k - L_k y_{k-1}.
    Returns log det H = sum_k log |det S_k|."""
    F, d = D.shape[0], D.shape[2]
    logdet = _inverse(D[0, m], Sinv[0], work)
    with_rhs = rhs.shape[0] > 0
    if with_rhs:
        y[0] = rhs[0, m]
    for k in range(1, F):
        _bmul(B[k - 1, m], Sinv[k - 1], L, False)  # L = B S^-1 (S^-1 symmetric)
        for i in range(d):  # S = D - L B^T = D - (B L^T)^T
            for j in range(d):
                work[i, j] = L[j, i]
        _bmul(B[k - 1, m], work, S, False)
        for i in range(d):
            for j in range(d):
                work[i, j] = D[k, m, i, j] - S[j, i]
        logdet += _inverse(work, Sinv[k], S)
        if with_rhs:
            _mul(L, y[k - 1], Ly, False)
            for i in range(d):
                for c in range(y.shape[2]):
                    y[k, i, c] = rhs[k, m, i, c] - Ly[i, c]
    return logdet


_NO_RHS = np.empty((0, 1, 1, 1))


@njit(cache=True, nogil=True, error_model="numpy")
def _sweeps(m0, m1, D, B, rhs, out, Sigma, ld, AtQiA, Qi, Bm, tr, want):  # pragma: no cover  (compiled)
    """Chains m0..m1-1: log det (always), the solution of rhs (want & 1), the marginals Sigma (want & 2) and
    tr(H^-1 H_m) of the motion part H_m (want & 4: diagonal blocks AtQiA (frames < F - 1) + Qi (frames > 0),
    sub-diagonal Bm, each (M, d, d))."""
    F, d = D.shape[0], D.shape[2]
    r = rhs.shape[3]
    Sinv, y = np.empty((F, d, d)), np.empty((F, d, r))
    L, S, work, G, GS = np.empty((d, d)), np.empty((d, d)), np.empty((d, d)), np.empty((d, d)), np.empty((d, d))
    cur, nxt = np.empty((d, d)), np.empty((d, d))
    Ly, t_ = np.empty((d, r)), np.empty((d, r))
    for m in range(m0, m1):
        ld[m] = _forward(D, B, m, Sinv, L, S, work, rhs if want & 1 else _NO_RHS, y, Ly)
        if want & 1:
            _mul(Sinv[F - 1], y[F - 1], out[F - 1, m], False)
        nxt[:] = Sinv[F - 1]
        if want & 2:
            Sigma[F - 1, m] = nxt
        t = 0.0
        if want & 4 and F > 1:
            for i in range(d):
                for j in range(d):
                    t += nxt[i, j] * Qi[m, j, i]
        for k in range(F - 2, -1, -1):
            if want & 1:  # dx_k = S_k^-1 (y_k - B_k^T dx_{k+1})
                _bmul(B[k, m], out[k + 1, m], Ly, True)
                for i in range(d):
                    for c in range(r):
                        t_[i, c] = y[k, i, c] - Ly[i, c]
                _mul(Sinv[k], t_, out[k, m], False)
            if want & 6:  # Sigma_k = S_k^-1 + G Sigma_{k+1} G^T, G = S_k^-1 B_k^T = (B_k S_k^-1)^T
                _bmul(B[k, m], Sinv[k], GS, False)
                for i in range(d):
                    for j in range(d):
                        G[i, j] = GS[j, i]
                _mul(G, nxt, GS, False)  # G Sigma_{k+1} = -Sigma_{k, k+1}
                _mul(GS, G, S, True)
                for i in range(d):
                    for j in range(d):
                        cur[i, j] = Sinv[k, i, j] + S[i, j]
                for i in range(d):
                    for j in range(i + 1, d):
                        cur[i, j] = cur[j, i] = 0.5 * (cur[i, j] + cur[j, i])
                if want & 4:
                    for i in range(d):
                        for j in range(d):
                            t += cur[i, j] * (AtQiA[m, j, i] + (Qi[m, j, i] if k > 0 else 0.0)) \
                                - 2.0 * GS[i, j] * Bm[m, j, i]
                if want & 2:
                    Sigma[k, m] = cur
                nxt[:] = cur
        tr[m] = t


_EMPTY3 = np.empty((0, 0, 0))


def tridiagonal(D, B, rhs=None, marginals: bool = False, motion=None) -> dict:
    """Sweeps over every chain's block-tridiagonal H (D (F, M, d, d) diagonal blocks, B (F - 1, M, g, b, b) the
    blocks H[k + 1, k], block diagonal with g blocks of b = d / g). Returns log det H (M,) as "logdet", and as
    asked: "dx" (F, M, d, r) solving H dx = rhs (rhs (F, M, d, r)); "Sigma" (F, M, d, d) the diagonal blocks of
    H^-1; "trace" (M,) tr(H^-1 H_m) for the motion part H_m given as motion = (AtQiA, Qi, Bm), each (M, d, d)
    (diagonal blocks AtQiA on frames < F - 1 plus Qi on frames > 0, sub-diagonal blocks Bm)."""
    F, M, d = D.shape[:3]
    want = (rhs is not None) | 2 * marginals | 4 * (motion is not None)
    D, B = np.require(D, requirements="CW"), np.require(B, requirements="CW")
    rhs_ = np.require(rhs, requirements="CW") if rhs is not None else np.zeros((F, M, d, 1))
    out = np.empty_like(rhs_) if rhs is not None else np.empty((1, M, d, 1))
    Sigma = np.empty_like(D) if marginals else np.empty((1, M, d, d))
    AtQiA, Qi, Bm = (np.require(a, requirements="CW") for a in motion) if motion is not None else (_EMPTY3,) * 3
    ld, tr = np.empty(M), np.zeros(M)
    split(M, -(-MIN_PART_BLOCKS // max(F, 1)),
          lambda m0, m1: _sweeps(m0, m1, D, B, rhs_, out, Sigma, ld, AtQiA, Qi, Bm, tr, want))
    res = {"logdet": ld}
    if rhs is not None:
        res["dx"] = out
    if marginals:
        res["Sigma"] = Sigma
    if motion is not None:
        res["trace"] = tr
    return res


def needs_compiling() -> bool:
    """Whether the next solve compiles these loops (the first run after an install or an update): numba's on-disk
    cache holds no compiled copy of the row kernel. Reads numba's cache index (private API): False where that fails."""
    try:
        return len(_rows._cache._cache_file._load_index()) == 0
    except Exception:  # noqa: BLE001  (a newer numba: no note, no harm)
        return False
