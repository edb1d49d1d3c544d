"""Every detection named by where the named markers are: each marker's 3D path from its named detections, carried
across the frames where it has fewer than two views, projected into every camera and matched to the detections.

Per frame and marker: the linear triangulation of its named detections (views more than the gate off dropped,
worst first); on a frame without one, the position interpolated from the nearest triangulated frames on both
sides (or extrapolated from one side, at most MAX_REACH frames), with a standard deviation that grows with the
distance in time (the marker's own acceleration, measured on its triangulated path). In each camera and frame the
projected markers and the detections are matched by the assignment of least cost (error^2 / (sigma_detection^2
+ sigma_projection^2) + 2 ln(sigma^2): an uncertain marker does not win a detection cheaply); a match is kept
when the best assignment without it costs at least ``margin`` more (its confidence is 1 / (1 + e^(-margin / 2))):
two markers on one merged blob, or a blob between two projections, stay unnamed. Two rounds: the names of the
first give the triangulations of the second.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .tracks import CHI2_2DOF_GATE, assign
from .views import Geometry, _prune, project, triangulate

MAX_REACH = 6  # frames a position is carried from its nearest triangulated frame
MIN_ACCEL = 5.0  # [m/s^2] the least acceleration a carried position allows for


@dataclass
class FrameIndex:
    """The detections of the frames, as arrays: frame (N,), camera (N,), ideal pixels uv (N, 2), their noise sig
    (N,) [ideal px], and each frame's rows ``start[f - first] .. start[f - first + 1]`` (sorted by frame)."""

    frame: np.ndarray
    camera: np.ndarray
    uv: np.ndarray
    sig: np.ndarray
    first: int
    start: np.ndarray

    def rows(self, f: int) -> np.ndarray:
        k = f - self.first
        return np.arange(self.start[k], self.start[k + 1])


