"""The fast smoother (batgraph.graph.fast) reaches the same optimum, covariances and log-determinant as
an independent solver of the same cost: a dense Gauss-Newton on the full stacked problem written here
(finite-difference Jacobians, spec units p [m], v [m/s] and a [m/s^2], dense inverse), and the GTSAM
smoother; for the random walk, constant velocity and constant acceleration.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from conftest import observations_table, tiny_rig, tiny_scene

from batgraph.camera import Rig
from batgraph.graph import factors, fast, schedule
from batgraph.graph.smoother import posterior_logdet, run_smoother
from batgraph.measurement import ideal_observations
from batgraph.motion import constant_acceleration_F, constant_acceleration_Q, constant_velocity_Q
from batgraph.result import Options
from batgraph.session import PAPER_PHYSICS, MotionConfig, Session, dense_observations
from batgraph.triangulate import triangulate_ideal

FPS = 100.0
SIGMA_M = 0.004  # random-walk std per frame [m]; the scene moves ~0.6 m/s * 0.01 s
ACCEL_PSD = 20.0  # constant-velocity q [m^2/s^3]
JERK_PSD = 1e4  # constant-acceleration j [m^2/s^5]
MODELS = ["random_walk", "constant_velocity", "constant_acceleration"]


def make_session(n_frames: int = 24, seed: int = 3) -> Session:
    """4 cameras (mild distortion), 4 markers, noisy pixels with random weights, gaps and 2 outliers.

    m0: unobserved on frames 0-3 (before its first view) and single-view on 4-5; m1: a gap of 8
    unobserved frames in the middle; m2: two planted 40 px outliers; m3: seen by one camera only,
    so it is never triangulated and must come back NaN.
    """
    rng = np.random.default_rng(seed)
    rig = tiny_rig(4, size_wh=(1280, 720), focal_px=900.0, dist=np.array([-0.05, 0.01, 0.0, 0.0, 0.0]))
    xyz = tiny_scene(n_frames, 4, seed)
    markers = [f"m{j}" for j in range(4)]
    obs = observations_table(rig, xyz, markers)
    drop = ((obs.marker == "m0") & (obs.frame <= 3)) | ((obs.marker == "m0") & obs.frame.isin([4, 5])
                                                        & (obs.camera != "cam1"))
    drop |= (obs.marker == "m1") & obs.frame.between(9, 16)
    drop |= (obs.marker == "m3") & (obs.camera != "cam2")
    obs = obs[~drop].reset_index(drop=True)
    obs["weight"] = rng.uniform(0.5, 1.0, len(obs))
    obs[["u", "v"]] += rng.normal(0, 0.7, (len(obs), 2))
    out = obs.index[(obs.marker == "m2") & (obs.camera == "cam3") & obs.frame.isin([7, 15])]
    obs.loc[out, "u"] += 40.0
    return Session("fast", FPS, rig, obs, MotionConfig(model="random_walk", sigma_m=SIGMA_M, **PAPER_PHYSICS,
                                                      accel_psd_m2_s3=ACCEL_PSD),
                   pixel_sigma_px=0.7, marker_names=markers)


def dense_reference(session: Session, ideal, p_init: np.ndarray, model: str, robust: str, k: float = 2.0):
    """Gauss-Newton with backtracking on the whole stacked problem of the spec, dense linear algebra.

    Variables per estimated marker and frame: p [m] (and v [m/s], a [m/s^2]); Jacobians of the projections by
    central differences (h = 1e-6 m), robust losses by IRLS weights. Returns xyz (F, M, 3),
    cov (F, M, 3, 3), logdet of the full Hessian, cost.
    """
    C, F, M = ideal.seen.shape
    est = np.isfinite(p_init).all(axis=(0, 2))
    ms = np.nonzero(est)[0]
    d = {"random_walk": 3, "constant_velocity": 6, "constant_acceleration": 9}[model]
    n = len(ms) * F * d
    dt = 1 / session.fps

    def var(j, f):  # index of marker slot j, frame f
        return (j * F + f) * d

    obs = [(c, f, m) for c in range(C) for f in range(F) for m in ms if ideal.seen[c, f, m]]
    Linv = {o: np.linalg.inv(np.linalg.cholesky(ideal.cov_px2[o])) for o in obs}
    if model == "random_walk":
        Wm, Fm = np.eye(3) / SIGMA_M, np.eye(3)
        W0 = np.eye(3) / 10.0
    elif model == "constant_velocity":
        Wm = np.linalg.inv(np.linalg.cholesky(constant_velocity_Q(ACCEL_PSD, dt)))
        Fm = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
        W0 = np.eye(6) / 10.0
    else:
        Wm = np.linalg.inv(np.linalg.cholesky(constant_acceleration_Q(JERK_PSD, dt)))
        Fm = constant_acceleration_F(dt)
        W0 = np.diag([0.1] * 6 + [1e-3] * 3)  # 10 m, 10 m/s, 1000 m/s^2
    z = np.zeros(n)
    for j, m in enumerate(ms):
        v = np.gradient(p_init[:, m], axis=0) * session.fps
        for f in range(F):
            z[var(j, f):var(j, f) + 3] = p_init[f, m]
            if d >= 6:
                z[var(j, f) + 3:var(j, f) + 6] = v[f]
            if d == 9:
                z[var(j, f) + 6:var(j, f) + 9] = np.gradient(v, axis=0)[f] * session.fps
    mu0 = {j: np.r_[p_init[0, m], np.zeros(d - 3)] for j, m in enumerate(ms)}

    def proj(c, p):
        return session.rig[c].project(p, distort=False)

    def linear_rows():  # motion and prior rows: (A rows over all vars, offset) so r = A z - b
        rows, b = [], []
        for j in range(len(ms)):
            for f in range(F - 1):
                A = np.zeros((d, n))
                A[:, var(j, f + 1):var(j, f + 1) + d] = Wm
                A[:, var(j, f):var(j, f) + d] = -Wm @ Fm
                rows.append(A)
                b.append(np.zeros(d))
            A = np.zeros((d, n))
            A[:, var(j, 0):var(j, 0) + d] = W0
            rows.append(A)
            b.append(W0 @ mu0[j])
        return np.vstack(rows), np.concatenate(b)

    Alin, blin = linear_rows()

    def loss(r2):  # GTSAM mEstimator loss and weight, written out independently of fast.robust_loss
        r = np.sqrt(r2)
        if robust == "huber" and r > k:
            return k * r - 0.5 * k * k, k / r
        return 0.5 * r2, 1.0

    def evaluate(z, with_jac):
        cost = 0.5 * np.sum((Alin @ z - blin) ** 2)
        H = Alin.T @ Alin
        g = Alin.T @ (Alin @ z - blin)
        for (c, f, m) in obs:
            j = int(np.nonzero(ms == m)[0][0])
            i0 = var(j, f)
            p = z[i0:i0 + 3]
            r = Linv[(c, f, m)] @ (proj(c, p) - ideal.uv_px[c, f, m])
            rho, w = loss(r @ r)
            cost += float(rho)
            if with_jac:
                J = np.zeros((2, 3))
                for a in range(3):
                    h = np.zeros(3)
                    h[a] = 1e-6
                    J[:, a] = (proj(c, p + h) - proj(c, p - h)) / 2e-6
                Jw = Linv[(c, f, m)] @ J
                H[i0:i0 + 3, i0:i0 + 3] += w * Jw.T @ Jw
                g[i0:i0 + 3] += w * Jw.T @ r
        return cost, H, g

    cost, H, g = evaluate(z, True)
    for _ in range(400):  # plain IRLS converges linearly (rate ~0.65 here): iterate to a 1e-12 m step
        dz = np.linalg.solve(H, -g)
        t = 1.0
        while True:
            c_new = evaluate(z + t * dz, False)[0]
            if c_new <= cost or t < 1e-6:
                break
            t /= 2
        z = z + t * dz
        done = np.abs(t * dz).max() < 1e-12
        cost, H, g = evaluate(z, True)
        if done:
            break
    Sigma = np.linalg.inv(H)
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    for j, m in enumerate(ms):
        for f in range(F):
            i0 = var(j, f)
            xyz[f, m] = z[i0:i0 + 3]
            cov[f, m] = Sigma[i0:i0 + 3, i0:i0 + 3]
    return xyz, cov, np.linalg.slogdet(H)[1], cost


def gtsam_graph(session: Session, ideal, model: str, robust: str):
    """The smoother's graph (batgraph.graph.factors), its initial values and the estimated markers."""
    F = ideal.seen.shape[1]
    tri, _ = triangulate_ideal(session.rig, ideal)
    p_init, v_init, estimated = factors.initial_track(tri, session.fps)
    markers = np.flatnonzero(estimated)
    obs = factors.ObservationFactors(session.rig, ideal, robust, 2.0)
    mm = factors.MotionModel(model, 1 / session.fps, sigma_m=SIGMA_M, accel_psd_m2_s3=ACCEL_PSD,
                             jerk_psd_m2_s5=JERK_PSD)
    graph = factors.observation_graph(obs, markers, F)
    graph.push_back(factors.motion_graph(factors.MotionFactors(mm), p_init, markers))
    return graph, factors.initial_values(obs, mm, p_init, v_init, markers), markers


