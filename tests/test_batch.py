"""Many sessions at once (batgraph.batch): two real worker processes (forked, and a Dask cluster), one
deliberately broken session, one whose worker dies."""

from __future__ import annotations

import os
from pathlib import Path

import dask
import pandas as pd
import psutil
import pytest

from batgraph import forked
from batgraph.batch import (
    SUMMARY_COLUMNS,
    SUMMARY_FILE,
    BatchItem,
    exit_code,
    expand_sessions,
    format_batch_table,
    is_batch,
    output_dirs,
    reconstruct_many,
)
from batgraph.errors import InputError

BAD_ROW = 3  # 0-based data row of observations.csv made non-numeric -> "line 5" (header is line 1)


def break_u(folder: Path, row: int = BAD_ROW) -> Path:
    """Replace observations.csv's u on data row ``row`` with text; returns the file."""
    path = folder / "observations.csv"
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    df.loc[row, "u"] = "abc"
    df.to_csv(path, index=False)
    return path


def worker_children() -> list[psutil.Process]:
    """This process's child processes except multiprocessing's resource tracker (which lives as long as we do)."""
    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if "resource_tracker" not in " ".join(p.cmdline()) and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


ENGINES = ["forked", "dask"]


def use_engine(engine: str, monkeypatch) -> None:
    """Forked workers (the default on Linux) or a local Dask cluster (where batgraph cannot fork: here by
    ``BATGRAPH_FORK=0``); the other engine, if the batch took it, fails the test."""
    import batgraph.batch

    def not_this(*args, **kwargs):
        raise AssertionError(f"the batch did not run on the {engine} engine")

    if engine == "dask":
        monkeypatch.setenv("BATGRAPH_FORK", "0")
        monkeypatch.setattr(batgraph.batch, "_run_forked", not_this)
    elif not forked.can_fork(min_cores=1):
        pytest.skip("no fork here")
    else:
        monkeypatch.setattr(batgraph.batch, "_run_with_dask", not_this)


