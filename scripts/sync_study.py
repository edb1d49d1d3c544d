"""--sync estimate against the truth: the smoother with the timing estimated, given, ignored, and synchronised.

Simulated scenes, both generators (batgraph.simulate's flight, batgraph.wingbeat's hold-out bat), 5 cameras at
120 fps, 1 px noise, offsets 0, +3.1, -2.4, +1.7, -4.0 ms plus whole-frame lags 0, +3, -2, 0, -4 frames and a
6 ms rolling shutter; per seed the same scene synchronised (the twin), with the timing given, ignored and
estimated. Per case: observed-point RMSE and its ratio to the twin's, 95 % coverage per status, each offset's and
the readout's error and its z-score (error / reported sd). Then the MCSC LED rig (real, hardware-triggered) kept at
every 5th frame with phases 0-3 of the old frames (offsets 0-0.6 of a new frame; tests/real_unsync.py, needs the
real data beside the repository): median and 90th percentile of the 3D error against its published 3D.
With --replicates N: instead, per generator and seed, N draws of the pixel noise (1 px) on the same noise-free
scene, the timing given and estimated: whether the reported standard deviations hold over the noise.
Usage: python scripts/sync_study.py [--seeds 1,2,3] [--replicates N] [--generators flight,wingbeat]; prints
markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from batgraph.evaluate import coverage95, rms
from batgraph.result import Options
from batgraph.runner import run_methods
from batgraph.simulate import Timing, simulate_flight
from batgraph.wingbeat import simulate_wingbeat

OFFSETS_S = np.array([0.0, 3.1, -2.4, 1.7, -4.0]) * 1e-3 + np.array([0, 3, -2, 0, -4]) / 120.0
READOUT_S = 0.006
GENERATORS = {"flight": lambda rng, timing, noise=1.0: simulate_flight(rng, n_cameras=5, timing=timing,
                                                                       pixel_sigma_px=noise),
              "wingbeat": lambda rng, timing, noise=1.0: simulate_wingbeat(rng, n_cameras=5, timing=timing,
                                                                           pixel_sigma_px=noise)}


def smoother(session, sync: bool):
    t0 = time.perf_counter()
    run = run_methods(session, ["smoother"], Options(progress=False, sync=sync))
    return run, time.perf_counter() - t0


def errors(run, truth_name: str = "truth"):
    """(errors (n, 3) [m], covariances (n, 3, 3), status (n,)) of the smoother's points against the truth."""
    tr = run.trajectories
    j = tr[tr.method == "smoother"].merge(getattr(run.session, truth_name), on=["frame", "marker"],
                                          suffixes=("", "_t"))
    e = j[["x", "y", "z"]].to_numpy() - j[["x_t", "y_t", "z_t"]].to_numpy()
    cov = j[[f"cov_{min(a, b)}{max(a, b)}" for a in "xyz" for b in "xyz"]].to_numpy().reshape(-1, 3, 3)
    return e, cov, j["status"].to_numpy()


def accuracy(run) -> dict:
    e, cov, status = errors(run)
    ok = np.isfinite(e).all(1)
    d2 = np.full(len(e), np.nan)
    d2[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(cov[ok], e[ok][..., None])[..., 0])
    out = {"rmse_mm": rms(np.linalg.norm(e[status == "observed"], axis=1)) * 1e3}
    for st in ("observed", "single_view", "unobserved"):
        c = coverage95(d2[status == st])
        out[st] = float("nan") if c is None else 100 * c
    return out


def timing_errors(run) -> str:
    """Each estimated offset's and readout's error [ms] against the truth, with its z-score."""
    refined = run.estimates["smoother"].info.get("rig_refined") or {}
    truth = run.session.true_timing.set_index("camera")
    parts = []
    for name, v in refined.items():
        d_off = (v["time_offset_s"] - truth.loc[name, "time_offset_s"]) * 1e3
        z = d_off / (v["time_offset_sd_s"] * 1e3) if v["time_offset_sd_s"] > 0 else 0.0
        parts.append(f"{d_off:+.3f} ({z:+.1f})")
    v = next(iter(refined.values()))
    d_ro = (v["readout_s"] - READOUT_S) * 1e3
    z_ro = d_ro / (v["readout_sd_s"] * 1e3) if v["readout_sd_s"] > 0 else float("nan")
    return f"offsets {', '.join(parts[1:])}; readout {d_ro:+.3f} ({z_ro:+.1f})"


