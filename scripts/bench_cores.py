"""Whole commands on 2, 4, 8, 16 of a machine's cores: how reconstruct and a batch scale with the cores.

Each command runs in a fresh process whose CPU affinity (inherited by its children: the forked method children, a
batch's workers) is the first C cores of this machine; batgraph sizes its threads and workers from that affinity,
as on a C-core machine. Commands: the default reconstruct (--viewer none) of the bundled sample and of a simulated
30 x 180 x 160 session (seed 3), and a batch of 16 small simulated sessions (10 cameras x 30 markers x 120 frames)
with one worker and with the default (one per core). Every command on every C runs in turn, --repeats rounds; one
table per command, ratios against its run on the fewest cores (the batch's against one worker on the same cores).
Run it on a machine with many cores (it needs no GTSAM); on 2 cores it measures little. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import tempfile

from benchproc import SAMPLE, alternate, batgraph, machine, run, table

BATCH = 16


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cores", default="2,4,8,16", help="comma list of core counts (capped at this machine's)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    cpus = sorted(os.sched_getaffinity(0))
    counts = sorted({min(int(c), len(cpus)) for c in args.cores.split(",")})
    print(f"machine: {machine()}; core counts {counts}")
    with tempfile.TemporaryDirectory() as tmp:
        run(batgraph("simulate", "flight", f"{tmp}/big", "--cameras", "30", "--markers", "180", "--seed", "3"))
        for s in range(BATCH):
            run(batgraph("simulate", "flight", f"{tmp}/many/s{s:02d}", "--cameras", "10", "--markers", "30",
                         "--frames", "120", "--seed", str(s)))
        commands = {"sample": [str(SAMPLE)], "30 x 180 x 160": [f"{tmp}/big"],
                    "batch, 1 worker": [f"{tmp}/many/*", "--workers", "1"], "batch, 1 per core": [f"{tmp}/many/*"]}
        jobs = {f"{what}, {c} cores": (lambda a=a, c=c, w=what: run(
            batgraph("reconstruct", *a, "--out", f"{tmp}/out/{w}{c}", "--viewer", "none", "--quiet"), cpus=cpus[:c]))
            for what, a in commands.items() for c in counts}
        runs = alternate(jobs, args.repeats, warmup=True)
    for what in ("sample", "30 x 180 x 160", "batch, 1 per core"):
        print(f"\n### reconstruct {what}\n")
        print(table({f"{c} cores": runs[f"{what}, {c} cores"] for c in counts}, f"{counts[0]} cores"))
    for c in counts:
        print(f"\n### batch of {BATCH} on {c} cores\n")
        print(table({w: runs[f"batch, {w}, {c} cores"] for w in ("1 worker", "1 per core")}, "1 worker"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
