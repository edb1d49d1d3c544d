"""Choosing the motion model and its noise level: given values, or the constant-velocity q from the data.

Rule for the smoother (documented in the README): when neither ``options.accel_psd_m2_s3`` nor the
session's ``[motion] accel_psd_m2_s3`` sets it, the white-noise acceleration PSD q [m^2/s^3] is the
maximiser of the Laplace approximation of the marginal likelihood (type-II maximum likelihood)

    log p(y | q) ~ -E(x*) - 0.5 log det Lambda_post + 0.5 log det Lambda_prior(q) + const,

E = the graph's total cost at its optimum x* for this q, Lambda_post = its Gauss-Newton information
(from GTSAM's elimination), and log det Lambda_prior(q) = -n_steps log det Q(q) + const per marker
chain (the prior over a chain is x0 times one transition per step; the frame-0 gauge priors do not
depend on q). The search is on log10 q over 1 .. 1e6 m^2/s^3: a grid at every decade, then golden
section around the best grid point. The score itself is computed by the caller (a GTSAM graph in
:mod:`batgraph.graph.smoother`), so any solver of the same cost can reuse this search. With outlier
rejection the smoother scores only the observations its Cauchy cleaning step kept (mislabels
inflated q: 26 instead of 20 on the simulated flight with 5 % of them).

Rule for the filter, which must not see the future: the session/option value if given, else
:func:`causal_accel_psd` from the motion config alone. This module does not build graphs.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from tqdm.auto import tqdm

from ..motion import random_walk_sigma_m
from ..result import Options
from ..session import Session
from .factors import MOTION_MODELS

LOG10_Q_RANGE = (0.0, 6.0)  # plausible accel PSD 1 .. 1e6 m^2/s^3
LOG10_Q_TOL = 0.05  # golden-section stops when the bracket is this narrow (12 % in q; the peak is flat)
_GOLDEN = (math.sqrt(5) - 1) / 2


def motion_choice(session: Session, options: Options) -> tuple[str, float | None, float | None]:
    """(model, sigma_m, accel_psd) from options first, then session.toml.

    sigma_m [m]: the random walk's per-axis std per frame (paper eq. 4-5 or ``sigma_m``), always given.
    accel_psd [m^2/s^3]: options.accel_psd_m2_s3, else the session's, else None ("choose from data").
    """
    model = options.motion_model or session.motion.model
    if model not in MOTION_MODELS:
        raise ValueError(f"motion model must be one of {MOTION_MODELS}, got {model!r}")
    q = options.accel_psd_m2_s3 if options.accel_psd_m2_s3 is not None else session.motion.accel_psd_m2_s3
    return model, random_walk_sigma_m(session.motion, session.fps), None if q is None else float(q)


def cv_logdet_Q(accel_psd_m2_s3: float, dt_s: float) -> float:
    """log det Q(q, dt) of one constant-velocity step, Q (6, 6) = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I3.

    det of the 2x2 per axis is q^2 dt^4 / 12, so log det Q = 3 log(q^2 dt^4 / 12).
    """
    return 3.0 * math.log(accel_psd_m2_s3**2 * dt_s**4 / 12.0)


def laplace_log_evidence(error: float, logdet_post: float, accel_psd_m2_s3: float, dt_s: float,
                         n_steps: int) -> float:
    """Laplace log marginal likelihood up to a q-independent constant (module docstring).

    error: total cost E(x*) (0.5 sum of squared whitened residuals, robust where robust).
    logdet_post: log det of the posterior information at x* (GTSAM's Bayes tree logDeterminant
        is half of it: it is log det R, R^T R = Lambda).
    n_steps: number of constant-velocity steps in the graph (sum over marker chains of F - 1).
    """
    logdet_prior = -n_steps * cv_logdet_Q(accel_psd_m2_s3, dt_s)
    return -error - 0.5 * logdet_post + 0.5 * logdet_prior


def maximise_log10(score: Callable[[float], float], lo: float = LOG10_Q_RANGE[0], hi: float = LOG10_Q_RANGE[1],
                   tol: float = LOG10_Q_TOL, progress: bool = False) -> tuple[float, list[tuple[float, float]]]:
    """Maximise ``score(q)`` over log10 q in [lo, hi]: decade grid, then golden section around the best.

    Returns (q*, [(q, score), ...] in evaluation order). ``score`` is called with q (not its log);
    callers warm-start each solve from the previous one, so the order is kept monotone on the grid.
    """
    n_golden = math.ceil(math.log(tol / 2.0) / math.log(_GOLDEN)) + 2
    grid = np.arange(math.ceil(lo), math.floor(hi) + 1, dtype=float)
    bar = tqdm(total=len(grid) + n_golden, desc="choosing accel PSD", disable=not progress, leave=False)
    trace: list[tuple[float, float]] = []
    cache: dict[float, float] = {}

    def f(x: float) -> float:
        if x not in cache:
            cache[x] = score(10.0**x)
            trace.append((10.0**x, cache[x]))
            bar.update()
        return cache[x]

    best = max(grid, key=f)
    a, b = max(lo, best - 1.0), min(hi, best + 1.0)
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    while b - a > tol:
        if f(c) >= f(d):
            b, d = d, c
            c = b - _GOLDEN * (b - a)
        else:
            a, c = c, d
            d = a + _GOLDEN * (b - a)
    x_best = max(cache, key=cache.get)
    bar.close()
    return 10.0**x_best, trace


def causal_accel_psd(session: Session) -> float:
    """Constant-velocity q [m^2/s^3] from the motion config alone (the filter's default; sees no data).

    The paper's eq. 4 bounds a wing's speed by the flap's peak speed alpha_f l_w f_f. A sinusoidal
    flap with that peak speed has peak acceleration a = 2 pi f_f alpha_f l_w f_f, and its velocity
    changes per frame by a sin(.) dt, of mean square a^2 dt^2 / 2 (3-D). White-noise acceleration
    of PSD q changes it by 3 q dt per frame (3 axes); matching the two gives q = a^2 dt / 6.
    Steady flight adds no acceleration. Paper flight values (4 Hz, 90 deg, 0.5 m, 120 fps):
    q = 8.7 m^2/s^3; on the simulated flight the truth's own per-frame velocity changes give 9.2 and
    the smoother's marginal likelihood 20. Without a flap (a = 0) q is the range's floor, 1.
    """
    m, fps = session.motion, session.fps
    a = 2 * math.pi * m.flap_hz * math.radians(m.flap_angle_deg) * m.span_m * m.flap_hz
    return max(a * a / fps / 6.0, 10.0 ** LOG10_Q_RANGE[0])
