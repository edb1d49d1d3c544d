#!/usr/bin/env python3
"""Association measured on simulated scenes with known labels: both generators, several seeds.

Per case: a simulated session (batgraph.simulate.simulate_flight or batgraph.wingbeat.simulate_wingbeat) becomes a
detections session (batgraph.associate.scenes: labels stripped, spurious blobs, merged blobs, one seed frame),
``batgraph associate`` names it, the names are scored against the truth (batgraph.associate.score), and
``batgraph reconstruct --methods smoother`` runs on the recovered labels, on the true labels (the real, unmerged
detections) and on the recovered labels less the wrong ones, for the RMSE on observed points against truth.csv: the
last says whether the names left out or the wrong ones cost accuracy. Prints one line per case and the medians.

Usage: ``python scripts/associate_study.py [--scenes flight14,flight24,wingbeat] [--seeds 0,1,2] [--out DIR]
[--no-smoother] [--sync] [--seed-frames N] [--also-label F1,F2] [--measure-noise]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from batgraph.associate import scenes, score, write_associated  # noqa: E402
from batgraph.cli import main  # noqa: E402
from batgraph.evaluate import dense_from_table  # noqa: E402
from batgraph.naming import name_detections  # noqa: E402
from batgraph.result import Options  # noqa: E402
from batgraph.session import write_session  # noqa: E402
from batgraph.simulate import Timing, simulate_flight  # noqa: E402
from batgraph.wingbeat import simulate_wingbeat  # noqa: E402

OUT_OF_STEP_S = (0.0, 3.1e-3, -2.4e-3, 1.7e-3, -4.0e-3)  # a free-running rig at 120 fps (frames 8.3 ms apart)


def simulate(scene: str, seed: int):
    """The simulated session of a case: 'flightN' (N markers, 160 frames) or 'wingbeat' (14 markers, 72 frames);
    with '_steps' the 5 cameras are out of step by OUT_OF_STEP_S (unknown to the association), with '_stated' by the
    same, stated in calibration.toml (time_offset_s)."""
    rng = np.random.default_rng(seed)
    base, _, steps = scene.partition("_")
    timing = Timing(time_offsets_s=OUT_OF_STEP_S, known=steps == "stated") if steps else None
    if base.startswith("flight"):
        return simulate_flight(rng, n_markers=int(base[6:] or 14), n_frames=160, pixel_sigma_px=1.0, timing=timing)
    return simulate_wingbeat(rng, pixel_sigma_px=1.0, timing=timing)


def smoother_rmse(session_dir: Path, out: Path, sync: bool = False) -> float:
    """The smoother's RMSE on observed points against truth.csv [m] (with ``sync``, with --sync estimate)."""
    rc = main(["reconstruct", str(session_dir), "--methods", "smoother", "--viewer", "none", "--quiet", "--out",
               str(out), *(["--sync", "estimate"] if sync else [])])
    if rc != 0:
        return float("nan")
    return json.loads((out / "summary.json").read_text())["methods"]["smoother"]["truth"]["rmse_m"]["observed"]


def hidden_rivals(session) -> dict:
    """Blobs another marker could have made, from the true positions (session.truth) and 1 px of noise: for each of
    the markers' detections (session.observations, true labels), the chance that it is the blob of a marker this
    camera does not see on that frame, against its own, from the two projections' distances (equal priors; nothing
    in the image tells which marker the camera sees). Returns the share of the detections an ideal namer would name
    wrongly if it named them all (``hidden_wrong``: the mean chance) and the share it would leave unnamed if it named
    only those with a chance of at most 1 % (``hidden_doubt``)."""
    obs = session.observations
    X, _, frames, names = dense_from_table(session.truth)  # (F, M, 3) [m]
    uv = session.rig.project(X.reshape(-1, 3)).reshape(len(session.rig), *X.shape[:2], 2)
    c = obs["camera"].map({n: i for i, n in enumerate(session.rig.names)}).to_numpy()
    f = obs["frame"].to_numpy() - frames[0]
    m = obs["marker"].map({n: i for i, n in enumerate(names)}).to_numpy()
    seen = np.zeros(uv.shape[:3], bool)
    seen[c, f, m] = True
    d2 = np.nan_to_num(((uv[c, f] - obs[["u", "v"]].to_numpy()[:, None]) ** 2).sum(axis=-1), nan=np.inf)  # (N, M)
    rival = np.where(seen[c, f], np.inf, d2)
    rival[np.arange(len(m)), m] = np.inf
    log_ratio = np.clip((rival - d2[np.arange(len(m)), m][:, None]) / 2.0, -50.0, 50.0)
    chance = np.minimum((1.0 / (1.0 + np.exp(log_ratio))).sum(axis=1), 1.0)
    return {"hidden_wrong": float(chance.mean()), "hidden_doubt": float((chance > 0.01).mean())}


