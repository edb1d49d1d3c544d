"""The batch smoother: Levenberg-Marquardt over the whole factor graph, then marginal covariances.

Solves the project's cost spec with GTSAM (the reference every fast path is tested against); graph
construction is in :mod:`batgraph.graph.factors`, the choice of the constant-velocity noise in
:mod:`batgraph.graph.noise`. Uses every frame, past and future, so it bridges occlusion gaps.
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from ..measurement import IdealObservations
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import triangulate_ideal
from . import factors, noise
from .factors import MotionFactors, MotionModel, ObservationFactors

MAX_ITERATIONS = 200
FIT_MARKERS = 8  # markers used to choose q (evenly spread over the estimated ones); q is global


# Why QR everywhere: GTSAM's Cholesky declares a clique indeterminate when the last two diagonal
# entries of its R differ by more than 2^12, and a marker seen by one camera for a few dozen frames
# has a depth variance ~1e6-1e8 times its lateral one under the constant-velocity prior (measured:
# gtsam.Marginals failed at q = 1e4 on the simulated flight, LM needed 200 iterations at q = 1e6).
# QR has no such test, so LM solves with MULTIFRONTAL_QR, marginals come from a QR iSAM2 Bayes
# tree (gtsam.Marginals has no QR option in Python) and log-determinants from a QR Bayes net.


def lm_params(max_iterations: int = MAX_ITERATIONS) -> gtsam.LevenbergMarquardtParams:
    """Tight tolerances (cost spec: relative cost decrease < 1e-12), QR linear solves."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(max_iterations)
    params.setLinearSolverType("MULTIFRONTAL_QR")
    return params


