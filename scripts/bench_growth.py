"""How the smoother method's time grows with cameras, markers and frames.

From the paper-scale flight (30 cameras x 180 markers x 160 frames) one size changes at a time: cameras, markers, or
frames (the same 1.33 s flight filmed at a higher frame rate, so that the bat stays in view and the observations
grow with the frames). Every scene is simulated first; then each round runs schedule.run_smoother once on every
scene in turn (the machine's load moves, so a round sees all sizes under about the same load), and the table gives
per size the median wall and CPU time, the ratio to the axis's smallest size and the exponent of the growth
log(t / t0) / log(n / n0) against that size and against the observations. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchproc import alternate, machine, median, ratio, timed  # noqa: E402

from batgraph import warm  # noqa: E402
from batgraph.measurement import ideal_observations  # noqa: E402
from batgraph.result import Options  # noqa: E402
from batgraph.session import dense_observations  # noqa: E402
from batgraph.simulate import simulate_flight  # noqa: E402
from batgraph.solver import schedule  # noqa: E402

BASE = {"cameras": 30, "markers": 180, "frames": 160}
FPS = 120.0  # at 160 frames


def scene(cameras: int, markers: int, frames: int, seed: int) -> tuple:
    """(session, dense, ideal) of the flight at this size (fps scaled with the frames)."""
    session = simulate_flight(np.random.default_rng(seed), n_cameras=cameras, n_markers=markers, n_frames=frames,
                              fps=FPS * frames / BASE["frames"])
    dense = dense_observations(session)
    return session, dense, ideal_observations(session.rig, dense, session.pixel_sigma_px)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[5, 10, 20, 30])
    ap.add_argument("--markers", type=int, nargs="+", default=[45, 90, 180])
    ap.add_argument("--frames", type=int, nargs="+", default=[160, 320, 640])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    print(f"machine: {machine()}")
    axes = {axis: [{**BASE, axis: n} for n in getattr(args, axis)] for axis in BASE}
    sizes = {tuple(s.values()) for points in axes.values() for s in points}
    scenes = {size: scene(*size, args.seed) for size in sorted(sizes)}
    warm.compile_all()
    options = Options(progress=False)
    label = "{} x {} x {}".format
    runs = alternate({label(*size): (lambda s=s: timed(lambda: schedule.run_smoother(*s, options)))
                      for size, s in scenes.items()}, args.repeats)
    for axis, points in axes.items():
        print(f"\n### {axis} (others as in 30 cameras x 180 markers x 160 frames)\n")
        print(f"| {axis} | observations | wall [s] | CPU [s] | wall / first | exponent in {axis} | exponent in "
              "observations |\n|---|---|---|---|---|---|---|")
        first = None
        for size in points:
            key = tuple(size.values())
            rs, obs = runs[label(*key)], int(scenes[key][2].seen.sum())
            first = first or (size[axis], obs, rs)
            r = ratio(rs, first[2])
            grow = [f"{math.log(r) / math.log(n / n0):.2f}" if n != n0 else ""
                    for n, n0 in ((size[axis], first[0]), (obs, first[1]))]
            print(f"| {size[axis]} | {obs} | {median(rs):.2f} | {median(rs, 'cpu'):.2f} | {r:.2f} | {grow[0]} | "
                  f"{grow[1]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
