"""Self-checks before any estimator, and what they measure: per-camera pixel noise, units, impossible
geometry (exit 2 naming the camera), warnings in summary.json, and sessions without bat physics."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomli_w

from batgraph import checks
from batgraph.camera import Rig
from batgraph.cli import main
from batgraph.errors import InputError
from batgraph.measurement import ideal_observations
from batgraph.pixel_noise import estimate_pixel_sigma, sample_markers
from batgraph.session import dense_observations, read_session
from batgraph.triangulate import dlt_points

ROOT = Path(__file__).resolve().parents[1]
FLIGHT = ROOT / "data" / "samples" / "flight_5cam"
EAR = ROOT / "data" / "samples" / "ear_2cam"


def _copy(src: Path, dst: Path, *, drop_noise: bool = True, drop_physics: bool = False) -> Path:
    """A copy of a bundled sample; optionally without [noise] pixel_sigma_px / the [motion] physics."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("out"))
    text = (dst / "session.toml").read_text()
    if drop_noise:
        text = re.sub(r"\[noise\]\npixel_sigma_px = [0-9.]+\n", "", text)
    if drop_physics:
        text = re.sub(r"(flight_speed_mps|span_m|flap_hz|flap_angle_deg) = .*\n", "", text)
    (dst / "session.toml").write_text(text)
    return dst


def _sigma(folder: Path) -> dict[str, float]:
    s = read_session(folder)
    d = dense_observations(s)
    sigma, _ = estimate_pixel_sigma(s.rig, ideal_observations(s.rig, d, 1.0))
    return dict(zip(s.rig.names, sigma, strict=True))


def _reconstruct(folder: Path, out: Path, *extra: str) -> int:
    return main(["reconstruct", str(folder), "--out", str(out), "--viewer", "none", "--quiet", *extra])


def test_pixel_noise_is_measured_per_camera(tmp_path):
    """The flight sample has 1 px noise; cam3 gets 2.83 px more (3 px in all). Measured per camera:
    0.98 / 1.00 / 2.9x / 1.06 / 0.99 px; bounds 12 % (each camera has ~2000 observations, the
    statistical error of a variance from n chi-square-2 samples is 1/sqrt(n) ~ 2 % in sigma)."""
    folder = _copy(FLIGHT, tmp_path / "s")
    obs = pd.read_csv(folder / "observations.csv")
    rng = np.random.default_rng(0)
    sel = obs["camera"] == "cam3"
    obs.loc[sel, ["u", "v"]] += np.sqrt(3.0**2 - 1.0) * rng.standard_normal((int(sel.sum()), 2))
    obs.to_csv(folder / "observations.csv", index=False)
    sigma = _sigma(folder)
    for cam, want in {"cam1": 1, "cam2": 1, "cam3": 3, "cam4": 1, "cam5": 1}.items():
        assert sigma[cam] == pytest.approx(want, rel=0.12), (cam, sigma)


def test_a_large_session_is_measured_on_a_sample_of_markers_every_camera_keeps():
    """Above max_points (frame, marker) points the noise is measured on markers spread over the list, topped up
    with a camera's own markers where the spread leaves it too few observations; the sample's sigmas are the
    whole session's to the statistical error (flight sample, 10 of 24 markers, >= 500 observations a camera: within
    2.3 %, that sample's error in sigma ~2 %)."""
    seen = np.zeros((3, 100, 40), bool)
    seen[:2] = True  # cameras 0 and 1 see every marker; camera 2 only markers 37 and 38
    seen[2, :, 37:39] = True
    assert list(sample_markers(seen, max_points=4000)) == list(range(40))  # small enough: all
    spread = [0, 10, 20, 29, 39]  # 500 // 100 = 5 markers spread evenly
    assert list(sample_markers(seen, max_points=500, min_observations=100)) == sorted(spread + [37])
    assert list(sample_markers(seen, max_points=500, min_observations=150)) == sorted(spread + [37, 38])
    assert list(sample_markers(seen, max_points=500, min_observations=250)) == sorted(spread + [37, 38])  # all it has
    s = read_session(FLIGHT)
    iu = ideal_observations(s.rig, dense_observations(s), 1.0)
    full, info_full = estimate_pixel_sigma(s.rig, iu)
    part, info = estimate_pixel_sigma(s.rig, iu, max_points=10 * iu.seen.shape[1], min_observations=500)
    assert len(info_full["markers"]) == 24 and len(info["markers"]) == 10
    assert info["xyz_m"].shape[1] == 10
    np.testing.assert_allclose(part, full, rtol=0.04)


