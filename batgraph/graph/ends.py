"""Honest covariances at a track's ends: the smoother's extrapolation checked against the track itself.

Before a marker's first and after its last frame seen by >= 2 cameras the smoother extrapolates with its
motion model. Where the model misses a persistent motion (a wing's acceleration through a stroke, which a
white-noise acceleration takes for noise), the extrapolation's covariance grows too slowly: on the hold-out
generator's scenes the 95 % ellipsoids of unobserved points at the track ends held the truth 80-87 % of the
time (docs/accuracy.md before this step), and hiding the ends of long tracks showed ratios of squared
error to covariance growing with the distance, 1.5-11x at 8 frames on the flapping scenes (the truth's
d2 over chi-square's median, seeds 1-3).

The check (one more solve of the same cost, and step 6's covariances where single-view points lie outside a span;
both smoothers call it, the GTSAM one with the fast solver as for rigid.ambiguity_covariances):

1. On every marker whose span (first to last frame with >= 2 views) holds >= ``MIN_SPAN_FRAMES`` frames,
   every observation of its first and last ``BACKTEST_FRAMES`` span frames is hidden, and the caller's solve
   runs again: the marker now extrapolates over frames where its triangulation is known.
2. Each hidden frame with a triangulation gives d2 = e^T (S_solve + S_tri)^-1 e, e = extrapolated - triangulated
   position (the linear DLT and its first-order covariance, batgraph.triangulate), at a horizon h = frames
   from the nearest frame the solve still saw.
3. The widening per frame c >= 0 is the one that makes the 95th percentile of d2 / (1 + c h) chi-square's
   (3 DOF) 95 % point (:func:`growth_rate`, pooled over the markers; 0 when it is already at or below it): the
   ellipsoids are for 95 % coverage, so that is what is matched. Matching the median instead (until the
   eighteenth session) rested on the triangulation's overconfident covariance: with the DLT's own
   (batgraph.triangulate) it left 87-89 % of the unobserved track ends covered on the first generator and the
   glide, against 96 % on the first generator and 97 % on the dorsal scene with the percentile (3 seeds
   pooled, docs/accuracy.md; the glide's 23 points: 87 % either way, its backtest finding c = 0).
   Why linear in h: a constant acceleration a that the model does not carry adds (a t^2 / 2)^2 to the squared
   error against the white-noise model's q t^3 / 3, a ratio 1 + (3 a^2 / 4 q) t.
4. Every unobserved point outside its marker's span gets its covariance times (1 + c h), h its distance in
   frames from the span.
5. A point outside its span seen by one camera has two of its three directions measured by the ray; what the
   motion model extrapolates is its depth along the ray. So the same hidden frames are read along a ray too:
   at the ends of markers seen by one camera beyond that end (:func:`ray_cameras`, the camera of the
   single-view frame nearest the span), z^2 = (u . e)^2 / (u^T S_solve u (1 + c' h) + u^T S_tri u), u the unit
   ray from that camera's centre to the extrapolated point, and c' >= 0 makes the 95th percentile of z^2
   chi-square's (1 DOF) 95 % point (:func:`ray_growth_rate`). Every single-view point outside its span then
   gets its variance along its own ray times (1 + c' h) (a rank-one term, Sigma + c' h (u^T Sigma u) u u^T).
   Why along the ray only: widening the whole motion part of their covariance by c took the hold-out dorsal
   and turn scenes' single-view ends from 96-98 % to 100 %, where the motion the model misses lies mostly
   across those rays; along the ray the first generator's single-view ends went from 87 to 94-95 % (3 seeds
   pooled, measured while this was written; docs/accuracy.md). It errs wide: the hidden frames hide every view,
   and a single-view stretch's rays, frame after frame, pin its depth better than no ray does (the bundled
   sample: 85.4 -> 99.1 %, 644 points, c' = 0.60; within 8 frames of the track 98 and 89 % were covered before).
   Keeping the one camera on the hidden frames instead measured c' = 0 over 8 frames on the first generator,
   whose misses lie beyond them (76-82 % covered at 9-32 frames), so it was not used.
6. Through the motion model a single-view stretch's rays, frame after frame, pin its depth along them: how much
   depends on the model being right over the whole stretch, which no hidden frame of step 1 shows when its
   segment partners stay in view. With constant acceleration (the default "auto" picks it for every marker of
   the first generator's seeds 1 and 3) the variance along the ray at 9 frames past the span was 3.6 mm against
   errors of 37 mm (99 mm with constant velocity), and the check of step 5 found c' = 0.078 and 0 on those two
   seeds (0.036 and 0 keeping that one camera on the hidden frames): the first generator's single-view ends were
   covered 88.5 % (seed 1 81.9 %). So each
   single-view point outside its span gets, along its ray, at least the variance the solve gives it without its
   view (:func:`no_view_variances`: the covariances of the segment groups holding such points without their
   single-view observations outside the spans, linearised at the final solution, not iterated), before step 5's
   factor: (1 + c' h) max(v, v0) along u, v its own, v0 the one without its view. Measured (3 seeds pooled, the
   first generator): "auto" 88.5 -> 93.8 %, constant velocity 94.5 -> 97.1 %; the hold-out dorsal and glide scenes
   the same (98.1 and 94.0 %).

The estimate itself does not change, nor any covariance inside a span. Figures (the smoother's info
``track_ends``): backtest_frames, markers, samples, median_ratio and p95_ratio (the median and the 95th
percentile of d2 over chi-square's at c = 0), growth_per_frame (c) and widened_points; ray_samples,
ray_p95_ratio (the 95th percentile of z^2 over chi-square's at c' = 0), ray_growth_per_frame (c'),
widened_single_view_points and depth_floored_points (those whose variance without their view was the larger).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..camera import Rig
from ..measurement import IdealObservations
from ..motion import CHI2_1DOF_95, CHI2_3DOF_95, CHI2_3DOF_MEDIAN
from ..session import span_distance
from ..triangulate import triangulate_ideal
from . import cost as spec
from .rigid import along, groups, solve_rigid, unit_rays

BACKTEST_FRAMES = 8  # frames hidden at each end of a long span
MIN_SPAN_FRAMES = 2 * BACKTEST_FRAMES + 10  # a span this long keeps >= 10 frames seen between its hidden ends
MIN_SAMPLES = 20  # fewer hidden frames with a triangulation: no widening (c = 0); 20 leave one past the 95th percentile
# At most about this many markers are checked (whole segment groups, spread over the markers): 16 hidden frames
# each, ~1000 samples. At 30 x 180 x 160 (seed 3) all 180 gave c = 0.240 in a 0.93 s hidden solve; 64 gave 0.249
# (0.6 s, most of it the 14-marker segment group), 48 gave 0.229 and 32 gave 0.353: fewer markers, a noisier c
BACKTEST_MARKERS = 64


def hidden_ends(n_views: np.ndarray, frames: int = BACKTEST_FRAMES,
                min_span: int = MIN_SPAN_FRAMES) -> tuple[np.ndarray, np.ndarray]:
    """The backtest's hidden points: (hide (F, M) bool, horizon (F, M) int). A marker whose span holds
    >= ``min_span`` frames has its first and last ``frames`` span frames hidden, each at horizon h = frames to
    the nearest frame left seen (1 .. frames); horizon is 0 elsewhere."""
    F, M = n_views.shape
    hide, horizon = np.zeros((F, M), bool), np.zeros((F, M), int)
    dist = span_distance(n_views)
    for m in np.flatnonzero((dist == 0).sum(axis=0) >= min_span):
        inside = np.flatnonzero(dist[:, m] == 0)
        f0, f1 = inside[0], inside[-1]
        h = np.arange(1, frames + 1)
        hide[f0:f0 + frames, m] = hide[f1 - frames + 1:f1 + 1, m] = True
        horizon[f0:f0 + frames, m] = h[::-1]
        horizon[f1 - frames + 1:f1 + 1, m] = h
    return hide, horizon


def straight_start(xyz_m: np.ndarray, hide: np.ndarray, horizon: np.ndarray,
                   fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (F, M, 3) [m, m/s] to start the hidden solve from: ``xyz_m`` and its velocities
    (np.gradient) where seen; on a hidden frame (``hide``) at horizon h, the straight line from its seen
    neighbour h frames away (the frame after a hidden start, before a hidden end) at that neighbour's velocity,
    a one-sided difference with the next seen frame (which the neighbour keeps too), so that nothing of
    ``xyz_m`` on hidden frames is used."""
    F = xyz_m.shape[0]
    p = xyz_m.copy()
    vel = np.gradient(xyz_m, axis=0) * fps if F > 1 else np.zeros_like(xyz_m)
    f, m = np.nonzero(hide)
    h = horizon[f, m]
    after = (f + h < F) & ~hide[np.minimum(f + h, F - 1), m]  # a hidden start: its seen neighbour comes after
    src = np.where(after, f + h, f - h)
    nxt = np.clip(np.where(after, src + 1, src - 1), 0, F - 1)  # the seen frame beyond the neighbour
    v = (xyz_m[src, m] - xyz_m[nxt, m]) * (fps / np.where(after, -1, 1))[:, None]
    p[f, m] = xyz_m[src, m] + v * (np.where(after, -h, h) / fps)[:, None]
    vel[f, m] = vel[src, m] = v
    return p, vel


