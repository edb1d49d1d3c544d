"""GTSAM factor-graph construction for batgraph: variable keys, projection, motion and prior factors.

The cost is the one in the project's cost spec (see :mod:`batgraph.graph`): projection factors on
ideal (undistorted) pixels with the mapped pixel noise, a random-walk, constant-velocity or
constant-acceleration motion prior along every marker's frames, weak gauge priors on each marker's
first frame, and (where the calibration carries a pose covariance) camera poses as variables with
priors. This module builds factors and initial values only; solving is in :mod:`batgraph.graph.smoother` and
:mod:`batgraph.graph.filter`. What needs no GTSAM (constants, the motion model's parameters, the initial
track, residuals and the rejection rule) is in :mod:`batgraph.graph.cost` and re-exported here.

Why ideal pixels and not GTSAM's Cal3DS2 on raw pixels: Cal3DS2 has no k3 (GoPro-like lenses need
it), while undistorting once with all five OpenCV coefficients and carrying the pixel noise through
the undistortion Jacobian (:mod:`batgraph.measurement`) handles every lens the rig file can
describe. The two routes agree to first order in the noise; ``tests/test_graph.py`` solves the
same k3 = 0 scene both ways and bounds their difference.
"""

from __future__ import annotations

from collections.abc import Mapping

import gtsam
import numpy as np

from ..camera import Camera, Rig
from ..geometry import pose as geometry_pose
from ..measurement import IdealObservations
from .cost import (  # noqa: F401  (re-exported: the numpy part of the cost, importable without GTSAM)
    CHI2_2DOF_999,
    MOTION_MODELS,
    PRIOR_ACCELERATION_SIGMA_MPS2,
    PRIOR_POSITION_SIGMA_M,
    PRIOR_VELOCITY_SIGMA_MPS,
    REJECT_SQ_RESIDUAL,
    ROBUST_LOSSES,
    MotionModel,
    acceleration_mps2,
    initial_track,
    motion_model,
    noise_scale,
    outlier_flags,
    scaled_motion,
    to_exclude,
    velocity_mps,
    whitened_sq_residuals,
    without_observations,
)

_FRAME_BITS = 32  # key index = marker << 32 | frame: room for 2^32 frames and 2^24 markers
# Symbols: positions 'x', velocities 'v', accelerations 'a', camera poses 'c'. Accelerations and
# velocities sort before positions on purpose: see _LinearMotionFactorMaker.


# ----- keys ---------------------------------------------------------------------------------------
def p_key(m: int, k: int) -> int:
    """Key of marker m's position at frame index k (Point3, world [m])."""
    return gtsam.symbol("x", (m << _FRAME_BITS) | k)


def v_key(m: int, k: int) -> int:
    """Key of marker m's velocity at frame index k, stored as the displacement per frame.

    The variable is u = v dt (Point3 used as a vector, world [m per frame]), not v [m/s]: the cost is
    the same, but p and u then share a unit, and GTSAM's Cholesky (which declares a clique
    indeterminate when the last two diagonal entries of its R differ by more than 2^12) keeps
    working up to q = 1e6 m^2/s^3, where v in m/s made it fail. Use :func:`velocity_mps`.
    """
    return gtsam.symbol("v", (m << _FRAME_BITS) | k)


def a_key(m: int, k: int) -> int:
    """Key of marker m's acceleration at frame index k (constant acceleration), stored as w = a dt^2
    (Point3 used as a vector, world [m per frame^2]; the same reason as :func:`v_key`).
    Use :func:`acceleration_mps2`."""
    return gtsam.symbol("a", (m << _FRAME_BITS) | k)


def state_keys(model: MotionModel, m: int, k: int) -> list[int]:
    """The keys of marker m's state at frame index k: [p] (random walk), [p, u], or [p, u, w]."""
    return [p_key(m, k), v_key(m, k), a_key(m, k)][:model.order + 1]


def length_key(s: int) -> int:
    """Key of segment s's length (a 1-vector [m]; segment-length factors, batgraph.graph.rigid)."""
    return gtsam.symbol("l", s)


