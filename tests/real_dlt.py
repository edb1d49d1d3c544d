"""DLTdv projects built from REAL rigs (../shared/data/real), for the DLTdv importer's tests.

A helper module, not a test file. It knows nothing of batgraph's importer: it reads the published
calibrations and labels, writes DLTdv files (``*xypts.csv``, ``*dltCoefs.csv``, ``*xyzpts.csv``) in a
chosen pixel convention, world handedness and unit, and checks them with its own plain linear DLT
(:func:`dlt_triangulate`), so a test can hold the importer to the published 3D.

Conventions (OpenCV: origin at the centre of the top-left pixel, v down, 0-based). DLTdv, every
version: origin lower-left, y up, 1-based: ``u_dltdv = u_cv + 1, v_dltdv = H - v_cv``. "upper-left"
below is the other reading some tools use: ``u + 1, v + 1``.

MCSC LED rig (mcsc_led_selfcal_4cam; flydra / MultiCamSelfCal, 4 cameras 659 x 494, 464 frames)
----------------------------------------------------------------------------------------------
What the files say, measured here (``python tests/real_dlt.py`` prints the figures again):

* ``points.dat`` holds raw (distorted) pixels, 0-based (flydra's): undistorted with
  ``cv2.undistortPoints(uv, K, kc, P=K)`` (K and Bouguet kc = k1 k2 p1 p2 from ``basename{n}.rad``)
  (undistortion run to convergence) and linearly triangulated with the P matrices, they reproject
  with median 0.279 px, p95 0.968 px (Pmatrices.dat; Pmat.cal 0.281 / 0.952); with the pixels
  shifted by +1 (1-based) median 0.959 px, p95 2.08 px (Pmat.cal 1.053 / 2.031). Projecting the
  published ``Xe.dat`` through ``Pmatrices.dat``: median 0.255 px, p95 0.705 px against the 0-based
  clicks vs 1.443 / 1.879 px against 1-based ones. So the P matrices are for 0-based (OpenCV)
  undistorted pixels.
* ``Pmatrices.dat`` (and ``Xe.dat``, ``Ce.dat``, ``Re.dat``) is MCSC's own projective-to-Euclidean
  frame: det(P[:, :3]) < 0 for all 4 cameras while the depth w = P[2] @ [X, 1] > 0 for every point of
  ``Xe.dat`` (sign(det) * w < 0 for 100 % of the triangulated points), i.e. with y-down pixels that
  world is LEFT-HANDED (mirrored), and its unit is arbitrary.
* ``camera{n}.Pmat.cal`` is the same rig after "Align-Existing" to ``original_cam_centers.dat``
  (flydra's world, metres): det > 0 and w > 0 for 100 % of the points, i.e. RIGHT-HANDED, in metres.
  The map from the MCSC frame to it is a similarity with a reflection: fitted on the camera centres
  ``Ce.dat`` -> ``Cst.dat`` (the aligned centres), scale 0.22741 m per MCSC unit, det(R) = -1,
  residual 4e-16 m; ``Pmat.cal`` equals ``Pmatrices.dat`` composed with its inverse to 9e-16 relative.
* ``Xe.dat`` columns are 87 of the frames 0, 5, 10, ... (``Use-Nth-Frame: 5``); ``cam1.points4cal.dat``
  (X Y Z 1 u v 1, X = Xe exactly, u v = raw points.dat exactly) gives which frame each is.

This module uses the aligned, right-handed, metric rig (``camera{n}.Pmat.cal``), the undistorted
clicks of all 464 frames (IdMat visibility: 1599 clicks), and as published 3D ``Xe.dat`` mapped by
the similarity above (87 frames). This lens's barrel distortion (k1 = -0.27..-0.29) moves 118 of
the clicks outside the 659 x 494 image once undistorted (up to 107 px); a DLTdv user can only click
inside the image, so they are dropped (``load_mcsc(crop=False)`` keeps them), and 80 of the 87
published points keep >= 2 views. Linear DLT triangulation of the written files reproduces those
to median 0.083 mm, p95 0.65 mm, max 3.09 mm (uncropped: 87 points, 0.081 / 0.49 / 1.25 mm): that
is this calibration's precision here (Xe is MCSC's bundle-adjusted point, the DLT a linear estimate
from the same clicks; the worst are points left with 2 views).

DANNCE mouse rig (dannce_mouse_6cam/label3d_dannce.mat; Label3D, MATLAB, 6 cameras)
-------------------------------------------------------------------------------------
* K is MATLAB's IntrinsicMatrix (K.T is the usual matrix) and has SKEW (K.T[0, 1] = -5.8 px on
  Camera1). ``r.T`` is the OpenCV rotation (det +1), t in mm, distortion [k1 k2 p1 p2 k3] from
  RDistort (k1 k2 k3) and TDistort (p1 p2). With the skew kept, data_2d is exactly the projection
  of data_3d (median 1e-13 px, max 5e-13 px per camera: Label3D stores reprojected labels);
  ``cv2.projectPoints`` ignores K[0, 1], which is where the 0.14-0.92 px of the folder's README come
  from (without skew: median 0.92 px on Camera1, 0.14 px on Camera5).
* The world is right-handed (det R = +1, every landmark at positive depth), in mm.
* MATLAB pixels are 1-based (centre of the top-left pixel is (1, 1)), K's principal point likewise;
  both are shifted by -1 here to OpenCV's 0-based pixels (an exact re-labelling of pixel
  coordinates: the 3D does not change).
* Image size: not in the file. The demo's COM config crops ``[0, 1152] x [0, 1024]``
  (spoonsso/dannce demo/markerless_mouse_1/COM/config.yaml), so W x H = 1152 x 1024 is used; every
  label lies inside it (MATLAB pixels u 41-1106, v 68-999), and so does every undistorted label
  (OpenCV pixels u 33-1111, v 63-1002).
* Undistortion: normalise with the full K (skew included), undistort with
  ``cv2.undistortPoints(..., I, dist)`` run to convergence (round trip 2e-12 px), re-apply K; the
  undistorted labels are then exactly the pinhole projections of data_3d, so the DLT of the written
  files reproduces data_3d to median 5e-8 mm, max 1.1e-7 mm (limited by the 6 decimals of xypts).

81 labelled frames (sparse samples of the video, frames 27..17858, written as consecutive rows),
22 landmarks, 3.8 % of the 2D labels missing, 67 of the 1782 3D landmarks missing (NaN): 1715
published points.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

REAL = Path(__file__).resolve().parents[2] / "shared/data/real"
MCSC = "mcsc_led_selfcal_4cam"
DANNCE = "dannce_mouse_6cam"
UNITS = {"m": 1.0, "cm": 100.0, "mm": 1000.0}  # file units per metre
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def real_folder(name: str) -> Path:
    """The folder of a real data set; skips the calling test (pytest.skip) when it is absent."""
    folder = REAL / name
    if not folder.is_dir():
        import pytest

        pytest.skip(f"real data {folder} is absent (expected ../shared/data/real/{name} next to the repository)")
    return folder


@dataclass
class RealRig:
    """A real rig in OpenCV conventions, world right-handed, metres.

    P: (C, 3, 4) projection matrices to OpenCV (upper-left, 0-based) UNDISTORTED pixels.
    uv: (F, M, C, 2) undistorted clicks [px, OpenCV], NaN = missing.
    xyz: (F, M, 3) published 3D [m], NaN where none was published.
    image_hw: (H, W) [px]; fps: a frame rate for the importer (the rigs' own rates are not published).
    camera_names: the data set's own names (the importer's default names are cam1..);
    notes: loader-specific raw material (K, distortion, native matrices, counts) for the figures.
    """

    name: str
    P: np.ndarray
    uv: np.ndarray
    xyz: np.ndarray
    image_hw: tuple[int, int]
    camera_names: list[str]
    fps: float = 100.0
    notes: dict = field(default_factory=dict)

    @property
    def image_wh(self) -> tuple[int, int]:
        return (self.image_hw[1], self.image_hw[0])


# ----------------------------------------------------------------------------------------------
# geometry helpers (independent of batgraph)
# ----------------------------------------------------------------------------------------------
def pixel_affine(pixel_origin: str, height_px: float) -> np.ndarray:
    """A (3, 3): ``[u, v, 1]_dltdv = A @ [u, v, 1]_opencv``."""
    if pixel_origin == "lower-left":
        return np.array([[1.0, 0, 1], [0, -1, float(height_px)], [0, 0, 1]])
    if pixel_origin == "upper-left":
        return np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 1]])
    raise ValueError(f"pixel_origin must be 'lower-left' or 'upper-left', got {pixel_origin!r}")


def apply_affine(A: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.asarray(uv, float) @ A[:2, :2].T + A[:2, 2]


def project_P(P: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(C, 3, 4) x (..., 3) -> (..., C, 2) pixels."""
    X = np.concatenate([xyz, np.ones(xyz.shape[:-1] + (1,))], axis=-1)
    h = np.einsum("cij,...j->...ci", P, X)
    return h[..., :2] / h[..., 2:]