def test_pixel_noise_with_two_cameras_counts_the_leverage(tmp_path):
    """Two cameras: a triangulated point takes 3 of each point's 4 degrees of freedom, so raw reprojection
    errors understate the noise ~2x; with the leverage correction the ear sample's 1 px comes back
    (measured 1.008 / 1.008 px; bound 10 %)."""
    sigma = _sigma(_copy(EAR, tmp_path / "s"))
    assert all(s == pytest.approx(1.0, rel=0.10) for s in sigma.values()), sigma


def test_preflight_hands_on_the_observations_at_the_noise_it_chose(tmp_path):
    """The estimators get preflight's undistortion at the measured noise (not 1 px): the same as undistorting
    again."""
    s = read_session(_copy(FLIGHT, tmp_path / "s"))
    d = dense_observations(s)
    pre = checks.preflight(s, d)
    assert np.all(np.abs(pre.sigma_px - 1.0) > 1e-3), pre.sigma_px
    again = ideal_observations(s.rig, d, pre.sigma_px)
    assert np.array_equal(pre.ideal.uv_px, again.uv_px, equal_nan=True)
    np.testing.assert_allclose(pre.ideal.cov_px2, again.cov_px2, rtol=1e-13, atol=0)

    # preflight's linear triangulation comes with them, for the same rig only, and equals one made afresh
    assert again.linear_xyz is None and pre.ideal.linear_xyz[0] is s.rig
    fresh = dlt_points(s.rig, again)
    assert np.array_equal(dlt_points(s.rig, pre.ideal), fresh, equal_nan=True)
    kept = dlt_points(s.rig, pre.ideal)
    kept[:] = 0.0  # a copy each time: the kept one cannot be changed through it
    assert np.array_equal(dlt_points(s.rig, pre.ideal), fresh, equal_nan=True)
    moved = dataclasses.replace(s.rig[0], tvec=s.rig[0].tvec + 0.5)
    other = Rig([moved, *list(s.rig)[1:]])
    assert not np.array_equal(dlt_points(other, pre.ideal), fresh, equal_nan=True)  # another rig: computed


def test_reconstruct_uses_and_reports_the_measured_noise(tmp_path):
    folder = _copy(FLIGHT, tmp_path / "s")
    assert _reconstruct(folder, tmp_path / "o", "--methods", "triangulate") == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["pixel_noise"]["source"] == "estimated"
    used = summary["pixel_sigma_px"]
    assert set(used) == {f"cam{i}" for i in range(1, 6)}
    assert all(0.9 < v < 1.1 for v in used.values()), used
    assert summary["warnings"] == []
    assert all(c["behind_fraction"] == 0 for c in summary["checks"].values() if "behind_fraction" in c)


def test_camera_with_inverted_pose_is_an_input_error(tmp_path, capsys):
    """cam2's pose written world_from_camera (a classic slip): its points land behind it -> exit 2, one
    line naming cam2 and the likely causes; nothing written."""
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False)
    cal = tomllib.loads((folder / "calibration.toml").read_text())
    import cv2

    R = cv2.Rodrigues(np.array(cal["cam_1"]["rotation"]))[0]
    t = np.array(cal["cam_1"]["translation"])
    cal["cam_1"]["rotation"] = cv2.Rodrigues(R.T)[0].ravel().tolist()
    cal["cam_1"]["translation"] = (-R.T @ t).tolist()
    (folder / "calibration.toml").write_text(tomli_w.dumps(cal))
    assert _reconstruct(folder, tmp_path / "o") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera cam2" in err[0] and "behind it" in err[0] and "world_from_camera" in err[0]
    assert not (tmp_path / "o").exists()


