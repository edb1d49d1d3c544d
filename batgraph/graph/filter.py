"""The online filter: iSAM2 fed one frame at a time; frame k's answer uses frames <= k only.

Same factors as the smoother (:mod:`batgraph.graph.factors`). A marker joins at its first frame
with a triangulation (>= 2 views), initialised there with the smoother's weak gauge priors (velocity
prior at 0); its outputs before that are NaN. From then on it gets variables on every frame, with
the motion factor even when unobserved. The constant-velocity q is the session/option value, else
:func:`batgraph.graph.noise.causal_accel_psd` of the motion config: no data, so no look-ahead.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import gtsam
import numpy as np
from tqdm.auto import tqdm

from ..measurement import IdealObservations
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from ..triangulate import dlt_points
from . import factors
from .factors import MotionFactors, ObservationFactors
from .noise import filter_motion  # defined without GTSAM for the fast filter

RELINEARIZE_THRESHOLD = 1e-5  # [m] (and [m/s], [rad]): relinearise a variable when its delta exceeds it
EXTRA_UPDATES = 2  # further iSAM2 steps per frame (relinearisation) while the newest points still move
SETTLED_M = 1e-7  # ... by more than this [m]


class IncrementalSolver:
    """iSAM2 in the VisualISAM2Example style: add new factors and values, update, clear."""

    def __init__(self, relinearize_threshold: float = RELINEARIZE_THRESHOLD):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = 1
        params.setFactorization("QR")  # Cholesky rejects long single-view stretches (see smoother.py)
        self.isam = gtsam.ISAM2(params)
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()

    def add(self, new_factors: list[gtsam.NonlinearFactor], new_values: gtsam.Values | None = None) -> None:
        for f in new_factors:
            self.new_factors.push_back(f)
        if new_values is not None:
            self.new_values.insert(new_values)

    def update(self, watch_keys: list[int] = (), extra_updates: int = EXTRA_UPDATES) -> None:
        """One iSAM2 update with what was added, then up to ``extra_updates`` relinearising steps
        while any of ``watch_keys`` (Point3) still moves by more than SETTLED_M."""
        if self.new_factors.size() == 0 and self.new_values.size() == 0:
            return
        self.isam.update(self.new_factors, self.new_values)
        self.new_factors.resize(0)
        self.new_values.clear()
        before = self.points(watch_keys)
        for _ in range(extra_updates):
            self.isam.update()
            after = self.points(watch_keys)
            if len(watch_keys) == 0 or np.abs(after - before).max() <= SETTLED_M:
                break
            before = after

    def points(self, keys: list[int]) -> np.ndarray:
        """Current estimates of Point3 ``keys``, (n, 3)."""
        return np.array([self.isam.calculateEstimatePoint3(k) for k in keys]).reshape(-1, 3)

    def covariances(self, keys: list[int]) -> np.ndarray:
        """Current marginal covariances of ``keys``, (n, d, d)."""
        return np.array([self.isam.marginalCovariance(k) for k in keys])


def run_filter(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options,
               on_frame: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> Estimate:
    """The ``filter`` method: frame-by-frame iSAM2.

    ideal: ideal pixels (C, F, M, 2) and covariances (C, F, M, 2, 2) (batgraph.measurement).
    on_frame(k_index, xyz (M, 3) [m], cov (M, 3, 3) [m^2]): called after each frame's update (live
        viewer), NaN for markers that have not joined.
    Returns Estimate(method="filter"): xyz_m (F, M, 3) and cov_m2 (F, M, 3, 3) as they were right
    after frame k's update; outlier (C, F, M) from those per-frame estimates (|r|^2 > 13.8155).
    """
    t0 = time.perf_counter()
    C, F, M = ideal.seen.shape
    model, info = filter_motion(session, options)
    motion = MotionFactors(model)
    obs = ObservationFactors(session.rig, ideal, options.robust, options.robust_k)
    tri = dlt_points(session.rig, ideal)
    joinable = np.isfinite(tri).all(axis=-1)  # (F, M)
    solver = IncrementalSolver()
    solver.add(*obs.camera_priors())
    active = np.zeros(M, bool)
    last_p, last_u = np.zeros((M, 3)), np.zeros((M, 3))  # u = v dt [m/frame] (factors.v_key)
    xyz = np.full((F, M, 3), np.nan)
    cov = np.full((F, M, 3, 3), np.nan)
    for k in tqdm(range(F), desc="filter", disable=not options.progress, leave=False):
        values = gtsam.Values()
        new = []
        for m in np.flatnonzero(active):
            new.append(motion.between(int(m), k - 1))
            values.insert(factors.p_key(int(m), k), last_p[m] + last_u[m])  # predicted (u = 0 for a random walk)
            if model.has_velocity:
                values.insert(factors.v_key(int(m), k), last_u[m])
        for m in np.flatnonzero(~active & joinable[k]):
            new += factors.prior_factors(model, int(m), k, tri[k, m])
            values.insert(factors.p_key(int(m), k), tri[k, m])
            if model.has_velocity:
                values.insert(factors.v_key(int(m), k), np.zeros(3))
        active |= joinable[k]
        markers = np.flatnonzero(active)
        new += obs.frame(k, markers)
        solver.add(new, values)
        keys = [factors.p_key(int(m), k) for m in markers]
        solver.update(keys)
        if len(markers):
            xyz[k, markers] = last_p[markers] = solver.points(keys)
            cov[k, markers] = solver.covariances(keys)
            if model.has_velocity:
                last_u[markers] = solver.points([factors.v_key(int(m), k) for m in markers])
        if on_frame is not None:
            on_frame(k, xyz[k], cov[k])
    rig = obs.solved_rig(solver.isam.calculateEstimate()) if obs.any_variable else session.rig
    outlier = factors.outlier_flags(rig, ideal, xyz)
    info.update({"motion_model": model.name, "robust": options.robust, "robust_k": options.robust_k,
                 "camera_variables": int(obs.variable.sum()), "relinearize_threshold": RELINEARIZE_THRESHOLD})
    return Estimate("filter", xyz, cov, outlier, time.perf_counter() - t0, info)
