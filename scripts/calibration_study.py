#!/usr/bin/env python3
"""`calibrate` without a wand, measured end to end through the command line on scenes with a known rig.

Each scene: 5 cameras, 72 frames, 14 markers, 1 px noise, cameras 2-5 of the written calibration turned
by 0.5 deg and shifted by 5 mm (``batgraph.wingbeat`` with ``batgraph.simulate.perturb_rig``, and
``simulate_flight``). For each: `batgraph calibrate S --out refined.toml`, then
`batgraph reconstruct S --calibration X --methods smoother` with X = the written (wrong) calibration, the
refined one and the true one; the smoother's RMSE on observed points against truth.csv. The refined rig is
first moved onto the true rig by the similarity fit over camera centres and orientations that
``batgraph.geometry.gauge`` defines (images cannot observe the world frame and scale); "aligned pts" moves
the smoother's observed points onto the truth by a similarity as well. Pose errors: every camera of a rig
after the same similarity fit to the true rig. The same with the true rig as the written calibration
(an exact input must not be made worse). The same for `reconstruct --refine-rig` (the poses refined jointly with
the trajectories; its OUT/rig.toml against the true rig). Prints markdown tables; takes ~30 min on 2 cores.

    python scripts/calibration_study.py [--seeds 1 2 3] [--generators wingbeat flight] [--work DIR]
        [--rot-deg 0.5] [--trans-mm 5] [--frames 72] [--refine-rig-only] [--json FILE] [--tables FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from batgraph import evaluate  # noqa: E402
from batgraph.calibrate import aligned_rig, write_calibration  # noqa: E402
from batgraph.camera import Rig  # noqa: E402
from batgraph.geometry import pose  # noqa: E402
from batgraph.session import read_calibration, write_session  # noqa: E402
from batgraph.simulate import perturb_rig, simulate_flight  # noqa: E402
from batgraph.wingbeat import simulate_wingbeat  # noqa: E402

ERROR = {"rot_deg": 0.5, "trans_mm": 5.0, "frames": 72}  # the calibration error and length of every scene


def scene(generator: str, seed: int, exact: bool):
    """The session (written rig perturbed unless ``exact``; true_rig set)."""
    rot, trans, frames = ERROR["rot_deg"], ERROR["trans_mm"], ERROR["frames"]
    if generator == "wingbeat":
        s = simulate_wingbeat(np.random.default_rng(seed), n_cameras=5, n_frames=frames, pixel_sigma_px=1.0)
        wrong = perturb_rig(np.random.default_rng(1000 + seed), s.rig, rot, trans, [1, 2, 3, 4])
        s = dataclasses.replace(s, rig=wrong, true_rig=s.rig)
    else:
        s = simulate_flight(np.random.default_rng(seed), n_cameras=5, n_markers=14, n_frames=frames,
                            calib_rot_deg=rot, calib_trans_mm=trans)
    if exact:
        s = dataclasses.replace(s, rig=s.true_rig)
    return s


def cli(*args) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "batgraph", *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, timeout=1800)
    if r.returncode != 0:
        raise RuntimeError(f"batgraph {' '.join(map(str, args))}: {r.stderr.strip()}")
    return r


def pose_errors(rig: Rig, truth: Rig) -> tuple[list[float], list[float]]:
    a = aligned_rig(rig, truth)
    return ([1000 * float(np.linalg.norm(x.center_world - y.center_world)) for x, y in zip(a, truth, strict=True)],
            [float(np.degrees(pose.rotation_angle(x.R, y.R))) for x, y in zip(a, truth, strict=True)])


def smoother_rmse(folder: Path, calibration: Path, out: Path, *extra: str) -> dict:
    """RMSE on observed points [mm] from summary.json, after a point similarity too, and per-camera RMS px."""
    cli("reconstruct", folder, "--calibration", calibration, "--methods", "smoother", "--viewer", "none",
        "--out", out, "--quiet", *extra)
    m = json.loads((out / "summary.json").read_text())["methods"]["smoother"]
    est = pd.read_csv(out / "trajectories.csv")
    est = est[(est["method"] == "smoother") & (est["status"] == "observed")]
    truth = pd.read_csv(folder / "truth.csv").set_index(["frame", "marker"])
    X = est[["x", "y", "z"]].to_numpy()
    Y = truth.loc[list(zip(est["frame"], est["marker"], strict=True)), ["x", "y", "z"]].to_numpy()
    mx, my = X.mean(0), Y.mean(0)
    U, S, Vt = np.linalg.svd((Y - my).T @ (X - mx))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    s = np.trace(np.diag(S) @ D) / ((X - mx) ** 2).sum()
    Xa = s * (X - mx) @ (U @ D @ Vt).T + my
    rms = [c["rms_px"] for c in m["reprojection"].values()]
    return {"rmse_mm": 1000 * m["truth"]["rmse_m"]["observed"],
            "rmse_pts_mm": 1000 * evaluate.rms(np.linalg.norm(Xa - Y, axis=-1)),
            "reproj_ratio": max(rms) / min(rms)}


def measure_refine_rig(s, folder: Path, tag: str, work: Path, row: dict) -> None:
    """`reconstruct --refine-rig` (the poses refined jointly with the trajectories): the smoother's scores in the
    user's frame and points aligned, and the poses of OUT/rig.toml against the truth."""
    out = work / f"out_{folder.name}_refine_rig"
    row[f"{tag}_joint"] = smoother_rmse(folder, folder / "calibration.toml", out, "--refine-rig")
    row[f"{tag}_joint"]["pose"] = pose_errors(read_calibration(out / "rig.toml"), s.true_rig)