def gtsam_marginals(graph, values, markers, F: int, M: int, model: str):
    """gtsam.Marginals of every p[m, k] (F, M, 3, 3) and the log det of the Gauss-Newton Hessian (spec
    units, batgraph.graph.smoother.posterior_logdet) of the graph linearised at ``values``."""
    cov = np.full((F, M, 3, 3), np.nan)
    marg = gtsam.Marginals(graph, values)
    for k in range(F):
        for m in markers:
            cov[k, m] = marg.marginalCovariance(factors.p_key(int(m), k))
    n_velocity = len(markers) * F if model != "random_walk" else 0
    n_acceleration = len(markers) * F if model == "constant_acceleration" else 0
    return cov, posterior_logdet(graph, values, 1 / FPS, n_velocity, n_acceleration)


def gtsam_reference(session: Session, ideal, model: str, robust: str):
    """The smoother's graph solved by GTSAM's LM to a standstill (no relative or absolute tolerance: it
    runs until the error stops decreasing), then its marginals. Returns xyz, cov, logdet, error, and
    (graph, markers) for evaluating it elsewhere."""
    C, F, M = ideal.seen.shape
    graph, initial, markers = gtsam_graph(session, ideal, model, robust)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(0.0)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(1000)
    sol = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    cov, logdet = gtsam_marginals(graph, sol, markers, F, M, model)
    return factors.positions(sol, markers, F, M), cov, logdet, graph.error(sol), graph, markers


