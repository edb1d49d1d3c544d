"""The self-contained HTML comparison report (report.html): every method side by side, plots embedded.

It reads finished tables (trajectories, reprojection, summary) and draws them; it estimates nothing
and writes nothing but the one HTML file. Figures are matplotlib ``Figure`` objects rendered to
PNG in memory (no pyplot, so no global backend state) and embedded as base64 ``data:`` URIs, so
the file opens anywhere, offline, with no external ``src`` or ``href``.

Sections: overview, 3D trajectories, reprojection error per camera with 95 % ellipses in mm at the
marker's depth (the paper's Fig. 5 b-f), reprojections over the 2D features (Fig. 6), marker
coordinates over time with 95 % bands and occlusion shading, a per-camera error table next to the
paper's published figures, and -- when the session has them -- errors against truth (RMSE by status,
95 % coverage) and differences to a reference reconstruction (e.g. DLTdv's xyzpts).
"""

from __future__ import annotations

import base64
import html
import io
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse
from matplotlib.ticker import FuncFormatter, MaxNLocator

from . import atomic, evaluate
from . import methods as methods_registry
from .camera import Rig
from .motion import CHI2_3DOF_95

# The markers named in the paper's Fig. 6, in its order.
PAPER_MARKERS = ("body2", "shoulder_r", "elbow_r", "wrist_r", "digit5_r", "digit4_r", "digit3_r")
STATUSES = ("all", "observed", "single_view", "unobserved")
CHI2_2DOF_95 = 5.991464547107979  # 95 % quantile of chi-square, 2 DOF (reprojection ellipses)

COV_COLUMNS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
MAX_SCATTER = 1500  # residual points drawn per (method, camera): keeps PNGs small and fast
MAX_TRACK_FRAMES = 600  # frames drawn per track in the image-space and time plots
DPI = 100
MAX_ASPECT = 4.0  # 3D panels: an axis shorter than 1/4 of the longest is stretched so that it stays readable


# ----------------------------------------------------------------------------------------------
# numbers (reusable by evaluate.py)
# ----------------------------------------------------------------------------------------------
def focal_px(rig: Rig) -> dict[str, float]:
    """Per camera name, the focal length that turns pixels into millimetres (evaluate.focal_px) [px]."""
    return {c.name: evaluate.focal_px(c) for c in rig}


def reprojection_in_mm(reprojection: pd.DataFrame, trajectories: pd.DataFrame, rig: Rig) -> pd.DataFrame:
    """Express reprojection errors in millimetres at the marker's depth.

    reprojection: CONTRACT.md section 3 columns (method, frame, camera, marker, u, v, u_hat, v_hat,
        err_px [, outlier]); pixels of the raw image.
    trajectories: method, frame, marker, x, y, z [m, world]; the estimate whose reprojection it is.
    Returns a copy of ``reprojection`` with ``depth_m`` (z of that method's estimated point in the
    camera frame [m]), ``err_mm = err_px * depth_m / f_px * 1000``, and the signed components
    ``du_mm, dv_mm`` of ``(u_hat - u, v_hat - v)`` scaled the same way; NaN where the method has no
    estimate or the camera is not in the rig. ``f_px`` is sqrt(fx fy) (evaluate.focal_px); lens distortion's
    local scale change is ignored (a few per cent at the edge of a GoPro image).
    """
    rep = reprojection.copy()
    if "err_px" not in rep:
        rep["err_px"] = np.hypot(rep["u_hat"] - rep["u"], rep["v_hat"] - rep["v"])
    keys = ["method", "frame", "marker"]
    xyz = (trajectories[keys + ["x", "y", "z"]].drop_duplicates(keys)
           .set_index(keys).reindex(pd.MultiIndex.from_frame(rep[keys])).to_numpy(float))
    depth = np.full(len(rep), np.nan)
    f = np.full(len(rep), np.nan)
    cams = rep["camera"].to_numpy()
    focal = focal_px(rig)
    for name in pd.unique(cams):
        if name not in focal:
            continue
        sel = cams == name
        depth[sel] = rig[name].to_cam(xyz[sel])[:, 2]
        f[sel] = focal[name]
    depth[depth <= 0] = np.nan  # behind the camera: no meaningful scale
    scale = depth / f * 1000.0  # mm per px
    rep["depth_m"] = depth
    rep["err_mm"] = rep["err_px"].to_numpy(float) * scale
    rep["du_mm"] = (rep["u_hat"] - rep["u"]).to_numpy(float) * scale
    rep["dv_mm"] = (rep["v_hat"] - rep["v"]).to_numpy(float) * scale
    return rep


def camera_error_stats(rep_mm: pd.DataFrame) -> pd.DataFrame:
    """Per (method, camera) reprojection statistics over inlier observations.

    rep_mm: output of :func:`reprojection_in_mm`. Rows with ``outlier`` True or no observed u, v
    are left out of the statistics and counted in ``n_outliers``.
    Returns columns method, camera, n, n_outliers, mean_px, median_px, rms_px, p95_px,
    mean_mm_at_depth, p95_mm_at_depth.
    """
    rep = rep_mm.astype({"err_px": float, "err_mm": float})
    rep = rep[np.isfinite(rep["err_px"].to_numpy())]
    out = (rep["outlier"].fillna(False).astype(bool) if "outlier" in rep
           else pd.Series(False, index=rep.index))
    inl = rep[~out.to_numpy()].assign(err2=lambda d: d["err_px"] ** 2)
    g = inl.groupby(["method", "camera"], sort=False)
    stats = pd.DataFrame({
        "n": g["err_px"].size(),
        "mean_px": g["err_px"].mean(),
        "median_px": g["err_px"].median(),
        "rms_px": np.sqrt(g["err2"].mean()),
        "p95_px": g["err_px"].quantile(0.95),
        "mean_mm_at_depth": g["err_mm"].mean(),
        "p95_mm_at_depth": g["err_mm"].quantile(0.95),
    })
    n_out = out.groupby([rep["method"], rep["camera"]], sort=False).sum().rename("n_outliers")
    stats = stats.join(n_out, how="outer").reset_index()
    stats["n"] = stats["n"].fillna(0).astype(int)
    stats["n_outliers"] = stats["n_outliers"].fillna(0).astype(int)
    return stats[["method", "camera", "n", "n_outliers", "mean_px", "median_px", "rms_px", "p95_px",
                  "mean_mm_at_depth", "p95_mm_at_depth"]]


