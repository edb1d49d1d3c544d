"""Fast online filter for a fixed rig: per-marker iterated (Gauss-Newton) Kalman updates, compiled.

It answers what the iSAM2 filter (:mod:`batgraph.graph.filter`) answers after each frame k: each
marker's latest state given frames <= k, with the same factors (projections to ideal pixels with the
mapped noise and GTSAM's robust losses, the filter's motion model and noise, the weak priors at the
joining frame), the same joining rule (a marker joins at its first frame with a finite triangulation,
>= 2 views, and is NaN before) and the same outlier flags. With fixed cameras the markers are
independent, so each marker's filtering posterior is a Gaussian on its latest state: predict it with
the motion model, then take the MAP under that Gaussian and frame k's observations, covariance from the
Gauss-Newton information with GTSAM's IRLS weights at the MAP. On a linear-Gaussian problem this is the
Kalman filter, which iSAM2 equals exactly; on projections it differs from iSAM2 only in that iSAM2 also
relinearises past states (and re-weights their robust factors) with later frames (tests/test_fast_filter.py
measures it). Deliberately no camera uncertainty: a rig with any ``pose_cov`` goes to :func:`run_filter`.

State per marker (as in batgraph.graph.fast): x = p [m] (random walk) or x = [p, u], u = v dt [m per
frame] (constant velocity; factors.v_key's variable), so both halves share a unit.

The update of one marker under its prediction N(mu, P): minimise 0.5 (p - mu_p)^T P_pp^-1 (p - mu_p) +
sum rho(|r|) over p (r the whitened residuals L^-1 (h(p) - z) of its rows on frame k) by Levenberg-Marquardt
from p = mu_p (iSAM2's predicted value), each step the robust loss's own curvature after an accepted step
(IRLS after a rejected one, then damping grows), until the step is < STEP_TOL_M or a kept step lowers the
cost by < REL_COST_TOL relatively. Observations see p only, so the rest of the state follows from the
prior's conditional u | p: with G = P_up P_pp^-1, u = mu_u + G (p - mu_p) and the joint covariance is
[[S, S G^T], [G S, P_uu - G P_pu + G S G^T]], S = (P_pp^-1 + sum w Jw^T Jw)^-1 with GTSAM's IRLS weights w
at the MAP. An update whose information is singular to rounding (S not finite: mislabels drove the point
to a camera centre) is discarded, the marker keeping its prediction there (info "discarded_updates").

Why compiled (batgraph.graph.kernels.filter_markers: every marker's frames in one loop, markers over
threads): the update is a few 3 x 3 solves per marker and frame, which numpy vectorised over markers ran
as ~12 calls of small arrays per Levenberg-Marquardt iteration in a Python loop over frames: 0.8-1.3 s on the
bundled 24-marker flight, 1.6-2.2 s at 30 x 180 x 160; compiled 0.02 s and 0.35-0.5 s (BENCHMARKS.md).
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
from . import kernels
from .cost import MotionModel
from .fast import _Observations, _one_thread, projection_rows
from .noise import filter_motion

MAX_ITERATIONS = 100  # per frame; measured 2-8 on the simulated flight (Huber, the loss's own curvature)
STEP_TOL_M = 1e-10  # stop when a marker's largest step component is below this [m] (cost spec)
REL_COST_TOL = 1e-15  # ... or its cost decreases by less than this, relatively (rounding level)
FRAMES_PER_CALL = 16  # frames per compiled call when nothing is called per frame (the progress bar's steps)


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
    model, info = filter_motion(session, options)
    A, Q, P0 = motion_matrices(model)
    join, tri = join_frames(session.rig, ideal)
    xyz, cov_out, iterations, discarded = _filter_frames(session.rig, ideal, options, on_frame, A, Q, P0, join, tri)
    outlier = spec.outlier_flags(session.rig, ideal, xyz)
    info.update({"solver": "fast", "motion_model": model.name, "robust": options.robust,
                 "robust_k": options.robust_k, "camera_variables": 0, "max_iterations_per_frame": iterations,
                 "discarded_updates": discarded,
                 "cpu_s": time.process_time() - cpu0})
    return Estimate("filter", xyz, cov_out, outlier, time.perf_counter() - t0, info)


def _filter_frames(rig, ideal: IdealObservations, options: Options, on_frame, A: np.ndarray, Q: np.ndarray,
                   P0: np.ndarray, join: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Every frame's update of every joined marker (batgraph.graph.kernels.filter_markers), FRAMES_PER_CALL
    frames per compiled call (one with ``on_frame``, called after each). Returns xyz (F, M, 3) [m], cov
    (F, M, 3, 3) [m^2] (NaN before a marker joins), the most iterations an update took and the number of
    updates discarded (their posterior information singular to rounding)."""
    _, F, M = ideal.seen.shape
    d = A.shape[0]
    obs, bounds = marker_rows(rig, ideal, join)
    mean, cov = np.zeros((M, d)), np.zeros((M, d, d))
    xyz = np.full((F, M, 3), np.nan)
    cov_out = np.full((F, M, 3, 3), np.nan)
    iterations, discarded = np.zeros(M, np.int64), np.zeros(M, np.int64)
    step = 1 if on_frame is not None else FRAMES_PER_CALL
    with tqdm(total=F, desc="filter (fast)", disable=not options.progress, leave=False) as bar:
        for f0 in range(0, F, step):
            f1 = min(F, f0 + step)
            kernels.filter_markers(f0, f1, join, tri, A, Q, P0, bounds, obs.cam, obs.P, obs.uv, obs.Linv,
                                   obs.behind_px, kernels.ROBUST_CODE[options.robust], options.robust_k,
                                   MAX_ITERATIONS, STEP_TOL_M, REL_COST_TOL, mean, cov, xyz, cov_out, iterations,
                                   discarded)
            if on_frame is not None:
                on_frame(f0, xyz[f0], cov_out[f0])
            bar.update(f1 - f0)
    return xyz, cov_out, int(iterations.max(initial=0)), int(discarded.sum())


def marker_rows(rig, ideal: IdealObservations, join: np.ndarray) -> tuple[_Observations, np.ndarray]:
    """Every observation of a marker from its joining frame ``join`` (M,) on, as batgraph.graph.fast's
    projection rows sorted by (marker, frame, camera), and where each (marker, frame)'s rows begin:
    bounds (M F + 1,), the rows of marker m on frame f being bounds[m F + f]..bounds[m F + f + 1] - 1."""
    _, F, M = ideal.seen.shape
    use = ideal.seen & (join >= 0) & (np.arange(F)[:, None] >= join)  # (C, F, M)
    m, f, c = np.nonzero(use.transpose(2, 1, 0))
    rows = projection_rows(rig, ideal, c, f, m, m, M)
    return rows, np.searchsorted(m * F + f, np.arange(M * F + 1))
