"""What the benchmark scripts share: the machine's line, whole commands timed in fresh processes, and jobs run in
turn (A B C A B C ...) with medians and round-by-round ratios against a baseline job.

The machine these run on is shared and its load moves within minutes, so a figure is quoted as a median of
alternated runs and a speed as a ratio to a baseline measured in the same rounds. Standard library only, so that
a machine without GTSAM runs bench_cores.py.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "samples" / "flight_5cam"


def machine() -> str:
    """One line: usable / all cores, CPU model, RAM, load average, Python, date."""
    cpu, ram = platform.processor() or "?", 0.0
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
        ram = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                   if line.startswith("MemTotal")) / 2**20
    except (OSError, StopIteration):
        pass
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{len(os.sched_getaffinity(0))} of {os.cpu_count()} cores, {cpu}, {ram:.1f} GiB RAM, load {load}, "
            f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M')}")


def batgraph(*args: str) -> list[str]:
    """``python -m batgraph ARGS`` with this interpreter."""
    return [sys.executable, "-m", "batgraph", *args]


# A small launcher starts the command and reads its rusage: a child spawned straight from a large benchmark
# process inherits that process's resident high-water mark at exec.
_LAUNCH = """import json, os, subprocess, sys, time
cpus = os.environ.pop("BENCH_CPUS", "")
if cpus:
    os.sched_setaffinity(0, [int(c) for c in cpus.split(",")])
t0 = time.perf_counter()
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
err = p.stderr.read()
_, status, ru = os.wait4(p.pid, 0)
p.returncode = os.waitstatus_to_exitcode(status)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": ru.ru_utime + ru.ru_stime, "rss": ru.ru_maxrss / 1024,
                  "code": p.returncode, "err": err[-2000:].decode(errors="replace")}))
"""


def run(argv: list[str], env: dict | None = None, cpus: list[int] | None = None) -> dict:
    """``argv`` in a fresh process from the repository root, its output discarded: wall [s], cpu = user + system of
    it and its children [s], rss = the largest resident set of it or one child [MiB]. ``env`` is added to this
    environment; ``cpus``: the processors it (and its children) may use. A failed command raises."""
    env = {**os.environ, **(env or {}), **({"BENCH_CPUS": ",".join(map(str, cpus))} if cpus else {})}
    out = subprocess.run([sys.executable, "-c", _LAUNCH, *argv], cwd=ROOT, env=env, capture_output=True, text=True,
                         check=True)
    res = json.loads(out.stdout)
    if res.pop("code") != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {res['err']}")
    del res["err"]
    return res


def timed(fn: Callable[[], object]) -> dict:
    """``fn()`` in this process: wall [s], cpu [s] (this process, every thread), and its result."""
    t0, c0 = time.perf_counter(), time.process_time()
    result = fn()
    return {"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0, "result": result}


def alternate(jobs: dict[str, Callable[[], dict]], rounds: int, warmup: bool = False,
              log: Callable[[str], None] = print) -> dict[str, list[dict]]:
    """Every job once per round, in turn, for ``rounds`` rounds (after one untimed round with ``warmup``): each
    job's figures (dicts from :func:`run` or :func:`timed`) per round."""
    runs: dict[str, list[dict]] = {name: [] for name in jobs}
    for r in range(-1 if warmup else 0, rounds):
        for name, job in jobs.items():
            res = job()
            if r >= 0:
                runs[name].append(res)
            log(f"  {'warm-up' if r < 0 else f'round {r + 1}'}: {name}: {res['wall']:.2f} s wall, "
                f"{res['cpu']:.2f} s CPU")
    return runs


def median(runs: list[dict], key: str = "wall") -> float:
    return statistics.median(r[key] for r in runs)


def ratio(runs: list[dict], base: list[dict], key: str = "wall") -> float:
    """The median of the round-by-round ratios runs[r] / base[r]."""
    return statistics.median(a[key] / b[key] for a, b in zip(runs, base, strict=True))


def table(runs: dict[str, list[dict]], baseline: str | None = None) -> str:
    """A markdown table: per job the median wall (min-max) and CPU [s], the peak memory where measured, and the
    ratios of wall and CPU to ``baseline``'s (medians of the round-by-round ratios)."""
    peak = all("rss" in r for rs in runs.values() for r in rs)
    cols = ["job", "wall [s], median (min-max)", "CPU [s]"] + ["peak [MiB]"] * peak
    cols += [f"wall / {baseline}", f"CPU / {baseline}"] if baseline else []
    lines = ["| " + " | ".join(cols) + " |", "|---" * len(cols) + "|"]
    for name, rs in runs.items():
        walls = [r["wall"] for r in rs]
        row = [name, f"{median(rs):.2f} ({min(walls):.2f}-{max(walls):.2f})", f"{median(rs, 'cpu'):.2f}"]
        row += [f"{median(rs, 'rss'):.0f}"] if peak else []
        row += [f"{ratio(rs, runs[baseline]):.2f}", f"{ratio(rs, runs[baseline], 'cpu'):.2f}"] if baseline else []
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)