def measure(generator: str, seed: int, work: Path, calibrate: bool = True) -> dict:
    row = {"generator": generator, "seed": seed}
    for exact in (False, True):
        s = scene(generator, seed, exact)
        tag = "exact" if exact else "wrong"
        folder = work / f"{generator}{seed}_{tag}"
        write_session(s, folder)
        if not exact:
            row["pose_before"] = pose_errors(s.rig, s.true_rig)
            for label, cal in (("input", folder / "calibration.toml"), ("true", folder / "calibration_true.toml")):
                row[label] = smoother_rmse(folder, cal, work / f"out_{generator}{seed}_{label}")
        measure_refine_rig(s, folder, tag, work, row)
        if not calibrate:
            continue
        refined = folder / "refined.toml"
        r = cli("calibrate", folder, "--out", refined, "--quiet")
        row[f"{tag}_kept"] = "input rig, unchanged" in r.stdout
        written = read_calibration(refined)
        if not exact:
            row["pose_after"] = pose_errors(written, s.true_rig)
        write_calibration(folder / "refined_aligned.toml", aligned_rig(written, s.true_rig))
        row[f"{tag}_refined"] = smoother_rmse(folder, folder / "refined_aligned.toml",
                                              work / f"out_{generator}{seed}_{tag}_refined")
    return row


def _median_row(rows: list[dict], cells) -> str:
    vals = np.array([cells(r) for r in rows])
    return " | ".join(f"{v:.2f}" for v in np.median(vals, axis=0))


def joint_tables(rows: list[dict]) -> str:
    """Markdown: `reconstruct --refine-rig`'s smoother RMSE (user's frame; points aligned), pose errors, exact
    input."""
    def cells(r):
        t, j, e = r["true"], r["wrong_joint"], r["exact_joint"]
        (pb, rb), (pa, ra) = r["pose_before"], j["pose"]
        return [r["input"]["rmse_mm"], t["rmse_mm"], j["rmse_mm"], t["rmse_pts_mm"], j["rmse_pts_mm"],
                j["rmse_pts_mm"] / t["rmse_pts_mm"], t["reproj_ratio"], j["reproj_ratio"], np.median(np.divide(pb, pa)),
                np.median(np.divide(rb, ra)), e["rmse_mm"] / t["rmse_mm"], e["rmse_pts_mm"] / t["rmse_pts_mm"]]

    out = ["| scene | seed | input rig mm | true rig mm | --refine-rig mm | true, points aligned mm | --refine-rig, "
           "points aligned mm | ratio | per-camera RMS worst / best, true rig | --refine-rig | pose error ratio "
           "input / refined: position | rotation | exact input: ratio | points aligned |", "|---|---|" + "---|" * 12]
    for g in dict.fromkeys(r["generator"] for r in rows):
        sub = [r for r in rows if r["generator"] == g]
        for r in sub:
            out.append(f"| {g} | {r['seed']} | " + " | ".join(f"{v:.2f}" for v in cells(r)) + " |")
        out.append(f"| {g} | median | {_median_row(sub, cells)} |")
    out += ["", "| scene | seed | position error mm, input -> --refine-rig | rotation error deg |", "|---|---|---|---|"]
    for r in rows:
        (pb, rb), (pa, ra) = r["pose_before"], r["wrong_joint"]["pose"]
        out.append(f"| {r['generator']} | {r['seed']} | "
                   + ", ".join(f"{a:.1f}->{b:.1f}" for a, b in zip(pb, pa, strict=True)) + " | "
                   + ", ".join(f"{a:.2f}->{b:.2f}" for a, b in zip(rb, ra, strict=True)) + " |")
    return "\n".join(out)


