"""Per-camera timing in the rig: calibration.toml keys, unknown keys named, mixed frame rates on the session clock,
and the time_frac / row_frac arrays the estimators read."""

from __future__ import annotations

import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomli_w
from conftest import observations_table, tiny_rig, tiny_scene

from batgraph.camera import Camera, Rig
from batgraph.errors import InputError
from batgraph.measurement import ideal_observations
from batgraph.session import (
    Session,
    calibration_toml,
    dense_observations,
    read_calibration,
    read_session,
    retime,
    write_session,
)

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def _edit(path: Path, edit) -> None:
    doc = tomllib.loads(path.read_text())
    edit(doc)
    path.write_text(tomli_w.dumps(doc))


def _error(folder: Path) -> str:
    with pytest.raises(InputError) as e:
        read_session(folder)
    assert "\n" not in str(e.value)
    return str(e.value)


def _session(rig: Rig, fps: float = 100.0, n_frames: int = 12) -> Session:
    xyz = tiny_scene(n_frames, 3)
    return Session("t", fps, rig, observations_table(rig, xyz), pixel_sigma_px=1.0)


# ----------------------------------------------------------------------------------------------
# calibration.toml keys
# ----------------------------------------------------------------------------------------------
def test_timing_keys_round_trip(tmp_path):
    rig = tiny_rig(3)
    rig.cameras[1] = Camera(**{**{k: getattr(rig[1], k) for k in ("name", "size_wh", "K", "dist", "rvec", "tvec")},
                               "fps": 50.0, "time_offset_s": -0.0043, "readout_s": 0.006,
                               "time_offset_sd_s": 2e-5, "readout_sd_s": 1e-4})
    path = tmp_path / "calibration.toml"
    path.write_text(calibration_toml(Rig(rig.cameras)))
    back = read_calibration(path, warnings=[])
    cam = back[1]
    assert (cam.fps, cam.time_offset_s, cam.readout_s, cam.time_offset_sd_s, cam.readout_sd_s) == (
        50.0, -0.0043, 0.006, 2e-5, 1e-4)
    assert back[0].fps is None and back[0].time_offset_s == 0 and back[0].readout_s == 0
    assert back[0].time_offset_sd_s is None
    tab = tomllib.loads(path.read_text())
    assert not {"fps", "time_offset_s", "readout_s"} & set(tab["cam_0"]), "a camera without timing writes none"
    # a known offset whose sd is 0 (a perfect estimate) keeps its sd
    assert calibration_toml(Rig([Camera("a", (10, 10), np.eye(3), time_offset_sd_s=0.0)])).count("time_offset_sd_s")


@pytest.mark.parametrize("key, value, words", [
    ("fps", 0.0, "must be > 0"), ("fps", -30.0, "must be > 0"), ("time_offset_s", float("nan"), "finite"),
    ("readout_s", -0.001, ">= 0"), ("time_offset_s", "4 ms", "expected a number"),
    ("time_offset_sd_s", -1.0, ">= 0"), ("readout_sd_s", float("inf"), "finite"),
])
def test_timing_keys_validated(session_folder, key, value, words):
    _edit(session_folder / "calibration.toml", lambda d: d["cam_1"].__setitem__(key, value))
    msg = _error(session_folder)
    assert key in msg and words in msg and "[cam_1]" in msg


def test_readout_must_be_shorter_than_a_frame(session_folder):
    cal = session_folder / "calibration.toml"
    _edit(cal, lambda d: d["cam_0"].update(fps=100.0, readout_s=0.01))
    assert "not shorter than one frame" in _error(session_folder)
    _edit(cal, lambda d: (d["cam_0"].pop("fps"), d["cam_0"].update(readout_s=0.5)))  # the session's fps
    msg = _error(session_folder)
    assert "readout_s" in msg and "cam1" in msg


def test_typo_of_a_timing_key_is_an_error(session_folder):
    _edit(session_folder / "calibration.toml", lambda d: d["cam_1"].__setitem__("time_ofset_s", 0.0043))
    msg = _error(session_folder)
    assert "'time_ofset_s'" in msg and "did you mean 'time_offset_s'" in msg and "[cam_1]" in msg


