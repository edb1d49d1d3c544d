"""Variables shared by every marker: each camera's time offset and rolling-shutter readout, solved jointly with the
trajectories.

Camera c's row v (raw pixels) of its frame j is captured at j / fps_c + offset_c + readout_c v / height on the
session clock (batgraph.measurement's time_frac holds it with the rig's known timing); the variables are each
camera's corrections (d_offset_c, d_readout_c) [s]. The reference camera's offset is not one: only differences of
offsets show in the images. Weak Gaussian priors (PRIOR_SD_S) keep the system regular where the data says little.

The joint minimiser by variable projection: for the current corrections, the markers' minimiser x*(theta) (any
backend's fit); then, with the rows' Jacobians at x*, the Schur complement on theta of the joint Gauss-Newton
system, S = H_tt - sum_m H_tx H_xx^-1 H_xt (each marker's block-tridiagonal H_xx, the structure bundle adjustment
uses), a damped step of theta, and the markers re-solved from x* - H_xx^-1 H_xt d_theta (their first-order move);
a step is kept when the total cost decreases. At the minimiser theta's covariance is S^-1, and each point's covariance
gains Y_k S^-1 Y_k^T (Y = H_xx^-1 H_xt): the timing's uncertainty reaches the 3D.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from . import fit as fit_mod
from . import kernels, segments
from . import model as mm
from .kernels import tridiagonal
from .problem import derivatives

PRIOR_SD_S = 0.01  # [s]: the corrections' prior (weak: offsets of a synchronised-to-a-frame rig are < 5 ms)
MAX_STEPS = 20
TRACE = False
STEP_TOL_S = 1e-7  # [s]: converged when every correction moves by less


@dataclass(frozen=True)
class Timing:
    """Which timing quantities are variables: offset (C,) bool, readout (C,) bool (the reference camera's offset
    is never one). A variable's index in theta: offsets first, then readouts."""

    offset: np.ndarray
    readout: np.ndarray

    @property
    def columns(self) -> tuple[np.ndarray, np.ndarray]:
        """(offset column (C,), readout column (C,)) in theta, -1 where not a variable."""
        n_o = int(self.offset.sum())
        o, r = np.full(len(self.offset), -1), np.full(len(self.readout), -1)
        o[self.offset] = np.arange(n_o)
        r[self.readout] = n_o + np.arange(int(self.readout.sum()))
        return o, r

    @property
    def n(self) -> int:
        return int(self.offset.sum() + self.readout.sum())

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d_offset (C,), d_readout (C,)) [s] of theta (0 where not a variable)."""
        o, r = self.columns
        return np.where(o >= 0, theta[np.maximum(o, 0)], 0.0), np.where(r >= 0, theta[np.maximum(r, 0)], 0.0)


def shifted(setup: fit_mod.Setup, timing: Timing, theta: np.ndarray) -> fit_mod.Setup:
    """``setup`` with every observation's capture time moved by theta's corrections."""
    d_off, d_ro = timing.split(theta)
    ideal = setup.ideal
    C, F, M = ideal.seen.shape
    base = np.zeros((C, F, M)) if ideal.time_frac is None else ideal.time_frac
    row = np.zeros((C, F, M)) if ideal.row_frac is None else ideal.row_frac
    frac = base + setup.fps * (d_off[:, None, None] + d_ro[:, None, None] * row)
    return replace(setup, ideal=replace(ideal, time_frac=frac, row_frac=row, linear_xyz=None))


@dataclass
class Linear:
    """The timing's part of the joint Gauss-Newton system at a fit: g (n,), H_tt (n, n), and the Schur complement
    S = H_tt - H_tx H_xx^-1 H_xt (n, n) with Y = H_xx^-1 H_xt per point, (F, M, 9, n) (scaled states)."""

    g: np.ndarray
    H: np.ndarray
    S: np.ndarray
    Y: np.ndarray


def linearise(setup: fit_mod.Setup, fit: fit_mod.Fit, timing: Timing) -> Linear:
    """The timing's gradient, Hessian, Schur complement and Y at ``fit`` (IRLS weights)."""
    F, M = setup.shape
    n = timing.n
    g, H, S = np.zeros(n), np.zeros((n, n)), np.zeros((n, n))
    Y = np.zeros((F, M, 9, n))
    for name, ms, group in _units(setup, fit):
        prob = setup.problem(ms, name, np.ones(len(ms)))
        x = np.ascontiguousarray(fit.state[:, ms, :prob.d])
        Hxt, gu, Hu = _row_terms(prob, x, timing, setup.fps)
        g += gu
        H += Hu
        y = _solve_x(prob, x, group, Hxt, setup, fit)
        Y[:, ms, :prob.d] = y
        S -= np.einsum("fmin,fmio->no", Hxt, y)
    S += H
    return Linear(g, H, S, Y)


