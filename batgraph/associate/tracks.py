"""Every marker the seed names, tracked in 3D frame by frame away from the seed frame (forward, then backward):
each frame's points (batgraph.associate.views) are assigned to the markers by motion, neighbours and segments.

A marker's state is a constant-velocity Kalman filter (batgraph.motion's F and Q) whose acceleration noise adapts
to its own innovations. On each frame, in rounds, as the joint assignment of greatest total log likelihood ratio
against clutter (batgraph.associate.assignment): first the markers tracked up to the frame before, by motion
alone; then, repeatedly, the rest, predicted from their neighbours (:func:`_coherent`, :func:`patch_shift`: a
wing's markers move together) and their segments to the partners placed so far (batgraph.associate.segments).
A link is kept when the next-best assignment is worse by ``ambiguity`` nats and its own evidence is ``min_llr`` or
more; else the marker stays unassigned on that frame (its track splits) rather than risk a swap. A marker without a
point takes lone detections along its predicted rays where that prediction is sharp (``join_max_px``); one that
finds nothing coasts, and is lost after ``max_miss`` frames or past ``max_std_m``. In large rigs the points come
from the markers' predictions (views.projected_points) and go to the marker that found them. Markers already named
on a frame (:class:`Anchors`, batgraph.associate.gaps) take their positions there as sure links before the rounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..motion import constant_velocity_F, constant_velocity_Q
from . import segments as seg_mod
from .assignment import assign, mahalanobis, mahalanobis_within
from .views import FramePoints, Geometry

CHI2_3DOF_GATE = 16.27  # 99.9 % of chi-square with 3 DOF: a point's distance to a marker's prediction
CHI2_2DOF_GATE = 13.82  # 99.9 % with 2 DOF: a detection's distance to a marker's projected prediction
FIRST_ROUND_CHI2 = 9.35  # 97.5 % with 3 DOF: the first round (motion alone) takes only points near the prediction
MIN_EXTENT_M = 0.1  # the smallest side of the marker set's box (:func:`extent`)
LINK_GATE = 60.0  # [nats] an assignment's cost is LINK_GATE - log likelihood ratio; unassigned costs half each
ROUNDS = 6
MATURE = 2  # points after which a marker's velocity is its own
REFERENCE_FPS = 120.0  # [Hz] the rate TrackOptions.q_min is set for (a bat rig's)
COHERENT_M = 0.04  # [m] the reach of an assigned marker's motion over its neighbours' predictions
RESEGMENT_FRAMES = 15  # segment lengths are measured again after this many frames
DOUBT_BELOW = 0.99  # an assignment less sure than this does not carry a name by continuity (a suspected switch)


@dataclass
class TrackOptions:
    """accel_psd_m2_s3: the starting acceleration noise q [m^2/s^3] (each marker adapts its own within [q_min,
    q_max]; the association sets the start and q_min from the seed, :func:`start_noise`); speed_mps: a new
    marker's velocity std [m/s] (flow_std_mps when the body's motion is known, :func:`bulk_velocity`); ambiguity:
    the least margin [nats] over the next-best assignment; min_llr: the least evidence [nats] against clutter of a
    link; max_miss [frames], max_std_m [m]: when a coasting marker is lost;
    join_max_px: the largest projected std [px] of a prediction that may take a lone detection; acquire_llr: the
    segment evidence [nats] that places a marker without a prediction; learn: learn steady distances as segments;
    volume_m3, range_m: the marker set's box [m^3] and size [m] (clutter is uniform in them, :func:`extent`);
    noise_m: the points' position noise [m] (the floor of the predictions' and segments' stds); segment_lengths:
    {(a, b): length [m]} of the declared segments where the seed placed both markers."""

    accel_psd_m2_s3: float = 50.0
    q_min: float = 10.0  # at REFERENCE_FPS (:func:`start_noise`)
    q_max: float = 1e5
    speed_mps: float = 3.0
    flow_std_mps: float = 1.0
    ambiguity: float = 5.0
    min_llr: float = 2.0
    max_miss: int = 30
    max_std_m: float = 0.08
    join_max_px: float = 4.0
    acquire_llr: float = 8.0
    learn: bool = True
    volume_m3: float = 0.3 ** 3
    range_m: float = 0.3
    noise_m: float = 0.0
    segment_lengths: dict | None = None


@dataclass
class FrameDetections:
    """The detections by frame: ideal pixels uv (N, 2), their ideal-pixel noise sig (N,), camera (N,), frame (N,),
    and each frame's rows ``start[f - first] .. start[f - first + 1]`` (sorted by frame)."""

    frame: np.ndarray
    camera: np.ndarray
    uv: np.ndarray
    sig: np.ndarray
    first: int
    start: np.ndarray

    def rows(self, f: int) -> np.ndarray:
        k = f - self.first
        if k < 0 or k + 1 >= len(self.start):
            return np.zeros(0, np.int64)
        return np.arange(self.start[k], self.start[k + 1])

    @property
    def n_frames(self) -> int:
        return len(self.start) - 1


@dataclass
class Sweep:
    """What the tracker found per frame k (of the detections' frame axis) and marker: kind (F, L) 0 nothing, 1 a
    point, 2 detections joined along the rays; views (F, L, C) detection index per camera (-1: none); conf (F, L)
    the assignment's confidence 1 / (1 + e^-margin); xyz (F, L, 3) [m] the point (kind 1) or the filtered
    position (kind 2)."""

    kind: np.ndarray
    views: np.ndarray
    conf: np.ndarray
    xyz: np.ndarray

    @classmethod
    def empty(cls, F: int, L: int, C: int) -> Sweep:
        return cls(np.zeros((F, L), np.int8), np.full((F, L, C), -1, np.int64), np.zeros((F, L)),
                   np.full((F, L, 3), np.nan))


