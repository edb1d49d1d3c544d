"""Rig calibration by bundle adjustment of all cameras at once (pycolmap), with an explicit gauge.

What it does: builds a pycolmap reconstruction from a session (one camera + one image per rig
camera, one 3D point per (frame, marker) seen by >= 2 cameras), refines every camera pose (and on
request focal length, principal point, distortion) jointly with the points, rejects outliers
iteratively, fixes the gauge as documented below, and estimates each camera's pose covariance
with pycolmap's BA covariance. It can also start from scratch (essential matrix + PnP), with the
scale from a wand of known length, as easyWand / Argus do. It does not estimate trajectories.

Camera model: pycolmap ``FULL_OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6) with
k4 = k5 = k6 = 0 is exactly OpenCV's 5-parameter model that calibration.toml stores; ``OPENCV``
has no k3, which GoPro-like lenses need (|k3| r^6 is several px at the image corners). COLMAP
cannot hold skew: observations are de-skewed with the input K before the adjustment
(``u' = u - s (v - cy) / fy``, exact) and the skew is written back unchanged. When distortion is
refined, COLMAP frees k4..k6 too; the refined lens is then re-fitted to the 5-parameter model by
linear least squares on a grid over the image (the fit residual is reported).

Pose conventions: COLMAP stores cam_from_world (like calibration.toml), so :func:`rigid_from_camera`
and :func:`camera_pose_from_rigid` only repackage the arrays; GTSAM's Pose3 of a camera is
world_from_cam with another tangent, and COLMAP's pose covariances are converted to it by
:func:`batgraph.geometry.pose.pose_cov_gtsam_from_colmap` (importable from here too), like every other pose
conversion in :mod:`batgraph.geometry.pose`.

Gauge (7 degrees of freedom that images cannot fix):

* origin and axes: ``gauge="camera0"`` (default) holds the reference camera (``ref_camera``,
  default the first) at its input pose, so the world frame is the input calibration's as seen by
  that camera; ``gauge="input"`` instead aligns the refined camera centres to the input ones by a
  7-parameter similarity (Umeyama), for when no single camera is trusted more than the others.
* scale: from a wand when one is given (``wand=(end_a, end_b, length_m)`` or session.toml's
  ``[wand] ends = ["wand_a", "wand_b"], length_m = 0.5``): the median triangulated wand length is
  set to ``length_m``. Otherwise from the input calibration: the least-squares scale between the
  refined and input camera centres relative to the reference camera. When the input centres
  coincide (a rig with unknown poses), the scale is arbitrary (reference-to-nearest camera = 1)
  and the report says so.

Pose covariances (``Camera.pose_cov``, written as ``pose_covariance``) are conditional on that
gauge: the reference camera's pose and the scale are held fixed (the reference camera gets no
covariance: it stays a fixed camera; the camera carrying COLMAP's scale gauge has one translation
direction at ``GAUGE_FLOOR_M``), and the uncertainty of the
wand length / input scale itself is not included. They are scaled by the a-posteriori pixel
variance (sum of squared residuals / degrees of freedom).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import atomic
from .camera import Camera, Rig
from .errors import InputError
from .geometry import pose
from .geometry.pose import pose_cov_gtsam_from_colmap
from .session import DenseObservations, Session, calibration_toml, dense_observations
from .triangulate import triangulate

CHI2_2DOF_999 = 13.8155  # |r|^2 / sigma^2 threshold: 99.9 % of inlier 2D residuals fall below it
RAYLEIGH_MEDIAN = math.sqrt(2 * math.log(2))  # median of |r| / sigma for a 2D Gaussian residual
GAUGES = ("camera0", "input")
# The camera holding COLMAP's scale gauge has one translation coordinate fixed (zero variance); a
# prior needs an invertible covariance, so that coordinate gets this std [m], far below any real one.
GAUGE_FLOOR_M = 1e-6
CHI2_3DOF_95 = 7.8147  # chi-square quantile, 3 degrees of freedom, 0.95 (95 % radius of a 3D Gaussian)
# Without a metric reference the refined rig must predict held-out frames at least this much better (RMS ratio)
HELD_OUT_GAIN = 0.9


@dataclass
class Wand:
    """Two markers a known distance apart: ``ends`` are marker labels, ``length_m`` [m]."""

    end_a: str
    end_b: str
    length_m: float


def wand_from_session(session: Session) -> Wand | None:
    """The ``[wand]`` table of session.toml (``ends = [a, b]``, ``length_m``), or None when absent."""
    tab = session.extra_toml.get("wand")
    if tab is None:
        return None
    where = f"{session.path / 'session.toml' if session.path else 'session.toml'} [wand]"
    if not isinstance(tab, dict):
        raise InputError(f"{where}: expected a table [wand] with keys ends, length_m")
    ends, length = tab.get("ends"), tab.get("length_m")
    if not (isinstance(ends, list) and len(ends) == 2 and all(isinstance(e, str) for e in ends)):
        raise InputError(f"{where} ends: expected two marker names, got {ends!r}")
    if isinstance(length, bool) or not isinstance(length, int | float) or not length > 0:
        raise InputError(f"{where} length_m: expected a length > 0 [m], got {length!r}")
    markers = set(session.observations["marker"])
    for e in ends:
        if e not in markers:
            raise InputError(f"{where} ends: marker {e!r} has no observations")
    return Wand(ends[0], ends[1], float(length))


# ==================================================================================================
# COLMAP's pose objects (the conventions themselves: batgraph.geometry.pose)
# ==================================================================================================
def rigid_from_camera(cam: Camera) -> pycolmap.Rigid3d:
    """batgraph's cam_from_world (rvec, tvec) -> COLMAP's Rigid3d (also cam_from_world: same pose)."""
    return pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.tvec.copy())


def camera_pose_from_rigid(cam_from_world: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP Rigid3d cam_from_world -> (rvec (3,) [rad], tvec (3,) [m]) of batgraph's cam_from_world."""
    R = np.asarray(cam_from_world.rotation.matrix())
    return pose.rvec_from_R(R), np.asarray(cam_from_world.translation, dtype=float).copy()


