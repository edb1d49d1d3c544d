"""Fast online filter for a fixed rig: per-marker iterated (Gauss-Newton) Kalman updates, vectorised across
markers.

It answers what the iSAM2 filter (:mod:`batgraph.graph.filter`) answers after each frame k: each
marker's latest state given frames <= k, with the same factors (projections to ideal pixels with the
mapped noise and GTSAM's robust losses, the filter's motion model and noise, the weak priors at the
joining frame), the same joining rule (a marker joins at its first frame with a finite triangulation,
>= 2 views, and is NaN before) and the same outlier flags. With fixed cameras the markers are
independent, so each marker's filtering posterior is a Gaussian on its latest state: predict it with
the motion model, then take the MAP under that Gaussian and frame k's observations
(Levenberg-Marquardt per marker to convergence,
robust losses as in GTSAM), covariance from the Gauss-Newton information with GTSAM's IRLS weights at
the MAP. On a linear-Gaussian problem this is the Kalman filter, which iSAM2 equals exactly; on
projections it differs from iSAM2 only in that iSAM2 also relinearises past states (and re-weights
their robust factors) with later frames (tests/test_fast_filter.py measures it).
Deliberately no camera uncertainty: a rig with any ``pose_cov`` goes to :func:`run_filter`.

State per marker (as in batgraph.graph.fast): x = p [m] (random walk) or x = [p, u], u = v dt [m per
frame] (constant velocity; factors.v_key's variable), so both halves share a unit.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from tqdm.auto import tqdm

from ..measurement import IdealObservations
from ..motion import constant_velocity_Q
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import cost as spec
from .cost import MotionModel, robust_loss
from .fast import _Observations, _one_thread, projection_rows
from .noise import filter_motion

MAX_ITERATIONS = 100  # per frame; measured 2-8 on the simulated flight (Huber, the loss's own curvature)
STEP_TOL_M = 1e-10  # stop when a marker's largest step component is below this [m] (cost spec)
REL_COST_TOL = 1e-15  # ... or its cost decreases by less than this, relatively (rounding level)


def motion_matrices(model: MotionModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transition A (d, d), process covariance Q (d, d) and the joining prior's covariance P0 (d, d).

    In the filter's state (module docstring): random walk d = 3, A = I, Q = sigma_m^2 I,
    P0 = (10 m)^2 I; constant velocity d = 6, A = [[I, I], [0, I]], Q = S Q(q, dt) S with
    S = diag(I, dt I) (batgraph.motion.constant_velocity_Q in [p, v]), P0 = diag((10 m)^2 I, (10 m/s dt)^2 I).
    """
    if not model.has_velocity:
        return np.eye(3), model.sigma_m**2 * np.eye(3), spec.PRIOR_POSITION_SIGMA_M**2 * np.eye(3)
    dt = model.dt_s
    S = np.diag([1.0] * 3 + [dt] * 3)
    A = np.block([[np.eye(3), np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    P0 = np.diag([spec.PRIOR_POSITION_SIGMA_M**2] * 3 + [(spec.PRIOR_VELOCITY_SIGMA_MPS * dt) ** 2] * 3)
    return A, S @ constant_velocity_Q(model.accel_psd_m2_s3, dt) @ S, P0


def predict(mean: np.ndarray, cov: np.ndarray, A: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One motion step of n markers: mean (n, d) -> A mean, cov (n, d, d) -> A cov A^T + Q."""
    return mean @ A.T, A @ cov @ A.T + Q


def _robust_curvature(d2: np.ndarray, robust: str, k: float) -> np.ndarray | None:
    """a / |r|^2 of the robust loss's curvature ``w Jw^T (I - a r r^T / |r|^2) Jw`` (None for "none").

    The same Newton-type term as batgraph.graph.fast's steps (a = 1 beyond Huber's k; Cauchy
    a = min(1, 2|r|^2 / (k^2 + |r|^2)), clamped so the block stays PSD): quadratic convergence instead of
    IRLS's linear rate, same gradient, same minimiser. Covariances never use it (GTSAM's IRLS weights).
    """
    if robust == "none":
        return None
    kk = k * k
    a = (d2 > kk).astype(float) if robust == "huber" else np.minimum(1.0, 2 * d2 / (kk + d2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(d2 > 0, a / d2, 0.0)


def _blocks(n: int, rows, r: np.ndarray, Jw: np.ndarray, weight: np.ndarray,
            a: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Sum of each marker's observation terms: gradient (n, 3) = sum w Jw^T r, and the 3x3 blocks (n, 3, 3)
    sum w Jw^T Jw (minus the robust curvature term when ``a`` is given); one bincount per entry."""
    Jr = Jw[0] * r[0] + Jw[1] * r[1]  # Jw^T r, (3, n_rows)
    g = np.stack([np.bincount(rows.m, weights=weight * Jr[i], minlength=n) for i in range(3)], axis=-1).astype(float)
    H = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            Hij = Jw[0, i] * Jw[0, j] + Jw[1, i] * Jw[1, j]
            if a is not None:
                Hij = Hij - a * Jr[i] * Jr[j]
            H[:, i, j] = H[:, j, i] = np.bincount(rows.m, weights=weight * Hij, minlength=n)
    return g, H


def newton_steps(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """-H^-1 g per marker, (n, 3), for H (n, 3, 3) and g (n, 3); NaN for a marker whose H is singular to
    LAPACK (a zero pivot), whose step the caller then rejects (its cost is not finite) and damps further.
    Met on the simulated 5-camera flight with 5 % mislabels (seed 1): an H with eigenvalues 3.9e4 and
    ~3e20 1/m^2 (whitened projection Jacobians of a point ~1e-7 m in front of a camera centre), where
    np.linalg.solve raised for the whole batch and the filter stopped with a traceback."""
    try:
        return -np.linalg.solve(H, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full(g.shape, np.nan)
        for i in range(len(H)):
            try:
                out[i] = -np.linalg.solve(H[i], g[i])
            except np.linalg.LinAlgError:
                pass
        return out


def iterated_update(mean: np.ndarray, cov: np.ndarray, rows, robust: str = "huber", robust_k: float = 2.0,
                    p_start: np.ndarray | None = None, max_iterations: int = MAX_ITERATIONS,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MAP of n markers' states under the prior N(mean, cov) and their observations, and its covariance.

    mean: (n, d) [m] (d = 3: p; d = 6: [p, u = v dt]); cov: (n, d, d) [m^2].
    rows: the observations, any object with ``m`` (n_rows,) int (the marker's row in ``mean``) and
        ``residuals(x (1, n, 3), jacobian: bool) -> (r (2, n_rows), Jw (2, 3, n_rows) or None)``, the
        whitened residuals L^-1 (h(p) - z) and their Jacobians in p [1/m] (batgraph.graph.fast's
        projection rows; a linear h works too).
    p_start: where the iteration starts, (n, 3) [m]; default the prior mean (iSAM2's predicted value).
    Minimises 0.5 (p - mu_p)^T P_pp^-1 (p - mu_p) + sum rho(|r|) over p, per marker (Levenberg-Marquardt,
    vectorised, each marker with its own damping) until its step is < 1e-10 m. Observations see p only,
    so the rest of the state follows from the prior's conditional u | p: with G = P_up P_pp^-1,
    u = mu_u + G (p - mu_p) and the joint covariance is [[S, S G^T], [G S, P_uu - G P_pu + G S G^T]],
    S = (P_pp^-1 + sum w Jw^T Jw)^-1 with GTSAM's IRLS weights w at the MAP.
    Returns mean (n, d), cov (n, d, d) and the iterations per marker (n,).
    """
    n, d = mean.shape
    mu = mean[:, :3]
    Ppp = cov[:, :3, :3]
    Lp = np.linalg.inv(Ppp)

    def evaluate(p: np.ndarray, rows_, ms: np.ndarray):  # markers ms at p (len(ms), 3): cost, r, Jw
        r, Jw = rows_.residuals(p[None], jacobian=True)
        rho, _ = robust_loss(r[0] * r[0] + r[1] * r[1], robust, robust_k)
        e = p - mu[ms]
        total = 0.5 * np.einsum("ni,nij,nj->n", e, Lp[ms], e) + np.bincount(rows_.m, weights=rho, minlength=len(ms))
        return np.where(np.isnan(total), np.inf, total), r, Jw

    p = (mu if p_start is None else p_start).copy()
    # one residual + Jacobian pass per iteration: the trial point's Jacobians are kept for the next
    # step when it is accepted (the usual case); r_all, J_all hold every row's at the current p
    c, r_all, J_all = evaluate(p, rows, np.arange(n))
    lam = np.zeros(n)
    active = np.ones(n, bool)
    newton = np.zeros(n, bool)  # take the robust loss's curvature (else IRLS) in this marker's next step
    iterations = np.zeros(n, int)
    diag = np.arange(3)
    sub, cols, idx = rows, np.arange(n), np.arange(len(rows.m))  # active markers' rows (idx: into rows)
    r, Jw = r_all, J_all
    for _ in range(max_iterations):
        if not active.any():
            break
        act = np.flatnonzero(active)
        if len(act) < len(cols):  # converged markers drop out (most converge in a few iterations)
            keep = active[cols][sub.m]
            sub, cols, idx = sub.of_markers(active[cols]), act, idx[keep]
            r, Jw = r[:, keep], Jw[:, :, keep]
        pa = p[act]
        d2 = r[0] * r[0] + r[1] * r[1]
        _, w = robust_loss(d2, robust, robust_k)
        a = _robust_curvature(d2, robust, robust_k)
        g, H = _blocks(len(act), sub, r, Jw, w, None if a is None else a * newton[act][sub.m])
        g += (Lp[act] @ (pa - mu[act])[..., None])[..., 0]
        H += Lp[act]
        H[:, diag, diag] *= 1.0 + lam[act, None]
        dp = newton_steps(H, g)
        c_new, r_new, J_new = evaluate(pa + dp, sub, act)
        ok = c_new <= c[act]
        step = np.abs(dp).max(axis=1)
        rel = (c[act] - c_new) / np.maximum(c[act], np.finfo(float).tiny)
        p[act[ok]] = pa[ok] + dp[ok]
        row_ok = ok[sub.m]
        r, Jw = np.where(row_ok, r_new, r), np.where(row_ok, J_new, Jw)
        r_all[:, idx], J_all[:, :, idx] = r, Jw
        stuck = lam[act] > 1e12
        done = (ok & (rel < REL_COST_TOL)) | (step < STEP_TOL_M) | stuck
        iterations[act] += 1
        c[act] = np.where(ok, c_new, c[act])
        # far from the minimum (e.g. most residuals beyond Huber's k at the prediction) the curvature
        # step can overshoot: a rejected curvature step is retried as an IRLS step before damping grows
        retry = ~ok & newton[act]
        lam[act] = np.where(ok, np.where(lam[act] > 1e-9, lam[act] / 10, 0.0),
                            np.where(retry, lam[act], np.maximum(lam[act] * 10, 1e-6)))
        newton[act] = ok
        active[act] = ~done
    r, Jw = r_all, J_all
    _, w = robust_loss(r[0] * r[0] + r[1] * r[1], robust, robust_k)
    S = np.linalg.inv(Lp + _blocks(n, rows, r, Jw, w, None)[1])
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    out_mean = mean.copy()
    out_cov = np.empty_like(cov)
    out_mean[:, :3] = p
    out_cov[:, :3, :3] = S
    if d > 3:
        G = cov[:, 3:, :3] @ Lp  # (n, 3, 3)
        GS = G @ S
        out_mean[:, 3:] += (G @ (p - mu)[..., None])[..., 0]
        out_cov[:, 3:, :3] = GS
        out_cov[:, :3, 3:] = np.swapaxes(GS, -1, -2)
        Puu = cov[:, 3:, 3:] - G @ cov[:, :3, 3:] + GS @ np.swapaxes(G, -1, -2)
        out_cov[:, 3:, 3:] = 0.5 * (Puu + np.swapaxes(Puu, -1, -2))
    return out_mean, out_cov, iterations


def frame_rows(rig, ideal: IdealObservations, join: np.ndarray) -> _Observations:
    """Every observation of a marker from its joining frame ``join`` (M,) on, as batgraph.graph.fast's
    projection rows (fast.projection_rows) sorted by frame, so each frame's rows are one contiguous slice;
    the column ``m`` is the marker itself."""
    _, F, M = ideal.seen.shape
    use = ideal.seen & (join >= 0) & (np.arange(F)[:, None] >= join)  # (C, F, M)
    f, c, m = np.nonzero(use.transpose(1, 0, 2))
    return projection_rows(rig, ideal, c, f, m, m, M)


def join_frames(rig, ideal: IdealObservations) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's joining frame index (M,) int (-1: never joins) and its triangulation there (M, 3) [m].

    The filter's rule: the first frame whose triangulation (batgraph.triangulate.dlt_points) is
    finite; only the candidate frames are triangulated (a point's DLT does not depend on the others').
    """
    multi = ideal.seen.sum(axis=0) >= 2  # (F, M): where a triangulation can be finite
    M = multi.shape[1]
    join = np.full(M, -1)
    tri = np.full((M, 3), np.nan)
    todo = multi.any(axis=0)
    while todo.any():
        ms = np.flatnonzero(todo)
        ks = multi[:, ms].argmax(axis=0)
        sub = IdealObservations(ideal.uv_px[:, ks, ms][:, None], ideal.cov_px2[:, ks, ms][:, None])
        xyz = dlt_points(rig, sub)[0]  # (n, 3)
        ok = np.isfinite(xyz).all(axis=-1)
        join[ms[ok]], tri[ms[ok]] = ks[ok], xyz[ok]
        multi[ks[~ok], ms[~ok]] = False  # degenerate DLT: try the marker's next multi-view frame
        todo[ms[ok]] = False
        todo &= multi.any(axis=0)
    return join, tri


@_one_thread
def run_filter_fast(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options,
                    on_frame: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> Estimate:
    """The ``filter`` method on the fast path (fixed rig); the iSAM2 filter's answer, frame by frame.

    ideal: ideal pixels (C, F, M, 2) and covariances (C, F, M, 2, 2) (batgraph.measurement).
    on_frame(k_index, xyz (M, 3) [m], cov (M, 3, 3) [m^2]): called after each frame's update, NaN for
        markers that have not joined (as batgraph.graph.filter.run_filter).
    Returns Estimate(method="filter"): xyz_m (F, M, 3), cov_m2 (F, M, 3, 3) right after frame k's update;
    outlier (C, F, M) from those per-frame estimates (|r|^2 > 13.8155, plain Gaussian whitening).
    Falls back to run_filter (iSAM2) when any camera has a pose covariance.
    """
    if any(cam.pose_cov is not None for cam in session.rig):
        from .filter import run_filter  # the GTSAM reference (camera variables); imports GTSAM

        return run_filter(session, dense, ideal, options, on_frame)
    t0, cpu0 = time.perf_counter(), time.process_time()
    C, F, M = ideal.seen.shape
    model, info = filter_motion(session, options)
    A, Q, P0 = motion_matrices(model)
    d = A.shape[0]
    join, tri = join_frames(session.rig, ideal)
    obs = frame_rows(session.rig, ideal, join)
    bounds = np.searchsorted(obs.f, np.arange(F + 1))
    mean, cov = np.zeros((M, d)), np.zeros((M, d, d))
    xyz = np.full((F, M, 3), np.nan)
    cov_out = np.full((F, M, 3, 3), np.nan)
    col = np.zeros(M, int)  # marker -> its row among the active markers of the current frame
    iterations = 0
    for k in tqdm(range(F), desc="filter (fast)", disable=not options.progress, leave=False):
        old = np.flatnonzero((join >= 0) & (join < k))
        mean[old], cov[old] = predict(mean[old], cov[old], A, Q)
        new = np.flatnonzero(join == k)
        mean[new] = 0.0
        mean[new, :3] = tri[new]
        cov[new] = P0
        act = np.flatnonzero((join >= 0) & (join <= k))
        if len(act):
            col[act] = np.arange(len(act))
            a, b = bounds[k], bounds[k + 1]
            rows = _Observations(np.zeros(b - a, int), col[obs.m[a:b]], obs.cam[a:b], obs.P, obs.uv[:, a:b],
                                 obs.Linv[:, a:b], obs.behind_px, 1, len(act))
            prior = mean[act], cov[act]
            mean[act], cov[act], it = iterated_update(*prior, rows, options.robust, options.robust_k)
            iterations = max(iterations, int(it.max()))
            xyz[k, act] = mean[act, :3]
            cov_out[k, act] = cov[act, :3, :3]
        if on_frame is not None:
            on_frame(k, xyz[k], cov_out[k])
    outlier = spec.outlier_flags(session.rig, ideal, xyz)
    info.update({"solver": "fast", "motion_model": model.name, "robust": options.robust,
                 "robust_k": options.robust_k, "camera_variables": 0, "max_iterations_per_frame": iterations,
                 "cpu_s": time.process_time() - cpu0})
    return Estimate("filter", xyz, cov_out, outlier, time.perf_counter() - t0, info)