@dataclass
class Anchors:
    """Markers already named, which a sweep takes as they are: xyz (F, L, 3) [m] their positions (NaN: none) and
    views (F, L, C) their detections (global indices, -1: none)."""

    xyz: np.ndarray
    views: np.ndarray


@dataclass
class Seed:
    """Markers placed by the user on one frame: label (S,), xyz (S, 3) [m], views (S, C) their detections; velocity
    (S, 3) [m/s] and its std (S,) once measured (:func:`initial_velocity`)."""

    label: np.ndarray
    xyz: np.ndarray
    views: np.ndarray
    velocity: np.ndarray | None = None
    velocity_std: np.ndarray | None = None


class _Targets:
    """The markers' filter states (L, ...): x (6,), P (6, 6), q, NIS average, age (points and ray joins of its
    own since placed), miss, alive."""

    def __init__(self, L: int, opt: TrackOptions):
        self.x = np.zeros((L, 6))
        self.P = np.tile(np.eye(6), (L, 1, 1))
        self.q = np.full(L, opt.accel_psd_m2_s3)
        self.nis = np.full(L, 3.0)
        self.age = np.zeros(L, np.int64)
        self.miss = np.zeros(L, np.int64)
        self.alive = np.zeros(L, bool)
        self.last = np.full(L, -10 ** 9, np.int64)  # the frame index of each marker's last point
        self.opt = opt

    def place(self, lab: np.ndarray, xyz: np.ndarray, R: np.ndarray, v: np.ndarray, sv) -> None:
        """Start markers ``lab`` at points xyz (n, 3) with covariances R (n, 3, 3), velocity v (n, 3) of std sv
        [m/s] (one or (n,))."""
        self.x[lab] = np.concatenate([xyz, v], axis=1)
        P = np.zeros((len(lab), 6, 6))
        P[:, :3, :3] = R
        P[:, 3:, 3:] = np.eye(3) * (np.broadcast_to(np.asarray(sv, float), (len(lab),)) ** 2)[:, None, None]
        self.P[lab] = P
        self.age[lab], self.miss[lab], self.alive[lab] = 0, 0, True

    def update(self, lab: np.ndarray, z: np.ndarray, R: np.ndarray, x0: np.ndarray, P0: np.ndarray,
               adapt: np.ndarray | None = None) -> None:
        """Kalman update with 3D points z (n, 3), covariances R (n, 3, 3); q adapts (where ``adapt`` (n,), default
        everywhere) to the innovation against the constant-velocity prediction alone (x0 (n, 6), P0 (n, 6, 6)),
        not the one its neighbours corrected."""
        P = self.P[lab]
        S = P[:, :3, :3] + R
        r = z - self.x[lab, :3]
        K = np.linalg.solve(S, P[:, :3, :]).transpose(0, 2, 1)  # P H^T S^-1 with H = [I 0] (P, S symmetric)
        self.x[lab] = self.x[lab] + np.einsum("nij,nj->ni", K, r)
        self.P[lab] = P - K @ P[:, :3, :]
        a = np.ones(len(lab), bool) if adapt is None else adapt
        self._adapt(lab[a], mahalanobis(z[a] - x0[a, :3], P0[a, :3, :3] + R[a]), 3.0)
        self.miss[lab] = 0

    def update_ray(self, t: int, P: np.ndarray, uv: np.ndarray, sig: float) -> None:
        """Extended Kalman update of marker t with one ideal-pixel detection uv (2,) of noise sig [px]."""
        x, Pt = self.x[t], self.P[t]
        h = P[:, :3] @ x[:3] + P[:, 3]
        H = np.zeros((2, 6))
        H[:, :3] = jacobian(P, x[None, :3])[0]
        S = H @ Pt @ H.T + sig * sig * np.eye(2)
        K = Pt @ H.T @ np.linalg.inv(S)
        r = uv - h[:2] / h[2]
        self.x[t] = x + K @ r
        self.P[t] = Pt - K @ H @ Pt
        self._adapt(np.array([t]), np.array([float(r @ np.linalg.solve(S, r))]), 2.0)
        self.age[t] += 1

    def _adapt(self, lab: np.ndarray, nis: np.ndarray, dof: float) -> None:
        self.nis[lab] = 0.7 * self.nis[lab] + 0.3 * nis * 3.0 / dof
        self.q[lab] = np.clip(self.q[lab] * np.clip(np.sqrt(self.nis[lab] / 3.0), 0.7, 1.5), self.opt.q_min,
                              self.opt.q_max)
        self.miss[lab] = 0

    def pos_std(self) -> np.ndarray:
        return np.sqrt(np.max(np.linalg.eigvalsh(self.P[:, :3, :3]), axis=1))


