"""The calibration issue's target, end to end through the command line and real files.

A rig whose written calibration is wrong (cameras 2-5 turned 1 deg and shifted 10 mm, as
`simulate --calib-rot-deg 1 --calib-trans-mm 10` does) films a flight and, as easyWand / Argus users
do, a 0.5 m wand (`simulate wand`, same seed: same rig, same error). `calibrate` on the wand recording
writes a calibration.toml with pose covariances; `reconstruct --calibration` uses it for the flight.
The smoother's RMSE on observed points must come within 10 % of its RMSE with the true calibration.
"""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from batgraph.session import read_session, write_session

ROOT = Path(__file__).resolve().parents[1]
ERROR_ARGS = ["--calib-rot-deg", "1", "--calib-trans-mm", "10", "--seed", "2"]


def run(*args):
    script, *rest = args
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / f"{script}.py"), *map(str, rest)],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    return r


def observed_rmse_m(out: Path, method: str = "smoother") -> float:
    return json.loads((out / "summary.json").read_text())["methods"][method]["truth"]["rmse_m"]["observed"]


@pytest.fixture(scope="module")
def rmse(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("target")
    flight, wand, cal = tmp / "flight", tmp / "wand", tmp / "wand_calibration.toml"
    run("simulate", "flight", flight, "--cameras", "5", "--markers", "14", *ERROR_ARGS)
    # like for like: the wand rig has pose covariances, with which the smoother leaves [markers] rigid out
    write_session(dataclasses.replace(read_session(flight), rigid=[]), flight)
    run("simulate", "wand", wand, "--frames", "600", *ERROR_ARGS)
    before = {p.name: p.read_bytes() for p in flight.iterdir() if p.is_file()}
    run("calibrate", wand, "--out", cal, "--quiet")
    out = {}
    for label, calibration in (("true", flight / "calibration_true.toml"), ("wand", cal)):
        run("reconstruct", flight, "--calibration", calibration, "--methods", "smoother", "--viewer", "none",
            "--out", tmp / label, "--quiet")
        out[label] = observed_rmse_m(tmp / label)
    assert {p.name: p.read_bytes() for p in flight.iterdir() if p.is_file()} == before  # flight untouched
    return out


def test_wand_calibration_brings_the_smoother_within_10_percent_of_the_true_rig(rmse):
    """Measured (14 markers, seed 2): true calibration 1.722 mm, after the wand calibration 1.780 mm (+3.3 %);
    with the written (wrong) calibration 104 mm. 24 markers, seeds 1-3: see the closing note / README."""
    assert rmse["wand"] < 1.10 * rmse["true"]
