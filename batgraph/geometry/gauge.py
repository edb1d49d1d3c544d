"""The gauge of a rig seen only through images: the 7 degrees of freedom of a world similarity.

Images fix a rig's poses only up to a similarity of the world (rotation 3, translation 3, scale 1): moving
every camera and point by ``x' = s R x + t`` leaves every projection unchanged. This module fits that
similarity between two rigs (:func:`fit_similarity`), gives its tangent directions (:func:`gauge_directions`),
the first-order map that removes them from a perturbation of the rig (:func:`gauge_projection`), and the
Mahalanobis distance between two rigs with the gauge removed (:func:`gauge_free_chi2`).
Poses are cam_from_world arrays (R_cw (C, 3, 3), t_cw (C, 3) [m]); a rig's tangent (6C,) stacks the GTSAM
Pose3 tangents of world_from_cam, perturbed on the right, ``xi = [omega (rad), v (m)]``, as ``Camera.pose_cov``.
The fit minimises over (s, R, t) the sum over cameras of ``|s R c_i + t - c'_i|^2 + L^2 |log(R R_i R_i'^T)|^2``
(c: camera centre, R_i: world_from_cam orientation, L: a lever arm [m], default the rms distance of the
target's centres from their centroid): every camera weighs the same and a turn by theta counts as a
displacement of theta L. Centres alone fix the similarity only for 3 or more cameras off a line; with the
orientations two cameras suffice.
"""

from __future__ import annotations

import numpy as np

from . import pose


def _log(R: np.ndarray) -> np.ndarray:
    """SO(3) log of rotation matrices (..., 3, 3) -> (..., 3) [rad], accurate near the identity
    (OpenCV's Rodrigues returns 0 below 1e-5 rad)."""
    from scipy.spatial.transform import Rotation  # 50 ms to import: only calibrate needs it

    R = np.asarray(R, float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-1])


