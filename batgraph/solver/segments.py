"""Segment-length factors: markers on one rigid segment (a bone) keep their distance.

For every segment s = (a, b) of session.toml's ``[markers] rigid`` and every frame k the cost adds
0.5 ((|p_a,k - p_b,k| - L_s) / sigma)^2, with L_s one variable per segment [m] (estimated, never given) and
sigma = ``[markers] rigid_sigma_m``. Plain Gaussian: a pair that is not rigid is a wrong declaration, reported
(each segment's length scatter), not an outlier to down-weight.

Segments join markers, so a connected group of markers is solved as one column: its state at frame k is its g
members' states stacked (n = g d values), block tridiagonal in frames with block-diagonal sub-diagonal blocks
(each member's own motion), and the s lengths border it, H = [[T, C], [C^T, E]]. The step is the Schur complement
on the lengths, [z, W] = T^-1 [r_x, C], dL = (E - C^T W)^-1 (r_L - C^T z), dx = z - W dL; the marginals stay exact,
Sigma_x = T^-1 + W S^-1 W^T (diagonal blocks), cov(L) = S^-1, log det H = log det T + log det S. Near the minimum
the curvature adds |p_a - p_b|'s own, (r / sigma) (I - u u^T) / |p_a - p_b| (Gauss-Newton leaves it out; for a
single-view marker at a track end it is all the curvature across the segment besides the weak motion prior).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..measurement import of_markers
from ..triangulate import triangulate_ideal
from .kernels import mirror_lower
from .problem import Problem

MIN_DISTANCE_M = 1e-9  # two markers of a segment closer than this have no direction
# The full curvature (compressed segments too) once the last accepted step is below this [m]: on 9 simulated
# scenes the final solves took 0.3-0.8x the iterations of the clamped curvature alone, the same minimiser.
NEAR_STEP_M = 1e-3


def pairs_of(rigid: list[tuple[str, str]], names: list[str]) -> np.ndarray:
    """Marker index pairs (S, 2), in ``names``' order, of the segments whose two markers are in ``names``."""
    index = {n: i for i, n in enumerate(names)}
    return np.array([(index[a], index[b]) for a, b in rigid if a in index and b in index], int).reshape(-1, 2)


