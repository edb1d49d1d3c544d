"""Estimates -> the contract's tables (trajectories, reprojection) and summary.json figures.

Errors against truth, per-camera reprojection statistics, 95 % ellipsoid coverage and differences to
a reference reconstruction. Knows nothing about how an estimate was made, nor about files.

Definitions used throughout (also in the README):
* RMSE = sqrt(mean ||xyz - truth||^2) over (frame, marker) pairs, 3D Euclidean, in metres.
* coverage95 = fraction of truth points with (x - t)^T Sigma^-1 (x - t) <= 7.8147 (chi-square, 3 DOF, 95 %).
* status: ``observed`` (>= 2 views), ``single_view`` (1), ``unobserved`` (0), from the input observations.
* span: ``inside`` (from a marker's first to its last frame with >= 2 views, both included) or ``outside``
  (before or after: the track's ends, where every method extrapolates).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .motion import CHI2_3DOF_95
from .result import Estimate
from .session import DenseObservations, Session

STATUSES = ("observed", "single_view", "unobserved")
SPANS = ("inside", "outside")
TRAJ_COLUMNS = ["method", "frame", "time_s", "marker", "x", "y", "z", "cov_xx", "cov_xy", "cov_xz",
                "cov_yy", "cov_yz", "cov_zz", "n_views", "status", "span"]
REPROJ_COLUMNS = ["method", "frame", "camera", "marker", "u", "v", "u_hat", "v_hat", "err_px", "outlier"]
_COV_IDX = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def status_of(n_views: np.ndarray) -> np.ndarray:
    """Status strings for view counts of any shape."""
    return np.where(n_views >= 2, "observed", np.where(n_views == 1, "single_view", "unobserved"))


def span_of(n_views: np.ndarray) -> np.ndarray:
    """Span strings, shape (F, M), for view counts of shape (F, M) (frames in order): ``inside`` from a
    marker's first to its last frame with >= 2 views, ``outside`` elsewhere (all of a marker never seen twice)."""
    return np.where(inside_span(n_views), "inside", "outside")


def inside_span(n_views: np.ndarray) -> np.ndarray:
    """Boolean (F, M): frame within [first, last] frame where the marker has >= 2 views."""
    two = np.asarray(n_views) >= 2
    seen_before = np.cumsum(two, axis=0) > 0
    seen_after = np.cumsum(two[::-1], axis=0)[::-1] > 0
    return seen_before & seen_after


def add_span(traj: pd.DataFrame) -> pd.DataFrame:
    """A trajectories table with its ``span`` column (re)computed from n_views, per method and marker."""
    out = traj.copy()
    out["span"] = "outside"
    for _, g in out.groupby(["method", "marker"], sort=False):
        two = g.loc[g["n_views"] >= 2, "frame"]
        if len(two):
            idx = g.index[(g["frame"] >= two.min()) & (g["frame"] <= two.max())]
            out.loc[idx, "span"] = "inside"
    return out


def trajectories_table(session: Session, dense: DenseObservations, est: Estimate) -> pd.DataFrame:
    """The contract's trajectories table for one method: every frame x marker, NaN where no estimate.

    Positions and covariances are in the user's frame (the rig's world with ``world_mirror`` applied), as
    truth.csv and reference_xyz.csv are.
    """
    F, M = len(dense.frames), len(dense.markers)
    n_views = dense.n_views
    df = pd.DataFrame({
        "method": est.method,
        "frame": np.repeat(dense.frames, M),
        "time_s": np.repeat(dense.frames / session.fps, M),
        "marker": np.tile(np.asarray(dense.markers, dtype=object), F),
    })
    xyz, cov = session.rig.to_user(est.xyz_m.reshape(F * M, 3), est.cov_m2.reshape(F * M, 3, 3))
    df["x"], df["y"], df["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for (i, j), name in zip(_COV_IDX, TRAJ_COLUMNS[7:13], strict=True):
        df[name] = cov[:, i, j]
    df["n_views"] = n_views.reshape(-1)
    df["status"] = status_of(n_views.reshape(-1))
    df["span"] = span_of(n_views).reshape(-1)
    return df


def reprojection_table(session: Session, dense: DenseObservations, est: Estimate) -> pd.DataFrame:
    """One row per observation: raw pixels, the estimate reprojected with distortion, error, outlier flag."""
    seen = dense.seen
    parts = []
    for c, cam in enumerate(session.rig):
        fi, mi = np.nonzero(seen[c])
        if len(fi) == 0:
            continue
        uv = dense.uv_px[c, fi, mi]
        uv_hat = cam.project(est.xyz_m[fi, mi])
        parts.append(pd.DataFrame({
            "method": est.method, "frame": dense.frames[fi], "camera": cam.name,
            "marker": np.asarray(dense.markers, dtype=object)[mi], "u": uv[:, 0], "v": uv[:, 1],
            "u_hat": uv_hat[:, 0], "v_hat": uv_hat[:, 1],
            "err_px": np.linalg.norm(uv_hat - uv, axis=1), "outlier": est.outlier[c, fi, mi],
        }))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=REPROJ_COLUMNS)