# ==================================================================================================
# building and solving the pycolmap problem
# ==================================================================================================
def _colmap_params(cam: Camera) -> list[float]:
    K = cam.K
    return [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *cam.dist.tolist(), 0.0, 0.0, 0.0]


def _deskew(cam: Camera, uv_px: np.ndarray) -> np.ndarray:
    """Remove the skew term from raw pixels (..., 2): COLMAP's models have no skew."""
    s = cam.K[0, 1]
    if s == 0:
        return uv_px
    out = uv_px.copy()
    out[..., 0] -= s * (uv_px[..., 1] - cam.K[1, 2]) / cam.K[1, 1]
    return out


def fit_five_parameter(params: np.ndarray, size_wh: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Refit COLMAP FULL_OPENCV params (12,) to OpenCV's 5-parameter model (k1, k2, p1, p2, k3).

    The rational model's distortion is sampled on a 30 x 20 grid of undistorted normalised points
    covering the image; the 5-parameter model is linear in its coefficients there, so the fit is
    one least-squares solve. Returns (dist (5,), max fit residual [px]).
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = params
    w, h = size_wh
    u, v = np.meshgrid(np.linspace(0, w - 1, 30), np.linspace(0, h - 1, 20))
    xd = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy], -1)
    # undistort the grid through the rational model by fixed-point iteration (mild lenses converge)
    x = xd.copy()
    for _ in range(100):
        r2 = (x**2).sum(-1)
        rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        tan = np.stack([2 * p1 * x[:, 0] * x[:, 1] + p2 * (r2 + 2 * x[:, 0] ** 2),
                        p1 * (r2 + 2 * x[:, 1] ** 2) + 2 * p2 * x[:, 0] * x[:, 1]], -1)
        x = (xd - tan) / rad[:, None]
    r2 = (x**2).sum(-1)
    X, Y = x[:, 0], x[:, 1]
    # rows: [k1, k2, p1, p2, k3] coefficients of (xd - x, yd - y)
    A = np.concatenate([
        np.stack([X * r2, X * r2**2, 2 * X * Y, r2 + 2 * X**2, X * r2**3], -1),
        np.stack([Y * r2, Y * r2**2, r2 + 2 * Y**2, 2 * X * Y, Y * r2**3], -1),
    ])
    b = np.concatenate([xd[:, 0] - X, xd[:, 1] - Y])
    dist, *_ = np.linalg.lstsq(A, b, rcond=None)
    resid_px = np.abs(A @ dist - b) * np.concatenate([np.full(len(X), fx), np.full(len(Y), fy)])
    return dist, float(resid_px.max())


@dataclass
class _Problem:
    """The observations the adjustment uses: point p of (frame f, marker m), camera c, uv raw px."""

    cam_idx: np.ndarray  # (n_obs,)
    point_idx: np.ndarray  # (n_obs,)
    uv_px: np.ndarray  # (n_obs, 2) raw pixels (with the camera's skew)
    point_fm: np.ndarray  # (n_points, 2) frame index, marker index into DenseObservations


def _problem_from_dense(dense: DenseObservations, xyz: np.ndarray,
                        max_points: int | None) -> tuple[_Problem, np.ndarray]:
    """Observations of every (frame, marker) triangulated from >= 2 views (evenly thinned to max_points)."""
    ok = np.isfinite(xyz[..., 0]) & (dense.n_views >= 2)
    fs, ms = np.nonzero(ok)
    if max_points is not None and len(fs) > max_points:
        keep = np.unique(np.linspace(0, len(fs) - 1, max_points).round().astype(int))
        fs, ms = fs[keep], ms[keep]
    seen = dense.seen[:, fs, ms]  # (C, P)
    c_idx, p_idx = np.nonzero(seen)
    uv = dense.uv_px[c_idx, fs[p_idx], ms[p_idx]]
    return _Problem(c_idx, p_idx, uv, np.stack([fs, ms], -1)), xyz[fs, ms]


def _image_id(c: int, ref: int, n_cams: int) -> int:
    """COLMAP image (and camera) id of rig camera c: the reference camera is 1, the others follow.

    COLMAP's two-camera gauge takes the first image as its anchor, so the anchor must be ours.
    """
    return 1 + (c - ref) % n_cams


