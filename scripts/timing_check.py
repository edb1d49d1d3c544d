"""The timing self-check (batgraph.timing) on the bundled samples, simulated rigs and the real datasets.

For each data set: the self-check's figures per camera with two estimates of the track (the simulated truth where
there is one; the per-frame triangulation and its np.gradient), the largest step (offset against the median camera)
in sds and in pixels, the cameras it names, and the lag scan's lags. Synchronised rigs give the null figures the
thresholds must clear; rigs with a camera 2 ms out at 120 fps (and the issue's scene) the figures they must catch.

Usage: ``python scripts/timing_check.py [--quick]`` (prints markdown; docs/timing.md quotes it). Needs
../shared/data/real for the real rows (skipped without it).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from batgraph import checks, timing  # noqa: E402
from batgraph import simulate as S  # noqa: E402
from batgraph import wingbeat as W  # noqa: E402
from batgraph.session import dense_observations, read_session  # noqa: E402
from batgraph.triangulate import triangulate_ideal  # noqa: E402

OFF_2MS = (0.0, 0.0, 0.002, 0.0, 0.0)
ISSUE = S.Timing(time_offsets_s=(0.0, 0.0031, -0.0024, 0.0017, -0.0040), readout_s=0.006)


def _truth_track(session, dense):
    """The simulated truth and its velocity (central differences of the closed form, 10 us) on dense.frames."""
    t = dense.frames / session.fps
    if "wingbeat" in session.extra_toml:
        p = session.extra_toml["wingbeat"]
        at = lambda tt: W.wingbeat_scene(p, tt).points_m  # noqa: E731
    else:
        sim = session.extra_toml["simulation"]
        if sim["scene"] == "flight":
            at = lambda tt: S.flight_scene(sim["n_frames"], sim["fps"], sim["n_markers"], sim["phase0_rad"],  # noqa: E731
                                           tuple(sim["offset_yz_m"]), tt).points_m
        else:
            at = lambda tt: S.ear_scene(sim["n_frames"], sim["fps"], sim["phase0_rad"], sim["drift_hz"],  # noqa: E731
                                        sim["drift_phase_rad"], sim["drift_amp_m"], tt).points_m
    h = 1e-5
    return at(t), (at(t + h) - at(t - h)) / (2 * h)


def run(session, estimate: str) -> dict:
    """The self-check and the lag scan of one session with one estimate ("truth" or "triangulation")."""
    dense = dense_observations(session, timing=True)
    pre = checks.preflight(session, dense)
    ideal = pre.ideal
    if estimate == "truth":
        xyz, vel = _truth_track(session, dense)
    else:
        xyz, _ = triangulate_ideal(session.rig, ideal)
        vel = np.gradient(xyz, axis=0) * session.fps if len(xyz) > 1 else np.full_like(xyz, np.nan)
    t0 = time.perf_counter()
    chk = timing.timing_check(session.rig, ideal, xyz, vel, session.fps)
    wall = time.perf_counter() - t0
    lags = timing.scan_lags(session.rig, ideal, dense.frames, session.fps)
    tb = chk.table
    z = np.abs(tb["step_s"] / tb["step_sd_s"]).replace(np.inf, np.nan)
    px = np.abs(tb["step_s"]) * tb["image_speed_px_s"]
    return {"table": tb, "z": float(np.nanmax(z)) if z.notna().any() else np.nan,
            "px": float(np.nanmax(px)) if px.notna().any() else np.nan,
            "ms": float(np.nanmax(np.abs(tb["step_s"])) * 1e3),
            "named": ", ".join(tb["camera"][tb["flagged"]]) or "-",
            "rolling": ", ".join(tb["camera"][tb["rolling"]]) or "-",
            "lags": ",".join(f"{x:g}" for x in lags.table["lag_frames"]), "wall_s": wall, "warnings": chk.warnings,
            "sigma": pre.sigma_px}


def _row(name: str, session, estimate: str) -> str:
    r = run(session, estimate)
    return (f"| {name} | {estimate} | {len(session.rig)} | {np.median(r['sigma']):.2g} | {r['ms']:.3f} | "
            f"{r['z']:.1f} | {r['px']:.2f} | {r['named']} | {r['rolling']} | {r['lags']} | {r['wall_s']:.2f} |")


def simulated(quick: bool):
    seeds = range(2) if quick else range(5)
    for s in seeds:
        yield f"flight seed {s}", S.simulate_flight(np.random.default_rng(s), n_markers=24), ("truth", "triangulation")
        yield f"flight seed {s}, cam3 2 ms out", S.simulate_flight(
            np.random.default_rng(s), n_markers=24, timing=S.Timing(time_offsets_s=OFF_2MS)), ("truth", "triangulation")
        yield f"wingbeat seed {s}", W.simulate_wingbeat(np.random.default_rng(s), n_frames=160), (
            "truth", "triangulation")
        yield f"wingbeat seed {s}, hs3 2 ms out", W.simulate_wingbeat(
            np.random.default_rng(s), n_frames=160, timing=S.Timing(time_offsets_s=OFF_2MS)), ("truth", "triangulation")
        yield f"ear seed {s}", S.simulate_ear(np.random.default_rng(s)), ("truth", "triangulation")
        yield f"ear seed {s}, cam2 0.5 ms out (1/8 frame)", S.simulate_ear(
            np.random.default_rng(s), timing=S.Timing(time_offsets_s=(0.0, 0.0005))), ("truth", "triangulation")
        yield f"ear seed {s}, cam2 2 ms out (1/2 frame)", S.simulate_ear(
            np.random.default_rng(s), timing=S.Timing(time_offsets_s=(0.0, 0.002))), ("truth", "triangulation")
    for s in seeds:
        yield f"flight seed {s}, 4 px noise, 3 % mislabels", S.simulate_flight(
            np.random.default_rng(s), n_markers=24, pixel_sigma_px=4.0, outlier_rate=0.03), ("triangulation",)
        yield f"wingbeat turn seed {s}, 4 px noise", W.simulate_wingbeat(
            np.random.default_rng(s), n_frames=160, flight="turn", pixel_sigma_px=4.0), ("triangulation",)
        yield f"issue scene seed {s} (offsets, 6 ms readout)", S.simulate_flight(
            np.random.default_rng(s), timing=ISSUE), ("truth", "triangulation")


def real(tmp: Path):
    import real_dlt
    import real_unsync

    if not real_dlt.REAL.is_dir():
        return
    from batgraph.session import Session

    yield "MCSC LED (4 cams, 464 frames)", real_unsync.mcsc_session()
    given, ignored = real_unsync.unsynchronise(real_unsync.mcsc_session(), 5)
    yield "MCSC every 5th, phases 0-0.6 frame, offsets given", given
    yield "MCSC every 5th, phases 0-0.6 frame, offsets ignored", ignored
    yield "DANNCE mouse (6 cams, 81 labelled frames)", real_unsync.dlt_rig_session(real_dlt.load_dannce(), "dannce")
    yield "Pose2Sim demo (4 cams, 100 frames)", real_unsync.pose2sim_session(tmp)
    rig, obs, _ = real_dlt.load_caliscope()
    yield "Caliscope ChArUco (4 webcams)", Session("caliscope", 30.0, rig, obs, pixel_sigma_px=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds instead of 5")
    args = ap.parse_args()
    head = ("| data | estimate | cams | sigma px | max step ms | max z | max px | named | rolling | lags | check s |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    print(head)
    for folder in sorted((ROOT / "data" / "samples").iterdir()):
        s = read_session(folder)
        for est in ("truth", "triangulation"):
            print(_row(f"sample {folder.name}", s, est), flush=True)
    for name, s, ests in simulated(args.quick):
        for est in ests:
            print(_row(name, s, est), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, s in real(Path(tmp)):
            print(_row(name, s, "triangulation"), flush=True)


if __name__ == "__main__":
    main()
