"""3D tracks of anonymous markers: each frame's points (batgraph.associate.views) linked to the tracks of the frame
before, with a constant-velocity Kalman filter's prediction and covariance as the gate.

Per frame: every live track is predicted (batgraph.motion's constant-velocity F and Q); tracks and points are
linked by the assignment of least total Mahalanobis cost (scipy's linear_sum_assignment on each connected
group of gated pairs, with a track's miss and a point's birth costing half the gate each). A link is kept only
when the best assignment without it costs at least ``ambiguity`` more: otherwise the track ends and the point
starts a new one (a split, for the labels to bridge: batgraph.associate.labelling), rather than risk a swap.
A track without a point looks for detections that no point used along its predicted rays: in each camera the
free detections and such tracks are assigned by the same rule on projected Mahalanobis costs; two views or more
are triangulated, one view updates the filter through its ray. A track that finds nothing coasts, and ends
after ``max_miss`` frames or when its position's standard deviation passes ``max_std_m``.
Each track's acceleration noise adapts to its own innovations (slow body markers get tight gates, wing tips
loose ones). Knows nothing of marker names.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..motion import constant_velocity_F, constant_velocity_Q
from .views import FramePoints, Geometry, triangulate

CHI2_3DOF_GATE = 16.27  # 99.9 % of chi-square with 3 DOF: a point's distance to its track's prediction
CHI2_2DOF_GATE = 13.82  # 99.9 % with 2 DOF: a detection's distance to a track's projected prediction
BIG = 1e9


@dataclass
class TrackOptions:
    """accel_psd_m2_s3: the constant-velocity model's starting acceleration noise q [m^2/s^3] (each track then
    adapts its own, within [q_min, q_max]); speed_mps: the std of a new track's velocity [m/s]; ambiguity: the
    least extra cost (chi-square units, -2 log likelihood ratio) of the next-best assignment for a link to be
    kept; max_miss: frames a track coasts without any detection; max_std_m: the largest position std a coasting
    track may reach."""

    accel_psd_m2_s3: float = 50.0
    q_min: float = 1.0
    q_max: float = 1e5
    speed_mps: float = 3.0
    ambiguity: float = 9.0
    max_miss: int = 10
    max_std_m: float = 0.03


@dataclass
class Tracklets:
    """Every track's points, one row per (track, frame), sorted by track then frame: track (E,), frame (E,),
    state (E, 6) the filtered position [m] and velocity [m/s], cov (E, 6, 6) its covariance, views (E, C) global
    detection index per camera (-1: none), kind (E,) 0 = a point of the frame, 1 = detections joined along the
    predicted rays, 2 = coasting (no detection; only between two frames with detections)."""

    track: np.ndarray
    frame: np.ndarray
    state: np.ndarray
    cov: np.ndarray
    views: np.ndarray
    kind: np.ndarray

    @property
    def xyz(self) -> np.ndarray:
        return self.state[:, :3]


class _Live:
    """The live tracks' filter states as arrays (T, ...): state x (6,), covariance P (6, 6), q, NIS average,
    frames missed, track id."""

    def __init__(self):
        self.x = np.zeros((0, 6))
        self.P = np.zeros((0, 6, 6))
        self.q = np.zeros(0)
        self.nis = np.zeros(0)
        self.miss = np.zeros(0, np.int64)
        self.id = np.zeros(0, np.int64)
        self.age = np.zeros(0, np.int64)

    def keep(self, mask: np.ndarray) -> None:
        for k in ("x", "P", "q", "nis", "miss", "id", "age"):
            setattr(self, k, getattr(self, k)[mask])

    def add(self, x, P, q, ids) -> None:
        self.x = np.concatenate([self.x, x])
        self.P = np.concatenate([self.P, P])
        self.q = np.concatenate([self.q, q])
        self.nis = np.concatenate([self.nis, np.full(len(x), 3.0)])
        self.miss = np.concatenate([self.miss, np.zeros(len(x), np.int64)])
        self.id = np.concatenate([self.id, ids])
        self.age = np.concatenate([self.age, np.zeros(len(x), np.int64)])


def point_covariance(geom: Geometry, xyz: np.ndarray, views: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """First-order covariance (P, 3, 3) [m^2] of triangulated points: (sum_c J_c^T J_c / sigma_c^2)^-1 over each
    point's views (J_c the ideal-pixel Jacobian, sigma_c its detection's ideal-pixel noise)."""
    info = np.zeros((len(xyz), 3, 3))
    for c in range(views.shape[1]):
        s = views[:, c] >= 0
        if s.any():
            J = _jacobian(geom.P[c], xyz[s])
            info[s] += np.einsum("nji,njk->nik", J, J) / sig[views[s, c]][:, None, None] ** 2
    info += np.eye(3) * 1e-6 * np.trace(info, axis1=1, axis2=2)[:, None, None]  # two near-parallel rays
    return np.linalg.inv(info)


def _jacobian(P: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """d(ideal px)/d(xyz) (n, 2, 3) of one camera P (3, 4) at points (n, 3)."""
    h = xyz @ P[:, :3].T + P[:, 3]
    uv = h[:, :2] / h[:, 2:3]
    return (P[None, :2, :3] - uv[:, :, None] * P[None, 2:3, :3]) / h[:, 2, None, None]


def _components(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int) -> np.ndarray:
    """Connected component label of every row node then every column node of a bipartite graph of edges."""
    n = n_rows + n_cols
    g = coo_matrix((np.ones(len(rows)), (rows, n_rows + cols)), shape=(n, n))
    return connected_components(g, directed=False)[1]


def assign(cost: np.ndarray, gate: float, ambiguity: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-cost links of rows to columns (cost (R, K), inf beyond the gate; leaving a row or a column out costs
    gate / 2 each). Returns (rows, cols, margin): the links and, for each, how much more the best assignment
    without it costs (:func:`_margin`; inf where nothing else competes). Solved per connected group of gated
    pairs."""
    R, K = cost.shape
    r_idx, c_idx = np.nonzero(np.isfinite(cost))
    if not len(r_idx):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    comp = _components(r_idx, c_idx, R, K)
    out_r, out_c, out_m = [], [], []
    for g in np.unique(comp[r_idx]):
        rows = np.flatnonzero(comp[:R] == g)
        cols = np.flatnonzero(comp[R:] == g)
        sub = cost[np.ix_(rows, cols)]
        if sub.shape == (1, 1):
            out_r.append(rows[0])
            out_c.append(cols[0])
            out_m.append(np.inf)
            continue
        links, total = _solve(sub, gate)
        for a, b in links:
            out_r.append(rows[a])
            out_c.append(cols[b])
            out_m.append(_margin(sub, gate, a, b, total) if ambiguity > 0 else np.inf)
    return np.asarray(out_r, np.int64), np.asarray(out_c, np.int64), np.asarray(out_m)


