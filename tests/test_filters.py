"""Tests of the paper's EKF and UKF (batgraph.filters) on small synthetic scenes built here with
batgraph.camera (zero distortion, cameras on a ring looking at the origin, markers moving smoothly)."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd

from batgraph.camera import Camera, Rig
from batgraph.measurement import ideal_observations
from batgraph.result import Options
from batgraph.session import PAPER_PHYSICS, DenseObservations, MotionConfig, Session

FPS = 120.0


def look_at_camera(name: str, center: np.ndarray, target=(0.0, 0.0, 0.0), f_px: float = 1000.0,
                   pose_cov: np.ndarray | None = None) -> Camera:
    """A 1280x720 zero-distortion camera at ``center`` [m] looking at ``target``, world z up."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes (x right, y down, z forward) in world
    K = np.array([[f_px, 0.0, 640.0], [0.0, f_px, 360.0], [0.0, 0.0, 1.0]])
    return Camera(name, (1280, 720), K, np.zeros(5), cv2.Rodrigues(R)[0].ravel(), -R @ center, pose_cov)


def ring_rig(n_cams: int, radius_m: float = 3.0, pose_cov: np.ndarray | None = None) -> Rig:
    ang = 2 * np.pi * np.arange(n_cams) / n_cams + 0.3
    return Rig([look_at_camera(f"cam{i}", np.array([radius_m * np.cos(a), radius_m * np.sin(a),
                                                    0.4 + 0.2 * (i % 2)]), pose_cov=pose_cov)
                for i, a in enumerate(ang)])


def smooth_truth(n_frames: int, n_markers: int, rng: np.random.Generator) -> np.ndarray:
    """Marker positions (F, M, 3) [m]: spread over +-0.2 m, each on a 5 cm Lissajous curve at 1.5-3 Hz
    (at most ~8 mm per frame per axis at 120 fps, below the random walk's sigma_m = 13 mm)."""
    t = np.arange(n_frames)[:, None, None] / FPS
    centre = rng.uniform(-0.2, 0.2, (1, n_markers, 3))
    phase = rng.uniform(0, 2 * np.pi, (1, n_markers, 3))
    freq = np.array([2.0, 3.0, 1.5])
    return centre + 0.05 * np.sin(2 * np.pi * freq * t + phase)


def make_scene(rig: Rig, truth: np.ndarray, noise_px: float, pixel_sigma_px: float,
               rng: np.random.Generator, hidden: np.ndarray | None = None):
    """(session, dense, ideal) for ``truth`` (F, M, 3) seen by ``rig`` with Gaussian pixel noise.

    hidden: optional bool (C, F, M) of observations to drop (occlusion).
    """
    C, (F, M) = len(rig), truth.shape[:2]
    uv = rig.project(truth, distort=True) + noise_px * rng.standard_normal((C, F, M, 2))
    seen = np.isfinite(uv[..., 0]) & np.stack([cam.in_image(uv[c]) for c, cam in enumerate(rig)])
    if hidden is not None:
        seen &= ~hidden
    uv[~seen] = np.nan
    markers = [f"m{j}" for j in range(M)]
    dense = DenseObservations(rig.names, np.arange(F), markers, uv, seen.astype(float))
    c, f, m = np.nonzero(seen)
    obs = pd.DataFrame({"frame": f, "camera": np.array(rig.names)[c], "marker": np.array(markers)[m],
                        "u": uv[c, f, m, 0], "v": uv[c, f, m, 1], "weight": 1.0})
    session = Session("synthetic", FPS, rig, obs, MotionConfig(model="random_walk", **PAPER_PHYSICS), pixel_sigma_px,
                      marker_names=markers)
    return session, dense, ideal_observations(rig, dense, pixel_sigma_px)


QUIET = Options(progress=False)


def run_both(session, dense, ideal):
    from batgraph.filters import run_ekf, run_ukf

    return run_ekf(session, dense, ideal, QUIET), run_ukf(session, dense, ideal, QUIET)


