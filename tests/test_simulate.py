"""Tests of the bat-flight and bat-ear simulator against independent geometry (small scenes, fast)."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest

from batgraph import simulate as S
from batgraph.session import dense_observations, read_session, write_session

EPS = S.HIT_EPS


def _flight(seed=1, **kw):
    return S.simulate_flight(np.random.default_rng(seed), **kw)


def _in_field(session, scene):
    """bool (C, F, M): in front of the camera, inside the lens's valid field and the image (true rig)."""
    rig = session.true_rig or session.rig
    uv = rig.project(scene.points_m)
    return np.isfinite(uv[..., 0]) & np.stack([c.in_image(uv[i]) for i, c in enumerate(rig)])


# ----- independent, non-vectorised occlusion checks -------------------------------------------------
def _blocked_by_triangle(o, p, tri):
    """Solve o + t (p - o) = v0 + a e1 + b e2 for (t, a, b) with np.linalg.solve."""
    A = np.column_stack([p - o, -(tri[1] - tri[0]), -(tri[2] - tri[0])])
    if abs(np.linalg.det(A)) < 1e-14:
        return False  # segment parallel to the triangle's plane
    t, a, b = np.linalg.solve(A, tri[0] - o)
    return bool(EPS < t < 1 - EPS and a >= 0 and b >= 0 and a + b <= 1)


def _blocked_by_ellipsoid(o, p, center, axes, semi):
    """Roots of |o' + t d'|^2 = 1 in the ellipsoid's unit-sphere coordinates, one point at a time."""
    oo = axes.T @ (o - center) / semi
    dd = axes.T @ (p - o) / semi
    roots = np.roots([dd @ dd, 2 * oo @ dd, oo @ oo - 1])
    real = np.sort(roots[np.abs(roots.imag) < 1e-12].real)
    return bool(len(real) == 2 and real[0] != real[1] and EPS < real[0] < 1 - EPS)


# ----- tests ----------------------------------------------------------------------------------------
def test_noise_free_observations_reproject_exactly():
    """Without noise every observation is the truth projected by the written rig: measured ~1e-10 px;
    bound 1e-6 px (the brief's). Both scenes; the written rig equals the rendering rig here."""
    for sess in (_flight(n_frames=30, n_markers=30, pixel_sigma_px=0.0),
                 S.simulate_ear(np.random.default_rng(2), n_frames=40, pixel_sigma_px=0.0)):
        assert sess.true_rig is None and len(sess.mislabels) == 0
        obs = sess.observations.merge(sess.truth, on=["frame", "marker"], how="left")
        assert len(obs) == len(sess.observations) > 100 and obs["x"].notna().all()
        err = []
        for cam in sess.rig:
            o = obs[obs["camera"] == cam.name]
            uv = cam.project(o[["x", "y", "z"]].to_numpy())
            err.append(np.abs(uv - o[["u", "v"]].to_numpy()).max())
        assert max(err) < 1e-6


def test_truth_matches_scene_and_skeleton():
    """truth.csv is the scene's points; markers, skeleton and motion are as documented."""
    sess = _flight(n_frames=12, n_markers=20)
    scene = S.scene_from_session(sess)
    xyz = sess.truth[["x", "y", "z"]].to_numpy().reshape(12, 20, 3)
    assert np.array_equal(xyz, scene.points_m)
    assert sess.marker_names[:8] == ["body1", "body2", "shoulder_r", "elbow_r", "wrist_r", "digit3_r",
                                     "digit4_r", "digit5_r"]
    assert sess.marker_names[14:] == ["mem_r_001", "mem_r_002", "mem_r_003", "mem_l_001", "mem_l_002", "mem_l_003"]
    assert ("elbow_l", "wrist_l") in sess.skeleton and ("body1", "shoulder_r") in sess.skeleton
    m = sess.motion
    assert (m.model, m.flight_speed_mps, m.span_m, m.flap_hz, m.flap_angle_deg) == ("auto", 3.0, 0.5,
                                                                                     4.0, 90.0)
    # the bat flies along -x at 3 m/s and spans 0.5 m (+-2 cm for the folding upstroke)
    body = scene.points_m[:, 0]
    assert np.allclose(np.diff(body[:, 0]) * sess.fps, -3.0, atol=0.05)
    full = S.flight_scene(30, 120.0)
    assert 0.48 < np.ptp(full.points_m[..., 1], axis=1).max() < 0.52
    with pytest.raises(ValueError):
        S.flight_scene(5, 120.0, n_markers=13)
    with pytest.raises(ValueError):
        S.flight_scene(5, 120.0, n_markers=181)