def test_millimetre_calibration_warns_and_units_key_fixes_it(tmp_path):
    """The flight rig with translations in mm: read as metres the cameras are ~1200-1500 m from the points
    -> a warning naming each camera and 'millimetres'. With [metadata] units = "mm" the triangulation
    equals the metre rig's to 1e-9 m and there is no warning."""
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False)
    cal = tomllib.loads((folder / "calibration.toml").read_text())
    for key, tab in cal.items():
        if key.startswith("cam_"):
            tab["translation"] = [1000 * x for x in tab["translation"]]
    (folder / "calibration.toml").write_text(tomli_w.dumps(cal))
    assert _reconstruct(folder, tmp_path / "mm_as_m", "--methods", "triangulate") == 0
    warnings = json.loads((tmp_path / "mm_as_m" / "summary.json").read_text())["warnings"]
    assert sum("millimetres read as metres" in w for w in warnings) == 5, warnings
    assert any("camera cam1 is" in w for w in warnings)
    report = (tmp_path / "mm_as_m" / "report.html").read_text()
    assert "<b>Warnings</b>" in report and "millimetres read as metres" in report  # at the top
    assert report.index("<b>Warnings</b>") < report.index("Session <b>")

    cal["metadata"] = {"units": "mm"}
    (folder / "calibration.toml").write_text(tomli_w.dumps(cal))
    assert _reconstruct(folder, tmp_path / "mm", "--methods", "triangulate") == 0
    assert _reconstruct(FLIGHT, tmp_path / "m", "--methods", "triangulate") == 0
    a = pd.read_csv(tmp_path / "mm" / "trajectories.csv")
    b = pd.read_csv(tmp_path / "m" / "trajectories.csv")
    np.testing.assert_allclose(a[["x", "y", "z"]].to_numpy(), b[["x", "y", "z"]].to_numpy(), atol=1e-9)
    assert json.loads((tmp_path / "mm" / "summary.json").read_text())["warnings"] == []


def test_a_miscalibrated_camera_is_named(tmp_path):
    """cam4's observations shifted by 30 px (a wrong principal point): its measured noise is far above the
    others' -> a warning naming cam4 (measured 16x the others' median); no other camera is named."""
    folder = _copy(FLIGHT, tmp_path / "s")
    obs = pd.read_csv(folder / "observations.csv")
    obs.loc[obs["camera"] == "cam4", "u"] += 30.0
    obs.to_csv(folder / "observations.csv", index=False)
    s = read_session(folder)
    pre = checks.preflight(s, dense_observations(s))
    named = [w for w in pre.warnings if "pixel noise" in w]
    assert len(named) == 1 and named[0].startswith("camera cam4:"), pre.warnings


def test_stated_noise_far_below_the_residuals_warns(tmp_path):
    """session.toml says 0.1 px on a 1 px session: every camera's residuals are ~10x that -> a warning each."""
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False)
    (folder / "session.toml").write_text((folder / "session.toml").read_text().replace(
        "pixel_sigma_px = 1.0", "pixel_sigma_px = 0.1"))
    s = read_session(folder)
    pre = checks.preflight(s, dense_observations(s))
    assert sum("the session's pixel_sigma_px 0.1 px" in w for w in pre.warnings) == 5, pre.warnings


def test_no_physics_measures_the_motion_noise_from_the_track(tmp_path):
    """A session.toml with no [motion] physics (imported data is not a bat): the filter's q and the random
    walk's sigma_m come from the triangulated track. On the flight sample q = 21 (the paper's physics:
    8.7) and the filter's RMSE on observed points 2.31 mm (2.42 with the physics); bound 3 mm. The
    rewritten session.toml carries no physics."""
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False, drop_physics=True)
    assert _reconstruct(folder, tmp_path / "o", "--methods", "filter,ekf") == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    track = summary["checks"]["motion_from_track"]
    assert 3 < track["causal_accel_psd_m2_s3"] < 100 and 0.003 < track["sigma_m"] < 0.05
    for method in ("filter", "ekf"):
        assert summary["methods"][method]["truth"]["rmse_m"]["observed"] < 0.003
    s = read_session(folder)
    assert not s.motion.has_physics


def test_calibration_metadata_is_validated(tmp_path):
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False)
    cal = tomllib.loads((folder / "calibration.toml").read_text())
    cal["metadata"] = {"units": "feet"}
    (folder / "calibration.toml").write_text(tomli_w.dumps(cal))
    with pytest.raises(InputError, match=r"\[metadata\] units: 'feet' is not one of m, cm, mm"):
        read_session(folder)
    cal["metadata"] = {"world_mirror": [1, 1, 0]}
    (folder / "calibration.toml").write_text(tomli_w.dumps(cal))
    with pytest.raises(InputError, match="world_mirror: expected three values of 1 or -1"):
        read_session(folder)


def test_sparse_labelled_frames_fall_back_to_loose_motion_noise(tmp_path):
    """Labels on every 20th frame only (DANNCE-like) and no physics: nothing to measure the motion from, so
    a warning says so and the filter runs with loose noise instead of the session failing."""
    folder = _copy(FLIGHT, tmp_path / "s", drop_noise=False, drop_physics=True)
    obs = pd.read_csv(folder / "observations.csv")
    obs[obs["frame"] % 20 == 0].to_csv(folder / "observations.csv", index=False)
    assert _reconstruct(folder, tmp_path / "o", "--methods", "filter,triangulate") == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert any("loose motion noise" in w for w in summary["warnings"]), summary["warnings"]