def groups(pairs: np.ndarray, estimated: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The connected groups of estimated markers joined by segments: [(members (g,) sorted marker indices,
    segments (s,) row indices into pairs)], g >= 2 (a segment with a marker not estimated is dropped)."""
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    keep = np.flatnonzero(estimated[pairs].all(axis=1)) if len(pairs) else np.zeros(0, int)
    if not len(keep):
        return []
    a, b = pairs[keep, 0], pairs[keep, 1]
    M = len(estimated)
    _, label = connected_components(coo_matrix((np.ones(len(keep)), (a, b)), shape=(M, M)), directed=False)
    return [(np.flatnonzero(label == lab), keep[label[a] == lab]) for lab in np.unique(label[a])]


def with_groups(markers: np.ndarray, pairs: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """markers (M,) bool grown to the whole of every segment group that holds one of them."""
    out = np.array(markers, bool)
    for members, _ in groups(pairs, estimated):
        if out[members].any():
            out[members] = True
    return out


def partner_levels(level: np.ndarray, unset: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Levels (M,) where each marker of ``unset`` (M,) bool takes the least level of its segment partners (pairs
    (S, 2)) that are set (finite), spreading along chains of unset markers; one with no such partner keeps its own
    (a bone's two ends move together: the level of a marker whose own frames cannot set it)."""
    level, unset = np.array(level, float), np.array(unset, bool)
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    while True:
        took = {}
        for a, b in np.concatenate([pairs, pairs[:, ::-1]]):
            if unset[a] and not unset[b] and np.isfinite(level[b]):
                took[a] = min(took.get(a, np.inf), level[b])
        if not took:
            return level
        for m, value in took.items():
            level[m], unset[m] = value, False


@dataclass
class Segments:
    """The segment terms of one group: local (s, 2) pairs of member columns, sigma [m]."""

    local: np.ndarray
    sigma: float

    def residuals(self, x: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(whitened residuals (F, s), unit vectors b -> a (F, s, 3), distances (F, s) [m]) at states x (F, g, d)."""
        diff = x[:, self.local[:, 0], :3] - x[:, self.local[:, 1], :3]
        dist = np.maximum(np.linalg.norm(diff, axis=-1), MIN_DISTANCE_M)
        return (dist - L) / self.sigma, diff / dist[..., None], dist

    def cost(self, x: np.ndarray, L: np.ndarray) -> float:
        r = self.residuals(x, L)[0]
        c = 0.5 * float(np.sum(r * r))
        return c if np.isfinite(c) else np.inf

    def border(self, x: np.ndarray, L: np.ndarray, T: np.ndarray, gx: np.ndarray, exact: bool, full: bool):
        """Add the segment terms to the group's stacked blocks T (F, n, n) and gradient gx (F, n) in place;
        returns the border (C (F, n, s), E (s, s), gL (s,)). ``exact`` adds |p_a - p_b|'s own curvature where the
        segment is stretched (r > 0: positive semi-definite), ``full`` where it is compressed too."""
        d = T.shape[-1] // x.shape[1]
        r, u, dist = self.residuals(x, L)
        s2 = self.sigma**2
        uu = u[..., :, None] * u[..., None, :] / s2
        if exact:
            bend = (r if full else np.maximum(r, 0.0)) / (self.sigma * dist)
            uu = uu + bend[..., None, None] * (np.eye(3) - s2 * uu)
        C = np.zeros(gx.shape + (len(self.local),))
        for j, (a, b) in enumerate(self.local):
            pa, pb = slice(a * d, a * d + 3), slice(b * d, b * d + 3)
            T[:, pa, pa] += uu[:, j]
            T[:, pb, pb] += uu[:, j]
            T[:, pa, pb] -= uu[:, j]
            T[:, pb, pa] -= uu[:, j]
            C[:, pa, j], C[:, pb, j] = -u[:, j] / s2, u[:, j] / s2
            gx[:, pa] += u[:, j] * (r[:, j, None] / self.sigma)
            gx[:, pb] -= u[:, j] * (r[:, j, None] / self.sigma)
        return C, np.eye(len(self.local)) * (len(x) / s2), -r.sum(axis=0) / self.sigma


def initial_lengths(xyz_m: np.ndarray, pairs: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Each segment's median distance (S,) [m] over the frames where a camera sees both its markers (seen (F, M)
    bool), over every frame where none does (NaN frames skipped). Elsewhere the start is the motion model's guess:
    a marker seen on a few frames of a wingbeat is extrapolated far off, and a length started there stays off."""
    both = seen[:, pairs[:, 0]] & seen[:, pairs[:, 1]]
    both |= ~both.any(axis=0)
    dist = np.linalg.norm(xyz_m[:, pairs[:, 0]] - xyz_m[:, pairs[:, 1]], axis=-1)
    return np.nanmedian(np.where(both, dist, np.nan), axis=0)


class Group:
    """:class:`batgraph.solver.lm.Objective` of one segment group: one column, state (x (F, g, d), L (s,)); the
    members' rows, motion and priors from ``problem`` (the group's markers only)."""

    def __init__(self, problem: Problem, segments: Segments):
        self.problem, self.seg = problem, segments
        self.robust = problem.loss.name != "none"
        self._proposed = self._accepted = np.inf  # the last proposed and accepted steps' size [m]

    def cost(self, state):
        x, L = state
        c, near = self.problem.cost(x)
        return np.array([c.sum() + self.seg.cost(x, L)]), np.array([near.max(initial=0.0)])

    def blocks(self, state, exact: bool):
        """(cost (1,), near (1,), T (F, n, n), BG (F - 1, 1, g, d, d), C, E, gx (F, n), gL)."""
        x, L = state
        c, near, D, B, g = self.problem.system(x, exact)
        F, gm, d = x.shape
        T = np.zeros((F, gm * d, gm * d))
        for i in range(gm):
            T[:, i * d:(i + 1) * d, i * d:(i + 1) * d] = D[:, i]
        gx = g.reshape(F, gm * d).copy()
        close = self._accepted < NEAR_STEP_M
        C, E, gL = self.seg.border(x, L, T, gx, exact and close, full=close)
        cost = np.array([c.sum() + self.seg.cost(x, L)])
        return cost, np.array([near.max(initial=0.0)]), T, B.reshape(F - 1, gm, d, d), C, E, gx, gL

    def system(self, state, exact):
        cost, near, *sys = self.blocks(state, bool(exact[0]))
        return cost, near, tuple(sys)

    def solve(self, system, damping):
        T, BG, C, E, gx, gL = system
        i, j = np.arange(T.shape[-1]), np.arange(len(E))
        T, E = T.copy(), E.copy()
        T[:, i, i] *= 1.0 + damping[0]
        E[j, j] *= 1.0 + damping[0]
        dx, dL = bordered_solve(T, BG, C, E, -gx, -gL)
        self._proposed = self.size((dx, dL))[0]
        return dx, dL

    def gain(self, system, step):
        return np.array([-0.5 * (np.sum(system[4] * step[0]) + system[5] @ step[1])])

    def size(self, step):
        return np.array([max(np.abs(step[0]).max(initial=0.0), np.abs(step[1]).max(initial=0.0))])

    def add(self, state, step):
        x, L = state
        return x + step[0].reshape(x.shape), L + step[1]

    def take(self, keep):
        return self

    def take_state(self, state, keep):
        return state[0].copy(), state[1].copy()

    def put_state(self, state, keep, part):
        state[0][:], state[1][:] = part
        self._accepted = self._proposed


def sweeps(T: np.ndarray, Bb: np.ndarray, rhs: np.ndarray | None, marginals: bool = False) -> dict:
    """batgraph.solver.kernels.tridiagonal for one chain of wide blocks (a group: T (F, n, n), Bb (F - 1, g, b, b)
    block-diagonal H[k + 1, k], rhs (F, n, r) or None), by LAPACK's Cholesky inverse per frame (an indefinite
    block, possible with the exact curvature, by LU): "logdet", "dx", "Sigma" as that function's."""
    F, n = T.shape[:2]
    g, b = Bb.shape[1:3] if F > 1 else (1, n)

    Bt = np.swapaxes(Bb, -1, -2)

    def bmul(k, X, trans=False):  # B_k X (or B_k^T X) for X (n, r)
        return np.matmul(Bt[k] if trans else Bb[k], X.reshape(g, b, -1)).reshape(n, -1)

    Sinv = np.empty((F, n, n))
    Sinv[0], ld = _sym_inverse(T[0])
    y = None if rhs is None else np.empty_like(rhs)
    if y is not None:
        y[0] = rhs[0]
    for k in range(1, F):
        L = bmul(k - 1, Sinv[k - 1])
        Sinv[k], ldk = _sym_inverse(T[k] - bmul(k - 1, L.T))
        ld += ldk
        if y is not None:
            y[k] = rhs[k] - L @ y[k - 1]
    out = {"logdet": np.array([ld])}
    if y is not None:
        dx = np.empty_like(y)
        dx[-1] = Sinv[-1] @ y[-1]
        for k in range(F - 2, -1, -1):
            dx[k] = Sinv[k] @ (y[k] - bmul(k, dx[k + 1], trans=True))
        out["dx"] = dx
    if marginals:
        Sig = np.empty_like(Sinv)
        Sig[-1] = Sinv[-1]
        for k in range(F - 2, -1, -1):
            G = bmul(k, Sinv[k]).T
            Sig[k] = Sinv[k] + G @ Sig[k + 1] @ G.T
            Sig[k] = 0.5 * (Sig[k] + Sig[k].T)
        out["Sigma"] = Sig
    return out


def _sym_inverse(S: np.ndarray) -> tuple[np.ndarray, float]:
    """(S^-1, log |det S|) of a symmetric S: Cholesky (potrf + potri), else LU."""
    c, info = lapack.dpotrf(S.T, lower=1, clean=0)  # S.T: the same matrix, Fortran-ordered (no copy)
    if info == 0:
        inv, info = lapack.dpotri(c, lower=1)
        if info == 0:
            return mirror_lower(inv), 2.0 * float(np.log(np.diagonal(c)).sum())
    return np.linalg.inv(S), float(np.linalg.slogdet(S)[1])


def bordered_solve(T, BG, C, E, rx, rL) -> tuple[np.ndarray, np.ndarray]:
    """[[T, C], [C^T, E]] [dx, dL] = [rx, rL] by the Schur complement on dL; T (F, n, n) with sub-diagonal blocks
    BG (F - 1, g, b, b), C (F, n, s), E (s, s), rx (F, n) and rL (s,), or (F, n, r) and (s, r) for r at once."""
    one = rx.ndim == 2
    rx, rL = (rx[..., None], rL[:, None]) if one else (rx, rL)
    r = rx.shape[-1]
    Y = sweeps(T, BG, np.concatenate([rx, C], axis=-1))["dx"]
    z, W = Y[..., :r], Y[..., r:]
    S = E - np.einsum("fns,fnt->st", C, W)
    dL = np.linalg.solve(S, rL - np.einsum("fns,fnr->sr", C, z))
    dx = z - W @ dL
    return (dx[..., 0], dL[:, 0]) if one else (dx, dL)


def marginals(group: Group, state, covariances: bool) -> tuple:
    """At the minimiser: (the members' state covariances (F, g, d, d) or None, the lengths' covariance (s, s),
    log det H of the group in scaled units)."""
    _, _, T, BG, C, E, _, _ = group.blocks(state, False)
    sw = sweeps(T, BG, C, marginals=covariances)
    W = sw["dx"]
    S = E - np.einsum("fns,fnt->st", C, W)
    S_inv = np.linalg.inv(S)
    logdet = float(sw["logdet"][0] + np.linalg.slogdet(S)[1])
    if not covariances:
        return None, S_inv, logdet
    Sig = sw["Sigma"] + W @ S_inv @ np.swapaxes(W, -1, -2)
    Sig = 0.5 * (Sig + np.swapaxes(Sig, -1, -2))
    F, gm, d = state[0].shape
    return np.stack([Sig[:, i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(gm)], axis=1), S_inv, logdet


MIN_SCATTER_FRAMES = 10  # fewer frames with both markers triangulated: no triangulated scatter (0)


def triangulated_excess(setup, pairs: np.ndarray) -> np.ndarray:
    """Each segment's length scatter beyond what the triangulation's noise explains, (S,) [m]: from the per-frame
    linear triangulation of the frames where both markers have >= 2 views, sqrt(s^2 - n) with s = 1.4826 x the
    median absolute deviation of the lengths (robust to a mislabelled frame) and n the median of their variances
    u^T (S_a + S_b) u; 0 within 3 standard errors of zero (the MAD's, s^2 sqrt(5.4 / frames)) or with fewer than
    MIN_SCATTER_FRAMES frames. Unlike the scatter at the smoother's solution, which the segment factor pulls in,
    this sees neither the segment nor the motion model. setup: batgraph.solver.fit.Setup; pairs (S, 2)."""
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    out = np.zeros(len(pairs))
    if not len(pairs):
        return out
    sel = np.unique(pairs)
    xyz, cov = triangulate_ideal(setup.rig, of_markers(setup.ideal, sel))
    for s, (a, b) in enumerate(np.searchsorted(sel, pairs)):
        d, S = xyz[:, a] - xyz[:, b], cov[:, a] + cov[:, b]
        ok = np.isfinite(d).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
        n = int(ok.sum())
        if n < MIN_SCATTER_FRAMES:
            continue
        length = np.linalg.norm(d[ok], axis=-1)
        u = d[ok] / np.where(length > 0, length, 1.0)[:, None]
        s2 = (1.4826 * np.median(np.abs(length - np.median(length)))) ** 2
        excess = s2 - float(np.median(np.einsum("ni,nij,nj->n", u, S[ok], u)))
        if excess > 3 * s2 * np.sqrt(5.4 / n):
            out[s] = np.sqrt(excess)
    return out