def as_values(xyz: np.ndarray, velocity: np.ndarray | None, markers,
              acceleration: np.ndarray | None = None) -> gtsam.Values:
    """The fast path's solution as GTSAM Values (p and, as the model has them, v and a keys)."""
    values = gtsam.Values()
    for m in markers:
        for k in range(xyz.shape[0]):
            values.insert(factors.p_key(int(m), k), xyz[k, m])
            if velocity is not None:  # the graph's velocity variable is u = v dt [m per frame]
                values.insert(factors.v_key(int(m), k), velocity[k, m] / FPS)
            if acceleration is not None:  # ... and its acceleration variable w = a dt^2 [m per frame^2]
                values.insert(factors.a_key(int(m), k), acceleration[k, m] / FPS**2)
    return values


@pytest.fixture(scope="module")
def scene():
    return make_problem()


def make_problem():
    """(session, dense, ideal, p_init) of :func:`make_session` (the tests' scene; test_rigid uses it too)."""
    session = make_session()
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    tri, _ = triangulate_ideal(session.rig, ideal)
    return session, dense, ideal, factors.initial_track(tri, session.fps)[0]


def _level(model):
    return {"random_walk": SIGMA_M, "constant_velocity": ACCEL_PSD, "constant_acceleration": JERK_PSD}[model]


def _rel_cov_error(cov, cov_ref):
    """Largest |cov - cov_ref| relative to each 3x3 block's largest entry (off-diagonals can be ~0)."""
    scale = np.abs(cov_ref).max(axis=(-1, -2), keepdims=True)
    return np.nanmax(np.abs(cov - cov_ref) / scale)


