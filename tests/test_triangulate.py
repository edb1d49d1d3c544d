"""The triangulation baseline's covariance is the DLT's own: checked against the spread of many DLT
solutions of one point under known pixel noise (Monte Carlo), not against a formula."""

import numpy as np
import pytest

from batgraph.camera import Camera, Rig
from batgraph.geometry import pose
from batgraph.measurement import IdealObservations
from batgraph.motion import CHI2_3DOF_95
from batgraph.triangulate import triangulate_ideal

POINT_M = np.array([0.1, -0.05, 1.2])


def _rig() -> Rig:
    """Three views of POINT_M at 0.8, 2.5 and 6 m with different focal lengths (one skewed): the DLT
    weighs the far view by its depth squared, far from what its pixel noise is worth (see the test)."""
    cams = []
    for i, (dist_m, az_deg, f_px, skew) in enumerate([(0.8, 0.0, 800.0, 0.0), (2.5, 70.0, 1500.0, 0.0),
                                                        (6.0, 150.0, 3000.0, 40.0)]):
        az = np.radians(az_deg)
        center = POINT_M + dist_m * np.array([np.cos(az), np.sin(az), 0.3])
        R, t = pose.look_at(center, POINT_M, np.array([-np.sin(az), np.cos(az), 0.0]))
        K = np.array([[f_px, skew, 960.0], [0.0, 1.1 * f_px, 540.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(f"c{i}", (1920, 1080), K, np.zeros(5), pose.rvec_from_R(R), t))
    return Rig(cams)


def _noisy_views(rig: Rig, sigma_px: np.ndarray, n: int, rng: np.random.Generator) -> IdealObservations:
    """n noisy observations of POINT_M per camera, as n frames of one marker: uv (C, n, 1, 2)."""
    C = len(rig)
    uv = np.empty((C, n, 1, 2))
    cov = np.empty((C, n, 1, 2, 2))
    for c, cam in enumerate(rig):
        uv[c, :, 0] = cam.project(POINT_M[None])[0] + sigma_px[c] * rng.standard_normal((n, 2))
        cov[c] = sigma_px[c] ** 2 * np.eye(2)
    return IdealObservations(uv, cov)


def test_the_covariance_is_the_spread_of_the_dlt_solutions_not_the_maximum_likelihood_bound():
    rig = _rig()
    sigma_px = np.array([0.5, 1.0, 3.0])  # the near view is the sharp one
    n = 4000
    ideal = _noisy_views(rig, sigma_px, n, np.random.default_rng(7))
    xyz, cov = triangulate_ideal(rig, ideal)
    err = xyz[:, 0] - POINT_M  # (n, 3)
    empirical = np.cov(err.T)
    given = cov[:, 0].mean(axis=0)
    # The maximum-likelihood bound (sum_c J^T S^-1 J)^-1: what was given before; this scene must tell them apart.
    jacobians = [cam.ideal_jacobian_world(POINT_M) for cam in rig]
    info = sum(J.T @ J / s**2 for J, s in zip(jacobians, sigma_px, strict=True))
    bound = np.linalg.inv(info)
    scale = np.linalg.norm(empirical)
    assert np.linalg.norm(bound - empirical) > 0.5 * scale
    assert np.linalg.norm(given - empirical) < 0.1 * scale  # Monte Carlo error at n = 4000: ~3 %
    d2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov[:, 0]), err)
    assert np.mean(d2 <= CHI2_3DOF_95) == pytest.approx(0.95, abs=0.015)


def test_where_the_dlt_weights_are_the_inverse_noise_its_covariance_is_the_maximum_likelihood_bound():
    """The DLT weighs view c by W_c = depth_c^2 fx fy K2^-T K2^-1 (triangulate._first_order_cov): with pixel
    noise S_c proportional to W_c^-1 the sandwich reduces to (sum_c J^T S^-1 J)^-1."""
    rig = Rig(list(_rig())[:2])  # no skew, focal aspect 1.1: W_c = depth_c^2 diag(1.1, 1 / 1.1)
    depths = np.array([(cam.R @ POINT_M + cam.tvec)[2] for cam in rig])
    S = np.stack([np.diag([1 / 1.1, 1.1]) / d**2 for d in depths])  # (2, 2, 2) [px^2]
    uv = np.stack([cam.project(POINT_M[None])[0] for cam in rig])[:, None, None, :]
    _, cov = triangulate_ideal(rig, IdealObservations(uv, S[:, None, None]))
    info = sum(cam.ideal_jacobian_world(POINT_M).T @ np.linalg.inv(Sc) @ cam.ideal_jacobian_world(POINT_M)
               for cam, Sc in zip(rig, S, strict=True))
    np.testing.assert_allclose(cov[0, 0], np.linalg.inv(info), rtol=1e-8)
