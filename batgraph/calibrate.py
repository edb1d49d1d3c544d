"""Rig calibration by bundle adjustment of all cameras at once (pycolmap), judged by what the images determine.

Builds a pycolmap reconstruction from a session (one camera and image per rig camera, one 3D point per
(frame, marker) seen by >= 2 cameras), refines every pose (on request focal length, principal point and
lens) jointly with the points, rejects outliers iteratively, fixes the gauge and estimates the poses' joint
covariance (pycolmap's, scaled by the a-posteriori pixel variance). It can also start from scratch
(essential matrix + PnP) with the scale from a wand of known length, as easyWand / Argus do.
Lens: ``FULL_OPENCV`` with k4 = k5 = k6 = 0 is OpenCV's 5-parameter model; skew is taken out of the
detections before and put back after. Poses: COLMAP's cam_from_world is calibration.toml's; covariances go
to GTSAM's Pose3 tangent (:func:`batgraph.geometry.pose.pose_cov_gtsam_from_colmap`, re-exported here).
Gauge (:mod:`batgraph.geometry.gauge`): "input" fits the refined rig onto the input one by a similarity;
"camera0" holds the reference camera and takes the scale from the wand, else from the input centres.
:func:`calibrate_session` refuses (InputError) a rig the observations cannot determine and, without a wand,
writes the refinement only when it differs significantly from the input and predicts held-out frames better.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from . import atomic
from .camera import Camera, Rig
from .errors import InputError
from .evaluate import rms
from .geometry import gauge as rig_gauge
from .geometry import pose
from .geometry.pose import pose_cov_gtsam_from_colmap as pose_cov_gtsam_from_colmap  # re-exported
from .session import DenseObservations, Session, calibration_toml, dense_observations
from .triangulate import triangulate

if TYPE_CHECKING:
    import pycolmap

CHI2_2DOF_999 = 13.8155  # |r|^2 / sigma^2 threshold: 99.9 % of inlier 2D residuals fall below it
RAYLEIGH_MEDIAN = math.sqrt(2 * math.log(2))  # median of |r| / sigma for a 2D Gaussian residual
GAUGES = ("auto", "camera0", "input")
# The camera holding COLMAP's scale gauge has one translation coordinate fixed (zero variance); a
# prior needs an invertible covariance, so that coordinate gets this std [m] ([rad] for a rotation
# where a 2-camera rig's gauge-free covariance is singular), far below any real one.
GAUGE_FLOOR_M = 1e-6
CHI2_3DOF_95 = 7.8147  # chi-square quantile, 3 degrees of freedom, 0.95 (95 % radius of a 3D Gaussian)
SIGNIFICANCE = 0.99  # the input rig is rejected when its gauge-free chi-square exceeds this quantile
# What the observations must hold to determine a rig (below these calibrate refuses, naming which)
MIN_FRAMES = 10  # frames with a marker seen by 2 or more cameras (the held-out check cuts them into blocks)
MIN_CAMERA_POINTS = 10  # points a camera shares with the others (a pose has 6 unknowns, a point gives 2 equations)
LINE_RATIO = 0.02  # points whose spread across their main axis is below this fraction of the spread along it
EQUATIONS_PER_UNKNOWN = 2  # equations beyond the points' own per unknown of the rig (an a-posteriori sigma needs some)


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
    import pycolmap  # imported where used: a reconstruct never needs it

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
    import pycolmap

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
    import pycolmap

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
def _rig_arrays(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world of every camera: R (C, 3, 3), t (C, 3) [m]."""
    return np.stack([c.R for c in rig]), np.stack([c.tvec for c in rig])


def _transform_rig(rig: Rig, s: float, R: np.ndarray, t: np.ndarray) -> Rig:
    """Apply the world similarity x' = s R x + t to every camera (see batgraph.geometry.pose.similarity_*)."""
    out = []
    for cam in rig:
        Rc, tc = pose.similarity_cam_from_world(cam.R, cam.tvec, s, R, t)
        cov = None if cam.pose_cov is None else pose.similarity_pose_cov(cam.pose_cov, s)
        out.append(Camera(cam.name, cam.size_wh, cam.K.copy(), cam.dist.copy(), pose.rvec_from_R(Rc), tc, cov))
    return Rig(out)