@pytest.mark.parametrize("model", MODELS)
def test_fast_equals_dense_gauss_newton(scene, model):
    """Least squares (robust none): positions to 1e-6 m, covariances to 1e-6 relative, logdet to 1e-6,
    against the dense solver in the spec's units (p m, v m/s, a m/s^2: checks the fast path's internal
    v dt, a dt^2 scaling).

    Both stop on steps < 1e-10 m (the dense one < 1e-12 m); measured <= 7e-10 m, 2e-10 relative,
    4e-10 (the reference's finite-difference Jacobians, ~3e-10 relative, dominate).
    """
    session, dense, ideal, p_init = scene
    xyz, cov, info = fast.solve_fast(session, ideal, p_init, model, _level(model), FPS, "none", 2.0)
    xyz_ref, cov_ref, logdet_ref, cost_ref = dense_reference(session, ideal, p_init, model, "none")
    assert np.isnan(xyz[:, 3]).all() and np.isnan(cov[:, 3]).all()  # m3: never triangulated
    assert np.isfinite(xyz[:, :3]).all()
    np.testing.assert_allclose(xyz[:, :3], xyz_ref[:, :3], rtol=0, atol=1e-6)
    assert _rel_cov_error(cov[:, :3], cov_ref[:, :3]) < 1e-6
    assert abs(info["logdet"] - logdet_ref) < 1e-6
    assert abs(info["cost"] - cost_ref) < 1e-10 * cost_ref
    assert info["converged"][:3].all()


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
def test_fast_equals_gtsam(scene, model, robust):
    """Against GTSAM on the smoother's own graph (batgraph.graph.factors).

    Same optimum: positions to 1e-6 m of GTSAM's LM run to a standstill, and the fast solution's GTSAM
    error no larger than at GTSAM's (to rounding, 1e-12 relative). Same marginals: gtsam.Marginals and
    GTSAM's log det evaluated at the fast solution equal the fast path's to 1e-6 relative / 1e-6
    (measured <= 1e-13, <= 3e-12). Against GTSAM's own stopping point the robust covariances differ
    more, 1e-5 relative / 1e-5 (measured <= 4e-7, 7e-7): GTSAM's IRLS converges linearly and stands
    still ~1e-8 m from the minimiser in the weakly determined directions, where an IRLS weight k/|r|
    moves by ~1e-5 per 1e-7 m; the fast path converges quadratically to a 1e-10 m step.
    """
    session, dense, ideal, p_init = scene
    C, F, M = ideal.seen.shape
    xyz, cov, info = fast.solve_fast(session, ideal, p_init, model, _level(model), FPS, robust, 2.0)
    xyz_ref, cov_ref, logdet_ref, err_ref, graph, markers = gtsam_reference(session, ideal, model, robust)
    np.testing.assert_allclose(xyz, xyz_ref, rtol=0, atol=1e-6)
    mine = as_values(xyz, info["velocity"], markers, info["acceleration"])
    assert graph.error(mine) <= err_ref * (1 + 1e-12)
    assert abs(graph.error(mine) - info["cost"]) < 1e-12 * info["cost"]
    cov_at_fast, logdet_at_fast = gtsam_marginals(graph, mine, markers, F, M, model)
    assert _rel_cov_error(cov[:, :3], cov_at_fast[:, :3]) < 1e-6
    assert abs(info["logdet"] - logdet_at_fast) < 1e-6
    assert _rel_cov_error(cov[:, :3], cov_ref[:, :3]) < (1e-6 if robust == "none" else 1e-5)
    assert abs(info["logdet"] - logdet_ref) < (1e-6 if robust == "none" else 1e-5)


def _assert_same_levels(a: dict, b: dict) -> None:
    """Two smoothers' info chose the same q and j per marker, to rounding: 1e-6 relative (the search's
    secant steps follow the slopes, corrected by the scores' differences over points 0.05-0.2 decade apart,
    which two solvers of one cost reach to rounding (~1e-6 nats: the two solvers stop ~1e-7 m apart in weak
    directions), and the evidence's flat peak magnifies that: measured up to 1.5e-7; 3e-8 with Brent's
    search on the scores alone)."""
    for key in ("accel_psd_m2_s3", "jerk_psd_m2_s5"):
        x, y = a.get(key) or {}, b.get(key) or {}
        assert x.keys() == y.keys()
        np.testing.assert_allclose([x[k] for k in x], [y[k] for k in x], rtol=1e-6)


@pytest.mark.parametrize(("model", "robust", "bound_cov"), [("random_walk", "none", 1e-6),
                                                          ("random_walk", "huber", 1e-4),
                                                          ("constant_velocity", "huber", 1e-4),
                                                          ("constant_acceleration", "huber", 1e-4),
                                                          ("auto", "huber", 1e-4)])
