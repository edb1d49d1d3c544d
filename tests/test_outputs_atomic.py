"""A result folder is one result: killed at any step of writing, it holds the previous complete result or
the new complete one, the user's own files survive, and the next run removes what the killed one left."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from batgraph import atomic
from batgraph.cli import main

OWNED = ("a.csv", "b.csv", "c.rrd")


def _snapshot(folder: Path) -> dict[str, str]:
    """relative path -> sha1 of every file under ``folder`` (hidden ones included)."""
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _hidden_siblings(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}."))


def _hidden_inside(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ----- batgraph.atomic.result_folder on its own -------------------------------------------------
def _old_result(target: Path) -> None:
    target.mkdir()
    (target / "a.csv").write_text("old a")
    (target / "c.rrd").write_text("old c")  # b.csv absent in the old result
    (target / "notes.txt").write_text("the user's notes")
    (target / "exports").mkdir()
    (target / "exports" / "x.c3d").write_text("an export")
    (target / ".a.abcd1234.csv").write_text("half a file of a killed pre-staging run")


def test_swap_keeps_foreign_files_and_drops_stale_outputs(tmp_path):
    target = tmp_path / "out"
    _old_result(target)
    with atomic.result_folder(target, OWNED) as stage:
        (stage / "a.csv").write_text("new a")
        (stage / "b.csv").write_text("new b")
    assert _snapshot(target).keys() == {"a.csv", "b.csv", "notes.txt", "exports/x.c3d"}
    assert (target / "a.csv").read_text() == "new a" and (target / "notes.txt").read_text() == "the user's notes"
    assert not (target / "c.rrd").exists()  # of the old result, not written by this one
    assert _hidden_siblings(target) == [] and _hidden_inside(target) == []
    assert oct(target.stat().st_mode & 0o777) != oct(0o700)  # not mkdtemp's private mode


def test_an_error_while_writing_leaves_the_old_result(tmp_path):
    target = tmp_path / "out"
    _old_result(target)
    before = _snapshot(target)
    with pytest.raises(RuntimeError), atomic.result_folder(target, OWNED) as stage:
        (stage / "a.csv").write_text("new a")
        raise RuntimeError("writer failed")
    assert _snapshot(target) == before
    assert _hidden_siblings(target) == []


KILL_SCRIPT = textwrap.dedent("""
    import os, shutil, sys
    from pathlib import Path
    from batgraph import atomic

    target, k = Path(sys.argv[1]), int(sys.argv[2])
    calls = [0]
    def step(real):
        def f(*a, **kw):
            calls[0] += 1
            if calls[0] == k:
                os._exit(9)  # SIGKILL-like: no cleanup, no finally
            return real(*a, **kw)
        return f
    os.rename, os.replace, shutil.rmtree = step(os.rename), step(os.replace), step(shutil.rmtree)
    with atomic.result_folder(target, ("a.csv", "b.csv", "c.rrd")) as stage:
        for name in ("a.csv", "b.csv", "c.rrd"):
            atomic.write_text(stage / name, "new " + name)
    sys.exit(0)
