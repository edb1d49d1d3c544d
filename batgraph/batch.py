"""Many sessions at once: one ``reconstruct`` per worker process at a time, each failure reported, never
stopping the rest.

What it does: expands session folders and globs, runs :func:`batgraph.pipeline.reconstruct` for each in
worker processes forked from this one (batgraph.forked.stream_jobs, on Linux), or on a local Dask
``distributed`` cluster where forking is not possible (macOS, Windows, ``BATGRAPH_FORK=0``), or on an existing
Dask cluster at ``scheduler``; gathers one :class:`BatchItem` per session and writes ``batch_summary.csv``.
Forked workers start with batgraph already imported (a Dask cluster's spawned workers each import Python,
Dask and batgraph afresh). What it deliberately does not do: split one session across
workers, retry a session, or copy files between machines (with a remote scheduler, the session and output
folders must be on a file system that every worker sees, and the workers need batgraph installed).
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import logging
import os
import time
import traceback
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from tqdm.auto import tqdm

from . import forked
from . import methods as methods_registry
from .errors import InputError
from .formats.csv_text import write_csv
from .pipeline import DEFAULT_METHODS, reconstruct
from .result import Options
from .solver import threads as kernels

STATUSES = ("ok", "input error", "failed")
SUMMARY_FILE = "batch_summary.csv"
SUMMARY_COLUMNS = ["session", "status", "message", "runtime_s", "smoother_rmse_m", "session_dir", "out_dir"]


@dataclass
class BatchItem:
    """The outcome of one session of a batch.

    session_dir, out_dir: the session folder and where its outputs went (or would have gone).
    status: "ok", "input error" (bad session files; ``message`` names file, row/key and problem) or
      "failed" (any other exception; ``message`` is "ExceptionType: first line", ``traceback`` the full text).
    runtime_s: wall time of the session's reconstruct call [s]; for a session whose worker died, the time
      from its start (a Dask cluster: from its submission) to the failure.
    summary: the session's summary.json content when ok, else None.
    files: the files written when ok.  warnings: the session's input warnings when ok.
    pid: id of the process that ran it (the caller's own for a single session without workers).
    kernel_threads: the threads the compiled kernels had there when ok (batgraph.solver.threads).
    """

    session_dir: Path
    out_dir: Path
    status: str
    message: str
    runtime_s: float
    summary: dict | None = None
    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    traceback: str | None = None
    pid: int | None = None
    kernel_threads: int | None = None

    @property
    def name(self) -> str:
        """The session folder's name (the batch table's and summary's key)."""
        return self.session_dir.resolve().name

    def rmse_m(self, method: str = "smoother") -> float | None:
        """RMSE against truth over all points [m] of ``method``, or None (no truth, not run, not ok)."""
        m = (self.summary or {}).get("methods", {}).get(method, {})
        return m.get("truth", {}).get("rmse_m", {}).get("all")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _failure_message(e: BaseException) -> str:
    """"ExceptionType: first line" of ``e``; Dask's KilledWorker in a sentence a user can act on."""
    if type(e).__name__ == "KilledWorker":  # Dask's own text is a paragraph about task keys and addresses
        return "KilledWorker: the worker process died while running this session (a crash in native code, " \
               "or out of memory)"
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def run_session(session_dir: Path, out_dir: Path, methods: list[str], options: Options,
                viewer: str = "save", calibration: Path | None = None, validate: bool = False,
                kernel_threads: int | None = None) -> BatchItem:
    """One session -> BatchItem; every exception becomes a status (the job of a worker: forked, or a Dask task).

    Module-level so that workers import it by name; returns only the small summary, never the
    arrays, because the result travels back to the client. kernel_threads: the threads of the compiled
    kernels in this process (batgraph.solver.threads.set_threads; None leaves them as they are).
    """
    t0 = time.perf_counter()
    if kernel_threads is not None:
        kernels.set_threads(kernel_threads)
    try:
        result = reconstruct(session_dir, out_dir, methods, options, viewer=viewer, calibration=calibration,
                             validate=validate)
    except InputError as e:
        return BatchItem(session_dir, out_dir, "input error", _one_line(e), time.perf_counter() - t0, pid=os.getpid())
    except Exception as e:  # noqa: BLE001 - any crash of one session must not stop the batch
        return BatchItem(session_dir, out_dir, "failed", _one_line(_failure_message(e)), time.perf_counter() - t0,
                         traceback=traceback.format_exc(), pid=os.getpid())
    return BatchItem(session_dir, out_dir, "ok", "", time.perf_counter() - t0, summary=result.summary,
                     files=list(result.files), warnings=list(result.session.warnings), pid=os.getpid(),
                     kernel_threads=kernels.threads())


def is_batch(session_args: list[str | Path]) -> bool:
    """Whether a command line names a batch: several entries or a glob pattern (not counting matches).

    Decided from the arguments, not the file system, so that ``--out DIR`` means the same thing whether a
    pattern happens to match one folder or many: DIR itself for one plain session, DIR/<session> for a batch.
    """
    return len(session_args) > 1 or any(glob.has_magic(os.path.expanduser(str(a))) and not Path(a).is_dir()
                                        for a in session_args)


def exit_code(items: list[BatchItem]) -> int:
    """Process exit code of a batch: 0 all ok, 2 if every other session had bad input, 1 if any crashed."""
    if any(it.status == "failed" for it in items):
        return 1
    return 2 if any(it.status == "input error" for it in items) else 0


def expand_sessions(session_dirs: list[str | Path]) -> list[Path]:
    """Session folders and glob patterns -> folders, in the given order, each once.

    A pattern (``*``, ``?``, ``[``) expands to the folders it matches, sorted; one that matches no folder
    raises InputError naming it. A plain path is kept as given even if missing: that session then reports
    its own "input error" without stopping the others.
    """
    if not session_dirs:
        raise InputError("reconstruct: no session folder given")
    seen: dict[Path, Path] = {}  # resolved -> as given: a folder named twice (glob and by hand) runs once
    for entry in session_dirs:
        text = os.path.expanduser(str(entry))
        if glob.has_magic(text) and not Path(text).is_dir():  # a folder really named "[2024] flight" is kept
            found = [Path(p) for p in sorted(glob.glob(text)) if Path(p).is_dir()]
            if not found:
                raise InputError(f"{entry}: pattern matches no session folder")
        else:
            found = [Path(text)]
        for p in found:
            seen.setdefault(p.resolve(), p)
    return list(seen.values())


def output_dirs(sessions: list[Path], out_root: Path | None) -> list[Path]:
    """Each session's output folder: SESSION/out, or out_root/<session folder name> (names must be unique)."""
    if out_root is None:
        return [s / "out" for s in sessions]
    seen: dict[str, Path] = {}
    for s in sessions:
        name = s.resolve().name
        if name in seen:
            raise InputError(f"{seen[name]} and {s}: two sessions named {name!r} would write to the same folder "
                             f"{Path(out_root) / name} (rename one, or omit --out to write into each SESSION/out)")
        seen[name] = s
    return [Path(out_root) / s.resolve().name for s in sessions]


def _check_methods(methods: list[str]) -> list[str]:
    # Checked once here, so that a typo is one error instead of one "input error" per session.
    for m in methods:
        methods_registry.get(m)
    return list(methods)


def _run_on_cluster(client, jobs: list[tuple[Path, Path]], methods: list[str], options: Options, viewer: str,
                    calibration: Path | None, progress: bool, max_in_flight: int | None = None,
                    validate: bool = False, kernel_threads: int | None = None) -> list[BatchItem]:
    """One task per session, collected as they finish; a task that dies becomes a "failed" item.

    max_in_flight: submit at most this many sessions at once (None: all). With one per worker thread,
    a worker that dies takes down only the session it was running: Dask assigns short task lists to
    workers eagerly, and a dying worker's whole assigned list is counted as suspect.
    kernel_threads: each worker's share of the cores for the compiled kernels (see :func:`run_session`).
    """
    from distributed import as_completed

    pending = deque(enumerate(jobs))
    index = {}  # future -> (job index, submission time)

    def submit_next():
        if not pending:
            return None
        i, (s, o) = pending.popleft()
        # Absolute paths: a worker need not share this process's working directory. pure=False and an
        # explicit key: two sessions must never be merged into one task by Dask's hashing.
        cal = None if calibration is None else calibration.absolute()
        fut = client.submit(run_session, s.absolute(), o.absolute(), methods, options, viewer, cal, validate,
                            kernel_threads, pure=False, key=f"reconstruct-{i}-{s.name}")
        index[fut] = (i, time.perf_counter())
        return fut

    first = [f for f in (submit_next() for _ in range(max_in_flight or len(jobs))) if f is not None]
    finished = as_completed(first, loop=client.loop)
    items: list[BatchItem | None] = [None] * len(jobs)
    with _progress_bar(len(jobs), progress) as bar:
        for fut in finished:
            i, t_submit = index.pop(fut)
            s, o = jobs[i]
            try:
                items[i] = dataclasses.replace(fut.result(), session_dir=s, out_dir=o)  # paths as the caller gave
            except Exception as e:  # noqa: BLE001 - the worker died (KilledWorker), or could not run the task
                items[i] = BatchItem(s, o, "failed", _one_line(_failure_message(e)), time.perf_counter() - t_submit,
                                     traceback="".join(traceback.format_exception(e)))
            fut.release()
            if (nxt := submit_next()) is not None:
                finished.add(nxt)
            bar.set_postfix_str(f"{s.name}: {items[i].status}", refresh=False)
            bar.update()
    return items


def reconstruct_many(session_dirs: list[str | Path], out_root: str | Path | None = None,
                     methods: list[str] | None = None, options: Options | None = None,
                     scheduler: str | None = None, n_workers: int | None = None,
                     progress: bool = True, viewer: str = "save",
                     calibration: str | Path | None = None, validate: bool = False) -> list[BatchItem]:
    """``reconstruct`` on many sessions in parallel (worker processes); one BatchItem per session, in input order.

    session_dirs: folders and/or glob patterns (:func:`expand_sessions`). out_root: None -> each SESSION/out;
    else out_root/<session folder name>, plus out_root/batch_summary.csv. scheduler: an existing Dask
    scheduler (``tcp://host:8786``); None -> ``n_workers`` processes (default min(sessions, cores), kernels on
    cores // n threads) forked from this one, or a local Dask cluster (127.0.0.1, no dashboards) where forking
    is not possible or for more than forked.MAX_JOBS sessions; one session without a scheduler runs here.
    progress: a bar over finished sessions. viewer: "save" or "none" ("spawn": one session here only).
    calibration: one calibration.toml for every session (a worker must read it). validate: each session's
    leave-one-camera-out validation too (its folds serial inside a worker).
    Raises InputError for bad arguments (unknown method, a glob matching nothing, duplicate names under
    out_root, n_workers < 1 or with a scheduler, "spawn" with a cluster, an unreachable scheduler); a bad or
    crashing session is reported in its item. The local cluster's workers re-import the main script: call
    this under ``if __name__ == "__main__":``.
    """
    options = options or Options()
    calibration = Path(calibration) if calibration is not None else None
    methods = _check_methods(list(methods or DEFAULT_METHODS))
    sessions = expand_sessions(session_dirs)
    jobs = list(zip(sessions, output_dirs(sessions, Path(out_root) if out_root is not None else None), strict=True))
    if n_workers is not None and scheduler is not None:
        raise InputError("--workers: sets the size of the local cluster; it cannot be combined with --scheduler")
    if n_workers is not None and n_workers < 1:
        raise InputError(f"--workers: must be a positive integer, got {n_workers}")
    if viewer not in ("save", "spawn", "none"):
        raise InputError(f"--viewer: expected save, spawn or none, got {viewer!r}")
    in_workers = len(jobs) > 1 or scheduler is not None
    if viewer == "spawn" and in_workers:
        raise InputError("--viewer spawn: streams one session live, so it needs a single session and no "
                         "--scheduler (use --viewer save to get each session's recording.rrd)")

    if not in_workers:
        # The common case: no cluster start-up; the method bars of this one session stay as the caller chose.
        one = dataclasses.replace(options, progress=options.progress and progress)
        items = [run_session(*jobs[0], methods, one, viewer, calibration, validate)]
    else:
        options = dataclasses.replace(options, progress=False)  # no nested bars from inside workers
        if scheduler is None and forked.can_fork(min_cores=1) and len(jobs) <= forked.MAX_JOBS:
            items = _run_forked(jobs, methods, options, viewer, calibration, n_workers, progress, validate)
        else:
            items = _run_with_dask(jobs, methods, options, viewer, calibration, scheduler, n_workers, progress,
                                   validate)

    if out_root is not None:
        write_batch_summary(items, Path(out_root) / SUMMARY_FILE)
    return items


def _workers_and_threads(n_workers: int | None, n_jobs: int) -> tuple[int, int]:
    """(worker processes, compiled-kernel threads of each): ``n_workers`` (default the usable cores) but no more
    than the sessions, and the cores shared out between them."""
    n = min(n_workers or forked.usable_cores(), n_jobs)
    return n, max(1, forked.usable_cores() // n)


def _progress_bar(n: int, progress: bool):
    return tqdm(total=n, desc="sessions", unit="session", disable=not progress)


def _run_forked(jobs: list[tuple[Path, Path]], methods: list[str], options: Options, viewer: str,
                calibration: Path | None, n_workers: int | None, progress: bool, validate: bool
                ) -> list[BatchItem]:
    """Each session in one of ``n_workers`` forked worker processes (:func:`batgraph.forked.stream_jobs`); a
    session whose worker dies becomes a "failed" item and a new worker takes up the rest."""
    n, threads = _workers_and_threads(n_workers, len(jobs))

    def one(i: int) -> BatchItem:  # absolute paths in messages, as from a Dask worker (see _run_on_cluster)
        s, o = jobs[i]
        cal = None if calibration is None else calibration.absolute()
        return run_session(s.absolute(), o.absolute(), methods, options, viewer, cal, validate, threads)

    def lost(i: int, why: str, seconds: float) -> BatchItem:  # a worker's death: run_session itself never raises
        return BatchItem(*jobs[i], "failed", _one_line(f"{why} while running this session (a crash in native "
                                                       "code, or out of memory)"), seconds)

    items: list[BatchItem | None] = [None] * len(jobs)
    with _progress_bar(len(jobs), progress) as bar, \
            contextlib.closing(forked.stream_jobs(one, len(jobs), n, lost)) as results:
        for i, item in results:
            items[i] = item = dataclasses.replace(item, session_dir=jobs[i][0], out_dir=jobs[i][1])  # as given
            bar.set_postfix_str(f"{item.name}: {item.status}", refresh=False)
            bar.update()
    return items


def _run_with_dask(jobs, methods, options, viewer, calibration, scheduler, n_workers, progress,
                   validate=False) -> list[BatchItem]:
    """Open the client (and a local cluster when no scheduler is given), run, and always close them."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, set_as_default=False)
        except (OSError, ValueError, TypeError) as e:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({_failure_message(e)})") from None
        with client:
            return _run_on_cluster(client, jobs, methods, options, viewer, calibration, progress, validate=validate)

    # the cores shared out: each worker's compiled kernels get cores // n threads (a worker of a remote
    # scheduler keeps its own default, BATGRAPH_THREADS or its machine's cores)
    n, threads = _workers_and_threads(n_workers, len(jobs))
    # allowed-failures 0: a session that kills its worker (e.g. a native crash) fails once instead of
    # killing three more workers on retries; safe because only one session per worker is in flight.
    # memory_limit 0: a session is one indivisible task, so Dask's spill/pause machinery cannot help it,
    # and the nanny must not kill a large session at 1/n of the RAM.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
            LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address=None, worker_dashboard_address=None, memory_limit=0,
                         # Dask's warnings (a long session holding the GIL, workers killed on Ctrl-C) are noise
                         # here: every session's outcome is reported in its BatchItem
                         silence_logs=logging.ERROR,
                         # the scheduler's HTTP server (health, metrics) runs even without a dashboard:
                         # keep it on localhost and on a free port instead of 8787
                         scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster, \
            Client(cluster, set_as_default=False) as client:
        return _run_on_cluster(client, jobs, methods, options, viewer, calibration, progress, max_in_flight=n,
                               validate=validate, kernel_threads=threads)


def batch_table(items: list[BatchItem]) -> pd.DataFrame:
    """The batch summary as a table: one row per session with SUMMARY_COLUMNS (RMSE in metres, empty if none)."""
    return pd.DataFrame([{
        "session": it.name, "status": it.status, "message": it.message, "runtime_s": round(it.runtime_s, 3),
        "smoother_rmse_m": it.rmse_m("smoother"), "session_dir": str(it.session_dir), "out_dir": str(it.out_dir),
    } for it in items], columns=SUMMARY_COLUMNS)


def write_batch_summary(items: list[BatchItem], path: Path) -> Path:
    """Write batch_summary.csv atomically; returns its path."""
    write_csv(path, batch_table(items), "%.9g")
    return path


def format_batch_table(items: list[BatchItem], verbose: bool = False) -> str:
    """The terminal's end-of-batch table: session, status, time, smoother RMSE [mm], message; then a count.

    verbose: append the traceback of every "failed" session.
    """
    width = max([len("session"), *(len(it.name) for it in items)])
    lines = [f"{'session':<{width}}  {'status':<11}{'time s':>8}{'RMSE mm':>9}  message"]
    for it in items:
        rmse = it.rmse_m("smoother")
        lines.append(f"{it.name:<{width}}  {it.status:<11}{it.runtime_s:>8.2f}"
                     f"{'-' if rmse is None else f'{rmse * 1000:.2f}':>9}  {it.message}".rstrip())
    counts = {s: sum(it.status == s for it in items) for s in STATUSES}
    lines.append(f"{counts['ok']} of {len(items)} sessions ok"
                 + "".join(f", {counts[s]} {s}" for s in STATUSES[1:] if counts[s]))
    if verbose:
        for it in items:
            if it.traceback:
                lines += ["", f"{it.name}:", it.traceback.rstrip()]
    return "\n".join(lines)
