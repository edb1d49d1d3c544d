"""The motion models of the smoother and filter, in the solver's scaled state: transition, noise, gauge prior,
the position between two frames, and the normalising constants the marginal likelihood needs.

Models (``name``): "random_walk" (the paper's eq. 3-5: p' = p + w), "constant_velocity" (white-noise
acceleration of PSD q [m^2/s^3]) and "constant_acceleration" (white-noise jerk of PSD j [m^2/s^5]). A model of
order n has the state x = [p, u, w][: n + 1] per frame, u = v dt and w = a dt^2: every block in metres, which
keeps the Gauss-Newton blocks well conditioned. Noise matrices in physical units are batgraph.motion's.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..motion import constant_acceleration_Q, constant_velocity_Q

MODELS = ("random_walk", "constant_velocity", "constant_acceleration")
AUTO = "auto"  # per marker (per segment group) the one of AUTO_CANDIDATES with the larger marginal likelihood
AUTO_CANDIDATES = ("constant_velocity", "constant_acceleration")
ORDER = {"random_walk": 0, "constant_velocity": 1, "constant_acceleration": 2}
LEVEL_NAME = {"random_walk": "sigma_m", "constant_velocity": "accel_psd_m2_s3",
              "constant_acceleration": "jerk_psd_m2_s5"}
# The weak gauge priors on a chain's first frame, N(0, sigma^2) on p - p_init, v and a: they only fix what the
# data leaves free; their normalising constants enter the marginal likelihood, so models of different order
# compare (a 15 Hz wing tip of 15 cm amplitude peaks at 1300 m/s^2).
PRIOR_SIGMA = (10.0, 10.0, 1000.0)  # [m], [m/s], [m/s^2]


def check(name: str) -> str:
    if name not in MODELS:
        raise ValueError(f"motion model must be one of {MODELS}, got {name!r}")
    return name


def state_dim(name: str) -> int:
    """d, the size of one frame's state: 3 (order + 1)."""
    return 3 * (ORDER[check(name)] + 1)


def noise_scale(name: str, level: float | np.ndarray) -> float | np.ndarray:
    """s with Q(level) = s Q(1): sigma_m^2 for the random walk, q or j otherwise."""
    return np.square(level) if name == "random_walk" else np.asarray(level, float)


