"""The method registry (batgraph.methods) and the functions that run the methods (batgraph.runner); the
command line's checks of ``--methods`` and its progress bars."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_tiny_session

from batgraph import methods, runner
from batgraph.cli import main
from batgraph.errors import InputError

ROOT = Path(__file__).parents[1]


def test_every_method_has_a_run_function_held_as_a_function():
    """Each registered method runs through a function (not a name looked up at run time); the smoother and filter
    take Options.solver themselves (batgraph.solver: their own solver, or GTSAM's graph)."""
    assert set(runner.RUN) == set(methods.ALL_METHODS)
    assert all(callable(f) for f in runner.RUN.values())
    assert runner.run_function("ekf", "gtsam") is runner.RUN["ekf"]
    assert runner.run_function("smoother", "gtsam") is runner.RUN["smoother"]


@pytest.mark.parametrize("typed, meant", [("smootherr", "smoother"), ("Filter", "filter"), ("triangulation",
                                                                                           "triangulate")])
def test_a_misspelt_method_gets_did_you_mean(typed, meant):
    with pytest.raises(InputError, match=f"unknown method '{typed}'; did you mean {meant}\\?"):
        methods.parse(f"smoother,{typed}")


def test_a_method_like_none_lists_the_choices_only():
    with pytest.raises(InputError) as e:
        methods.parse("kalman")
    assert "did you mean" not in str(e.value) and "choose from smoother, filter, ekf, ukf, triangulate" in str(e.value)


def test_the_command_says_did_you_mean_in_one_line(tmp_path, capsys):
    assert main(["reconstruct", str(ROOT / "data" / "samples" / "ear_2cam"), "--out", str(tmp_path / "o"),
                 "--methods", "smootherr"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "did you mean smoother?" in err[0]


def test_validate_writes_no_progress_bar_into_a_log_file(tmp_path):
    """`batgraph validate` with stderr redirected to a file (not a terminal): no progress bar, no carriage
    return, in the log."""
    folder = write_tiny_session(tmp_path / "s", n_cams=3, n_frames=12, n_markers=2)
    log = tmp_path / "validate.log"
    with open(log, "w") as err:
        done = subprocess.run([sys.executable, "-m", "batgraph", "validate", str(folder), "--methods",
                               "smoother,triangulate", "--workers", "1", "--viewer", "none"],
                              stdout=subprocess.DEVNULL, stderr=err, timeout=600)
    text = log.read_text()
    assert done.returncode == 0, text
    assert "\r" not in text and "it/s" not in text and "validation folds" not in text, text
