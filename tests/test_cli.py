"""End to end through the real command line: the contract's commands, files, exit codes and messages."""

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

import batgraph
from batgraph.evaluate import REPROJ_COLUMNS, TRAJ_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "samples" / "flight_5cam"


def run(*args, cwd=ROOT):
    """`python scripts/NAME.py ...` (the scripts are the same entry as the `batgraph` console script)."""
    script, *rest = args
    return subprocess.run([sys.executable, str(ROOT / "scripts" / f"{script}.py"), *map(str, rest)],
                          capture_output=True, text=True, cwd=cwd, timeout=600)


def test_reconstruct_sample_with_triangulation_writes_the_contract_files(tmp_path):
    out = tmp_path / "out"
    before = {p.name: p.read_bytes() for p in SAMPLE.iterdir() if p.is_file()}
    r = run("reconstruct", SAMPLE, "--methods", "triangulate", "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    for name in ("trajectories.csv", "reprojection.csv", "summary.json", "report.html", "recording.rrd",
                 "trajectories.c3d", "trajectories.trc"):
        assert (out / name).is_file(), name
    traj = pd.read_csv(out / "trajectories.csv")
    assert list(traj.columns) == TRAJ_COLUMNS
    assert len(traj) == 160 * 24  # every frame x marker of the sample
    assert set(traj["status"]) == {"observed", "single_view", "unobserved"}
    assert list(pd.read_csv(out / "reprojection.csv").columns) == REPROJ_COLUMNS
    summary = json.loads((out / "summary.json").read_text())
    rmse = summary["methods"]["triangulate"]["truth"]["rmse_m"]
    assert 0.0005 < rmse["observed"] < 0.006  # measured 2.92 mm at 1 px noise
    assert {p.name: p.read_bytes() for p in SAMPLE.iterdir() if p.is_file()} == before  # inputs untouched
    assert not list(out.glob(".*"))  # no temporary left behind by the atomic writes


@pytest.mark.parametrize("breakage, words", [
    (lambda d: (d / "observations.csv").write_text("frame,camera,marker,u,v\n0,cam1,m,abc,1\n"),
     ["observations.csv", "line 2", "u"]),
    (lambda d: (d / "calibration.toml").unlink(), ["calibration.toml", "not found"]),
    (lambda d: (d / "session.toml").write_text('[session]\nname = "x"\nfps = -1\n'), ["session.toml", "fps"]),
])
def test_bad_input_is_one_line_exit_2_and_no_traceback(tmp_path, breakage, words):
    bad = tmp_path / "bad"
    shutil.copytree(SAMPLE, bad)
    breakage(bad)
    r = run("reconstruct", bad, "--methods", "triangulate", "--quiet")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("batgraph: error:")
    for w in words:
        assert w in lines[0]
    assert not (bad / "out").exists()


def test_bad_calibration_option_is_one_line_exit_2(tmp_path):
    """`reconstruct --calibration FILE`: a missing file, or one without the session's cameras, is named."""
    other = tmp_path / "other.toml"
    other.write_text((SAMPLE / "calibration.toml").read_text().replace('name = "cam1"', 'name = "camX"'))
    for cal, words in ((tmp_path / "missing.toml", ["missing.toml", "not found"]),
                       (other, ["other.toml", "'cam1'", "observations.csv"])):
        r = run("reconstruct", SAMPLE, "--calibration", cal, "--methods", "triangulate", "--out", tmp_path / "o",
                "--quiet")
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
        assert all(w in r.stderr for w in words), r.stderr
    assert not (tmp_path / "o").exists()


