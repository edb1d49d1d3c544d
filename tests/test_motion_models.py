"""The constant-acceleration (white-noise jerk) model and the per-marker choice of model ("auto").

Checks: batgraph.motion's Q and F against the continuous-time definition; the scaled state of
batgraph.graph.cost; the Laplace evidence of batgraph.graph.noise is the exact marginal likelihood of a
linear-Gaussian chain for every model (so evidences of different models compare: the gauge priors'
normalising constants are in it); and the smoother's choice picks constant velocity on tracks drawn
from that model and constant acceleration on smooth wing-like oscillations.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import cv_scene, observations_table, tiny_rig
from scipy.linalg import expm

from batgraph import triangulate
from batgraph.graph import cost, fast, noise, schedule
from batgraph.measurement import ideal_observations
from batgraph.motion import constant_acceleration_F, constant_acceleration_Q, constant_velocity_F, constant_velocity_Q
from batgraph.result import Options
from batgraph.session import PAPER_PHYSICS, MotionConfig, Session, dense_observations

FPS = 100.0
CANDIDATES = ["random_walk", "constant_velocity", "constant_acceleration"]


@pytest.mark.parametrize("dt", [1 / 1000, 1 / 120, 1 / 30])
def test_constant_acceleration_matches_continuous_white_jerk(dt):
    """F = expm(Ac dt) and Q = j int_0^dt expm(Ac s) G G^T expm(Ac s)^T ds for the chain p' = v, v' = a,
    a' = jerk (G = [0, 0, I]), by quadrature (Simpson, 2001 points: 1e-12 relative); per-axis det of Q
    = j^3 dt^9 / 8640; batgraph.graph.noise.logdet_Q agrees for every model."""
    j = 7.0
    Ac = np.kron(np.diag([1.0, 1.0], 1), np.eye(3))
    G = np.kron(np.array([[0.0], [0.0], [1.0]]), np.eye(3))
    np.testing.assert_allclose(constant_acceleration_F(dt), expm(Ac * dt), rtol=0, atol=1e-15)
    s = np.linspace(0.0, dt, 2001)
    Ft = np.array([constant_acceleration_F(t) for t in s])  # = expm(Ac t), checked above
    vals = Ft @ G @ G.T @ np.swapaxes(Ft, 1, 2)
    w = np.ones(len(s))
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    Q = j * np.einsum("k,kij->ij", w, vals) * (s[1] - s[0]) / 3
    np.testing.assert_allclose(constant_acceleration_Q(j, dt), Q, rtol=1e-10, atol=1e-12 * np.abs(Q).max())
    assert np.linalg.det(constant_acceleration_Q(j, dt)[::3, ::3]) == pytest.approx(j**3 * dt**9 / 8640, rel=1e-9)
    for name, Qf, level in [("constant_velocity", constant_velocity_Q, 3.0), ("constant_acceleration",
                                                                             constant_acceleration_Q, j)]:
        assert noise.logdet_Q(name, level, dt) == pytest.approx(np.linalg.slogdet(Qf(level, dt))[1], rel=1e-12)
    assert noise.logdet_Q("random_walk", 0.01, dt) == pytest.approx(3 * np.log(1e-4), rel=1e-12)


@pytest.mark.parametrize("name", ["constant_velocity", "constant_acceleration"])
def test_scaled_state_is_the_physical_one(name):
    """cost.scaled_motion is batgraph.motion's model in x = S [p, v, a], S = diag(I, dt I, dt^2 I):
    A = S F S^-1, Q1 = S Q(1) S, P0 = S^-1 diag(sigma^-2) S^-1 (the gauge priors 10 m, 10 m/s, 1000 m/s^2)."""
    dt = 1 / 120
    A, Q1, P0 = cost.scaled_motion(name, dt)
    order = cost.MOTION_ORDER[name]
    S = np.diag(np.repeat(dt ** np.arange(order + 1), 3))
    F, Q = (constant_velocity_F, constant_velocity_Q) if order == 1 else (constant_acceleration_F,
                                                                        constant_acceleration_Q)
    np.testing.assert_allclose(A, S @ F(dt) @ np.linalg.inv(S), atol=1e-12)
    np.testing.assert_allclose(Q1, S @ Q(1.0, dt) @ S, rtol=1e-12, atol=1e-30)
    sig = np.repeat([10.0, 10.0, 1000.0][:order + 1], 3)
    np.testing.assert_allclose(P0, np.linalg.inv(S) @ np.diag(sig**-2.0) @ np.linalg.inv(S), rtol=1e-12)
    assert noise.prior_logdet(name) == pytest.approx(np.linalg.slogdet(np.diag(sig**-2.0))[1], rel=1e-12)


@pytest.mark.parametrize("name", CANDIDATES)
def test_laplace_evidence_is_exact_on_a_linear_gaussian_chain(name):
    """A chain of 15 frames with the model's prior (gauge priors and one transition per step, spec units)
    and linear position measurements z_k = p_k + N(0, r^2 I) (a gap of 4 frames): the Laplace formula
    (noise.laplace_log_evidence with the dense optimum's cost and log det) plus the data's own normaliser
    -n/2 log(2 pi r^2) equals the exact log N(z; H mu, H Sigma H^T + R), to 1e-6 (measured <= 3e-8: the
    dense prior covariance has 10 m gauge variances beside 2 mm noise). Exact for every model,
    the gauge priors' normalising constants included, so evidences of different models compare."""
    rng = np.random.default_rng(2)
    dt, F, r = 1 / FPS, 15, 0.002
    level = {"random_walk": 0.01, "constant_velocity": 30.0, "constant_acceleration": 3e4}[name]
    order = cost.MOTION_ORDER[name]
    d = 3 * (order + 1)
    Fm = [np.eye(3), constant_velocity_F(dt), constant_acceleration_F(dt)][order]
    Q = [level**2 * np.eye(3), constant_velocity_Q(level, dt), constant_acceleration_Q(level, dt)][order]
    P0 = np.diag(np.repeat([10.0, 10.0, 1000.0][:order + 1], 3) ** 2.0)
    mu0 = np.concatenate([rng.normal(0, 0.1, 3), np.zeros(d - 3)])
    # the prior as stacked whitened residuals r(X) = L X - c over X = (x_0, ..., x_F-1)
    W0, Wq = np.linalg.inv(np.linalg.cholesky(P0)), np.linalg.inv(np.linalg.cholesky(Q))
    L = np.zeros((F * d, F * d))
    L[:d, :d] = W0
    for k in range(1, F):
        L[k * d:(k + 1) * d, (k - 1) * d:k * d] = -Wq @ Fm
        L[k * d:(k + 1) * d, k * d:(k + 1) * d] = Wq
    c = np.zeros(F * d)
    c[:d] = W0 @ mu0
    seen = np.ones(F, bool)
    seen[6:10] = False
    H = np.zeros((3 * seen.sum(), F * d))
    for i, k in enumerate(np.flatnonzero(seen)):
        H[3 * i:3 * i + 3, k * d:k * d + 3] = np.eye(3)
    z = np.cumsum(rng.normal(0, 0.01, (F, 3)), axis=0)[seen].ravel() + rng.normal(0, r, H.shape[0])
    Lam_post = L.T @ L + H.T @ H / r**2
    x = np.linalg.solve(Lam_post, L.T @ c + H.T @ z / r**2)
    E = 0.5 * np.sum((L @ x - c) ** 2) + 0.5 * np.sum((H @ x - z) ** 2) / r**2
    laplace = noise.laplace_log_evidence(E, np.linalg.slogdet(Lam_post)[1], level, dt, F - 1, model=name)
    laplace -= 0.5 * len(z) * np.log(2 * np.pi * r**2)
    # the prior's moments by propagation (no inverse of the ill-conditioned L^T L): x_k ~ N(m_k, P_k),
    # cov(x_l, x_k) = F^(l-k) P_k
    m, P = [mu0], [P0]
    for _ in range(1, F):
        m.append(Fm @ m[-1])
        P.append(Fm @ P[-1] @ Fm.T + Q)
    Sigma = np.zeros((F * d, F * d))
    for k in range(F):
        C = P[k]
        for l in range(k, F):
            Sigma[l * d:(l + 1) * d, k * d:(k + 1) * d] = C
            Sigma[k * d:(k + 1) * d, l * d:(l + 1) * d] = C.T
            C = Fm @ C
    mean = np.concatenate(m)
    Szz = H @ Sigma @ H.T + r**2 * np.eye(len(z))
    e = z - H @ mean
    exact = -0.5 * (e @ np.linalg.solve(Szz, e) + np.linalg.slogdet(2 * np.pi * Szz)[1])
    assert laplace == pytest.approx(exact, abs=1e-6)


def wing_scene(n_frames: int = 80, seed: int = 0) -> tuple[Session, np.ndarray]:
    """Three markers on smooth oscillations (wing-like): 6 Hz flaps of 4-8 cm amplitude about a point drifting
    at 0.5 m/s, sampled at 100 fps (17 frames per beat), 4 cameras, 0.5 px noise. Returns (session, truth)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / FPS
    amp = np.array([0.04, 0.06, 0.08])
    phase = rng.uniform(0, 2 * np.pi, 3)
    truth = np.zeros((n_frames, 3, 3))
    truth[..., 0] = 0.5 * t[:, None] - 0.2
    truth[..., 1] = amp * np.sin(2 * np.pi * 6.0 * t[:, None] + phase)
    truth[..., 2] = 0.5 * amp * np.cos(2 * np.pi * 6.0 * t[:, None] + phase)
    rig = tiny_rig(4, size_wh=(1280, 720), focal_px=900.0)
    obs = observations_table(rig, truth)
    obs[["u", "v"]] += rng.normal(0, 0.5, (len(obs), 2))
    return Session("wing", FPS, rig, obs, MotionConfig(model="auto", **PAPER_PHYSICS), pixel_sigma_px=0.5), truth


def _auto(session: Session):
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    return schedule.run_smoother_fast(session, dense, ideal, Options(progress=False)), dense


def test_auto_picks_constant_velocity_on_constant_velocity_tracks():
    """Tracks drawn from the constant-velocity model (q = 3 and 100 m^2/s^3, 80 frames): "auto" (the default
    since the twentieth session: a session that states no model gets it) keeps constant velocity for every marker
    (measured evidence margins 42, 106, 69 nats)."""
    session, _, _, _ = cv_scene([3.0, 100.0, 30.0], n_frames=80, seed=4)
    assert MotionConfig(**PAPER_PHYSICS).model == "auto"  # the default
    session = dataclasses.replace(session, motion=MotionConfig(model="auto", **PAPER_PHYSICS))
    est, dense = _auto(session)
    ev = est.info["log_evidence_per_marker"]
    assert all(e["constant_velocity"] > e["constant_acceleration"] for e in ev.values()), ev
    assert est.info["motion_model"] == "auto"
    assert set(est.info["motion_model_per_marker"].values()) == {"constant_velocity"}
    assert set(est.info["accel_psd_m2_s3"]) == set(dense.markers) and est.info["jerk_psd_m2_s5"] == {}


def test_auto_picks_constant_acceleration_on_wing_like_tracks():
    """Smooth 6 Hz oscillations (wing_scene): "auto" picks constant acceleration for every marker, and
    the answer is the constant-acceleration smoother's with the reported jerk PSDs (markers are
    independent), closer to the truth than constant velocity alone (measured margins 20, 40, 60 nats;
    RMSE 0.68 vs 0.81 mm)."""
    session, truth = wing_scene()
    est, dense = _auto(session)
    ev = est.info["log_evidence_per_marker"]
    assert all(e["constant_acceleration"] > e["constant_velocity"] for e in ev.values()), ev
    assert set(est.info["motion_model_per_marker"].values()) == {"constant_acceleration"}
    ca_session = dataclasses.replace(session, motion=MotionConfig("constant_acceleration", **PAPER_PHYSICS))
    ca = schedule.run_smoother_fast(ca_session, dense, ideal_observations(session.rig, dense, 0.5),
                                    Options(progress=False))
    assert ca.info["jerk_psd_m2_s5"] == est.info["jerk_psd_m2_s5"]
    np.testing.assert_allclose(est.xyz_m, ca.xyz_m, rtol=0, atol=1e-12)
    cv = schedule.run_smoother_fast(session, dense, ideal_observations(session.rig, dense, 0.5),
                                Options(motion_model="constant_velocity", progress=False))
    rmse = {k: float(np.sqrt(np.mean((e.xyz_m - truth) ** 2))) for k, e in (("auto", est), ("cv", cv))}
    assert rmse["auto"] < rmse["cv"]


def test_filters_keep_constant_velocity_for_auto():
    """The filters cannot choose per marker from the whole sequence: "auto" (and constant acceleration)
    filter with constant velocity at the causal q, and say what was asked."""
    session, _ = wing_scene(n_frames=10)
    for asked in ("auto", "constant_acceleration"):
        model, info = noise.filter_motion(session, Options(motion_model=asked))
        assert model.name == "constant_velocity" and info["motion_model_requested"] == asked
        assert info["accel_psd_m2_s3"] == noise.causal_accel_psd(session)


def _into_camera_scene():
    """One marker accelerating (30 m/s^2) straight towards camera 1, its last 12 of 40 frames (100 fps)
    seen by that camera alone: the single-view rays all meet at the camera's centre, and a loose
    constant-acceleration prior extrapolates the track through it. Returns (rig, ideal, p_init, v_init)."""
    rng = np.random.default_rng(0)
    F = 40
    rig = tiny_rig(4, size_wh=(1280, 720), focal_px=900.0)
    c0 = rig.cameras[0].center_world
    t = np.arange(F) / FPS
    start = np.array([0.0, 0.0, 0.1])
    u = (c0 - start) / np.linalg.norm(c0 - start)
    wobble = 0.02 * np.stack([np.sin(20 * t), np.cos(20 * t), 0 * t], -1)
    truth = (start + (2.0 * t + 15.0 * t**2)[:, None] * u + wobble)[:, None, :]
    obs = observations_table(rig, truth)
    obs[["u", "v"]] += rng.normal(0, 0.5, (len(obs), 2))
    obs = obs[~((obs.frame >= F - 12) & (obs.camera != "cam1"))]
    session = Session("into_camera", FPS, rig, obs, MotionConfig(**PAPER_PHYSICS), pixel_sigma_px=0.5)
    ideal = ideal_observations(rig, dense_observations(session), 0.5)
    p, v, _ = cost.initial_track(triangulate.dlt_points(rig, ideal), FPS)
    return rig, ideal, p, v


def test_solve_stops_when_the_track_runs_into_a_camera():
    """Constant acceleration at a loose j = 1e7 m^2/s^5 on _into_camera_scene: the cost has no minimum in
    front of camera 1, only an infimum at its centre (depth -> 0+), which Levenberg-Marquardt used to
    approach for all its 200 iterations (measured; on the flight sample most markers at j >= 1e6, the
    cause of the slow "auto" search). The solve stops once an observed point is nearer the camera than
    1e-3 of its closest start depth (98 iterations), flagged at_camera and not converged, at a cost within
    1e-4 of 1000 iterations'; the noise search gives such a level no Laplace score (-inf). A tight j
    (1e4) keeps an interior minimum: converged, not flagged."""
    rig, ideal, p, v = _into_camera_scene()
    _, _, info = fast.solve_fast(rig, ideal, p, "constant_acceleration", 1e7, FPS, "huber", v_init=v,
                                 covariances=False)
    assert info["at_camera"][0] and not info["converged"][0]
    assert info["iterations"] < 150
    c0 = rig.cameras[0].center_world
    assert np.linalg.norm(info["position"][:, 0] - c0, axis=-1).min() < 3e-3  # the camera is ~3 m away
    _, _, long = fast.solve_fast(rig, ideal, p, "constant_acceleration", 1e7, FPS, "huber", v_init=v,
                                 covariances=False, max_iterations=1000)
    assert info["cost"] == pytest.approx(long["cost"], abs=1e-4)
    _, _, tight = fast.solve_fast(rig, ideal, p, "constant_acceleration", 1e4, FPS, "huber", v_init=v,
                                  covariances=False)
    assert tight["converged"][0] and not tight["at_camera"][0] and tight["iterations"] < 40
    sol = fast.solve_levels(rig, ideal, p, "constant_acceleration", np.array([[1e4], [1e7]]), FPS, v_start=v)
    np.testing.assert_array_equal(sol["at_camera"][:, 0], [False, True])
    level, info_n = fast.choose_noise_per_marker(rig, ideal, p, v, np.array([0]), FPS, "huber", 2.0,
                                                 model="constant_acceleration")
    assert np.isfinite(info_n["log_evidence"][0]) and level[0] < 1e7