def test_noise_free_scene_is_tracked():
    """Noise-free pixels, 4 cameras at 3 m, f = 1000 px, 3 markers moving up to 10 mm per frame.

    With the assumed pixel sigma at 0.01 px the filters trust the pixels and what is left is the
    linearisation: one Gauss-Newton step (EKF) or the sigma points' second-order mean shift (UKF,
    ~0.5 tr(hess h P) with P ~ sigma_m^2) away from a point that moved up to 10 mm at 3 m depth.
    Measured max 4 um (EKF), 8 um (UKF); bound 20 um.
    With an honest 1 px sigma the random walk makes the estimate lag the motion by about
    (sigma_meas / sigma_m)^2 * step ~ (2 mm / 13 mm)^2 * 10 mm ~ 0.25 mm. Measured 0.25 mm; bound 0.5 mm.
    The first frame is the triangulation of exact pixels: error < 1e-9 m.
    """
    rng = np.random.default_rng(0)
    rig, truth = ring_rig(4), smooth_truth(60, 3, rng)
    for assumed_px, bound_m in ((0.01, 20e-6), (1.0, 0.5e-3)):
        for est in run_both(*make_scene(rig, truth, 0.0, assumed_px, rng)):
            err = np.linalg.norm(est.xyz_m - truth, axis=-1)
            assert np.isfinite(err).all()
            assert err[0].max() < 1e-9, est.method
            assert err.max() < bound_m, (est.method, assumed_px, err.max())
            assert not est.outlier.any()


def test_ekf_and_ukf_agree_with_small_noise_and_honest_covariance():
    """0.5 px noise (assumed 0.5 px), 4 cameras, 4 markers, 80 frames.

    Both filters' RMSE vs truth: measured 1.7 mm; bound 3 mm. EKF vs UKF: the UKF differs only by
    the second-order terms its sigma points see, ~0.5 tr(hess h P) ~ 0.02 px ~ 60 um at 3 m.
    Measured max 5 um; bound 60 um (and 30x below the filters' own error).
    Covariance honesty: mean NEES (err^T P^-1 err, 3 dof) over all frames and markers must be
    near 3; measured 3.2 (both); bound [2, 4.5] (320 correlated samples).
    """
    rng = np.random.default_rng(1)
    rig, truth = ring_rig(4), smooth_truth(80, 4, rng)
    ekf, ukf = run_both(*make_scene(rig, truth, 0.5, 0.5, rng))
    diff = np.linalg.norm(ekf.xyz_m - ukf.xyz_m, axis=-1).max()
    assert diff < 60e-6, diff
    for est in (ekf, ukf):
        e = est.xyz_m - truth
        rmse = np.sqrt(np.mean(np.sum(e**2, axis=-1)))
        assert rmse < 3e-3, (est.method, rmse)
        nees = np.einsum("fmi,fmij,fmj->fm", e, np.linalg.inv(est.cov_m2), e).mean()
        assert 2.0 < nees < 4.5, (est.method, nees)
        assert est.info["sigma_m"] > 0 and "triangulation" in est.info["init"]


def test_linear_gaussian_update_equals_textbook_kalman_filter():
    """With a linear h (y = H x + v) both filters are the Kalman filter: the EKF algebraically, the
    UKF because the unscented transform is exact for linear maps. A textbook KF (explicit inverse,
    P = (I - K H) P) runs 10 steps of a 6-state random walk with 5 noisy linear measurements.
    EKF: round-off only, measured 6e-16 relative; bound 1e-10. UKF: alpha = 1e-3 makes w_m[0] ~ -1e6,
    so its sums cancel ~1e6-fold: measured 1.2e-10 relative; bound 1e-7.
    """
    from batgraph.filters.ekf import ekf_predict, ekf_update
    from batgraph.filters.ukf import ukf_predict, ukf_update

    rng = np.random.default_rng(2)
    n, m, q = 6, 5, 0.01**2
    H = rng.normal(size=(m, n)) * 100
    A = rng.normal(size=(m, m))
    Q = A @ A.T + np.eye(m)
    x0, P0 = rng.normal(size=n), np.diag(rng.uniform(1e-4, 1e-3, n))
    kf = (x0.copy(), P0.copy())
    ekf = (x0.copy(), P0.copy())
    ukf = (x0.copy(), P0.copy())
    truth = x0 + 0.02 * rng.normal(size=n)
    for _ in range(10):
        truth = truth + np.sqrt(q) * rng.normal(size=n)
        y = H @ truth + rng.multivariate_normal(np.zeros(m), Q)
        x, P = kf[0], kf[1] + q * np.eye(n)
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + Q)
        kf = (x + K @ (y - H @ x), (np.eye(n) - K @ H) @ P)
        xe, Pe = ekf_predict(*ekf, q)
        ekf = ekf_update(xe, Pe, y, H @ xe, H, Q)
        xu, Pu = ukf_predict(*ukf, q)
        ukf = ukf_update(xu, Pu, y, Q, lambda X: X @ H.T)
        for (xa, Pa), tol in ((ekf, 1e-10), (ukf, 1e-7)):
            assert np.abs(xa - kf[0]).max() < tol * np.abs(kf[0]).max()
            assert np.abs(Pa - kf[1]).max() < tol * np.abs(kf[1]).max()


