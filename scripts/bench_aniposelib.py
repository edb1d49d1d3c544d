"""aniposelib's triangulation against batgraph's on the same simulated observations, both scored against the truth.

Two steps in two environments (aniposelib needs opencv-contrib-python, which conflicts with batgraph's
opencv-python-headless, so it lives in its own venv, .venv-bench, made by ``make bench``):

  .venv/bin/python scripts/bench_aniposelib.py export DIR
      simulates the flight (30 x 180 x 160 by default) and writes DIR/calibration.toml (aniposelib's format),
      DIR/session (the same scene as a batgraph session) and DIR/points.npz: raw pixels ``points`` (C, F*M, 2), NaN
      where unseen (point index = frame * M + marker), the truth and batgraph's answers (F*M, 3) [m]: its per-frame
      triangulation and its smoother method, and their times in that process.
  .venv-bench/bin/python scripts/bench_aniposelib.py run DIR
      times CameraGroup.triangulate(points, undistort=True) (its first call includes jax's compilation), scores
      all three answers against the truth, reprojects the truth through aniposelib's cameras (the check that it
      reads calibration.toml as batgraph wrote it: ~1.18 px, the median of a 2D residual of 1 px noise per
      axis), and times whole processes in turn: a script around aniposelib (import, load, triangulate, write a
      CSV) and ``batgraph reconstruct DIR/session`` with --methods triangulate and with the default methods;
      ratios against the aniposelib script.
The ``run`` step imports only numpy, aniposelib and scripts/benchproc.py. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchproc import ROOT, alternate, machine, run, table  # noqa: E402

# What a user's script around aniposelib does: load, triangulate, write a CSV (argv: DIR out.csv)
_ANIPOSE_SCRIPT = """
import sys
import numpy as np
from aniposelib.cameras import CameraGroup
data = np.load(sys.argv[1] + "/points.npz")
cgroup = CameraGroup.load(sys.argv[1] + "/calibration.toml")
order = [list(data["camera_names"]).index(name) for name in cgroup.get_names()]
xyz = cgroup.triangulate(np.ascontiguousarray(data["points"][order]), undistort=True)
C, F, M = (int(x) for x in data["shape_cfm"])
frame, marker = np.divmod(np.arange(F * M), M)
np.savetxt(sys.argv[2], np.column_stack([frame, marker, xyz]), delimiter=",", fmt=["%d", "%d", "%.9g", "%.9g", "%.9g"],
           header="frame,marker,x,y,z", comments="")
"""


def export(out_dir: Path, n_cameras: int, n_markers: int, n_frames: int, seed: int) -> None:
    """Simulate; write calibration.toml, the session and points.npz with batgraph's answers and times."""
    sys.path.insert(0, str(ROOT))
    from batgraph import warm
    from batgraph.evaluate import dense_from_table
    from batgraph.measurement import ideal_observations
    from batgraph.result import Options
    from batgraph.session import calibration_toml, dense_observations, write_session
    from batgraph.simulate import simulate_flight
    from batgraph.solver import schedule
    from batgraph.triangulate import triangulate_ideal

    session = simulate_flight(np.random.default_rng(seed), n_cameras=n_cameras, n_markers=n_markers,
                              n_frames=n_frames)
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    C, F, M = ideal.seen.shape
    warm.compile_all()
    t0 = time.perf_counter()
    xyz_tri = triangulate_ideal(session.rig, ideal)[0]
    t1 = time.perf_counter()
    xyz_smoother = schedule.run_smoother(session, dense, ideal, Options(progress=False)).xyz_m
    t2 = time.perf_counter()
    truth = dense_from_table(session.truth, dense.frames, dense.markers)[0]
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "calibration.toml").write_text(calibration_toml(session.rig))
    write_session(session, out_dir / "session")
    np.savez(out_dir / "points.npz", points=dense.uv_px.reshape(C, F * M, 2), camera_names=np.array(dense.cameras),
             shape_cfm=np.array([C, F, M]), xyz_truth=truth.reshape(-1, 3), xyz_triangulate=xyz_tri.reshape(-1, 3),
             xyz_smoother=xyz_smoother.reshape(-1, 3), triangulate_s=t1 - t0, smoother_s=t2 - t1,
             batgraph_python=sys.executable)
    print(f"exported {C} cameras x {M} markers x {F} frames (seed {seed}), {int(ideal.seen.sum())} observations, "
          f"to {out_dir}; batgraph's per-frame triangulation {t1 - t0:.2f} s, smoother method {t2 - t1:.2f} s "
          "(one run each)")