def point_errors(trajectories: pd.DataFrame, points: pd.DataFrame) -> pd.DataFrame:
    """Errors of every estimate against a point table (truth or a reference reconstruction).

    trajectories: CONTRACT.md section 3 columns (cov_* and status optional).
    points: frame, marker, x, y, z [m, world].
    Returns method, frame, marker, status, err_m (Euclidean distance [m]) and d2 (squared
    Mahalanobis distance under the estimate's covariance; NaN without a valid covariance), for the
    (frame, marker) pairs both tables have and where the method gave an estimate. The arithmetic is
    evaluate.errors_against's, so report and summary.json agree.
    """
    traj = trajectories.assign(**{c: np.nan for c in COV_COLUMNS if c not in trajectories})
    if "status" not in traj:
        traj = traj.assign(status="")
    j = evaluate.errors_against(traj, points)
    j = j[np.isfinite(j["err_m"].to_numpy(float))]
    return pd.DataFrame({"method": j["method"].to_numpy(), "frame": j["frame"].to_numpy(),
                         "marker": j["marker"].to_numpy(), "status": j["status"].astype(str).to_numpy(),
                         "err_m": j["err_m"].to_numpy(float), "d2": j["mahal2"].to_numpy(float)})


def status_metrics(errors: pd.DataFrame) -> pd.DataFrame:
    """RMSE, mean, p95 distance and 95 % coverage per method and status (plus ``all``).

    errors: output of :func:`point_errors`. Coverage is the fraction of points whose squared
    Mahalanobis distance is within the 3-DOF 95 % chi-square quantile (7.8147), over points that
    have a covariance. Returns columns method, status, n, rmse_m, mean_m, p95_m, coverage95.
    """
    errors = errors.astype({"err_m": float, "d2": float})
    both = pd.concat([errors.assign(status="all"), errors[errors["status"].isin(STATUSES[1:])]])
    both = both.assign(e2=both["err_m"] ** 2, inside=np.where(np.isfinite(both["d2"]),
                                                                (both["d2"] <= CHI2_3DOF_95).astype(float), np.nan))
    g = both.groupby(["method", "status"], sort=False)
    out = pd.DataFrame({"n": g["err_m"].size(), "rmse_m": np.sqrt(g["e2"].mean()), "mean_m": g["err_m"].mean(),
                        "p95_m": g["err_m"].quantile(0.95), "coverage95": g["inside"].mean()})
    return out.reset_index()


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _methods(trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: dict) -> list[str]:
    found = set(trajectories["method"].astype(str)) | set(reprojection["method"].astype(str))
    found |= set((summary or {}).get("methods", {}) or {})
    return methods_registry.ordered(found)


def _style(methods: list[str]) -> dict[str, tuple[str, str]]:
    return {m: methods_registry.style(m) for m in methods}


def _selected_markers(markers: list[str], n_max: int = 7) -> list[str]:
    named = [m for m in PAPER_MARKERS if m in markers]
    return named if named else list(markers[:min(n_max, 6)])


def _experiment(session) -> str:
    """Which of the paper's experiments a session resembles: 'ear' or 'flight' (by its name)."""
    tokens = re.split(r"[^a-z0-9]+", str(getattr(session, "name", "")).lower())
    return "ear" if "ear" in tokens else "flight"