def cov_matrices(traj: pd.DataFrame) -> np.ndarray:
    """(n, 3, 3) covariance matrices from a trajectories table's cov_* columns."""
    c = traj[TRAJ_COLUMNS[7:13]].to_numpy(float)
    xx, xy, xz, yy, yz, zz = c.T
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def errors_against(traj: pd.DataFrame, points: pd.DataFrame) -> pd.DataFrame:
    """Join a method's trajectories with truth/reference points: adds ex, ey, ez, err_m, mahal2.

    Rows where either side has no value are kept with NaN errors (so callers can count them).
    """
    ref = points.rename(columns={"x": "tx", "y": "ty", "z": "tz"})
    j = traj.merge(ref, on=["frame", "marker"], how="inner")
    e = j[["x", "y", "z"]].to_numpy(float) - j[["tx", "ty", "tz"]].to_numpy(float)
    j["ex"], j["ey"], j["ez"] = e.T
    j["err_m"] = np.linalg.norm(e, axis=1)
    cov = cov_matrices(j)
    ok = np.isfinite(e).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    ok[ok] = np.linalg.eigvalsh(cov[ok])[:, 0] > 0  # a degenerate covariance has no ellipsoid: no coverage figure
    m2 = np.full(len(j), np.nan)
    if ok.any():
        m2[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(cov[ok], e[ok][..., None])[..., 0])
    j["mahal2"] = m2
    return j


def _rmse(err: np.ndarray) -> float | None:
    err = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(err**2))) if len(err) else None


def truth_stats(traj: pd.DataFrame, truth: pd.DataFrame) -> dict:
    """RMSE [m], coverage95 and counts, overall and per status, for one method's table."""
    j = errors_against(traj, truth)
    out = {"rmse_m": {}, "coverage95": {}, "n": {}, "n_estimated": {}}
    groups = [("all", j)] + [(s, j[j["status"] == s]) for s in STATUSES]
    for name, g in groups:
        est = np.isfinite(g["err_m"].to_numpy())
        m2 = g["mahal2"].to_numpy()
        out["rmse_m"][name] = _rmse(g["err_m"].to_numpy())
        has_cov = np.isfinite(m2)
        out["coverage95"][name] = float(np.mean(m2[has_cov] <= CHI2_3DOF_95)) if has_cov.any() else None
        out["n"][name] = int(len(g))
        out["n_estimated"][name] = int(est.sum())
    return out


def reference_stats(traj: pd.DataFrame, reference: pd.DataFrame) -> dict:
    """Differences to another tool's 3D (e.g. DLTdv's xyzpts): RMS, median, max [m] and count."""
    j = errors_against(traj, reference)
    d = j["err_m"].to_numpy()
    d = d[np.isfinite(d)]
    if not len(d):
        return {"n": 0}
    return {"n": int(len(d)), "rms_m": float(np.sqrt(np.mean(d**2))), "median_m": float(np.median(d)),
            "max_m": float(d.max())}


def focal_px(cam) -> float:
    """The focal length [px] that turns a pixel error into millimetres at a depth: sqrt(fx fy)."""
    return float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))


def reprojection_stats(session: Session, reproj: pd.DataFrame, traj: pd.DataFrame) -> dict:
    """Per camera: n, mean/median/rms/p95 error [px], the mean error in mm at the marker's depth
    (err_px * depth / focal), and the number flagged as outliers."""
    xyz = traj.set_index(["frame", "marker"])[["x", "y", "z"]]
    out = {}
    for cam in session.rig:
        r = reproj[reproj["camera"] == cam.name]
        e = r["err_px"].to_numpy(float)
        ok = np.isfinite(e)
        if not ok.any():
            out[cam.name] = {"n": 0}
            continue
        p = xyz.reindex(pd.MultiIndex.from_frame(r[["frame", "marker"]])).to_numpy(float)
        depth = cam.to_cam(p)[:, 2]
        mm = e * depth / focal_px(cam) * 1000
        out[cam.name] = {
            "n": int(ok.sum()), "mean_px": float(e[ok].mean()), "median_px": float(np.median(e[ok])),
            "rms_px": float(np.sqrt(np.mean(e[ok] ** 2))), "p95_px": float(np.percentile(e[ok], 95)),
            "mean_mm_at_depth": float(np.nanmean(mm[ok])), "n_outliers": int(r["outlier"].sum()),
        }
    return out


def method_summary(session: Session, est: Estimate, traj: pd.DataFrame, reproj: pd.DataFrame) -> dict:
    """summary.json's entry for one method."""
    s = {"runtime_s": est.runtime_s, "reprojection": reprojection_stats(session, reproj, traj),
         "n_estimated": int(np.isfinite(traj["x"]).sum()), "n_points": int(len(traj))}
    if session.truth is not None:
        s["truth"] = truth_stats(traj, session.truth)
    if session.reference is not None:
        s["reference"] = reference_stats(traj, session.reference)
    if session.mislabels is not None and len(reproj):
        planted = set(map(tuple, session.mislabels[["frame", "camera", "marker"]].astype(str).to_numpy()))
        keys = reproj[["frame", "camera", "marker"]].astype(str).to_numpy()
        is_planted = np.array([tuple(k) in planted for k in keys], dtype=bool)
        flagged = reproj["outlier"].to_numpy(bool)
        s["outlier_detection"] = {"planted": int(is_planted.sum()), "flagged": int(flagged.sum()),
                                  "flagged_planted": int((flagged & is_planted).sum())}
    if est.info:
        s["info"] = est.info
    return s