def pose_key(c: int) -> int:
    """Key of camera c's pose (Pose3, world_from_cam) when cameras are variables."""
    return gtsam.symbol("c", c)


# ----- motion ---------------------------------------------------------------------------------------
def whitened_motion_blocks(model: MotionModel) -> np.ndarray:
    """Whitened Jacobian of the motion residual of ``model`` (constant velocity or acceleration) in the
    graph's variables, shape (d, 2 d), columns [x_k, x_k+1] with x = [p, u = v dt (, w = a dt^2)].

    e = x_k+1 - A x_k with A, Q from :func:`batgraph.graph.cost.scaled_motion` (batgraph.motion's Q in
    the scaled state); W^T W = Q^-1, so 0.5 |W [-A, I] x|^2 = 0.5 e^T Q^-1 e exactly.
    """
    A, Q1, _ = scaled_motion(model.name, model.dt_s)
    W = np.linalg.cholesky(np.linalg.inv(noise_scale(model.name, model.level) * Q1)).T
    return W @ np.hstack([-A, np.eye(len(A))])


class _LinearMotionFactorMaker:
    """Builds the 2n-key motion LinearContainerFactor (n = 2 variables per frame: p, u; n = 3: p, u, w)
    for given keys, from the whitened rows R (d, 6 n) of :func:`whitened_motion_blocks` (blocks precomputed).

    GTSAM's Python JacobianFactor constructors take at most three keys, so the factor is made from its
    information matrix: one 2-key HessianFactor per pair of keys (each key's own block in its first
    pair), summed into one HessianFactor (exact), converted by GTSAM's Cholesky into a d-row
    JacobianFactor. That Cholesky pivots in sorted key order, i.e. (w_k, w_k+1, u_k, u_k+1, p_k, p_k+1)
    with the symbols chosen here; its first d columns must have full rank (for constant velocity
    (u_k, u_k+1), for constant acceleration (w_k, w_k+1, u_k): both are; the positions alone would not
    be). The information is scaled to unit maximum diagonal before that Cholesky (its zero-pivot
    threshold is absolute) and the scale is returned through the noise sigmas, so the whitened rows
    reproduce R exactly. The factor is linear in vector-space variables, so a LinearContainerFactor
    linearised at zero is exact everywhere (tested). (LinearContainerFactor.rekey shares the wrapped
    factor between copies, so every factor is built afresh.)
    """

    def __init__(self, R: np.ndarray):
        H = R.T @ R
        self._rows = len(R)
        n = H.shape[0] // 3
        self._scale = 1.0 / np.diag(H).max()
        b = (H * self._scale).reshape(n, 3, n, 3).transpose(0, 2, 1, 3)  # [i, j] = (3, 3)
        Z = np.zeros((3, 3))
        first = {i: (i, i + 1) if i < n - 1 else (n - 2, n - 1) for i in range(n)}  # the pair holding b[i, i]
        self._pairs = [(i, j, b[i, i] if first[i] == (i, j) else Z, b[i, j].copy(),
                        b[j, j] if first[j] == (i, j) else Z) for i in range(n) for j in range(i + 1, n)]
        self._sigmas = np.full(self._rows, np.sqrt(self._scale))
        self._z, self._zero = np.zeros(3), np.zeros(3)

    def __call__(self, keys: list[int]) -> gtsam.LinearContainerFactor:
        z = self._z
        parts = gtsam.GaussianFactorGraph()
        for i, j, Gii, Gij, Gjj in self._pairs:
            parts.push_back(gtsam.HessianFactor(keys[i], keys[j], Gii, Gij, z, Gjj, z, 0.0))
        jac = gtsam.JacobianFactor(gtsam.HessianFactor(parts))
        if jac.rows() != self._rows or sorted(jac.keys()) != sorted(keys):
            raise RuntimeError(f"motion factor has {jac.rows()} rows, keys {list(jac.keys())}")
        jac.setModel(False, self._sigmas)
        zero = gtsam.Values()
        for key in keys:
            zero.insert(key, self._zero)
        return gtsam.LinearContainerFactor(jac, zero)


