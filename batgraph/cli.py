"""Command line: parses arguments and calls library functions; nothing else lives here.

``batgraph reconstruct|simulate|import|export|view ...``; ``scripts/NAME.py`` are thin wrappers.
User errors (:class:`batgraph.errors.InputError`) print one line and exit with code 2.
"""

from __future__ import annotations

# isort: off
from . import _startup  # first: BLAS threads and no collection while the modules below load
# isort: on
import argparse
import gc
import math
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from numba.core.errors import NumbaWarning

from .batch import exit_code, format_batch_table, is_batch, reconstruct_many
from .calibrate import calibrate_session, write_calibration
from .camera import Rig
from .detect import BlobOptions, detect, report_lines
from .errors import InputError
from .formats.anipose import import_anipose
from .formats.c3d_trc import write_c3d, write_table, write_trc
from .formats.csv_text import write_csv
from .formats.deeplabcut import import_deeplabcut
from .formats.dltdv import export_dltdv, import_dltdv, point_names
from .formats.pose2sim import import_pose2sim
from .inputs import (
    angle_deg,
    check_output_dir,
    check_output_file,
    fraction,
    frame_count,
    image_side,
    nonnegative_float,
    nonnegative_int,
    number,
    os_error_message,
    positive_float,
    positive_int,
    probability,
    read_json_object,
)
from .intrinsics import Board, calibrate_intrinsics
from .methods import help_text as methods_help
from .naming import associate_command as associate
from .pipeline import DEFAULT_METHODS, parse_methods, read_result_tables, reconstruct
from .result import SYNC, Options
from .session import read_calibration, read_session, write_session
from .simulate import Timing, simulate_ear, simulate_flight, simulate_wand
from .solver import kernels
from .summary import terminal_lines
from .validation_table import COLUMNS, format_table
from .viewer import display_available, open_recording

_startup.imports_done()


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (``batgraph CMD: error: ...``) and exit code 2, as InputError's;
    option ranges are checked by the ``type=`` functions of batgraph.inputs."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _progress_bars(args) -> bool:
    """Progress bars only for a person at a terminal: not with --quiet, nor into a log file or pipe
    (a bar redrawn with carriage returns is noise there)."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def _add_model_options(p) -> None:
    """The model's and the solvers' options, which reconstruct and validate share (read by :func:`_options`)."""
    p.add_argument("--motion", choices=["auto", "constant_velocity", "constant_acceleration", "random_walk"],
                   help="motion model (default: session.toml [motion] model, else auto: the smoother picks constant "
                        "velocity or acceleration per marker by marginal likelihood; the filters use constant "
                        "velocity for auto and constant_acceleration)")
    p.add_argument("--accel-psd", type=positive_float, metavar="Q",
                   help="constant-velocity white-noise acceleration PSD [m^2/s^3] (default: chosen from the data)")
    p.add_argument("--sync", choices=["estimate", "given"],
                   help="estimate: each camera's time offset and rolling-shutter readout from the markers, with the "
                        "trajectories (written to OUT/rig.toml); given: the calibration's timing as it is (default: "
                        "session.toml [sync] estimate, else given)")
    p.add_argument("--robust", choices=["huber", "cauchy", "none"], default="huber",
                   help="robust loss on projection factors (default huber)")
    p.add_argument("--robust-k", type=positive_float, default=2.0, help="robust loss threshold [sigmas] (default 2)")
    p.add_argument("--solver", choices=["fast", "gtsam"], default="fast",
                   help="smoother/filter solver: batgraph's vectorised per-marker solvers (fast, default; same "
                        "problem, tested against GTSAM) or GTSAM's LM / iSAM2 directly (gtsam)")


def _options(args, refine_rig: bool = False) -> Options:
    """The run's Options from the arguments of :func:`_add_model_options` (and --quiet's progress bars)."""
    return Options(motion_model=args.motion, robust=args.robust, robust_k=args.robust_k,
                   accel_psd_m2_s3=args.accel_psd, sync=SYNC[args.sync], refine_rig=refine_rig,
                   progress=_progress_bars(args), solver=args.solver)


# ----- reconstruct -----------------------------------------------------------------------------
def _add_reconstruct(sub):
    p = sub.add_parser("reconstruct", help="3D trajectories of every marker on every frame, with covariance",
                       description="Reconstruct 3D marker trajectories from a session folder (or several). A "
                                   "folder of unlabelled detections (detections.csv and seed_labels.csv, no "
                                   "observations) is named first, as `batgraph associate` does.")
    p.add_argument("sessions", nargs="+", metavar="SESSION", help="session folder(s) or glob pattern(s)")
    p.add_argument("--out", help="output folder (default SESSION/out; with several sessions OUT/<session>)")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration.toml to use instead of each session's own (e.g. from `calibrate` on a wand "
                        "recording); the session folders are not modified")
    p.add_argument("--methods", help=methods_help())
    p.add_argument("--compare", action="store_true", help="add every other method, for a side-by-side report")
    _add_model_options(p)
    p.add_argument("--refine-rig", action="store_true",
                   help="refine every camera's pose with the trajectories (a rig bumped since its calibration; the "
                        "refined rig goes to OUT/rig.toml)")
    p.add_argument("--viewer", choices=["spawn", "save", "none"],
                   help="Rerun: stream the filter live to a viewer window and save recording.rrd (spawn, the "
                        "default with a display), only write recording.rrd (save, the default without one), or none")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the sessions on an existing Dask cluster (default: worker processes here)")
    p.add_argument("--workers", type=positive_int, help="worker processes for several sessions (default: one per core)")
    p.add_argument("--verbose", action="store_true", help="with several sessions: tracebacks of crashed ones")
    p.add_argument("--quiet", action="store_true", help="no progress bars or summary table")
    p.add_argument("--validate", action="store_true",
                   help="also run leave-one-camera-out validation (see `batgraph validate`): validation.csv, "
                        "summary.json 'validation', a report section")
    p.set_defaults(func=_cmd_reconstruct)


def summary_lines(summary: dict) -> list[str]:
    """The end-of-run text (batgraph.summary.terminal_lines): reads summary.json's figures; computes none."""
    return terminal_lines(summary)


