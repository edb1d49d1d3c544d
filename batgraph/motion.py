"""Motion models: the paper's random walk (eq. 3-5) and a constant-velocity (white-noise acceleration)
prior, as noise matrices in physical units. Choosing a noise level from data lives with the estimators.
"""

from __future__ import annotations

import math

import numpy as np

from .session import MotionConfig

CHI2_3DOF_95 = 7.814727903251178  # 95 % quantile of chi-square, 3 DOF (the paper rounds it to 7.8147, eq. 5)


def max_motion_per_frame_m(motion: MotionConfig, fps: float) -> float:
    """Paper eq. 4: d_m = sqrt((v_f / f_c)^2 + (alpha_f l_w f_f / f_c)^2) [m]."""
    alpha = math.radians(motion.flap_angle_deg)
    return math.hypot(motion.flight_speed_mps / fps, alpha * motion.span_m * motion.flap_hz / fps)


def random_walk_sigma_m(motion: MotionConfig, fps: float) -> float:
    """Per-axis std of the random walk per frame [m]: ``sigma_m`` if set, else sqrt(d_m^2 / 7.8147) (eq. 5)."""
    if motion.sigma_m is not None:
        return float(motion.sigma_m)
    return max_motion_per_frame_m(motion, fps) / math.sqrt(CHI2_3DOF_95)


def constant_velocity_Q(accel_psd_m2_s3: float, dt_s: float) -> np.ndarray:
    """Process covariance of one step of the constant-velocity model, shape (6, 6).

    State [p (3) m, v (3) m/s]; continuous white-noise acceleration of PSD q [m^2/s^3]:
    ``Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]``; transition ``F = [[I, dt I], [0, I]]``.
    """
    q, dt = accel_psd_m2_s3, dt_s
    I = np.eye(3)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def constant_velocity_F(dt_s: float) -> np.ndarray:
    """Transition matrix of the constant-velocity model, shape (6, 6)."""
    return np.block([[np.eye(3), dt_s * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
