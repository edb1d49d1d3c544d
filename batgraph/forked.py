"""Work in forked child processes: one call beside this process's own work (the report, while the other outputs
are written), or a list of jobs shared over the cores (the methods, a batch's sessions).

:class:`Standby` forks a child at once that imports the report's modules while this process goes on, then
waits for its one call's arguments (:meth:`Standby.run` pickles them into a pipe; :meth:`Pending.wait` returns
the result or raises what the call raised). :func:`map_jobs` computes ``fn(0) .. fn(n - 1)`` here and in up to
cores - 1 forked children, each taking the next undone index: processes, not threads, since most of the
methods' work holds the GIL; a child sees this process's memory as at the fork, so only results are pickled.
:func:`stream_jobs` hands jobs to children only and yields each result as it comes, a dead child's job
reported and the child replaced (batgraph.batch). Children leave with ``os._exit``, as multiprocessing's do.
The work runs in this process instead where a child would not help or cannot be made: not Linux (no fork on
Windows, unsafe on macOS), a daemonic process (a Dask worker), one usable core, or ``BATGRAPH_FORK=0``.
concurrent.futures.ProcessPoolExecutor would pickle the function and its arguments and keep a pool alive;
one fork per call is all this needs.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import struct
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from multiprocessing.connection import wait as wait_for

ENV = "BATGRAPH_FORK"  # "0": never fork (run the work in this process)


def usable_cores() -> int:
    """The cores this process may use (respects taskset / container CPU sets where the OS reports them)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def can_fork(min_cores: int = 2) -> bool:
    """Whether work runs in forked children (:class:`Standby`, :func:`map_jobs`, :func:`stream_jobs`): on Linux
    (macOS's system libraries are not safe to use after a fork, which is why Python's default there is spawn),
    this process may have children, it has >= ``min_cores`` cores and ``BATGRAPH_FORK`` is not "0"."""
    return (os.environ.get(ENV, "").strip() != "0" and sys.platform.startswith("linux")
            and not multiprocessing.current_process().daemon and usable_cores() >= min_cores)


class Pending:
    """A call started by :meth:`Standby.run` (or a map_jobs worker): :meth:`wait` for it, or :meth:`cancel` it."""

    def __init__(self, process=None, conn=None, what: str = ""):
        self._process, self._conn, self.what = process, conn, what

    @property
    def forked(self) -> bool:
        """Whether the work runs in a child process (False: it already ran in this one)."""
        return self._process is not None

    def wait(self) -> None:
        """Wait for the child; raise the exception the work raised (the child's traceback in its notes), or
        RuntimeError when the child died without a word (e.g. killed for memory)."""
        if self._process is not None:
            self._recv()

    def _recv(self):
        """The child's one message, after which it is joined: its payload, or the error raised."""
        try:
            msg = self._conn.recv()
        except EOFError:
            msg = None
        finally:
            self._conn.close()
            self._process.join()
        code, self._process = self._process.exitcode, None
        if msg is None:
            raise RuntimeError(f"{self.what}: its process ended without a result (exit code {code})")
        if msg[0] == "error":
            exc, tb = msg[1], msg[2]
            exc.add_note(f"(raised in the {self.what} process)\n{tb}")
            raise exc
        return msg[1] if len(msg) > 1 else None

    def cancel(self) -> None:
        """Stop the child if it still runs (the parent failed; its staging folder is about to go)."""
        if self._process is not None:
            # SIGKILL, not SIGTERM: a library may handle SIGTERM (pycolmap's glog crash handler prints a
            # backtrace), and a child signalled between fork and malloc's reinitialisation then deadlocks
            # in that handler (the test suite hung so on test_forked, the parent waiting on it for ever)
            self._process.kill()
            self._process.join()
            self._conn.close()
            self._process = None


def _child(work: Callable[[], None], conn, reply: bool = True) -> None:
    """The child's body: run ``work``; send ("ok",) (if ``reply``; else ``work`` sends its own) or
    ("error", exception, traceback text)."""
    try:
        work()
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent
        tb = traceback.format_exc()
        try:
            pickle.dumps(e)
        except Exception:  # noqa: BLE001 - an exception that cannot travel goes back as its text
            e = RuntimeError(f"{type(e).__name__}: {e}")
        conn.send(("error", e, tb))
    else:
        if reply:
            conn.send(("ok",))
    finally:
        conn.close()