@functools.lru_cache(maxsize=64)
def scaled(name: str, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, Q1, P0), each (d, d): x[k+1] = A x[k] + w, w ~ N(0, noise_scale(level) Q1) [m^2], and the gauge priors'
    information on the first frame [1/m^2], all in the scaled state x = S [p, v, a], S = diag(1, dt, dt^2).
    The arrays are shared (cached): do not write into them."""
    order, I = ORDER[check(name)], np.eye(3)
    if order == 0:
        return I, I, I / PRIOR_SIGMA[0] ** 2
    s = np.repeat(dt_s ** np.arange(order + 1), 3)
    Q = (constant_velocity_Q if order == 1 else constant_acceleration_Q)(1.0, dt_s)
    A = np.kron(np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])[:order + 1, :order + 1], I)
    return A, s[:, None] * Q * s[None, :], np.diag(np.repeat(PRIOR_SIGMA[:order + 1], 3) ** -2.0 / s**2)


def log_det_scale(name: str, dt_s: float) -> float:
    """log det S of one frame: information in physical units [p m, v m/s, a m/s^2] is S Lambda S."""
    order = ORDER[check(name)]
    return 3.0 * math.log(dt_s) * order * (order + 1) / 2


def log_evidence(cost: np.ndarray, logdet_post: np.ndarray, level: np.ndarray, name: str, dt_s: float,
                 n_steps: int, n_chains: int = 1) -> np.ndarray:
    """Laplace log marginal likelihood of a noise level, up to a constant shared by every model and level:
    -E(x*) - 0.5 log det Lambda_post + 0.5 log det Lambda_prior, per chain (arrays broadcast).

    cost: E at the minimiser x* (robust data terms + motion + gauge priors); logdet_post: log det of the
    posterior information in physical units; n_steps motion steps and n_chains first-frame priors per entry.
    The prior's log det is -n_steps log det Q + n_chains log det P0 (its (2 pi)^(d F / 2) cancels the posterior's).
    """
    _, Q1, _ = scaled(name, dt_s)
    d = len(Q1)
    logdet_q = d * np.log(noise_scale(name, level)) + np.linalg.slogdet(Q1)[1] - 2 * log_det_scale(name, dt_s)
    logdet_p0 = -6.0 * float(np.log(PRIOR_SIGMA[:ORDER[name] + 1]).sum())
    return -np.asarray(cost) - 0.5 * np.asarray(logdet_post) + 0.5 * (-n_steps * logdet_q + n_chains * logdet_p0)


def interpolation(name: str, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The position at fraction s in [0, 1] of a frame interval as weights on the states at its ends.

    Returns (W (n, 2, 3), dW (n, 2, 3)): p(s) = sum_j W[:, 0, j] x_k[j] + W[:, 1, j] x_{k+1}[j] over the state's
    blocks j (p, u, w: unused entries 0) and dW = dW/ds. This is the model's posterior mean between the two
    states (its Gaussian-process interpolation: linear for the random walk, the cubic Hermite spline for constant
    velocity, the quintic one for constant acceleration), the same for every noise level.
    """
    s = np.asarray(s, float)
    W, dW = np.zeros(s.shape + (2, 3)), np.zeros(s.shape + (2, 3))
    order = ORDER[check(name)]
    if order == 0:
        W[..., 0, 0], W[..., 1, 0] = 1 - s, s
        dW[..., 0, 0], dW[..., 1, 0] = -1.0, 1.0
        return W, dW
    if order == 1:
        s2, s3 = s * s, s * s * s
        W[..., 0, :2] = np.stack([2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s], axis=-1)
        W[..., 1, :2] = np.stack([-2 * s3 + 3 * s2, s3 - s2], axis=-1)
        dW[..., 0, :2] = np.stack([6 * s2 - 6 * s, 3 * s2 - 4 * s + 1], axis=-1)
        dW[..., 1, :2] = np.stack([-6 * s2 + 6 * s, 3 * s2 - 2 * s], axis=-1)
        return W, dW
    p = np.stack([s**i for i in range(6)], axis=-1)  # 1, s, .., s^5
    dp = np.stack([np.zeros_like(s)] + [i * s ** (i - 1) for i in range(1, 6)], axis=-1)
    W[..., 0, :] = p @ _QUINTIC[:3].T
    W[..., 1, :] = p @ _QUINTIC[3:].T
    dW[..., 0, :] = dp @ _QUINTIC[:3].T
    dW[..., 1, :] = dp @ _QUINTIC[3:].T
    return W, dW


# The quintic Hermite basis, coefficients of 1, s, .., s^5, for p_k, p'_k, p''_k, p_{k+1}, p'_{k+1}, p''_{k+1}
_QUINTIC = np.array([
    [1, 0, 0, -10, 15, -6], [0, 1, 0, -6, 8, -3], [0, 0, 0.5, -1.5, 1.5, -0.5],
    [0, 0, 0, 10, -15, 6], [0, 0, 0, -4, 7, -3], [0, 0, 0, 0.5, -1, 0.5]], float)


def extrapolation(name: str, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The position s frames from one state (before the first frame or after the last, s may be negative) as
    weights on it, the model's mean (p + u s + w s^2 / 2): (W (n, 3), dW/ds (n, 3))."""
    s = np.asarray(s, float)
    order = ORDER[check(name)]
    W = np.stack([np.ones_like(s), s, 0.5 * s * s], axis=-1)
    dW = np.stack([np.zeros_like(s), np.ones_like(s), s], axis=-1)
    W[..., order + 1:] = dW[..., order + 1:] = 0.0
    return W, dW