def _margin(sub: np.ndarray, gate: float, a: int, b: int, total: float) -> float:
    """How much more the best assignment without the link (a, b) costs, when in it row a or column b links to
    something else (inf when both are simply left out: then nothing competes for them)."""
    forbidden = sub.copy()
    forbidden[a, b] = np.inf
    links, alt = _solve(forbidden, gate)
    if not any(x == a or y == b for x, y in links):
        return np.inf
    return alt - total


def _solve(sub: np.ndarray, gate: float) -> tuple[list[tuple[int, int]], float]:
    """Least-cost assignment with a miss / birth of cost gate / 2 for each row / column left out."""
    R, K = sub.shape
    full = np.full((R + K, K + R), BIG)
    full[:R, :K] = np.where(np.isfinite(sub), sub, BIG)
    full[np.arange(R), K + np.arange(R)] = gate / 2
    full[R + np.arange(K), np.arange(K)] = gate / 2
    full[R:, K:] = 0.0
    r, c = linear_sum_assignment(full)
    links = [(int(a), int(b)) for a, b in zip(r, c, strict=True) if a < R and b < K]
    return links, float(full[r, c].sum())


def mahalanobis(diff: np.ndarray, S: np.ndarray) -> np.ndarray:
    """diff^T S^-1 diff for diff (..., d) and S (..., d, d)."""
    return np.einsum("...i,...i->...", diff, np.linalg.solve(S, diff[..., None])[..., 0])


