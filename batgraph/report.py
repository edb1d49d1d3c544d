"""The self-contained HTML comparison report (report.html): every method side by side, plots embedded.

It draws finished tables (trajectories, reprojection) and a batgraph.summary.Summary; it estimates
nothing and writes nothing but the one HTML file. Figures are inline SVG (batgraph.svg: drawn by the
browser, sharp at any zoom), so the file opens anywhere, offline, with no script and no external ``src``
or ``href``.

Sections: the verdict, overview, 3D trajectories, reprojection error per camera with 95 % ellipses in mm at the
marker's depth (the paper's Fig. 5 b-f), reprojections over the 2D features (Fig. 6), marker
coordinates over time with 95 % bands and occlusion shading, a per-camera error table next to the
paper's published figures, and -- when the session has them -- errors against truth (RMSE by status,
95 % coverage) and differences to a reference reconstruction (e.g. DLTdv's xyzpts).
"""

from __future__ import annotations

import html
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from . import atomic, evaluate, svg
from . import methods as methods_registry
from .summary import HEADLINE_GROUPS, UNITS, Summary, comparison_rows
from .validation_table import COLUMNS, SUBSETS, group_label

# The markers named in the paper's Fig. 6, in its order.
PAPER_MARKERS = ("body2", "shoulder_r", "elbow_r", "wrist_r", "digit5_r", "digit4_r", "digit3_r")
CHI2_2DOF_95 = 5.991464547107979  # 95 % quantile of chi-square, 2 DOF (reprojection ellipses)

MAX_SCATTER = 1500  # residual points drawn per (method, camera): keeps the figures small
MAX_TRACK_FRAMES = 600  # frames drawn per track in the image-space and time plots
# Per-camera figures draw at most this many panels (evenly spaced over the rig; the per-camera table lists
# every camera): 30 small panels are unreadable side by side.
MAX_CAMERA_PANELS = 10
MAX_ASPECT = 4.0  # 3D panels: an axis shorter than 1/4 of the longest is stretched so that it stays readable


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _methods(trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: Summary) -> list[str]:
    found = {str(m) for table in (trajectories, reprojection) for m in pd.unique(table["method"])}
    found |= set(summary.methods)
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


def _legend_items(methods, style, extra=()) -> list[tuple[str, dict]]:
    """Legend entries (svg.Figure.legend) of the methods' line styles, then ``extra`` (label, style) pairs."""
    return [(m, {"colour": style[m][0], "dash": style[m][1], "width": 1.6}) for m in methods] + list(extra)


# ----------------------------------------------------------------------------------------------
# figures: each returns an svg.Figure (or None when there is nothing to draw); sizes in px
# ----------------------------------------------------------------------------------------------
def _grid(n: int, max_cols: int) -> tuple[int, int]:
    """(rows, columns) for ``n`` panels in rows of at most ``max_cols``."""
    ncol = min(n, max_cols)
    return int(math.ceil(n / ncol)), ncol


def _separated(parts: list[np.ndarray]) -> np.ndarray:
    """(n_i, D) arrays joined into one with a NaN row between them (one broken line, svg.Axes.line)."""
    if not parts:
        return np.empty((0, 2))
    gap = np.full((1, parts[0].shape[1]), np.nan)
    return np.concatenate([x for p in parts for x in (p, gap)])