def tables(rows: list[dict]) -> str:
    """Markdown: the smoother's RMSE (rig aligned by cameras; points aligned), pose errors, exact input."""
    if "wrong_refined" not in rows[0]:
        return joint_tables(rows)
    def rmse(r):
        i, t, f = r["input"], r["true"], r["wrong_refined"]
        return [i["rmse_mm"], t["rmse_mm"], f["rmse_mm"], f["rmse_mm"] / t["rmse_mm"], t["rmse_pts_mm"],
                f["rmse_pts_mm"], f["rmse_pts_mm"] / t["rmse_pts_mm"], t["reproj_ratio"], f["reproj_ratio"]]

    out = ["| scene | seed | input rig mm | true rig mm | refined mm | refined / true | true, points aligned mm | "
           "refined, points aligned mm | refined / true | per-camera RMS worst / best, true | refined | written |",
           "|---|---|" + "---|" * 10]
    for g in dict.fromkeys(r["generator"] for r in rows):
        sub = [r for r in rows if r["generator"] == g]
        for r in sub:
            out.append(f"| {g} | {r['seed']} | " + " | ".join(f"{v:.2f}" for v in rmse(r))
                       + f" | {'input' if r['wrong_kept'] else 'refined'} |")
        out.append(f"| {g} | median | {_median_row(sub, rmse)} | |")
    out += ["", "| scene | seed | position error mm, input -> refined | rotation error deg, input -> refined | "
            "median ratio input / refined: position, rotation |", "|---|---|---|---|---|"]
    for r in rows:
        (pb, rb), (pa, ra) = r["pose_before"], r["pose_after"]
        out.append(f"| {r['generator']} | {r['seed']} | "
                   + ", ".join(f"{a:.1f}->{b:.1f}" for a, b in zip(pb, pa, strict=True)) + " | "
                   + ", ".join(f"{a:.2f}->{b:.2f}" for a, b in zip(rb, ra, strict=True))
                   + f" | {np.median(np.divide(pb, pa)):.1f}, {np.median(np.divide(rb, ra)):.1f} |")
    out += ["", "| scene | seed | exact input: written | smoother mm with it | with the true rig | ratio |",
            "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['generator']} | {r['seed']} | {'input' if r['exact_kept'] else 'refined'} | "
                   f"{r['exact_refined']['rmse_mm']:.2f} | {r['true']['rmse_mm']:.2f} | "
                   f"{r['exact_refined']['rmse_mm'] / r['true']['rmse_mm']:.3f} |")
    return "\n".join(out) + "\n\n" + joint_tables(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--generators", nargs="+", default=["wingbeat", "flight"], choices=["wingbeat", "flight"])
    ap.add_argument("--work", type=Path, help="folder for the sessions and results (default: a temporary one)")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument("--tables", type=Path, help="only print the tables of rows written earlier by --json")
    ap.add_argument("--rot-deg", type=float, default=ERROR["rot_deg"], help="cameras 2-5 turned by [deg]")
    ap.add_argument("--trans-mm", type=float, default=ERROR["trans_mm"], help="cameras 2-5 moved by [mm]")
    ap.add_argument("--frames", type=int, default=ERROR["frames"])
    ap.add_argument("--refine-rig-only", action="store_true", help="only `reconstruct --refine-rig`, no calibrate")
    args = ap.parse_args()
    ERROR.update(rot_deg=args.rot_deg, trans_mm=args.trans_mm, frames=args.frames)
    if args.tables:
        print(tables(json.loads(args.tables.read_text())))
        return 0
    work = args.work or Path(tempfile.mkdtemp(prefix="calibration_study_"))
    rows = []
    for g in args.generators:
        for seed in args.seeds:
            rows.append(measure(g, seed, work, calibrate=not args.refine_rig_only))
            print(f"{g} seed {seed}: done", file=sys.stderr, flush=True)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))
    print(tables(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
