"""batgraph.geometry: pose conversions, pinhole projection and its Jacobians, distortion, each against an
independent reference (GTSAM, OpenCV, finite differences) on random cameras.

Finite differences are central with step h; their truncation error is ~ h^2 f''' / 6, so each bound below
sits well above the measured error and well below the size of the entries it checks.
"""

from __future__ import annotations

import subprocess
import sys

import cv2
import gtsam
import numpy as np
import pytest

from batgraph.geometry import distortion, pinhole, pose

DIST = np.array([-0.25, 0.07, 0.0005, -0.0003, -0.008])  # GoPro-like (k1, k2, p1, p2, k3)


def _random_camera(rng: np.random.Generator, skew: float = 1.5):
    """K (3, 3) with skew, cam_from_world R (3, 3), t (3,) [m] of a camera ~3 m from the origin looking
    near it, and 50 world points (50, 3) [m] around the origin (all in front of it)."""
    K = np.array([[rng.uniform(700, 1200), skew, rng.uniform(600, 700)],
                  [0.0, rng.uniform(700, 1200), rng.uniform(300, 400)], [0.0, 0.0, 1.0]])
    centre = rng.normal(size=3)
    centre *= 3.0 / np.linalg.norm(centre)
    R, t = pose.look_at(centre, rng.uniform(-0.2, 0.2, 3), rng.normal(size=3))
    return K, R, t, rng.uniform(-0.5, 0.5, (50, 3))