class Standby:
    """A child forked early that prepares (imports) while this process works on, then runs one call.

    ``prepare()`` runs in the child at once and returns the function to call; :meth:`run` sends that
    function's arguments (pickled straight into a pipe, so no second copy of them is held here) and returns
    the :class:`Pending` call. Used for the report, drawn while this process writes the other outputs. Where
    no child can be made (:func:`can_fork`), or an argument cannot be pickled, ``prepare()`` runs in
    :meth:`run`, here, and the call with it.
    """

    def __init__(self, prepare: Callable[[], Callable[..., None]], what: str):
        self._prepare, self.what = prepare, what
        self._pending, self._args_fd = None, None
        if can_fork():
            ctx = multiprocessing.get_context("fork")
            args_in, self._args_fd = os.pipe()
            recv, send = ctx.Pipe(duplex=False)
            # not daemonic: the call may fork children of its own (map_jobs); it is always waited for or cancelled
            process = ctx.Process(target=_standby_child, args=(prepare, args_in, self._args_fd, send),
                                  name=f"batgraph {what}", daemon=False)
            process.start()
            send.close()
            os.close(args_in)
            self._pending = Pending(process, recv, what)

    def run(self, *args) -> Pending:
        """Call the prepared function with ``args`` (in the child, or here where there is none)."""
        if self._pending is None:
            self._prepare()(*args)
            return Pending(what=self.what)
        fd, self._args_fd = self._args_fd, None
        try:
            with open(fd, "wb") as out:
                pickle.dump(args, out, protocol=pickle.HIGHEST_PROTOCOL)
        except BrokenPipeError:  # the child is gone (it failed to prepare): wait() says how
            pass
        except (pickle.PicklingError, TypeError, AttributeError):  # an argument cannot travel: call it here
            self._pending.cancel()
            self._prepare()(*args)
            return Pending(what=self.what)
        return self._pending

    def cancel(self) -> None:
        """Stop the child (the call was not wanted, or the caller failed); nothing once the call is done."""
        if self._pending is not None:
            if self._args_fd is not None:
                os.close(self._args_fd)
                self._args_fd = None
            self._pending.cancel()

    def __enter__(self) -> Standby:
        return self

    def __exit__(self, *exc) -> None:
        self.cancel()


def _standby_child(prepare: Callable[[], Callable[..., None]], args_in: int, args_out: int, conn) -> None:
    os.close(args_out)  # the parent's end: the pipe ends (EOF) when the parent closes it without a call

    def work():
        call = prepare()
        with open(args_in, "rb") as source:
            try:
                args = pickle.load(source)
            except EOFError:  # the parent gave up (it failed, or wanted no call): nothing to do
                return
        call(*args)

    _child(work, conn)


_INDEX = struct.Struct("=i")  # one job index in the dispenser pipe
MAX_JOBS = 16384  # every index is written before any is read: 4 bytes each must fit the 64 KiB pipe buffer


def _take(fn: Callable[[int], object], tickets: int) -> list[tuple[int, object]]:
    """Run ``fn`` on each index read from the pipe ``tickets`` until it is empty: (index, result) pairs. The
    pipe holds every index, written at once and closed for writing, so a 4-byte read takes one whole index
    (Linux serialises readers of a pipe) and no two processes take the same one."""
    out = []
    while len(b := os.read(tickets, _INDEX.size)) == _INDEX.size:
        i = _INDEX.unpack(b)[0]
        out.append((i, fn(i)))
    return out


def _take_child(fn: Callable[[int], object], tickets: int, conn) -> None:
    _child(lambda: conn.send(("ok", _take(fn, tickets))), conn, reply=False)


def map_jobs(fn: Callable[[int], object], n: int, workers: int | None = None) -> list:
    """``[fn(0), ..., fn(n - 1)]``, computed by this process and up to ``workers`` - 1 forked children (default:
    the usable cores; no children where :func:`can_fork` says no), each taking the next index not yet taken
    from a pipe that holds them all (no semaphore, hence no multiprocessing resource tracker process).
    Results travel back pickled. The first exception raised (here or in a child) is raised once every child
    has stopped."""
    if n > MAX_JOBS:
        raise ValueError(f"map_jobs takes at most {MAX_JOBS} jobs, got {n}")
    workers = min(n, workers or usable_cores())
    if workers < 2 or not can_fork():
        return [fn(i) for i in range(n)]
    ctx = multiprocessing.get_context("fork")
    tickets, fill = os.pipe()
    os.write(fill, b"".join(_INDEX.pack(i) for i in range(n)))
    os.close(fill)
    children = []
    try:
        for _ in range(workers - 1):
            recv, send = ctx.Pipe(duplex=False)
            process = ctx.Process(target=_take_child, args=(fn, tickets, send), name="batgraph worker",
                                  daemon=True)
            process.start()
            send.close()
            children.append(Pending(process, recv, "worker"))
        pairs = _take(fn, tickets)
        for child in children:
            pairs += child._recv()
    finally:
        for child in children:
            child.cancel()
        os.close(tickets)
    results = dict(pairs)
    if len(pairs) != n or len(results) != n:  # each index taken exactly once
        raise RuntimeError(f"map_jobs: {len(pairs)} results for {len(results)} of {n} jobs")
    return [results[i] for i in range(n)]