def test_projection_and_jacobian_match_camera_and_finite_differences():
    """Eq. 6 and 16 built from stacked projection matrices equal batgraph.camera's pinhole
    (Camera.project(distort=False), Camera.ideal_jacobian_world): measured 1e-13; bound 1e-9.
    The dense stacked H (eq. 17-18, block placement by camera and state slot) equals central
    differences of h over the whole state (step 1e-6 m, truncation ~ h''' d^2 ~ 1e-9 px/m relative):
    measured 7e-8 px/m on entries up to 350 px/m; bound 1e-4 px/m.
    """
    from batgraph.filters.common import FrameMeasurement, RigArrays
    from batgraph.geometry.pinhole import point_jacobian, project_ideal

    rng = np.random.default_rng(3)
    rig = ring_rig(3)
    arrays = RigArrays.from_rig(rig)
    pts = rng.uniform(-0.3, 0.3, (5, 3))
    cam = np.repeat(np.arange(3), 5)
    xyz = np.tile(pts, (3, 1))
    uv = project_ideal(arrays.proj[cam], xyz)
    J = point_jacobian(arrays.proj[cam], xyz)
    for c in range(3):
        assert np.abs(uv[cam == c] - rig[c].project(pts, distort=False)).max() < 1e-9
        assert np.abs(J[cam == c] - rig[c].ideal_jacobian_world(pts)).max() < 1e-9

    # a frame where camera 1 misses marker 2 and camera 2 misses marker 0; state order != label order
    seen = np.ones((3, 5), bool)
    seen[1, 2] = seen[2, 0] = False
    c, mk = np.nonzero(seen)
    slot = np.array([3, 0, 4, 1, 2])[mk]
    x = np.empty((5, 3))
    x[np.array([3, 0, 4, 1, 2])] = pts
    x = x.ravel()
    meas = FrameMeasurement(np.zeros(2 * len(c)), np.tile(np.eye(2), (len(c), 1, 1)), c, slot, arrays)
    H = meas.jacobian(x)
    d = 1e-6
    fd = np.stack([(meas.h(x + d * e) - meas.h(x - d * e)) / (2 * d) for e in np.eye(15)], axis=1)
    assert np.abs(H - fd).max() < 1e-4, np.abs(H - fd).max()
    assert np.count_nonzero(H) == 2 * 3 * len(c)  # one 2x3 block per row pair (eq. 17)


