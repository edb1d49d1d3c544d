"""Estimates -> the output tables (trajectories, reprojection; docs/formats.md) and summary.json figures.

Errors against truth, per-camera reprojection statistics, 95 % ellipsoid coverage and differences to
a reference reconstruction. Knows nothing about how an estimate was made, nor about files.

Definitions used throughout:
* RMSE = sqrt(mean ||xyz - truth||^2) over (frame, marker) pairs, 3D Euclidean, in metres (:func:`rms`).
* coverage95 = fraction of truth points with (x - t)^T Sigma^-1 (x - t) <= 7.8147 (chi-square, 3 DOF, 95 %;
  :func:`coverage95`).
* status: ``observed`` (>= 2 views), ``single_view`` (1), ``unobserved`` (0), from the input observations.
* span: ``inside`` (from a marker's first to its last frame with >= 2 views, both included) or ``outside``
  (before or after: the track's ends, where every method extrapolates).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .labels import factorize, text_column
from .motion import CHI2_3DOF_95
from .result import Estimate
from .session import DenseObservations, Session, span_distance

STATUSES = ("observed", "single_view", "unobserved")
SPANS = ("inside", "outside")
TRAJ_COLUMNS = ["method", "frame", "time_s", "marker", "x", "y", "z", "cov_xx", "cov_xy", "cov_xz",
                "cov_yy", "cov_yz", "cov_zz", "n_views", "status", "span"]
REPROJ_COLUMNS = ["method", "frame", "camera", "marker", "u", "v", "u_hat", "v_hat", "err_px", "outlier"]
_COV_IDX = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def status_of(n_views: np.ndarray) -> np.ndarray:
    """Status strings for view counts of any shape."""
    return np.where(n_views >= 2, "observed", np.where(n_views == 1, "single_view", "unobserved"))


def span_of(n_views: np.ndarray, takes: list[slice] | None = None) -> np.ndarray:
    """Span strings, shape (F, M), for view counts of shape (F, M) (frames in order): ``inside`` from a
    marker's first to its last frame with >= 2 views within each take (slices along F; None = one take),
    ``outside`` elsewhere (all of a marker never seen twice in that take)."""
    return np.where(inside_span(n_views, takes), "inside", "outside")


def inside_span(n_views: np.ndarray, takes: list[slice] | None = None) -> np.ndarray:
    """Boolean (F, M): frame within [first, last] frame of its take where the marker has >= 2 views."""
    n_views = np.asarray(n_views)
    if takes is not None and len(takes) > 1:
        return np.concatenate([inside_span(n_views[sl]) for sl in takes])
    return span_distance(n_views) == 0


def take_of(frames: np.ndarray) -> np.ndarray:
    """Take number of each frame of a result table, (N,) int: a new take starts after a frame missing from
    the table (a result table holds every frame of its takes and none between; batgraph.session.frame_axis)."""
    frames = np.asarray(frames, np.int64)
    present = np.unique(frames)
    starts = present[np.r_[True, np.diff(present) > 1]]
    return np.searchsorted(starts, frames, side="right") - 1


OPENING_SHARE = 0.9
"""The viewer and the report open on the first frame where at least this share of the most markers seen by >= 2
cameras on any one frame are so seen: nearly the whole animal, as early as it shows."""


def opening_frame(seen_twice: np.ndarray, frames: np.ndarray) -> int | None:
    """The frame to show first (see OPENING_SHARE); None without frames. seen_twice: per frame (F,) the markers
    seen by >= 2 cameras; frames: the frame numbers (F,). A track's first frames are often seen by one camera,
    where every point is an extrapolation: a viewer opening there shows no animal."""
    seen_twice = np.asarray(seen_twice)
    if not len(seen_twice):
        return None
    target = math.ceil(OPENING_SHARE * int(seen_twice.max()))
    return int(np.asarray(frames)[np.argmax(seen_twice >= target)])


def add_span(traj: pd.DataFrame) -> pd.DataFrame:
    """A trajectories table with its ``span`` column (re)computed from n_views, per method, marker and take."""
    out = traj.copy()
    two = out["frame"].where(out["n_views"] >= 2)
    g = two.groupby([out["method"], out["marker"], take_of(out["frame"].to_numpy())], sort=False)
    first, last = g.transform("min"), g.transform("max")  # NaN for a marker never seen twice
    out["span"] = np.where((out["frame"] >= first) & (out["frame"] <= last), "inside", "outside")
    return out


def trajectories_table(session: Session, dense: DenseObservations, est: Estimate) -> pd.DataFrame:
    """The trajectories table (trajectories.csv) for one method: every frame x marker, NaN where no estimate.

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
    df["span"] = span_of(n_views, dense.take_slices).reshape(-1)
    return df


