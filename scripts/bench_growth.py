"""How batgraph's time and peak memory grow with frames (160, 640, 1200) and cameras (5, 10, 30).

Each configuration runs in a fresh subprocess (``--one C M F``) so that its peak resident memory
(getrusage ru_maxrss) is its own; the parent prints one table with ratios. Stages, in order, in that
subprocess: simulation (simulate_flight, its bat slowed so it stays in view for all F frames, +
dense_observations + ideal_observations), the initial track
(per-frame triangulation + factors.initial_track), the fast smoother solve at a FIXED q (so the growth
is the solver's, not the q search's), the fast filter, and optionally the smoother method end to end.
The solve and the filter run REPEATS times each and report the median wall time (this machine is shared
and noisy: single runs of the same configuration have differed by 1.5x). The resident high-water mark
is read after each stage; being a high-water mark it is cumulative.
Nothing is asserted; BENCHMARKS.md records a run. The paper's stacked EKF is in scripts/bench.py (d).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FIXED_Q = 8.0  # acceleration PSD [m^2/s^3]; scripts/bench.py's data-chosen q on the 30x180x160 flight is 8.28
FRAMES = (160, 640, 1200)  # at 30 cameras x 180 markers
REPEATS = 3  # the estimators' stages run this many times in a configuration; the table shows the median
CAMERAS = (5, 10, 30)  # at 180 markers x 160 frames


def _maxrss_mib() -> float:
    """This process's resident high-water mark so far [MiB] (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _stage(out: dict, name: str, fn, repeats: int = 1):
    """Run ``fn()`` ``repeats`` times; record the median wall and process CPU time [s] (and every wall
    time) and the resident high-water mark after it. Returns the last call's result."""
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    out[name] = {"wall_s": float(np.median(walls)), "cpu_s": float(np.median(cpus)), "wall_runs_s": walls,
                 "rss_mib": _maxrss_mib()}
    return result


def run_one(n_cameras: int, n_markers: int, n_frames: int, end_to_end: bool) -> dict:
    """All stages on one simulated flight; a dict of per-stage figures (printed as JSON by ``--one``)."""
    import batgraph.simulate as simulate
    from batgraph.graph import factors, fast, schedule
    from batgraph.graph.fast_filter import run_filter_fast
    from batgraph.measurement import ideal_observations
    from batgraph.result import Options
    from batgraph.session import dense_observations
    from batgraph.simulate import simulate_flight
    from batgraph.triangulate import dlt_points

    # simulate_flight's bat crosses the camera volume (~4 m) at 3 m/s in ~160 frames and is then out of
    # view; to keep it in view for all F frames (observations growing with F) it flies the same 4 m
    # slower. A module constant of the simulation is patched in this subprocess only.
    simulate.FLIGHT_SPEED_MPS = 3.0 * 160 / n_frames
    out: dict = {"C": n_cameras, "M": n_markers, "F": n_frames, "speed_mps": simulate.FLIGHT_SPEED_MPS,
                 "rss_start_mib": _maxrss_mib()}
    session = _stage(out, "simulate_flight", lambda: simulate_flight(
        np.random.default_rng(0), n_cameras=n_cameras, n_markers=n_markers, n_frames=n_frames))
    dense = _stage(out, "dense+ideal", lambda: dense_observations(session))
    ideal = _stage(out, "ideal", lambda: ideal_observations(session.rig, dense, session.pixel_sigma_px))
    out["dense+ideal"] = _merge(out)  # one set-up row: both conversions
    out["observations"] = int(ideal.seen.sum())
    p_init, v_init, _ = _stage(out, "triangulate+init", lambda: factors.initial_track(
        dlt_points(session.rig, ideal), session.fps))
    opt = Options(progress=False)
    _, _, info = _stage(out, "solve_fast", lambda: fast.solve_fast(
        session.rig, ideal, p_init, "constant_velocity", FIXED_Q, session.fps, opt.robust, opt.robust_k,
        v_init=v_init), REPEATS)
    out["solve_iterations"] = int(info["iterations"])
    _stage(out, "filter_fast", lambda: run_filter_fast(session, dense, ideal, opt), REPEATS)
    if end_to_end:
        _stage(out, "smoother_e2e", lambda: schedule.run_smoother_fast(session, dense, ideal, opt))
    out["rss_peak_mib"] = _maxrss_mib()
    return out