def _scale_joint(cov: np.ndarray, s: float) -> np.ndarray:
    """A joint rig covariance (6C, 6C) after a world similarity of scale s (translations scale by s)."""
    d = np.tile(np.r_[1.0, 1.0, 1.0, s, s, s], len(cov) // 6)
    return cov * np.outer(d, d)


def _with_covariances(rig: Rig, cov: np.ndarray, fixed: list[int]) -> Rig:
    """Cameras carrying their 6x6 blocks of a joint covariance (6C, 6C); ``fixed`` cameras carry none.

    A block with a direction of (numerically) zero variance (COLMAP's scale gauge, or a 2-camera rig's
    gauge-free covariance) gets GAUGE_FLOOR_M^2 added on its diagonal so that a prior can invert it.
    """
    cams = []
    for c, cam in enumerate(rig):
        block = None
        if c not in fixed:
            block = 0.5 * (cov[6 * c:6 * c + 6, 6 * c:6 * c + 6] + cov[6 * c:6 * c + 6, 6 * c:6 * c + 6].T)
            if np.linalg.eigvalsh(block).min() < GAUGE_FLOOR_M**2:
                block = block + GAUGE_FLOOR_M**2 * np.eye(6)
        cams.append(Camera(cam.name, cam.size_wh, cam.K, cam.dist, cam.rvec, cam.tvec, block))
    return Rig(cams, world_mirror=rig.world_mirror)


def _wand_lengths(rig: Rig, dense: DenseObservations, wand: Wand, sigma_px: float) -> np.ndarray:
    """Triangulated wand length on every frame where both ends have >= 2 views, (n,) [m]."""
    ia, ib = dense.markers.index(wand.end_a), dense.markers.index(wand.end_b)
    sub = DenseObservations(dense.cameras, dense.frames, [wand.end_a, wand.end_b],
                            dense.uv_px[:, :, [ia, ib]], dense.weight[:, :, [ia, ib]])
    xyz, _ = triangulate(rig, sub, sigma_px)
    d = np.linalg.norm(xyz[:, 0] - xyz[:, 1], axis=-1)
    return d[np.isfinite(d)]


@dataclass
class _Gauged:
    """The refined rig in its final gauge, with its joint pose covariance there (6C, 6C)."""

    rig: Rig
    cov: np.ndarray | None
    scale: dict
    lever_m: float  # the similarity fit's lever arm [m] (batgraph.geometry.gauge)


def _apply_gauge(fit: _Fit, rig_in: Rig, dense: DenseObservations, wand: Wand | None, gauge_name: str,
                 ref: int, sigma: float) -> _Gauged:
    """Move the bundle adjustment's rig (reference camera held, COLMAP's scale) into the chosen gauge."""
    rig, cov = fit.rig, fit.cov
    R_in, t_in = _rig_arrays(rig_in)
    lever = rig_gauge.default_lever_m(np.array([c.center_world for c in rig_in]))
    info: dict = {}
    if wand is not None:
        lengths = _wand_lengths(rig, dense, wand, sigma)
        if len(lengths) == 0:
            raise InputError(f"calibrate: the wand ends {wand.end_a!r}, {wand.end_b!r} are never both triangulated")
        s_w = wand.length_m / float(np.median(lengths))
        info = {"source": "wand", "wand_length_m": wand.length_m, "n_wand_frames": int(len(lengths)),
                "median_length_before_m": float(np.median(lengths))}
    if gauge_name == "input":
        if wand is not None:  # the wand's scale, then the rigid fit to the input
            rig, cov = _transform_rig(rig, s_w, np.eye(3), np.zeros(3)), None if cov is None else _scale_joint(cov, s_w)
        s, R, t = rig_gauge.fit_similarity(*_rig_arrays(rig), R_in, t_in, lever_m=lever, with_scale=wand is None)
        rig = _transform_rig(rig, s, R, t)
        if cov is not None:
            P = rig_gauge.gauge_projection(*_rig_arrays(rig), lever)
            cov = P @ _scale_joint(cov, s) @ P.T
        if wand is None:
            info = {"source": "input calibration (similarity fit over camera centres and orientations)"}
        info["scale_applied"] = float(s) * (s_w if wand is not None else 1.0)
        fixed = []
    else:
        c_ref = rig[ref].center_world
        if wand is not None:
            s = s_w
        else:
            rel_out = np.array([c.center_world for c in rig]) - c_ref
            rel_in = np.array([c.center_world for c in rig_in]) - rig_in[ref].center_world
            if np.linalg.norm(rel_in, axis=1).max() < 1e-9:
                d = np.linalg.norm(rel_out, axis=1)
                s = 1.0 / d[d > 0].min()
                info = {"source": "arbitrary (input camera centres coincide; nearest camera at 1 unit)"}
            else:
                s = float((rel_out * rel_in).sum() / (rel_out**2).sum())
                info = {"source": "input calibration (least squares over camera centres)"}
        rig = _transform_rig(rig, s, np.eye(3), (1 - s) * c_ref)  # about the reference camera: it keeps its pose
        cov = None if cov is None else _scale_joint(cov, s)
        info["scale_applied"] = float(s)
        fixed = [ref]
    if wand is not None:
        info["median_length_after_m"] = float(np.median(_wand_lengths(rig, dense, wand, sigma)))
    if cov is not None:
        rig = _with_covariances(rig, cov, fixed)
    return _Gauged(rig, cov, info, lever)


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
# what the observations can determine
# ==================================================================================================
def _spread(xyz: np.ndarray) -> np.ndarray:
    """Principal standard deviations (3,) [m] of points (n, 3), largest first."""
    return np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(xyz.T)), 0, None))[::-1] if len(xyz) > 2 else np.zeros(3)


