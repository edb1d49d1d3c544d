"""Pinhole projection of world points and its Jacobians, vectorised; written once for every estimator.

Two forms of the same camera (conventions in :mod:`batgraph.geometry`):

* by K, R, t (cam_from_world) with optional distortion: :func:`project`, to raw or ideal pixels,
  NaN behind the camera or outside the lens's valid field;
* by the projection matrix P = K [R | t] to ideal pixels (paper eq. 6), for the estimators' inner
  loops: :func:`project_ideal`, :func:`point_jacobian` (paper eq. 16), :func:`pose_jacobian`. Their
  core, :func:`project_rows` / :func:`point_jacobian_rows`, takes P component-major, ``(12, *B)``,
  so that a solver can keep its rows contiguous (its hot path).

No check that a point is in front of the camera in the P form: callers that need one look at the
depth (``1 / inv_depth``) that :func:`project_rows` returns.
"""

from __future__ import annotations

import numpy as np

from .distortion import distort_normalized, max_valid_radius
from .pose import point_pose_jacobian, transform_points

MIN_DEPTH = 1e-9  # [normalised] z below this counts as behind the camera in :func:`project`


def projection_matrix(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """P = K [R | t] (3, 4) of a camera matrix K (3, 3) and cam_from_world R (3, 3), t (3,) [m]."""
    return K @ np.hstack([R, t[:, None]])


def pixels_from_normalized(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised coordinates (..., 2) -> pixels (..., 2) by K (3, 3) (skew K[0, 1] included)."""
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    return np.stack([u, v], axis=-1)


def normalized_from_pixels(uv_px: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) -> normalised coordinates (..., 2) by K^-1 (3, 3) (upper triangular, as K)."""
    x = K_inv[0, 0] * uv_px[..., 0] + K_inv[0, 1] * uv_px[..., 1] + K_inv[0, 2]
    y = K_inv[1, 1] * uv_px[..., 1] + K_inv[1, 2]
    return np.stack([x, y], axis=-1)


def project(xyz_world_m: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
            dist: np.ndarray | None = None, r_max: float | None = None) -> np.ndarray:
    """Project world points (..., 3) [m] through one camera to pixels (..., 2).

    K (3, 3) [px]; R (3, 3), t (3,) [m]: cam_from_world. dist: OpenCV (k1, k2, p1, p2, k3) (5,) for
    raw (distorted) pixels, None for ideal pixels. r_max: the lens's largest valid undistorted radius
    (:func:`batgraph.geometry.distortion.max_valid_radius`, computed when None). NaN for points
    behind the camera (depth <= 1e-9 m) and, with distortion, beyond r_max.
    """
    xyz_cam = transform_points(R, t, np.asarray(xyz_world_m, dtype=float))
    z = xyz_cam[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where(z > MIN_DEPTH, xyz_cam[..., :2] / z, np.nan)
    if dist is not None:
        r_max = max_valid_radius(dist) if r_max is None else r_max
        r = np.linalg.norm(xy, axis=-1, keepdims=True)
        xy = np.where(r <= r_max, distort_normalized(xy, dist), np.nan)
    return pixels_from_normalized(xy, K)


# ----- the P form: ideal pixels ------------------------------------------------------------------
def project_rows(P: np.ndarray, xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ideal pixels of points by projection matrices, component-major: (u, v, inv_depth), each (*B,).

    P: entries of K [R | t] in row-major order, shape (12, *B) (``P[4 i + j]`` = P[i, j]).
    xyz_m: world points, shape (3, *B) [m]; P and xyz_m broadcast over *B.
    inv_depth = 1 / (P[2] . [x, 1]) [1/m for a unit-K camera]; +-inf at zero depth, negative behind.
    """
    x, y, z = xyz_m[0], xyz_m[1], xyz_m[2]
    depth = P[8] * x + P[9] * y + P[10] * z + P[11]
    with np.errstate(divide="ignore"):
        inv_depth = 1.0 / depth
    u = (P[0] * x + P[1] * y + P[2] * z + P[3]) * inv_depth
    v = (P[4] * x + P[5] * y + P[6] * z + P[7]) * inv_depth
    return u, v, inv_depth


def point_jacobian_rows(P: np.ndarray, u: np.ndarray, v: np.ndarray,
                        inv_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d(ideal px) / d(xyz_world) (paper eq. 16) at a :func:`project_rows` result: (du, dv), each (3, *B) [px/m].

    ``d u / d x = (P[0, :3] - u P[2, :3]) / depth``, likewise v with P[1, :3]; P as in :func:`project_rows`.
    """
    m3 = P[8:11]
    return (P[0:3] - u * m3) * inv_depth, (P[4:7] - v * m3) * inv_depth


def _rows(P: np.ndarray, xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P (..., 3, 4) and xyz (..., 3) -> component-major views (12, ...) and (3, ...), P's leading axes
    padded so that every row broadcasts against the points' (and the (3, ...) Jacobian rows do too)."""
    xyz_m = np.asarray(xyz_m, dtype=float)
    Pf = P.reshape((1,) * max(xyz_m.ndim - P.ndim + 1, 0) + P.shape[:-2] + (12,))
    return np.moveaxis(Pf, -1, 0), np.moveaxis(xyz_m, -1, 0)


def project_ideal(P: np.ndarray, xyz_world_m: np.ndarray) -> np.ndarray:
    """Pinhole projection, paper eq. 6: ``(1/lambda) K Pi_0 H x`` with lambda the depth.

    P: projection matrices K [R | t], shape (..., 3, 4); xyz_world_m: points, shape (..., 3) [m]
    (leading axes broadcast). Returns ideal pixels, shape (..., 2).
    """
    u, v, _ = project_rows(*_rows(P, xyz_world_m))
    return np.stack([u, v], axis=-1)


def point_jacobian(P: np.ndarray, xyz_world_m: np.ndarray) -> np.ndarray:
    """Paper eq. 16, d(ideal px)/d(xyz_world): ``(1/lambda) M - (1/lambda) uv m3^T``, shape (..., 2, 3) [px/m].

    P (..., 3, 4) and xyz_world_m (..., 3) as in :func:`project_ideal`; M = first two rows and m3 =
    last row of P[..., :3], lambda the depth.
    """
    Pr, X = _rows(P, xyz_world_m)
    du, dv = point_jacobian_rows(Pr, *project_rows(Pr, X))
    return np.stack([np.moveaxis(du, 0, -1), np.moveaxis(dv, 0, -1)], axis=-2)


def pose_jacobian(P: np.ndarray, R: np.ndarray, t: np.ndarray, xyz_world_m: np.ndarray) -> np.ndarray:
    """d(ideal px)/d(xi) for the camera pose perturbed as ``world_from_cam * Exp(xi)``, shape (..., 2, 6).

    P (..., 3, 4) = K [R | t]; R (..., 3, 3), t (..., 3) [m]: cam_from_world; xyz_world_m (..., 3) [m].
    xi = [omega (rad), v (m)] in GTSAM's Pose3 tangent order. d uv / d p_c is eq. 16 with the
    rotation taken out (J_world R^T), times d p_c / d xi (:func:`batgraph.geometry.pose.point_pose_jacobian`).
    """
    xyz_cam = transform_points(R, t, xyz_world_m)
    return point_jacobian(P, xyz_world_m) @ np.swapaxes(R, -1, -2) @ point_pose_jacobian(xyz_cam)
