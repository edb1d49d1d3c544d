"""The gauge of a rig (batgraph.geometry.gauge): similarity fit, its directions, its removal."""

import numpy as np
import pytest

from batgraph.geometry import gauge, pose


def _rig(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n cameras 1.5-2.5 m from the origin, looking at it (cam_from_world arrays)."""
    R, t = [], []
    for _ in range(n):
        c = rng.normal(size=3)
        c *= rng.uniform(1.5, 2.5) / np.linalg.norm(c)
        Rcw, tcw = pose.look_at(c, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        R.append(Rcw)
        t.append(tcw)
    return np.array(R), np.array(t)


def _perturb(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right-perturb every world_from_cam pose by its block of xi (6C,): T exp(xi) to first order."""
    R_wc, c = pose.world_from_cam(R, t)
    xi = xi.reshape(-1, 6)
    R_new = np.stack([R_wc[i] @ pose.R_from_rvec(xi[i, :3]) for i in range(len(R))])
    c_new = c + (R_wc @ xi[:, 3:, None])[..., 0]
    return pose.cam_from_world(R_new, c_new)


def _apply(R, t, s, Rs, ts):
    return pose.similarity_cam_from_world(R, t, s, Rs, ts)


@pytest.mark.parametrize("n", [2, 3, 5])
def test_fit_recovers_a_known_similarity_exactly(n):
    """b = a moved by (s, R, t): the fit returns it to 1e-10, from centres and orientations (2 cameras too)."""
    rng = np.random.default_rng(n)
    R, t = _rig(rng, n)
    s0, R0, t0 = 1.3, pose.R_from_rvec([0.4, -0.2, 1.0]), np.array([0.5, -1.0, 2.0])
    Rb, tb = _apply(R, t, s0, R0, t0)
    s, Rf, tf = gauge.fit_similarity(R, t, Rb, tb)
    assert abs(s - s0) < 1e-10 and np.abs(Rf - R0).max() < 1e-10 and np.abs(tf - t0).max() < 1e-10


def test_gauge_directions_match_a_finite_similarity():
    """Moving the world by a small similarity theta moves the rig's tangent by G theta (first order:
    the difference at step 1e-6 is below 1e-10)."""
    R, t = _rig(np.random.default_rng(0), 4)
    G = gauge.gauge_directions(R, t)
    for k in range(7):
        th = np.zeros(7)
        th[k] = 1e-6
        Rb, tb = _apply(R, t, float(np.exp(th[6])), pose.R_from_rvec(th[:3]), th[3:6])
        d = gauge.rig_difference(Rb, tb, R, t)
        assert np.abs(d - 1e-6 * G[:, k]).max() < 1e-10


def test_projection_is_what_refitting_does():
    """A rig perturbed by xi (1e-5) and fitted back onto the unperturbed one moves by P xi (first order;
    measured difference 1e-10 against 1e-5 of the perturbation); P G = 0 and P P = P."""
    rng = np.random.default_rng(1)
    R, t = _rig(rng, 5)
    L = gauge.default_lever_m(pose.world_from_cam(R, t)[1])
    P = gauge.gauge_projection(R, t, L)
    G = gauge.gauge_directions(R, t)
    assert np.abs(P @ G).max() < 1e-10 and np.abs(P @ P - P).max() < 1e-10
    xi = 1e-5 * rng.normal(size=30)
    Ra, ta = _perturb(R, t, xi)
    s, Rs, ts = gauge.fit_similarity(Ra, ta, R, t, lever_m=L)
    d = gauge.rig_difference(*_apply(Ra, ta, s, Rs, ts), R, t)
    assert np.abs(d - P @ xi).max() < 1e-3 * np.abs(xi).max()


def test_chi2_ignores_the_gauge_and_counts_the_rest():
    """A pure similarity has chi2 0; a perturbation drawn from cov has chi2 ~ chi2(6C - 7): mean of 2000 draws
    within 3 % of 23 (measured 23.0), whatever the gauge in which the covariance is given."""
    rng = np.random.default_rng(2)
    R, t = _rig(rng, 5)
    L = gauge.default_lever_m(pose.world_from_cam(R, t)[1])
    A = rng.normal(size=(30, 30)) * np.tile([1e-3] * 3 + [2e-3] * 3, 5)
    cov = A @ A.T
    # the same uncertainty in another gauge: camera 0 held fixed (add gauge motions that cancel it)
    G = gauge.gauge_directions(R, t)
    T = np.eye(30) - G @ np.linalg.lstsq(G[:6], np.eye(30)[:6], rcond=None)[0]
    cov0 = T @ cov @ T.T
    assert np.abs(cov0[:6]).max() < 1e-15
    chi2_sim, dof = gauge.gauge_free_chi2(G @ rng.normal(size=7) * 1e-3, cov, R, t, L)
    assert dof == 23 and chi2_sim < 1e-6
    draws = rng.multivariate_normal(np.zeros(30), cov, size=2000)
    for c in (cov, cov0):
        vals = [gauge.gauge_free_chi2(x, c, R, t, L)[0] for x in draws]
        assert abs(np.mean(vals) / 23 - 1) < 0.03