def solve_batch(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt to convergence from ``initial``. Returns (solution, iterations)."""
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params())
    solution = optimizer.optimize()
    return solution, int(optimizer.iterations())


def marginal_covariances(graph: gtsam.NonlinearFactorGraph, solution: gtsam.Values, keys: list[int]) -> np.ndarray:
    """Marginal covariance of each key, (n, d, d): what gtsam.Marginals gives (Gauss-Newton information at
    ``solution``, robust-whitened), computed through a QR-factorised iSAM2 Bayes tree (see above)."""
    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    params.enableRelinearization = False
    isam = gtsam.ISAM2(params)
    isam.update(graph, solution)
    return np.array([isam.marginalCovariance(k) for k in keys])


def posterior_logdet(graph: gtsam.NonlinearFactorGraph, solution: gtsam.Values, dt_s: float,
                     n_velocity: int = 0) -> float:
    """log det of the Gauss-Newton information at ``solution``, in units m (p) and m/s (v).

    From a QR Bayes net: log det Lambda = 2 sum log|diag R|. The graph's velocity
    variables are u = v dt (factors.v_key); Lambda_v = dt^2 Lambda_u, so each of the ``n_velocity``
    3-vectors adds 6 log dt.
    """
    lin = graph.linearize(solution)
    bayes_net = lin.eliminateSequential(gtsam.Ordering.ColamdGaussianFactorGraph(lin), gtsam.EliminateQR)
    # QR's R may have negative diagonal entries (GTSAM's logDeterminant would take their log)
    log_det_R = sum(np.log(np.abs(np.diag(bayes_net.at(i).R()))).sum() for i in range(bayes_net.size()))
    return 2.0 * log_det_R + 6 * n_velocity * np.log(dt_s)


def log_evidence(graph: gtsam.NonlinearFactorGraph, solution: gtsam.Values, q: float, dt_s: float,
                 n_steps: int, n_velocity: int) -> float:
    """Laplace log marginal likelihood of q (see :mod:`batgraph.graph.noise`) at the optimum ``solution``."""
    logdet_post = posterior_logdet(graph, solution, dt_s, n_velocity)
    return noise.laplace_log_evidence(graph.error(solution), logdet_post, q, dt_s, n_steps)


def choose_accel_psd(obs: ObservationFactors, p_init: np.ndarray, v_init: np.ndarray, markers: np.ndarray,
                     dt_s: float, progress: bool = False) -> tuple[float, dict]:
    """Maximum-marginal-likelihood q [m^2/s^3] on a subset of ``markers`` (noise.py's rule).

    The markers are independent given fixed cameras, so the evidence is a sum over markers and a
    spread subset (FIT_MARKERS, evenly over the index order) estimates the common q at a fraction
    of the cost; with camera variables the subset is a sub-graph sharing the cameras. Each solve
    is warm-started from the previous one. Returns (q, info for Estimate.info).
    """
    n_fit = min(FIT_MARKERS, len(markers))
    fit = markers[np.unique(np.linspace(0, len(markers) - 1, n_fit).round().astype(int))]
    F = p_init.shape[0]
    base = factors.observation_graph(obs, fit, F)
    model0 = MotionModel("constant_velocity", dt_s, accel_psd_m2_s3=1.0)
    state = {"values": factors.initial_values(obs, model0, p_init, v_init, fit)}

    def score(q: float) -> float:
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(base)  # shares the projection factors; only the motion factors change with q
        graph.push_back(factors.motion_graph(MotionFactors(MotionModel("constant_velocity", dt_s,
                                                                       accel_psd_m2_s3=q)), p_init, fit))
        state["values"], _ = solve_batch(graph, state["values"])
        return log_evidence(graph, state["values"], q, dt_s, len(fit) * (F - 1), len(fit) * F)

    q, trace = noise.maximise_log10(score, progress=progress)
    return q, {"rule": "max Laplace marginal likelihood over log10 q in [0, 6] (grid + golden section)",
               "fit_markers": [int(m) for m in fit],
               "scores": [{"accel_psd_m2_s3": a, "log_evidence": s} for a, s in trace]}


def run_smoother(session: Session, dense: DenseObservations, ideal: IdealObservations,
                 options: Options) -> Estimate:
    """The ``smoother`` method: batch LM over every frame, marginal covariances, outlier flags.

    ideal: ideal pixels (C, F, M, 2) and covariances (C, F, M, 2, 2) of ``dense`` (batgraph.measurement).
    Returns Estimate(method="smoother"): xyz_m (F, M, 3), cov_m2 (F, M, 3, 3), NaN for markers never
    triangulated; outlier (C, F, M) where |r|^2 > 13.8155 at the solution (plain Gaussian whitening).
    """
    t0 = time.perf_counter()
    C, F, M = ideal.seen.shape
    dt = 1.0 / session.fps
    model_name, sigma_m, q = noise.motion_choice(session, options)
    tri, _ = triangulate_ideal(session.rig, ideal)
    p_init, v_init, estimated = factors.initial_track(tri, session.fps)
    markers = np.flatnonzero(estimated)
    obs = ObservationFactors(session.rig, ideal, options.robust, options.robust_k)
    info: dict = {"solver": "gtsam", "motion_model": model_name, "robust": options.robust,
                  "robust_k": options.robust_k, "camera_variables": int(obs.variable.sum())}
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    if len(markers) == 0:
        return Estimate("smoother", xyz, cov, np.zeros((C, F, M), bool), time.perf_counter() - t0, info)
    if model_name == "random_walk":
        model = MotionModel("random_walk", dt, sigma_m=sigma_m)
        info["sigma_m"] = sigma_m
    else:
        if q is None:
            q, info["accel_psd_selection"] = choose_accel_psd(obs, p_init, v_init, markers, dt, options.progress)
            info["accel_psd_source"] = "data"
        else:
            info["accel_psd_source"] = "given"
        model = MotionModel("constant_velocity", dt, accel_psd_m2_s3=q)
        info["accel_psd_m2_s3"] = q
    graph = factors.observation_graph(obs, markers, F)
    graph.push_back(factors.motion_graph(MotionFactors(model), p_init, markers))
    solution, info["iterations"] = solve_batch(graph, factors.initial_values(obs, model, p_init, v_init, markers))
    info["final_error"] = float(graph.error(solution))
    xyz = factors.positions(solution, markers, F, M)
    keys = [factors.p_key(int(m), k) for k in range(F) for m in markers]
    cov[:, markers] = marginal_covariances(graph, solution, keys).reshape(F, len(markers), 3, 3)
    outlier = factors.outlier_flags(obs.solved_rig(solution), ideal, xyz)
    return Estimate("smoother", xyz, cov, outlier, time.perf_counter() - t0, info)
