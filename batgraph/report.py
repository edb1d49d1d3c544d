"""The self-contained HTML comparison report (report.html): every method side by side, plots embedded.

It reads finished tables (trajectories, reprojection, summary) and draws them; it estimates nothing
and writes nothing but the one HTML file. Figures are matplotlib ``Figure`` objects rendered to
PNG in memory (no pyplot, so no global backend state) and embedded as base64 ``data:`` URIs, so
the file opens anywhere, offline, with no external ``src`` or ``href``. The figures are drawn after the
text, shared over the cores by forked processes (:class:`_Figures`, batgraph.forked.map_jobs); the HTML is
the same as when one process draws them all.

Sections: overview, 3D trajectories, reprojection error per camera with 95 % ellipses in mm at the
marker's depth (the paper's Fig. 5 b-f), reprojections over the 2D features (Fig. 6), marker
coordinates over time with 95 % bands and occlusion shading, a per-camera error table next to the
paper's published figures, and -- when the session has them -- errors against truth (RMSE by status,
95 % coverage) and differences to a reference reconstruction (e.g. DLTdv's xyzpts).
"""

from __future__ import annotations

import base64
import contextlib
import gc
import html
import io
import math
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse
from matplotlib.ticker import FuncFormatter, MaxNLocator

from . import atomic, evaluate, forked
from . import methods as methods_registry
from .summary import HEADLINE_GROUPS, Summary, refresh_verdict, summarize

# The markers named in the paper's Fig. 6, in its order.
PAPER_MARKERS = ("body2", "shoulder_r", "elbow_r", "wrist_r", "digit5_r", "digit4_r", "digit3_r")
CHI2_2DOF_95 = 5.991464547107979  # 95 % quantile of chi-square, 2 DOF (reprojection ellipses)

MAX_SCATTER = 1500  # residual points drawn per (method, camera): keeps PNGs small and fast
MAX_TRACK_FRAMES = 600  # frames drawn per track in the image-space and time plots
# Per-camera figures draw at most this many panels (evenly spaced over the rig; the per-camera table lists
# every camera): drawing is per axis, so 30 panels per figure made a 30-camera report ~4 s slower.
MAX_CAMERA_PANELS = 10
DPI = 100
MAX_ASPECT = 4.0  # 3D panels: an axis shorter than 1/4 of the longest is stretched so that it stays readable


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _methods(trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: dict) -> list[str]:
    found = {str(m) for table in (trajectories, reprojection) for m in pd.unique(table["method"])}
    found |= set((summary or {}).get("methods", {}) or {})
    return methods_registry.ordered(found)


def _style(methods: list[str]) -> dict[str, tuple[str, str]]:
    return {m: methods_registry.style(m) for m in methods}


def _selected_markers(markers: list[str], n_max: int = 7) -> list[str]:
    named = [m for m in PAPER_MARKERS if m in markers]
    return named if named else list(markers[:min(n_max, 6)])


def _panel_cameras(cameras: list[str]) -> tuple[list[str], str]:
    """The cameras the per-camera figures draw (at most MAX_CAMERA_PANELS, evenly spaced over the rig's
    order) and a caption note saying so ("" when every camera is drawn)."""
    if len(cameras) <= MAX_CAMERA_PANELS:
        return list(cameras), ""
    pick = np.unique(np.linspace(0, len(cameras) - 1, MAX_CAMERA_PANELS).round().astype(int))
    return [cameras[i] for i in pick], (f" {len(pick)} of the {len(cameras)} cameras are drawn (evenly spaced "
                                         "over the rig: cameras " + ", ".join(html.escape(cameras[i]) for i in pick) +
                                         "); the per-camera table lists every camera.")