def _units(setup: fit_mod.Setup, fit: fit_mod.Fit):
    """(model, markers, group segments or None): each model's chains, then each segment group."""
    solved = np.array([m is not None for m in fit.models])
    found = segments.groups(fit.pairs, solved) if len(fit.pairs) else []
    grouped = np.zeros(len(solved), bool)
    for members, _ in found:
        grouped[members] = True
    for name in dict.fromkeys(m for m in fit.models[solved & ~grouped]):
        yield name, np.flatnonzero((fit.models == name) & ~grouped), None
    for members, seg_ids in found:
        yield fit.models[members[0]], members, seg_ids


def _row_terms(prob, x, timing: Timing, fps: float):
    """(H_xt (F, M', d, n), g_t (n,), H_tt (n, n)) of a problem's rows at x (IRLS weights)."""
    rows = prob.rows
    t = kernels.row_terms(x, rows, prob.cams.P, prob.cams.behind, prob.loss.code, float(prob.loss.k))
    o, r = timing.columns
    jt = np.einsum("nij,nj->ni", t["J"], t["dp"]) * fps  # d r / d time [1/s], (n, 2)
    cols = np.stack([o[rows.cam], r[rows.cam]], axis=1)  # (n, 2): each row's offset and readout columns
    scale = np.stack([np.ones(len(rows.cam)), rows.row], axis=1)
    jw = t["w"][:, None] * np.einsum("nij,ni->nj", t["J"], jt)  # w J_x^T j_t, (n, 3)
    F, M, d = x.shape
    n = timing.n
    Hxt = np.zeros((F, M, d, n))
    g, H = np.zeros(n), np.zeros((n, n))
    wr = t["w"] * np.einsum("ni,ni->n", jt, t["r"])
    ww = t["w"] * np.einsum("ni,ni->n", jt, jt)
    for a in range(2):
        on = cols[:, a] >= 0
        ca, sa = cols[on, a], scale[on, a]
        np.add.at(g, ca, sa * wr[on])
        for b in range(2):
            both = on & (cols[:, b] >= 0)
            np.add.at(H, (cols[both, a], cols[both, b]), scale[both, a] * scale[both, b] * ww[both])
        for e in range(2):
            frame = rows.k[on] + e
            ok = frame < F
            for j in range(d // 3):
                w = rows.W[on, e, j][ok] * sa[ok]
                for q in range(3):
                    np.add.at(Hxt, (frame[ok], rows.marker[on][ok], 3 * j + q, ca[ok]), w * jw[on][ok, q])
    return Hxt, g, H


def _solve_x(prob, x, seg_ids, Hxt, setup, fit):
    """H_xx^-1 H_xt (F, M', d, n) at x (IRLS): the chains' block-tridiagonal solve, a group's bordered one."""
    if seg_ids is None:
        _, _, D, B, _ = prob.system(x, False)
        return tridiagonal(D, B[:, :, None], rhs=Hxt)["dx"]
    members = np.unique(fit.pairs[seg_ids])
    seg = segments.Segments(np.searchsorted(members, fit.pairs[seg_ids]), setup.rigid_sigma_m)
    L = fit.length_m[seg_ids]
    _, _, T, BG, C, E, _, _ = segments.Group(prob, seg).blocks((x, L), False)
    F, gm, d = x.shape
    rhs = Hxt.reshape(F, gm * d, -1)
    return segments.bordered_solve(T, BG, C, E, rhs, np.zeros((len(L), rhs.shape[-1])))[0].reshape(F, gm, d, -1)


def solve(setup: fit_mod.Setup, backend, models: np.ndarray, levels: np.ndarray, start: tuple, timing: Timing,
          theta0: np.ndarray | None = None) -> tuple:
    """The joint minimiser of the markers and the timing corrections from theta0 (module docstring): (fit at the
    minimiser with the timing's uncertainty in its covariances, theta (n,) [s], its covariance (n, n) [s^2],
    setup with the corrections applied, steps taken).

    The steps are Levenberg-Marquardt's on the reduced problem with the Hessian S + A: S the Gauss-Newton Schur
    complement, A a structured secant correction (Dennis, Gay and Welsch's, as NL2SOL) built from the exact reduced
    gradients along the steps. Gauss-Newton alone converged linearly (a step 0.7x the last) where the data barely
    tell an offset from a readout (every camera sees the bat over a band of rows)."""
    n = timing.n
    theta = np.zeros(n) if theta0 is None else np.asarray(theta0, float).copy()
    prior = 1.0 / PRIOR_SD_S**2
    cur = shifted(setup, timing, theta)
    fit = backend.fit(cur, models, levels, start)
    total = _total(fit, theta, prior)
    lin = linearise(cur, fit, timing)
    A, lam, steps = np.zeros((n, n)), 1e-3, 0
    g = lin.g + prior * theta
    while steps < MAX_STEPS and lam < 1e8:
        steps += 1
        S = lin.S + prior * np.eye(n)
        step = -np.linalg.solve(S + A + lam * np.diag(np.diag(S)), g)
        new_theta = theta + step
        new_setup = shifted(setup, timing, new_theta)
        x = fit.state - np.einsum("fmin,n->fmi", lin.Y, step)
        new_fit = backend.fit(new_setup, models, levels, _motion(x, fit, setup.fps))
        new_total = _total(new_fit, new_theta, prior)
        if TRACE:
            print(f"step {steps}: lam {lam:.0e} total {total:.4f} -> {new_total:.4f} |step| {np.abs(step).max():.1e}")
        if not new_total <= total:
            lam *= 10
            continue
        new_lin = linearise(new_setup, new_fit, timing)
        new_g = new_lin.g + prior * new_theta
        A = _secant(A, step, new_g - g, new_lin.S + prior * np.eye(n))
        theta, fit, total, cur, lin, g = new_theta, new_fit, new_total, new_setup, new_lin, new_g
        lam = max(lam / 10, 1e-9)
        if np.abs(step).max() < STEP_TOL_S:
            break
    cov_t = np.linalg.inv(lin.S + prior * np.eye(n))
    if fit.cov is not None:
        Yp = lin.Y[..., :3, :]
        fit.cov = fit.cov + np.einsum("fmin,no,fmjo->fmij", Yp, cov_t, Yp)
    return fit, theta, cov_t, cur, steps


def _secant(A: np.ndarray, s: np.ndarray, y: np.ndarray, S_new: np.ndarray) -> np.ndarray:
    """The structured secant update of A after a step s with gradient change y, so that (S_new + A') s = y
    (Dennis-Gay-Welsch); A unchanged when y . s <= 0 (no curvature along the step to learn)."""
    ys = float(y @ s)
    if ys <= 0:
        return A
    r = y - S_new @ s - A @ s
    return A + (np.outer(r, y) + np.outer(y, r)) / ys - float(r @ s) * np.outer(y, y) / ys**2


def _total(fit: fit_mod.Fit, theta: np.ndarray, prior: float) -> float:
    solved = np.array([m is not None for m in fit.models])
    return float(fit.cost[solved].sum() + 0.5 * prior * theta @ theta)


def _motion(x: np.ndarray, fit: fit_mod.Fit, fps: float) -> tuple:
    """(p, v, a) (F, M, 3) of padded scaled states x (F, M, 9) whose models are fit.models."""
    F, M = fit.xyz.shape[:2]
    p, v, a = x[..., :3].copy(), np.full((F, M, 3), np.nan), np.full((F, M, 3), np.nan)
    for name in dict.fromkeys(m for m in fit.models if m is not None):
        ms = fit.models == name
        vv, aa = derivatives(x[:, ms, :mm.state_dim(name)], fps)
        if vv is not None:
            v[:, ms] = vv
        if aa is not None:
            a[:, ms] = aa
    return p, np.where(np.isfinite(v), v, fit.velocity), np.where(np.isfinite(a), a, fit.acceleration)