def growth_rate(d2: np.ndarray, horizon: np.ndarray, tol: float = 1e-4) -> float:
    """The least c >= 0 with the 95th percentile of d2 / (1 + c horizon) <= chi-square's 95 % point (3 DOF), by
    bisection to ``tol``; 0 when fewer than MIN_SAMPLES samples or the percentile is already there.
    d2, horizon: (n,)."""
    d2, horizon = np.asarray(d2, float), np.asarray(horizon, float)
    return _least_c(lambda c: float(np.quantile(d2 / (1.0 + c * horizon), 0.95)) - CHI2_3DOF_95, len(d2), tol)


def ray_growth_rate(e_ray: np.ndarray, var_solve: np.ndarray, var_tri: np.ndarray, horizon: np.ndarray,
                    tol: float = 1e-4) -> float:
    """The least c >= 0 with the 95th percentile of e_ray^2 / (var_solve (1 + c horizon) + var_tri) <= chi-square's
    95 % point (1 DOF), as :func:`growth_rate`. e_ray: errors along a ray [m]; var_solve, var_tri: the solve's and
    the triangulation's variances along it [m^2]; horizon: frames; all (n,)."""
    e2, vs, vt, h = (np.asarray(a, float) for a in (np.square(e_ray), var_solve, var_tri, horizon))
    return _least_c(lambda c: float(np.quantile(e2 / (vs * (1.0 + c * h) + vt), 0.95)) - CHI2_1DOF_95, len(e2), tol)


