"""How many threads the compiled loops use, and the pool that runs their parts.

Each compiled loop releases the GIL and works on a contiguous range of markers (or frames), so a call is split
into at most :func:`threads` parts run side by side; parts never change an answer (markers are independent).
``BATGRAPH_THREADS`` (environment) or :func:`set_threads` sets the number (default: the cores this process may
use); batgraph.batch gives each worker process its share.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

from ..forked import usable_cores


def _default() -> int:
    text = os.environ.get("BATGRAPH_THREADS", "").strip()
    return int(text) if text.isdigit() and int(text) > 0 else usable_cores()


_state: dict = {"n": _default(), "pool": None}
_POOL_LOCK = threading.Lock()


def _forget_pool() -> None:
    """A forked child has none of the pool's threads (fork copies the calling thread only): start afresh."""
    global _POOL_LOCK
    _state["pool"] = None
    _POOL_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def threads() -> int:
    """How many threads the compiled loops use (>= 1)."""
    return _state["n"]


def set_threads(n: int) -> None:
    """Use ``n`` (>= 1) threads from now on (e.g. a batch worker's share of the cores)."""
    n = max(1, int(n))
    if n != _state["n"] and _state["pool"] is not None:
        _state["pool"].shutdown()
        _state["pool"] = None
    _state["n"] = n


def split(n_items: int, min_part: int, run) -> None:
    """``run(lo, hi)`` over contiguous parts of range(n_items): at most :func:`threads` parts, none under
    ``min_part`` items unless there is one, side by side (the first on the calling thread)."""
    k = max(1, min(_state["n"], n_items // max(min_part, 1)))
    if k == 1:
        run(0, n_items)
        return
    with _POOL_LOCK:  # side_by_side's jobs may split at the same moment
        if _state["pool"] is None:
            _state["pool"] = ThreadPoolExecutor(max_workers=_state["n"] - 1, thread_name_prefix="batgraph-kernel")
    cuts = [(j * n_items) // k for j in range(k + 1)]
    futures = [_state["pool"].submit(run, cuts[j], cuts[j + 1]) for j in range(1, k)]
    run(cuts[0], cuts[1])
    for f in futures:
        f.result()


def side_by_side(jobs: list) -> list:
    """Call each of ``jobs`` (functions of no argument) and return their results in order, the first on the calling
    thread and the others each on a thread of its own when :func:`threads` > 1. For independent work whose own
    compiled loops are too small to split (e.g. one noise search per motion model); a job may call :func:`split`."""
    if _state["n"] == 1 or len(jobs) < 2:
        return [job() for job in jobs]
    with ThreadPoolExecutor(max_workers=len(jobs) - 1, thread_name_prefix="batgraph-job") as pool:
        futures = [pool.submit(job) for job in jobs[1:]]
        first = jobs[0]()
        return [first] + [f.result() for f in futures]


@contextmanager
def one_blas_thread():
    """BLAS held to one thread while the solver runs (re-entrant): its linear algebra is small blocks, where more
    threads only add synchronisation (a 126-wide Cholesky inverse: 0.16 ms on one thread, 0.73 ms on two of a
    loaded 2-core machine)."""
    if _state.get("blas"):
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        _state["blas"] = True
        try:
            yield
        finally:
            _state["blas"] = False
