"""Each marker's noise level, and (for "auto") its motion model, by the largest Laplace marginal likelihood.

The search is over log10 of the level (q [m^2/s^3] for constant velocity, the jerk PSD j [m^2/s^5] for constant
acceleration), per marker and vectorised: each step solves every marker still searching at its own level in one
batch (batgraph.solver.chains), and :class:`SlopeSearch` takes the evidence's value and slope there. A model's
evidences compare across models because each is the same data term times a normalised prior over the chain
(batgraph.solver.model.log_evidence), so "auto" keeps, per marker or per segment group (summed), the model
whose best evidence is larger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from . import chains, lm
from . import model as mm
from .kernels import tridiagonal
from .problem import Problem, derivatives, gradient, log_det_units, start_state
from .threads import side_by_side

# log10 of each model's level searched: q from a gliding body (0.01) to a wing tip's extreme; j from a body
# changing its acceleration by ~1 m/s^2 in a second to a 15 Hz wing tip (~1e9)
LOG10_RANGE = {"constant_velocity": (-2.0, 6.0), "constant_acceleration": (0.0, 10.0)}
START = {"constant_velocity": 1.0, "constant_acceleration": 5.0}  # where the search begins (a wing's q ~ 10)
TOL = 0.05  # decades: a search stops when the maximum is located this closely (12 % in the level; the peak is flat)
MAX_STEPS = 24
WARM_LOOSER = 0.2  # decades: a solve starts from the marker's last solution unless that was stiffer by more
NEAR_FIRST_STEP = 0.1  # decades: the true search's first step from the surrogate's maximum


@dataclass
class Choice:
    """The search's answer for M markers: model (M,) names, level (M,), log_evidence (M,) and each model's
    evidence per marker {model: (M,)}, the solution x at the chosen model and level per model {model: (F, M, d)}
    (NaN for markers of another model), and the solves each model's search took."""

    model: np.ndarray
    level: np.ndarray
    log_evidence: np.ndarray
    evidence_by_model: dict
    solution: dict
    n_solves: dict


def choose(template: Problem, start: tuple, candidates: tuple[str, ...], groups: list[np.ndarray] = (),
           progress=None) -> Choice:
    """Each marker's model among ``candidates`` and its level (module docstring). template: the problem (any
    model and level: both are replaced); start: (p, v, a) (F, M, 3) [m, m/s, m/s^2] (a may be None), the first
    solves' start; groups: marker index arrays that must share one model (segment groups: their summed evidence)."""
    M = template.n_markers
    jobs = [partial(choose_level, replace(template, model=name, rows=template.rows.placed(name, template.n_frames)),
                    start, progress) for name in candidates]
    found = dict(zip(candidates, side_by_side(jobs), strict=True))  # the models' searches are independent
    ev = np.stack([np.where(np.isfinite(found[n][1]), found[n][1], -np.inf) for n in candidates])
    won = np.argmax(ev, axis=0)
    for members in groups:
        won[members] = np.argmax(ev[:, members].sum(axis=1))
    model = np.array(candidates, dtype=object)[won]
    level = np.choose(won, [found[n][0] for n in candidates])
    return Choice(model, level, ev[won, np.arange(M)], {n: found[n][1] for n in candidates},
                  {n: np.where((model == n)[None, :, None], found[n][2], np.nan) for n in candidates},
                  {n: found[n][3] for n in candidates})


