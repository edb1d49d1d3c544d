"""Correspondence across cameras on one frame: which detections of different cameras are one marker.

Distortion is removed first (ideal pixels, with each detection's noise scaled by the undistortion's
Jacobian). Pairs of detections of two cameras whose Sampson distance to each other's epipolar line is within
the pixel noise's gate seed a 3D point (linear triangulation, batgraph.triangulate); the point is projected into
every other camera and the nearest detection within the gate is added; views whose reprojection error is beyond
the gate are dropped again. The candidate points are then chosen by a greedy global assignment (most views
first, then the smallest chi-square per degree of freedom; each detection used at most once). A point from two
views only is kept when neither of its detections could form another two-view point: two rays always meet
somewhere, so such ghosts are left to the tracker, which knows where each marker should be (batgraph.associate.tracks).
Nothing here looks at other frames.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from ..camera import Rig
from ..triangulate import dlt_pixels, normalised_cameras

CHI2_1DOF_GATE = 16.0  # Sampson distance^2 / sigma^2 (1 DOF): 4 sigma, room for a calibration's error
CHI2_2DOF_GATE = 16.0  # a view's reprojection error^2 / sigma^2 (2 DOF): p = 3e-4 for a true view
MAX_PARTNERS = 4  # cameras each camera is paired with to seed points in a large rig (every pair up to 8 cameras)


@dataclass
class Geometry:
    """A rig prepared for matching: ideal projection matrices P (C, 3, 4), fundamental matrices in ideal pixels
    ``F[(i, j)]`` (x_j^T F x_i = 0), the camera pairs that seed points, each image's area [px^2] and the normalised
    cameras the linear triangulation uses (batgraph.triangulate.normalised_cameras)."""

    rig: Rig
    P: np.ndarray
    F: dict
    pairs: list[tuple[int, int]]
    area_px2: np.ndarray
    cams: tuple[np.ndarray, np.ndarray, np.ndarray]


def geometry(rig: Rig, max_partners: int = MAX_PARTNERS) -> Geometry:
    """Every camera pair up to 2 * max_partners cameras; beyond, each camera with the max_partners cameras whose
    viewing directions make the angle nearest 90 degrees with its own (the best-conditioned triangulations),
    among those that look the same way (a positive dot product: they can share the volume). Also each image's
    area [px^2] (the sparsest clutter)."""
    C = len(rig)
    if C <= 2 * max_partners:
        pairs = [(i, j) for i in range(C) for j in range(i + 1, C)]
    else:
        z = np.stack([c.R[2] for c in rig])  # optical axes in the world
        cos = z @ z.T
        pairs = set()
        for i in range(C):
            score = np.where(cos[i] > -0.2, np.abs(cos[i]), np.inf)
            score[i] = np.inf
            for j in np.argsort(score)[:max_partners]:
                if np.isfinite(score[j]):
                    pairs.add((min(i, int(j)), max(i, int(j))))
        pairs = sorted(pairs)
    P = np.stack([c.P for c in rig])
    area = np.array([float(c.size_wh[0]) * c.size_wh[1] for c in rig])
    return Geometry(rig, P, {(i, j): rig.fundamental(i, j) for i, j in pairs}, pairs, area,
                    normalised_cameras(rig))


def undistort(rig: Rig, camera: np.ndarray, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw pixels (N, 2) of cameras (N,) -> (ideal pixels (N, 2), ideal px per raw px (N,)): the square root of
    the undistortion Jacobian's determinant, which scales a detection's noise onto ideal pixels."""
    ideal = np.full_like(uv_px, np.nan, dtype=float)
    scale = np.ones(len(uv_px))
    for c, cam in enumerate(rig):
        s = camera == c
        if s.any():
            ideal[s], J = cam.undistort_with_jacobian(uv_px[s])
            scale[s] = np.sqrt(np.abs(np.linalg.det(J)))
    return ideal, scale


def triangulate(geom: Geometry, uv: np.ndarray, views: np.ndarray) -> np.ndarray:
    """Linear triangulation of candidate points: views (P, C) local detection index per camera (-1: none), uv
    (n, 2) ideal pixels of the frame's detections. Returns xyz (P, 3) [m], NaN where fewer than 2 views."""
    C = views.shape[1]
    pix = np.full((C, len(views), 2), np.nan)
    for c in range(C):
        s = views[:, c] >= 0
        pix[c, s] = uv[views[s, c]]
    return dlt_pixels(geom.cams, pix)


