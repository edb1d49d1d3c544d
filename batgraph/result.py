"""What every estimator returns and the options they share; no estimation here."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SYNC = {"estimate": True, "given": False, None: None}
"""The ``--sync`` flag's value as Options.sync (None: not given, so session.toml's [sync] estimate decides)."""


@dataclass
class Options:
    """Options shared by the estimators (CLI flags and session.toml end up here).

    motion_model: "auto", "constant_velocity", "constant_acceleration" or "random_walk"; None = the
        session's [motion] model.
    robust: loss on projection rows: "huber", "cauchy" or "none"; robust_k its threshold [sigmas].
    outlier_rejection: with a robust loss, the smoother's rejection schedule (batgraph.solver.schedule).
    accel_psd_m2_s3: constant-velocity noise; None = session value, else chosen from the data.
    sync: estimate each camera's time offset and rolling-shutter readout with the trajectories (True), take the
        calibration's timing as it is (False), or do as session.toml's [sync] estimate says (None).
    refine_rig: refine every camera's pose with the trajectories (under its pose covariance, or a default).
    progress: show progress bars.
    solver: "fast" (batgraph's solver) or "gtsam" (GTSAM's Levenberg-Marquardt and iSAM2 on the same cost).
    """

    motion_model: str | None = None
    robust: str = "huber"
    robust_k: float = 2.0
    outlier_rejection: bool = True
    accel_psd_m2_s3: float | None = None
    sync: bool | None = None
    refine_rig: bool = False
    progress: bool = True
    solver: str = "fast"

    def estimates_sync(self, session) -> bool:
        """Whether the timing is estimated on ``session``: ``sync`` where set, else its session.toml's [sync]
        estimate."""
        if self.sync is not None:
            return self.sync
        return bool(session.extra_toml.get("sync", {}).get("estimate", False))


@dataclass
class Estimate:
    """One method's answer for a whole session.

    xyz_m: positions, shape (F, M, 3) [m, world]; NaN where the method gives no estimate.
    cov_m2: marginal covariances, shape (F, M, 3, 3) [m^2]; NaN where none.
    outlier: flagged observations, bool (C, F, M); all False when the method flags none.
    runtime_s: wall time of the estimation.
    info: method-specific figures for summary.json (chosen noise, iterations, ...).
    rig: the rig as the method used it when it estimated any of it (timing, poses; OUT/rig.toml), else None.
    """

    method: str
    xyz_m: np.ndarray
    cov_m2: np.ndarray
    outlier: np.ndarray
    runtime_s: float = 0.0
    info: dict = field(default_factory=dict)
    rig: object = None