def _near_line(xyz: np.ndarray) -> tuple[bool, float, float]:
    """(spread across < LINE_RATIO x spread along, across [m], along [m]) of points (n, 3)."""
    sd = _spread(xyz)
    return bool(sd[1] < LINE_RATIO * sd[0]) or sd[0] == 0, float(sd[1]), float(sd[0])


def undetermined_reason(rig: Rig, dense: DenseObservations, xyz: np.ndarray, n_unknown: int,
                        intrinsics: bool = False) -> str | None:
    """Why the observations cannot determine the rig, in one line, or None when they can.

    xyz: the points triangulated with the starting rig (F, M, 3) [m], NaN where < 2 views.
    n_unknown: the rig's unknowns beyond the gauge (6C - 7 poses, plus intrinsics when refined).
    Too few frames (< MIN_FRAMES with a point), too few points (their equations beyond their own
    positions, sum of 2 k - 3 over points seen k times, fewer than EQUATIONS_PER_UNKNOWN per unknown),
    points near a line (rotations about it are unobserved), with ``intrinsics`` (focal lengths or lens
    refined) points near a plane (thinner than LINE_RATIO of their extent: focal length trades against
    distance), a camera sharing fewer than MIN_CAMERA_POINTS points with the others or seeing them near
    a line. Poses alone are determined by points in a plane.
    """
    seen = dense.seen
    ok = np.isfinite(xyz[..., 0]) & (seen.sum(0) >= 2)
    n_frames = int(ok.any(1).sum())
    if n_frames < MIN_FRAMES:
        return (f"too few frames: {n_frames} frames have a marker seen by 2 or more cameras "
                f"(at least {MIN_FRAMES} are needed)")
    k = seen.sum(0)[ok]
    eqs = int((2 * k - 3).sum())
    if eqs < EQUATIONS_PER_UNKNOWN * n_unknown:
        return (f"too few points: {int(ok.sum())} points seen by 2 or more cameras give {eqs} equations beyond "
                f"their own positions for the rig's {n_unknown} unknowns (at least "
                f"{EQUATIONS_PER_UNKNOWN * n_unknown} are needed)")
    line, across, along = _near_line(xyz[ok])
    if line:
        return (f"degenerate motion: the points lie near a line ({1000 * across:.1f} mm across, {1000 * along:.0f} mm "
                "along it): rotations about it are not observed")
    sd = _spread(xyz[ok])
    if intrinsics and sd[2] < LINE_RATIO * sd[0]:
        return (f"degenerate motion: the points lie near a plane ({1000 * sd[2]:.1f} mm thick, {1000 * sd[0]:.0f} mm "
                "across): focal lengths and lens distortion are not observed (refine the poses only)")
    for c, cam in enumerate(rig):
        mine = ok & seen[c]
        if mine.sum() < MIN_CAMERA_POINTS:
            return (f"camera {cam.name!r} sees too little: {int(mine.sum())} points that other cameras also see "
                    f"(at least {MIN_CAMERA_POINTS} are needed)")
        line, across, along = _near_line(xyz[mine])
        if line:
            return (f"camera {cam.name!r} sees too little: its {int(mine.sum())} points lie near a line "
                    f"({1000 * across:.1f} mm across, {1000 * along:.0f} mm along it)")
    return None


