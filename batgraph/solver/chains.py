"""Markers solved one by one, all at once: each marker's chain is block tridiagonal in frames, so the linear
solve is one sweep over frames per marker (batgraph.solver.kernels), and its marginal covariances, log det and
the marginal likelihood's slope come from the same sweeps. Exact for a problem whose markers share nothing
(fixed cameras, no segments): the backend every fast path uses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import lm
from . import model as mm
from .kernels import tridiagonal
from .problem import Problem, log_det_units


class Chains:
    """:class:`batgraph.solver.lm.Objective` of a :class:`Problem`'s markers: state x (F, M, d)."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.robust = problem.loss.name != "none"

    def cost(self, x):
        return self.problem.cost(x)

    def system(self, x, exact):
        cost, near, D, B, g = self.problem.system(x, exact)
        return cost, near, (D, B, g)

    def solve(self, system, damping):
        D, B, g = system
        i = np.arange(D.shape[-1])
        Dd = D.copy()
        Dd[..., i, i] *= 1.0 + damping[None, :, None]
        return tridiagonal(Dd, B[:, :, None], rhs=-g[..., None])["dx"][..., 0]

    def gain(self, system, dx):
        return -0.5 * np.einsum("fmi,fmi->m", system[2], dx)

    def size(self, dx):
        return np.abs(dx).max(axis=(0, 2)) if dx.size else np.zeros(dx.shape[1])

    def add(self, x, dx):
        return x + dx

    def take(self, keep):
        return Chains(self.problem.of_markers(keep))

    def take_state(self, x, keep):
        return x[:, keep]

    def put_state(self, x, keep, part):
        x[:, keep] = part


@dataclass
class Solution:
    """A solve of a problem's M markers: x (F, M, d) the minimiser (scaled state); cost (M,); logdet (M,) of the
    Gauss-Newton information in physical units; Sigma (F, M, d, d) its inverse's diagonal blocks (scaled state) or
    None; slope (M,) d log evidence / d ln level or None; iterations (M,), converged (M,), at_camera (M,)."""

    x: np.ndarray
    cost: np.ndarray
    logdet: np.ndarray
    Sigma: np.ndarray | None
    slope: np.ndarray | None
    iterations: np.ndarray
    converged: np.ndarray
    at_camera: np.ndarray

    def log_evidence(self, problem: Problem) -> np.ndarray:
        """Each marker's Laplace log marginal likelihood at its level (-inf where the solve ran into a camera)."""
        F = self.x.shape[0]
        ev = mm.log_evidence(self.cost, self.logdet, problem.level, problem.model, 1.0 / problem.fps, F - 1)
        return np.where(self.at_camera, -np.inf, ev)


def solve(problem: Problem, x0: np.ndarray, settings: lm.Settings = lm.TIGHT, covariances: bool = False,
          slope: bool = False) -> Solution:
    """Minimise ``problem`` from x0 (F, M, d) (copied), then the information's log det and, as asked, the
    marginal covariances and the evidence's slope, at the minimiser with the IRLS curvature."""
    res = lm.minimise(Chains(problem), np.array(x0, float), settings)
    _, _, D, B, _ = problem.system(res.state, False)
    sweeps = tridiagonal(D, B[:, :, None], marginals=covariances,
                         motion=problem.motion_blocks() if slope else None)
    F = res.state.shape[0]
    logdet = sweeps["logdet"] + log_det_units(problem.model, problem.fps, F)
    return Solution(res.state, res.cost, logdet, sweeps.get("Sigma"),
                    evidence_slope(problem, res.state, sweeps["trace"]) if slope else None,
                    res.iterations, res.converged, res.at_camera)


def evidence_slope(problem: Problem, x: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """d log evidence / d ln level (M,) at the minimiser x, from tr(H^-1 H_m) (M,) of the motion part H_m:
    E_motion(x) + 0.5 tr(H^-1 H_m) - 0.5 (F - 1) d (the envelope theorem through x; how the rows' Jacobians and
    weights move with x is left out). Its zero is EM's fixed point. Per ln sigma_m for the random walk: twice that."""
    F, d = x.shape[0], problem.d
    per_scale = problem.motion_cost(x) + 0.5 * trace - 0.5 * (F - 1) * d
    return 2.0 * per_scale if problem.model == "random_walk" else per_scale
