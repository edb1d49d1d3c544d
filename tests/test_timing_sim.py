"""Simulated cameras out of step: each observation is the true marker at its own capture time, in both generators."""

from __future__ import annotations

import numpy as np
import pytest

from batgraph import simulate as S
from batgraph import wingbeat as W
from batgraph.cli import main
from batgraph.session import read_session

ISSUE_OFFSETS_S = (0.0, 0.0031, -0.0024, 0.0017, -0.0040)  # the issue's bat scene: 0, +3.1, -2.4, +1.7, -4.0 ms


def _scene_at(session):
    """scene_at(times) of a simulated session (flight, ear or wingbeat), exact (closed form)."""
    if "wingbeat" in session.extra_toml:
        p = session.extra_toml["wingbeat"]
        return lambda t: W.wingbeat_scene(p, t)
    sim = session.extra_toml["simulation"]
    if sim["scene"] == "flight":
        return lambda t: S.flight_scene(sim["n_frames"], sim["fps"], sim["n_markers"], sim["phase0_rad"],
                                        tuple(sim["offset_yz_m"]), t)
    return lambda t: S.ear_scene(sim["n_frames"], sim["fps"], sim["phase0_rad"], sim["drift_hz"],
                                 sim["drift_phase_rad"], sim["drift_amp_m"], t)


@pytest.mark.parametrize("make", [
    lambda: S.simulate_flight(np.random.default_rng(3), n_markers=40, n_frames=40),
    lambda: W.simulate_wingbeat(np.random.default_rng(3), fps=120.0, n_frames=40, flap_hz=15.0),
])
def test_spline_between_frames_matches_the_closed_form(make):
    """The scene between its frames (SceneSpline) is the closed form to < 1 um at random instants."""
    sess = make()
    at = _scene_at(sess)
    span = S.SceneSpline(at, -1 / sess.fps, 41 / sess.fps, sess.fps)
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 39 / sess.fps, 3000)
    m = rng.integers(0, span.M, 3000)
    exact = at(t).points_m[np.arange(3000), m]
    assert np.abs(span.points(t, m) - exact).max() < 1e-6


def test_zero_timing_reproduces_the_plain_renderer():
    """The timed renderer with a negligible offset gives the synchronised renderer's observations (same noise)."""
    plain = S.simulate_flight(np.random.default_rng(1), n_markers=24)
    timed = S.simulate_flight(np.random.default_rng(1), n_markers=24,
                              timing=S.Timing(time_offsets_s=(0, 0, 0, 0, 1e-13)))
    a, b = plain.observations, timed.observations
    assert len(a) == len(b)
    assert (a[["frame", "camera", "marker"]].to_numpy() == b[["frame", "camera", "marker"]].to_numpy()).all()
    assert np.abs(a[["u", "v"]].to_numpy() - b[["u", "v"]].to_numpy()).max() < 1e-8
    assert S.Timing().trivial(5, 120.0) and not S.Timing(readout_s=0.006).trivial(5, 120.0)


@pytest.mark.parametrize("generator", ["flight", "ear", "wingbeat"])
def test_each_observation_is_the_truth_at_its_capture_time(generator):
    """Noise-free: every observation is the closed-form marker at j / fps_c + offset + readout * v / h, projected."""
    if generator == "flight":
        timing = S.Timing(time_offsets_s=ISSUE_OFFSETS_S, readout_s=0.006, camera_fps=(120, 60, 120, 120, 120))
        sess = S.simulate_flight(np.random.default_rng(2), n_frames=40, pixel_sigma_px=0.0, timing=timing)
    elif generator == "ear":
        sess = S.simulate_ear(np.random.default_rng(2), n_frames=60, pixel_sigma_px=0.0,
                              timing=S.Timing(time_offsets_s=(0.0, 0.0013), readout_s=(0.002, 0.003)))
    else:
        sess = W.simulate_wingbeat(np.random.default_rng(2), n_frames=40, pixel_sigma_px=0.0,
                                   timing=S.Timing(time_offsets_s=(0.0, 0.021, -0.0024, 0.0017, -0.04),
                                                   readout_s=0.006))
    at = _scene_at(sess)
    truth = sess.true_timing.set_index("camera")
    obs = sess.observations.sample(300, random_state=0)
    own = obs["camera_frame"] if "camera_frame" in obs else obs["frame"]
    for (_, row), j in zip(obs.iterrows(), own, strict=True):
        cam, tt = sess.rig[row.camera], truth.loc[row.camera]
        t = j / tt.fps + tt.time_offset_s + tt.readout_s * row.v / cam.size_wh[1]
        m = sess.marker_names.index(row.marker)
        uv = cam.project(at(np.array([t])).points_m[0, m])
        assert np.hypot(*(uv - [row.u, row.v])) < 1e-3, (row.camera, j, row.marker)