# ==================================================================================================
# one adjustment, the held-out check and the verdict
# ==================================================================================================
@dataclass
class _Fit:
    """One bundle adjustment of a rig on some observations (before the gauge's scale)."""

    rig: Rig  # poses only (covariances: cov)
    prob: _Problem
    used: np.ndarray  # (n_obs,) inliers that are in the final adjustment
    err: np.ndarray  # (n_obs,) residual [px] under ``rig``
    n_points: int
    var_px2: float  # a-posteriori pixel variance
    rounds: list
    fit_px: list
    termination: str
    cov: np.ndarray | None = None  # (6C, 6C) joint pose covariance, GTSAM tangents; zero for held coordinates


def _joint_covariance(cov, rig: Rig, ref: int, t_start: dict, var_px2: float) -> np.ndarray | None:
    """pycolmap's pose covariance -> the joint (6C, 6C) covariance of the rig in GTSAM's tangents.

    The reference camera is constant (zero rows); the camera holding COLMAP's scale gauge has one
    translation coordinate constant (COLMAP does not say which: the one that did not move at all).
    """
    C = len(rig)
    free = []
    for c, cam in enumerate(rig):
        block = cov.get_cam_cov_from_world(_image_id(c, ref, C))
        if block is None:
            free.append([])
        elif block.shape == (6, 6):
            free.append(list(range(6)))
        else:
            fixed = 3 + int(np.argmin(np.abs(cam.tvec - t_start[c])))
            free.append([d for d in range(6) if d != fixed])
    full = np.zeros((6 * C, 6 * C))
    for a in range(C):
        for b in range(a, C):
            if not free[a] or not free[b]:
                continue
            x = cov.get_cam_cross_cov_from_world(_image_id(a, ref, C), _image_id(b, ref, C))
            if x is None or x.shape != (len(free[a]), len(free[b])):
                return None
            ia, ib = 6 * a + np.array(free[a]), 6 * b + np.array(free[b])
            full[np.ix_(ia, ib)] = x
            full[np.ix_(ib, ia)] = x.T
    J = np.zeros((6 * C, 6 * C))
    for c, cam in enumerate(rig):
        J[6 * c:6 * c + 6, 6 * c:6 * c + 6] = pose.pose_cov_jacobian(cam.R, cam.tvec)
    out = var_px2 * J @ full @ J.T
    return 0.5 * (out + out.T)


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
    joint = None if cov is None else _joint_covariance(cov, rig_ba, ref, t_start, var_px2)
    if covariance and joint is None:
        raise InputError("calibrate: the observations do not determine the rig (the bundle adjustment's "
                         "covariance is singular)")
    return _Fit(rig_ba, prob, used, err, int((ids >= 0).sum()), var_px2, rounds, fit_px,
                str(summary.termination_type), joint)


def _subset_frames(dense: DenseObservations, sel: np.ndarray) -> DenseObservations:
    return DenseObservations(dense.cameras, dense.frames[sel], dense.markers, dense.uv_px[:, sel], dense.weight[:, sel])


