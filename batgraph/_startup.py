"""What the command line sets before its modules load. Imported first by batgraph.cli.

One BLAS thread per process, unless the user chose otherwise (OpenBLAS reads the variable when it loads):
batgraph spreads its own work over the cores (the report's forked child, methods side by side, the kernels'
thread pool, Dask workers), and its solves already pin BLAS to one thread around small-matrix work
(threadpoolctl, batgraph.solver.threads.one_blas_thread). Elsewhere numpy's and scipy's OpenBLAS each kept one
worker per core: on a 16-core machine the bundled flight used 21.6 s of CPU for 7.6-8.8 s of wall time, and
12.7 s with OPENBLAS_NUM_THREADS=1 at the same wall time. Nothing is set when the user set any of
USER_THREAD_VARIABLES (OpenBLAS also obeys OpenMP's).

No garbage collection while the modules load (:func:`imports_done` ends the pause): ~1,300 modules (numba,
pandas, scipy) create objects that are never garbage, and collecting among them took 5 % of the default command
on the bundled sample (paired runs, 2 cores).
"""

import gc
import os

USER_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

if not any(os.environ.get(name) for name in USER_THREAD_VARIABLES):
    os.environ["OPENBLAS_NUM_THREADS"] = "1"

_was_enabled = gc.isenabled()
gc.disable()


def imports_done() -> None:
    """Collect again, with every object alive now (the modules') out of the collector's sight (gc.freeze)."""
    gc.freeze()
    if _was_enabled:
        gc.enable()