def _png(fig: Figure) -> str:
    """The figure as a PNG ``data:`` URI, cropped to its drawn content plus a 0.1 inch margin.

    One Agg draw, then the pixels that are not the white background bound the crop: what
    ``savefig(bbox_inches="tight")`` gives, without its extra layout-only draw and tight-box pass (together
    ~40 % of a report's time). The figures below keep every artist (legends included) inside their canvas;
    should one still reach the canvas's edge (e.g. very long marker names), the figure is saved the slow way,
    with ``bbox_inches="tight"``, so that nothing is cut off.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3]  # opaque white figure: alpha is 255 everywhere
    ink = (rgb != 255).any(axis=2)
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    buf = io.BytesIO()
    if len(rows) and (rows[0] == 0 or cols[0] == 0 or rows[-1] == ink.shape[0] - 1 or cols[-1] == ink.shape[1] - 1):
        fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    else:
        if len(rows):
            pad = round(0.1 * DPI)
            rgb = rgb[max(rows[0] - pad, 0):rows[-1] + pad + 1, max(cols[0] - pad, 0):cols[-1] + pad + 1]
        Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="png")
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


def _finite_runs(tracks: np.ndarray) -> list[np.ndarray]:
    """The pieces of each track in ``tracks`` (K, F, D) between non-finite points, as a list of (n, D) arrays
    with n >= 2: the segments ``plot`` would draw for each track, for one ``LineCollection`` of them all."""
    runs = []
    for track in tracks:
        ok = np.isfinite(track).all(axis=1)
        for a, b in _status_runs(np.arange(len(track)), ok):
            if b > a:
                runs.append(track[a:b + 1])
    return runs


def _trajectory_cube(trajectories: pd.DataFrame, method: str, frames: np.ndarray,
                     markers: list[str]) -> np.ndarray:
    """xyz of one method as a dense array (F, M, 3) [m], NaN where absent."""
    return evaluate.dense_from_table(trajectories, frames, markers, method=method)[0]


def _points_cube(points: pd.DataFrame | None, frames: np.ndarray, markers: list[str]) -> np.ndarray | None:
    """xyz of truth / reference points as (F, M, 3) [m], or None without any."""
    if points is None or len(points) == 0:
        return None
    return evaluate.dense_from_table(points.drop_duplicates(["frame", "marker"]), frames, markers)[0]


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
    return Figure(figsize=(panel_in[0] * ncol, panel_in[1] * nrow), dpi=DPI), nrow, ncol


def _legend_size_in(fig: Figure, legend) -> tuple[float, float]:
    """(width, height) [in] of ``legend`` as it will be drawn: its texts measured, nothing drawn."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    box = legend.get_window_extent(FigureCanvasAgg(fig).get_renderer())
    return box.width / fig.dpi, box.height / fig.dpi


def _widen_for(fig: Figure, width_in: float, margin_in: float = 0.2) -> None:
    """Widen ``fig`` (its panels keep their fractions) so that something ``width_in`` wide, centred, fits."""
    if width_in + margin_in > fig.get_figwidth():
        fig.set_figwidth(width_in + margin_in)


def _room_right(fig: Figure, legend, gap_in: float = 0.35) -> None:
    """Move the panels' right edge left so that ``legend``, placed just right of them, ends inside ``fig``."""
    fig.subplots_adjust(right=1.0 - (_legend_size_in(fig, legend)[0] + gap_in) / fig.get_figwidth())


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
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    truth_runs = _finite_runs(truth_cube[::st].transpose(1, 0, 2)) if truth_cube is not None else []
    for k, m in enumerate(methods):
        ax = fig.add_subplot(nrow, ncol, k + 1, projection="3d")
        ax.computed_zorder = False  # truth behind the estimates, the skeleton on top: in the order added
        c = cubes[m]
        if truth_runs:
            ax.add_collection3d(Line3DCollection(truth_runs, colors="k", linewidths=0.6, alpha=0.35))
        tracks = c[::st].transpose(1, 0, 2)  # (M, F, 3)
        runs = [(r, cmap[j]) for j in range(len(markers)) for r in _finite_runs(tracks[j:j + 1])]
        if runs:
            ax.add_collection3d(Line3DCollection([r for r, _ in runs], colors=[col for _, col in runs],
                                                 linewidths=1.0))
        bones = [c[f, [a, b]] for f in snap for a, b in sk if np.isfinite(c[f, [a, b]]).all()]
        if bones:
            ax.add_collection3d(Line3DCollection(bones, colors="#3060c0", linewidths=1.2, alpha=0.7))
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
    legend = fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8, frameon=False)
    _widen_for(fig, _legend_size_in(fig, legend)[0])
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
    from matplotlib.collections import LineCollection

    fig, nrow, ncol = _panel_grid(len(cams), 3, (4.6, 3.6))
    cmap = _marker_colours(len(selected))
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    for k, cam in enumerate(cams):
        ax = fig.add_subplot(nrow, ncol, k + 1)
        o = obs[obs["camera"] == cam]
        w_img, h_img = session.rig[cam].size_wh
        points, colours = [], []
        for j, mk in enumerate(selected):
            om = o[o["marker"] == mk]
            if len(om) == 0:
                continue
            uv = om[["u", "v"]].to_numpy(float)[::max(1, st)]
            points.append(uv)
            colours += [cmap[j]] * len(uv)
            # label at the track's median: the tracks' starts often coincide, their middles less so
            ax.annotate(mk, np.median(uv, axis=0), fontsize=7, fontweight="bold", color=cmap[j], xytext=(4, 0),
                        textcoords="offset points")
        uv = np.concatenate(points)
        ax.scatter(uv[:, 0], uv[:, 1], s=7, facecolor="none", edgecolor=colours, lw=0.7, zorder=3)
        for m in methods:
            uvm = reproj_tracks[m][cam]  # (F, M_sel, 2)
            colour, ls = style[m]
            ax.add_collection(LineCollection(_finite_runs(uvm[::st].transpose(1, 0, 2)), colors=colour,
                                             linestyles=ls, linewidths=0.9, alpha=0.85), autolim=False)
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
    panels_in = 1.55 * len(selected) + 0.9
    fig = Figure(figsize=(13.0, panels_in), dpi=DPI)
    axes = fig.subplots(len(selected), 3, sharex=True, squeeze=False)
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    has_cov = all(c in trajectories for c in evaluate.TRAJ_COLUMNS[7:13])
    cubes = {m: evaluate.dense_from_table(trajectories, frames, selected, method=m)[:2] for m in methods}
    half = 0.5 / fps
    for i, mk in enumerate(selected):
        for a, axis in enumerate("xyz"):
            ax = axes[i, a]
            if status_fm is not None:
                s = status_fm[mk]
                for name, colour in (("single_view", "#f6d7a7"), ("unobserved", "#f4a6a6")):
                    for f0, f1 in _status_runs(frames, s == name):
                        ax.axvspan(f0 / fps - half, f1 / fps + half, color=colour, lw=0, zorder=0)
            for m in methods:
                xyz, cov = cubes[m]
                y = xyz[:, i, a]
                colour, ls = style[m]
                if has_cov:
                    sd = np.sqrt(np.clip(cov[:, i, a, a], 0, None))
                    ax.fill_between(t[::st], (y - 1.96 * sd)[::st], (y + 1.96 * sd)[::st], color=colour,
                                    alpha=0.15, lw=0)
                ax.plot(t[::st], y[::st], color=colour, ls=ls, lw=1.0)
            if truth_cube is not None:
                ax.plot(t[::st], truth_cube[::st, i, a], color="k", lw=0.8, ls=(0, (1, 1)))
            if ref_cube is not None:
                ax.plot(t[::st], ref_cube[::st, i, a], color="#9467bd", lw=0.8, marker=".", ms=2, ls="")
            if i == 0:
                ax.set_title(f"{axis} [m]", fontsize=10)
            if a == 0:
                ax.set_ylabel(mk, fontsize=9)
            ax.tick_params(labelsize=7)
            ax.margins(x=0)
            # few ticks on these small panels: matplotlib builds an object per tick, ~40 % of this figure's time
            ax.yaxis.set_major_locator(MaxNLocator(3))
            ax.xaxis.set_major_locator(MaxNLocator(4))
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
    # above the panels, in a band of its own height: the gap does not grow with the number of markers
    legend = fig.legend(handles=extra_h, loc="upper center", bbox_to_anchor=(0.5, 1.0), ncol=len(extra_h),
                        fontsize=8, frameon=False)
    height = panels_in + _legend_size_in(fig, legend)[1]
    fig.set_figheight(height)
    fig.subplots_adjust(top=1.0 - (height - panels_in + 0.4) / height, bottom=0.5 / height, hspace=0.15,
                        wspace=0.18)
    return fig


