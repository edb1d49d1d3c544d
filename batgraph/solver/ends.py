"""Honest covariances where the data do not pin a point: the track ends, and a segment's second depth.

Beyond a marker's span (its first to last frame seen by >= 2 cameras) the smoother extrapolates with its motion
model, whose white-noise acceleration (or jerk) takes a wing's persistent stroke for noise, so its covariance there
grows too slowly (alone, single-view points outside a span were covered 70-84 % and unobserved ones 74 % on three
scenes; docs/ablation.md). Three steps, each needed in that ablation (the estimates never move):
1. The backtest: on up to BACKTEST_MARKERS markers with a span of >= MIN_SPAN_FRAMES, hide the first and last
   BACKTEST_FRAMES span frames, solve again, and find the least c >= 0 with the 95th percentile of
   d2 / (1 + c h) at chi-square's (3 DOF), d2 the hidden frames' squared error against their triangulation over both
   covariances, h the frames to the nearest seen one; every unobserved point outside its span gets cov (1 + c h).
2. The no-view floor: a single-view point outside its span gets, along its ray, at least the variance the solve
   gives it without its view (its rays pin its depth only as well as the model holds over the whole stretch).
3. The second depth: a single-view point on a segment lies on its ray and on a sphere about its partner, which the
   ray meets twice; the covariance gains the other intersection's weighted second moment along the ray.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..motion import CHI2_3DOF_95
from ..session import span_distance
from ..triangulate import triangulate_ideal
from . import fit as fit_mod
from . import lm, segments

BACKTEST_FRAMES = 8  # frames hidden at each end of a long span
MIN_SPAN_FRAMES = 2 * BACKTEST_FRAMES + 10  # a span this long keeps >= 10 frames seen between its hidden ends
MIN_SAMPLES = 20  # fewer hidden frames with a triangulation: no widening (20 leave one past the 95th percentile)
BACKTEST_MARKERS = 64  # about this many markers are checked (whole groups, spread over the list): ~1000 samples
AMBIGUITY_MIN_SEPARATION_SD = 3.0  # a second intersection nearer than this many along-ray stds is no other mode
AMBIGUITY_MIN_WEIGHT = 1e-6  # a second mode less probable than this (motion-only posterior) is not counted


def widen(setup: fit_mod.Setup, backend, models, levels, fit: fit_mod.Fit) -> tuple[np.ndarray, dict]:
    """The three steps (module docstring) on ``fit``, the final solve of ``setup`` (its used observations) at
    ``models`` and ``levels`` (M,): (covariances (F, M, 3, 3), figures). A fit without covariances is returned."""
    cov, figures = fit.cov, {}
    if cov is None:
        return cov, figures
    if len(fit.pairs):
        cov, figures["depth_ambiguous_points"] = _second_depth(setup, backend, models, levels, fit, cov)
    cov, ends = _track_ends(setup, backend, models, levels, fit, cov)
    if ends:
        figures["track_ends"] = ends
    return cov, figures


def _solver(setup, backend, models, levels) -> Callable:
    """solve(sub_setup, markers (M,) bool, start (p, v), settings) -> fit, at the final solve's models and levels."""

    def solve(sub, markers, start, settings=lm.TIGHT):
        return backend.fit(sub, np.where(markers, models, None), levels, (*start, None), settings)

    return solve


def _track_ends(setup, backend, models, levels, fit, cov) -> tuple[np.ndarray, dict]:
    n_views = setup.ideal.seen.sum(axis=0)
    dist = span_distance(n_views)
    outside = (dist > 0) & np.isfinite(cov).all(axis=(-2, -1))
    targets, rays = outside & (n_views == 0), outside & (n_views == 1)
    if not (targets.any() or rays.any()):
        return cov, {}
    solve = _solver(setup, backend, models, levels)
    units = [members for members, _ in segments.groups(setup.pairs, models != None)]  # noqa: E711
    hide, horizon = hidden_ends(n_views)
    sel = backtest_markers(hide.any(axis=0), units)
    figures = {"backtest_frames": BACKTEST_FRAMES, "markers": int((hide[:, sel]).any(axis=0).sum()), "samples": 0,
               "p95_ratio": None, "growth_per_frame": 0.0, "widened_points": 0, "depth_floored_points": 0}
    c = _backtest(solve, setup, fit, sel, hide & sel[None], horizon, figures) if (hide & sel[None]).any() else 0.0
    out = cov.copy()
    if c > 0 and targets.any():
        out[targets] *= (1.0 + c * dist[targets])[:, None, None]
        figures["widened_points"] = int(targets.sum())
    if rays.any():  # the no-view floor, along each single-view point's own ray
        f, m = np.nonzero(rays)
        u = unit_rays(setup.rig, setup.ideal.seen[:, f, m].argmax(axis=0), fit.xyz[f, m])[0]
        var = along(u, cov[f, m])
        floor = _no_view_variances(solve, setup, fit, rays, u, units)
        grow = np.maximum(floor - var, 0.0)
        out[f, m] += grow[:, None, None] * u[:, :, None] * u[:, None, :]
        figures["depth_floored_points"] = int((grow > 0).sum())
    return out, figures