def _prediction_errors(rig: Rig, held: DenseObservations, sigma: float) -> tuple[np.ndarray, np.ndarray, str]:
    """Each observation predicted from the others: (|error| px (n,), frame index (n,), how).

    Every camera in turn is left out, the points it sees are triangulated by the other cameras (those
    seen by 2 or more of them) and projected into it. Where no point has 2 other views (2-camera rigs),
    every point is triangulated by all its views and reprojected instead (how = "all cameras").
    """
    seen = held.seen
    n_views = seen.sum(0)
    errs, frames = [], []
    if (seen & (n_views >= 3)[None]).any():
        for c, cam in enumerate(rig):
            use = seen[c] & (n_views >= 3)
            if not use.any():
                continue
            uv = held.uv_px.copy()
            uv[c] = np.nan
            with np.errstate(divide="ignore", invalid="ignore"):
                xyz, _ = triangulate(rig, DenseObservations(held.cameras, held.frames, held.markers, uv,
                                                            held.weight), sigma)
            errs.append(np.linalg.norm(cam.project(xyz[use]) - held.uv_px[c][use], axis=-1))
            frames.append(np.nonzero(use)[0])
        return np.concatenate(errs), np.concatenate(frames), "camera left out"
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz, _ = triangulate(rig, held, sigma)
    for c, cam in enumerate(rig):
        use = seen[c] & (n_views >= 2)
        errs.append(np.linalg.norm(cam.project(xyz[use]) - held.uv_px[c][use], axis=-1))
        frames.append(np.nonzero(use)[0])
    return np.concatenate(errs), np.concatenate(frames), "all cameras"


def _held_out_check(rig0: Rig, dense: DenseObservations, ref: int, sigma: float, fraction: float,
                    **adjust) -> dict:
    """Cross-validation over blocks of frames: each fold refined on the others, then predicted.

    Frames are cut into 20 consecutive blocks (neighbouring frames see nearly the same points, so single
    frames would not be held out really) and dealt into round(1 / fraction) folds; every fold is predicted
    by the starting rig and by a rig refined on the other folds (:func:`_prediction_errors`). The RMS is
    taken over the observations the refined rigs do not call outliers (robust threshold on their own
    prediction errors), the same set for both. Returns {} when there are too few frames.
    """
    F = len(dense.frames)
    n_folds = max(2, round(1 / fraction))
    fold = np.minimum(np.arange(F) * 20 // max(F, 1), 19) % n_folds
    e_in, e_ref, how = [], [], ""
    for k in range(n_folds):
        test = fold == k
        if test.sum() < 2 or (~test).sum() < 2:
            continue
        try:
            fit = _adjust(rig0, _subset_frames(dense, ~test), ref, sigma, covariance=False, progress=False, **adjust)
        except InputError:
            continue
        held = _subset_frames(dense, test)
        a, _, how = _prediction_errors(rig0, held, sigma)
        b, _, _ = _prediction_errors(fit.rig, held, sigma)
        e_in.append(a)
        e_ref.append(b)
    if not e_in:
        return {}
    a, b = np.concatenate(e_in), np.concatenate(e_ref)
    fin = np.isfinite(a) & np.isfinite(b)
    if not fin.any():
        return {}
    ok = fin & (b <= math.sqrt(CHI2_2DOF_999) * float(np.median(b[fin])) / RAYLEIGH_MEDIAN)
    return {"folds": len(e_in), "fraction": 1.0 / n_folds, "n_frames": F, "n_observations": int(ok.sum()),
            "prediction": how, "rms_input_px": rms(a[ok], math.nan), "rms_refined_px": rms(b[ok], math.nan)}


def _r95(cov: np.ndarray | None) -> tuple[float, float]:
    """95 % radius [m] of a camera's position and [rad] of its rotation: sqrt(chi2_3(0.95) * largest variance)."""
    if cov is None:
        return 0.0, 0.0
    k = math.sqrt(CHI2_3DOF_95)
    return (k * math.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)),
            k * math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))


