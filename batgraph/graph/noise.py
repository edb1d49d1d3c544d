"""Choosing the motion model and its noise level: given values, or the model and its noise from the data.

Rule for the smoother (documented in the README): when neither ``options.accel_psd_m2_s3`` nor the
session's ``[motion] accel_psd_m2_s3`` sets it, the white-noise acceleration PSD q [m^2/s^3] is the
maximiser of the Laplace approximation of the marginal likelihood (type-II maximum likelihood)

    log p(y | q) ~ -E(x*) - 0.5 log det Lambda_post + 0.5 log det Lambda_prior(q) + const,

E = the graph's total cost at its optimum x* for this q, Lambda_post = its Gauss-Newton information
(from GTSAM's elimination), and log det Lambda_prior(q) = -n_steps log det Q(q) + const per marker
chain (the prior over a chain is x0 times one transition per step; the frame-0 gauge priors do not
depend on q). The search is on log10 q over 0.01 .. 1e6 m^2/s^3: a grid at every decade, then golden
section around the best grid point (:func:`maximise_log10`, one q for all markers), or per marker (as
:func:`batgraph.graph.fast.choose_noise_per_marker` runs it) from the evidence's values and slopes
(:class:`SlopeSearch`: the slope d/d ln q = E_motion(x*) + 0.5 tr(Lambda_post^-1 Lambda_motion) - 0.5 n_steps d
comes with the posterior's lag-one covariances in one backward sweep after the log det's forward one (56 against
29 ms at 160 frames x 180 markers); its zero is EM's fixed
point), or, for the "loo" rule and the oscillating model, a grid every LOG10_GRID_STEP decades, then Brent's
search per marker (:class:`Bracket`). With outlier
rejection the smoother scores only the observations its Cauchy cleaning step kept (mislabels inflated q:
26 instead of 20 on the simulated flight with 5 % of them).

q is chosen PER MARKER (:func:`choose_accel_psd_per_marker`): with fixed cameras the markers are
independent, so the evidence is a sum of per-marker terms and each marker's q maximises its own term
exactly (wing tips accelerate far more than the body: on the simulated flight body markers get
q ~ 0.03-1, elbows ~3, wrists ~18, digit tips 30-56 m^2/s^3). One global q (~20) made the body's
extrapolation at the sequence ends too loose and the tips' too tight (95 % coverage of single-view
points at the ends 75-78 %). With camera variables the markers share the cameras; the smoother then
scores each marker with the cameras held at their calibrated means (the evidence conditional on
them), which kept the per-marker accuracy (a global q cost 8.6 % RMSE there). :func:`maximise_log10`
takes a score computed by the caller, so any solver of the same cost can reuse the search. The search
itself is in :mod:`batgraph.graph.fast` (it needs the solver); this module imports no solver and no GTSAM.

The MODEL is chosen per marker the same way (``[motion] model = "auto"``;
opt-in, constant velocity is the default):
:func:`batgraph.graph.fast.choose_model_per_marker` runs the search above for each model of
cost.AUTO_CANDIDATES (constant velocity, q [m^2/s^3]; constant acceleration, white-noise jerk PSD j
[m^2/s^5] over log10 j in LOG10_RANGE) and keeps per marker the model whose best evidence is larger.
The two evidences are comparable because both are the same data term (the same observations, the
same robust loss) times a normalised Gaussian prior over the marker's chain, and the Laplace formula
above is then complete when log det Lambda_prior includes the gauge priors on the first frame
(:func:`prior_logdet`): their normalising constants differ between models (constant acceleration has
a third prior, on a[0]); the (2 pi)^(d F / 2) of prior and posterior cancel, and so do units (log det
of posterior and prior are taken in the same variables). An explicit model keeps that model.

Rule for the filter, which must not see the future: the session/option value if given, else
:func:`causal_accel_psd` from the motion config alone. This module does not build graphs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from ..motion import G_MPS2, random_walk_sigma_m
from ..result import Options
from ..session import NOISE_RULES, Session  # noqa: F401  (NOISE_RULES re-exported)
from .cost import (
    AUTO_CANDIDATES,
    MOTION_MODELS,
    MOTION_ORDER,
    OSCILLATING,
    PRIOR_ACCELERATION_SIGMA_MPS2,
    PRIOR_POSITION_SIGMA_M,
    PRIOR_VELOCITY_SIGMA_MPS,
    SELECTORS,
    WINGBEAT_CANDIDATES,
    MotionModel,
    Oscillation,
    log_det_scale,
    noise_scale,
    oscillating_motion,
    scaled_motion,
)

LOG10_Q_RANGE = (-2.0, 6.0)  # plausible accel PSD 0.01 (a gliding body) .. 1e6 m^2/s^3
# The search range of each model's noise level chosen from data: log10 of q [m^2/s^3] (constant velocity)
# or of the jerk PSD j [m^2/s^5] (constant acceleration: a body changing its acceleration by ~1 m/s^2 in
# a second, j ~ 1, .. a 15 Hz wing tip, j ~ (2 pi 15)^6 0.15^2 / (2 pi 15) ~ 1e9)
LOG10_RANGE = {"constant_velocity": LOG10_Q_RANGE, "constant_acceleration": (0.0, 10.0), OSCILLATING: LOG10_Q_RANGE}
NOISE_UNIT = {"random_walk": "sigma_m", "constant_velocity": "accel_psd_m2_s3",
              "constant_acceleration": "jerk_psd_m2_s5", OSCILLATING: "oscillating_accel_psd_m2_s3"}
# The oscillating model's two levels (batgraph.graph.fast.choose_noise_per_marker): the first harmonic's std
# sigma_m [m] in 10^-4 (0.1 mm: a body's bob seen through a few pixels of noise) .. 10^-1 (a wing tip), searched
# jointly with the trend's q on a grid of decades of sigma_m x every LOG10_GRID_STEP decades of q, then refined.
OSC_LOG10_SIGMA_RANGE = (-4.0, -1.0)
# The per-marker grid of the "loo" rule and the oscillating model (batgraph.graph.fast.choose_noise_per_marker; the
# evidence's q and j use SlopeSearch, no grid): every LOG10_GRID_STEP decades of the level, then Brent's search
# within a step of the grid's best point. Every
# 2 decades instead of every decade: the chosen q moved <= 0.022 decade (the search's tolerance is LOG10_Q_TOL),
# each marker's evidence -0.07..+0.05 nats, on 8 simulated and hold-out scenes (BENCHMARKS.md), in 0.6-0.8x the time.
LOG10_GRID_STEP = 2.0
CAUSAL_Q_FLOOR = 1.0  # the filter's q without a flap [m^2/s^3]: it sees no data, so stays loose
# When the tracks flap (batgraph.graph.schedule.periodic_advice finds a wingbeat at f Hz; every model but "wingbeat",
# whose oscillating candidate follows the bob instead, and only for a q chosen from the data), no marker is taken
# to move on a straight line: its constant-velocity q is kept >= :func:`flapping_q_floor`, the q of the heave of a
# body whose lift swings by FLAPPING_LIFT_SWING body weights over the stroke (:func:`flapping_heave_m`). Why: a body
# marker bobbing with the wingbeat by less than the pixel noise (2.3-2.6 mm RMS, 0.6-0.8 px under 2 px of noise on
# the hold-out dorsal scene) leaves an evidence that falls monotonically to the search's floor (q = 0.01; -29 nats at
# q = 1), and the straight track's ellipsoids then held 26-59 % of those markers' truths on the hold-out scenes that
# flap (dorsal, 15 Hz, 10 Hz); their RMSE was the same or lower at the floor. Until the eighteenth session the floor
# was a 1 mm oscillation, an assumed least heave: the dorsal scene's observed points were then still covered 89.5 %
# (its body markers 63-81 %). The heave of a lift that swings by one weight (most of it on the downstroke, little on
# the upstroke: F = m g (1 + cos w t)) is a first-principles figure, not fitted to a scene: g / w^2, 3.9 mm at 8 Hz,
# 1.1 mm at 15 Hz, 16 mm at 4 Hz; the hold-out generator's body bobs +-3 mm whatever its frequency (wingbeat.py).
FLAPPING_LIFT_SWING = 1.0  # the vertical force's swing over a wingbeat [body weights]
GLOBAL_RULE = (f"max Laplace marginal likelihood over log10 q in [{LOG10_Q_RANGE[0]:g}, {LOG10_Q_RANGE[1]:g}]"
               " (decade grid + golden section), one q for all markers")
SLOPE_SEARCH = "per-marker search on the evidence's values and slopes, Brent's with derivatives"
PER_MARKER_RULE = (f"max Laplace marginal likelihood per marker over log10 q in [{LOG10_Q_RANGE[0]:g}, "
                   f"{LOG10_Q_RANGE[1]:g}] ({SLOPE_SEARCH})")
AUTO_RULE = ("per marker, the model of larger Laplace marginal likelihood, each at its own best noise level "
             "(constant velocity: q, constant acceleration: jerk PSD j)")
WINGBEAT_RULE = ("per marker, the model of larger Laplace marginal likelihood, each at its own best noise level "
                 "(constant velocity: q; oscillating: the trend's q and the oscillation's sigma_m)")
CANDIDATES_RULE = {AUTO_CANDIDATES: AUTO_RULE, WINGBEAT_CANDIDATES: WINGBEAT_RULE}
LOG10_Q_TOL = 0.05  # a search stops when its bracket is this narrow (12 % in q; the peak is flat)
_GOLDEN = (math.sqrt(5) - 1) / 2


def motion_choice(session: Session, options: Options) -> tuple[str, float | None, float | None]:
    """(model, sigma_m, accel_psd) from options first, then session.toml.

    model: one of cost.MOTION_MODELS, or a selector of cost.SELECTORS ("auto", "wingbeat": each marker's
        model from the data; a given q makes it "constant_velocity", the model q belongs to).
    sigma_m [m]: the random walk's per-axis std per frame (paper eq. 4-5 or ``sigma_m``), always given.
    accel_psd [m^2/s^3]: options.accel_psd_m2_s3, else the session's, else None ("choose from data");
        the constant-velocity q (the constant-acceleration jerk PSD is always chosen from the data).
    """
    model = options.motion_model or session.motion.model
    if model not in (*MOTION_MODELS, *SELECTORS):
        raise ValueError(f"motion model must be one of {(*MOTION_MODELS, *SELECTORS)}, got {model!r}")
    q = options.accel_psd_m2_s3 if options.accel_psd_m2_s3 is not None else session.motion.accel_psd_m2_s3
    if model in SELECTORS and q is not None:
        model = "constant_velocity"
    return model, random_walk_sigma_m(session.motion, session.fps), None if q is None else float(q)


def noise_rule(session: Session, options: Options) -> str:
    """The rule that scores a noise level chosen from the data: options.noise_rule, else the session's
    [motion] noise_rule (session.NOISE_RULES)."""
    rule = options.noise_rule or session.motion.noise_rule
    if rule not in NOISE_RULES:
        raise ValueError(f"noise rule must be one of {NOISE_RULES}, got {rule!r}")
    return rule


def logdet_Q(model: str, level: float | np.ndarray, dt_s: float) -> float | np.ndarray:
    """log det Q(level, dt) of one step of ``model`` in the spec's variables [p m, v m/s, a m/s^2], (d, d).

    Constant velocity: :func:`cv_logdet_Q`; constant acceleration: 3 log(j^3 dt^9 / 8640); random walk:
    3 log(sigma_m^2). level: scalar or array.
    """
    _, Q1, _ = scaled_motion(model, dt_s)
    d = len(Q1)
    return d * np.log(noise_scale(model, np.asarray(level, float))) + np.linalg.slogdet(Q1)[1] - 2 * log_det_scale(
        model, dt_s)


def prior_logdet(model: str) -> float:
    """log det of the information of one chain's first-frame gauge priors, spec units (cost spec):
    -6 (log 10 m + log 10 m/s + log 1000 m/s^2), cut to the model's order (random walk: position only)."""
    sig = np.array([PRIOR_POSITION_SIGMA_M, PRIOR_VELOCITY_SIGMA_MPS, PRIOR_ACCELERATION_SIGMA_MPS2])
    return float(-6.0 * np.log(sig[:MOTION_ORDER[model] + 1]).sum())