def _build_reconstruction(rig: Rig, prob: _Problem, keep: np.ndarray, xyz: np.ndarray,
                          ref: int) -> tuple[pycolmap.Reconstruction, np.ndarray]:
    """pycolmap reconstruction of the kept observations. Returns (rec, point3D id per point, -1 if dropped)."""
    rec = pycolmap.Reconstruction()
    C = len(rig)
    n_per_point = np.bincount(prob.point_idx[keep], minlength=len(xyz))
    use_point = (n_per_point >= 2) & np.isfinite(xyz).all(-1)
    keep = keep & use_point[prob.point_idx]
    slot = np.full(len(prob.cam_idx), -1)
    ids_c = [_image_id(c, ref, C) for c in range(C)]
    for c in np.argsort(ids_c):  # add in id order
        cam = rig[int(c)]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model="FULL_OPENCV", width=cam.size_wh[0], height=cam.size_wh[1], params=_colmap_params(cam),
            camera_id=ids_c[c]))
        sel = np.flatnonzero(keep & (prob.cam_idx == c))
        slot[sel] = np.arange(len(sel))
        img = pycolmap.Image(name=cam.name, keypoints=_deskew(cam, prob.uv_px[sel]).reshape(-1, 2),
                             camera_id=ids_c[c], image_id=ids_c[c])
        rec.add_image_with_trivial_frame(img, rigid_from_camera(cam))
    # tracks: group the kept observations by point (sorted so each point's elements are contiguous)
    obs = np.flatnonzero(keep)
    obs = obs[np.argsort(prob.point_idx[obs], kind="stable")]
    starts = np.searchsorted(prob.point_idx[obs], np.arange(len(xyz) + 1))
    ids = np.full(len(xyz), -1)
    for p in np.flatnonzero(use_point):
        track = pycolmap.Track()
        for o in obs[starts[p]:starts[p + 1]]:
            track.add_element(ids_c[int(prob.cam_idx[o])], int(slot[o]))
        ids[p] = rec.add_point3D(xyz[p], track)
    return rec, ids


