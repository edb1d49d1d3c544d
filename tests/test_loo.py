"""The leave-one-frame-out noise rule ([motion] noise_rule = "loo"; batgraph.graph.noise.loo_log_predictive).

Checks: the closed form per (frame, marker) equals the leave-out computed the long way on the dense
Gauss-Newton system (the cell's observation information taken out, the posterior re-solved, the left-out
pixels' predictive density evaluated); the fast solver's score equals refitting without the frame's
observations (nonlinear, to the linearisation's accuracy); the search with the rule picks each marker's
best-scoring level; and the rule is read, written and refused like any other session key.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import cv_scene

from batgraph import triangulate
from batgraph.errors import InputError
from batgraph.graph import cost, fast, noise
from batgraph.measurement import IdealObservations
from batgraph.pipeline import run_methods
from batgraph.result import Options
from batgraph.session import read_session, write_session

FPS = 100.0


def _scene(n_frames: int = 24):
    """Two constant-velocity markers (q 2 and 40 m^2/s^3), 4 cameras, 0.5 px; marker 1 seen by one camera
    on frames 9-12 (a single-view stretch, where a frame's own pixels leave the depth to the prior)."""
    session, dense, ideal, truth = cv_scene([2.0, 40.0], n_frames, seed=3, fps=FPS)
    uv, cov = ideal.uv_px.copy(), ideal.cov_px2.copy()
    uv[1:, 9:13, 1] = np.nan
    return session, IdealObservations(uv, cov), truth


def _track(session, ideal):
    p0, v0, _ = cost.initial_track(triangulate.dlt_points(session.rig, ideal), FPS)
    return p0, v0


def _dense_loo(session, ideal, xyz, q, marker):
    """The leave-one-frame-out score of one marker the long way: the dense Gauss-Newton system of its
    chain at the solution xyz (F, 3) (states [p, v dt], as the fast solver's), each observed frame's
    pixel information taken out, the leave-out mean and covariance solved densely, and the left-out
    whitened pixels' Gaussian log density (constant dropped) summed over frames."""
    F = xyz.shape[0]
    prob = fast._Problem("constant_velocity", np.array([q]), FPS, "none", 2.0)
    d = prob.d
    H = np.zeros((F * d, F * d))
    for k in range(F):
        H[k * d:(k + 1) * d, k * d:(k + 1) * d] += (prob.AtQiA[0] if k < F - 1 else 0) + (prob.Qi[0] if k else 0)
        if k:
            H[k * d:(k + 1) * d, (k - 1) * d:k * d] = prob.B[0]
            H[(k - 1) * d:k * d, k * d:(k + 1) * d] = prob.B[0].T
    H[:d, :d] += prob.P0
    sub = IdealObservations(ideal.uv_px[:, :, [marker]], ideal.cov_px2[:, :, [marker]])
    obs = fast._observations(session.rig, sub, np.array([True]))
    r, J = obs.residuals(xyz[:, None, :], jacobian=True)  # (2, n), (2, 3, n)
    rows_of = [np.flatnonzero(obs.f == k) for k in range(F)]
    Jk = [np.concatenate([J[0][:, rows].T, J[1][:, rows].T]) for rows in rows_of]  # (2 n_k, 3)
    rk = [np.concatenate([r[0][rows], r[1][rows]]) for rows in rows_of]
    for k in range(F):
        H[k * d:k * d + 3, k * d:k * d + 3] += Jk[k].T @ Jk[k]
    total = 0.0
    for k in range(F):
        if not len(rk[k]):
            continue
        Hout = H.copy()
        Hout[k * d:k * d + 3, k * d:k * d + 3] -= Jk[k].T @ Jk[k]
        rhs = np.zeros(F * d)
        rhs[k * d:k * d + 3] = Jk[k].T @ rk[k]  # the gradient the cell's pixels leave behind at the solution
        step = np.linalg.solve(Hout, rhs)
        r_out = rk[k] + Jk[k] @ step[k * d:k * d + 3]  # the pixels' residual at the leave-out mean
        S = np.eye(len(rk[k])) + Jk[k] @ np.linalg.inv(Hout)[k * d:k * d + 3, k * d:k * d + 3] @ Jk[k].T
        total += -0.5 * r_out @ np.linalg.solve(S, r_out) - 0.5 * np.linalg.slogdet(S)[1]
    return total


@pytest.mark.parametrize("q", [0.3, 40.0, 3000.0])
def test_closed_form_equals_the_dense_leave_out(q):
    """solve_fast's loo_per_marker equals the dense leave-one-frame-out computation at the same solution,
    to 1e-8 relative, for a smooth, a matched and a loose prior (single-view frames included)."""
    session, ideal, _ = _scene()
    p0, v0 = _track(session, ideal)
    xyz, _, info = fast.solve_fast(session.rig, ideal, p0, "constant_velocity", q, FPS, "none", v_init=v0, loo=True)
    for m in range(2):
        ref = _dense_loo(session, ideal, xyz[:, m], q, m)
        assert info["loo_per_marker"][m] == pytest.approx(ref, rel=1e-8)


def test_closed_form_equals_refitting_without_the_frame():
    """Refit the marker with one frame's pixels removed (the nonlinear solve), predict the removed pixels
    there (their linearised Gaussian predictive density): the per-frame closed-form score agrees to
    1e-3 relative (measured <= 6e-4, largest at the track's last frame: the projection's curvature over
    the leave-out step, which the closed form linearises)."""
    session, ideal, _ = _scene()
    p0, v0 = _track(session, ideal)
    q = 40.0
    xyz, Sigma, info = fast.solve_fast(session.rig, ideal, p0, "constant_velocity", q, FPS, "none", v_init=v0)
    obs = fast._observations(session.rig, ideal, np.array([True, True]))
    x = np.concatenate([xyz, info["velocity"] / FPS], axis=-1)
    _, lin = fast._Problem("constant_velocity", q, FPS, "none", 2.0).evaluate(x, x[0], obs, jacobian=True)
    for k in (0, 5, 10, 23):  # an end, the middle, inside the single-view stretch (marker 1), the other end
        for m in (0, 1):
            uv = ideal.uv_px.copy()
            uv[:, k, m] = np.nan
            left = IdealObservations(uv, ideal.cov_px2)
            x_out, S_out, _ = fast.solve_fast(session.rig, left, p0, "constant_velocity", q, FPS, "none",
                                              v_init=v0, p_start=xyz)
            rows = np.flatnonzero((obs.f == k) & (obs.m == m))
            r, J = obs.residuals(x_out, jacobian=True)
            rk = np.concatenate([r[0][rows], r[1][rows]])
            Jk = np.concatenate([J[0][:, rows].T, J[1][:, rows].T])
            S = np.eye(len(rk)) + Jk @ S_out[k, m] @ Jk.T
            brute = -0.5 * rk @ np.linalg.solve(S, rk) - 0.5 * np.linalg.slogdet(S)[1]
            A = np.zeros((3, 3))  # the closed form of this one cell, from the full solve
            A[fast._IU[0], fast._IU[1]] = lin.Hw[k, m]
            A[fast._IU[1], fast._IU[0]] = lin.Hw[k, m]
            mine = noise.loo_log_predictive(lin.rr[k, m:m + 1], lin.g[k, m:m + 1], A[None], Sigma[k, m][None])[0]
            assert mine == pytest.approx(brute, rel=1e-3)


def test_search_picks_the_best_scoring_level():
    """choose_noise_per_marker with rule "loo": each marker's chosen q scores at least as well as every
    decade of the grid (solve_fast's loo_per_marker at that q), and the rule is named in its info."""
    session, ideal, _ = _scene(40)
    p0, v0 = _track(session, ideal)
    q, info = fast.choose_noise_per_marker(session.rig, ideal, p0, v0, np.array([0, 1]), FPS, "huber", 2.0,
                                           rule="loo")
    assert "leave-one-frame-out" in info["rule"]
    best = fast.solve_fast(session.rig, ideal, p0, "constant_velocity", q, FPS, "huber", v_init=v0,
                           loo=True)[2]["loo_per_marker"]
    for decade in range(-2, 7):
        other = fast.solve_fast(session.rig, ideal, p0, "constant_velocity", 10.0**decade, FPS, "huber",
                                v_init=v0, loo=True)[2]["loo_per_marker"]
        assert np.all(best >= other - 1e-6)
    np.testing.assert_allclose(info["log_evidence"], best, rtol=1e-9)
    with pytest.raises(ValueError, match="rule"):
        fast.choose_noise_per_marker(session.rig, ideal, p0, v0, np.array([0]), FPS, "huber", 2.0, rule="aic")


def test_smoother_both_solvers_agree_under_the_rule():
    """The smoother method with noise_rule "loo" on the fast path and through GTSAM: the same q per marker
    (both search with the fast solver's score) and positions within 1e-6 m; the rule is in the figures."""
    session = cv_scene([2.0, 40.0], 30, seed=3, fps=FPS)[0]
    opts = Options(progress=False, noise_rule="loo")
    a = run_methods(session, ["smoother"], opts).estimates["smoother"]
    b = run_methods(session, ["smoother"], dataclasses.replace(opts, solver="gtsam")).estimates["smoother"]
    assert "leave-one-frame-out" in a.info["accel_psd_rule"]
    for name in a.info["accel_psd_m2_s3"]:
        assert a.info["accel_psd_m2_s3"][name] == pytest.approx(b.info["accel_psd_m2_s3"][name], rel=1e-6)
    np.testing.assert_allclose(a.xyz_m, b.xyz_m, atol=1e-6)


def test_session_reads_writes_and_refuses_the_rule(make_session_folder):
    """[motion] noise_rule round-trips through session.toml (only when not the default) and a wrong value
    is one InputError line naming the file and key."""
    folder = make_session_folder()
    session = read_session(folder)
    assert session.motion.noise_rule == "evidence"
    out = folder.parent / "loo_session"
    write_session(dataclasses.replace(session, motion=dataclasses.replace(session.motion, noise_rule="loo")), out)
    assert 'noise_rule = "loo"' in (out / "session.toml").read_text()
    assert read_session(out).motion.noise_rule == "loo"
    text = (out / "session.toml").read_text().replace('noise_rule = "loo"', 'noise_rule = "aic"')
    (out / "session.toml").write_text(text)
    with pytest.raises(InputError, match=r"session.toml \[motion\] noise_rule: 'aic'"):
        read_session(out)