def reprojection_table(session: Session, dense: DenseObservations, est: Estimate) -> pd.DataFrame:
    """One row per observation: raw pixels, the estimate reprojected with distortion, error, outlier flag."""
    return reprojection_tables(session, dense, [est])


def reprojection_tables(session: Session, dense: DenseObservations, estimates: list[Estimate]) -> pd.DataFrame:
    """The reprojection tables of several estimates stacked in their order (each as :func:`reprojection_table`:
    per camera in the rig's order, its observations frame by frame, marker by marker).

    The observations' own columns (frame, camera, marker, u, v) are gathered once and repeated for every
    estimate, and the table is built once; only u_hat, v_hat, err_px and outlier are per estimate.
    """
    seen = dense.seen
    per_camera = [np.nonzero(seen[c]) for c in range(len(session.rig))]
    parts = [(c, fi, mi) for c, (fi, mi) in enumerate(per_camera) if len(fi)]
    if not parts:
        return pd.concat([pd.DataFrame(columns=REPROJ_COLUMNS) for _ in estimates], ignore_index=True)
    fi = np.concatenate([p[1] for p in parts])
    mi = np.concatenate([p[2] for p in parts])
    ci = np.concatenate([np.full(len(p[1]), p[0]) for p in parts])
    uv = dense.uv_px[ci, fi, mi]  # (n, 2) raw pixels
    uv_hat, outlier = [], []
    for est in estimates:
        rig = est.rig if est.rig is not None else session.rig  # the rig the estimate was made with
        for c, f, m in parts:  # camera by camera, as the rows are
            tau = _capture_frames(session.rig[c], rig[c], dense, c, f, m, session.fps)
            uv_hat.append(rig[c].project(est.xyz_m[f, m] if tau is None else at_time(est.xyz_m, f, m, tau)))
            outlier.append(est.outlier[c, f, m])
    uv_hat = np.concatenate(uv_hat)
    k = len(estimates)
    uv_all = np.tile(uv, (k, 1))
    return pd.DataFrame({
        "method": text_column([est.method for est in estimates], np.repeat(np.arange(k), len(fi))),
        "frame": np.tile(dense.frames[fi], k),
        "camera": text_column(session.rig.names, np.tile(ci, k)),
        "marker": text_column(dense.markers, np.tile(mi, k)),
        "u": uv_all[:, 0], "v": uv_all[:, 1], "u_hat": uv_hat[:, 0], "v_hat": uv_hat[:, 1],
        "err_px": np.linalg.norm(uv_hat - uv_all, axis=1), "outlier": np.concatenate(outlier),
    })


def _capture_frames(given, used, dense: DenseObservations, c: int, f: np.ndarray, m: np.ndarray, fps: float):
    """Each observation's capture time after its frame [frames] (n,) with camera ``used``'s timing (the given
    camera's as the observations hold it, moved by the difference in offset and readout), or None when all are 0."""
    base = np.zeros(len(f)) if dense.time_frac is None else dense.time_frac[c, f, m]
    row = np.zeros(len(f)) if dense.row_frac is None else dense.row_frac[c, f, m]
    tau = base + fps * ((used.time_offset_s - given.time_offset_s) + (used.readout_s - given.readout_s) * row)
    return tau if np.any(tau != 0) else None