def _rig_from_reconstruction(rec: pycolmap.Reconstruction, rig: Rig, refine_distortion: bool,
                             ref: int) -> tuple[Rig, list[float]]:
    """Read cameras back (skew restored, 5-parameter distortion). Returns (rig, distortion refit residual px)."""
    cams, fit_px = [], []
    for c, cam in enumerate(rig):
        i = _image_id(c, ref, len(rig))
        p = np.asarray(rec.camera(i).params, dtype=float)
        K = np.array([[p[0], cam.K[0, 1], p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        if refine_distortion:
            dist, resid = fit_five_parameter(p, cam.size_wh)
        else:
            dist, resid = cam.dist.copy(), 0.0
        rvec, tvec = camera_pose_from_rigid(rec.image(i).cam_from_world())
        cams.append(Camera(cam.name, cam.size_wh, K, dist, rvec, tvec))
        fit_px.append(resid)
    return Rig(cams), fit_px


def _solve(rec: pycolmap.Reconstruction, *, refine_focal: bool, refine_pp: bool,
           refine_distortion: bool, loss: str, loss_scale_px: float, max_iterations: int,
           covariance: bool) -> tuple[pycolmap.CeresBundleAdjuster, object]:
    """One bundle adjustment: reference camera constant, scale fixed by one coordinate of another camera."""
    opts = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine_focal, refine_principal_point=refine_pp, refine_extra_params=refine_distortion,
        print_summary=False)
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
    opts.ceres.loss_function_scale = loss_scale_px
    opts.ceres.solver_options.max_num_iterations = max_iterations
    opts.ceres.solver_options.function_tolerance = 1e-12
    opts.ceres.solver_options.num_threads = 1
    cfg = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        cfg.add_image(image_id)
    cfg.set_constant_rig_from_world_pose(rec.image(1).frame_id)  # the reference camera (_image_id)
    # COLMAP then also holds the largest-baseline coordinate of a second camera: the scale gauge
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    summary = ba.solve()
    cov = None
    if covariance:
        cov = pycolmap.estimate_ba_covariance(
            pycolmap.BACovarianceOptions(params=pycolmap.BACovarianceOptionsParams.POSES), rec, ba)
    return ba, (summary, cov)


def _points_from_reconstruction(rec: pycolmap.Reconstruction, ids: np.ndarray) -> np.ndarray:
    xyz = np.full((len(ids), 3), np.nan)
    for p in np.flatnonzero(ids >= 0):
        xyz[p] = rec.point3D(int(ids[p])).xyz
    return xyz


def _residuals_px(rig: Rig, prob: _Problem, xyz: np.ndarray) -> np.ndarray:
    """|observed - projected| raw pixels per observation (n_obs,); NaN where the point is missing."""
    err = np.full(len(prob.cam_idx), np.nan)
    for c, cam in enumerate(rig):
        sel = prob.cam_idx == c
        uv_hat = cam.project(xyz[prob.point_idx[sel]])
        err[sel] = np.linalg.norm(uv_hat - prob.uv_px[sel], axis=-1)
    return err


# ==================================================================================================
# gauge
# ==================================================================================================
def _similarity(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, R, t) minimising sum |s R src + t - dst|^2 over points (n, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(-1).mean()) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def _transform_rig(rig: Rig, s: float, R: np.ndarray, t: np.ndarray) -> Rig:
    """Apply the world similarity x' = s R x + t to every camera (see batgraph.geometry.pose.similarity_*)."""
    out = []
    for cam in rig:
        Rc, tc = pose.similarity_cam_from_world(cam.R, cam.tvec, s, R, t)
        cov = None if cam.pose_cov is None else pose.similarity_pose_cov(cam.pose_cov, s)
        out.append(Camera(cam.name, cam.size_wh, cam.K.copy(), cam.dist.copy(), pose.rvec_from_R(Rc), tc, cov))
    return Rig(out)


def _wand_lengths(rig: Rig, dense: DenseObservations, wand: Wand, sigma_px: float) -> np.ndarray:
    """Triangulated wand length on every frame where both ends have >= 2 views, (n,) [m]."""
    ia, ib = dense.markers.index(wand.end_a), dense.markers.index(wand.end_b)
    sub = DenseObservations(dense.cameras, dense.frames, [wand.end_a, wand.end_b],
                            dense.uv_px[:, :, [ia, ib]], dense.weight[:, :, [ia, ib]])
    xyz, _ = triangulate(rig, sub, sigma_px)
    d = np.linalg.norm(xyz[:, 0] - xyz[:, 1], axis=-1)
    return d[np.isfinite(d)]


# ==================================================================================================
# initialisation from scratch (essential matrix, then PnP)
# ==================================================================================================
def _initial_rig_from_scratch(rig: Rig, dense: DenseObservations, ref: int, sigma_px: float) -> Rig:
    """Relative poses from the observations alone; reference camera keeps its input pose.

    The camera sharing most points with the reference gets its pose from the essential matrix
    (RANSAC, undistorted normalised coordinates) at unit baseline; the others, in order of shared
    triangulated points, by PnP (RANSAC) on the points triangulated so far.
    """
    C = len(rig)
    seen = dense.seen
    xy = np.stack([rig[c].undistort_normalized(dense.uv_px[c]) for c in range(C)])  # (C, F, M, 2)
    shared = (seen[ref][None] & seen).reshape(C, -1).sum(-1)
    shared[ref] = -1
    second = int(np.argmax(shared))
    both = seen[ref] & seen[second]
    p0, p1 = xy[ref][both], xy[second][both]
    if len(p0) < 8:
        raise InputError(f"calibrate: cameras {rig[ref].name!r} and {rig[second].name!r} share only "
                         f"{len(p0)} points; at least 8 are needed to start from scratch")
    f_mean = float(np.mean([rig[ref].K[0, 0], rig[second].K[0, 0]]))
    E, inl = cv2.findEssentialMat(p0, p1, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=3.0 * sigma_px / f_mean)
    _, R, t, _ = cv2.recoverPose(E, p0, p1, np.eye(3), mask=inl)
    R_ref, t_ref = rig[ref].R, rig[ref].tvec
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {ref: (R_ref, t_ref)}
    # second camera: cam2_from_ref = (R, t) -> cam2_from_world = (R R_ref, R t_ref + t)
    poses[second] = (R @ R_ref, R @ t_ref + t.reshape(3))

    def current_rig() -> Rig:
        return Rig([Camera(cam.name, cam.size_wh, cam.K, cam.dist, pose.rvec_from_R(poses[c][0]),
                           poses[c][1]) if c in poses else cam for c, cam in enumerate(rig)])

    while len(poses) < C:
        known = sorted(poses)
        sub = DenseObservations([dense.cameras[c] for c in known], dense.frames, dense.markers,
                                dense.uv_px[known], dense.weight[known])
        xyz, _ = triangulate(Rig([current_rig()[c] for c in known]), sub, sigma_px)
        ok = np.isfinite(xyz[..., 0])
        todo = [c for c in range(C) if c not in poses]
        counts = [(seen[c] & ok).sum() for c in todo]
        c = todo[int(np.argmax(counts))]
        use = seen[c] & ok
        if use.sum() < 6:
            raise InputError(f"calibrate: camera {rig[c].name!r} sees only {int(use.sum())} points seen by the "
                             "others; at least 6 are needed to place it")
        good, rvec, tvec, _ = cv2.solvePnPRansac(xyz[use], xy[c][use], np.eye(3), None,
                                                 reprojectionError=3.0 * sigma_px / rig[c].K[0, 0],
                                                 iterationsCount=1000, confidence=0.9999)
        if not good:
            raise InputError(f"calibrate: could not place camera {rig[c].name!r} by PnP")
        poses[c] = (pose.R_from_rvec(rvec), tvec.reshape(3))
    return current_rig()


# ==================================================================================================
# one adjustment, the held-out check and the verdict
# ==================================================================================================
@dataclass
class _Fit:
    """One bundle adjustment of a rig on some observations (before the gauge's scale)."""

    rig: Rig  # with pose_cov where computed
    prob: _Problem
    used: np.ndarray  # (n_obs,) inliers that are in the final adjustment
    err: np.ndarray  # (n_obs,) residual [px] under ``rig``
    n_points: int
    var_px2: float  # a-posteriori pixel variance
    rounds: list
    fit_px: list
    termination: str


def _adjust(rig0: Rig, dense: DenseObservations, ref: int, sigma: float, *, refine_intrinsics: bool,
            refine_distortion: bool, max_iterations: int, max_points: int | None, progress: bool,
            covariance: bool = True) -> _Fit:
    """Outlier-rejection rounds (robust loss), then a plain least-squares adjustment with covariances."""
    C = len(rig0)
    xyz0, _ = triangulate(rig0, dense, sigma)
    prob, xyz_p = _problem_from_dense(dense, xyz0, max_points)
    if len(xyz_p) == 0:
        raise InputError("calibrate: no marker is seen by 2 or more cameras on any frame")

    keep = np.ones(len(prob.cam_idx), bool)
    rig_cur, rounds = rig0, []
    bar = _progress(max_iterations, progress)
    for it in range(max_iterations):
        rec, ids = _build_reconstruction(rig_cur, prob, keep, xyz_p, ref)
        # robust loss while outliers may remain; the covariance round below is plain least squares
        _solve(rec, refine_focal=refine_intrinsics, refine_pp=refine_intrinsics,
               refine_distortion=refine_distortion, loss="CAUCHY", loss_scale_px=3.0 * sigma,
               max_iterations=100, covariance=False)
        rig_cur, _ = _rig_from_reconstruction(rec, rig_cur, refine_distortion, ref)
        xyz_p = np.where((ids >= 0)[:, None], _points_from_reconstruction(rec, ids), xyz_p)
        err = _residuals_px(rig_cur, prob, xyz_p)
        inl = keep & np.isfinite(err)
        # robust sigma from the median residual, inflated by sqrt(2 n_obs / dof): fitted residuals
        # are smaller than the noise (a 2-view point keeps 1 of its 4 residual dimensions)
        n_fit = 3 * int((ids >= 0).sum()) + 6 * (C - 1) - 1 + (4 * C if refine_intrinsics else 0)
        shrink = math.sqrt(2 * inl.sum() / max(2 * inl.sum() - n_fit, 1))
        sigma_hat = float(np.median(err[inl]) / RAYLEIGH_MEDIAN * shrink)
        thresh = math.sqrt(CHI2_2DOF_999) * sigma_hat
        new_keep = np.isfinite(err) & (err <= thresh)
        rounds.append({"round": it + 1, "sigma_hat_px": sigma_hat, "threshold_px": thresh,
                       "n_used": int(new_keep.sum())})
        bar.update(1)
        changed = (new_keep != keep).sum()
        keep = new_keep
        if changed == 0:
            break
    bar.close()

    # final adjustment on the inliers, plain least squares, with covariances
    rec, ids = _build_reconstruction(rig_cur, prob, keep, xyz_p, ref)
    t_start = {c: np.asarray(rec.image(_image_id(c, ref, C)).cam_from_world().translation).copy()
               for c in range(C)}
    ba, (summary, cov) = _solve(rec, refine_focal=refine_intrinsics, refine_pp=refine_intrinsics,
                                refine_distortion=refine_distortion, loss="TRIVIAL", loss_scale_px=1.0,
                                max_iterations=100, covariance=covariance)
    rig_ba, fit_px = _rig_from_reconstruction(rec, rig_cur, refine_distortion, ref)
    xyz_p = np.where((ids >= 0)[:, None], _points_from_reconstruction(rec, ids), xyz_p)
    used = keep & (ids[prob.point_idx] >= 0)
    err = _residuals_px(rig_ba, prob, xyz_p)
    n_params = 3 * int((ids >= 0).sum()) + 6 * (C - 1) - 1
    if refine_intrinsics:
        n_params += 4 * C
    dof = max(2 * int(used.sum()) - n_params, 1)
    var_px2 = float(np.nansum(err[used] ** 2) / dof)

    cams = []
    for c, cam in enumerate(rig_ba):
        pc = None if cov is None else cov.get_cam_cov_from_world(_image_id(c, ref, C))
        full = None
        if pc is not None and pc.shape == (6, 6):
            full = pose_cov_gtsam_from_colmap(pc * var_px2, cam.R, cam.tvec)
        elif pc is not None and pc.shape == (5, 5):
            # the camera holding the scale gauge: its fixed translation coordinate has zero variance
            # COLMAP does not say which coordinate it held: it is the one that did not move at all
            fixed = 3 + int(np.argmin(np.abs(cam.tvec - t_start[c])))
            free = [d for d in range(6) if d != fixed]
            cc = np.zeros((6, 6))
            cc[np.ix_(free, free)] = pc * var_px2
            cc[fixed, fixed] = GAUGE_FLOOR_M**2  # keeps the prior invertible; see GAUGE_FLOOR_M
            full = pose_cov_gtsam_from_colmap(cc, cam.R, cam.tvec)
        cams.append(Camera(cam.name, cam.size_wh, cam.K, cam.dist, cam.rvec, cam.tvec, full))
    return _Fit(Rig(cams), prob, used, err, int((ids >= 0).sum()), var_px2, rounds, fit_px,
                str(summary.termination_type))


def _subset_frames(dense: DenseObservations, sel: np.ndarray) -> DenseObservations:
    return DenseObservations(dense.cameras, dense.frames[sel], dense.markers, dense.uv_px[:, sel], dense.weight[:, sel])


def _held_out_check(rig0: Rig, dense: DenseObservations, ref: int, sigma: float, fraction: float,
                    **adjust) -> dict:
    """Refine on most frames, then compare how the starting rig and the refined one explain the others.

    Frames are cut into 20 consecutive blocks and every ``round(1 / fraction)``-th block is held out
    (neighbouring frames see nearly the same points, so single frames would not be held out really).
    Each rig triangulates the held-out points itself (all cameras) and its reprojection RMS is taken over
    the observations that the refined rig does not reject as outliers (the same set for both).
    Returns {} when there are too few frames.
    """
    F = len(dense.frames)
    step = max(2, round(1 / fraction))
    block = np.minimum(np.arange(F) * 20 // max(F, 1), 19)
    test = block % step == step - 1
    if test.sum() < 2 or (~test).sum() < 2:
        return {}
    try:
        fit = _adjust(rig0, _subset_frames(dense, ~test), ref, sigma, covariance=False, progress=False, **adjust)
    except InputError:
        return {}
    held = _subset_frames(dense, test)
    errs = []
    for rig in (rig0, fit.rig):
        with np.errstate(divide="ignore", invalid="ignore"):
            xyz, _ = triangulate(rig, held, sigma)
        prob, xyz_p = _problem_from_dense(held, xyz, None)
        errs.append(_residuals_px(rig, prob, xyz_p))
    sigma_hat = fit.rounds[-1]["sigma_hat_px"] if fit.rounds else sigma
    ok = np.isfinite(errs[0]) & np.isfinite(errs[1]) & (errs[1] <= math.sqrt(CHI2_2DOF_999) * sigma_hat)
    if not ok.any():
        return {}
    return {"fraction": float(test.mean()), "n_frames": int(test.sum()), "n_observations": int(ok.sum()),
            "rms_input_px": _rms(errs[0][ok]), "rms_refined_px": _rms(errs[1][ok])}


def _pose_change(cam_in: Camera, cam_out: Camera) -> tuple[float, float, float, float]:
    """(moved [m], turned [rad], position Mahalanobis^2 and its dof) of cam_in against cam_out's covariance.

    The covariance is GTSAM's, of world_from_cam: the translation block is the centre's in camera axes.
    The direction held by COLMAP's scale gauge (variance at GAUGE_FLOOR_M) is left out.
    """
    moved = float(np.linalg.norm(cam_in.center_world - cam_out.center_world))
    turned = float(pose.rotation_angle(cam_in.R, cam_out.R))
    if cam_out.pose_cov is None:
        return moved, turned, float("nan"), 0
    d = cam_out.R @ (cam_in.center_world - cam_out.center_world)
    w, v = np.linalg.eigh(cam_out.pose_cov[3:, 3:])
    keep = w > (10 * GAUGE_FLOOR_M) ** 2
    z = (v[:, keep].T @ d) / np.sqrt(w[keep])
    return moved, turned, float(z @ z), int(keep.sum())


def _r95(cov: np.ndarray | None) -> tuple[float, float]:
    """95 % radius [m] of a camera's position and [rad] of its rotation: sqrt(chi2_3(0.95) * largest variance)."""
    if cov is None:
        return 0.0, 0.0
    k = math.sqrt(CHI2_3DOF_95)
    return (k * math.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)),
            k * math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))