def _fig_group_bars(values: dict[str, dict[str, float | None]], methods, style, ylabel: str, scale: float,
                    hline: float | None, title: str, ax):
    """Bars per headline group (x) and method (colour): values[method][group]; None draws nothing."""
    groups = list(HEADLINE_GROUPS)
    x = np.arange(len(groups))
    w = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        y = [values.get(m, {}).get(g) for g in groups]
        ax.bar(x + (k - (len(methods) - 1) / 2) * w, [np.nan if v is None else v * scale for v in y], w,
               color=style[m][0], label=m)
    if hline is not None:
        ax.axhline(hline, color="k", ls="--", lw=0.8)
    ax.set_xticks(x, [textwrap.fill(HEADLINE_GROUPS[g], 14) for g in groups], fontsize=7)  # no overlap
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.tick_params(labelsize=7)


def _fig_truth(summary, errors, methods, style, fps):
    """RMSE and 95 % coverage per headline group (from summary.json), and the error over time."""
    fig = Figure(figsize=(14.0, 3.6), dpi=DPI)
    a1, a2, a3 = fig.subplots(1, 3, gridspec_kw=dict(width_ratios=[1.2, 1.2, 1.4]))
    rmse = {m: _get(summary, "methods", m, "truth", "rmse_m") or {} for m in methods}
    cov = {m: _get(summary, "methods", m, "truth", "coverage95") or {} for m in methods}
    _fig_group_bars(rmse, methods, style, "RMSE [mm, log]", 1000.0, None, "RMSE vs truth", a1)
    a1.set_yscale("log")
    _fig_group_bars(cov, methods, style, "fraction inside", 1.0, 0.95, "truth inside the 95 % ellipsoid", a2)
    a2.set_ylim(0, 1.05)
    _fig_error_time(errors, methods, style, fps, a3, "median error over markers [mm]")
    a3.set_title("error vs truth over time", fontsize=10)
    a1.legend(fontsize=7, frameon=False)
    fig.subplots_adjust(wspace=0.3)
    return fig


_MAP_CODES = {"observed": 0, "single_view": 1, "unobserved": 2, "outside": 3}
_MAP_COLOURS = ("#2ca02c", "#ff9f1c", "#d62728", "#c7c7c7")
_MAP_LABELS = ("seen by >= 2 cameras", "seen by 1 camera (gap)", "seen by none (gap)", "track end (extrapolated)")


