"""Exact batch smoother for a fixed rig: every marker's block-tridiagonal Gauss-Newton system solved at once.

It minimises exactly the smoother's cost (projection factors with GTSAM's robust losses, random-walk or
constant-velocity motion factors, weak first-frame priors; the graph of batgraph.graph.factors) and
returns the marginal covariances ``gtsam.Marginals`` gives at the minimiser, but it deliberately handles
no camera uncertainty: with fixed cameras the markers are independent and each marker's chain is block
tridiagonal, which is what makes a vectorised numpy solver exact and fast. Rigs with pose covariances
go to the GTSAM smoother.

Layout: the state is ``x`` of shape (F, M, d) [m], frames first so that one frame of every marker is a
contiguous (M, d) slice for the sweeps over frames. d = 3 (random walk: position) or 6 (constant
velocity: position and u = v dt, the displacement per frame, as in factors.v_key, so both halves are in
metres and every 6x6 block is well conditioned) or 9 (constant acceleration: [p, v dt, a dt^2], likewise);
results are reported in the spec's units (v in m/s, a in m/s^2).

Speed (issue "Speed a user feels"; BENCHMARKS.md): the linear solves are sweeps over frames, each step
one batched operation over every column being solved. Measured alternatives on 5 x 24 x 160 and
160 x 216 / 1200 x 180 systems (6x6 blocks): one banded Cholesky over all markers (LAPACK dpbtrf,
kd = 11) was no faster (its unblocked per-column BLAS calls cost as much as numpy's per-frame calls);
odd-even cyclic reduction (log2 F sweeps, 2x the flops) was 1-2x slower; closed-form batched 6x6
inverses did not beat LAPACK's at these batch sizes. What made the smoother faster is fewer and cheaper
sweeps: the q search solves every point of its grid as ONE batch (candidates x markers as columns,
:func:`solve_levels`), computes no covariances while searching (log det from the forward sweep),
merges the forward elimination and substitution into one sweep, and gives exact (Newton) steps their
own damping, so a Huber kink no longer makes a marker alternate rejected exact / accepted IRLS steps
for tens of iterations. BLAS is held to one thread while solving (:func:`one_blas_thread`).
The two inner loops, the projection factors' sums over observation rows and the block-tridiagonal
sweeps, are compiled (batgraph.graph.kernels, numba): at 30 x 180 x 160 an evaluation 51 -> 13 ms and a
solve 19 -> 13 ms, the smoother method 12.3 -> 8.1 s (BENCHMARKS.md).
"""

from __future__ import annotations

import functools
import math
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from tqdm.auto import tqdm

from ..camera import Rig
from ..geometry import pinhole
from ..measurement import IdealObservations
from ..session import Session
from . import cost as spec
from . import dense_tridiagonal, kernels, noise
from .cost import robust_loss  # noqa: F401  (re-exported: fast_filter and tests use it from here)

MODELS = (*spec.MOTION_MODELS, spec.OSCILLATING)
ROBUST = spec.ROBUST_LOSSES
PRIOR_SIGMA_P_M = spec.PRIOR_POSITION_SIGMA_M  # weak gauge prior on p[m, 0] [m] (cost spec, factor 3)
PRIOR_SIGMA_V_MPS = spec.PRIOR_VELOCITY_SIGMA_MPS  # weak gauge prior on v[m, 0] [m/s]
# Convergence: the spec asks for a relative cost decrease < 1e-12 or a step < 1e-10 m. Near the
# minimum a 1e-12 relative decrease still allows ~1e-8 m, to which the IRLS weights of robust factors
# (and so the covariances) are sensitive at 1e-6 relative; stopping on the step (or on a decrease at
# rounding level) costs one or two more quadratically convergent iterations and lands on the minimiser.
REL_COST_TOL = 1e-15
STEP_TOL_M = 1e-10  # largest step component [m]
# The noise search's and the cleaning solve's step tolerance [m]. Their solutions serve a score (the evidence,
# its slope) or a residual test, not the output: at the minimum the cost is flat, so a position off by
# 1e-7 m moves a marker's cost by ~(1e-7 / 1e-3 m posterior std)^2 ~ 1e-8 nats and the slope's motion term
# by ~1e-4 of a per-frame motion residual; Gauss-Newton's quadratic convergence makes the step after a
# 1e-7 m one ~1e-12 m, so a strict tolerance costs one more iteration (of ~4-5 a search solve needs).
LOOSE_STEP_TOL_M = 1e-7
# A step whose predicted decrease (from the quadratic model) is below a few rounding units of the
# marker's cost cannot be judged by comparing costs (their sums differ by rounding, ~10-30 eps measured
# on 10^4-term costs); such a step is ~1e-9 m or less and the marker is at its minimiser to rounding.
ROUNDING_EPS = 4.0
# A marker whose iterate brings an observed point closer to that camera than this fraction of the
# closest depth at the start is running into the camera's centre, where every ray of the camera meets:
# there the cost has no minimum in front of the camera, only an infimum on the cheirality boundary
# (depth -> 0+), which Gauss-Newton approaches geometrically for hundreds of iterations (measured on
# the flight sample: constant acceleration at j >= 1e5 m^2/s^5 extrapolating a single-view run through
# the camera). Such a solve stops, not converged and ``at_camera``: its Laplace evidence is undefined.
AT_CAMERA_DEPTH_FRACTION = 1e-3
# solve_levels repeats the observation rows once per candidate noise level; candidates go in groups
# of at most this many rows in all (~64 B a row: 32 MB), so memory stays bounded at any scene size; a
# larger scene solves its candidates one by one (there the sweeps are work, not per-call overhead).
MAX_BATCH_ROWS = 1 << 19
# ... and of at most this many values in one array of the candidates' diagonal blocks (F, K M, d, d) (32 MB): the
# oscillating model's d = 18 makes those blocks 9 times the constant velocity's (its 63 candidates in groups by
# rows alone peaked at 1.6 GB on the bundled 24-marker flight).
MAX_BATCH_STATE = 1 << 22