def test_run_smoother_fast_matches_run_smoother(scene, model, robust, bound_cov):
    """The ``smoother`` method both ways, as ``reconstruct`` calls it: same initialisation, same q (or
    jerk PSD j, or per-marker model with "auto") chosen from the data (no q in the session: the same
    marginal-likelihood search must pick the same ones, to rounding: _assert_same_levels), positions to
    1e-6 m, the same outlier flags.

    Covariances: 1e-6 relative for least squares (measured 2e-10); for Huber 1e-4 (measured 1.3e-5),
    because the GTSAM smoother stops at a relative error decrease of 1e-12, ~1.5e-7 m from the
    minimiser in weak directions, which moves the IRLS weights by ~1e-5 (see test_fast_equals_gtsam).
    """
    session, dense, ideal, _ = scene
    session = dataclasses.replace(session, motion=dataclasses.replace(session.motion, accel_psd_m2_s3=None))
    opt = Options(motion_model=model, robust=robust, progress=False)
    a = schedule.run_smoother_fast(session, dense, ideal, opt)
    b = run_smoother(session, dense, ideal, opt)
    assert a.method == b.method == "smoother" and a.info["solver"] == "fast"
    np.testing.assert_allclose(a.xyz_m, b.xyz_m, rtol=0, atol=1e-6)
    assert _rel_cov_error(a.cov_m2, b.cov_m2) < bound_cov
    np.testing.assert_array_equal(a.outlier, b.outlier)
    if model != "random_walk":
        assert a.info["accel_psd_source"] == b.info["accel_psd_source"] == "data"
        assert a.info["motion_model_per_marker"] == b.info["motion_model_per_marker"]
        _assert_same_levels(a.info, b.info)
    if model == "auto":  # every estimated marker has a model, each the better of its two evidences
        assert set(a.info["motion_model_per_marker"]) == {"m0", "m1", "m2"}
        for name, chosen in a.info["motion_model_per_marker"].items():
            ev = a.info["log_evidence_per_marker"][name]
            assert ev[chosen] == max(ev.values())


def test_rig_with_pose_covariance_goes_to_gtsam(scene):
    """A camera with a pose covariance makes the markers dependent: the fast path hands over to GTSAM."""
    session, dense, ideal, _ = scene
    cams = [dataclasses.replace(c) for c in session.rig]
    cams[0].pose_cov = np.diag([1e-6] * 3 + [1e-6] * 3)
    session = dataclasses.replace(session, rig=Rig(cams))
    est = schedule.run_smoother_fast(session, dense, ideal, Options(motion_model="random_walk", progress=False))
    assert est.info["solver"] == "gtsam" and est.info["camera_variables"] == 1


def test_marginals_match_dense_inverse():
    """The backward recursion gives the diagonal blocks of H^-1 and log det H of a random SPD block-
    tridiagonal H (6x6 blocks, 7 frames, 2 markers): exact algebra, so 1e-10 relative (measured 1e-15)."""
    rng = np.random.default_rng(1)
    F, M, d = 7, 2, 6
    B = rng.normal(size=(d, d))
    D = np.empty((F, M, d, d))
    for f in range(F):
        for m in range(M):
            X = rng.normal(size=(d, d))
            D[f, m] = X @ X.T + 3 * np.abs(B).sum() * np.eye(d)  # diagonally dominant -> SPD
    Sigma, logdet = fast.marginals(D, B)
    for m in range(M):
        H = np.zeros((F * d, F * d))
        for f in range(F):
            H[f * d:(f + 1) * d, f * d:(f + 1) * d] = D[f, m]
            if f + 1 < F:
                H[(f + 1) * d:(f + 2) * d, f * d:(f + 1) * d] = B
                H[f * d:(f + 1) * d, (f + 1) * d:(f + 2) * d] = B.T
        Hi = np.linalg.inv(H)
        for f in range(F):
            np.testing.assert_allclose(Sigma[f, m], Hi[f * d:(f + 1) * d, f * d:(f + 1) * d], rtol=1e-10,
                                       atol=1e-10 * np.abs(Hi).max())
        assert abs(logdet[m] - np.linalg.slogdet(H)[1]) < 1e-10