def at_time(xyz_m: np.ndarray, f: np.ndarray, m: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Positions (n, 3) of markers m at frames f + tau [frames] from a track (F, M, 3): Catmull-Rom (cubic,
    through the frames around) inside the frames, straight on from the end frames' step beyond them (as the
    motion models extrapolate), and the frame's own value where the frames needed are not estimated."""
    F = len(xyz_m)
    t = np.clip(f + tau, 0, F - 1)
    k = np.clip(np.floor(t).astype(np.int64), 0, max(F - 2, 0))
    u = (t - k)[:, None]
    p = [xyz_m[np.clip(k + j, 0, F - 1), m] for j in (-1, 0, 1, 2)]
    out = 0.5 * (2 * p[1] + (p[2] - p[0]) * u + (2 * p[0] - 5 * p[1] + 4 * p[2] - p[3]) * u**2
                 + (3 * p[1] - p[0] - 3 * p[2] + p[3]) * u**3)
    if F > 1:
        beyond = (f + tau - t)[:, None]  # frames past the first (< 0) or last (> 0) frame
        step = np.where(beyond < 0, xyz_m[1, m] - xyz_m[0, m], xyz_m[F - 1, m] - xyz_m[F - 2, m])
        out = out + beyond * step
    bad = ~np.isfinite(out).all(axis=1)
    out[bad] = xyz_m[f[bad], m[bad]]
    return out


def method_rows(table: pd.DataFrame) -> dict[str, slice | np.ndarray]:
    """The rows (positions, for ``iloc``) of each method in a table with a ``method`` column, in order of first
    appearance: a slice where a method's rows are one block (as the pipeline stacks them), else their indices.
    ``table.iloc[rows]`` is ``table[table["method"] == m]`` without comparing every row's text per method."""
    labels = factorize(table["method"])
    out = {}
    order = np.argsort(labels.codes, kind="stable")
    starts = np.searchsorted(labels.codes[order], np.arange(len(labels.names) + 1))
    for k, name in enumerate(labels.names):
        rows = order[starts[k]:starts[k + 1]]
        contiguous = len(rows) and rows[-1] - rows[0] + 1 == len(rows)
        out[str(name)] = slice(int(rows[0]), int(rows[-1]) + 1) if contiguous else rows
    return out


