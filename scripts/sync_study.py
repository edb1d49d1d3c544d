"""--sync estimate against the truth: the smoother with the timing given, ignored and estimated.

Scenes: the simulated 5-camera flight with offsets 0, +3.1, -2.4, +1.7, -4.0 ms and a 6 ms rolling shutter
(seeds 1-3; with --lags the offsets plus whole frames), and the MCSC LED rig (real, hardware-triggered) kept
at every 5th frame with phases 0-3 of the old frames, i.e. known offsets of 0-0.6 of a new frame (needs the real
data beside the repository; tests/real_unsync.py). Prints one markdown table: per case the estimated offsets and
readout, the RMSE and coverage of the observed points (simulated) or the median and 90th percentile of the 3D
error against the published 3D (MCSC), and the smoother's time. Usage: python scripts/sync_study.py [--lags]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from batgraph.cli import main as cli_main
from batgraph.evaluate import CHI2_3DOF_95
from batgraph.result import Options
from batgraph.runner import run_methods
from batgraph.session import read_session

OFFSETS_MS = "0,3.1,-2.4,1.7,-4.0"
LAGS_MS = "0,28.1,-19.1,1.7,-37.3"  # the same sub-frame offsets plus 3, -2, 0, -4 frames at 120 fps
READOUT_MS = "6"


def simulated(folder: Path, seed: int, offsets_ms: str, known: bool):
    args = ["flight", str(folder), "--seed", str(seed), "--time-offsets-ms", offsets_ms, "--readout-ms", READOUT_MS]
    cli_main(["simulate", *args, *(["--timing-known"] if known else []), "--force"])
    return read_session(folder)


def smoother(session, sync: bool):
    t0 = time.perf_counter()
    run = run_methods(session, ["smoother"], Options(progress=False, sync=sync))
    return run, time.perf_counter() - t0


def timing_text(run) -> str:
    refined = run.estimates["smoother"].info.get("rig_refined") or {}
    offs = ", ".join(f"{v['time_offset_s'] * 1e3:+.2f}" for v in refined.values())
    ro = sorted({round(v["readout_s"] * 1e3, 2) for v in refined.values()})
    return f"{offs} ms; readout {', '.join(f'{r:g}' for r in ro)} ms" if refined else "-"


def against_truth(run) -> str:
    """RMSE [mm] and 95 % coverage [%] of the smoother's observed points against the session's truth."""
    tr = run.trajectories
    tr = tr[(tr.method == "smoother") & (tr.status == "observed")]
    j = tr.merge(run.session.truth, on=["frame", "marker"], suffixes=("", "_t"))
    e = j[["x", "y", "z"]].to_numpy() - j[["x_t", "y_t", "z_t"]].to_numpy()
    cov = j[[f"cov_{a}{b}" for a in "xyz" for b in "xyz"]].to_numpy().reshape(-1, 3, 3)
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])
    rmse_mm = np.sqrt(np.mean(np.sum(e ** 2, 1))) * 1e3
    return f"RMSE {rmse_mm:.2f} mm, coverage {np.mean(d2 <= CHI2_3DOF_95) * 100:.1f} %"


def against_reference(run) -> str:
    tr = run.trajectories
    j = tr[tr.method == "smoother"].merge(run.session.reference, on=["frame", "marker"], suffixes=("", "_r"))
    e = np.linalg.norm(j[["x", "y", "z"]].to_numpy() - j[["x_r", "y_r", "z_r"]].to_numpy(), axis=1)
    e = e[np.isfinite(e)] * 1e3
    return f"median {np.median(e):.1f} mm, p90 {np.percentile(e, 90):.1f} mm ({len(e)} points)"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lags", action="store_true", help="add whole-frame lags to the simulated offsets")
    p.add_argument("--seeds", default="1,2,3")
    args = p.parse_args()
    offsets = LAGS_MS if args.lags else OFFSETS_MS
    print("| scene | timing | estimated offsets; readout | accuracy | smoother [s] |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in map(int, args.seeds.split(",")):
            known = simulated(Path(tmp) / f"known{seed}", seed, offsets, True)
            unknown = simulated(Path(tmp) / f"unknown{seed}", seed, offsets, False)
            for label, session, sync in (("given", known, False), ("ignored", unknown, False),
                                         ("estimated", unknown, True)):
                run, sec = smoother(session, sync)
                print(f"| flight seed {seed} ({offsets} ms, {READOUT_MS} ms readout) | {label} | "
                      f"{timing_text(run)} | {against_truth(run)} | {sec:.1f} |", flush=True)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import real_unsync

    try:
        mcsc = real_unsync.mcsc_session()
    except Exception as exc:  # the real data are not beside the repository
        print(f"(MCSC skipped: {exc})")
        return
    given, ignored = real_unsync.unsynchronise(mcsc, 5, (0, 1, 2, 3))
    truth = ", ".join(f"{p / mcsc.fps * 1e3:g}" for p in (0, 1, 2, 3))
    for label, session, sync in (("given", given, False), ("ignored", ignored, False), ("estimated", ignored, True)):
        run, sec = smoother(session, sync)
        print(f"| MCSC every 5th frame (offsets {truth} ms) | {label} | {timing_text(run)} | "
              f"{against_reference(run)} | {sec:.1f} |", flush=True)


if __name__ == "__main__":
    main()
