"""Per-frame linear multi-view triangulation (DLT), all frames and markers at once: the classic baseline.

What DLTdv, Argus, easyWand and aniposelib do per frame. Each point uses only its own frame's
observations from >= 2 cameras; no motion model, no robust loss. Its covariance is the first-order
one, ``(sum_c J_c^T W_c J_c)^-1`` with J_c the projection Jacobian at the solution and W_c the
inverse ideal-pixel noise covariance (see batgraph.measurement).
"""

from __future__ import annotations

import time

import numpy as np

from .camera import Rig
from .measurement import IdealObservations, ideal_observations
from .result import Estimate, Options
from .session import DenseObservations, Session


def triangulate_ideal(rig: Rig, ideal: IdealObservations) -> tuple[np.ndarray, np.ndarray]:
    """Linear DLT on undistorted observations.

    ideal: ideal pixels (C, F, M, 2) with noise covariances (C, F, M, 2, 2).
    Returns xyz_m (F, M, 3) and cov_m2 (F, M, 3, 3) [world]; NaN where fewer than 2 views.

    Rows are built in normalised coordinates (well conditioned) and scaled by each camera's focal
    length, so each row is ``depth * pixel residual`` as in Hartley & Zisserman's DLT; the
    homogeneous system is solved by a batched SVD.
    """
    C, F, M = ideal.uv_px.shape[:3]
    seen = ideal.seen  # (C, F, M)
    A = np.zeros((F, M, C, 2, 4))
    for c, cam in enumerate(rig):
        Kinv = np.linalg.inv(cam.K)
        uv = np.where(seen[c][..., None], ideal.uv_px[c], 0.0)
        x = Kinv[0, 0] * uv[..., 0] + Kinv[0, 1] * uv[..., 1] + Kinv[0, 2]
        y = Kinv[1, 1] * uv[..., 1] + Kinv[1, 2]
        Pn = np.hstack([cam.R, cam.tvec[:, None]])  # cam_from_world, normalised camera
        f = np.sqrt(cam.K[0, 0] * cam.K[1, 1])
        s = np.where(seen[c], f, 0.0)[..., None]
        A[:, :, c, 0] = s * (x[..., None] * Pn[2] - Pn[0])
        A[:, :, c, 1] = s * (y[..., None] * Pn[2] - Pn[1])
    n_views = seen.sum(axis=0)
    ok = n_views >= 2
    xyz = np.full((F, M, 3), np.nan)
    if ok.any():
        _, _, vt = np.linalg.svd(A[ok].reshape(-1, 2 * C, 4), full_matrices=False)
        X = vt[:, -1, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            xyz[ok] = X[:, :3] / X[:, 3:4]
    return xyz, _first_order_cov(rig, ideal, xyz)


def _first_order_cov(rig: Rig, ideal: IdealObservations, xyz_m: np.ndarray) -> np.ndarray:
    """(sum_c J^T W J)^-1 at xyz_m (F, M, 3); NaN where xyz is NaN or the information is singular."""
    F, M = xyz_m.shape[:2]
    info = np.zeros((F, M, 3, 3))
    valid = np.isfinite(xyz_m).all(axis=-1)
    X = np.where(valid[..., None], xyz_m, 0.0)
    for c, cam in enumerate(rig):
        s = ideal.seen[c] & valid
        if not s.any():
            continue
        J = cam.ideal_jacobian_world(X[s])  # (n, 2, 3)
        W = np.linalg.inv(ideal.cov_px2[c][s])  # (n, 2, 2)
        info[s] += np.swapaxes(J, -1, -2) @ W @ J
    cov = np.full((F, M, 3, 3), np.nan)
    det = np.linalg.det(info)
    good = valid & (np.abs(det) > 0)
    cov[good] = np.linalg.inv(info[good])
    return cov


def triangulate(rig: Rig, dense: DenseObservations, pixel_sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate raw observations: xyz_m (F, M, 3) and cov_m2 (F, M, 3, 3), NaN where < 2 views."""
    return triangulate_ideal(rig, ideal_observations(rig, dense, pixel_sigma_px))


def run(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options) -> Estimate:
    """The ``triangulate`` method of ``reconstruct``."""
    t0 = time.perf_counter()
    xyz, cov = triangulate_ideal(session.rig, ideal)
    C, F, M = ideal.seen.shape
    return Estimate("triangulate", xyz, cov, np.zeros((C, F, M), bool), time.perf_counter() - t0)