""")


def test_kill_at_every_step_leaves_old_or_new_and_the_next_run_recovers(tmp_path):
    """A process killed before each rename/replace/removal of a run (k = 1, 2, ...) until one completes."""
    script = tmp_path / "kill.py"
    script.write_text(KILL_SCRIPT)
    seen = set()
    for k in range(1, 30):
        target = tmp_path / f"out{k}"
        _old_result(target)
        old = _snapshot(target)
        new = {"a.csv", "b.csv", "c.rrd", "notes.txt", "exports/x.c3d"}
        rc = subprocess.run([sys.executable, str(script), str(target), str(k)], timeout=60).returncode
        # between the two renames of the swap the folder is briefly absent; recovery finishes the swap
        state = _snapshot(target) if target.exists() else None
        atomic.recover_folder(target, OWNED)
        after = _snapshot(target)
        if after == old:
            seen.add("old")
            assert state in (old, None)
        else:
            seen.add("new")
            assert after.keys() == new, (k, after.keys())
            assert all((target / n).read_text() == f"new {n}" for n in OWNED if n in after)
            assert (target / "notes.txt").read_text() == "the user's notes"
            assert state is None or state.keys() in (old.keys(), new)
        assert _hidden_siblings(target) == [], (k, _hidden_siblings(target))
        assert not any(n.startswith(atomic.TMP_TAG) for n in _hidden_inside(target))
        if rc == 0:
            break
    else:
        pytest.fail("the run never completed")
    assert seen == {"old", "new"} and k > 5  # 3 files, 3 renames, the removal of the old folder


def test_only_a_session_of_detections_makes_a_scratch_folder(small_session, tmp_path, monkeypatch):
    """reconstruct makes its scratch folder for the names only where it names detections, so a killed or
    interrupted run of a labelled session (a batch's workers stopped by Ctrl-C) leaves nothing in the system's
    temporary folder."""
    import tempfile

    from batgraph.pipeline import reconstruct

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "system-tmp"))
    (tmp_path / "system-tmp").mkdir()
    made = []
    real = tempfile.TemporaryDirectory

    def spy(*args, **kwargs):
        made.append(kwargs.get("prefix"))
        return real(*args, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryDirectory", spy)
    reconstruct(small_session, tmp_path / "out", ["triangulate"], viewer="none")
    assert "batgraph-names-" not in made and list((tmp_path / "system-tmp").iterdir()) == []


def test_running_writer_temporaries_are_left_alone(tmp_path):
    """Only temporaries of processes that are gone are removed (this process's own are kept)."""
    target = tmp_path / "out"
    _old_result(target)
    mine = tmp_path / f".out{atomic.TMP_TAG}{os.getpid()}-abc123"
    mine.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    gone = tmp_path / f".out{atomic.TMP_TAG}{dead.pid}-abc124"
    gone.mkdir()
    atomic.recover_folder(target, OWNED)
    assert mine.exists() and not gone.exists()


def test_working_directory_is_written_in_place(tmp_path, monkeypatch):
    """The folder the shell is in cannot be swapped (the shell would be left in a deleted folder):
    the files are then replaced one by one, and the foreign ones stay."""
    target = tmp_path / "out"
    _old_result(target)
    monkeypatch.chdir(target)
    with atomic.result_folder(".", OWNED) as stage:
        assert stage.parent == target
        (stage / "a.csv").write_text("new a")
    assert (target / "a.csv").read_text() == "new a" and not (target / "c.rrd").exists()
    assert (target / "notes.txt").exists() and _hidden_siblings(target) == []


# ----- reconstruct ------------------------------------------------------------------------------
NAMES = ("labels.csv", "association.json")  # written only where reconstruct named unlabelled detections


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("atomic") / "s"
    assert main(["simulate", "flight", str(folder), "--cameras", "3", "--frames", "20", "--seed", "1"]) == 0
    return folder


RECONSTRUCT_KILL = textwrap.dedent("""
    import os, shutil, sys
    from batgraph.pipeline import reconstruct

    session, out, k = sys.argv[1], sys.argv[2], int(sys.argv[3])
    calls = [0]
    def step(real):
        def f(*a, **kw):
            calls[0] += 1
            if calls[0] == k:
                os._exit(9)
            return real(*a, **kw)
        return f
    os.rename, os.replace, shutil.rmtree = step(os.rename), step(os.replace), step(shutil.rmtree)
    reconstruct(session, out, ["triangulate"], viewer="save", validate=False)
""")


def test_reconstruct_killed_at_each_output_step(small_session, tmp_path):
    """The old result (triangulate, no recording) and a user's file; the new run adds recording.rrd. Killed
    before each file's rename into the staging folder and each step of the swap: the folder is the old
    result or the new one, with the notes; the next reconstruct leaves no temporary behind."""
    from batgraph.pipeline import OUTPUT_FILES, reconstruct

    script = tmp_path / "kill.py"
    script.write_text(RECONSTRUCT_KILL)
    base = tmp_path / "base"
    reconstruct(small_session, base, ["triangulate"], viewer="none")
    (base / "notes.txt").write_text("the user's notes")
    old = _snapshot(base)
    new_names = {*OUTPUT_FILES} - {"validation.csv", "rig.toml", *NAMES} | {"notes.txt"}  # rig.toml: refined rigs
    outcomes = []
    for k in range(1, 40):
        out = tmp_path / f"out{k}"
        subprocess.run(["cp", "-a", str(base), str(out)], check=True)
        rc = subprocess.run([sys.executable, str(script), str(small_session), str(out), str(k)], timeout=300,
                            capture_output=True).returncode
        if out.exists():
            now = _snapshot(out)
            assert now == old or set(now) == new_names, (k, sorted(now))
            outcomes.append("old" if now == old else "new")
        else:  # killed between the two renames of the swap: only .out.batgraph-new and -old exist
            assert _hidden_siblings(out) == [f".{out.name}{atomic.NEW_TAG}", f".{out.name}{atomic.OLD_TAG}"]
            outcomes.append("between")
        if rc == 0:
            break
    else:
        pytest.fail("reconstruct never completed")
    assert outcomes[0] == "old" and outcomes[-1] == "new" and "between" in outcomes
    # the next run on a folder a kill left half swapped and with a stale temporary
    k_between = outcomes.index("between") + 1
    out = tmp_path / f"out{k_between}"
    reconstruct(small_session, out, ["triangulate"], viewer="none")
    assert set(_snapshot(out)) == {*OUTPUT_FILES} - {"validation.csv", "recording.rrd", "rig.toml", *NAMES} | {
        "notes.txt"}
    assert (out / "notes.txt").read_text() == "the user's notes"
    assert _hidden_siblings(out) == [] and _hidden_inside(out) == []
    for k in range(1, len(outcomes)):  # every other killed folder: the next run's recovery alone
        atomic.recover_folder(tmp_path / f"out{k}", OUTPUT_FILES)
        assert _hidden_siblings(tmp_path / f"out{k}") == []
        assert not any(".recording." in n for n in _hidden_inside(tmp_path / f"out{k}"))


def test_validation_csv_belongs_to_the_result(small_session, tmp_path, monkeypatch):
    """A failing writer (report) leaves the previous result, validation.csv included, untouched."""
    from batgraph import pipeline

    out = tmp_path / "out"
    out.mkdir()
    (out / "validation.csv").write_text("a previous run's validation")
    (out / "calibration.toml").write_text("written by calibrate")
    import batgraph.report

    def boom(*a, **kw):
        raise RuntimeError("report writer failed")

    monkeypatch.setattr(batgraph.report, "write_report", boom)
    with pytest.raises(RuntimeError):
        pipeline.reconstruct(small_session, out, ["triangulate"], viewer="none")
    assert _snapshot(out).keys() == {"validation.csv", "calibration.toml"}
    monkeypatch.undo()
    pipeline.reconstruct(small_session, out, ["triangulate"], viewer="none")
    assert not (out / "validation.csv").exists()  # not this result's
    assert (out / "calibration.toml").read_text() == "written by calibrate"


def test_a_failure_after_the_estimators_leaves_the_old_result(small_session, tmp_path, monkeypatch):
    """A summary that fails after the estimators ran leaves the previous result as it was and no staging folder
    behind."""
    from batgraph import pipeline, summary

    out = tmp_path / "out"
    pipeline.reconstruct(small_session, out, ["triangulate"], viewer="none")
    old = _snapshot(out)

    def boom(*a, **kw):
        raise RuntimeError("summary failed")

    monkeypatch.setattr(summary, "summarize", boom)
    with pytest.raises(RuntimeError, match="summary failed"):
        pipeline.reconstruct(small_session, out, ["smoother", "triangulate"], viewer="none")
    assert _snapshot(out) == old
    assert _hidden_siblings(out) == [] and _hidden_inside(out) == []


def test_write_outputs_writes_a_result_of_run_methods(small_session, tmp_path):
    """The library's route: run_methods, then write_outputs into a folder (the same files as reconstruct's)."""
    from batgraph.pipeline import OUTPUT_FILES, run_methods, write_outputs
    from batgraph.result import Options
    from batgraph.session import read_session

    result = run_methods(read_session(small_session), ["triangulate"], Options(progress=False))
    files = write_outputs(result, tmp_path / "out", viewer="none")
    assert {p.name for p in files} == {*OUTPUT_FILES} - {"validation.csv", "recording.rrd", "rig.toml", *NAMES}
    assert all(p.is_file() for p in files) and _hidden_siblings(tmp_path / "out") == []
    assert len((tmp_path / "out" / "trajectories.csv").read_text().splitlines()) == len(result.trajectories) + 1


def test_batch_sessions_are_swapped_each(small_session, tmp_path):
    """Each session folder of a batch is written the same way (a user file in one survives)."""
    from batgraph.batch import reconstruct_many

    b = tmp_path / "b"
    subprocess.run(["cp", "-a", str(small_session), str(b)], check=True)
    root = tmp_path / "results"
    (root / "b").mkdir(parents=True)
    (root / "b" / "notes.txt").write_text("keep me")
    (root / ".b.batgraph-tmp-999999999-0abc").mkdir()  # a killed run's leftover (no such process)
    items = reconstruct_many([small_session, b], root, ["triangulate"], viewer="none", n_workers=1, progress=False)
    assert [it.status for it in items] == ["ok", "ok"], [it.message for it in items]
    assert (root / "b" / "notes.txt").read_text() == "keep me" and (root / "b" / "trajectories.csv").exists()
    assert sorted(p.name for p in root.iterdir()) == ["b", "batch_summary.csv", "s"]


# ----- what reconstruct prints ------------------------------------------------------------------
def test_redirected_output_has_no_progress_bars_and_quiet_says_where(small_session, tmp_path):
    """Into a pipe or log file: no carriage returns or cursor codes (bars are for terminals); --quiet prints
    one line, on stdout, naming the output folder."""
    exe = [sys.executable, "-m", "batgraph.cli", "reconstruct", str(small_session), "--methods", "triangulate",
           "--viewer", "none"]
    out = tmp_path / "o"
    loud = subprocess.run([*exe, "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert loud.returncode == 0, loud.stderr
    for text in (loud.stdout, loud.stderr):
        assert "\r" not in text and "\x1b[" not in text
    quiet = subprocess.run([*exe, "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0 and "\r" not in quiet.stderr
    assert len(quiet.stdout.splitlines()) == 1 and str(out) in quiet.stdout


# ----- a full disk ------------------------------------------------------------------------------
STEPS = ("trajectories.csv", "reprojection.csv", "summary.json", "report.html", "trajectories.c3d",
         "trajectories.trc", "recording.rrd", "validation.csv")


def test_a_full_disk_at_each_output_step_is_one_line_and_keeps_the_previous_result(small_session, tmp_path,
                                                                                   monkeypatch, capsys):
    """Each output file's write fails with ENOSPC in turn (the rename of its finished temporary, in this process
    or in the child that writes it): exit 2, one line naming that file in the output folder (not the staging
    folder) and saying the previous result is unchanged; the folder is byte for byte the previous result."""
    import errno

    from batgraph.cli import main
    from batgraph.pipeline import OUTPUT_FILES

    assert set(STEPS) == set(OUTPUT_FILES) - {"rig.toml", *NAMES}  # written by the same steps, only for a refined
    # rig and for unlabelled detections
    base = tmp_path / "base"
    argv = ["reconstruct", str(small_session), "--methods", "triangulate", "--validate", "--viewer", "save",
            "--quiet"]
    assert main([*argv, "--out", str(base)]) == 0
    (base / "notes.txt").write_text("the user's notes")
    old = _snapshot(base)
    real_replace = os.replace
    for step in STEPS:
        def full(src, dst, *a, step=step, **kw):
            if Path(dst).name == step and Path(src).name.startswith("."):  # a finished temporary of that file
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(src))
            return real_replace(src, dst, *a, **kw)

        out = tmp_path / f"out_{step}"
        subprocess.run(["cp", "-a", str(base), str(out)], check=True)
        capsys.readouterr()
        monkeypatch.setattr(os, "replace", full)
        code = main([*argv, "--out", str(out)])
        monkeypatch.setattr(os, "replace", real_replace)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, (step, err)
        assert err[0] == (f"batgraph: error: {out / step}: no space left on the device; {out} still holds the "
                          "previous result, unchanged (free some space and run again)"), err
        assert _snapshot(out) == old, step
        assert _hidden_siblings(out) == [] and _hidden_inside(out) == []


def _mount_tmpfs(folder: Path, kib: int) -> bool:
    folder.mkdir(exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(folder)],
                          capture_output=True).returncode == 0


def test_a_really_full_disk_at_any_point_of_writing(tmp_path):
    """A small tmpfs holding the previous result of the bundled sample and room for 5 % .. 80 % of a new one: the
    run fails wherever the disk fills up (the report, the tables in their child processes, the recording, whose
    writer, Rerun, says only "File-writer thread shut down prematurely"): exit 2, one line on stderr naming the
    folder, no traceback, no Rust log lines, the previous result unchanged, no temporary left. With room enough
    it succeeds. Needs permission to mount a tmpfs (root); skipped otherwise."""
    sample = Path(__file__).resolve().parents[1] / "data" / "samples" / "flight_5cam"
    exe = [sys.executable, "-m", "batgraph", "reconstruct", str(sample), "--methods", "triangulate", "--quiet"]
    base = tmp_path / "base"
    assert subprocess.run([*exe, "--out", str(base)], capture_output=True, timeout=300).returncode == 0
    size_kib = sum(p.stat().st_size for p in base.iterdir()) // 1024 + 64
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, 4 * size_kib):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    subprocess.run(["umount", str(disk)], check=True)
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    for room in (0.05, 0.2, 0.4, 0.6, 0.8, 2.0):
        assert _mount_tmpfs(disk, int(size_kib * (1 + room)))
        try:
            out = disk / "out"
            subprocess.run(["cp", "-a", str(base), str(out)], check=True)
            old = _snapshot(out)
            r = subprocess.run([*exe, "--out", str(out)], capture_output=True, text=True, timeout=300, env=env)
            if room == 2.0:
                assert r.returncode == 0, r.stderr
                continue
            assert r.returncode == 2, (room, r.stderr)
            lines = r.stderr.splitlines()
            assert len(lines) == 1 and "no space left on the device" in lines[0], (room, r.stderr)
            assert f"{out} still holds the previous result, unchanged" in lines[0]
            assert _snapshot(out) == old, room
            assert sorted(p.name for p in disk.iterdir()) == ["out"] and _hidden_inside(out) == []
        finally:
            subprocess.run(["umount", str(disk)], check=True)


def test_no_writer_starts_on_a_full_disk(tmp_path):
    """On a file system with less than atomic.FULL_BYTES free, atomic_path raises ENOSPC naming the file before
    the writer runs: Rerun's file sink, started on a full disk, could wait for ever for its dead writer thread
    (the bundled sample's reconstruct hung so in 1 of 10 runs with 5 % room). Needs a tmpfs mount (root)."""
    import errno

    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, 2048):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        (disk / "filler").write_bytes(b"x" * (2048 * 1024 - atomic.FULL_BYTES // 2))
        assert atomic.disk_full(disk)
        ran = []
        with pytest.raises(OSError) as e, atomic.atomic_path(disk / "recording.rrd") as tmp:
            ran.append(tmp)
        assert e.value.errno == errno.ENOSPC and e.value.filename == str(disk / "recording.rrd")
        assert ran == [] and sorted(p.name for p in disk.iterdir()) == ["filler"]
        (disk / "filler").unlink()
        assert not atomic.disk_full(disk)
        atomic.write_text(disk / "small.txt", "fits")
        assert (disk / "small.txt").read_text() == "fits"
    finally:
        subprocess.run(["umount", str(disk)], check=True)
