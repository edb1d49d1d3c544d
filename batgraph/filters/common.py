"""What the paper's EKF and UKF share: the stacked pinhole measurement of one frame (eq. 6-8, 16), its
noise (ideal-pixel covariance plus eq. 10), and the frame loop with triangulation initialisation.

The filters' own predict/update equations live in :mod:`.ekf` and :mod:`.ukf`; nothing here is
robust, smoothed or iterated.

State layout: the stacked positions of the markers currently in the filter, ``x`` of shape (3n,)
[m, world], in the order the markers entered (a marker enters at its first triangulated frame and
never leaves); ``P`` of shape (3n, 3n) [m^2]. Measurement rows are stacked camera-major as in
eq. 8: (camera 0: its markers in label order, camera 1: ...), two rows (u, v) per seen pair, in
ideal (undistorted) pixels. Unseen pairs have no rows (the paper's occlusion trimming). The pinhole
itself (eq. 6, 16) and its pose Jacobian are :mod:`batgraph.geometry.pinhole`'s.
With many rows (30 cameras x 180 markers: ~10,000) the updates switch to the same algebra through
the matrix inversion lemma (see LARGE_ROWS), so Q is kept factored (:class:`MeasurementNoise`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from ..camera import Rig
from ..geometry import pinhole
from ..measurement import IdealObservations
from ..motion import random_walk_sigma_m
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import triangulate_ideal

INIT_DESCRIPTION = (
    "each marker enters the stacked state at its first frame with a finite per-frame triangulation "
    "(batgraph.triangulate: linear DLT on >= 2 views): position = triangulated point, covariance "
    "block = its first-order triangulation covariance, zero cross-covariance; that frame's "
    "observations of the marker are not fed to the filter again (the triangulation already used "
    "them); before that frame the marker is not in the state and is reported NaN. The triangulation "
    "covariance has pixel noise only (no camera pose covariance)"
)


@dataclass
class RigArrays:
    """The rig as stacked arrays, so one frame's measurement is projected without a loop over cameras.

    proj: K [R | t] to ideal pixels, shape (C, 3, 4) (eq. 6: ``K Pi_0 H_c0``).
    R, t: rotation (C, 3, 3) and translation (C, 3) [m] of cam_from_world.
    pose_cov: covariance of each camera's world_from_cam pose in GTSAM's Pose3 tangent order
        [rotation rad, translation m], shape (C, 6, 6); zero for cameras without one; None when no
        camera has one.
    """

    proj: np.ndarray
    R: np.ndarray
    t: np.ndarray
    pose_cov: np.ndarray | None

    @classmethod
    def from_rig(cls, rig: Rig) -> RigArrays:
        covs = [c.pose_cov for c in rig]
        pose_cov = None
        if any(c is not None for c in covs):
            pose_cov = np.stack([np.zeros((6, 6)) if c is None else c for c in covs])
        return cls(np.stack([c.P for c in rig]), np.stack([c.R for c in rig]),
                   np.stack([c.tvec for c in rig]), pose_cov)


def pose_jacobian(rig: RigArrays, cam: np.ndarray, xyz_world_m: np.ndarray) -> np.ndarray:
    """d(ideal px)/d(xi) for the camera pose perturbed as ``world_from_cam * exp(xi)``, shape (p, 2, 6).

    cam: camera index of each row, shape (p,); xyz_world_m: points, shape (p, 3) [m]; xi in GTSAM's
    Pose3 tangent order (see :func:`batgraph.geometry.pinhole.pose_jacobian`).
    """
    return pinhole.pose_jacobian(rig.proj[cam], rig.R[cam], rig.t[cam], xyz_world_m)


@dataclass
class FrameMeasurement:
    """The trimmed stacked measurement of one frame (eq. 8-9 with unseen rows dropped).

    y: observed ideal pixels, shape (2p,) [px], rows (u, v) per seen pair, camera-major.
    cov_px2: their pixel noise, shape (p, 2, 2) [px^2] (already mapped through the undistortion).
    cam: camera index per pair, shape (p,); slot: the marker's position in the state, shape (p,).
    rig: the stacked rig.
    """

    y: np.ndarray
    cov_px2: np.ndarray
    cam: np.ndarray
    slot: np.ndarray
    rig: RigArrays

    @property
    def n_pairs(self) -> int:
        return len(self.cam)

    def points(self, x: np.ndarray) -> np.ndarray:
        """The measured markers' positions from state(s) x (..., 3n): shape (..., p, 3)."""
        return x.reshape(x.shape[:-1] + (-1, 3))[..., self.slot, :]

    def h(self, x: np.ndarray) -> np.ndarray:
        """Measurement function h (eq. 8) of state(s) x (..., 3n) -> predicted ideal pixels (..., 2p)."""
        uv = pinhole.project_ideal(self.rig.proj[self.cam], self.points(x))
        return uv.reshape(uv.shape[:-2] + (-1,))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Dense H = dh/dx at x (3n,), shape (2p, 3n) [px/m]: eq. 16 blocks placed as eq. 17-18."""
        p, n3 = self.n_pairs, x.shape[-1]
        J = pinhole.point_jacobian(self.rig.proj[self.cam], self.points(x))
        H = np.zeros((2 * p, n3))
        rows = 2 * np.arange(p)[:, None, None] + np.arange(2)[None, :, None]
        cols = 3 * self.slot[:, None, None] + np.arange(3)[None, None, :]
        H[rows, cols] = J
        return H

    def noise(self, x: np.ndarray) -> MeasurementNoise:
        """Measurement covariance Q at state x (3n,), (2p, 2p) [px^2], kept in factored form.

        The per-observation 2x2 pixel blocks on the diagonal, plus eq. 10 for cameras with a pose
        covariance: ``G Sigma_p G^T`` with G = :func:`pose_jacobian` placed in its camera's six
        columns, so rows of one camera share its pose and different cameras' poses are independent.
        As in the paper, this calibration term is re-drawn independently every frame (a real pose
        error is the same on every frame; the smoother, batgraph.solver, models that with camera variables).
        """
        if self.rig.pose_cov is None:
            return MeasurementNoise(self.cov_px2)
        p, C = self.n_pairs, len(self.rig.proj)
        G = np.zeros((p, 2, C, 6))
        G[np.arange(p), :, self.cam, :] = pose_jacobian(self.rig, self.cam, self.points(x))
        Sigma = np.zeros((C, 6, C, 6))
        Sigma[np.arange(C), :, np.arange(C), :] = self.rig.pose_cov
        return MeasurementNoise(self.cov_px2, G.reshape(2 * p, 6 * C), Sigma.reshape(6 * C, 6 * C))


@dataclass
class MeasurementNoise:
    """Q = blockdiag(blocks) + G Sigma G^T, shape (m, m) [px^2], m = 2p; formed only on request.

    blocks: per-observation pixel covariances, shape (p, 2, 2); G: (m, k), Sigma: (k, k) PSD, or
    None (no eq. 10 term). With thousands of rows the dense Q would not fit in memory comfortably;
    :meth:`solve` applies Q^-1 by the matrix inversion lemma at O(m k^2) instead.
    """

    blocks: np.ndarray
    G: np.ndarray | None = None
    Sigma: np.ndarray | None = None

    def dense(self) -> np.ndarray:
        p = len(self.blocks)
        Q = np.zeros((p, 2, p, 2))
        Q[np.arange(p), :, np.arange(p), :] = self.blocks
        Q = Q.reshape(2 * p, 2 * p)
        if self.G is not None:
            Q += self.G @ self.Sigma @ self.G.T
        return Q

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Q^-1 B for B of shape (m,) or (m, j).

        Woodbury in the form that never inverts Sigma (cameras without a pose covariance have zero
        blocks): Q^-1 = D^-1 - D^-1 G Sigma (I + G^T D^-1 G Sigma)^-1 G^T D^-1, D = blockdiag.
        """
        Dinv = np.linalg.inv(self.blocks)  # (p, 2, 2)
        shape = B.shape
        B2 = B.reshape(len(self.blocks), 2, -1)
        out = (Dinv @ B2).reshape(shape)
        if self.G is not None:
            DinvG = (Dinv @ self.G.reshape(len(self.blocks), 2, -1)).reshape(self.G.shape)
            inner = np.eye(self.G.shape[1]) + self.G.T @ DinvG @ self.Sigma
            out = out - DinvG @ (self.Sigma @ np.linalg.solve(inner, self.G.T @ out))
        return out