def test_unknown_keys_warn_and_load(session_folder):
    _edit(session_folder / "calibration.toml", lambda d: (d["cam_0"].__setitem__("lens_serial", "A12"),
                                                         d.setdefault("metadata", {}).__setitem__("operator", "x")))
    session = read_session(session_folder)
    text = " ".join(session.warnings)
    assert "'lens_serial'" in text and "'operator'" in text and "ignored" in text
    with pytest.warns(UserWarning) as caught:  # read on its own: never silent either
        read_calibration(session_folder / "calibration.toml")
    text = " ".join(str(r.message) for r in caught)
    assert "lens_serial" in text and "operator" in text


def test_peer_tool_keys_are_known(tmp_path):
    """What aniposelib, Anipose, Pose2Sim, Caliscope and FreeMoCap write loads without a word."""
    rig = tiny_rig(2)
    doc = tomllib.loads(calibration_toml(rig))
    doc["cam_0"].update(fisheye=False, port=0, cam_id=0, rotation_count=0, error=0.4, exposure=-7, grid_count=3,
                        ignore=False, verified_resolutions=[[640, 480]])
    doc["metadata"].update(adjusted=True, error=0.5, charuco_square_size=39, charuco_board_object="b",
                           path_to_recorded_videos="v", date_time_calibrated="2024", groundplane_calibration=True)
    path = tmp_path / "c.toml"
    path.write_text(tomli_w.dumps(doc))
    notes = []
    read_calibration(path, warnings=notes)
    assert notes == []


@pytest.mark.skipif(not (REAL / "pose2sim_demo_4cam_human").is_dir(), reason="real data absent")
def test_pose2sim_calibration_loads_silently():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_calibration(REAL / "pose2sim_demo_4cam_human" / "S00_Calibration" / "Calib_qualisys.toml")


# ----------------------------------------------------------------------------------------------
# session.toml keys
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("table, key, hint", [
    ("session", "fsp", "fps"), ("noise", "pixel_sigma", "pixel_sigma_px"), ("motion", "flap_hertz", "flap_hz"),
    ("markers", "skeletons", "skeleton"),
])
def test_session_typos_are_errors(session_folder, table, key, hint):
    _edit(session_folder / "session.toml", lambda d: d.setdefault(table, {}).__setitem__(key, 1.0))
    msg = _error(session_folder)
    assert f"[{table}]" in msg and f"'{key}'" in msg and f"did you mean '{hint}'" in msg


def test_session_unknown_keys_and_tables(session_folder):
    _edit(session_folder / "session.toml", lambda d: (d["session"].__setitem__("operator", "me"),
                                                     d.__setitem__("notes", {"weather": "rain"})))
    text = " ".join(read_session(session_folder).warnings)
    assert "'operator'" in text and "[notes]" in text
    _edit(session_folder / "session.toml", lambda d: d.__setitem__("moton", {"model": "auto"}))
    assert "did you mean [motion]" in _error(session_folder)


def test_the_paper_table_is_a_known_one(session_folder):
    """[paper] experiment (docs/formats.md) is read by the summary, so it loads without a warning."""
    _edit(session_folder / "session.toml", lambda d: d.__setitem__("paper", {"experiment": "flight"}))
    s = read_session(session_folder)
    assert not any("paper" in w for w in s.warnings) and s.extra_toml["paper"]["experiment"] == "flight"


def test_no_timing_no_change(session_folder):
    """Without timing keys the observations are the file's and the dense arrays carry no timing."""
    s = read_session(session_folder)
    assert "camera_frame" not in s.observations and not any("unknown" in w for w in s.warnings)
    d = dense_observations(s)
    assert d.time_frac is None and d.row_frac is None
    ideal = ideal_observations(s.rig, d, 1.0)
    assert ideal.time_frac is None and ideal.with_sigma(2.0).time_frac is None
    assert ideal.take(slice(0, 2)).row_frac is None
    assert dense_observations(s, timing=True).time_frac.any() == False  # noqa: E712 - asked for: zeros