@dataclass
class CaseOptions:
    """smoother: also the smoother's RMSEs (two reconstructs); sync: as associate --sync estimate; seed_frames: how many
    frames the user labels (scenes.seed_frames); also: frames labelled besides those; noise_stated: session.toml
    states the simulated noise (1 px), else the association measures it, as on a user's data."""

    smoother: bool = True
    sync: bool = False
    seed_frames: int = 1
    also: tuple[int, ...] = ()
    noise_stated: bool = True


def run_case(scene: str, seed: int, work: Path, opt: CaseOptions | None = None) -> dict:
    """One case's scores (and smoother RMSEs)."""
    opt = opt or CaseOptions()
    sync = opt.sync
    session = simulate(scene, seed)
    if not opt.noise_stated:
        session = dataclasses.replace(session, pixel_sigma_px=None)
    frames = tuple(scenes.seed_frames(session.observations, opt.seed_frames)) + opt.also
    sc = scenes.make_scene(session, np.random.default_rng(1000 + seed), scenes.SceneOptions(seed_frames=frames))
    case = work / f"{scene}_{seed}"
    scenes.write_scene(session, sc, case / "input")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        named = name_detections(case / "input", Path(scratch), Options(sync=sync, progress=False))
        wall = time.perf_counter() - t0
        obs, labels, fig = named.observations, named.labels, named.figures
        write_associated(case / "input", case / "associated", obs, labels, fig, named.calibration)
    figures = score.score(sc.truth, sc.detections["frame"].to_numpy(), labels["marker"].to_numpy(), session.fps,
                          len(session.marker_names))
    row = {"scene": scene, "seed": seed, "associate_s": wall, "clock_rounds": fig.summary["clock_rounds"],
           "clocks_estimated": fig.summary["clocks_estimated"], **figures, **hidden_rivals(session)}
    if opt.smoother:
        real = (sc.truth["kind"] == "marker").to_numpy()
        true_obs = sc.detections[real].assign(marker=sc.truth["marker"][real].to_numpy(), weight=1.0)
        session.observations = true_obs[["frame", "camera", "marker", "u", "v", "weight"]].reset_index(drop=True)
        write_session(session, case / "true_labels")
        row["rmse_true_mm"] = 1e3 * smoother_rmse(case / "true_labels", case / "true_labels" / "out", sync)
        row["rmse_recovered_mm"] = 1e3 * smoother_rmse(case / "associated", case / "associated" / "out", sync)
        row["rmse_ratio"] = row["rmse_recovered_mm"] / row["rmse_true_mm"]
        right = (labels["marker"].to_numpy() == sc.truth["marker"].to_numpy()) & real
        session.observations = sc.detections[right].assign(marker=labels["marker"][right].to_numpy(), weight=1.0)[
            ["frame", "camera", "marker", "u", "v", "weight"]].reset_index(drop=True)
        write_session(session, case / "right_only")
        row["rmse_right_only_ratio"] = 1e3 * smoother_rmse(case / "right_only", case / "right_only" / "out", sync) / \
            row["rmse_true_mm"]
    return row


def cases(scenes: str, seeds: str) -> Iterator[tuple[str, int]]:
    """Every (scene, seed) of the comma-separated ``scenes`` and ``seeds``, scene by scene."""
    for scene in scenes.split(","):
        for seed in (int(s) for s in seeds.split(",")):
            yield scene, seed


def row_line(row: dict) -> str:
    """One case's figures as key=value on one line (4 significant digits)."""
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items())


def main_study(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="flight14,flight24,wingbeat")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--out", help="keep the case folders here (default: a temporary folder)")
    p.add_argument("--no-smoother", action="store_true", help="skip the two reconstructs per case")
    p.add_argument("--sync", action="store_true", help="as associate --sync estimate (the clocks measured from the "
                   "first names, the detections named again on them); the reconstructs with --sync estimate too")
    p.add_argument("--seed-frames", type=int, default=1, help="how many frames the user labels (scenes.seed_frames)")
    p.add_argument("--also-label", default="", help="frames labelled besides those, e.g. 20,140")
    p.add_argument("--measure-noise", action="store_true", help="session.toml states no noise: the association "
                   "measures it (and reconstruct, per camera), as on a user's data")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        for scene, seed in cases(args.scenes, args.seeds):
            row = run_case(scene, seed, work, CaseOptions(
                not args.no_smoother, args.sync, args.seed_frames,
                tuple(int(f) for f in args.also_label.split(",") if f), not args.measure_noise))
            rows.append(row)
            print(row_line(row), flush=True)
    table = pd.DataFrame(rows)
    cols = [c for c in ("real_correct", "real_wrong", "real_unnamed", "switches_per_100_marker_s", "spurious_unnamed",
                        "merged_unnamed", "hidden_wrong", "hidden_doubt", "rmse_ratio", "rmse_right_only_ratio",
                        "associate_s") if c in table]
    print("\nmedians over seeds:")
    print(table.groupby("scene")[cols].median().to_string(float_format=lambda x: f"{x:.4g}"))
    return 0


if __name__ == "__main__":
    sys.exit(main_study())