def test_the_calibration_states_only_what_a_user_knows():
    timing = S.Timing(time_offsets_s=ISSUE_OFFSETS_S, readout_s=0.006, camera_fps=(120, 60, 120, 120, 120))
    sess = S.simulate_flight(np.random.default_rng(4), n_frames=30, timing=timing)
    assert [c.time_offset_s for c in sess.rig] == [0.0] * 5 and [c.readout_s for c in sess.rig] == [0.0] * 5
    assert [c.fps for c in sess.rig] == [None, 60.0, None, None, None]
    assert np.allclose(sess.true_timing["time_offset_s"], ISSUE_OFFSETS_S)
    assert np.allclose(sess.true_timing["readout_s"], 0.006)
    known = S.simulate_flight(np.random.default_rng(4), n_frames=30, timing=S.Timing(
        time_offsets_s=ISSUE_OFFSETS_S, readout_s=0.006, known=True))
    assert np.allclose([c.time_offset_s for c in known.rig], ISSUE_OFFSETS_S)
    assert np.allclose([c.readout_s for c in known.rig], 0.006)
    # the truth stays on the session clock: the same for the synchronised twin
    twin = S.simulate_flight(np.random.default_rng(4), n_frames=30)
    assert twin.truth.equals(sess.truth) and twin.true_timing is None


def test_whole_frame_lags_shift_the_frames():
    """A camera 3 frames late: its frame j shows what the others show at frame j + 3."""
    sess = S.simulate_flight(np.random.default_rng(5), n_frames=40, pixel_sigma_px=0.0,
                             timing=S.Timing(time_offsets_s=(0.0, 3 / 120, 0.0, 0.0, 0.0), known=True))
    obs = sess.observations
    late = obs[obs["camera"] == "cam2"]
    assert np.array_equal(late["frame"], late["camera_frame"] + 3)
    assert late["camera_frame"].max() <= 36 and late["frame"].max() <= 39


def test_simulate_cli_timing_flags(tmp_path):
    out = tmp_path / "s"
    assert main(["simulate", "flight", str(out), "--frames", "30", "--time-offsets-ms", "0,3.1,-2.4,1.7,-4.0",
                 "--readout-ms", "6", "--camera-fps", "120,120,60,120,120"]) == 0
    back = read_session(out)
    assert back.true_timing is not None and np.allclose(back.true_timing["time_offset_s"], ISSUE_OFFSETS_S)
    assert [c.time_offset_s for c in back.rig] == [0.0] * 5 and back.rig[2].fps == 60.0
    assert (out / "truth_timing.toml").exists()
    assert main(["simulate", "ear", str(tmp_path / "e"), "--frames", "20", "--time-offsets-ms", "0,1",
                 "--readout-ms", "2", "--timing-known"]) == 0
    assert read_session(tmp_path / "e").rig[1].time_offset_s == 0.001
    assert read_session(tmp_path / "e").rig[1].readout_s == 0.002


@pytest.mark.parametrize("argv, words", [
    (["--time-offsets-ms", "0,1"], "expected 5 values"),
    (["--camera-fps", "240,120,120,120,120"], "raise --fps"),
    (["--readout-ms", "9"], "shorter than a frame"),
    (["--timing-known"], "give the timing"),
])
def test_simulate_cli_timing_errors(tmp_path, capsys, argv, words):
    assert main(["simulate", "flight", str(tmp_path / "s"), "--frames", "10", *argv]) == 2
    assert words in capsys.readouterr().err