def dense_from_table(table: pd.DataFrame, frames: np.ndarray | None = None, markers: list[str] | None = None,
                     method: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The inverse of :func:`trajectories_table`: rows -> dense arrays (the one converter every module uses).

    table: frame, marker, x, y, z [m] (cov_* and method optional; truth.csv works too).
    frames: the frame axis (sorted ints); None = contiguous from the table's first to its last frame.
    markers: the marker axis; None = order of first appearance. Rows outside either axis are dropped.
    method: keep only that method's rows (None: the table must hold one method, or no method column).
    Returns (xyz (F, M, 3) [m], cov (F, M, 3, 3) [m^2], frames, markers); NaN where the table has no value.
    """
    t = table
    if "method" in t.columns:
        if method is not None:
            t = t[t["method"] == method]
        elif t["method"].nunique() > 1:
            raise ValueError(f"the table holds several methods {list(pd.unique(t['method']))}; pass method=")
    names = list(markers) if markers is not None else list(dict.fromkeys(t["marker"].astype(str)))
    frame = t["frame"].to_numpy(np.int64)
    if frames is None:
        frames = np.arange(frame.min(), frame.max() + 1) if len(frame) else np.zeros(0, np.int64)
    frames = np.asarray(frames, np.int64)
    F, M = len(frames), len(names)
    fi = np.searchsorted(frames, frame)
    mi = t["marker"].astype(str).map({n: i for i, n in enumerate(names)}).to_numpy(float)
    ok = (fi < F) & np.isfinite(mi)
    ok[ok] = frames[fi[ok]] == frame[ok]
    fi, mi = fi[ok], mi[ok].astype(int)
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    xyz[fi, mi] = t[["x", "y", "z"]].to_numpy(float)[ok]
    if all(c in t.columns for c in TRAJ_COLUMNS[7:13]):
        cov[fi, mi] = cov_matrices(t[ok])
    return xyz, cov, frames, names


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


GROUPS = ("all", *STATUSES, *SPANS, *(f"{st}/{sp}" for st in STATUSES for sp in SPANS))
"""The groups every figure is given for: all points, each status, each span, and each status within each span
(e.g. ``single_view/inside``: gaps inside a track that one camera sees)."""


def group_masks(table: pd.DataFrame) -> dict[str, np.ndarray]:
    """The rows of a table with ``status`` and ``span`` columns that belong to each group of GROUPS: {group:
    bool (n,)}. Each text column is compared once per value (a comparison of a text column costs ~1 ms even
    on a small table, and a summary asks for every group of every method)."""
    status = {st: (table["status"] == st).to_numpy(bool) for st in STATUSES}
    span = {sp: (table["span"] == sp).to_numpy(bool) for sp in SPANS}
    return {"all": np.ones(len(table), bool), **status, **span,
            **{f"{st}/{sp}": status[st] & span[sp] for st in STATUSES for sp in SPANS}}


def errors_by_method(traj: pd.DataFrame, points: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """:func:`errors_against` of each method of a stacked trajectories table (with ``span`` added if missing),
    the join with ``points`` made once for all of them: per method, the frame errors_against of that method's
    rows alone gives (same rows, order and index); a method with no row in the join is left out."""
    j = errors_against(traj if "span" in traj.columns else add_span(traj), points)
    return {m: j.iloc[rows].reset_index(drop=True) for m, rows in method_rows(j).items()}


def point_errors(traj: pd.DataFrame, points: pd.DataFrame, joined: pd.DataFrame | None = None) -> pd.DataFrame:
    """errors_against restricted to the rows where the method gave an estimate: method, frame, marker,
    status, span, err_m [m] and mahal2 (NaN without a valid covariance). joined: ``errors_against`` of these
    rows, where the caller has it (:func:`errors_by_method`)."""
    if joined is None:
        joined = errors_against(traj if "span" in traj.columns else add_span(traj), points)
    j = joined
    j = j[np.isfinite(j["err_m"].to_numpy(float))]
    return j[["method", "frame", "marker", "status", "span", "err_m", "mahal2"]].reset_index(drop=True)


def rms(errors: np.ndarray, empty: float | None = None) -> float | None:
    """Root mean square of the finite entries of ``errors`` (any shape, any unit: the RMSE of 3D errors [m], a
    reprojection RMS [px]); ``empty`` (default None) when there are none."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if len(e) else empty


def coverage95(mahal2: np.ndarray) -> float | None:
    """Fraction of the points inside their 95 % ellipsoid: squared Mahalanobis distances (n,) <= CHI2_3DOF_95,
    over the finite ones (NaN: no valid covariance, no ellipsoid); None when there are none."""
    d2 = np.asarray(mahal2, dtype=float)
    d2 = d2[np.isfinite(d2)]
    return float(np.mean(d2 <= CHI2_3DOF_95)) if len(d2) else None


def truth_stats(traj: pd.DataFrame, truth: pd.DataFrame, joined: pd.DataFrame | None = None) -> dict:
    """One method's errors against truth per group (GROUPS): rmse_m, mean_m, p95_m [m], coverage95, n (truth
    points in the group), n_estimated (of those, the ones the method estimates; the figures are over these).
    joined: ``errors_against`` of these rows, where the caller has it (:func:`errors_by_method`)."""
    if joined is None:
        joined = errors_against(traj if "span" in traj.columns else add_span(traj), truth)
    j = joined
    out = {"rmse_m": {}, "mean_m": {}, "p95_m": {}, "coverage95": {}, "n": {}, "n_estimated": {}}
    masks = group_masks(j)
    err_all, m2_all = j["err_m"].to_numpy(float), j["mahal2"].to_numpy(float)
    for name in GROUPS:
        err, m2 = err_all[masks[name]], m2_all[masks[name]]
        est = np.isfinite(err)
        out["rmse_m"][name] = rms(err)
        out["mean_m"][name] = float(err[est].mean()) if est.any() else None
        out["p95_m"][name] = float(np.percentile(err[est], 95)) if est.any() else None
        out["coverage95"][name] = coverage95(m2)
        out["n"][name] = int(len(err))
        out["n_estimated"][name] = int(est.sum())
    return out


def reference_stats(traj: pd.DataFrame, reference: pd.DataFrame, joined: pd.DataFrame | None = None) -> dict:
    """Differences to another tool's 3D (e.g. DLTdv's xyzpts): RMS, median, max [m] and count, over all
    common points, plus rms_m and n per group (GROUPS). joined: as :func:`point_errors`'."""
    d = point_errors(traj, reference, joined)
    if not len(d):
        return {"n": 0}
    e = d["err_m"].to_numpy()
    groups = {g: e[mask] for g, mask in group_masks(d).items()}
    return {"n": int(len(e)), "rms_m": rms(e), "median_m": float(np.median(e)),
            "max_m": float(e.max()), "rms_by_group_m": {g: rms(v) for g, v in groups.items()},
            "n_by_group": {g: int(len(v)) for g, v in groups.items()}}


def focal_px(cam) -> float:
    """The focal length [px] that turns a pixel error into millimetres at a depth: sqrt(fx fy)."""
    return float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))