def _least_c(excess: Callable[[float], float], n: int, tol: float) -> float:
    """The least c >= 0 with excess(c) <= 0 (excess decreasing in c), by doubling then bisection to ``tol``;
    0 when n < MIN_SAMPLES or excess(0) <= 0."""
    if n < MIN_SAMPLES or excess(0.0) <= 0:
        return 0.0
    lo, hi = 0.0, 1.0
    while excess(hi) > 0 and hi < 1e6:
        lo, hi = hi, 2 * hi
    while hi - lo > tol * max(hi, 1.0):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
    return hi


def backtest_markers(long_span: np.ndarray, units: list[np.ndarray] | None = None,
                     most: int = BACKTEST_MARKERS) -> np.ndarray:
    """The markers to check, (M,) bool: the ``units`` (marker index arrays solved together: segment groups;
    default every marker alone) holding a marker with ``long_span`` (M,) bool: the fewest of them, spread evenly
    over that list (in marker order), that hold ``most`` such markers; all of them when they hold fewer."""
    M = len(long_span)
    units = [np.array([m]) for m in range(M)] if units is None else list(units)
    covered = np.zeros(M, bool)
    for u in units:
        covered[u] = True
    units += [np.array([m]) for m in np.flatnonzero(~covered)]
    useful = sorted((u for u in units if long_span[u].any()), key=lambda u: int(np.min(u)))
    chosen = np.zeros(M, bool)
    pick = []
    for k in range(1, len(useful) + 1):  # k units spread as noise.fit_markers spreads markers, k growing
        pick = np.unique(np.linspace(0, len(useful) - 1, k).round().astype(int))
        if sum(int(long_span[useful[i]].sum()) for i in pick) >= most:
            break
    for i in pick:
        chosen[useful[i]] = True
    return chosen