def _assess(rig_start: Rig, g: _Gauged, metric: bool, held_out: dict, initial: str, arbitrary_scale: bool) -> dict:
    """The verdict on the refinement (see :func:`calibrate_session`) and its figures."""
    from scipy.stats import chi2 as chi2_dist

    rig_out = g.rig
    cams = {}
    for ci, co in zip(rig_start, rig_out, strict=True):
        r95_pos, r95_rot = _r95(co.pose_cov)
        cams[co.name] = {"moved_mm": 1000 * float(np.linalg.norm(ci.center_world - co.center_world)),
                         "turned_deg": _angle_deg(ci.R, co.R),
                         "r95_position_mm": 1000 * r95_pos, "r95_rotation_deg": math.degrees(r95_rot)}
    out = {"metric_reference": metric, "held_out": held_out, "cameras": cams, "determined": True, "reasons": []}
    if arbitrary_scale:
        out.update(determined=False, significant=None,
                   reasons=["no metric reference: started from scratch without a wand, the scale is arbitrary"])
        return out
    test = {}
    if g.cov is not None and initial == "input":
        R_out, t_out = _rig_arrays(rig_out)
        delta = rig_gauge.rig_difference(*_rig_arrays(rig_start), R_out, t_out)
        x2, dof = rig_gauge.gauge_free_chi2(delta, g.cov, R_out, t_out, g.lever_m)
        test = {"chi2": x2, "dof": dof, "level": SIGNIFICANCE, "bound": float(chi2_dist.ppf(SIGNIFICANCE, dof)),
                "p_value": float(chi2_dist.sf(x2, dof))}
    out["poses"] = test
    reasons = []
    if held_out and held_out["rms_refined_px"] >= held_out["rms_input_px"]:
        reasons.append(f"the refined rigs predict the held-out frames no better than the input ("
                       f"{held_out['rms_refined_px']:.2f} px vs {held_out['rms_input_px']:.2f} px RMS, "
                       f"{held_out['prediction']})")
    if test and not metric and test["chi2"] <= test["bound"]:
        reasons.append(f"the input rig lies within the refinement's noise (gauge-free chi-square {test['chi2']:.1f} "
                       f"for {test['dof']} degrees of freedom, {100 * SIGNIFICANCE:.0f} % bound {test['bound']:.1f})")
    out["significant"] = not reasons
    out["reasons"] = reasons
    return out


# ==================================================================================================
# the public entry points
# ==================================================================================================
def _check_arguments(session: Session, gauge_name: str, ref_camera: int, wand, initial: str,
                     hold_out: float) -> tuple[Wand | None, str, str]:
    """Validate calibrate_session's arguments; resolve the wand, initial="auto" and gauge="auto"."""
    if gauge_name not in GAUGES:
        raise InputError(f"calibrate: gauge must be one of {', '.join(GAUGES)}, got {gauge_name!r}")
    C = len(session.rig)
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
    centres = np.array([c.center_world for c in session.rig])
    no_poses = np.linalg.norm(centres - centres[0], axis=1).max() < 1e-9
    if gauge_name == "auto":
        gauge_name = "camera0" if wand is not None or initial == "scratch" else "input"
    if gauge_name == "input" and no_poses:
        raise InputError("calibrate: gauge 'input' fits the refined rig to the input camera poses, but every input "
                         "camera is at the same place (use gauge 'camera0')")
    return wand, initial, gauge_name


