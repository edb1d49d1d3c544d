"""The smoother's schedule, written once over a backend (batgraph.solver.backends):

1. Cleaning (with a robust loss and outlier rejection): the Cauchy loss from the initial track, constant velocity
   at the causal q (the random walk at its sigma); Cauchy's redescending influence leaves a mislabel unfitted.
2. Exclude the observations with |r|^2 > 25 at that solution (:func:`to_exclude`).
3. Each marker's model ("auto") and noise level by the marginal likelihood (batgraph.solver.search) on the rest,
   without the segments; a marker seen on too few frames to show its motion noise takes its segment partners'
   (:func:`_partner_levels`); a constant-velocity q at least :func:`flapping_floor`.
4. Final solves with the chosen loss and the segments until the excluded set is stable (later rounds only the
   markers whose exclusions changed). The first starts from one with the segments SEGMENT_RELAX times softer: from
   the segment-free solution a single-view end can lie nearer the far one of a segment's two depths.
5. The covariances where the data do not pin a point (batgraph.solver.ends); flags |r|^2 > 13.8155.
Variables shared by every marker (``--sync estimate``, ``--refine-rig``, pose covariances; batgraph.solver.shared)
are first estimated at the cleaning solve (what the data do not show is kept as given: :func:`_shown`), steps 2-4
run with them, and the last solve estimates them jointly.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ..measurement import IdealObservations
from ..motion import G_MPS2, WINGBEAT_PROMINENCE, causal_accel_psd, random_walk_sigma_m, wingbeat_peak
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import ends, lm, search, segments, shared
from . import fit as fit_mod
from . import model as mm
from .backends import FAST
from .problem import Loss, gradient
from .threads import one_blas_thread

CLEANING_LOSS = Loss("cauchy")
REJECT_SQ_RESIDUAL = 25.0  # |r| > 5 sigma: at 13.8 an excluded inlier drifts off the solution and stays out
OUTLIER_SQ_RESIDUAL = 13.8155  # chi-square 2 DOF, 99.9 %: the flags reported
REJECTION_ROUNDS = 3
SEGMENT_RELAX = 10.0  # the first solve with the segments has them this many times softer (step 4)


def initial_track(xyz_tri_m: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(p_init, v_init (F, M, 3) [m, m/s], estimated (M,)) from per-frame triangulations (F, M, 3) (NaN where
    < 2 views): linear interpolation over missing frames, constant beyond the ends, np.gradient for v; a marker
    never triangulated is not estimated (NaN)."""
    F, M = xyz_tri_m.shape[:2]
    ok = np.isfinite(xyz_tri_m).all(axis=-1)
    estimated = ok.any(axis=0)
    p = np.full((F, M, 3), np.nan)
    frames = np.arange(F)
    for m in np.flatnonzero(estimated):
        for a in range(3):
            p[:, m, a] = np.interp(frames, frames[ok[:, m]], xyz_tri_m[ok[:, m], m, a])
    return p, gradient(p, fps), estimated


