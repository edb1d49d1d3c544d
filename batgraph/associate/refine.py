"""Every detection named by where the named markers are: each marker's 3D path from its named detections, carried
across the frames where it has fewer than two views, projected into every camera and matched to the detections.

Per frame and marker: the linear triangulation of its named detections (views more than the gate off dropped,
worst first); on a frame without one, the position interpolated from the nearest triangulated frames on both
sides (or extrapolated from one side, at most MAX_REACH frames), with a standard deviation that grows with the
distance in time (the marker's own acceleration, measured on its triangulated path). In each camera and frame the
projected markers and the detections are matched by the assignment of least cost (error^2 / (sigma_detection^2
+ sigma_projection^2) + 2 ln(sigma^2): an uncertain marker does not win a detection cheaply); a match is kept
when the best assignment without it costs at least ``margin`` more (its confidence is 1 / (1 + e^(-margin / 2))):
two markers on one merged blob, or a blob between two projections, stay unnamed. A camera's detections are matched
to where the marker's named views in the other cameras put it (where it has two others, :func:`leave_one_out`), so
that a neighbour's detection taken as the marker's does not vouch for itself. Two rounds: the names of the
first give the triangulations of the second.
"""

from __future__ import annotations

import numpy as np

from .assignment import assign, mahalanobis_within
from .tracks import CHI2_2DOF_GATE, PATCH_GAP, FrameDetections, jacobian, patch_shift, point_covariance
from .views import Geometry, _prune, project, triangulate

MAX_REACH = 6  # frames a position is carried from its nearest triangulated frame
POINT_SIGMA = 4.0
POINT_SLACK_M = 0.003
MIN_ACCEL = 5.0  # [m/s^2] the least acceleration a carried position allows for


def _named_views(fi: FrameDetections, label: np.ndarray, k: int, n_labels: int, C: int, least: int) -> tuple:
    """Frame k's detection rows and each marker's named view per camera, (L, C) indices into those rows (-1: none);
    the views None where the frame has fewer than ``least`` named detections."""
    rows = fi.rows(fi.first + k)
    lab = label[rows]
    named = lab >= 0
    if named.sum() < least:
        return rows, None
    views = np.full((n_labels, C), -1, np.int64)
    views[lab[named], fi.camera[rows[named]]] = np.flatnonzero(named)
    return rows, views