def hidden_ends(n_views: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(hide (F, M) bool, horizon (F, M) int): the first and last BACKTEST_FRAMES frames of every span of at least
    MIN_SPAN_FRAMES, each at h = frames to the nearest frame left seen (1 .. BACKTEST_FRAMES); 0 elsewhere."""
    F, M = n_views.shape
    hide, horizon = np.zeros((F, M), bool), np.zeros((F, M), int)
    dist = span_distance(n_views)
    h = np.arange(1, BACKTEST_FRAMES + 1)
    for m in np.flatnonzero((dist == 0).sum(axis=0) >= MIN_SPAN_FRAMES):
        inside = np.flatnonzero(dist[:, m] == 0)
        f0, f1 = inside[0], inside[-1]
        hide[f0:f0 + BACKTEST_FRAMES, m] = hide[f1 - BACKTEST_FRAMES + 1:f1 + 1, m] = True
        horizon[f0:f0 + BACKTEST_FRAMES, m], horizon[f1 - BACKTEST_FRAMES + 1:f1 + 1, m] = h[::-1], h
    return hide, horizon


def backtest_markers(long_span: np.ndarray, units: list[np.ndarray]) -> np.ndarray:
    """The markers to check (M,) bool: the fewest units (segment groups, else single markers) holding a marker
    with ``long_span``, spread evenly over them, that hold BACKTEST_MARKERS such markers (all when fewer)."""
    M = len(long_span)
    covered = np.zeros(M, bool)
    for u in units:
        covered[u] = True
    useful = sorted((u for u in list(units) + [np.array([m]) for m in np.flatnonzero(~covered)]
                     if long_span[u].any()), key=lambda u: int(np.min(u)))
    chosen, pick = np.zeros(M, bool), []
    for k in range(1, len(useful) + 1):
        pick = np.unique(np.linspace(0, len(useful) - 1, k).round().astype(int))
        if sum(int(long_span[useful[i]].sum()) for i in pick) >= BACKTEST_MARKERS:
            break
    for i in pick:
        chosen[useful[i]] = True
    return chosen


def _backtest(solve, setup, fit, sel, hide, horizon, figures) -> float:
    """Step 1's rate c from the hidden solve of markers ``sel`` (M,) bool; ``figures`` gets what was measured."""
    drop = np.broadcast_to(hide[None], setup.ideal.seen.shape)
    p, v = straight_start(fit.xyz, hide, horizon, setup.fps)
    hidden = solve(setup.without(drop), sel, (p, v))
    seen_hidden = replace(setup.ideal, uv_px=np.where(hide[None, ..., None], setup.ideal.uv_px, np.nan))
    tri, cov_tri = triangulate_ideal(setup.rig, seen_hidden)
    e, S = hidden.xyz - tri, hidden.cov + cov_tri
    ok = hide & np.isfinite(e).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
    ok[ok] = np.linalg.det(S[ok]) > 0
    d2 = np.einsum("ni,ni->n", e[ok], np.linalg.solve(S[ok], e[ok][..., None])[..., 0])
    c = growth_rate(d2, horizon[ok])
    figures.update(samples=int(ok.sum()), growth_per_frame=c)
    if len(d2):
        figures["p95_ratio"] = float(np.quantile(d2, 0.95) / CHI2_3DOF_95)
    return c


def straight_start(xyz: np.ndarray, hide: np.ndarray, horizon: np.ndarray, fps: float) -> tuple:
    """(positions, velocities) (F, M, 3) to start the hidden solve from: ``xyz`` where seen; on a hidden frame at
    horizon h, the straight line from its seen neighbour h frames away at that neighbour's one-sided velocity, so
    that nothing of ``xyz`` on hidden frames is used (a start there carries the hidden observations back in)."""
    F = xyz.shape[0]
    p = xyz.copy()
    vel = np.gradient(xyz, axis=0) * fps if F > 1 else np.zeros_like(xyz)
    f, m = np.nonzero(hide)
    h = horizon[f, m]
    after = (f + h < F) & ~hide[np.minimum(f + h, F - 1), m]  # a hidden start: its seen neighbour comes after
    src = np.where(after, f + h, f - h)
    nxt = np.clip(np.where(after, src + 1, src - 1), 0, F - 1)
    v = (xyz[src, m] - xyz[nxt, m]) * (fps / np.where(after, -1, 1))[:, None]
    p[f, m] = xyz[src, m] + v * (np.where(after, -h, h) / fps)[:, None]
    vel[f, m] = vel[src, m] = v
    return p, vel


def growth_rate(d2: np.ndarray, horizon: np.ndarray, tol: float = 1e-4) -> float:
    """The least c >= 0 with the 95th percentile of d2 / (1 + c horizon) at chi-square's 95 % point (3 DOF), by
    doubling and bisection to ``tol``; 0 with fewer than MIN_SAMPLES samples or already there. Linear in the
    horizon: an acceleration a the model does not carry adds (a t^2 / 2)^2 to its q t^3 / 3, ratio 1 + 3a^2 t / 4q."""
    d2, h = np.asarray(d2, float), np.asarray(horizon, float)

    def excess(c: float) -> float:
        return float(np.quantile(d2 / (1.0 + c * h), 0.95)) - CHI2_3DOF_95

    if len(d2) < MIN_SAMPLES or excess(0.0) <= 0:
        return 0.0
    lo, hi = 0.0, 1.0
    while excess(hi) > 0 and hi < 1e6:
        lo, hi = hi, 2 * hi
    while hi - lo > tol * max(hi, 1.0):
        lo, hi = ((lo + hi) / 2, hi) if excess((lo + hi) / 2) > 0 else (lo, (lo + hi) / 2)
    return hi


def _no_view_variances(solve, setup, fit, rays, u, units) -> np.ndarray:
    """Step 2: the variances (n,) along u (n, 3) of the n points ``rays`` (F, M) without their observations: the
    covariances of the markers (whole units) holding them, linearised at the final solution, not iterated (only a
    variance is wanted; iterating without those views took 165 iterations on the 5-camera flight)."""
    need = rays.any(axis=0)
    for unit in units:
        if need[unit].any():
            need[unit] = True
    drop = np.broadcast_to(rays[None], setup.ideal.seen.shape)
    xyz = np.where(need[None, :, None], fit.xyz, np.nan)
    at = solve(setup.without(drop), need, (xyz, fit.velocity), lm.Settings(max_iterations=0))
    f, m = np.nonzero(rays)
    return along(u, at.cov[f, m])


def along(u: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The variances u^T cov u (n,) [m^2] of covariances (n, 3, 3) along unit vectors u (n, 3)."""
    return np.einsum("ni,nij,nj->n", u, cov, u)


def unit_rays(rig, cams: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays from cameras ``cams`` (n,) to points xyz (n, 3) [m]: unit vectors (n, 3), lengths (n,) [m] and the
    cameras' centres (n, 3)."""
    centres = np.array([cam.center_world for cam in rig])[cams]
    t = np.linalg.norm(xyz - centres, axis=-1)
    return (xyz - centres) / np.where(t > 0, t, 1.0)[:, None], t, centres


def _second_depth(setup, backend, models, levels, fit, cov) -> tuple[np.ndarray, int]:
    """Step 3 (module docstring): the covariances with each single-view segment member's second intersection, and
    how many grew. The modes are weighted by the motion-only posterior (the same solve without segments) along
    the ray; the covariance becomes the second moment about the estimate, cov + w_o (t_o - t_e)^2 u u^T."""
    seen = setup.ideal.seen
    asked = np.zeros(len(models), bool)
    asked[np.unique(fit.pairs)] = True
    asked &= (seen.sum(axis=0) == 1).any(axis=0)
    if not asked.any():
        return cov, 0
    free = backend.fit(setup, np.where(asked, models, None), levels, (fit.xyz, fit.velocity, None),
                       with_segments=False)
    n_views, first_cam = seen.sum(axis=0), np.argmax(seen, axis=0)
    extra, u_all = np.zeros(n_views.shape), np.zeros(fit.xyz.shape)
    pairs = np.concatenate([fit.pairs, fit.pairs[:, ::-1]])
    for (m, p), L in zip(pairs, np.concatenate([fit.length_m, fit.length_m]), strict=True):
        both = np.isfinite(fit.xyz[:, m]).all(-1) & np.isfinite(fit.xyz[:, p]).all(-1)
        f = np.flatnonzero((n_views[:, m] == 1) & both)
        u, t_e, c0 = unit_rays(setup.rig, first_cam[f, m], fit.xyz[f, m])
        sd_e = np.sqrt(np.maximum(along(u, cov[f, m]), 0.0))
        t_free = np.einsum("ni,ni->n", free.xyz[f, m] - c0, u)
        s2 = along(u, free.cov[f, m]) + sd_e**2
        d = c0 - fit.xyz[f, p]
        b = np.einsum("ni,ni->n", u, d)
        disc = b * b - (np.einsum("ni,ni->n", d, d) - L * L)
        root = np.sqrt(np.maximum(disc, 0.0))
        t1, t2 = -b - root, -b + root
        t_o = np.where(np.abs(t1 - t_e) > np.abs(t2 - t_e), t1, t2)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            w_o = 1.0 / (1.0 + np.exp(np.minimum(0.5 * ((t_o - t_free) ** 2 - (t_e - t_free) ** 2) / s2, 700.0)))
        other = ((t_e > 0) & (disc > 0) & (t_o > 0) & (np.abs(t_o - t_e) >= AMBIGUITY_MIN_SEPARATION_SD * sd_e)
                 & np.isfinite(t_free) & (s2 > 0) & (w_o >= AMBIGUITY_MIN_WEIGHT))
        add = np.where(other, w_o * (t_o - t_e) ** 2, 0.0)
        bigger = add > extra[f, m]
        extra[f[bigger], m], u_all[f[bigger], m] = add[bigger], u[bigger]
    grown = extra > 0
    out = cov.copy()
    out[grown] += extra[grown][:, None, None] * np.einsum("ni,nj->nij", u_all[grown], u_all[grown])
    return out, int(grown.sum())