def calibrate_ends(solve: Callable[..., tuple[np.ndarray, np.ndarray]], rig: Rig, ideal: IdealObservations,
                   xyz_m: np.ndarray, cov_m2: np.ndarray, fps: float,
                   units: list[np.ndarray] | None = None) -> tuple[np.ndarray, dict]:
    """The module's check and widening. ``solve(ideal_subset, p_start, v_start, markers, max_iterations=200)`` ->
    (xyz (F, M', 3) [m], cov (F, M', 3, 3) [m^2]): the smoother's final solve (same models, levels, loss and
    segments) of the markers ``markers`` (M',) int on ``ideal_subset`` (C, F, M', 2), a subset of their observations
    that the final solve used, started from positions p_start (F, M', 3) [m] and velocities v_start [m/s] (with
    max_iterations=0 the covariances there, not iterated: step 6). ideal: those
    observations (C, F, M); xyz_m, cov_m2: the final solve's solution on them; fps [1/s]; units: the markers
    solved together (:func:`backtest_markers`). Returns the covariances (a copy where any widened) and the
    figures ({} when no point seen by fewer than two cameras lies outside a span: nothing is solved then).

    The hidden solve starts from ``xyz_m`` with each hidden stretch replaced by the straight line from its seen
    neighbour (that frame's position and velocity, np.gradient of xyz_m): a start at xyz_m itself would carry
    the hidden observations into the backtest wherever the solve stops short of its optimum, or picks the
    optimum nearest the truth among several (segments' spheres; measured: 0.08 against 0.37 per frame on the
    dorsal scene with 30 iterations)."""
    n_views = ideal.seen.sum(axis=0)
    dist = span_distance(n_views)
    outside = (dist > 0) & np.isfinite(cov_m2).all(axis=(-2, -1))
    targets, rays = outside & (n_views == 0), outside & (n_views == 1)
    if not (targets.any() or rays.any()):
        return cov_m2, {}
    hide, horizon = hidden_ends(n_views)
    sel = np.flatnonzero(backtest_markers(hide.any(axis=0), units))
    figures = {"backtest_frames": BACKTEST_FRAMES, "markers": int(hide[:, sel].any(axis=0).sum()), "samples": 0,
               "median_ratio": None, "p95_ratio": None, "growth_per_frame": 0.0, "widened_points": 0,
               "ray_samples": 0, "ray_p95_ratio": None, "ray_growth_per_frame": 0.0, "widened_single_view_points": 0,
               "depth_floored_points": 0}
    c = c_ray = 0.0
    if hide.any():
        c, c_ray = _backtest(solve, rig, ideal, xyz_m, fps, sel, hide[:, sel], horizon[:, sel], dist, rays, figures)
    out = cov_m2
    if c > 0 and targets.any():
        out = out.copy()
        out[targets] *= (1.0 + c * dist[targets])[:, None, None]
        figures["widened_points"] = int(targets.sum())
    if rays.any():  # steps 5 and 6: each single-view point's variance along its own ray
        f, m = np.nonzero(rays)
        u = unit_rays(rig, ideal.seen[:, f, m].argmax(axis=0), xyz_m[f, m])[0]
        var = along(u, cov_m2[f, m])
        floor = no_view_variances(solve, ideal, xyz_m, fps, units, rays, u)
        floored = floor > var
        grow = (1.0 + c_ray * dist[f, m]) * np.where(floored, floor, var) - var
        if (grow > 0).any():
            out = out.copy() if out is cov_m2 else out
            grow = np.maximum(grow, 0.0)
            out[f, m] += grow[:, None, None] * u[:, :, None] * u[:, None, :]
        figures.update(widened_single_view_points=int(np.sum(grow > 0)), depth_floored_points=int(floored.sum()))
    return out, figures


