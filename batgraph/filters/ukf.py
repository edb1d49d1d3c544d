"""The paper's unscented Kalman filter (eq. 19-29), exactly as written: the same random walk,
measurement and occlusion trimming as the EKF, with 2n+1 sigma points of the whole stacked state.

The paper does not give its unscented-transform parameters; this uses the standard scaled
unscented transform of Wan & van der Merwe (2000) with their defaults alpha = 1e-3, beta = 2,
kappa = 0: lambda = alpha^2 (n + kappa) - n, sigma points x and x +- sqrt(n + lambda) columns of
chol(P), w_m[0] = lambda / (n + lambda), w_c[0] = w_m[0] + 1 - alpha^2 + beta, the rest
1 / (2 (n + lambda)). A small alpha keeps the points near the mean, which matters here: n is up to
540, and alpha = 1 would put them sqrt(540) ~ 23 standard deviations out, behind the cameras.
Initialisation as in the EKF (see :data:`.common.INIT_DESCRIPTION`).
Deliberately not here: square-root or augmented-state variants, robust losses, smoothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ..measurement import IdealObservations
from ..result import Estimate, Options
from ..session import DenseObservations, Session
from .common import LARGE_ROWS, FrameMeasurement, MeasurementNoise, dense_noise, noise_solver, run_filter, symmetrize


@dataclass(frozen=True)
class UnscentedParams:
    """Scaled unscented transform parameters (Wan & van der Merwe 2000 defaults)."""

    alpha: float = 1e-3
    beta: float = 2.0
    kappa: float = 0.0

    def weights(self, n: int) -> tuple[np.ndarray, np.ndarray, float]:
        """(w_m (2n+1,), w_c (2n+1,), gamma = sqrt(n + lambda)) for state dimension n."""
        lam = self.alpha**2 * (n + self.kappa) - n
        w = np.full(2 * n + 1, 1.0 / (2 * (n + lam)))
        wm, wc = w.copy(), w.copy()
        wm[0] = lam / (n + lam)
        wc[0] = wm[0] + 1 - self.alpha**2 + self.beta
        return wm, wc, float(np.sqrt(n + lam))


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    """A matrix L with L L^T = P: Cholesky, or (if round-off made P semi-definite) the symmetric
    eigen-square-root with negative eigenvalues clipped to zero."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(P)
        return vecs * np.sqrt(np.clip(vals, 0.0, None))


def sigma_points(x: np.ndarray, P: np.ndarray, gamma: float) -> np.ndarray:
    """UT(x, P) of eq. 19 and 23: rows x, x + gamma L_i, x - gamma L_i (L = chol P), shape (2n+1, n)."""
    L = gamma * _sqrt_psd(P)
    return np.concatenate([x[None], x[None] + L.T, x[None] - L.T])


def ukf_predict(x: np.ndarray, P: np.ndarray, sigma_m2: float,
                params: UnscentedParams = UnscentedParams()) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 19-22 with A = I and R = sigma_m2 I: sigma points, propagated, re-averaged, + R.

    Computed literally although with A = I it returns (x, P + R) up to round-off: the paper's
    filter, not a shortcut. x (n,) [m], P (n, n) [m^2].
    """
    wm, wc, gamma = params.weights(len(x))
    X = sigma_points(x, P, gamma)  # A = I: X* = X (eq. 20)
    x_pred = wm @ X
    D = X - x_pred
    return x_pred, symmetrize(D.T @ (wc[:, None] * D)) + sigma_m2 * np.eye(len(x))


def ukf_update(x: np.ndarray, P: np.ndarray, y: np.ndarray, Q: np.ndarray | MeasurementNoise,
               h: Callable[[np.ndarray], np.ndarray], params: UnscentedParams = UnscentedParams(),
               form: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Eq. 23-29 for any measurement function.

    x (n,), P (n, n): predicted state and covariance; y (m,): measurement; Q: its noise (m, m),
    dense or factored; h: maps sigma points (2n+1, n) to predicted measurements (2n+1, m), all at once.
    form "gain" is the paper's: S = sum w_c dY dY^T + Q, K = P_xy S^-1 (Cholesky solve),
    x += K (y - y_hat), P -= K S K^T. form "information" applies S^-1 by the matrix inversion lemma
    (S = Q + U W U^T with U the (m, 2n+1) deviations, W = diag(w_c)) and uses K S K^T =
    P_xy S^-1 P_xy^T: the same algebra without an m x m matrix. "auto" takes "gain" unless
    m > max(2n+1, LARGE_ROWS). P is symmetrised (see common.symmetrize).
    """
    wm, wc, gamma = params.weights(len(x))
    X = sigma_points(x, P, gamma)
    Y = h(X)
    y_hat = wm @ Y
    DY = Y - y_hat
    DYw = wc[:, None] * DY
    Pxy = (X - x).T @ DYw
    N, m = Y.shape
    if form == "auto":
        form = "information" if m > max(N, LARGE_ROWS) else "gain"
    if form == "gain":
        S = DY.T @ DYw + dense_noise(Q)
        K = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), Pxy.T).T
        return x + K @ (y - y_hat), symmetrize(P - K @ S @ K.T)
    if form != "information":
        raise ValueError(f"form must be 'auto', 'gain' or 'information', got {form!r}")
    Q_solve = noise_solver(Q)
    B = np.column_stack([Pxy.T, y - y_hat])  # (m, n + 1)
    QiU, QiB = Q_solve(DY.T), Q_solve(B)
    inner = np.eye(N) + (DY @ QiU) * wc[None, :]  # I + U^T Q^-1 U W
    SiB = QiB - QiU @ (wc[:, None] * np.linalg.solve(inner, DY @ QiB))  # S^-1 B
    n = len(x)
    return x + Pxy @ SiB[:, n], symmetrize(P - Pxy @ SiB[:, :n])


def run_ukf(session: Session, dense: DenseObservations, ideal: IdealObservations, options: Options,
            params: UnscentedParams = UnscentedParams()) -> Estimate:
    """The ``ukf`` method: filtered positions (F, M, 3) [m] and marginal covariances (F, M, 3, 3).

    The estimate of frame k uses frames <= k only. Q is evaluated at the predicted mean (it is
    additive in eq. 26). options: only ``progress`` is used.
    """

    def predict(x, P, sigma_m2):
        return ukf_predict(x, P, sigma_m2, params)

    def update(x, P, meas: FrameMeasurement):
        return ukf_update(x, P, meas.y, meas.noise(x), meas.h, params)

    info = {"ukf_alpha": params.alpha, "ukf_beta": params.beta, "ukf_kappa": params.kappa}
    return run_filter("ukf", session, dense, ideal, options, predict, update, info)
