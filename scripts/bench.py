"""The smoother's speed against a plain GTSAM graph, where its time goes, and the default command warm and cold.

Sections (each prints a markdown table; medians of jobs run in turn, ratios round by round; nothing is asserted):
- smoother: a fresh simulated flight (30 cameras x 180 markers x 160 frames, --seed): the smoother method as
  reconstruct runs it; the same on the baseline's cost (random walk at the paper's sigma, no robust loss, no
  segments: positions must agree with GTSAM's); the baseline, a GTSAM graph of the paper's random walk built in a
  Python loop (TriangulationFactorCal3_S2 on ideal pixels with the fixed cameras, BetweenFactorPoint3, a prior per
  marker) solved by GTSAM's default Levenberg-Marquardt, then gtsam.Marginals of every point; the filter method.
  The smoother method's steps are timed where its schedule calls them.
- command: ``python -m batgraph reconstruct data/samples/flight_5cam --out X`` with --viewer none and save, and the
  same with --methods triangulate (start-up and outputs), warm, fresh processes.
- first-run: that command with an empty numba cache (NUMBA_CACHE_DIR a new folder), the compile step ``python -m
  batgraph.warm`` into an empty cache and the command after it, each against the warm command.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchproc import SAMPLE, alternate, batgraph, machine, median, run, table, timed  # noqa: E402

from batgraph import warm  # noqa: E402
from batgraph.evaluate import dense_from_table  # noqa: E402
from batgraph.measurement import ideal_observations  # noqa: E402
from batgraph.motion import random_walk_sigma_m  # noqa: E402
from batgraph.result import Options  # noqa: E402
from batgraph.session import dense_observations  # noqa: E402
from batgraph.simulate import simulate_flight  # noqa: E402
from batgraph.solver import filter as filter_method  # noqa: E402
from batgraph.solver import model as mm  # noqa: E402
from batgraph.solver import schedule  # noqa: E402
from batgraph.triangulate import dlt_points  # noqa: E402

OPTIONS = Options(progress=False)


def gtsam_random_walk(session, ideal) -> dict:
    """The baseline: the paper's random walk as a GTSAM graph built one factor at a time, GTSAM's default LM, then
    gtsam.Marginals of every point. xyz (F, M, 3) [m] and the seconds of each step."""
    import gtsam

    clock = timed(lambda: schedule.initial_track(dlt_points(session.rig, ideal), session.fps))
    p0, _, estimated = clock["result"]
    seen = ideal.seen  # computed at each access: once here, not per point
    C, F, M = seen.shape
    cams = [gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(c.world_from_cam()[0]), c.world_from_cam()[1]),
                                       gtsam.Cal3_S2(c.K[0, 0], c.K[1, 1], c.K[0, 1], c.K[0, 2], c.K[1, 2]))
            for c in session.rig]
    walk = gtsam.noiseModel.Isotropic.Sigma(3, random_walk_sigma_m(session.motion, session.fps))  # [m] per frame
    prior = gtsam.noiseModel.Isotropic.Sigma(3, mm.PRIOR_SIGMA[0])  # [m] on the first position: the smoother's

    def key(m, k):
        return gtsam.symbol("p", m * F + k)

    def build():
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for m in map(int, np.flatnonzero(estimated)):
            graph.push_back(gtsam.PriorFactorPoint3(key(m, 0), p0[0, m], prior))
            for k in range(F):
                values.insert(key(m, k), p0[k, m])
                if k + 1 < F:
                    graph.push_back(gtsam.BetweenFactorPoint3(key(m, k), key(m, k + 1), np.zeros(3), walk))
                for c in np.flatnonzero(seen[:, k, m]):
                    noise = gtsam.noiseModel.Gaussian.Covariance(ideal.cov_px2[c, k, m])  # [px^2]
                    graph.push_back(gtsam.TriangulationFactorCal3_S2(cams[c], ideal.uv_px[c, k, m], noise, key(m, k)))
        return graph, values

    built = timed(build)
    graph, values = built["result"]
    params = gtsam.LevenbergMarquardtParams()  # GTSAM's defaults
    solved = timed(lambda: gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize())
    sol = solved["result"]

    def marginals():
        marg = gtsam.Marginals(graph, sol)
        return [marg.marginalCovariance(key(int(m), k)) for m in np.flatnonzero(estimated) for k in range(F)]

    marg = timed(marginals)
    xyz = np.full((F, M, 3), np.nan)
    for m in np.flatnonzero(estimated):
        xyz[:, m] = [sol.atPoint3(key(int(m), k)) for k in range(F)]
    return {"xyz": xyz, "initial track": clock["wall"], "build": built["wall"], "LM": solved["wall"],
            "marginals": marg["wall"]}


# The schedule's steps (batgraph.solver.schedule), timed where the method calls them: (module, attribute, label)
STEPS = ((schedule, "dlt_points", "triangulation"), (schedule, "_clean", "cleaning and exclusion"),
         (schedule, "_choose", "noise search"), (schedule, "_final", "final solves and rejection"),
         (schedule.shared, "solve", "shared variables"), (schedule.ends, "widen", "track ends and second depth"))


def smoother_steps(session, dense, ideal) -> dict:
    """The smoother method (schedule.run_smoother) with each of its STEPS timed [s] where the schedule calls it (the
    same run, the same answer); xyz (F, M, 3) [m]."""
    out = {label: 0.0 for _, _, label in STEPS}

    def clocked(fn, label):
        def run_step(*a, **kw):
            res = timed(lambda: fn(*a, **kw))
            out[label] += res["wall"]
            return res["result"]
        return run_step

    with contextlib.ExitStack() as stack:
        for module, name, label in STEPS:
            original = getattr(module, name)
            setattr(module, name, clocked(original, label))
            stack.callback(setattr, module, name, original)
        out["xyz"] = schedule.run_smoother(session, dense, ideal, OPTIONS).xyz_m
    return out


def rmse_mm(xyz: np.ndarray, truth: np.ndarray) -> float:
    err = np.linalg.norm(xyz - truth, axis=-1)
    return 1000 * float(np.sqrt(np.nanmean(err[np.isfinite(err)] ** 2)))


def bench_smoother(args) -> None:
    """Section smoother (module docstring)."""
    session = simulate_flight(np.random.default_rng(args.seed), n_cameras=args.cameras, n_markers=args.markers,
                              n_frames=args.frames)
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    truth = dense_from_table(session.truth, dense.frames, dense.markers)[0]
    plain = replace(session, rigid=[])
    same_cost = replace(OPTIONS, motion_model="random_walk", robust="none")
    print(f"scene: simulate_flight(default_rng({args.seed})), {len(session.rig)} cameras x {len(dense.markers)} "
          f"markers x {len(dense.frames)} frames, {int(ideal.seen.sum())} observations, {len(session.rigid)} segments")
    warm.compile_all()  # loads the compiled loops (compiles them into an empty cache)
    def fresh():  # the observations without their cached linear triangulation: every job triangulates
        return replace(ideal, linear_xyz=None)

    jobs = {
        "smoother method": lambda: timed(lambda: smoother_steps(session, dense, fresh())),
        "smoother, the baseline's cost": lambda: timed(
            lambda: schedule.run_smoother(plain, dense, fresh(), same_cost).xyz_m),
        "GTSAM random walk (baseline)": lambda: timed(lambda: gtsam_random_walk(session, fresh())),
        "filter method": lambda: timed(lambda: filter_method.run(session, dense, fresh(), OPTIONS).xyz_m),
    }
    runs = alternate(jobs, args.repeats)
    print(table(runs, "GTSAM random walk (baseline)"))
    base = [r["result"] for r in runs["GTSAM random walk (baseline)"]]
    steps = [r["result"] for r in runs["smoother method"]]
    print("\nbaseline's steps [s], medians: " + ", ".join(
        f"{k} {np.median([b[k] for b in base]):.2f}" for k in base[0] if k != "xyz"))
    print("smoother's steps [s], medians: " + ", ".join(
        f"{k} {np.median([s[k] for s in steps]):.2f}" for k in steps[0] if k != "xyz"))
    same = runs["smoother, the baseline's cost"][-1]["result"]
    method = steps[-1]["xyz"]
    print(f"same cost, smoother vs GTSAM: max |dx| {np.nanmax(np.abs(same - base[-1]['xyz'])):.1e} m")
    print("position RMSE against the truth [mm]: " + ", ".join(
        f"{name} {rmse_mm(xyz, truth):.2f}" for name, xyz in (("smoother method", method),
                                                               ("smoother on the baseline's cost", same),
                                                               ("GTSAM random walk", base[-1]["xyz"]))))


def bench_command(args) -> None:
    """Section command (module docstring); also the methods' own times as the command reports them (summary.json)."""
    with tempfile.TemporaryDirectory() as tmp:
        def reconstruct(label, *extra):
            out = f"{tmp}/{len(label)}"
            res = run(batgraph("reconstruct", str(SAMPLE), "--out", out, *extra))
            methods = json.loads(Path(out, "summary.json").read_text())["methods"]
            return {**res, **{name: m["runtime_s"] for name, m in methods.items() if name != "triangulate"}}

        jobs = {label: (lambda label=label, extra=extra: reconstruct(label, *extra)) for label, extra in (
            ("reconstruct --viewer none", ["--viewer", "none"]), ("reconstruct --viewer save", ["--viewer", "save"]),
            ("reconstruct --methods triangulate --viewer none", ["--methods", "triangulate", "--viewer", "none"]))}
        runs = alternate(jobs, args.command_repeats, warmup=True)
    print(table(runs, "reconstruct --methods triangulate --viewer none"))
    for label in ("reconstruct --viewer none", "reconstruct --viewer save"):
        print(f"{label}: the methods' own runtime_s (summary.json), medians: "
              + ", ".join(f"{m} {median(runs[label], m):.2f} s" for m in ("smoother", "filter")))


