"""The track ends' covariances (batgraph.graph.ends): spans and distances, the backtest's hidden frames and
start, the widening per frame, and its effect on a hold-out scene's unobserved points at the track ends."""

from __future__ import annotations

import numpy as np
import pytest

from batgraph.graph import ends, schedule
from batgraph.motion import CHI2_3DOF_95
from batgraph.result import Options


def test_span_distance_counts_frames_to_the_nearest_span_end():
    n_views = np.array([[0, 0, 1],
                        [2, 0, 1],
                        [1, 0, 2],
                        [3, 1, 2],
                        [0, 0, 0],
                        [1, 0, 0]])
    dist = ends.span_distance(n_views)
    # marker 0: span frames 1-3 (a single-view frame inside it is inside); marker 1 never seen twice
    assert dist[:, 0].tolist() == [1, 0, 0, 0, 1, 2]
    assert dist[:, 1].tolist() == [-1] * 6
    assert dist[:, 2].tolist() == [2, 1, 0, 0, 1, 2]


def test_hidden_ends_hide_the_first_and_last_frames_of_long_spans_only():
    F = 40
    n_views = np.zeros((F, 3), int)
    n_views[5:35, 0] = 2  # span of 30 frames >= MIN_SPAN_FRAMES (26)
    n_views[5:25, 1] = 2  # 20 frames: too short to check on
    hide, horizon = ends.hidden_ends(n_views)
    K = ends.BACKTEST_FRAMES
    assert hide[:, 0].sum() == 2 * K and not hide[:, 1].any() and not hide[:, 2].any()
    assert horizon[5:5 + K, 0].tolist() == list(range(K, 0, -1))  # frame 5 is K frames before frame 5 + K
    assert horizon[35 - K:35, 0].tolist() == list(range(1, K + 1))
    assert (horizon[~hide] == 0).all()


def test_straight_start_continues_a_straight_track_exactly():
    F, fps = 30, 100.0
    t = np.arange(F) / fps
    xyz = (np.array([0.1, -0.2, 1.0]) + np.outer(t, [0.5, 1.0, -2.0]))[:, None, :]
    hide = np.zeros((F, 1), bool)
    horizon = np.zeros((F, 1), int)
    hide[:4, 0], horizon[:4, 0] = True, [4, 3, 2, 1]
    hide[-3:, 0], horizon[-3:, 0] = True, [1, 2, 3]
    p, v = ends.straight_start(np.where(hide[..., None], np.nan, xyz), hide, horizon, fps)
    assert np.allclose(p, xyz, atol=1e-12) and np.allclose(v[hide[:, 0], 0], [0.5, 1.0, -2.0], atol=1e-9)


def test_backtest_markers_keep_groups_whole_and_spread_a_large_set():
    long_span = np.ones(100, bool)
    long_span[[5, 6]] = False
    group = np.array([10, 11, 12, 40])
    few = ends.backtest_markers(long_span[:20], [np.array([10, 11, 12])], most=32)
    assert few.sum() == 18 and not few[[5, 6]].any()  # all markers with a long span
    many = ends.backtest_markers(long_span, [group], most=32)
    assert 32 <= many.sum() <= 35 and (many[group].all() or not many[group].any())
    assert ends.backtest_markers(long_span, [group]).sum() >= ends.BACKTEST_MARKERS  # the default cap
    picked = np.flatnonzero(many)
    assert picked.min() < 10 and picked.max() > 90  # spread over the markers, not the first 32
    assert not many[[5, 6]].any()


def test_growth_rate_recovers_a_linear_widening_and_none_where_calibrated():
    rng = np.random.default_rng(3)
    h = rng.integers(1, 9, 4000)
    chi = rng.chisquare(3, 4000)
    assert ends.growth_rate(chi, h) < 0.03  # calibrated: the 95th percentile is chi-square's (to sampling noise)
    c = ends.growth_rate(chi * (1 + 0.4 * h), h)
    assert abs(c - 0.4) < 0.06
    assert np.quantile(chi * (1 + 0.4 * h) / (1 + c * h), 0.95) == pytest.approx(CHI2_3DOF_95, rel=1e-3)
    assert ends.growth_rate(chi[:ends.MIN_SAMPLES - 1] * 10, h[:ends.MIN_SAMPLES - 1]) == 0.0  # too few


@pytest.fixture(scope="module")
def dorsal():
    from batgraph.wingbeat import simulate_wingbeat

    return simulate_wingbeat(np.random.default_rng(1), flight="straight", n_cameras=4, fps=120.0, n_frames=96,
                             flap_hz=8.0, pixel_sigma_px=2.0, marker_side="dorsal")


def test_widened_ends_cover_the_truth_on_a_hold_out_scene(dorsal):
    """On the hold-out dorsal scene (seed 1) the unobserved points after a track's end (44, on wing markers
    whose stroke the constant-velocity extrapolation does not follow) are covered by their 95 % ellipsoids on
    < 90 % without the widening (measured 84.1 %; 79.5 % with the 1 mm flapping floor before the eighteenth
    session) and >= 90 % with it (measured 100 %: the backtest's 95th-percentile ratio 5.75, c = 0.82 per frame;
    93.6 % on seed 2). No other covariance changes, and the positions do not."""
    from batgraph import evaluate
    from batgraph.pipeline import run_methods

    out = {}
    for on in (False, True):
        with pytest.MonkeyPatch.context() as mp:
            if not on:
                mp.setattr(schedule, "widen_ends", lambda *a, **k: (a[11], {}))
            res = run_methods(dorsal, ["smoother"], Options(progress=False))
        e = evaluate.point_errors(res.trajectories, dorsal.truth)
        sel = (e.status == "unobserved") & (e.span == "outside")
        out[on] = (res.estimates["smoother"], np.mean(e.mahal2[sel] <= 7.814727903251178), sel.sum())
    (bare, cov_bare, n), (wide, cov_wide, _) = out[False], out[True]
    assert n >= 30 and cov_bare < 0.9 and cov_wide >= 0.9
    fig = wide.info["track_ends"]
    assert "track_ends" not in bare.info and fig["growth_per_frame"] > 0.1 and fig["samples"] > 100
    assert np.array_equal(wide.xyz_m, bare.xyz_m, equal_nan=True)
    from batgraph.session import dense_observations
    n_views = dense_observations(dorsal).n_views
    dist = ends.span_distance(n_views)
    target = (n_views == 0) & (dist > 0)
    assert fig["widened_points"] == target.sum()
    scale = np.where(target, 1 + fig["growth_per_frame"] * dist, 1.0)
    assert np.allclose(wide.cov_m2, bare.cov_m2 * scale[..., None, None], rtol=1e-12, equal_nan=True)