def _png(fig: Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _fmt(x, digits: int = 2) -> str:
    if x is None or isinstance(x, str):
        return html.escape(x) if x else "–"
    try:
        xf = float(x)
    except (TypeError, ValueError):
        return "–"
    return "–" if not math.isfinite(xf) else f"{xf:.{digits}f}"


def _get(d, *keys):
    """Nested dict lookup that returns None for any missing level."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _table(header: list[str], rows: list[list[str]], cls: str = "") -> str:
    """HTML table from already-escaped cell strings; a cell may be (text, attrs)."""
    def cell(c, tag):
        text, attrs = (c if isinstance(c, tuple) else (c, ""))
        return f"<{tag}{(' ' + attrs) if attrs else ''}>{text}</{tag}>"
    head = "".join(cell(h, "th") for h in header)
    body = "\n".join("<tr>" + "".join(cell(c, "td") for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>\n{body}\n</tbody></table>'


def _stride(n: int, n_max: int) -> int:
    return max(1, int(math.ceil(n / n_max)))


def _status_runs(frames: np.ndarray, mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of True in ``mask`` over sorted integer ``frames``: [(first, last)]."""
    if not mask.any():
        return []
    m = np.concatenate([[False], mask, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    ends = np.flatnonzero(np.diff(m) == -1) - 1
    return [(int(frames[a]), int(frames[b])) for a, b in zip(starts, ends, strict=True)]


def _trajectory_cube(trajectories: pd.DataFrame, method: str, frames: np.ndarray,
                     markers: list[str]) -> np.ndarray:
    """xyz of one method as a dense array (F, M, 3) [m], NaN where absent."""
    t = trajectories[trajectories["method"] == method].drop_duplicates(["frame", "marker"])
    idx = pd.MultiIndex.from_product([frames, markers], names=["frame", "marker"])
    return t.set_index(["frame", "marker"])[["x", "y", "z"]].reindex(idx).to_numpy(float).reshape(
        len(frames), len(markers), 3)


def _points_cube(points: pd.DataFrame | None, frames: np.ndarray, markers: list[str]) -> np.ndarray | None:
    if points is None or len(points) == 0:
        return None
    t = points.drop_duplicates(["frame", "marker"])
    idx = pd.MultiIndex.from_product([frames, markers], names=["frame", "marker"])
    return t.set_index(["frame", "marker"])[["x", "y", "z"]].reindex(idx).to_numpy(float).reshape(
        len(frames), len(markers), 3)


def _legend_handles(methods, style, extra=()):
    from matplotlib.lines import Line2D
    h = [Line2D([], [], color=style[m][0], ls=style[m][1], lw=1.6, label=m) for m in methods]
    return h + [Line2D([], [], **kw) for kw in extra]


# ----------------------------------------------------------------------------------------------
# figures: each returns a Figure (or None when there is nothing to draw)
# ----------------------------------------------------------------------------------------------
def _panel_grid(n: int, max_cols: int, panel_in: tuple[float, float]) -> tuple[Figure, int, int]:
    """A figure for ``n`` panels in rows of at most ``max_cols``, each ``panel_in`` (w, h) inches: (fig, nrow, ncol)."""
    ncol = min(n, max_cols)
    nrow = int(math.ceil(n / ncol))
    return Figure(figsize=(panel_in[0] * ncol, panel_in[1] * nrow)), nrow, ncol


def _fig_trajectories(trajectories, methods, style, frames, markers, skeleton, truth_cube):
    """One 3D panel per method; all markers' paths, coloured by marker; skeleton at a few frames."""
    cubes = {m: _trajectory_cube(trajectories, m, frames, markers) for m in methods}
    allpts = np.concatenate([c.reshape(-1, 3) for c in cubes.values()]
                            + ([truth_cube.reshape(-1, 3)] if truth_cube is not None else []))
    allpts = allpts[np.isfinite(allpts).all(axis=1)]
    if len(allpts) == 0:
        return None
    # robust limits: a diverged method must not shrink everyone else's bat to a dot
    lo, hi = np.percentile(allpts, 1, axis=0), np.percentile(allpts, 99, axis=0)
    pad = 0.08 * max(float((hi - lo).max()), 1e-3)
    lo, hi = lo - pad, hi + pad
    fig, nrow, ncol = _panel_grid(len(methods), 3, (4.6, 3.6))
    cmap = _marker_colours(len(markers))
    mi = {m: i for i, m in enumerate(markers)}
    sk = [(mi[a], mi[b]) for a, b in skeleton if a in mi and b in mi]
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    snap = np.linspace(0, len(frames) - 1, min(5, len(frames))).astype(int)
    for k, m in enumerate(methods):
        ax = fig.add_subplot(nrow, ncol, k + 1, projection="3d")
        c = cubes[m]
        if truth_cube is not None:
            for j in range(len(markers)):
                ax.plot(*truth_cube[::st, j].T, color="k", lw=0.6, alpha=0.35)
        for j in range(len(markers)):
            ax.plot(*c[::st, j].T, color=cmap[j], lw=1.0)
        for f in snap:
            for a, b in sk:
                seg = c[f, [a, b]]
                if np.isfinite(seg).all():
                    ax.plot(*seg.T, color="#3060c0", lw=1.2, alpha=0.7)
        n_est = int(np.isfinite(c[..., 0]).sum())
        ax.set_title(f"{m}  ({n_est}/{c.shape[0] * c.shape[1]} estimates)", fontsize=10, color=style[m][0])
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
        span = hi - lo
        ax.set_box_aspect(np.maximum(span, span.max() / MAX_ASPECT))
        ax.set_xlabel("x [m]", fontsize=8)
        ax.set_ylabel("y [m]", fontsize=8)
        ax.set_zlabel("z [m]", fontsize=8)
        ax.tick_params(labelsize=7)
        for a in (ax.xaxis, ax.yaxis, ax.zaxis):
            a.set_major_locator(MaxNLocator(4))
        ax.view_init(elev=22, azim=-65)
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], color=cmap[j], lw=2, label=mk) for j, mk in enumerate(markers[:20])]
    if truth_cube is not None:
        handles.append(Line2D([], [], color="k", lw=0.6, alpha=0.5, label="truth"))
    if sk:
        handles.append(Line2D([], [], color="#3060c0", lw=1.2, label="skeleton (5 frames)"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=0.12 if len(handles) > 8 else 0.08, wspace=0.05)
    return fig


def _marker_colours(n: int) -> list:
    from matplotlib import colormaps
    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _ellipse_params(d: np.ndarray):
    """Mean (2,), and width, height, angle [deg] of the 95 % ellipse of residuals ``d`` (n, 2)."""
    mean = d.mean(axis=0)
    cov = np.cov(d.T)
    w, v = np.linalg.eigh(cov)
    w = np.clip(w, 0, None)
    width, height = 2 * np.sqrt(CHI2_2DOF_95 * w[::-1])
    angle = math.degrees(math.atan2(v[1, 1], v[0, 1]))
    return mean, width, height, angle


def _fig_reprojection_ellipses(rep_mm, methods, style, cameras, rng):
    """Per camera: reprojection residual in mm at depth, scatter + 95 % ellipse per method (Fig. 5)."""
    rep = rep_mm[np.isfinite(rep_mm["du_mm"]) & np.isfinite(rep_mm["dv_mm"])]
    if "outlier" in rep:
        rep = rep[~rep["outlier"].fillna(False).astype(bool)]
    cams = [c for c in cameras if (rep["camera"] == c).any()]
    if not cams:
        return None
    fig, nrow, ncol = _panel_grid(len(cams), 5, (3.3, 3.5))
    groups = dict(tuple(rep.groupby(["camera", "method"], sort=False)))
    for k, cam in enumerate(cams):
        ax = fig.add_subplot(nrow, ncol, k + 1)
        extent = 0.0
        for m in methods:
            g = groups.get((cam, m))
            if g is None or len(g) < 3:
                continue
            d = g[["du_mm", "dv_mm"]].to_numpy(float)
            pick = d if len(d) <= MAX_SCATTER else d[rng.choice(len(d), MAX_SCATTER, replace=False)]
            colour, ls = style[m]
            ax.scatter(pick[:, 0], pick[:, 1], s=2, color=colour, alpha=0.25, lw=0)
            mean, w, h, ang = _ellipse_params(d)
            ax.add_patch(Ellipse(mean, w, h, angle=ang, fill=False, color=colour, ls=ls, lw=1.6))
            extent = max(extent, abs(mean).max() + 0.5 * max(w, h))
        lim = 1.15 * extent if extent > 0 else 1.0
        ax.set(xlim=(-lim, lim), ylim=(lim, -lim), aspect="equal")  # v (down) positive downward
        ax.axhline(0, color="0.7", lw=0.5)
        ax.axvline(0, color="0.7", lw=0.5)
        ax.set_title(f"camera {cam}", fontsize=10)
        ax.set_xlabel("Δu at depth [mm]", fontsize=8)
        if k % ncol == 0:
            ax.set_ylabel("Δv at depth [mm]", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.legend(handles=_legend_handles(methods, style), loc="lower center", ncol=len(methods),
               fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=0.2 if nrow == 1 else 0.1, wspace=0.35, hspace=0.35)
    return fig


def _fig_reprojection_image(session, reproj_tracks, methods, style, cameras, selected, frames):
    """Per camera: 2D features (dots) and each method's reprojected track (lines) of selected markers."""
    obs = session.observations
    obs = obs[obs["marker"].isin(selected)]
    cams = [c for c in cameras if (obs["camera"] == c).any()]
    if not cams:
        return None
    fig, nrow, ncol = _panel_grid(len(cams), 3, (4.6, 3.6))
    cmap = _marker_colours(len(selected))
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    for k, cam in enumerate(cams):
        ax = fig.add_subplot(nrow, ncol, k + 1)
        o = obs[obs["camera"] == cam]
        w_img, h_img = session.rig[cam].size_wh
        for j, mk in enumerate(selected):
            om = o[o["marker"] == mk]
            if len(om) == 0:
                continue
            uv = om[["u", "v"]].to_numpy(float)[::max(1, st)]
            ax.scatter(uv[:, 0], uv[:, 1], s=7, facecolor="none", edgecolor=cmap[j], lw=0.7, zorder=3)
            # label at the track's median: the tracks' starts often coincide, their middles less so
            ax.annotate(mk, np.median(uv, axis=0), fontsize=7, fontweight="bold", color=cmap[j], xytext=(4, 0),
                        textcoords="offset points")
        for m in methods:
            uvm = reproj_tracks[m][cam]  # (F, M_sel, 2)
            colour, ls = style[m]
            for j in range(len(selected)):
                ax.plot(uvm[::st, j, 0], uvm[::st, j, 1], color=colour, ls=ls, lw=0.9, alpha=0.85)
        uv_all = o[["u", "v"]].to_numpy(float)
        lo, hi = uv_all.min(axis=0), uv_all.max(axis=0)
        pad = 0.1 * max(float((hi - lo).max()), 20.0)
        ax.set(xlim=(max(lo[0] - pad, -0.5), min(hi[0] + pad, w_img - 0.5)),
               ylim=(min(hi[1] + pad, h_img - 0.5), max(lo[1] - pad, -0.5)), aspect="equal")
        ax.set_title(f"camera {cam}  ({w_img}×{h_img} px, zoomed)", fontsize=10)
        ax.set_xlabel("u [px]", fontsize=8)
        ax.set_ylabel("v [px]", fontsize=8)
        ax.tick_params(labelsize=7)
    extra = [dict(marker="o", ls="", mfc="none", mec="k", label="image features")]
    fig.legend(handles=_legend_handles(methods, style, extra), loc="lower center", ncol=len(methods) + 1,
               fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=0.16 if nrow == 1 else 0.08, wspace=0.3, hspace=0.3)
    return fig


def _fig_coordinates(trajectories, methods, style, frames, fps, selected, status_fm, truth_cube, ref_cube):
    """Selected markers (rows) x, y, z (columns) over time; 95 % bands; occlusion shaded."""
    t = frames / fps
    fig = Figure(figsize=(13.0, 1.55 * len(selected) + 0.9))
    axes = fig.subplots(len(selected), 3, sharex=True, squeeze=False)
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    cols = {m: trajectories[trajectories["method"] == m].drop_duplicates(["frame", "marker"])
            .set_index(["frame", "marker"]) for m in methods}
    idx_cache = {}
    half = 0.5 / fps
    for i, mk in enumerate(selected):
        idx = idx_cache.setdefault(mk, pd.MultiIndex.from_arrays([frames, [mk] * len(frames)]))
        for a, axis in enumerate("xyz"):
            ax = axes[i, a]
            if status_fm is not None:
                s = status_fm[mk]
                for name, colour in (("single_view", "#f6d7a7"), ("unobserved", "#f4a6a6")):
                    for f0, f1 in _status_runs(frames, s == name):
                        ax.axvspan(f0 / fps - half, f1 / fps + half, color=colour, lw=0, zorder=0)
            for m in methods:
                d = cols[m].reindex(idx)
                y = d[axis].to_numpy(float)
                colour, ls = style[m]
                cov = f"cov_{axis}{axis}"
                if cov in d:
                    sd = np.sqrt(np.clip(d[cov].to_numpy(float), 0, None))
                    ax.fill_between(t[::st], (y - 1.96 * sd)[::st], (y + 1.96 * sd)[::st], color=colour,
                                    alpha=0.15, lw=0)
                ax.plot(t[::st], y[::st], color=colour, ls=ls, lw=1.0)
            if truth_cube is not None:
                j = selected.index(mk)
                ax.plot(t[::st], truth_cube[::st, j, a], color="k", lw=0.8, ls=(0, (1, 1)))
            if ref_cube is not None:
                j = selected.index(mk)
                ax.plot(t[::st], ref_cube[::st, j, a], color="#9467bd", lw=0.8, marker=".", ms=2, ls="")
            if i == 0:
                ax.set_title(f"{axis} [m]", fontsize=10)
            if a == 0:
                ax.set_ylabel(mk, fontsize=9)
            ax.tick_params(labelsize=7)
            ax.margins(x=0)
    for a in range(3):
        axes[-1, a].set_xlabel("time [s]", fontsize=8)
    from matplotlib.patches import Patch
    extra_h = _legend_handles(methods, style)
    if truth_cube is not None:
        extra_h += _legend_handles([], {}, [dict(color="k", lw=0.8, ls=(0, (1, 1)), label="truth")])
    if ref_cube is not None:
        extra_h += _legend_handles([], {}, [dict(color="#9467bd", marker=".", ls="", label="reference")])
    extra_h += [Patch(color="#f6d7a7", label="single view"), Patch(color="#f4a6a6", label="unobserved"),
                Patch(color="0.6", alpha=0.3, label="95 % band (±1.96 σ)")]
    # above the panels: its height is fixed, so the gap does not grow with the number of markers
    fig.legend(handles=extra_h, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(extra_h), fontsize=8,
               frameon=False)
    fig.subplots_adjust(top=1.0 - 0.3 / (1.55 * len(selected) + 0.9), bottom=0.5 / (1.55 * len(selected) + 0.9),
                        hspace=0.15, wspace=0.18)
    return fig


def _fig_status_bars(metrics: pd.DataFrame, methods, style, value: str, ylabel: str, scale: float,
                     hline: float | None, title: str, ax):
    x = np.arange(len(STATUSES))
    w = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        mm = metrics[metrics["method"] == m].set_index("status").reindex(STATUSES)
        ax.bar(x + (k - (len(methods) - 1) / 2) * w, mm[value].to_numpy(float) * scale, w,
               color=style[m][0], label=m)
    if hline is not None:
        ax.axhline(hline, color="k", ls="--", lw=0.8)
    ax.set_xticks(x, [s.replace("_", " ") for s in STATUSES], fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.tick_params(labelsize=7)


def _fig_truth(metrics, errors, methods, style, fps):
    """RMSE by status, 95 % coverage by status, and the error over time (median over markers)."""
    fig = Figure(figsize=(13.0, 3.4))
    a1, a2, a3 = fig.subplots(1, 3, gridspec_kw=dict(width_ratios=[1, 1, 1.6]))
    _fig_status_bars(metrics, methods, style, "rmse_m", "RMSE [mm]", 1000.0, None, "RMSE vs truth by status", a1)
    _fig_status_bars(metrics, methods, style, "coverage95", "fraction inside", 1.0, 0.95,
                     "truth inside the 95 % ellipsoid", a2)
    a2.set_ylim(0, 1.05)
    _fig_error_time(errors, methods, style, fps, a3, "median error over markers [mm]")
    a3.set_title("error vs truth over time", fontsize=10)
    a1.legend(fontsize=7, frameon=False)
    fig.subplots_adjust(wspace=0.3)
    return fig


def _fig_error_time(errors, methods, style, fps, ax, ylabel):
    for m in methods:
        e = errors[errors["method"] == m].groupby("frame")["err_m"].median()
        if len(e):
            ax.plot(e.index.to_numpy() / fps, e.to_numpy() * 1000, color=style[m][0], ls=style[m][1], lw=1.0,
                    label=m)
    ax.set_yscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")  # "6" rather than "6 x 10^0"
    ax.yaxis.set_major_formatter(plain)
    ax.yaxis.set_minor_formatter(plain)
    ax.set_xlabel("time [s]", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)


def _fig_reference(errors, methods, style, fps):
    fig = Figure(figsize=(9.0, 3.0))
    ax = fig.add_subplot(1, 1, 1)
    _fig_error_time(errors, methods, style, fps, ax, "median distance over markers [mm]")
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="paper (ear): EKF/UKF within 1 mm of triangulation")
    ax.set_title("distance to the reference reconstruction over time", fontsize=10)
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


# ----------------------------------------------------------------------------------------------
# HTML
# ----------------------------------------------------------------------------------------------
CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.2em 2em;color:#222;max-width:1400px}
h1{font-size:1.5em;margin-bottom:.2em} h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
nav a{margin-right:1em;color:#1f5fa0;text-decoration:none} p.note{color:#555;font-size:.9em;max-width:70em}
div.warn{background:#fff3cd;border:1px solid #d39e00;padding:.3em 1em;max-width:70em}
table{border-collapse:collapse;font-size:.85em;margin:.6em 0} th,td{border:1px solid #ccc;padding:2px 8px}
th{background:#f0f0f0} td{text-align:right} td.l,th.l{text-align:left}
tr.paper td{background:#fff8e0;font-style:italic}
figure{margin:.6em 0} figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.85em;color:#444;max-width:75em}
"""


def _figure_html(fig: Figure | None, caption: str, alt: str) -> str:
    if fig is None:
        return f'<p class="note">No data to draw: {html.escape(alt)}.</p>'
    return (f'<figure><img alt="{html.escape(alt)}" src="{_png(fig)}">'
            f"<figcaption>{caption}</figcaption></figure>")


def _paper_table(experiment: str) -> str:
    rows = [
        ["ear (2 cameras, 250 fps)", "EKF, UKF vs stereo triangulation", "within 1 mm"],
        ["ear", "reprojection, EKF / UKF / triangulation", "within 5 px (≈ 2 mm in 3D); conclusion: &lt; 2 mm"],
        ["flight (5 GoPro, 120 fps)", "reprojection in 3D, camera 1 (calibration base)", "&lt; 3 mm"],
        ["flight", "reprojection in 3D, other cameras", "&lt; 20 mm (≈ 4 × marker size)"],
    ]
    rows = [[(c, 'class="l"') for c in r] for r in rows]
    hi = {"ear": (0, 1), "flight": (2, 3)}[experiment]
    rows = [[(c[0], c[1] + (' style="background:#fff8e0"' if i in hi else "")) for c in r]
            for i, r in enumerate(rows)]
    return _table([("experiment", 'class="l"'), ("quantity", 'class="l"'), ("published", 'class="l"')], rows,
                  "paper")


def _paper_camera_figure(experiment: str, cam_index: int) -> str:
    if experiment == "ear":
        return "≤ 5 px (≈ 2 mm)"
    return "&lt; 3 mm" if cam_index == 0 else "&lt; 20 mm"


def _camera_table(stats: pd.DataFrame, summary: dict, methods, cameras, experiment) -> str:
    """Rows (camera, method); summary.json values override the ones computed from the tables."""
    keys = ["n", "mean_px", "median_px", "rms_px", "p95_px", "mean_mm_at_depth", "p95_mm_at_depth"]
    s = stats.set_index(["camera", "method"])
    rows = []
    for ci, cam in enumerate(cameras):
        present = [m for m in methods if (cam, m) in s.index or _get(summary, "methods", m, "reprojection", cam)]
        for k, m in enumerate(present):
            vals = {c: (s.loc[(cam, m), c] if (cam, m) in s.index else None) for c in keys + ["n_outliers"]}
            from_summary = _get(summary, "methods", m, "reprojection", cam) or {}
            for c in keys:
                if from_summary.get(c) is not None:
                    vals[c] = from_summary[c]
            row = []
            if k == 0:
                row.append((html.escape(str(cam)), f'class="l" rowspan="{len(present)}"'))
            row += [(html.escape(m), 'class="l"'), _fmt(vals["n"], 0), _fmt(vals["n_outliers"], 0),
                    _fmt(vals["mean_px"]), _fmt(vals["median_px"]), _fmt(vals["rms_px"]), _fmt(vals["p95_px"]),
                    _fmt(vals["mean_mm_at_depth"]), _fmt(vals["p95_mm_at_depth"])]
            if k == 0:
                row.append((_paper_camera_figure(experiment, ci), f'class="l paper" rowspan="{len(present)}"'
                            ' style="background:#fff8e0"'))
            rows.append(row)
    if not rows:
        return '<p class="note">No reprojection errors.</p>'
    header = [("camera", 'class="l"'), ("method", 'class="l"'), "n", "outliers", "mean [px]", "median [px]",
              "RMS [px]", "p95 [px]", "mean [mm at depth]", "p95 [mm at depth]", ("paper (published)", 'class="l"')]
    return _table(header, rows, "cameras")


def _truth_metrics(errors: pd.DataFrame, summary: dict, methods) -> pd.DataFrame:
    """Computed metrics, overridden by summary.json's ``truth`` block where it has a value."""
    m = status_metrics(errors).set_index(["method", "status"])
    for meth in methods:
        tb = _get(summary, "methods", meth, "truth") or {}
        for key, col in (("rmse_m", "rmse_m"), ("coverage95", "coverage95"), ("n", "n")):
            for st, v in (tb.get(key) or {}).items():
                if st in STATUSES and v is not None:
                    m.loc[(meth, st), col] = v
    return m.reset_index()


def _metrics_table(metrics: pd.DataFrame, methods, with_coverage: bool) -> str:
    mi = metrics.set_index(["method", "status"])
    header = [("method", 'class="l"')]
    for st in STATUSES:
        header += [f"{st.replace('_', ' ')}: n", "RMSE [mm]"] + (["cov. 95 %"] if with_coverage else
                                                                   ["mean [mm]", "p95 [mm]"])
    rows = []
    for m in methods:
        row = [(html.escape(m), 'class="l"')]
        for st in STATUSES:
            r = mi.loc[(m, st)] if (m, st) in mi.index else None

            def g(col, r=r):
                return None if r is None else r.get(col)

            rmse, cov = g("rmse_m"), g("coverage95")
            row += [_fmt(g("n") if r is not None else 0, 0), _fmt(None if rmse is None else rmse * 1000)]
            if with_coverage:
                row.append(_fmt(None if cov is None else 100 * cov, 1) + (" %" if _fmt(cov) != "–" else ""))
            else:
                row += [_fmt(None if g("mean_m") is None else g("mean_m") * 1000),
                        _fmt(None if g("p95_m") is None else g("p95_m") * 1000)]
        rows.append(row)
    return _table(header, rows, "status")


def _sigma_text(sigma) -> str:
    if isinstance(sigma, dict):
        return ", ".join(f"{k} {_fmt(x)} px" for k, x in sigma.items())
    return f"{_fmt(sigma)} px"


def _validation_section(summary: dict) -> str | None:
    """Leave-one-camera-out table (summary["validation"], see batgraph.validate): rows (held-out camera,
    method), per (status, subset) group n, median and p90 [px]; None when the run was not validated."""
    v = _get(summary, "validation")
    if not isinstance(v, dict):
        return None
    from .validate import COLUMNS, SUBSETS, group_label

    t = pd.DataFrame(v.get("table") or [], columns=COLUMNS)
    present = set(zip(t["status"], t["subset"], strict=True))
    groups = [(st, sub) for sub in SUBSETS for st in STATUSES[1:] if (st, sub) in present]
    idx = t.set_index(["held_out", "method", "status", "subset"])
    rows = []
    for cam in dict.fromkeys(t["held_out"]):
        ms = list(dict.fromkeys(t.loc[t["held_out"] == cam, "method"]))
        for k, m in enumerate(ms):
            row = [(html.escape("all cameras" if cam == "all" else str(cam)), f'class="l" rowspan="{len(ms)}"')] \
                if k == 0 else []
            row.append((html.escape(str(m)), 'class="l"'))
            for g in groups:
                r = idx.loc[(cam, m, *g)] if (cam, m, *g) in idx.index else None
                row += ["–", "–", "–"] if r is None else [_fmt(r["n"], 0), _fmt(r["median_px"]), _fmt(r["p90_px"])]
            rows.append(row)
    header = [("held-out camera", 'class="l"'), ("method", 'class="l"')]
    for g in groups:
        header += [f"{html.escape(group_label(*g))}: n", "median [px]", "p90 [px]"]
    failed = v.get("failed") or {}
    return (
        '<p class="note">For each camera, every method was run again without that camera\'s observations, and '
        "its 3D estimate projected into the held-out camera (raw pixels) and compared with that camera's own "
        "detections: an accuracy figure that needs no ground truth (it includes the held-out camera's own "
        "detection noise and calibration error). Status: views of the point without the held-out camera "
        "(observed ≥ 2, 1-view, 0-view). <i>common</i>: the points every method estimates, so methods are "
        "compared on the same points; <i>no triangulation</i>: points the smoother estimates and per-frame "
        "triangulation cannot. The folds reuse the full run's pixel noise"
        + (f" ({html.escape(_sigma_text(v.get('pixel_sigma_px')))})" if v.get("pixel_sigma_px") is not None else "")
        + f"; {_fmt(v.get('runtime_s'), 1)} s on {_fmt(v.get('workers'), 0)} process(es).</p>"
        + f"<p><b>Verdict:</b> {html.escape(str(v.get('verdict', '')))}</p>"
        + (_table(header, rows, "validation") if rows else '<p class="note">No held-out observation could be '
           "predicted.</p>")
        + ("".join(f'<p class="note">Fold without {html.escape(str(c))} failed: {html.escape(str(m))}</p>'
                   for c, m in failed.items()))
    )


def render_report(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                  summary: dict | None) -> str:
    """The report as one HTML string (see the module docstring for its sections).

    session: :class:`batgraph.session.Session` (rig, fps, markers, skeleton, truth, reference).
    trajectories, reprojection: CONTRACT.md section 3 tables, every method stacked.
    summary: the summary.json dict; any key may be missing.
    """
    summary = summary or {}
    trajectories = trajectories.copy()
    trajectories["method"] = trajectories["method"].astype(str)
    reprojection = reprojection.copy()
    reprojection["method"] = reprojection["method"].astype(str)
    methods = _methods(trajectories, reprojection, summary)
    style = _style(methods)
    has_xyz = np.isfinite(trajectories[["x", "y", "z"]].to_numpy(float)).all(axis=1)
    estimated = set(trajectories.loc[has_xyz, "method"])
    plotted = [m for m in methods if m in estimated]  # a method without a single estimate has nothing to draw
    fps = float(session.fps)
    cameras = session.rig.names
    markers = list(session.markers)
    markers += [m for m in pd.unique(trajectories["marker"].astype(str)) if m not in markers]
    if len(trajectories):
        frames = np.arange(int(trajectories["frame"].min()), int(trajectories["frame"].max()) + 1)
    else:
        frames = session.frames
    selected = _selected_markers(markers)
    experiment = _experiment(session)
    rng = np.random.default_rng(0)  # only for thinning scatter plots; fixed so reports are reproducible
    truth = session.truth if session.truth is not None and len(session.truth) else None
    reference = session.reference if session.reference is not None and len(session.reference) else None

    status_fm = None
    if "status" in trajectories and plotted:
        st = trajectories[trajectories["method"] == plotted[0]].drop_duplicates(["frame", "marker"])
        st = st.pivot(index="frame", columns="marker", values="status").reindex(frames)
        status_fm = {mk: st[mk].astype(str).to_numpy() if mk in st else np.full(len(frames), "")
                     for mk in selected}

    sections: list[tuple[str, str, str]] = []  # (anchor, title, body html)

    # --- overview
    noise = _get(summary, "pixel_noise", "cameras") or {}
    cam_rows = [[(html.escape(c.name), 'class="l"'), f"{c.size_wh[0]}×{c.size_wh[1]}",
                 _fmt(c.K[0, 0], 1), _fmt(np.linalg.norm(c.center_world), 2),
                 _fmt(_get(noise, c.name, "sigma_px"), 2), _fmt(_get(summary, "pixel_sigma_px", c.name), 2)]
                for c in session.rig]
    warnings = summary.get("warnings") or []
    warn_html = ('<div class="warn"><p><b>Self-check warnings</b> (checked before any estimator ran):</p><ul>'
                 + "".join(f"<li>{html.escape(str(w))}</li>" for w in warnings) + "</ul></div>") if warnings else ""
    run_rows = []
    for m in methods:
        t = trajectories[trajectories["method"] == m]
        est = np.isfinite(t[["x", "y", "z"]].to_numpy(float)).all(axis=1) if len(t) else np.zeros(0, bool)
        counts = t["status"].value_counts() if "status" in t else pd.Series(dtype=int)
        run_rows.append([(html.escape(m), f'class="l" style="color:{style[m][0]}"'),
                         _fmt(_get(summary, "methods", m, "runtime_s"), 2), f"{int(est.sum())} / {len(t)}"]
                        + [str(int(counts.get(s, 0))) for s in STATUSES[1:]])
    overview = (
        warn_html
        + f'<p>Session <b>{html.escape(str(session.name))}</b>: {len(cameras)} cameras, {len(markers)} markers, '
        f"frames {frames[0]}–{frames[-1]} ({len(frames)} frames at {fps:g} fps, {len(frames) / fps:.2f} s). "
        f"Methods: {', '.join(html.escape(m) for m in methods)}. Compared against the paper's "
        f"<b>{experiment}</b> experiment (chosen from the session name).</p>"
        + _table([("method", 'class="l"'), "runtime [s]", "estimates / rows", "observed (≥ 2 views)",
                  "single view", "unobserved"], run_rows, "runs")
        + _table([("camera", 'class="l"'), "size [px]", "fx [px]", "distance to origin [m]",
                  "measured noise [px]", "noise used [px]"], cam_rows, "rig")
    )
    sections.append(("overview", "Overview", overview))

    # --- 3D trajectories
    truth_all = _points_cube(truth, frames, markers)
    fig = _fig_trajectories(trajectories, plotted, style, frames, markers, session.skeleton, truth_all) \
        if plotted else None
    sections.append(("trajectories", "3D trajectories", _figure_html(
        fig, "Every marker's path (colour = marker) for each method, in the world frame [m], on common "
        "axes (1st–99th percentile of all estimates), equally scaled unless one range is under a quarter of "
        "the longest (then that axis is stretched). Blue segments: the skeleton at five evenly spaced "
        "frames (the paper's Fig. 5a draws the wing the same way). Thin black: truth, when known.",
        "3D trajectories per method")))

    # --- reprojection ellipses (Fig. 5 b-f)
    rep_mm = reprojection_in_mm(reprojection, trajectories, session.rig) if len(reprojection) else None
    fig = _fig_reprojection_ellipses(rep_mm, methods, style, cameras, rng) if rep_mm is not None else None
    sections.append(("ellipses", "Reprojection error per camera (paper Fig. 5 b–f)", _figure_html(
        fig, "Reprojection residual (û − u, v̂ − v) of every inlier observation, expressed in millimetres at "
        "the marker's depth in that camera (residual × depth / f). Ellipses: 95 % ellipse of each method's "
        "residuals (mean ± χ²₂ 95 % of their covariance); EKF dashed and UKF solid as in the paper, "
        "smoother solid blue, filter dash-dot, triangulation dotted. Axes: v downward as in the image.",
        "reprojection error ellipses per camera")))

    # --- reprojection over image features (Fig. 6)
    sel_idx = [markers.index(m) for m in selected]
    reproj_tracks = {}
    for m in plotted:
        cube = _trajectory_cube(trajectories, m, frames, markers)[:, sel_idx]
        reproj_tracks[m] = {c.name: c.project(cube, distort=True) for c in session.rig}
    fig = _fig_reprojection_image(session, reproj_tracks, plotted, style, cameras, selected, frames) \
        if plotted else None
    sections.append(("features", "Reprojections over the 2D features (paper Fig. 6)", _figure_html(
        fig, f"Image features (open circles, colour = marker) of the markers {', '.join(selected)} and "
        "each method's 3D estimate projected back into the raw (distorted) image over every frame "
        "(lines, method style), so the lines also run through occlusion gaps. Pixels: OpenCV convention, "
        "v downward; each panel is zoomed to the features.",
        "reprojections over image features")))

    # --- coordinates over time
    ref_sel = _points_cube(reference, frames, selected)
    truth_sel = _points_cube(truth, frames, selected)
    fig = _fig_coordinates(trajectories, plotted, style, frames, fps, selected, status_fm, truth_sel, ref_sel) \
        if plotted else None
    sections.append(("coordinates", "Marker coordinates over time", _figure_html(
        fig, "World x, y, z [m] of the selected markers for each method, with 95 % bands (± 1.96 σ per axis "
        f"from the marginal covariance). Shaded: frames where the marker was seen by one camera only "
        f"(orange) or by none (red), from the status column of {html.escape(plotted[0]) if plotted else '–'}."
        + (" Dotted black: truth." if truth is not None else "")
        + (" Purple dots: reference reconstruction." if reference is not None else ""),
        "marker coordinates over time")))

    # --- per-camera table
    stats = camera_error_stats(rep_mm) if rep_mm is not None else camera_error_stats(
        pd.DataFrame(columns=["method", "camera", "err_px", "err_mm", "outlier"]))
    table = _camera_table(stats, summary, methods, cameras, experiment)
    sections.append(("table", "Reprojection error per camera, next to the paper", (
        '<p class="note">Per camera and method: inlier observations (n), flagged outliers, pixel '
        "statistics of |(û, v̂) − (u, v)| on the raw image, and the same error in millimetres at the "
        "marker's depth (err_px × depth / f × 1000, depth = z of the method's estimate in that camera). "
        "Values from summary.json where present, otherwise computed from reprojection.csv. The last column "
        f"is the paper's published figure for its {experiment} experiment"
        + (" (its camera 1 was the base of a pairwise calibration, hence its smaller error)"
           if experiment == "flight" else "") + ".</p>" + table
        + "<p class=\"note\">The paper's published figures (Bender et al., PAPER.md):</p>"
        + _paper_table(experiment))))

    # --- truth
    if truth is not None and plotted:
        errors = point_errors(trajectories[trajectories["method"].isin(plotted)], truth)
        metrics = _truth_metrics(errors, summary, plotted)
        fig = _fig_truth(metrics, errors, plotted, style, fps) if len(errors) else None
        sections.append(("truth", "Errors against truth", (
            '<p class="note">RMSE of the 3D estimate against truth.csv by the status of the (frame, marker): '
            "observed (≥ 2 views), single view, unobserved (motion model only); and the fraction of truth "
            "points inside their estimate's 95 % ellipsoid (squared Mahalanobis distance ≤ 7.815, "
            "χ²₃ 95 %): an honest covariance gives about 95 %.</p>"
            + _metrics_table(metrics, plotted, with_coverage=True)
            + _figure_html(fig, "Left: RMSE by status [mm]. Middle: 95 % coverage by status (dashed: the "
                           "nominal 0.95). Right: median over markers of the error on each frame [mm, log].",
                           "errors against truth"))))

    # --- reference
    if reference is not None and plotted:
        errors = point_errors(trajectories[trajectories["method"].isin(plotted)], reference)
        metrics = status_metrics(errors) if len(errors) else None
        fig = _fig_reference(errors, plotted, style, fps) if len(errors) else None
        sections.append(("reference", "Differences to the reference reconstruction", (
            '<p class="note">Distance between each method\'s estimate and the reference 3D points '
            "(reference_xyz.csv, e.g. DLTdv's xyzpts from an import) on the frames both have. Paper (ear "
            "data): EKF and UKF within 1 mm of stereo triangulation.</p>"
            + (_metrics_table(metrics, plotted, with_coverage=False) if metrics is not None
               else '<p class="note">No common (frame, marker) pairs.</p>')
            + _figure_html(fig, "Median over markers of the distance to the reference on each frame [mm, "
                           "log]; dashed: the paper's 1 mm.", "differences to the reference"))))

    validation = _validation_section(summary)
    if validation is not None:
        sections.append(("validation", "Leave-one-camera-out validation", validation))

    nav = " ".join(f'<a href="#{a}">{html.escape(t)}</a>' for a, t, _ in sections)
    body = "\n".join(f'<section id="{a}"><h2>{html.escape(t)}</h2>\n{b}\n</section>' for a, t, b in sections)
    title = f"batgraph report: {html.escape(str(session.name))}"
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
            f"<style>{CSS}</style></head><body>\n<h1>{title}</h1>\n<nav>{nav}</nav>\n{body}\n"
            '<p class="note">Written by batgraph. Self-contained: every figure is embedded.</p>'
            "</body></html>\n")


def write_report(path: str | Path, session, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                 summary: dict | None) -> Path:
    """Render the report (see :func:`render_report`) and write it to ``path`` atomically. Returns the path."""
    path = Path(path)
    atomic.write_text(path, render_report(session, trajectories, reprojection, summary))
    return path
