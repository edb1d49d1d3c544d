"""aniposelib's CameraGroup.triangulate against batgraph on the same 30 x 180 x 160 observations.

Two steps, two environments (aniposelib needs opencv-contrib-python, which conflicts with batgraph's
opencv-python-headless, so it lives in its own venv, .venv-bench; it is not a batgraph dependency):

  .venv/bin/python scripts/bench_aniposelib.py export DIR
      simulates the flight, writes DIR/calibration.toml (aniposelib's format) and DIR/points.npz:
      raw pixels ``points`` (C, F*M, 2) with NaN where unseen (point index = frame * M + marker),
      batgraph's per-frame triangulation ``xyz_batgraph`` (F*M, 3) [m], and batgraph's times [s] on
      this machine (per-frame triangulation, the fast smoother solve at a fixed q from the initial track,
      and the same smoother including the building of its initial track), medians of 3.
  .venv-bench/bin/python scripts/bench_aniposelib.py run DIR/points.npz DIR/calibration.toml
      times CameraGroup.load(...).triangulate(points, undistort=True) (first call, which includes jax's
      compilation, then the median of 3 more) and prints the ratios and the median 3D difference.

Both steps also time whole processes as a user runs them (issue 12: "the default reconstruct within 2x of
aniposelib's triangulate + CSV on the same sessions"): ``export`` writes the same scene as a batgraph session
(DIR/session) and times ``batgraph reconstruct DIR/session`` (default methods, every output but the
recording) in fresh processes; ``run`` times a fresh process that imports aniposelib, loads the calibration,
triangulates the points and writes them as a CSV (frame, marker, x, y, z), as a script around aniposelib
would. Medians of 3 each.

The ``run`` step imports only numpy and aniposelib. Nothing is asserted; BENCHMARKS.md records a run.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FIXED_Q = 8.0  # acceleration PSD [m^2/s^3] for the smoother solve (as scripts/bench_growth.py)


def _median_time(fn, repeats: int = 3) -> tuple[float, list[float], object]:
    """(median wall time [s], all times, last result) of ``fn()``."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def _process_time(argv: list[str], cwd: Path | None = None, repeats: int = 3) -> tuple[float, list[float]]:
    """(median wall time [s], all times) of a fresh process ``argv``, from its start to its exit."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(argv, cwd=cwd, check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


# What a user's script around aniposelib does: load, triangulate, write a CSV (argv: points.npz calibration out.csv)
_ANIPOSE_SCRIPT = """
import sys
import numpy as np
from aniposelib.cameras import CameraGroup
data = np.load(sys.argv[1])
cgroup = CameraGroup.load(sys.argv[2])
order = [list(data["camera_names"]).index(name) for name in cgroup.get_names()]
xyz = cgroup.triangulate(np.ascontiguousarray(data["points"][order]), undistort=True)
C, F, M = (int(x) for x in data["shape_cfm"])
frame, marker = np.divmod(np.arange(F * M), M)
np.savetxt(sys.argv[3], np.column_stack([frame, marker, xyz]), delimiter=",", fmt=["%d", "%d", "%.9g", "%.9g", "%.9g"],
           header="frame,marker,x,y,z", comments="")
"""


def export(out_dir: Path, n_cameras: int, n_markers: int, n_frames: int) -> None:
    """Simulate, write calibration.toml and points.npz, and time batgraph on the same data."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from batgraph.graph import factors, fast
    from batgraph.measurement import ideal_observations
    from batgraph.result import Options
    from batgraph.session import calibration_toml, dense_observations, write_session
    from batgraph.simulate import simulate_flight
    from batgraph.triangulate import dlt_points, triangulate_ideal

    session = simulate_flight(np.random.default_rng(0), n_cameras=n_cameras, n_markers=n_markers,
                              n_frames=n_frames)
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    C, F, M = ideal.seen.shape
    t_tri, tri_times, (xyz, _) = _median_time(lambda: triangulate_ideal(session.rig, ideal))
    p_init, v_init, _ = factors.initial_track(xyz, session.fps)
    opt = Options(progress=False)

    def smoother(p0, v0):
        return fast.solve_fast(session.rig, ideal, p0, "constant_velocity", FIXED_Q, session.fps, opt.robust,
                               opt.robust_k, v_init=v0)

    def smoother_from_pixels():  # its own initial track (DLT positions, interpolated), then the solve
        return smoother(*factors.initial_track(dlt_points(session.rig, ideal), session.fps)[:2])

    t_solve, solve_times, _ = _median_time(lambda: smoother(p_init, v_init))
    t_whole, whole_times, _ = _median_time(smoother_from_pixels)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "calibration.toml").write_text(calibration_toml(session.rig))
    write_session(session, out_dir / "session")
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        t_cmd, cmd_times = _process_time([sys.executable, "-m", "batgraph.cli", "reconstruct", str(out_dir / "session"),
                                          "--out", tmp, "--viewer", "none", "--quiet"], cwd=root)
    np.savez(out_dir / "points.npz", points=dense.uv_px.reshape(C, F * M, 2), xyz_batgraph=xyz.reshape(F * M, 3),
             camera_names=np.array(dense.cameras), shape_cfm=np.array([C, F, M]),
             batgraph_triangulate_s=t_tri, batgraph_solve_fast_s=t_solve, batgraph_smoother_with_init_s=t_whole,
             batgraph_reconstruct_s=t_cmd)
    print(f"exported {C} cameras x {M} markers x {F} frames, {int(ideal.seen.sum())} observations, to {out_dir}")
    print(f"batgraph per-frame triangulation (DLT + covariance): {t_tri:.2f} s (median of "
          f"{', '.join(f'{t:.2f}' for t in tri_times)})")
    print(f"batgraph fast smoother solve (q = {FIXED_Q} m^2/s^3, Huber, + marginal covariances): {t_solve:.2f} s "
          f"(median of {', '.join(f'{t:.2f}' for t in solve_times)})")
    print(f"batgraph fast smoother from the pixels (its initial track + the solve): {t_whole:.2f} s (median of "
          f"{', '.join(f'{t:.2f}' for t in whole_times)})")
    print(f"batgraph reconstruct {out_dir / 'session'} (default methods, every output but the recording), whole "
          f"process: {t_cmd:.2f} s (median of {', '.join(f'{t:.2f}' for t in cmd_times)})")


