#!/usr/bin/env python3
"""Association on real labelled data with its identities stripped: how many detections get their own name back.

* Pose2Sim demo (4 cameras, OpenPose keypoints of a balancing human, 60 fps): ``batgraph import pose2sim``.
* Caliscope (4 webcams, ChArUco corners of a board moved by hand; its frames are sync indices, not every one
  of which holds corners): a session from its corners and calibration (tests/real_dlt.py's loader).
* DANNCE mouse (6 cameras, 22 landmarks clicked on 81 frames sampled from a long recording, so not consecutive):
  written as a DLTdv project and imported (``batgraph import dltdv --units mm``), as scripts/real_data_study.py does.

Each: the observations without their markers become detections.csv, the frame where the most markers are seen by
three cameras or more (nearest the middle) is the seed, ``associate_session`` names the rest; printed: the scores
of batgraph.associate.score. Needs ../shared/data/real. Usage: ``python scripts/associate_real.py [--out DIR] [--sync]
[--only NAME]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

REAL = ROOT.parent / "shared" / "data" / "real"


def pose2sim(out: Path) -> Path:
    from batgraph.cli import main

    base = REAL / "pose2sim_demo_4cam_human"
    trial = base / "S00_P00_SingleParticipant" / "S00_P00_T01_BalancingTrial"
    argv = ["import", "pose2sim", *sorted(str(p) for p in (trial / "pose-associated").iterdir()), "--calibration",
            str(base / "S00_Calibration" / "Calib_qualisys.toml"), "--fps", "60", "--out", str(out), "--force"]
    assert main(argv) == 0
    return out


def caliscope(out: Path) -> Path:
    import real_dlt

    from batgraph.session import Session, write_session

    rig, obs, _ = real_dlt.load_caliscope()
    write_session(Session("caliscope", 30.0, rig, obs, pixel_sigma_px=None), out)
    return out


def dannce(out: Path) -> Path:
    import real_dlt

    from batgraph.cli import main

    rig = real_dlt.load_dannce()
    paths = real_dlt.write_dltdv_project(out.parent / "dannce_dltdv", rig.P, rig.uv, rig.image_hw,
                                         pixel_origin="lower-left", units="mm", xyz=rig.xyz)
    argv = ["import", "dltdv", "--xypts", paths["xypts"], "--coefs", paths["dltCoefs"], "--xyzpts", paths["xyzpts"],
            "--fps", rig.fps, "--units", "mm", "--image-size", rig.image_hw[1], rig.image_hw[0], "--out", out,
            "--force"]
    assert main([str(a) for a in argv]) == 0
    return out


def relabel(labelled: Path, work: Path, sync: bool = False) -> dict:
    from batgraph.associate import scenes, score
    from batgraph.naming import name_detections
    from batgraph.result import Options
    from batgraph.session import read_session

    session = read_session(labelled)
    sc = scenes.strip_labels(session)
    scenes.write_scene(session, sc, work)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        named = name_detections(work, Path(scratch), Options(sync=sync, progress=False))
    wall = time.perf_counter() - t0
    r = score.score(sc.truth, sc.detections["frame"].to_numpy(), named.labels["marker"].to_numpy(), session.fps,
                    len(session.markers))
    s = named.figures.summary
    return {"seconds": wall, "pixel_sigma_px": s["pixel_sigma_px"], "clocks_estimated": s["clocks_estimated"], **r}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", help="keep the sessions here (default: a temporary folder)")
    p.add_argument("--sync", action="store_true", help="as associate --sync estimate: name again on the clocks the "
                   "smoother measures from the first names")
    p.add_argument("--only", help="one of pose2sim, caliscope, dannce")
    args = p.parse_args(argv)
    if not REAL.is_dir():
        print(f"{REAL}: not found", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        for name, make in (("pose2sim", pose2sim), ("caliscope", caliscope), ("dannce", dannce)):
            if args.only and name != args.only:
                continue
            r = relabel(make(work / name), work / f"{name}_stripped", args.sync)
            print(name, " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