def reprojection_in_mm(reprojection: pd.DataFrame, trajectories: pd.DataFrame, rig) -> pd.DataFrame:
    """Reprojection errors in millimetres at the marker's depth.

    reprojection: reprojection.csv's columns (method, frame, camera, marker, u, v, u_hat, v_hat, err_px, outlier).
    trajectories: method, frame, marker, x, y, z [m, user frame]: the estimate whose reprojection it is.
    Returns a copy with ``depth_m`` (z of the estimated point in the camera [m]; NaN behind the camera),
    ``err_mm = err_px * depth_m / f_px * 1000`` and the signed components ``du_mm, dv_mm`` of
    (u_hat - u, v_hat - v) scaled the same way; f_px = sqrt(fx fy) (:func:`focal_px`); lens distortion's
    local scale change is ignored (a few per cent at the edge of a GoPro image).
    """
    rep = reprojection.copy()
    keys = ["method", "frame", "marker"]
    xyz = (trajectories[keys + ["x", "y", "z"]].drop_duplicates(keys)
           .set_index(keys).reindex(pd.MultiIndex.from_frame(rep[keys])).to_numpy(float))
    if len(xyz):
        xyz = rig.to_user(xyz)  # back to the rig's world (the mirror is its own inverse)
    depth = np.full(len(rep), np.nan)
    f = np.full(len(rep), np.nan)
    codes, names = pd.factorize(rep["camera"])
    for k, name in enumerate(names):
        if name not in rig.names:
            continue
        sel = codes == k
        depth[sel] = rig[name].to_cam(xyz[sel])[:, 2]
        f[sel] = focal_px(rig[name])
    depth[depth <= 0] = np.nan
    scale = depth / f * 1000.0  # mm per px
    rep["depth_m"] = depth
    rep["err_mm"] = rep["err_px"].to_numpy(float) * scale
    rep["du_mm"] = (rep["u_hat"] - rep["u"]).to_numpy(float) * scale
    rep["dv_mm"] = (rep["v_hat"] - rep["v"]).to_numpy(float) * scale
    return rep