def _fig_coverage_map(trajectories, method: str, frames: np.ndarray, markers: list[str], fps: float):
    """Marker x frame map of where the data are: observed / single view / unobserved inside each marker's
    span, and the track ends outside it (the rows of ``method``; status and span are the same for all)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    t = trajectories[trajectories["method"] == method].drop_duplicates(["frame", "marker"])
    if not len(t) or "status" not in t:
        return None
    code = t["status"].map(_MAP_CODES).to_numpy(float)
    if "span" in t:
        code = np.where(t["span"].to_numpy() == "outside", _MAP_CODES["outside"], code)
    grid = (pd.Series(code, index=pd.MultiIndex.from_frame(t[["marker", "frame"]]))
            .unstack("frame").reindex(index=markers, columns=frames).to_numpy(float))
    height = 0.9 + 0.17 * len(markers)
    fig = Figure(figsize=(12.0, height), dpi=DPI)
    fig.subplots_adjust(bottom=0.45 / height, top=1.0 - 0.15 / height)  # the time axis's labels inside, few markers too
    ax = fig.add_subplot(1, 1, 1)
    joined = len(frames) and frames[-1] - frames[0] + 1 != len(frames)  # several takes: their frames side by side
    x0, x1 = (0, len(frames)) if joined else (frames[0] / fps, (frames[-1] + 1) / fps)
    ax.imshow(np.ma.masked_invalid(grid), aspect="auto", interpolation="nearest", vmin=-0.5, vmax=3.5,
              cmap=ListedColormap(_MAP_COLOURS), extent=(x0, x1, len(markers), 0))
    ax.set_yticks(np.arange(len(markers)) + 0.5, markers, fontsize=6 if len(markers) > 30 else 7)
    ax.set_xlabel("frames of the takes, side by side" if joined else "time [s]", fontsize=8)
    ax.tick_params(labelsize=7)
    legend = ax.legend(handles=[Patch(color=c, label=lab) for c, lab in zip(_MAP_COLOURS, _MAP_LABELS, strict=True)],
                       loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    _room_right(fig, legend)
    return fig


def _fig_error_time(errors, methods, style, fps, ax, ylabel):
    for m in methods:
        e = errors[errors["method"] == m].groupby("frame")["err_m"].median()
        if len(e):
            ax.plot(e.index.to_numpy() / fps, e.to_numpy() * 1000, color=style[m][0], ls=style[m][1], lw=1.0,
                    label=m)
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # "6" rather than "6 x 10^0"
    # minor ticks: only 2 and 5 x 10^k labelled (every one overlaps its neighbours over a decade or two)
    ax.yaxis.set_minor_formatter(FuncFormatter(
        lambda v, _: f"{v:g}" if v > 0 and f"{v:.0e}"[0] in "25" else ""))
    ax.set_xlabel("time [s]", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)


def _fig_reference(errors, methods, style, fps):
    fig = Figure(figsize=(9.0, 3.0), dpi=DPI)
    ax = fig.add_subplot(1, 1, 1)
    _fig_error_time(errors, methods, style, fps, ax, "median distance over markers [mm]")
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="paper (ear): EKF/UKF within 1 mm of triangulation")
    ax.set_title("distance to the reference reconstruction over time", fontsize=10)
    legend = ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.set_figwidth(fig.get_figwidth() + _legend_size_in(fig, legend)[0])  # the panel keeps its width
    fig.subplots_adjust(bottom=0.18)  # room for the time axis's label
    _room_right(fig, legend)
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
p.verdict{font-size:1.05em;max-width:75em}
figure{margin:.6em 0} figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.85em;color:#444;max-width:75em}
"""


def _figure_html(fig: Figure | None, caption: str, alt: str) -> str:
    if fig is None:
        return f'<p class="note">No data to draw: {html.escape(alt)}.</p>'
    return (f'<figure><img alt="{html.escape(alt)}" src="{_png(fig)}">'
            f"<figcaption>{caption}</figcaption></figure>")


class _Figures:
    """The report's figures, drawn after the text, over the cores (batgraph.forked.map_jobs): each
    :meth:`add` gives a placeholder for the text, :meth:`fill` puts every figure's HTML in its place.
    A figure is built inside its job, so the work of making it is shared out too."""

    def __init__(self):
        self._jobs: list[tuple[object, str, str]] = []
        self._cost: list[float] = []

    def add(self, build, caption: str, alt: str, cost: float = 1.0) -> str:
        """``build()`` gives the Figure (or None: no data); returns the placeholder for its HTML. ``cost``:
        its relative drawing time (the costly figures are handed out first, so that none is left for last)."""
        self._jobs.append((build, caption, alt))
        self._cost.append(cost)
        return f"\x00figure {len(self._jobs) - 1}\x00"

    def fill(self, text: str) -> str:
        """``text`` with every placeholder replaced by its figure's HTML."""
        order = sorted(range(len(self._jobs)), key=lambda i: -self._cost[i])

        def draw(k: int) -> str:
            build, caption, alt = self._jobs[order[k]]
            return _figure_html(build(), caption, alt)

        drawn = forked.map_jobs(draw, len(order))
        for k, i in enumerate(order):
            text = text.replace(f"\x00figure {i}\x00", drawn[k])
        return text


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


