"""Evaluation against truth: RMSE and 95 % coverage by status, robust to degenerate covariances."""

import numpy as np
import pandas as pd

from batgraph.evaluate import errors_against, truth_stats


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


def test_singular_covariance_gets_no_coverage_instead_of_crashing():
    traj = _table(np.array([1.0, 1.0]), np.array([1.0, 0.0]), ["observed", "observed"])
    truth = pd.DataFrame({"frame": [0, 1], "marker": "a", "x": 0.0, "y": 0.0, "z": 0.0})
    m2 = errors_against(traj, truth)["mahal2"].to_numpy()
    assert m2[0] == 1.0 and np.isnan(m2[1])
    assert truth_stats(traj, truth)["coverage95"]["observed"] == 1.0