@pytest.mark.parametrize("engine", ENGINES)
def test_three_sessions_on_two_workers(make_session_folder, tmp_path, monkeypatch, engine):
    """Two good sessions and one with a non-numeric u on two worker processes.

    The broken one is reported as "input error" naming the file and line; it does not stop the others,
    whose outputs are written; both worker processes ran sessions and are gone afterwards. Sessions are
    given relative to the working directory, as on a command line.
    Measured 8-19 s on the shared 2-core machine with Dask (cluster start ~1.5 s, close ~0.3 s; each session
    1.5-5 s, mostly report.html); no time is asserted.
    """
    use_engine(engine, monkeypatch)
    good = [make_session_folder("flight_a", seed=1), make_session_folder("flight_c", seed=2)]
    bad = make_session_folder("flight_b", seed=3)
    bad_file = break_u(bad)
    out_root = tmp_path / "results"
    before = {p.pid for p in worker_children()}
    monkeypatch.chdir(tmp_path)
    given = [Path(f.name) for f in (good[0], bad, good[1])]

    items = reconstruct_many(given, out_root, ["triangulate"], n_workers=2, progress=False, viewer="none")

    assert [it.session_dir for it in items] == given  # input order, not finishing order
    assert [it.status for it in items] == ["ok", "input error", "ok"]
    for it in (items[0], items[2]):
        assert it.out_dir == out_root / it.session_dir.name
        for name in ("trajectories.csv", "reprojection.csv", "summary.json"):
            assert (it.out_dir / name).is_file()
        assert it.summary["methods"]["triangulate"]["n_estimated"] > 0
        assert it.message == "" and it.traceback is None
    msg = items[1].message
    assert str(bad_file) in msg and f"line {BAD_ROW + 2}" in msg and "'abc' is not a number" in msg
    assert "\n" not in msg
    assert not (out_root / "flight_b").exists()

    # each worker's compiled kernels had half of the cores
    cores = len(os.sched_getaffinity(0))
    assert [it.kernel_threads for it in (items[0], items[2])] == [max(1, cores // 2)] * 2
    # every session ran in a worker process, the two workers shared the work, and none is left running
    pids = {it.pid for it in items}
    assert os.getpid() not in pids and len(pids) == 2
    assert not any(psutil.pid_exists(p) for p in pids)
    assert {p.pid for p in worker_children()} <= before

    table = pd.read_csv(out_root / SUMMARY_FILE, keep_default_na=False)
    assert list(table.columns) == SUMMARY_COLUMNS
    assert list(table["session"]) == ["flight_a", "flight_b", "flight_c"]
    assert list(table["status"]) == ["ok", "input error", "ok"]
    assert table["message"][1] == msg
    text = format_batch_table(items)
    assert all(name in text for name in ("flight_a", "flight_b", "flight_c"))
    assert text.splitlines()[-1] == "2 of 3 sessions ok, 1 input error"


@pytest.mark.parametrize("engine", ENGINES)
def test_one_calibration_for_every_session_reaches_the_workers(make_session_folder, tmp_path, monkeypatch, engine):
    """`--calibration FILE` replaces each session's own calibration.toml, inside the workers too: a
    file whose first camera is renamed makes both (otherwise good) sessions input errors naming that file."""
    use_engine(engine, monkeypatch)
    sessions = [make_session_folder("flight_a", seed=1), make_session_folder("flight_b", seed=2)]
    day = tmp_path / "day.toml"
    day.write_text((sessions[0] / "calibration.toml").read_text().replace('name = "cam1"', 'name = "camX"', 1))
    assert day.read_text() != (sessions[0] / "calibration.toml").read_text()
    items = reconstruct_many(sessions, tmp_path / "out", ["triangulate"], n_workers=2, progress=False,
                             viewer="none", calibration=day)
    assert [it.status for it in items] == ["input error", "input error"]
    assert all(str(day) in it.message and "'cam1'" in it.message for it in items), [it.message for it in items]
    assert os.getpid() not in {it.pid for it in items}


def test_a_session_whose_worker_dies_is_failed_and_the_rest_run(make_session_folder, tmp_path, monkeypatch):
    """Forked workers: the second of three sessions kills its worker process (SIGKILL, as the out-of-memory
    killer would). It is "failed", saying so in one line; a new worker takes up the third; no worker is left."""
    import batgraph.batch

    if not forked.can_fork(min_cores=1):
        pytest.skip("no fork here")
    sessions = [make_session_folder(name, seed=i + 1) for i, name in enumerate(("a", "b", "c"))]
    real = batgraph.batch.reconstruct

    def dies_on_b(session_dir, *args, **kwargs):
        if Path(session_dir).name == "b":
            os.kill(os.getpid(), 9)
        return real(session_dir, *args, **kwargs)

    monkeypatch.setattr(batgraph.batch, "reconstruct", dies_on_b)  # the workers are forked: they see it
    before = {p.pid for p in worker_children()}
    items = reconstruct_many(sessions, tmp_path / "out", ["triangulate"], n_workers=1, progress=False,
                             viewer="none")
    assert [it.status for it in items] == ["ok", "failed", "ok"]
    assert items[1].message == ("its worker process died (exit code -9) while running this session (a crash in "
                                "native code, or out of memory)")
    assert items[0].pid != items[2].pid  # the dead worker was replaced
    assert (tmp_path / "out" / "c" / "trajectories.csv").is_file() and not (tmp_path / "out" / "b").exists()
    assert exit_code(items) == 1
    assert {p.pid for p in worker_children()} <= before


def test_single_session_runs_here_and_a_crash_is_reported(make_session_folder, tmp_path, monkeypatch):
    """One session, no scheduler: no cluster (runs in this process); a non-input exception -> "failed".

    The crash: the report writer raises (a bug, not bad input); the output folder is left as it was.
    A plain file where the output folder must go is the user's input error, named in one line.
    """
    import batgraph.report

    session = make_session_folder("only")
    out_root = tmp_path / "results"
    out_root.mkdir()
    (out_root / "only").write_text("in the way")
    (item,) = reconstruct_many([session], out_root, ["triangulate"], progress=False, viewer="none")
    # refused before any work (pipeline.reconstruct checks the output place first)
    assert item.status == "input error" and "exists and is a file" in item.message, item.message
    assert str(out_root / "only") in item.message and item.summary is None
    (out_root / "only").unlink()

    def crash(*a, **kw):
        raise OSError("disk on fire\nsecond line")

    monkeypatch.setattr(batgraph.report, "write_report", crash)
    (item,) = reconstruct_many([session], out_root, ["triangulate"], progress=False, viewer="none")

    assert item.pid == os.getpid()
    assert item.status == "failed"
    assert item.message == "OSError: disk on fire"
    assert "Traceback" in item.traceback and "crash" in item.traceback
    assert "Traceback" in format_batch_table([item], verbose=True)
    assert "Traceback" not in format_batch_table([item])
    table = pd.read_csv(out_root / SUMMARY_FILE, keep_default_na=False)
    assert list(table["status"]) == ["failed"]
    assert sorted(p.name for p in out_root.iterdir()) == [SUMMARY_FILE]  # no half result, no temporary


def test_glob_expands_sorted_to_folders_once(make_session_folder, tmp_path):
    """A pattern gives its matching folders sorted (files skipped); a folder named twice runs once."""
    c, a, b = (make_session_folder(n) for n in ("s_c", "s_a", "s_b"))
    make_session_folder("other")
    (tmp_path / "s_file.txt").write_text("not a session")

    got = expand_sessions([str(tmp_path / "s_*"), b])

    assert got == [a, b, c]
    assert is_batch([str(tmp_path / "s_*")]) and is_batch([a, b]) and not is_batch([a])


def test_batch_prints_each_sessions_warnings_with_its_name(make_session_folder, tmp_path, capsys):
    """A session's warnings reach the terminal in a batch too (even with --quiet), each after its session's name."""
    from batgraph.cli import main

    a, b = make_session_folder("s_a"), make_session_folder("s_b")
    (b / "session.toml").write_text((b / "session.toml").read_text() + "\n[lab]\nbat = \"Carollia 7\"\n")
    assert main(["reconstruct", str(a), str(b), "--out", str(tmp_path / "out"), "--methods", "triangulate",
                 "--viewer", "none", "--workers", "1", "--quiet"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(err) == 1 and err[0].startswith("batgraph: warning: s_b: ") and "[lab]" in err[0], err


def test_exit_code_ranks_crash_over_input_error():
    """0 when all ok; 2 when the only problems are bad input; 1 as soon as one session crashed."""
    def item(status):
        return BatchItem(Path("s"), Path("s/out"), status, "", 0.0)
    assert exit_code([item("ok"), item("ok")]) == 0
    assert exit_code([item("ok"), item("input error")]) == 2
    assert exit_code([item("input error"), item("failed"), item("ok")]) == 1


def test_glob_matching_nothing_and_duplicate_names_are_errors(make_session_folder, tmp_path):
    """Argument errors are raised up front, naming the pattern or both clashing folders."""
    pattern = str(tmp_path / "nothing_*")
    with pytest.raises(InputError, match="nothing_\\*: pattern matches no session folder"):
        expand_sessions([pattern])
    with pytest.raises(InputError, match="nothing_"):
        reconstruct_many([pattern], tmp_path / "out", ["triangulate"], progress=False)

    one = make_session_folder("x/flight")
    two = make_session_folder("y/flight")
    assert output_dirs([one, two], None) == [one / "out", two / "out"]
    with pytest.raises(InputError, match="two sessions named 'flight'") as e:
        reconstruct_many([one, two], tmp_path / "out", ["triangulate"], progress=False)
    assert str(one) in str(e.value) and str(two) in str(e.value)

    with pytest.raises(InputError, match="unknown method 'smoothr'"):
        reconstruct_many([one], None, ["smoothr"], progress=False)
    with pytest.raises(InputError, match="--viewer spawn"):
        reconstruct_many([one, two], None, ["triangulate"], viewer="spawn", progress=False)


def test_existing_scheduler_address(make_session_folder, tmp_path):
    """``scheduler=ADDRESS`` uses a cluster someone else started (here an in-process one), even for one session.

    An address where no scheduler listens is an InputError naming it (connect timeout shortened to 1 s).
    """
    from distributed import LocalCluster

    bad = make_session_folder("broken")
    break_u(bad)
    with LocalCluster(n_workers=1, processes=False, protocol="tcp", host="127.0.0.1", dashboard_address=None,
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        (item,) = reconstruct_many([bad], None, ["triangulate"], scheduler=cluster.scheduler_address,
                                   progress=False, viewer="none")
        assert item.status == "input error" and "'abc' is not a number" in item.message
        with pytest.raises(InputError, match="--workers"):
            reconstruct_many([bad], None, ["triangulate"], scheduler=cluster.scheduler_address, n_workers=2)

    nowhere = "tcp://127.0.0.1:9"  # discard port: nothing listens there
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}), \
            pytest.raises(InputError, match=f"--scheduler {nowhere}: cannot connect"):
        reconstruct_many([bad], None, ["triangulate"], scheduler=nowhere, progress=False)


def test_ctrl_c_stops_a_forked_batch_in_one_line(make_session_folder, tmp_path):
    """Ctrl-C (SIGINT to the terminal's process group) during a batch on forked workers: exit code 130,
    "batgraph: interrupted" and nothing else on stderr (no worker's traceback), no worker left running."""
    import signal
    import subprocess
    import sys
    import time

    if not forked.can_fork(min_cores=1):
        pytest.skip("no fork here")
    for i in range(6):
        make_session_folder(f"s{i}", seed=i + 1)
    proc = subprocess.Popen([sys.executable, "-m", "batgraph.cli", "reconstruct", str(tmp_path / "s*"), "--out",
                             str(tmp_path / "out"), "--workers", "2", "--viewer", "none", "--quiet"],
                            start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    workers = []
    deadline = time.monotonic() + 60
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
        workers = psutil.Process(proc.pid).children()
    assert len(workers) == 2, "the workers never started"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.decode() == "batgraph: interrupted\n", err.decode()
    time.sleep(0.2)
    assert not any(psutil.pid_exists(w.pid) and w.status() != psutil.STATUS_ZOMBIE for w in workers)
