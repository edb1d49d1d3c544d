"""Pinhole cameras with OpenCV 5-parameter distortion, and the rig that holds them.

Conventions, stated once for the whole project:

* Poses are **cam_from_world**: ``xyz_cam = R @ xyz_world + t``, ``R = Rodrigues(rvec)`` (the
  aniposelib / OpenCV / COLMAP convention). GTSAM's ``Pose3`` of a camera is world_from_cam;
  :meth:`Camera.world_from_cam` is the one place that converts.
* Camera axes: x right, y down, z forward (optical axis).
* Pixels follow OpenCV: (0, 0) is the centre of the top-left pixel, u to the right, v downward.
* "Distorted" pixels are raw image coordinates; "ideal" pixels are what an undistorted pinhole with
  the same K would see: ``uv_ideal = K @ [x/z, y/z, 1]``. Skew ``K[0, 1]`` is honoured everywhere.
* Distortion: OpenCV (k1, k2, p1, p2, k3) on normalised coordinates.

This module does geometry only: no file formats (see :mod:`batgraph.session`), no estimation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.linalg


def _as_float(a, shape: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {arr.shape}")
    return arr


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


@dataclass(eq=False)
class Camera:
    """One calibrated camera.

    name: label used in observations.csv.
    size_wh: image size (width, height) [px].
    K: intrinsic matrix, shape (3, 3) [px]; skew in K[0, 1] is allowed.
    dist: OpenCV distortion (k1, k2, p1, p2, k3), shape (5,).
    rvec: Rodrigues rotation of cam_from_world, shape (3,) [rad].
    tvec: translation of cam_from_world, shape (3,) [m].
    pose_cov: optional covariance of the pose, shape (6, 6), in GTSAM's Pose3 tangent order
        (rotation [rad], then translation [m]) of world_from_cam; see :mod:`batgraph.session`.
    """

    name: str
    size_wh: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pose_cov: np.ndarray | None = None

    def __post_init__(self):
        self.K = _as_float(self.K, (3, 3), f"camera {self.name!r} matrix")
        self.dist = _as_float(self.dist, (5,), f"camera {self.name!r} distortions")
        self.rvec = _as_float(self.rvec, (3,), f"camera {self.name!r} rotation")
        self.tvec = _as_float(self.tvec, (3,), f"camera {self.name!r} translation")
        if self.pose_cov is not None:
            self.pose_cov = _as_float(self.pose_cov, (6, 6), f"camera {self.name!r} pose_covariance")
        self.size_wh = (int(self.size_wh[0]), int(self.size_wh[1]))
        self._R = cv2.Rodrigues(self.rvec.reshape(3, 1))[0]
        self._K_inv = np.linalg.inv(self.K)
        self._r_max = max_valid_radius(self.dist)

    # ----- pose -------------------------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        """Rotation of cam_from_world, shape (3, 3)."""
        return self._R

    @property
    def center_world(self) -> np.ndarray:
        """Camera centre in the world frame, shape (3,) [m]."""
        return -self._R.T @ self.tvec

    @property
    def P(self) -> np.ndarray:
        """Projection matrix K [R | t] to ideal pixels, shape (3, 4)."""
        return self.K @ np.hstack([self._R, self.tvec[:, None]])

    def world_from_cam(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_wc (3, 3), t_wc (3,)): the pose as GTSAM's Pose3 of a camera expects it."""
        return self._R.T, self.center_world

    def to_cam(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) [m] -> camera frame (..., 3) [m]."""
        return xyz_world_m @ self._R.T + self.tvec

    # ----- projection -------------------------------------------------------------------------
    def project(self, xyz_world_m: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project world points to pixels.

        xyz_world_m: shape (..., 3) [m].
        distort: True for raw image pixels, False for ideal (undistorted) pixels.
        Returns uv_px, shape (..., 2); NaN for points behind the camera or (with distortion)
        outside the lens's valid field (see :func:`max_valid_radius`).
        """
        xyz_cam = self.to_cam(np.asarray(xyz_world_m, dtype=float))
        z = xyz_cam[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where(z > 1e-9, xyz_cam[..., :2] / z, np.nan)
        if distort:
            r = np.linalg.norm(xy, axis=-1, keepdims=True)
            xy = np.where(r <= self._r_max, distort_normalized(xy, self.dist), np.nan)
        return self._apply_K(xy)

    def _apply_K(self, xy: np.ndarray) -> np.ndarray:
        K = self.K
        u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
        v = K[1, 1] * xy[..., 1] + K[1, 2]
        return np.stack([u, v], axis=-1)

    def _remove_K(self, uv_px: np.ndarray) -> np.ndarray:
        Ki = self._K_inv
        x = Ki[0, 0] * uv_px[..., 0] + Ki[0, 1] * uv_px[..., 1] + Ki[0, 2]
        y = Ki[1, 1] * uv_px[..., 1] + Ki[1, 2]
        return np.stack([x, y], axis=-1)

    def undistort_normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """Raw pixels (..., 2) -> undistorted normalised coordinates (x/z, y/z), shape (..., 2).

        OpenCV's ``undistortPoints`` gives the starting point; two Newton steps on the exact
        Jacobian polish it, because OpenCV's fixed-point iteration stalls at ~1e-3 px near the
        edge of a strongly distorted (GoPro-like) lens. NaN in, NaN out.
        """
        uv = np.asarray(uv_px, dtype=float)
        xy_d = self._remove_K(uv)
        flat = xy_d.reshape(-1, 2)
        ok = np.isfinite(flat).all(axis=1)
        out = np.full_like(flat, np.nan)
        if ok.any() and np.any(self.dist):
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
            xy = cv2.undistortPoints(
                flat[ok].reshape(-1, 1, 2), np.eye(3), self.dist, criteria=criteria
            ).reshape(-1, 2)
            for _ in range(2):
                resid = distort_normalized(xy, self.dist) - flat[ok]
                J = distortion_jacobian(xy, self.dist)
                with np.errstate(all="ignore"):
                    step = xy - solve_2x2(J, resid)
                    better = np.linalg.norm(distort_normalized(step, self.dist) - flat[ok], axis=-1)
                # A noisy pixel just beyond the lens's largest distorted radius has no preimage and
                # OpenCV stops near the fold, where J is singular: keep only steps that help.
                xy = np.where((better < np.linalg.norm(resid, axis=-1))[:, None], step, xy)
            out[ok] = xy
        elif ok.any():
            out[ok] = flat[ok]
        return out.reshape(xy_d.shape)

    def undistort(self, uv_px: np.ndarray) -> np.ndarray:
        """Raw pixels (..., 2) -> ideal (undistorted) pixels (..., 2)."""
        return self._apply_K(self.undistort_normalized(uv_px))

    def ideal_from_raw_jacobian(self, uv_px: np.ndarray) -> np.ndarray:
        """d(ideal px) / d(raw px) at raw pixels ``uv_px`` (..., 2); shape (..., 2, 2).

        Maps a pixel noise covariance S on the raw image to ``J S J^T`` on ideal pixels, which is
        how batgraph keeps the pixel noise model honest after removing distortion.
        """
        return self.undistort_with_jacobian(uv_px)[1]

    def undistort_with_jacobian(self, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw pixels (..., 2) -> (ideal pixels (..., 2), d(ideal px) / d(raw px) (..., 2, 2)), one undistortion."""
        xy = self.undistort_normalized(uv_px)
        D = distortion_jacobian(xy, self.dist)  # d xy_d / d xy
        A = self.K[:2, :2]  # d px / d normalised (same for ideal and raw)
        Ainv = np.linalg.inv(A)
        # ideal = A xy + c, raw = A xy_d + c  ->  d ideal / d raw = A D^-1 A^-1
        Dinv = np.stack([solve_2x2(D, np.broadcast_to(col, xy.shape)) for col in Ainv.T], axis=-1)
        return self._apply_K(xy), A @ Dinv

    def ideal_jacobian_world(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """d(ideal px) / d(xyz_world) at points (..., 3); shape (..., 2, 3) [px/m] (paper eq. 16)."""
        xyz_cam = self.to_cam(np.asarray(xyz_world_m, dtype=float))
        X, Y, Z = xyz_cam[..., 0], xyz_cam[..., 1], xyz_cam[..., 2]
        K = self.K
        J = np.zeros(xyz_cam.shape[:-1] + (2, 3))
        J[..., 0, 0] = K[0, 0] / Z
        J[..., 0, 1] = K[0, 1] / Z
        J[..., 0, 2] = -(K[0, 0] * X + K[0, 1] * Y) / Z**2
        J[..., 1, 1] = K[1, 1] / Z
        J[..., 1, 2] = -K[1, 1] * Y / Z**2
        return J @ self._R

    def in_image(self, uv_px: np.ndarray) -> np.ndarray:
        """True where raw pixels (..., 2) lie inside the image (pixel centres -0.5 .. size-0.5)."""
        w, h = self.size_wh
        u, v = uv_px[..., 0], uv_px[..., 1]
        return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)

    # ----- DLT ---------------------------------------------------------------------------------
    def to_dlt(self) -> np.ndarray:
        """The 11 DLT coefficients of this camera's pinhole (distortion ignored), shape (11,).

        ``u = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)``, v likewise with L5..L8,
        in this module's (OpenCV) pixel convention.
        """
        P = self.P
        return (P / P[2, 3]).reshape(-1)[:11]

    @classmethod
    def from_dlt(cls, name: str, coefs: np.ndarray, size_wh: tuple[int, int]) -> Camera:
        """Camera from 11 DLT coefficients (OpenCV pixel convention); exact inverse of :meth:`to_dlt`.

        K comes from an RQ decomposition of the left 3x3 block, with positive focal lengths and
        det(R) = +1; skew is kept. Distortion is zero (a DLT has none).
        """
        L = _as_float(coefs, (11,), f"camera {name!r} DLT coefficients")
        P = np.append(L, 1.0).reshape(3, 4)
        M = P[:, :3]
        if np.linalg.det(M) < 0:  # the DLT's overall scale is negative: flip it
            P = -P
            M = P[:, :3]
        K, R = scipy.linalg.rq(M)
        S = np.diag(np.sign(np.diag(K)))  # make K's diagonal positive (S @ S = I)
        K, R = K @ S, S @ R
        scale = K[2, 2]
        t = np.linalg.solve(K, P[:, 3])
        K = K / scale
        rvec = cv2.Rodrigues(R)[0].reshape(3)
        return cls(name=name, size_wh=size_wh, K=K, dist=np.zeros(5), rvec=rvec, tvec=t)


@dataclass(eq=False)
class Rig:
    """The cameras of a session, in calibration.toml order."""

    cameras: list[Camera]

    def __post_init__(self):
        self._index = {c.name: i for i, c in enumerate(self.cameras)}

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        return self._index[name]

    def __getitem__(self, name_or_index: str | int) -> Camera:
        if isinstance(name_or_index, str):
            return self.cameras[self._index[name_or_index]]
        return self.cameras[name_or_index]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def project(self, xyz_world_m: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project points (..., 3) into every camera: uv_px of shape (n_cams, ..., 2), NaN if not visible."""
        return np.stack([c.project(xyz_world_m, distort=distort) for c in self.cameras])
