"""The compiled kernels (batgraph.graph.kernels) against plain numpy on random systems and observations."""

import numpy as np
import pytest

from batgraph.graph import kernels
from batgraph.graph.cost import robust_loss


def _tridiagonal(rng, F, M, d):
    """Random SPD block-tridiagonal systems: D (F, M, d, d), B (M, d, d), and the dense H (M, F d, F d)."""
    B = rng.normal(size=(M, d, d))
    X = rng.normal(size=(F, M, d, d))
    D = X @ np.swapaxes(X, -1, -2) + 2 * d * np.eye(d) + 2 * np.abs(B).sum(axis=(1, 2))[None, :, None, None] * np.eye(d)
    H = np.zeros((M, F * d, F * d))
    for k in range(F):
        H[:, k * d:(k + 1) * d, k * d:(k + 1) * d] = D[k]
        if k + 1 < F:
            H[:, (k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = B
            H[:, k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = np.swapaxes(B, -1, -2)
    return D, B, H


@pytest.mark.parametrize("d, indefinite", [(3, False), (6, False), (9, False), (18, False), (18, True), (40, False)])
def test_tridiagonal_kernels_equal_dense_linear_algebra(d, indefinite):
    """d = 18 > SMALL_BLOCK: the Cholesky inverse, or with ``indefinite`` (one frame's blocks flipped negative,
    as an exact-curvature step can make them) LAPACK's LU for that frame; d = 40 > CHOLESKY_BLOCK: LAPACK."""
    rng = np.random.default_rng(d)
    F, M, r = 7, 4, 3
    D, B, H = _tridiagonal(rng, F, M, d)
    if indefinite:
        D[F // 2] *= -1.0
        for m in range(M):
            H[m, F // 2 * d:(F // 2 + 1) * d, F // 2 * d:(F // 2 + 1) * d] = D[F // 2, m]
        assert (np.linalg.eigvalsh(H).min(axis=1) < 0).all()
    rhs = rng.normal(size=(F, M, d, r))
    dx = kernels.tridiagonal_solve(D, B, rhs)
    Hinv = np.linalg.inv(H)
    for m in range(M):
        want = np.linalg.solve(H[m], rhs[:, m].reshape(F * d, r))
        np.testing.assert_allclose(dx[:, m].reshape(F * d, r), want, rtol=1e-10, atol=1e-12)
    ld_want = np.linalg.slogdet(H)[1]
    np.testing.assert_allclose(kernels.tridiagonal_logdet(D, B), ld_want, rtol=1e-12)
    Sigma, ld = kernels.tridiagonal_marginals(D, B)
    np.testing.assert_allclose(ld, ld_want, rtol=1e-12)
    for k in range(F):
        np.testing.assert_allclose(Sigma[k], Hinv[:, k * d:(k + 1) * d, k * d:(k + 1) * d], rtol=1e-9, atol=1e-13)


@pytest.mark.parametrize("d", [3, 6, 9])
def test_motion_trace_equals_dense_trace(d):
    """tridiagonal_motion_trace: log det H and tr(H^-1 H_m) for a block-tridiagonal H_m of diagonal blocks
    AtQiA (frames 0..F-2) + Qi (1..F-1) and sub-diagonal blocks B, against dense inverses (to rounding)."""
    rng = np.random.default_rng(10 + d)
    F, M = 7, 4
    D, B, H = _tridiagonal(rng, F, M, d)
    X, Y = rng.normal(size=(2, M, d, d))
    AtQiA, Qi = X @ np.swapaxes(X, -1, -2), Y @ np.swapaxes(Y, -1, -2)
    ld, tr = kernels.tridiagonal_motion_trace(D, B, AtQiA, Qi)
    for m in range(M):
        Hm = np.zeros((F * d, F * d))
        for k in range(F - 1):
            a, b = slice(k * d, (k + 1) * d), slice((k + 1) * d, (k + 2) * d)
            Hm[a, a] += AtQiA[m]
            Hm[b, b] += Qi[m]
            Hm[b, a], Hm[a, b] = B[m], B[m].T
        np.testing.assert_allclose(tr[m], np.trace(np.linalg.solve(H[m], Hm)), rtol=1e-10)
        np.testing.assert_allclose(ld[m], np.linalg.slogdet(H[m])[1], rtol=1e-12)
    # the fused kernel (the noise search's surrogate): the same log det and trace, and the solve, in one sweep
    rhs = rng.normal(size=(F, M, d, 1))
    dx, ld2, tr2 = kernels.tridiagonal_solve_motion_trace(D, B, AtQiA, Qi, rhs)
    np.testing.assert_allclose(ld2, ld, rtol=1e-13)
    np.testing.assert_allclose(tr2, tr, rtol=1e-13)
    np.testing.assert_allclose(dx, kernels.tridiagonal_solve(D, B, rhs), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("g, b", [(2, 3), (3, 6), (14, 18)])  # d = 6 (loops), 18 and 252 (BLAS / LAPACK)
def test_block_diagonal_B_equals_the_dense_one(g, b):
    """A segment group's B, block-diagonal (its members' motions are independent), given as its blocks
    (M, g, b, b): the same solves, log det and marginals as the dense B = diag(blocks) (to rounding)."""
    rng = np.random.default_rng(g)
    F, M, d = 5, 1, g * b
    blocks = rng.normal(size=(M, g, b, b))
    dense_B = np.zeros((M, d, d))
    for m in range(M):
        for j in range(g):
            dense_B[m, j * b:(j + 1) * b, j * b:(j + 1) * b] = blocks[m, j]
    X = rng.normal(size=(F, M, d, d))
    D = (X @ np.swapaxes(X, -1, -2) + 2 * d * np.eye(d)
         + 2 * np.abs(dense_B).sum(axis=(1, 2))[None, :, None, None] * np.eye(d))
    rhs = rng.normal(size=(F, M, d, 2))
    np.testing.assert_allclose(kernels.tridiagonal_solve(D, blocks, rhs), kernels.tridiagonal_solve(D, dense_B, rhs),
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(kernels.tridiagonal_logdet(D, blocks), kernels.tridiagonal_logdet(D, dense_B),
                               rtol=1e-12)
    (S1, l1), (S2, l2) = kernels.tridiagonal_marginals(D, blocks), kernels.tridiagonal_marginals(D, dense_B)
    np.testing.assert_allclose(l1, l2, rtol=1e-12)
    np.testing.assert_allclose(S1, S2, rtol=1e-9, atol=1e-13)


@pytest.mark.parametrize("robust, n_cells, n", [("none", 12, 200), ("huber", 12, 200), ("cauchy", 12, 200),
                                               ("huber", 600, 20_000), ("cauchy", 5, 9_000)])
def test_projection_sums_equal_numpy(robust, n_cells, n):
    """Cost, curvature, gradient and closest inverse depth per cell against a numpy evaluation of the same
    rows, including rows behind their camera (residual 2 fx, zero Jacobian). 20,000 rows make 9 chunks
    that run in parallel; 9,000 rows in 5 cells make 4 chunks of which some are empty (cuts at cell starts)."""
    rng = np.random.default_rng(7)
    M, C = 3, 4
    k = 2.0
    pt = rng.normal(size=(3, n_cells)) * 0.3
    cell = np.sort(rng.integers(0, n_cells, n))
    col = cell % M
    cam = rng.integers(0, C, n)
    P = np.zeros((12, C))
    for c in range(C):
        Pc = np.hstack([800 * np.eye(3), rng.normal(size=(3, 1))])
        Pc[2, 3] = 2.0 if c else -0.1  # camera 0 sees some points behind it
        Pc[:2, 2] = 320.0, 240.0
        P[:, c] = Pc.ravel()
    uv = rng.normal(size=(2, n)) * 30 + np.array([[320.0], [240.0]])
    Linv = np.stack([np.full(n, 1.0), rng.normal(size=n) * 0.1, np.full(n, 0.9)])
    behind = np.full(C, 1600.0)
    out = [np.zeros(M), np.zeros(M), np.zeros((n_cells, 6)), np.zeros((n_cells, 6)), np.zeros((n_cells, 3)),
           np.zeros(n_cells)]
    kernels.projection_sums(pt, cell, col, cam, P, uv, Linv, behind, kernels.ROBUST_CODE[robust], k, True, *out)
    total, closest, Hw, Hc, g, rr = out
    # numpy, row by row
    p = pt[:, cell]
    Pr = P[:, cam].T.reshape(n, 3, 4)
    h = np.einsum("nij,jn->ni", Pr[:, :, :3], p) + Pr[:, :, 3]
    front = h[:, 2] > 0
    assert 0 < front.sum() < n
    uvp = h[:, :2] / h[:, 2:]
    e = np.where(front[:, None], uvp - uv.T, behind[cam][:, None])
    Lm = np.zeros((n, 2, 2))
    Lm[:, 0, 0], Lm[:, 1, 0], Lm[:, 1, 1] = Linv
    r = np.einsum("nij,nj->ni", Lm, e)
    J = (Pr[:, :2, :3] - uvp[:, :, None] * Pr[:, 2:, :3]) / h[:, 2, None, None]
    J[~front] = 0.0
    Jw = Lm @ J
    d2 = (r**2).sum(1)
    rho, w = robust_loss(d2, robust, k)
    np.testing.assert_allclose(total, np.bincount(col, rho, M), rtol=1e-12)
    np.testing.assert_allclose(closest, np.maximum(0, [max([0.0] + list(1 / h[(col == m) & front, 2]))
                                                       for m in range(M)]), rtol=1e-12)
    Jr = np.einsum("nij,ni->nj", Jw, r)
    np.testing.assert_allclose(g, np.stack([np.bincount(cell, w * Jr[:, i], n_cells) for i in range(3)], 1),
                               rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(rr, np.bincount(cell, w * d2, n_cells), rtol=1e-12)
    iu = np.triu_indices(3)
    JJ = np.einsum("nki,nkj->nij", Jw, Jw)[:, iu[0], iu[1]]
    np.testing.assert_allclose(Hw, np.stack([np.bincount(cell, w * JJ[:, s], n_cells) for s in range(6)], 1),
                               rtol=1e-10, atol=1e-12)
    if robust == "none":
        a = np.zeros(n)
    elif robust == "huber":
        a = (d2 > k * k).astype(float)
    else:
        a = np.minimum(1.0, 2 * d2 / (k * k + d2))
    RR = np.einsum("ni,nj->nij", Jr, Jr)[:, iu[0], iu[1]] * (w * a / d2)[:, None]
    np.testing.assert_allclose(Hc, np.stack([np.bincount(cell, RR[:, s], n_cells) for s in range(6)], 1),
                               rtol=1e-10, atol=1e-12)


def test_weighted_triangulation_recovers_points_and_their_information():
    """Noisy pixels of 3 cameras: the kernel's points are the weighted least-squares optimum (gradient J^T W r
    ~ 0, from numpy's pinhole Jacobians) and its Sigma is the inverse of sum J^T W J there; points behind every
    camera or with NaN starts are left alone."""
    from batgraph.geometry import pinhole

    rng = np.random.default_rng(3)
    C, F, M = 3, 4, 2
    P = np.zeros((C, 3, 4))
    for c in range(C):
        ang = 2 * np.pi * c / C
        R = np.array([[np.cos(ang), 0, -np.sin(ang)], [0, 1, 0], [np.sin(ang), 0, np.cos(ang)]])
        K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
        P[c] = pinhole.projection_matrix(K, R, np.array([0, 0, 3.0]))
    truth = rng.normal(size=(F, M, 3)) * 0.2
    uv = np.stack([pinhole.project_ideal(P[c], truth) for c in range(C)]) + rng.normal(size=(C, F, M, 2))
    W = np.broadcast_to(np.diag([1.0, 0.5]), (C, F, M, 2, 2)).copy()
    use = np.ones((C, F, M), bool)
    xyz = truth + 0.01
    xyz[0, 0] = np.nan
    r, h, Sigma = np.zeros((C, F, M, 2)), np.zeros((C, F, M)), np.full((F, M, 3, 3), np.nan)
    kernels.weighted_triangulation(P, uv, W, use, xyz, 5, r, h, Sigma)
    assert np.isnan(xyz[0, 0]).all() and np.isnan(Sigma[0, 0]).all() and (h[:, 0, 0] == 0).all()
    for f, m in [(f, m) for f in range(F) for m in range(M) if (f, m) != (0, 0)]:
        J = np.stack([pinhole.point_jacobian(P[c], xyz[f, m]) for c in range(C)])  # (C, 2, 3)
        res = uv[:, f, m] - np.stack([pinhole.project_ideal(P[c], xyz[f, m]) for c in range(C)])
        np.testing.assert_allclose(r[:, f, m], res, atol=1e-9)
        JW = np.einsum("cki,ckl->cil", J, W[:, f, m])
        np.testing.assert_allclose(h[:, f, m], np.sum(JW @ J * Sigma[f, m], axis=(-2, -1)), rtol=1e-10)
        assert np.abs(np.einsum("cil,cl->i", JW, res)).max() < 1e-6 * np.abs(JW).max()
        np.testing.assert_allclose(Sigma[f, m], np.linalg.inv((JW @ J).sum(0)), rtol=1e-9)


def test_leverage_is_numpys_sum_bit_for_bit():
    """kernels._leverage adds the nine products in numpy's order for np.sum(A * S', axis=(-2, -1)) (S' = S with
    non-finite entries as 0: what batgraph.pixel_noise summed before the kernel did), on values of 16 decades."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(2000, 3, 3)) * 10.0 ** rng.uniform(-8, 8, (2000, 3, 3))
    S = rng.normal(size=(2000, 3, 3)) * 10.0 ** rng.uniform(-8, 8, (2000, 3, 3))
    S[::7, 1, 2] = np.nan
    S[::11, 0, 0] = np.inf
    want = np.sum(A * np.where(np.isfinite(S), S, 0.0), axis=(-2, -1))
    got = np.array([kernels._leverage(a, s) for a, s in zip(A, S, strict=True)])
    assert got.tobytes() == want.tobytes()


@pytest.fixture
def kernel_threads():
    """Set the kernels' thread count inside a test; restored afterwards."""
    before = kernels.threads()
    yield kernels.set_threads
    kernels.set_threads(before)


def test_threads_split_the_work_without_changing_an_answer(kernel_threads):
    """Bit-identical results on 1 and 3 threads, on systems big enough to be split into parts: the
    tridiagonal kernels (64 frames x 100 markers: 3 parts), the projection sums (20,000 rows: 9 chunks)
    and the triangulation (200 frames x 30 markers: 2 parts)."""
    rng = np.random.default_rng(11)
    D, B, _ = _tridiagonal(rng, 64, 100, 1)  # d = 1 keeps the dense H small; the kernels see (F, M, 1, 1)
    X = rng.normal(size=(64, 100, 6, 6)) * 0.1
    D6 = X + np.swapaxes(X, -1, -2) + 7.0 * np.eye(6)
    B6 = np.ascontiguousarray(rng.normal(size=(100, 6, 6)) * 0.3)
    rhs = rng.normal(size=(64, 100, 6, 2))
    n, n_cells, M, C = 20_000, 3000, 50, 3
    cell = np.sort(rng.integers(0, n_cells, n))
    proj = (rng.normal(size=(3, n_cells)), cell, cell % M, rng.integers(0, C, n),
            np.tile(np.array([[800.0, 0, 320, 0, 0, 800, 240, 0, 0, 0, 1, 3]]).T, (1, C)),
            rng.normal(size=(2, n)) * 30 + 300, np.stack([np.ones(n), np.zeros(n), np.ones(n)]), np.full(C, 1600.0),
            kernels.ROBUST_CODE["huber"], 2.0, True)
    Ptri = np.stack([np.hstack([np.eye(3) * 800, np.array([[0.1 * c], [0], [3]])]) for c in range(3)])
    uv_tri = rng.normal(size=(3, 200, 30, 2)) * 20 + 300
    W = np.broadcast_to(np.eye(2), (3, 200, 30, 2, 2)).copy()

    def run(n_threads):
        kernel_threads(n_threads)
        out = [kernels.tridiagonal_solve(D6, B6, rhs), kernels.tridiagonal_logdet(D6, B6),
               *kernels.tridiagonal_marginals(D6, B6), kernels.tridiagonal_logdet(D, B)]
        sums = [np.zeros(M), np.zeros(M), np.zeros((n_cells, 6)), np.zeros((n_cells, 6)), np.zeros((n_cells, 3)),
                np.zeros(n_cells)]
        kernels.projection_sums(*proj, *sums)
        xyz = xyz0.copy()
        r, h, Sigma = np.zeros((3, 200, 30, 2)), np.zeros((3, 200, 30)), np.full((200, 30, 3, 3), np.nan)
        kernels.weighted_triangulation(Ptri, uv_tri, W, np.ones((3, 200, 30), bool), xyz, 3, r, h, Sigma)
        return out + sums + [xyz, r, h, Sigma]

    xyz0 = rng.normal(size=(200, 30, 3)) * 0.1
    one, three = run(1), run(3)
    for a, b in zip(one, three, strict=True):
        assert np.array_equal(a, b, equal_nan=True)


def test_a_reconstruct_compiles_each_kernel_for_one_layout_of_its_arrays(tmp_path):
    """A fresh process's default reconstruct of the bundled sample (its smoother, with a segment group and
    single-marker solves; its filter) holds one compiled copy of each tridiagonal kernel it called and of the
    projection sums (with the rows they call): a read-only or Fortran-ordered argument would add one (~10 s
    more on a first run). Counted on the dispatchers called from Python (a kernel called from a kernel is
    compiled into its caller)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "data" / "samples" / "flight_5cam"
    code = ("import sys\n"
            "from batgraph.cli import main\n"
            "main(['reconstruct', sys.argv[1], '--out', sys.argv[2], '--viewer', 'none', '--quiet'])\n"
            "from batgraph.graph import kernels as k\n"
            "for f in (k._solve_markers, k._logdet_markers, k._marginals_markers, k._solve_trace_markers,\n"
            "          k._motion_trace_markers, k._projection_chunks):\n"
            "    print(f.py_func.__name__, len(f.signatures))\n")
    out = subprocess.run([sys.executable, "-c", code, str(sample), str(tmp_path / "out")], capture_output=True,
                         text=True, timeout=900, env={**os.environ, "BATGRAPH_FORK": "0"})
    assert out.returncode == 0, out.stderr[-2000:]
    counts = {name: int(n) for name, n in (line.split() for line in out.stdout.splitlines() if line.startswith("_"))}
    assert len(counts) == 6 and counts["_solve_markers"] == 1 and counts["_projection_chunks"] == 1, out.stdout
    assert max(counts.values()) == 1, out.stdout  # the others: once or not at all
