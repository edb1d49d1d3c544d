"""Variables shared by every marker: each camera's time offset, rolling-shutter readout and pose, solved jointly
with the trajectories (the structure bundle adjustment uses).

Timing: camera c's raw row v of its frame j is read at j / fps_c + offset_c + readout_c v / height on the session
clock; the variables are the offsets' corrections (the reference camera's is fixed: only differences show) and one
readout per sensor mode (same image size and rate: a readout per camera is confounded with the wings' own
vertical motion; docs/timing.md). Poses: a left perturbation of cam_from_world, R' = exp(w) R, t' = exp(w) t + d,
under the calibration's pose covariance; the similarity directions the images cannot see are projected out.
The solve is variable projection: the markers' minimiser x*(theta) from any backend, then a damped Gauss-Newton
step on the Schur complement S = H_tt - H_tx H_xx^-1 H_xt (each marker's block-tridiagonal H_xx, at the markers'
noise levels), the markers re-solved from their first-order move. theta's covariance is S^-1; each point's covariance
gains Y S^-1 Y^T (Y = H_xx^-1 H_xt), so the rig's uncertainty reaches the 3D.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera, Rig
from ..geometry.pose import R_from_rvec, rvec_from_R, skew
from . import fit as fit_mod
from . import kernels, lm, segments
from . import model as mm
from .kernels import tridiagonal
from .problem import derivatives

PRIOR_SD_S = 0.01  # [s]: the corrections' prior (weak: offsets of a synchronised-to-a-frame rig are < 5 ms)
# Converged when the model's predicted decrease is below this [nats of the cost]: the variables then sit within a
# small fraction of their posterior standard deviation of the minimum (a decrease of 0.5 per standard deviation).
DECREMENT_TOL = 0.01


KINDS = ("offset", "readout", "pose")
WIDTH = {"offset": 1, "readout": 1, "pose": 6}


@dataclass(frozen=True)
class Shared:
    """Which camera quantities are variables: offset, readout, pose (C,) bool each (the reference camera's offset
    never is); pose_cov (C, 6, 6) the pose priors' covariances. theta holds the offsets, then the readouts, then
    6 values per pose."""

    offset: np.ndarray
    readout: np.ndarray
    pose: np.ndarray
    pose_cov: np.ndarray | None = None
    mode: np.ndarray | None = None  # (C,) int: cameras of one sensor mode share one readout (None: each its own)

    @classmethod
    def none(cls, C: int) -> Shared:
        z = np.zeros(C, bool)
        return cls(z, z, z)

    @property
    def columns(self) -> dict[str, np.ndarray]:
        """Each kind's first column in theta per camera (C,), -1 where not a variable; cameras of one sensor mode
        share their readout's column."""
        out, start = {}, 0
        for kind in KINDS:
            on = getattr(self, kind)
            col = np.full(len(on), -1)
            slot = self._slots(kind)
            col[on] = start + WIDTH[kind] * slot[on]
            out[kind] = col
            start += WIDTH[kind] * (int(slot[on].max()) + 1 if on.any() else 0)
        return out

    def _slots(self, kind: str) -> np.ndarray:
        """Each camera's variable among its kind's (C,): in order; readouts by sensor mode."""
        on = getattr(self, kind)
        if kind == "readout" and self.mode is not None:
            modes = list(dict.fromkeys(self.mode[on]))
            return np.array([modes.index(m) if o else -1 for m, o in zip(self.mode, on, strict=True)])
        return np.cumsum(on) - 1

    @property
    def n(self) -> int:
        return sum(WIDTH[k] * (int(self._slots(k)[getattr(self, k)].max()) + 1 if getattr(self, k).any() else 0)
                   for k in KINDS)

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d_offset (C,), d_readout (C,) [s], d_pose (C, 6) [rad, m]) of theta (0 where not a variable)."""
        cols = self.columns
        C = len(self.offset)
        out = [np.zeros(C), np.zeros(C), np.zeros((C, 6))]
        for i, kind in enumerate(KINDS):
            on = cols[kind] >= 0
            idx = cols[kind][on][:, None] + np.arange(WIDTH[kind])
            out[i][on] = theta[idx].reshape(out[i][on].shape)
        return tuple(out)

    def join(self, d_offset: np.ndarray, d_readout: np.ndarray, d_pose: np.ndarray) -> np.ndarray:
        """theta (n,) holding these per-camera corrections (the inverse of :meth:`split`; a sensor mode takes its
        last camera's readout)."""
        theta = np.zeros(self.n)
        cols = self.columns
        for kind, values in zip(KINDS, (d_offset, d_readout, d_pose), strict=True):
            on = cols[kind] >= 0
            idx = cols[kind][on][:, None] + np.arange(WIDTH[kind])
            theta[idx] = np.asarray(values, float)[on].reshape(idx.shape)
        return theta

    def prior_info(self) -> np.ndarray:
        """The priors' information (n, n): PRIOR_SD_S^-2 on the timing, pose_cov^-1 per pose."""
        P = np.eye(self.n) / PRIOR_SD_S**2
        cols = self.columns
        for c in np.flatnonzero(self.pose):
            k = cols["pose"][c]
            P[k:k + 6, k:k + 6] = np.linalg.inv(self.pose_cov[c])
        return P


def gauge_basis(rig: Rig, shared: Shared) -> np.ndarray:
    """The directions of theta (n, g) that move the variable cameras as one similarity of the world would (a
    rotation and translation of the world, or its scale, about what the fixed cameras pin): the images cannot see
    them, so the solve keeps the input rig's frame and scale along them. Orthonormal columns; g = 7 when every camera
    is a variable, 1 (the scale about it) with one fixed camera, 0 with two."""
    n, cols = shared.n, shared.columns
    C = len(rig)
    if not shared.pose.any():
        return np.zeros((n, 0))
    full = np.zeros((C, 6, 7))  # each camera's left perturbation per world generator (rotation, translation, scale)
    for c, cam in enumerate(rig):
        R, t = cam.R, cam.tvec
        for i in range(3):
            e = np.eye(3)[i]
            full[c, :3, i], full[c, 3:, i] = -R @ e, np.cross(R @ e, t)
            full[c, 3:, 3 + i] = -R @ e
        full[c, 3:, 6] = t
    fixed = ~shared.pose
    if fixed.any():  # combinations of the generators that leave every fixed camera where it is
        A = full[fixed].reshape(-1, 7)
        _, sv, Vt = np.linalg.svd(A)
        rank = int((sv > 1e-9 * max(sv.max(initial=0.0), 1.0)).sum())
        free = Vt[rank:].T  # (7, g)
    else:
        free = np.eye(7)
    G = np.zeros((n, free.shape[1]))
    for c in np.flatnonzero(shared.pose):
        k = cols["pose"][c]
        G[k:k + 6] = full[c] @ free
    if not G.size:
        return G
    q, r = np.linalg.qr(G)
    return q[:, np.abs(np.diag(r)) > 1e-12 * max(np.abs(r).max(initial=0.0), 1.0)]


def applied(setup: fit_mod.Setup, shared: Shared, theta: np.ndarray) -> fit_mod.Setup:
    """``setup`` with theta's corrections: capture times moved, poses perturbed."""
    d_off, d_ro, d_pose = shared.split(theta)
    ideal = setup.ideal
    C, F, M = ideal.seen.shape
    row = np.zeros((C, F, M)) if ideal.row_frac is None else ideal.row_frac
    if shared.offset.any() or shared.readout.any():
        base = np.zeros((C, F, M)) if ideal.time_frac is None else ideal.time_frac
        frac = base + setup.fps * (d_off[:, None, None] + d_ro[:, None, None] * row)
        ideal = replace(ideal, time_frac=frac, row_frac=row, linear_xyz=None)
    return replace(setup, ideal=ideal, rig=applied_rig(setup.rig, shared, theta))


def applied_rig(rig: Rig, shared: Shared, theta: np.ndarray) -> Rig:
    """``rig`` with theta's pose corrections (the timing's are in the observations' capture times)."""
    if not shared.pose.any():
        return rig
    d_pose = shared.split(theta)[2]
    return Rig([_moved(cam, d_pose[c]) if shared.pose[c] else cam for c, cam in enumerate(rig)],
               world_mirror=rig.world_mirror)


def _moved(cam: Camera, xi: np.ndarray) -> Camera:
    """cam with cam_from_world perturbed on the left by xi = (d_omega, d_t) [rad, m]."""
    dR = R_from_rvec(xi[:3])
    R = dR @ cam.R
    return replace(cam, rvec=rvec_from_R(R), tvec=dR @ cam.tvec + xi[3:])


@dataclass
class Linear:
    """The shared variables' part of the joint Gauss-Newton system at a fit: g (n,), H_tt (n, n), the Schur complement
    S = H_tt - H_tx H_xx^-1 H_xt (n, n) with Y = H_xx^-1 H_xt per point, (F, M, 9, n) (scaled states)."""

    g: np.ndarray
    H: np.ndarray
    S: np.ndarray
    Y: np.ndarray


def linearise(setup: fit_mod.Setup, fit: fit_mod.Fit, shared: Shared, levels: np.ndarray,
              exact: bool = False) -> Linear:
    """The shared variables' gradient, Hessian, Schur complement and Y at ``fit`` (markers at noise levels ``levels``
    (M,), as solved: the motion prior sets how much of a timing change the trajectories absorb): the rows' curvature
    the robust loss's own with ``exact`` (the steps: IRLS's overstates it past Huber's k, and the steps then crawl),
    IRLS's without (the covariances, as everywhere)."""
    F, M = setup.shape
    n = shared.n
    g, H, S = np.zeros(n), np.zeros((n, n)), np.zeros((n, n))
    Y = np.zeros((F, M, 9, n))
    for name, ms, group in _units(setup, fit):
        prob = setup.problem(ms, name, levels[ms])
        x = np.ascontiguousarray(fit.state[:, ms, :prob.d])
        Hxt, gu, Hu = _row_terms(prob, x, shared, setup, exact)
        g += gu
        H += Hu
        y = _solve_x(prob, x, group, Hxt, setup, fit, exact)
        Y[:, ms, :prob.d] = y
        S -= Hxt.reshape(-1, n).T @ y.reshape(-1, n)
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


def _row_terms(prob, x, shared: Shared, setup, exact: bool):
    """(H_xt (F, M', d, n), g_t (n,), H_tt (n, n)) of a problem's rows at x (:func:`linearise`'s curvature)."""
    rows = prob.rows
    t = kernels.row_terms(x, rows, prob.cams, prob.loss)
    cols, Jt = _theta_jacobians(rows, t, shared, setup)  # (n_rows, p), (n_rows, 2, p)
    used = (cols >= 0).any(axis=0)
    F, M, d = x.shape
    g, H, Hxt = kernels.shared_terms(rows.k, np.ascontiguousarray(rows.marker), rows.W, t["r"], t["J"], t["w"], t["a"],
                                     np.ascontiguousarray(Jt[:, :, used]), np.ascontiguousarray(cols[:, used]),
                                     exact, F, M, d, shared.n)
    return Hxt, g, H


def _theta_jacobians(rows, t: dict, shared: Shared, setup) -> tuple[np.ndarray, np.ndarray]:
    """Each row's theta columns (n_rows, 8) (-1: none) and whitened Jacobians (n_rows, 2, 8): offset, readout, and
    the pose's six (left perturbation of cam_from_world: d p_cam = -[p_cam]x d_omega + d_t)."""
    cols = shared.columns
    cam = rows.cam
    out_c = np.full((len(cam), 8), -1)
    out_j = np.zeros((len(cam), 2, 8))
    jt = np.einsum("nij,nj->ni", t["J"], t["dp"]) * setup.fps  # d r / d capture time [1/s]
    out_c[:, 0], out_j[:, :, 0] = cols["offset"][cam], jt
    out_c[:, 1], out_j[:, :, 1] = cols["readout"][cam], jt * rows.row[:, None]
    if shared.pose.any():
        R = np.stack([c.R for c in setup.rig])[cam]  # (n, 3, 3)
        tv = np.stack([c.tvec for c in setup.rig])[cam]
        p_cam = np.einsum("nij,nj->ni", R, t["p"]) + tv
        Jc = np.einsum("nij,nkj->nik", t["J"], R)  # d r / d p_cam = J R^T
        base = cols["pose"][cam]
        for i in range(6):
            out_c[:, 2 + i] = np.where(base >= 0, base + i, -1)
        out_j[:, :, 2:5] = -np.einsum("nij,njk->nik", Jc, skew(p_cam))
        out_j[:, :, 5:8] = Jc
    return out_c, out_j


def _solve_x(prob, x, seg_ids, Hxt, setup, fit, exact: bool):
    """H_xx^-1 H_xt (F, M', d, n) at x: the chains' block-tridiagonal solve, a group's bordered one."""
    if seg_ids is None:
        _, _, D, B, _ = prob.system(x, exact)
        return tridiagonal(D, B[:, :, None], rhs=Hxt)["dx"]
    members = np.unique(fit.pairs[seg_ids])
    seg = segments.Segments(np.searchsorted(members, fit.pairs[seg_ids]), setup.rigid_sigma_m)
    L = fit.length_m[seg_ids]
    _, _, T, BG, C, E, _, _ = segments.Group(prob, seg).blocks((x, L), exact)
    F, gm, d = x.shape
    rhs = Hxt.reshape(F, gm * d, -1)
    return segments.bordered_solve(T, BG, C, E, rhs, np.zeros((len(L), rhs.shape[-1])))[0].reshape(F, gm, d, -1)


def solve(setup: fit_mod.Setup, backend, models: np.ndarray, levels: np.ndarray, start, shared: Shared,
          theta0: np.ndarray | None = None) -> tuple:
    """The joint minimiser of the markers and the shared variables from theta0 (module docstring): (fit at the
    minimiser with theta's uncertainty in its covariances, theta (n,) [s, rad, m], its covariance (n, n),
    setup with the corrections applied, steps taken). start: the markers' (p, v, a) to solve from, or their
    minimiser at theta0 already (a fit_mod.Fit of ``setup`` there, taken as it is).

    The steps are Levenberg-Marquardt's on the reduced problem with the Gauss-Newton Schur complement S as its
    Hessian."""
    n = shared.n
    theta = np.zeros(n) if theta0 is None else np.asarray(theta0, float).copy()
    prior = shared.prior_info()
    Z = _complement(gauge_basis(setup.rig, shared), n)  # the directions the images determine (n, n - g)
    cur = applied(setup, shared, theta)
    fit = start if isinstance(start, fit_mod.Fit) else backend.fit(cur, models, levels, start, lm.LOOSE,
                                                                   covariances=False)
    total = _total(fit, theta, prior)
    lin = linearise(cur, fit, shared, levels, exact=True)
    first, factor, floor, stuck = lm.TIGHT.damping  # the driver's damping rules
    lam, steps = 0.0, 0
    g = lin.g + prior @ theta
    while steps < lm.TIGHT.max_iterations and lam <= stuck:
        steps += 1
        S = Z.T @ (lin.S + prior) @ Z
        newton = np.linalg.solve(S, Z.T @ g)
        if 0.5 * float(Z.T @ g @ newton) < DECREMENT_TOL:
            break
        step = _limited(-Z @ np.linalg.solve(S + lam * np.diag(np.diag(S)), Z.T @ g), shared, setup.fps)
        new_theta = theta + step
        new_setup = applied(setup, shared, new_theta)
        x = fit.state - np.einsum("fmin,n->fmi", lin.Y, step)
        new_fit = backend.fit(new_setup, models, levels, _motion(x, fit, setup.fps), lm.LOOSE,
                              covariances=False)
        new_total = _total(new_fit, new_theta, prior)
        if not new_total <= total:
            lam = max(lam * factor, first)
            continue
        theta, fit, total, cur = new_theta, new_fit, new_total, new_setup
        lin = linearise(cur, fit, shared, levels, exact=True)
        g = lin.g + prior @ theta
        lam = lam / factor if lam > floor else 0.0
    lin = linearise(cur, fit, shared, levels)
    cov_t = Z @ np.linalg.inv(Z.T @ (lin.S + prior) @ Z) @ Z.T
    at = backend.fit(cur, models, levels, (fit.xyz, fit.velocity, fit.acceleration), lm.Settings(max_iterations=0))
    if at.cov is not None:  # the markers' covariances at the minimiser, once (the steps' fits skip them)
        Yp = lin.Y[..., :3, :]
        fit = replace(fit, cov=at.cov + (Yp @ cov_t) @ Yp.swapaxes(-1, -2), logdet=at.logdet,
                      length_sd_m=at.length_sd_m)
    return fit, theta, cov_t, cur, steps


MAX_STEP_FRAMES = 0.25  # a step moves a capture time by at most this fraction of a frame (the model's reach)


def _limited(step: np.ndarray, shared: Shared, fps: float) -> np.ndarray:
    """``step`` scaled down so that no capture time moves by more than MAX_STEP_FRAMES: beyond that the rows'
    linearisation no longer predicts them."""
    d_off, d_ro, _ = shared.split(step)
    most = float(np.max(np.abs(d_off) + np.abs(d_ro), initial=0.0)) * fps
    return step * min(1.0, MAX_STEP_FRAMES / most) if most > 0 else step


def poses_evidence(rig: Rig, shared: Shared, theta: np.ndarray, cov: np.ndarray) -> dict:
    """How much more probable the data make the poses as given than the poses moved under their prior: the log
    Bayes factor (Savage-Dickey: the posterior density of no move over its prior density, in the directions the
    images determine) with the chi-square of the move and its degrees of freedom. theta (n,) and cov (n, n) from
    :func:`solve`. Positive: keep the poses as given; the prior's width is the price of moving them (Occam's
    factor), so a move of a few standard deviations in each direction does not pay for it."""
    cols = shared.columns["pose"]
    idx = np.concatenate([np.arange(k, k + 6) for k in cols if k >= 0])
    G = gauge_basis(rig, shared)[idx]
    Z = _complement(G, len(idx))
    u = Z.T @ theta[idx]
    post = np.linalg.inv(Z.T @ cov[np.ix_(idx, idx)] @ Z)
    prior = Z.T @ shared.prior_info()[np.ix_(idx, idx)] @ Z
    chi2 = float(u @ post @ u)
    occam = 0.5 * (np.linalg.slogdet(post)[1] - np.linalg.slogdet(prior)[1])
    return {"log_bayes_factor": -0.5 * chi2 + float(occam), "chi2": chi2, "dof": int(len(u))}


def _complement(G: np.ndarray, n: int) -> np.ndarray:
    """An orthonormal basis (n, n - g) of the complement of G's columns (n, g)."""
    if not G.shape[1]:
        return np.eye(n)
    q = np.linalg.qr(np.hstack([G, np.eye(n)]))[0]
    return q[:, G.shape[1]:n]


def _total(fit: fit_mod.Fit, theta: np.ndarray, prior: np.ndarray) -> float:
    solved = np.array([m is not None for m in fit.models])
    return float(fit.cost[solved].sum() + 0.5 * theta @ prior @ theta)


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