def replicates(generators: list[str], seeds: list[int], n: int) -> None:
    """Per scene, n draws of 1 px noise added to its noise-free observations: RMSE and observed coverage with the
    timing given and estimated (each its own draw: the two sessions' rows differ), and the estimate's timing errors
    with their z-scores."""
    print("| generator, seed, draw | given: RMSE [mm], coverage | estimated: RMSE [mm], coverage | "
          "timing error [ms] (z) |\n|---|---|---|---|")
    for gen in generators:
        make = GENERATORS[gen]
        for seed in seeds:
            clean = {known: make(np.random.default_rng(seed), Timing(tuple(OFFSETS_S), READOUT_S, known=known), 0.0)
                     for known in (True, False)}
            for draw in range(n):
                cells = []
                for known, sync in ((True, False), (False, True)):
                    obs = clean[known].observations.copy()
                    noise = np.random.default_rng(1000 + draw).normal(0.0, 1.0, (len(obs), 2))
                    obs[["u", "v"]] += noise
                    run, _ = smoother(dataclasses.replace(clean[known], observations=obs, pixel_sigma_px=1.0), sync)
                    a = accuracy(run)
                    cells.append(f"{a['rmse_mm']:.2f}, {a['observed']:.1f} %")
                print(f"| {gen} {seed} {draw} | {cells[0]} | {cells[1]} | {timing_errors(run)} |", flush=True)


def simulated(seeds: list[int]) -> None:
    print("| generator, seed | case | observed RMSE [mm] (x twin) | coverage obs / single / unobs [%] | "
          "timing error [ms] (z) | smoother [s] |\n|---|---|---|---|---|---|")
    for gen, make in GENERATORS.items():
        for seed in seeds:
            twin = make(np.random.default_rng(seed), None)
            known = make(np.random.default_rng(seed), Timing(tuple(OFFSETS_S), READOUT_S, known=True))
            unknown = make(np.random.default_rng(seed), Timing(tuple(OFFSETS_S), READOUT_S))
            base = None
            for case, session, sync in (("synchronised", twin, False), ("given", known, False),
                                        ("ignored", unknown, False), ("estimated", unknown, True)):
                run, sec = smoother(session, sync)
                a = accuracy(run)
                base = base or a["rmse_mm"]
                cover = " / ".join(f"{a[s]:.1f}" for s in ("observed", "single_view", "unobserved"))
                timing = timing_errors(run) if sync else "-"
                print(f"| {gen} {seed} | {case} | {a['rmse_mm']:.2f} ({a['rmse_mm'] / base:.2f}) | {cover} | "
                      f"{timing} | {sec:.1f} |", flush=True)


def mcsc() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import real_unsync

    try:
        rig = real_unsync.mcsc_session()
    except Exception as exc:  # the real data are not beside the repository
        print(f"(MCSC skipped: {exc})")
        return
    given, ignored = real_unsync.unsynchronise(rig, 5, (0, 1, 2, 3))
    truth = [p / rig.fps * 1e3 for p in (0, 1, 2, 3)]
    print(f"\n| MCSC, every 5th frame (offsets {', '.join(f'{t:g}' for t in truth)} ms) | estimated offsets [ms] | "
          "3D error median / p90 [mm] | smoother [s] |\n|---|---|---|---|")
    for case, session, sync in (("given", given, False), ("ignored", ignored, False), ("estimated", ignored, True)):
        run, sec = smoother(session, sync)
        e = np.linalg.norm(errors(run, "reference")[0], axis=1)
        e = e[np.isfinite(e)] * 1e3
        refined = run.estimates["smoother"].info.get("rig_refined") or {}
        offs = ", ".join(f"{v.get('time_offset_s', 0.0) * 1e3:.2f} +- {v.get('time_offset_sd_s', 0.0) * 1e3:.2f}"
                         for v in refined.values()) or "-"
        print(f"| {case} | {offs} | {np.median(e):.1f} / {np.percentile(e, 90):.1f} ({len(e)} points) | "
              f"{sec:.1f} |", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1,2,3")
    p.add_argument("--replicates", type=int, default=0, help="draws of the pixel noise per scene (0: the tables)")
    p.add_argument("--generators", default=",".join(GENERATORS))
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.replicates:
        replicates(args.generators.split(","), seeds, args.replicates)
        return
    simulated(seeds)
    mcsc()


if __name__ == "__main__":
    main()
