"""The second scene generator (batgraph.wingbeat): a rigid joint-angle wing chain, its stroke, physical
membrane occlusion, and a pipeline run on a scene batgraph was not tuned on."""

from __future__ import annotations

import math

import numpy as np
import pytest

from batgraph import evaluate, wingbeat
from batgraph.pipeline import run_methods
from batgraph.result import Options
from batgraph.session import dense_observations, read_session, write_session
from batgraph.simulate import segments_hit_triangles


def _cube(session) -> np.ndarray:
    """Truth as (F, M, 3) [m] in marker_names order."""
    t = session.truth.set_index(["frame", "marker"]).sort_index()
    F, names = session.truth["frame"].nunique(), session.marker_names
    return np.stack([t.xs(m, level="marker")[["x", "y", "z"]].to_numpy() for m in names], axis=1).reshape(F, -1, 3)


@pytest.fixture(scope="module")
def straight():
    return wingbeat.simulate_wingbeat(np.random.default_rng(1))  # 5 cameras, 120 fps, 72 frames, 1 px


@pytest.mark.parametrize("flight", wingbeat.FLIGHTS)
def test_bones_and_body_are_rigid(flight):
    """Every pair in [markers] rigid keeps its distance to 1e-9 m; bones are the documented lengths x the bat's size."""
    s = wingbeat.simulate_wingbeat(np.random.default_rng(7), flight=flight, fps=250.0, n_frames=100,
                                   marker_side="dorsal")
    xyz, idx = _cube(s), {m: i for i, m in enumerate(s.marker_names)}
    assert s.rigid and all(a in idx and b in idx for a, b in s.rigid)
    for a, b in s.rigid:
        d = np.linalg.norm(xyz[:, idx[a]] - xyz[:, idx[b]], axis=-1)
        assert d.max() - d.min() < 1e-9, (a, b)
    scale = s.extra_toml["wingbeat"]["size_scale"]
    d = np.linalg.norm(xyz[:, idx["L_wrist"]] - xyz[:, idx["L_elbow"]], axis=-1)
    assert d[0] == pytest.approx(wingbeat.BONES_M["radius"] * scale, abs=1e-12)
    # the wings really move: the wingtip is not rigid to the body (except in a glide, where it nearly is)
    tip = np.linalg.norm(xyz[:, idx["R_tip3"]] - xyz[:, idx["head"]], axis=-1)
    assert np.ptp(tip) > (0.02 if flight != "glide" else 0.0)


@pytest.mark.parametrize("amplitude_deg", [80.0, 100.0, 120.0])
def test_stroke_amplitude_and_downstroke(amplitude_deg):
    """The humerus sweeps exactly the stroke amplitude about the stroke axis; the wingtip (digit III), with the
    distal wing's lag and bends, sweeps 1.0-1.2x it (measured 1.06-1.12x); the downstroke lasts D; the wing
    folds on the upstroke (span ratio measured 0.55)."""
    D, tilt = 0.55, 25.0
    p = np.linspace(0, 1, 2001)
    s = wingbeat.stroke_phase(p, D)
    assert wingbeat.stroke_phase(np.array([D]), D)[0] == pytest.approx(0.5, abs=1e-12)
    assert np.all(np.diff(s) > 0)
    joints, _ = wingbeat.wing_chain(wingbeat.wing_angles(s, amplitude_deg), tilt)
    g = math.radians(tilt)
    m = np.array([-math.sin(g), 0, math.cos(g)])  # with outward (y), spans the plane normal to the stroke axis

    def sweep(point):  # angle about the stroke axis, up from the outward direction [deg]
        d = joints[point] - joints["shoulder"]
        return np.degrees(np.arctan2(d @ m, d[:, 1]))

    hum = np.degrees(wingbeat.wing_angles(s, amplitude_deg)["stroke"])
    assert np.ptp(hum) == pytest.approx(amplitude_deg, abs=1e-3)
    assert amplitude_deg <= np.ptp(sweep("tip3")) <= 1.2 * amplitude_deg
    top, bottom = p[np.argmax(hum)], p[np.argmin(hum)]
    assert bottom - top == pytest.approx(D, abs=1e-3)
    reach = np.max(np.stack([joints[j][:, 1] for j in ("wrist", "tip3", "tip4", "tip5")]), axis=0)
    mid_down, mid_up = reach[np.argmin(np.abs(s - 0.25))], reach[np.argmin(np.abs(s - 0.75))]
    assert 0.4 < mid_up / mid_down < 0.75