def test_huber_downweights_planted_outliers(scene):
    """The two 40 px outliers of m2 are flagged (chi-square 2 DOF 99.9 %) and Huber keeps m2's track
    closer to the other inliers than plain least squares does (its IRLS weight there is ~2/|r| << 1).

    Rejection off: this is Huber alone (with rejection this stiff random walk also excludes 12 inlier
    views of m1 next to its gap, measured; the schedule is tested below)."""
    session, dense, ideal, p_init = scene
    est = schedule.run_smoother_fast(session, dense, ideal, Options(motion_model="random_walk", robust="huber",
                                                                outlier_rejection=False))
    c = session.rig.index("cam3")
    assert est.outlier[c, 7, 2] and est.outlier[c, 15, 2]
    assert est.outlier.sum() <= 4  # the two planted ones, and at most two chance 99.9 % exceedances
    xyz_none, _, _ = fast.solve_fast(session, ideal, p_init, "random_walk", SIGMA_M, FPS, "none")
    truth = tiny_scene(len(dense.frames), 4, 3)
    err_huber = np.linalg.norm(est.xyz_m[[7, 15], 2] - truth[[7, 15], 2], axis=-1).max()
    err_none = np.linalg.norm(xyz_none[[7, 15], 2] - truth[[7, 15], 2], axis=-1).max()
    assert err_huber < err_none


def single_view_mislabels() -> tuple[Session, list[tuple[str, int, str]]]:
    """make_session with two mislabels, each the only view of its (frame, marker): the detection of
    another marker in the same camera and frame, so the initial track (>= 2 views) ignores it.

    m0 frame 5 (single-view, cam1) takes m2's cam1 pixels; m2 frame 11 is left to cam1 alone, which
    sees m0's pixels there. Returns (session, [(camera, frame, marker) of each mislabel]).
    """
    session = make_session()
    obs = session.observations
    obs = obs[~((obs.marker == "m2") & (obs.frame == 11) & (obs.camera != "cam1"))].reset_index(drop=True)
    planted = [("cam1", 5, "m0", "m2"), ("cam1", 11, "m2", "m0")]
    for cam, frame, marker, other in planted:
        at = (obs.camera == cam) & (obs.frame == frame)
        obs.loc[at & (obs.marker == marker), ["u", "v"]] = obs.loc[at & (obs.marker == other), ["u", "v"]].to_numpy()
    return dataclasses.replace(session, observations=obs), [p[:3] for p in planted]


def mislabels_with_q_from_data():
    """:func:`single_view_mislabels` with no given q (chosen from the data): (session, planted, dense, ideal)."""
    session, planted = single_view_mislabels()
    session = dataclasses.replace(session, motion=dataclasses.replace(session.motion, accel_psd_m2_s3=None))
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    return session, planted, dense, ideal


@pytest.mark.parametrize("model", ["random_walk", "constant_velocity", "auto"])
def test_rejection_schedule_matches_run_smoother(model):
    """Default options (Huber + outlier rejection; constant velocity with q chosen from the data) on
    two single-view mislabels: both paths exclude the same set D (converged rounds, so D is the
    |r|^2 > 25 set at the solution through factors.to_exclude), which holds both mislabels, flag the
    same observations, pick the same q, and agree on positions to 1e-6 m (measured 1.3e-7 m random
    walk, 4e-9 m constant velocity; GTSAM stops at a 1e-12 relative error decrease) and covariances
    to 1e-4 relative (measured 1.2e-5, 2.4e-7; as the Huber case above). D: 15 (random walk, which
    also drops inliers of m1 next to its gap) and 4 (the two mislabels and m2's two 40 px outliers).
    Without the schedule the answer moves by > 1 mm (measured 52 mm, 18 mm), so each check can fail."""
    session, planted, dense, ideal = mislabels_with_q_from_data()
    opt = Options(motion_model=model, progress=False)
    a = schedule.run_smoother_fast(session, dense, ideal, opt)
    b = run_smoother(session, dense, ideal, opt)
    D = [factors.to_exclude(np.nan_to_num(factors.whitened_sq_residuals(session.rig, ideal, e.xyz_m)) >
                            factors.REJECT_SQ_RESIDUAL, ideal.seen) for e in (a, b)]
    where = tuple(np.array([(session.rig.index(c), int(np.searchsorted(dense.frames, f)), dense.markers.index(m))
                            for c, f, m in planted]).T)
    assert a.info["rejection_converged"] and b.info["rejection_converged"]
    assert a.info["rejected"] == b.info["rejected"] == D[0].sum()
    np.testing.assert_array_equal(D[0], D[1])
    assert D[0][where].all() and a.outlier[where].all()
    np.testing.assert_array_equal(a.outlier, b.outlier)
    np.testing.assert_allclose(a.xyz_m, b.xyz_m, rtol=0, atol=1e-6)
    assert _rel_cov_error(a.cov_m2, b.cov_m2) < 1e-4
    if model != "random_walk":
        assert a.info["motion_model_per_marker"] == b.info["motion_model_per_marker"]
        _assert_same_levels(a.info, b.info)
    off = schedule.run_smoother_fast(session, dense, ideal, Options(motion_model=model, outlier_rejection=False,
                                                                   progress=False))
    assert np.nanmax(np.abs(off.xyz_m - b.xyz_m)) > 1e-3