def reprojection_stats(session: Session, rep_mm: pd.DataFrame) -> dict:
    """Per camera, over its inlier observations (outlier False) with an estimate: n, mean/median/rms/p95
    error [px], mean/median/p95 error in mm at the marker's depth (see :func:`reprojection_in_mm`); plus
    n_outliers (observations the method flagged, left out of every figure) and outlier_fraction."""
    out = {}
    # the columns once, then each camera's rows by index (a boolean filter of the whole table per camera
    # took 0.12 s per method at 30 cameras x 1M rows)
    codes, names = pd.factorize(rep_mm["camera"].astype(str))
    rows_of = dict(zip(names, np.split(np.argsort(codes, kind="stable"), np.cumsum(np.bincount(codes))[:-1]),
                       strict=True)) if len(codes) else {}
    flagged_all = rep_mm["outlier"].fillna(False).astype(bool).to_numpy()
    e_all, mm_all = rep_mm["err_px"].to_numpy(float), rep_mm["err_mm"].to_numpy(float)
    for cam in session.rig:
        rows = rows_of.get(cam.name, np.zeros(0, np.int64))
        flagged, e = flagged_all[rows], e_all[rows]
        ok = np.isfinite(e) & ~flagged
        n_out = int(flagged.sum())
        if not ok.any():
            out[cam.name] = {"n": 0, "n_outliers": n_out}
            continue
        mm = mm_all[rows][ok]
        mm = mm[np.isfinite(mm)]
        out[cam.name] = {
            "n": int(ok.sum()), "n_outliers": n_out, "outlier_fraction": n_out / (int(ok.sum()) + n_out),
            "mean_px": float(e[ok].mean()), "median_px": float(np.median(e[ok])),
            "rms_px": rms(e[ok]), "p95_px": float(np.percentile(e[ok], 95)),
            "mean_mm_at_depth": float(mm.mean()) if len(mm) else None,
            "median_mm_at_depth": float(np.median(mm)) if len(mm) else None,
            "p95_mm_at_depth": float(np.percentile(mm, 95)) if len(mm) else None,
        }
    return out


def _keys(table: pd.DataFrame) -> pd.MultiIndex:
    """(frame, camera, marker) of each row, frame as an integer and the labels as text."""
    return pd.MultiIndex.from_arrays([table["frame"].to_numpy(np.int64), table["camera"].astype(str),
                                      table["marker"].astype(str)])


def method_summary(session: Session, traj: pd.DataFrame, reproj: pd.DataFrame, runtime_s: float | None = None,
                   info: dict | None = None, truth_errors: pd.DataFrame | None = None,
                   reference_errors: pd.DataFrame | None = None) -> dict:
    """summary.json's entry for one method, from its own rows of the two tables. truth_errors, reference_errors:
    ``errors_against`` of these rows and the session's truth / reference, where the caller has them
    (:func:`errors_by_method`)."""
    rep_mm = reprojection_in_mm(reproj, traj, session.rig)
    t = traj if "span" in traj.columns else add_span(traj)
    has = np.isfinite(t["x"].to_numpy(float))
    masks = group_masks(t)
    s = {"runtime_s": runtime_s, "reprojection": reprojection_stats(session, rep_mm),
         "n_estimated": int(has.sum()), "n_points": int(len(t)),
         "estimated": {g: int((has & masks[g]).sum()) for g in GROUPS},
         "points": {g: int(masks[g].sum()) for g in GROUPS}}
    if session.truth is not None:
        s["truth"] = truth_stats(t, session.truth, truth_errors)
    if session.reference is not None:
        s["reference"] = reference_stats(t, session.reference, reference_errors)
    if session.mislabels is not None and len(reproj):
        is_planted = _keys(reproj).isin(_keys(session.mislabels))
        flagged = reproj["outlier"].to_numpy(bool)
        s["outlier_detection"] = {"planted": int(is_planted.sum()), "flagged": int(flagged.sum()),
                                  "flagged_planted": int((flagged & is_planted).sum())}
    if info:
        s["info"] = info
    return s