def _backtest(solve: Callable[..., tuple[np.ndarray, np.ndarray]], rig: Rig, ideal: IdealObservations,
              xyz_m: np.ndarray, fps: float, sel: np.ndarray, hide: np.ndarray, horizon: np.ndarray,
              dist: np.ndarray, rays: np.ndarray, figures: dict) -> tuple[float, float]:
    """Steps 1-3 and 5's rate: the hidden solve of markers ``sel`` (M',) int with ``hide`` (F, M') bool hidden at
    ``horizon`` (F, M') int, and its growth rates (c, c'); ``figures`` is updated with what was measured. dist:
    span_distance (F, M); rays: the single-view points outside their spans (F, M) bool; the rest as
    :func:`calibrate_ends`."""
    sub = IdealObservations(ideal.uv_px[:, :, sel], ideal.cov_px2[:, :, sel])
    uv = sub.uv_px.copy()
    uv[:, hide] = np.nan
    p_start, v_start = straight_start(xyz_m[:, sel], hide, horizon, fps)
    xyz_h, cov_h = solve(IdealObservations(uv, sub.cov_px2), p_start, v_start, sel)
    seen_hidden = sub.uv_px.copy()  # the hidden points' own triangulation: the other points' is not asked for
    seen_hidden[:, ~hide] = np.nan
    tri, cov_tri = triangulate_ideal(rig, IdealObservations(seen_hidden, sub.cov_px2))
    e = xyz_h - tri
    S = cov_h + cov_tri
    ok = hide & np.isfinite(e).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
    ok[ok] = np.linalg.det(S[ok]) > 0
    d2 = np.einsum("ni,ni->n", e[ok], np.linalg.solve(S[ok], e[ok][..., None])[..., 0])
    c = growth_rate(d2, horizon[ok])
    figures.update(samples=int(ok.sum()), growth_per_frame=c)
    if len(d2):
        figures.update(median_ratio=float(np.median(d2) / CHI2_3DOF_MEDIAN),
                       p95_ratio=float(np.quantile(d2, 0.95) / CHI2_3DOF_95))
    if not rays.any():
        return c, 0.0
    cam = ray_cameras(ideal.seen[:, :, sel], dist[:, sel], hide)  # step 5: the same frames along the rays
    use = ok & (cam >= 0)
    u = unit_rays(rig, cam[use], xyz_h[use])[0]
    e_ray = np.einsum("ni,ni->n", u, e[use])
    var_h, var_tri = along(u, cov_h[use]), along(u, cov_tri[use])
    c_ray = ray_growth_rate(e_ray, var_h, var_tri, horizon[use])
    figures.update(ray_samples=int(use.sum()), ray_growth_per_frame=c_ray)
    if use.any():
        figures["ray_p95_ratio"] = float(np.quantile(e_ray**2 / (var_h + var_tri), 0.95) / CHI2_1DOF_95)
    return c, c_ray


