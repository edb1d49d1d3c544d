"""The smoother's schedule on the fast path (fixed rig): cleaning, rejection, model and noise choice, final solves.

The same schedule as the GTSAM reference (batgraph.graph.smoother, whose docstring states it step by step),
with every solve done by the numpy backend: batgraph.graph.fast (markers one by one, vectorised) and, when
the session declares rigid segments, batgraph.graph.rigid (markers joined by segments solved jointly).
Segment-length factors enter the final solves only: the cleaning solve (it spots mislabels, one marker at a
time) and the noise search (each marker's evidence, which segments would make inseparable) run without
them; markers joined by segments share one motion model, chosen by their summed evidence ("auto").
"""

from __future__ import annotations

import time

import numpy as np

from ..camera import Rig
from ..measurement import IdealObservations
from ..motion import WINGBEAT_BAND_HZ, WINGBEAT_PROMINENCE, wingbeat_frequency, wingbeat_peak
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import cost as spec
from . import noise, rigid
from .ends import widen_ends
from .fast import LOOSE_STEP_TOL_M, choose_model_per_marker, one_blas_thread, searched_start, solve_fast


def _rejected(rig: Rig, ideal: IdealObservations, xyz_m: np.ndarray) -> np.ndarray:
    """What the rejection schedule leaves out at ``xyz_m`` (F, M, 3) [m]: observations of ``ideal`` with
    |r|^2 > spec.REJECT_SQ_RESIDUAL (plain Gaussian whitening) through spec.to_exclude, (C, F, M)."""
    r2 = np.nan_to_num(spec.whitened_sq_residuals(rig, ideal, xyz_m), nan=0.0)
    return spec.to_exclude(r2 > spec.REJECT_SQ_RESIDUAL, ideal.seen)


def run_smoother_fast(session: Session, dense: DenseObservations, ideal: IdealObservations,
                      options: Options) -> Estimate:
    """The ``smoother`` method on the fast path (fixed rig); same answer as the GTSAM batch smoother.

    Follows batgraph.graph.smoother.run_smoother step by step, including its outlier-rejection
    schedule (Cauchy cleaning solve, exclusion set D, the model ("auto": constant velocity or
    acceleration) and its noise chosen per marker without D by :func:`choose_model_per_marker`, final
    rounds until D is stable, the first from the search's solutions (fast.searched_start); see that module's
    docstring), each solve being fast.solve_per_model
    (solve_fast per model) with the same start, or with ``[markers] rigid`` segments rigid.solve_rigid
    (the final rounds; module docstring). "wingbeat": per marker constant velocity or oscillating (at
    :func:`wingbeat_hz`; figures wingbeat_hz, wingbeat_hz_source, oscillation_sigma_m).
    Figures: motion_model (as asked), motion_model_per_marker {name: model}, accel_psd_m2_s3 /
    jerk_psd_m2_s5 {name: level} of the markers of each model,
    log_evidence_per_marker (auto), acceleration_rms_mps2 of constant-acceleration markers
    (noise.model_figures), and with segments rigid_sigma_m and segments {"a-b": {length_m,
    length_sigma_m, scatter_rms_m}} (rigid.solve_rigid).
    Falls back to run_smoother when any camera has a pose covariance.
    """

    with one_blas_thread():
        return _run(session, dense, ideal, options)


