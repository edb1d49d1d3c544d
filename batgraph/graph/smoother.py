"""The batch smoother: Levenberg-Marquardt over the whole factor graph, then marginal covariances.

Solves the project's cost spec with GTSAM (the reference every fast path is tested against); graph
construction is in :mod:`batgraph.graph.factors`, the choice of the motion model and its noise in
:mod:`batgraph.graph.noise`. Uses every frame, past and future, so it bridges occlusion gaps.

Outlier rejection (``options.outlier_rejection``, with a robust loss; every fast path must follow it):

1. Cleaning: minimise the cost with the Cauchy loss (threshold ``robust_k``) from the initial track
   (p_init, v_init) at q0 = the given q, else :func:`batgraph.graph.noise.causal_accel_psd` (the
   random walk uses its sigma). The initial track interpolates >= 2-view triangulations only, so a
   mislabel that is a frame's only observation does not attract it, and Cauchy's redescending
   influence leaves it unfitted; Huber (bounded but not vanishing influence) would fit it whenever
   the motion prior is cheaper to bend than k |r|, which corrupted single-view stretches and the
   velocities that extrapolation relies on. (Huber first and Cauchy from the Huber solution does
   not work: the Huber solution already sits in the mislabel's basin.)
2. D = observations with |r|^2 > 25 (factors.REJECT_SQ_RESIDUAL, plain Gaussian whitening) at the
   cleaning solution, kept in D only where its (frame, marker) is seen by one camera or has at
   least one view not over 25 (:func:`batgraph.graph.factors.to_exclude`: a mislabel is a single
   observation; a frame with every view rejected means the motion prior, not the data, is wrong).
3. q (when not given): the marginal-likelihood search of :mod:`batgraph.graph.noise` with the chosen
   loss on the observations not in D (outliers inflated it), warm-started from the cleaning solution:
   one q PER MARKER (fast.choose_accel_psd_per_marker, scored exactly with the fast solver: with
   fixed cameras the markers are independent). With camera variables the score is the evidence
   conditional on the cameras at their calibrated means (the markers share the cameras, so the exact
   evidence would not split per marker); one global q instead cost 8.6 % in RMSE on observed points
   (1.448 -> 1.572 mm, simulated 5-camera flight, seed 1). A given q (options or session) is global.
   With model "auto" (the default since the twentieth session) the same search runs for constant
   velocity (q) and constant acceleration (jerk PSD j), and each marker keeps the model of larger evidence
   (fast.choose_model_per_marker); an explicit constant_acceleration searches j only. The cleaning
   solve of steps 1-2 uses constant velocity for both (fast.cleaning_motion).
4. Final: the chosen loss (``robust``) on the observations not in D, warm-started from step 3's solutions
   at the chosen levels (fast.searched_start; the cleaning solution where step 3 did not run, or found no
   level for a marker); then D' = step 2's rule at that solution over ALL observations; while D' != D (at most
   REJECTION_ROUNDS solves in all), D = D' and re-solve warm (the fast schedule re-solves only the markers whose
   observations in D changed, each with its segment group: the others' problems are unchanged). Covariances
   come from the last solve's graph (D excluded); the outlier flags are, as always, |r|^2 > 13.8155 at the
   final solution over all observations (so every excluded observation is flagged when the rounds converged).

With ``robust="none"`` or rejection off, the answer is the single minimiser of the cost as before.
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from ..errors import InputError
from ..measurement import IdealObservations
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import factors, noise, rigid
from .cost import AUTO, AUTO_CANDIDATES, CLEANING_LOSS, REJECTION_ROUNDS, WINGBEAT, motion_model  # noqa: F401  (the schedule's constants, module docstring)
from .ends import widen_ends
from .factors import MotionFactors, MotionModel, ObservationFactors  # noqa: F401  (MotionModel re-exported)
from .fast import choose_model_per_marker, searched_start
from .schedule import cleaning_motion, flapping_floor, periodic_advice

MAX_ITERATIONS = 200
SEGMENTS_WITH_CAMERA_VARIABLES = (
    "[markers] rigid: the segments are left out because cameras with a pose covariance make every marker "
    "depend on every other, and GTSAM's QR over a group of joined markers took minutes per solve (a 14-marker "
    "group, 80 frames, one variable camera: 15 s against 1.3 s without segments, and over 7 min at 160 "
    "frames, measured); the fast path, with the rig fixed, uses them")


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
                     n_velocity: int = 0, n_acceleration: int = 0) -> float:
    """log det of the Gauss-Newton information at ``solution``, in units m (p), m/s (v) and m/s^2 (a).

    From a QR Bayes net: log det Lambda = 2 sum log|diag R|. The graph's velocity
    variables are u = v dt (factors.v_key); Lambda_v = dt^2 Lambda_u, so each of the ``n_velocity``
    3-vectors adds 6 log dt; its accelerations are w = a dt^2 (factors.a_key), so each of the
    ``n_acceleration`` 3-vectors adds 12 log dt.
    """
    lin = graph.linearize(solution)
    bayes_net = lin.eliminateSequential(gtsam.Ordering.ColamdGaussianFactorGraph(lin), gtsam.EliminateQR)
    # QR's R may have negative diagonal entries (GTSAM's logDeterminant would take their log)
    log_det_R = sum(np.log(np.abs(np.diag(bayes_net.at(i).R()))).sum() for i in range(bayes_net.size()))
    return 2.0 * log_det_R + (6 * n_velocity + 12 * n_acceleration) * np.log(dt_s)


def log_evidence(graph: gtsam.NonlinearFactorGraph, solution: gtsam.Values, q: float, dt_s: float,
                 n_steps: int, n_velocity: int, model: str = "constant_velocity", n_acceleration: int = 0,
                 n_chains: int = 1) -> float:
    """Laplace log marginal likelihood of the noise level q (see :mod:`batgraph.graph.noise`; for constant
    acceleration the jerk PSD) at the optimum ``solution`` of a graph of ``n_chains`` marker chains."""
    logdet_post = posterior_logdet(graph, solution, dt_s, n_velocity, n_acceleration)
    return noise.laplace_log_evidence(graph.error(solution), logdet_post, q, dt_s, n_steps, model, n_chains)


def _solve_cost(session: Session, ideal: IdealObservations, model: MotionModel | dict[int, MotionModel],
                robust: str, robust_k: float, p_init: np.ndarray, v_init: np.ndarray, markers: np.ndarray,
                start: gtsam.Values | None, pairs: np.ndarray | None = None,
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int, ObservationFactors]:
    """Minimise the cost on ``ideal``'s observations of ``markers`` from ``start`` (default the initial track).

    model: one motion model, or one per marker index (any mix of models and noise levels).
    pairs: (S, 2) marker indices of segment-length factors (session.rigid_sigma_m; batgraph.graph.rigid),
    their lengths started at the median distance in the start where the start has none.
    Returns (graph, solution, iterations, its ObservationFactors).
    """
    F = p_init.shape[0]
    obs = ObservationFactors(session.rig, ideal, robust, robust_k)
    graph = factors.observation_graph(obs, markers, F)
    if isinstance(model, dict):
        motion = {m: MotionFactors(mm) for m, mm in model.items()}
    else:
        motion = MotionFactors(model)
    graph.push_back(factors.motion_graph(motion, p_init, markers))
    if start is None:
        start = factors.initial_values(obs, model, p_init, v_init, markers)
    if pairs is not None and len(pairs):
        graph.push_back(factors.segment_graph(pairs, session.rigid_sigma_m, F))
        start = gtsam.Values(start)
        factors.insert_lengths(start, pairs, F)
    solution, iterations = solve_batch(graph, start)
    return graph, solution, iterations, obs


def _velocities(values: gtsam.Values, markers: np.ndarray, n_frames: int, n_markers: int,
                dt_s: float) -> np.ndarray:
    """v of ``markers`` from ``values`` as (n_frames, n_markers, 3) [m/s] (stored as u = v dt); NaN elsewhere
    (and for markers whose model has no velocity)."""
    v = np.full((n_frames, n_markers, 3), np.nan)
    for m in markers:
        if values.exists(factors.v_key(int(m), 0)):
            for k in range(n_frames):
                v[k, m] = factors.velocity_mps(values.atPoint3(factors.v_key(int(m), k)), dt_s)
    return v


def _flags(obs: ObservationFactors, ideal: IdealObservations, solution: gtsam.Values,
           markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(outlier flags, rejected) (C, F, M) of every observation in ``ideal`` at ``solution``:
    |r|^2 > 13.8155 (as factors.outlier_flags) and > 25 (as factors.rejected)."""
    C, F, M = ideal.seen.shape
    r2 = factors.whitened_sq_residuals(obs.solved_rig(solution), ideal, factors.positions(solution, markers, F, M))
    r2 = np.nan_to_num(r2, nan=0.0)
    return r2 > factors.CHI2_2DOF_999, r2 > factors.REJECT_SQ_RESIDUAL


