"""The timing self-check and the lag scan, against simulated truth, on both generators and on real data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import observations_table, tiny_rig

from batgraph import simulate as S
from batgraph import timing as T
from batgraph import wingbeat as W
from batgraph.checks import preflight
from batgraph.measurement import ideal_observations
from batgraph.session import Session, dense_observations, read_session
from batgraph.triangulate import triangulate_ideal

SAMPLES = Path(__file__).resolve().parents[1] / "data" / "samples"
ISSUE_OFFSETS_S = (0.0, 0.0031, -0.0024, 0.0017, -0.0040)


def _truth_track(session, frames):
    """The closed-form truth and its velocity (central differences, 10 us) at session frames."""
    t = np.asarray(frames) / session.fps
    if "wingbeat" in session.extra_toml:
        p = session.extra_toml["wingbeat"]

        def at(tt):
            return W.wingbeat_scene(p, tt).points_m
    else:
        sim = session.extra_toml["simulation"]

        def at(tt):
            if sim["scene"] == "flight":
                return S.flight_scene(sim["n_frames"], sim["fps"], sim["n_markers"], sim["phase0_rad"],
                                      tuple(sim["offset_yz_m"]), tt).points_m
            return S.ear_scene(sim["n_frames"], sim["fps"], sim["phase0_rad"], sim["drift_hz"], sim["drift_phase_rad"],
                               sim["drift_amp_m"], tt).points_m
    return at(t), (at(t + 1e-5) - at(t - 1e-5)) / 2e-5


def _check(session, estimate: str = "triangulation") -> T.TimingCheck:
    dense = dense_observations(session)
    ideal = preflight(session, dense).ideal  # the noise measured as reconstruct measures it
    if estimate == "truth":
        xyz, vel = _truth_track(session, dense.frames)
    else:
        xyz, _ = triangulate_ideal(session.rig, ideal)
        vel = np.gradient(xyz, axis=0) * session.fps
    return T.timing_check(session.rig, ideal, xyz, vel, session.fps)


def _two_ms(gen: str, seed: int, **kw):
    timing = S.Timing(time_offsets_s=(0.0, 0.0, 0.002, 0.0, 0.0), **kw)
    if gen == "flight":
        return S.simulate_flight(np.random.default_rng(seed), n_markers=24, timing=timing)
    return W.simulate_wingbeat(np.random.default_rng(seed), n_frames=160, timing=timing)


# ----------------------------------------------------------------------------------------------
# the self-check
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("gen, seed, estimate", [("flight", 0, "truth"), ("flight", 1, "triangulation"),
                                                 ("wingbeat", 0, "truth"), ("wingbeat", 1, "truth")])
def test_a_camera_2ms_out_at_120fps_is_named(gen, seed, estimate):
    chk = _check(_two_ms(gen, seed), estimate)
    third = chk.table.iloc[2]
    assert chk.table["flagged"].tolist() == [False, False, True, False, False]
    assert len(chk.warnings) == 1 and chk.warnings[0].startswith(f"{third.camera} looks ~2.0 ms out of step")
    assert "--sync estimate" in chk.warnings[0]
    assert abs(third.step_s - 0.002) < 0.2e-3


@pytest.mark.parametrize("folder", ["flight_5cam", "ear_2cam"])
@pytest.mark.parametrize("estimate", ["truth", "triangulation"])
def test_bundled_samples_are_quiet(folder, estimate):
    chk = _check(read_session(SAMPLES / folder), estimate)
    assert chk.warnings == []
    assert np.all(np.abs(chk.table["step_s"]) < 0.3e-3)


@pytest.mark.parametrize("make", [
    lambda: S.simulate_flight(np.random.default_rng(2), n_markers=24, pixel_sigma_px=4.0, outlier_rate=0.03),
    lambda: W.simulate_wingbeat(np.random.default_rng(2), n_frames=160, flight="turn"),
    lambda: S.simulate_ear(np.random.default_rng(2)),
])
def test_synchronised_rigs_are_quiet(make):
    assert _check(make()).warnings == []


def test_mislabels_do_not_hide_or_fake_an_offset():
    sess = S.simulate_flight(np.random.default_rng(3), n_markers=24, outlier_rate=0.03,
                             timing=S.Timing(time_offsets_s=(0.0, 0.0, 0.002, 0.0, 0.0)))
    chk = _check(sess)
    assert chk.table["flagged"].tolist() == [False, False, True, False, False]


def test_the_issue_scene_offsets_and_readouts():
    """The issue's 5-camera rig (0, +3.1, -2.4, +1.7, -4.0 ms, 6 ms readout): every offset camera named, the
    rolling shutters too; with the truth in calibration.toml (time_frac carries it), nothing is left to say."""
    timing = S.Timing(time_offsets_s=ISSUE_OFFSETS_S, readout_s=0.006)
    chk = _check(S.simulate_flight(np.random.default_rng(0), timing=timing), "truth")
    assert chk.table["flagged"].tolist() == [False, True, True, True, True]
    assert chk.table["rolling"].all() and np.all(np.abs(chk.table["readout_s"] - 0.006) < 0.8e-3)
    rel = np.array(ISSUE_OFFSETS_S) - ISSUE_OFFSETS_S[int(np.flatnonzero(chk.table["camera"] == chk.reference)[0])]
    assert np.all(np.abs(chk.table["offset_s"] - rel) < 0.6e-3)
    known = S.simulate_flight(np.random.default_rng(0), timing=S.Timing(time_offsets_s=ISSUE_OFFSETS_S,
                                                                          readout_s=0.006, known=True))
    quiet = _check(known, "truth")
    assert quiet.warnings == [] and np.all(np.abs(quiet.table["offset_s"]) < 0.3e-3)


def test_offsets_are_relative_to_the_reference():
    """A shift common to every camera moves the points, nothing else; the reference has the most observations."""
    a = _check(_two_ms("flight", 4), "truth").table
    shifted = S.simulate_flight(np.random.default_rng(4), n_markers=24,
                                timing=S.Timing(time_offsets_s=(0.001, 0.001, 0.003, 0.001, 0.001)))
    b = _check(shifted, "truth")
    assert b.reference == b.table["camera"][b.table["n_obs"].idxmax()]
    assert float(b.table.loc[b.table["camera"] == b.reference, "offset_s"].iloc[0]) == 0.0
    assert np.allclose(a["offset_s"], b.table["offset_s"], atol=0.3e-3)


def test_a_pair_of_cameras():
    sess = S.simulate_ear(np.random.default_rng(0), timing=S.Timing(time_offsets_s=(0.0, 0.002)))
    chk = _check(sess, "truth")
    assert len(chk.warnings) == 1 and chk.warnings[0].startswith("cam2 looks ~2.")
    assert "ms behind cam1" in chk.warnings[0]


def test_rows_from_the_pixels_match_the_dense_rows():
    sess = read_session(SAMPLES / "flight_5cam")
    dense = dense_observations(sess, timing=True)
    ideal = ideal_observations(sess.rig, dense, 1.0)
    rows = T._raw_rows(sess.rig, ideal)
    assert np.abs(rows - dense.row_frac)[dense.seen].max() < 1e-6


# ----------------------------------------------------------------------------------------------
# the lag scan
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("gen", ["flight", "wingbeat"])
@pytest.mark.parametrize("sub", [(0.0,) * 5, (0.0, 0.3, -0.4, 0.2, 0.45)])
def test_lags_of_up_to_5_frames(gen, sub):
    lags = np.array([0, 3, -2, 5, -5]) + np.array(sub)
    timing = S.Timing(time_offsets_s=tuple(lags / 120), readout_s=0.006)
    sess = (S.simulate_flight(np.random.default_rng(4), n_markers=14, timing=timing) if gen == "flight"
            else W.simulate_wingbeat(np.random.default_rng(4), n_frames=160, timing=timing))
    dense = dense_observations(sess)
    scan = T.scan_lags(sess.rig, ideal_observations(sess.rig, dense, 1.0), dense.frames, sess.fps)
    ref = int(np.flatnonzero(scan.table["camera"] == scan.reference)[0])
    rel = lags - lags[ref]
    assert np.array_equal(scan.table["lag_frames"], np.ceil(rel - 0.5))
    assert np.all(np.abs(scan.table["offset_frames"] - rel) < 0.2)
    assert not scan.table["ambiguous"].any()
    assert np.allclose(scan.table["time_offset_s"], scan.table["lag_frames"] / 120)


def test_a_still_scene_is_ambiguous():
    """Markers that do not move cannot tell one frame from another."""
    rig = tiny_rig(3)
    xyz = np.broadcast_to(np.array([[0.0, 0.0, 0.1], [0.1, -0.05, 0.2], [-0.1, 0.1, 0.0]]), (40, 3, 3))
    obs = observations_table(rig, xyz)
    sess = Session("still", 100.0, rig, obs, pixel_sigma_px=1.0)
    dense = dense_observations(sess)
    scan = T.scan_lags(rig, ideal_observations(rig, dense, 1.0), dense.frames, 100.0, min_points=3)
    others = scan.table[scan.table["camera"] != scan.reference]
    assert others["ambiguous"].all()


def test_a_lag_beyond_the_scan_is_said():
    timing = S.Timing(time_offsets_s=(0.0, 7 / 120, 0.0, 0.0, 0.0))
    sess = S.simulate_flight(np.random.default_rng(4), n_markers=14, timing=timing)
    dense = dense_observations(sess)
    scan = T.scan_lags(sess.rig, ideal_observations(sess.rig, dense, 1.0), dense.frames, sess.fps, max_lag=5)
    assert "beyond the scan" in scan.table["note"].iloc[1]