def run(points_path: Path, calib_path: Path) -> None:
    """Time aniposelib's triangulate on the exported points; compare with batgraph's times and 3D points."""
    from aniposelib.cameras import CameraGroup

    data = np.load(points_path)
    points = data["points"]
    cgroup = CameraGroup.load(str(calib_path))
    # CameraGroup.load sorts the toml tables by name (cam_0, cam_1, cam_10, ...): reorder the points to match
    order = [list(data["camera_names"]).index(name) for name in cgroup.get_names()]
    points = np.ascontiguousarray(points[order])
    t0 = time.perf_counter()
    xyz = cgroup.triangulate(points, undistort=True)
    t_first = time.perf_counter() - t0
    t_anipose, times, xyz = _median_time(lambda: cgroup.triangulate(points, undistort=True))
    ref = data["xyz_batgraph"]
    both = np.isfinite(xyz).all(-1) & np.isfinite(ref).all(-1)
    d = np.linalg.norm(xyz[both] - ref[both], axis=-1)
    C, F, M = (int(x) for x in data["shape_cfm"])
    t_tri, t_solve = float(data["batgraph_triangulate_s"]), float(data["batgraph_solve_fast_s"])
    t_whole = float(data["batgraph_smoother_with_init_s"])
    print(f"aniposelib CameraGroup.triangulate(undistort=True), {C} cameras x {F * M} points: first call "
          f"{t_first:.2f} s (includes jax compilation), then {t_anipose:.2f} s (median of "
          f"{', '.join(f'{t:.2f}' for t in times)})")
    print(f"points triangulated: aniposelib {int(np.isfinite(xyz).all(-1).sum())}, batgraph "
          f"{int(np.isfinite(ref).all(-1).sum())}; |aniposelib - batgraph| median {1000 * np.median(d):.3f} mm, "
          f"95th percentile {1000 * np.percentile(d, 95):.3f} mm, max {1000 * d.max():.2f} mm")
    if "batgraph_reconstruct_s" in data:
        t_cmd = float(data["batgraph_reconstruct_s"])
        with tempfile.TemporaryDirectory() as tmp:
            t_user, user_times = _process_time([sys.executable, "-c", _ANIPOSE_SCRIPT, str(points_path),
                                                str(calib_path), str(Path(tmp) / "points3d.csv")])
        print(f"aniposelib as a script, whole process (import, load, triangulate, write the CSV): {t_user:.2f} s "
              f"(median of {', '.join(f'{t:.2f}' for t in user_times)}); batgraph reconstruct, whole process: "
              f"{t_cmd:.2f} s: ratio batgraph / aniposelib {t_cmd / t_user:.2f} (issue 12 asks <= 2)")
    print(f"ratio aniposelib triangulate / batgraph fast smoother solve: {t_anipose / t_solve:.2f}x "
          f"(first call: {t_first / t_solve:.2f}x); aniposelib / batgraph smoother with its initial track: "
          f"{t_anipose / t_whole:.2f}x; aniposelib / batgraph per-frame triangulation: {t_anipose / t_tri:.2f}x")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="(batgraph venv) write points.npz + calibration.toml and time batgraph")
    e.add_argument("out_dir", type=Path)
    e.add_argument("--cameras", type=int, default=30)
    e.add_argument("--markers", type=int, default=180)
    e.add_argument("--frames", type=int, default=160)
    r = sub.add_parser("run", help="(.venv-bench) time aniposelib on the exported points")
    r.add_argument("points", type=Path)
    r.add_argument("calibration", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "export":
        export(args.out_dir, args.cameras, args.markers, args.frames)
    else:
        run(args.points, args.calibration)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
