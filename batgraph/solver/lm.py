"""The one Levenberg-Marquardt driver: many independent columns (a marker's chain, or a segment group) at once,
each with its own damping, acceptance and stopping; the linear solve is the objective's (its strategy).

A step solves (H + lambda diag H) dx = -g. After an accepted step the next one uses the robust loss's own
curvature ("exact": Newton-like, quadratic convergence past a Huber kink), after a rejected exact step the
IRLS curvature, which majorises the loss, each kind with its own damping (one damping for both let an undamped
exact step overshoot the kink again after every accepted IRLS step). Converged columns drop out of the next
iterations. A column stops when its step is below ``step_tol_m``, its relative decrease below ``rel_cost_tol``,
a rejected step's predicted decrease is below the cost's rounding, its damping passes ``stuck`` (no step, however
short, decreases it), or an accepted step ran into a camera centre (``at_camera``: no minimum in front of it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Settings:
    """Every setting of the driver, in one place.

    step_tol_m: a column is done when its largest step component is below this [m] (a solve that only scores
        a noise level uses LOOSE, 1e-7 m: Gauss-Newton's quadratic convergence makes the next step ~1e-12 m).
    rel_cost_tol: ... or when an accepted step decreases its cost by less than this, relatively.
    rounding_eps: ... or when a rejected step's predicted decrease is below this many eps of the cost.
    at_camera_fraction: an accepted step that brings an observed point closer to its camera than this fraction
        of the closest depth at the start has run into the camera centre, where every ray meets.
    damping: (first damping after a rejection, factor per rejection / acceptance, floor below which it is 0,
        ceiling beyond which the column is stuck).
    """

    max_iterations: int = 200
    step_tol_m: float = 1e-10
    rel_cost_tol: float = 1e-15
    rounding_eps: float = 4.0
    at_camera_fraction: float = 1e-3
    damping: tuple[float, float, float, float] = (1e-6, 10.0, 1e-9, 1e12)


TIGHT = Settings()
LOOSE = Settings(step_tol_m=1e-7)


class Objective(Protocol):
    """What the driver needs of a set of n independent columns (see batgraph.solver.chains, .segments)."""

    robust: bool  # whether the two curvatures differ (a robust loss)

    def cost(self, state) -> tuple[np.ndarray, np.ndarray]: ...  # (cost (n,), largest inverse depth (n,))

    def system(self, state, exact: np.ndarray) -> tuple: ...  # (cost, near, linear system)

    def solve(self, system, damping: np.ndarray): ...  # the step of every column

    def gain(self, system, step) -> np.ndarray: ...  # -0.5 g . step per column (n,)

    def size(self, step) -> np.ndarray: ...  # largest |step| per column (n,) [m]

    def add(self, state, step): ...  # state + step

    def take(self, keep: np.ndarray) -> Objective: ...  # the columns where keep (bool (n,))

    def take_state(self, state, keep: np.ndarray): ...

    def put_state(self, state, keep: np.ndarray, part) -> None: ...  # in place


@dataclass
class Result:
    state: object
    cost: np.ndarray  # (n,)
    iterations: np.ndarray  # (n,)
    converged: np.ndarray  # (n,) bool
    at_camera: np.ndarray  # (n,) bool


def minimise(obj: Objective, state, settings: Settings = TIGHT) -> Result:
    """Levenberg-Marquardt on every column of ``obj`` from ``state`` (module docstring); ``state`` is updated in
    place and returned in the result."""
    s = settings
    cost, near = obj.cost(state)
    n = len(cost)
    limit = np.where(near > 0, near / s.at_camera_fraction, np.inf)
    lam, lam_x = np.zeros(n), np.zeros(n)
    exact, active = np.zeros(n, bool), np.ones(n, bool)
    iters, converged, at_camera = np.zeros(n, int), np.zeros(n, bool), np.zeros(n, bool)
    eps = np.finfo(float).eps
    sub, cols, sub_state = obj, np.arange(n), state
    for _ in range(s.max_iterations):
        act = np.flatnonzero(active)
        if len(act) == 0:
            break
        if len(act) < len(cols):  # converged columns drop out
            sub, cols = sub.take(active[cols]), act
            sub_state = obj.take_state(state, active)
        _, _, system = sub.system(sub_state, exact[act])
        damping = np.where(exact[act] & obj.robust, lam_x[act], lam[act])
        step = sub.solve(system, damping)
        trial = sub.add(sub_state, step)
        c_new, near_new = sub.cost(trial)
        ok = c_new <= cost[act]
        rel = (cost[act] - c_new) / np.maximum(cost[act], np.finfo(float).tiny)
        flat = ~ok & (sub.gain(system, step) <= s.rounding_eps * eps * cost[act])
        stuck = lam[act] > s.damping[3]
        pupil = ok & (near_new > limit[act])
        if ok.any():
            part = sub.take_state(trial, ok)
            sub.put_state(sub_state, ok, part)
            if sub is not obj:
                obj.put_state(state, _mask(n, act[ok]), part)
        cost[act] = np.where(ok, c_new, cost[act])
        at_camera[act] = pupil
        done = (ok & (rel < s.rel_cost_tol)) | (sub.size(step) < s.step_tol_m) | flat | stuck | pupil
        converged[act] = done & ~stuck & ~pupil
        iters[act] += 1
        lam[act], lam_x[act] = _next_damping(exact[act] & obj.robust, ok, damping, lam[act], lam_x[act], obj.robust,
                                             s.damping)
        exact[act] = ok
        active[act] = ~done
    return Result(state, cost, iters, converged, at_camera)


def _mask(n: int, idx: np.ndarray) -> np.ndarray:
    m = np.zeros(n, bool)
    m[idx] = True
    return m


def _next_damping(was_exact, ok, damping, lam, lam_x, robust: bool, d: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(IRLS damping, exact damping) after a step: an accepted step divides its kind's damping by the factor
    (0 below the floor), a rejected one multiplies it (from the first damping); one damping without a robust loss."""
    first, factor, floor, _ = d
    less = np.where(damping > floor, damping / factor, 0.0)
    more = np.maximum(damping * factor, first)
    lam_x = np.where(was_exact, np.where(ok, less, more), lam_x)
    lam = np.where(was_exact, lam, np.where(ok, less, more))
    return lam, (lam_x if robust else lam)