def _marker_styles(markers: list[str]) -> list[dict]:
    """A line style per marker (svg.Figure.legend): the colours of svg.colours, solid for the first 20, dashed
    for the next 20, dotted beyond, so that no two of up to 60 markers look alike."""
    cmap = svg.colours(len(markers))
    return [{"colour": cmap[j], "dash": ("-", "--", ":")[min(j // 20, 2)], "width": 1.6} for j in range(len(markers))]


def _robust_view(points: list[np.ndarray], pad_fraction: float = 0.08) -> svg.View3D | None:
    """A View3D of the 1st-99th percentile box of ``points`` (arrays (..., 3) [m]), padded; None without any
    finite point. Robust: a diverged method must not shrink everyone else's bat to a dot."""
    allpts = np.concatenate([p.reshape(-1, 3) for p in points])
    allpts = allpts[np.isfinite(allpts).all(axis=1)]
    if len(allpts) == 0:
        return None
    lo, hi = np.percentile(allpts, 1, axis=0), np.percentile(allpts, 99, axis=0)
    pad = pad_fraction * max(float((hi - lo).max()), 1e-3)
    lo, hi = lo - pad, hi + pad
    span = np.maximum(hi - lo, 1e-9)
    return svg.View3D(lo, hi, np.maximum(span, span.max() / MAX_ASPECT))


def _fig_trajectories(trajectories, methods, style, frames, markers, skeleton, truth_cube):
    """One 3D panel per method, two to a row (svg.View3D: the same view for all); every marker's path in its own
    style (legend beneath, every marker); the skeleton at a few frames; truth thin black."""
    cubes = {m: _trajectory_cube(trajectories, m, frames, markers) for m in methods}
    view = _robust_view(list(cubes.values()) + ([truth_cube] if truth_cube is not None else []))
    if view is None:
        return None
    styles = _marker_styles(markers)
    mi = {m: i for i, m in enumerate(markers)}
    sk = [(mi[a], mi[b]) for a, b in skeleton if a in mi and b in mi]
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    snap = np.linspace(0, len(frames) - 1, min(5, len(frames))).astype(int)
    legend = [(mk, styles[j]) for j, mk in enumerate(markers)]
    if truth_cube is not None:
        legend.append(("truth", {"colour": "#000", "width": 0.6, "opacity": 0.5}))
    if sk:
        legend.append(("skeleton (5 frames)", {"colour": "#3060c0", "width": 1.2}))
    nrow, ncol = _grid(len(methods), 2)
    (x0, x1), (y0, y1) = view.limits()
    pw = 640
    ih = min(max((pw - 120) * (y1 - y0) / (x1 - x0), 200.0), 460.0)  # the panels take the view's proportions
    ph = ih + 70
    cell = max(svg.text_width(lab, 11) for lab, _ in legend) + 40
    width = max(pw * ncol, cell + 20)
    ncol_legend = max(1, min(len(legend), int((width - 20) // cell)))
    fig = svg.Figure(width, ph * nrow + 10 + math.ceil(len(legend) / ncol_legend) * 18)
    for k, m in enumerate(methods):
        r, c = divmod(k, ncol)
        ax = fig.add_axes((c * pw + 60, r * ph + 30, pw - 120, ih), (x0, x1), (y0, y1), equal=True)
        cube = cubes[m]
        view.draw_box(ax)  # under the paths
        if truth_cube is not None:
            ax.line(*view.project(_separated(list(truth_cube[::st].transpose(1, 0, 2)))), "#000", 0.6, opacity=0.35)
        tracks = cube[::st]
        for j in range(len(markers)):
            ax.line(*view.project(tracks[:, j]), styles[j]["colour"], 1.0, styles[j]["dash"])
        bones = [cube[f, [a, b]] for f in snap for a, b in sk if np.isfinite(cube[f, [a, b]]).all()]
        if bones:
            ax.line(*view.project(_separated(bones)), "#3060c0", 1.2, opacity=0.7)
        n_est = int(np.isfinite(cube[..., 0]).sum())
        fig.text(c * pw + pw / 2, r * ph + 18, f"{m}  ({n_est}/{cube.shape[0] * cube.shape[1]} estimates)", 13,
                 style[m][0], "middle")
    fig.legend(legend, fig.width / 2, nrow * ph + 4, ncol=ncol_legend)
    return fig


SUBJECT_WINDOW_S = 0.05
"""The verdict's picture draws each marker's path this long [s] before and after its frame."""


def _fig_subject(trajectories, method: str, frame: int, frames, markers, skeleton, fps: float):
    """The animal as the verdict's method sees it on ``frame``: each marker a dot (its name on hover), the
    skeleton, and each marker's path SUBJECT_WINDOW_S around (the whole path where fewer than 3 markers make no
    shape), zoomed on them; the track ends (extrapolated, outside a marker's span) left out. None when nothing
    is estimated there."""
    t = trajectories[(trajectories["method"] == method)]
    if "span" in t:
        t = t[t["span"] == "inside"]
    cube = evaluate.dense_from_table(t, frames, markers)[0]  # (F, M, 3)
    k = int(np.searchsorted(frames, frame))
    now = cube[min(k, len(frames) - 1)]
    ok = np.isfinite(now).all(axis=1)
    if not ok.any():
        return None
    half = max(2, int(round(SUBJECT_WINDOW_S * fps)))
    near = cube[max(0, k - half):k + half + 1] if ok.sum() >= 3 else cube
    view = _robust_view([now[ok], near], pad_fraction=0.15)
    styles = _marker_styles(markers)
    (x0, x1), (y0, y1) = view.limits()
    w = 560
    ih = min(max((w - 100) * (y1 - y0) / (x1 - x0), 220.0), 400.0)
    fig = svg.Figure(w, ih + 70)
    ax = fig.add_axes((50, 30, w - 100, ih), (x0, x1), (y0, y1), equal=True)
    view.draw_box(ax)
    for j in range(len(markers)):
        ax.line(*view.project(near[:, j]), styles[j]["colour"], 1.0, opacity=0.5)
    mi = {m: i for i, m in enumerate(markers)}
    bones = [now[[mi[a], mi[b]]] for a, b in skeleton if a in mi and b in mi and ok[[mi[a], mi[b]]].all()]
    if bones:
        ax.line(*view.project(_separated(bones)), "#222", 1.6)
    X, Y = view.project(now[ok])
    ax.marks(X, Y, [styles[j]["colour"] for j in np.flatnonzero(ok)], 7.0, [markers[j] for j in np.flatnonzero(ok)])
    n = int(ok.sum())
    fig.text(w / 2, 18, f"{method} on frame {frame} ({frame / fps:.3f} s): {n} marker{'s' if n != 1 else ''}", 13,
             "#222", "middle")
    return fig


def _ellipse_points(d: np.ndarray, n: int = 73) -> np.ndarray:
    """The 95 % ellipse (mean +- chi2_2 95 % of the covariance) of residuals ``d`` (n, 2), as (n, 2) points."""
    mean = d.mean(axis=0)
    w, v = np.linalg.eigh(np.cov(d.T))
    t = np.linspace(0, 2 * np.pi, n)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)  # (n, 2) in the eigenvectors' frame
    return mean + (circle * np.sqrt(CHI2_2DOF_95 * np.clip(w, 0, None))) @ v.T


def _fig_reprojection_ellipses(rep_mm, methods, style, cameras, rng):
    """Per camera: reprojection residual in mm at depth, scatter + 95 % ellipse per method (Fig. 5)."""
    rep = rep_mm[np.isfinite(rep_mm["du_mm"]) & np.isfinite(rep_mm["dv_mm"])]
    if "outlier" in rep:
        rep = rep[~rep["outlier"].fillna(False).astype(bool)]
    cams = [c for c in cameras if (rep["camera"] == c).any()]
    if not cams:
        return None
    nrow, ncol = _grid(len(cams), 5)
    pw, ph = 270, 300
    fig = svg.Figure(max(pw * ncol, 120 * len(methods) + 40), ph * nrow + 24)
    groups = dict(tuple(rep.groupby(["camera", "method"], sort=False)))
    for k, cam in enumerate(cams):
        r, c = divmod(k, ncol)
        drawn, extent = [], 0.0
        for m in methods:
            g = groups.get((cam, m))
            if g is None or len(g) < 3:
                continue
            d = g[["du_mm", "dv_mm"]].to_numpy(float)
            pick = d if len(d) <= MAX_SCATTER else d[rng.choice(len(d), MAX_SCATTER, replace=False)]
            ell = _ellipse_points(d)
            drawn.append((m, pick, ell))
            extent = max(extent, float(np.abs(ell).max()))
        lim = 1.15 * extent if extent > 0 else 1.0
        # v (down) positive downward, as in the image
        ax = fig.add_axes((c * pw + 62, r * ph + 28, pw - 80, pw - 80), (-lim, lim), (-lim, lim), y_down=True,
                          equal=True)
        ax.hline(0, "#b3b3b3", 0.5)
        ax.vline(0, "#b3b3b3", 0.5)
        for m, pick, _ in drawn:
            ax.points(pick[:, 0], pick[:, 1], style[m][0], 2.0, opacity=0.25)
        for m, _, ell in drawn:
            ax.line(ell[:, 0], ell[:, 1], style[m][0], 1.6, style[m][1])
        ax.frame("Δu at depth [mm]", "Δv at depth [mm]" if c == 0 else "", f"camera {cam}", n_xticks=4, n_yticks=4)
    fig.legend(_legend_items(methods, style), fig.width / 2, nrow * ph)
    return fig


def _fig_reprojection_image(session, reproj_tracks, methods, style, cameras, selected, frames):
    """Per camera: 2D features (rings) and each method's reprojected track (lines) of selected markers."""
    obs = session.observations
    obs = obs[obs["marker"].isin(selected)]
    # numpy columns once: a DataFrame filter per panel and marker cost ~1 ms each (text columns)
    cam_of, marker_of = obs["camera"].to_numpy(object), obs["marker"].to_numpy(object)
    uv_of = obs[["u", "v"]].to_numpy(float)
    cams = [c for c in cameras if (cam_of == c).any()]
    if not cams:
        return None
    nrow, ncol = _grid(len(cams), 3)
    limits = {}
    for cam in cams:  # each panel zoomed to its camera's features
        uv_all = uv_of[cam_of == cam]
        w_img, h_img = session.rig[cam].size_wh
        lo, hi = uv_all.min(axis=0), uv_all.max(axis=0)
        pad = 0.1 * max(float((hi - lo).max()), 20.0)
        limits[cam] = ((max(lo[0] - pad, -0.5), min(hi[0] + pad, w_img - 0.5)),
                       (max(lo[1] - pad, -0.5), min(hi[1] + pad, h_img - 0.5)))
    pw = 440
    # the rows as tall as the tallest panel needs at this width (equal axes), within 120-300 px
    ih = min(max(max((v[1] - v[0]) / (u[1] - u[0]) for u, v in limits.values()) * (pw - 80), 120.0), 300.0)
    ph = ih + 75
    fig = svg.Figure(pw * ncol, ph * nrow + 24)
    cmap = svg.colours(len(selected))
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    for k, cam in enumerate(cams):
        r, c = divmod(k, ncol)
        in_cam = cam_of == cam
        w_img, h_img = session.rig[cam].size_wh
        ax = fig.add_axes((c * pw + 62, r * ph + 28, pw - 80, ih), *limits[cam], y_down=True, equal=True)
        for m in methods:
            uvm = reproj_tracks[m][cam][::st]  # (F, M_sel, 2)
            colour, ls = style[m]
            ax.line(*_separated(list(uvm.transpose(1, 0, 2))).T, colour, 0.9, ls, opacity=0.85)
        for j, mk in enumerate(selected):
            rows = in_cam & (marker_of == mk)
            if not rows.any():
                continue
            uv = uv_of[rows][::max(1, st)]
            ax.points(uv[:, 0], uv[:, 1], cmap[j], 5.0, hollow=True)
            # label at the track's median: the tracks' starts often coincide, their middles less so
            mid = np.median(uv, axis=0)
            ax.text(mid[0], mid[1], mk, 9, cmap[j], dx=5, dy=3, weight="bold")
        ax.frame("u [px]", "v [px]", f"camera {cam}  ({w_img}×{h_img} px, zoomed)", n_xticks=4, n_yticks=4)
    fig.legend(_legend_items(methods, style, [("image features", {"colour": "#000", "points": True, "hollow": True})]),
               fig.width / 2, nrow * ph)
    return fig


def _fig_coordinates(trajectories, methods, style, frames, fps, selected, status_fm, truth_cube, ref_cube):
    """Selected markers (rows) x, y, z (columns) over time; 95 % bands; occlusion shaded."""
    t = frames / fps
    st = _stride(len(frames), MAX_TRACK_FRAMES)
    has_cov = all(c in trajectories for c in evaluate.TRAJ_COLUMNS[7:13])
    cubes = {m: evaluate.dense_from_table(trajectories, frames, selected, method=m)[:2] for m in methods}
    half = 0.5 / fps
    legend = _legend_items(methods, style)
    if truth_cube is not None:
        legend.append(("truth", {"colour": "#000", "dash": ":", "width": 1.0}))
    if ref_cube is not None:
        legend.append(("reference", {"colour": "#9467bd", "points": True}))
    legend += [("single view", {"colour": "#f6d7a7", "patch": True}),
               ("unobserved", {"colour": "#f4a6a6", "patch": True}),
               ("95 % band (±1.96 σ)", {"colour": "#999", "patch": True, "opacity": 0.3})]
    pw, ph, gap, left = 400, 105, 16, 95
    fig = svg.Figure(left + 3 * pw + 20, 0)
    top = fig.legend(legend, fig.width / 2, 2) + 28  # above the panels, in a band of its own height
    fig.height = top + len(selected) * (ph + gap) + 36
    x_lim = (t[0], t[-1]) if len(t) > 1 else (t[0] - half, t[0] + half)
    for i, mk in enumerate(selected):
        for a, axis in enumerate("xyz"):
            lines = []
            for m in methods:
                xyz, cov = cubes[m]
                y = xyz[:, i, a]
                sd = np.sqrt(np.clip(cov[:, i, a, a], 0, None)) if has_cov else None
                lines.append((m, y[::st], None if sd is None else (y - 1.96 * sd)[::st],
                              None if sd is None else (y + 1.96 * sd)[::st]))
            shown = [v for _, *ys in lines for v in ys if v is not None]
            shown += [c[::st, i, a] for c in (truth_cube, ref_cube) if c is not None]
            vals = np.concatenate(shown) if shown else np.empty(0)
            vals = vals[np.isfinite(vals)]
            y_lim = (vals.min(), vals.max()) if len(vals) else (0.0, 1.0)
            y_pad = 0.05 * (y_lim[1] - y_lim[0]) or 0.01
            ax = fig.add_axes((left + a * pw + 20, top + i * (ph + gap), pw - 40, ph), x_lim,
                              (y_lim[0] - y_pad, y_lim[1] + y_pad))
            if status_fm is not None:
                s = status_fm[mk]
                for name, colour in (("single_view", "#f6d7a7"), ("unobserved", "#f4a6a6")):
                    runs = np.array(_status_runs(frames, s == name), float).reshape(-1, 2)
                    ax.vspan(runs[:, 0] / fps - half, runs[:, 1] / fps + half, colour)
            for m, _, lo_, hi_ in lines:
                if lo_ is not None:
                    ax.band(t[::st], lo_, hi_, style[m][0], 0.15)
            for m, y, _, _ in lines:
                ax.line(t[::st], y, style[m][0], 1.0, style[m][1])
            if truth_cube is not None:
                ax.line(t[::st], truth_cube[::st, i, a], "#000", 0.9, ":")
            if ref_cube is not None:
                ax.points(t[::st], ref_cube[::st, i, a], "#9467bd", 2.5)
            last = i == len(selected) - 1
            ax.frame("time [s]" if last else "", mk if a == 0 else "", f"{axis} [m]" if i == 0 else "",
                     xticks=last, n_xticks=5, n_yticks=3)
    return fig


def _fig_group_bars(fig, box, values: dict[str, dict[str, float | None]], methods, style, ylabel: str,
                    scale: float, hline: float | None, title: str, log: bool = False, ylim=None):
    """Bars per headline group (x) and method (colour) in ``box`` of ``fig``: values[method][group]; None draws
    nothing."""
    groups = list(HEADLINE_GROUPS)
    vals = np.array([[np.nan if values.get(m, {}).get(g) is None else values[m][g] * scale for g in groups]
                     for m in methods], float).reshape(len(methods), len(groups))
    if ylim is None:
        fin = vals[np.isfinite(vals) & (vals > 0)] if log else vals[np.isfinite(vals)]
        ylim = ((fin.min() / 1.5, fin.max() * 1.5) if log else (0.0, fin.max() * 1.1)) if len(fin) else (0.1, 1.0)
    ax = fig.add_axes(box, (-0.5, len(groups) - 0.5), ylim, ylog=log)
    w = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        x = np.arange(len(groups)) + (k - (len(methods) - 1) / 2) * w
        ok = np.isfinite(vals[k])
        ax.rects(x[ok] - w / 2, x[ok] + w / 2, np.full(ok.sum(), ylim[0]), vals[k][ok], style[m][0])
    if hline is not None:
        ax.hline(hline, "#000", 0.8, "--")
    ax.frame("", ylabel, title, xticks=False)
    for j, g in enumerate(groups):  # the groups' names under the bars, wrapped
        for n, piece in enumerate(textwrap.wrap(HEADLINE_GROUPS[g], 14)):
            fig.text(float(ax.px(j)), box[1] + box[3] + 15 + 12 * n, piece, 10, anchor="middle")
    return ax


def _fig_truth(summary: Summary, errors, methods, style, fps):
    """RMSE and 95 % coverage per headline group (from summary.json), and the error over time."""
    fig = svg.Figure(1380, 330)
    rmse = {m: _get(summary.methods, m, "truth", "rmse_m") or {} for m in methods}
    cov = {m: _get(summary.methods, m, "truth", "coverage95") or {} for m in methods}
    _fig_group_bars(fig, (70, 30, 340, 210), rmse, methods, style, "RMSE [mm, log]", 1000.0, None, "RMSE vs truth",
                    log=True)
    _fig_group_bars(fig, (500, 30, 340, 210), cov, methods, style, "fraction inside", 1.0, 0.95,
                    "truth inside the 95 % ellipsoid", ylim=(0.0, 1.05))
    _fig_error_time(fig, (930, 30, 430, 210), errors, methods, style, fps, "median error over markers [mm]",
                    "error vs truth over time")
    fig.legend(_legend_items(methods, style), fig.width / 2, 300)
    return fig


_MAP_CODES = {"observed": 0, "single_view": 1, "unobserved": 2, "outside": 3}
_MAP_COLOURS = ("#2ca02c", "#ff9f1c", "#d62728", "#c7c7c7")
_MAP_LABELS = ("seen by >= 2 cameras", "seen by 1 camera (gap)", "seen by none (gap)", "track end (extrapolated)")


def _fig_coverage_map(trajectories, method: str, frames: np.ndarray, markers: list[str], fps: float):
    """Marker x frame map of where the data are: observed / single view / unobserved inside each marker's
    span, and the track ends outside it (the rows of ``method``; status and span are the same for all)."""
    t = trajectories[trajectories["method"] == method].drop_duplicates(["frame", "marker"])
    if not len(t) or "status" not in t:
        return None
    code = t["status"].map(_MAP_CODES).to_numpy(float)
    if "span" in t:
        code = np.where(t["span"].to_numpy() == "outside", _MAP_CODES["outside"], code)
    grid = (pd.Series(code, index=pd.MultiIndex.from_frame(t[["marker", "frame"]]))
            .unstack("frame").reindex(index=markers, columns=frames).to_numpy(float))
    return _marker_frame_map(grid, frames, markers, fps, _MAP_COLOURS, _MAP_LABELS)


def _marker_frame_map(grid: np.ndarray, frames: np.ndarray, markers: list[str], fps: float, colours: list[str],
                      labels: list[str]) -> svg.Figure:
    """A marker x frame map: grid (M, F) holds a class index per cell (NaN: none drawn), shown in colours[class]
    with its label in the legend; frames (F,) on the time axis (side by side where they are not consecutive)."""
    joined = len(frames) and frames[-1] - frames[0] + 1 != len(frames)  # several takes: their frames side by side
    edges = np.arange(len(frames) + 1, dtype=float) if joined else np.append(frames, frames[-1] + 1) / fps
    row = 12 if len(markers) > 30 else 16
    left = 20 + max(svg.text_width(m, 10) for m in markers)
    legend_w = max(svg.text_width(lab, 11) for lab in labels) + 50
    fig = svg.Figure(1200, max(row * len(markers) + 50, 18 * len(labels) + 20))  # the legend fits too
    ax = fig.add_axes((left, 8, 1200 - left - legend_w - 20, row * len(markers)), (edges[0], edges[-1]),
                      (0, len(markers)), y_down=True)
    for c, colour in enumerate(colours):  # one rectangle per run of a class along a marker's row
        on = np.pad(grid == c, ((0, 0), (1, 1))).astype(np.int8)
        starts, ends = np.nonzero(np.diff(on, axis=1) == 1), np.nonzero(np.diff(on, axis=1) == -1)
        ax.rects(edges[starts[1]], edges[ends[1]], starts[0].astype(float), starts[0] + 1.0, colour)
    ax.frame("frames of the takes, side by side" if joined else "time [s]", "", "",
             yticklabels=(np.arange(len(markers)) + 0.5, list(markers)))
    fig.legend([(lab, {"colour": col, "patch": True}) for col, lab in zip(colours, labels, strict=True)],
               1200 - legend_w, 8, ncol=1, anchor="start")
    return fig


_HOW_LABELS = {"none": "not named", "seed": "seed (your clicks)", "tracked": "tracked (a 3D point)",
               "ray": "joined along its predicted ray", "reprojection": "matched where its path projects"}
_HOW_COLOURS = ["#eeeeee", "#000000", "#1b9e77", "#7570b3", "#d95f02"]


def _association_section(r: _Report) -> str | None:
    """How the markers were named from unlabelled detections (summary.association, batgraph.associate): the
    counts, a marker x frame map of how each name was obtained and the suspected identity switches; None when
    the run took labelled observations."""
    a = r.summary.association
    if not isinstance(a, dict):
        return None
    codes = list(a.get("how_codes") or {})
    how = a.get("how") or {}
    markers = [m for m in how if m]
    parts = [
        f'<p>The observations are the names <code>batgraph associate</code> gave {a.get("detections")} unlabelled '
        f'detections from your seed frame: {a.get("named")} named ({100 * float(a.get("named_fraction", 0)):.1f} %), '
        f'pixel noise {_fmt(a.get("pixel_sigma_px"))} px, {a.get("suspected_switches")} suspected identity '
        "switch(es)"
        + (", named again on the cameras' clocks measured from the first names (--sync estimate)"
           if a.get("clocks_estimated") else "")
        + ". labels.csv gives every detection's name, track and confidence; a detection left unnamed "
        "(spurious, merged or in doubt) is not used.</p>"]
    if markers and codes:
        first = int(a.get("first_frame", 0))
        grid = np.array([[codes.index(ch) for ch in how[m]] for m in markers], float)
        frames = first + np.arange(grid.shape[1])
        labels = [_HOW_LABELS.get(a["how_codes"][c], a["how_codes"][c]) for c in codes]
        parts.append(r.figures.add(
            lambda: _marker_frame_map(grid, frames, markers, r.fps, _HOW_COLOURS[:len(codes)], labels),
            "How each marker got its name on each frame (the way most of its detections there were named).",
            "marker by frame map of how names were obtained"))
    switches = a.get("switches") or []
    if switches:
        rows = [[str(s["frame"]), html.escape(str(s["marker"])), _fmt(s["confidence"], 3)] for s in switches[:50]]
        parts.append('<p class="note">Suspected identity switches: where a marker\'s track resumes and its name was '
                     f"carried on with a confidence below {_fmt(a.get('suspect_below'))}"
                     + (f" (the first 50 of {len(switches)})" if len(switches) > 50 else "")
                     + ". Most wrong names are not marked here: on simulated flights 3 % of them lay within 2 "
                     "frames of one (docs/associate.md).</p>"
                     + _table(["frame", "marker", "confidence"], rows))
    return "".join(parts)


def _fig_error_time(fig, box, errors, methods, style, fps, ylabel: str, title: str, hline: float | None = None):
    """Median error over markers per frame [mm, log] of each method, in ``box`` of ``fig``; ``hline``: a dashed
    line at that value [mm] (kept in view)."""
    series = []
    for m in methods:
        e = errors[errors["method"] == m].groupby("frame")["err_m"].median()
        if len(e):
            series.append((m, e.index.to_numpy() / fps, e.to_numpy() * 1000))
    ys = np.concatenate([y for *_, y in series]) if series else np.empty(0)
    ys = np.append(ys[np.isfinite(ys) & (ys > 0)], [] if hline is None else [hline])
    xs = np.concatenate([x for _, x, _ in series]) if series else np.zeros(1)
    ax = fig.add_axes(box, (xs.min(), xs.max()), (ys.min() / 1.3, ys.max() * 1.3) if len(ys) else (0.1, 10.0),
                      ylog=True)
    for m, x, y in series:
        ax.line(x, np.where(y > 0, y, np.nan), style[m][0], 1.0, style[m][1])
    if hline is not None:
        ax.hline(hline, "#000", 0.8, "--")
    ax.frame("time [s]", ylabel, title)


def _fig_reference(errors, methods, style, fps):
    text = "paper (ear): EKF/UKF within 1 mm of triangulation"
    legend = _legend_items(methods, style, [(text, {"colour": "#000", "dash": "--", "width": 0.8})])
    legend_w = max(svg.text_width(lab, 11) for lab, _ in legend) + 50
    fig = svg.Figure(900 + legend_w, 300)
    _fig_error_time(fig, (80, 30, 800, 215), errors, methods, style, fps, "median distance over markers [mm]",
                    "distance to the reference reconstruction over time", hline=1.0)
    fig.legend(legend, 900, 30, ncol=1, anchor="start")
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
p.verdict,ul.verdict{font-size:1.05em;max-width:75em} ul.verdict{margin-top:0}
td.sub{padding-left:1.5em;color:#555}
figure{margin:.6em 0} figure img{max-width:100%;height:auto;border:1px solid #eee}
svg.fig{max-width:100%;height:auto} div.top{display:flex;flex-wrap:wrap;gap:1.5em;align-items:flex-start}
div.top>div{flex:1 1 36em} div.top>figure{flex:0 1 560px;margin:0}
figcaption{font-size:.85em;color:#444;max-width:75em}
"""


def _figure_html(fig: svg.Figure | None, caption: str, alt: str, key: str) -> str:
    """A figure's HTML: its SVG (clip ids prefixed ``key``, unique in the page) and caption."""
    if fig is None:
        return f'<p class="note">No data to draw: {html.escape(alt)}.</p>'
    return f'<figure>{fig.svg(key, alt)}<figcaption>{caption}</figcaption></figure>'


class _Figures:
    """The report's figures: each :meth:`add` gives a placeholder for the text, :meth:`fill` draws every figure
    and puts its HTML in its place (the text first, so that a figure's failure cannot hide the tables)."""

    def __init__(self):
        self._jobs: list[tuple[object, str, str]] = []

    def add(self, build, caption: str, alt: str) -> str:
        """``build()`` gives the svg.Figure (or None: no data); returns the placeholder for its HTML."""
        self._jobs.append((build, caption, alt))
        return f"\x00figure {len(self._jobs) - 1}\x00"

    def fill(self, text: str) -> str:
        """``text`` with every placeholder replaced by its figure's HTML."""
        for i, (build, caption, alt) in enumerate(self._jobs):
            text = text.replace(f"\x00figure {i}\x00", _figure_html(build(), caption, alt, f"f{i}"))
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


def _camera_table(summary: Summary, methods, cameras, experiment: str | None) -> str:
    """Rows (camera, method), from summary.json's per-camera reprojection figures (inliers only)."""
    rows = []
    for ci, cam in enumerate(cameras):
        present = [m for m in methods if (_get(summary.methods, m, "reprojection", cam, "n") or 0)
                   + (_get(summary.methods, m, "reprojection", cam, "n_outliers") or 0)]
        for k, m in enumerate(present):
            v = _get(summary.methods, m, "reprojection", cam)
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


def _group_table(summary: Summary, methods, block: str) -> str:
    """Each method's own figures per headline group from summary.json ``methods[m][block]`` (truth or
    reference): n estimated, RMSE [mm] (and 95 % coverage against truth). Methods are *not* compared on the
    same points here: see the verdict's table for that."""
    header = [("method", 'class="l"')]
    for g in HEADLINE_GROUPS.values():
        header += [f"{html.escape(g)}: n", "RMSE [mm]"] + (["cov. 95 %"] if block == "truth" else [])
    rows = []
    for m in methods:
        b = _get(summary.methods, m, block) or {}
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


def _comparison_table(summary: Summary, style) -> str:
    """The verdict's table (summary.comparison_rows, as the terminal shows it): per kind of point, the verdict
    method's points (n) and every method's figure on exactly those points."""
    c = summary.comparison
    if c is None or not c.groups:
        return '<p class="note">No accuracy figure: nothing could be compared.</p>'
    header = [("points", 'class="l"'), "n"] + [(html.escape(m), f'style="color:{style.get(m, ("#000",))[0]}"')
                                               for m in c.methods]
    rows = [[(html.escape(label), 'class="l sub"' if label.startswith(" ") else 'class="l"'), _fmt(n, 0)]
            + [html.escape(cells[m]) for m in c.methods] for label, n, cells in comparison_rows(c)]
    return (f'<p class="note">{html.escape(UNITS[c.against])}, per kind of point, on the points the '
            f"{html.escape(str(c.use))} estimates (n). A method that estimates only some of them shows how many; "
            "the row beneath then compares every method on the points they all estimate.</p>"
            + _table(header, rows, "compare"))


def _sigma_text(sigma) -> str:
    if isinstance(sigma, dict):
        return ", ".join(f"{k} {_fmt(x)} px" for k, x in sigma.items())
    return f"{_fmt(sigma)} px"


def _validation_rows(t: pd.DataFrame) -> tuple[list, list]:
    """(header, rows) of the validation table: rows (held-out camera, method), per (status, subset) group
    n, median and p90 [px]."""
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
    return header, rows


def _validation_section(summary: Summary) -> str | None:
    """Leave-one-camera-out table (summary.validation, see batgraph.validation_table); None when the run was
    not validated."""
    v = summary.validation
    if not isinstance(v, dict):
        return None
    header, rows = _validation_rows(pd.DataFrame(v.get("table") or [], columns=COLUMNS))
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


@dataclass
class _Report:
    """What every section of one report reads: the tables, the summary and what is derived once from them."""

    session: object
    trajectories: pd.DataFrame
    reprojection: pd.DataFrame
    summary: Summary
    methods: list[str]
    plotted: list[str]  # the methods with at least one estimate (the others have nothing to draw)
    style: dict[str, tuple[str, str]]
    frames: np.ndarray  # the result's frame axis: every frame of every take, none between
    markers: list[str]
    selected: list[str]
    truth: pd.DataFrame | None
    reference: pd.DataFrame | None
    figures: _Figures = field(default_factory=lambda: _Figures())

    @property
    def fps(self) -> float:
        return float(self.session.fps)

    @property
    def experiment(self) -> str | None:
        return self.summary.paper_experiment


def _prepare(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: Summary) -> _Report:
    trajectories = trajectories.copy()
    trajectories["method"] = trajectories["method"].astype(str)
    if "span" not in trajectories and "n_views" in trajectories:
        trajectories = evaluate.add_span(trajectories)
    reprojection = reprojection.copy()
    reprojection["method"] = reprojection["method"].astype(str)
    methods = _methods(trajectories, reprojection, summary)
    has_xyz = np.isfinite(trajectories[["x", "y", "z"]].to_numpy(float)).all(axis=1)
    estimated = set(trajectories.loc[has_xyz, "method"])
    markers = list(session.markers)
    markers += [m for m in pd.unique(trajectories["marker"].astype(str)) if m not in markers]
    frames = np.unique(trajectories["frame"].to_numpy(np.int64)) if len(trajectories) else session.frames
    return _Report(session, trajectories, reprojection, summary, methods, [m for m in methods if m in estimated],
                   _style(methods), frames, markers, _selected_markers(markers),
                   session.truth if session.truth is not None and len(session.truth) else None,
                   session.reference if session.reference is not None and len(session.reference) else None)


def _warnings_html(summary: Summary) -> str:
    """The warnings, one line each, with their details (summary.json ``warning_details``) beneath."""
    if not summary.warnings:
        return ""
    items = "".join(f"<li>{html.escape(str(w))}"
                    + (f'<br><span class="note">{html.escape(summary.warning_details[w])}</span>'
                       if summary.warning_details.get(w) else "") + "</li>" for w in summary.warnings)
    return f'<div class="warn"><p><b>Warnings</b></p><ul>{items}</ul></div>'


def _ends_note(summary: Summary) -> str:
    """What the smoother did at the track ends (its info ``track_ends``), one sentence, or ""."""
    ends = _get(summary.methods, "smoother", "info", "track_ends") or {}
    widened = []
    if ends.get("widened_points"):
        widened.append(f"the covariances of the {ends['widened_points']} unseen points at the track ends by 1 + "
                       f"{ends['growth_per_frame']:.3f} h (the 95th percentile of the squared errors was "
                       f"{ends['p95_ratio']:.2f}x what its covariances said)")
    if ends.get("widened_single_view_points"):
        ratio = ends.get("ray_p95_ratio")
        floored = ends.get("depth_floored_points") or 0
        widened.append(f"the variance along the ray of the {ends['widened_single_view_points']} points seen by one "
                       "camera there" + (f" ({floored} of them first raised to the variance the solve gives them "
                                         "without that view)" if floored else "")
                       + f" by 1 + {ends['ray_growth_per_frame']:.3f} h"
                       + (f" (the errors along those cameras' rays: {ratio:.2f}x)" if ratio is not None else ""))
    return (f" The smoother checked its extrapolation on {ends['markers']} tracks (their first and last "
            f"{ends['backtest_frames']} frames hidden) and widened " + " and ".join(widened) +
            ", h the distance in frames from the track." if widened else "")


def _verdict_section(r: _Report) -> str:
    """Which result to use, its headlines (one per kind of point), the warnings, the comparison, the data map."""
    verdict = r.summary.verdict
    use = verdict.use if verdict else (r.plotted[0] if r.plotted else None)

    def data_map():
        return _fig_coverage_map(r.trajectories, use, r.frames, r.markers, r.fps) if use and len(r.frames) else None

    def subject():
        frame = r.summary.opening_frame
        return None if use is None or frame is None else _fig_subject(
            r.trajectories, use, frame, r.frames, r.markers, r.session.skeleton, r.fps)

    head = ""
    if verdict:
        head = (f'<p class="verdict">Use the <b style="color:{r.style.get(use, ("#000",))[0]}">{html.escape(use)}'
                f"</b> result: {html.escape(verdict.why)}.</p><p class=\"verdict\"><b>How good:</b></p>"
                '<ul class="verdict">' + "".join(f"<li>{html.escape(h)}</li>" for h in verdict.headlines) + "</ul>")
    picture = r.figures.add(subject, "The first frame where nearly every marker is seen by two or more cameras "
                            "(where the 3D viewer opens), with the markers' paths around it; the track ends are left "
                            "out. A marker's name shows on hover.",
                            "the animal on its first well-seen frame")
    return ('<div class="top"><div>' + head + _warnings_html(r.summary) + _comparison_table(r.summary, r.style)
            + f"</div>{picture}</div>"
            + r.figures.add(data_map, "Where the data are, per marker and frame: seen by two or more cameras (green), "
                            "by one (orange) or none (red) inside the marker's track, and the track ends before its "
                            "first and after its last frame seen twice (grey), where every method extrapolates. "
                            "trajectories.csv has the same as its status and span columns; C3D/TRC exports leave the "
                            "track ends out by default." + _ends_note(r.summary), "where the data are"))


PAPER_REFERENCE = ("M. J. Bender, H. G. McClelland, G. Bledt, A. Kurdila, T. Furukawa and R. Müller: “Trajectory "
                   "Estimation of Bat Flight Using a Multi-View Camera System”, American Institute of Aeronautics "
                   "and Astronautics (AIAA) paper, Virginia Tech.")
"""The paper whose EKF and UKF batgraph implements and whose published figures the report shows."""


def _overview_section(r: _Report) -> str:
    """The session's facts, each method's run (runtime, what it estimates) and the rig."""
    s, frames = r.summary, r.frames
    noise = _get(s.pixel_noise, "cameras") or {}
    cam_rows = [[(html.escape(c.name), 'class="l"'), f"{c.size_wh[0]}×{c.size_wh[1]}",
                 _fmt(c.K[0, 0], 1), _fmt(np.linalg.norm(c.center_world), 2),
                 _fmt(_get(noise, c.name, "sigma_px"), 2), _fmt(_get(s.pixel_sigma_px, c.name), 2)]
                for c in r.session.rig]
    run_rows = []
    for m in r.methods:
        est, pts = _get(s.methods, m, "estimated") or {}, _get(s.methods, m, "points") or {}
        run_rows.append([(html.escape(m), f'class="l" style="color:{r.style[m][0]}"'),
                         _fmt(_get(s.methods, m, "runtime_s"), 2)]
                        + [f"{_fmt(est.get(g), 0)} / {_fmt(pts.get(g), 0)}" for g in HEADLINE_GROUPS])
    n_takes = int(evaluate.take_of(frames).max()) + 1 if len(frames) else 0
    return (
        f'<p>Session <b>{html.escape(str(r.session.name))}</b>: {len(r.session.rig)} cameras, {len(r.markers)} '
        f"markers, frames {frames[0]}–{frames[-1]} ({len(frames)} frames at {r.fps:g} fps, {len(frames) / r.fps:.2f} s"
        + (f", in {n_takes} takes solved on their own" if n_takes > 1 else "") + "). "
        f"Methods: {', '.join(html.escape(m) for m in r.methods)}. "
        + f"The EKF and UKF are those of {html.escape(PAPER_REFERENCE)} "
        + (f"This session is that paper's <b>{r.experiment}</b> experiment (declared by the session), so its "
           "published figures are shown beside batgraph's." if r.experiment else
           "Its published figures are not shown: the session does not declare itself one of the "
           "paper's scenes (session.toml <code>[paper] experiment = \"flight\"</code> or <code>\"ear\"</code>).")
        + "</p>"
        + _table([("method", 'class="l"'), "runtime [s]"] + [f"estimated: {html.escape(g)}"
                                                              for g in HEADLINE_GROUPS.values()], run_rows, "runs")
        + _table([("camera", 'class="l"'), "size [px]", "fx [px]", "distance to origin [m]",
                  "measured noise [px]", "noise used [px]"], cam_rows, "rig"))


def _trajectories_section(r: _Report) -> str:
    def paths():
        return _fig_trajectories(r.trajectories, r.plotted, r.style, r.frames, r.markers, r.session.skeleton,
                                 _points_cube(r.truth, r.frames, r.markers)) if r.plotted else None

    return r.figures.add(
        paths, "Every marker's path (colour and dash = marker) for each method, in the world frame [m], on common "
        "axes (1st–99th percentile of all estimates), equally scaled unless one range is under a quarter of "
        "the longest (then that axis is stretched). Blue segments: the skeleton at five evenly spaced "
        "frames (the paper's Fig. 5a draws the wing the same way). Thin black: truth, when known.",
        "3D trajectories per method")


def _ellipses_section(r: _Report) -> str:
    panel_cameras, panel_note = _panel_cameras(r.session.rig.names)

    def ellipses():
        drawn = r.reprojection[r.reprojection["camera"].isin(panel_cameras)]  # the others are not drawn
        if not len(drawn):
            return None
        rep_mm = evaluate.reprojection_in_mm(drawn, r.trajectories, r.session.rig)
        rng = np.random.default_rng(0)  # only for thinning the scatter; fixed so reports are reproducible
        return _fig_reprojection_ellipses(rep_mm, r.methods, r.style, panel_cameras, rng)

    return r.figures.add(
        ellipses, "Reprojection residual (û − u, v̂ − v) of every inlier observation, expressed in millimetres at "
        "the marker's depth in that camera (residual × depth / f). Ellipses: 95 % ellipse of each method's "
        "residuals (mean ± χ²₂ 95 % of their covariance); line styles and colours as everywhere in batgraph "
        "(EKF dashed and UKF solid as in the paper). Axes: v downward as in the image." + panel_note,
        "reprojection error ellipses per camera")


def _features_section(r: _Report) -> str:
    panel_cameras, panel_note = _panel_cameras(r.session.rig.names)

    def features():
        if not r.plotted:
            return None
        sel_idx = [r.markers.index(m) for m in r.selected]
        reproj_tracks = {}
        for m in r.plotted:
            cube = r.session.rig.to_user(_trajectory_cube(r.trajectories, m, r.frames, r.markers)[:, sel_idx])
            reproj_tracks[m] = {c.name: c.project(cube, distort=True) for c in r.session.rig
                                if c.name in panel_cameras}
        return _fig_reprojection_image(r.session, reproj_tracks, r.plotted, r.style, panel_cameras, r.selected,
                                       r.frames)

    return r.figures.add(
        features, f"Image features (open circles, colour = marker) of the markers {', '.join(r.selected)} and "
        "each method's 3D estimate projected back into the raw (distorted) image over every frame "
        "(lines, method style), so the lines also run through occlusion gaps. Pixels: OpenCV convention, "
        "v downward; each panel is zoomed to the features." + panel_note, "reprojections over image features")


def _coordinates_section(r: _Report) -> str:
    status_fm = None
    if "status" in r.trajectories and r.plotted:
        st = r.trajectories[r.trajectories["method"] == r.plotted[0]].drop_duplicates(["frame", "marker"])
        st = st.pivot(index="frame", columns="marker", values="status").reindex(r.frames)
        status_fm = {mk: st[mk].astype(str).to_numpy() if mk in st else np.full(len(r.frames), "")
                     for mk in r.selected}

    def coordinates():
        return _fig_coordinates(r.trajectories, r.plotted, r.style, r.frames, r.fps, r.selected, status_fm,
                                _points_cube(r.truth, r.frames, r.selected),
                                _points_cube(r.reference, r.frames, r.selected)) if r.plotted else None

    return r.figures.add(
        coordinates, "World x, y, z [m] of the selected markers for each method, with 95 % bands (± 1.96 σ per axis "
        f"from the marginal covariance). Shaded: frames where the marker was seen by one camera only "
        f"(orange) or by none (red), from the status column of {html.escape(r.plotted[0]) if r.plotted else '–'}."
        + (" Dotted black: truth." if r.truth is not None else "")
        + (" Purple dots: reference reconstruction." if r.reference is not None else ""),
        "marker coordinates over time")




def _camera_table_section(r: _Report) -> str:
    experiment = r.experiment
    return (
        '<p class="note">Per camera and method, over the inlier observations only (n): pixel statistics of '
        "|(û, v̂) − (u, v)| on the raw image, and the same error in millimetres at the marker's depth "
        "(err_px × depth / f × 1000, depth = z of the method's estimate in that camera). Observations the "
        "method flagged as outliers are counted, with their share, and left out of every figure."
        + (f" The last column is the paper's published figure for its {experiment} experiment"
           + (" (its camera 1 was the base of a pairwise calibration, hence its smaller error)"
              if experiment == "flight" else "") + "." if experiment else "")
        + "</p>" + _camera_table(r.summary, r.methods, r.session.rig.names, experiment)
        + ('<p class="note">The paper\'s published figures (Bender et al., cited under "Session and runs"):</p>'
           + _paper_table(experiment) if experiment else ""))


def _ms95(value_s, sd_s) -> str:
    """A time [s] and its standard deviation as "x.xx ± 1.96 sd" in ms; "—" when the check could not tell."""
    if value_s is None or sd_s is None or not np.isfinite(value_s) or not np.isfinite(sd_s):
        return "—"
    return f"{value_s * 1e3:+.2f} ± {1.96 * sd_s * 1e3:.2f}"


def _rig_section(summary: Summary) -> str | None:
    """The timing and poses the smoother estimated (--sync estimate, --refine-rig), and the timing self-check;
    None when the run has neither."""
    info = (summary.methods.get("smoother") or {}).get("info") or {}
    refined, poses = info.get("rig_refined"), (info.get("cleaning") or {}).get("poses")
    checked = (summary.checks or {}).get("timing")
    out = []
    if poses and poses["kept_as_given"]:
        out.append(f'<p class="note">The camera poses are kept as calibration.toml gives them: the markers do not '
                   f"show the rig moved (the move's chi-square {poses['chi2']:.1f} for {poses['dof']} degrees of "
                   f"freedom; log Bayes factor {poses['log_bayes_factor']:+.1f} for the poses as given).</p>")
    if refined:
        ms = lambda v, sd: f"{v * 1e3:.3f} ± {1.96 * sd * 1e3:.3f}" if sd else f"{v * 1e3:.3f}"  # noqa: E731
        rows = [[html.escape(cam),
                 ms(v["time_offset_s"], v["time_offset_sd_s"]) if "time_offset_s" in v else "—",
                 ms(v["readout_s"], v["readout_sd_s"]) if "readout_s" in v else "—",
                 f"{v['rotation_deg']:.3f} ± {1.96 * v['rotation_sd_deg']:.3f}" if "rotation_deg" in v else "—",
                 f"{v['translation_m'] * 1e3:.2f} ± {1.96 * v['translation_sd_m'] * 1e3:.2f}"
                 if "translation_m" in v else "—"] for cam, v in refined.items()]
        out.append('<p class="note">As the smoother estimated them with the trajectories, ± 95 % (1.96 standard '
                   "deviations): each camera's time offset (the first camera's clock is the session's) and "
                   "readout, and how far each pose moved from calibration.toml's. The rig is in rig.toml, for "
                   "--calibration on the recording's other trials.</p>"
                   + _table(["camera", "time offset [ms]", "readout [ms]", "rotation moved [deg]",
                             "translation moved [mm]"], rows))
    if checked:
        rows = [[html.escape(str(c["camera"])), _ms95(c.get("step_s"), c.get("step_sd_s")),
                 _ms95(c.get("readout_s"), c.get("readout_sd_s")),
                 "out of step" if c.get("flagged") else ("rolling shutter" if c.get("rolling") else "")]
                for c in checked]
        out.append('<p class="note">The timing self-check (no estimation): each camera\'s residuals regressed on '
                   "the markers' image velocity, against the median camera (its step) and growing with the image "
                   "row (a readout beyond calibration.toml's), ± 95 %. A camera named here warns: run with --sync "
                   "estimate.</p>" + _table(["camera", "step [ms]", "readout beyond stated [ms]", "named"], rows))
    return "\n".join(out) or None


def _truth_section(r: _Report) -> str:
    errors = evaluate.point_errors(r.trajectories[r.trajectories["method"].isin(r.plotted)], r.truth)
    return (
        '<p class="note">Each method\'s own estimates against truth.csv, per kind of point: seen by ≥ 2 '
        "cameras, gaps inside a track seen by one camera or none, and the track ends (before a marker's first "
        "and after its last frame seen twice: extrapolation); n = the points the method estimates, so the "
        "rows differ in n — the verdict's table compares the methods on the same points. Coverage: the "
        "fraction of truth points inside their estimate's 95 % ellipsoid (squared Mahalanobis distance "
        "≤ 7.815, χ²₃ 95 %): an honest covariance gives about 95 %.</p>"
        + _group_table(r.summary, r.plotted, "truth")
        + r.figures.add(lambda: _fig_truth(r.summary, errors, r.plotted, r.style, r.fps) if len(errors) else None,
                        "Left: RMSE per kind of point [mm, log]. Middle: 95 % coverage (dashed: the "
                        "nominal 0.95). Right: median over markers of the error on each frame [mm, log].",
                        "errors against truth"))


def _reference_section(r: _Report) -> str:
    ref_errors = evaluate.point_errors(r.trajectories[r.trajectories["method"].isin(r.plotted)], r.reference)
    return (
        '<p class="note">Distance between each method\'s estimate and the reference 3D points '
        "(reference_xyz.csv, e.g. DLTdv's xyzpts from an import) on the frames both have. Paper (ear "
        "data): EKF and UKF within 1 mm of stereo triangulation.</p>"
        + (_group_table(r.summary, r.plotted, "reference") if len(ref_errors)
           else '<p class="note">No common (frame, marker) pairs.</p>')
        + r.figures.add(lambda: _fig_reference(ref_errors, r.plotted, r.style, r.fps) if len(ref_errors) else None,
                        "Median over markers of the distance to the reference on each frame [mm, "
                        "log]; dashed: the paper's 1 mm.", "differences to the reference"))


def render_report(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame, summary: Summary) -> str:
    """The report as one HTML string: a section per part of the result, each title used once.

    session: :class:`batgraph.session.Session` (rig, fps, markers, skeleton, truth, reference).
    trajectories, reprojection: the result's tables, every method stacked. summary: the run's
    :class:`batgraph.summary.Summary`, whose figures are shown as they are (nothing is recomputed).
    """
    r = _prepare(session, trajectories, reprojection, summary)
    sections = [("verdict", "Verdict", _verdict_section(r)),
                ("overview", "Session and runs", _overview_section(r)),
                ("trajectories", "3D trajectories", _trajectories_section(r)),
                ("ellipses", "Residual ellipses in mm at depth (paper Fig. 5 b–f)", _ellipses_section(r)),
                ("features", "Reprojections over the 2D features (paper Fig. 6)", _features_section(r)),
                ("coordinates", "Marker coordinates over time", _coordinates_section(r)),
                ("table", "Reprojection error per camera and method", _camera_table_section(r))]
    if r.truth is not None and r.plotted:
        sections.append(("truth", "Errors against truth", _truth_section(r)))
    if r.reference is not None and r.plotted:
        sections.append(("reference", "Differences to the reference reconstruction", _reference_section(r)))
    rig = _rig_section(summary)
    if rig is not None:
        sections.append(("rig", "Cameras' timing and poses", rig))
    validation = _validation_section(summary)
    if validation is not None:
        sections.append(("validation", "Leave-one-camera-out validation", validation))
    association = _association_section(r)
    if association is not None:
        sections.append(("association", "Names from unlabelled detections", association))
    nav = " ".join(f'<a href="#{a}">{html.escape(t)}</a>' for a, t, _ in sections)
    body = "\n".join(f'<section id="{a}"><h2>{html.escape(t)}</h2>\n{b}\n</section>' for a, t, b in sections)
    title = f"batgraph report: {html.escape(str(session.name))}"
    return r.figures.fill(
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
        f"<style>{CSS}</style></head><body>\n<h1>{title}</h1>\n<nav>{nav}</nav>\n{body}\n"
        '<p class="note">Written by batgraph. Self-contained: every figure is embedded.</p></body></html>\n')


def write_report(path: str | Path, session, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                 summary: Summary) -> Path:
    """Render the report (see :func:`render_report`) and write it to ``path`` atomically. Returns the path."""
    path = Path(path)
    atomic.write_text(path, render_report(session, trajectories, reprojection, summary))
    return path