def test_occluded_marker_keeps_estimate_and_covariance_grows_by_R():
    """Marker 1 is hidden from every camera on frames 20-34; marker 2 is seen by one camera only
    on frames 0-9. Without pose covariances the markers never become correlated (H, Q block-
    diagonal per marker), so while hidden the estimate must stay put and its covariance block
    grow by exactly R = sigma_m^2 I per frame (eq. 12 / eq. 22). EKF: round-off only, measured
    x unchanged to the bit and growth - R ~1e-15 sigma_m^2; bounds 1e-15 m, 1e-12 sigma_m^2.
    UKF: its literal unscented prediction averages sigma points with weights ~1e6, losing ~1e6 eps
    per frame: measured 9e-10 m drift over 15 frames and 2e-12 sigma_m^2; bounds 1e-8 m, 1e-8 sigma_m^2.
    Marker 2 enters at frame 10 (its first triangulation): NaN before, the triangulation there.
    After re-acquisition marker 1 is back on track (0.3 px noise): measured max 1.5 mm from frame
    40 on (10 cm just before); bound 3 mm.
    """
    from batgraph.triangulate import triangulate_ideal

    rng = np.random.default_rng(4)
    rig, truth = ring_rig(4), smooth_truth(50, 3, rng)
    hidden = np.zeros((4, 50, 3), bool)
    hidden[:, 20:35, 1] = True
    hidden[1:, :10, 2] = True
    session, dense, ideal = make_scene(rig, truth, 0.3, 0.3, rng, hidden)
    tri, _ = triangulate_ideal(rig, ideal)
    for est, tol_P, tol_x in zip(run_both(session, dense, ideal), (1e-12, 1e-8), (1e-15, 1e-8), strict=True):
        s2 = est.info["sigma_m"] ** 2
        assert np.isnan(est.xyz_m[:10, 2]).all() and np.isnan(est.cov_m2[:10, 2]).all()
        assert np.allclose(est.xyz_m[10, 2], tri[10, 2], rtol=0, atol=1e-12)
        assert np.abs(est.xyz_m[20:35, 1] - est.xyz_m[19, 1]).max() <= tol_x
        growth = np.diff(est.cov_m2[19:35, 1], axis=0) - s2 * np.eye(3)
        assert np.abs(growth).max() < tol_P * s2, (est.method, np.abs(growth).max() / s2)
        assert np.linalg.norm(est.xyz_m[40:, 1] - truth[40:, 1], axis=-1).max() < 3e-3


POSE_COV = np.diag([1e-3**2] * 3 + [2e-3**2] * 3)  # 1 mrad, 2 mm per axis (GTSAM order: rot, trans)


def test_pose_covariance_term_eq10():
    """Eq. 10 with a camera pose uncertainty: dh/dxi for world_from_cam * exp(xi) matches central
    differences through GTSAM's own Pose3.compose(Expmap(xi)) (step 1e-6, entries up to 1000 px):
    measured 8e-8 px; bound 1e-4 px. Q gains exactly G Sigma_p G^T (checked to 1e-12 px^2), which
    couples rows of the same camera only, and is positive semi-definite. The filters then report
    larger covariances than with a perfect rig: per camera the pose adds ~2 mm (translation) and
    1 mrad x 3 m = 3 mm (rotation) against 0.3 px x 3 mm/px ~ 1 mm of pixel noise, so the marginal
    variance should grow several-fold: measured mean ratio 14 (sigma 0.6 -> 2.2 mm); bound > 4.
    """
    import gtsam

    from batgraph.filters.common import FrameMeasurement, RigArrays, pose_jacobian

    rng = np.random.default_rng(5)
    rig = ring_rig(3, pose_cov=POSE_COV)
    arrays = RigArrays.from_rig(rig)
    pts = rng.uniform(-0.3, 0.3, (4, 3))
    cam = np.repeat(np.arange(3), 4)
    xyz = np.tile(pts, (3, 1))
    G = pose_jacobian(arrays, cam, xyz)
    d = 1e-6
    for c, camera in enumerate(rig):
        R_wc, t_wc = camera.world_from_cam()
        pose = gtsam.Pose3(gtsam.Rot3(R_wc), t_wc)
        fd = []
        for e in np.eye(6):
            uv = []
            for s in (d, -d):
                moved = pose.compose(gtsam.Pose3.Expmap(s * e))
                R_cw = moved.rotation().matrix().T
                cam_moved = Camera("m", camera.size_wh, camera.K, np.zeros(5),
                                   cv2.Rodrigues(R_cw)[0].ravel(), -R_cw @ moved.translation())
                uv.append(cam_moved.project(pts, distort=False))
            fd.append((uv[0] - uv[1]) / (2 * d))
        fd = np.stack(fd, axis=-1)  # (4, 2, 6)
        assert np.abs(G[cam == c] - fd).max() < 1e-4, np.abs(G[cam == c] - fd).max()

    # the noise of one frame: with and without pose covariances
    x = pts.ravel()
    cov_px2 = np.tile(np.eye(2), (len(cam), 1, 1))
    plain = RigArrays(arrays.proj, arrays.R, arrays.t, None)
    Q0 = FrameMeasurement(np.zeros(2 * len(cam)), cov_px2, cam, np.tile(np.arange(4), 3), plain).noise(x).dense()
    Q1 = FrameMeasurement(np.zeros(2 * len(cam)), cov_px2, cam, np.tile(np.arange(4), 3), arrays).noise(x).dense()
    Gf = G.reshape(-1, 6)
    same_cam = np.repeat(cam[:, None] == cam[None, :], 2, axis=0).repeat(2, axis=1)
    assert np.abs(Q1 - Q0 - Gf @ POSE_COV @ Gf.T * same_cam).max() < 1e-12
    assert np.abs((Q1 - Q0)[~same_cam]).max() == 0 and np.abs((Q1 - Q0)[same_cam]).max() > 1.0
    assert np.linalg.eigvalsh(Q1 - Q0).min() > -1e-9

    # end to end: honest about the rig's uncertainty
    truth = smooth_truth(30, 3, rng)
    rig4 = ring_rig(4)
    rig4_cov = ring_rig(4, pose_cov=POSE_COV)
    scene = make_scene(rig4, truth, 0.3, 0.3, np.random.default_rng(6))
    scene_cov = (Session(**{**scene[0].__dict__, "rig": rig4_cov}),) + scene[1:]
    for a, b in zip(run_both(*scene), run_both(*scene_cov), strict=True):
        ratio = np.trace(b.cov_m2[5:], axis1=-2, axis2=-1).mean() / np.trace(a.cov_m2[5:], axis1=-2,
                                                                                axis2=-1).mean()
        assert ratio > 4, (a.method, ratio)