def calibrate_session(
    session: Session, *, refine_intrinsics: bool = False, refine_distortion: bool = False,
    gauge: str = "auto", ref_camera: int = 0, wand: Wand | tuple[str, str, float] | None = None,
    initial: str = "auto", max_iterations: int = 10, max_points: int | None = 20000,
    progress: bool = True, hold_out: float = 0.2, keep_input_if_undetermined: bool = True,
) -> tuple[Rig, dict]:
    """Refine the session's rig by bundle adjustment of all cameras at once, and judge the refinement.

    refine_intrinsics / refine_distortion: also refine focal lengths and principal points / the lens (refitted
        to the 5-parameter model). gauge: "auto", "input" or "camera0" (module docstring); ref_camera: index of
        the reference camera (held by the adjustment; with "camera0" it keeps its input pose).
    wand: (end_a, end_b, length_m) or a :class:`Wand`; None = session.toml's [wand] if present. initial: "input"
        (the session's calibration), "scratch" (essential matrix and PnP) or "auto" ("scratch" with a wand).
    max_iterations: outlier-rejection rounds; max_points: at most this many (frame, marker) points; hold_out:
        1 / the number of folds of the held-out check (0 skips it); keep_input_if_undetermined: False returns
        the refinement even when the verdict keeps the input.
    Returns (rig, report): the rig with pose_cov (6, 6) per camera, or the input rig (``report["kept_input"]``)
    when the verdict (``report["assessment"]``, docs/calibration.md) keeps it; from scratch without a wand or
    input poses the scale is arbitrary (``determined`` False). Raises InputError when the observations cannot
    determine the rig (:func:`undetermined_reason`).
    """
    wand, initial, gauge_name = _check_arguments(session, gauge, ref_camera, wand, initial, hold_out)
    rig_in = session.rig
    C = len(rig_in)
    given = session.pixel_sigma_px
    # the starting noise scale of the robust loss and thresholds: the session's, else 1 px (the bundle
    # adjustment's rounds measure the a-posteriori sigma themselves; the input rig may be far off)
    sigma = float(np.median(list(given.values()))) if isinstance(given, dict) else float(given or 1.0)
    dense = dense_observations(session)
    if wand is not None:
        for e in (wand.end_a, wand.end_b):
            if e not in dense.markers:
                raise InputError(f"calibrate: wand end {e!r} has no observations")
    rig0 = _initial_rig_from_scratch(rig_in, dense, ref_camera, sigma) if initial == "scratch" else rig_in
    n_unknown = 6 * C - 7 + (4 * C if refine_intrinsics else 0) + (5 * C if refine_distortion else 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz_start, _ = triangulate(rig0, dense, sigma)
    why = undetermined_reason(rig0, dense, xyz_start, n_unknown, refine_intrinsics or refine_distortion)
    if why is not None:
        raise InputError(f"calibrate: the observations cannot determine the rig: {why}")
    adjust = {"refine_intrinsics": refine_intrinsics, "refine_distortion": refine_distortion,
              "max_iterations": max_iterations, "max_points": max_points}
    fit = _adjust(rig0, dense, ref_camera, sigma, progress=progress, **adjust)
    held_out = _held_out_check(rig0, dense, ref_camera, sigma, hold_out, **adjust) if hold_out > 0 else {}
    g = _apply_gauge(fit, rig_in, dense, wand, gauge_name, ref_camera, sigma)

    report = _report(session, rig0, g.rig, fit, dense, sigma)
    arbitrary = g.scale["source"].startswith("arbitrary")
    assessment = _assess(rig_in, g, wand is not None, held_out, initial, arbitrary)
    if gauge_name == "camera0":
        assessment["gauge_note"] = (f"camera {rig_in[ref_camera].name!r} is held at its input pose (it carries no "
                                    "covariance: the others' are relative to it)")
    kept = (initial == "input" and keep_input_if_undetermined
            and not (assessment["determined"] and assessment["significant"]))
    report.update({"gauge": {"origin_axes": gauge_name, "ref_camera": rig_in[ref_camera].name,
                             "note": gauge_note(gauge_name, rig_in[ref_camera].name, g.scale["source"])},
                   "scale": g.scale, "initial": initial, "rounds": fit.rounds, "n_points": fit.n_points,
                   "pixel_sigma_px": math.sqrt(fit.var_px2), "refine_intrinsics": refine_intrinsics,
                   "refine_distortion": refine_distortion,
                   "distortion_refit_max_px": dict(zip(rig_in.names, fit.fit_px, strict=True)),
                   "ceres_termination": fit.termination,
                   "camera_model": "FULL_OPENCV with k4 = k5 = k6 = 0 (= OpenCV k1 k2 p1 p2 k3)",
                   "assessment": assessment, "kept_input": kept})
    return (rig_in if kept else g.rig), report


def gauge_note(gauge_name: str, ref_name: str, scale_source: str) -> str:
    """One sentence for calibration.toml's [metadata]: where the written rig's world frame and scale come from."""
    if gauge_name == "input":
        frame = ("world frame and scale fitted to the input calibration (a similarity over every camera's centre and "
                 "orientation; the images do not observe them)")
        if scale_source == "wand":
            frame = "scale from the wand; world frame fitted to the input calibration (rigid, over every camera)"
        return frame + "; pose_covariance: that fit's degrees of freedom removed (relative to the fitted frame)"
    return (f"world frame from camera {ref_name!r} held at its input pose; scale: {scale_source}; "
            f"pose_covariance: relative to camera {ref_name!r}")


def aligned_rig(rig: Rig, target: Rig) -> Rig:
    """``rig`` moved onto ``target`` by the similarity fit over camera centres and orientations: what the images
    cannot observe (world frame and scale) taken from ``target``, to compare two rigs or a rig with the truth."""
    return _transform_rig(rig, *rig_gauge.fit_similarity(*_rig_arrays(rig), *_rig_arrays(target)))


def _aligned_errors(rig: Rig, truth: Rig) -> list[tuple[float, float]]:
    """(position [mm], rotation [deg]) error of every camera after a similarity fit of ``rig`` to ``truth``."""
    moved = aligned_rig(rig, truth)
    return [(1000 * float(np.linalg.norm(a.center_world - b.center_world)), _angle_deg(a.R, b.R))
            for a, b in zip(moved, truth, strict=True)]


def _report(session: Session, rig_in: Rig, rig_out: Rig, fit: _Fit, dense: DenseObservations, sigma: float) -> dict:
    """Per-camera figures on the observations used. "before" = the starting rig (input, or the
    from-scratch initialisation) with every point re-triangulated by it; moved/turned are relative
    to that rig; error_* / input_error_* compare with the session's true rig (simulations) after a
    similarity fit of each rig to it (what the images can determine)."""
    prob, used = fit.prob, fit.used
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz_before, _ = triangulate(rig_in, dense, sigma)
    err_before = _residuals_px(rig_in, prob, xyz_before[prob.point_fm[:, 0], prob.point_fm[:, 1]])
    truth = session.true_rig
    if truth is not None:
        err_out, err_in = _aligned_errors(rig_out, truth), _aligned_errors(session.rig, truth)
    cams = {}
    for c, (ci, co) in enumerate(zip(rig_in, rig_out, strict=True)):
        sel = prob.cam_idx == c
        u = sel & used
        row = {
            "n_obs": int(sel.sum()), "n_used": int(u.sum()), "n_rejected": int((sel & ~used).sum()),
            "rms_before_px": rms(err_before[u], math.nan), "rms_after_px": rms(fit.err[u], math.nan),
            "median_after_px": float(np.median(fit.err[u])) if u.any() else float("nan"),
            "moved_mm": 1000 * float(np.linalg.norm(co.center_world - ci.center_world)),
            "turned_deg": _angle_deg(co.R, ci.R),
        }
        if co.pose_cov is not None:
            sd = np.sqrt(np.clip(np.diag(co.pose_cov), 0, None))
            row["sd_rotation_deg"] = np.degrees(sd[:3]).tolist()
            row["sd_translation_mm"] = (1000 * sd[3:]).tolist()
        if truth is not None:
            row["error_mm"], row["error_deg"] = err_out[c]
            row["input_error_mm"], row["input_error_deg"] = err_in[c]
        cams[co.name] = row
    return {"cameras": cams}


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


def write_calibration(path: str | Path, rig: Rig, note: str | None = None) -> Path:
    """Write ``rig`` (with pose covariances) as calibration.toml, atomically; ``note`` goes to
    ``[metadata] gauge`` (where the world frame, scale and covariances come from). Returns the path."""
    path = Path(path)
    text = calibration_toml(rig)
    if note:
        import tomllib

        import tomli_w

        doc = tomllib.loads(text)
        doc["metadata"]["gauge"] = note
        text = tomli_w.dumps(doc)
    atomic.write_text(path, text)
    return path
