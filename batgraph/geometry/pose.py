"""Rigid poses: rotation vectors, cam_from_world <-> world_from_cam, similarity transforms, tangents.

The only place in batgraph that converts between pose conventions (see :mod:`batgraph.geometry`):
batgraph and COLMAP store cam_from_world, GTSAM's ``Pose3`` of a camera is world_from_cam, and the
two libraries perturb poses in different tangent spaces. Pure functions on arrays; no GTSAM or
pycolmap objects (callers build those from the arrays returned here).

Shapes: a pose is ``(R, t)`` with R of shape (..., 3, 3) and t of shape (..., 3) [m] unless a
function says it takes one pose; leading axes broadcast.
"""

from __future__ import annotations

import cv2
import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x of vectors v (..., 3): shape (..., 3, 3), ``[v]x w = v x w``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return S - np.swapaxes(S, -1, -2)


# ----- rotations --------------------------------------------------------------------------------
def R_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues rotation vector (3,) [rad] -> rotation matrix (3, 3) (OpenCV's ``Rodrigues``)."""
    return cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]


def rvec_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> Rodrigues rotation vector (3,) [rad] (the SO(3) log, OpenCV's ``Rodrigues``)."""
    return cv2.Rodrigues(np.asarray(R, dtype=float))[0].reshape(3)


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation between two rotation matrices (3, 3), ``|log(Ra Rb^T)|`` [rad], in [0, pi]."""
    return float(np.linalg.norm(rvec_from_R(Ra @ Rb.T)))


# ----- cam_from_world <-> world_from_cam ---------------------------------------------------------
def _inverse(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) -> (R^T, -R^T t): the inverse rigid transform."""
    R_inv = np.swapaxes(R, -1, -2)
    return R_inv, -(R_inv @ np.asarray(t, dtype=float)[..., None])[..., 0]


def world_from_cam(R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R_cw (..., 3, 3), t_cw (..., 3) [m]) -> world_from_cam (R_wc, t_wc).

    world_from_cam is the pose GTSAM's ``Pose3`` of a camera holds; t_wc is the camera centre in the
    world frame.
    """
    return _inverse(R_cw, t_cw)


def cam_from_world(R_wc: np.ndarray, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """world_from_cam (R_wc (..., 3, 3), t_wc (..., 3) [m], e.g. a GTSAM Pose3, or an orientation and
    a camera centre) -> cam_from_world (R_cw, t_cw), batgraph's and COLMAP's convention."""
    return _inverse(R_wc, t_wc)


def transform_points(R: np.ndarray, t: np.ndarray, xyz_m: np.ndarray) -> np.ndarray:
    """Apply poses b_from_a to points in frame a: ``R x + t``, points in frame b, shape (..., 3) [m].

    R (3, 3) and t (3,): one pose for every point xyz_m (..., 3) (one matrix product); or R (..., 3, 3),
    t (..., 3): a pose per point, broadcast against xyz_m (..., 3).
    """
    if np.ndim(R) == 2:
        return xyz_m @ R.T + t
    return (R @ xyz_m[..., None])[..., 0] + t


def look_at(center_m: np.ndarray, target_m: np.ndarray, right_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R (3, 3), t (3,) [m]) of a camera at ``center_m`` (3,) looking at ``target_m`` (3,).

    Image x (right) is ``right_hint`` (3,) made perpendicular to the optical axis; it is flipped if
    that would put world-up (+z) at the bottom of the image (camera y points down).
    """
    z = target_m - center_m
    z = z / np.linalg.norm(z)
    x = right_hint - (right_hint @ z) * z
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    if y[2] > 1e-9:  # image v (down) should not point up in the world
        x, y = -x, -y
    R = np.stack([x, y, z])  # rows: the camera axes in world coordinates
    return cam_from_world(R.T, center_m)


# ----- similarity transforms of the world -------------------------------------------------------
def similarity_cam_from_world(R_cw: np.ndarray, t_cw: np.ndarray, s: float, R: np.ndarray,
                              t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cam_from_world pose (R_cw (..., 3, 3), t_cw (..., 3) [m]) after the world moves by x' = s R x + t.

    s: scale; R (3, 3), t (3,) [m]. The camera frame scales with the world (metric units stay
    metres), so ``x_cam' = s x_cam``: R_cw' = R_cw R^T, t_cw' = s t_cw - R_cw' t. Projections are
    unchanged: a point and the camera move together.
    """
    R_new = R_cw @ R.T
    return R_new, s * t_cw - (R_new @ t[..., None])[..., 0]


def similarity_pose_cov(pose_cov: np.ndarray, s: float) -> np.ndarray:
    """A GTSAM Pose3 (world_from_cam) tangent covariance (..., 6, 6) after a world similarity of scale s.

    The body-frame rotation tangent is unchanged and the body-frame translation scales by s (the
    world's rotation and translation do not enter a right perturbation).
    """
    S = np.diag([1.0, 1.0, 1.0, s, s, s])
    return S @ pose_cov @ S


# ----- tangents: GTSAM and COLMAP ----------------------------------------------------------------
def point_pose_jacobian(xyz_cam_m: np.ndarray) -> np.ndarray:
    """d(xyz_cam) / d(xi) for the camera pose perturbed as ``world_from_cam * Exp(xi)``, shape (..., 3, 6).

    xyz_cam_m: points in the camera frame (..., 3) [m]; xi = [omega (rad), v (m)] in GTSAM's Pose3
    tangent order. To first order the point in the camera frame moves by ``p_c x omega - v``:
    ``[[p_c]x, -I]`` (GTSAM's Pose3::transformTo Jacobian).
    """
    S = skew(xyz_cam_m)
    return np.concatenate([S, np.broadcast_to(-np.eye(3), S.shape)], axis=-1)


def pose_cov_jacobian(R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """d(GTSAM world_from_cam tangent) / d(COLMAP cam_from_world tangent), shape (6, 6).

    COLMAP's pose block is Ceres' EigenQuaternion x Euclidean(3) manifold on cam_from_world
    (R, t): ``R <- Exp(2 dq) R`` (Ceres' quaternion increment is the half angle, applied on the
    left) and ``t <- t + dt``; tangent order [dq, dt]. GTSAM's Pose3 retraction on world_from_cam
    T = (R^T, -R^T t) is ``T <- T Exp([w, v])`` (body frame), tangent order [w, v]. Inverting the
    perturbed cam_from_world to first order gives ``w = -2 dq``, ``v = -dt - [t]x 2 dq``.
    R_cw (3, 3), t_cw (3,) [m]: the pose it is linearised at.
    """
    del R_cw  # the map does not depend on the rotation (both perturbations are frame-consistent)
    J = np.zeros((6, 6))
    J[:3, :3] = -2.0 * np.eye(3)
    J[3:, :3] = -2.0 * skew(t_cw)
    J[3:, 3:] = -np.eye(3)
    return J


def pose_cov_gtsam_from_colmap(cov_colmap: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """A pycolmap pose covariance -> batgraph's ``pose_covariance`` (GTSAM Pose3 tangent of world_from_cam).

    cov_colmap: (6, 6) from ``BACovariance.get_cam_cov_from_world``: tangent of cam_from_world in
        Ceres' order [quaternion increment (half angle) (3), translation (3) [m]].
    R_cw (3, 3), t_cw (3,) [m]: the cam_from_world pose it is linearised at.
    Returns (6, 6): covariance of GTSAM's Pose3 tangent [rotation rad (3), translation m (3)] of
    world_from_cam, right (body-frame) perturbation (see :func:`pose_cov_jacobian`).
    """
    J = pose_cov_jacobian(R_cw, t_cw)
    out = J @ np.asarray(cov_colmap, dtype=float) @ J.T
    return 0.5 * (out + out.T)
