"""OpenCV's 5-parameter lens distortion (k1, k2, p1, p2, k3) on normalised coordinates: forward, Jacobian, inverse.

Normalised coordinates are ``(x/z, y/z)`` in the camera frame; "undistorted" ones are what a pinhole
sees, "distorted" ones what the lens delivers (raw pixels are ``K`` applied to them). Nothing here
knows about poses or pixels beyond the 2x2 block of K that :func:`ideal_from_raw_jacobian` needs.
"""

from __future__ import annotations

import cv2
import numpy as np

# OpenCV's undistortPoints (its default 5 fixed-point iterations) starts the Newton polish; measured on a
# GoPro-like lens (k = -0.28, 0.09, -0.012) out to its fold: 5 + 3 Newton steps leave < 3e-11 px, at half
# the time of 50 iterations + 2 Newton steps (5 + 2 left 1e-4 px).
_CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 5, 1e-14)
NEWTON_STEPS = 3


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's 5-parameter distortion to normalised coordinates.

    xy: undistorted normalised coordinates ``(x/z, y/z)``, shape (..., 2).
    dist: (k1, k2, p1, p2, k3), shape (5,).
    Returns distorted normalised coordinates, shape (..., 2).
    """
    k1, k2, p1, p2, k3 = dist
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def distortion_jacobian(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """d(distorted normalised) / d(undistorted normalised), shape (..., 2, 2), at ``xy`` (..., 2)."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    J = np.empty(xy.shape[:-1] + (2, 2))
    J[..., 0, 0] = radial + 2 * g * x * x + 2 * p1 * y + 6 * p2 * x
    J[..., 0, 1] = 2 * g * x * y + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 0] = 2 * g * x * y + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 1] = radial + 2 * g * y * y + 6 * p1 * y + 2 * p2 * x
    return J


def solve_2x2(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """J^-1 r for batches of 2x2 systems, J (..., 2, 2), r (..., 2), by Cramer's rule (inf/NaN where J is
    singular). Written out because numpy's batched solve costs ~10x as much on 2x2 blocks and raises on a
    single singular one."""
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    return np.stack([J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1],
                     J[..., 0, 0] * r[..., 1] - J[..., 1, 0] * r[..., 0]], axis=-1) / det[..., None]


def max_valid_radius(dist: np.ndarray) -> float:
    """Largest undistorted normalised radius where the radial model is still monotonic.

    Beyond it, OpenCV's polynomial folds back and a point would land at the wrong place in the
    image: physically, outside the lens's field. ``inf`` when the model is monotonic everywhere.
    """
    k1, k2, _, _, k3 = dist
    # d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3, s = r^2
    roots = np.roots([7 * k3, 5 * k2, 3 * k1, 1.0]) if k3 else np.roots([5 * k2, 3 * k1, 1.0]) if k2 else (
        np.array([-1 / (3 * k1)]) if k1 else np.array([])
    )
    s = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    return float(np.sqrt(min(s))) if s else float("inf")


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates (..., 2) -> undistorted normalised coordinates (..., 2).

    OpenCV's ``undistortPoints`` gives the starting point; three Newton steps on the exact Jacobian
    polish it, because OpenCV's fixed-point iteration stalls at ~1e-3 px near the edge of a strongly
    distorted (GoPro-like) lens. NaN in, NaN out; the identity when ``dist`` is all zero.
    """
    flat = np.asarray(xy_d, dtype=float).reshape(-1, 2)
    ok = np.isfinite(flat).all(axis=1)
    out = np.full_like(flat, np.nan)
    if ok.any() and np.any(dist):
        target = flat[ok]
        xy = cv2.undistortPoints(target.reshape(-1, 1, 2), np.eye(3), np.asarray(dist, dtype=float),
                                 criteria=_CV_CRITERIA).reshape(-1, 2)
        resid = distort_normalized(xy, dist) - target
        for _ in range(NEWTON_STEPS):
            with np.errstate(all="ignore"):
                step = xy - solve_2x2(distortion_jacobian(xy, dist), resid)
                resid_step = distort_normalized(step, dist) - target
                # A noisy pixel just beyond the lens's largest distorted radius has no preimage and
                # OpenCV stops near the fold, where J is singular: keep only steps that help.
                better = (np.einsum("ij,ij->i", resid_step, resid_step) < np.einsum("ij,ij->i", resid, resid))[:, None]
            xy, resid = np.where(better, step, xy), np.where(better, resid_step, resid)
        out[ok] = xy
    elif ok.any():
        out[ok] = flat[ok]
    return out.reshape(np.shape(xy_d))


def ideal_from_raw_jacobian(xy: np.ndarray, dist: np.ndarray, K: np.ndarray) -> np.ndarray:
    """d(ideal px) / d(raw px) at undistorted normalised coordinates ``xy`` (..., 2); shape (..., 2, 2).

    K: the camera matrix (3, 3) [px]. With A = K[:2, :2], ideal = A xy + c and raw = A xy_d + c, so
    d ideal / d raw = A D^-1 A^-1, D = :func:`distortion_jacobian` (inf/NaN where D is singular).
    """
    D = distortion_jacobian(xy, dist)  # d xy_d / d xy
    A = K[:2, :2]  # d px / d normalised (same for ideal and raw)
    Ainv = np.linalg.inv(A)
    Dinv = np.stack([solve_2x2(D, np.broadcast_to(col, xy.shape)) for col in Ainv.T], axis=-1)
    return A @ Dinv