def bench_first_run(args) -> None:
    """Section first-run (module docstring)."""
    with tempfile.TemporaryDirectory() as tmp:
        command = batgraph("reconstruct", str(SAMPLE), "--out", f"{tmp}/out", "--viewer", "none")
        run(command)  # the warm command's cache (this checkout's), filled if it is not
        caches, state = (f"{tmp}/cache{i}" for i in itertools.count()), {}

        def compile_step():
            state["cache"] = {"NUMBA_CACHE_DIR": next(caches)}
            return run([sys.executable, "-m", "batgraph.warm"], state["cache"])

        jobs = {"warm command": lambda: run(command),
                "command, empty cache": lambda: run(command, {"NUMBA_CACHE_DIR": next(caches)}),
                "compile step, empty cache": compile_step,
                "command after the compile step": lambda: run(command, state["cache"])}
        runs = alternate(jobs, args.cold_repeats)
    print(table(runs, "warm command"))
    for name in ("command, empty cache", "command after the compile step"):
        print(f"{name} - warm command (medians): {median(runs[name]) - median(runs['warm command']):+.1f} s wall, "
              f"{median(runs[name], 'cpu') - median(runs['warm command'], 'cpu'):+.1f} s CPU")


SECTIONS = {"smoother": bench_smoother, "command": bench_command, "first-run": bench_first_run}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma list of {', '.join(SECTIONS)}")
    ap.add_argument("--cameras", type=int, default=30)
    ap.add_argument("--markers", type=int, default=180)
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--seed", type=int, default=7, help="the smoother section's scene (the bundled sample is seed 1)")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the smoother section")
    ap.add_argument("--command-repeats", type=int, default=5, help="rounds of the command section (after a warm-up)")
    ap.add_argument("--cold-repeats", type=int, default=2, help="rounds of the first-run section")
    args = ap.parse_args(argv)
    print(f"machine: {machine()}")
    for name in args.sections.split(","):
        print(f"\n## {name}", flush=True)
        SECTIONS[name](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
