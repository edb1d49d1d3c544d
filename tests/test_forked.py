"""Tests of batgraph.forked: work in forked children gives what the same work gives here, errors come back, a
child that dies is an error, and the report drawn over several processes is the report drawn in one."""

from __future__ import annotations

import os
import time

import pytest

from batgraph import forked

needs_fork = pytest.mark.skipif(not forked.can_fork(), reason="no fork here (one core, daemonic or no fork)")


def start(work, what: str) -> forked.Pending:
    """``work()`` in a child forked now (a Standby with nothing to prepare and no arguments)."""
    return forked.Standby(lambda: work, what).run()


def test_map_jobs_is_the_list_comprehension_and_uses_children():
    def job(i):
        time.sleep(0.05)  # long enough that the children take some of the jobs
        return i * i, os.getpid()

    out = forked.map_jobs(job, 12)
    assert [v for v, _ in out] == [i * i for i in range(12)]
    if forked.can_fork():
        assert len({pid for _, pid in out}) >= 2  # not all here: the children took some
    assert forked.map_jobs(job, 0) == []


@needs_fork
def test_map_jobs_raises_what_a_child_raised():
    parent = os.getpid()

    def job(i):
        time.sleep(0.02)
        if os.getpid() != parent:
            raise ValueError(f"bad job {i}")
        return i

    with pytest.raises(ValueError, match="bad job") as info:
        forked.map_jobs(job, 8, workers=2)
    assert any("raised in the worker process" in n for n in info.value.__notes__)


def test_map_jobs_raises_what_this_process_raised():
    def job(i):
        if i == 0:
            raise KeyError("first")
        time.sleep(0.02)
        return i

    with pytest.raises(KeyError, match="first"):
        forked.map_jobs(job, 6, workers=2)


@needs_fork
def test_a_call_runs_in_a_child_and_wait_returns_after_it(tmp_path):
    target = tmp_path / "out.txt"

    def work():
        time.sleep(0.1)
        target.write_text(str(os.getpid()))

    pending = start(work, "test")
    assert pending.forked
    pending.wait()
    assert int(target.read_text()) != os.getpid()


@needs_fork
def test_a_calls_error_and_death_reach_the_parent():
    def bad():
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left") as info:
        start(bad, "report").wait()
    assert info.value.errno == 28

    class Unpicklable(Exception):
        def __reduce__(self):
            raise TypeError("no")

    def odd():
        raise Unpicklable("odd failure")

    with pytest.raises(RuntimeError, match="Unpicklable: odd failure"):
        start(odd, "report").wait()
    with pytest.raises(RuntimeError, match="ended without a result"):
        start(lambda: os._exit(3), "report").wait()


@needs_fork
def test_cancel_stops_a_running_child(tmp_path):
    target = tmp_path / "late.txt"

    def slow():
        time.sleep(5)
        target.write_text("too late")

    pending = start(slow, "report")
    t0 = time.perf_counter()
    pending.cancel()
    assert time.perf_counter() - t0 < 2 and not target.exists()
    pending.wait()  # nothing left to wait for


def test_switched_off_runs_here(monkeypatch, tmp_path):
    monkeypatch.setenv(forked.ENV, "0")
    assert not forked.can_fork()
    pids = []
    pending = start(lambda: pids.append(os.getpid()), "report")
    assert not pending.forked and pids == [os.getpid()]
    assert forked.map_jobs(lambda i: os.getpid(), 3) == [os.getpid()] * 3


def test_map_jobs_says_when_there_are_too_many_jobs():
    with pytest.raises(ValueError, match="at most 16384"):
        forked.map_jobs(lambda i: i, forked.MAX_JOBS + 1)
    assert forked.map_jobs(lambda i: i, 3000) == list(range(3000))  # many small jobs, each taken exactly once


def _prepare_writer(log):
    """A Standby preparation: records which process prepared, returns a writer of its arguments."""
    def prepare():
        tmp = log.with_suffix(".tmp")  # then renamed: the test polls for the file and must not read it half-written
        tmp.write_text(f"{os.getpid()}\n")
        tmp.replace(log)

        def write(path, payload):
            path.write_text(f"{payload['n']} {os.getpid()}")
        return write
    return prepare


@needs_fork
def test_standby_prepares_in_its_child_before_it_is_given_work(tmp_path):
    log, target = tmp_path / "prepared.txt", tmp_path / "out.txt"
    standby = forked.Standby(_prepare_writer(log), "test")
    deadline = time.time() + 10
    while not log.exists() and time.time() < deadline:  # prepared with no arguments sent yet
        time.sleep(0.01)
    assert log.exists() and int(log.read_text()) != os.getpid()
    pending = standby.run(target, {"n": 7, "big": list(range(200_000))})  # larger than a pipe's buffer
    pending.wait()
    n, pid = target.read_text().split()
    assert n == "7" and int(pid) == int(log.read_text())
    standby.cancel()  # after the call: nothing to stop


@needs_fork
def test_standby_cancelled_or_failing(tmp_path):
    target = tmp_path / "never.txt"
    with forked.Standby(_prepare_writer(tmp_path / "log.txt"), "test") as standby:
        pass  # the caller failed before run(): the child goes, nothing is written
    assert not standby._pending.forked and not target.exists()

    def broken():
        raise ImportError("no matplotlib here")

    with pytest.raises(ImportError, match="no matplotlib"), forked.Standby(broken, "report") as standby:
        time.sleep(0.2)  # the child has failed before it is given work: run() still returns, wait() raises
        standby.run(target, {"n": 1}).wait()