@dataclass
class FrameDetections:
    """The detections the tracker may join along rays: ideal pixels uv (N, 2), their ideal-pixel noise sig (N,),
    camera (N,), and each frame's rows: frame f holds rows start[f - first] .. start[f - first + 1]."""

    uv: np.ndarray
    sig: np.ndarray
    camera: np.ndarray
    first: int
    start: np.ndarray

    def rows(self, f: int) -> np.ndarray:
        k = f - self.first
        if k < 0 or k + 1 >= len(self.start):
            return np.zeros(0, np.int64)
        return np.arange(self.start[k], self.start[k + 1])


class _Recorder:
    """Collects track rows frame by frame; :meth:`done` drops each track's trailing coasting rows."""

    def __init__(self, n_cams: int):
        self.parts = []
        self.C = n_cams

    def add(self, ids, f, x, P, views, kind) -> None:
        if len(ids):
            self.parts.append((np.asarray(ids, np.int64), np.full(len(ids), f, np.int64), x.copy(), P.copy(),
                               views, np.full(len(ids), kind, np.int64)))

    def done(self) -> Tracklets:
        if not self.parts:
            z = np.zeros(0, np.int64)
            return Tracklets(z, z, np.zeros((0, 6)), np.zeros((0, 6, 6)), np.zeros((0, self.C), np.int64), z)
        cols = [np.concatenate([p[i] for p in self.parts]) for i in range(6)]
        order = np.lexsort((cols[1], cols[0]))
        track, frame, state, cov, views, kind = (c[order] for c in cols)
        # the last row with detections of each track: rows after it (coasting to the track's end) are dropped
        seen = np.where(kind < 2, np.arange(len(kind)), -1)
        ends = np.r_[np.flatnonzero(np.diff(track)), len(track) - 1]
        last_seen = np.maximum.reduceat(seen, np.r_[0, ends[:-1] + 1])
        keep = np.arange(len(kind)) <= np.repeat(last_seen, np.diff(np.r_[-1, ends]))
        return Tracklets(track[keep], frame[keep], state[keep], cov[keep], views[keep], kind[keep])


def track(geom: Geometry, points: dict[int, FramePoints], dets: FrameDetections, frames: np.ndarray, fps: float,
          opt: TrackOptions) -> Tracklets:
    """Tracks through ``frames`` (sorted) of the points (views holding global detection indices) and the free
    detections (see module docstring)."""
    C = len(geom.rig)
    dt = 1.0 / fps
    F = constant_velocity_F(dt)
    Q1 = constant_velocity_Q(1.0, dt)
    live, rec, next_id = _Live(), _Recorder(C), 0
    prev, prev_xyz = None, np.zeros((0, 3))
    for f in frames:
        f = int(f)
        if prev is not None and f != prev + 1:  # a gap in the frame axis: every track ends
            live.keep(np.zeros(len(live.id), bool))
        prev = f
        before = (live.x[:, :3].copy(), live.P[:, :3, :3].copy())
        live.x = live.x @ F.T
        live.P = F @ live.P @ F.T + live.q[:, None, None] * Q1
        pts = points.get(f)
        T = len(live.id)
        births, linked, ended = np.zeros(0, np.int64), np.zeros(T, bool), np.zeros(T, bool)
        used = np.zeros(0, np.int64)
        Rz = np.zeros((0, 3, 3))
        flow = None
        if pts is not None and len(pts.xyz):
            flow = bulk_velocity(prev_xyz, pts.xyz, dt)
            prev_xyz = pts.xyz
            Rz = point_covariance(geom, pts.xyz, pts.views, dets.sig)
            births, linked, ended = _link(live, pts, Rz, opt, rec, f, before, dt)
            used = pts.views[pts.views >= 0]
        joined = _join(geom, live, ~linked & ~ended, dets, f, used, opt, rec)
        coasting = ~linked & ~joined & ~ended
        live.miss = np.where(coasting, live.miss + 1, 0)
        rec.add(live.id[coasting], f, live.x[coasting], live.P[coasting],
                np.full((int(coasting.sum()), C), -1, np.int64), 2)
        std = np.sqrt(np.max(np.linalg.eigvalsh(live.P[:, :3, :3]), axis=1)) if T else np.zeros(0)
        live.keep(~ended & (live.miss <= opt.max_miss) & (std <= opt.max_std_m))
        if len(births):
            next_id = _birth(live, pts, Rz, births, opt, rec, f, next_id, flow)
    return rec.done()


