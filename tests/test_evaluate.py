"""Evaluation against truth: RMSE and 95 % coverage by status, robust to degenerate covariances."""

import numpy as np
import pandas as pd

from batgraph.evaluate import coverage95, errors_against, rms, truth_stats
from batgraph.motion import CHI2_3DOF_95


def _table(err_x, cov_diag, status):
    n = len(err_x)
    return pd.DataFrame({"method": "m", "frame": np.arange(n), "marker": "a", "x": err_x, "y": 0.0, "z": 0.0,
                         "cov_xx": cov_diag, "cov_xy": 0.0, "cov_xz": 0.0, "cov_yy": cov_diag, "cov_yz": 0.0,
                         "cov_zz": cov_diag, "n_views": 2, "status": status})


def test_rmse_and_coverage_by_status():
    """Errors of 1 and 3 sigma along x: mahalanobis^2 1 and 9 (one inside 7.8147, one outside)."""
    traj = _table(np.array([1.0, 3.0, 2.0]), np.array([1.0, 1.0, np.nan]), ["observed", "observed", "single_view"])
    truth = pd.DataFrame({"frame": [0, 1, 2], "marker": "a", "x": 0.0, "y": 0.0, "z": 0.0})
    s = truth_stats(traj, truth)
    assert s["rmse_m"]["observed"] == np.sqrt(5.0)
    assert s["coverage95"]["observed"] == 0.5
    assert s["coverage95"]["single_view"] is None  # no covariance, no coverage figure
    assert s["rmse_m"]["all"] == np.sqrt(14 / 3)
    assert s["n"]["unobserved"] == 0 and s["rmse_m"]["unobserved"] is None


def test_rms_and_coverage95_skip_missing_values():
    assert rms(np.array([3.0, np.nan, 4.0, -np.inf])) == np.sqrt(12.5)
    assert rms(np.array([np.nan])) is None and np.isnan(rms(np.zeros(0), np.nan))
    assert coverage95(np.array([1.0, np.nan, CHI2_3DOF_95, 9.0])) == 2 / 3  # the quantile itself is inside
    assert coverage95(np.array([np.nan, np.nan])) is None


def test_coverage95_of_gaussian_errors_is_95_percent():
    """Errors drawn from the covariance itself: 95 % of them inside (binomial sd 0.2 % at 1e4 points)."""
    rng = np.random.default_rng(0)
    L = np.array([[2.0, 0.0, 0.0], [0.5, 1.0, 0.0], [-0.3, 0.2, 0.5]])
    e = rng.normal(size=(10_000, 3)) @ L.T
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(L @ L.T, e.T).T)
    assert abs(coverage95(d2) - 0.95) < 0.01


def test_singular_covariance_gets_no_coverage_instead_of_crashing():
    traj = _table(np.array([1.0, 1.0]), np.array([1.0, 0.0]), ["observed", "observed"])
    truth = pd.DataFrame({"frame": [0, 1], "marker": "a", "x": 0.0, "y": 0.0, "z": 0.0})
    m2 = errors_against(traj, truth)["mahal2"].to_numpy()
    assert m2[0] == 1.0 and np.isnan(m2[1])
    assert truth_stats(traj, truth)["coverage95"]["observed"] == 1.0


def test_stacked_reprojection_tables_are_the_single_tables_concatenated(session_folder):
    """reprojection_tables gathers the observations once; the rows, values and dtypes are those of each method's
    reprojection_table stacked (what the pipeline built before)."""
    from batgraph.evaluate import reprojection_table, reprojection_tables
    from batgraph.result import Estimate
    from batgraph.session import dense_observations, read_session

    session = read_session(session_folder)
    dense = dense_observations(session)
    C, F, M = dense.uv_px.shape[:3]
    rng = np.random.default_rng(0)
    ests = []
    for name in ("smoother", "filter", "triangulate"):
        xyz = rng.normal(size=(F, M, 3)) * 0.1
        xyz[0, 0] = np.nan
        ests.append(Estimate(name, xyz, np.full((F, M, 3, 3), np.nan), rng.random((C, F, M)) < 0.2, 0.0))
    want = pd.concat([reprojection_table(session, dense, e) for e in ests], ignore_index=True)
    got = reprojection_tables(session, dense, ests)
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert [str(d) for d in got.dtypes] == [str(d) for d in want.dtypes]


def test_method_rows_are_the_rows_of_each_method():
    from batgraph.evaluate import method_rows

    for methods in (["a", "a", "b", "b", "b", "c"], ["a", "b", "a", "c", "b"]):  # blocks, interleaved
        table = pd.DataFrame({"method": pd.Series(methods, dtype="str"), "v": np.arange(len(methods))})
        rows = method_rows(table)
        assert list(rows) == list(dict.fromkeys(methods))
        for m, r in rows.items():
            pd.testing.assert_frame_equal(table.iloc[r], table[table["method"] == m])
        assert isinstance(rows["c"], slice)
    assert method_rows(pd.DataFrame({"method": pd.Series([], dtype="str")})) == {}


def test_errors_by_method_is_each_methods_join():
    from batgraph.evaluate import errors_by_method

    a = _table(np.array([1.0, 3.0, 2.0]), np.array([1.0, 1.0, np.nan]), ["observed", "observed", "single_view"])
    traj = pd.concat([a, a.assign(method="n", x=a["x"] * 2).iloc[1:]], ignore_index=True)
    truth = pd.DataFrame({"frame": [2, 0, 1], "marker": "a", "x": 0.0, "y": 0.0, "z": 0.0})
    got = errors_by_method(traj, truth)
    for m in ("m", "n"):
        want = errors_against(traj[traj["method"] == m].assign(span="inside"), truth)
        pd.testing.assert_frame_equal(got[m], want, check_exact=True)


def test_at_time_interpolates_between_frames_and_extrapolates_straight_beyond():
    """evaluate.at_time (a detection's position at its capture time): Catmull-Rom's slopes are central differences,
    exact for a quadratic, so a quadratic track comes back exactly between interior frames; beyond the last frame
    the track goes straight on with its last step; a marker whose neighbouring frames are not estimated keeps its
    frame's value."""
    from batgraph.evaluate import at_time

    F = 10
    t = np.arange(F, dtype=float)
    track = np.stack([0.1 + 0.02 * t - 0.003 * t**2, 0.5 * t, np.ones(F)], axis=-1)[:, None, :]  # (F, 1, 3)
    track = np.concatenate([track, np.full((F, 1, 3), np.nan)], axis=1)
    track[4, 1] = [1.0, 2.0, 3.0]  # marker 1 estimated on one frame only
    f, m = np.array([2, 5, 7, 9, 4]), np.array([0, 0, 0, 0, 1])
    tau = np.array([0.3, -0.45, 0.9, 0.5, 0.25])
    got = at_time(track, f, m, tau)
    s = (f + tau)[:3]
    np.testing.assert_allclose(got[:3, 0], 0.1 + 0.02 * s - 0.003 * s**2, atol=1e-12)
    np.testing.assert_allclose(got[3], track[9, 0] + 0.5 * (track[9, 0] - track[8, 0]), atol=1e-12)
    np.testing.assert_allclose(got[4], [1.0, 2.0, 3.0])
