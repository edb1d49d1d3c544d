"""How batgraph's whole commands use a machine's cores: the same commands on 2, 4, 8, ... of this machine's cores.

Issue 12 asks that a 16-core machine not be slower than a 2-core one, and that a batch's workers scale.
Each command runs in a fresh process whose CPU affinity (inherited by its children: the forked method
children, Dask's workers) is the first C cores of this machine; batgraph sizes its kernel threads, its
forks and its Dask cluster from that affinity, as it would on a C-core machine. Sections:
(a) the default ``reconstruct`` of the paper-scale scene (30 x 180 x 160, seed 3) and of the bundled
    5-camera sample, on each C of --cores; ratios against the first C;
(b) a batch of 16 small simulated sessions (10 cameras x 30 markers x 120 frames): on the first C with
    1 worker and with C workers (the default), and on the last C with 1, C/4 and C workers; with each of
    --engines: forked workers (the default on Linux) and a local Dask cluster (``BATGRAPH_FORK=0``).
Wall and CPU (user + system) medians over --repeats (--batch-repeats for (b)); nothing is asserted.
Run it on a machine with many cores (e.g. the 16-core device: it needs no GTSAM, no pycolmap and no
Rerun); on 2 cores it measures little. BENCHMARKS.md records a run. Every line is printed as soon as it is measured.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchproc import BATCH_SESSIONS, ROOT, SAMPLE, machine, run_process, simulate_sessions  # noqa: E402

ENGINES = {"forked": {}, "dask": {"BATGRAPH_FORK": "0"}}  # a batch's workers: the environment that picks them


def measure(what: str, cli: list[str], cpus: list[int], repeats: int, env: dict | None = None) -> dict:
    """Run ``cli`` ``repeats`` times on ``cpus``; print and return the medians (wall, cpu [s])."""
    runs = [run_process(cli, ROOT, cpus, env) for _ in range(repeats)]
    med = {k: statistics.median(r[k] for r in runs) for k in ("wall", "cpu", "rss")}
    walls = ", ".join(f"{r['wall']:.2f}" for r in runs)
    print(f"{what} on {len(cpus)} cores: wall {med['wall']:.2f} s ({walls}), CPU {med['cpu']:.2f} s, "
          f"peak RSS {med['rss']:.0f} MiB", flush=True)
    return med


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cores", default="2,4,8,16", help="comma list of core counts (capped at this machine's)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch-repeats", type=int, default=None, help="repeats of (b) (default --repeats)")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: reconstruct,batch")
    ap.add_argument("--engines", default="forked,dask", help="(b): comma list of batch workers: forked,dask")
    args = ap.parse_args(argv)
    skip = set(filter(None, args.skip.split(",")))
    available = sorted(os.sched_getaffinity(0))
    counts = sorted({min(int(c), len(available)) for c in args.cores.split(",")})
    info = machine()
    print(f"machine: {info['nproc']} cores ({len(available)} usable), {info['cpu']}, {info['ram_gib']:.1f} GiB "
          f"RAM, Python {info['python']}, numpy {info['numpy']}; core counts {counts}", flush=True)
    quiet = ["--viewer", "none", "--quiet"]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        # a first run compiles the kernels into numba's cache (minutes on a fresh install): not timed
        run_process(["reconstruct", str(SAMPLE), "--out", f"{tmp}/warm", *quiet], ROOT)
        print(f"warm-up (compiles the kernels when the cache is cold): {time.perf_counter() - t0:.1f} s", flush=True)
        t0 = time.perf_counter()
        simulate_sessions(tmp, None if "reconstruct" in skip else (30, 180, 160), batch="batch" not in skip,
                          parallel=len(available))
        print(f"simulated the sessions in {time.perf_counter() - t0:.1f} s", flush=True)
        rows = []
        if "reconstruct" not in skip:
            for what, session in (("reconstruct 30 x 180 x 160 (default methods)", f"{tmp}/big"),
                                  ("reconstruct flight_5cam (default methods)", str(SAMPLE))):
                meds = {c: measure(what, ["reconstruct", session, "--out", f"{tmp}/r{c}", *quiet],
                                   available[:c], args.repeats) for c in counts}
                base = counts[0]
                rows += [(f"{what}, {c} / {base} cores", meds[c]["wall"] / meds[base]["wall"],
                          meds[c]["cpu"] / meds[base]["cpu"]) for c in counts[1:]]
        if "batch" not in skip:
            batch = ["reconstruct", f"{tmp}/many/*", *quiet]
            plans = [(counts[0], 1), (counts[0], counts[0])]
            if counts[-1] != counts[0]:
                plans += [(counts[-1], 1), (counts[-1], max(1, counts[-1] // 4)), (counts[-1], counts[-1])]
            walls = {}
            engines = args.engines.split(",")
            for c, n in dict.fromkeys(plans):
                for e in engines:
                    walls[e, c, n] = measure(f"batch of {BATCH_SESSIONS} sessions, {n} {e} workers",
                                             [*batch, "--out", f"{tmp}/b{e}{c}_{n}", "--workers", str(n)],
                                             available[:c], args.batch_repeats or args.repeats, ENGINES[e])["wall"]
            for e, c, n in walls:
                if n > 1:
                    rows.append((f"batch, {e}, {c} cores: {n} workers / 1 worker", walls[e, c, n] / walls[e, c, 1],
                                 None))
                if e != engines[0]:
                    rows.append((f"batch, {c} cores, {n} workers: {engines[0]} / {e}",
                                 walls[engines[0], c, n] / walls[e, c, n], None))
    print()
    for what, wall, cpu in rows:
        print(f"{what}: wall {wall:.2f}" + ("" if cpu is None else f", CPU {cpu:.2f}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