def _camera_table(summary: dict, methods, cameras, experiment: str | None) -> str:
    """Rows (camera, method), from summary.json's per-camera reprojection figures (inliers only)."""
    rows = []
    for ci, cam in enumerate(cameras):
        present = [m for m in methods if (_get(summary, "methods", m, "reprojection", cam, "n") or 0)
                   + (_get(summary, "methods", m, "reprojection", cam, "n_outliers") or 0)]
        for k, m in enumerate(present):
            v = _get(summary, "methods", m, "reprojection", cam)
            frac = v.get("outlier_fraction")
            row = [(html.escape(str(cam)), f'class="l" rowspan="{len(present)}"')] if k == 0 else []
            row += [(html.escape(m), 'class="l"'), _fmt(v.get("n"), 0), _fmt(v.get("n_outliers"), 0),
                    _fmt(None if frac is None else 100 * frac, 1), _fmt(v.get("mean_px")), _fmt(v.get("median_px")),
                    _fmt(v.get("rms_px")), _fmt(v.get("p95_px")), _fmt(v.get("mean_mm_at_depth")),
                    _fmt(v.get("p95_mm_at_depth"))]
            if k == 0 and experiment:
                row.append((_paper_camera_figure(experiment, ci), f'class="l paper" rowspan="{len(present)}"'
                            ' style="background:#fff8e0"'))
            rows.append(row)
    if not rows:
        return '<p class="note">No reprojection errors.</p>'
    header = [("camera", 'class="l"'), ("method", 'class="l"'), "inliers n", "outliers", "outliers [%]",
              "mean [px]", "median [px]", "RMS [px]", "p95 [px]", "mean [mm at depth]", "p95 [mm at depth]"]
    if experiment:
        header.append(("paper (published)", 'class="l"'))
    return _table(header, rows, "cameras")


def _group_table(summary: dict, methods, block: str) -> str:
    """Each method's own figures per headline group from summary.json ``methods[m][block]`` (truth or
    reference): n estimated, RMSE [mm] (and 95 % coverage against truth). Methods are *not* compared on the
    same points here: see the verdict's table for that."""
    header = [("method", 'class="l"')]
    for g in HEADLINE_GROUPS.values():
        header += [f"{html.escape(g)}: n", "RMSE [mm]"] + (["cov. 95 %"] if block == "truth" else [])
    rows = []
    for m in methods:
        b = _get(summary, "methods", m, block) or {}
        row = [(html.escape(m), 'class="l"')]
        for g in HEADLINE_GROUPS:
            if block == "truth":
                n, rmse, cov = (_get(b, "n_estimated", g), _get(b, "rmse_m", g), _get(b, "coverage95", g))
                row += [_fmt(n, 0), _fmt(None if rmse is None else 1000 * rmse),
                        _fmt(None if cov is None else 100 * cov, 1) + (" %" if cov is not None else "")]
            else:
                n, rms = _get(b, "n_by_group", g), _get(b, "rms_by_group_m", g)
                row += [_fmt(n, 0), _fmt(None if rms is None else 1000 * rms)]
        rows.append(row)
    return _table(header, rows, "status")


def _comparison_table(summary: dict, style) -> str:
    """The like-for-like table: per headline group, the points every listed method estimates (n) and each
    method's figure on exactly those points (summary.json ``comparison``)."""
    c = Summary.from_json(summary).comparison
    if c is None or not c.groups:
        return '<p class="note">One method ran: nothing to compare.</p>'
    unit = {"truth": "RMSE vs truth [mm] (95 % coverage)", "reference": "RMS difference to the reference [mm]",
            "reprojection": "median reprojection error of inlier observations [px]"}[c.against]
    header = [("points", 'class="l"'), "n"] + [(html.escape(m), f'style="color:{style.get(m, ("#000",))[0]}"')
                                               for m in c.methods]
    rows = []
    for g, label in HEADLINE_GROUPS.items():
        gc = c.groups.get(g)
        if gc is None:
            continue
        row = [(html.escape(label), 'class="l"'), _fmt(gc.n, 0)]
        for m in c.methods:
            v = gc.values.get(m)
            if v is None:
                row.append("not estimated")
            elif c.against == "truth":
                cov = v.get("coverage95")
                row.append(_fmt(None if v.get("rmse_m") is None else 1000 * v["rmse_m"])
                           + (f" ({100 * cov:.0f} %)" if cov is not None else ""))
            elif c.against == "reference":
                row.append(_fmt(None if v.get("rms_m") is None else 1000 * v["rms_m"]))
            else:
                row.append(_fmt(v.get("median_px")))
        rows.append(row)
    return (f'<p class="note">Methods compared on the same points: {unit}. n = the points (or observations) '
            "every method of the row estimates; a method that estimates none of a group is marked, not counted."
            "</p>" + _table(header, rows, "compare"))


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
    groups = [(st, sub) for sub in SUBSETS for st in evaluate.STATUSES if (st, sub) in present]
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