def _assess(rig_start: Rig, rig_out: Rig, metric: bool, held_out: dict, initial: str) -> dict:
    """Whether the refinement is determined by the observations, and why not (see :func:`calibrate_session`)."""
    reasons = []
    cams = {}
    worst_in_pos = worst_in_rot = worst_out_pos = worst_out_rot = 0.0
    for ci, co in zip(rig_start, rig_out, strict=True):
        moved, turned, d2, dof = _pose_change(ci, co)
        r95_pos, r95_rot = _r95(co.pose_cov)
        cams[co.name] = {"moved_mm": 1000 * moved, "turned_deg": math.degrees(turned),
                         "r95_position_mm": 1000 * r95_pos, "r95_rotation_deg": math.degrees(r95_rot),
                         "position_mahalanobis2": d2, "position_dof": dof}
        # the input's error is at least |change| - r95 (triangle inequality), the refinement's at most r95
        worst_in_pos, worst_out_pos = max(worst_in_pos, moved - r95_pos), max(worst_out_pos, r95_pos)
        worst_in_rot, worst_out_rot = max(worst_in_rot, turned - r95_rot), max(worst_out_rot, r95_rot)
    if held_out and held_out["rms_refined_px"] > (HELD_OUT_GAIN if not metric else 1.0) * held_out["rms_input_px"]:
        reasons.append(f"on the {held_out['n_frames']} held-out frames the refined rig predicts the observations "
                       f"no better than the input ({held_out['rms_refined_px']:.2f} px vs "
                       f"{held_out['rms_input_px']:.2f} px RMS)")
    if not metric:
        if initial == "scratch":
            reasons.append("no metric reference: started from scratch without a wand, the scale is arbitrary")
        elif not (worst_in_pos > worst_out_pos and worst_in_rot > worst_out_rot):
            reasons.append(
                "no metric reference (wand), and the pose covariances do not show the refinement to be better than "
                f"the input: a camera moved by at most {_max_of(cams, 'moved_mm'):.2f} mm and "
                f"{_max_of(cams, 'turned_deg'):.3f} deg, while the refined poses are known to "
                f"{1000 * worst_out_pos:.2f} mm and {math.degrees(worst_out_rot):.3f} deg (95 %)")
    return {"determined": not reasons, "reasons": reasons, "metric_reference": metric, "held_out": held_out,
            "cameras": cams,
            "input_error_at_least_mm": 1000 * max(worst_in_pos, 0.0),
            "input_error_at_least_deg": math.degrees(max(worst_in_rot, 0.0)),
            "refined_error_at_most_mm": 1000 * worst_out_pos,
            "refined_error_at_most_deg": math.degrees(worst_out_rot)}