# ----------------------------------------------------------------------------------------------
# mixed frame rates and offsets: camera frames -> session frames
# ----------------------------------------------------------------------------------------------
def _with(rig: Rig, **per_camera) -> Rig:
    cams = []
    for i, c in enumerate(rig):
        kw = {k: v[i] for k, v in per_camera.items()}
        cams.append(Camera(c.name, c.size_wh, c.K, c.dist, c.rvec, c.tvec, **kw))
    return Rig(cams)


def test_mixed_rates_and_offsets_map_to_session_frames(tmp_path):
    rig = tiny_rig(3)
    s = _session(rig, fps=120.0, n_frames=20)
    timed = _with(rig, fps=[120.0, 60.0, 120.0], time_offset_s=[0.0, 0.0, 2.6 / 120])
    write_session(Session("t", 120.0, timed, s.observations, pixel_sigma_px=1.0), tmp_path / "s")
    back = read_session(tmp_path / "s")
    obs = back.observations
    for cam, factor, shift in (("cam1", 1, 0), ("cam2", 2, 0), ("cam3", 1, 3)):  # 2.6 frames: nearest is 3
        o = obs[obs["camera"] == cam]
        assert np.array_equal(o["frame"], factor * o["camera_frame"] + shift)
    d = dense_observations(back)
    c3 = d.cameras.index("cam3")
    seen = d.seen[c3]
    assert np.allclose(d.time_frac[c3][seen], -0.4) and np.all(d.time_frac[0][d.seen[0]] == 0)
    assert np.all(d.time_frac[~d.seen] == 0) and np.all(d.row_frac[~d.seen] == 0)
    # the files are written back with the cameras' own frames
    write_session(back, tmp_path / "again")
    assert (tmp_path / "again" / "observations.csv").read_bytes() == (tmp_path / "s" / "observations.csv").read_bytes()


def test_time_frac_adds_the_readout_and_rows(tmp_path):
    rig = tiny_rig(2)
    s = _session(rig, fps=100.0)
    timed = _with(rig, readout_s=[0.0, 0.004], time_offset_s=[0.0, 0.001])
    d = dense_observations(retime(s, timed))
    seen = d.seen[1]
    v = d.uv_px[1][seen][:, 1]
    assert np.allclose(d.row_frac[1][seen], v / rig[1].size_wh[1])
    assert np.allclose(d.time_frac[1][seen], 0.1 + 0.4 * v / rig[1].size_wh[1])
    ideal = ideal_observations(timed, d, 1.0)
    assert ideal.time_frac is d.time_frac and ideal.with_sigma(3.0).row_frac is d.row_frac
    sl = slice(2, 5)
    assert np.array_equal(ideal.take(sl).time_frac, d.time_frac[:, sl])
    assert np.array_equal(d.take(sl).row_frac, d.row_frac[:, sl])


def test_faster_camera_is_an_input_error(session_folder):
    _edit(session_folder / "calibration.toml", lambda d: d["cam_1"].__setitem__("fps", 500.0))
    msg = _error(session_folder)
    assert "500 fps" in msg and "raise [session] fps" in msg and "cam2" in msg


def test_observations_before_session_start_are_dropped_with_a_warning(session_folder):
    _edit(session_folder / "calibration.toml", lambda d: d["cam_1"].__setitem__("time_offset_s", -0.5))
    fps = tomllib.loads((session_folder / "session.toml").read_text())["session"]["fps"]
    s = read_session(session_folder)
    assert (s.observations["frame"] >= 0).all()
    assert any("before session frame 0" in w and "cam2" in w for w in s.warnings)
    lag = round(0.5 * fps)
    o = s.observations[s.observations["camera"] == "cam2"]
    assert np.array_equal(o["frame"], o["camera_frame"] - lag)


def test_retime_back_to_the_session_clock():
    rig = tiny_rig(2)
    s = _session(rig)
    shifted = retime(s, _with(rig, time_offset_s=[0.0, 0.05]))
    assert "camera_frame" in shifted.observations
    back = retime(shifted, rig)
    assert "camera_frame" not in back.observations
    pd.testing.assert_frame_equal(back.observations.reset_index(drop=True), s.observations.reset_index(drop=True),
                                  check_like=True)