def test_simulate_then_export_dltdv_and_console_script(tmp_path):
    r = run("simulate", "ear", tmp_path / "ear", "--frames", "20", "--seed", "3")
    assert r.returncode == 0, r.stderr
    r = run("reconstruct", tmp_path / "ear", "--methods", "triangulate,ekf", "--viewer", "none", "--quiet")
    assert r.returncode == 0, r.stderr
    batgraph = Path(sys.executable).parent / "batgraph"
    r = subprocess.run([str(batgraph), "export", "dltdv", str(tmp_path / "ear" / "out"), "--method", "ekf"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    xyz = pd.read_csv(tmp_path / "ear" / "out" / "ekf_xyzpts.csv")
    assert xyz.shape == (20, 3 * 9) and list(xyz.columns[:3]) == ["head1_X", "head1_Y", "head1_Z"]
    r = run("simulate", "ear", tmp_path / "ear")  # exists, not empty
    assert r.returncode == 2 and "--force" in r.stderr


def test_command_line_runs_blas_on_one_thread_unless_the_user_chose():
    """batgraph.cli sets OPENBLAS_NUM_THREADS=1 before numpy loads (batgraph._startup: its own work uses the
    cores; OpenBLAS's idle workers nearly doubled the CPU time on 16 cores), and leaves a user's setting alone."""
    import os

    code = ("import batgraph.cli, numpy, threadpoolctl; "
            "print(max(i['num_threads'] for i in threadpoolctl.threadpool_info() if i['internal_api'] == 'openblas'))")
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    plain = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert plain.stdout.strip() == "1"
    if len(os.sched_getaffinity(0)) < 2:  # OpenBLAS holds itself to the processors it may use
        pytest.skip("one processor: a user's 2 threads read as 1")
    chosen = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_NUM_THREADS": "2"}, capture_output=True,
                            text=True, check=True)
    assert chosen.stdout.strip() == "2"


def test_the_command_line_loads_no_optional_heavy_library():
    """Importing batgraph.cli (every subcommand's module, imported at the top) loads none of GTSAM, pycolmap, Rerun,
    Dask or matplotlib: each is imported where it is used (measured: `batgraph --help` 0.75 s on 2 cores, the
    reconstruct command's imports 0.05 s more than its own modules'). `--help` works."""
    code = ("import sys, batgraph.cli; "
            "print(sorted(m for m in ('gtsam', 'pycolmap', 'rerun', 'dask', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    help_ = subprocess.run([sys.executable, "-m", "batgraph.cli", "--help"], capture_output=True, text=True)
    assert help_.returncode == 0 and "reconstruct" in help_.stdout


def test_imports_of_batgraph_modules_sit_at_the_top():
    """The import graph is what the code's top lines say: an import of a batgraph module inside a function is only
    there to keep GTSAM lazy (batgraph.solver.reference)."""
    inside, paths = [], sorted(Path(batgraph.__file__).parent.rglob("*.py"))
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                inside += [(path.name, sub.module) for sub in ast.walk(node) if isinstance(sub, ast.ImportFrom)
                           and (sub.level > 0 or (sub.module or "").startswith("batgraph"))]
    assert len(paths) > 50 and all(module == "reference" for _, module in inside), inside


def test_a_run_that_will_compile_says_so_first(tmp_path, monkeypatch, capsys):
    """One stderr line before a run that compiles the kernels (the first after an install takes 15-40 s on
    2 cores), also with --quiet (a silent minute looks hung), none when they are cached. kernels.needs_compiling()
    is True against an empty numba
    cache (a fresh process with NUMBA_CACHE_DIR there: nothing is compiled by asking) and False once the
    kernels have run in this process (compiled and cached, or loaded)."""
    from batgraph import cli, warm
    from batgraph.solver import kernels
    ask = "from batgraph.solver import kernels; print(kernels.needs_compiling())"
    fresh = subprocess.run([sys.executable, "-c", ask], capture_output=True, text=True, timeout=120,
                           env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")})
    assert fresh.stdout.strip() == "True", fresh.stderr
    warm.compile_all()
    assert kernels.needs_compiling() is False
    for compiling, quiet in ((True, False), (True, True), (False, False)):
        monkeypatch.setattr(kernels, "needs_compiling", lambda c=compiling: c)
        out = tmp_path / f"out{compiling}{quiet}"
        assert cli.main(["reconstruct", str(SAMPLE), "--methods", "triangulate", "--viewer", "none", "--out", str(out),
                         *(["--quiet"] if quiet else [])]) == 0
        said = "compiling its inner loops" in capsys.readouterr().err
        assert said == compiling


@pytest.mark.slow
def test_the_first_run_after_an_install_says_so_and_leaks_no_compiler_warning(tmp_path):
    """A real first run: an empty numba cache (NUMBA_CACHE_DIR), --quiet. stderr holds the one-line notice and
    nothing of numba's (it warned NumbaPerformanceWarning while compiling the smoother's sweeps), and no Rust
    log lines of Rerun's; stdout the one line saying where the results went."""
    session = tmp_path / "s"
    assert run("simulate", "flight", session, "--cameras", "3", "--frames", "30", "--seed", "2").returncode == 0
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    r = subprocess.run([sys.executable, "-m", "batgraph", "reconstruct", str(session), "--methods", "smoother",
                        "--out", str(tmp_path / "out"), "--quiet"], capture_output=True, text=True, timeout=900,
                       env={**env, "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache"), "PYTHONWARNINGS": "default"})
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert lines[0].startswith("batgraph: compiling its inner loops"), r.stderr
    assert all(line.startswith("batgraph: warning: ") for line in lines[1:]), r.stderr  # batgraph's own only
    assert "Numba" not in r.stderr and "Warning:" not in r.stderr
    assert len(r.stdout.splitlines()) == 1 and str(tmp_path / "out") in r.stdout


def test_a_result_folder_given_as_a_session_says_what_it_is(tmp_path):
    """reconstruct / validate / calibrate pointed at a reconstruct result folder (trajectories.csv, summary.json,
    no session.toml): one line saying it is a result, what a session holds and what to do with a result; exit 2,
    nothing written. A session folder that only lacks session.toml still gets the file's own message."""
    out = tmp_path / "result"
    r = run("reconstruct", SAMPLE, "--methods", "triangulate", "--viewer", "none", "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    before = sorted(p.name for p in out.iterdir())
    for command in ("reconstruct", "validate", "calibrate"):
        r = run(command, out, "--quiet")
        assert r.returncode == 2 and "Traceback" not in r.stderr, (command, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1, (command, r.stderr)
        for words in ("a reconstruct result folder", "no session.toml", "session folder it was made from",
                      f"batgraph export c3d|trc|csv|dltdv {out}"):
            assert words in lines[0], (command, lines[0])
    assert sorted(p.name for p in out.iterdir()) == before
    bare = tmp_path / "bare"
    shutil.copytree(SAMPLE, bare)
    (bare / "session.toml").unlink()
    r = run("reconstruct", bare, "--quiet")
    assert r.returncode == 2 and "session.toml" in r.stderr and "result folder" not in r.stderr