def residuals(geom: Geometry, uv: np.ndarray, sig: np.ndarray, views: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Normalised squared reprojection errors (P, C) (error^2 / sigma^2 per view; NaN where no view, inf for a
    view behind its camera)."""
    out = np.full(views.shape, np.nan)
    for c in range(views.shape[1]):
        s = views[:, c] >= 0
        if not s.any():
            continue
        P = geom.P[c]
        h = xyz[s] @ P[:, :3].T + P[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            e = h[:, :2] / h[:, 2:3] - uv[views[s, c]]
            r2 = np.sum(e * e, axis=1) / sig[views[s, c]] ** 2
        out[s, c] = np.where(h[:, 2] > 0, r2, np.inf)
    return out


def project(geom: Geometry, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pixels (C, P, 2) and depths (C, P) [m] of points (P, 3) in every camera."""
    h = np.einsum("cij,pj->cpi", geom.P[:, :, :3], xyz) + geom.P[:, None, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[..., :2] / h[..., 2:3], h[..., 2]


def _epipolar_pairs(geom: Geometry, uv: np.ndarray, sig: np.ndarray, by_cam: list[np.ndarray]) -> np.ndarray:
    """Seed candidates (P, C): every pair of detections of two cameras within the epipolar gate."""
    C = len(by_cam)
    out = []
    for i, j in geom.pairs:
        A, B = by_cam[i], by_cam[j]
        if not len(A) or not len(B):
            continue
        F = geom.F[(i, j)]
        xa = np.column_stack([uv[A], np.ones(len(A))])
        xb = np.column_stack([uv[B], np.ones(len(B))])
        la, lb = xa @ F.T, xb @ F  # epipolar lines of a in image j, of b in image i
        num = xb @ la.T  # (nb, na): x_b^T F x_a
        den = (sig[B, None] ** 2 * (la[:, 0] ** 2 + la[:, 1] ** 2)[None]
               + sig[A][None] ** 2 * (lb[:, 0] ** 2 + lb[:, 1] ** 2)[:, None])
        bi, ai = np.nonzero(num * num <= CHI2_1DOF_GATE * den)
        v = np.full((len(ai), C), -1, np.int64)
        v[:, i], v[:, j] = A[ai], B[bi]
        out.append(v)
    return np.concatenate(out) if out else np.zeros((0, C), np.int64)


def _extend(geom: Geometry, uv: np.ndarray, sig: np.ndarray, by_cam: list[np.ndarray], trees: list,
            views: np.ndarray) -> np.ndarray:
    """Add to each candidate, in every camera it lacks, the detection nearest its projection within the gate."""
    xyz = triangulate(geom, uv, views)
    proj, depth = project(geom, xyz)
    for c, tree in enumerate(trees):
        lack = (views[:, c] < 0) & (depth[c] > 0) & np.isfinite(proj[c, :, 0])
        if tree is None or not lack.any():
            continue
        r = np.sqrt(CHI2_2DOF_GATE) * float(np.max(sig[by_cam[c]]))
        d, k = tree.query(proj[c, lack], distance_upper_bound=r)
        hit = np.isfinite(d)
        rows = np.flatnonzero(lack)[hit]
        views[rows, c] = by_cam[c][k[hit]]
    return views


def _drop_crowded(geom: Geometry, uv: np.ndarray, sig: np.ndarray, by_cam: list[np.ndarray], trees: list,
                  views: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Drop the views in which a second detection lies within the gate of the point's projection and not RATIO times
    farther than the first (plus one noise std): which of the two is the marker is decided later, with the marker's
    track (batgraph.associate.refine)."""
    proj, _ = project(geom, xyz)
    views = views.copy()
    for c, tree in enumerate(trees):
        have = views[:, c] >= 0
        if tree is None or not have.any() or len(by_cam[c]) < 2:
            continue
        r = np.sqrt(CHI2_2DOF_GATE) * float(np.max(sig[by_cam[c]]))
        d, _ = tree.query(proj[c, have], k=2, distance_upper_bound=r)
        crowded = np.isfinite(d[:, 1]) & (d[:, 1] < RATIO * d[:, 0] + float(np.median(sig[by_cam[c]])))
        views[np.flatnonzero(have)[crowded], c] = -1
    return views[(views >= 0).sum(axis=1) >= 2]


def _prune(geom: Geometry, uv: np.ndarray, sig: np.ndarray, llr0: np.ndarray, views: np.ndarray,
           rounds: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Drop, one per round, each candidate's worst view while it is beyond the gate or worth less than nothing
    (error^2 / 2 > its log likelihood ratio, :func:`view_llr`); candidates left with one view go. Returns
    (views, xyz, r2, kept): the candidates left, their points, errors and indices into ``views``."""
    kept = np.arange(len(views))
    xyz = triangulate(geom, uv, views)
    r2 = residuals(geom, uv, sig, views, xyz)
    for _ in range(rounds):
        worth = np.where(views >= 0, llr0[np.maximum(views, 0)] - 0.5 * np.nan_to_num(r2, nan=0.0), np.inf)
        worth = np.where(r2 > CHI2_2DOF_GATE, -np.inf, worth)
        worst = np.argmin(worth, axis=1)
        bad = worth[np.arange(len(views)), worst] < 0
        if not bad.any():
            break
        views[np.flatnonzero(bad), worst[bad]] = -1
        keep = (views >= 0).sum(axis=1) >= 2
        views, kept, xyz, r2, bad = views[keep], kept[keep], xyz[keep], r2[keep], bad[keep]
        if bad.any():  # only the candidates that lost a view move
            xyz[bad] = triangulate(geom, uv, views[bad])
            r2[bad] = residuals(geom, uv, sig, views[bad], xyz[bad])
    return views, xyz, r2, kept


def view_llr(uv: np.ndarray, sig: np.ndarray, by_cam: list[np.ndarray], trees: list, area_px2: np.ndarray
             ) -> np.ndarray:
    """Each detection's log likelihood ratio (n,) of being a marker's view at zero error against being clutter:
    ln(1 / (2 pi sigma^2 lambda)), lambda the density of detections around it [1/px^2] (three neighbours within
    the distance to its third nearest other detection; at least one per image). Where the image is crowded a
    view is worth less, and one far from its projection is worth nothing (:func:`_prune`)."""
    out = np.zeros(len(uv))
    for c, tree in enumerate(trees):
        b = by_cam[c]
        if tree is None:
            continue
        lam = np.full(len(b), 1.0 / area_px2[c])
        if len(b) >= 4:
            d, _ = tree.query(uv[b], k=4)
            lam = np.maximum(lam, 3.0 / (np.pi * np.maximum(d[:, 3], 1e-3) ** 2))
        out[b] = -np.log(2 * np.pi * sig[b] ** 2 * lam)
    return out


@dataclass
class FramePoints:
    """The 3D points of one frame: views (P, C) index of each view's detection (-1: none), xyz (P, 3) [m],
    score (P,) the sum of its views' log likelihood ratios less half their normalised squared errors; source (P,)
    the marker whose prediction found the point (:func:`projected_points`), or None."""

    views: np.ndarray
    xyz: np.ndarray
    score: np.ndarray
    source: np.ndarray | None = None

    @property
    def n_views(self) -> np.ndarray:
        return (self.views >= 0).sum(axis=1)


def candidates(geom: Geometry, uv: np.ndarray, sig: np.ndarray, camera: np.ndarray) -> tuple[FramePoints, np.ndarray]:
    """Every candidate point of one frame's detections (uv (n, 2) ideal px, sig (n,) ideal px, camera (n,)),
    duplicates removed, each with >= 2 views within the gate; and each detection's log likelihood ratio (n,)."""
    from scipy.spatial import cKDTree  # 50 ms to import: only associate needs it

    C = len(geom.rig)
    by_cam = [np.flatnonzero(camera == c) for c in range(C)]
    trees = [cKDTree(uv[b]) if len(b) else None for b in by_cam]
    llr0 = view_llr(uv, sig, by_cam, trees, geom.area_px2)
    views = _epipolar_pairs(geom, uv, sig, by_cam)
    if not len(views):
        return FramePoints(np.zeros((0, C), np.int64), np.zeros((0, 3)), np.zeros(0)), llr0
    views = _extend(geom, uv, sig, by_cam, trees, views)
    views, xyz, r2, _ = _prune(geom, uv, sig, llr0, views)
    views = _extend(geom, uv, sig, by_cam, trees, views)  # again from the better point
    views, xyz, r2, _ = _prune(geom, uv, sig, llr0, views)
    views = _drop_crowded(geom, uv, sig, by_cam, trees, views, xyz)
    views, xyz, r2, _ = _prune(geom, uv, sig, llr0, views)
    views, first = np.unique(views, axis=0, return_index=True)
    xyz, r2 = xyz[first], r2[first]
    ok = np.isfinite(xyz).all(axis=1) & ((views >= 0).sum(axis=1) >= 2)
    return FramePoints(views[ok], xyz[ok], _score(views[ok], r2[ok], llr0)), llr0


def _score(views: np.ndarray, r2: np.ndarray, llr0: np.ndarray) -> np.ndarray:
    return np.sum(np.where(views >= 0, llr0[np.maximum(views, 0)] - 0.5 * np.nan_to_num(r2, nan=0.0), 0.0), axis=1)


def select(geom: Geometry, uv: np.ndarray, sig: np.ndarray, llr0: np.ndarray, cands: FramePoints,
           min_views: int = 3) -> FramePoints:
    """Greedy global assignment of candidates with >= min_views views, the highest score first (the sum of its
    views' log likelihood ratios, :func:`view_llr`, less half their squared errors); each detection used once.
    A candidate that lost views to one chosen before it is scored again on the views it has left and goes back
    in the queue."""
    heap = [(-float(sc), k, cands.views[k]) for k, sc in enumerate(cands.score) if cands.n_views[k] >= min_views]
    heapq.heapify(heap)
    used = np.zeros(len(uv), bool)
    chosen, tie = [], len(cands.score)
    while heap:
        _, _, v = heapq.heappop(heap)
        have = v >= 0
        clash = have & used[np.maximum(v, 0)]
        if not clash.any():
            chosen.append(v)
            used[v[have]] = True
            continue
        v = np.where(clash, -1, v)
        if (v >= 0).sum() >= min_views:
            vv, xyz, r2, _ = _prune(geom, uv, sig, llr0, v[None].copy())
            if len(vv) and (vv >= 0).sum() >= min_views and np.isfinite(xyz).all():
                tie += 1
                heapq.heappush(heap, (-float(_score(vv, r2, llr0)[0]), tie, vv[0]))
    C = cands.views.shape[1]
    if not chosen:
        return FramePoints(np.zeros((0, C), np.int64), np.zeros((0, 3)), np.zeros(0))
    views = np.stack(chosen)
    xyz = triangulate(geom, uv, views)
    return FramePoints(views, xyz, _score(views, residuals(geom, uv, sig, views, xyz), llr0))


def free_pairs(cands: FramePoints, used: np.ndarray) -> FramePoints:
    """The two-view candidates on unused detections (they may share detections: two rays always meet somewhere,
    so which of them is a marker is for the tracker to say, from where its markers should be)."""
    two = cands.n_views == 2
    v = cands.views[two]
    free = ~(used[np.maximum(v, 0)] & (v >= 0)).any(axis=1)
    idx = np.flatnonzero(two)[free]
    return FramePoints(cands.views[idx], cands.xyz[idx], cands.score[idx])


RATIO = 1.5  # a projected marker's nearest detection must be this many times closer than its second nearest


def projected_points(geom: Geometry, uv: np.ndarray, sig: np.ndarray, camera: np.ndarray, xyz: np.ndarray,
                     std_m: np.ndarray) -> FramePoints:
    """Points from predicted markers instead of from epipolar pairs (for large rigs, where matching every camera
    pair costs too much): each prediction xyz (L, 3) [m] (std std_m (L,) [m]; NaN: none) is projected into every
    camera and takes the detection nearest its projection when it is within the gate, RATIO times nearer than the
    second nearest, and the projection nearest to it is this marker's (mutual); markers with two such views or
    more are triangulated and their views beyond the gate dropped. uv (n, 2), sig (n,), camera (n,): the frame's
    detections (ideal px). Returns one point per such marker, views as indices into uv, in marker order (the
    markers behind them are ``FramePoints.source``)."""
    from scipy.spatial import cKDTree  # 50 ms to import: only associate needs it

    C = len(geom.rig)
    have = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    views = np.full((len(have), C), -1, np.int64)
    proj, depth = project(geom, xyz[have])
    focal = np.array([c.K[0, 0] for c in geom.rig])
    for c in range(C):
        rc = np.flatnonzero(camera == c)
        ok = np.flatnonzero((depth[c] > 0) & np.isfinite(proj[c, :, 0]))
        if len(rc) < 1 or not len(ok):
            continue
        k = min(2, len(rc))
        d, j = cKDTree(uv[rc]).query(proj[c, ok], k=k)
        d, j = (d[:, None], j[:, None]) if k == 1 else (d, j)
        s_px = np.hypot(std_m[have[ok]] * focal[c] / depth[c, ok], sig[rc[j[:, 0]]])
        near = d[:, 0] <= np.sqrt(CHI2_2DOF_GATE) * s_px
        alone = (d[:, 1] >= RATIO * d[:, 0]) if k == 2 else np.ones(len(ok), bool)
        back = cKDTree(proj[c, ok]).query(uv[rc[j[:, 0]]])[1]  # the projection nearest to each chosen detection
        mutual = back == np.arange(len(ok))
        take = near & alone & mutual
        views[ok[take], c] = rc[j[take, 0]]
    two = (views >= 0).sum(axis=1) >= 2
    views, src = views[two], have[two]
    if not len(views):
        return FramePoints(np.zeros((0, C), np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
    v, x, r2, kept = _prune(geom, uv, sig, np.full(len(uv), 50.0), views.copy())
    return FramePoints(v, x, np.zeros(len(v)), src[kept])