def positions(geom: Geometry, fi: FrameDetections, label: np.ndarray, n_labels: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each marker's triangulated position per frame: xyz (F, L, 3) [m] and its std (F, L) [m], NaN where it has
    fewer than two consistent named views; and the names (N,) less those of views dropped as beyond the gate."""
    F = len(fi.start) - 1
    C = len(geom.rig)
    xyz = np.full((F, n_labels, 3), np.nan)
    std = np.full((F, n_labels), np.nan)
    label = label.copy()
    for k in range(F):
        rows, views = _named_views(fi, label, k, n_labels, C, 2)
        if views is None:
            continue
        have = np.flatnonzero((views >= 0).sum(axis=1) >= 2)
        if not len(have):
            continue
        llr = np.full(len(rows), 50.0)  # the views are named: only the gate drops one
        v, x, _, keep = _prune(geom, fi.uv[rows], fi.sig[rows], llr, views[have].copy())
        before = views[have]
        after = np.full_like(before, -1)
        after[keep] = v
        dropped = before[(before >= 0) & (after < 0)]
        label[rows[dropped]] = -1
        if not len(v):
            continue
        xyz[k, have[keep]] = x
        std[k, have[keep]] = _std(geom, fi, rows, v, x)
    return xyz, std, label


def leave_one_out(geom: Geometry, fi: FrameDetections, label: np.ndarray, n_labels: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where each marker should appear in each camera by its other cameras' views: ideal pixels (F, L, C, 2) and
    their covariance (F, L, C, 2, 2) [px^2] (the first-order covariance of the point triangulated from the
    marker's named views in the other cameras, projected), NaN unless the marker has named views in that camera
    and two others. A detection is then matched to a position it did not pull towards itself: a neighbour's
    detection taken as the marker's does not vouch for itself."""
    F = len(fi.start) - 1
    C = len(geom.rig)
    uv = np.full((F, n_labels, C, 2), np.nan)
    cov = np.full((F, n_labels, C, 2, 2), np.nan)
    for k in range(F):
        rows, views = _named_views(fi, label, k, n_labels, C, 3)
        if views is None:
            continue
        m, c = np.nonzero((views >= 0) & ((views >= 0).sum(axis=1) >= 3)[:, None])
        if not len(m):
            continue
        v = views[m].copy()
        v[np.arange(len(m)), c] = -1
        x = triangulate(geom, fi.uv[rows], v)
        ok = np.isfinite(x).all(axis=1)
        m, c, v, x = m[ok], c[ok], v[ok], x[ok]
        P = point_covariance(geom, x, np.where(v >= 0, rows[np.maximum(v, 0)], -1), fi.sig)
        for cam in np.unique(c):
            s = c == cam
            h = x[s] @ geom.P[cam][:, :3].T + geom.P[cam][:, 3]
            J = jacobian(geom.P[cam], x[s])
            uv[k, m[s], cam] = h[:, :2] / h[:, 2:3]
            cov[k, m[s], cam] = J @ P[s] @ J.transpose(0, 2, 1)
    return uv, cov


def _std(geom: Geometry, fi: FrameDetections, rows: np.ndarray, views: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """A point's position std [m]: the pixel noise over the views' pixels per metre, over sqrt(views - 1)."""
    proj, depth = project(geom, xyz)
    f = np.array([c.K[0, 0] for c in geom.rig])
    have = views >= 0
    m_per_px = np.where(have.T, depth / f[:, None], np.nan)  # (C, P)
    sig = np.where(have, fi.sig[rows][np.maximum(views, 0)], np.nan).T
    n = have.sum(axis=1)
    return np.nanmean(m_per_px * sig, axis=0) / np.sqrt(np.maximum(n - 1, 1))


def carry(xyz: np.ndarray, std: np.ndarray, fps: float, noise_m: float = 0.0,
          patch: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Positions on the frames without a triangulation (see module docstring): (F, L, 3), (F, L) [m].

    Each marker's missing frame gets up to three estimates, combined by inverse variance: the local polynomial
    through its nearest triangulated frames (within MAX_REACH), and from its last triangulated frame before and
    its first after (within PATCH_GAP), that position moved as its neighbours triangulated on both frames moved
    (batgraph.associate.tracks.patch_shift: a wing's markers move together, so this bridges long gaps; not with
    ``patch`` False, for a large rig, where it costs as much as the tracking)."""
    F, L = std.shape
    out, out_std = xyz.copy(), std.copy()
    dt = 1.0 / fps
    seen = np.isfinite(std)
    for m in range(L):
        have = np.flatnonzero(seen[:, m])
        missing = np.flatnonzero(~seen[:, m])
        if len(have) < 1 or not len(missing):
            continue
        acc = _accel(xyz[have, m], have, dt) if len(have) >= 3 else 50.0
        pos = np.searchsorted(have, missing)
        for j, k in enumerate(missing):
            est = []
            left = have[pos[j] - 1] if pos[j] > 0 else None
            right = have[pos[j]] if pos[j] < len(have) else None
            if len(have) >= 2 and min(abs(k - x) for x in (left, right) if x is not None) <= MAX_REACH:
                near = have[np.argsort(np.abs(have - k))[:4]]
                deg = 2 if len(near) >= 3 else 1
                coef = np.polyfit((near - k) * dt, xyz[near, m], deg)
                dl = k - left if left is not None else None
                dr = right - k if right is not None else None
                span = dl * dr if dl is not None and dr is not None else 2 * min(x for x in (dl, dr) if x) ** 2
                est.append((coef[-1], np.nanmean(std[near, m]) + 0.5 * acc * span * dt * dt))
            for anchor in (left, right) if patch else ():
                if anchor is not None and abs(k - anchor) <= PATCH_GAP:
                    shift = patch_shift(xyz, seen, m, anchor, k, noise_m)
                    if shift is not None:
                        est.append((xyz[anchor, m] + shift[0], float(np.hypot(shift[1], std[anchor, m]))))
            if est:
                w = np.array([1.0 / s_ ** 2 for _, s_ in est])
                out[k, m] = (w[:, None] * np.array([x for x, _ in est])).sum(axis=0) / w.sum()
                out_std[k, m] = 1.0 / np.sqrt(w.sum())
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


def match(geom: Geometry, fi: FrameDetections, xyz: np.ndarray, std: np.ndarray, margin: float,
          fixed: np.ndarray, det_xyz: np.ndarray, det_std: np.ndarray, noise_m: float = 0.0,
          others: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each detection's marker (N,) (-1: none), its confidence (N,) and, for the unnamed ones, the best candidate
    (N,) (-1: none within the gate), by matching the projected markers in every camera and frame. ``fixed`` (N,)
    holds names that stay (the seed's; -1 elsewhere). det_xyz (N, 3) [m], det_std (N,) [m]: the point of three
    views or more each detection is in (NaN: none); a marker may not take a detection whose point lies more than
    POINT_SIGMA combined stds from it (that detection is another marker's). others: where each marker should
    appear by its other cameras (:func:`leave_one_out`); where given, a camera's detections are matched to that
    instead of the projected position."""
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
            far = (np.linalg.norm(det_xyz[rc][None] - xyz[k, have[ok]][:, None], axis=-1)
                   > POINT_SIGMA * np.hypot(std[k, have[ok]][:, None], det_std[rc][None])
                   + max(POINT_SLACK_M, 2 * noise_m))
            m = d2 / s2
            if others is not None:
                lo = np.isfinite(others[0][k, have[ok], c, 0])
                if lo.any():
                    S = others[1][k, have[ok][lo], c][:, None] + np.eye(2) * fi.sig[rc][None, :, None, None] ** 2
                    m[lo] = mahalanobis_within(fi.uv[rc][None] - others[0][k, have[ok][lo], c][:, None], S,
                                               CHI2_2DOF_GATE, ~far[lo])
                    s2[lo] = np.sqrt(np.linalg.det(S))
            cost = np.where((m < CHI2_2DOF_GATE) & ~far, m + 2 * np.log(s2 / np.min(s2)), np.inf)
            r, d, mg = assign(cost, CHI2_2DOF_GATE + 2 * np.log(np.max(s2) / np.min(s2)), margin)
            best = np.where(np.isfinite(cost).any(axis=0), np.argmin(cost, axis=0), -1)
            cand[rc] = np.where(best >= 0, have[ok][np.maximum(best, 0)], -1)
            sure = mg >= margin
            label[rc[d[sure]]] = have[ok][r[sure]]
            conf[rc[d]] = 1.0 / (1.0 + np.exp(-np.minimum(mg, 50) / 2))
    return label, conf, cand


AMBIGUOUS_CHI2 = 9.21  # 99 % of chi-square with 2 DOF


def shared_views(geom: Geometry, fi: FrameDetections, label: np.ndarray, fixed: np.ndarray, n_labels: int
                 ) -> np.ndarray:
    """Which named detections (N,) bool another marker could as well have made: the detection lies within the 99 %
    gate (AMBIGUOUS_CHI2; the detection's noise and the projection's) of where another marker projects, one that
    is triangulated on that frame from its own named views and has no named detection in that camera (a marker
    hidden there whose projection falls on a visible one's blob; two markers' blobs merged into one). The seed's
    clicks (``fixed`` >= 0) never are."""
    xyz, std, _ = positions(geom, fi, label, n_labels)
    out = np.zeros(len(fi.frame), bool)
    focal = np.array([c.K[0, 0] for c in geom.rig])
    for k in range(std.shape[0]):
        rows = fi.rows(fi.first + k)
        named = rows[label[rows] >= 0]
        have = np.flatnonzero(np.isfinite(std[k]))
        if len(have) < 2 or not len(named):
            continue
        proj, depth = project(geom, xyz[k, have])
        for c in np.unique(fi.camera[named]):
            in_c = named[fi.camera[named] == c]
            test = in_c[fixed[in_c] < 0]
            other = (depth[c] > 0) & ~np.isin(have, label[in_c])  # no named detection in camera c (nor the own)
            if not len(test) or not other.any():
                continue
            s2 = fi.sig[test][:, None] ** 2 + (std[k, have[other]] * focal[c] / depth[c, other])[None] ** 2
            d2 = np.sum((fi.uv[test][:, None] - proj[c, other][None]) ** 2, axis=-1)
            out[test] = (d2 < AMBIGUOUS_CHI2 * s2).any(axis=1)
    return out