def no_view_variances(solve: Callable[..., tuple[np.ndarray, np.ndarray]], ideal: IdealObservations,
                      xyz_m: np.ndarray, fps: float, units: list[np.ndarray] | None, rays: np.ndarray,
                      u: np.ndarray) -> np.ndarray:
    """Step 6: the variances (n,) [m^2] along unit vectors u (n, 3) at the n points ``rays`` (F, M) bool (in
    np.nonzero order) without their observations: the covariances of the ``units`` (as :func:`calibrate_ends`)
    that hold any of them, linearised at the final solution ``xyz_m`` (the Gauss-Newton information of the
    observations left, the motion model and the segments there), not iterated: only a variance is wanted, and
    iterating to the minimiser without those views took 165 iterations (9.9 s) on the simulated 5-camera flight
    (seed 1), against one evaluation."""
    M = xyz_m.shape[1]
    need = rays.any(axis=0)
    for unit in ([] if units is None else units):
        if need[unit].any():
            need[unit] = True
    sel = np.flatnonzero(need)
    uv = ideal.uv_px[:, :, sel].copy()
    uv[:, rays[:, sel]] = np.nan
    start = xyz_m[:, sel]
    _, cov = solve(IdealObservations(uv, ideal.cov_px2[:, :, sel]), start,
                   np.gradient(start, axis=0) * fps if len(start) > 1 else np.zeros_like(start), sel,
                   max_iterations=0)
    f, m = np.nonzero(rays)
    column = np.zeros(M, int)
    column[sel] = np.arange(len(sel))
    return along(u, cov[f, column[m]])


def ray_cameras(seen: np.ndarray, dist: np.ndarray, hide: np.ndarray) -> np.ndarray:
    """For each hidden frame (``hide`` (F, M) bool), the camera that sees its marker on the single-view frame
    nearest beyond that end of the span (a hidden frame before the span's middle belongs to its start), (F, M)
    int, -1 where that end has no single-view frame beyond it or the frame is not hidden. seen: (C, F, M) bool;
    dist: :func:`span_distance` (F, M)."""
    n_views = seen.sum(axis=0)
    out = np.full(hide.shape, -1)
    for m in np.flatnonzero(hide.any(axis=0)):
        inside = np.flatnonzero(dist[:, m] == 0)
        f0, f1 = inside[0], inside[-1]
        before = np.flatnonzero(n_views[:f0, m] == 1)
        after = f1 + 1 + np.flatnonzero(n_views[f1 + 1:, m] == 1)
        hidden = np.flatnonzero(hide[:, m])
        start = hidden < 0.5 * (f0 + f1)
        if len(before):
            out[hidden[start], m] = seen[:, before[-1], m].argmax()
        if len(after):
            out[hidden[~start], m] = seen[:, after[0], m].argmax()
    return out


def widen_ends(rig: Rig, ideal: IdealObservations, p_init: np.ndarray, model: np.ndarray, level: np.ndarray,
               fps: float, robust: str, robust_k: float, pairs: np.ndarray, sigma_m: float, xyz_m: np.ndarray,
               cov_m2: np.ndarray, oscillation: spec.Oscillation | None = None) -> tuple[np.ndarray, dict]:
    """Both smoothers' step: :func:`calibrate_ends` with the fast solver (rigid.solve_rigid at the final solve's
    models, levels, loss and segments; arguments as solve_rigid's, ``ideal`` the observations the final solve
    used). The markers of a segment group are checked together or not at all."""
    pairs = np.asarray(pairs, int).reshape(-1, 2)

    def solve(sub: IdealObservations, p_start: np.ndarray, v_start: np.ndarray, sel: np.ndarray,
              max_iterations: int = 200) -> tuple[np.ndarray, np.ndarray]:
        inside = np.isin(pairs, sel).all(axis=1)  # a chosen group's segments, in the subset's marker numbers
        xyz, cov, _ = solve_rigid(rig, sub, p_init[:, sel], model[sel], np.asarray(level)[sel], fps, robust,
                                  robust_k, np.searchsorted(sel, pairs[inside]), sigma_m, v_init=v_start,
                                  p_start=p_start, max_iterations=max_iterations,
                                  oscillation=None if oscillation is None else oscillation.of(sel))
        return xyz, cov

    estimated = np.isfinite(p_init).all(axis=(0, 2))
    units = [members for members, _ in groups(pairs, estimated)]
    return calibrate_ends(solve, rig, ideal, xyz_m, cov_m2, fps, units)
