#!/usr/bin/env python3
"""Association's speed and memory against ``reconstruct``'s on the same session (30 cameras x 180 markers x 160
frames by default): both as the commands a user runs, in child processes, alternated, medians printed with the
ratio. Memory: each child's peak resident set (ru_maxrss), printed per detection.

The scene: batgraph.simulate.simulate_flight (seed 3, as BENCHMARKS.md's) made a detections session by
batgraph.associate.scenes (2 % spurious blobs, blobs closer than 3 px merged, one seed frame); ``reconstruct``
runs on the same flight with its true labels (the default methods, ``--viewer none``).

Usage: ``python scripts/bench_associate.py [--cameras 30] [--markers 180] [--frames 160] [--repeats 3]``.
Measured (this machine, 2 shared cores, 3 alternated runs): see docs/associate.md.
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


_PEAK = ("import resource, runpy, sys\n"
         "sys.argv = ['batgraph'] + sys.argv[1:]\n"
         "try:\n    runpy.run_module('batgraph', run_name='__main__')\n"
         "finally:\n    print('peak_kib', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n")


def _child(args: list[str], code: str = _PEAK, env: dict | None = None) -> tuple[float, float]:
    """(wall [s], peak RSS [MiB]) of ``python -m batgraph ARGS`` (or ``python -c CODE ARGS``, CODE printing its
    peak as _PEAK does) in a child process (the child reports its own peak: the parent's RUSAGE_CHILDREN would give
    the largest of all children so far)."""
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-c", code, *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True, env=env)
    wall = time.perf_counter() - t0
    peak = [line for line in run.stderr.splitlines() if line.startswith("peak_kib")]
    return wall, float(peak[-1].split()[1]) / 1024.0 if peak else float("nan")


def main(argv: list[str] | None = None) -> int:
    from batgraph.associate import scenes
    from batgraph.session import write_session
    from batgraph.simulate import simulate_flight

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cameras", type=int, default=30)
    p.add_argument("--markers", type=int, default=180)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = simulate_flight(np.random.default_rng(3), n_cameras=args.cameras, n_markers=args.markers,
                                  n_frames=args.frames)
        write_session(session, tmp / "labelled")
        sc = scenes.make_scene(session, np.random.default_rng(4))
        scenes.write_scene(session, sc, tmp / "detections")
        n = len(sc.detections)
        print(f"{args.cameras} cameras x {args.markers} markers x {args.frames} frames: {n} detections "
              f"({len(session.observations)} observations)", flush=True)
        assoc, recon = [], []
        for r in range(args.repeats):  # alternated, so that a busy machine slows both alike
            assoc.append(_child(["associate", str(tmp / "detections"), "--out", str(tmp / f"a{r}")]))
            recon.append(_child(["reconstruct", str(tmp / "labelled"), "--viewer", "none", "--quiet", "--out",
                                 str(tmp / f"r{r}")]))
            print(f"  run {r + 1}: associate {assoc[-1][0]:.2f} s, reconstruct {recon[-1][0]:.2f} s", flush=True)
        a = statistics.median(w for w, _ in assoc)
        b = statistics.median(w for w, _ in recon)
        print(f"median wall: associate {a:.2f} s, reconstruct {b:.2f} s, ratio {a / b:.2f}")
        print(f"peak RSS (max over runs): associate {max(m for _, m in assoc):.0f} MiB "
              f"({max(m for _, m in assoc) * 2 ** 20 / n:.0f} bytes per detection), reconstruct "
              f"{max(m for _, m in recon):.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
