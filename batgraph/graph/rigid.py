"""Segment-length factors: markers on one rigid segment (a bone) keep their distance.

Cost, added to the smoother's (:mod:`batgraph.graph.cost`) for every segment s = (a, b) of session.toml's
``[markers] rigid`` and every frame k of the take:

    0.5 ((|p_a,k - p_b,k| - L_s) / sigma)^2

with L_s one variable per segment [m], estimated with the trajectories (never given), and sigma =
``[markers] rigid_sigma_m`` (default batgraph.session.DEFAULT_RIGID_SIGMA_M, the few millimetres a
skin marker moves over its bone). Plain Gaussian, no robust loss: a pair that is not rigid is a wrong
declaration, which :func:`solve_rigid` reports (each segment's length scatter), not an outlier to
down-weight. Gauss-Newton: dr/dp_a = u^T / sigma, dr/dp_b = -u^T / sigma, dr/dL = -1 / sigma, with u
the unit vector from b to a; the curvature of |p_a - p_b| is left out, as GTSAM's Gauss-Newton does.

Fast backend. Segments couple markers, so the markers joined by segments (a connected group) are
solved together; markers in no segment stay in the vectorised per-marker solve (batgraph.graph.fast).
A group's state at frame k is its g members' states stacked (n = g d values), so without the lengths
its Hessian T is block tridiagonal in frames with n x n blocks (segment terms add to the diagonal
blocks); the s lengths touch every frame and border it:

    H = [[T, C], [C^T, E]],   C (F n, s),   E (s, s) diagonal.

Solved exactly by the Schur complement on the lengths: [z, W] = T^-1 [rhs_x, C] (one block-tridiagonal
sweep with 1 + s right-hand sides), S = E - C^T W (s x s), dL = S^-1 (rhs_L - C^T z), dx = z - W dL.
The marginals stay exact: the x part of H^-1 is T^-1 + W S^-1 W^T, so each frame's diagonal block is
T^-1's (fast.marginals) plus W_k S^-1 W_k^T; cov(L) = S^-1; log det H = log det T + log det S.
A group has one motion model (each member keeps its own noise level); "auto" picks it per group
(fast.choose_model_per_marker's ``groups``). The Levenberg-Marquardt step, its damping and stopping
rules are fast.solve_fast's, with the group as one column.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..camera import Rig
from ..measurement import IdealObservations
from ..triangulate import triangulate_ideal
from . import cost as spec
from . import fast

MIN_DISTANCE_M = 1e-9  # two markers of a segment closer than this have no direction: u is taken as 0


def segment_pairs(rigid: list[tuple[str, str]], names: list[str]) -> np.ndarray:
    """Marker index pairs (S, 2) int, in ``names``' order, of the segments whose two markers are in ``names``."""
    index = {n: i for i, n in enumerate(names)}
    return np.array([(index[a], index[b]) for a, b in rigid if a in index and b in index], int).reshape(-1, 2)


