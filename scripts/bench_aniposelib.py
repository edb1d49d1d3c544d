"""aniposelib's CameraGroup.triangulate against batgraph on the same 30 x 180 x 160 observations.

Two steps, two environments (aniposelib needs opencv-contrib-python, which conflicts with batgraph's
opencv-python-headless, so it lives in its own venv, .venv-bench; it is not a batgraph dependency):

  .venv/bin/python scripts/bench_aniposelib.py export DIR
      simulates the flight, writes DIR/calibration.toml (aniposelib's format) and DIR/points.npz:
      raw pixels ``points`` (C, F*M, 2) with NaN where unseen (point index = frame * M + marker),
      batgraph's per-frame triangulation ``xyz_batgraph`` (F*M, 3) [m], the simulated ``xyz_truth``
      (F*M, 3) [m], where batgraph's Python and the session are, and batgraph's times [s] on
      this machine (per-frame triangulation, the fast smoother solve at a fixed q from the initial track,
      and the same smoother including the building of its initial track), medians of 3.
  .venv-bench/bin/python scripts/bench_aniposelib.py run DIR/points.npz DIR/calibration.toml
      times CameraGroup.load(...).triangulate(points, undistort=True) (first call, which includes jax's
      compilation, then the median of 3 more) and prints the ratios, the median 3D difference, both
      triangulations' errors against the simulated truth, and the truth's and both answers' reprojection
      residuals through aniposelib's own cameras (the truth's say that aniposelib reads calibration.toml as
      batgraph wrote it: ~1.18 px, the median of a 2D residual of 1 px noise per axis).

Whole processes as a user runs them (issue 12: "the default reconstruct within 2x of aniposelib's triangulate
+ CSV on the same sessions"): ``export`` also writes the scene as a batgraph session (DIR/session), and ``run``
times, in PAIRS alternated pairs, ``batgraph reconstruct DIR/session`` (default methods, every output but the
recording; batgraph's own Python, as ``export`` recorded it) and a fresh process that imports aniposelib, loads
the calibration, triangulates the points and writes them as a CSV (frame, marker, x, y, z), as a script around
aniposelib would; medians. Alternated, because this machine's load moves by tens of percent within minutes.

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
PAIRS = 5  # whole processes timed in alternation, batgraph's then aniposelib's


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
        subprocess.run(argv, cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # warnings
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
    truth = np.full((F, M, 3), np.nan)  # the simulated positions, to score both triangulations
    t = session.truth
    truth[t["frame"].to_numpy(), t["marker"].map({m: j for j, m in enumerate(dense.markers)}).to_numpy()] = (
        t[["x", "y", "z"]].to_numpy())
    np.savez(out_dir / "points.npz", points=dense.uv_px.reshape(C, F * M, 2), xyz_batgraph=xyz.reshape(F * M, 3),
             xyz_truth=truth.reshape(F * M, 3), batgraph_python=sys.executable, batgraph_root=str(root),
             session_dir=str((out_dir / "session").resolve()),
             camera_names=np.array(dense.cameras), shape_cfm=np.array([C, F, M]),
             batgraph_triangulate_s=t_tri, batgraph_solve_fast_s=t_solve, batgraph_smoother_with_init_s=t_whole)
    print(f"exported {C} cameras x {M} markers x {F} frames, {int(ideal.seen.sum())} observations, to {out_dir}")
    print(f"batgraph per-frame triangulation (DLT + covariance): {t_tri:.2f} s (median of "
          f"{', '.join(f'{t:.2f}' for t in tri_times)})")
    print(f"batgraph fast smoother solve (q = {FIXED_Q} m^2/s^3, Huber, + marginal covariances): {t_solve:.2f} s "
          f"(median of {', '.join(f'{t:.2f}' for t in solve_times)})")
    print(f"batgraph fast smoother from the pixels (its initial track + the solve): {t_whole:.2f} s (median of "
          f"{', '.join(f'{t:.2f}' for t in whole_times)})")


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
    if "xyz_truth" in data:  # both against the simulated truth; the truth reprojected by aniposelib's own cameras
        truth = data["xyz_truth"]
        ok = both & np.isfinite(truth).all(-1)
        for name, pts in (("aniposelib", xyz), ("batgraph", ref)):
            e = 1000 * np.linalg.norm(pts[ok] - truth[ok], axis=-1)
            print(f"{name} triangulation against the truth: median {np.median(e):.3f} mm, RMSE "
                  f"{np.sqrt(np.mean(e ** 2)):.3f} mm, 95th percentile {np.percentile(e, 95):.3f} mm")
        seen = np.isfinite(points).all(-1)
        for name, pts in (("the truth", truth), ("aniposelib's points", xyz), ("batgraph's points", ref)):
            r = np.linalg.norm(cgroup.project(np.nan_to_num(pts)) - points, axis=-1)[seen & np.isfinite(pts).all(-1)]
            print(f"{name} reprojected by aniposelib's cameras: median residual {np.median(r):.3f} px")
    if "batgraph_python" in data:  # the two whole processes alternated in one window: this machine's load moves
        with tempfile.TemporaryDirectory() as tmp:
            ani_argv = [sys.executable, "-c", _ANIPOSE_SCRIPT, str(points_path), str(calib_path),
                        str(Path(tmp) / "points3d.csv")]
            bg_argv = [str(data["batgraph_python"]), "-m", "batgraph.cli", "reconstruct", str(data["session_dir"]),
                       "--out", str(Path(tmp) / "out"), "--viewer", "none", "--quiet"]
            user_times, cmd_times = [], []
            for _ in range(PAIRS):
                cmd_times += _process_time(bg_argv, cwd=Path(str(data["batgraph_root"])), repeats=1)[1]
                user_times += _process_time(ani_argv, repeats=1)[1]
        t_user, t_cmd = statistics.median(user_times), statistics.median(cmd_times)
        print(f"whole processes, {PAIRS} alternated pairs: aniposelib as a script (import, load, triangulate, write "
              f"the CSV) {t_user:.2f} s (median of {', '.join(f'{t:.2f}' for t in user_times)}); batgraph reconstruct "
              f"(default methods, every output but the recording) {t_cmd:.2f} s (median of "
              f"{', '.join(f'{t:.2f}' for t in cmd_times)}): ratio batgraph / aniposelib {t_cmd / t_user:.2f} "
              f"(issue 12 asks <= 2)")
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