def _max_of(cams: dict, key: str) -> float:
    return max((c[key] for c in cams.values()), default=0.0)


# ==================================================================================================
# the public entry points
# ==================================================================================================
def calibrate_session(
    session: Session, *, refine_intrinsics: bool = False, refine_distortion: bool = False,
    gauge: str = "camera0", ref_camera: int = 0, wand: Wand | tuple[str, str, float] | None = None,
    initial: str = "auto", max_iterations: int = 10, max_points: int | None = 20000,
    progress: bool = True, hold_out: float = 0.2, keep_input_if_undetermined: bool = True,
) -> tuple[Rig, dict]:
    """Refine the session's rig by bundle adjustment of all cameras at once.

    refine_intrinsics: also refine focal lengths and principal points (per camera).
    refine_distortion: also refine distortion (refitted to the 5-parameter model, see module doc).
    gauge: "camera0" or "input" (see module docstring); ref_camera: index of the reference camera.
    wand: (end_a, end_b, length_m) or a :class:`Wand`; None = session.toml's [wand] if present.
    initial: "input" starts from the session's calibration, "scratch" from the essential matrix
        and PnP (intrinsics from the session), "auto" = "scratch" when a wand is given, else "input".
    max_iterations: outlier-rejection rounds (each a full adjustment).
    max_points: at most this many (frame, marker) points (evenly thinned), None = all.
    hold_out: fraction of frames (in blocks) held out of a second adjustment to check that the
        refinement predicts observations it did not see better than the starting rig; 0 skips it.
    keep_input_if_undetermined: when the refinement is not determined (see below) and it started from
        the input rig, return the input rig unchanged (``report["kept_input"]``); False returns the
        refined rig anyway.

    Determined (``report["assessment"]``): with a wand (metric reference), when the refined rig predicts
    the held-out frames at least as well as the starting rig. Without one, the scale and the world frame
    come from the input rig, which the images cannot check, so the refinement must also show that it is
    better than the input: it must predict the held-out frames at least 10 % better (RMS), and the
    largest change of a camera (minus its 95 % radius from the pose covariance: a lower bound of the
    input's error) must exceed the largest 95 % radius of a refined camera (an upper bound of the
    refinement's error), for positions and for rotations. From scratch without a wand the scale is
    arbitrary: never determined. These bounds are conditional on the gauge: with ``gauge="camera0"``
    the reference camera is taken as exact.

    Returns (rig, report). rig: the refined rig with pose_cov (6, 6) per camera, or the input rig when it
    was kept. report has "cameras" (per camera of the refined rig: rms_before_px, rms_after_px,
    median_after_px, n_obs, n_used, n_rejected, moved_mm, turned_deg, and with a true rig error_mm /
    error_deg, input_error_mm / input_error_deg), "pixel_sigma_px" (a-posteriori), "gauge", "scale",
    "rounds", "n_points", "assessment" (determined, reasons, held_out, per-camera bounds) and
    "kept_input".
    """
    if gauge not in GAUGES:
        raise InputError(f"calibrate: gauge must be one of {', '.join(GAUGES)}, got {gauge!r}")
    rig_in = session.rig
    C = len(rig_in)
    if C < 2:
        raise InputError("calibrate: at least 2 cameras are needed")
    if not 0 <= ref_camera < C:
        raise InputError(f"calibrate: ref_camera must be in 0..{C - 1}, got {ref_camera}")
    if wand is None:
        wand = wand_from_session(session)
    elif not isinstance(wand, Wand):
        wand = Wand(str(wand[0]), str(wand[1]), float(wand[2]))
    if initial == "auto":
        initial = "scratch" if wand is not None else "input"
    if initial not in ("input", "scratch"):
        raise InputError(f"calibrate: initial must be 'auto', 'input' or 'scratch', got {initial!r}")
    if not 0 <= hold_out < 1:
        raise InputError(f"calibrate: hold_out must be in [0, 1), got {hold_out}")
    # the starting noise scale of the robust loss and thresholds: the session's, else 1 px (the bundle
    # adjustment's rounds measure the a-posteriori sigma themselves; the input rig may be far off)
    given = session.pixel_sigma_px
    sigma = float(np.median(list(given.values()))) if isinstance(given, dict) else float(given or 1.0)
    dense = dense_observations(session)
    if wand is not None:
        for e in (wand.end_a, wand.end_b):
            if e not in dense.markers:
                raise InputError(f"calibrate: wand end {e!r} has no observations")
    rig0 = _initial_rig_from_scratch(rig_in, dense, ref_camera, sigma) if initial == "scratch" else rig_in
    adjust = {"refine_intrinsics": refine_intrinsics, "refine_distortion": refine_distortion,
              "max_iterations": max_iterations, "max_points": max_points}
    fit = _adjust(rig0, dense, ref_camera, sigma, progress=progress, **adjust)
    rig_out, prob, used, err, fit_px = fit.rig, fit.prob, fit.used, fit.err, fit.fit_px
    held_out = _held_out_check(rig0, dense, ref_camera, sigma, hold_out, **adjust) if hold_out > 0 else {}

    # gauge: origin/axes, then scale
    scale_info: dict
    if gauge == "input":
        s, R, t = _similarity(np.array([c.center_world for c in rig_out]), np.array([c.center_world for c in rig_in]))
        rig_out = _transform_rig(rig_out, s, R, t)
    c_ref = rig_out[ref_camera].center_world
    if wand is not None:
        lengths = _wand_lengths(rig_out, dense, wand, sigma)
        if len(lengths) == 0:
            raise InputError(f"calibrate: the wand ends {wand.end_a!r}, {wand.end_b!r} are never both triangulated")
        s = wand.length_m / float(np.median(lengths))
        scale_info = {"source": "wand", "wand_length_m": wand.length_m, "n_wand_frames": int(len(lengths)),
                      "median_length_before_m": float(np.median(lengths))}
    else:
        rel_out = np.array([c.center_world for c in rig_out]) - c_ref
        rel_in = np.array([c.center_world for c in rig_in]) - rig_in[ref_camera].center_world
        if np.linalg.norm(rel_in, axis=1).max() < 1e-9:
            d = np.linalg.norm(rel_out, axis=1)
            s = 1.0 / d[d > 0].min()
            scale_info = {"source": "arbitrary (input camera centres coincide; nearest camera at 1 unit)"}
        else:
            s = float((rel_out * rel_in).sum() / (rel_out**2).sum())
            scale_info = {"source": "input calibration (least squares over camera centres)"}
    if gauge == "camera0" or wand is not None:
        # scale about the reference camera's centre so that camera keeps its pose
        rig_out = _transform_rig(rig_out, s, np.eye(3), (1 - s) * c_ref)
    scale_info["scale_applied"] = float(s)
    if wand is not None:
        scale_info["median_length_after_m"] = float(np.median(_wand_lengths(rig_out, dense, wand, sigma)))

    report = _report(session, rig0, rig_out, prob, used, err, dense, sigma)
    assessment = _assess(rig_in, rig_out, wand is not None, held_out, initial)
    if gauge == "camera0":
        assessment["gauge_note"] = (f"camera {rig_in[ref_camera].name!r} is held at its input pose: the bounds take "
                                    "it as exact (if it is off, every camera is off with it; --gauge input fits the "
                                    "world frame to all input cameras instead)")
    kept = not assessment["determined"] and keep_input_if_undetermined and initial == "input"
    report.update({"gauge": {"origin_axes": gauge, "ref_camera": rig_in[ref_camera].name}, "scale": scale_info,
                   "initial": initial, "rounds": fit.rounds, "n_points": fit.n_points,
                   "pixel_sigma_px": math.sqrt(fit.var_px2), "refine_intrinsics": refine_intrinsics,
                   "refine_distortion": refine_distortion,
                   "distortion_refit_max_px": dict(zip(rig_in.names, fit_px, strict=True)),
                   "ceres_termination": fit.termination,
                   "camera_model": "FULL_OPENCV with k4 = k5 = k6 = 0 (= OpenCV k1 k2 p1 p2 k3)",
                   "assessment": assessment, "kept_input": kept})
    return (rig_in if kept else rig_out), report