class MotionFactors:
    """Factory of motion factors between frames k and k+1 of marker m (pre-built noise/template)."""

    def __init__(self, model: MotionModel):
        self.model = model
        if model.has_velocity:
            self._make = _LinearMotionFactorMaker(whitened_motion_blocks(model))
        else:
            self._noise = gtsam.noiseModel.Isotropic.Sigma(3, model.sigma_m)  # [m] per axis per frame
            self._zero = np.zeros(3)

    def between(self, m: int, k: int) -> gtsam.NonlinearFactor:
        """The factor joining the state (p, u, w as the model has them) of marker m at frames k and k + 1."""
        if self.model.has_velocity:
            return self._make(state_keys(self.model, m, k) + state_keys(self.model, m, k + 1))
        return gtsam.BetweenFactorPoint3(p_key(m, k), p_key(m, k + 1), self._zero, self._noise)

    def chain(self, m: int, frames: range) -> list[gtsam.NonlinearFactor]:
        """Motion factors along consecutive frame indices ``frames`` of marker m."""
        return [self.between(m, k) for k in frames[:-1]]


def prior_factors(model: MotionModel, m: int, k: int, xyz_m: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """Weak gauge priors on marker m's first frame k: p ~ N(xyz_m, (10 m)^2 I), v ~ N(0, (10 m/s)^2 I)
    (constant velocity and acceleration), a ~ N(0, (1000 m/s^2)^2 I) (constant acceleration).

    (The velocity prior is on u = v dt, so its sigma is 10 m/s * dt [m/frame]: the same prior; the
    acceleration prior is on w = a dt^2, sigma 1000 m/s^2 * dt^2.)
    """
    out = [gtsam.PriorFactorPoint3(p_key(m, k), np.asarray(xyz_m, float),
                                   gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_POSITION_SIGMA_M))]
    if model.has_velocity:
        out.append(gtsam.PriorFactorPoint3(v_key(m, k), np.zeros(3),
                                           gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_VELOCITY_SIGMA_MPS * model.dt_s)))
    if model.has_acceleration:
        sigma_w = PRIOR_ACCELERATION_SIGMA_MPS2 * model.dt_s**2
        out.append(gtsam.PriorFactorPoint3(a_key(m, k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma_w)))
    return out


# ----- cameras and projections ----------------------------------------------------------------------
def gtsam_calibration(cam: Camera) -> gtsam.Cal3_S2:
    """Cal3_S2(fx, fy, skew, cx, cy) of ``cam``'s K (ideal pixels)."""
    K = cam.K
    return gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])


def gtsam_camera(cam: Camera) -> gtsam.PinholeCameraCal3_S2:
    """The ideal-pixel pinhole of ``cam`` as GTSAM sees it (Pose3 = world_from_cam, see batgraph.geometry.pose)."""
    R_wc, t_wc = cam.world_from_cam()
    return gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(R_wc), t_wc), gtsam_calibration(cam))


def pixel_noise(cov_px2: np.ndarray, robust: str, robust_k: float) -> gtsam.noiseModel.Base:
    """Noise of one ideal-pixel observation: Gaussian with covariance ``cov_px2`` (2, 2) [px^2], robustified.

    Huber/Cauchy act on the norm of the whitened 2-vector, threshold ``robust_k`` in sigmas.
    """
    base = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov_px2, float))
    if robust == "none":
        return base
    if robust == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), base)
    if robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_k), base)
    raise ValueError(f"robust loss must be one of {ROBUST_LOSSES}, got {robust!r}")


