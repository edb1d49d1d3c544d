"""The online filter: each frame's estimate from frames up to it only; the iSAM2 filter's answer with fixed cameras.

A marker joins at its first frame with a triangulation (>= 2 views), from the weak gauge priors there (velocity 0),
and is NaN before. After each frame the markers are independent Gaussians on their latest state: predict with the
motion model (x' = A x, P' = A P A^T + Q), then update with the frame's rows: the MAP of the prediction times the
rows' robust likelihood (the same problem as the smoother's, one frame long, the prediction as its prior; the same
row kernel and Levenberg-Marquardt driver), covariance the inverse Gauss-Newton information there (IRLS weights).
A row captured after its frame's time is placed on the model's mean from that state (batgraph.solver.model).
On a linear-Gaussian problem this is the Kalman filter, which iSAM2 equals; on projections iSAM2 also relinearises
past states with later frames. An update whose information is singular to rounding (a mislabel drove the point to
a camera centre) is discarded: the marker keeps its prediction there.

The filter's motion model: the random walk, or constant velocity ("auto" and constant acceleration filter with it:
no causal rule chooses a jerk PSD); q given, else batgraph.motion.causal_accel_psd of the motion config (no data).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from tqdm.auto import tqdm

from ..measurement import IdealObservations, of_markers
from ..motion import causal_accel_psd
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import fit as fit_mod
from . import lm
from . import model as mm
from .chains import Chains
from .problem import Cameras, Loss, Problem, Rows
from .schedule import OUTLIER_SQ_RESIDUAL, motion_choice
from .threads import one_blas_thread


def filter_motion(session: Session, options: Options) -> tuple[str, float, dict]:
    """(model, level, figures): the random walk at its sigma_m, else constant velocity at the given q or the causal
    one (figure motion_model_requested when the session asked for another model)."""
    name, sigma_m, q = motion_choice(session, options)
    if name == "random_walk":
        return name, sigma_m, {"sigma_m": sigma_m}
    level = q if q is not None else causal_accel_psd(session.motion, session.fps)
    info = {"accel_psd_m2_s3": level, "accel_psd_source": "given" if q is not None else "motion config"}
    if name != "constant_velocity":
        info["motion_model_requested"] = name
    return "constant_velocity", level, info


def join_frames(rig, ideal: IdealObservations) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's joining frame (M,) (-1: never) and its triangulation there (M, 3) [m]: the first frame whose
    linear triangulation is finite (only the candidate frames are triangulated)."""
    multi = ideal.seen.sum(axis=0) >= 2
    M = multi.shape[1]
    join, tri = np.full(M, -1), np.full((M, 3), np.nan)
    todo = multi.any(axis=0)
    while todo.any():
        ms = np.flatnonzero(todo)
        ks = multi[:, ms].argmax(axis=0)
        xyz = dlt_points(rig, IdealObservations(ideal.uv_px[:, ks, ms][:, None], ideal.cov_px2[:, ks, ms][:, None]))[0]
        ok = np.isfinite(xyz).all(axis=-1)
        join[ms[ok]], tri[ms[ok]] = ks[ok], xyz[ok]
        multi[ks[~ok], ms[~ok]] = False  # a degenerate triangulation: the marker's next multi-view frame
        todo[ms[ok]] = False
        todo &= multi.any(axis=0)
    return join, tri


