"""What every estimator returns and the options they share; no estimation here."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Options:
    """Options shared by the estimators (CLI flags and session.toml end up here).

    motion_model: "constant_velocity" or "random_walk"; None = the session's [motion] model.
    robust: loss on projection factors: "huber", "cauchy" or "none".
    robust_k: loss threshold in whitened units (sigmas).
    outlier_rejection: with a robust loss, the smoother first solves with a Cauchy loss from the
        triangulated track and drops the observations that solution flags before its final solve
        (batgraph.graph.smoother); ignored when robust is "none".
    accel_psd_m2_s3: constant-velocity noise; None = session value, else chosen from the data.
    noise_rule: how a noise level chosen from the data is scored, "loo" or "evidence"; None = the
        session's [motion] noise_rule (batgraph.graph.noise).
    progress: show progress bars.
    solver: "fast" (default) solves the smoother and filter with batgraph's vectorised per-marker
        solvers when every camera is fixed (they solve the GTSAM graph's problem and are tested against
        it); "gtsam" always uses GTSAM (LM / iSAM2) directly. Cameras with pose covariances always use GTSAM.
    """

    motion_model: str | None = None
    robust: str = "huber"
    robust_k: float = 2.0
    outlier_rejection: bool = True
    accel_psd_m2_s3: float | None = None
    noise_rule: str | None = None
    progress: bool = True
    solver: str = "fast"


@dataclass
class Estimate:
    """One method's answer for a whole session.

    xyz_m: positions, shape (F, M, 3) [m, world]; NaN where the method gives no estimate.
    cov_m2: marginal covariances, shape (F, M, 3, 3) [m^2]; NaN where none.
    outlier: flagged observations, bool (C, F, M); all False when the method flags none.
    runtime_s: wall time of the estimation.
    info: method-specific figures for summary.json (chosen noise, iterations, ...).
    """

    method: str
    xyz_m: np.ndarray
    cov_m2: np.ndarray
    outlier: np.ndarray
    runtime_s: float = 0.0
    info: dict = field(default_factory=dict)