def stream_jobs(fn: Callable[[int], object], n: int, workers: int,
                lost: Callable[[int, str, float], object]) -> Iterator[tuple[int, object]]:
    """``(i, fn(i))`` for every i in range(n), as they finish, each computed in one of ``workers`` forked
    children; this process only hands out indices (the dispenser pipe of :func:`map_jobs`) and collects, so
    that its caller can show progress. For jobs that must each come back whatever befalls the others (a
    batch's sessions): a child that dies on job i (a native crash, the out-of-memory killer) or whose ``fn``
    raises gives ``(i, lost(i, why, seconds on it))``, and where it died a new child takes its place.
    The children are daemonic, so they fork none of their own (:func:`can_fork` is False in them): each runs
    its jobs' work in turn, the cores being shared out between the children. Use it in a ``with
    contextlib.closing(...)`` (or exhaust it): closing stops the children still running. Needs
    :func:`can_fork` (``min_cores=1``); ``n`` at most MAX_JOBS.

    Why not Dask's local cluster (which batgraph.batch keeps for ``--scheduler`` and where forking is not
    possible): its workers are spawned, so each one imports Python, Dask and batgraph afresh and loads the
    compiled kernels (16 sessions: 29.2 s with 2 workers there, 21.1 s so, on 2 cores).
    """
    if n > MAX_JOBS:
        raise ValueError(f"stream_jobs takes at most {MAX_JOBS} jobs, got {n}")
    if n == 0:
        return
    ctx = multiprocessing.get_context("fork")
    tickets, fill = os.pipe()
    os.write(fill, b"".join(_INDEX.pack(i) for i in range(n)))
    os.close(fill)
    children: dict = {}  # connection -> [process, index of the job it is on (None between jobs), its start time]

    def start():
        recv, send = ctx.Pipe(duplex=False)
        process = ctx.Process(target=_stream_child, args=(fn, tickets, send), name="batgraph worker", daemon=True)
        # Ctrl-C held back over the fork: a child signalled before it ignores SIGINT would print a traceback from
        # Python's own after-fork hooks; the child drops it (_stream_child), this process takes it just after.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        send.close()
        children[recv] = [process, None, 0.0]

    done: set[int] = set()
    try:
        for _ in range(min(workers, n)):
            start()
        while len(done) < n and children:
            for conn in wait_for(list(children)):
                entry = children[conn]
                try:
                    msg = conn.recv()
                except EOFError:  # the child is gone: at the end of the indices, or dead on the job it was on
                    del children[conn]
                    conn.close()
                    entry[0].join()
                    if entry[1] is not None:
                        i, seconds = entry[1], time.perf_counter() - entry[2]
                        done.add(i)
                        yield i, lost(i, f"its worker process died (exit code {entry[0].exitcode})", seconds)
                        if len(done) < n:
                            start()  # it finds the dispenser empty at once if every other job is taken
                    continue
                if msg[0] == "start":
                    entry[1], entry[2] = msg[1], time.perf_counter()
                    continue
                i, seconds, entry[1] = msg[1], time.perf_counter() - entry[2], None
                done.add(i)
                yield i, (msg[2] if msg[0] == "done" else lost(i, msg[2], seconds))
        for i in range(n):  # taken by a child that died before it could say so (never seen; not to be lost)
            if i not in done:
                yield i, lost(i, "its worker process died", 0.0)
    finally:
        for conn, (process, _, _) in children.items():
            process.kill()
            process.join()
            conn.close()
        os.close(tickets)


def _stream_child(fn: Callable[[int], object], tickets: int, conn) -> None:
    """A :func:`stream_jobs` child: ("start", i) when it takes job i, then ("done", i, result) or
    ("failed", i, the exception's type and message), until the dispenser is empty or the parent is gone.
    Ctrl-C is the parent's to handle (it stops the children): a child ignores it, and prints no traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked over the fork (stream_jobs' start)
    parent = os.getppid()
    try:
        while os.getppid() == parent and len(b := os.read(tickets, _INDEX.size)) == _INDEX.size:
            i = _INDEX.unpack(b)[0]
            conn.send(("start", i))
            try:
                result = fn(i)
            except Exception as e:  # noqa: BLE001 - the job failed, not this child: on to the next
                conn.send(("failed", i, f"{type(e).__name__}: {e}"))
            else:
                conn.send(("done", i, result))
    finally:
        conn.close()