def test_trajectories_are_smooth():
    """C2 (in fact C-infinity): finite-difference acceleration and jerk do not grow when the frame
    rate goes up 10x, which a kink in position (or velocity) would make grow like 1/dt. Measured
    ratios ~1.0; bound 1.2."""
    coarse = S.flight_scene(41, 120.0, 40, 0.3)
    fine = S.flight_scene(401, 1200.0, 40, 0.3)
    assert np.allclose(fine.points_m[::10], coarse.points_m, atol=1e-12)
    for order in (2, 3):
        peak = [np.abs(np.diff(s.points_m, n=order, axis=0)).max() * fps**order
                for s, fps in ((coarse, 120.0), (fine, 1200.0))]
        assert peak[1] < 1.2 * peak[0]


def test_visibility_helper_basic_cases():
    """Hand-built cases: a triangle across the segment hides, one having the marker as vertex or
    containing it does not, an ellipsoid across the segment hides."""
    cam = np.array([[0.0, 0.0, 0.0]])
    pts = np.array([[0.0, 0.0, 2.0], [0.5, 0.5, 1.0], [0.2, 0.2, 1.0], [3.0, 0.0, 2.0]])
    tri = np.array([[[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [0.5, 0.5, 1.0]]])  # plane z = 1; pts[1] is a vertex
    vis = S.visibility(cam, pts, tri)
    assert vis.tolist() == [[False, True, True, True]]  # pts[2] lies inside the triangle, pts[3] misses it
    ell = [(np.array([1.5, 0.0, 1.0]), np.eye(3), np.array([0.2, 0.2, 0.2]))]
    assert S.visibility(cam, pts, tri[:0], ell).tolist() == [[True, True, True, False]]


def test_occlusion_is_exact():
    """For 2,000 random in-field (frame, camera, marker) samples, a marker is observed exactly when
    the independent per-triangle linear solve and per-ellipsoid quadratic say its segment is clear.
    Measured 0 disagreements; bound 0. The sample must contain membrane and body occlusions."""
    sess = _flight(seed=4, n_frames=60, n_markers=60, pixel_sigma_px=0.0)
    scene = S.scene_from_session(sess)
    seen = dense_observations(sess).seen  # (C, F, M), markers in session order = scene order
    assert sess.markers == scene.marker_names
    field = _in_field(sess, scene)
    c_i, f_i, m_i = np.nonzero(field)
    pick = np.random.default_rng(0).choice(len(c_i), 2000, replace=False)
    centers = [c.center_world for c in sess.rig]
    n_tri = n_body = 0
    for c, f, m in zip(c_i[pick], f_i[pick], m_i[pick], strict=True):
        o, p = centers[c], scene.points_m[f, m]
        by_tri = any(_blocked_by_triangle(o, p, tri) for tri in scene.triangles_m[f])
        by_body = any(_blocked_by_ellipsoid(o, p, e.center_m[f], e.axes[f], e.semi_axes_m) for e in scene.ellipsoids)
        assert seen[c, f, m] == (not (by_tri or by_body)), (c, f, m, by_tri, by_body)
        n_tri += by_tri
        n_body += by_body
    assert n_tri > 50 and n_body > 50


def test_observed_exactly_when_clear_in_front_and_in_image():
    """Without noise, an observation exists iff the line of sight is clear and the point projects
    (in front, inside the lens's valid field) into the image; nothing else drops a point."""
    sess = _flight(seed=3, n_frames=40, n_markers=30, pixel_sigma_px=0.0)
    scene = S.scene_from_session(sess)
    expected = S.scene_visibility(scene, sess.rig) & _in_field(sess, scene)
    assert expected.sum() > 1000 and (dense_observations(sess).seen == expected).all()


def test_visibility_follows_the_wingbeat():
    """Upstroke is worse (paper): on the upstroke a larger share of in-field points is occluded
    (measured 15 % vs 8 % at seed 1) and fewer cameras see each point (2.7 vs 3.3 views, though
    part of that is which frames fall at the ends of the path). Bounds: occlusion +3 points,
    views strictly fewer."""
    sess = _flight(n_markers=60, pixel_sigma_px=0.0)
    scene = S.scene_from_session(sess)
    up = S.is_upstroke(scene.phase_rad)
    assert 0.4 < up.mean() < 0.6
    seen = dense_observations(sess).seen
    field = _in_field(sess, scene)
    occluded = [1 - seen[:, sel].sum() / field[:, sel].sum() for sel in (up, ~up)]
    assert occluded[0] > occluded[1] + 0.03
    n_views = seen.sum(axis=0)
    assert n_views[up].mean() < n_views[~up].mean()
    # with 5 cameras most (marker, frame) pairs are seen by >= 2 cameras (measured 0.80; bound 0.7)
    assert (n_views >= 2).mean() > 0.7


def test_deterministic_for_a_seed():
    a = _flight(seed=7, n_frames=20, n_markers=20, outlier_rate=0.05, calib_rot_deg=0.3, calib_trans_mm=2.0)
    b = _flight(seed=7, n_frames=20, n_markers=20, outlier_rate=0.05, calib_rot_deg=0.3, calib_trans_mm=2.0)
    c = _flight(seed=8, n_frames=20, n_markers=20, outlier_rate=0.05, calib_rot_deg=0.3, calib_trans_mm=2.0)
    pd.testing.assert_frame_equal(a.observations, b.observations)
    pd.testing.assert_frame_equal(a.truth, b.truth)
    pd.testing.assert_frame_equal(a.mislabels, b.mislabels)
    for ca, cb in zip(a.rig, b.rig, strict=True):
        assert np.array_equal(ca.K, cb.K) and np.array_equal(ca.rvec, cb.rvec) and np.array_equal(ca.tvec, cb.tvec)
    assert a.extra_toml == b.extra_toml and a.extra_toml["simulation"]["seed"] == 7
    assert not a.truth[["x", "y", "z"]].equals(c.truth[["x", "y", "z"]])


def test_mislabels_as_stated():
    """outlier_rate 0.1 mislabels round(0.1 * n_obs) rows, listed in ``mislabels``, each moved to
    another visible marker's pixels; every other row is unchanged (independent random streams)."""
    clean = _flight(seed=3, n_frames=30, n_markers=30)
    dirty = _flight(seed=3, n_frames=30, n_markers=30, outlier_rate=0.1)
    key = ["frame", "camera", "marker"]
    pd.testing.assert_frame_equal(clean.observations[key], dirty.observations[key])
    n = len(dirty.observations)
    assert len(dirty.mislabels) == round(0.1 * n)
    j = dirty.observations.merge(dirty.mislabels.assign(bad=True), on=key, how="left")
    bad = j["bad"].fillna(False).to_numpy(bool)
    moved = np.hypot(*(dirty.observations[["u", "v"]].to_numpy() - clean.observations[["u", "v"]].to_numpy()).T)
    assert (moved[~bad] == 0).all()
    # a mislabel takes another marker's projection (+ this row's 1 px noise): far from its own, and
    # within noise of some other observation of that camera and frame (measured: all but none)
    assert np.median(moved[bad]) > 20
    near_other = 0
    for r in dirty.observations[bad].itertuples():
        same = clean.observations[(clean.observations.frame == r.frame) & (clean.observations.camera == r.camera)
                                  & (clean.observations.marker != r.marker)]
        near_other += np.hypot(same.u - r.u, same.v - r.v).min() < 10
    assert near_other == bad.sum()


def test_calibration_error_as_stated():
    """Written vs true rig: camera 1 untouched; the others turned by exactly calib_rot_deg and their
    centres moved by exactly calib_trans_mm (measured to ~1e-12); observations come from the true rig."""
    ref = _flight(seed=5, n_frames=15, n_markers=16)
    sess = _flight(seed=5, n_frames=15, n_markers=16, calib_rot_deg=0.5, calib_trans_mm=5.0)
    pd.testing.assert_frame_equal(ref.observations, sess.observations)
    assert sess.true_rig is not None
    for i, (w, t, r) in enumerate(zip(sess.rig, sess.true_rig, ref.rig, strict=True)):
        assert np.array_equal(t.rvec, r.rvec) and np.array_equal(t.tvec, r.tvec)
        angle = np.degrees(np.linalg.norm(cv2.Rodrigues(w.R @ t.R.T)[0]))
        shift_mm = 1000 * np.linalg.norm(w.center_world - t.center_world)
        if i == 0:
            assert angle < 1e-9 and shift_mm < 1e-9
        else:
            assert abs(angle - 0.5) < 1e-9 and abs(shift_mm - 5.0) < 1e-9
        assert np.array_equal(w.K, t.K) and np.array_equal(w.dist, t.dist)
    chosen = _flight(seed=5, n_frames=15, n_markers=16, calib_rot_deg=1.0, calib_cameras=[0, 2])
    moved = [np.linalg.norm(cv2.Rodrigues(w.R @ t.R.T)[0]) > 0 for w, t in zip(chosen.rig, chosen.true_rig,
                                                                             strict=True)]
    assert moved == [True, False, True, False, False]
    with pytest.raises(ValueError):
        _flight(n_frames=5, calib_rot_deg=1.0, calib_cameras=[5])


def test_ear_scene():
    """Ear: two low-distortion cameras 0.4 m away, 45 deg apart; head points move < 1 mm (sub-mm
    drift); the ear tip sweeps centimetres and distal points move more than proximal ones."""
    sess = S.simulate_ear(np.random.default_rng(1), n_frames=60)
    assert len(sess.rig) == 2 and sess.fps == 250.0 and sess.motion.flight_speed_mps == 0.0
    assert (sess.motion.span_m, sess.motion.flap_hz, sess.motion.flap_angle_deg) == (0.05, 10.0, 90.0)
    c = [cam.center_world - np.array([0, 0, 0.02]) for cam in sess.rig]
    assert all(0.3 < np.linalg.norm(x) < 0.5 for x in c)
    baseline = np.degrees(np.arccos(c[0] @ c[1] / np.linalg.norm(c[0]) / np.linalg.norm(c[1])))
    assert 30 < baseline < 60
    assert all(abs(cam.dist[0]) < 0.05 for cam in sess.rig)
    xyz = sess.truth[["x", "y", "z"]].to_numpy().reshape(60, 9, 3)
    reach = np.linalg.norm(xyz - xyz.mean(axis=0), axis=-1).max(axis=0)  # (9,) [m]
    assert (reach[:3] < 1e-3).all()
    assert (np.diff(reach[3:]) > 0).all() and reach[-1] > 0.01
    # per-frame steps: the paper's d_m (3.1 mm) uses the mean angular speed; a 90 deg sinusoidal bend
    # at 10 Hz peaks at pi/4 * 2 pi * 10 rad/s = 9.9 mm per frame at a rigid 5 cm tip; the bending
    # ear's tip measured 4.8 mm, head points < 0.01 mm. Bounds: (3.1, 9.9) mm and 0.1 mm.
    step = np.linalg.norm(np.diff(xyz, axis=0), axis=-1).max(axis=0)
    assert step[:3].max() < 1e-4 and 0.0031 < step[3:].max() < 0.0099
    # every point is seen by both cameras (nothing in the way)
    assert len(sess.observations) == 2 * 60 * 9


def test_session_round_trip(tmp_path):
    """The simulated session writes and reads back; the [simulation] table rebuilds the same scene."""
    sess = _flight(seed=2, n_frames=10, n_markers=18, outlier_rate=0.05, calib_trans_mm=3.0)
    back = read_session(write_session(sess, tmp_path / "s"))
    assert back.extra_toml == sess.extra_toml and back.true_rig is not None
    assert len(back.mislabels) == len(sess.mislabels) > 0
    assert np.array_equal(S.scene_from_session(back).points_m, S.scene_from_session(sess).points_m)
    assert back.marker_names == sess.marker_names and back.skeleton == sess.skeleton