def _update(live: _Live, sel: np.ndarray, z: np.ndarray, Rz: np.ndarray, nis: np.ndarray) -> None:
    """Kalman update of the live tracks ``sel`` with 3D points z (n, 3), covariances Rz (n, 3, 3), and the
    adaptation of their q to the normalised innovation nis (n,) (3 expected)."""
    P = live.P[sel]
    S = P[:, :3, :3] + Rz
    K = np.linalg.solve(S, P[:, :3, :]).transpose(0, 2, 1)  # P H^T S^-1, H = [I 0] (S symmetric)
    live.x[sel] = live.x[sel] + np.einsum("nij,nj->ni", K, z - live.x[sel, :3])
    live.P[sel] = P - K @ P[:, :3, :]
    live.age[sel] += 1
    _adapt(live, sel, nis, 3.0)


def _adapt(live: _Live, sel: np.ndarray, nis: np.ndarray, dof: float) -> None:
    live.nis[sel] = 0.7 * live.nis[sel] + 0.3 * nis / dof * 3.0
    live.q[sel] = live.q[sel] * np.clip(np.sqrt(live.nis[sel] / 3.0), 0.7, 1.5)


def _link(live: _Live, pts: FramePoints, Rz: np.ndarray, opt: TrackOptions, rec: _Recorder, f: int,
          before: tuple[np.ndarray, np.ndarray], dt: float):
    """Link the frame's points to live tracks; returns (points left for births (n,), linked (T,), ended (T,)).

    In rounds. The first links only the tracks whose velocity rests on MATURE points or more (a young track's
    wide gate would make every link near it look ambiguous). Each later round moves the predictions of the
    tracks still unlinked by what their linked neighbours did (:func:`_coherent`: a wing's markers share most
    of their motion) and assigns the rest again. A track still ambiguous when nothing more links ends.
    before: the live tracks' positions (T, 3) [m] and their covariances (T, 3, 3) on the frame before.
    """
    T, n = len(live.id), len(pts.xyz)
    linked, ambiguous = np.zeros(T, bool), np.zeros(T, bool)
    free = np.ones(n, bool)
    if T == 0:
        return np.arange(n), linked, ambiguous
    x0, P0 = live.x.copy(), live.P.copy()
    moved = np.zeros((T, 3))  # a linked track's point less its position on the frame before
    resid = np.zeros((T, 3))  # ... less its prediction
    for rnd in range(COHERENT_ROUNDS):
        tr, pi = np.flatnonzero(~linked), np.flatnonzero(free)
        if rnd == 0:
            tr = tr[live.age[tr] >= MATURE]
        else:
            _coherent(live, tr, linked, resid, moved, x0, P0, before, dt)
        if not len(tr) or not len(pi):
            continue
        d = pts.xyz[pi][None] - live.x[tr][:, None, :3]
        m = mahalanobis(d, live.P[tr][:, None, :3, :3] + Rz[pi][None])
        rows, cols, margin = assign(np.where(m < CHI2_3DOF_GATE, m, np.inf), CHI2_3DOF_GATE, opt.ambiguity)
        sure = margin >= opt.ambiguity
        ambiguous[tr] = False
        ambiguous[tr[rows[~sure]]] = True
        r, c = tr[rows[sure]], pi[cols[sure]]
        if not len(r) and rnd > 0:
            break
        resid[r] = pts.xyz[c] - x0[r, :3]
        moved[r] = pts.xyz[c] - before[0][r]
        _update(live, r, pts.xyz[c], Rz[c], m[rows[sure], cols[sure]])
        linked[r] = True
        free[c] = False
        rec.add(live.id[r], f, live.x[r], live.P[r], pts.views[c], 0)
    return np.flatnonzero(free), linked, ambiguous & ~linked