def jacobian(P: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """d(ideal px)/d(xyz) (n, 2, 3) of one camera's projection matrix P (3, 4) at points (n, 3)."""
    h = xyz @ P[:, :3].T + P[:, 3]
    uv = h[:, :2] / h[:, 2:3]
    return (P[None, :2, :3] - uv[:, :, None] * P[None, 2:3, :3]) / h[:, 2, None, None]


def point_covariance(geom: Geometry, xyz: np.ndarray, views: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """First-order covariance (P, 3, 3) [m^2] of triangulated points: (sum_c J_c^T J_c / sigma_c^2)^-1 over each
    point's views (J_c the ideal-pixel Jacobian, sigma_c its detection's ideal-pixel noise)."""
    info = np.zeros((len(xyz), 3, 3))
    for c in range(views.shape[1]):
        s = views[:, c] >= 0
        if s.any():
            J = jacobian(geom.P[c], xyz[s])
            info[s] += np.einsum("nji,njk->nik", J, J) / sig[views[s, c]][:, None, None] ** 2
    info += np.eye(3) * 1e-6 * np.trace(info, axis1=1, axis2=2)[:, None, None]  # two near-parallel rays
    return np.linalg.inv(info)


INIT_GATE_M = 0.03  # [m] how far a seeded marker's point may be on the next frame from where the body's flow puts it
INIT_MIN_STD_MPS = 0.25  # [m/s] the least std of a seeded marker's first velocity


def seed_displacements(p: np.ndarray, z: np.ndarray, dt: float, flow: np.ndarray | None) -> np.ndarray:
    """Each seeded marker's displacement (S, 3) [m] to its point on the frame dt [s] away (points z (n, 3)), NaN
    where none: the seeded positions p (S, 3), moved by the body's ``flow`` [m/s], matched to the points (least
    total distance, within INIT_GATE_M)."""
    from scipy.optimize import linear_sum_assignment

    disp = np.full(p.shape, np.nan)
    if not len(z):
        return disp
    base = p + (0.0 if flow is None else flow * dt)
    d = np.linalg.norm(z[None] - base[:, None], axis=-1)
    r, c = linear_sum_assignment(np.where(d < INIT_GATE_M, d, 1e3))
    ok = d[r, c] < INIT_GATE_M
    disp[r[ok]] = z[c[ok]] - p[r[ok]]
    return disp


def initial_velocity(p: np.ndarray, z: np.ndarray, dt: float, flow: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Seeded markers' velocities (S, 3) [m/s] and stds (S,) from the next frame's points z (n, 3)
    (:func:`seed_displacements`): each marker takes the median displacement of the matched markers within PATCH_M of
    it (itself included: one wrong match is outvoted), its std their spread (at least INIT_MIN_STD_MPS)."""
    disp = seed_displacements(p, z, dt, flow)
    v = np.zeros((len(p), 3)) + (0.0 if flow is None else flow)
    sv = np.full(len(p), 1.0)
    for i in range(len(p)):
        near = (np.linalg.norm(p - p[i], axis=1) < PATCH_M) & np.isfinite(disp[:, 0])
        if near.sum() >= 2:
            med = np.median(disp[near], axis=0)
            v[i] = med / abs(dt)
            spread = 1.4826 * np.median(np.linalg.norm(disp[near] - med, axis=1)) / abs(dt)
            sv[i] = max(spread, INIT_MIN_STD_MPS)
    return v * np.sign(dt), sv


def start_noise(seed: Seed, before: np.ndarray, after: np.ndarray, dt: float, noise_m: float, opt: TrackOptions
                ) -> TrackOptions:
    """``opt`` with the acceleration noise measured on the seed. accel_psd_m2_s3: the largest q the seeded markers
    show between the frames either side of the seed (points before, after (n, 3) [m]; a marker's second difference
    has a per-axis variance of q dt^3 plus 6 noise_m^2), at most opt's own (a bat wing's) and at least q_min:
    a start far above what the markers do makes neighbouring markers ambiguous on the first frames (a board moved
    by hand at 30 fps, predicted with a wing's q, 26 mm std a frame against 53 mm between its corners); opt's start
    where fewer than 3 markers are matched on both frames. q_min: opt's, which holds at REFERENCE_FPS, at the same
    process noise per frame (q dt^3 / 3) at the rig's rate: how sure of its next position a marker may become."""
    q_min = opt.q_min * (REFERENCE_FPS * dt) ** -3
    a = sum(seed_displacements(seed.xyz, z, s * dt, bulk_velocity(seed.xyz, z, s * dt))
            for s, z in ((-1.0, before), (1.0, after)))
    a = a[np.isfinite(a[:, 0])]
    start = opt.accel_psd_m2_s3
    if len(a) >= 3:
        start = min(start, (float(np.max(np.sum(a * a, axis=1))) / 3.0 - 6.0 * noise_m ** 2) / dt ** 3)
    return replace(opt, accel_psd_m2_s3=max(start, q_min), q_min=q_min)


def extent(xyz: np.ndarray) -> tuple[float, float]:
    """The marker set's box [m^3] and diagonal [m] from its seeded positions (n, 3): each side 1.5 times their
    spread, at least MIN_EXTENT_M."""
    side = np.maximum(1.5 * np.ptp(xyz, axis=0), MIN_EXTENT_M) if len(xyz) else np.full(3, MIN_EXTENT_M)
    return float(np.prod(side)), float(np.linalg.norm(side))


def bulk_velocity(a: np.ndarray, b: np.ndarray, dt: float, radius_m: float = 0.005) -> np.ndarray | None:
    """The displacement most pairs of points a (n, 3) -> b (k, 3) share, per second [m/s] (the body's motion: a
    marker placed without a velocity starts with it); None when fewer than 3 pairs agree."""
    from scipy.spatial import cKDTree

    if len(a) < 3 or len(b) < 3:
        return None
    D = (b[None] - a[:, None]).reshape(-1, 3)
    counts = np.array([len(x) for x in cKDTree(D).query_ball_point(D, radius_m)])
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None
    return D[np.linalg.norm(D - D[best], axis=1) <= radius_m].mean(axis=0) / dt


PAIR_PRIOR = 2.0  # [nats] a two-view candidate's handicap: it is real less often than a point of three views


def pair_prior(views: np.ndarray) -> np.ndarray:
    """Log prior odds (n,) that a candidate is a marker: 0 for three views or more; for two, -PAIR_PRIOR less the
    log of the number of two-view candidates its busier detection is in (of k rival pairings, one at most is real)."""
    n = (views >= 0).sum(axis=1)
    two = n == 2
    out = np.zeros(len(views))
    if two.any():
        ids = views[two][views[two] >= 0]
        count = np.bincount(ids)
        busiest = np.max(np.where(views[two] >= 0, count[np.maximum(views[two], 0)], 0), axis=1)
        out[two] = -PAIR_PRIOR - np.log(busiest)
    return out


class _Frame:
    """One frame's working set: the points (xyz (n, 3), R (n, 3, 3), views (n, C)), which are taken, which markers
    are assigned and where they were placed, and what the assigned markers did (for :func:`_coherent`)."""

    def __init__(self, pts: FramePoints, R: np.ndarray, L: int):
        self.xyz, self.R, self.views = pts.xyz, R, pts.views
        self.taken = np.zeros(len(pts.xyz), bool)
        self.assigned = np.zeros(L, bool)
        self.placed = np.full((L, 3), np.nan)
        self.resid = np.zeros((L, 3))  # an assigned marker's point less its prediction
        self.moved = np.zeros((L, 3))  # ... less its position on the frame before
        self.moves = np.zeros(L, bool)  # which markers have resid and moved (tracked before this frame)
        self.prior = pair_prior(pts.views)
        self.source = pts.source

    def add(self, xyz: np.ndarray, R: np.ndarray, views: np.ndarray) -> np.ndarray:
        """Append points (n, 3) with covariances R (n, 3, 3) and views (n, C); returns their indices."""
        n0 = len(self.xyz)
        self.xyz = np.concatenate([self.xyz, xyz])
        self.R = np.concatenate([self.R, R])
        self.views = np.concatenate([self.views, views])
        self.taken = np.concatenate([self.taken, np.zeros(len(xyz), bool)])
        self.prior = np.concatenate([self.prior, np.zeros(len(xyz))])
        if self.source is not None:
            self.source = np.concatenate([self.source, np.full(len(xyz), -1, self.source.dtype)])
        return np.arange(n0, len(self.xyz))


def sweep(geom: Geometry, points, dets: FrameDetections, frames: np.ndarray, dt: float, seeds: dict[int, Seed],
          pairs: list[tuple[int, int]], out: Sweep, opt: TrackOptions, first=None,
          anchors: Anchors | None = None) -> None:
    """Track every marker through ``frames`` (in the order given; dt [s] negative backward), starting at the seed
    frames' placements; results go into ``out`` (see module docstring). points(frame, predicted xyz (L, 3) [m] (NaN:
    none), their std (L,) [m]) -> the frame's FramePoints (views as global detection indices); first(frame): the
    points the seeded markers' first velocities are measured on, where ``points`` needs predictions to find any.)
    anchors: markers already named, linked to their positions (:func:`_anchor`)."""
    L = out.kind.shape[1]
    F_dt = constant_velocity_F(dt)
    Q1 = constant_velocity_Q(1.0, abs(dt))
    tg = _Targets(L, opt)
    seg = _measure(out, pairs, opt)
    since = 0
    step = 1 if dt > 0 else -1
    flow = None  # the body's velocity [m/s] from the first seed to the next frame's points (lost markers' start)
    if len(frames) > 1 and int(frames[0]) in seeds:
        sd = seeds[int(frames[0])]
        guess = np.full((L, 3), np.nan)
        guess[sd.label] = sd.xyz
        nxt = first(int(frames[0]) + step) if first is not None else points(int(frames[0]) + step, guess,
                                                                              np.full(L, INIT_GATE_M))
        flow = bulk_velocity(sd.xyz, nxt.xyz, dt)
        sd.velocity, sd.velocity_std = initial_velocity(sd.xyz, nxt.xyz, dt, flow)
    for f in frames:
        f = int(f)
        k = f - dets.first
        before = (tg.x[:, :3].copy(), tg.P[:, :3, :3].copy())
        tg.x = tg.x @ F_dt.T
        tg.P = F_dt @ tg.P @ F_dt.T + tg.q[:, None, None] * Q1
        pred = np.where(tg.alive[:, None], tg.x[:, :3], np.nan)
        pts = points(f, pred, tg.pos_std())
        fr = _Frame(pts, point_covariance(geom, pts.xyz, pts.views, dets.sig) if len(pts.xyz) else
                    np.zeros((0, 3, 3)), L)
        if f in seeds:
            _place_seed(tg, fr, seeds[f], geom, dets, out, k, opt, flow)
        if anchors is not None:
            _anchor(tg, fr, anchors, k, geom, dets, out, before, opt, flow)
        _rounds(tg, fr, seg, out, k, before, dt, opt, flow)
        used = np.concatenate([fr.views[fr.taken].ravel(), out.views[k][fr.assigned].ravel()])
        joined = _join(geom, tg, fr, dets, f, used[used >= 0], out, k, opt)
        idle = tg.alive & ~fr.assigned & ~joined
        tg.miss[idle] += 1
        tg.alive &= (tg.miss <= opt.max_miss) & (tg.pos_std() <= opt.max_std_m)
        since += 1
        if since >= RESEGMENT_FRAMES:
            seg, since = _measure(out, pairs, opt), 0


def _anchor(tg: _Targets, fr: _Frame, anchors: Anchors, k: int, geom: Geometry, dets: FrameDetections, out: Sweep,
            before: tuple[np.ndarray, np.ndarray], opt: TrackOptions, flow: np.ndarray | None) -> None:
    """The markers anchored on frame k are linked to their anchored positions (as sure links, confidence 1) before
    the rounds, so that their detections are taken and the rounds name only the others."""
    lab = np.flatnonzero(np.isfinite(anchors.xyz[k, :, 0]) & ~fr.assigned)
    if not len(lab):
        return
    v = anchors.views[k, lab]
    z = anchors.xyz[k, lab]
    p = fr.add(z, point_covariance(geom, z, v, dets.sig), v)
    steady = tg.alive[lab] & (np.abs(k - tg.last[lab]) == 1) & (tg.age[lab] >= MATURE)
    _commit(tg, fr, lab, p, v, np.full(len(lab), 50.0), out, k, tg.x.copy(), tg.P.copy(), steady, before, opt, flow)


def _measure(out: Sweep, pairs: list[tuple[int, int]], opt: TrackOptions) -> seg_mod.Segments:
    """Segments measured on the points assigned so far (kind 1)."""
    X = np.where((out.kind == 1)[..., None], out.xyz, np.nan)
    return seg_mod.measure(X, pairs, opt.learn, opt.noise_m, opt.segment_lengths)


def _place_seed(tg: _Targets, fr: _Frame, seed: Seed, geom: Geometry, dets: FrameDetections, out: Sweep, k: int,
                opt: TrackOptions, flow: np.ndarray | None) -> None:
    """Put the seeded markers where the user placed them; a marker already tracked keeps its velocity."""
    R = point_covariance(geom, seed.xyz, seed.views, dets.sig)
    keep_v = tg.alive[seed.label] & (tg.age[seed.label] >= MATURE)
    if seed.velocity is not None:
        v, sv = seed.velocity, seed.velocity_std
    else:
        v, sv = np.tile(0.0 if flow is None else flow, (len(seed.label), 1)), np.full(len(seed.label), opt.speed_mps)
    v = np.where(keep_v[:, None], tg.x[seed.label, 3:], v)
    tg.place(seed.label, seed.xyz, R, v, sv)
    tg.age[seed.label[keep_v]] = MATURE
    fr.assigned[seed.label] = True
    fr.placed[seed.label] = seed.xyz
    tg.last[seed.label] = k
    clicked = np.isin(fr.views, seed.views[seed.views >= 0]) & (fr.views >= 0)
    fr.taken |= clicked.any(axis=1)
    out.kind[k, seed.label] = 1
    out.views[k, seed.label] = seed.views
    out.conf[k, seed.label] = 1.0
    out.xyz[k, seed.label] = seed.xyz


def _rounds(tg: _Targets, fr: _Frame, seg: seg_mod.Segments, out: Sweep, k: int,
            before: tuple[np.ndarray, np.ndarray], dt: float, opt: TrackOptions, flow: np.ndarray | None) -> None:
    """Assign the frame's points to the markers in rounds (see module docstring)."""
    x0, P0 = tg.x.copy(), tg.P.copy()
    patch = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    if fr.source is not None:
        _take_sources(tg, fr, seg, out, k, x0, P0, before, opt, flow)
    for rnd in range(ROUNDS):
        cand = np.flatnonzero(~fr.assigned)
        steady = tg.alive & (np.abs(k - tg.last) == 1) & (tg.age >= MATURE)  # tracked up to the frame before
        if rnd > 0:
            _coherent(tg, cand[steady[cand]], fr, x0, P0, before, dt)
        patch = _patch(tg, fr, out, k, cand)
        pred_x, pred_S, has = _predictions(tg, cand, steady & (rnd == 0), patch)
        free = np.flatnonzero(~fr.taken)
        lab = np.zeros(0, np.int64)
        if len(cand) and len(free):
            gate = FIRST_ROUND_CHI2 if rnd == 0 else CHI2_3DOF_GATE
            llr, feasible = _llr(pred_x, pred_S, has, cand, fr, free, seg, opt, gate)
            rows, cols, margin = assign(np.where(feasible, LINK_GATE - llr, np.inf), LINK_GATE, opt.ambiguity, True)
            # every marker competes for the points; the first round commits the steady markers' links only
            strong = llr[rows, cols] >= opt.min_llr
            sure = np.flatnonzero((margin >= opt.ambiguity) & strong & (steady[cand[rows]] | (rnd > 0)))
            margin = np.minimum(margin, llr[rows, cols])
            sure, views = _disjoint(fr.views[free[cols[sure]]], margin[sure], sure)
            lab = cand[rows[sure]]
            if len(lab):
                _commit(tg, fr, lab, free[cols[sure]], views, margin[sure], out, k, x0, P0, steady[lab], before, opt,
                        flow)
        if rnd > 0 and not len(lab):
            break
    idle = ~fr.assigned  # a marker left unassigned keeps its corrected position but not the shrunk covariance
    tg.P[idle] = P0[idle]
    anchored = patch[0][tg.alive[patch[0]] & idle[patch[0]]]  # ... and a coasting one follows its neighbours
    if len(anchored):
        at = np.isin(patch[0], anchored)
        tg.update(anchored, patch[1][at], patch[2][at], x0[anchored], P0[anchored], np.zeros(len(anchored), bool))


SEGMENT_SIGMA = 4.0


def _segments_hold(seg: seg_mod.Segments, lab: np.ndarray, z: np.ndarray, placed: np.ndarray) -> np.ndarray:
    """Whether each link (markers lab (n,) at points z (n, 3)) keeps its segments to the markers placed on this
    frame or linked with it (n,) bool: no partner's distance off by more than SEGMENT_SIGMA stds."""
    where = placed.copy()
    where[lab] = z
    part = seg.partner[lab]
    d = np.linalg.norm(where[np.maximum(part, 0)] - z[:, None], axis=-1)
    off = (part >= 0) & np.isfinite(d) & (np.abs(d - seg.length[lab]) > SEGMENT_SIGMA * seg.sigma[lab])
    return ~off.any(axis=1)


def _predictions(tg: _Targets, cand: np.ndarray, steady: np.ndarray,
                 patch: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each candidate marker should be (T, 3) and its covariance (T, 3, 3), and whether it has a prediction
    (T,): a ``steady`` marker's filter, else its patch's (:func:`_patch`), else a live filter's (coherent-corrected
    where it was steady)."""
    pred_x, pred_S = tg.x[cand, :3].copy(), tg.P[cand, :3, :3].copy()
    has = tg.alive[cand].copy()
    at = {int(m): i for i, m in enumerate(patch[0])}
    for j, m in enumerate(cand):
        if not steady[m] and int(m) in at:
            i = at[int(m)]
            pred_x[j], pred_S[j], has[j] = patch[1][i], patch[2][i], True
    return pred_x, pred_S, has


PATCH_M = 0.06  # [m] the neighbours whose motion a marker's patch prediction follows (Gaussian weights)
PATCH_GAP = 40  # [frames] the longest gap a patch prediction bridges
PATCH_FLOOR_M = 0.002  # [m] a patch prediction's least std ...
PATCH_GROWTH_M = 0.001  # [m] ... and its growth per frame of gap (the patch deforms)


def patch_shift(X: np.ndarray, known: np.ndarray, m: int, k_from: int, k_to: int,
                noise_m: float = 0.0) -> tuple[np.ndarray, float] | None:
    """How marker m moved from frame k_from to k_to, as the markers known on both frames near it did.

    Its affine coordinates alpha among those neighbours on k_from (sum 1, sum alpha_i (x_i - x_m) = 0, held near
    Gaussian weights w of width PATCH_M about m: min |sum alpha_i (x_i - x_m)|^2 + AFFINE_M^2 |alpha - w|^2 / w)
    carried to k_to: shift = sum alpha_i (displacement_i). A wing's patch turns and bends as it flaps: the
    affine coordinates follow a turn that a mean shift would miss (a marker 3 cm from its neighbours on a wing
    turning at 80 rad/s lags them by 2 cm per frame at 120 fps). X (F, L, 3) [m] positions, known (F, L) where
    they are; noise_m [m] their noise. Returns (shift (3,) [m], its std [m]: max(PATCH_FLOOR_M, noise_m) +
    PATCH_GROWTH_M per frame of gap + half the difference between the affine and the mean shift), or None without a
    neighbour within 2 PATCH_M."""
    nb = np.flatnonzero(known[k_from] & known[k_to])
    nb = nb[nb != m]
    D = X[k_from, nb] - X[k_from, m]
    d = np.linalg.norm(D, axis=1)
    near = d < 2 * PATCH_M
    if not near.any():
        return None
    near = np.flatnonzero(near)
    near = near[np.argsort(d[near])[:PATCH_NEIGHBOURS]]
    D, disp = D[near], X[k_to, nb[near]] - X[k_from, nb[near]]
    w = np.exp(-0.5 * (d[near] / PATCH_M) ** 2)
    w = w / w.sum()
    n = len(w)
    # KKT system of min |D^T a|^2 + mu sum (a - w)^2 / w  s.t. 1^T a = 1
    mu = AFFINE_M ** 2
    A = np.zeros((n + 1, n + 1))
    A[:n, :n] = D @ D.T + mu * np.diag(1.0 / w)
    A[:n, n] = A[n, :n] = 1.0
    rhs = np.r_[mu * np.ones(n), 1.0]
    alpha = np.linalg.solve(A, rhs)[:n]
    shift, mean = alpha @ disp, w @ disp
    floor = max(PATCH_FLOOR_M, noise_m)
    return shift, floor + PATCH_GROWTH_M * abs(k_to - k_from) + 0.5 * float(np.linalg.norm(shift - mean))


AFFINE_M = 0.01  # [m] how far from the smooth weights the affine coordinates may go for 1 m of fit
PATCH_NEIGHBOURS = 8  # the nearest neighbours a patch prediction uses


def _patch(tg: _Targets, fr: _Frame, out: Sweep, k: int, cand: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predictions of markers from their neighbours (:func:`patch_shift` from the frame of each one's last point to
    this one). Returns (markers (n,), positions (n, 3) [m], covariances (n, 3, 3) [m^2], isotropic)."""
    labs, xs, Ss = [], [], []
    if not len(cand):
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
    X = out.xyz.copy()
    known = out.kind == 1
    X[k] = fr.placed
    known[k] = np.isfinite(fr.placed[:, 0])
    for m in cand:
        kp = int(tg.last[m])
        if not 0 < abs(k - kp) <= PATCH_GAP:
            continue
        shift = patch_shift(X, known, int(m), kp, k, tg.opt.noise_m)
        if shift is None:
            continue
        labs.append(m)
        xs.append(out.xyz[kp, m] + shift[0])
        Ss.append(np.eye(3) * shift[1] ** 2)
    if not labs:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
    return np.asarray(labs, np.int64), np.asarray(xs), np.asarray(Ss)


def _take_sources(tg: _Targets, fr: _Frame, seg: seg_mod.Segments, out: Sweep, k: int, x0: np.ndarray,
                  P0: np.ndarray, before: tuple[np.ndarray, np.ndarray], opt: TrackOptions,
                  flow: np.ndarray | None) -> None:
    """Points found from the markers' own predictions (views.projected_points: each view already the mutual,
    unambiguous choice in its camera) go to the marker that found them, where they lie within its gate and keep
    its segments."""
    src = fr.source
    ok = ~fr.assigned[src] & tg.alive[src]
    if not ok.any():
        return
    p, lab = np.flatnonzero(ok), src[ok]
    m = mahalanobis(fr.xyz[p] - tg.x[lab, :3], tg.P[lab, :3, :3] + fr.R[p])
    good = (m <= CHI2_3DOF_GATE) & _segments_hold(seg, lab, fr.xyz[p], fr.placed)
    p, lab = p[good], lab[good]
    if len(lab):
        steady = np.abs(k - tg.last[lab]) == 1
        _commit(tg, fr, lab, p, fr.views[p], np.full(len(p), 10.0), out, k, x0, P0, steady, before, opt, flow)


def _disjoint(views: np.ndarray, margin: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The links ``idx`` (sorted) with their views (n, C): a detection two links' points share stays with the surer
    link (a point of three views may hold one view of a neighbour's); a link left with no view goes."""
    order = np.argsort(-margin, kind="stable")
    seen: set[int] = set()
    keep, out = [], []
    for i in order:
        v = views[i].copy()
        clash = np.array([x >= 0 and int(x) in seen for x in v])
        v[clash] = -1
        if (v >= 0).any():
            seen.update(int(x) for x in v[v >= 0])
            keep.append(i)
            out.append(v)
    if not keep:
        return np.zeros(0, np.int64), np.zeros((0, views.shape[1]), np.int64)
    at = np.argsort(np.asarray(idx)[keep])
    return np.asarray(idx)[keep][at], np.asarray(out)[at]


def _llr(pred_x: np.ndarray, pred_S: np.ndarray, has: np.ndarray, cand: np.ndarray, fr: _Frame, free: np.ndarray,
         seg: seg_mod.Segments, opt: TrackOptions, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Log likelihood ratios (T, n) of the free points being the candidate markers, and which pairs may link: a
    marker with a prediction (pred_x (T, 3), pred_S (T, 3, 3) where ``has``) by motion (Mahalanobis distance within
    ``gate``) plus segments, one without by segments alone (acquire_llr); plus each point's prior (pair_prior)."""
    z, R = fr.xyz[free], fr.R[free]
    S = pred_S[:, None] + R[None]
    m = mahalanobis(z[None] - pred_x[:, None], S)
    motion = -0.5 * (m + np.linalg.slogdet(S)[1] + 3 * math.log(2 * math.pi)) + math.log(opt.volume_m3)
    segs = seg_mod.evidence(seg, cand, z, fr.placed, opt.range_m)
    has = has[:, None]
    llr = np.where(has, motion + segs, segs) + fr.prior[free][None]
    feasible = np.where(has, m <= gate, segs >= opt.acquire_llr) & (llr > 0)
    return llr, feasible


def _commit(tg: _Targets, fr: _Frame, lab: np.ndarray, p: np.ndarray, views: np.ndarray, margin: np.ndarray,
            out: Sweep, k: int,
            x0: np.ndarray, P0: np.ndarray, steady: np.ndarray, before: tuple[np.ndarray, np.ndarray],
            opt: TrackOptions, flow: np.ndarray | None) -> None:
    """Update (or, for a lost marker, place) the markers ``lab`` with points ``p`` (of which the views (n, C) are
    theirs) and record them."""
    z, R = fr.xyz[p], fr.R[p]
    alive = tg.alive[lab]
    u = lab[alive]
    fr.resid[u] = z[alive] - x0[u, :3]
    fr.moved[u] = z[alive] - before[0][u]
    fr.moves[u] = steady[alive]
    tg.update(u, z[alive], R[alive], x0[u], P0[u], steady[alive])
    tg.age[u] += 1  # a point of its own: after MATURE of them the marker is steady
    a = lab[~alive]
    if len(a):
        near = _neighbour_velocity(z[~alive], fr, x0)
        v = np.where(np.isfinite(near), near, 0.0 if flow is None else flow)
        tg.place(a, z[~alive], R[~alive], v, opt.speed_mps)
    fr.assigned[lab] = True
    fr.placed[lab] = z
    tg.last[lab] = k
    fr.taken |= np.isin(fr.views, views[views >= 0]).any(axis=1)
    out.kind[k, lab] = 1
    out.views[k, lab] = views
    out.conf[k, lab] = 1.0 / (1.0 + np.exp(-np.minimum(margin, 50.0)))
    out.xyz[k, lab] = z


def _neighbour_velocity(z: np.ndarray, fr: _Frame, x0: np.ndarray) -> np.ndarray:
    """The mean velocity of the markers that moved this frame within COHERENT_M of each point (n, 3), NaN where none."""
    out = np.full((len(z), 3), np.nan)
    nb = np.flatnonzero(fr.moves)
    if len(nb):
        near = np.linalg.norm(z[:, None] - x0[nb][None, :, :3], axis=-1) < COHERENT_M
        for i in np.flatnonzero(near.any(axis=1)):
            out[i] = x0[nb[near[i]], 3:].mean(axis=0)
    return out


def _coherent(tg: _Targets, tr: np.ndarray, fr: _Frame, x0: np.ndarray, P0: np.ndarray,
              before: tuple[np.ndarray, np.ndarray], dt: float) -> None:
    """New predictions for the unassigned tracked markers ``tr`` from the markers that moved this frame (Gaussian
    weights of reach COHERENT_M): a mature marker's prediction x0 (L, 6) moves by their mean innovation, its
    position covariance shrinks to a quarter of P0's (L, 6, 6) plus the innovations' spread; a young one moves from
    its position on the frame before by their mean displacement, which also becomes its velocity."""
    nb = np.flatnonzero(fr.moves)
    if not len(nb) or not len(tr):
        return
    d2 = np.sum((x0[tr][:, None, :3] - x0[nb][None, :, :3]) ** 2, axis=-1)
    w = np.exp(-0.5 * d2 / COHERENT_M ** 2) * (d2 < (3 * COHERENT_M) ** 2)
    wsum = w.sum(axis=1)
    has = wsum > 1e-3
    if not has.any():
        return
    t, w = tr[has], w[has] / wsum[has, None]
    mature = tg.age[t] >= MATURE
    step = np.where(mature[:, None], w @ fr.resid[nb], w @ fr.moved[nb])
    dev = np.where(mature[:, None, None], fr.resid[nb][None], fr.moved[nb][None]) - step[:, None]
    spread = np.einsum("tk,tki,tkj->tij", w, dev, dev) + np.eye(3) * 1e-6
    tm, ty = t[mature], t[~mature]
    tg.x[tm, :3] = x0[tm, :3] + step[mature]
    # the position block becomes A' = P0 / 4 + spread; P' = M P0 M^T with M = blockdiag(L' L^-1, I) keeps the
    # velocity's covariance and its correlation with the position consistent (positive definite)
    A = P0[tm, :3, :3]
    M = np.tile(np.eye(6), (len(tm), 1, 1))
    M[:, :3, :3] = np.linalg.cholesky(0.25 * A + spread[mature]) @ np.linalg.inv(np.linalg.cholesky(A))
    tg.P[tm] = M @ P0[tm] @ M.transpose(0, 2, 1)
    tg.x[ty, :3] = before[0][ty] + step[~mature]
    tg.x[ty, 3:] = step[~mature] / dt
    A = spread[~mature] + before[1][ty]
    tg.P[ty] = np.block([[A, A / dt], [A / dt, A / dt ** 2]]) + np.diag([0, 0, 0, 1.0, 1.0, 1.0]) * 1e-4


def _join(geom: Geometry, tg: _Targets, fr: _Frame, dets: FrameDetections, f: int, used: np.ndarray, out: Sweep,
          k: int, opt: TrackOptions) -> np.ndarray:
    """Free detections joined, camera by camera, to the tracked unassigned markers whose projected prediction is
    sharp (join_max_px); returns which markers joined any (L,)."""
    L = len(tg.x)
    joined = np.zeros(L, bool)
    rows = dets.rows(f)
    free = rows[~np.isin(rows, used)]
    want = np.flatnonzero(tg.alive & ~fr.assigned)
    if not len(free) or not len(want):
        return joined
    views = np.full((L, len(geom.rig)), -1, np.int64)
    conf = np.ones(L)
    for c in range(len(geom.rig)):
        fc = free[dets.camera[free] == c]
        h = tg.x[want, :3] @ geom.P[c][:, :3].T + geom.P[c][:, 3]
        if not len(fc) or not (h[:, 2] > 0).any():
            continue
        t = want[h[:, 2] > 0]
        J = jacobian(geom.P[c], tg.x[t, :3])
        S = J @ tg.P[t, :3, :3] @ J.transpose(0, 2, 1)
        sharp = np.sqrt(np.linalg.eigvalsh(S)[:, 1]) <= opt.join_max_px
        if not sharp.any():
            continue
        t, S = t[sharp], S[sharp]
        uv_hat = (h[h[:, 2] > 0][sharp, :2] / h[h[:, 2] > 0][sharp, 2:3])
        Sfull = S[:, None] + np.eye(2) * dets.sig[fc][None, :, None, None] ** 2
        m = mahalanobis_within(dets.uv[fc][None] - uv_hat[:, None], Sfull, CHI2_2DOF_GATE)
        r, d, margin = assign(np.where(m < CHI2_2DOF_GATE, m, np.inf), CHI2_2DOF_GATE, 2 * opt.ambiguity)
        sure = margin >= 2 * opt.ambiguity
        views[t[r[sure]], c] = fc[d[sure]]
        conf[t[r[sure]]] = np.minimum(conf[t[r[sure]]], 1.0 / (1.0 + np.exp(-np.minimum(margin[sure], 100) / 2)))
    for t in np.flatnonzero((views >= 0).any(axis=1)):
        for c in np.flatnonzero(views[t] >= 0):
            tg.update_ray(t, geom.P[c], dets.uv[views[t, c]], float(dets.sig[views[t, c]]))
        joined[t] = True
        out.kind[k, t] = 2
        out.views[k, t] = views[t]
        out.conf[k, t] = conf[t]
        out.xyz[k, t] = tg.x[t, :3]
    return joined


def doubtful(sw: Sweep, k0: int) -> np.ndarray:
    """Where a link of the tracker is in doubt (F, L) bool, as a mark on the later of the two frames it joins (in
    frame order): the tracker placed the marker with a confidence below DOUBT_BELOW. Forward of frame k0 (the
    frame a sweep started from; -1: a forward sweep over every frame) a link on frame k joins it to the frames
    before; backward of it (k0 = F - 1: a backward sweep over every frame), to the frames after (the mark goes on
    k + 1)."""
    weak = (sw.kind > 0) & (sw.conf < DOUBT_BELOW)
    out = np.zeros_like(weak)
    out[k0 + 1:] = weak[k0 + 1:]
    if k0 > 0:
        out[1:k0 + 1] |= weak[:k0]
    return out


def per_detection(sw: Sweep, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per detection (N,): the marker the sweep gave it (-1: none), the sweep's kind there (1 a point, 2 a ray
    join, 0 none) and its track: a run of consecutive frames on which the sweep placed the marker (a frame without
    splits it)."""
    F, L = sw.kind.shape
    label, kind, track = np.full(N, -1, np.int64), np.zeros(N, np.int64), np.full(N, -1, np.int64)
    on = sw.kind > 0
    starts = on & ~np.vstack([np.zeros((1, L), bool), on[:-1]])
    run = np.cumsum(starts.T.ravel()).reshape(L, F).T - 1  # run number, counted marker by marker
    k, lab = np.nonzero(on)
    v = sw.views[k, lab]  # (n, C)
    has = v >= 0
    det = v[has]
    label[det] = np.broadcast_to(lab[:, None], v.shape)[has]
    kind[det] = np.broadcast_to(sw.kind[k, lab][:, None], v.shape)[has]
    track[det] = np.broadcast_to(run[k, lab][:, None], v.shape)[has]
    return label, kind, track