def test_information_form_equals_paper_gain_form():
    """Above LARGE_ROWS rows the updates switch to the matrix-inversion-lemma form; it must be the
    paper's update. One frame of 4 cameras x 5 markers with pose covariances (so Q is not block-
    diagonal and the state is correlated), both forms forced: measured differences 1e-15 of the
    correction / of P for the EKF and 4e-12 for the UKF (its inner system carries weights ~1e6);
    bound 1e-9 relative. The factored Q^-1 (Woodbury) equals the dense inverse: measured 1e-15
    relative; bound 1e-12.
    """
    from batgraph.filters.common import FrameMeasurement, RigArrays
    from batgraph.filters.ekf import ekf_update
    from batgraph.filters.ukf import ukf_update

    rng = np.random.default_rng(7)
    rig = RigArrays.from_rig(ring_rig(4, pose_cov=POSE_COV))
    pts = rng.uniform(-0.3, 0.3, (5, 3))
    cam, mk = np.nonzero(rng.random((4, 5)) < 0.8)
    A = rng.normal(size=(15, 15)) * 3e-3
    P = A @ A.T + 1e-4 * np.eye(15)
    x = pts.ravel() + rng.multivariate_normal(np.zeros(15), P)
    meas = FrameMeasurement(np.zeros(2 * len(cam)), np.tile(np.eye(2) * 0.5, (len(cam), 1, 1)), cam, mk, rig)
    meas.y = meas.h(pts.ravel()) + 0.5 * rng.standard_normal(2 * len(cam))
    Q = meas.noise(x)
    B = rng.normal(size=(2 * len(cam), 3))
    assert np.abs(Q.solve(B) - np.linalg.solve(Q.dense(), B)).max() < 1e-12 * np.abs(Q.solve(B)).max()
    H = meas.jacobian(x)
    results = {
        "ekf": [ekf_update(x, P, meas.y, meas.h(x), H, Q, form=f) for f in ("gain", "information")],
        "ukf": [ukf_update(x, P, meas.y, Q, meas.h, form=f) for f in ("gain", "information")],
    }
    for method, ((xg, Pg), (xi, Pi)) in results.items():
        assert np.abs(xg - xi).max() < 1e-9 * np.abs(xg - x).max(), (method, np.abs(xg - xi).max())
        assert np.abs(Pg - Pi).max() < 1e-9 * np.abs(Pg).max(), (method, np.abs(Pg - Pi).max())