class ObservationFactors:
    """Projection factors of one session's ideal observations, and the cameras they use.

    Cameras without ``pose_cov`` are fixed: TriangulationFactorCal3_S2 on the Point3 alone. Cameras
    with ``pose_cov`` (6x6, Pose3 tangent order [rot rad, trans m] of world_from_cam) are Pose3
    variables with a PriorFactorPose3 and GenericProjectionFactorCal3_S2 observations: the graph
    form of the paper's eq. 10 (calibration uncertainty reaches the 3D covariances through the
    shared camera variables instead of an inflated measurement covariance).
    """

    def __init__(self, rig: Rig, ideal: IdealObservations, robust: str = "huber", robust_k: float = 2.0):
        if robust not in ROBUST_LOSSES:
            raise ValueError(f"robust loss must be one of {ROBUST_LOSSES}, got {robust!r}")
        self.rig, self.ideal, self.robust, self.robust_k = rig, ideal, robust, robust_k
        self.cameras = [gtsam_camera(c) for c in rig]
        self.calibrations = [gtsam_calibration(c) for c in rig]  # owned objects (the factor keeps a shared_ptr)
        self.variable = np.array([c.pose_cov is not None for c in rig])
        self._seen = ideal.seen  # (C, F, M)

    @property
    def any_variable(self) -> bool:
        return bool(self.variable.any())

    def camera_priors(self) -> tuple[list[gtsam.NonlinearFactor], gtsam.Values]:
        """Pose priors and initial poses of the variable cameras (empty when all are fixed)."""
        factors, values = [], gtsam.Values()
        for c in np.flatnonzero(self.variable):
            pose = self.cameras[c].pose()
            noise = gtsam.noiseModel.Gaussian.Covariance(self.rig[int(c)].pose_cov)
            factors.append(gtsam.PriorFactorPose3(pose_key(int(c)), pose, noise))
            values.insert(pose_key(int(c)), pose)
        return factors, values

    def frame(self, k: int, markers: np.ndarray) -> list[gtsam.NonlinearFactor]:
        """Projection factors of frame index k for the marker indices ``markers`` (int array)."""
        out = []
        uv, cov = self.ideal.uv_px, self.ideal.cov_px2
        for c, cam in enumerate(self.cameras):
            for m in np.asarray(markers)[self._seen[c, k, markers]]:
                noise = pixel_noise(cov[c, k, m], self.robust, self.robust_k)
                if self.variable[c]:
                    out.append(gtsam.GenericProjectionFactorCal3_S2(
                        uv[c, k, m], noise, pose_key(c), p_key(int(m), k), self.calibrations[c]))
                else:
                    out.append(gtsam.TriangulationFactorCal3_S2(cam, uv[c, k, m], noise, p_key(int(m), k)))
        return out

    def solved_rig(self, values: gtsam.Values) -> Rig:
        """The rig with variable cameras moved to their poses in ``values`` (fixed ones unchanged)."""
        if not self.any_variable:
            return self.rig
        cams = []
        for c, cam in enumerate(self.rig):
            if self.variable[c]:
                pose = values.atPose3(pose_key(c))  # world_from_cam
                R_cw, t_cw = geometry_pose.cam_from_world(pose.rotation().matrix(), np.asarray(pose.translation()))
                cam = Camera(cam.name, cam.size_wh, cam.K, cam.dist, geometry_pose.rvec_from_R(R_cw), t_cw,
                             cam.pose_cov)
            cams.append(cam)
        return Rig(cams)


# ----- segment lengths ----------------------------------------------------------------------------
def _segment_error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
    """|p_a - p_b| - L (1,) [m] of a segment-length factor on keys (p_a, p_b, L), with its Jacobians."""
    ka, kb, kl = this.keys()
    diff = values.atPoint3(ka) - values.atPoint3(kb)
    dist = float(np.linalg.norm(diff))
    if H is not None:
        u = (diff / max(dist, 1e-9)).reshape(1, 3)
        H[0], H[1], H[2] = u, -u, -np.ones((1, 1))
    return np.array([dist - values.atVector(kl)[0]])


def segment_graph(pairs: np.ndarray, sigma_m: float, n_frames: int) -> gtsam.NonlinearFactorGraph:
    """Segment-length factors (batgraph.graph.rigid's cost) of marker pairs (S, 2) on every frame
    0..n_frames-1: a Python CustomFactor on (p_a,k, p_b,k, length_key(s)), Gaussian noise sigma_m [m].
    Slow (a Python call per factor and iteration): the reference, not the fast path."""
    graph = gtsam.NonlinearFactorGraph()
    model = gtsam.noiseModel.Isotropic.Sigma(1, sigma_m)
    for s, (a, b) in enumerate(np.asarray(pairs, int)):
        for k in range(n_frames):
            graph.push_back(gtsam.CustomFactor(model, [p_key(int(a), k), p_key(int(b), k), length_key(s)],
                                               _segment_error))
    return graph