def cv_logdet_Q(accel_psd_m2_s3: float | np.ndarray, dt_s: float) -> float | np.ndarray:
    """log det Q(q, dt) of one constant-velocity step, Q (6, 6) = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I3.

    det of the 2x2 per axis is q^2 dt^4 / 12, so log det Q = 3 log(q^2 dt^4 / 12). q: scalar or array.
    """
    return 3.0 * np.log(np.square(accel_psd_m2_s3) * dt_s**4 / 12.0)


def laplace_log_evidence(error: float, logdet_post: float, accel_psd_m2_s3: float, dt_s: float,
                         n_steps: int, model: str = "constant_velocity", n_chains: int = 1,
                         oscillation: Oscillation | None = None) -> float:
    """Laplace log marginal likelihood up to a constant common to every model and noise level
    (the data term's normaliser; module docstring).

    Every argument but dt_s, model and n_chains may also be an array (per marker: error, logdet_post and
    the noise level of each chain).

    error: total cost E(x*) (0.5 sum of squared whitened residuals, robust where robust, plus the
        motion and gauge-prior terms).
    logdet_post: log det of the posterior information at x*, spec units [p m, v m/s, a m/s^2] (GTSAM's
        Bayes tree logDeterminant is half of it: it is log det R, R^T R = Lambda).
    accel_psd_m2_s3: the model's noise level (for constant acceleration the jerk PSD [m^2/s^5]).
    n_steps: number of motion steps in the graph (sum over marker chains of F - 1).
    n_chains: number of marker chains, each with its first-frame gauge priors (:func:`prior_logdet`).
    oscillation: the "oscillating" model's (its sigma_m broadcast with the level): the step's log det Q and the
        first frame's prior (which depends on sigma_m) from cost.oscillating_motion (:func:`oscillating_logdets`).
    """
    if model == OSCILLATING:
        log_q, log_p0 = oscillating_logdets(accel_psd_m2_s3, oscillation, dt_s)
        logdet_prior = -n_steps * log_q + n_chains * log_p0
    else:
        logdet_prior = -n_steps * logdet_Q(model, accel_psd_m2_s3, dt_s) + n_chains * prior_logdet(model)
    return -error - 0.5 * logdet_post + 0.5 * logdet_prior