def groups(pairs: np.ndarray, estimated: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The connected groups of estimated markers joined by segments.

    pairs: (S, 2) marker indices; estimated: (M,) bool (a segment with a marker not estimated is dropped).
    Returns [(members (g,) sorted marker indices, segments (s,) row indices into pairs)], g >= 2.
    """
    M = len(estimated)
    keep = np.flatnonzero(estimated[pairs].all(axis=1)) if len(pairs) else np.zeros(0, int)
    if len(keep) == 0:
        return []
    a, b = pairs[keep, 0], pairs[keep, 1]
    _, label = connected_components(coo_matrix((np.ones(len(keep)), (a, b)), shape=(M, M)), directed=False)
    out = []
    for lab in np.unique(label[a]):
        out.append((np.flatnonzero(label == lab), keep[label[a] == lab]))
    return out


class _Segments:
    """The segment terms of one group: ``local`` (s, 2) pairs of member positions, state size d per member,
    sigma [m]. States x are (F, g, d) [m] (fast's layout), lengths L (s,) [m]."""

    def __init__(self, local: np.ndarray, d: int, sigma_m: float):
        self.local, self.d, self.sigma = local, d, sigma_m

    def residuals(self, x: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals r (F, s) and unit vectors u (F, s, 3) from b to a."""
        r, u, _ = self._geometry(x, L)
        return r, u

    def _geometry(self, x: np.ndarray, L: np.ndarray):
        diff = x[:, self.local[:, 0], :3] - x[:, self.local[:, 1], :3]
        dist = np.maximum(np.linalg.norm(diff, axis=-1), MIN_DISTANCE_M)
        return (dist - L) / self.sigma, diff / dist[..., None], dist

    def cost(self, x: np.ndarray, L: np.ndarray) -> float:
        r, _ = self.residuals(x, L)
        c = 0.5 * float(np.sum(r * r))
        return c if np.isfinite(c) else np.inf

    def system(self, x: np.ndarray, L: np.ndarray, D: np.ndarray, g: np.ndarray, exact: bool = False,
               full: bool = False):
        """The group's bordered Gauss-Newton system from its members' blocks D (F, g, d, d) and gradient
        g (F, g, d): returns T (F, n, n), gx (F, n), C (F, n, s), E (s, s), gL (s,), n = g d.

        ``exact`` adds the curvature of |p_a - p_b| that Gauss-Newton leaves out, (r / sigma) (I - u u^T) /
        |p_a - p_b|, where r > 0 (clamped at 0 so that the system stays positive semi-definite, as the
        robust losses' own curvature is): across the segment it is all the curvature a single-view marker
        at a track end has besides its weak motion prior, and without it the iteration crept there (110
        iterations measured); the marginals use Gauss-Newton's, as GTSAM's do. ``full`` (with ``exact``;
        near the minimum, NEAR_STEP_M) adds it where r < 0 too: the full Hessian, with which the last
        iterations converge quadratically. Clamped there, the missing curvature left them converging
        linearly (step ratio 0.57 per iteration, ~20 iterations from 1e-4 to 1e-9 m, on the 5-camera
        flight's 14-marker group); a step the full curvature spoils is rejected and retried with
        Gauss-Newton's, as for the robust losses."""
        F, gm, d = g.shape
        n = gm * d
        T = np.zeros((F, n, n))
        for i in range(gm):
            T[:, i * d:(i + 1) * d, i * d:(i + 1) * d] = D[:, i]
        gx = g.reshape(F, n).copy()
        r, u, dist = self._geometry(x, L)
        s2 = self.sigma * self.sigma
        C = np.zeros((F, n, len(self.local)))
        uu = u[..., :, None] * u[..., None, :] / s2  # (F, s, 3, 3)
        if exact:
            bend = ((r if full else np.maximum(r, 0.0)) / (self.sigma * dist))[..., None, None]
            uu = uu + bend * (np.eye(3) - s2 * uu)
        for j, (a, b) in enumerate(self.local):
            pa, pb = slice(a * d, a * d + 3), slice(b * d, b * d + 3)
            T[:, pa, pa] += uu[:, j]
            T[:, pb, pb] += uu[:, j]
            T[:, pa, pb] -= uu[:, j]
            T[:, pb, pa] -= uu[:, j]
            C[:, pa, j] = -u[:, j] / s2
            C[:, pb, j] = u[:, j] / s2
            gx[:, pa] += u[:, j] * (r[:, j, None] / self.sigma)
            gx[:, pb] -= u[:, j] * (r[:, j, None] / self.sigma)
        E = np.eye(len(self.local)) * (F / s2)
        gL = -r.sum(axis=0) / self.sigma
        return T, gx, C, E, gL


# Near the minimum, where the segments' full curvature is used (_Segments.system's ``full``): the last accepted
# step's largest component below this [m]. On 9 simulated scenes (3 generators x 3 seeds) the final solves took
# 0.3-0.8x the iterations of the clamped curvature, the same minimiser to 2e-7 m.
NEAR_STEP_M = 1e-3


def _block_diag(B: np.ndarray, g: int) -> np.ndarray:
    """The group's sub-diagonal block as the kernels take a block-diagonal one, (1, g, d, d), from its
    members' B: one (d, d) for all, or (g, d, d) (fast._solve and kernels.tridiagonal_solve)."""
    return np.ascontiguousarray(np.broadcast_to(B, (g,) + B.shape[-2:]))[None]


def _bordered_solve(T, BG, C, E, rx, rL) -> tuple[np.ndarray, np.ndarray]:
    """Solve [[T, C], [C^T, E]] [dx, dL] = [rx, rL] by the Schur complement on dL (module docstring).
    T (F, n, n) with sub-diagonal block BG (n, n), C (F, n, s), E (s, s), rx (F, n), rL (s,)."""
    Y = fast._solve(T[:, None], BG, np.concatenate([rx[..., None], C], axis=-1)[:, None])[:, 0]
    z, W = Y[..., 0], Y[..., 1:]
    S = E - np.einsum("fns,fnt->st", C, W)
    dL = np.linalg.solve(S, rL - np.einsum("fns,fn->s", C, z))
    return z - W @ dL, dL


def _levenberg_marquardt(prob, obs, x: np.ndarray, mu0: np.ndarray, L: np.ndarray, seg: _Segments,
                         max_iterations: int):
    """fast's Levenberg-Marquardt (same damping, acceptance and stopping rules) for one group, one column.

    x (F, g, d), mu0 (g, d), L (s,). Returns (x, L, members' costs (g,), linearisation at x, iterations,
    converged, at_camera)."""
    F, gm, d = x.shape
    near = np.zeros(gm)
    cost_m, lin = prob.evaluate(x, mu0, obs, jacobian=True, closest=near)
    cost = cost_m.sum() + seg.cost(x, L)
    limit = np.where(near > 0, near / fast.AT_CAMERA_DEPTH_FRACTION, np.inf)
    robust = prob.robust != "none"
    BG = _block_diag(prob.B, gm)
    diag_x, diag_L = np.arange(gm * d), np.arange(len(L))
    lam = lam_x = np.float64(0.0)
    exact, converged, at_camera, iters = False, False, False, 0
    last_step = np.inf  # the last accepted step's largest component [m]
    eps = np.finfo(float).eps
    while iters < max_iterations:
        iters += 1
        T, gx, C, E, gL = seg.system(x, L, *prob.system(x, mu0, lin, exact), exact=exact,
                                     full=last_step < NEAR_STEP_M)
        damping = lam_x if exact and robust else lam
        T[:, diag_x, diag_x] *= 1.0 + damping
        E[diag_L, diag_L] *= 1.0 + damping
        dx, dL = _bordered_solve(T, BG, C, E, -gx, -gL)
        xn, Ln = x + dx.reshape(F, gm, d), L + dL
        near_new = np.zeros(gm)
        cost_mn, lin_new = prob.evaluate(xn, mu0, obs, jacobian=True, closest=near_new)
        cost_new = cost_mn.sum() + seg.cost(xn, Ln)
        ok = bool(cost_new <= cost)
        step = max(np.abs(dx).max(), np.abs(dL).max(initial=0.0))
        rel = (cost - cost_new) / max(cost, np.finfo(float).tiny)
        gain = -0.5 * (np.sum(gx * dx) + gL @ dL)
        flat = not ok and gain <= fast.ROUNDING_EPS * eps * cost
        if ok:
            x, L, lin, cost, cost_m = xn, Ln, lin_new, cost_new, cost_mn
            last_step = step
        stuck = lam > 1e12
        at_camera = ok and bool((near_new > limit).any())
        lam, lam_x = fast.next_damping(exact and robust, ok, damping, lam, lam_x, robust)
        exact = ok
        if (ok and rel < fast.REL_COST_TOL) or step < fast.STEP_TOL_M or flat or stuck or at_camera:
            converged = not (stuck or at_camera)
            break
    return x, L, cost_m, lin, iters, converged, at_camera


def _group_marginals(prob, x, mu0, lin, L, seg: _Segments, covariances: bool):
    """At the minimiser: the members' marginal state covariances (F, g, d, d) (or None), the lengths'
    covariance (s, s) and log det H of the group (scaled state, lengths in m)."""
    F, gm, d = x.shape
    T, _, C, E, _ = seg.system(x, L, *prob.system(x, mu0, lin, exact=False))
    BG = _block_diag(prob.B, gm)
    W, Sig, ld_T = fast.solve_and_marginals(T[:, None], BG, C[:, None], covariances)
    W = W[:, 0]  # T^-1 C, (F, n, s)
    S = E - np.einsum("fns,fnt->st", C, W)
    Sinv = np.linalg.inv(S)
    ld_S = np.linalg.slogdet(S)[1]
    if not covariances:
        return None, Sinv, float(ld_T[0] + ld_S)
    Sig = Sig[:, 0] + W @ Sinv @ fast._T(W)
    Sig = 0.5 * (Sig + fast._T(Sig))
    cov = np.stack([Sig[:, i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(gm)], axis=1)
    return cov, Sinv, float(ld_T[0] + ld_S)


def initial_lengths(xyz_m: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Each segment's median distance over frames (S,) [m] of positions (F, M, 3) [m] (NaN frames skipped)."""
    return np.nanmedian(np.linalg.norm(xyz_m[:, pairs[:, 0]] - xyz_m[:, pairs[:, 1]], axis=-1), axis=0)


@fast._one_thread
def solve_rigid(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, model: np.ndarray, level: np.ndarray,
                fps: float, robust: str, robust_k: float, pairs: np.ndarray, sigma_m: float,
                v_init: np.ndarray | None = None, p_start: np.ndarray | None = None,
                a_init: np.ndarray | None = None, covariances: bool = True, max_iterations: int = 200,
                oscillation: spec.Oscillation | None = None) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """fast.solve_per_model with segment-length factors on ``pairs`` (S, 2) marker indices, stiffness
    sigma_m [m]: markers in no segment are solved per marker as there, each group of joined markers
    jointly (module docstring). Arguments and returns as fast.solve_per_model's (the members of a group
    must share one model); a group's log det (not separable into markers) is on its first member's
    logdet_per_marker, its segments' cost on its first member's cost_per_marker. The info adds
    ``segments``: one dict per segment used, {pair: (a, b) marker indices, length_m, length_sigma_m
    (marginal std), scatter_rms_m (RMS of |p_a - p_b| - length over frames at the solution)}.
    """
    F, M = p_init.shape[:2]
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    found = groups(np.asarray(pairs, int).reshape(-1, 2), estimated)
    grouped = np.zeros(M, bool)
    for members, _ in found:
        grouped[members] = True
    free = np.where(grouped, None, model)
    xyz, cov, info = fast.solve_per_model(rig, ideal, np.where(grouped[None, :, None], np.nan, p_init), free, level,
                                          fps, robust, robust_k, v_init=v_init, p_start=p_start, a_init=a_init,
                                          covariances=covariances, oscillation=oscillation)
    info["segments"] = []
    dt = 1.0 / fps
    for members, seg_ids in found:
        names = set(model[members])
        if len(names) != 1 or None in names:
            raise ValueError(f"markers {members.tolist()} are joined by segments but have models "
                             f"{sorted(map(str, names))}")
        name = names.pop()
        prob = fast._Problem(name, np.asarray(level, float)[members], fps, robust, robust_k,
                             None if name != spec.OSCILLATING else oscillation.of(members))
        mask = np.zeros(M, bool)
        mask[members] = True
        obs = fast._observations(rig, ideal, mask)
        x, mu0 = fast._start(prob, p_init, v_init, p_start, members, fps, a_init)
        local = np.searchsorted(members, pairs[seg_ids])
        seg = _Segments(local, prob.d, sigma_m)
        L0 = initial_lengths(x[..., :3], local)
        x, L, cost_m, lin, iters, converged, at_camera = _levenberg_marquardt(prob, obs, x, mu0, L0, seg,
                                                                             max_iterations)
        cov_g, cov_L, ld = _group_marginals(prob, x, mu0, lin, L, seg, covariances)
        xyz[:, members] = x[..., :3]
        if covariances:
            cov[:, members] = cov_g[..., :3, :3]
        v, a = fast._derivatives(x, dt, None if oscillation is None else oscillation.hz)
        for key, val in (("velocity", v), ("acceleration", a)):
            if val is not None:
                info[key][:, members] = val
        r, _ = seg.residuals(x, L)
        seg_cost = 0.5 * float(np.sum(r * r))
        info["iterations_per_marker"][members] = iters
        info["converged"][members] = converged
        info["at_camera"][members] = at_camera
        info["estimated"][members] = True
        info["cost_per_marker"][members] = cost_m
        info["cost_per_marker"][members[0]] += seg_cost
        info["logdet_per_marker"][members] = 0.0
        info["logdet_per_marker"][members[0]] = ld + 2 * F * len(members) * spec.log_det_scale(name, dt)
        for j, sid in enumerate(seg_ids):
            info["segments"].append({"pair": (int(pairs[sid, 0]), int(pairs[sid, 1])), "length_m": float(L[j]),
                                     "length_sigma_m": float(np.sqrt(cov_L[j, j])),
                                     "scatter_rms_m": float(np.sqrt(np.mean((r[:, j] * sigma_m) ** 2)))})
    return fast.merge_markers((xyz, cov, info), None, None)


MIN_SCATTER_FRAMES = 10  # fewer frames with both markers triangulated: no triangulated scatter (0)


def triangulated_excess(rig: Rig, ideal: IdealObservations, pairs: np.ndarray) -> np.ndarray:
    """Each segment's length scatter over the frames beyond what the triangulation's noise explains, (S,) [m]:
    from the per-frame linear triangulation (batgraph.triangulate.triangulate_ideal) of the frames where both
    markers have >= 2 views, sqrt(s^2 - n) with s = 1.4826 x the median absolute deviation of the lengths
    |x_a - x_b| (robust to a mislabelled frame) and n the median of their variances u^T (S_a + S_b) u; 0 when
    s^2 - n is within 3 standard errors of zero (se = s^2 sqrt(5.4 / frames), the MAD's) or fewer than
    MIN_SCATTER_FRAMES frames. Unlike the scatter at the smoother's solution, which the segment factor itself
    pulls in and which depends on the motion model (opposite wing tips declared rigid, 96 frames: 6.2 mm RMS with
    constant velocity, 5.3 mm with "auto"), this does not see the segment or the model. ideal: (C, F, M);
    pairs: (S, 2) marker indices."""
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    out = np.zeros(len(pairs))
    if not len(pairs):
        return out
    sel = np.unique(pairs)
    xyz, cov = triangulate_ideal(rig, IdealObservations(ideal.uv_px[:, :, sel], ideal.cov_px2[:, :, sel]))
    col = np.searchsorted(sel, pairs)
    for s, (a, b) in enumerate(col):
        d = xyz[:, a] - xyz[:, b]
        S = cov[:, a] + cov[:, b]
        ok = np.isfinite(d).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
        n = int(ok.sum())
        if n < MIN_SCATTER_FRAMES:
            continue
        length = np.linalg.norm(d[ok], axis=-1)
        u = d[ok] / np.where(length > 0, length, 1.0)[:, None]
        s2 = (1.4826 * np.median(np.abs(length - np.median(length)))) ** 2
        excess = s2 - float(np.median(along(u, S[ok])))
        if excess > 3 * s2 * np.sqrt(5.4 / n):
            out[s] = np.sqrt(excess)
    return out


def with_groups(markers: np.ndarray, pairs: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """markers (M,) bool, grown to the whole of every segment group (:func:`groups`) that holds one of them."""
    out = np.array(markers, bool)
    for members, _ in groups(np.asarray(pairs, int).reshape(-1, 2), estimated):
        if out[members].any():
            out[members] = True
    return out


def merge_solutions(base: tuple, part: tuple, markers: np.ndarray) -> tuple:
    """Two of :func:`solve_rigid`'s (xyz, cov, info): ``base`` with the markers ``markers`` (M,) bool, whole segment
    groups (:func:`with_groups`), and their segments taken from ``part`` (fast.merge_markers), in place. Returns
    ``base``."""
    fast.merge_markers(base, part, markers)
    redone = {seg["pair"]: seg for seg in part[2]["segments"]}
    base[2]["segments"] = [redone.get(seg["pair"], seg) for seg in base[2]["segments"]]
    return base



# A second ray-sphere intersection counts as another mode only this far (in the reported along-ray stds)
# from the estimate; closer, the Gaussian at the estimate already covers it.
AMBIGUITY_MIN_SEPARATION_SD = 3.0
AMBIGUITY_MIN_WEIGHT = 1e-6  # a second mode less probable than this (motion-only posterior) is not counted


def along(u: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The variances u^T cov u (n,) [m^2] of covariances (n, 3, 3) along unit vectors u (n, 3)."""
    return np.einsum("ni,nij,nj->n", u, cov, u)


def unit_rays(rig: Rig, cams: np.ndarray, xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays from cameras ``cams`` (n,) int to points xyz_m (n, 3) [m]: unit vectors u (n, 3) (0 where a point
    is at its camera's centre), their lengths t (n,) [m] and the centres (n, 3) [m, world]."""
    centres = np.array([cam.center_world for cam in rig])[cams]
    t = np.linalg.norm(xyz_m - centres, axis=-1)
    return (xyz_m - centres) / np.where(t > 0, t, 1.0)[:, None], t, centres


def ambiguity_covariances(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray | None,
                          model: np.ndarray, level: np.ndarray, fps: float, robust: str, robust_k: float,
                          segments: list[dict], xyz: np.ndarray, cov: np.ndarray,
                          oscillation: spec.Oscillation | None = None) -> tuple[np.ndarray, int]:
    """Both smoothers' last step with segments: the motion-only solve (fast.solve_per_model at the same
    models and levels, from ``xyz``) and :func:`depth_ambiguity` with it. ``segments``: solve_rigid's
    info["segments"] (pair, length_m); other arguments as solve_rigid's and depth_ambiguity's. Returns
    depth_ambiguity's (covariances, number of points whose covariance grew). The motion-only solve is that of
    the markers it is asked about, those in a segment with a single-view frame (none: no solve; at 30 x 180 x
    160, 0.33 s saved)."""
    if not segments:
        return cov, 0
    pairs = np.array([s["pair"] for s in segments], int)
    asked = np.zeros(len(model), bool)
    asked[np.unique(pairs)] = True
    asked &= (ideal.seen.sum(axis=0) == 1).any(axis=0)
    if not asked.any():
        return cov, 0
    free_xyz, free_cov, _ = fast.solve_per_model(rig, ideal, p_init, np.where(asked, model, None), level, fps, robust,
                                                 robust_k, v_init=v_init, p_start=xyz, oscillation=oscillation)
    lengths = np.array([s["length_m"] for s in segments], float)
    return depth_ambiguity(rig, ideal, xyz, cov, pairs, lengths, free_xyz, free_cov)


def depth_ambiguity(rig: Rig, ideal: IdealObservations, xyz: np.ndarray, cov: np.ndarray, pairs: np.ndarray,
                    lengths: np.ndarray, xyz_free: np.ndarray, cov_free: np.ndarray) -> tuple[np.ndarray, int]:
    """Covariances of single-view points that account for the second depth a segment allows.

    A marker seen by one camera on a frame lies on that camera's ray; a segment to a partner puts it on a
    sphere about the partner, and a ray meets a sphere twice. The solve settles in one intersection and
    its Gauss-Newton covariance (``cov``) is that mode's alone, tight along the ray; when the motion prior
    cannot tell the two apart (at a track's end, where it extrapolates), the truth is at the other one
    about as often (measured on the simulated 5-camera flight, seed 1: 58 % of the single-view points at
    the track ends outside their 95 % ellipsoid were nearer the other intersection, against 1 % of those
    inside it).

    Per single-view (frame, marker) in a segment, for each partner p: the ray from the camera's centre
    through the estimate, t along it; the intersections of the ray with the sphere of radius ``lengths``
    about p's estimate; t_o the one farther from the estimate t_e. It is another mode when it lies in
    front of the camera and at least AMBIGUITY_MIN_SEPARATION_SD reported along-ray stds away. The
    marker's other segments are not asked whether they allow it: where this matters (a track's end) the
    partners are single-view or extrapolated too and flip with it (a mirrored wing); checking the other
    mode against them left 58 of the 118 uncovered points of that scene uncovered. The two modes are
    weighted by the motion-only posterior (``xyz_free``, ``cov_free``: the same solve without segments)
    along the ray, w_i ~ exp(-0.5 (t_i - t_free)^2 / s^2) with s^2 its along-ray variance plus the
    reported one (a mode under AMBIGUITY_MIN_WEIGHT is not counted), and the covariance becomes the
    second moment about the estimate,
    cov + w_o (t_o - t_e)^2 u u^T (u the ray's unit vector; the largest over partners). The estimate is kept.

    ideal: the observations the solve used (C, F, M); xyz, cov: the solve with segments (F, M, 3),
    (F, M, 3, 3) [m, m^2]; pairs (S, 2) marker indices and lengths (S,) [m] of the segments used;
    xyz_free, cov_free: as xyz, cov without segments. Returns the covariances (a copy) and the number of
    points whose covariance grew.
    """
    n_views = ideal.seen.sum(axis=0)  # (F, M)
    first_cam = np.argmax(ideal.seen, axis=0)  # (F, M): the camera of a single-view point
    extra = np.zeros(n_views.shape)  # (F, M): the largest w_o (t_o - t_e)^2 over a point's partners [m^2]
    u_all = np.zeros(xyz.shape)
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    for (m, p), L in zip(np.concatenate([pairs, pairs[:, ::-1]]), np.concatenate([lengths, lengths]), strict=True):
        f = np.flatnonzero((n_views[:, m] == 1) & np.isfinite(xyz[:, m]).all(axis=-1)
                           & np.isfinite(xyz[:, p]).all(axis=-1))
        u, t_e, c0 = unit_rays(rig, first_cam[f, m], xyz[f, m])
        sd_e = np.sqrt(np.maximum(along(u, cov[f, m]), 0.0))
        t_free = np.einsum("ni,ni->n", xyz_free[f, m] - c0, u)
        s2 = along(u, cov_free[f, m]) + sd_e**2
        d = c0 - xyz[f, p]
        b = np.einsum("ni,ni->n", u, d)
        disc = b * b - (np.einsum("ni,ni->n", d, d) - L * L)
        root = np.sqrt(np.maximum(disc, 0.0))
        t1, t2 = -b - root, -b + root
        t_o = np.where(np.abs(t1 - t_e) > np.abs(t2 - t_e), t1, t2)  # the intersection farther from the estimate
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            log_ratio = 0.5 * ((t_o - t_free) ** 2 - (t_e - t_free) ** 2) / s2  # log w_e - log w_o
            w_o = 1.0 / (1.0 + np.exp(np.minimum(log_ratio, 700.0)))
        other = ((t_e > 0) & (disc > 0) & (t_o > 0) & (np.abs(t_o - t_e) >= AMBIGUITY_MIN_SEPARATION_SD * sd_e)
                 & np.isfinite(t_free) & (s2 > 0) & (w_o >= AMBIGUITY_MIN_WEIGHT))
        add = np.where(other, w_o * (t_o - t_e) ** 2, 0.0)
        bigger = add > extra[f, m]
        extra[f[bigger], m], u_all[f[bigger], m] = add[bigger], u[bigger]
    grown = extra > 0
    cov = cov.copy()
    cov[grown] += extra[grown][:, None, None] * np.einsum("ni,nj->nij", u_all[grown], u_all[grown])
    grown = int(grown.sum())
    return cov, grown