def test_rejects_bad_input(scene):
    session, dense, ideal, p_init = scene
    with pytest.raises(ValueError, match="model"):
        fast.solve_fast(session, ideal, p_init, "jerk", 1.0, FPS)
    with pytest.raises(ValueError, match="p_init"):
        fast.solve_fast(session, ideal, p_init[:-1], "random_walk", SIGMA_M, FPS)


@pytest.mark.parametrize("model", ["constant_velocity", "constant_acceleration"])
def test_solve_levels_equals_solve_fast_per_candidate(scene, model):
    """The noise search's batch (candidates x markers as one Levenberg-Marquardt run, no covariances) gives
    each candidate what solve_fast gives alone with that row of noise levels: positions to 1e-8 m, cost
    and log det to 1e-8 relative, and with ``slope`` the evidence's slope (fast.evidence_slope) to 1e-8
    relative and the same log det (the columns are independent; only rounding differs, measured <= 1e-12)."""
    session, dense, ideal, p_init = scene
    M = p_init.shape[1]
    s = _level(model) / ACCEL_PSD
    levels = s * np.array([[ACCEL_PSD] * M, [2.0] * M, np.geomspace(0.5, 500.0, M)])
    batch = fast.solve_levels(session.rig, ideal, p_init, model, levels, FPS, "huber", 2.0, slope=True)
    small = fast.solve_levels(session.rig, ideal, p_init, model, levels, FPS, "huber", 2.0, max_rows=1)
    assert small["slope"] is None
    for k, row in enumerate(levels):
        xyz, cov, info = fast.solve_fast(session, ideal, p_init, model, row, FPS, "huber", 2.0,
                                         covariances=False)
        assert cov is None and info["slope_per_marker"] is None
        _, _, sloped = fast.solve_fast(session, ideal, p_init, model, row, FPS, "huber", 2.0, covariances=False,
                                       slope=True)
        np.testing.assert_allclose(sloped["logdet_per_marker"], info["logdet_per_marker"], rtol=1e-12)
        np.testing.assert_allclose(batch["slope"][k], sloped["slope_per_marker"], rtol=1e-8, atol=1e-8)
        for got in (batch, small):  # one group of 3 candidates, and one candidate per group
            np.testing.assert_allclose(got["position"][k], xyz, rtol=0, atol=1e-8)
            for key in ("velocity", "acceleration"):
                if info[key] is not None:
                    np.testing.assert_allclose(got[key][k], info[key], rtol=0, atol=1e-6 * FPS ** (key != "velocity"))
            np.testing.assert_allclose(got["cost"][k], info["cost_per_marker"], rtol=1e-8)
            np.testing.assert_allclose(got["logdet"][k], info["logdet_per_marker"], rtol=1e-8)
        _, _, with_cov = fast.solve_fast(session, ideal, p_init, model, row, FPS, "huber", 2.0)
        np.testing.assert_allclose(info["logdet_per_marker"], with_cov["logdet_per_marker"], rtol=1e-10)