def choose_level(problem: Problem, start: tuple, progress=None) -> tuple:
    """The level of maximum evidence of every marker of ``problem`` (its model): (level (M,), log evidence (M,),
    the solution there (F, M, d), number of solves). A marker whose every solve ran into a camera scores -inf.

    Where to begin comes from the evidence's :class:`Surrogate` at the start (the whole search on it costs no
    projection). The surrogate alone does not decide: it leaves out how the rows move with the solution; the
    search on true solves then starts at its maximum with short first steps, beside the range's lower end."""
    name, M = problem.model, problem.n_markers
    lo, hi = LOG10_RANGE[name]
    x_start = start_state(name, problem.fps, *start)
    n_solves = 0

    def solve(u, live, x_from):
        nonlocal n_solves
        n_solves += 1
        if progress is not None:
            progress.update()
        sub = problem.of_markers(live).with_level(10.0 ** u[live])
        sol = chains.solve(sub, x_from[:, live], lm.LOOSE, slope=True)
        f, g, x = np.full(M, -np.inf), np.full(M, np.nan), x_from.copy()
        f[live], g[live] = sol.log_evidence(sub), sol.slope * math.log(10.0)
        x[:, live] = sol.x
        return f, g, x

    sur = Surrogate(problem, x_start)
    u0 = _search(sur.evaluate, np.full(M, START[name]), lo, hi)
    search = SlopeSearch(u0, lo, hi, first_step=NEAR_FIRST_STEP)
    f_lo, g_lo, x_lo = solve(np.full(M, lo), np.ones(M, bool), sur.minimiser(np.full(M, 10.0**lo)))
    search.lower_end(f_lo, g_lo)
    f, g, last = solve(u0, np.ones(M, bool), x_start)
    search.update(u0, f, g)
    u_last = u0
    kept = last
    for _ in range(MAX_STEPS - 2):
        live = ~search.done()
        if not live.any():
            break
        u = search.next()
        warm = u <= u_last + WARM_LOOSER
        f, g, new = solve(u, live, np.where(warm[None, :, None], last, x_start))
        search.update(u, f, g)
        kept = np.where((live & (search.answer[0] == u))[None, :, None], new, kept)
        last = np.where(live[None, :, None], new, last)
        u_last = np.where(live, u, u_last)
    x, f = search.answer
    kept = np.where((x == lo)[None, :, None], x_lo, kept)
    return 10.0 ** x, f, kept, n_solves