def _compile_note(args) -> None:
    """One line on stderr before a run that will first compile batgraph's inner loops (batgraph.solver.kernels),
    so that a minute of silence after an install is explained; also with --quiet (a silent minute looks hung)."""
    if args.solver != "fast":
        return

    if kernels.needs_compiling():
        print("batgraph: compiling its inner loops for this machine, once after an install or update "
              "(about 15-40 s on 2 cores; cached on disk after)", file=sys.stderr)


def _check_not_a_result(session: str | Path) -> None:
    """InputError when ``session`` is a reconstruct result folder (trajectories.csv or summary.json, no
    session.toml), a common slip: say so and what to do, as ``export`` does for the reverse one."""
    folder = Path(session)
    try:
        if not folder.is_dir() or (folder / "session.toml").exists():
            return
        found = [n for n in ("trajectories.csv", "summary.json") if (folder / n).is_file()]
    except OSError:
        return  # reading the session reports it
    if found:
        raise InputError(f"{folder}: a reconstruct result folder ({', '.join(found)}; no session.toml), not a "
                         f"session: give the session folder it was made from (session.toml, calibration.toml, "
                         f"observations.csv), or use this result: batgraph export c3d|trc|csv|dltdv {folder}, "
                         f"batgraph view {folder}, {folder / 'report.html'}")


def _cmd_reconstruct(args) -> int:
    for session in args.sessions:
        _check_not_a_result(session)
    methods = parse_methods(args.methods, args.compare)
    options = _options(args, args.refine_rig)
    batch = is_batch(args.sessions) or args.scheduler is not None
    if args.out is not None or (not batch and Path(args.sessions[0]).is_dir()):
        check_output_dir(args.out if args.out is not None else Path(args.sessions[0]) / "out")
    viewer = args.viewer
    if viewer is None:
        viewer = "spawn" if display_available() and not batch else "save"
    if batch:
        _compile_note(args)
        items = reconstruct_many(args.sessions, args.out, methods, options, scheduler=args.scheduler,
                                 n_workers=args.workers, progress=_progress_bars(args), viewer=viewer,
                                 calibration=args.calibration, validate=args.validate)
        for it in items:  # even with --quiet: a warning may mean the numbers are wrong
            for w in it.warnings:
                print(f"batgraph: warning: {it.name}: {w}", file=sys.stderr)
        if args.quiet:
            for it in items:
                if it.status != "ok":
                    print(f"batgraph: {it.status}: {it.message}", file=sys.stderr)
            n_ok = sum(it.status == "ok" for it in items)  # where the results went, even with --quiet
            where = Path(args.out) / "<session>" if args.out else "<session>/out"
            print(f"wrote {n_ok} of {len(items)} results to {where}"
                  + (f" (summary: {Path(args.out) / 'batch_summary.csv'})" if args.out else ""))
        else:
            print(format_batch_table(items, verbose=args.verbose))
        return exit_code(items)
    _compile_note(args)
    result = reconstruct(args.sessions[0], args.out, methods, options, viewer=viewer, calibration=args.calibration,
                         validate=args.validate, validate_workers=args.workers)
    for w in result.session.warnings:  # even with --quiet: a warning may mean the numbers are wrong
        print(f"batgraph: warning: {w}", file=sys.stderr)
    if args.quiet:  # one line: where the results went
        print(f"{result.session.name}: wrote {len(result.files)} files to {result.out_dir}")
    else:
        print(f"{result.session.name}: wrote {', '.join(p.name for p in result.files)} to {result.out_dir}")
        print("\n".join(summary_lines(result.summary)))
        if "validation" in result.summary:
            print("\n".join(validation_lines(result.summary["validation"])))
        print(f"report: {result.out_dir / 'report.html'}")
        if viewer != "none":
            print(f"3D viewer: batgraph view {result.out_dir}   (or: rerun {result.out_dir / 'recording.rrd'})")
    return 0


# ----- validate --------------------------------------------------------------------------------
def _add_validate(sub):
    p = sub.add_parser("validate", help="leave-one-camera-out accuracy of every method, without ground truth",
                       description="Reconstruct SESSION as `reconstruct` does (every output written), then, for "
                                   "each camera, run every method without that camera's observations and measure "
                                   "how well the estimate predicts them: median and p90 error [px] per camera, "
                                   "method and status. Writes validation.csv; adds 'validation' to summary.json "
                                   "and a section to report.html.")
    p.add_argument("session", metavar="SESSION", help="session folder")
    p.add_argument("--out", help="output folder (default SESSION/out)")
    p.add_argument("--calibration", metavar="FILE", help="calibration.toml to use instead of the session's own")
    p.add_argument("--methods", help="comma-separated: smoother, filter, ekf, ukf, triangulate "
                                     "(default smoother,filter,triangulate)")
    p.add_argument("--compare", action="store_true", help="add every other method")
    _add_model_options(p)
    p.add_argument("--viewer", choices=["save", "none"], default="save",
                   help="write recording.rrd (save, default) or not (none)")
    p.add_argument("--workers", type=positive_int, help="processes for the folds (default: one per core)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or tables")
    p.set_defaults(func=_cmd_validate)


def validation_lines(validation: dict) -> list[str]:
    """The terminal's validation table (from summary.json's "validation" section) and its verdict."""
    table = pd.DataFrame(validation.get("table") or [], columns=COLUMNS)
    lines = ["leave-one-camera-out: error [px] of each method's 3D projected into the held-out camera "
             "(status without that camera; common = points every method estimates)"]
    lines += format_table(table)
    lines.append(f"verdict: {validation.get('verdict', '')}")
    return lines


def _cmd_validate(args) -> int:
    _check_not_a_result(args.session)
    if args.out is not None or Path(args.session).is_dir():
        check_output_dir(args.out if args.out is not None else Path(args.session) / "out")
    text = args.methods or ",".join([*DEFAULT_METHODS, "triangulate"])
    methods = parse_methods(text, args.compare)
    options = _options(args)
    _compile_note(args)
    result = reconstruct(args.session, args.out, methods, options, viewer=args.viewer, calibration=args.calibration,
                         validate=True, validate_workers=args.workers)
    for w in result.session.warnings:  # even with --quiet: a warning may mean the numbers are wrong
        print(f"batgraph: warning: {w}", file=sys.stderr)
    if not args.quiet:
        print(f"{result.session.name}: wrote {', '.join(p.name for p in result.files)} to {result.out_dir}")
        print("\n".join(validation_lines(result.summary["validation"])))
        print(f"report: {result.out_dir / 'report.html'}")
    return 0


