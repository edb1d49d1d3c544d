"""The real datasets in ../shared/data/real through batgraph as a user runs it; writes docs/real_data.md.

Per dataset: import (or build) the session with the plain command, ``reconstruct --validate`` with the
smoother, the filter and triangulation, then report what the self-checks said, the pixel noise measured
per camera, and the leave-one-camera-out table (median / p90 px in the held-out camera).

* MCSC LED rig (4 cameras): written as a DLTdv project with lower-left pixels (DLTdv's convention) by
  the tests' loader (tests/real_dlt.py), imported with ``batgraph import dltdv`` (origin detected).
* DANNCE mouse (6 cameras): the same, world in millimetres, imported with ``--units mm``.
* Pose2Sim demo (4 cameras, OpenPose keypoints): ``batgraph import pose2sim`` with Pose2Sim's TRC.
* Caliscope ChArUco (4 webcams, 2175 corners): a session from its corners and its calibration.

Usage: ``python scripts/real_data_study.py [--out DIR]`` (make realdata). Needs ../shared/data/real.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the dataset loaders are the tests' (one reading of each file)

import real_dlt  # noqa: E402

from batgraph.cli import main  # noqa: E402
from batgraph.session import Session, write_session  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
METHODS = "smoother,filter,triangulate"


def _dltdv(name: str, loader, out: Path, units: str) -> Path:
    rig = loader()
    paths = real_dlt.write_dltdv_project(out / f"{name}_dltdv", rig.P, rig.uv, rig.image_hw,
                                         pixel_origin="lower-left", units=units, xyz=rig.xyz)
    session = out / name
    argv = ["import", "dltdv", "--xypts", paths["xypts"], "--coefs", paths["dltCoefs"], "--xyzpts", paths["xyzpts"],
            "--fps", rig.fps, "--units", units, "--image-size", rig.image_hw[1], rig.image_hw[0], "--out", session,
            "--force"]
    assert main([str(a) for a in argv]) == 0
    return session


def _pose2sim(out: Path) -> Path:
    trial = REAL / "pose2sim_demo_4cam_human" / "S00_P00_SingleParticipant" / "S00_P00_T01_BalancingTrial"
    dirs = sorted((trial / "pose-associated").iterdir())
    trc = sorted((trial / "pose-3d").glob("*_0-100.trc"))[0]
    calib = REAL / "pose2sim_demo_4cam_human" / "S00_Calibration" / "Calib_qualisys.toml"
    argv = ["import", "pose2sim", *dirs, "--calibration", calib, "--fps", 60, "--reference-trc", trc,
            "--out", out / "pose2sim", "--force"]
    assert main([str(a) for a in argv]) == 0
    return out / "pose2sim"


def _caliscope(out: Path) -> Path:
    rig, obs, _ = real_dlt.load_caliscope()
    write_session(Session("caliscope", 30.0, rig, obs, pixel_sigma_px=None), out / "caliscope")
    return out / "caliscope"


def _run(session: Path, out: Path) -> tuple[dict, pd.DataFrame, float]:
    t0 = time.perf_counter()
    rc = main(["reconstruct", str(session), "--methods", METHODS, "--validate", "--viewer", "none", "--quiet",
               "--out", str(out)])
    wall = time.perf_counter() - t0
    assert rc == 0, f"{session}: exit {rc}"
    return json.loads((out / "summary.json").read_text()), pd.read_csv(out / "validation.csv"), wall


def _section(name: str, what: str, summary: dict, val: pd.DataFrame, wall: float) -> list[str]:
    noise = summary["pixel_noise"]["cameras"]
    lines = [f"## {name}", "", what, "",
             f"{summary['n_cameras']} cameras, {summary['n_frames']} frames, {summary['n_markers']} markers, "
             f"{summary['n_observations']} observations; reconstruct --validate {wall:.1f} s wall.", "",
             "Warnings (self-checks and the smoother's): "
             + ("; ".join(summary["warnings"]) if summary["warnings"] else "no warning") + ".", "",
             "| camera | measured noise [px] | inliers / rejected | distance to points [m] | behind |",
             "|---|---|---|---|---|"]
    for cam, n in noise.items():
        chk = summary["checks"].get(cam, {})
        dist = chk.get("median_distance_m")
        lines.append(f"| {cam} | {n['sigma_px']:.3g} | {n['n_used']} / {n['n_rejected']} | "
                     f"{'-' if dist is None else f'{dist:.3g}'} | {100 * chk.get('behind_fraction', 0):.0f} % |")
    lines += ["", "Leave-one-camera-out, median / p90 [px] in the held-out camera:", "",
              "| held out | points | " + " | ".join(METHODS.split(",")) + " |", "|---|---|" + "---|" * 3]
    for (cam, status, subset), g in val.groupby(["held_out", "status", "subset"], sort=False):
        if status == "unobserved":
            continue
        cells = []
        for m in METHODS.split(","):
            r = g[g.method == m]
            cells.append("-" if r.empty else f"{r.median_px.iat[0]:.2f} / {r.p90_px.iat[0]:.2f} (n {r.n.iat[0]})")
        lines.append(f"| {cam} | {status}, {subset} | " + " | ".join(cells) + " |")
    ref = {m: v.get("reference", {}) for m, v in summary["methods"].items()}
    if any(ref.values()):
        lines += ["", "Difference to the dataset's own 3D (median per method): " + ", ".join(
            f"{m} {1000 * r['median_m']:.2f} mm" for m, r in ref.items() if r.get("median_m") is not None) + "."]
    return lines + [""]


def main_study(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(ROOT / "bench_out" / "real"), help="work folder")
    p.add_argument("--doc", default=str(ROOT / "docs" / "real_data.md"), help="markdown to write")
    args = p.parse_args(argv)
    if not REAL.is_dir():
        print(f"{REAL}: not found (the real datasets live beside the project)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cases = [
        ("MCSC LED rig (flydra, 4 cameras)", "An LED waved through a fly-tracking rig; DLTdv project, lower-left "
         "pixels, detected.", lambda: _dltdv("mcsc", real_dlt.load_mcsc, out, "m")),
        ("DANNCE mouse (6 cameras)", "Landmarks labelled in 3D; DLTdv project in millimetres (--units mm), "
         "the 81 labelled frames in label order. Its 2D labels are the exact projections of its 3D labels "
         "(to 5e-13 px with K's skew, tests/real_dlt.py), not independent clicks: the noise reads ~0 and every "
         "method predicts a held-out camera exactly, so this set checks conventions and units, not accuracy.",
         lambda: _dltdv("dannce", real_dlt.load_dannce, out, "mm")),
        ("Pose2Sim demo (4 cameras, human)", "OpenPose BODY_25B keypoints, Qualisys calibration; Pose2Sim's "
         "triangulation as the reference.", lambda: _pose2sim(out)),
        ("Caliscope ChArUco (4 webcams)", "Real ChArUco corner detections with Caliscope's bundle-adjusted "
         "calibration.", lambda: _caliscope(out)),
    ]
    lines = ["# batgraph on the real datasets", "",
             "Made by `make realdata` (scripts/real_data_study.py) on "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Pixel noise measured per camera from the "
             "data (no [noise] in session.toml); methods " + METHODS + ".", ""]
    for name, what, build in cases:
        session = build()
        summary, val, wall = _run(session, out / f"{session.name}_out")
        lines += _section(name, what, summary, val, wall)
        print("\n".join(_section(name, what, summary, val, wall)))
    Path(args.doc).write_text("\n".join(lines))
    print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_study())