def _search(evaluate, u0: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """SlopeSearch on a cheap ``evaluate(level) -> (evidence, slope per ln level)`` from u0: each marker's answer
    (log10 level)."""
    per_decade = math.log(10.0)
    f_lo, g_lo = evaluate(np.full(len(u0), 10.0**lo))
    search = SlopeSearch(u0.astype(float), lo, hi)
    search.lower_end(f_lo, g_lo * per_decade)
    u = u0
    for _ in range(MAX_STEPS):
        f, g = evaluate(10.0**u)
        search.update(u, f, g * per_decade)
        if search.done().all():
            break
        u = search.next()
    return search.answer[0]


class Surrogate:
    """The evidence as a function of each marker's level with the rows replaced by their quadratic model at x0
    (F, M, d) (IRLS curvature and gradient there); the motion and prior terms exact. At any level its minimiser,
    cost, log det and slope take one sweep and no projection."""

    def __init__(self, problem: Problem, x0: np.ndarray):
        self.problem, self.x0 = problem, x0
        self.c, _, self.D, self.B, self.g = problem.row_system(x0, False)

    def _at(self, level: np.ndarray) -> tuple:
        p = self.problem.with_level(level)
        D, B, g = self.D.copy(), self.B.copy(), self.g.copy()
        p.add_motion(self.x0, D, B, g)
        sw = tridiagonal(D, B[:, :, None], rhs=-g[..., None], motion=p.motion_blocks())
        return p, sw, self.x0 + sw["dx"][..., 0]

    def minimiser(self, level: np.ndarray) -> np.ndarray:
        x = self._at(level)[2]
        return np.where(np.isfinite(x).all(axis=(0, 2))[None, :, None], x, self.x0)

    def evaluate(self, level: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log evidence (M,), its slope per ln level (M,)) at levels (M,)."""
        p, sw, x = self._at(level)
        dx = x - self.x0
        quad = 0.5 * np.einsum("fmi,fmij,fmj->m", dx, self.D, dx) + np.einsum("fmi,fmij,fmj->m", dx[1:], self.B,
                                                                                dx[:-1])
        cost = self.c + np.einsum("fmi,fmi->m", self.g, dx) + quad + p.motion_cost(x) + p.prior_cost(x)
        F = x.shape[0]
        ld = sw["logdet"] + log_det_units(p.model, p.fps, F)
        ev = mm.log_evidence(cost, ld, level, p.model, 1.0 / p.fps, F - 1)
        return np.where(np.isfinite(ev), ev, -np.inf), chains.evidence_slope(p, x, sw["trace"])


def motion_of(x: np.ndarray, fps: float) -> tuple:
    """(p, v, a) (F, M, 3) of scaled states x (F, M, d): the start of another model's solve (a from np.gradient
    of v where x has none)."""
    v, a = derivatives(x, fps)
    p = x[..., :3]
    v = gradient(p, fps) if v is None else v
    return p, v, gradient(v, fps) if a is None else a


@dataclass
class SlopeSearch:
    """The maximum of the evidence over one log10 level, per marker and vectorised (arrays (M,)), from its values
    and slopes (per decade): Brent's search with derivatives (Numerical Recipes' dbrent), written here vectorised
    because each point is one batched solve of every marker (scipy's searches are one scalar at a time).

    m is the best point by score, w the second; the maximum lies in the bracket [a, b] (the range at first): a
    worse point is an end on its side of m, a better one makes the old m the end on its side, and the slope at
    the new best point says on which side of it the maximum lies. The next point is the zero of the slope's
    secant through (m, w) or through the last two points, whichever is shorter, when it lies inside the bracket,
    uphill of m and under half the step before last; else the middle between m and the bracket's end uphill (a
    first step of ``first_step`` towards an end whose slope is not known). The slope leaves out how the rows move
    with the solution, so a secant through two close points is corrected by their scores. A marker is done when
    such a step is under tol / 2, its bracket is tol wide, or the slope at a range end points out of the range.
    A point without a score (-inf) closes the bracket on its side. The lower end, scored beside the first point
    (:meth:`lower_end`), is kept as the answer where it scores better (the evidence can peak there too).
    """

    x: np.ndarray
    lo: float
    hi: float
    tol: float = TOL
    first_step: float = 1.0
    BIAS_SPAN = 0.2  # decades: a secant through points at most this far apart is corrected by their scores

    def __post_init__(self):
        n = len(self.x)
        nan = np.full(n, np.nan)
        self.a, self.b = np.full(n, float(self.lo)), np.full(n, float(self.hi))
        self.ga, self.gb = nan.copy(), nan.copy()
        self.m, self.fm, self.gm = self.x.astype(float).copy(), np.full(n, -np.inf), nan.copy()
        self.w, self.fw, self.gw = nan.copy(), nan.copy(), nan.copy()
        self.last, self.f_last, self.g_last = nan.copy(), nan.copy(), nan.copy()
        self.prev, self.f_prev, self.g_prev = nan.copy(), nan.copy(), nan.copy()
        self.e, self.step = np.full(n, np.inf), np.full(n, np.inf)
        self.lo_f = np.full(n, -np.inf)
        self._done = np.zeros(n, bool)
        self._next = self.x.astype(float).copy()

    def done(self) -> np.ndarray:
        return self._done.copy()

    def next(self) -> np.ndarray:
        return np.where(self._done, self.m, self._next)

    def lower_end(self, f: np.ndarray, g: np.ndarray) -> None:
        """Score f and slope g at the range's lower end: a rising slope makes it the bracket's end, a falling one
        a maximum of its own."""
        rise = np.isfinite(f) & (g > 0)
        self.ga = np.where(rise, g, self.ga)
        self.lo_f = np.where(np.isfinite(f) & (g <= 0), f, -np.inf)
        scored = np.isfinite(f) & np.isfinite(g)
        self._put(scored, w=self.lo, fw=f, gw=g, last=self.lo, f_last=f, g_last=g)

    @property
    def answer(self) -> tuple[np.ndarray, np.ndarray]:
        """Each marker's best point (log10 level) and its score."""
        low = self.lo_f > self.fm
        return np.where(low, float(self.lo), self.m), np.where(low, self.lo_f, self.fm)

    def _put(self, where: np.ndarray, **values) -> None:
        for name, value in values.items():
            setattr(self, name, np.where(where, value, getattr(self, name)))

    def update(self, u: np.ndarray, fu: np.ndarray, gu: np.ndarray) -> None:
        """Take the scores fu and slopes gu (per decade) at the points u :meth:`next` proposed."""
        live = ~self._done
        ok = live & np.isfinite(fu) & np.isfinite(gu)
        bad = live & ~ok
        first = bad & ~np.isfinite(self.fm)  # nothing scored yet: try a stiffer level
        self._put(bad & (u > self.m) | first, b=u, gb=np.nan)
        self._put(bad & (u < self.m) & ~first, a=u, ga=np.nan)
        better, worse = ok & (fu > self.fm), ok & ~(fu > self.fm)
        self._put(worse & (u < self.m), a=u, ga=gu)
        self._put(worse & (u > self.m), b=u, gb=gu)
        self._put(better & (u > self.m) & np.isfinite(self.fm), a=self.m, ga=self.gm)
        self._put(better & (u < self.m), b=self.m, gb=self.gm)
        self._put(better & (gu > 0), a=u, ga=gu)
        self._put(better & (gu <= 0), b=u, gb=gu)
        self._put(worse & ~(self.fw > fu), w=u, fw=fu, gw=gu)
        self._put(better, w=self.m, fw=self.fm, gw=self.gm)
        self._put(better, m=u, fm=fu, gm=gu)
        self._put(ok, prev=self.last, f_prev=self.f_last, g_prev=self.g_last)
        self._put(ok, last=u, f_last=fu, g_last=gu)
        p, raw_step, secant_ok, corrected = self._propose()
        p = np.where(first, np.maximum(self.lo, u - 2 * self.first_step), p)
        t = self.tol
        at_edge = ok & (((u <= self.lo) & (gu <= 0)) | ((u >= self.hi) & (gu > 0))) & (u == self.m)
        converged = ok & secant_ok & corrected & (raw_step < t / 2)
        narrow = self.b - self.a <= t * (1 + 1e-9)
        hopeless = first & (u <= self.lo)
        self._done |= live & (at_edge | converged | narrow | hopeless)
        self._put(live, e=np.where(secant_ok, self.step, np.inf), step=np.abs(p - self.m), _next=p)

    def _secant(self, x, fx, gx, y, fy, gy) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(all="ignore"):
            h = x - y
            close = np.isfinite(fy) & (np.abs(h) <= self.BIAS_SPAN) & (h != 0)
            bias = np.where(close, (fx - fy) / h - 0.5 * (gx + gy), 0.0)
            change = (gx - gy) / h
            z = np.where(change < 0, x - (gx + bias) / change, np.nan)
        return z, close

    def _propose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        a, b, m, g, t = self.a, self.b, self.m, self.gm, self.tol
        z1, c1 = self._secant(m, self.fm, g, self.w, self.fw, self.gw)
        z2, c2 = self._secant(self.last, self.f_last, self.g_last, self.prev, self.f_prev, self.g_prev)

        def fits(z):
            return np.isfinite(z) & (z > a) & (z < b) & ((z - m) * g >= 0) & (np.abs(z - m) < 0.5 * self.e)

        f1, f2 = fits(z1), fits(z2)
        use1 = f1 & (~f2 | (np.abs(z1 - m) <= np.abs(z2 - m)))
        z = np.where(use1, z1, np.where(f2, z2, np.nan))
        corrected, secant_ok = np.where(use1, c1, c2), f1 | f2
        up = g > 0
        end = np.where(up, b, a)
        end_known = np.where(up, np.isfinite(self.gb) | (b < self.hi), np.isfinite(self.ga) | (a > self.lo))
        probe = np.where(np.abs(end - m) <= self.first_step, end, m + np.sign(end - m) * self.first_step)
        z = np.where(secant_ok, z, np.where(end_known, 0.5 * (m + end), probe))
        d = z - m
        z = np.clip(np.where(np.abs(d) < t / 2, m + np.where(d >= 0, 1.0, -1.0) * t / 2, z), a, b)
        return np.where(np.isfinite(m), z, self.m), np.abs(d), secant_ok, corrected
