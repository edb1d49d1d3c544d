"""Whole batgraph commands as a user runs them, timed in fresh processes: shared by the benchmark scripts.

Imports only the standard library (so that a machine without GTSAM, e.g. the 16-core device of
scripts/bench_cores.py, can run it).
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "samples" / "flight_5cam"
BATCH_SESSIONS = 16  # the batch: small sessions of 10 cameras x 30 markers x 120 frames


def machine() -> dict:
    """nproc, CPU model and RAM of this machine, from /proc; the versions of Python and numpy."""
    import numpy as np

    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem_kb = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                      if line.startswith("MemTotal"))
    except OSError:
        mem_kb = 0
    return {"nproc": os.cpu_count(), "cpu": cpu, "ram_gib": mem_kb / 2**20, "python": platform.python_version(),
            "numpy": np.__version__}


# The command runs in a child that writes its own peak resident memory (VmHWM of /proc/self/status: the
# high-water mark of its address space after exec) on exit; rusage's ru_maxrss would include the pages
# the child shared with this process at fork.
_CHILD = ("import atexit, os, runpy, sys\n"
          "def _hwm():\n"
          "    with open('/proc/self/status') as f, open(os.environ['BENCH_HWM'], 'w') as out:\n"
          "        out.write(next(l.split()[1] for l in f if l.startswith('VmHWM')))\n"
          "atexit.register(_hwm)\n"
          "sys.argv = ['batgraph', *sys.argv[1:]]\n"
          "runpy.run_module('batgraph.cli', run_name='__main__', alter_sys=True)\n")


def run_process(cli: list[str], cwd: Path, cpus: Iterable[int] | None = None, env: dict | None = None) -> dict:
    """``python -m batgraph.cli *cli`` in a fresh process from ``cwd`` (so that tree's batgraph is imported),
    on the CPUs ``cpus`` only when given (its affinity, inherited by its children), with ``env`` added to
    this process's environment: wall [s], CPU = user + system [s] (rusage of the child), peak resident
    memory [MiB] (its VmHWM)."""
    cpus = None if cpus is None else set(cpus)
    with tempfile.NamedTemporaryFile(suffix=".hwm") as hwm:
        env = {**os.environ, **(env or {}), "BENCH_HWM": hwm.name}
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", _CHILD, *cli], cwd=cwd, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                preexec_fn=None if cpus is None else lambda: os.sched_setaffinity(0, cpus))
        err = proc.stderr.read().decode(errors="replace")
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.stderr.close()
        code = os.waitstatus_to_exitcode(status)
        proc.returncode = code
        if code != 0:
            raise RuntimeError(f"batgraph {' '.join(cli)} in {cwd} failed ({code}): {err[-2000:]}")
        peak_kib = float(Path(hwm.name).read_text() or "nan")
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "rss": peak_kib / 1024}


def simulate_sessions(tmp: str, big: tuple[int, int, int] | None = (30, 180, 160), batch: bool = True,
                      wingbeat: bool = False, parallel: int = 1) -> None:
    """Simulate the benchmark's sessions under ``tmp``: ``big`` (cameras, markers, frames; seed 3) in tmp/big,
    the accuracy study's 5-camera flight (14 markers, 160 frames, seed 1) in tmp/f5 when ``wingbeat``, and the
    batch's BATCH_SESSIONS small sessions in tmp/many/sNN when ``batch``; ``parallel`` processes at a time."""
    from concurrent.futures import ThreadPoolExecutor

    clis = []
    if big is not None:
        clis.append(["simulate", "flight", f"{tmp}/big", "--cameras", str(big[0]), "--markers", str(big[1]),
                     "--frames", str(big[2]), "--seed", "3"])
    if wingbeat:
        clis.append(["simulate", "flight", f"{tmp}/f5", "--cameras", "5", "--seed", "1"])
    for seed in range(BATCH_SESSIONS if batch else 0):
        clis.append(["simulate", "flight", f"{tmp}/many/s{seed:02d}", "--cameras", "10", "--markers", "30",
                     "--frames", "120", "--seed", str(seed)])
    with ThreadPoolExecutor(max(1, parallel)) as pool:
        list(pool.map(lambda cli: run_process(cli, ROOT), clis))