def test_tiled_observations_keep_frame_order(scene):
    """_Observations.tile: K copies of every marker as columns m + j M', rows sorted by frame."""
    session, dense, ideal, p_init = scene
    obs = fast._observations(session.rig, ideal, np.isfinite(p_init).all(axis=(0, 2)))
    t = obs.tile(3)
    assert t.n_markers == 3 * obs.n_markers and len(t.f) == 3 * len(obs.f)
    assert np.all(np.diff(t.f) >= 0) and np.all(np.diff(t.cell) >= 0)
    for j in range(3):
        rows = (t.m >= j * obs.n_markers) & (t.m < (j + 1) * obs.n_markers)
        np.testing.assert_array_equal(t.m[rows] - j * obs.n_markers, obs.m)
        np.testing.assert_array_equal(t.uv[:, rows], obs.uv)


def test_rows_built_once_equal_rows_built_per_solve(scene):
    """observation_rows + _rows_of (the noise search builds the rows once) give the rows _observations builds
    for any subset of markers, and solve_fast the same answer with them, bit for bit."""
    session, dense, ideal, p_init = scene
    rows = fast.observation_rows(session.rig, ideal)
    M = p_init.shape[1]
    for keep in (np.ones(M, bool), np.arange(M) % 2 == 0, np.arange(M) == M - 1):
        a, b = fast._rows_of(rows, keep), fast._observations(session.rig, ideal, keep)
        for key in ("f", "m", "cam", "uv", "Linv", "P", "behind_px"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert (a.n_markers, a.n_frames) == (b.n_markers, b.n_frames)
    p = np.where((np.arange(M) % 2 == 0)[None, :, None], p_init, np.nan)  # every other marker estimated
    x0, _, i0 = fast.solve_fast(session, ideal, p, "constant_velocity", ACCEL_PSD, FPS, covariances=False)
    x1, _, i1 = fast.solve_fast(session, ideal, p, "constant_velocity", ACCEL_PSD, FPS, covariances=False,
                                rows=rows)
    np.testing.assert_array_equal(x0, x1)
    np.testing.assert_array_equal(i0["logdet_per_marker"], i1["logdet_per_marker"])
    with pytest.raises(ValueError, match="rows hold"):
        fast._rows_of(rows, np.ones(M + 1, bool))


def test_logdet_alone_equals_marginals():
    """fast.logdet (forward sweep only, what the q search uses) equals the log det of fast.marginals."""
    rng = np.random.default_rng(2)
    F, M, d = 9, 3, 6
    B = rng.normal(size=(M, d, d))
    X = rng.normal(size=(F, M, d, d))
    D = X @ np.swapaxes(X, -1, -2) + 3 * np.abs(B).sum(axis=(1, 2))[None, :, None, None] * np.eye(d)
    np.testing.assert_allclose(fast.logdet(D, B), fast.marginals(D, B)[1], rtol=1e-12)


def test_fast_paths_do_not_import_gtsam():
    """The numpy solvers, the noise rules and the cost import without GTSAM (a 0.1-0.3 s import);
    only the GTSAM reference modules load it."""
    import subprocess
    import sys

    code = ("import sys, batgraph.graph.fast, batgraph.graph.fast_filter, batgraph.graph.noise, "
            "batgraph.graph.cost; assert 'gtsam' not in sys.modules, 'gtsam imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("model", ["constant_velocity", "auto"])
def test_final_solve_starts_from_the_search(model, monkeypatch):
    """The rejection schedule's first final round starts from the noise search's solutions at the chosen
    levels (fast.searched_start), which solved the same observations: it reaches the answer the cleaning
    solution's start reaches (positions to 1e-6 m, covariances to 1e-4 relative) in fewer iterations.
    Measured on the two-mislabel scene: first round 1 against 5 iterations, with either model."""
    session, _, dense, ideal = mislabels_with_q_from_data()
    opt = Options(motion_model=model, progress=False)
    a = schedule.run_smoother_fast(session, dense, ideal, opt)
    monkeypatch.setattr(schedule, "searched_start", lambda solution, p, v, fps: (p, v, None))
    b = schedule.run_smoother_fast(session, dense, ideal, opt)
    print("first round: from the search", a.info["iterations_per_round"], "from the cleaning solution",
          b.info["iterations_per_round"])
    np.testing.assert_allclose(a.xyz_m, b.xyz_m, rtol=0, atol=1e-6)
    assert _rel_cov_error(a.cov_m2, b.cov_m2) < 1e-4
    assert a.info["iterations_per_round"][0] < b.info["iterations_per_round"][0]