def insert_lengths(values: gtsam.Values, pairs: np.ndarray, n_frames: int) -> None:
    """Insert each segment's length (the median distance of its markers' positions in ``values``) where missing."""
    for s, (a, b) in enumerate(np.asarray(pairs, int)):
        if not values.exists(length_key(s)):
            d = [np.linalg.norm(values.atPoint3(p_key(int(a), k)) - values.atPoint3(p_key(int(b), k)))
                 for k in range(n_frames)]
            values.insert(length_key(s), np.array([float(np.median(d))]))


# ----- whole graphs -----------------------------------------------------------------------------------
def observation_graph(obs: ObservationFactors, markers: np.ndarray, n_frames: int) -> gtsam.NonlinearFactorGraph:
    """Camera priors and every projection factor of ``markers`` (int array) over frame indices 0..n_frames-1."""
    graph = gtsam.NonlinearFactorGraph()
    for f in obs.camera_priors()[0]:
        graph.push_back(f)
    for k in range(n_frames):
        for f in obs.frame(k, markers):
            graph.push_back(f)
    return graph


def motion_graph(motion: MotionFactors | Mapping[int, MotionFactors], p_init: np.ndarray,
                 markers: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """Gauge priors on frame 0 (at p_init[0, m]) and the motion chain over every frame of ``markers``.

    motion: one MotionFactors for every marker, or a mapping marker index -> its own (a per-marker
    noise level, e.g. the constant-velocity q chosen per marker). p_init: initial positions (F, M, 3) [m].
    """
    graph = gtsam.NonlinearFactorGraph()
    frames = range(p_init.shape[0])
    for m in markers:
        mf = motion[int(m)] if isinstance(motion, Mapping) else motion
        for f in prior_factors(mf.model, int(m), 0, p_init[0, m]):
            graph.push_back(f)
        for f in mf.chain(int(m), frames):
            graph.push_back(f)
    return graph


def initial_values(obs: ObservationFactors, model: MotionModel | Mapping[int, MotionModel], p_init: np.ndarray,
                   v_init: np.ndarray, markers: np.ndarray, a_init: np.ndarray | None = None) -> gtsam.Values:
    """Initial p (and u = v dt, w = a dt^2 as the model has them) of ``markers`` on every frame, and the
    variable cameras' calibrated poses.

    model: one for every marker, or one per marker index. p_init, v_init, a_init: (F, M, 3) [m], [m/s],
    [m/s^2]; a_init defaults to np.gradient(v_init) fps (as batgraph.graph.fast's start).
    """
    values = obs.camera_priors()[1]
    for m in markers:
        mm = model[int(m)] if isinstance(model, Mapping) else model
        dt = mm.dt_s
        a_m = None
        if mm.has_acceleration:
            a_m = a_init[:, m] if a_init is not None else (
                np.gradient(v_init[:, m], axis=0) / dt if len(v_init) > 1 else np.zeros_like(v_init[:, m]))
        for k in range(p_init.shape[0]):
            values.insert(p_key(int(m), k), p_init[k, m])
            if mm.has_velocity:
                values.insert(v_key(int(m), k), v_init[k, m] * dt)
            if mm.has_acceleration:
                values.insert(a_key(int(m), k), a_m[k] * dt * dt)
    return values


def positions(values: gtsam.Values, markers: np.ndarray, n_frames: int, n_markers: int) -> np.ndarray:
    """p of ``markers`` from ``values`` as (n_frames, n_markers, 3) [m]; NaN for the other markers."""
    xyz = np.full((n_frames, n_markers, 3), np.nan)
    for m in markers:
        for k in range(n_frames):
            xyz[k, m] = values.atPoint3(p_key(int(m), k))
    return xyz