def score(name: str, xyz: np.ndarray, truth: np.ndarray, ok: np.ndarray) -> str:
    e = 1000 * np.linalg.norm(xyz[ok] - truth[ok], axis=-1)
    return (f"| {name} | {int(ok.sum())} | {np.median(e):.3f} | {np.sqrt(np.mean(e ** 2)):.3f} | "
            f"{np.percentile(e, 95):.3f} |")


def run_step(folder: Path, rounds: int) -> None:
    """The aniposelib side (module docstring)."""
    from aniposelib.cameras import CameraGroup

    print(f"machine: {machine()}")
    data = np.load(folder / "points.npz")
    cgroup = CameraGroup.load(str(folder / "calibration.toml"))
    # CameraGroup.load sorts the cameras by name (cam_0, cam_1, cam_10, ...): the points follow that order
    order = [list(data["camera_names"]).index(name) for name in cgroup.get_names()]
    points = np.ascontiguousarray(data["points"][order])
    times = []
    for _ in range(4):
        t0 = time.perf_counter()
        xyz = cgroup.triangulate(points, undistort=True)
        times.append(time.perf_counter() - t0)
    print(f"aniposelib CameraGroup.triangulate: first call {times[0]:.2f} s (jax compiles), then "
          f"{statistics.median(times[1:]):.2f} s (median of 3); batgraph in its export: triangulation "
          f"{float(data['triangulate_s']):.2f} s, smoother method {float(data['smoother_s']):.2f} s\n")
    truth = data["xyz_truth"]
    answers = {"aniposelib triangulate": xyz, "batgraph per-frame triangulation": data["xyz_triangulate"],
               "batgraph smoother method": data["xyz_smoother"]}
    both = np.isfinite(truth).all(-1) & np.isfinite(xyz).all(-1) & np.isfinite(data["xyz_triangulate"]).all(-1)
    print("| against the truth, points both triangulations give | points | median [mm] | RMSE [mm] | 95th pct [mm] |\n"
          "|---|---|---|---|---|")
    for name, a in answers.items():
        print(score(name, a, truth, both))
    seen = np.isfinite(points).all(-1)
    r = np.linalg.norm(cgroup.project(np.nan_to_num(truth)) - points, axis=-1)[seen & np.isfinite(truth).all(-1)]
    print(f"\nthe truth reprojected by aniposelib's cameras: median residual {np.median(r):.3f} px\n")
    with tempfile.TemporaryDirectory() as tmp:
        bg = [str(data["batgraph_python"]), "-m", "batgraph", "reconstruct", str(folder / "session"),
              "--viewer", "none"]
        jobs = {"aniposelib script": lambda: run([sys.executable, "-c", _ANIPOSE_SCRIPT, str(folder), f"{tmp}/a.csv"]),
                "batgraph reconstruct --methods triangulate": lambda: run(
                    [*bg, "--out", f"{tmp}/t", "--methods", "triangulate"]),
                "batgraph reconstruct (smoother, filter)": lambda: run([*bg, "--out", f"{tmp}/d"])}
        runs = alternate(jobs, rounds, warmup=True)
    print(table(runs, "aniposelib script"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="(batgraph's venv) write the scene and batgraph's answers")
    e.add_argument("out_dir", type=Path)
    e.add_argument("--cameras", type=int, default=30)
    e.add_argument("--markers", type=int, default=180)
    e.add_argument("--frames", type=int, default=160)
    e.add_argument("--seed", type=int, default=0)
    r = sub.add_parser("run", help="(.venv-bench) aniposelib on the exported points, and whole processes")
    r.add_argument("folder", type=Path)
    r.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    if args.cmd == "export":
        export(args.out_dir, args.cameras, args.markers, args.frames, args.seed)
    else:
        run_step(args.folder, args.rounds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