def _run(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options) -> Estimate:
    if any(cam.pose_cov is not None for cam in session.rig):
        from .smoother import run_smoother  # the GTSAM reference (camera variables); imports GTSAM

        return run_smoother(session, dense, ideal, options)
    t0 = time.perf_counter()
    rig, fps, robust, k = session.rig, session.fps, options.robust, options.robust_k
    model, sigma_m, q = noise.motion_choice(session, options)
    tri = dlt_points(rig, ideal)
    p_init, v_init, estimated = spec.initial_track(tri, fps)
    reject = options.outlier_rejection and robust != "none"
    figures: dict = {"solver": "fast", "motion_model": model, "robust": robust, "robust_k": k,
                     "outlier_rejection": reject}
    if model != spec.WINGBEAT:  # a periodic motion this model takes for noise: the user is told
        figures.update(periodic_advice(tri, fps, model))
    C, F, M = ideal.seen.shape
    if not estimated.any():  # nothing triangulated anywhere: every output is NaN
        return Estimate("smoother", np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan),
                        np.zeros((C, F, M), bool), time.perf_counter() - t0, figures)
    markers = np.flatnonzero(estimated)
    pairs = rigid.segment_pairs(session.rigid, dense.markers)
    groups = [members for members, _ in rigid.groups(pairs, estimated)]
    excluded = np.zeros((C, F, M), bool)
    p_start, v_start, a_start = p_init, v_init, None  # where the next solve starts (a warm start after cleaning)
    if reject:  # steps 1-2: Cauchy from the initial track at q0, D at its solution
        clean, q0 = cleaning_motion(model, sigma_m, q, session)
        xyz0, _, info0 = solve_fast(rig, ideal, p_init, clean, q0, fps, spec.CLEANING_LOSS, k, v_init=v_init,
                                    covariances=False, step_tol_m=LOOSE_STEP_TOL_M)  # only its positions are used
        excluded = _rejected(rig, ideal, xyz0)
        p_start = xyz0
        v_start = v_init if info0["velocity"] is None else info0["velocity"]
        figures["cleaning"] = {"loss": spec.CLEANING_LOSS, "robust_k": k, "iterations": info0["iterations"],
                               "n_flagged": int(excluded.sum())}
        if clean == "constant_velocity":
            figures["cleaning"]["accel_psd_m2_s3"] = q0
    models = np.full(M, None, dtype=object)
    oscillation = None  # the oscillating markers' (model "wingbeat")
    if model == "random_walk" or q is not None:  # one given noise level
        models[markers], level = model, np.full(M, sigma_m if model == "random_walk" else q)
        figures.update({"sigma_m": sigma_m} if model == "random_walk" else noise.q_figures(q))
        figures["motion_model_per_marker"] = {dense.markers[m]: model for m in markers}
    else:  # step 3: model (auto, wingbeat) and noise per marker on the observations left, from the cleaning solution
        candidates = spec.SELECTORS.get(model, (model,))
        hz = None
        if model == spec.WINGBEAT:
            hz, figures["wingbeat_hz_source"] = wingbeat_hz(session, tri)
            figures["wingbeat_hz"] = hz
            if hz is None:  # no frequency to oscillate at: every marker constant velocity, and the user is told
                candidates = ("constant_velocity",)
                figures["wingbeat_left_out"] = NO_WINGBEAT
        models, level, selection = choose_model_per_marker(
            rig, spec.without_observations(ideal, excluded), p_init, v_init, markers, fps, robust, k, candidates,
            p_start, v_start, progress=options.progress, groups=groups, rule=noise.noise_rule(session, options),
            oscillation_hz=hz, q_floor=flapping_floor(figures))
        figures.update(noise.model_figures(models, level, markers, dense.markers, selection, candidates,
                                           figures.get("periodic_motion_hz")))
        if spec.OSCILLATING in candidates:
            oscillation = spec.Oscillation(hz, selection[spec.OSCILLATING]["sigma_m"])
        # the final solve starts where the search solved each marker at its level (the same observations; the
        # first round's iterations, measured: 7 -> 4 at 30 x 180 x 160, 15 -> 3 on the 5-camera sample with
        # "auto"), else where the search started
        p_start, v_start, a_start = searched_start(selection["solution"], p_start, v_start, fps)
    rounds = []
    n_rounds = spec.REJECTION_ROUNDS if reject else 1
    redo, result = estimated, None  # the markers the next round solves; the solution so far
    for r in range(n_rounds):  # step 4: final solves until the rejected set is the excluded one
        solved = rigid.solve_rigid(rig, spec.without_observations(ideal, excluded),
                                   np.where(redo[None, :, None], p_init, np.nan), np.where(redo, models, None), level,
                                   fps, robust, k, pairs, session.rigid_sigma_m, v_init=v_start, p_start=p_start,
                                   a_init=a_start, oscillation=oscillation)
        result = solved if result is None else rigid.merge_solutions(result, solved, redo)
        xyz, cov, info = result
        rounds.append(solved[2]["iterations"])
        again = _rejected(rig, ideal, xyz)
        if r == n_rounds - 1 or (again == excluded).all():
            break
        # a later round solves only the markers whose observations changed, with their segment groups: the
        # others' problems are the same and solved (at 30 x 180 x 160 the second round 0.35-0.43 s -> ms)
        redo = rigid.with_groups((again != excluded).any(axis=(0, 1)), pairs, estimated)
        excluded, p_start, v_start, a_start = again, xyz, info["velocity"], info["acceleration"]
    used = spec.without_observations(ideal, excluded)
    if info["segments"]:  # the second depth a segment allows a single-view point
        cov, figures["depth_ambiguous_points"] = rigid.ambiguity_covariances(
            rig, used, p_init, v_init, models, level, fps, robust, k, info["segments"], xyz, cov,
            oscillation=oscillation)
    cov, ends_figures = widen_ends(rig, used, p_init, models, level, fps, robust, k,
                                   pairs, session.rigid_sigma_m, xyz, cov, oscillation=oscillation)
    if ends_figures:  # the covariances of points seen by < 2 cameras at the track ends, checked on the track (ends.py)
        figures["track_ends"] = ends_figures
    outlier = spec.outlier_flags(rig, ideal, xyz)
    figures.update(iterations=sum(rounds), final_error=info["cost"], logdet=info["logdet"],
                   markers_not_converged=int((info["estimated"] & ~info["converged"]).sum()))
    if (models == "constant_acceleration").any():  # the accelerations the model estimated [m/s^2]
        figures["acceleration_rms_mps2"] = {
            dense.markers[m]: float(np.sqrt(np.mean(np.sum(info["acceleration"][:, m] ** 2, axis=-1))))
            for m in markers if models[m] == "constant_acceleration"}
    if info["segments"]:
        figures["rigid_sigma_m"] = session.rigid_sigma_m
        excess = rigid.triangulated_excess(rig, ideal, [s["pair"] for s in info["segments"]])
        figures["segments"] = {f"{dense.markers[s['pair'][0]]}-{dense.markers[s['pair'][1]]}":
                               {**{k_: s[k_] for k_ in ("length_m", "length_sigma_m", "scatter_rms_m")},
                                "triangulated_excess_m": float(e)}
                               for s, e in zip(info["segments"], excess, strict=True)}
    if reject:
        figures["iterations_per_round"] = rounds
        figures["rejected"] = int(excluded.sum())
        figures["rejection_converged"] = bool((again == excluded).all())
    return Estimate("smoother", xyz, cov, outlier, time.perf_counter() - t0, figures)


