"""Speed and memory of batgraph's estimators on the paper-scale flight (30 cameras, 180 markers, 160 frames).

Prints a table and ratios measured in this run (medians over repeats); nothing here is asserted. Run by
``make bench``; BENCHMARKS.md records a run. Sections:
(a) the smoother's fast path (batgraph.graph.fast) against a straightforward GTSAM build-and-solve of
    the same graph (one Python loop adding factors, LM, gtsam.Marginals for every point), checking
    that both reach the same optimum; (a') the same with segment-length factors on the simulator's bones
    (batgraph.graph.rigid) against without;
(b) the filters' frames per second (iSAM2 and the fast per-marker filter) and their difference;
(c) per-frame triangulation time;
(d) how the paper's stacked EKF's time and memory grow with the number of markers;
(e) whole commands as a user runs them (first): ``batgraph reconstruct`` of the bundled 5-camera flight
    with the default methods and with ``--methods triangulate``, ``batgraph --help``, the default
    reconstruct of a simulated session of the scene's size (seed 3), ``--motion wingbeat`` on a simulated
    5-camera flight (the accuracy study's, seed 1: 14 markers joined by its bones), and a batch of 16 small simulated
    sessions (10 cameras x 30 markers x 120 frames) with 1 and with 2 workers; each a fresh process:
    wall time, CPU time (user + system) and peak resident memory, medians over
    repeats; with ``--baseline-tree DIR`` (an older checkout, e.g. ``git worktree add /tmp/old HEAD~5``)
    the same commands from that tree, run alternately, and the new / old ratios.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import statistics
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchproc import BATCH_SESSIONS, ROOT, SAMPLE, machine, run_process, simulate_sessions  # noqa: E402

from batgraph.graph import factors, fast, noise, rigid, schedule  # noqa: E402
from batgraph.measurement import IdealObservations, ideal_observations  # noqa: E402
from batgraph.result import Options  # noqa: E402
from batgraph.session import Session, dense_observations  # noqa: E402
from batgraph.simulate import simulate_flight  # noqa: E402
from batgraph.triangulate import dlt_points, triangulate_ideal  # noqa: E402

EKF_MARKERS = (10, 20, 45, 90, 180)


def timed(fn, repeats: int):
    """(median wall time [s], all times, last result) of ``fn()`` over ``repeats`` runs."""
    times, out = [], None
    for _ in range(repeats):
        gc.collect()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out



# ----- (a) the smoother ------------------------------------------------------------------------------
def gtsam_straightforward(session: Session, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                          model: str, level: float, robust: str, robust_k: float) -> dict:
    """The baseline: build the smoother's graph in one Python loop, default LM (spec tolerances), Marginals.

    Same factors as batgraph.graph.smoother (TriangulationFactorCal3_S2 with the mapped pixel noise and
    GTSAM's robust model, BetweenFactorPoint3 or the constant-velocity factor, weak priors), but built
    the obvious way: a loop over markers, frames and cameras, one factor at a time. LM parameters are
    GTSAM's defaults except the stopping rule, which the cost spec fixes (relative decrease 1e-12).
    Returns xyz (F, M, 3), cov (F, M, 3, 3), and the time of each stage.
    """
    import gtsam

    t0 = time.perf_counter()
    C, F, M = ideal.seen.shape
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    mm = factors.MotionModel(model, 1.0 / session.fps, sigma_m=level if model == "random_walk" else None,
                             accel_psd_m2_s3=level if model == "constant_velocity" else None)
    motion = factors.MotionFactors(mm)
    cams = [factors.gtsam_camera(c) for c in session.rig]
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for m in np.flatnonzero(estimated):
        m = int(m)
        for f in factors.prior_factors(mm, m, 0, p_init[0, m]):
            graph.push_back(f)
        for k in range(F):
            values.insert(factors.p_key(m, k), p_init[k, m])
            if mm.has_velocity:  # the graph's velocity variable is u = v dt [m per frame] (factors.v_key)
                values.insert(factors.v_key(m, k), v_init[k, m] * mm.dt_s)
            if k + 1 < F:
                graph.push_back(motion.between(m, k))
            for c in np.flatnonzero(ideal.seen[:, k, m]):
                graph.push_back(gtsam.TriangulationFactorCal3_S2(
                    cams[c], ideal.uv_px[c, k, m], factors.pixel_noise(ideal.cov_px2[c, k, m], robust, robust_k),
                    factors.p_key(m, k)))
    t1 = time.perf_counter()
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    sol = optimizer.optimize()
    t2 = time.perf_counter()
    marginals = gtsam.Marginals(graph, sol)
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    for m in np.flatnonzero(estimated):
        for k in range(F):
            key = factors.p_key(int(m), k)
            xyz[k, m] = sol.atPoint3(key)
            cov[k, m] = marginals.marginalCovariance(key)
    t3 = time.perf_counter()
    return {"xyz": xyz, "cov": cov, "build_s": t1 - t0, "solve_s": t2 - t1, "marginals_s": t3 - t2,
            "total_s": t3 - t0, "iterations": int(optimizer.iterations()), "error": graph.error(sol),
            "n_factors": int(graph.size()), "graph": graph}


def gtsam_marginals_at(graph, xyz: np.ndarray, velocity: np.ndarray | None, markers: np.ndarray,
                       dt_s: float) -> tuple[np.ndarray, float]:
    """gtsam.Marginals of every p[m, k] with the graph linearised at a given solution, (F, M, 3, 3)."""
    import gtsam

    F, M = xyz.shape[:2]
    values = gtsam.Values()
    for m in markers:
        for k in range(F):
            values.insert(factors.p_key(int(m), k), xyz[k, m])
            if velocity is not None:
                values.insert(factors.v_key(int(m), k), velocity[k, m] * dt_s)
    marginals = gtsam.Marginals(graph, values)
    cov = np.full((F, M, 3, 3), np.nan)
    for m in markers:
        for k in range(F):
            cov[k, m] = marginals.marginalCovariance(factors.p_key(int(m), k))
    return cov, graph.error(values)


def fast_smoother(session: Session, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                  model: str, level: float, robust: str, robust_k: float) -> dict:
    """The fast path on the same problem from the same initial track."""
    xyz, cov, info = fast.solve_fast(session.rig, ideal, p_init, model, level, session.fps, robust, robust_k,
                                     v_init=v_init)
    return {"xyz": xyz, "cov": cov, "velocity": info["velocity"], "iterations": info["iterations"],
            "error": info["cost"]}


def rel_cov_diff(cov: np.ndarray, ref: np.ndarray) -> float:
    """Largest |cov - ref| relative to each 3x3 block's largest entry."""
    return float(np.nanmax(np.abs(cov - ref) / np.abs(ref).max(axis=(-1, -2), keepdims=True)))


def bench_smoother(session: Session, dense, ideal: IdealObservations, args) -> list[tuple[str, str, str]]:
    """(a): the fast path vs the straightforward GTSAM baseline, same graph, same initial track."""
    C, F, M = ideal.seen.shape
    opt = Options(progress=False)
    model = session.motion.model
    rows = []
    t_init, _, tri = timed(lambda: dlt_points(session.rig, ideal), 1)
    p_init, v_init, estimated = factors.initial_track(tri, session.fps)
    markers = np.flatnonzero(estimated)
    if model == "constant_velocity":
        t_q, _, (level, _) = timed(lambda: fast.choose_accel_psd_fast(
            session.rig, ideal, p_init, v_init, markers, session.fps, opt.robust, opt.robust_k), 1)
        rows.append(("smoother: choose q (fast path, 8 markers, ~18 solves)", f"{t_q:.2f} s",
                     f"q = {level:.4g} m^2/s^3, used by both solvers below"))
    else:
        level = noise.motion_choice(session, opt)[1]
    print(f"(a) smoother: {model}, {'q' if model == 'constant_velocity' else 'sigma_m'} = {level:.4g}, "
          f"robust {opt.robust} k = {opt.robust_k}; initial track (triangulation + interpolation) {t_init:.2f} s")
    args_ = (model, level, opt.robust, opt.robust_k)
    t_fast, times, a = timed(lambda: fast_smoother(session, ideal, p_init, v_init, *args_), args.repeats)
    print(f"    fast path, all {len(markers)} markers: {t_fast:.2f} s (median of {args.repeats}: "
          f"{', '.join(f'{t:.2f}' for t in times)}), {a['iterations']} iterations")
    rows.append((f"smoother fast path: {len(markers)} markers, solve + covariances", f"{t_fast:.2f} s",
                 f"median of {args.repeats}; {a['iterations']} LM iterations (max over markers)"))
    sub = markers if args.baseline_markers is None else markers[
        np.unique(np.linspace(0, len(markers) - 1, args.baseline_markers).round().astype(int))]
    nan_other = np.full_like(p_init, np.nan)
    p_sub, v_sub = nan_other.copy(), nan_other.copy()
    p_sub[:, sub], v_sub[:, sub] = p_init[:, sub], v_init[:, sub]
    t_base, _, b = timed(lambda: gtsam_straightforward(session, ideal, p_sub, v_sub, *args_), 1)
    if len(sub) < len(markers):
        t_fast_sub, _, a_sub = timed(lambda: fast_smoother(session, ideal, p_sub, v_sub, *args_), args.repeats)
    else:
        t_fast_sub, a_sub = t_fast, a
    dx = float(np.nanmax(np.abs(a_sub["xyz"][:, sub] - b["xyz"][:, sub])))
    dcov = rel_cov_diff(a_sub["cov"][:, sub], b["cov"][:, sub])
    print(f"    GTSAM straightforward, {len(sub)} markers: {t_base:.1f} s = build {b['build_s']:.1f} + LM "
          f"{b['solve_s']:.1f} ({b['iterations']} iterations, {b['n_factors']} factors) + Marginals "
          f"{b['marginals_s']:.1f}; fast path on the same markers {t_fast_sub:.2f} s")
    cov_at, err_at = gtsam_marginals_at(b["graph"], a_sub["xyz"], a_sub["velocity"], sub, 1.0 / session.fps)
    dcov_at = rel_cov_diff(a_sub["cov"][:, sub], cov_at[:, sub])
    print(f"    same optimum: max |xyz_fast - xyz_gtsam| = {dx:.2e} m (goal <= 1e-6); GTSAM's graph error at "
          f"its solution {b['error']:.10g}, at the fast one {err_at - b['error']:+.2e} from that")
    print(f"    covariances: fast vs GTSAM at GTSAM's solution {dcov:.1e} relative; vs gtsam.Marginals at the "
          f"fast solution {dcov_at:.1e} relative")
    rows.append((f"smoother GTSAM straightforward: {len(sub)} markers", f"{t_base:.1f} s",
                 f"1 run; build {b['build_s']:.1f} + LM {b['solve_s']:.1f} + Marginals {b['marginals_s']:.1f} s"))
    rows.append((f"  ratio GTSAM / fast ({len(sub)} markers)", f"{t_base / t_fast_sub:.0f}x",
                 f"goal >= 5x; max position diff {dx:.1e} m; cov diff {dcov_at:.0e} rel at the same point"))
    plain = dataclasses.replace(session, rigid=[])
    t_meth, _, est = timed(lambda: schedule.run_smoother_fast(plain, dense, ideal, Options(progress=False)), 1)
    q = est.info.get("accel_psd_m2_s3", float("nan"))
    q_text = (f"per-marker q {min(q.values()):.3g}..{max(q.values()):.3g}" if isinstance(q, dict) else f"q = {q:.4g}")
    rows.append(("smoother method end to end (fast path: init + robust schedule + choose q per marker + solve)",
                 f"{t_meth:.2f} s", f"1 run, no segments; {q_text}"))
    return rows + bench_segments(session, dense, ideal, p_init, v_init, args)


def bench_segments(session: Session, dense, ideal: IdealObservations, p_init: np.ndarray, v_init: np.ndarray,
                   args) -> list[tuple[str, str, str]]:
    """(a'): segment-length factors (the simulator's bones, [markers] rigid): one final solve with and without
    them at the same q, alternating, medians; and the smoother method end to end both ways."""
    opt = Options(progress=False)
    pairs = rigid.segment_pairs(session.rigid, dense.markers)
    M = p_init.shape[1]
    estimated = np.isfinite(p_init).all(axis=(0, 2))
    models = np.where(estimated, "constant_velocity", None).astype(object)
    level = np.full(M, noise.causal_accel_psd(session))
    solve = {"without": lambda: fast.solve_per_model(session.rig, ideal, p_init, models, level, session.fps,
                                                     opt.robust, opt.robust_k, v_init=v_init),
             "with": lambda: rigid.solve_rigid(session.rig, ideal, p_init, models, level, session.fps, opt.robust,
                                               opt.robust_k, pairs, session.rigid_sigma_m, v_init=v_init)}
    plain = dataclasses.replace(session, rigid=[])
    method = {"without": lambda: schedule.run_smoother_fast(plain, dense, ideal, opt),
              "with": lambda: schedule.run_smoother_fast(session, dense, ideal, opt)}
    times = {(k, w): [] for k in ("solve", "method") for w in ("without", "with")}
    for _ in range(args.repeats):
        for w in ("without", "with"):
            times["solve", w].append(timed(solve[w], 1)[0])
            times["method", w].append(timed(method[w], 1)[0])
    med = {k: statistics.median(v) for k, v in times.items()}
    n_grouped = len(np.unique(pairs))
    print(f"(a') segments: {len(pairs)} segments joining {n_grouped} of {M} markers; one solve without / with: "
          f"{med['solve', 'without']:.2f} / {med['solve', 'with']:.2f} s; method end to end "
          f"{med['method', 'without']:.2f} / {med['method', 'with']:.2f} s (medians of {args.repeats})")
    return [(f"smoother solve with {len(pairs)} segments / without (same q)",
             f"{med['solve', 'with'] / med['solve', 'without']:.2f}x",
             f"goal <= 2x; {med['solve', 'with']:.2f} vs {med['solve', 'without']:.2f} s, medians of {args.repeats}"),
            (f"smoother method end to end with {len(pairs)} segments / without",
             f"{med['method', 'with'] / med['method', 'without']:.2f}x",
             f"{med['method', 'with']:.2f} vs {med['method', 'without']:.2f} s, medians of {args.repeats}")]


def _subset_markers(dense, ideal: IdealObservations, markers: np.ndarray, n_frames: int | None = None):
    """DenseObservations and IdealObservations of ``markers`` (and the first ``n_frames`` frames)."""
    from batgraph.session import DenseObservations

    fr = slice(None) if n_frames is None else slice(0, n_frames)
    d = DenseObservations(dense.cameras, dense.frames[fr], [dense.markers[m] for m in markers],
                          dense.uv_px[:, fr][:, :, markers], dense.weight[:, fr][:, :, markers])
    return d, IdealObservations(ideal.uv_px[:, fr][:, :, markers], ideal.cov_px2[:, fr][:, :, markers])


def bench_filter(session: Session, dense, ideal: IdealObservations, repeats: int) -> list[tuple[str, str, str]]:
    """(b): frames per second of the iSAM2 filter and of the fast filter (batgraph.graph.fast_filter) over
    the whole scene (each includes its own triangulation and outlier flags), their difference, and the
    fast filter on the paper's 5-camera flight. Wall time and the process's CPU time (less sensitive to
    other jobs on the machine)."""
    rows = []
    F, M = ideal.seen.shape[1:]
    opt = Options(progress=False)
    fast_est = None
    try:
        from batgraph.graph.fast_filter import run_filter_fast
    except ImportError:
        rows.append(("fast filter", "n/a", "batgraph.graph.fast_filter not present"))
    else:
        run_filter_fast(session, dense, ideal, opt)  # warm-up
        t, times, fast_est = timed(lambda: run_filter_fast(session, dense, ideal, opt), repeats)
        cpu = F / fast_est.info["cpu_s"]  # of the last run
        print(f"(b) fast filter: {F} frames in {t:.2f} s = {F / t:.0f} frames/s (median of {repeats}: "
              f"{', '.join(f'{x:.2f}' for x in times)}); CPU {fast_est.info['cpu_s']:.2f} s")
        rows.append((f"fast filter: {M} markers, {F} frames", f"{F / t:.0f} fr/s",
                     f"median of {repeats} ({', '.join(f'{F / x:.0f}' for x in times)}); {cpu:.0f} fr/s by CPU "
                     f"time; goal >= 120"))
        s5 = simulate_flight(np.random.default_rng(0), n_cameras=5, n_frames=F)
        d5 = dense_observations(s5)
        i5 = ideal_observations(s5.rig, d5, s5.pixel_sigma_px)
        t5, _, e5 = timed(lambda: run_filter_fast(s5, d5, i5, opt), repeats)
        M5 = i5.seen.shape[2]
        print(f"    fast filter, 5-camera flight ({M5} markers): {F / t5:.0f} frames/s")
        rows.append((f"fast filter: 5-camera flight, {M5} markers, {F} frames", f"{F / t5:.0f} fr/s",
                     f"median of {repeats}; {F / e5.info['cpu_s']:.0f} fr/s by CPU time"))
    try:
        from batgraph.graph.filter import run_filter
    except ImportError:
        return rows + [("filter (iSAM2)", "n/a", "batgraph.graph.filter not present")]
    t, _, est = timed(lambda: run_filter(session, dense, ideal, opt), 1)
    print(f"(b) iSAM2 filter: {F} frames in {t:.2f} s = {F / t:.1f} frames/s")
    rows.insert(0, (f"filter (iSAM2): {M} markers, {F} frames", f"{F / t:.1f} fr/s", f"1 run, {t:.1f} s"))
    if fast_est is not None:
        d = fast_est.xyz_m - est.xyz_m
        ok = np.isfinite(d).all(-1)
        maha = np.sqrt(np.einsum("ni,ni->n", d[ok], np.linalg.solve(est.cov_m2[ok], d[ok][..., None])[..., 0]))
        dcov = rel_cov_diff(fast_est.cov_m2[ok], est.cov_m2[ok])
        same = bool((np.isnan(fast_est.xyz_m) == np.isnan(est.xyz_m)).all())
        n_flag = int((fast_est.outlier != est.outlier).sum())
        print(f"    fast vs iSAM2: max {np.abs(d[ok]).max():.1e} m, {maha.max():.2f} sigma (median "
              f"{np.median(maha):.3f}); covariances {dcov:.1e} relative; same NaN pattern {same}; "
              f"outlier flags differ on {n_flag} of {int(est.outlier.sum())}")
        rows.append(("  ratio fast / iSAM2 filter", f"{t / statistics.median(times):.0f}x",
                     f"max diff {np.abs(d[ok]).max():.1e} m = {maha.max():.2f} sigma (median {np.median(maha):.3f}); "
                     f"cov {dcov:.0e} rel; NaN pattern same: {same}; flags differ: {n_flag}"))
    return rows


def bench_triangulate(session: Session, ideal: IdealObservations, repeats: int) -> list[tuple[str, str, str]]:
    """(c): per-frame multi-view DLT over all frames and markers."""
    C, F, M = ideal.seen.shape
    t, _, _ = timed(lambda: triangulate_ideal(session.rig, ideal), repeats)
    print(f"(c) triangulation: {F} frames in {t:.2f} s = {1000 * t / F:.1f} ms per frame")
    return [(f"triangulation (DLT + covariance): {M} markers, per frame", f"{1000 * t / F:.1f} ms",
             f"median of {repeats}; {F / t:.0f} frames/s")]


def bench_ekf(args) -> list[tuple[str, str, str]]:
    """(d): the stacked EKF's time per frame and peak memory against the number of markers."""
    try:
        from batgraph.filters.ekf import run_ekf
    except ImportError:
        return [("EKF", "n/a", "batgraph.filters.ekf not present")]
    rows = []
    session = simulate_flight(np.random.default_rng(0), n_cameras=args.cameras, n_markers=max(EKF_MARKERS),
                              n_frames=args.ekf_frames)
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    M = ideal.seen.shape[2]
    d, i = _subset_markers(dense, ideal, np.arange(min(M, 5)))
    run_ekf(session, d, i, Options(progress=False))  # warm-up: first calls into LAPACK are slower
    for n in EKF_MARKERS:
        if n > M:
            break
        ms = np.unique(np.linspace(0, M - 1, n).round().astype(int))
        d, i = _subset_markers(dense, ideal, ms)
        tracemalloc.start()
        t0 = time.perf_counter()
        run_ekf(session, d, i, Options(progress=False))
        t = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        per_frame = t / args.ekf_frames
        print(f"(d) EKF, {n} markers: {1000 * per_frame:.1f} ms per frame, peak memory {peak / 2**20:.0f} MiB")
        rows.append((f"EKF (stacked state 3n = {3 * n}): {n} markers, per frame", f"{1000 * per_frame:.1f} ms",
                     f"{1 / per_frame:.1f} frames/s; peak traced memory {peak / 2**20:.0f} MiB"))
        if per_frame > args.ekf_limit_s:
            rows.append(("EKF: stopped", "", f"{per_frame:.1f} s per frame > {args.ekf_limit_s} s: impractical"))
            break
    return rows


def bench_commands(args, batch: bool = True) -> list[tuple[str, str, str]]:
    """(e): whole commands, fresh processes, medians; against ``--baseline-tree`` when given (alternating);
    ``batch``: also the 16-session batch with 1 and 2 workers."""
    trees = {"new": ROOT}
    if args.baseline_tree:
        trees["old"] = Path(args.baseline_tree).resolve()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        big = f"{args.cameras} x {args.markers} x {args.frames}"
        # the accuracy study's 5-camera flight (14 markers, 160 frames, its bones as [markers] rigid: one group)
        simulate_sessions(tmp, (args.cameras, args.markers, args.frames), batch=batch, wingbeat=True)
        quiet = ["--viewer", "none", "--quiet"]
        commands = {
            "reconstruct flight_5cam (default methods)": ["reconstruct", str(SAMPLE), "--out", f"{tmp}/a", *quiet],
            "reconstruct flight_5cam --methods triangulate": ["reconstruct", str(SAMPLE), "--out", f"{tmp}/b",
                                                              *quiet, "--methods", "triangulate"],
            "batgraph --help": ["--help"],
            f"reconstruct {big} (default methods)": ["reconstruct", f"{tmp}/big", "--out", f"{tmp}/c", *quiet],
            "reconstruct simulated 5-camera flight --motion wingbeat": ["reconstruct", f"{tmp}/f5", "--out",
                                                                       f"{tmp}/d", *quiet, "--motion", "wingbeat"],
        }
        if batch:
            commands.update({f"reconstruct {BATCH_SESSIONS} sessions --workers {n}": [
                "reconstruct", f"{tmp}/many/*", "--out", f"{tmp}/w{n}", "--workers", str(n), *quiet] for n in (1, 2)})
        wall_of: dict[str, dict[str, float]] = {}
        for what, cli in commands.items():
            got: dict[str, list[dict]] = {name: [] for name in trees}
            for _ in range(args.repeats):
                for name, tree in trees.items():  # alternate old and new so both see the same machine load
                    got[name].append(run_process(cli, tree))
            med = {name: {k: statistics.median(r[k] for r in runs) for k in ("wall", "cpu", "rss")}
                   for name, runs in got.items()}
            for name in trees:
                walls = ", ".join(f"{r['wall']:.2f}" for r in got[name])
                print(f"(e) {what} [{name}]: wall {med[name]['wall']:.2f} s ({walls}), CPU {med[name]['cpu']:.2f} s, "
                      f"peak RSS {med[name]['rss']:.0f} MiB")
                rows.append((f"{what} [{name}]", f"{med[name]['wall']:.2f} s",
                             f"median of {args.repeats}; CPU {med[name]['cpu']:.2f} s; peak RSS "
                             f"{med[name]['rss']:.0f} MiB"))
            if "old" in trees:
                r = {k: med["new"][k] / med["old"][k] for k in ("wall", "cpu", "rss")}
                rows.append((f"  ratio new / old: {what}", f"{r['wall']:.2f}",
                             f"wall; CPU {r['cpu']:.2f}; peak RSS {r['rss']:.2f}"))
            wall_of[what] = {name: m["wall"] for name, m in med.items()}
        if not batch:
            return rows
        one, two = (wall_of[f"reconstruct {BATCH_SESSIONS} sessions --workers {n}"] for n in (1, 2))
        for name in trees:
            rows.append((f"  ratio 2 workers / 1 worker [{name}]", f"{two[name] / one[name]:.2f}",
                         "wall (issue 12 asks <= 0.6)"))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cameras", type=int, default=30)
    ap.add_argument("--markers", type=int, default=180)
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline-markers", type=int, default=None,
                    help="run the GTSAM baseline on this many markers (default: all, or a subset if too slow)")
    ap.add_argument("--ekf-frames", type=int, default=12, help="frames per EKF run in section (d)")
    ap.add_argument("--ekf-limit-s", type=float, default=20.0, help="stop (d) when one frame takes longer")
    ap.add_argument("--skip", default="",
                    help="comma list of sections to skip: commands,smoother,filter,triangulate,ekf; batch skips "
                         "only the 16-session batch of (e)")
    ap.add_argument("--baseline-tree", default=None,
                    help="(e): also run the commands from this older source tree and print new / old ratios")
    args = ap.parse_args(argv)
    skip = set(filter(None, args.skip.split(",")))
    info = machine()
    print(f"machine: {info['nproc']} cores, {info['cpu']}, {info['ram_gib']:.1f} GiB RAM, "
          f"Python {info['python']}, numpy {info['numpy']}")
    rows = []
    if "commands" not in skip:
        rows += bench_commands(args, batch="batch" not in skip)
    t0 = time.perf_counter()
    session = simulate_flight(np.random.default_rng(0), n_cameras=args.cameras, n_markers=args.markers,
                              n_frames=args.frames)
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    C, F, M = ideal.seen.shape
    print(f"scene: simulate_flight(default_rng(0)): {C} cameras x {M} markers x {F} frames, "
          f"{int(ideal.seen.sum())} observations ({time.perf_counter() - t0:.1f} s to simulate)")
    if "smoother" not in skip:
        rows += bench_smoother(session, dense, ideal, args)
    if "filter" not in skip:
        rows += bench_filter(session, dense, ideal, args.repeats)
    if "triangulate" not in skip:
        rows += bench_triangulate(session, ideal, args.repeats)
    if "ekf" not in skip:
        rows += bench_ekf(args)
    print()
    width = max(len(r[0]) for r in rows)
    print(f"{'what':{width}s} {'figure':>11s}  notes")
    for what, value, notes in rows:
        print(f"{what:{width}s} {value:>11s}  {notes}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