def _report(session: Session, rig_in: Rig, rig_out: Rig, prob: _Problem, used: np.ndarray,
            err_after: np.ndarray, dense: DenseObservations, sigma: float) -> dict:
    """Per-camera figures on the observations used. "before" = the starting rig (input, or the
    from-scratch initialisation) with every point re-triangulated by it; moved/turned are relative
    to that rig; error_* compare with the session's true rig (simulations)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz_before, _ = triangulate(rig_in, dense, sigma)
    err_before = _residuals_px(rig_in, prob, xyz_before[prob.point_fm[:, 0], prob.point_fm[:, 1]])
    truth = session.true_rig
    cams = {}
    for c, (ci, co) in enumerate(zip(rig_in, rig_out, strict=True)):
        sel = prob.cam_idx == c
        u = sel & used
        row = {
            "n_obs": int(sel.sum()), "n_used": int(u.sum()), "n_rejected": int((sel & ~used).sum()),
            "rms_before_px": _rms(err_before[u]), "rms_after_px": _rms(err_after[u]),
            "median_after_px": float(np.median(err_after[u])) if u.any() else float("nan"),
            "moved_mm": 1000 * float(np.linalg.norm(co.center_world - ci.center_world)),
            "turned_deg": _angle_deg(co.R, ci.R),
        }
        if co.pose_cov is not None:
            sd = np.sqrt(np.clip(np.diag(co.pose_cov), 0, None))
            row["sd_rotation_deg"] = np.degrees(sd[:3]).tolist()
            row["sd_translation_mm"] = (1000 * sd[3:]).tolist()
        if truth is not None:
            ct = truth[c]
            row["error_mm"] = 1000 * float(np.linalg.norm(co.center_world - ct.center_world))
            row["error_deg"] = _angle_deg(co.R, ct.R)
            row["input_error_mm"] = 1000 * float(np.linalg.norm(ci.center_world - ct.center_world))
            row["input_error_deg"] = _angle_deg(ci.R, ct.R)
        cams[co.name] = row
    return {"cameras": cams}


def _rms(e: np.ndarray) -> float:
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(pose.rotation_angle(Ra, Rb)))


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, show: bool):
    if not show:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc="calibrate (BA rounds)", unit="round", leave=False)


def write_calibration(path: str | Path, rig: Rig) -> Path:
    """Write ``rig`` (with pose covariances) as calibration.toml, atomically. Returns the path."""
    path = Path(path)
    atomic.write_text(path, calibration_toml(rig))
    return path
