"""Camera model: projection vs OpenCV, undistortion round trips, Jacobians vs finite differences, DLT <-> K,R,t."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import look_at

from batgraph.camera import Camera, distort_normalized, max_valid_radius
from batgraph.geometry.pinhole import pixels_from_normalized

GOPRO_DIST = np.array([-0.25, 0.07, 0.0005, -0.0003, -0.008])
GOPRO_SIZE = (1920, 1080)


def _gopro(skew: float = 0.0) -> Camera:
    """A 1920x1080 GoPro-like camera: strong barrel distortion, off-centre principal point."""
    K = np.array([[1100.0, skew, 965.0], [0.0, 1098.0, 536.0], [0.0, 0.0, 1.0]])
    return look_at("gopro", [2.0, -3.0, 1.2], [0.1, 0.2, 0.3], K, GOPRO_SIZE, GOPRO_DIST)


def _points_in_view(cam: Camera, n: int, rng, r_frac: float = 0.95) -> np.ndarray:
    """n world points (n, 3) [m] in front of ``cam`` within r_frac of its valid radius, 1-6 m deep."""
    w, h = cam.size_wh
    uv = rng.uniform([-0.2 * w, -0.2 * h], [1.2 * w, 1.2 * h], size=(n, 2))
    xy = (uv - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    r = np.linalg.norm(xy, axis=1, keepdims=True)
    xy = np.where(r < r_frac * min(max_valid_radius(cam.dist), 3.0), xy, xy / r * 0.5)
    z = rng.uniform(1.0, 6.0, size=(n, 1))
    xyz_cam = np.hstack([xy * z, z])
    return (xyz_cam - cam.tvec) @ cam.R  # world = R^T (cam - t)


def test_project_matches_opencv():
    """Raw pixels equal cv2.projectPoints' (no skew: OpenCV has none). Measured 4.5e-13 px; bound 1e-9 px."""
    rng = np.random.default_rng(1)
    cam = _gopro()
    xyz = _points_in_view(cam, 500, rng)
    ours = cam.project(xyz)
    cv, _ = cv2.projectPoints(xyz.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.K, cam.dist)
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours, cv.reshape(-1, 2), rtol=0, atol=1e-9)
    ideal, _ = cv2.projectPoints(xyz.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.K, np.zeros(5))
    np.testing.assert_allclose(cam.project(xyz, distort=False), ideal.reshape(-1, 2), rtol=0, atol=1e-9)


