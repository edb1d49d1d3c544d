#!/usr/bin/env python3
"""`batgraph detect`'s speed and memory against decoding the same videos, and against `batgraph associate` of what
it finds: whole commands in child processes, alternated, medians printed with the ratios.

The footage: batgraph.simulate.simulate_flight (seed 3, 14 markers, 5 cameras of 1280 x 720, 160 frames) drawn by
batgraph.render as MPEG-4 videos (lossy, as a camera's own encoder). Runs: ``detect`` as it is (the cameras shared
over the cores), ``detect`` on one core (``BATGRAPH_FORK=0``), a plain decode of every frame of every video
(batgraph.frames, one core: what reading alone costs), and ``associate`` of the detections (one seed frame clicked).

Usage: ``python scripts/bench_detect.py [--frames 160] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_associate import _child  # noqa: E402  (scripts/ is on the path when run as a script)
from detect_study import alone  # noqa: E402

_DECODE = ("import resource, sys\nfrom batgraph.frames import Recording\n"
           "n = sum(1 for p in sys.argv[1:] for _ in Recording.open(p).frames())\n"
           "print('peak_kib', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n")


def main(argv: list[str] | None = None) -> int:
    from batgraph.associate import scenes
    from batgraph.formats.csv_text import write_csv
    from batgraph.render import render_session
    from batgraph.session import write_session
    from batgraph.simulate import simulate_flight

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = simulate_flight(np.random.default_rng(3), n_markers=14, n_frames=args.frames)
        obs = session.observations
        videos = [str(v) for v in render_session(session.rig, obs, args.frames, tmp / "footage",
                                                 np.random.default_rng(3), video=".mp4")]
        folder = tmp / "session"
        write_session(session, folder)
        (folder / "observations.csv").unlink()
        on_seed = obs[obs["frame"] == scenes.seed_frames(obs, 1)[0]].reset_index(drop=True)
        seed = on_seed[alone(on_seed)][["frame", "camera", "marker", "u", "v"]]  # two clicks on one blob: refused
        write_csv(folder / "seed_labels.csv", seed, "%.6f")
        detections = str(folder / "detections.csv")
        size = sum(Path(v).stat().st_size for v in videos) / 1e6
        print(f"5 cameras x {args.frames} frames of 1280 x 720 (MPEG-4, {size:.0f} MB), {len(obs)} observations",
              flush=True)
        runs: dict[str, list[tuple[float, float]]] = {"detect": [], "detect, one core": [], "decode only": [],
                                                      "associate": []}
        for r in range(args.repeats):  # alternated, so that a busy machine slows all alike
            runs["detect"].append(_child(["detect", *videos, "--out", detections, "--quiet"]))
            runs["detect, one core"].append(_child(["detect", *videos, "--out", detections, "--quiet"],
                                                   env=dict(os.environ, BATGRAPH_FORK="0")))
            runs["decode only"].append(_child(videos, code=_DECODE))
            runs["associate"].append(_child(["associate", str(folder), "--out", str(tmp / "named")]))
            print(f"  run {r + 1}: " + ", ".join(f"{k} {v[-1][0]:.2f} s" for k, v in runs.items()), flush=True)
        base = statistics.median(w for w, _ in runs["decode only"])
        for k, v in runs.items():
            walls = [w for w, _ in v]
            print(f"{k:18s} wall {statistics.median(walls):7.2f} s ({min(walls):.2f}-{max(walls):.2f}), "
                  f"{statistics.median(walls) / base:5.2f} x decode only, peak {max(m for _, m in v):.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
