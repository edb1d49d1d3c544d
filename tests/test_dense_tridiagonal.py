"""batgraph.graph.dense_tridiagonal (a large segment group's system, by LAPACK) against dense linear algebra,
and fast's dispatch to it."""

import numpy as np
import pytest
from test_kernels import _tridiagonal

from batgraph.graph import dense_tridiagonal, fast, kernels


def _blocks_of(B: np.ndarray, g: int) -> np.ndarray:
    """A block-diagonal copy of B (d, d) as its blocks (g, b, b), and that dense block-diagonal matrix."""
    b = B.shape[0] // g
    blocks = np.stack([B[j * b:(j + 1) * b, j * b:(j + 1) * b] for j in range(g)])
    dense = np.zeros_like(B)
    for j in range(g):
        dense[j * b:(j + 1) * b, j * b:(j + 1) * b] = blocks[j]
    return blocks, dense


def _system(rng, F: int, d: int, g: int, indefinite: bool):
    """One block-tridiagonal H (F d, F d) with block-diagonal B of g blocks: D (F, d, d), blocks (g, b, b), H.
    ``indefinite``: one frame's diagonal block flipped negative (as an exact-curvature step can make it),
    so that Cholesky fails there and the LU inverse is taken."""
    D, B, _ = _tridiagonal(rng, F, 1, d)
    blocks, Bd = _blocks_of(B[0], g)
    D = D[:, 0]
    if indefinite:
        D[F // 2] *= -1.0
    H = np.zeros((F * d, F * d))
    for k in range(F):
        H[k * d:(k + 1) * d, k * d:(k + 1) * d] = D[k]
        if k + 1 < F:
            H[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = Bd
            H[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = Bd.T
    return D, blocks, H


@pytest.mark.parametrize("g, b", [(1, 6), (3, 6), (4, 18)])
@pytest.mark.parametrize("indefinite", [False, True])
def test_dense_path_equals_dense_linear_algebra(g, b, indefinite):
    """Solve, log |det H| and the diagonal blocks of H^-1 to rounding, positive definite or not."""
    rng = np.random.default_rng(g * b)
    F, d, r = 6, g * b, 3
    D, blocks, H = _system(rng, F, d, g, indefinite)
    assert (np.linalg.eigvalsh(H).min() < 0) == indefinite
    rhs = rng.normal(size=(F, d, r))
    dx = dense_tridiagonal.solve(D, blocks, rhs)
    np.testing.assert_allclose(dx.reshape(F * d, r), np.linalg.solve(H, rhs.reshape(F * d, r)), rtol=1e-9,
                               atol=1e-11)
    ld_want = np.linalg.slogdet(H)[1]
    assert abs(dense_tridiagonal.logdet(D, blocks) - ld_want) < 1e-10 * abs(ld_want)
    Sigma, ld = dense_tridiagonal.marginals(D, blocks)
    assert abs(ld - ld_want) < 1e-10 * abs(ld_want)
    Hinv = np.linalg.inv(H)
    for k in range(F):
        want = Hinv[k * d:(k + 1) * d, k * d:(k + 1) * d]
        np.testing.assert_allclose(Sigma[k], 0.5 * (want + want.T), rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(Sigma[k], Sigma[k].T)


def test_fast_sends_large_groups_to_lapack_and_the_answers_agree(monkeypatch):
    """fast._solve / logdet / marginals take the dense path for one system of blocks >= MIN_DENSE wide and
    the compiled kernels otherwise; both give the same answers (to rounding) on a 14-member group of
    oscillating-model blocks (252 wide, the hold-out scenes' skeleton)."""
    rng = np.random.default_rng(5)
    F, g, b = 4, 14, 18
    D, blocks, _ = _system(rng, F, g * b, g, indefinite=False)
    D4, B4 = D[:, None], blocks[None]
    rhs = rng.normal(size=(F, 1, g * b, 2))
    calls = []
    real = dense_tridiagonal.solve
    monkeypatch.setattr(dense_tridiagonal, "solve", lambda *a: calls.append(1) or real(*a))
    dx = fast._solve(D4, B4, rhs)
    assert calls == [1]
    np.testing.assert_allclose(dx, kernels.tridiagonal_solve(D4, B4, rhs), rtol=1e-9, atol=1e-12)
    Sigma, ld = fast.marginals(D4, B4)
    Sigma_k, ld_k = kernels.tridiagonal_marginals(D4, B4)
    np.testing.assert_allclose(Sigma, Sigma_k, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ld, ld_k, rtol=1e-12)
    np.testing.assert_allclose(fast.logdet(D4, B4), ld_k, rtol=1e-12)
    monkeypatch.setattr(dense_tridiagonal, "MIN_DENSE", g * b + 1)  # now below the threshold: the kernels
    fast._solve(D4, B4, rhs)
    assert calls == [1]