def _image_grid(cam: Camera, n: int = 41) -> np.ndarray:
    """Raw pixels covering the whole image, edges and the four corner pixel centres included, (n*n, 2)."""
    w, h = cam.size_wh
    u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, n), np.linspace(-0.5, h - 0.5, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("skew", [0.0, 2.5])
def test_undistort_round_trip_whole_image(skew):
    """raw -> undistort -> distort -> raw over the whole GoPro image, corners included.

    Measured max 4.5e-13 px (OpenCV's 5 fixed-point iterations + 3 Newton steps; 50 + 2 gave the same);
    bound 1e-9 px. Also undistort(project(x)) == project(x, distort=False) for world points: measured
    9.1e-13 px, bound 1e-9.
    """
    cam = _gopro(skew)
    raw = _image_grid(cam)
    corners = np.array([[-0.5, -0.5], [1919.5, -0.5], [-0.5, 1079.5], [1919.5, 1079.5]])
    raw = np.vstack([raw, corners])
    xy = cam.undistort_normalized(raw)
    assert (np.linalg.norm(xy, axis=1) < max_valid_radius(cam.dist)).all(), "the image lies inside the lens field"
    back = pixels_from_normalized(distort_normalized(xy, cam.dist), cam.K)
    err_raw = np.abs(back - raw).max()
    assert err_raw < 1e-9, err_raw
    ideal = cam.undistort(raw)
    np.testing.assert_allclose(pixels_from_normalized(xy, cam.K), ideal, rtol=0, atol=1e-12)

    xyz = _points_in_view(cam, 2000, np.random.default_rng(2))
    raw_pts = cam.project(xyz)
    inside = cam.in_image(raw_pts)
    assert inside.sum() > 1000
    err_ideal = np.abs(cam.undistort(raw_pts[inside]) - cam.project(xyz[inside], distort=False)).max()
    assert err_ideal < 1e-9, err_ideal


def test_undistort_passes_nan_and_handles_zero_distortion():
    cam = look_at("c", [0, -3, 0], [0, 0, 0], np.array([[800.0, 1.0, 320], [0, 790, 240], [0, 0, 1]]))
    uv = np.array([[10.0, 20.0], [np.nan, np.nan], [600.0, 400.0]])
    out = cam.undistort(uv)
    np.testing.assert_allclose(out[[0, 2]], uv[[0, 2]], atol=1e-12)
    assert np.isnan(out[1]).all()


def _central_diff(f, x: np.ndarray, h: float) -> np.ndarray:
    """d f / d x by central differences: f maps (n, k) -> (n, m); returns (n, m, k)."""
    cols = []
    for j in range(x.shape[1]):
        e = np.zeros(x.shape[1])
        e[j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_ideal_from_raw_jacobian_vs_finite_differences():
    """d(ideal)/d(raw) over the whole image vs central differences with h = 1e-3 px.

    The difference's truncation error is O(h^2 f''') ~ 1e-8 and rounding O(eps |ideal| / h) ~ 1e-10;
    measured max relative error 2.8e-10; bound 1e-6 (relative to the Jacobian's largest entry).
    """
    cam = _gopro(skew=1.5)
    raw = _image_grid(cam, 21)
    J = cam.ideal_from_raw_jacobian(raw)
    J_fd = _central_diff(cam.undistort, raw, 1e-3)
    rel = np.abs(J - J_fd).max(axis=(1, 2)) / np.abs(J).max(axis=(1, 2))
    assert rel.max() < 1e-6, rel.max()
    # at the corners the lens compresses strongly: the Jacobian must be far from identity there
    assert np.abs(J).max() > 1.5


def test_ideal_jacobian_world_vs_finite_differences():
    """d(ideal px)/d(xyz_world) (paper eq. 16) with skew vs central differences, h = 1e-6 m.

    Measured max relative error 7.8e-10; bound 1e-6.
    """
    cam = _gopro(skew=3.0)
    xyz = _points_in_view(cam, 200, np.random.default_rng(3))
    J = cam.ideal_jacobian_world(xyz)
    J_fd = _central_diff(lambda x: cam.project(x, distort=False), xyz, 1e-6)
    rel = np.abs(J - J_fd).max(axis=(1, 2)) / np.abs(J).max(axis=(1, 2))
    assert J.shape == (200, 2, 3) and rel.max() < 1e-6, rel.max()


@pytest.mark.parametrize("target_behind", [False, True])
def test_dlt_round_trip_with_skew(target_behind):
    """K, R, t -> 11 DLT coefficients -> K, R, t exactly, skew included; also when the world origin lies
    behind the camera (the DLT's scale P[2, 3] is then negative). Measured 4e-13 px on K, 3e-16 on R and t; bound 1e-9.
    """
    K = np.array([[1234.5, 4.2, 650.3], [0.0, 1229.0, 370.9], [0.0, 0.0, 1.0]])
    centre = [0.5, 0.5, 0.5] if target_behind else [3.0, -2.0, 1.5]
    target = [2.0, 2.0, 1.0] if target_behind else [0.0, 0.0, 0.2]
    cam = look_at("c", centre, target, K, (1280, 720))
    assert (cam.tvec[2] < 0) == target_behind
    L = cam.to_dlt()
    assert L.shape == (11,)
    back = Camera.from_dlt("c", L, (1280, 720))
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(back.R, cam.R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.tvec, cam.tvec, rtol=0, atol=1e-9)
    assert np.linalg.det(back.R) == pytest.approx(1.0)
    np.testing.assert_allclose(back.to_dlt(), L, rtol=1e-12, atol=1e-15)
    # and the DLT formula itself projects like the camera (no distortion)
    xyz = np.random.default_rng(4).uniform(-0.5, 0.5, size=(20, 3)) + np.asarray(target)
    den = xyz @ L[8:11] + 1
    uv = np.stack([(xyz @ L[0:3] + L[3]) / den, (xyz @ L[4:7] + L[7]) / den], axis=1)
    np.testing.assert_allclose(uv, cam.project(xyz, distort=False), rtol=0, atol=1e-9)


def test_from_dlt_of_a_random_matrix_round_trips():
    """Any non-degenerate 11-vector is a pinhole with skew: from_dlt -> to_dlt reproduces it (bound 1e-10)."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        L = rng.normal(size=11) * np.r_[[100.0] * 4, [100.0] * 4, [0.1] * 3]
        cam = Camera.from_dlt("r", L, (100, 100))
        assert (np.diag(cam.K)[:2] > 0).all() and cam.K[2, 2] == pytest.approx(1.0)
        np.testing.assert_allclose(cam.to_dlt(), L, rtol=1e-10, atol=1e-10 * np.abs(L).max())


def test_points_behind_the_camera_are_nan():
    cam = _gopro()
    front = cam.center_world + 2.0 * cam.R[2] + 0.1 * cam.R[0]
    behind = cam.center_world - 2.0 * cam.R[2] + 0.1 * cam.R[0]
    on_plane = cam.center_world + 0.3 * cam.R[0]
    xyz = np.stack([front, behind, on_plane])
    for distort in (True, False):
        uv = cam.project(xyz, distort=distort)
        assert np.isfinite(uv[0]).all() and np.isnan(uv[1:]).all()


def test_points_beyond_the_lens_field_are_nan():
    cam = _gopro()
    r_max = max_valid_radius(cam.dist)
    xyz_cam = np.array([[0.9 * r_max, 0, 1.0], [1.1 * r_max, 0, 1.0]])
    xyz = (xyz_cam - cam.tvec) @ cam.R
    uv = cam.project(xyz)
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    assert np.isfinite(cam.project(xyz, distort=False)).all()


@pytest.mark.parametrize(
    "dist",
    [GOPRO_DIST, np.array([-0.3, 0, 0, 0, 0]), np.array([-0.1, -0.05, 0, 0, 0.01]), np.array([0.1, 0.01, 0, 0, 0.001])],
)
def test_max_valid_radius_is_where_the_radial_function_stops_increasing(dist):
    """r * radial(r) increases on [0, r_max) and decreases just past it (or never turns: inf)."""
    k1, k2, _, _, k3 = dist

    def rd(r):
        r2 = r * r
        return r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)

    r_max = max_valid_radius(dist)
    if np.isinf(r_max):
        r = np.linspace(0, 20, 20001)
        assert (np.diff(rd(r)) > 0).all()
        return
    r = np.linspace(0, r_max, 10001)
    assert (np.diff(rd(r)) > 0).all()
    assert rd(r_max * (1 + 1e-3)) < rd(r_max)
    if k2 == 0 and k3 == 0:
        assert r_max == pytest.approx(np.sqrt(-1 / (3 * k1)), rel=1e-12)


def test_max_valid_radius_of_no_distortion_is_inf():
    assert max_valid_radius(np.zeros(5)) == np.inf


def test_fundamental_matrix_holds_for_projected_points():
    """x_b^T F x_a = 0 for the ideal pixels of one world point in cameras a and b (Rig.fundamental), and F of (b, a)
    is F of (a, b) transposed, up to scale; a point off the epipolar line gives a clearly non-zero product."""
    from batgraph.simulate import simulate_flight

    rig = simulate_flight(np.random.default_rng(0), n_cameras=4, n_frames=10).rig
    xyz = np.random.default_rng(1).normal([0.0, 0.0, 0.0], 0.2, (50, 3))
    for a, b in ((0, 1), (1, 3), (2, 0)):
        xa, xb = rig[a].project(xyz, distort=False), rig[b].project(xyz, distort=False)
        ok = np.isfinite(xa).all(axis=1) & np.isfinite(xb).all(axis=1)
        assert ok.sum() > 10
        ha = np.column_stack([xa[ok], np.ones(ok.sum())])
        hb = np.column_stack([xb[ok], np.ones(ok.sum())])
        F = rig.fundamental(a, b)
        F = F / np.linalg.norm(F)
        line = ha @ F.T  # the epipolar lines in camera b
        dist = np.abs(np.einsum("ni,ni->n", hb, line)) / np.linalg.norm(line[:, :2], axis=1)
        assert dist.max() < 1e-6  # [px]
        back = rig.fundamental(b, a)
        np.testing.assert_allclose(back / np.linalg.norm(back), F.T * np.sign(back.ravel() @ F.T.ravel()), atol=1e-9)
        off = np.abs(np.einsum("ni,ni->n", hb + [5.0, -5.0, 0.0], line)) / np.linalg.norm(line[:, :2], axis=1)
        assert np.median(off) > 1.0