def positions(geom: Geometry, fi: FrameIndex, label: np.ndarray, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's triangulated position per frame: xyz (F, L, 3) [m] and its std (F, L) [m], NaN where it has
    fewer than two consistent named views."""
    F = len(fi.start) - 1
    C = len(geom.rig)
    xyz = np.full((F, n_labels, 3), np.nan)
    std = np.full((F, n_labels), np.nan)
    for k in range(F):
        rows = fi.rows(fi.first + k)
        lab = label[rows]
        named = lab >= 0
        if named.sum() < 2:
            continue
        views = np.full((n_labels, C), -1, np.int64)
        views[lab[named], fi.camera[rows[named]]] = np.flatnonzero(named)
        have = np.flatnonzero((views >= 0).sum(axis=1) >= 2)
        if not len(have):
            continue
        llr = np.full(len(rows), 50.0)  # the views are named: only the gate drops one
        v, x, _, keep = _prune(geom, fi.uv[rows], fi.sig[rows], llr, views[have].copy())
        if not len(v):
            continue
        xyz[k, have[keep]] = x
        std[k, have[keep]] = _std(geom, fi, rows, v, x)
    return xyz, std


def _std(geom: Geometry, fi: FrameIndex, rows: np.ndarray, views: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """A point's position std [m]: the pixel noise over the views' pixels per metre, over sqrt(views - 1)."""
    proj, depth = project(geom, xyz)
    f = np.array([c.K[0, 0] for c in geom.rig])
    have = views >= 0
    m_per_px = np.where(have.T, depth / f[:, None], np.nan)  # (C, P)
    sig = np.where(have, fi.sig[rows][np.maximum(views, 0)], np.nan).T
    n = have.sum(axis=1)
    return np.nanmean(m_per_px * sig, axis=0) / np.sqrt(np.maximum(n - 1, 1))


def carry(xyz: np.ndarray, std: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions on the frames without a triangulation (see module docstring): (F, L, 3), (F, L) [m]."""
    F, L = std.shape
    out, out_std = xyz.copy(), std.copy()
    dt = 1.0 / fps
    for m in range(L):
        have = np.flatnonzero(np.isfinite(std[:, m]))
        if len(have) < 2:
            continue
        acc = _accel(xyz[have, m], have, dt)
        missing = np.flatnonzero(~np.isfinite(std[:, m]))
        if not len(missing):
            continue
        pos = np.searchsorted(have, missing)
        left = np.where(pos > 0, have[np.maximum(pos - 1, 0)], -10 ** 9)
        right = np.where(pos < len(have), have[np.minimum(pos, len(have) - 1)], 10 ** 9)
        dl, dr = missing - left, right - missing
        ok = np.minimum(dl, dr) <= MAX_REACH
        for j in np.flatnonzero(ok):
            near = have[np.argsort(np.abs(have - missing[j]))[:4]]
            deg = 2 if len(near) >= 3 and np.ptp(near) > 0 else 1
            t = (near - missing[j]) * dt
            coef = np.polyfit(t, xyz[near, m], deg)
            out[missing[j], m] = coef[-1]
            span = dl[j] * dr[j] if (dl[j] < 10 ** 8 and dr[j] < 10 ** 8) else 2 * min(dl[j], dr[j]) ** 2
            out_std[missing[j], m] = np.nanmean(std[near, m]) + 0.5 * acc * span * dt * dt
    return out, out_std


def _accel(x: np.ndarray, frames: np.ndarray, dt: float) -> float:
    """A marker's acceleration scale [m/s^2] from second differences of its consecutive triangulated frames (the
    90th percentile; at least MIN_ACCEL)."""
    run = (np.diff(frames[:-1]) == 1) & (np.diff(frames[1:]) == 1)
    if not run.any():
        return 50.0
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    a = np.linalg.norm(d2[run], axis=1) / dt ** 2
    return max(float(np.percentile(a, 90)), MIN_ACCEL)


def match(geom: Geometry, fi: FrameIndex, xyz: np.ndarray, std: np.ndarray, margin: float,
          fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each detection's marker (N,) (-1: none), its confidence (N,) and, for the unnamed ones, the best candidate
    (N,) (-1: none within the gate), by matching the projected markers in every camera and frame. ``fixed`` (N,)
    holds names that stay (the seed's; -1 elsewhere)."""
    N = len(fi.frame)
    label = fixed.copy()
    conf = np.where(fixed >= 0, 1.0, 0.0)
    cand = np.full(N, -1, np.int64)
    F, L = std.shape
    focal = np.array([c.K[0, 0] for c in geom.rig])
    for k in range(F):
        rows = fi.rows(fi.first + k)
        have = np.flatnonzero(np.isfinite(std[k]))
        if not len(rows) or not len(have):
            continue
        proj, depth = project(geom, xyz[k, have])  # (C, P, 2), (C, P)
        for c in np.unique(fi.camera[rows]):
            rc = rows[fi.camera[rows] == c]
            free_lab = ~np.isin(have, fixed[rc])
            rc = rc[fixed[rc] < 0]
            ok = (depth[c] > 0) & free_lab
            if not len(rc) or not ok.any():
                continue
            s_proj = std[k, have[ok]] * focal[c] / depth[c, ok]  # (P,) px
            d2 = np.sum((proj[c, ok][:, None] - fi.uv[rc][None]) ** 2, axis=-1)  # (P, n)
            s2 = s_proj[:, None] ** 2 + fi.sig[rc][None] ** 2
            m = d2 / s2
            cost = np.where(m < CHI2_2DOF_GATE, m + 2 * np.log(s2 / np.min(s2)), np.inf)
            r, d, mg = assign(cost, CHI2_2DOF_GATE + 2 * np.log(np.max(s2) / np.min(s2)), margin)
            best = np.where(np.isfinite(cost).any(axis=0), np.argmin(cost, axis=0), -1)
            cand[rc] = np.where(best >= 0, have[ok][np.maximum(best, 0)], -1)
            sure = mg >= margin
            label[rc[d[sure]]] = have[ok][r[sure]]
            conf[rc[d]] = 1.0 / (1.0 + np.exp(-np.minimum(mg, 50) / 2))
    return label, conf, cand