def _centres_orientations(R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R_wc, c = pose.world_from_cam(np.asarray(R_cw, float), np.asarray(t_cw, float))
    return c, R_wc


def default_lever_m(t_centres_m: np.ndarray) -> float:
    """rms distance [m] of camera centres (C, 3) from their centroid (1 m when they coincide)."""
    d = np.sqrt(((t_centres_m - t_centres_m.mean(0)) ** 2).sum(-1).mean())
    return float(d) if d > 1e-9 else 1.0


def fit_similarity(R_cw_a: np.ndarray, t_cw_a: np.ndarray, R_cw_b: np.ndarray, t_cw_b: np.ndarray, *,
                   lever_m: float | None = None, with_scale: bool = True,
                   iterations: int = 10) -> tuple[float, np.ndarray, np.ndarray]:
    """The world similarity ``x' = s R x + t`` that best moves rig a onto rig b (see module docstring).

    R_cw_*: (C, 3, 3), t_cw_*: (C, 3) [m] cam_from_world of the same cameras in the same order.
    lever_m: L [m] (None: :func:`default_lever_m` of rig b's centres). with_scale: False holds s = 1.
    Returns (s, R (3, 3), t (3,) [m]); apply it with ``pose.similarity_cam_from_world``.
    Gauss-Newton from the orientations' chordal mean and the centres' least-squares scale.
    """
    ca, Ra = _centres_orientations(R_cw_a, t_cw_a)
    cb, Rb = _centres_orientations(R_cw_b, t_cw_b)
    L = default_lever_m(cb) if lever_m is None else float(lever_m)
    U, _, Vt = np.linalg.svd((Rb @ np.swapaxes(Ra, -1, -2)).sum(0))  # chordal mean of Rb Ra^T
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a0, b0 = ca - ca.mean(0), cb - cb.mean(0)
    s = float((b0 * (a0 @ R.T)).sum() / max((a0**2).sum(), 1e-300)) if with_scale else 1.0
    s = s if s > 0 else 1.0
    t = cb.mean(0) - s * R @ ca.mean(0)
    n = len(ca)
    for _ in range(iterations):
        sRc = s * ca @ R.T
        r_pos = sRc + t - cb
        r_rot = L * _log(R @ Ra @ np.swapaxes(Rb, -1, -2))
        J = np.zeros((n, 6, 7))  # d(residual) / d(omega, tau, log s): R <- exp(omega) R
        J[:, :3, :3] = -pose.skew(sRc)
        J[:, :3, 3:6] = np.eye(3)
        J[:, :3, 6] = sRc
        J[:, 3:, :3] = L * np.eye(3)
        J = J.reshape(6 * n, 7) if with_scale else J[:, :, :6].reshape(6 * n, 6)
        r = np.concatenate([r_pos, r_rot], axis=1).reshape(-1)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        R = pose.R_from_rvec(step[:3]) @ R
        t = t + step[3:6]
        if with_scale:
            s *= float(np.exp(step[6]))
        if np.abs(step).max() < 1e-12:
            break
    return s, R, t


def gauge_directions(R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """The rig tangent (6C,) moved by an infinitesimal world similarity, shape (6C, 7).

    Columns: world rotation omega (3) [rad], world translation tau (3) [m], log scale (1), about the
    world origin. Camera i (orientation R_i = world_from_cam, centre c_i) moves by
    ``[R_i^T omega, R_i^T (omega x c_i + tau + c_i log s)]`` in GTSAM's body-frame tangent.
    """
    c, R_wc = _centres_orientations(R_cw, t_cw)
    Rt = np.swapaxes(R_wc, -1, -2)
    G = np.zeros((len(c), 6, 7))
    G[:, :3, :3] = Rt
    G[:, 3:, :3] = -Rt @ pose.skew(c)
    G[:, 3:, 3:6] = Rt
    G[:, 3:, 6] = (Rt @ c[:, :, None])[..., 0]
    return G.reshape(-1, 7)


def fit_metric(n_cameras: int, lever_m: float) -> np.ndarray:
    """The diagonal (6C,) of the fit's metric W on the rig tangent: L^2 for rotations, 1 for translations."""
    return np.tile(np.r_[[lever_m**2] * 3, [1.0] * 3], n_cameras)


def gauge_projection(R_cw: np.ndarray, t_cw: np.ndarray, lever_m: float) -> np.ndarray:
    """(6C, 6C): how a perturbation of the rig moves it once the similarity is fitted again.

    ``P = I - G (G^T W G)^-1 G^T W`` (G: :func:`gauge_directions`, W: :func:`fit_metric`): the rig's
    poses after :func:`fit_similarity` to a fixed target change by ``P xi`` when the rig moves by xi
    (first order, at a fitted rig). P G = 0, so ``P cov P^T`` is the same from a covariance in any
    gauge (e.g. a bundle adjustment's with one camera held fixed): the covariance with the gauge removed.
    """
    G = gauge_directions(R_cw, t_cw)
    w = fit_metric(len(R_cw), lever_m)
    WG = G * w[:, None]
    return np.eye(len(w)) - G @ np.linalg.solve(G.T @ WG, WG.T)


def rig_difference(R_cw_a: np.ndarray, t_cw_a: np.ndarray, R_cw_b: np.ndarray, t_cw_b: np.ndarray) -> np.ndarray:
    """Rig a relative to rig b in b's tangent (6C,): per camera ``[log(R_b^T R_a), R_b^T (c_a - c_b)]``
    (R: world_from_cam orientation, c: centre [m]); GTSAM's ``Logmap(T_b^-1 T_a)`` to first order."""
    ca, Ra = _centres_orientations(R_cw_a, t_cw_a)
    cb, Rb = _centres_orientations(R_cw_b, t_cw_b)
    Rbt = np.swapaxes(Rb, -1, -2)
    return np.concatenate([_log(Rbt @ Ra), (Rbt @ (ca - cb)[:, :, None])[..., 0]], axis=1).reshape(-1)


def gauge_free_chi2(delta: np.ndarray, cov: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray,
                    lever_m: float) -> tuple[float, int]:
    """Mahalanobis distance^2 of a rig difference (6C,) under a rig covariance (6C, 6C), gauge removed.

    Both are projected by :func:`gauge_projection` at the rig (R_cw, t_cw) and compared on the
    complement of the gauge (6C - 7 dimensions, fewer where ``cov`` is singular there too).
    Returns (chi2, degrees of freedom).
    """
    P = gauge_projection(R_cw, t_cw, lever_m)
    s = np.sqrt(fit_metric(len(R_cw), lever_m))  # whitened units (rotations times L): only for the numerics
    d = s * (P @ delta)
    S = s[:, None] * (P @ cov @ P.T) * s[None, :]
    ev, V = np.linalg.eigh(0.5 * (S + S.T))
    keep = ev > 1e-9 * max(ev.max(), 1e-300)
    z = (V[:, keep].T @ d) / np.sqrt(ev[keep])
    return float(z @ z), int(keep.sum())