def _exp_right(R_wc: np.ndarray, t_wc: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """world_from_cam * Exp(xi) by GTSAM (its own tangent convention), as (R_wc, t_wc)."""
    T = gtsam.Pose3(gtsam.Rot3(R_wc), t_wc).compose(gtsam.Pose3.Expmap(xi))
    return T.rotation().matrix(), np.asarray(T.translation())


# ----- poses -------------------------------------------------------------------------------------
def test_pose_round_trips_and_gtsam_inverse():
    """cam_from_world -> world_from_cam -> back is the identity (measured 2e-15; bound 1e-12); the
    world_from_cam pose equals GTSAM's Pose3 inverse of cam_from_world (measured 2e-16; bound 1e-12) and
    maps camera points back to the world (measured 8e-16 m); Rodrigues rvec -> R -> rvec returns the
    vector (angles up to 3 rad: measured 1.5e-15; bound 1e-9)."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, R, t, xyz = _random_camera(rng)
        R_wc, t_wc = pose.world_from_cam(R, t)
        R2, t2 = pose.cam_from_world(R_wc, t_wc)
        assert np.abs(R2 - R).max() < 1e-12 and np.abs(t2 - t).max() < 1e-12
        inv = gtsam.Pose3(gtsam.Rot3(R), t).inverse()
        assert np.abs(inv.rotation().matrix() - R_wc).max() < 1e-12
        assert np.abs(np.asarray(inv.translation()) - t_wc).max() < 1e-12
        back = pose.transform_points(R_wc, t_wc, pose.transform_points(R, t, xyz))
        assert np.abs(back - xyz).max() < 1e-12
        rvec = rng.normal(size=3)
        rvec *= rng.uniform(0.01, 3.0) / np.linalg.norm(rvec)
        assert np.abs(pose.rvec_from_R(pose.R_from_rvec(rvec)) - rvec).max() < 1e-9
    # batched: a stack of poses converts as each one does
    Rs = np.stack([pose.R_from_rvec(rng.normal(size=3)) for _ in range(4)])
    ts = rng.normal(size=(4, 3))
    Rb, tb = pose.world_from_cam(Rs, ts)
    for k in range(4):
        Rk, tk = pose.world_from_cam(Rs[k], ts[k])
        assert np.abs(Rb[k] - Rk).max() == 0 and np.abs(tb[k] - tk).max() < 1e-15


def test_rotation_angle_and_look_at():
    """rotation_angle of Exp(theta a) R against R is theta (bound 1e-9 rad). look_at puts the target on the
    optical axis (at the principal point: bound 1e-9 px) with world-up (+z) up in the image."""
    rng = np.random.default_rng(1)
    R = pose.R_from_rvec(rng.normal(size=3))
    for theta in (1e-3, 0.5, 2.0, 3.0):
        axis = rng.normal(size=3)
        dR = pose.R_from_rvec(theta * axis / np.linalg.norm(axis))
        assert abs(pose.rotation_angle(dR @ R, R) - theta) < 1e-9
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    centre, target = np.array([3.0, -2.0, 1.0]), np.array([0.1, 0.2, 0.3])
    R, t = pose.look_at(centre, target, np.array([1.0, 0.0, 0.0]))
    uv = pinhole.project(np.stack([target, target + [0, 0, 0.1]]), K, R, t)
    assert np.abs(uv[0] - K[:2, 2]).max() < 1e-9
    assert uv[1, 1] < uv[0, 1]  # a point above the target is higher in the image (smaller v)
    assert np.abs(pose.world_from_cam(R, t)[1] - centre).max() < 1e-12


def test_similarity_keeps_projections_and_scales_the_pose_tangent():
    """x' = s R x + t applied to the points and (similarity_cam_from_world) to the camera leaves every
    projection unchanged (raw pixels with distortion; measured 1.1e-13 px, bound 1e-8 px).
    similarity_pose_cov: a GTSAM right perturbation xi of world_from_cam becomes diag(1, 1, 1, s, s, s) xi
    after the similarity (to first order: |xi| ~ 1e-6, measured 1.4e-9 relative to |xi|; bound 1e-6, where
    an unscaled translation would be off by s - 1 = 0.7)."""
    rng = np.random.default_rng(2)
    K, R_c, t_c, xyz = _random_camera(rng)
    s, Rs, ts = 1.7, pose.R_from_rvec(rng.normal(size=3)), rng.normal(size=3)
    R2, t2 = pose.similarity_cam_from_world(R_c, t_c, s, Rs, ts)
    xyz2 = s * xyz @ Rs.T + ts
    uv, uv2 = pinhole.project(xyz, K, R_c, t_c, DIST), pinhole.project(xyz2, K, R2, t2, DIST)
    assert np.isfinite(uv).all() and np.abs(uv2 - uv).max() < 1e-8

    xi = 1e-6 * rng.normal(size=6)
    Rw, tw = pose.world_from_cam(R_c, t_c)
    Rp, tp = _exp_right(Rw, tw, xi)  # perturbed, then moved by the similarity
    Rp2, tp2 = pose.world_from_cam(*pose.similarity_cam_from_world(*pose.cam_from_world(Rp, tp), s, Rs, ts))
    T2 = gtsam.Pose3(gtsam.Rot3(pose.world_from_cam(R2, t2)[0]), pose.world_from_cam(R2, t2)[1])
    xi2 = gtsam.Pose3.Logmap(T2.between(gtsam.Pose3(gtsam.Rot3(Rp2), tp2)))
    S = np.sqrt(np.diag(pose.similarity_pose_cov(np.eye(6), s)))
    assert np.abs(xi2 - S * xi).max() < 1e-6 * np.abs(xi).max()
    assert np.abs(S - [1, 1, 1, s, s, s]).max() == 0


def test_colmap_to_gtsam_tangent_jacobian_by_finite_differences():
    """pose_cov_jacobian = d(GTSAM Logmap(T0^-1 T) of world_from_cam) / d(COLMAP tangent [dq, dt]) of
    cam_from_world, where COLMAP (Ceres' quaternion manifold) turns R into Exp(2 dq) R and t into t + dt.
    Central differences, step 1e-6: measured 4e-10; bound 1e-7 (entries up to 2 |t| = 6)."""
    rng = np.random.default_rng(3)
    _, R, t, _ = _random_camera(rng)
    T0 = gtsam.Pose3(gtsam.Rot3(pose.world_from_cam(R, t)[0]), pose.world_from_cam(R, t)[1])

    def gtsam_tangent(d: np.ndarray) -> np.ndarray:
        R_p = pose.R_from_rvec(2.0 * d[:3]) @ R  # quaternion increment d (half angle) on the left
        R_wc, t_wc = pose.world_from_cam(R_p, t + d[3:])
        return gtsam.Pose3.Logmap(T0.between(gtsam.Pose3(gtsam.Rot3(R_wc), t_wc)))

    h = 1e-6
    fd = np.stack([(gtsam_tangent(h * e) - gtsam_tangent(-h * e)) / (2 * h) for e in np.eye(6)], axis=1)
    J = pose.pose_cov_jacobian(R, t)
    assert np.abs(J - fd).max() < 1e-7, np.abs(J - fd).max()
    cov = np.diag(rng.uniform(1e-7, 1e-5, 6))
    assert np.abs(pose.pose_cov_gtsam_from_colmap(cov, R, t) - J @ cov @ J.T).max() < 1e-18


# ----- pinhole -----------------------------------------------------------------------------------
@pytest.mark.parametrize("skew", [0.0, 1.5])
def test_projection_equals_gtsam_pinhole(skew):
    """Ideal pixels of project (K, R, t) and project_ideal (P) equal GTSAM's PinholeCameraCal3_S2 on the
    world_from_cam pose: measured 2.3e-13 px; bound 1e-9 px. Points behind the camera are NaN in project."""
    rng = np.random.default_rng(4)
    K, R, t, xyz = _random_camera(rng, skew)
    R_wc, t_wc = pose.world_from_cam(R, t)
    cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(R_wc), t_wc),
                                     gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]))
    ref = np.array([cam.project(p) for p in xyz])
    assert np.abs(pinhole.project(xyz, K, R, t) - ref).max() < 1e-9
    P = pinhole.projection_matrix(K, R, t)
    assert np.abs(pinhole.project_ideal(P, xyz) - ref).max() < 1e-9
    assert np.abs(pinhole.project_ideal(np.broadcast_to(P, (50, 3, 4)), xyz) - ref).max() < 1e-9
    behind = 2 * t_wc - xyz[0]  # the mirror image of a visible point through the camera centre
    assert np.isnan(pinhole.project(behind, K, R, t)).all()


def test_projection_with_distortion_equals_opencv():
    """project with dist equals cv2.projectPoints (same K, rvec, tvec, 5 coefficients; zero skew, which
    projectPoints ignores) on points inside the lens's valid field: measured 1.1e-13 px; bound 1e-9 px.
    Beyond max_valid_radius it is NaN."""
    rng = np.random.default_rng(5)
    K, R, t, xyz = _random_camera(rng, 0.0)
    ref = cv2.projectPoints(xyz, pose.rvec_from_R(R), t, K, DIST)[0].reshape(-1, 2)
    uv = pinhole.project(xyz, K, R, t, DIST)
    assert np.isfinite(uv).all() and np.abs(uv - ref).max() < 1e-9
    r_max = distortion.max_valid_radius(DIST)
    far = pose.transform_points(*pose.world_from_cam(R, t), np.array([1.2 * r_max, 0.0, 1.0]))
    assert np.isnan(pinhole.project(far, K, R, t, DIST)).all()
    assert np.isfinite(pinhole.project(far, K, R, t)).all()  # the ideal pinhole has no such limit


def test_point_and_pose_jacobians_match_finite_differences():
    """point_jacobian (eq. 16, entries up to 350 px/m) vs central differences of project_ideal (step 1e-6 m):
    measured 1.2e-7; bound 1e-5 px/m. pose_jacobian (entries up to 1000 px per rad) vs central differences
    through GTSAM's world_from_cam * Exp(xi) (step 1e-6): measured 8e-8; bound 1e-4 px. The component-major
    rows (project_rows, point_jacobian_rows) give the same numbers as the matrix form (exactly)."""
    rng = np.random.default_rng(6)
    K, R, t, xyz = _random_camera(rng)
    P = pinhole.projection_matrix(K, R, t)
    J = pinhole.point_jacobian(P, xyz)
    h = 1e-6
    fd = np.stack([(pinhole.project_ideal(P, xyz + h * e) - pinhole.project_ideal(P, xyz - h * e)) / (2 * h)
                   for e in np.eye(3)], axis=-1)
    assert J.shape == (50, 2, 3) and np.abs(J - fd).max() < 1e-5, np.abs(J - fd).max()

    Pr = np.repeat(P.reshape(12, 1), len(xyz), axis=1)
    u, v, inv_depth = pinhole.project_rows(Pr, xyz.T)
    du, dv = pinhole.point_jacobian_rows(Pr, u, v, inv_depth)
    assert np.array_equal(np.stack([u, v], -1), pinhole.project_ideal(P, xyz))
    assert np.array_equal(np.stack([du.T, dv.T], axis=1), J)

    G = pinhole.pose_jacobian(P, R, t, xyz)
    R_wc, t_wc = pose.world_from_cam(R, t)

    def moved(xi):
        R_cw, t_cw = pose.cam_from_world(*_exp_right(R_wc, t_wc, xi))
        return pinhole.project(xyz, K, R_cw, t_cw)

    fd = np.stack([(moved(h * e) - moved(-h * e)) / (2 * h) for e in np.eye(6)], axis=-1)
    assert G.shape == (50, 2, 6) and np.abs(G - fd).max() < 1e-4, np.abs(G - fd).max()


# ----- distortion --------------------------------------------------------------------------------
def test_distortion_jacobians_and_inverse():
    """distortion_jacobian vs central differences (step 1e-7, normalised coordinates up to 0.9 of the
    valid radius): measured 3e-9; bound 1e-6. undistort_normalized inverts distort_normalized there:
    measured 9e-16; bound 1e-12. ideal_from_raw_jacobian (d ideal px / d raw px, with skew) vs central
    differences of undistortion in pixels (step 1e-3 px): measured 1.4e-9; bound 1e-6."""
    rng = np.random.default_rng(7)
    r_max = distortion.max_valid_radius(DIST)
    ang = rng.uniform(0, 2 * np.pi, 200)
    rad = 0.9 * r_max * np.sqrt(rng.uniform(0, 1, 200))
    xy = np.stack([rad * np.cos(ang), rad * np.sin(ang)], -1)
    D = distortion.distortion_jacobian(xy, DIST)
    h = 1e-7
    fd = np.stack([(distortion.distort_normalized(xy + h * e, DIST) - distortion.distort_normalized(xy - h * e, DIST))
                   / (2 * h) for e in np.eye(2)], axis=-1)
    assert np.abs(D - fd).max() < 1e-6, np.abs(D - fd).max()
    xy_d = distortion.distort_normalized(xy, DIST)
    assert np.abs(distortion.undistort_normalized(xy_d, DIST) - xy).max() < 1e-12

    K = np.array([[1100.0, 2.5, 965.0], [0.0, 1098.0, 536.0], [0.0, 0.0, 1.0]])
    K_inv = np.linalg.inv(K)
    raw = pinhole.pixels_from_normalized(xy_d, K)

    def ideal(uv):
        return pinhole.pixels_from_normalized(
            distortion.undistort_normalized(pinhole.normalized_from_pixels(uv, K_inv), DIST), K)

    hp = 1e-3
    fd = np.stack([(ideal(raw + hp * e) - ideal(raw - hp * e)) / (2 * hp) for e in np.eye(2)], axis=-1)
    J = distortion.ideal_from_raw_jacobian(xy, DIST, K)
    assert np.abs(J - fd).max() < 1e-6, np.abs(J - fd).max()


def test_geometry_imports_neither_gtsam_nor_pycolmap():
    """The geometry layer is numpy / scipy / OpenCV only (the fast solvers and importers must not need GTSAM)."""
    code = ("import sys; import batgraph.geometry.pose, batgraph.geometry.pinhole, batgraph.geometry.distortion; "
            "print(sorted(m for m in ('gtsam', 'pycolmap') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