def test_span_speed_and_paths():
    """A 20-30 cm span bat at the stated speed; a turn changes heading by yaw rate x duration; a glide descends."""
    for flight in wingbeat.FLIGHTS:
        s = wingbeat.simulate_wingbeat(np.random.default_rng(3), flight=flight, n_frames=120, fps=200.0)
        p, xyz = s.extra_toml["wingbeat"], _cube(s)
        idx = {m: i for i, m in enumerate(s.marker_names)}
        span = np.linalg.norm(xyz[:, idx["R_tip3"]] - xyz[:, idx["L_tip3"]], axis=-1).max()
        assert 0.18 < span < 0.34, span
        body = xyz[:, idx["rump"]]
        v = np.diff(body, axis=0) * s.fps
        speed = np.linalg.norm(v[:, :2], axis=1).mean()
        assert speed == pytest.approx(p["speed_mps"], rel=0.05)
        heading = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
        turned = math.degrees(heading[-10:].mean() - heading[:10].mean())
        if flight == "turn":
            assert abs(p["yaw_rate_deg_s"]) >= 60
            expect = p["yaw_rate_deg_s"] * 109 / s.fps  # the two means are 109 frames apart
            assert turned == pytest.approx(expect, rel=0.1)
        else:
            assert abs(turned) < 5
        climb = (body[-1, 2] - body[0, 2]) / np.linalg.norm(body[-1, :2] - body[0, :2])
        assert climb == pytest.approx(-math.tan(math.radians(8)) if flight == "glide" else 0.0, abs=0.02)


def test_membrane_hides_markers(straight):
    """A marker whose ray from a camera crosses a wing-membrane triangle is never observed by that camera, such
    rays exist, and some points are single-view only because of them."""
    p = straight.extra_toml["wingbeat"]
    scene = wingbeat.wingbeat_scene(p)
    centers = np.stack([c.center_world for c in straight.rig])
    dense = dense_observations(straight)
    assert len(dense.frames) == p["n_frames"] and dense.markers == scene.marker_names
    F = p["n_frames"]
    blocked = np.stack([segments_hit_triangles(centers, scene.points_m[f], scene.triangles_m[f]) for f in range(F)],
                       axis=1)  # (C, F, M)
    uv = straight.rig.project(scene.points_m)
    in_view = np.isfinite(uv[..., 0]) & np.stack([c.in_image(uv[i]) for i, c in enumerate(straight.rig)])
    assert (blocked & in_view).sum() > 50
    assert not (dense.seen & blocked).any()
    n_views = dense.n_views
    assert ((n_views == 1) & (in_view & blocked).any(axis=0)).sum() > 0  # single-view: the membrane took a view


def test_dorsal_markers_hide_more(straight):
    """Markers on the dorsal skin are also hidden from the wing's ventral side: fewer observations, same truth."""
    d = wingbeat.simulate_wingbeat(np.random.default_rng(1), marker_side="dorsal")
    assert np.array_equal(d.truth[["x", "y", "z"]].to_numpy(), straight.truth[["x", "y", "z"]].to_numpy())
    assert len(d.observations) < 0.97 * len(straight.observations)
    key = ["frame", "camera", "marker"]
    both = straight.observations.merge(d.observations, on=key, suffixes=("", "_d"))
    assert len(both) == len(d.observations)  # dorsal only removes observations, same noise on the others
    assert np.array_equal(both["u"].to_numpy(), both["u_d"].to_numpy())


def test_session_states_no_motion_physics_and_round_trips(straight, tmp_path):
    """Nothing in the session comes from batgraph's motion models; [wingbeat] and [markers] rigid survive a write."""
    assert not straight.motion.has_physics and straight.motion.accel_psd_m2_s3 is None
    assert straight.motion.sigma_m is None
    assert straight.pixel_sigma_px == 1.0
    again = wingbeat.simulate_wingbeat(np.random.default_rng(1))
    assert again.observations.equals(straight.observations)
    back = read_session(write_session(straight, tmp_path / "wb"))
    assert back.extra_toml["wingbeat"] == straight.extra_toml["wingbeat"]
    assert back.rigid == straight.rigid
    with pytest.raises(ValueError):
        wingbeat.simulate_wingbeat(np.random.default_rng(1), flight="hover")
    drawn = wingbeat.simulate_wingbeat(np.random.default_rng(2), pixel_sigma_px=None, n_frames=10)
    lo, hi = wingbeat.PIXEL_SIGMA_PX_RANGE
    assert lo <= drawn.pixel_sigma_px <= hi and lo <= drawn.extra_toml["wingbeat"]["pixel_sigma_px"] <= hi


def test_pipeline_on_the_hold_out_scene(straight):
    """Smoother and triangulation run on the held-out generator; the smoother estimates every point and its
    RMSE on observed points is finite and a sane size (measured 1.4-1.8 mm at 1 px over seeds; bound 10 mm)."""
    res = run_methods(straight, ["smoother", "triangulate"], Options(progress=False))
    traj = res.trajectories
    sm = evaluate.truth_stats(traj[traj["method"] == "smoother"], straight.truth)
    tri = evaluate.truth_stats(traj[traj["method"] == "triangulate"], straight.truth)
    assert sm["n_estimated"]["all"] == sm["n"]["all"] == 72 * 14
    assert np.isfinite(sm["rmse_m"]["observed"]) and sm["rmse_m"]["observed"] < 0.010
    assert np.isfinite(tri["rmse_m"]["observed"]) and tri["rmse_m"]["observed"] < 0.010