def oscillating_logdets(q: float | np.ndarray, oscillation: Oscillation, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(log det Q, log det P0) of the oscillating model in the spec's variables [p m, v m/s, c m, s m], for the
    trend's q [m^2/s^3] and oscillation.sigma_m broadcast together (any shape; results of that shape): the
    scaled state's (cost.oscillating_motion) with v = u / dt, i.e. Q_spec = S^-1 Q S^-1, P0_spec = S P0 S."""
    q_arr, sig = np.broadcast_arrays(np.asarray(q, float), np.asarray(oscillation.sigma_m, float))
    _, Q, P0 = oscillating_motion(dt_s, Oscillation(oscillation.hz, sig.ravel()), q_arr.ravel())
    ls = log_det_scale(OSCILLATING, dt_s)
    return ((np.linalg.slogdet(Q)[1] - 2 * ls).reshape(q_arr.shape),
            (np.linalg.slogdet(P0)[1] + 2 * ls).reshape(q_arr.shape))


FIT_MARKERS = 8  # markers one global q is fitted on (evenly spread over the estimated ones)


def fit_markers(markers: np.ndarray, n_fit: int = FIT_MARKERS) -> np.ndarray:
    """The markers one global q is fitted on: ``n_fit`` spread evenly over ``markers`` (int array).

    Markers are independent given fixed cameras, so the evidence is a sum over markers and a spread
    subset estimates the common q at a fraction of the cost (used by both smoother paths).
    """
    n_fit = min(n_fit, len(markers))
    return markers[np.unique(np.linspace(0, len(markers) - 1, n_fit).round().astype(int))]


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


@dataclass
class Bracket:
    """Brent's search for the maximum of a score over one log10 level, per marker and vectorised (arrays (M,)).

    The maximum lies in [a, b]; m is the best point so far (score fm), w and v the second and third best
    (fw, fv; NaN where not evaluated). :meth:`next` proposes each marker's next point, :meth:`update` takes
    its score. The proposal is the vertex of the parabola through (m, w, v) when it lies inside the bracket
    and is shorter than half the step before last (successive parabolic interpolation: near a smooth
    maximum a few points locate it where golden section needs ~10), else the golden-section point of the
    bracket's larger side (scores not known, not concave, or parabolic steps that stopped shrinking: an
    evidence far steeper on one side than the other). Every point is at least tol / 2 from m, so that it
    narrows the bracket; where m is within tol / 2 of an end (e.g. a grid point at the range's edge, where
    a marker's q often stays), the point is the probe on the other side that leaves a bracket tol wide if
    it scores worse (unless m just moved there: a climb along a slope). A marker is done when its bracket is
    at most tol wide: its maximum is then located to the tolerance, as by golden section on a unimodal score
    (R. P. Brent, Algorithms for Minimization without Derivatives, 1973, ch. 5; written here because
    scipy's is one scalar search at a time, and each of these points is one solve of every marker).
    """

    a: np.ndarray
    b: np.ndarray
    m: np.ndarray
    fm: np.ndarray
    w: np.ndarray
    fw: np.ndarray
    v: np.ndarray
    fv: np.ndarray
    tol: float = LOG10_Q_TOL

    def __post_init__(self):
        self._steps = (np.full(len(self.m), np.inf), np.full(len(self.m), np.inf))  # before last, last
        self._pending = self._steps
        self._moved = np.zeros(len(self.m), bool)  # the last point scored better than m (m moved to it)

    def done(self) -> np.ndarray:
        return self.b - self.a <= self.tol * (1 + 1e-9)

    def next(self) -> np.ndarray:
        """Each marker's next point, strictly inside its bracket (m itself where done)."""
        a, m, b, t = self.a, self.m, self.b, self.tol
        da, db = m - a, b - m
        with np.errstate(all="ignore"):
            r = (m - self.w) * (self.fm - self.fv)
            q = (m - self.v) * (self.fm - self.fw)
            p = (m - self.v) * q - (m - self.w) * r
            q = 2.0 * (q - r)
            vertex = m - p / q  # the stationary point of the parabola through (m, w, v)
            curvature = ((self.fw - self.fm) / (self.w - m) - (self.fv - self.fm) / (self.v - m)) / (self.w - self.v)
        concave = curvature < 0  # (False where NaN: a point not evaluated, or two points alike)
        before_last, last = self._steps
        parabolic = (np.isfinite(vertex) & concave & (vertex > a) & (vertex < b)
                     & (np.abs(vertex - m) < 0.5 * before_last))
        right = np.where(parabolic & (vertex != m), vertex > m, db >= da)  # which side of m to try
        side = np.where(right, db, da)
        dist = np.where(parabolic, np.abs(vertex - m), (1 - _GOLDEN) * side)
        dist = np.clip(dist, np.minimum(t / 2, side / 2), 0.9 * side)
        short = np.minimum(da, db)
        # m at an end it did not just come from (a crawl along a slope is left to the steps above): the probe
        edge = (short <= t / 2 * (1 + 1e-9)) & ~self._moved  # that closes the bracket if it scores worse
        right = np.where(edge, db >= da, right)
        dist = np.where(edge, np.minimum(t - short, 0.9 * np.maximum(da, db)), dist)
        self._pending = (np.where(parabolic | edge, last, np.maximum(da, db)), dist)
        return np.where(self.done(), m, np.where(right, m + dist, m - dist))

    def update(self, u: np.ndarray, fu: np.ndarray) -> None:
        """Take the scores fu at the points u that :meth:`next` proposed (done markers are left as they are;
        a NaN score counts as -inf)."""
        live = ~self.done()
        fu = np.where(np.isnan(fu), -np.inf, fu)
        self._steps = tuple(np.where(live, new, old) for new, old in zip(self._pending, self._steps, strict=True))
        better, right = live & (fu > self.fm), u > self.m
        worse = live & ~better
        # the bracket: the old best becomes the end on the far side of a better point; a worse point an end
        self.a = np.where(better & right, self.m, np.where(worse & ~right, u, self.a))
        self.b = np.where(better & ~right, self.m, np.where(worse & right, u, self.b))
        # the three best points (Brent's x, w, v)
        second = worse & ((fu >= self.fw) | np.isnan(self.fw) | (self.w == self.m))
        third = worse & ~second & ((fu >= self.fv) | np.isnan(self.fv) | (self.v == self.m) | (self.v == self.w))
        shift = better | second
        self.v, self.fv = (np.where(shift, self.w, np.where(third, u, self.v)),
                           np.where(shift, self.fw, np.where(third, fu, self.fv)))
        self.w, self.fw = (np.where(better, self.m, np.where(second, u, self.w)),
                           np.where(better, self.fm, np.where(second, fu, self.fw)))
        self.m, self.fm = np.where(better, u, self.m), np.where(better, fu, self.fm)
        self._moved = np.where(live, better, self._moved)


@dataclass
class SlopeSearch:
    """The maximum of the evidence over one log10 level, per marker and vectorised (arrays (M,)), from its
    values and slopes (batgraph.graph.fast.evidence_slope's, per decade here): Brent's search with
    derivatives (Numerical Recipes' dbrent, written here vectorised for the reason :class:`Bracket` gives).

    m is the best point by score, w the second. The maximum lies in the bracket [a, b] (the range's ends lo, hi
    at first): a worse point is an end on its side of m, a better one makes the old m the end on its own side,
    and the slope at the new best point says on which side of it the maximum lies (a bracket from the slopes'
    signs alone lost m where slopes and scores disagreed, on a ragged evidence). The next point is the zero of
    the slope's secant through (m, w), or through the last two points, whichever is shorter, when it lies inside
    the bracket, on m's uphill side and shorter than half the step before last; else the middle between m and
    the bracket's end uphill (a first step of ``first_step`` decades towards an end whose slope is not known yet, or
    that end itself when it is nearer). Every step is at least tol / 2. The slope leaves out how the projection
    blocks move with the solution (~1 % of its scale), so a secant through two points at most BIAS_SPAN_DECADES
    apart is corrected by their scores: the mean slope of the scores over the pair minus the slopes' mean (the
    two agree for a quadratic score). A marker is done when such a corrected secant step is under tol / 2 (the
    zero located to it), when the bracket is at most tol wide, or when the slope at an end of the range points
    out of it (the maximum is there). The answer is each marker's best point evaluated (:attr:`answer`). A point
    without a score (-inf: the solve ran into a camera centre) closes the bracket on its side of m. Unimodality
    is assumed inside the search (as by :class:`Bracket`); the range's lower end is scored beside the first
    point (:meth:`lower_end`), which catches a second maximum there.
    """

    x: np.ndarray
    lo: float
    hi: float
    tol: float = LOG10_Q_TOL
    first_step: float = 1.0  # decades: the first step towards a range end whose slope is not known yet
    FIRST_STEP_DECADES = 1.0  # a marker with no scored point yet steps twice this towards stiffer levels
    BIAS_SPAN_DECADES = 0.2

    def __post_init__(self):
        n = len(self.x)
        nan = np.full(n, np.nan)
        self.a, self.b = np.full(n, float(self.lo)), np.full(n, float(self.hi))
        self.ga, self.gb = nan.copy(), nan.copy()
        self.m, self.fm, self.gm = self.x.astype(float).copy(), np.full(n, -np.inf), nan.copy()
        self.w, self.fw, self.gw = nan.copy(), nan.copy(), nan.copy()
        self.last, self.f_last, self.g_last = nan.copy(), nan.copy(), nan.copy()
        self.prev, self.f_prev, self.g_prev = nan.copy(), nan.copy(), nan.copy()
        self.e = np.full(n, np.inf)  # the step before last (a secant step must be under half of it)
        self.step = np.full(n, np.inf)  # the last step
        self.lo_f = np.full(n, -np.inf)  # the score at lo where lo is a maximum of its own (:meth:`lower_end`)
        self._done = np.zeros(n, bool)
        self._next = self.x.astype(float).copy()

    def done(self) -> np.ndarray:
        return self._done.copy()

    def next(self) -> np.ndarray:
        """Each marker's next point (its best point where done)."""
        return np.where(self._done, self.m, self._next)

    def lower_end(self, f: np.ndarray, g: np.ndarray) -> None:
        """Take the score f and slope g (per decade) at the range's lower end lo, evaluated beside the first
        point: a rising slope there makes lo the bracket's lower end; a falling one makes lo a maximum of its
        own (the evidence can have one there besides an interior one: measured 1.2 nats above it on a
        simulated wing marker), kept as the answer where it scores better than the search's."""
        rise = np.isfinite(f) & (g > 0)
        self.ga = np.where(rise, g, self.ga)
        self.lo_f = np.where(np.isfinite(f) & (g <= 0), f, -np.inf)
        # the first secant goes through lo and the first point
        scored = np.isfinite(f) & np.isfinite(g)
        self._put(scored, w=self.lo, fw=f, gw=g, last=self.lo, f_last=f, g_last=g)

    @property
    def answer(self) -> tuple[np.ndarray, np.ndarray]:
        """Each marker's best point (log10 level) and its score: the search's, or lo where that scores better."""
        low = self.lo_f > self.fm
        return np.where(low, float(self.lo), self.m), np.where(low, self.lo_f, self.fm)

    def _put(self, where: np.ndarray, **values) -> None:
        """Set the named per-marker attributes to ``values`` where ``where`` holds."""
        for name, value in values.items():
            setattr(self, name, np.where(where, value, getattr(self, name)))

    def update(self, u: np.ndarray, fu: np.ndarray, gu: np.ndarray) -> None:
        """Take the scores fu and slopes gu (per decade) at the points u that :meth:`next` proposed (done
        markers are left as they are)."""
        live = ~self._done
        ok = live & np.isfinite(fu) & np.isfinite(gu)
        bad = live & ~ok
        first = bad & ~np.isfinite(self.fm)  # no point of this marker has a score yet: try a stiffer level
        self._put(bad & (u > self.m) | first, b=u, gb=np.nan)
        self._put(bad & (u < self.m) & ~first, a=u, ga=np.nan)
        # the bracket from the scores (a worse point is an end on its side of m; a better one makes m the end
        # on m's side), then from the slope at the new best point (on which side of it the maximum lies)
        better = ok & (fu > self.fm)
        worse = ok & ~better
        self._put(worse & (u < self.m), a=u, ga=gu)
        self._put(worse & (u > self.m), b=u, gb=gu)
        self._put(better & (u > self.m) & np.isfinite(self.fm), a=self.m, ga=self.gm)
        self._put(better & (u < self.m), b=self.m, gb=self.gm)
        self._put(better & (gu > 0), a=u, ga=gu)
        self._put(better & (gu <= 0), b=u, gb=gu)
        # the best two points, and the last two
        self._put(worse & ~(self.fw > fu), w=u, fw=fu, gw=gu)
        self._put(better, w=self.m, fw=self.fm, gw=self.gm)
        self._put(better, m=u, fm=fu, gm=gu)
        self._put(ok, prev=self.last, f_prev=self.f_last, g_prev=self.g_last)
        self._put(ok, last=u, f_last=fu, g_last=gu)
        p, raw_step, secant_ok, corrected = self._propose()
        p = np.where(first, np.maximum(self.lo, u - 2 * self.FIRST_STEP_DECADES), p)
        t = self.tol
        at_edge = ok & (((u <= self.lo) & (gu <= 0)) | ((u >= self.hi) & (gu > 0))) & (u == self.m)
        converged = ok & secant_ok & corrected & (raw_step < t / 2)
        narrow = self.b - self.a <= t * (1 + 1e-9)
        hopeless = first & (u <= self.lo)  # no level scored down to the range's lower end: -inf stays the answer
        self._done |= live & (at_edge | converged | narrow | hopeless)
        # Brent's guard: a secant step must be under half the step before last (after any other step, free)
        self._put(live, e=np.where(secant_ok, self.step, np.inf), step=np.abs(p - self.m), _next=p)

    def _secant(self, x, fx, gx, y, fy, gy) -> tuple[np.ndarray, np.ndarray]:
        """The zero of the slope's secant through two points, and whether it was corrected by their scores."""
        with np.errstate(all="ignore"):
            h = x - y
            close = np.isfinite(fy) & (np.abs(h) <= self.BIAS_SPAN_DECADES) & (h != 0)
            bias = np.where(close, (fx - fy) / h - 0.5 * (gx + gy), 0.0)
            change = (gx - gy) / h
            z = np.where(change < 0, x - (gx + bias) / change, np.nan)  # a concave secant only
        return z, close

    def _propose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(next point, its distance from m before it was made at least tol / 2, whether it is an accepted
        secant step, whether that secant was bias-corrected)."""
        a, b, m, g, t = self.a, self.b, self.m, self.gm, self.tol
        z1, c1 = self._secant(m, self.fm, g, self.w, self.fw, self.gw)
        z2, c2 = self._secant(self.last, self.f_last, self.g_last, self.prev, self.f_prev, self.g_prev)

        def fits(z):  # inside the bracket, uphill of m, under half the step before last
            return np.isfinite(z) & (z > a) & (z < b) & ((z - m) * g >= 0) & (np.abs(z - m) < 0.5 * self.e)

        f1, f2 = fits(z1), fits(z2)
        use1 = f1 & (~f2 | (np.abs(z1 - m) <= np.abs(z2 - m)))
        z = np.where(use1, z1, np.where(f2, z2, np.nan))
        corrected = np.where(use1, c1, c2)
        secant_ok = f1 | f2
        # else: the middle between m and the bracket's end uphill; a first step towards an untried range end
        up = g > 0
        end, end_known = np.where(up, b, a), np.where(up, np.isfinite(self.gb) | (b < self.hi),
                                                      np.isfinite(self.ga) | (a > self.lo))
        half = 0.5 * (m + end)
        probe = np.where(np.abs(end - m) <= self.first_step, end, m + np.sign(end - m) * self.first_step)
        z = np.where(secant_ok, z, np.where(end_known, half, probe))
        # at least tol / 2 from m, inside [a, b]
        d = z - m
        z = np.where(np.abs(d) < t / 2, m + np.where(d >= 0, 1.0, -1.0) * t / 2, z)
        z = np.clip(z, a, b)
        return np.where(np.isfinite(m), z, self.m), np.abs(d), secant_ok, corrected


GIVEN_RULE = "given (options or session), one q for all markers"
# How a noise level is scored when chosen from the data ([motion] noise_rule): "evidence" = the Laplace
# marginal likelihood (module docstring); "loo" = the leave-one-frame-out log predictive density of the
# observations (:func:`loo_log_predictive`), which scores what the model predicts for a frame from all
# the others and so prefers the level that follows motion the model family fits badly (a body bobbing
# with the wingbeat) where the evidence prefers a smoother, overconfident track. session.NOISE_RULES.


def flapping_heave_m(hz: float) -> float:
    """The heave amplitude [m] of a body flapping at ``hz`` [Hz] whose lift swings by FLAPPING_LIFT_SWING body
    weights over the stroke: vertical acceleration amplitude FLAPPING_LIFT_SWING g, so A = FLAPPING_LIFT_SWING g / w^2
    with w = 2 pi hz (3.9 mm at 8 Hz)."""
    return FLAPPING_LIFT_SWING * G_MPS2 / (2.0 * math.pi * hz) ** 2


def flapping_q_floor(hz: float) -> float:
    """The least constant-velocity q [m^2/s^3] of a marker on an animal flapping at ``hz`` [Hz]: that of an
    oscillation of amplitude :func:`flapping_heave_m` (its acceleration, amplitude A w^2 with w = 2 pi hz, taken as
    white over a band ~w wide: q ~ A^2 w^4 / w = A^2 w^3 = (FLAPPING_LIFT_SWING g)^2 / w). 3.8 at 4 Hz, 1.9 at
    8 Hz, 1.0 at 15 Hz."""
    return flapping_heave_m(hz) ** 2 * (2.0 * math.pi * hz) ** 3


def q_figures(q: float | np.ndarray, markers: np.ndarray | None = None, names: list[str] | None = None,
              selection: dict | None = None) -> dict:
    """The figures both smoothers report about q: a given one (``q`` a number) or, with ``selection``
    from :func:`choose_accel_psd_per_marker`, one per marker (``q`` (M,), ``markers`` int indices,
    ``names`` the marker labels)."""
    if selection is None:
        return {"accel_psd_source": "given", "accel_psd_rule": GIVEN_RULE, "accel_psd_m2_s3": q}
    return {"accel_psd_selection": selection, "accel_psd_source": "data", "accel_psd_rule": PER_MARKER_RULE,
            "accel_psd_m2_s3": {names[m]: float(q[m]) for m in markers}}


def per_marker_rule(model: str, rule: str = "evidence") -> str:
    """The per-marker search's rule for ``model``'s noise level under score ``rule`` (NOISE_RULES;
    PER_MARKER_RULE for constant velocity and the evidence)."""
    lo, hi = LOG10_RANGE[model]
    score = "Laplace marginal likelihood" if rule == "evidence" else "leave-one-frame-out log predictive density"
    if model == OSCILLATING:
        s_lo, s_hi = OSC_LOG10_SIGMA_RANGE
        return (f"max {score} per marker over log10 q (the trend's) in [{lo:g}, {hi:g}] x log10 sigma_m (the "
                f"oscillation's) in [{s_lo:g}, {s_hi:g}] (shared grid, every {LOG10_GRID_STEP:g} decades of q x "
                "every decade of sigma_m, + per-marker Brent search on q, then on sigma_m)")
    what = "q" if model == "constant_velocity" else "j"
    how = (SLOPE_SEARCH if rule == "evidence"
           else f"shared grid every {LOG10_GRID_STEP:g} decades + per-marker Brent search")
    return f"max {score} per marker over log10 {what} in [{lo:g}, {hi:g}] ({how})"


def loo_log_predictive(rr: np.ndarray, g: np.ndarray, A: np.ndarray, Sigma: np.ndarray) -> np.ndarray:
    """Leave-one-frame-out log predictive density of each (frame, marker) cell's observations, up to a
    constant common to every noise level: the ``"loo"`` rule's score (NOISE_RULES; a marker's score is
    the sum over its frames).

    rr: sum of w |r|^2 over the cell's observations (whitened residuals r at the solution x*, IRLS
    weights w: the robust loss's Gaussian surrogate), shape (...); g: sum of w J^T r, (..., 3) [1/m];
    A: sum of w J^T J, (..., 3, 3) [1/m^2] (J: whitened Jacobians in the position); Sigma: the
    position's marginal covariance at x* from the same Gauss-Newton system, (..., 3, 3) [m^2].
    Cells without observations (rr = 0 and A = 0) score 0.

    For the Gaussian (linearised) model the posterior without the cell's observations has precision
    Sigma^-1 - A, the cell's predictive residual is r_(-t) = (I - H)^-1 r with the leverage
    H = J Sigma J^T, and its predictive covariance I + J Sigma_(-t) J^T = (I - H)^-1, so
    log p(y_t | y_(-t)) = -0.5 r^T (I - H)^-1 r + 0.5 log det (I - H) + const; by Woodbury and
    Sylvester r^T (I - H)^-1 r = rr + g^T (Sigma^-1 - A)^-1 g and det (I - H) = det (I_3 - Sigma A),
    3x3 per cell whatever the number of views. -inf where the cell's leave-out precision is not
    positive (rounding, when one cell's views carry nearly all of a marker's information).
    """
    out = np.zeros(rr.shape)
    has = rr > 0
    S, Ah, gh = Sigma[has], A[has], g[has]
    with np.errstate(invalid="ignore", divide="ignore"):
        P = np.linalg.inv(S) - Ah  # the leave-out precision (Sigma_(-t))^-1
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        sign_p, _ = np.linalg.slogdet(P)
        sign, ld = np.linalg.slogdet(np.eye(3) - S @ Ah)
        ok = (sign > 0) & (sign_p > 0)
        quad = rr[has] + np.einsum("ni,ni->n", gh, np.linalg.solve(np.where(ok[:, None, None], P, np.eye(3)),
                                                                     gh[..., None])[..., 0])
    out[has] = np.where(ok, -0.5 * quad + 0.5 * ld, -np.inf)
    return out


_PREFIX = {"constant_velocity": "accel_psd", "constant_acceleration": "jerk_psd", OSCILLATING: "oscillating_accel_psd"}


def model_figures(model: np.ndarray, level: np.ndarray, markers: np.ndarray, names: list[str],
                  selection: dict, candidates: tuple[str, ...], flap_hz: float | None = None) -> dict:
    """The figures both smoothers report about a per-marker choice from the data
    (:func:`batgraph.graph.fast.choose_model_per_marker`; one candidate = only its noise level chosen).

    model (M,) names, level (M,) noise levels, markers: int indices of the estimated markers, names:
    marker labels. Gives motion_model_per_marker {name: model}, per model its noise per marker
    (accel_psd_m2_s3 {name: q} for the constant-velocity markers, jerk_psd_m2_s5 {name: j} for the
    constant-acceleration ones, oscillating_accel_psd_m2_s3 and oscillation_sigma_m {name: sigma_m [m]} for
    the oscillating ones), its search's rule and counts (``accel_psd_selection``, ``jerk_psd_selection``, ...)
    and, with several candidates, log_evidence_per_marker {name: {model: score}}; when the search's q floor
    (:func:`flapping_q_floor` at ``flap_hz``, the wingbeat found) raised markers, accel_psd_floor
    {accel_psd_m2_s3, flapping_heave_m, markers}.
    """
    out = {"accel_psd_source": "data", "motion_model_per_marker": {names[m]: str(model[m]) for m in markers}}
    if len(candidates) > 1:
        out["motion_model_rule"] = CANDIDATES_RULE.get(tuple(candidates), AUTO_RULE)
        out["log_evidence_per_marker"] = {names[m]: {c: float(selection["log_evidence"][c][m]) for c in candidates}
                                          for m in markers}
    for c in candidates:
        sel = selection[c]
        out[f"{_PREFIX[c]}_rule"] = sel["rule"]
        out[f"{_PREFIX[c]}_selection"] = {"rule": sel["rule"], "n_solves": sel["n_solves"],
                                          "per_marker": sel["per_marker"]}
        out[NOISE_UNIT[c]] = {names[m]: float(level[m]) for m in markers if model[m] == c}
        if c == OSCILLATING:
            out["oscillation_sigma_m"] = {names[m]: float(sel["sigma_m"][m]) for m in markers if model[m] == c}
    raised = selection.get("raised_to_floor")
    if raised is not None and raised[markers].any():
        out["accel_psd_floor"] = {"accel_psd_m2_s3": float(level[raised][0]),
                                  "flapping_heave_m": None if flap_hz is None else flapping_heave_m(flap_hz),
                                  "markers": [names[m] for m in markers if raised[m]]}
    return out


def causal_accel_psd(session: Session) -> float:
    """Constant-velocity q [m^2/s^3] from the motion config alone (the filter's default; sees no data).

    The paper's eq. 4 bounds a wing's speed by the flap's peak speed alpha_f l_w f_f. A sinusoidal
    flap with that peak speed has peak acceleration a = 2 pi f_f alpha_f l_w f_f, and its velocity
    changes per frame by a sin(.) dt, of mean square a^2 dt^2 / 2 (3-D). White-noise acceleration
    of PSD q changes it by 3 q dt per frame (3 axes); matching the two gives q = a^2 dt / 6.
    Steady flight adds no acceleration. Paper flight values (4 Hz, 90 deg, 0.5 m, 120 fps):
    q = 8.7 m^2/s^3; on the simulated flight the truth's own per-frame velocity changes give 9.2 and
    the smoother's marginal likelihood 20. Without a flap (a = 0) q is CAUSAL_Q_FLOOR, 1 (not the
    search range's floor 0.01: a filter that cannot check the data should not assume near-rigid motion).
    Without physics (data that is not a bat flight) it is ``causal_accel_psd_m2_s3``, measured by
    reconstruct from the triangulated track: a hyperparameter from the whole session, while each
    estimate still uses only frames up to its own.
    """
    m, fps = session.motion, session.fps
    if not m.has_physics:  # no bat physics stated: the value reconstruct measured from the triangulated track
        if m.causal_accel_psd_m2_s3 is None:
            raise ValueError("[motion] has no physics and no measured q (batgraph.motion.noise_from_track)")
        return float(m.causal_accel_psd_m2_s3)
    a = 2 * math.pi * m.flap_hz * math.radians(m.flap_angle_deg) * m.span_m * m.flap_hz
    return max(a * a / fps / 6.0, CAUSAL_Q_FLOOR)


def choose_accel_psd_per_marker(*args, **kwargs) -> tuple[np.ndarray, dict]:
    """:func:`batgraph.graph.fast.choose_accel_psd_per_marker` (the search needs the solver, which imports
    this module; kept here for existing callers, imported when called)."""
    from .fast import choose_accel_psd_per_marker

    return choose_accel_psd_per_marker(*args, **kwargs)


def filter_motion(session: Session, options: Options) -> tuple[MotionModel, dict]:
    """The filter's motion model and where its noise came from (given, or the causal default).

    The filters have the random walk and constant velocity: "auto" (the smoother's per-marker choice
    needs the whole sequence) and "constant_acceleration" (no causal rule for its jerk PSD) filter with
    constant velocity; ``motion_model_requested`` in the figures says so.
    """
    model_name, sigma_m, q = motion_choice(session, options)
    dt = 1.0 / session.fps
    if model_name == "random_walk":
        return MotionModel("random_walk", dt, sigma_m=sigma_m), {"sigma_m": sigma_m}
    source = "given" if q is not None else "motion config (noise.causal_accel_psd)"
    q = q if q is not None else causal_accel_psd(session)
    info = {"accel_psd_m2_s3": q, "accel_psd_source": source}
    if model_name != "constant_velocity":
        info["motion_model_requested"] = model_name
    return MotionModel("constant_velocity", dt, accel_psd_m2_s3=q), info