COHERENT_ROUNDS = 5
COHERENT_M = 0.04  # [m] the reach of a linked track's motion over its neighbours' predictions
MATURE = 2  # points after which a track's velocity is its own


def _coherent(live: _Live, tr: np.ndarray, linked: np.ndarray, resid: np.ndarray, moved: np.ndarray,
              x0: np.ndarray, P0: np.ndarray, before: tuple[np.ndarray, np.ndarray], dt: float) -> bool:
    """New predictions for the unlinked tracks ``tr`` from their linked neighbours (Gaussian weights of reach
    COHERENT_M): a mature track's prediction x0 (T, 6) moves by their mean innovation ``resid``, its position
    covariance shrinks to a quarter of P0's (T, 6, 6) plus the innovations' spread; a young track moves from its
    position on the frame before by their mean displacement ``moved``, which also becomes its velocity. Returns
    whether any track had linked neighbours."""
    lk = np.flatnonzero(linked)
    if not len(lk) or not len(tr):
        return False
    d2 = np.sum((x0[tr][:, None, :3] - x0[lk][None, :, :3]) ** 2, axis=-1)
    w = np.exp(-0.5 * d2 / COHERENT_M ** 2) * (d2 < (3 * COHERENT_M) ** 2)
    wsum = w.sum(axis=1)
    has = wsum > 1e-3
    if not has.any():
        return False
    t, w = tr[has], w[has] / wsum[has, None]
    mature = live.age[t] >= MATURE
    step = np.where(mature[:, None], w @ resid[lk], w @ moved[lk])
    dev = np.where(mature[:, None, None], resid[lk][None], moved[lk][None]) - step[:, None]
    spread = np.einsum("tk,tki,tkj->tij", w, dev, dev) + np.eye(3) * 1e-6
    tm, ty = t[mature], t[~mature]
    live.x[tm, :3] = x0[tm, :3] + step[mature]
    # the position block becomes A' = P0 / 4 + spread; P' = M P0 M^T with M = blockdiag(L' L^-1, I) keeps the
    # velocity's covariance and its correlation with the position consistent (positive definite)
    A = P0[tm, :3, :3]
    M = np.tile(np.eye(6), (len(tm), 1, 1))
    M[:, :3, :3] = np.linalg.cholesky(0.25 * A + spread[mature]) @ np.linalg.inv(np.linalg.cholesky(A))
    live.P[tm] = M @ P0[tm] @ M.transpose(0, 2, 1)
    live.x[ty, :3] = before[0][ty] + step[~mature]
    live.x[ty, 3:] = step[~mature] / dt
    A = spread[~mature] + before[1][ty]
    live.P[ty] = np.block([[A, A / dt], [A / dt, A / dt ** 2]]) + np.diag([0, 0, 0, 1, 1, 1]) * 1e-4
    return True


def _join(geom: Geometry, live: _Live, want: np.ndarray, dets: FrameDetections, f: int, used: np.ndarray,
          opt: TrackOptions, rec: _Recorder) -> np.ndarray:
    """Free detections joined to the tracks ``want`` (T,) along their predicted rays, camera by camera;
    returns the tracks that joined any (T,)."""
    T = len(live.id)
    joined = np.zeros(T, bool)
    rows = dets.rows(f)
    free = rows[~np.isin(rows, used)]
    tr = np.flatnonzero(want & (live.age >= 1))  # a track's velocity is known after its second point
    if not len(free) or not len(tr):
        return joined
    views = np.full((T, len(geom.rig)), -1, np.int64)
    for c in range(len(geom.rig)):
        fc = free[dets.camera[free] == c]
        if not len(fc):
            continue
        x = live.x[tr, :3]
        h = x @ geom.P[c][:, :3].T + geom.P[c][:, 3]
        front = h[:, 2] > 0
        if not front.any():
            continue
        t_in = tr[front]
        J = _jacobian(geom.P[c], live.x[t_in, :3])
        uv_hat = h[front, :2] / h[front, 2:3]
        S = J @ live.P[t_in, :3, :3] @ J.transpose(0, 2, 1)
        diff = dets.uv[fc][None] - uv_hat[:, None]
        Sfull = S[:, None] + np.eye(2) * dets.sig[fc][None, :, None, None] ** 2
        m = mahalanobis(diff, Sfull)
        cost = np.where(m < CHI2_2DOF_GATE, m, np.inf)
        r, k, margin = assign(cost, CHI2_2DOF_GATE, opt.ambiguity)
        sure = margin >= opt.ambiguity
        views[t_in[r[sure]], c] = fc[k[sure]]
    got = np.flatnonzero((views >= 0).any(axis=1))
    for t in got:  # one 2D update per view, each along the ray at the current estimate
        for c in np.flatnonzero(views[t] >= 0):
            _update_2d(live, t, geom.P[c], dets.uv[views[t, c]], dets.sig[views[t, c]])
    joined[got] = True
    rec.add(live.id[got], f, live.x[got], live.P[got], views[got], 1)
    return joined