def depth_sign(P: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """sign(det(M)) * w per camera, (..., C): > 0 = in front for a y-down pixel convention."""
    X = np.concatenate([xyz, np.ones(xyz.shape[:-1] + (1,))], axis=-1)
    w = np.einsum("cj,...j->...c", P[:, 2], X)
    return np.sign(np.linalg.det(P[:, :, :3])) * w


def coefs_to_P(L: np.ndarray) -> np.ndarray:
    L = np.asarray(L, float).reshape(-1, 11)
    return np.concatenate([L, np.ones((len(L), 1))], axis=1).reshape(-1, 3, 4)


def dlt_project(L: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """The DLT of coefficients L (C, 11) applied to xyz (..., 3) -> (..., C, 2), in the file's pixels."""
    return project_P(coefs_to_P(L), xyz)


def dlt_triangulate(L: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Plain linear DLT (what DLTdv does): least squares on the 11 coefficients, per point.

    L: (C, 11); uv: (..., C, 2) in the coefficients' pixels, NaN = missing. Each camera seeing the
    point adds ``(L1 - u L9) X + (L2 - u L10) Y + (L3 - u L11) Z = u - L4`` and likewise for v.
    Returns (..., 3), NaN where fewer than 2 cameras see the point.
    """
    L = np.asarray(L, float)
    uv = np.asarray(uv, float)
    shape = uv.shape[:-2]
    flat = uv.reshape(-1, len(L), 2)
    seen = np.isfinite(flat).all(-1)  # (N, C)
    u = np.where(seen, flat[..., 0], 0.0)[..., None]
    v = np.where(seen, flat[..., 1], 0.0)[..., None]
    A = np.concatenate([L[None, :, 0:3] - u * L[None, :, 8:11], L[None, :, 4:7] - v * L[None, :, 8:11]], axis=1)
    b = np.concatenate([u[..., 0] - L[None, :, 3], v[..., 0] - L[None, :, 7]], axis=1)
    w = np.concatenate([seen, seen], axis=1).astype(float)
    A, b = A * w[..., None], b * w
    out = np.full((len(flat), 3), np.nan)
    ok = seen.sum(1) >= 2
    if ok.any():
        out[ok] = (np.linalg.pinv(A[ok]) @ b[ok][..., None])[..., 0]
    return out.reshape(shape + (3,))


def error_figures_mm(xyz_a_m: np.ndarray, xyz_b_m: np.ndarray) -> dict:
    """Median / p95 / max distance [mm] and count over points finite in both."""
    d = np.linalg.norm(np.asarray(xyz_a_m) - np.asarray(xyz_b_m), axis=-1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"n": 0, "median_mm": np.nan, "p95_mm": np.nan, "max_mm": np.nan}
    return {"n": int(d.size), "median_mm": float(np.median(d) * 1e3), "p95_mm": float(np.percentile(d, 95) * 1e3),
            "max_mm": float(d.max() * 1e3)}


def _similarity(A: np.ndarray, B: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t minimising |s R a + t - b| (Umeyama), reflections allowed (det R = +-1)."""
    ma, mb = A.mean(0), B.mean(0)
    U, S, Vt = np.linalg.svd((B - mb).T @ (A - ma))
    R = U @ Vt
    s = S.sum() / ((A - ma) ** 2).sum()
    return s, R, mb - s * R @ ma


# ----------------------------------------------------------------------------------------------
# MCSC LED rig
# ----------------------------------------------------------------------------------------------
def _octave(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#", ndmin=2)


def _rad(path: Path) -> tuple[np.ndarray, np.ndarray]:
    v = dict(re.findall(r"(\w+)\s*=\s*([-+\d.eE]+)", path.read_text()))
    K = np.array([[float(v[f"K{r}{c}"]) for c in (1, 2, 3)] for r in (1, 2, 3)])
    kc = np.array([float(v[f"kc{j}"]) for j in (1, 2, 3, 4)])
    return K, kc


def inside_image(uv: np.ndarray, image_hw) -> np.ndarray:
    """True where OpenCV pixels (..., 2) lie in the image (pixel centres -0.5 .. size - 0.5)."""
    h, w = image_hw
    return (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5)


def load_mcsc(frames: slice | np.ndarray | None = None, crop: bool = True) -> RealRig:
    """The MCSC LED rig: aligned P (metres, right-handed), undistorted clicks, Xe in metres.

    frames: a subset of the 464 frames (None: all). One marker ("led").
    crop: drop clicks whose UNDISTORTED position falls outside the image (this lens's barrel
    distortion moves edge clicks up to 107 px out): a DLTdv user can only click inside the image.
    """
    d = real_folder(MCSC)
    names = (d / "camera_order.txt").read_text().split()
    n = len(names)
    pts = _octave(d / "points.dat")  # (3n, F): x, y, 1 per camera, raw px
    vis = _octave(d / "IdMat.dat").astype(bool)  # (n, F)
    F = pts.shape[1]
    raw = pts.reshape(n, 3, F)[:, :2].transpose(2, 0, 1)  # (F, n, 2)
    raw = np.where(vis.T[..., None], raw, np.nan)
    uv = np.full_like(raw, np.nan)
    Ks, kcs = [], []
    for c in range(n):
        K, kc = _rad(d / f"basename{c + 1}.rad")
        Ks.append(K)
        kcs.append(kc)
        ok = np.isfinite(raw[:, c, 0])
        dist = np.r_[kc, 0.0]
        uv[ok, c] = cv2.undistortPoints(raw[ok, c].reshape(-1, 1, 2), K, dist, P=K,
                                        criteria=_CRITERIA).reshape(-1, 2)
    n_clicks = int(np.isfinite(uv[..., 0]).sum())
    if crop:
        uv[~inside_image(uv, (494, 659))] = np.nan
    P = np.stack([_octave(d / f"camera{c + 1}.Pmat.cal") for c in range(n)])
    # Xe (MCSC frame) -> aligned frame: the similarity that maps Ce (MCSC centres) to Cst (aligned)
    Ce, Cst = _octave(d / "Ce.dat").T, _octave(d / "Cst.dat")
    s, R, t = _similarity(Ce, Cst)
    Xe = _octave(d / "Xe.dat")[:3].T
    Xe_m = s * Xe @ R.T + t
    # which frame each Xe column is: cam1.points4cal.dat rows are (Xe, raw uv of camera 1)
    corr = _octave(d / "cam1.points4cal.dat")
    xe_idx = [int(np.argmin(np.abs(Xe - r[:3]).sum(1))) for r in corr]
    fr_idx = [int(np.nanargmin(np.abs(raw[:, 0] - r[4:6]).sum(1))) for r in corr]
    xyz = np.full((F, 1, 3), np.nan)
    xyz[fr_idx, 0] = Xe_m[xe_idx]
    notes = {"K": np.stack(Ks), "kc": np.stack(kcs), "similarity_scale": s, "similarity_det": float(np.linalg.det(R)),
             "Pmatrices": _octave(d / "Pmatrices.dat").reshape(n, 3, 4), "Xe_native": Xe,
             "xe_frames": np.array(fr_idx), "clicks": n_clicks,
             "clicks_outside_dropped": n_clicks - int(np.isfinite(uv[..., 0]).sum()),
             "Ce_to_Cst_residual_m": float(np.abs(s * Ce @ R.T + t - Cst).max())}
    rig = RealRig(MCSC, P, uv[:, None], xyz, (494, 659), names, fps=100.0, notes=notes)
    if frames is not None:
        rig.uv, rig.xyz = rig.uv[frames], rig.xyz[frames]
    return rig


def mcsc_conventions() -> dict:
    """The figures of the module docstring for MCSC (pixel base and handedness of the P matrices)."""
    rig = load_mcsc(crop=False)
    out = {}
    uv = rig.uv[:, 0]  # (F, C, 2)
    for name, P in (("Pmatrices", rig.notes["Pmatrices"]), ("Pmat.cal", rig.P)):
        for off in (0.0, 1.0):
            L = (P / P[:, 2:3, 3:4]).reshape(-1, 12)[:, :11]
            X = dlt_triangulate(L, uv + off)
            e = np.linalg.norm(project_P(P, X) - (uv + off), axis=-1)
            out[f"{name} reproj, pixels {'1' if off else '0'}-based: median/p95 px"] = (
                round(float(np.nanmedian(e)), 3), round(float(np.nanpercentile(e, 95)), 3))
        X = dlt_triangulate((P / P[:, 2:3, 3:4]).reshape(-1, 12)[:, :11], uv)
        sgn = depth_sign(P, X[np.isfinite(X).all(-1)])
        out[f"{name} det sign per camera"] = np.sign(np.linalg.det(P[:, :, :3])).tolist()
        out[f"{name} fraction of points in front with y-down pixels"] = float((sgn > 0).mean())
    Xn = rig.notes["Xe_native"]
    Pm = rig.notes["Pmatrices"]
    for off in (0.0, 1.0):
        fr = rig.notes["xe_frames"]
        obs = uv[fr] + off
        e = np.linalg.norm(project_P(Pm, Xn) - obs, axis=-1)
        out[f"Xe through Pmatrices vs clicks {'1' if off else '0'}-based: median/p95 px"] = (
            round(float(np.nanmedian(e)), 3), round(float(np.nanpercentile(e, 95)), 3))
    out["Ce->Cst similarity: scale, det R, residual m"] = (rig.notes["similarity_scale"], rig.notes["similarity_det"],
                                                          rig.notes["Ce_to_Cst_residual_m"])
    cropped = load_mcsc()
    out["clicks, dropped as outside the image once undistorted"] = (cropped.notes["clicks"],
                                                                     cropped.notes["clicks_outside_dropped"])
    return out


# ----------------------------------------------------------------------------------------------
# DANNCE mouse rig
# ----------------------------------------------------------------------------------------------
def _distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    k1, k2, p1, p2, k3 = dist
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return np.stack([x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], axis=-1)


def load_dannce() -> RealRig:
    """The DANNCE mouse rig: P = K [R | t] (metres, right-handed, 0-based px), undistorted labels, data_3d [m]."""
    import scipy.io

    d = real_folder(DANNCE)
    m = scipy.io.loadmat(d / "label3d_dannce.mat", squeeze_me=True, struct_as_record=False)
    names = [str(s) for s in m["camnames"]]
    n = len(names)
    shift = np.array([[1.0, 0, -1], [0, 1, -1], [0, 0, 1]])  # MATLAB 1-based -> OpenCV 0-based pixels
    xyz_mm = np.asarray(m["labelData"][0].data_3d, float).reshape(-1, 22, 3)
    F, M = xyz_mm.shape[:2]
    uv = np.full((F, M, n, 2), np.nan)
    Ps, Ks, dists, reproj = [], [], [], []
    for c in range(n):
        p, lab = m["params"][c], m["labelData"][c]
        K = shift @ np.asarray(p.K, float).T
        R = np.asarray(p.r, float).T
        t_m = np.asarray(p.t, float).ravel() / 1000.0
        dist = np.r_[np.asarray(p.RDistort, float)[:2], np.asarray(p.TDistort, float), np.asarray(p.RDistort, float)[2]]
        raw = np.asarray(lab.data_2d, float).reshape(F, M, 2) - 1.0
        assert np.array_equal(np.asarray(lab.data_3d, float).reshape(F, M, 3), xyz_mm, equal_nan=True)
        ok = np.isfinite(raw).all(-1)
        xd = apply_affine(np.linalg.inv(K), raw[ok])
        xu = cv2.undistortPoints(xd.reshape(-1, 1, 2), np.eye(3), dist, criteria=_CRITERIA).reshape(-1, 2)
        uv[ok, c] = apply_affine(K, xu)
        # how the labels relate to the 3D (the module docstring's figures)
        Xc = (xyz_mm / 1000.0) @ R.T + t_m
        pred = apply_affine(K, _distort_normalized(Xc[..., :2] / Xc[..., 2:], dist))
        reproj.append(np.linalg.norm(pred - raw, axis=-1)[ok])
        Ps.append(K @ np.hstack([R, t_m[:, None]]))
        Ks.append(K)
        dists.append(dist)
    rig = RealRig(DANNCE, np.stack(Ps), uv, xyz_mm / 1000.0, (1024, 1152), names, fps=100.0,
                  notes={"K": np.stack(Ks), "dist": np.stack(dists), "label_reproj_px": reproj,
                         "data_frame": np.asarray(m["labelData"][0].data_frame)})
    return rig


def dannce_conventions() -> dict:
    rig = load_dannce()
    out = {}
    for c, e in enumerate(rig.notes["label_reproj_px"]):
        out[f"{rig.camera_names[c]} data_3d -> data_2d with skew: median/max px"] = (float(np.median(e)),
                                                                                     float(e.max()))
        out[f"{rig.camera_names[c]} skew K[0,1] px"] = float(rig.notes["K"][c][0, 1])
    ok = np.isfinite(rig.xyz).all(-1)
    out["det R / fraction in front"] = (np.linalg.det(rig.P[:, :, :3]).round(1).tolist(),
                                        float((depth_sign(rig.P, rig.xyz[ok]) > 0).mean()))
    raw_ok = np.isfinite(rig.uv).all(-1)
    out["2D missing fraction"] = float(1 - raw_ok.mean())
    out["3D complete"] = bool(ok.all())
    return out


# ----------------------------------------------------------------------------------------------
# writing a DLTdv project
# ----------------------------------------------------------------------------------------------
def project_matrices(rig_P: np.ndarray, image_hw, *, pixel_origin="lower-left", mirror: bool = False,
                     units: str = "m") -> np.ndarray:
    """The (C, 3, 4) DLT matrices, normalised to P[2, 3] = 1, of a project written with these options.

    pixel_origin: one convention for every camera, or a sequence of one per camera.
    """
    P = np.asarray(rig_P, float)
    n = len(P)
    origins = [pixel_origin] * n if isinstance(pixel_origin, str) else list(pixel_origin)
    if len(origins) != n:
        raise ValueError(f"{len(origins)} pixel origins for {n} cameras")
    k = UNITS[units]
    world = np.diag([1.0 / k, 1.0 / k, (-1.0 if mirror else 1.0) / k, 1.0])  # X_m = world @ X_file
    out = np.stack([pixel_affine(o, image_hw[0]) @ P[c] @ world for c, o in enumerate(origins)])
    return out / out[:, 2:3, 3:4]


def file_xyz(xyz_m: np.ndarray, *, mirror: bool = False, units: str = "m") -> np.ndarray:
    """Right-handed metres -> the project's user frame and units (z negated when mirrored)."""
    out = np.array(xyz_m, float) * UNITS[units]
    if mirror:
        out[..., 2] = -out[..., 2]
    return out


def write_dltdv_project(folder, rig_P: np.ndarray, uv_undistorted: np.ndarray, image_hw, *,
                        pixel_origin="lower-left", mirror: bool = False, units: str = "m",
                        xyz: np.ndarray | None = None, prefix: str = "trial") -> dict:
    """Write a DLTdv project (xypts, dltCoefs, optional xyzpts) of a real rig.

    rig_P: (C, 3, 4) to OpenCV (upper-left, 0-based) UNDISTORTED pixels, world right-handed, metres.
    uv_undistorted: (F, M, C, 2) clicks [px, OpenCV, undistorted], NaN = missing.
    image_hw: (H, W) [px]. pixel_origin: "lower-left" (DLTdv: u + 1, H - v) or "upper-left" (u + 1,
    v + 1); a sequence of one per camera mixes conventions (to test that the importer notices).
    mirror: negate the world Z (a left-handed user frame); units: "m", "cm" or "mm" for the world.
    xyz: (F, M, 3) published 3D [m, right-handed], written as xyzpts in the project's frame and units.
    Returns {"xypts", "dltCoefs", "xyzpts"} paths (xyzpts None without xyz).
    """
    from batgraph.formats import dltdv

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    P = project_matrices(rig_P, image_hw, pixel_origin=pixel_origin, mirror=mirror, units=units)
    n = len(P)
    origins = [pixel_origin] * n if isinstance(pixel_origin, str) else list(pixel_origin)
    uv = np.array(uv_undistorted, float)
    F, M = uv.shape[:2]
    for c, o in enumerate(origins):
        uv[:, :, c] = apply_affine(pixel_affine(o, image_hw[0]), uv[:, :, c])
    f, p, c = np.nonzero(np.isfinite(uv).all(-1))
    table = pd.DataFrame({"frame": f, "camera_index": c, "point_index": p, "u": uv[f, p, c, 0], "v": uv[f, p, c, 1]})
    paths = {"xypts": folder / f"{prefix}xypts.csv", "dltCoefs": folder / f"{prefix}dltCoefs.csv", "xyzpts": None}
    dltdv.write_xypts(paths["xypts"], table, n_cams=n, n_points=M, n_frames=F)
    L = P.reshape(n, 12)[:, :11]
    paths["dltCoefs"].write_text("".join(",".join(f"{x:.17g}" for x in row) + "\n" for row in L.T))
    if xyz is not None:
        X = file_xyz(xyz, mirror=mirror, units=units)
        ff, pp = np.meshgrid(np.arange(F), np.arange(M), indexing="ij")
        paths["xyzpts"] = folder / f"{prefix}xyzpts.csv"
        dltdv.write_xyzpts(paths["xyzpts"], pd.DataFrame({"frame": ff.ravel(), "point_index": pp.ravel(),
                                                          "x": X[..., 0].ravel(), "y": X[..., 1].ravel(),
                                                          "z": X[..., 2].ravel()}), n_points=M, n_frames=F)
    return paths


# ----------------------------------------------------------------------------------------------
# reading a project back, independently of batgraph
# ----------------------------------------------------------------------------------------------
def read_coefs(path) -> np.ndarray:
    """(C, 11) from a dltCoefs file (11 rows x cameras)."""
    return np.loadtxt(path, delimiter=",", ndmin=2).T


def read_clicks(path, n_cams: int) -> np.ndarray:
    """(F, M, C, 2) from an xypts file (pt{p}_cam{c}_X/Y columns, in file order)."""
    df = pd.read_csv(path)
    F = len(df)
    M = df.shape[1] // (2 * n_cams)
    out = np.full((F, M, n_cams, 2), np.nan)
    for p in range(M):
        for c in range(n_cams):
            out[:, p, c, 0] = df[f"pt{p + 1}_cam{c + 1}_X"].to_numpy(float)
            out[:, p, c, 1] = df[f"pt{p + 1}_cam{c + 1}_Y"].to_numpy(float)
    return out


def verify_project(paths: dict, xyz_m: np.ndarray, *, mirror: bool = False, units: str = "m") -> dict:
    """Triangulate the written clicks with the written coefficients (plain DLT) and compare with the
    published 3D in the project's frame. Returns error figures [mm] (see :func:`error_figures_mm`)."""
    L = read_coefs(paths["dltCoefs"])
    uv = read_clicks(paths["xypts"], len(L))
    X_file = dlt_triangulate(L, uv)
    X_m = X_file / UNITS[units]
    want = file_xyz(xyz_m, mirror=mirror, units="m")
    return error_figures_mm(X_m, want)


VARIANTS = {  # name: write_dltdv_project options, and the units to import with
    "lower-left": dict(pixel_origin="lower-left", mirror=False, units="m"),
    "upper-left": dict(pixel_origin="upper-left", mirror=False, units="m"),
    "mirrored": dict(pixel_origin="lower-left", mirror=True, units="m"),
    "millimetres": dict(pixel_origin="lower-left", mirror=False, units="mm"),
}
LOADERS = {"mcsc": load_mcsc, "dannce": load_dannce}


if __name__ == "__main__":  # print the figures the docstrings quote
    import tempfile

    for k, v in mcsc_conventions().items():
        print("MCSC  ", k, v)
    for k, v in dannce_conventions().items():
        print("DANNCE", k, v)
    with tempfile.TemporaryDirectory() as tmp:
        for rname, load in LOADERS.items():
            rig = load()
            for vname, opts in VARIANTS.items():
                paths = write_dltdv_project(Path(tmp) / rname / vname, rig.P, rig.uv, rig.image_hw, xyz=rig.xyz, **opts)
                fig = verify_project(paths, rig.xyz, mirror=opts["mirror"], units=opts["units"])
                print(f"{rname:7s} {vname:12s} DLT vs published 3D: n={fig['n']} median {fig['median_mm']:.3g} mm, "
                      f"p95 {fig['p95_mm']:.3g} mm, max {fig['max_mm']:.3g} mm")


# ----------------------------------------------------------------------------------------------
# Caliscope ChArUco (caliscope_charuco_4cam): not a DLT rig, but one reading of its files for all users
# ----------------------------------------------------------------------------------------------
def load_caliscope():
    """Caliscope's 4-webcam calibration and its 2175 ChArUco corners.

    Returns (rig: batgraph Rig cam0..cam3 from camera_array.toml (R is a 3x3 cam_from_world, metres),
    observations: frame (sync_index), camera, marker ("c<keypoint_id>"), u, v [raw px],
    board: keypoint_id -> obj_loc_x/y/z [m] in the board's frame).
    """
    from batgraph.camera import Camera, Rig

    folder = real_folder("caliscope_charuco_4cam")
    arr = tomllib.loads((folder / "camera_array.toml").read_text())["cameras"]
    rig = Rig([Camera(f"cam{k}", tuple(v["size"]), v["matrix"], v["distortions"],
                      cv2.Rodrigues(np.array(v["rotation"]))[0].ravel(), v["translation"])
               for k, v in sorted(arr.items())])
    xy = pd.read_csv(folder / "calibration" / "extrinsic" / "CHARUCO" / "xy_CHARUCO.csv")
    obs = pd.DataFrame({"frame": xy.sync_index.astype(np.int64), "camera": "cam" + xy.cam_id.astype(str),
                        "marker": "c" + xy.keypoint_id.astype(str), "u": xy.img_loc_x, "v": xy.img_loc_y,
                        "weight": 1.0})
    board = xy.groupby("keypoint_id")[["obj_loc_x", "obj_loc_y", "obj_loc_z"]].first()
    return rig, obs, board