def run(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options,
        on_frame: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> Estimate:
    """The ``filter`` method: xyz (F, M, 3), cov (F, M, 3, 3) right after each frame's update (NaN before a marker
    joins); outlier flags (C, F, M) from those estimates. on_frame(k, xyz (M, 3), cov (M, 3, 3)) after frame k.
    ``options.solver`` "gtsam", or a camera with a pose covariance (a variable shared by every marker, which this
    filter's independent markers cannot carry): GTSAM's iSAM2 (batgraph.solver.reference.run_filter)."""
    if options.solver == "gtsam" or any(c.pose_cov is not None for c in session.rig):
        return _run_gtsam(session, ideal, options, on_frame)
    with one_blas_thread():
        return _run(session, ideal, options, on_frame)


def _run_gtsam(session, ideal, options, on_frame) -> Estimate:
    from .reference import run_filter  # GTSAM is a slow import

    t0 = time.perf_counter()
    name, level, info = filter_motion(session, options)
    loss = Loss(options.robust, options.robust_k)
    xyz, cov, n_variables = run_filter(session, ideal, (name, level), join_frames(session.rig, ideal), loss, on_frame)
    info.update({"solver": "gtsam", "motion_model": name, "robust": options.robust, "robust_k": options.robust_k,
                 "camera_variables": n_variables})
    return Estimate("filter", xyz, cov, np.zeros(ideal.seen.shape, bool), time.perf_counter() - t0, info)


def _run(session, ideal, options, on_frame) -> Estimate:
    t0 = time.perf_counter()
    name, level, info = filter_motion(session, options)
    C, F, M = ideal.seen.shape
    d, fps = mm.state_dim(name), session.fps
    A, Q1, P0_info = mm.scaled(name, 1.0 / fps)
    Q, P0 = Q1 * mm.noise_scale(name, level), np.linalg.inv(P0_info)
    join, tri = join_frames(session.rig, ideal)
    cams, loss = Cameras.of(session.rig), Loss(options.robust, options.robust_k)
    rows = _frame_rows(ideal, join)
    mean, cov = np.zeros((M, d)), np.zeros((M, d, d))
    state = np.full((F, M, 9), np.nan)
    xyz, cov_out = np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan)
    most, discarded = 0, 0
    for k in tqdm(range(F), desc="filter", disable=not options.progress, leave=False):
        new = join == k
        mean[new] = 0.0
        mean[new, :3] = tri[new]
        cov[new] = P0
        old = (join >= 0) & (join < k)
        mean[old] = mean[old] @ A.T
        cov[old] = A @ cov[old] @ A.T + Q
        on = join >= 0
        on &= join <= k
        if on.any():
            it, bad = _update(rows[k], cams, fps, name, loss, mean, cov, on)
            most, discarded = max(most, it), discarded + bad
            state[k, on, :d] = mean[on]
            xyz[k, on], cov_out[k, on] = mean[on, :3], cov[on, :3, :3]
        if on_frame is not None:
            on_frame(k, xyz[k], cov_out[k])
    setup = fit_mod.Setup(ideal, session.rig, fps, loss, xyz)
    fit = fit_mod.Fit.empty(F, M, False)
    fit.state, fit.models = state, np.where(join >= 0, name, None)
    flags = np.nan_to_num(fit_mod.sq_residuals(setup, fit), nan=0.0) > OUTLIER_SQ_RESIDUAL
    info.update({"solver": "fast", "motion_model": name, "robust": options.robust, "robust_k": options.robust_k,
                 "max_iterations_per_frame": most, "discarded_updates": discarded})
    return Estimate("filter", xyz, cov_out, flags, time.perf_counter() - t0, info)


def _frame_rows(ideal: IdealObservations, join: np.ndarray) -> list[Rows]:
    """Each frame's observations of the joined markers as one-frame rows (frame 0), markers numbered as in M."""
    F = ideal.seen.shape[1]
    out = []
    for k in range(F):
        r = Rows.of(of_markers(_frames(ideal, k), slice(None)))
        r.frame[:] = 0
        out.append(r)
    return out


def _frames(ideal: IdealObservations, k: int) -> IdealObservations:
    import dataclasses

    shape = ideal.uv_px.shape[:3]
    return dataclasses.replace(ideal, linear_xyz=None, **{
        f.name: getattr(ideal, f.name)[:, k:k + 1] for f in dataclasses.fields(ideal)
        if isinstance(getattr(ideal, f.name), np.ndarray) and getattr(ideal, f.name).shape[:3] == shape})


def _update(rows: Rows, cams, fps, name, loss, mean, cov, on) -> tuple[int, int]:
    """One frame's update of the markers ``on`` (M,) bool, mean (M, d) and cov (M, d, d), in place; returns
    (iterations, updates discarded)."""
    ms = np.flatnonzero(on)
    sub = rows.of_markers(on)
    info = np.linalg.inv(cov[ms])
    prob = Problem(sub, cams, fps, 1, name, np.ones(len(ms)), loss, mean[ms, :3], prior=(mean[ms], info))
    res = lm.minimise(Chains(prob), mean[ms][None].copy(), lm.LOOSE)
    _, _, D, _, _ = prob.system(res.state, False)
    with np.errstate(all="ignore"):
        post = np.linalg.inv(D[0])
    ok = np.isfinite(post).all(axis=(1, 2))
    post = 0.5 * (post + np.swapaxes(post, -1, -2))
    mean[ms[ok]], cov[ms[ok]] = res.state[0, ok], post[ok]
    return int(res.iterations.max(initial=0)), int((~ok).sum())