def run_smoother(session: Session, dense: DenseObservations, ideal: IdealObservations,
                 options: Options) -> Estimate:
    """The ``smoother`` method: batch LM over every frame, marginal covariances, outlier flags.

    ideal: ideal pixels (C, F, M, 2) and covariances (C, F, M, 2, 2) of ``dense`` (batgraph.measurement).
    Returns Estimate(method="smoother"): xyz_m (F, M, 3), cov_m2 (F, M, 3, 3), NaN for markers never
    triangulated; outlier (C, F, M) where |r|^2 > 13.8155 at the solution (plain Gaussian whitening).
    With a robust loss and ``options.outlier_rejection``, the solution is the final solve of the
    rejection schedule (module docstring); the observations it left out are among the flagged ones.
    Segment-length factors (``[markers] rigid``, batgraph.graph.rigid) enter the final solves on a fixed
    rig (the reference the fast path is tested against); with camera variables they are left out and
    info["segments_left_out"] says why (SEGMENTS_WITH_CAMERA_VARIABLES).
    """
    t0 = time.perf_counter()
    C, F, M = ideal.seen.shape
    dt = 1.0 / session.fps
    model_name, sigma_m, q = noise.motion_choice(session, options)
    if model_name == WINGBEAT and q is None:
        raise InputError(f'[motion] model = "{WINGBEAT}" needs the fast smoother with fixed cameras: the GTSAM '
                         "smoother (--solver gtsam, or cameras with pose covariances) has no oscillating model")
    tri = dlt_points(session.rig, ideal)
    p_init, v_init, estimated = factors.initial_track(tri, session.fps)
    markers = np.flatnonzero(estimated)
    pairs = rigid.segment_pairs(session.rigid, dense.markers)
    reject = options.outlier_rejection and options.robust != "none"
    info: dict = {"solver": "gtsam", "motion_model": model_name, "robust": options.robust,
                  "robust_k": options.robust_k, "outlier_rejection": reject,
                  "camera_variables": int(sum(c.pose_cov is not None for c in session.rig))}
    if model_name != WINGBEAT:  # the fast schedule's warning, and its q floor
        info.update(periodic_advice(tri, session.fps, model_name))
    if info["camera_variables"] and len(pairs):
        info["segments_left_out"] = SEGMENTS_WITH_CAMERA_VARIABLES
        pairs = pairs[:0]
    found = rigid.groups(pairs, estimated)
    pairs = pairs[np.concatenate([ids for _, ids in found])] if found else pairs[:0]
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    if len(markers) == 0:
        return Estimate("smoother", xyz, cov, np.zeros((C, F, M), bool), time.perf_counter() - t0, info)

    excluded = np.zeros((C, F, M), bool)
    start = None
    p_start, v_start = p_init, v_init
    if reject:  # steps 1-2: Cauchy from the initial track at q0, flags there
        clean, q0 = cleaning_motion(model_name, sigma_m, q, session)
        graph, start, iterations, obs = _solve_cost(session, ideal, motion_model(clean, dt, q0), CLEANING_LOSS,
                                                    options.robust_k, p_init, v_init, markers, None)
        excluded = factors.to_exclude(_flags(obs, ideal, start, markers)[1], ideal.seen)
        info["cleaning"] = {"loss": CLEANING_LOSS, "robust_k": options.robust_k, "iterations": iterations,
                            "n_flagged": int(excluded.sum())}
        if clean == "constant_velocity":
            info["cleaning"]["accel_psd_m2_s3"] = q0
        p_start = factors.positions(start, markers, F, M)
        v_start = _velocities(start, markers, F, M, dt) if clean != "random_walk" else v_init
    models = np.full(M, None, dtype=object)
    models_chosen = not (model_name == "random_walk" or q is not None)
    if not models_chosen:  # one given noise level
        models[markers], level = model_name, np.full(M, sigma_m if model_name == "random_walk" else q)
        info.update({"sigma_m": sigma_m} if model_name == "random_walk" else noise.q_figures(q))
        info["motion_model_per_marker"] = {dense.markers[m]: model_name for m in markers}
    else:  # step 3, per marker (cameras at their means when they are variables)
        candidates = AUTO_CANDIDATES if model_name == AUTO else (model_name,)
        models, level, selection = choose_model_per_marker(
            session.rig, factors.without_observations(ideal, excluded), p_init, v_init, markers, session.fps,
            options.robust, options.robust_k, candidates, p_start, v_start, progress=options.progress,
            groups=[members for members, _ in found], rule=noise.noise_rule(session, options),
            q_floor=flapping_floor(info))
        info.update(noise.model_figures(models, level, markers, dense.markers, selection, candidates,
                                        info.get("periodic_motion_hz")))
    model = {int(m): motion_model(models[m], dt, level[m]) for m in markers}
    if start is not None:  # the final solves start, in the chosen models' variables, from the noise search's
        if models_chosen:  # solutions where it ran (as the fast schedule), else from the cleaning solution
            p_start, v_start, _ = searched_start(selection["solution"], p_start, v_start, session.fps)
        cleaned, start = start, factors.initial_values(obs, model, p_start, v_start, markers)
        for c in np.flatnonzero(obs.variable):  # and its camera poses
            start.update(factors.pose_key(int(c)), cleaned.atPose3(factors.pose_key(int(c))))
    rounds = []
    n_rounds = REJECTION_ROUNDS if reject else 1
    for r in range(n_rounds):  # step 4: final solves until the flags are the excluded set
        graph, solution, iterations, obs = _solve_cost(session, factors.without_observations(ideal, excluded),
                                                       model, options.robust, options.robust_k, p_init, v_init,
                                                       markers, start, pairs)
        rounds.append(iterations)
        outlier, again = _flags(obs, ideal, solution, markers)
        again = factors.to_exclude(again, ideal.seen)
        if r == n_rounds - 1 or (again == excluded).all():
            break
        excluded, start = again, solution
    info["iterations"] = sum(rounds)
    if reject:
        info["iterations_per_round"] = rounds
        info["rejected"] = int(excluded.sum())
        info["rejection_converged"] = bool((again == excluded).all())
    info["final_error"] = float(graph.error(solution))
    xyz = factors.positions(solution, markers, F, M)
    keys = [factors.p_key(int(m), k) for k in range(F) for m in markers]
    cov[:, markers] = marginal_covariances(graph, solution, keys).reshape(F, len(markers), 3, 3)
    used = factors.without_observations(ideal, excluded)
    if len(pairs):
        lengths = [float(solution.atVector(factors.length_key(s))[0]) for s in range(len(pairs))]
        cov, info["depth_ambiguous_points"] = rigid.ambiguity_covariances(  # as the fast schedule (rigid.py)
            session.rig, used, p_init, v_init, models, level, session.fps,
            options.robust, options.robust_k,
            [{"pair": tuple(ab), "length_m": L} for ab, L in zip(pairs, lengths, strict=True)], xyz, cov)
        var = marginal_covariances(graph, solution, [factors.length_key(s) for s in range(len(pairs))])
        info["rigid_sigma_m"] = session.rigid_sigma_m
        excess = rigid.triangulated_excess(session.rig, ideal, pairs)
        info["segments"] = {f"{dense.markers[a]}-{dense.markers[b]}": {
            "length_m": float(solution.atVector(factors.length_key(s))[0]),
            "length_sigma_m": float(np.sqrt(var[s].ravel()[0])),
            "scatter_rms_m": float(np.sqrt(np.mean((np.linalg.norm(xyz[:, a] - xyz[:, b], axis=-1)
                                                    - solution.atVector(factors.length_key(s))[0]) ** 2))),
            "triangulated_excess_m": float(excess[s])}
            for s, (a, b) in enumerate(pairs)}
    cov, ends_figures = widen_ends(session.rig, used, p_init, models, level, session.fps, options.robust,
                                   options.robust_k, pairs, session.rigid_sigma_m, xyz,
                                   cov)  # the fast schedule's last step (ends.py), with the fast solver
    if ends_figures:
        info["track_ends"] = ends_figures
    return Estimate("smoother", xyz, cov, outlier, time.perf_counter() - t0, info)
