"""Pinhole cameras with OpenCV 5-parameter distortion, and the rig that holds them.

The conventions (cam_from_world poses, OpenCV pixels and distortion, ideal vs raw pixels) are stated
in :mod:`batgraph.geometry`, whose pure functions do every conversion and projection; the methods
here apply them to one camera's K, dist, rvec, tvec. No file formats (see :mod:`batgraph.session`),
no estimation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import dlt, pinhole, pose
from .geometry.distortion import (  # noqa: F401  (re-exported: part of this module's interface)
    distort_normalized,
    distortion_jacobian,
    ideal_from_raw_jacobian,
    max_valid_radius,
    solve_2x2,
    undistort_normalized,
)


def _as_float(a, shape: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {arr.shape}")
    return arr


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
    fps: this camera's frame rate [Hz]; None = the session's.
    time_offset_s: its frame j is exposed at ``j / fps + time_offset_s`` on the session clock [s].
    readout_s: rolling-shutter readout [s]: raw image row v is read ``readout_s * v / height`` after row 0
        (0 = global shutter). time_offset_sd_s, readout_sd_s: their standard deviations when estimated.
    """

    name: str
    size_wh: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pose_cov: np.ndarray | None = None
    fps: float | None = None
    time_offset_s: float = 0.0
    readout_s: float = 0.0
    time_offset_sd_s: float | None = None
    readout_sd_s: float | None = None

    def __post_init__(self):
        self.K = _as_float(self.K, (3, 3), f"camera {self.name!r} matrix")
        self.dist = _as_float(self.dist, (5,), f"camera {self.name!r} distortions")
        self.rvec = _as_float(self.rvec, (3,), f"camera {self.name!r} rotation")
        self.tvec = _as_float(self.tvec, (3,), f"camera {self.name!r} translation")
        if self.pose_cov is not None:
            self.pose_cov = _as_float(self.pose_cov, (6, 6), f"camera {self.name!r} pose_covariance")
        self.size_wh = (int(self.size_wh[0]), int(self.size_wh[1]))
        self._R = pose.R_from_rvec(self.rvec)
        self._K_inv = np.linalg.inv(self.K)
        self._r_max = max_valid_radius(self.dist)
        self.fps = None if self.fps is None else float(self.fps)
        self.time_offset_s, self.readout_s = float(self.time_offset_s), float(self.readout_s)

    # ----- timing -----------------------------------------------------------------------------
    def frame_rate(self, session_fps: float) -> float:
        """This camera's frame rate [Hz]: its own ``fps``, else the session's."""
        return float(session_fps) if self.fps is None else self.fps

    def on_session_clock(self, session_fps: float) -> bool:
        """True when its frame k is the session's frame k, exposed all at once (no offset, no readout)."""
        return self.frame_rate(session_fps) == float(session_fps) and self.time_offset_s == 0 and self.readout_s == 0

    def capture_time_s(self, frame: np.ndarray, v_raw_px: np.ndarray, session_fps: float) -> np.ndarray:
        """Session-clock time [s] at which raw row ``v_raw_px`` of this camera's own frame ``frame`` was read."""
        rate = self.frame_rate(session_fps)
        return np.asarray(frame) / rate + self.time_offset_s + self.readout_s * np.asarray(v_raw_px) / self.size_wh[1]

    # ----- pose -------------------------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        """Rotation of cam_from_world, shape (3, 3)."""
        return self._R

    @property
    def center_world(self) -> np.ndarray:
        """Camera centre in the world frame, shape (3,) [m]."""
        return self.world_from_cam()[1]

    @property
    def P(self) -> np.ndarray:
        """Projection matrix K [R | t] to ideal pixels, shape (3, 4)."""
        return pinhole.projection_matrix(self.K, self._R, self.tvec)

    def world_from_cam(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_wc (3, 3), t_wc (3,)): the pose as GTSAM's Pose3 of a camera expects it."""
        return pose.world_from_cam(self._R, self.tvec)

    def to_cam(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) [m] -> camera frame (..., 3) [m]."""
        return pose.transform_points(self._R, self.tvec, xyz_world_m)

    # ----- projection -------------------------------------------------------------------------
    def project(self, xyz_world_m: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project world points to pixels.

        xyz_world_m: shape (..., 3) [m].
        distort: True for raw image pixels, False for ideal (undistorted) pixels.
        Returns uv_px, shape (..., 2); NaN for points behind the camera or (with distortion)
        outside the lens's valid field (see :func:`max_valid_radius`).
        """
        return pinhole.project(xyz_world_m, self.K, self._R, self.tvec, self.dist if distort else None,
                               self._r_max)

    def undistort_normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """Raw pixels (..., 2) -> undistorted normalised coordinates (x/z, y/z), shape (..., 2).

        See :func:`batgraph.geometry.distortion.undistort_normalized` (OpenCV, then three Newton steps).
        NaN in, NaN out.
        """
        return undistort_normalized(pinhole.normalized_from_pixels(np.asarray(uv_px, dtype=float), self._K_inv),
                                    self.dist)

    def undistort(self, uv_px: np.ndarray) -> np.ndarray:
        """Raw pixels (..., 2) -> ideal (undistorted) pixels (..., 2)."""
        return pinhole.pixels_from_normalized(self.undistort_normalized(uv_px), self.K)

    def ideal_from_raw_jacobian(self, uv_px: np.ndarray) -> np.ndarray:
        """d(ideal px) / d(raw px) at raw pixels ``uv_px`` (..., 2); shape (..., 2, 2).

        Maps a pixel noise covariance S on the raw image to ``J S J^T`` on ideal pixels, which is
        how batgraph keeps the pixel noise model honest after removing distortion.
        """
        return self.undistort_with_jacobian(uv_px)[1]

    def undistort_with_jacobian(self, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw pixels (..., 2) -> (ideal pixels (..., 2), d(ideal px) / d(raw px) (..., 2, 2)), one undistortion."""
        xy = self.undistort_normalized(uv_px)
        return pinhole.pixels_from_normalized(xy, self.K), ideal_from_raw_jacobian(xy, self.dist, self.K)

    def ideal_jacobian_world(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """d(ideal px) / d(xyz_world) at points (..., 3); shape (..., 2, 3) [px/m] (paper eq. 16)."""
        return pinhole.point_jacobian(self.P, xyz_world_m)

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
        K, R, t = dlt.krt_from_projection(dlt.dlt_matrix(L))
        rvec = pose.rvec_from_R(R)
        return cls(name=name, size_wh=size_wh, K=K, dist=np.zeros(5), rvec=rvec, tvec=t)


@dataclass(eq=False)
class Rig:
    """The cameras of a session, in calibration.toml order.

    world_mirror: (3,) of +-1: the rig's world is right-handed; a user's world that is mirrored (a DLT
        calibration may be left-handed) is ``x_user = world_mirror * x_world`` (``[metadata] world_mirror``
        in calibration.toml). Results are reported in the user's frame (:meth:`to_user`).
    """

    cameras: list[Camera]
    world_mirror: np.ndarray = field(default_factory=lambda: np.ones(3))

    def __post_init__(self):
        self._index = {c.name: i for i, c in enumerate(self.cameras)}
        self.world_mirror = np.asarray(self.world_mirror, dtype=float)
        if self.world_mirror.shape != (3,) or not np.all(np.abs(self.world_mirror) == 1):
            raise ValueError(f"world_mirror must be three values of +-1, got {self.world_mirror!r}")

    @property
    def mirrored(self) -> bool:
        """True when the user's world is left-handed (see ``world_mirror``)."""
        return bool(np.prod(self.world_mirror) < 0)

    def to_user(self, xyz_m: np.ndarray, cov_m2: np.ndarray | None = None):
        """Points (..., 3) [m] (and covariances (..., 3, 3) [m^2]) from the rig's world to the user's frame.

        The mirror is its own inverse, so the same call converts back. Returns xyz, or (xyz, cov) when
        cov_m2 is given.
        """
        m = self.world_mirror
        xyz = np.asarray(xyz_m) * m
        return xyz if cov_m2 is None else (xyz, np.asarray(cov_m2) * m[:, None] * m[None, :])

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

    def on_session_clock(self, session_fps: float) -> bool:
        """True when every camera exposes the session's frame k all at once (:meth:`Camera.on_session_clock`)."""
        return all(c.on_session_clock(session_fps) for c in self.cameras)

    def project(self, xyz_world_m: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project points (..., 3) into every camera: uv_px of shape (n_cams, ..., 2), NaN if not visible."""
        return np.stack([c.project(xyz_world_m, distort=distort) for c in self.cameras])

    def fundamental(self, a: int, b: int) -> np.ndarray:
        """The fundamental matrix F (3, 3) with x_b^T F x_a = 0 for ideal (undistorted) pixels x_a of camera a and
        x_b of camera b, homogeneous."""
        ca, cb = self.cameras[a], self.cameras[b]
        R = cb.R @ ca.R.T  # cam_b from cam_a
        t = cb.tvec - R @ ca.tvec
        E = pose.skew(t) @ R  # the essential matrix
        return np.linalg.inv(cb.K).T @ E @ np.linalg.inv(ca.K)