def _merge(out: dict) -> dict:
    """The dense + ideal conversions as one stage (times added, high-water mark after both)."""
    a, b = out["dense+ideal"], out.pop("ideal")
    return {"wall_s": a["wall_s"] + b["wall_s"], "cpu_s": a["cpu_s"] + b["cpu_s"], "rss_mib": b["rss_mib"]}


STAGES = ("simulate_flight", "dense+ideal", "triangulate+init", "solve_fast", "filter_fast", "smoother_e2e")


def run_child(C: int, M: int, F: int, end_to_end: bool, timeout_s: float) -> dict | None:
    """``run_one`` in a fresh interpreter; its JSON plus the child's ru_maxrss seen by the parent."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    cmd = [sys.executable, __file__, "--one", str(C), str(M), str(F)] + ([] if end_to_end else ["--no-e2e"])
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=True)
    except subprocess.TimeoutExpired:
        print(f"  {C}x{M}x{F}: over the {timeout_s:.0f} s budget, cut", flush=True)
        return None
    except subprocess.CalledProcessError as e:
        print(f"  {C}x{M}x{F}: failed\n{e.stderr[-2000:]}", flush=True)
        return None
    res = json.loads(p.stdout.strip().splitlines()[-1])
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    # RUSAGE_CHILDREN is the max over all waited-for children: it identifies this child only if it grew
    res["children_maxrss_mib"] = after / 1024 if after > before else None
    return res


def table(results: list[dict], axis: str) -> None:
    """Wall [s] / CPU [s] per stage, peak RSS, and the ratio to the previous row along ``axis``."""
    head = f"{'C x M x F':>14s} {'obs':>9s}"
    for s in STAGES:
        head += f" | {s:>22s}"
    print(head + f" | {'peak RSS':>9s}")
    prev = None
    for r in results:
        line = f"{r['C']:>4d}x{r['M']:>3d}x{r['F']:>5d} {r['observations']:>9d}"
        for s in STAGES:
            if s not in r:
                line += f" | {'not run':>22s}"
                continue
            w, c = r[s]["wall_s"], r[s]["cpu_s"]
            ratio = f"({w / prev[s]['wall_s']:.2f}x)" if prev is not None and s in prev else ""
            line += f" | {w:7.2f} {c:6.2f}c {ratio:>7s}"
        line += f" | {r['rss_peak_mib']:6.0f} MiB"
        print(line)
        prev = r
    print(f"  ratios are wall time against the previous row ({axis}); 'c' = process CPU seconds; solve_fast and "
          f"filter_fast: medians of {REPEATS} runs in the configuration's process (the first includes first-touch "
          "memory)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--one", nargs=3, type=int, metavar=("C", "M", "F"), help="run one configuration (internal)")
    ap.add_argument("--no-e2e", action="store_true", help="(with --one) skip the smoother end to end")
    ap.add_argument("--e2e-max-frames", type=int, default=160,
                    help="run the smoother end to end only up to this many frames (time budget)")
    ap.add_argument("--timeout", type=float, default=900.0, help="per-configuration budget [s]")
    ap.add_argument("--frames", type=int, nargs="+", default=list(FRAMES))
    ap.add_argument("--cameras", type=int, nargs="*", default=list(CAMERAS))
    ap.add_argument("--markers", type=int, default=180)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(*args.one, end_to_end=not args.no_e2e)))
        return 0
    print(f"fixed q = {FIXED_Q} m^2/s^3 (constant velocity, Huber k = 2) for solve_fast; smoother end to end "
          f"(run_smoother_fast, Options(progress=False)) up to {args.e2e_max_frames} frames", flush=True)
    by_frames, by_cams = [], []
    for F in args.frames:
        r = run_child(30, args.markers, F, F <= args.e2e_max_frames, args.timeout)
        if r is not None:
            by_frames.append(r)
            print(json.dumps(r), flush=True)
    for C in args.cameras:
        same = next((r for r in by_frames if r["C"] == C and r["F"] == 160), None)
        r = same or run_child(C, args.markers, 160, True, args.timeout)
        if r is not None:
            by_cams.append(r)
            if same is None:
                print(json.dumps(r), flush=True)
    print("\ngrowth with frames (30 cameras):")
    table(by_frames, "frames")
    print("\ngrowth with cameras (160 frames):")
    table(by_cams, "cameras")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