@dataclass
class _Observations:
    """Projection factors of the markers being solved, sorted by (frame, marker); n rows, component-major.

    f, m: frame index and column of the marker in the state being solved, (n,) int, sorted by
    f * M' + m. cam: observing camera (n,) int. P: K [R | t] of every camera as (12, C), row 4 i + j
    holding P[i, j] (ideal pixels; the third row gives the depth). uv: ideal pixels, (2, n). Linv:
    whitening L^-1 = [[a, 0], [b, c]], L = chol(cov_px2), as (3, n) = (a, b, c) [1/px]. behind_px:
    GTSAM's residual when the point is behind camera c, 2 fx, (C,). n_frames, n_markers: F, M'.
    """

    f: np.ndarray
    m: np.ndarray
    cam: np.ndarray
    P: np.ndarray
    uv: np.ndarray
    Linv: np.ndarray
    behind_px: np.ndarray
    n_frames: int
    n_markers: int

    @cached_property
    def cell(self) -> np.ndarray:
        """The (frame, marker) cell of each row, f * M' + m, (n,) int, non-decreasing."""
        return self.f * self.n_markers + self.m

    def of_markers(self, keep: np.ndarray) -> _Observations:
        """The rows of the markers where ``keep`` (bool over current columns), columns renumbered."""
        col = np.cumsum(keep) - 1
        rows = np.flatnonzero(keep[self.m])
        return _Observations(self.f[rows], col[self.m[rows]], self.cam[rows], self.P, _columns(self.uv, rows),
                             _columns(self.Linv, rows), self.behind_px, self.n_frames, int(keep.sum()))

    def tile(self, K: int) -> _Observations:
        """K copies of every marker as columns m + j M' (j < K) of K M' markers, rows still sorted by frame."""
        if K == 1:
            return self
        n = len(self.f)
        order = np.argsort(np.tile(self.f, K), kind="stable")  # frame-major, copies in order within a frame
        rows = np.tile(np.arange(n), K)[order]
        col = (self.m[None, :] + self.n_markers * np.arange(K)[:, None]).ravel()[order]
        return _Observations(self.f[rows], col, self.cam[rows], self.P, _columns(self.uv, rows),
                             _columns(self.Linv, rows), self.behind_px, self.n_frames, K * self.n_markers)

    def residuals(self, x: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals r (2, n) of every row at x (F, M', >= 3) [m] and, if asked, whitened
        Jacobians Jw (2, 3, n) [1/m] (see :meth:`block_residuals`)."""
        r0, r1, Jw0, Jw1 = self.block_residuals(_positions(x), slice(None), jacobian)
        return np.stack([r0, r1]), None if Jw0 is None else np.stack([Jw0, Jw1])

    def block_residuals(self, pt: np.ndarray, rows: slice, jacobian: bool, inv_depth_out: list | None = None):
        """Whitened residuals (r0, r1), each (k,), of ``rows`` at positions pt (3, F * M') [m] and, if
        asked, the rows of the whitened Jacobian (Jw0, Jw1), each (3, k) [1/m].

        r = L^-1 (pi(p) - uv) in front of the camera (depth > 0); behind it r = L^-1 (2 fx, 2 fx) with a
        zero Jacobian, which is what GTSAM's TriangulationFactor returns on a cheirality exception
        (an initial track can put a single-view point behind its camera).
        inv_depth_out: if a list, each row's inverse depth [1/m] (0 behind the camera) is appended to it.
        """
        p = np.take(pt, self.cell[rows], axis=1)  # (3, k)
        P = np.take(self.P, self.cam[rows], axis=1)  # (12, k)
        u, v, inv_depth = pinhole.project_rows(P, p)
        front = (inv_depth > 0) & (inv_depth < np.inf)  # depth > 0 (1 / +0 is +inf: a point on the camera plane)
        e0, e1 = u - self.uv[0, rows], v - self.uv[1, rows]
        if not front.all():
            behind = ~front
            e0[behind] = e1[behind] = self.behind_px[self.cam[rows][behind]]
            inv_depth[behind] = 0.0
        if inv_depth_out is not None:
            inv_depth_out.append(inv_depth)
        a, b, c = self.Linv[:, rows]
        r0, r1 = a * e0, b * e0 + c * e1
        if not jacobian:
            return r0, r1, None, None
        J0, J1 = pinhole.point_jacobian_rows(P, u, v, inv_depth)  # d (u, v) / d p, (3, k) each [px/m]
        Jw0 = a * J0
        J1 *= c
        J1 += b * J0
        return r0, r1, Jw0, J1


def _positions(x: np.ndarray) -> np.ndarray:
    """The positions of a state x (F, M', d) as (3, F * M') [m], column f * M' + m (contiguous rows)."""
    F, M = x.shape[:2]
    return np.ascontiguousarray(x[..., :3].reshape(F * M, 3).T)


def projection_rows(rig: Rig, ideal: IdealObservations, c: np.ndarray, f: np.ndarray, m: np.ndarray,
                    col: np.ndarray, n_markers: int) -> _Observations:
    """The observations (camera c, frame f, marker m) of ``ideal`` (each (n,) int, in the row order wanted)
    as :class:`_Observations` with marker columns ``col`` (n,) among ``n_markers``: the cameras' P = K [R | t],
    the ideal pixels, the whitening L^-1 of chol(cov_px2) (closed-form 2x2 Cholesky) and GTSAM's
    behind-camera residual 2 fx."""
    cov = ideal.cov_px2[c, f, m]
    l00 = np.sqrt(cov[:, 0, 0])
    l10 = cov[:, 1, 0] / l00
    l11 = np.sqrt(cov[:, 1, 1] - l10 * l10)
    Linv = np.stack([1 / l00, -l10 / (l00 * l11), 1 / l11])
    P = np.stack([cam.P.ravel() for cam in rig], axis=-1)  # (12, C)
    behind = np.array([2.0 * cam.K[0, 0] for cam in rig])
    # c from np.nonzero is a strided view: contiguous, like every other row array (one compiled kernel)
    return _Observations(f, col, np.ascontiguousarray(c), P, ideal.uv_px[c, f, m].T.copy(), Linv, behind,
                         ideal.seen.shape[1], n_markers)


def _columns(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """a[:, rows] C-contiguous (numpy's fancy indexing on the second axis gives a Fortran-ordered array, which
    the kernels would compile for separately)."""
    return np.ascontiguousarray(a[:, rows])


def _observations(rig: Rig, ideal: IdealObservations, estimated: np.ndarray) -> _Observations:
    """Every observation of the ``estimated`` markers (bool (M,)) as :class:`_Observations`, sorted by
    (frame, marker), columns numbered among the estimated markers."""
    f, m, c = np.nonzero((ideal.seen & estimated[None, None, :]).transpose(1, 2, 0))  # (F, M, C) order
    return projection_rows(rig, ideal, c, f, m, (np.cumsum(estimated) - 1)[m], int(estimated.sum()))


def observation_rows(rig: Rig, ideal: IdealObservations) -> _Observations:
    """Every observation of every marker of ``ideal``, as solve_fast's and solve_levels' ``rows``."""
    return _observations(rig, ideal, np.ones(ideal.seen.shape[2], bool))


def _rows_of(rows: _Observations, estimated: np.ndarray) -> _Observations:
    """The rows of the ``estimated`` markers (bool (M,)) out of :func:`observation_rows`' (the same rows, order
    and columns as :func:`_observations` builds)."""
    if rows.n_markers != len(estimated):
        raise ValueError(f"rows hold {rows.n_markers} markers, the problem {len(estimated)}")
    return rows if estimated.all() else rows.of_markers(estimated)


# the 6 distinct entries (i, j), i <= j, of a symmetric 3x3 block
_IU = np.triu_indices(3)
# the Linearization arrays kernels.projection_sums is given when no Jacobian is asked for
_NO_CELLS6, _NO_CELLS3, _NO_CELLS1 = np.zeros((0, 6)), np.zeros((0, 3)), np.zeros(0)


@dataclass
class _Linearization:
    """The projection factors' part of the Gauss-Newton system at some x, per (frame, marker).

    Hw: ``sum w Jw^T Jw`` with the IRLS weights w (GTSAM's robust whitening), (F, M', 6) upper-triangle
    entries (rows of _IU) [1/m^2]; Hc: the correction ``sum w a Jw^T r r^T Jw / |r|^2`` whose
    subtraction gives the robust loss's own curvature (see :meth:`_Problem.evaluate`), same shape;
    g: gradient ``sum w Jw^T r``, (F, M', 3) [1/m]; rr: ``sum w |r|^2``, (F, M') (the leave-one-out score's).
    """

    Hw: np.ndarray
    Hc: np.ndarray
    g: np.ndarray
    rr: np.ndarray

    def take(self, cols: np.ndarray) -> _Linearization:
        return _Linearization(self.Hw[:, cols], self.Hc[:, cols], self.g[:, cols], self.rr[:, cols])

    def put(self, cols: np.ndarray, other: _Linearization) -> None:
        self.Hw[:, cols], self.Hc[:, cols], self.g[:, cols], self.rr[:, cols] = other.Hw, other.Hc, other.g, other.rr

    def loo(self, Sigma: np.ndarray) -> np.ndarray:
        """Each marker's leave-one-frame-out log predictive score (M',) (noise.loo_log_predictive summed
        over frames) with the marginal covariances Sigma (F, M', d, d) of the same (IRLS) system."""
        A = np.zeros(self.g.shape + (3,))
        A[..., _IU[0], _IU[1]] = self.Hw
        A[..., _IU[1], _IU[0]] = self.Hw
        return noise.loo_log_predictive(self.rr, self.g, A, Sigma[..., :3, :3]).sum(axis=0)


class _Problem:
    """The cost of the shared spec for a set of markers at once, and its Gauss-Newton linearisation.

    Motion in the (scaled) state: e_k = x[k+1] - A x[k] with information Qi, i.e. cost 0.5 e^T Qi e;
    A, Qi = Q1^-1 / noise_scale and the gauge priors' information P0 are cost.scaled_motion's: random
    walk d = 3, A = I3, Qi = I3 / sigma_m^2; constant velocity d = 6, A = [[I, I], [0, I]]; constant
    acceleration d = 9, A = [[I, I, I/2], [0, I, I], [0, 0, I]] (state [p, v dt, a dt^2]). The methods
    take the state x (F, M', d) of M' markers, their prior means mu0 (M', d) and their observations.

    ``noise`` (sigma_m [m], q [m^2/s^3] or j [m^2/s^5]) is a scalar or one value per marker (M',): every
    noise is a scale of a unit one (Q(q) = q Q(1), sigma_m^2 I), so Qi = ``wq`` Qi1 with the per-marker
    weight wq = 1 / noise_scale, shape () or (M',); Qi, AtQiA and B are then (d, d) or (M', d, d). The
    "oscillating" model (d = 18, cost.oscillating_motion) has two levels per marker, ``noise`` (the trend's q)
    and ``oscillation``'s sigma_m: its Qi and P0 are full matrices per marker (M', d, d) (Qi1 is None).
    """

    def __init__(self, model: str, noise: float | np.ndarray, fps: float, robust: str, robust_k: float,
                 oscillation: spec.Oscillation | None = None):
        self.robust, self.k = robust, robust_k
        self.model = model
        self.d = spec.state_dim(model)
        if model == spec.OSCILLATING:  # two noise levels per marker: Qi and P0 are full matrices per marker
            self.A, Q, self.P0 = spec.oscillating_motion(1.0 / fps, oscillation, noise)
            self.Qi = np.linalg.inv(Q)
            self.Qi = 0.5 * (self.Qi + _T(self.Qi))
            self.Qi1, self.wq = None, np.ones(len(Q))
        else:
            self.A, Q1, self.P0 = spec.scaled_motion(model, 1.0 / fps)
            self.Qi1 = np.linalg.inv(Q1)
            self.Qi1 = 0.5 * (self.Qi1 + self.Qi1.T)
            self.wq = 1.0 / spec.noise_scale(model, np.asarray(noise, float))
            w3 = self.wq[..., None, None]  # (1, 1) or (M', 1, 1)
            self.Qi = w3 * self.Qi1
        self.AtQiA = self.A.T @ self.Qi @ self.A
        self.B = -self.Qi @ self.A  # the off-diagonal block H[k+1, k], constant over frames

    def of_markers(self, keep: np.ndarray) -> _Problem:
        """The problem of the markers where ``keep`` (bool over current columns): per-marker noise subset."""
        if self.wq.ndim == 0:
            return self
        out = object.__new__(_Problem)
        out.__dict__.update(self.__dict__)
        out.wq, out.Qi, out.AtQiA, out.B = self.wq[keep], self.Qi[keep], self.AtQiA[keep], self.B[keep]
        if self.P0.ndim == 3:
            out.P0 = self.P0[keep]
        return out

    def _times_P0(self, e0: np.ndarray) -> np.ndarray:
        """e0 P0 per marker (M', d) for first-frame deviations e0 (M', d) (P0 symmetric, shared or per marker)."""
        return np.einsum("mi,mij->mj", e0, self.P0) if self.P0.ndim == 3 else e0 @ self.P0

    def _motion_cost(self, e: np.ndarray) -> np.ndarray:
        """0.5 sum_k e_k^T Qi e_k per marker (M',) of the motion residuals e (F-1, M', d)."""
        if self.Qi1 is None:
            return 0.5 * np.einsum("fmi,fmi->m", np.matmul(e.transpose(1, 0, 2), self.Qi).transpose(1, 0, 2), e)
        return 0.5 * self.wq * np.einsum("fmi,fmi->m", e @ self.Qi1, e)  # (a three-operand einsum: 6x slower)

    def evaluate(self, x: np.ndarray, mu0: np.ndarray, obs: _Observations, jacobian: bool,
                 closest: np.ndarray | None = None) -> tuple[np.ndarray, _Linearization | None]:
        """Total cost per marker (M',) (inf where not finite) and, if asked, the projection factors'
        linearisation at x. ``closest`` (M',), if given, is filled with each marker's largest inverse
        depth over its observations [1/m] (0 when all are behind their cameras).

        The curvature correction Hc is ``w a / |r|^2 (Jw^T r)(Jw^T r)^T`` with a = 1 beyond Huber's k,
        a = min(1, 2|r|^2 / (k^2 + |r|^2)) for Cauchy (clamped so that Hw - Hc stays PSD), 0 for no
        robust loss: Hw - Hc is the robust loss's own curvature in the whitened residual, with which
        the iteration converges quadratically instead of IRLS's linear rate; Hw alone (IRLS) majorises
        the loss (a safe step when the other is rejected) and is what the marginal covariances use.
        """
        F, M = x.shape[:2]
        total = np.zeros(M)
        near = np.zeros(M) if closest is None else closest
        near[:] = 0.0
        n = F * M
        Hw, Hc, g, rr = (np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 3)), np.zeros(n)) if jacobian \
            else (_NO_CELLS6, _NO_CELLS6, _NO_CELLS3, _NO_CELLS1)
        kernels.projection_sums(_positions(x), obs.cell, obs.m, obs.cam, obs.P, obs.uv, obs.Linv, obs.behind_px,
                                kernels.ROBUST_CODE[self.robust], float(self.k), jacobian, total, near, Hw, Hc, g, rr)
        lin = _Linearization(Hw.reshape(F, M, 6), Hc.reshape(F, M, 6), g.reshape(F, M, 3), rr.reshape(F, M)) \
            if jacobian else None
        total += self._motion_cost(x[1:] - x[:-1] @ self.A.T)
        e0 = x[0] - mu0
        total += 0.5 * np.einsum("mi,mi->m", e0, self._times_P0(e0))
        total = np.where(np.isnan(total), np.inf, total)
        return total, lin

    def system(self, x: np.ndarray, mu0: np.ndarray, lin: _Linearization,
               exact: bool | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton diagonal blocks D (F, M', d, d) and gradient g (F, M', d) at x.

        Projection blocks from ``lin`` (at x): Hw - Hc (the robust loss's own curvature) where
        ``exact`` (bool, scalar or per marker (M',)), Hw (IRLS) elsewhere; plus the motion and prior
        cost. The off-diagonal blocks are ``self.B`` (constant over frames).
        """
        F, M = x.shape[:2]
        Hp = lin.Hw - np.asarray(exact, float)[..., None] * lin.Hc  # (F, M', 6)
        D = np.zeros((F, M, self.d, self.d))
        D[..., _IU[0], _IU[1]] = Hp
        D[..., _IU[1], _IU[0]] = Hp
        g = np.zeros((F, M, self.d))
        g[..., :3] = lin.g
        e = x[1:] - x[:-1] @ self.A.T  # (F-1, M, d)
        eQ = np.einsum("fmi,mij->fmj", e, self.Qi) if self.Qi1 is None else (e @ self.Qi1) * self.wq[..., None]
        g[:-1] -= eQ @ self.A
        g[1:] += eQ
        D[:-1] += self.AtQiA
        D[1:] += self.Qi
        D[0] += self.P0
        g[0] += self._times_P0(x[0] - mu0)
        return D, g


@contextmanager
def one_blas_thread():
    """BLAS/OpenMP limited to one thread (threadpoolctl) while the solver runs; re-entrant and cheap
    inside an outer one. Its linear algebra is batches of 3x3 / 6x6 blocks, where extra threads only
    add synchronisation (a 16-core machine must not be slower than a 2-core one)."""
    if _BLAS_GUARD["depth"]:
        _BLAS_GUARD["depth"] += 1
        try:
            yield
        finally:
            _BLAS_GUARD["depth"] -= 1
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        _BLAS_GUARD["depth"] = 1
        try:
            yield
        finally:
            _BLAS_GUARD["depth"] = 0


_BLAS_GUARD = {"depth": 0}


def _one_thread(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)
    return wrapper


def _T(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


def _per_marker_B(B: np.ndarray, M: int) -> np.ndarray:
    """The sub-diagonal block as (M, d, d) contiguous from (d, d) or (M, d, d); a block-diagonal one given as
    its blocks (M, g, b, b) (a segment group, batgraph.graph.rigid) as it is."""
    if B.ndim == 4:
        return np.ascontiguousarray(B)
    return np.ascontiguousarray(np.broadcast_to(B, (M,) + B.shape[-2:]))


def _solve(D: np.ndarray, B: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the block-tridiagonal systems H dx = rhs of all markers (H[k+1, k] = B, constant over frames).

    D: diagonal blocks (F, M, d, d); B (d, d) or per marker (M, d, d), or a block-diagonal one per marker as
    its blocks (M, g, b, b) (d = g b); rhs (F, M, d), or (F, M, d, r) for r right-hand sides at once.
    Returns dx of rhs's shape.
    One sweep over frames eliminates and substitutes forwards (S_k = D_k - L_k B^T with L_k = B S_{k-1}^-1,
    y_k = rhs_k - L_k y_{k-1}), one sweep back-substitutes (compiled: kernels.tridiagonal_solve; one system
    of blocks at least dense_tridiagonal.MIN_DENSE wide, a large segment group, by LAPACK there).
    """
    many = rhs.ndim == D.ndim
    rhs = rhs if many else rhs[..., None]
    Bb = _dense_blocks(D, B)
    if Bb is not None:
        dx = dense_tridiagonal.solve(D[:, 0], Bb, rhs[:, 0])[:, None]
    else:
        dx = kernels.tridiagonal_solve(np.ascontiguousarray(D), _per_marker_B(B, D.shape[1]),
                                       np.ascontiguousarray(rhs))
    return dx if many else dx[..., 0]


def _dense_blocks(D: np.ndarray, B: np.ndarray) -> np.ndarray | None:
    """The blocks (g, b, b) of B when D (F, M, d, d) is one system of blocks at least
    dense_tridiagonal.MIN_DENSE wide (a large segment group, solved by LAPACK there), else None (the kernels)."""
    if D.shape[1] != 1 or D.shape[-1] < dense_tridiagonal.MIN_DENSE:
        return None
    B = np.asarray(B)
    return B.reshape((-1,) + B.shape[-2:]) if B.ndim >= 3 else B[None]


def logdet(D: np.ndarray, B: np.ndarray) -> np.ndarray:
    """log det H (M,) of block-tridiagonal H (see :func:`marginals`): sum_k log det S_k, forward sweep only."""
    Bb = _dense_blocks(D, B)
    if Bb is not None:
        return np.array([dense_tridiagonal.logdet(D[:, 0], Bb)])
    return kernels.tridiagonal_logdet(np.ascontiguousarray(D), _per_marker_B(B, D.shape[1]))


def solve_and_marginals(D: np.ndarray, B: np.ndarray, rhs: np.ndarray, covariances: bool = True
                        ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """:func:`_solve` of rhs (F, M, d, r), :func:`marginals`' Sigma (F, M, d, d) (None unless ``covariances``)
    and log det H (M,); for a large segment group in one forward sweep (dense_tridiagonal), else as those."""
    Bb = _dense_blocks(D, B)
    if Bb is not None:
        dx, Sigma, ld = dense_tridiagonal.solve_and_marginals(D[:, 0], Bb, rhs[:, 0], covariances)
        return dx[:, None], None if Sigma is None else Sigma[:, None], np.array([ld])
    dx = _solve(D, B, rhs)
    if covariances:
        return (dx, *marginals(D, B))
    return dx, None, logdet(D, B)


def evidence_slope(prob: _Problem, x: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log det H (M',), d log evidence / d ln level (M',)) at the minimiser x (F, M', d) of ``prob`` whose
    Gauss-Newton diagonal blocks are D (F, M', d, d); H is in the solver's scaled state, as :func:`logdet`'s.

    For a model whose motion information is Qi = Qi1 / level (constant velocity: q; constant acceleration:
    j), the Laplace log evidence (noise.laplace_log_evidence) -E(x*) - 0.5 log det H + 0.5 log det H_prior
    has, through x* (envelope theorem: x* minimises E) and through the motion part H_m of H, the slope
        d/d ln level = E_motion(x*) + 0.5 tr(H^-1 H_m) - 0.5 (F - 1) d
    (E_motion = 0.5 sum_k e_k^T Qi e_k; the prior's log det is -(F - 1) d ln level + const). It leaves out
    how H's projection blocks move with x* (their Jacobians and robust weights; tested small against
    finite differences of the score). Zero slope is EM's fixed point: the posterior's expected motion
    cost sum_k E[e_k^T Qi e_k] equals the number of motion dimensions (F - 1) d.
    """
    if prob.Qi1 is None:
        raise ValueError("the evidence's slope needs a model whose noise is one scale (not oscillating)")
    ld, tr = kernels.tridiagonal_motion_trace(np.ascontiguousarray(D), *_each(prob, D.shape[1]))
    return ld, _slope(prob, x, tr)


def _slope(prob: _Problem, x: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """:func:`evidence_slope`'s slope (M',) at x (F, M', d) from the trace tr(H^-1 H_m) (M',)."""
    F, d = x.shape[0], prob.d
    return prob._motion_cost(x[1:] - x[:-1] @ prob.A.T) + 0.5 * trace - 0.5 * (F - 1) * d


def _each(prob: _Problem, M: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """prob's B, AtQiA and Qi as (M, d, d) C-contiguous (one per marker, as the kernels take them)."""
    return tuple(np.ascontiguousarray(np.broadcast_to(a, (M, prob.d, prob.d))) for a in (prob.B, prob.AtQiA, prob.Qi))


class _Surrogate:
    """Each marker's Laplace evidence as a function of its noise level, with the projection factors replaced by
    their quadratic model at a state x0 (F, M', d): their gradient g and IRLS curvature Hw there (the curvature
    the log det and the marginals use; for Huber a majoriser of the loss); the motion and gauge-prior terms
    exact.

    :meth:`evaluate` at any level needs no projection: the quadratic model's minimiser there (a Gauss-Newton step
    from x0 at that level), its cost and log det, and for a model whose motion information is one scale
    (constant velocity, acceleration) its slope (:func:`evidence_slope`'s formula, exactly the derivative of the
    surrogate's own score, since nothing it leaves out moves), all in one block-tridiagonal sweep
    (kernels.tridiagonal_solve_motion_trace); the "oscillating" model (levels q and sigma_m) takes a solve and a
    log det. Where x0 minimises the cost at a level, the surrogate's cost, log det and slope at that level are
    solve_fast's. Elsewhere it misses how the projections' Jacobians and weights move with
    the solution: linearised at a solution, its maximum was within 0.05 decade of the evidence's on the accuracy
    study's scenes but 0.12 decade off on a test scene with long weakly observed runs, so the noise search only
    begins where it points (:func:`_slope_search`).
    """

    def __init__(self, prob: _Problem, fps: float, x0: np.ndarray, mu0: np.ndarray, obs: _Observations,
                 hz: float | None = None):
        """Linearised at x0 (F, M', d) with prior means mu0 (M', d), the markers of ``obs``; ``prob``'s levels are
        immaterial. hz: the wingbeat frequency [Hz] of the "oscillating" model."""
        self.model, self.fps, self.robust, self.k, self.hz = prob.model, fps, prob.robust, prob.k, hz
        cost, self.lin = prob.evaluate(x0, mu0, obs, jacobian=True)
        self.x0, self.mu0 = x0, mu0
        e0 = x0[0] - mu0
        # the projection factors' part of the cost at x0 (M',)
        self.e_data = cost - prob._motion_cost(x0[1:] - x0[:-1] @ prob.A.T) - 0.5 * np.einsum(
            "mi,mi->m", e0, prob._times_P0(e0))

    def take(self, cols: np.ndarray) -> _Surrogate:
        """The surrogate of the columns ``cols`` (int or bool over M')."""
        out = object.__new__(_Surrogate)
        out.__dict__.update(self.__dict__)
        out.x0, out.mu0, out.lin, out.e_data = self.x0[:, cols], self.mu0[cols], self.lin.take(cols), self.e_data[cols]
        return out

    def evaluate(self, level: np.ndarray, sigma_m: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
        """At noise levels ``level`` (M',) (and the "oscillating" model's sigma_m (M',)): the surrogate's cost
        (M',), log det (M', spec units, as solve_fast's logdet_per_marker), evidence slope per ln level (M',
        :func:`evidence_slope`; None for "oscillating") and minimiser x (F, M', d)."""
        osc = None if self.hz is None else spec.Oscillation(self.hz, np.asarray(sigma_m, float))
        prob = _Problem(self.model, np.asarray(level, float), self.fps, self.robust, self.k, osc)
        D, g = prob.system(self.x0, self.mu0, self.lin, exact=False)
        if prob.Qi1 is None:
            dx, _, ld = solve_and_marginals(D, prob.B, -g[..., None], covariances=False)
            x, trace = self.x0 + dx[..., 0], None
        else:
            dx, ld, trace = kernels.tridiagonal_solve_motion_trace(D, *_each(prob, D.shape[1]),
                                                                   np.ascontiguousarray(-g[..., None]))
            x = self.x0 + dx[..., 0]
        dp = x[..., :3] - self.x0[..., :3]
        H = self.lin.Hw  # upper triangle (00, 01, 02, 11, 12, 22) per cell
        quad = (H[..., 0] * dp[..., 0] ** 2 + H[..., 3] * dp[..., 1] ** 2 + H[..., 5] * dp[..., 2] ** 2
                + 2 * (H[..., 1] * dp[..., 0] * dp[..., 1] + H[..., 2] * dp[..., 0] * dp[..., 2]
                       + H[..., 4] * dp[..., 1] * dp[..., 2]))
        e0 = x[0] - self.mu0
        cost = (self.e_data + np.einsum("fmi,fmi->m", self.lin.g, dp) + 0.5 * quad.sum(axis=0)
                + prob._motion_cost(x[1:] - x[:-1] @ prob.A.T) + 0.5 * np.einsum("mi,mi->m", e0, prob._times_P0(e0)))
        slope = None if trace is None else _slope(prob, x, trace)
        return cost, ld + 2 * x.shape[0] * spec.log_det_scale(self.model, 1.0 / self.fps), slope, x


def marginals(D: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks of H^-1 and log det H for block-tridiagonal H (RTS-style backward recursion).

    D: diagonal blocks (F, M, d, d); B: the sub-diagonal block H[k+1, k], constant over frames, (d, d)
    or per marker (M, d, d).
    Returns Sigma (F, M, d, d) and logdet (M,). With S_k the forward Schur complements,
    Sigma_{F-1} = S_{F-1}^-1 and Sigma_k = S_k^-1 + G_k Sigma_{k+1} G_k^T, G_k = S_k^-1 B^T
    (x_k given x_{k+1} is N(-G_k x_{k+1}, S_k^-1)); log det H = sum_k log det S_k (compiled:
    kernels.tridiagonal_marginals; a large segment group by LAPACK: see :func:`_solve`).
    """
    Bb = _dense_blocks(D, B)
    if Bb is not None:
        Sigma, ld = dense_tridiagonal.marginals(D[:, 0], Bb)
        return Sigma[:, None], np.array([ld])
    return kernels.tridiagonal_marginals(np.ascontiguousarray(D), _per_marker_B(B, D.shape[1]))


@_one_thread
def solve_fast(session_or_rig: Session | Rig, ideal: IdealObservations, p_init: np.ndarray, model: str,
               noise_level: float | np.ndarray, fps: float, robust: str = "huber", robust_k: float = 2.0,
               v_init: np.ndarray | None = None, p_start: np.ndarray | None = None, max_iterations: int = 200,
               covariances: bool = True, a_init: np.ndarray | None = None, loo: bool = False,
               oscillation: spec.Oscillation | None = None, rows: _Observations | None = None,
               slope: bool = False, step_tol_m: float = STEP_TOL_M) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Minimise the smoother's cost for a fixed rig; positions, marginal covariances and figures.

    session_or_rig: the rig (or a session, whose rig is used); camera pose covariances are ignored.
    ideal: ideal pixels (C, F, M, 2) and their covariances (C, F, M, 2, 2) (batgraph.measurement).
    p_init: initial positions (F, M, 3) [m, world], finite on every frame of an estimated marker and
        all NaN for a marker not estimated (see batgraph.graph.cost.initial_track); p_init[0] is the
        mean of the weak position prior and p_init the starting point unless ``p_start`` is given.
    model: "random_walk" (noise_level = sigma_m, per-axis std per frame [m]), "constant_velocity"
        (noise_level = q, acceleration PSD [m^2/s^3]) or "constant_acceleration" (noise_level = j, jerk
        PSD [m^2/s^5]); noise_level is one value for every marker or one per marker, shape (M,) (entries
        of markers not estimated are ignored and may be NaN). "oscillating" (noise_level = the trend's q
        [m^2/s^3]) also needs ``oscillation`` (cost.Oscillation: the wingbeat frequency and each marker's
        sigma_m, a scalar or (M,)); see cost.oscillating_motion.
    fps: frame rate [Hz]; robust, robust_k: loss on projection factors (see :func:`robust_loss`).
    v_init: starting velocities (F, M, 3) [m/s] (constant velocity / acceleration); default
        np.gradient(p_init) * fps. a_init: starting accelerations (F, M, 3) [m/s^2] (constant
        acceleration); default np.gradient of the starting velocities times fps.
    p_start: starting positions (F, M, 3) [m] (a warm start), default p_init.
    covariances: False skips the marginal covariances (cov is None; log det is still computed, from
        the forward sweep alone): what a search over the noise level by the evidence needs.
    loo: also each marker's leave-one-frame-out score (needs, and implies, the marginal covariances).
    rows: every observation of every marker of ``ideal`` (:func:`observation_rows`), for a caller that solves
        the same observations many times (the noise search: building them cost ~36 ms a solve at 30 x 180 x 160);
        default built here.
    step_tol_m: the step tolerance below [m]; :data:`LOOSE_STEP_TOL_M` for a solve that only scores.

    Levenberg-Marquardt per marker (vectorised: all markers step together, each with its own damping
    lambda * diag(H), a step accepted only when that marker's cost does not increase) until the
    largest step is < ``step_tol_m`` (default 1e-10 m), the relative cost decrease < 1e-15, or a rejected
    step's predicted decrease is below the cost's rounding (4 eps; such steps are ~1e-9 m). The first step, and a step
    after a rejected one, use the IRLS curvature (it majorises the robust loss); the others the robust
    loss's own curvature (see ``_Problem.evaluate``), so robust problems converge in a few iterations.

    Returns xyz (F, M, 3) [m], cov (F, M, 3, 3) [m^2] (marginal of each p[m, k] from the Gauss-Newton
    Hessian at the minimiser, with the IRLS weights there), both NaN for markers not estimated, and
    info: iterations (max over markers), iterations_per_marker (M,), converged (M,) bool, cost (total
    at the minimiser), at_camera (M,) bool (stopped, not converged: the iterate ran into a camera
    centre along a single-view run, where the cost has no minimum in front of the camera; see
    AT_CAMERA_DEPTH_FRACTION), cost_per_marker (M,), logdet (log det of the whole Hessian in the spec's
    variables [p m, v m/s, a m/s^2]; sum over markers), logdet_per_marker (M,), velocity (F, M, 3) [m/s]
    or None, acceleration (F, M, 3) [m/s^2] or None, estimated (M,) bool, loo_per_marker (M,) (each
    marker's leave-one-frame-out score, noise.loo_log_predictive; None unless ``loo``).
    """
    rig = session_or_rig.rig if isinstance(session_or_rig, Session) else session_or_rig
    C, F, M = ideal.seen.shape
    _check(model, robust, p_init, noise_level, F, M)
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    ms = np.flatnonzero(estimated)  # the state holds the estimated markers only
    level = np.asarray(noise_level, float)
    osc = None if oscillation is None else oscillation.of(ms)
    if model == spec.OSCILLATING:
        if oscillation is None:
            raise ValueError("the oscillating model needs an oscillation (cost.Oscillation)")
        level = np.broadcast_to(level, (M,))
    prob = _Problem(model, level if level.ndim == 0 else level[ms], fps, robust, robust_k, osc)
    obs = _observations(rig, ideal, estimated) if rows is None else _rows_of(rows, estimated)
    x, mu0 = _start(prob, p_init, v_init, p_start, ms, fps, a_init)
    x, cost, lin, iters, converged, at_camera = _levenberg_marquardt(prob, obs, x, mu0, max_iterations, step_tol_m)
    D, _ = prob.system(x, mu0, lin, exact=False)
    covariances = covariances or loo
    slope_e = None
    if covariances:
        Sigma_e, logdet_e = marginals(D, prob.B)
    elif slope:
        Sigma_e, (logdet_e, slope_e) = None, evidence_slope(prob, x, D)
    else:
        Sigma_e, logdet_e = None, logdet(D, prob.B)
    loo_e = lin.loo(Sigma_e) if loo else None
    dt = 1.0 / fps
    d = prob.d
    # back to the spec's variables: v = u / dt, a = w / dt^2, so H_v = H_u dt^2, H_a = H_w dt^4 per axis
    logdet_e = logdet_e + 2 * F * spec.log_det_scale(model, dt)
    x_all = np.full((F, M, d), np.nan)
    x_all[:, ms] = x
    xyz = x_all[..., :3]
    if covariances:
        Sigma = np.full((F, M, d, d), np.nan)
        Sigma[:, ms] = Sigma_e
        cov = Sigma[..., :3, :3]
    else:
        cov = None
    velocity, acceleration = _derivatives(x_all, dt, None if oscillation is None else oscillation.hz)

    def per_marker(a, fill):
        out = np.full(M, fill, dtype=np.asarray(a).dtype)
        out[ms] = a
        return out

    info = {
        "iterations": int(iters.max(initial=0)), "iterations_per_marker": per_marker(iters, 0),
        "converged": per_marker(converged, False), "at_camera": per_marker(at_camera, False),
        "cost": float(cost.sum()),
        "cost_per_marker": per_marker(cost, 0.0), "logdet": float(logdet_e.sum()),
        "logdet_per_marker": per_marker(logdet_e, 0.0), "position": xyz, "velocity": velocity,
        "acceleration": acceleration, "estimated": estimated,
        "loo_per_marker": None if loo_e is None else per_marker(loo_e, 0.0),
        "slope_per_marker": None if slope_e is None else per_marker(slope_e, np.nan),
    }
    return xyz, cov, info


def _check(model: str, robust: str, p_init: np.ndarray, noise_level, F: int, M: int) -> None:
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if robust not in ROBUST:
        raise ValueError(f"robust must be one of {ROBUST}, got {robust!r}")
    if p_init.shape != (F, M, 3):
        raise ValueError(f"p_init must have shape {(F, M, 3)}, got {p_init.shape}")
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    if np.isfinite(p_init[:, ~estimated]).any():
        raise ValueError("p_init must be finite on every frame of a marker or NaN on all of them")
    if np.ndim(noise_level) not in (0, 1) or np.ndim(noise_level) == 1 and np.shape(noise_level) != (M,):
        raise ValueError(f"noise_level must be a scalar or have shape {(M,)}, got {np.shape(noise_level)}")


def _start(prob: _Problem, p_init: np.ndarray, v_init: np.ndarray | None, p_start: np.ndarray | None,
           ms: np.ndarray, fps: float, a_init: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The starting state x (F, M', d) of markers ``ms`` and their prior means mu0 (M', d) (velocity and
    acceleration 0). Velocities v_init [m/s] default to np.gradient(p_init) fps, accelerations a_init
    [m/s^2] (constant acceleration) to np.gradient of the starting velocities times fps."""
    F = p_init.shape[0]
    dt = 1.0 / fps
    x = np.zeros((F, len(ms), prob.d))
    x[..., :3] = (p_init if p_start is None else p_start)[:, ms]
    if prob.d >= 6:
        v = _gradient(p_init, fps) if v_init is None else v_init
        x[..., 3:6] = v[:, ms] * dt
        if prob.d == 9:
            x[..., 6:9] = (_gradient(v[:, ms], fps) if a_init is None else a_init[:, ms]) * (dt * dt)
    mu0 = np.zeros((len(ms), prob.d))
    mu0[:, :3] = p_init[0, ms]
    return x, mu0


def _gradient(a: np.ndarray, fps: float) -> np.ndarray:
    """d a / dt along frames (axis 0) by np.gradient, zero for a single frame."""
    return np.gradient(a, axis=0) * fps if len(a) > 1 else np.zeros_like(a)


def _derivatives(x: np.ndarray, dt: float, hz: float | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Velocities [m/s] and accelerations [m/s^2] (..., 3) of states x (..., d) [m] (None where the model
    has none): v = u / dt, a = w / dt^2. The oscillating model (d > 9, wingbeat frequency ``hz``): the
    trend's u / dt plus each harmonic's d c_h / dt = 2 pi h hz s_h; no acceleration."""
    d = x.shape[-1]
    v = spec.velocity_mps(x[..., 3:6], dt) if d >= 6 else None
    if d > 9:
        for h in range(spec.OSC_HARMONICS):
            v = v + 2 * np.pi * (h + 1) * hz * x[..., 9 + 6 * h:12 + 6 * h]
    a = spec.acceleration_mps2(x[..., 6:9], dt) if d == 9 else None
    return v, a


def _levenberg_marquardt(prob: _Problem, obs_all: _Observations, x: np.ndarray, mu0: np.ndarray,
                         max_iterations: int, step_tol_m: float = STEP_TOL_M):
    """Levenberg-Marquardt per marker column from x (F, M', d) (see :func:`solve_fast`; step_tol_m [m]).

    Returns (x, cost (M',), linearisation at x, iterations (M',), converged (M',) bool, at_camera (M',)
    bool: stopped because an accepted iterate put an observed point at a depth below
    AT_CAMERA_DEPTH_FRACTION of the marker's closest depth at the start, i.e. the minimiser lies on the
    cheirality boundary at a camera centre and does not exist in front of it; never converged).
    """
    M = x.shape[1]
    d = prob.d
    near = np.zeros(M)  # each marker's largest inverse depth over its observations [1/m]
    cost, lin = prob.evaluate(x, mu0, obs_all, jacobian=True, closest=near)
    limit = np.where(near > 0, near / AT_CAMERA_DEPTH_FRACTION, np.inf)  # the "at the camera" inverse depth
    at_camera = np.zeros(M, bool)
    lam = np.zeros(M)  # damping of IRLS steps
    lam_x = np.zeros(M)  # damping of exact steps (own curvature): remembers their rejections
    exact = np.zeros(M, bool)  # the next step uses the loss's own curvature (else IRLS's)
    robust = prob.robust != "none"  # without a robust loss both curvatures are one: one damping
    active = np.ones(M, bool)
    iters = np.zeros(M, int)
    converged = np.zeros(M, bool)
    diag = np.arange(d)
    eps = np.finfo(float).eps
    obs, cols, obs_cols, prob_a = obs_all, np.arange(M), M, prob
    for _ in range(max_iterations):
        if not active.any():
            break
        # converged markers drop out: solve only the active ones (most converge in a few iterations)
        act = np.flatnonzero(active)
        if len(act) < obs_cols:  # shrink the observation set along with the active markers
            obs, prob_a = obs.of_markers(active[cols]), prob_a.of_markers(active[cols])
            cols, obs_cols = act, len(act)
        xa = x[:, act]
        D, g = prob_a.system(xa, mu0[act], lin.take(act), exact[act])
        damping = np.where(exact[act] & robust, lam_x[act], lam[act])
        D[..., diag, diag] *= 1.0 + damping[None, :, None]
        dx = _solve(D, prob_a.B, -g)
        xn = xa + dx
        near_new = np.zeros(len(act))
        cost_new, lin_new = prob_a.evaluate(xn, mu0[act], obs, jacobian=True, closest=near_new)
        ok = cost_new <= cost[act]
        step = np.abs(dx).max(axis=(0, 2))
        rel = (cost[act] - cost_new) / np.maximum(cost[act], np.finfo(float).tiny)
        gain = -0.5 * np.einsum("fmi,fmi->m", g, dx)  # the damped quadratic model's decrease
        flat = ~ok & (gain <= ROUNDING_EPS * eps * cost[act])  # no decrease the cost could resolve
        x[:, act[ok]] = xn[:, ok]
        lin.put(act[ok], lin_new.take(ok))
        stuck = lam[act] > 1e12  # IRLS steps (which majorise the loss) rejected even when tiny
        pupil = ok & (near_new > limit[act])  # accepted into a camera centre: no minimum in front of it
        at_camera[act] = pupil
        done = (ok & (rel < REL_COST_TOL)) | (step < step_tol_m) | flat | stuck | pupil
        converged[act] = done & ~stuck & ~pupil
        iters[act] += 1
        cost[act] = np.where(ok, cost_new, cost[act])
        # accepted: less damping (of that kind of step), next step exact; rejected exact step: more
        # damping for exact steps, retry now with the IRLS curvature (it majorises the robust loss);
        # rejected IRLS step: more damping. (One damping for both let an undamped exact step overshoot a
        # Huber kink again after every accepted IRLS step: measured 60 such rejected/accepted pairs.)
        lam[act], lam_x[act] = next_damping(exact[act] & robust, ok, damping, lam[act], lam_x[act], robust)
        exact[act] = ok
        active[act] = ~done
    return x, cost, lin, iters, converged, at_camera


def next_damping(was_exact, ok, damping, lam, lam_x, robust: bool):
    """The Levenberg-Marquardt damping after a step (arrays per column, or scalars): returns (lam, lam_x),
    the damping of IRLS and of exact steps. An accepted step divides its kind's damping by 10 (down to
    0), a rejected one multiplies it by 10 (from 1e-6); ``damping`` is what the step used, ``was_exact``
    whether it was an exact step. Without a robust loss both curvatures are one: one damping."""
    less = np.where(damping > 1e-9, damping / 10, 0.0)
    more = np.maximum(damping * 10, 1e-6)
    lam_x = np.where(was_exact, np.where(ok, less, more), lam_x)
    lam = np.where(was_exact, lam, np.where(ok, less, more))
    return lam, (lam_x if robust else lam)


@_one_thread
def solve_levels(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, model: str, levels: np.ndarray,
                 fps: float, robust: str = "huber", robust_k: float = 2.0, v_start: np.ndarray | None = None,
                 p_start: np.ndarray | None = None, max_iterations: int = 200, max_rows: int = MAX_BATCH_ROWS,
                 a_start: np.ndarray | None = None, loo: bool = False, oscillation: spec.Oscillation | None = None,
                 rows: _Observations | None = None, slope: bool = False, step_tol_m: float = STEP_TOL_M) -> dict:
    """:func:`solve_fast` at K noise levels at once, without covariances: the search over q in one batch.

    levels: (K, M) noise levels (sigma_m [m], q [m^2/s^3] or j [m^2/s^5]), one row per candidate. The K copies of
    every marker are independent columns of one Levenberg-Marquardt run (candidates x markers as the
    batch axis, each column with its own damping and stopping), so a candidate's answer is exactly
    the one solve_fast gives with that row (to the solver's tolerance); the observation rows are
    repeated per candidate, in groups of candidates of at most ``max_rows`` rows in all.
    v_start, p_start, a_start: one start (F, M, 3) for every candidate, or one per candidate (K, F, M, 3).
    oscillation: the "oscillating" model's, its sigma_m one per candidate and marker (K, M).
    rows, step_tol_m: as solve_fast's.
    Returns a dict of per-candidate arrays: cost (K, M), logdet (K, M) (spec units, as solve_fast's
    logdet_per_marker), position (K, F, M, 3), velocity and acceleration (K, F, M, 3) or None,
    iterations (K, M), converged (K, M), at_camera (K, M) (as solve_fast's), and with ``loo`` the
    leave-one-frame-out score loo (K, M) (solve_fast's loo_per_marker: the marginals are then computed), with
    ``slope`` the evidence's slope (K, M) per ln level (:func:`evidence_slope`; else None);
    NaN / 0 for markers not estimated.
    """
    levels = np.asarray(levels, float)
    C, F, M = ideal.seen.shape
    if levels.ndim != 2 or levels.shape[1] != M:
        raise ValueError(f"levels must have shape (K, {M}), got {levels.shape}")
    _check(model, robust, p_init, levels[0], F, M)
    K = len(levels)
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    ms = np.flatnonzero(estimated)
    obs = _observations(rig, ideal, estimated) if rows is None else _rows_of(rows, estimated)
    dt = 1.0 / fps
    d = spec.state_dim(model)
    out = {"cost": np.zeros((K, M)), "logdet": np.zeros((K, M)), "position": np.full((K, F, M, 3), np.nan),
           "velocity": np.full((K, F, M, 3), np.nan) if d >= 6 else None,
           "acceleration": np.full((K, F, M, 3), np.nan) if d == 9 else None,
           "iterations": np.zeros((K, M), int), "converged": np.zeros((K, M), bool),
           "at_camera": np.zeros((K, M), bool), "loo": np.zeros((K, M)) if loo else None,
           "slope": np.full((K, M), np.nan) if slope else None}
    group = max(1, min(int(max_rows // max(1, len(obs.f))), MAX_BATCH_STATE // max(1, F * len(ms) * d * d)))

    def pick(a, k):
        return a if a is None or a.ndim == 3 else a[k]

    for k0 in range(0, K, group):
        ks = np.arange(k0, min(K, k0 + group))
        osc = None if oscillation is None else spec.Oscillation(
            oscillation.hz, np.broadcast_to(oscillation.sigma_m, (K, M))[ks][:, ms].ravel())
        prob = _Problem(model, levels[ks][:, ms].ravel(), fps, robust, robust_k, osc)
        starts = [_start(prob, p_init, pick(v_start, k), pick(p_start, k), ms, fps, pick(a_start, k)) for k in ks]
        x = np.concatenate([s[0] for s in starts], axis=1)
        mu0 = np.concatenate([s[1] for s in starts])
        x, cost, lin, iters, converged, at_camera = _levenberg_marquardt(prob, obs.tile(len(ks)), x, mu0,
                                                                         max_iterations, step_tol_m)
        D, _ = prob.system(x, mu0, lin, exact=False)
        if loo:
            Sigma, ld = marginals(D, prob.B)
            score = lin.loo(Sigma)
        elif slope:
            ld, score = evidence_slope(prob, x, D)
        else:
            ld = logdet(D, prob.B)
        ld = ld + 2 * F * spec.log_det_scale(model, dt)  # spec units (as solve_fast)
        v, a = _derivatives(x, dt, None if oscillation is None else oscillation.hz)
        n = len(ms)
        for j, k in enumerate(ks):
            cols = slice(j * n, (j + 1) * n)
            out["cost"][k, ms], out["logdet"][k, ms] = cost[cols], ld[cols]
            if loo or slope:
                out["loo" if loo else "slope"][k, ms] = score[cols]
            out["iterations"][k, ms], out["converged"][k, ms] = iters[cols], converged[cols]
            out["at_camera"][k, ms] = at_camera[cols]
            out["position"][k][:, ms] = x[:, cols, :3]
            for key, val in (("velocity", v), ("acceleration", a)):
                if val is not None:
                    out[key][k][:, ms] = val[:, cols]
    return out


@_one_thread
def choose_noise_per_marker(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                            markers: np.ndarray, fps: float, robust: str, robust_k: float,
                            p_start: np.ndarray | None = None, v_start: np.ndarray | None = None,
                            progress: bool = False, model: str = "constant_velocity",
                            a_start: np.ndarray | None = None, rule: str = "evidence",
                            oscillation_hz: float | None = None) -> tuple[np.ndarray, dict]:
    """Each marker's best-scoring noise level of ``model`` for a fixed rig: q [m^2/s^3] (constant
    velocity) or j [m^2/s^5] (constant acceleration) (batgraph.graph.noise). ``rule`` (noise.NOISE_RULES):
    "evidence" scores by the Laplace marginal likelihood (as described below), "loo" by the
    leave-one-frame-out log predictive density (noise.loo_log_predictive; every solve then computes
    the marginal covariances); the search is the same.

    rig: fixed cameras (pose covariances ignored). ideal: ideal pixels (C, F, M, 2) and covariances
    (C, F, M, 2, 2). p_init, v_init: initial track (F, M, 3) [m], [m/s] (factors.initial_track);
    p_init[0] is the gauge prior's mean. markers: int indices of the markers to fit (estimated ones).
    p_start, v_start, a_start: where the first solves start (F, M, 3) [m], [m/s], [m/s^2]
    (default p_init, v_init and solve_fast's default accelerations), e.g. the cleaning solution.

    Constant velocity and constant acceleration scored by the evidence (the default): :func:`_slope_search`,
    the evidence's values and slopes (:func:`evidence_slope`) by noise.SlopeSearch, begun where the evidence's
    :class:`_Surrogate` at the start peaks (the range's lower end solved only where that surrogate does not put
    it far below), then one solve_fast of the markers still searching per step. On 7 simulated scenes the
    search begun at SLOPE_START chose q within 0.04 decade of the grid + Brent search below (evidence
    -0.6..+0.06 nats) in 0.5-0.9x its time, and j within 0.024 decade but for one wing tip whose evidence is
    ragged beside a camera centre (0.086 decade, -4.4 nats); begun at the surrogate's peak, it chose the same
    levels to 0.05 decade in about half the solves (BENCHMARKS.md).

    Otherwise (the "loo" rule, the oscillating model): the grid over noise.LOG10_RANGE[model], every
    noise.LOG10_GRID_STEP decades, is ONE batched solve
    (:func:`solve_levels`: levels x markers as the batch axis, every column from the start, so no stiff
    solution is ever carried to a neighbouring level, which once dragged wing markers off their track).
    Then Brent's search per marker (noise.Bracket: parabolic steps through the best three points, golden-section
    steps where those fail), vectorised (each step is one solve_fast of the markers still searching, one
    level each, warm-started from their previous step, without covariances), in [best - step, best + step]
    from the grid's three points there, until the bracket is noise.LOG10_Q_TOL wide (at most
    twice the steps golden section takes); the answer is each marker's best level evaluated. It
    took 4.5-7 steps per marker where golden section takes 10-12, and chose q within 0.018 decade of
    golden's (evidence within -0.06..+0.8 nats) on the simulated scenes of BENCHMARKS.md. Score
    per marker: laplace_log_evidence of its own chain (cost and log det from :func:`solve_fast`, which
    are exactly per marker; the gauge priors' constant included, so scores of models compare); -inf
    for a level whose solve ran into a camera centre (``at_camera``: no mode in front of the camera, so
    no Laplace approximation; a marker with no other level scores -inf and "auto" keeps the other model).
    n_solves counts the batched grid as one.

    The "oscillating" model (wingbeat frequency ``oscillation_hz`` [Hz]) has two noise levels per marker: the
    trend's q and the oscillation's sigma_m. Its grid is q every noise.LOG10_GRID_STEP decades times sigma_m
    every decade of noise.OSC_LOG10_SIGMA_RANGE; scored by the evidence, every grid point is scored first by the
    evidence's :class:`_Surrogate` at the start (no projection) and only each marker's GRID_TOP best are solved
    (one batched solve: each of its 18-wide blocks costs ~27 times a constant-velocity one), the same chosen
    levels as solving all 20 on six scenes (2026-11-25, BENCHMARKS.md) in 0.4-0.9x the search's time; with
    the "loo" rule all are solved. Brent's search then on log10 q within a grid step of the best point, at its
    sigma_m, and last on log10 sigma_m within a decade, at that q (coordinate-wise: measured against the full
    half-decade grid on the hold-out scenes in docs/accuracy.md); a grid neighbour not solved is an end of
    unknown score.

    Returns the level (M,) (NaN for markers not in ``markers``) and info: per_marker {index: level},
    rule, n_solves, log_evidence (M,) (each marker's best score; NaN for the others), solution: the solve at
    that level, (positions, velocities, accelerations) (F, M, 3) or None, NaN for the other markers and those
    with no scored level; oscillating: sigma_m (M,).
    """
    markers = np.asarray(markers, int)
    F, M = p_init.shape[:2]
    dt = 1.0 / fps
    sub = IdealObservations(ideal.uv_px[:, :, markers], ideal.cov_px2[:, :, markers])
    rows = observation_rows(rig, sub)  # built once for every solve of the search
    p0 = p_init[:, markers]
    cut = (lambda a: None if a is None else a[:, markers])  # noqa: E731
    start = (cut(p_init if p_start is None else p_start), cut(v_init if v_start is None else v_start), cut(a_start))
    n_solves = 0

    if rule not in noise.NOISE_RULES:
        raise ValueError(f"rule must be one of {noise.NOISE_RULES}, got {rule!r}")
    loo = rule == "loo"

    def evidence(cost, logdet_, level, loo_score=None, osc=None):
        return loo_score if loo else noise.laplace_log_evidence(cost, logdet_, level, dt, F - 1, model=model,
                                                                oscillation=osc)

    def solve(level: np.ndarray, from_: tuple, osc: spec.Oscillation | None, live: np.ndarray | None = None):
        """Scores (M',) at ``level`` and the solution (the next warm start); only the ``live`` markers are
        solved (solve_fast skips a marker whose initial track is NaN): the others score -inf and keep from_."""
        nonlocal n_solves
        n_solves += 1
        p = p0 if live is None else np.where(live[None, :, None], p0, np.nan)
        _, _, info = solve_fast(rig, sub, p, model, level, fps, robust, robust_k, v_init=from_[1],
                                p_start=from_[0], a_init=from_[2], covariances=False, loo=loo, oscillation=osc,
                                rows=rows, step_tol_m=LOOSE_STEP_TOL_M)
        score = evidence(info["cost_per_marker"], info["logdet_per_marker"], level, info["loo_per_marker"], osc)
        score = np.where(info["at_camera"], -np.inf, score)  # no mode in front of the camera: no Laplace score
        new = (info["position"], info["velocity"], info["acceleration"])
        if live is None:
            return score, new
        keep = (lambda n, o: None if n is None else np.where(live[None, :, None], n, o))  # noqa: E731
        return np.where(live, score, -np.inf), tuple(keep(n, o) for n, o in zip(new, from_, strict=True))

    def n_golden(width: float) -> int:
        return math.ceil(math.log(noise.LOG10_Q_TOL / width) / math.log(noise._GOLDEN)) + 2

    if not loo and model in SLOPE_START:
        level, ev, n_solves, at = _slope_search(rig, sub, rows, p0, start, model, fps, robust, robust_k, progress)
        lv, evm = np.full(M, np.nan), np.full(M, np.nan)
        lv[markers], evm[markers] = level, ev
        return lv, {"rule": noise.per_marker_rule(model, rule), "per_marker": {int(m): float(lv[m]) for m in markers},
                    "n_solves": n_solves, "log_evidence": evm, "solution": _full_width(at, markers, M)}
    osc_model = model == spec.OSCILLATING
    if osc_model and oscillation_hz is None:
        raise ValueError("the oscillating model needs the wingbeat frequency (oscillation_hz)")
    lo, hi = noise.LOG10_RANGE[model]
    step = noise.LOG10_GRID_STEP  # the grid's spacing in log10 q, and Brent's half bracket
    grid = np.arange(math.ceil(lo), math.floor(hi) + 1, step, dtype=float)
    s_lo, s_hi = noise.OSC_LOG10_SIGMA_RANGE
    sig_grid = np.arange(s_lo, s_hi + 0.5, 1.0) if osc_model else np.full(1, np.nan)  # log10 sigma_m, decades
    bar = tqdm(total=1 + n_golden(2 * step) + (n_golden(2.0) if osc_model else 0),
               desc=f"choosing {noise.NOISE_UNIT[model]} per marker", disable=not progress, leave=False)
    # the grid: every q (x every sigma_m) x every marker in one batched solve, each from the start
    sig_levels = sig_grid
    grid, sig_grid = np.repeat(grid, len(sig_grid)), np.tile(sig_grid, len(grid))
    levels = np.repeat(10.0 ** grid[:, None], len(markers), axis=1)
    osc_grid = spec.Oscillation(oscillation_hz, np.repeat(10.0 ** sig_grid[:, None], len(markers), axis=1)) \
        if osc_model else None
    cols = np.arange(len(markers))
    # which grid points are solved, per marker (rows of ``levels``): all of them, or (the evidence, where the
    # surrogate at the start scores every one) the GRID_TOP it scores best
    solved = np.repeat(np.arange(len(grid))[:, None], len(markers), axis=1)
    if not loo:
        first = _Problem(model, levels[0], fps, robust, robust_k, None if osc_grid is None else osc_grid.of(0))
        x_start, mu0 = _start(first, p0, start[1], start[0], cols, fps, start[2])
        sur = _Surrogate(first, fps, x_start, mu0, _rows_of(rows, np.ones(len(markers), bool)), oscillation_hz)
        approx = np.stack([evidence(*sur.evaluate(levels[k], None if osc_grid is None else osc_grid.sigma_m[k])[:2],
                                    levels[k], None, None if osc_grid is None else osc_grid.of(k))
                           for k in range(len(grid))])
        solved = _best_rows(approx, GRID_TOP)
    sol = solve_levels(rig, sub, p0, model, levels[solved, cols], fps, robust, robust_k,
                       v_start=start[1], p_start=start[0], a_start=start[2], loo=loo,
                       oscillation=None if osc_grid is None else spec.Oscillation(oscillation_hz,
                                                                                  osc_grid.sigma_m[solved, cols]),
                       rows=rows, step_tol_m=LOOSE_STEP_TOL_M)
    n_solves += 1
    bar.update()
    got = evidence(sol["cost"], sol["logdet"], levels[solved, cols], sol["loo"],
                   None if osc_grid is None else spec.Oscillation(oscillation_hz, osc_grid.sigma_m[solved, cols]))
    scores = np.full(levels.shape, np.nan)  # (len(grid), markers); NaN where not solved
    scores[solved, cols] = np.where(sol["at_camera"], -np.inf, got)
    j = np.argmax(np.where(np.isnan(got) | sol["at_camera"], -np.inf, got), axis=0)  # the best solved row
    best = solved[j, cols]
    x_best, y_best, s_best = grid[best], sig_grid[best], scores[best, cols]  # log10 q, log10 sigma_m, score
    state = tuple(None if sol[key] is None else np.ascontiguousarray(sol[key][j, :, cols].transpose(1, 0, 2))
                  for key in ("position", "velocity", "acceleration"))
    kept = state  # the solution at each marker's best point (the final solve's start)

    def oscillation(log10_sigma: np.ndarray) -> spec.Oscillation | None:
        return spec.Oscillation(oscillation_hz, 10.0**log10_sigma) if osc_model else None

    def f(values: np.ndarray, along_sigma: bool, live: np.ndarray) -> np.ndarray:
        """The score at log10 q = values (or log10 sigma_m = values, along_sigma) and the other level at its best,
        of the ``live`` markers (-inf for the others); keeps each marker's best point."""
        nonlocal state, kept, x_best, y_best, s_best
        x, y = (x_best, values) if along_sigma else (values, y_best)
        s, state = solve(10.0**x, state, oscillation(y), live)
        better = s > s_best
        kept = _where_state(better, state, kept)
        x_best, y_best, s_best = np.where(better, x, x_best), np.where(better, y, y_best), np.where(better, s, s_best)
        bar.update()
        return s

    def refine(f, a: np.ndarray, b: np.ndarray, fa: np.ndarray, fb: np.ndarray, m: np.ndarray, fm: np.ndarray,
               width: float) -> None:
        """The maximum per marker in [a, b] from m, the ends' scores fa, fb where known (noise.Bracket: Brent's
        steps, each one solve of the markers not yet done), at most twice as many steps as golden section on
        that width (the rare marker that needs more than golden's count costs only its own solves); f keeps
        the best point it evaluates."""
        a_better = ~(fb > fa)  # the better end is the second best point, the other the third
        br = noise.Bracket(a, b, m, fm, np.where(a_better, a, b), np.where(a_better, fa, fb),
                           np.where(a_better, b, a), np.where(a_better, fb, fa))
        for _ in range(2 * n_golden(width)):
            live = ~br.done()
            if not live.any():
                break
            v = br.next()
            br.update(v, f(v, live))

    iq, isg = np.divmod(best, len(sig_levels))  # the grid's best point: its q and sigma_m indices
    n_q = len(grid) // len(sig_levels)

    def grid_score(i: np.ndarray) -> np.ndarray:
        """The grid's score at q index i, at each marker's best sigma_m (NaN past the grid: no such point)."""
        ok = (i >= 0) & (i < n_q)
        return np.where(ok, scores[np.clip(i, 0, n_q - 1) * len(sig_levels) + isg, cols], np.nan)

    refine(lambda v, live: f(v, False, live), np.maximum(lo, x_best - step), np.minimum(hi, x_best + step),
           grid_score(iq - 1), grid_score(iq + 1), x_best.copy(), s_best.copy(), 2 * step)
    if osc_model:  # then sigma_m at that q, within a decade of the grid's best
        nan = np.full(len(markers), np.nan)
        refine(lambda v, live: f(v, True, live), np.maximum(s_lo, y_best - 1.0), np.minimum(s_hi, y_best + 1.0),
               nan, nan, y_best.copy(), s_best.copy(), 2.0)
    bar.close()
    level, ev = np.full(M, np.nan), np.full(M, np.nan)
    level[markers], ev[markers] = 10.0**x_best, s_best
    info = {"rule": noise.per_marker_rule(model, rule), "per_marker": {int(m): float(level[m]) for m in markers},
            "n_solves": n_solves, "log_evidence": ev,
            "solution": _full_width(_where_state(np.isfinite(s_best), kept, (np.nan,) * 3), markers, M)}
    if osc_model:
        info["sigma_m"] = np.full(M, np.nan)
        info["sigma_m"][markers] = 10.0**y_best
        info["wingbeat_hz"] = float(oscillation_hz)
    return level, info


choose_accel_psd_per_marker = choose_noise_per_marker  # the constant-velocity q per marker (its default model)


def _best_rows(scores: np.ndarray, n: int) -> np.ndarray:
    """The rows (n', M') of the n best scores (K, M') in each column, best first (NaN counts as the worst;
    n' = min(n, K))."""
    return np.argsort(-np.nan_to_num(scores, nan=-np.inf), axis=0, kind="stable")[:n]


def _full_width(state: tuple, markers: np.ndarray, M: int) -> tuple:
    """Arrays (F, M', 3) of the searched ``markers`` (or None) as (F, M, 3), NaN for the other markers."""
    def widen(a):
        if a is None:
            return None
        out = np.full((a.shape[0], M, 3), np.nan)
        out[:, markers] = a
        return out
    return tuple(widen(a) for a in state)


def _where_state(take: np.ndarray, new: tuple, old: tuple) -> tuple:
    """Solutions (positions, velocities, accelerations) (F, M', 3) or None: ``new``'s for the markers where
    ``take`` (M',) holds, ``old``'s elsewhere (old may be a scalar, e.g. NaN)."""
    return tuple(None if n_ is None else np.where(take[None, :, None], n_, o_) for n_, o_ in zip(new, old, strict=True))


# The grid points solved per marker where the evidence scores the grid (the oscillating model): those the surrogate
# at the start scores best. On four scenes (2026-11-25, from the triangulated tracks) the whole grid's best point
# was the surrogate's best on 51 of 56 markers and never below its fourth.
GRID_TOP = 4

# Where the slope search starts (log10 of q [m^2/s^3], j [m^2/s^5]): a wing's q (~10; bodies ~0.03-1, tips
# ~50 on the simulated flight) and the middle of the jerk PSD's range.
SLOPE_START = {"constant_velocity": 1.0, "constant_acceleration": 5.0}
SLOPE_MAX_STEPS = 24


# The search on true solves begins at the surrogate's maximum, so its first step, where the slope's secant is not
# known yet, is this long (decades; noise.SlopeSearch's first_step, 1 by default): within the span where two
# points' scores correct their slopes' secant. (A marker whose first solve has no score still steps back 2 decades.)
NEAR_FIRST_STEP_DECADES = 0.1
# A solve starts from the marker's last solution where its level is stiffer, or looser by at most this (decades);
# from ``start`` otherwise (a stiff solution carried to a much looser level once dragged wing markers off their track).
WARM_LOOSER_DECADES = 0.2
# The range's lower end is solved only where the surrogate at the start puts it less than this below the surrogate's
# maximum [nats]. That surrogate scores levels far from its linearisation too low, by 1-3x the true gap on the
# accuracy study's scenes (2026-11-25): every marker whose evidence peaked at the lower end was within it (at 0-1.5
# nats), and the markers it left out were 495-6100 nats worse there.
LO_SCREEN_NATS = 1000.0


def _slope_search(rig: Rig, sub: IdealObservations, rows: _Observations, p0: np.ndarray, start: tuple, model: str,
                  fps: float, robust: str, robust_k: float, progress: bool
                  ) -> tuple[np.ndarray, np.ndarray, int, tuple]:
    """Each marker's level of maximum Laplace evidence by noise.SlopeSearch (values and slopes from
    :func:`solve_fast` with ``slope=True``): (level (M',), its score (M',), number of solves, the solution at
    that level: (positions, velocities, accelerations) (F, M', 3) or None, NaN for a marker without one).

    sub, rows: the searched markers' observations; p0: their initial track (F, M', 3) [m] (the gauge prior);
    start: (positions, velocities, accelerations) (F, M', 3) or None, where the first solve starts.

    Where to begin comes from the evidence's :class:`_Surrogate` linearised at ``start``: noise.SlopeSearch on it
    (from SLOPE_START[model] and the range's lower end; no projection in any step) gives each marker's first
    level, and how far below its maximum it puts the lower end. Then noise.SlopeSearch on true solves: the
    lower end where the surrogate puts it less than LO_SCREEN_NATS below (from the surrogate's minimiser
    there), the first level (from ``start``), then one solve of the markers still searching per step, the first
    step NEAR_FIRST_STEP_DECADES long. The surrogate alone does not decide: its slope leaves out how the
    projections' Jacobians and weights move with the solution, as evidence_slope's does, and only true scores
    correct that (SlopeSearch's secants; the surrogate's own maximum was 0.12 decade off on a test scene with
    long weakly observed runs). A step starts from the marker's last solution where it is stiffer or at most
    WARM_LOOSER_DECADES looser, else from ``start``.
    """
    F, Mm = p0.shape[:2]
    lo, hi = noise.LOG10_RANGE[model]
    dt, per_decade = 1.0 / fps, math.log(10.0)
    n_solves = 0

    def score(cost, logdet_, x):
        return noise.laplace_log_evidence(cost, logdet_, 10.0**x, dt, F - 1, model=model)

    def solve(x, live, from_):
        """Solves of the ``live`` markers at log10 levels x (M',): scores (-inf elsewhere and where the solve ran
        into a camera centre), slopes per decade (NaN elsewhere) and solutions."""
        nonlocal n_solves
        n_solves += 1
        bar.update()
        _, _, info = solve_fast(rig, sub, np.where(live[None, :, None], p0, np.nan), model, 10.0**x, fps, robust,
                                robust_k, v_init=from_[1], p_start=from_[0], a_init=from_[2], covariances=False,
                                rows=rows, slope=True, step_tol_m=LOOSE_STEP_TOL_M)
        f = np.where(live & ~info["at_camera"], score(info["cost_per_marker"], info["logdet_per_marker"], x), -np.inf)
        return f, np.where(live, info["slope_per_marker"] * per_decade, np.nan), (
            info["position"], info["velocity"], info["acceleration"])

    bar = tqdm(total=SLOPE_MAX_STEPS, desc=f"choosing {noise.NOISE_UNIT[model]} per marker", disable=not progress,
               leave=False)
    every = np.ones(Mm, bool)
    first = _Problem(model, 10.0 ** SLOPE_START[model], fps, robust, robust_k)
    x_start, mu0 = _start(first, p0, start[1], start[0], np.arange(Mm), fps, start[2])
    sur = _Surrogate(first, fps, x_start, mu0, _rows_of(rows, every))
    x0, below = _surrogate_search(sur, np.full(Mm, SLOPE_START[model]), lo, hi, score)
    search = noise.SlopeSearch(x0, lo, hi, first_step=NEAR_FIRST_STEP_DECADES)
    near_lo = below < LO_SCREEN_NATS
    x_lo = np.full(Mm, float(lo))
    kept = None  # the solution at each marker's answer so far
    if near_lo.any():
        f, g, kept = solve(x_lo, near_lo, _surrogate_start(sur, x_lo, near_lo, start, fps))
        search.lower_end(f, g)
    f, g, last = solve(x0, every, start)
    search.update(x0, f, g)
    kept = last if kept is None else _where_state(search.answer[0] != lo, last, kept)
    last_x = x0.copy()
    for _ in range(SLOPE_MAX_STEPS - 2):
        live = ~search.done()
        if not live.any():
            break
        u = search.next()
        warm = live & (u <= last_x + WARM_LOOSER_DECADES)
        from_ = tuple(None if s_ is None else np.where(warm[None, :, None], l_, s_)
                      for l_, s_ in zip(last, start, strict=True))
        f, g, new = solve(u, live, from_)
        search.update(u, f, g)
        kept = _where_state(live & (search.answer[0] == u), new, kept)
        last = _where_state(live, new, last)
        last_x = np.where(live, u, last_x)
    bar.close()
    x, f = search.answer
    return 10.0**x, f, n_solves, _where_state(np.isfinite(f), kept, (np.nan,) * 3)


def _surrogate_search(sur: _Surrogate, x_from: np.ndarray, lo: float, hi: float, score
                      ) -> tuple[np.ndarray, np.ndarray]:
    """noise.SlopeSearch on the surrogate from log10 levels x_from (M',) and the range's lower end: each marker's
    answer (log10 level) and how far its score lies above the lower end's (nats; 0 where it is the answer, and
    where either has no score: nothing to screen by). score(cost, logdet, x) is the Laplace evidence at log10
    levels x."""
    M = len(x_from)
    per_decade = math.log(10.0)

    def scored(x, on):
        f, g = np.full(M, -np.inf), np.full(M, np.nan)
        cost, ld, slope, _ = sur.take(on).evaluate(10.0 ** x[on])
        f[on], g[on] = score(cost, ld, x[on]), slope * per_decade
        return f, g

    every = np.ones(M, bool)
    search = noise.SlopeSearch(x_from.astype(float), lo, hi)
    f_lo, g_lo = scored(np.full(M, float(lo)), every)
    search.lower_end(f_lo, g_lo)
    search.update(x_from, *scored(x_from, every))
    for _ in range(SLOPE_MAX_STEPS - 1):
        on = ~search.done()
        if not on.any():
            break
        u = search.next()
        search.update(u, *scored(u, on))
    x, f = search.answer
    scored_both = np.isfinite(f) & np.isfinite(f_lo)
    return x, np.where(scored_both, f - np.where(scored_both, f_lo, 0.0), 0.0)


def _surrogate_start(sur: _Surrogate, x: np.ndarray, which: np.ndarray, start: tuple, fps: float) -> tuple:
    """``start`` (positions, velocities, accelerations) (F, M', 3) or None, with the surrogate's minimiser at log10
    levels x (M',) for the markers ``which`` (where that minimiser is finite: a singular system keeps ``start``)."""
    p, v, a = (None if part is None else part.copy() for part in start)
    idx = np.flatnonzero(which)
    state = sur.take(idx).evaluate(10.0 ** x[idx])[3]
    finite = np.isfinite(state).all(axis=(0, 2))
    idx, state = idx[finite], state[:, finite]
    v_new, a_new = _derivatives(state, 1.0 / fps)
    p[:, idx], v[:, idx] = state[..., :3], v_new
    if a_new is not None:
        a = _gradient(v, fps) if a is None else a
        a[:, idx] = a_new
    return p, v, a


def choose_model_per_marker(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                            markers: np.ndarray, fps: float, robust: str, robust_k: float,
                            candidates: tuple[str, ...] = spec.AUTO_CANDIDATES, p_start: np.ndarray | None = None,
                            v_start: np.ndarray | None = None, progress: bool = False,
                            groups: list[np.ndarray] = (), rule: str = "evidence",
                            oscillation_hz: float | None = None,
                            q_floor: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Each marker's motion model among ``candidates`` and its noise level, by maximum Laplace evidence.

    ``rule`` (noise.NOISE_RULES) scores both the noise level and the model: the Laplace evidence or the
    leave-one-frame-out log predictive density (both are comparable across models: the same
    observations scored under each model's normalised prior / predictive).
    Runs :func:`choose_noise_per_marker` for each candidate model (arguments as there; each search
    batched over markers) and keeps per marker the model whose best evidence is the largest
    (batgraph.graph.noise explains why the scores compare). Markers are independent, so this is the
    joint choice exactly. ``groups``: marker index arrays that must share one model (markers joined by
    segment-length factors, batgraph.graph.rigid): a group takes the model of the largest sum of its
    members' evidences, searched without the segments (each member keeps its own noise level of that
    model). Returns model (M,) object array of names (None for markers not in
    ``markers``), level (M,) (that model's q [m^2/s^3] or j [m^2/s^5]; NaN elsewhere) and info:
    {model: that search's info} plus ``log_evidence`` {model: (M,)} and ``solution``: each marker's solution at
    its model and level, (positions [m], velocities [m/s], accelerations [m/s^2]) (F, M, 3), NaN where the
    model has no such part or the marker none (a start for the final solve; a group's members were searched
    without their segments). The "oscillating" candidate needs the
    wingbeat frequency ``oscillation_hz`` [Hz]; its info's sigma_m (M,) is each marker's oscillation std.
    ``q_floor`` [m^2/s^3] (noise.flapping_q_floor): a constant-velocity marker whose q came out below it gets it
    (after the model choice; info's ``raised_to_floor``, bool (M,), says which); None: no floor.
    """
    M = p_init.shape[1]
    found = {name: choose_noise_per_marker(rig, ideal, p_init, v_init, markers, fps, robust, robust_k, p_start,
                                           v_start, progress, model=name, rule=rule,
                                           oscillation_hz=oscillation_hz if name == spec.OSCILLATING else None)
             for name in candidates}
    ev = np.stack([found[name][1]["log_evidence"] for name in candidates])  # (n_candidates, M)
    ev_ok = np.where(np.isfinite(ev), ev, -np.inf)
    won = np.argmax(ev_ok, axis=0)
    for members in groups:
        won[members] = np.argmax(ev_ok[:, members].sum(axis=1))
    model = np.full(M, None, dtype=object)
    level = np.full(M, np.nan)
    F = p_init.shape[0]
    solution = [np.full((F, M, 3), np.nan) for _ in range(3)]
    for i, name in enumerate(candidates):
        mine = np.zeros(M, bool)
        mine[markers] = won[markers] == i
        model[mine], level[mine] = name, found[name][0][mine]
        for part, got in zip(solution, found[name][1]["solution"], strict=True):
            if got is not None:
                part[:, mine] = got[:, mine]
    info = {name: found[name][1] for name in candidates}
    info["log_evidence"] = {name: found[name][1]["log_evidence"] for name in candidates}
    info["solution"] = tuple(solution)
    raised = np.zeros(M, bool)
    if q_floor is not None:
        raised = (model == "constant_velocity") & (level < q_floor)
        level[raised] = q_floor
    info["raised_to_floor"] = raised
    return model, level, info


def searched_start(solution: tuple, p_start: np.ndarray, v_start: np.ndarray, fps: float) -> tuple:
    """The final solve's start (positions [m], velocities [m/s], accelerations [m/s^2]) (F, M, 3): the noise
    search's solution at each marker's chosen model and level (fast.choose_model_per_marker's ``solution``),
    and for a marker it does not hold, ``p_start``, ``v_start`` and their accelerations by :func:`_gradient` (as
    solve_fast's default)."""
    has = [np.isfinite(part).all(axis=(0, 2))[None, :, None] for part in solution]
    p = np.where(has[0], solution[0], p_start)
    v = np.where(has[1], solution[1], v_start)
    a = np.where(has[2], solution[2], _gradient(v, fps))
    return p, v, a


def solve_per_model(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, model: np.ndarray,
                    level: np.ndarray, fps: float, robust: str, robust_k: float, v_init: np.ndarray | None = None,
                    p_start: np.ndarray | None = None, a_init: np.ndarray | None = None,
                    covariances: bool = True, oscillation: spec.Oscillation | None = None,
                    ) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """:func:`solve_fast` with a motion model per marker: one solve per model over its markers, merged
    (markers are independent with fixed cameras, so this is the joint minimiser exactly).

    model: (M,) model names (None for markers not estimated); level (M,) each marker's noise level;
    oscillation: that of the "oscillating" markers (sigma_m (M,)).
    Other arguments and the returns as solve_fast's; the info's per-marker arrays, velocity (NaN for
    random-walk markers) and acceleration (NaN for markers without one) are merged, cost / logdet /
    iterations are totals / maxima over the solves.
    """
    F, M = p_init.shape[:2]
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan) if covariances else None
    merged = {"iterations_per_marker": np.zeros(M, int), "converged": np.zeros(M, bool), "at_camera": np.zeros(M, bool),
              "cost_per_marker": np.zeros(M), "logdet_per_marker": np.zeros(M), "estimated": np.zeros(M, bool),
              "velocity": np.full((F, M, 3), np.nan), "acceleration": np.full((F, M, 3), np.nan)}
    for name in dict.fromkeys(m for m in model if m is not None):
        mine = np.array([m == name for m in model])
        p_mine = np.where(mine[None, :, None], p_init, np.nan)
        x, c, info = solve_fast(rig, ideal, p_mine, name, np.where(mine, level, np.nan), fps, robust, robust_k,
                                v_init=v_init, p_start=p_start, covariances=covariances, a_init=a_init,
                                oscillation=oscillation if name == spec.OSCILLATING else None)
        merge_markers((xyz, cov, merged), (x, c, info), mine)
    return xyz, cov, merge_markers((xyz, cov, merged), None, None)[2]


PER_MARKER = ("iterations_per_marker", "converged", "at_camera", "cost_per_marker", "logdet_per_marker", "estimated")


def merge_markers(into: tuple, part: tuple | None, markers: np.ndarray | None) -> tuple:
    """Copy the markers ``markers`` (M,) bool of one solve, ``part`` = (xyz, cov, info) as :func:`solve_per_model`
    returns them, into another, ``into``, in place (its cov None where covariances were not asked): positions,
    covariances, the info's per-marker arrays, velocity and acceleration (where ``part`` has them); then ``into``'s
    totals anew (iterations the maximum, cost and logdet the sums over its estimated markers; position its xyz).
    part None: the totals only. Returns ``into``."""
    xyz, cov, info = into
    if part is not None:
        x, c, other = part
        xyz[:, markers] = x[:, markers]
        if cov is not None:
            cov[:, markers] = c[:, markers]
        for key in PER_MARKER:
            info[key][markers] = other[key][markers]
        for key in ("velocity", "acceleration"):
            if other[key] is not None:
                info[key][:, markers] = other[key][:, markers]
    est = info["estimated"]
    info.update(iterations=int(info["iterations_per_marker"][est].max(initial=0)),
                cost=float(info["cost_per_marker"][est].sum()), logdet=float(info["logdet_per_marker"][est].sum()),
                position=xyz)
    return into


@_one_thread
def choose_accel_psd_fast(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                          markers: np.ndarray, fps: float, robust: str, robust_k: float,
                          progress: bool = False, p_start: np.ndarray | None = None,
                          v_start: np.ndarray | None = None) -> tuple[float, dict]:
    """Maximum-marginal-likelihood q [m^2/s^3], batgraph.graph.noise's rule, scored with :func:`solve_fast`.

    One q for every marker (the benchmark's common q; the smoother itself chooses one per marker), fitted
    on noise.fit_markers' spread subset: the first solve starts from ``p_start`` (F, M, 3) [m] and ``v_start`` (F, M, 3)
    [m/s] (default the initial track p_init, v_init), each later one from the previous solution; the
    gauge priors stay at p_init[0]. The score's cost and log det come from the fast solver (log det of
    the Hessian in p [m], v [m/s], as batgraph.graph.smoother.posterior_logdet gives it).
    """

    fit = noise.fit_markers(markers)
    sub = IdealObservations(ideal.uv_px[:, :, fit], ideal.cov_px2[:, :, fit])
    F = p_init.shape[0]
    state = {"p": (p_init if p_start is None else p_start)[:, fit],
             "v": (v_init if v_start is None else v_start)[:, fit]}

    def score(q: float) -> float:
        _, _, info = solve_fast(rig, sub, p_init[:, fit], "constant_velocity", q, fps, robust, robust_k,
                                v_init=state["v"], p_start=state["p"])
        state["p"], state["v"] = info["position"], info["velocity"]
        return noise.laplace_log_evidence(info["cost"], info["logdet"], q, 1.0 / fps, len(fit) * (F - 1))

    q, trace = noise.maximise_log10(score, progress=progress)
    return q, {"rule": noise.GLOBAL_RULE,
               "fit_markers": [int(m) for m in fit],
               "scores": [{"accel_psd_m2_s3": a, "log_evidence": s} for a, s in trace]}