#: The smoother's note (figure ``wingbeat_left_out``, a warning in summary.json) when "wingbeat" finds no frequency.
NO_WINGBEAT = ("motion model wingbeat: no wingbeat found in the triangulated tracks (their periodogram has no peak "
               f"inside {WINGBEAT_BAND_HZ[0]:g}-{WINGBEAT_BAND_HZ[1]:g} Hz, or the take is too short for two cycles): "
               "every marker uses constant velocity; set [motion] flap_hz in session.toml if the animal flaps")


def periodic_advice(xyz_tri_m: np.ndarray, fps: float, model: str) -> dict:
    """When the triangulated tracks (F, M, 3) [m] move periodically (motion.wingbeat_peak: an interior peak
    at least WINGBEAT_PROMINENCE times the periodogram's median) and ``model`` is not "wingbeat": figures
    periodic_motion_hz and wingbeat_advice, one line that summary.json lists among its warnings; else {}.
    Why: constant velocity (and the other models but "wingbeat") takes a periodic motion it cannot follow for
    noise, and where that motion is small next to the pixel noise (a body bobbing with the wingbeat) its
    evidence picks a straight track whose ellipsoids miss the truth (docs/accuracy.md, the dorsal scene)."""
    peak = wingbeat_peak(xyz_tri_m, fps)
    if peak is None or peak[1] < WINGBEAT_PROMINENCE:
        return {}
    hz = peak[0]
    words = model.replace("_", " ") + (" (constant velocity or acceleration per marker)" if model == spec.AUTO else "")
    return {"periodic_motion_hz": hz, "wingbeat_advice": (
        f"the tracks move periodically at {hz:.1f} Hz (a wingbeat?), which the {words} "
        "motion model takes for noise: markers that move with it a little, like a body bobbing with the wingbeat, can "
        "get 95 % ellipsoids that hold their truth less often" + ("" if model == "random_walk" else (
            f" (a constant-velocity q chosen from the data is kept >= that of a {noise.flapping_heave_m(hz) * 1e3:.2g} "
            f"mm heave at this frequency, {noise.flapping_q_floor(hz):.2g} m^2/s^3: a lift that swings by "
            f"{noise.FLAPPING_LIFT_SWING:g} body weight over the stroke)")) +
        "; see the hold-out dorsal-marker scene in docs/accuracy.md; --motion wingbeat ([motion] model = "
        "\"wingbeat\") models it, at several times the smoother's time")}


def flapping_floor(figures: dict) -> float | None:
    """The constant-velocity q floor (noise.flapping_q_floor) [m^2/s^3] when :func:`periodic_advice` found a wingbeat
    (its figures in ``figures``), else None."""
    hz = figures.get("periodic_motion_hz")
    return None if hz is None else noise.flapping_q_floor(hz)


def wingbeat_hz(session: Session, xyz_tri_m: np.ndarray) -> tuple[float | None, str]:
    """The oscillating model's frequency [Hz] and where it came from: session.toml's ``[motion] flap_hz`` when
    given (and > 0), else measured from the triangulated tracks (F, M, 3) [m] (motion.wingbeat_frequency;
    None when the take is too short to hold two cycles of any frequency it looks for, or the periodogram's
    maximum is at an end of its band)."""
    if session.motion.flap_hz:
        return float(session.motion.flap_hz), "session"
    return wingbeat_frequency(xyz_tri_m, session.fps), "measured"


def cleaning_motion(model: str, sigma_m: float, q: float | None, session: Session) -> tuple[str, float]:
    """The motion model and noise level of the rejection schedule's cleaning solve (step 1): the random
    walk at sigma_m for a random walk; otherwise constant velocity at the given q, else the causal q
    (noise.causal_accel_psd), also for "auto" and constant acceleration (whose jerk PSD is chosen after
    cleaning; the cleaning solve only needs a plausible prior to spot mislabels)."""
    if model == "random_walk":
        return model, sigma_m
    return "constant_velocity", q if q is not None else noise.causal_accel_psd(session)