def test_standby_switched_off_prepares_at_run(monkeypatch, tmp_path):
    monkeypatch.setenv(forked.ENV, "0")
    log, target = tmp_path / "prepared.txt", tmp_path / "out.txt"
    standby = forked.Standby(_prepare_writer(log), "test")
    assert not log.exists()  # nothing prepared until there is work
    pending = standby.run(target, {"n": 3})
    assert not pending.forked and target.read_text() == f"3 {os.getpid()}" and log.exists()


def test_methods_side_by_side_give_what_they_give_one_after_the_other(monkeypatch):
    """run_methods forks the methods out (map_jobs): every estimate and table is the one-process one."""
    import numpy as np

    from batgraph.pipeline import run_methods
    from batgraph.result import Options
    from batgraph.simulate import simulate_flight

    session = simulate_flight(np.random.default_rng(3), n_cameras=4, n_frames=40)
    methods = ["smoother", "filter", "triangulate"]
    calls, map_jobs = [], forked.map_jobs

    def spy(fn, n, workers=None):
        calls.append(n)
        return map_jobs(fn, n, workers)

    monkeypatch.setattr(forked, "map_jobs", spy)
    monkeypatch.setenv(forked.ENV, "1")
    side = run_methods(session, methods, Options(progress=False))
    assert calls == [len(methods)]  # the methods went through map_jobs (which forks where it can)
    monkeypatch.setenv(forked.ENV, "0")
    here = run_methods(session, methods, Options(progress=False))
    assert list(side.estimates) == methods
    for m in methods:
        a, b = side.estimates[m], here.estimates[m]
        np.testing.assert_array_equal(a.xyz_m, b.xyz_m)
        np.testing.assert_array_equal(a.cov_m2, b.cov_m2)
        np.testing.assert_array_equal(a.outlier, b.outlier)
    assert side.trajectories.equals(here.trajectories) and side.reprojection.equals(here.reprojection)


@needs_fork
def test_standby_calls_here_what_cannot_be_pickled(tmp_path):
    """An argument that cannot travel to the child (a lambda) is not an error: the call runs here."""
    log, target = tmp_path / "prepared.txt", tmp_path / "out.txt"
    standby = forked.Standby(_prepare_writer(log), "test")
    pending = standby.run(target, {"n": 5, "odd": lambda: None})
    pending.wait()
    assert not pending.forked and target.read_text() == f"5 {os.getpid()}"


needs_fork_one_core = pytest.mark.skipif(not forked.can_fork(min_cores=1), reason="no fork here (daemonic or no fork)")


def _lost(i, why, seconds):
    return ("lost", i, why, seconds)


@needs_fork_one_core
def test_stream_jobs_gives_every_result_once_from_children_only():
    def job(i):
        time.sleep(0.02 * (i % 3))  # finishing out of order
        return i * i, os.getpid(), forked.can_fork(min_cores=1)

    got = list(forked.stream_jobs(job, 10, 3, _lost))
    assert sorted(i for i, _ in got) == list(range(10))
    assert all(v == i * i for i, (v, _, _) in got)
    pids = {pid for _, (_, pid, _) in got}
    assert os.getpid() not in pids and 1 <= len(pids) <= 3
    assert not any(inner for _, (_, _, inner) in got)  # daemonic: a worker forks no workers of its own
    assert list(forked.stream_jobs(job, 0, 3, _lost)) == []
    with pytest.raises(ValueError, match="at most 16384"):
        list(forked.stream_jobs(job, forked.MAX_JOBS + 1, 2, _lost))


@needs_fork_one_core
def test_stream_jobs_reports_a_failed_job_and_a_dead_child_and_goes_on():
    """Job 2 raises; job 5 kills its process (SIGKILL, as the out-of-memory killer would): each comes back
    through ``lost``, the dead child is replaced, and every other job is done, also with one worker."""
    def job(i):
        if i == 2:
            raise ValueError("bad job 2\nsecond line")
        if i == 5:
            os.kill(os.getpid(), 9)
        time.sleep(0.01)
        return i

    for workers in (1, 2):
        got = dict(forked.stream_jobs(job, 9, workers, _lost))
        assert sorted(got) == list(range(9))
        assert got[2][:3] == ("lost", 2, "ValueError: bad job 2\nsecond line")
        assert got[5][:3] == ("lost", 5, "its worker process died (exit code -9)") and got[5][3] >= 0
        assert all(got[i] == i for i in range(9) if i not in (2, 5))


@needs_fork_one_core
def test_stream_jobs_closed_early_stops_its_children(tmp_path):
    import contextlib

    import psutil

    def job(i):
        time.sleep(0.2 if i == 0 else 30)
        return os.getpid()

    before = {p.pid for p in psutil.Process().children()}  # e.g. multiprocessing's resource tracker
    with contextlib.closing(forked.stream_jobs(job, 4, 2, _lost)) as results:
        i, pid = next(results)
        children = {p.pid for p in psutil.Process().children()} - before
        assert i == 0 and pid in children and len(children) == 2
    time.sleep(0.1)
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in children)