# ----- simulate --------------------------------------------------------------------------------
def _add_simulate(sub):
    p = sub.add_parser("simulate", help="write a synthetic session with ground truth (bat flight, ear, wand)",
                       description="Write a simulated session folder with truth.csv. `wand` is a 0.5 m "
                                   "calibration wand waved through the flight tunnel, filmed by the same rig "
                                   "(and calibration error) as `flight` with the same --seed and --cameras.")
    p.add_argument("scene", choices=["flight", "ear", "wand"])
    p.add_argument("out", metavar="OUT_SESSION")
    p.add_argument("--cameras", type=positive_int, help="number of cameras (flight: default 5, up to 30)")
    p.add_argument("--markers", type=positive_int,
                   help="flight: total markers, 14 skeleton markers plus wing-membrane markers up to 180")
    p.add_argument("--frames", type=frame_count, help="number of frames (default 160 flight, 250 ear)")
    p.add_argument("--fps", type=positive_float, help="frame rate [Hz] (default 120 flight, 250 ear)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="random seed (default 0)")
    p.add_argument("--noise-px", type=nonnegative_float, default=1.0, help="pixel noise std [px] (default 1)")
    p.add_argument("--outlier-rate", type=fraction, default=0.0, help="fraction of mislabelled detections")
    p.add_argument("--calib-rot-deg", type=angle_deg, default=0.0,
                   help="calibration error: rotation of each affected camera [deg]")
    p.add_argument("--calib-trans-mm", type=nonnegative_float, default=0.0,
                   help="calibration error: translation of each affected camera [mm]")
    t = p.add_argument_group("timing (flight, ear; docs/timing.md)")
    t.add_argument("--time-offsets-ms", type=_numbers, metavar="A,B,...",
                   help="each camera's time offset [ms]: its frame j is exposed at j / fps + offset (whole-frame lags "
                        "are multiples of 1000 / fps)")
    t.add_argument("--readout-ms", type=_numbers, metavar="R[,R2,...]",
                   help="rolling-shutter readout [ms], one value or one per camera (default 0: global shutter)")
    t.add_argument("--camera-fps", type=_numbers, metavar="F1,F2,...",
                   help="each camera's frame rate [Hz], none above --fps (the session's)")
    t.add_argument("--timing-known", action="store_true",
                   help="write the true offsets and readouts into calibration.toml (default: it states only the "
                        "cameras' fps; the truth goes to truth_timing.toml)")
    p.add_argument("--force", action="store_true", help="overwrite an existing session folder")
    p.set_defaults(func=_cmd_simulate)


def _numbers(text: str) -> list[float]:
    """A comma-separated list of finite numbers (argparse type)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return values


def _timing(args, n_cameras: int):
    """The simulate command's timing flags as a batgraph.simulate.Timing (None without any); InputError if bad."""
    if args.time_offsets_ms is None and args.readout_ms is None and args.camera_fps is None:
        if args.timing_known:
            raise InputError("--timing-known: give the timing (--time-offsets-ms, --readout-ms, --camera-fps)")
        return None
    if args.scene == "wand":
        raise InputError("--time-offsets-ms, --readout-ms, --camera-fps: only for the flight and ear scenes")
    for flag, values, per_camera in (("--time-offsets-ms", args.time_offsets_ms, True),
                                     ("--readout-ms", args.readout_ms, False), ("--camera-fps", args.camera_fps, True)):
        if values is not None and len(values) != n_cameras and (per_camera or len(values) != 1):
            raise InputError(f"{flag}: expected {n_cameras} values (one per camera){'' if per_camera else ' or one'}, "
                             f"got {len(values)}")
    readout = [v / 1000 for v in args.readout_ms] if args.readout_ms is not None else [0.0]
    offsets = None if args.time_offsets_ms is None else tuple(v / 1000 for v in args.time_offsets_ms)
    timing = Timing(time_offsets_s=offsets,
                    readout_s=readout[0] if len(readout) == 1 else tuple(readout),
                    camera_fps=None if args.camera_fps is None else tuple(args.camera_fps), known=args.timing_known)
    try:
        timing.cameras(n_cameras, args.fps or (120.0 if args.scene == "flight" else 250.0))
    except ValueError as e:
        raise InputError(f"simulate timing: {e}" + (" (raise --fps)" if "camera_fps" in str(e) else "")) from None
    return timing


def _cmd_simulate(args) -> int:
    out = _check_new_session_folder(args.out, args.force)
    if not 0 <= args.outlier_rate < 1:
        raise InputError(f"--outlier-rate: must be in [0, 1), got {args.outlier_rate}")
    if args.noise_px < 0:
        raise InputError(f"--noise-px: must be >= 0, got {args.noise_px}")
    rng = np.random.default_rng(args.seed)
    common = {"pixel_sigma_px": args.noise_px, "outlier_rate": args.outlier_rate}
    if args.frames:
        common["n_frames"] = args.frames
    if args.fps:
        common["fps"] = args.fps
    if args.cameras and args.cameras > 30:
        raise InputError(f"--cameras: at most 30, got {args.cameras}")
    timing = _timing(args, 2 if args.scene == "ear" else args.cameras or 5)
    if args.scene == "flight":
        if args.markers is not None and not 14 <= args.markers <= 180:
            raise InputError(f"--markers: must be between 14 and 180, got {args.markers}")
        session = simulate_flight(rng, n_cameras=args.cameras or 5, n_markers=args.markers,
                                  calib_rot_deg=args.calib_rot_deg, calib_trans_mm=args.calib_trans_mm, timing=timing,
                                  **common)
    elif args.scene == "wand":
        session = simulate_wand(rng, n_cameras=args.cameras or 5, calib_rot_deg=args.calib_rot_deg,
                                calib_trans_mm=args.calib_trans_mm, **common)
    else:
        session = simulate_ear(rng, timing=timing, **common)
    write_session(session, out)
    print(f"wrote {args.scene} session to {out} ({len(session.rig)} cameras, {len(session.markers)} markers, "
          f"{len(session.frames)} frames, {len(session.observations)} observations)")
    return 0


def _check_new_session_folder(path, force: bool) -> Path:
    """The folder ``simulate`` / ``import`` may write a session into: writable, and empty unless --force."""
    out = check_output_dir(path, "session folder")
    try:
        full = out.is_dir() and any(out.iterdir())
    except OSError as e:
        raise InputError(f"{out}: cannot be read ({e.strerror or type(e).__name__})") from None
    if full and not force:
        what = "holds a session" if (out / "session.toml").exists() else "is not empty"
        raise InputError(f"{out}: folder exists and {what} (use --force to overwrite)")
    return out


# ----- import ----------------------------------------------------------------------------------
def _add_import(sub):
    p = sub.add_parser("import", help="convert another tool's files into a session folder")
    fmt = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    d = fmt.add_parser("dltdv", help="DLTdv / Argus / easyWand xypts + DLT coefficients",
                       description="Import a DLTdv trial: *xypts.csv and *dltCoefs.csv. The pixel origin and the "
                                   "world's handedness are read from the coefficients.")
    d.add_argument("--xypts", required=True, help="DLTdv *xypts.csv (one row per frame)")
    d.add_argument("--coefs", required=True, help="DLT coefficients *dltCoefs.csv (11 rows x cameras)")
    d.add_argument("--fps", required=True, type=positive_float, help="camera frame rate [Hz]")
    d.add_argument("--out", required=True, help="session folder to write")
    d.add_argument("--pixel-origin", choices=["lower-left", "upper-left"],
                   help="pixel origin of the files (default: detected from the coefficients; every DLTdv version "
                        "writes lower-left); one the coefficients contradict means a mirrored world")
    d.add_argument("--units", choices=["m", "cm", "mm"], default="m",
                   help="world units of the coefficients and xyzpts (default m); the session is in metres")
    d.add_argument("--dltdv-version", type=int, help=argparse.SUPPRESS)  # accepted and ignored: the origin is detected
    d.add_argument("--image-size", type=image_side, nargs=2, metavar=("W", "H"), help="image size [px]")
    d.add_argument("--xyzpts", help="DLTdv's own *xyzpts.csv, kept as a reference for reports")
    d.add_argument("--pixel-sigma", type=positive_float,
                   help="click noise std [px] (default: measured per camera by reconstruct)")
    d.add_argument("--offsets", nargs="+", metavar="FILE", default=[],
                   help="camera offsets: DLTdv8 *offsets.csv or Argus clicker *-offsets.csv (which video frame each "
                        "row shows; non-integer allowed) and/or Argus sync *_offsets.csv (to a fraction of a frame); "
                        "they become calibration.toml's time_offset_s (docs/timing.md)")
    d.add_argument("--force", action="store_true", help="overwrite an existing session folder")
    d.set_defaults(func=_cmd_import_dltdv)

    k = fmt.add_parser("deeplabcut", help="DeepLabCut 2D outputs (one .h5/.csv per camera) + calibration.toml")
    k.add_argument("files", nargs="+", help="one DeepLabCut output file per camera")
    k.add_argument("--calibration", required=True, help="aniposelib calibration.toml")
    k.add_argument("--camera-names", nargs="+", help="camera of each file (default: matched from file names)")
    k.add_argument("--threshold", type=probability, default=0.6, help="drop points below this likelihood (default 0.6)")
    k.add_argument("--individual", help="multi-animal DeepLabCut: which individual")
    _common_import_args(k)
    k.set_defaults(func=_cmd_import_keypoints)

    a = fmt.add_parser("anipose", help="an Anipose project's pose-2d files + calibration.toml")
    a.add_argument("project", help="Anipose project (or session) folder")
    a.add_argument("--calibration", help="calibration.toml (default: found in the project)")
    a.add_argument("--trial", help="which trial (default: the only one)")
    a.add_argument("--threshold", type=probability,
                   help="likelihood threshold (default: the project's score_threshold)")
    a.add_argument("--cam-regex", help="regex of the camera name in file names (default: the project's)")
    _common_import_args(a)
    a.set_defaults(func=_cmd_import_keypoints)

    o = fmt.add_parser("pose2sim", help="Pose2Sim / OpenPose JSON folders (one per camera) + calibration")
    o.add_argument("json_dirs", nargs="+", help="one folder of OpenPose JSON files per camera")
    o.add_argument("--calibration", required=True, help="Pose2Sim Calib_*.toml (aniposelib format)")
    o.add_argument("--keypoints", default="BODY_25B", help="keypoint model (default BODY_25B; its bones become "
                   "session.toml's skeleton)")
    o.add_argument("--camera-names", nargs="+", help="camera of each folder (default: matched from folder names)")
    o.add_argument("--threshold", type=probability, default=0.3,
                   help="drop keypoints below this confidence (default 0.3)")
    o.add_argument("--person", type=nonnegative_int, default=0, help="which person in each JSON file (default 0)")
    o.add_argument("--reference-trc", help="Pose2Sim's own 3D (.trc), kept for comparison in reports")
    o.add_argument("--pixel-sigma", type=positive_float,
                   help="keypoint noise std [px] (default: measured per camera by reconstruct)")
    _common_import_args(o)
    o.set_defaults(func=_cmd_import_keypoints)


def _common_import_args(p):
    p.add_argument("--fps", required=True, type=positive_float, help="camera frame rate [Hz]")
    p.add_argument("--out", required=True, help="session folder to write")
    p.add_argument("--units", choices=["m", "cm", "mm"],
                   help="translation units of the calibration (default: its [metadata] units, else m)")
    p.add_argument("--force", action="store_true", help="overwrite an existing session folder")


def _cmd_import_keypoints(args) -> int:
    _check_new_session_folder(args.out, args.force)
    if args.fps <= 0:
        raise InputError(f"--fps: must be > 0, got {args.fps}")
    if args.format == "deeplabcut":
        session = import_deeplabcut(args.files, args.calibration, args.fps, args.out, camera_names=args.camera_names,
                                    threshold=args.threshold, individual=args.individual, units=args.units)
    elif args.format == "anipose":
        session = import_anipose(args.project, args.fps, args.out, calibration=args.calibration,
                                 threshold=args.threshold, trial=args.trial, cam_regex=args.cam_regex,
                                 units=args.units)
    else:
        session = import_pose2sim(args.json_dirs, args.calibration, args.fps, args.out, keypoints=args.keypoints,
                                  threshold=args.threshold, camera_names=args.camera_names, person=args.person,
                                  reference_trc=args.reference_trc, pixel_sigma_px=args.pixel_sigma,
                                  units=args.units)
    print(f"wrote session to {args.out} ({len(session.rig)} cameras, {len(session.markers)} markers, "
          f"{len(session.observations)} observations)")
    return 0


def _cmd_import_dltdv(args) -> int:
    _check_new_session_folder(args.out, args.force)
    if args.fps <= 0:
        raise InputError(f"--fps: must be > 0, got {args.fps}")
    if args.dltdv_version is not None:
        print("note: --dltdv-version is ignored: every DLTdv version writes lower-left pixels, and the origin is "
              "read from the coefficients (use --pixel-origin to override)", file=sys.stderr)
    session = import_dltdv(args.xypts, args.coefs, args.fps, args.out, pixel_origin=args.pixel_origin,
                           units=args.units, image_size=tuple(args.image_size) if args.image_size else None,
                           xyzpts=args.xyzpts, pixel_sigma_px=args.pixel_sigma, offsets=args.offsets)
    imp = session.extra_toml["import"]
    print(f"pixel origin: {imp['pixel_origin']} ({imp['pixel_origin_note']}); world: {imp['world']}; "
          f"units: {imp['units']}" + ("; image size guessed from the principal point (give --image-size W H)"
                                      if imp["image_size"] == "inferred" else ""))
    if args.offsets:
        print("time offsets [ms]: " + ", ".join(f"{c.name} {1e3 * c.time_offset_s:+.3f}" for c in session.rig)
              + (f"; {imp['clicks_before_first_video_frame']} click(s) before a video's first frame dropped"
                 if imp.get("clicks_before_first_video_frame") else ""))
    print(f"wrote session to {args.out} ({len(session.rig)} cameras, {len(session.markers)} markers, "
          f"{len(session.observations)} observations)")
    return 0


# ----- calibrate -------------------------------------------------------------------------------
def _add_calibrate(sub):
    p = sub.add_parser("calibrate", help="refine the rig by bundle adjustment (pycolmap) of all cameras at once",
                       description="Bundle-adjust the whole rig from the session's own observations (or a wand) "
                                   "and write a calibration.toml with pose covariances.")
    p.add_argument("session", metavar="SESSION")
    p.add_argument("--out", help="calibration file to write (default SESSION/out/calibration.toml)")
    p.add_argument("--gauge", choices=["auto", "input", "camera0"], default="auto",
                   help="world frame and scale: fitted to the input rig by a similarity over every camera (input; "
                        "auto without a wand), or the reference camera held at its input pose (camera0; auto with "
                        "a wand or --from-scratch)")
    p.add_argument("--ref-camera", type=nonnegative_int, default=0, help="index of the reference camera (default 0)")
    p.add_argument("--wand", nargs=3, metavar=("END_A", "END_B", "LENGTH_M"),
                   help="two markers a known distance apart [m] (default: session.toml [wand])")
    p.add_argument("--from-scratch", action="store_true",
                   help="ignore the input poses: essential matrix + PnP, then bundle adjustment")
    p.add_argument("--refine-intrinsics", action="store_true", help="also refine focal lengths, principal points")
    p.add_argument("--refine-distortion", action="store_true", help="also refine distortion")
    p.add_argument("--hold-out", type=fraction, default=0.2, metavar="FRACTION",
                   help="1 / the number of folds (blocks of frames) of the held-out check: each fold is predicted "
                        "by a rig refined on the others (default 0.2: 5 folds; 0 skips the check)")
    p.add_argument("--force", action="store_true",
                   help="write the refined rig even when the verdict keeps the input rig")
    p.add_argument("--quiet", action="store_true", help="no progress bar or table (the verdict and the file "
                                                         "written are still printed)")
    p.set_defaults(func=_cmd_calibrate)

    q = sub.add_parser("calibrate-intrinsics", help="intrinsics of one camera from checkerboard/ChArUco images",
                       description="OpenCV intrinsic calibration from board images or videos.")
    q.add_argument("sources", nargs="+", help="images or videos of the board")
    q.add_argument("--board", choices=["checkerboard", "charuco"], required=True)
    q.add_argument("--cols", type=positive_int, required=True,
                   help="checkerboard: inner corners along x; ChArUco: squares along x")
    q.add_argument("--rows", type=positive_int, required=True, help="as --cols, along y")
    q.add_argument("--square-m", type=positive_float, required=True, help="square side [m]")
    q.add_argument("--marker-m", type=nonnegative_float, default=0.0, help="ChArUco marker side [m]")
    q.add_argument("--dictionary", default="DICT_4X4_50", help="ChArUco dictionary (default DICT_4X4_50)")
    q.add_argument("--name", default="cam1", help="camera name (default cam1)")
    q.add_argument("--dist-model", choices=["k1k2p1p2k3", "k1k2p1p2"], default="k1k2p1p2k3")
    q.add_argument("--every-nth", type=positive_int, default=1, help="use every n-th video frame")
    q.add_argument("--out", required=True, help="calibration.toml to write")
    q.set_defaults(func=_cmd_calibrate_intrinsics)


def _cmd_calibrate(args) -> int:
    _check_not_a_result(args.session)
    if args.out is not None or Path(args.session).is_dir():
        check_output_file(args.out if args.out is not None else Path(args.session) / "out" / "calibration.toml",
                          "calibration file (--out)")
    wand = None
    if args.wand:
        try:
            wand = (args.wand[0], args.wand[1], positive_float(args.wand[2]))
        except argparse.ArgumentTypeError as e:
            raise InputError(f"--wand: LENGTH_M {e}") from None
        if wand[0] == wand[1]:
            raise InputError(f"--wand: END_A and END_B are the same marker {wand[0]!r}")
    session = read_session(args.session)
    if wand is not None:
        seen = set(session.observations["marker"])
        for end in wand[:2]:
            if end not in seen:
                raise InputError(f"--wand: marker {end!r} has no observations in {args.session} "
                                 f"(markers: {', '.join(session.markers)})")
    if not 0 <= args.hold_out < 1:
        raise InputError(f"--hold-out: must be in [0, 1), got {args.hold_out}")
    rig, report = calibrate_session(session, gauge=args.gauge, ref_camera=args.ref_camera, wand=wand,
                                    initial="scratch" if args.from_scratch else "auto",
                                    refine_intrinsics=args.refine_intrinsics,
                                    refine_distortion=args.refine_distortion, progress=_progress_bars(args),
                                    hold_out=args.hold_out, keep_input_if_undetermined=not args.force)
    out = Path(args.out) if args.out else Path(args.session) / "out" / "calibration.toml"
    verdict = report["assessment"]
    if not args.quiet:
        print("\n".join(calibration_lines(report, session.true_rig is not None)))
    why = "; ".join(verdict["reasons"])
    if not verdict["determined"] and not args.force:
        raise InputError(f"{args.session}: calibrate: the observations do not determine the rig ({why}); nothing "
                         "written (give a wand: --wand or session.toml [wand], or --force to write it anyway)")
    if report["kept_input"]:
        print(f"batgraph: calibrate kept the input rig: {why} (--force writes the refinement anyway)",
              file=sys.stderr)
    elif why:
        print(f"batgraph: warning: the refinement is written although {why}", file=sys.stderr)
    write_calibration(out, rig, None if report["kept_input"] else report["gauge"]["note"])
    kept = " (the input rig, unchanged)" if report["kept_input"] else ""
    print(f"wrote {out}{kept}")
    return 0


def calibration_lines(report: dict, truth: bool) -> list[str]:
    """The terminal's calibrate table (per camera: fit, how far it moved with its 95 % bound) and the verdict."""
    lines = [f"{'camera':<10}{'RMS before px':>14}{'RMS after px':>13}{'used':>8}{'rejected':>9}"
             f"{'moved mm':>10}{'(95 %)':>8}{'turned deg':>11}{'(95 %)':>8}"
             + (f"{'error mm':>16}{'error deg':>16}" if truth else "")]
    a = report["assessment"]
    for name, c in report["cameras"].items():
        b = a["cameras"].get(name, {})
        line = (f"{name:<10}{c['rms_before_px']:>14.2f}{c['rms_after_px']:>13.2f}{c['n_used']:>8}"
                f"{c['n_rejected']:>9}{b.get('moved_mm', c['moved_mm']):>10.2f}{b.get('r95_position_mm', 0.0):>8.2f}"
                f"{b.get('turned_deg', c['turned_deg']):>11.3f}{b.get('r95_rotation_deg', 0.0):>8.3f}")
        if truth and c.get("error_mm") is not None:
            line += (f"{c['input_error_mm']:>8.2f} ->{c['error_mm']:>6.2f}"
                     f"{c['input_error_deg']:>8.3f} ->{c['error_deg']:>6.3f}")
        lines.append(line)
    lines.append("moved / turned: the written rig against the input; (95 %): the refined pose's 95 % radius"
                 + ("; error: input -> refined against the true rig after a similarity fit" if truth else ""))
    lines.append(f"frame: {report['gauge']['note']}")
    h = a.get("held_out") or {}
    if h:
        lines.append(f"held-out check: {h['folds']} folds of frames, each predicted ({h['prediction']}) by a rig "
                     f"refined on the others: RMS {h['rms_refined_px']:.2f} px (input rig: {h['rms_input_px']:.2f} px, "
                     f"{h['n_observations']} observations)")
    t = a.get("poses") or {}
    if t:
        lines.append(f"input vs refinement: gauge-free chi-square {t['chi2']:.1f} for {t['dof']} degrees of freedom "
                     f"({100 * t['level']:.0f} % bound {t['bound']:.1f})")
    if not a["determined"]:
        lines.append("verdict: not determined: " + "; ".join(a["reasons"]))
    elif report["kept_input"]:
        lines.append("verdict: the input rig is kept: " + "; ".join(a["reasons"]))
    else:
        lines.append("verdict: the refinement is written" + (" (forced)" if a["reasons"] else ""))
    return lines


def _cmd_calibrate_intrinsics(args) -> int:
    check_output_file(args.out, "calibration file (--out)")
    board = Board(args.board, args.cols, args.rows, args.square_m, args.marker_m, args.dictionary)
    cam, report = calibrate_intrinsics(args.sources, board, name=args.name, dist_model=args.dist_model,
                                       every_nth=args.every_nth)
    write_calibration(args.out, Rig([cam]))
    print(f"{args.name}: {report['n_views']} views, RMS {report['rms_px']:.3f} px; wrote {args.out}")
    return 0


# ----- view, export ----------------------------------------------------------------------------
def _add_view(sub):
    p = sub.add_parser("view", help="open a saved result (recording.rrd) in the Rerun viewer")
    p.add_argument("out_dir", metavar="OUT_DIR", help="a reconstruct output folder, or an .rrd file")
    p.set_defaults(func=_cmd_view)


def _cmd_view(args) -> int:
    open_recording(args.out_dir)
    return 0


def _add_export(sub):
    p = sub.add_parser("export", help="write a result in another tool's format",
                       description="Convert a reconstruct output folder for DLTdv/Argus, C3D readers or OpenSim (TRC), "
                                   "or to an analysis table (csv/parquet: positions, standard deviations, "
                                   "correlations, n_views, status, span; one row per frame and marker) for "
                                   "pandas or R. What each file holds: batgraph/formats/c3d_trc.py.")
    p.add_argument("format", choices=["dltdv", "c3d", "trc", "csv", "parquet"])
    p.add_argument("out_dir", metavar="OUT_DIR", help="a reconstruct output folder")
    p.add_argument("--method", help="which method (default: smoother if present, else the first); "
                                    "csv/parquet: 'all' writes every method")
    p.add_argument("--to", help="dltdv: file prefix (default OUT_DIR/<method>_); "
                                "others: file path (default OUT_DIR/<method>.<format>)")
    p.add_argument("--fps", type=positive_float, help="c3d/trc frame rate [Hz] (default: from summary.json)")
    p.add_argument("--units", choices=["m", "cm", "mm"],
                   help="dltdv: world units of xyzpts (default: those of the imported DLTdv project, else m); "
                        "trc/csv/parquet: default m; c3d is always mm")
    p.add_argument("--range", dest="range_", choices=["span", "observed", "all"],
                   help="which estimates to write, the others written as missing (NaN): span (default) = from each "
                        "marker's first to its last frame seen by >= 2 cameras; observed = only frames where it is "
                        "seen by >= 2 cameras; all = every estimate, the extrapolated track ends included")
    p.add_argument("--take", type=positive_int,
                   help="c3d/trc: which take of a result with several (1 = the first; default the longest): "
                        "a C3D or TRC file is one contiguous run of frames")
    p.set_defaults(func=_cmd_export)


def _cmd_export(args) -> int:
    out = Path(args.out_dir)
    traj, reproj = read_result_tables(out)
    methods = list(dict.fromkeys(traj["method"]))
    every = args.method == "all" and args.format in ("csv", "parquet")
    method = args.method or ("smoother" if "smoother" in methods else methods[0])
    if method not in methods and not every:
        raise InputError(f"{out / 'trajectories.csv'}: no method {method!r} (has: {', '.join(methods)})")
    if args.take is not None and args.format not in ("c3d", "trc"):
        raise InputError(f"export {args.format}: --take applies to c3d and trc only (the tables hold every take)")
    take = None if args.take is None else args.take - 1
    if args.format == "c3d" and args.units not in (None, "mm"):
        raise InputError("export c3d: C3D files are always written in mm (POINT:UNITS); drop --units")
    summary = out / "summary.json"
    facts = read_json_object(summary) if summary.is_file() else {}
    keep = args.range_ or "span"
    if args.format == "dltdv":
        imported = facts.get("import", {})
        units = args.units or (imported.get("units", "m") if isinstance(imported, dict) else "m")
        if units not in ("m", "cm", "mm"):
            raise InputError(f"{summary} import units: {units!r} is not one of m, cm, mm (give --units)")
        check_output_file(f"{args.to or out / f'{method}_'}xyzpts.csv")
        paths = export_dltdv(args.to or out / f"{method}_", traj, reproj, method, units=units, keep=keep)
        why = point_names(list(dict.fromkeys(traj.loc[traj["method"] == method, "marker"])))[1]
        if why:
            print(f"note: points numbered pt1..ptN in the order of trajectories.csv, not named: {why}",
                  file=sys.stderr)
    elif args.format in ("csv", "parquet"):
        dest = Path(args.to or out / f"{'all_methods' if every else method}.{args.format}")
        if dest.suffix != f".{args.format}":
            raise InputError(f"{dest}: an {args.format} export needs a .{args.format} file name")
        check_output_file(dest)
        paths = [write_table(dest, traj, units=args.units or "m", keep=keep, method=None if every else method)]
    else:
        fps = args.fps
        if fps is None:
            if "fps" not in facts:
                raise InputError(f"{summary}: file not found or no fps in it (give --fps)")
            fps = number(facts["fps"], f"{summary} fps", positive=True)
        dest = check_output_file(args.to or out / f"{method}.{args.format}")
        one = traj[traj["method"] == method]
        if args.format == "c3d":
            rig = facts.get("pixel_sigma_px")  # camera name -> px, in the rig's order
            cameras = list(rig) if isinstance(rig, dict) and rig else None
            paths = [write_c3d(dest, one, fps, keep=keep, reprojection=reproj, cameras=cameras, take=take)]
        else:
            paths = [write_trc(dest, one, fps, units=args.units or "m", keep=keep, take=take)]
    print("wrote " + ", ".join(str(p) for p in paths) + f" ({_RANGE_NOTE[keep]})")
    return 0


_RANGE_NOTE = {
    "span": "each marker from its first to its last frame seen by >= 2 cameras; the extrapolated track ends are "
            "left out, --range all writes them",
    "observed": "only points seen by >= 2 cameras",
    "all": "every estimate, the extrapolated track ends included",
}


# ----- associate -------------------------------------------------------------------------------
def _add_associate(sub):
    p = sub.add_parser("associate", help="name unlabelled marker detections (detections.csv) from a seed frame",
                       description="Label unlabelled detections (SESSION/detections.csv: frame, camera, u, v) from "
                                   "the markers named once in SESSION/seed_labels.csv (frame, camera, marker, u, v), "
                                   "and write a session with observations.csv (named detections) and labels.csv "
                                   "(every detection, its marker, track and confidence). See docs/associate.md.")
    p.add_argument("session", metavar="SESSION", help="session folder with detections.csv and seed_labels.csv")
    p.add_argument("--out", metavar="DIR", help="output session folder (default SESSION/associated)")
    p.add_argument("--pixel-sigma", type=positive_float, metavar="PX",
                   help="detection noise std [px] (default: session.toml [noise] pixel_sigma_px, else measured)")
    p.add_argument("--calibration", metavar="FILE",
                   help="use this calibration.toml instead of the session's (e.g. a reconstruct's rig.toml, with the "
                        "cameras' time offsets from --sync estimate); the output session holds it as calibration.toml")
    p.add_argument("--sync", choices=["estimate", "given"],
                   help="estimate: measure each camera's time offset and rolling shutter from the names (the "
                        "smoother, as reconstruct --sync estimate) and name the detections again on those clocks; "
                        "the output session holds them as calibration.toml (default: session.toml [sync] estimate, "
                        "else given)")

    def run(args) -> int:
        return associate(args, _progress_bars(args))

    p.set_defaults(func=run)


# ----- detect ----------------------------------------------------------------------------------
def _add_detect(sub):
    p = sub.add_parser("detect", help="find marker blobs in each camera's video (writes detections.csv)",
                       description="Find bright (or dark) marker blobs in each camera's video or image folder: "
                                   "background subtracted, thresholded, contrast-weighted centroids. Writes the "
                                   "unlabelled detections (frame, camera, u, v, size) that `batgraph associate` "
                                   "names. See docs/detect.md.")
    p.add_argument("sources", nargs="+", metavar="VIDEO",
                   help="one video file or folder of images (frames in name order) per camera")
    p.add_argument("--out", required=True, metavar="FILE", help="detections.csv to write (e.g. SESSION/detections.csv)")
    p.add_argument("--cameras", metavar="NAMES",
                   help="comma-separated camera names as in calibration.toml, one per VIDEO (default: each "
                        "VIDEO's name without its suffix)")
    p.add_argument("--polarity", choices=["bright", "dark"], default="bright",
                   help="markers brighter than their surround (default) or darker")
    p.add_argument("--threshold", type=positive_float, metavar="GRAY",
                   help="contrast a marker's pixels exceed, in gray levels (default: 6 x the measured image "
                        "noise, at least 5)")
    p.add_argument("--min-area", type=positive_int, default=4, metavar="PX", help="smallest blob [pixels] (default 4)")
    p.add_argument("--max-area", type=positive_int, default=400, metavar="PX",
                   help="largest blob [pixels] (default 400; the bat's body is larger)")
    p.add_argument("--background", choices=["median", "flat"], default="median",
                   help="median: per-pixel median of 25 frames spread over the recording (default); flat: each "
                        "frame's median gray level (markers on a plain backdrop)")
    p.add_argument("--quiet", action="store_true", help="no progress bar nor per-camera lines")
    p.set_defaults(func=_cmd_detect)


def _cmd_detect(args) -> int:
    out = check_output_file(args.out, "detections file (--out)")
    if out.suffix.lower() != ".csv":
        raise InputError(f"{out}: --out must be a .csv file (detections.csv)")
    cameras = ([c.strip() for c in args.cameras.split(",")] if args.cameras
               else [Path(s).stem if Path(s).suffix else Path(s).name for s in args.sources])
    if any(not c for c in cameras):
        raise InputError(f"--cameras: an empty name in {args.cameras!r}")
    calibration = out.parent / "calibration.toml"
    if calibration.is_file():  # writing into a session: its cameras' names, checked before minutes of video
        known = read_calibration(calibration, warnings=[]).names
        for c in cameras:
            if c not in known:
                raise InputError(f"{calibration}: no camera {c!r} (cameras: {', '.join(known)}); name the "
                                 "recordings as its cameras with --cameras")
    options = BlobOptions(polarity=args.polarity, threshold=args.threshold, min_area_px=args.min_area,
                          max_area_px=args.max_area, background=args.background)
    table, per_camera = detect(args.sources, cameras, options, progress=_progress_bars(args))
    write_csv(out, table, "%.3f")
    lines, warnings = report_lines(per_camera)
    if not args.quiet:
        print("\n".join(lines))
    for w in warnings:
        print(f"batgraph: warning: {w}", file=sys.stderr)
    print(f"wrote {out} ({len(table)} detections from {len(per_camera)} cameras)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="batgraph", description="3D trajectories of markers on flying animals from multi-camera 2D tracks.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_reconstruct(sub)
    _add_validate(sub)
    _add_simulate(sub)
    _add_import(sub)
    _add_calibrate(sub)
    _add_export(sub)
    _add_view(sub)
    _add_associate(sub)
    _add_detect(sub)
    return parser


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    parser = build_parser()
    if prog:
        parser.prog = prog
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error, already printed on one line (2)
        return e.code if isinstance(e.code, int) else 2
    try:
        _library_noise_off(args.command)
        return args.func(args)
    except InputError as e:
        print(f"batgraph: error: {_one_line(str(e))}", file=sys.stderr)
        return 2
    except OSError as e:  # while writing: a full disk, a read-only file system, permissions
        print(f"batgraph: error: {_one_line(os_error_message(e))}", file=sys.stderr)
        return 2
    except MemoryError as e:
        print(f"batgraph: error: out of memory{f' ({_one_line(str(e))})' if str(e) else ''}; "
              "the input is too large for this machine (split it into shorter sessions)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("batgraph: interrupted", file=sys.stderr)
        return 130


_COMPUTING = ("reconstruct", "validate", "calibrate")
"""The commands that run the estimators (and so may compile numba kernels and write a Rerun recording)."""


def _library_noise_off(command: str) -> None:
    """Switch off what batgraph's libraries would print to a user who can do nothing about it, for the commands
    that compute: numba's compiler warnings (a NumbaPerformanceWarning on the first run after an install is
    advice to batgraph's authors) and Rerun's Rust log lines (a failed write of recording.rrd logs three lines
    before the error that batgraph reports in one); for ``detect``, FFmpeg's log lines (a file that is no video gets
    its own one-line error). A RUST_LOG or OPENCV_FFMPEG_LOGLEVEL the user set is kept. Child processes forked
    later inherit both."""
    if command == "detect":
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; read when the first video opens
    if command not in _COMPUTING:
        return
    os.environ.setdefault("RUST_LOG", "off")  # read once, when Rerun's bindings load (lazily, later)
    warnings.simplefilter("ignore", NumbaWarning)


def entry() -> int:
    """The ``batgraph`` console script: :func:`main`, then no garbage collection on the way out.

    Python's shutdown runs full collections over every object alive, and after a run that is ~1,300
    modules' worth (numba, llvmlite, pandas, scipy): 0.35-0.4 s of a 2-3 s command on the bundled sample.
    ``gc.freeze()`` moves them out of the collector's sight; reference counting still frees what it frees,
    and atexit handlers (Rerun's flush) still run. Not in :func:`main`, which tests call many times in one
    process."""
    code = main()
    gc.freeze()
    return code


def _one_line(text: str) -> str:
    return " / ".join(line.strip() for line in text.splitlines() if line.strip())


def run_script(command: str) -> None:
    """Entry for ``scripts/<command>.py``: same as ``batgraph <command> ...``."""
    code = main([command, *sys.argv[1:]])
    gc.freeze()  # as entry()
    sys.exit(code)


if __name__ == "__main__":
    sys.exit(entry())