@contextlib.contextmanager
def _gc_paused():
    """Python's cyclic garbage collector off inside (as it was outside afterwards).

    Matplotlib builds many short-lived reference cycles (artists, transforms), which trigger collections
    that also walk every long-lived object of the run (tables, session): ~10 % of a report's time. The
    figures' cycles are collected after the report, by the collector's next ordinary run.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def render_report(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                  summary: dict | None) -> str:
    """The report as one HTML string (see the module docstring for its sections).

    session: :class:`batgraph.session.Session` (rig, fps, markers, skeleton, truth, reference).
    trajectories, reprojection: CONTRACT.md section 3 tables, every method stacked.
    summary: the summary.json dict, whose figures are shown as they are; None (or one without ``methods``)
        computes it from the tables with batgraph.summary.summarize, as reconstruct does.
    """
    with _gc_paused():
        return _render_report(session, trajectories, reprojection, summary)


def _render_report(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: dict | None) -> str:
    """:func:`render_report`'s work (the collector paused around it)."""
    trajectories = trajectories.copy()
    trajectories["method"] = trajectories["method"].astype(str)
    if "span" not in trajectories and "n_views" in trajectories:
        trajectories = evaluate.add_span(trajectories)
    reprojection = reprojection.copy()
    reprojection["method"] = reprojection["method"].astype(str)
    if not summary or not summary.get("methods"):
        summary = summarize(session, trajectories, reprojection)
    elif not summary.get("verdict"):
        summary = refresh_verdict(dict(summary))
    methods = _methods(trajectories, reprojection, summary)
    style = _style(methods)
    has_xyz = np.isfinite(trajectories[["x", "y", "z"]].to_numpy(float)).all(axis=1)
    estimated = set(trajectories.loc[has_xyz, "method"])
    plotted = [m for m in methods if m in estimated]  # a method without a single estimate has nothing to draw
    fps = float(session.fps)
    cameras = session.rig.names
    panel_cameras, panel_note = _panel_cameras(cameras)
    markers = list(session.markers)
    markers += [m for m in pd.unique(trajectories["marker"].astype(str)) if m not in markers]
    # the result's frame axis: every frame of every take, none between (batgraph.session.frame_axis)
    frames = np.unique(trajectories["frame"].to_numpy(np.int64)) if len(trajectories) else session.frames
    n_takes = int(evaluate.take_of(frames).max()) + 1 if len(frames) else 0
    selected = _selected_markers(markers)
    experiment = summary.get("paper_experiment")
    truth = session.truth if session.truth is not None and len(session.truth) else None
    reference = session.reference if session.reference is not None and len(session.reference) else None
    verdict = Summary.from_json(summary).verdict

    status_fm = None
    if "status" in trajectories and plotted:
        st = trajectories[trajectories["method"] == plotted[0]].drop_duplicates(["frame", "marker"])
        st = st.pivot(index="frame", columns="marker", values="status").reindex(frames)
        status_fm = {mk: st[mk].astype(str).to_numpy() if mk in st else np.full(len(frames), "")
                     for mk in selected}

    sections: list[tuple[str, str, str]] = []  # (anchor, title, body html)
    figures = _Figures()  # drawn at the end, over the cores

    # --- the verdict: which result, how good, what to look at, where the gaps are
    warnings = summary.get("warnings") or []
    warn_html = ('<div class="warn"><p><b>Warnings</b> (self-checks before any estimator ran, the noise '
                 "model's outlier counts, and the smoother's notes on its segments and motion model):</p><ul>"
                 + "".join(f"<li>{html.escape(str(w))}</li>" for w in warnings) + "</ul></div>") if warnings else ""
    use = verdict.use if verdict else (plotted[0] if plotted else None)

    def data_map():
        return _fig_coverage_map(trajectories, use, frames, markers, fps) if use and len(frames) else None

    verdict_html = (
        (f'<p class="verdict">Use the <b style="color:{style.get(use, ("#000",))[0]}">{html.escape(use)}</b> '
         f"result: {html.escape(verdict.why)}.</p><p class=\"verdict\"><b>How good:</b> "
         f"{html.escape(verdict.headline)}.</p>" if verdict else "")
        + warn_html
        + _comparison_table(summary, style)
        + figures.add(data_map, "Where the data are, per marker and frame: seen by two or more cameras (green), "
                      "by one (orange) or none (red) inside the marker's track, and the track ends before its "
                      "first and after its last frame seen twice (grey), where every method extrapolates. "
                      "trajectories.csv has the same as its status and span columns; C3D/TRC exports leave the "
                      "track ends out by default.", "where the data are", cost=0.1)
    )
    sections.append(("verdict", "Verdict", verdict_html))

    # --- session facts
    noise = _get(summary, "pixel_noise", "cameras") or {}
    cam_rows = [[(html.escape(c.name), 'class="l"'), f"{c.size_wh[0]}×{c.size_wh[1]}",
                 _fmt(c.K[0, 0], 1), _fmt(np.linalg.norm(c.center_world), 2),
                 _fmt(_get(noise, c.name, "sigma_px"), 2), _fmt(_get(summary, "pixel_sigma_px", c.name), 2)]
                for c in session.rig]
    run_rows = []
    for m in methods:
        est, pts = _get(summary, "methods", m, "estimated") or {}, _get(summary, "methods", m, "points") or {}
        run_rows.append([(html.escape(m), f'class="l" style="color:{style[m][0]}"'),
                         _fmt(_get(summary, "methods", m, "runtime_s"), 2)]
                        + [f"{_fmt(est.get(g), 0)} / {_fmt(pts.get(g), 0)}" for g in HEADLINE_GROUPS])
    overview = (
        f'<p>Session <b>{html.escape(str(session.name))}</b>: {len(cameras)} cameras, {len(markers)} markers, '
        f"frames {frames[0]}–{frames[-1]} ({len(frames)} frames at {fps:g} fps, {len(frames) / fps:.2f} s"
        + (f", in {n_takes} takes solved on their own" if n_takes > 1 else "") + "). "
        f"Methods: {', '.join(html.escape(m) for m in methods)}. "
        + (f"This session is the paper's <b>{experiment}</b> experiment (declared by the session), so the "
           "paper's published figures are shown beside batgraph's." if experiment else
           "The paper's published figures are not shown: the session does not declare itself one of the "
           "paper's scenes (session.toml <code>[paper] experiment = \"flight\"</code> or <code>\"ear\"</code>).")
        + "</p>"
        + _table([("method", 'class="l"'), "runtime [s]"] + [f"estimated: {html.escape(g)}"
                                                              for g in HEADLINE_GROUPS.values()], run_rows, "runs")
        + _table([("camera", 'class="l"'), "size [px]", "fx [px]", "distance to origin [m]",
                  "measured noise [px]", "noise used [px]"], cam_rows, "rig")
    )
    sections.append(("overview", "Session and runs", overview))

    # --- 3D trajectories
    def paths():
        return _fig_trajectories(trajectories, plotted, style, frames, markers, session.skeleton,
                                 _points_cube(truth, frames, markers)) if plotted else None

    sections.append(("trajectories", "3D trajectories", figures.add(
        paths, "Every marker's path (colour = marker) for each method, in the world frame [m], on common "
        "axes (1st–99th percentile of all estimates), equally scaled unless one range is under a quarter of "
        "the longest (then that axis is stretched). Blue segments: the skeleton at five evenly spaced "
        "frames (the paper's Fig. 5a draws the wing the same way). Thin black: truth, when known.",
        "3D trajectories per method", cost=0.15)))

    # --- reprojection ellipses (Fig. 5 b-f)
    def ellipses():
        drawn = reprojection[reprojection["camera"].isin(panel_cameras)]  # the others are not drawn
        if not len(drawn):
            return None
        rep_mm = evaluate.reprojection_in_mm(drawn, trajectories, session.rig)
        rng = np.random.default_rng(0)  # only for thinning the scatter; fixed so reports are reproducible
        return _fig_reprojection_ellipses(rep_mm, methods, style, panel_cameras, rng)

    sections.append(("ellipses", "Reprojection error per camera (paper Fig. 5 b–f)", figures.add(
        ellipses, "Reprojection residual (û − u, v̂ − v) of every inlier observation, expressed in millimetres at "
        "the marker's depth in that camera (residual × depth / f). Ellipses: 95 % ellipse of each method's "
        "residuals (mean ± χ²₂ 95 % of their covariance); line styles and colours as everywhere in batgraph "
        "(EKF dashed and UKF solid as in the paper). Axes: v downward as in the image." + panel_note,
        "reprojection error ellipses per camera", cost=0.2)))

    # --- reprojection over image features (Fig. 6)
    def features():
        if not plotted:
            return None
        sel_idx = [markers.index(m) for m in selected]
        reproj_tracks = {}
        for m in plotted:
            cube = session.rig.to_user(_trajectory_cube(trajectories, m, frames, markers)[:, sel_idx])
            reproj_tracks[m] = {c.name: c.project(cube, distort=True) for c in session.rig
                                if c.name in panel_cameras}
        return _fig_reprojection_image(session, reproj_tracks, plotted, style, panel_cameras, selected, frames)

    sections.append(("features", "Reprojections over the 2D features (paper Fig. 6)", figures.add(
        features, f"Image features (open circles, colour = marker) of the markers {', '.join(selected)} and "
        "each method's 3D estimate projected back into the raw (distorted) image over every frame "
        "(lines, method style), so the lines also run through occlusion gaps. Pixels: OpenCV convention, "
        "v downward; each panel is zoomed to the features." + panel_note,
        "reprojections over image features", cost=0.25)))

    # --- coordinates over time
    def coordinates():
        return _fig_coordinates(trajectories, plotted, style, frames, fps, selected, status_fm,
                                _points_cube(truth, frames, selected),
                                _points_cube(reference, frames, selected)) if plotted else None

    sections.append(("coordinates", "Marker coordinates over time", figures.add(
        coordinates, "World x, y, z [m] of the selected markers for each method, with 95 % bands (± 1.96 σ per axis "
        f"from the marginal covariance). Shaded: frames where the marker was seen by one camera only "
        f"(orange) or by none (red), from the status column of {html.escape(plotted[0]) if plotted else '–'}."
        + (" Dotted black: truth." if truth is not None else "")
        + (" Purple dots: reference reconstruction." if reference is not None else ""),
        "marker coordinates over time", cost=0.6)))

    # --- per-camera table
    table = _camera_table(summary, methods, cameras, experiment)
    sections.append(("table", "Reprojection error per camera", (
        '<p class="note">Per camera and method, over the inlier observations only (n): pixel statistics of '
        "|(û, v̂) − (u, v)| on the raw image, and the same error in millimetres at the marker's depth "
        "(err_px × depth / f × 1000, depth = z of the method's estimate in that camera). Observations the "
        "method flagged as outliers are counted, with their share, and left out of every figure."
        + (f" The last column is the paper's published figure for its {experiment} experiment"
           + (" (its camera 1 was the base of a pairwise calibration, hence its smaller error)"
              if experiment == "flight" else "") + "." if experiment else "")
        + "</p>" + table
        + ("<p class=\"note\">The paper's published figures (Bender et al., PAPER.md):</p>"
           + _paper_table(experiment) if experiment else ""))))

    # --- truth
    if truth is not None and plotted:
        errors = evaluate.point_errors(trajectories[trajectories["method"].isin(plotted)], truth)
        sections.append(("truth", "Errors against truth", (
            '<p class="note">Each method\'s own estimates against truth.csv, per kind of point: seen by ≥ 2 '
            "cameras, gaps inside a track seen by one camera or none, and the track ends (before a marker's first "
            "and after its last frame seen twice: extrapolation); n = the points the method estimates, so the "
            "rows differ in n — the verdict's table compares the methods on the same points. Coverage: the "
            "fraction of truth points inside their estimate's 95 % ellipsoid (squared Mahalanobis distance "
            "≤ 7.815, χ²₃ 95 %): an honest covariance gives about 95 %.</p>"
            + _group_table(summary, plotted, "truth")
            + figures.add(lambda: _fig_truth(summary, errors, plotted, style, fps) if len(errors) else None,
                          "Left: RMSE per kind of point [mm, log]. Middle: 95 % coverage (dashed: the "
                          "nominal 0.95). Right: median over markers of the error on each frame [mm, log].",
                          "errors against truth", cost=0.15))))

    # --- reference
    if reference is not None and plotted:
        ref_errors = evaluate.point_errors(trajectories[trajectories["method"].isin(plotted)], reference)
        sections.append(("reference", "Differences to the reference reconstruction", (
            '<p class="note">Distance between each method\'s estimate and the reference 3D points '
            "(reference_xyz.csv, e.g. DLTdv's xyzpts from an import) on the frames both have. Paper (ear "
            "data): EKF and UKF within 1 mm of stereo triangulation.</p>"
            + (_group_table(summary, plotted, "reference") if len(ref_errors)
               else '<p class="note">No common (frame, marker) pairs.</p>')
            + figures.add(lambda: _fig_reference(ref_errors, plotted, style, fps) if len(ref_errors) else None,
                          "Median over markers of the distance to the reference on each frame [mm, "
                          "log]; dashed: the paper's 1 mm.", "differences to the reference", cost=0.1))))

    validation = _validation_section(summary)
    if validation is not None:
        sections.append(("validation", "Leave-one-camera-out validation", validation))

    nav = " ".join(f'<a href="#{a}">{html.escape(t)}</a>' for a, t, _ in sections)
    body = "\n".join(f'<section id="{a}"><h2>{html.escape(t)}</h2>\n{b}\n</section>' for a, t, b in sections)
    title = f"batgraph report: {html.escape(str(session.name))}"
    return figures.fill(f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
            f"<style>{CSS}</style></head><body>\n<h1>{title}</h1>\n<nav>{nav}</nav>\n{body}\n"
            '<p class="note">Written by batgraph. Self-contained: every figure is embedded.</p>'
            "</body></html>\n")


def write_report(path: str | Path, session, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                 summary: dict | None) -> Path:
    """Render the report (see :func:`render_report`) and write it to ``path`` atomically. Returns the path."""
    path = Path(path)
    atomic.write_text(path, render_report(session, trajectories, reprojection, summary))
    return path
