"""The paper's extended Kalman filter (eq. 11-18), exactly as written: random walk over the stacked
positions of all markers, pinhole measurement in ideal pixels, occluded rows trimmed per frame.

Initialisation: each marker enters the state at its first triangulated frame, with the
triangulated position and its first-order covariance (see :data:`.common.INIT_DESCRIPTION`).
Deliberately not here: robust losses, iterations (IEKF), smoothing, outlier rejection.
Naming follows the paper: R is the process covariance, Q the measurement covariance.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ..measurement import IdealObservations
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from .common import LARGE_ROWS, FrameMeasurement, MeasurementNoise, dense_noise, noise_solver, run_filter, symmetrize


def ekf_predict(x: np.ndarray, P: np.ndarray, sigma_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 11-12 with A = I and R = sigma_m2 I: x (3n,) [m] unchanged, P (3n, 3n) [m^2] + R."""
    return x, P + sigma_m2 * np.eye(len(x))


def ekf_update(x: np.ndarray, P: np.ndarray, y: np.ndarray, h_x: np.ndarray, H: np.ndarray,
               Q: np.ndarray | MeasurementNoise, form: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Eq. 13-15 for any measurement linearised at x.

    x (n,), P (n, n): predicted state and covariance; y (m,): measurement; h_x (m,): h(x);
    H (m, n): dh/dx at x; Q: measurement covariance (m, m), dense or factored.
    form "gain" is the paper's: K = P H^T (H P H^T + Q)^-1 (Cholesky solve), x += K (y - h(x)),
    P = (I - K H) P. form "information" is the same algebra by the matrix inversion lemma,
    P = (P^-1 + H^T Q^-1 H)^-1, x += P H^T Q^-1 (y - h(x)): it factorises n x n instead of m x m.
    "auto" takes "gain" unless m > max(n, LARGE_ROWS). P is symmetrised (see common.symmetrize).
    """
    m, n = H.shape
    if form == "auto":
        form = "information" if m > max(n, LARGE_ROWS) else "gain"
    if form == "gain":
        PHt = P @ H.T
        S = H @ PHt + dense_noise(Q)
        K = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), PHt.T).T
        return x + K @ (y - h_x), symmetrize(P - K @ PHt.T)  # K H P = K (P H^T)^T, P symmetric
    if form != "information":
        raise ValueError(f"form must be 'auto', 'gain' or 'information', got {form!r}")
    Q_solve = noise_solver(Q)
    QiHr = Q_solve(np.column_stack([H, y - h_x]))
    info = scipy.linalg.cho_solve(scipy.linalg.cho_factor(P), np.eye(n)) + H.T @ QiHr[:, :n]
    factor = scipy.linalg.cho_factor(symmetrize(info))
    return x + scipy.linalg.cho_solve(factor, H.T @ QiHr[:, n]), symmetrize(scipy.linalg.cho_solve(factor, np.eye(n)))


def _frame_update(x: np.ndarray, P: np.ndarray, meas: FrameMeasurement) -> tuple[np.ndarray, np.ndarray]:
    return ekf_update(x, P, meas.y, meas.h(x), meas.jacobian(x), meas.noise(x))


def run_ekf(session: Session, dense: DenseObservations, ideal: IdealObservations,
            options: Options) -> Estimate:
    """The ``ekf`` method: filtered positions (F, M, 3) [m] and marginal covariances (F, M, 3, 3).

    The estimate of frame k uses frames <= k only. options: only ``progress`` is used (the
    paper's filter has no robust loss).
    """
    return run_filter("ekf", session, dense, ideal, options, ekf_predict, _frame_update)