def noise_solver(Q: np.ndarray | MeasurementNoise) -> Callable[[np.ndarray], np.ndarray]:
    """B -> Q^-1 B for a dense (m, m) Q (Cholesky) or a :class:`MeasurementNoise` (Woodbury)."""
    if isinstance(Q, MeasurementNoise):
        return Q.solve
    factor = scipy.linalg.cho_factor(Q)
    return lambda B: scipy.linalg.cho_solve(factor, B)


def dense_noise(Q: np.ndarray | MeasurementNoise) -> np.ndarray:
    """Q as a dense (m, m) array."""
    return Q.dense() if isinstance(Q, MeasurementNoise) else Q


# Above this many measurement rows (and more rows than the state has entries, resp. sigma points),
# the updates use the matrix inversion lemma instead of factorising the (m, m) innovation
# covariance S: the same algebra, O(n^3 + m n^2) instead of O(m^3); at 30 cameras x 180 markers
# (m ~ 10,000) that is seconds instead of minutes per frame.
LARGE_ROWS = 1000


def symmetrize(P: np.ndarray) -> np.ndarray:
    """(P + P^T) / 2: removes round-off asymmetry, which otherwise builds up over hundreds of frames
    until a Cholesky factorisation fails; in exact arithmetic the paper's P is already symmetric."""
    return 0.5 * (P + P.T)