def _update_2d(live: _Live, t: int, P: np.ndarray, uv: np.ndarray, sig: float) -> None:
    """Extended Kalman update of track t with one ideal-pixel detection uv (2,) of noise sig [px]."""
    x, Pt = live.x[t], live.P[t]
    J = _jacobian(P, x[None, :3])[0]  # (2, 3)
    h = P[:, :3] @ x[:3] + P[:, 3]
    H = np.zeros((2, 6))
    H[:, :3] = J
    S = H @ Pt @ H.T + sig * sig * np.eye(2)
    K = Pt @ H.T @ np.linalg.inv(S)
    innov = uv - h[:2] / h[2]
    live.x[t] = x + K @ innov
    live.P[t] = Pt - K @ H @ Pt
    nis = float(innov @ np.linalg.solve(S, innov))
    _adapt(live, np.array([t]), np.array([nis]), 2.0)


def bulk_velocity(a: np.ndarray, b: np.ndarray, dt: float, radius_m: float = 0.01) -> np.ndarray | None:
    """The displacement most pairs of points a (n, 3) -> b (k, 3) share, per second [m/s] (the body's motion,
    which a new track takes as its velocity when no live track is near it); None when fewer than 3 agree."""
    if len(a) < 3 or len(b) < 3:
        return None
    D = (b[None] - a[:, None]).reshape(-1, 3)
    counts = np.array([len(x) for x in cKDTree(D).query_ball_point(D, radius_m)])
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None
    inl = np.linalg.norm(D - D[best], axis=1) <= radius_m
    return D[inl].mean(axis=0) / dt


def _birth(live: _Live, pts: FramePoints, Rz: np.ndarray, births: np.ndarray, opt: TrackOptions, rec: _Recorder,
           f: int, next_id: int, flow: np.ndarray | None) -> int:
    """New tracks from the points ``births``: velocity and q from the live tracks within 5 cm, if any, else the
    bulk ``flow`` [m/s] (with half the speed's std about it)."""
    n = len(births)
    z = pts.xyz[births]
    v0 = np.zeros((n, 3)) if flow is None else np.tile(flow, (n, 1))
    sv = np.full(n, opt.speed_mps if flow is None else 0.5 * opt.speed_mps)
    q = np.full(n, opt.accel_psd_m2_s3)
    if len(live.id):
        near = np.linalg.norm(z[:, None] - live.x[None, :, :3], axis=-1) < NEIGHBOUR_M  # (n, T)
        for i in np.flatnonzero(near.any(axis=1)):
            vel = live.x[near[i], 3:]
            v0[i] = vel.mean(axis=0)
            sv[i] = max(float(np.sqrt(np.mean(np.var(vel, axis=0)))) + 0.3 * opt.speed_mps, 0.1)
            q[i] = float(np.median(live.q[near[i]]))
    P = np.zeros((n, 6, 6))
    P[:, :3, :3] = Rz[births]
    P[:, 3:, 3:] = sv[:, None, None] ** 2 * np.eye(3)
    ids = next_id + np.arange(n)
    live.add(np.concatenate([z, v0], axis=1), P, q, ids)
    rec.add(ids, f, live.x[-n:], live.P[-n:], pts.views[births], 0)
    return next_id + n


NEIGHBOUR_M = 0.05  # live tracks this close to a new point lend it their velocity