def to_exclude(rejected: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The rejected observations (C, F, M) to leave out: on a point seen once, the view; on one seen by several,
    a rejected view only when another view of it is not rejected (a mislabel is one observation: when every view
    of a point is rejected, the motion prior, not the data, is wrong)."""
    n_ok = (seen & ~rejected).sum(axis=0)
    return rejected & ((seen.sum(axis=0) == 1) | (n_ok >= 1))[None]


class Motion(NamedTuple):
    """The motion model asked for: its name (or "auto"), the random walk's sigma_m [m], a given constant-velocity
    q [m^2/s^3] or None (then chosen from the data)."""

    name: str
    sigma_m: float
    q: float | None


def motion_choice(session: Session, options: Options) -> Motion:
    """The Motion asked for: options first, then session.toml. A given q makes "auto" constant velocity, the model
    q belongs to."""
    name = options.motion_model or session.motion.model
    if name not in (*mm.MODELS, mm.AUTO):
        raise InputError(f"motion model must be one of {', '.join((*mm.MODELS, mm.AUTO))}, got {name!r}")
    q = options.accel_psd_m2_s3 if options.accel_psd_m2_s3 is not None else session.motion.accel_psd_m2_s3
    if name == mm.AUTO and q is not None:
        name = "constant_velocity"
    return Motion(name, random_walk_sigma_m(session.motion, session.fps), None if q is None else float(q))


def run_smoother(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options) -> Estimate:
    """The ``smoother`` method: :func:`run` on batgraph's solver, or on GTSAM's graph with ``options.solver``
    "gtsam" (batgraph.solver.reference, imported then: GTSAM is a slow import)."""
    if options.solver == "gtsam":
        from .reference import REFERENCE

        return run(session, dense, ideal, options, REFERENCE)
    return run(session, dense, ideal, options, FAST)


def run(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options, backend) -> Estimate:
    """The ``smoother`` method on ``backend`` (module docstring). Estimate: xyz (F, M, 3), cov (F, M, 3, 3) (NaN
    for markers never triangulated), outlier flags (C, F, M), info (figures for summary.json)."""
    with one_blas_thread():
        return _run(session, dense, ideal, options, backend)


def _run(session, dense, ideal, options, backend) -> Estimate:
    t0 = time.perf_counter()
    motion = motion_choice(session, options)
    fps, rig = session.fps, session.rig
    triangulated = dlt_points(rig, ideal)
    p_init, v_init, estimated = initial_track(triangulated, fps)
    C, F, M = ideal.seen.shape
    reject = options.outlier_rejection and options.robust != "none"
    info = {"solver": backend.name, "motion_model": motion.name, "robust": options.robust, "robust_k": options.robust_k,
            "outlier_rejection": reject}
    if not estimated.any():
        return Estimate("smoother", np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan),
                        np.zeros((C, F, M), bool), time.perf_counter() - t0, info)
    base = fit_mod.Setup(ideal, rig, fps, Loss(options.robust, options.robust_k), p_init,
                         segments.pairs_of(session.rigid, dense.markers), session.rigid_sigma_m)
    spec = shared_variables(session, options)
    poses_asked = bool(spec.pose.any())
    excluded, start = np.zeros((C, F, M), bool), (p_init, v_init, None)
    theta, setup = np.zeros(spec.n), base
    if reject or spec.n:
        cleaning_q = causal_accel_psd(session.motion, fps)
        excluded, start, theta, spec, info["cleaning"] = _clean(base, backend, motion, cleaning_q, spec, reject,
                                                                options.refine_rig)
        setup = shared.applied(base, spec, theta)
    models, levels, start, figures = _choose(setup.without(excluded), backend, motion, start,
                                             flapping_floor(triangulated, fps), options.progress, dense.markers)
    info.update(figures)
    fit, excluded, rounds, stable = _final(setup, backend, models, levels, start, excluded, reject)
    if spec.n:
        fit, theta, cov_theta, spec, info["shared_steps"] = _solve_shared(base.without(excluded), backend, models,
                                                                          levels, fit, spec, theta)
        setup = shared.applied(base, spec, theta)
        info["rig_refined"] = _rig_figures(spec, theta, cov_theta, rig)
    fit.cov, widened = ends.widen(setup.without(excluded), backend, models, levels, fit)
    info.update(widened)
    flags = np.nan_to_num(fit_mod.sq_residuals(setup, fit), nan=0.0) > OUTLIER_SQ_RESIDUAL
    info.update(_figures(fit, models, dense.markers, setup, rounds, excluded, reject))
    if reject:
        info["rejection_converged"] = stable
    est = Estimate("smoother", fit.xyz, fit.cov, flags, time.perf_counter() - t0, info)
    if spec.n:
        est.rig = rig_used(rig, spec, theta, cov_theta)
    elif poses_asked:  # the poses kept as given: OUT/rig.toml is still the rig to reuse
        est.rig = rig
    return est


def _solve_shared(setup, backend, models, levels, fit, spec: shared.Shared, theta: np.ndarray) -> tuple:
    """shared.solve from the final fit: (fit, theta, its covariance, spec, steps). A readout that ends below 0 is held
    at its known value (0 unless calibration.toml gives one) and the rest solved again: a rolling shutter reads down
    the image, so a negative readout is a global shutter's noise (the MCSC rig: -1.6 +- 3.9 ms), and offsets solved
    with it would not be those of the rig.toml that cannot state it."""
    fit, theta, cov, _, steps = shared.solve(setup, backend, models, levels, fit, spec, theta)
    d_off, d_ro, d_pose = spec.split(theta)
    known = np.array([cam.readout_s for cam in setup.rig])
    held = replace(spec, readout=spec.readout & (known + d_ro >= 0))
    if (held.readout == spec.readout).all() or not held.n:
        return fit, theta, cov, spec, steps
    fit, theta, cov, _, more = shared.solve(setup, backend, models, levels, (fit.xyz, fit.velocity, fit.acceleration),
                                            held, held.join(d_off, d_ro, d_pose))
    return fit, theta, cov, held, steps + more


def shared_variables(session: Session, options: Options) -> shared.Shared:
    """The variables shared by every marker (batgraph.solver.shared): with ``sync`` each camera's time offset but the
    first's (the session clock stays the first camera's, as DLTdv's and Argus's) and one readout per sensor mode; the
    poses of cameras with a pose covariance, or of every camera with ``refine_rig`` (prior REFINE_SD where none)."""
    rig = session.rig
    C = len(rig)
    sync = options.estimates_sync(session)
    pose = np.array([options.refine_rig or c.pose_cov is not None for c in rig])
    default = np.diag(np.repeat(np.square(REFINE_SD), 3))
    cov = np.stack([c.pose_cov if c.pose_cov is not None else default for c in rig])
    modes = [(c.size_wh, c.frame_rate(session.fps)) for c in rig]
    mode = np.array([modes.index(m) for m in modes])  # cameras of one image size and rate read out alike
    return shared.Shared(np.full(C, sync) & (np.arange(C) > 0), np.full(C, sync), pose, cov, mode)


def flapping_floor(xyz_m: np.ndarray, fps: float) -> float:
    """The least constant-velocity q [m^2/s^3] of a marker on an animal that flaps (0 when the triangulated tracks
    (F, M, 3) [m], NaN where not triangulated, do not move periodically, batgraph.motion.wingbeat_peak; tracks
    extrapolated through gaps and ends can hide the peak): that of the
    heave of a body whose lift swings by one body weight over the stroke, amplitude g / w^2 at the wingbeat
    w = 2 pi f, whose acceleration taken as white over a band ~w wide gives q ~ (g / w^2)^2 w^3 = g^2 / w (3.8 at
    4 Hz, 1.0 at 15 Hz). A body bobbing by less than the pixel noise otherwise gets a straight track whose
    ellipsoids miss it (the dorsal scene: observed points 97.0 % covered with it, 81.4 % without)."""
    peak = wingbeat_peak(xyz_m, fps)
    if peak is None or peak[1] < WINGBEAT_PROMINENCE:
        return 0.0
    return G_MPS2**2 / (2 * np.pi * peak[0])


# The pose prior of --refine-rig where a camera has no pose covariance: (rotation [rad], translation [m]) std; a
# rig bumped between its calibration and the flight.
REFINE_SD = (np.radians(1.0), 0.02)


def rig_used(rig, spec: shared.Shared, theta: np.ndarray, cov: np.ndarray):
    """The rig with the estimated timing and poses (and their standard deviations, covariances) written in."""
    d_off, d_ro, _ = spec.split(theta)
    sd = np.sqrt(np.diag(cov))
    cols = spec.columns
    moved = shared.applied_rig(rig, spec, theta)
    timed = spec.offset.any() or spec.readout.any()
    cams = []
    for c, cam in enumerate(moved):
        change = {}
        if timed:
            change.update(time_offset_s=cam.time_offset_s + d_off[c], readout_s=max(cam.readout_s + d_ro[c], 0.0),
                          time_offset_sd_s=float(sd[cols["offset"][c]]) if spec.offset[c] else 0.0,
                          readout_sd_s=float(sd[cols["readout"][c]]) if spec.readout[c] else 0.0)
        if spec.pose[c]:
            k = cols["pose"][c]
            change["pose_cov"] = cov[k:k + 6, k:k + 6]
        cams.append(replace(cam, **change))
    return type(rig)(cams, world_mirror=rig.world_mirror)


def _rig_figures(spec: shared.Shared, theta: np.ndarray, cov: np.ndarray, rig) -> dict:
    """Per camera: the timing corrections and pose moves with their standard deviations (summary.json)."""
    d_off, d_ro, d_pose = spec.split(theta)
    sd = np.sqrt(np.diag(cov))
    cols = spec.columns
    timed = spec.offset.any() or spec.readout.any()
    out = {}
    for c, cam in enumerate(rig):
        row = {}
        if timed:  # every camera, the clock's and those whose readout is held included
            row.update(time_offset_s=float(cam.time_offset_s + d_off[c]), readout_s=float(cam.readout_s + d_ro[c]),
                       time_offset_sd_s=float(sd[cols["offset"][c]]) if spec.offset[c] else 0.0,
                       readout_sd_s=float(sd[cols["readout"][c]]) if spec.readout[c] else 0.0)
        if spec.pose[c]:
            k = cols["pose"][c]
            row.update(rotation_deg=float(np.degrees(np.linalg.norm(d_pose[c, :3]))),
                       translation_m=float(np.linalg.norm(d_pose[c, 3:])),
                       rotation_sd_deg=float(np.degrees(np.sqrt(np.trace(cov[k:k + 3, k:k + 3]) / 3))),
                       translation_sd_m=float(np.sqrt(np.trace(cov[k + 3:k + 6, k + 3:k + 6]) / 3)))
        out[cam.name] = row
    return out


def _clean(setup, backend, motion, cleaning_q, spec, reject, refine_rig) -> tuple:
    """Steps 1-2 (and the shared variables' first estimate) at constant velocity with a given q, else
    ``cleaning_q`` [m^2/s^3] (the random walk at its sigma): (excluded (C, F, M), the next solves' start, theta,
    spec (what the data do not show dropped, :func:`_shown`; the poses only with ``refine_rig``), figures)."""
    est = setup.estimated
    name, sigma_m, q = motion
    clean_name, level = ("random_walk", sigma_m) if name == "random_walk" else (
        "constant_velocity", q if q is not None else cleaning_q)
    models, levels = np.where(est, clean_name, None), np.full(len(est), level)
    loss = Loss(CLEANING_LOSS.name, setup.loss.k) if reject else setup.loss
    cleaning = replace(setup, loss=loss)
    fit = backend.fit(cleaning, models, levels, (setup.p_init, None, None), lm.LOOSE, covariances=False,
                      with_segments=False)
    theta, shown = np.zeros(spec.n), {}
    if spec.n:
        first = fit
        fit, theta, cov, _, _ = shared.solve(cleaning, _NoCovariances(backend), models, levels, first, spec)
        kept, shown = _shown(setup.rig, spec, theta, cov, refine_rig)
        if (kept.pose != spec.pose).any():
            spec, theta, fit = kept, np.zeros(kept.n), first if not kept.n else fit
            if spec.n:
                fit, theta, _, _, _ = shared.solve(cleaning, _NoCovariances(backend), models, levels,
                                                   (fit.xyz, fit.velocity, None), spec)
    at = shared.applied(setup, spec, theta)
    excluded = np.zeros(setup.ideal.seen.shape, bool)
    if reject:
        excluded = to_exclude(np.nan_to_num(fit_mod.sq_residuals(at, fit), nan=0.0) > REJECT_SQ_RESIDUAL,
                              setup.ideal.seen)
    v = fit.velocity if clean_name != "random_walk" else gradient(setup.p_init, setup.fps)
    figures = {"loss": loss.name, "robust_k": setup.loss.k, "iterations": int(fit.iterations.max()),
               "n_flagged": int(excluded.sum()), mm.LEVEL_NAME[clean_name]: level, **shown}
    return excluded, (fit.xyz, v, None), theta, spec, figures


def _shown(rig, spec: shared.Shared, theta: np.ndarray, cov: np.ndarray, judge_poses: bool) -> tuple:
    """The shared variables the data show, and figures: with ``judge_poses`` (--refine-rig), the poses moved only
    where the evidence favours the move (shared.poses_evidence: an exact rig would otherwise take on the solve's
    noise, and the world frame with it). Poses that are variables only for their calibrated covariance stay
    variables: their uncertainty is wanted. Offsets and readouts always stay: where the data cannot tell a readout,
    its standard deviation says so and the offsets' include it."""
    if not (judge_poses and spec.pose.any()):
        return spec, {}
    evidence = shared.poses_evidence(rig, spec, theta, cov)
    as_given = evidence["log_bayes_factor"] > 0
    kept = replace(spec, pose=np.zeros_like(spec.pose)) if as_given else spec
    return kept, {"poses": {**evidence, "kept_as_given": bool(as_given)}}


class _NoCovariances:
    """A backend whose fits skip the covariances and the segments (the shared variables' first estimate)."""

    def __init__(self, backend):
        self.backend, self.name = backend, backend.name

    def fit(self, setup, models, levels, start, settings=lm.LOOSE, covariances=False, with_segments=False):
        return self.backend.fit(setup, models, levels, start, settings, False, False)


def _choose(setup, backend, motion, start, floor, progress, names) -> tuple:
    """Step 3: (models (M,), levels (M,), the final solves' start, figures for summary.json); floor: the least
    constant-velocity q chosen from the data [m^2/s^3] (:func:`flapping_floor`)."""
    name, sigma_m, q = motion
    estimated = setup.estimated
    M = len(estimated)
    if name == "random_walk" or q is not None:
        level = sigma_m if name == "random_walk" else q
        figures = {mm.LEVEL_NAME[name]: level, "noise_source": "given",
                   "motion_model_per_marker": {names[m]: name for m in np.flatnonzero(estimated)}}
        return np.where(estimated, name, None), np.full(M, level), start, figures
    candidates = mm.AUTO_CANDIDATES if name == mm.AUTO else (name,)
    groups = [members for members, _ in segments.groups(setup.pairs, estimated)]
    choice = backend.choose(setup, start, candidates, groups, progress)
    models = np.where(estimated, choice.model, None)
    own = choice.level.copy()
    choice.level = _partner_levels(setup, choice, estimated)
    borrowed = estimated & (choice.level != own)
    raised = (models == "constant_velocity") & (choice.level < floor)
    choice.level[raised] = floor
    figures = _choice_figures(choice, models, names, candidates)
    if borrowed.any():
        figures["level_from_segment_partners"] = [names[m] for m in np.flatnonzero(borrowed)]
    if raised.any():
        figures["accel_psd_floor"] = {"accel_psd_m2_s3": floor, "markers": [names[m] for m in np.flatnonzero(raised)]}
    x = np.full(start[0].shape[:2] + (9,), np.nan)
    for n in candidates:  # the search's solutions at the chosen models and levels: the final solves' start
        sol = choice.solution[n]
        x[..., :sol.shape[-1]] = np.where(np.isfinite(sol), sol, x[..., :sol.shape[-1]])
    p, v, a = search.motion_of(x, setup.fps)
    have = np.isfinite(p).all(axis=(0, 2))[None, :, None]
    p = np.where(have, p, start[0])
    v = np.where(have & np.isfinite(v).all(axis=(0, 2))[None, :, None], v,
                 start[1] if start[1] is not None else gradient(p, setup.fps))
    return models, choice.level, (p, v, np.where(np.isfinite(a), a, gradient(v, setup.fps))), figures


def _partner_levels(setup, choice, estimated: np.ndarray) -> np.ndarray:
    """Levels (M,): a marker seen on fewer frames than its motion model needs to show any motion noise (ORDER + 2:
    a constant-velocity track fits two frames exactly, a constant-acceleration one three, so nothing in its data
    measures the noise and its evidence rises to the stiffest level searched) takes its segment partners' level
    (segments.partner_levels); the others keep their own."""
    frames = setup.ideal.seen.any(axis=0).sum(axis=0)
    need = np.array([mm.ORDER[n] + 2 if n is not None else 0 for n in choice.model])
    return segments.partner_levels(choice.level, estimated & (frames < need), setup.pairs)


def _final(setup, backend, models, levels, start, excluded, reject) -> tuple:
    """Step 4: (the last fit, the excluded set, iterations per round, whether the excluded set was stable)."""
    rounds, fit, stable = [], None, True
    redo = models != None  # noqa: E711  (an object array)
    if len(setup.pairs):  # the segments' continuation (module docstring, step 4)
        soft = replace(setup.without(excluded), rigid_sigma_m=setup.rigid_sigma_m * SEGMENT_RELAX)
        fit = backend.fit(soft, models, levels, start, covariances=False)
        start, fit = (fit.xyz, fit.velocity, fit.acceleration), None
    for r in range(REJECTION_ROUNDS if reject else 1):
        solved = backend.fit(setup.without(excluded), np.where(redo, models, None), levels, start)
        fit = solved if fit is None else fit.merge(solved, redo)
        rounds.append(int(solved.iterations[redo].max(initial=0)))
        if not reject:
            break
        again = to_exclude(np.nan_to_num(fit_mod.sq_residuals(setup, fit), nan=0.0) > REJECT_SQ_RESIDUAL,
                           setup.ideal.seen)
        stable = bool((again == excluded).all())
        if r == REJECTION_ROUNDS - 1 or stable:
            break
        redo = segments.with_groups((again != excluded).any(axis=(0, 1)), setup.pairs, models != None)  # noqa: E711
        excluded, start = again, (fit.xyz, fit.velocity, fit.acceleration)
    return fit, excluded, rounds, stable


def _choice_figures(choice, models, names, candidates) -> dict:
    est = [m for m in range(len(models)) if models[m] is not None]
    out = {"noise_source": "data", "motion_model_per_marker": {names[m]: str(models[m]) for m in est},
           "noise_solves": {n: int(choice.n_solves[n]) for n in candidates}}
    for n in candidates:
        out[mm.LEVEL_NAME[n]] = {names[m]: float(choice.level[m]) for m in est if models[m] == n}
    if len(candidates) > 1:
        out["log_evidence_per_marker"] = {names[m]: {n: float(choice.evidence_by_model[n][m]) for n in candidates}
                                          for m in est}
    return out


def _figures(fit, models, names, setup, rounds, excluded, reject) -> dict:
    est = models != None  # noqa: E711
    out = {"iterations": int(sum(rounds)), "final_error": float(fit.cost[est].sum()),
           "markers_not_converged": int((est & ~fit.converged).sum())}
    if (models == "constant_acceleration").any():
        out["acceleration_rms_mps2"] = {names[m]: float(np.sqrt(np.mean(np.sum(fit.acceleration[:, m] ** 2, -1))))
                                        for m in np.flatnonzero(models == "constant_acceleration")}
    if reject:
        out.update(iterations_per_round=rounds, rejected=int(excluded.sum()))
    if len(fit.pairs):
        out["rigid_sigma_m"] = setup.rigid_sigma_m
        excess = segments.triangulated_excess(setup, fit.pairs)
        out["segments"] = {f"{names[a]}-{names[b]}": {
            "length_m": float(L), "length_sigma_m": float(sd), "triangulated_excess_m": float(e),
            "scatter_rms_m": float(np.sqrt(np.mean((np.linalg.norm(fit.xyz[:, a] - fit.xyz[:, b], axis=-1) - L) ** 2)))}
            for (a, b), L, sd, e in zip(fit.pairs, fit.length_m, fit.length_sd_m, excess, strict=True)}
    return out