Predict = Callable[[np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]]
Update = Callable[[np.ndarray, np.ndarray, FrameMeasurement], tuple[np.ndarray, np.ndarray]]


def run_filter(method: str, session: Session, dense: DenseObservations, ideal: IdealObservations,
               options: Options, predict: Predict, update: Update, info: dict | None = None) -> Estimate:
    """Run a random-walk filter over every frame (the loop both of the paper's filters share).

    predict(x, P, sigma_m2) -> (x, P): one motion step with process covariance sigma_m2 * I (eq. 5).
    update(x, P, meas) -> (x, P): the correction with one frame's trimmed measurement.
    Per frame k: predict the markers already in the state; insert those first triangulated at k
    (see INIT_DESCRIPTION); update with frame k's observations of the others; report x and the
    3x3 diagonal blocks of P. sigma_m comes from batgraph.motion.random_walk_sigma_m.

    dense, ideal: the session's observations, (C, F, M, ...) as in batgraph.session/measurement.
    Returns an Estimate with xyz_m (F, M, 3), cov_m2 (F, M, 3, 3), NaN before a marker enters.
    """
    t0 = time.perf_counter()
    rig = RigArrays.from_rig(session.rig)
    C, F, M = ideal.seen.shape
    sigma_m = random_walk_sigma_m(session.motion, session.fps)
    # Triangulate the very ideal observations the filter uses, so the initial covariance and the
    # filter's measurement noise are one model (triangulate(rig, dense, sigma) would recompute them).
    tri_xyz, tri_cov = triangulate_ideal(session.rig, ideal)
    ok = np.isfinite(tri_xyz).all(-1) & np.isfinite(tri_cov).all((-2, -1))
    first = np.where(ok.any(axis=0), ok.argmax(axis=0), -1)  # (M,), -1: never enters

    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    x, P = np.zeros(0), np.zeros((0, 0))
    order = np.zeros(0, int)  # marker index of each state slot
    slot_of = np.full(M, -1)
    frames = tqdm(range(F), desc=method, unit="frame", disable=not options.progress, leave=False)
    # One BLAS thread: per-frame matrices are a few hundred wide, and a multithreaded BLAS spends
    # more time synchronising than computing on them (measured 100x slower Cholesky on a busy
    # 2-core machine: 16 ms vs 0.17 ms at 226 x 226).
    with threadpool_limits(limits=1, user_api="blas"):
        for k in frames:
            if len(order):
                x, P = predict(x, P, sigma_m**2)
            old = slot_of >= 0
            new = np.flatnonzero(first == k)
            if len(new):
                n0, n1 = len(order), len(order) + len(new)
                x = np.concatenate([x, tri_xyz[k, new].ravel()])
                P_new = np.zeros((n1, 3, n1, 3))
                P_new[:n0, :, :n0, :] = P.reshape(n0, 3, n0, 3)
                P_new[np.arange(n0, n1), :, np.arange(n0, n1), :] = tri_cov[k, new]
                P = P_new.reshape(3 * n1, 3 * n1)
                slot_of[new] = np.arange(n0, n1)
                order = np.concatenate([order, new])
            cam, mk = np.nonzero(ideal.seen[:, k, :] & old[None, :])  # camera-major, as eq. 8
            if len(cam):
                meas = FrameMeasurement(ideal.uv_px[cam, k, mk].ravel(), ideal.cov_px2[cam, k, mk],
                                        cam, slot_of[mk], rig)
                x, P = update(x, P, meas)
            if len(order):
                n = len(order)
                xyz[k, order] = x.reshape(n, 3)
                cov[k, order] = P.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    return Estimate(method, xyz, cov, np.zeros((C, F, M), bool), time.perf_counter() - t0,
                    {"sigma_m": sigma_m, "init": INIT_DESCRIPTION, **(info or {})})
