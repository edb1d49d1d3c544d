"""Solve a session's markers, each with its own motion model and noise level: markers in no segment as chains
(batgraph.solver.chains, one batch per model), each segment group as one column (batgraph.solver.segments).
With fixed cameras this is the joint minimiser exactly: markers share nothing else."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from ..camera import Rig
from ..measurement import IdealObservations, without
from . import chains, kernels, lm, segments
from . import model as mm
from .problem import Cameras, Loss, Problem, Rows, derivatives, log_det_units, start_state
from .threads import one_blas_thread

PLAIN = Loss("none")  # plain Gaussian whitening


@dataclass
class Setup:
    """What every solve of one session shares: the observations (C, F, M), the rig, fps, the loss, the initial
    track p_init (F, M, 3) [m] (its first frame the gauge prior's mean; NaN for a marker not estimated) and the
    segments (pairs (S, 2) marker indices, their stiffness sigma [m])."""

    ideal: IdealObservations
    rig: Rig
    fps: float
    loss: Loss
    p_init: np.ndarray
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    rigid_sigma_m: float = 0.002

    @cached_property
    def cams(self) -> Cameras:
        return Cameras.of(self.rig)

    @property
    def estimated(self) -> np.ndarray:
        return np.isfinite(self.p_init).all(axis=(0, 2))

    @property
    def shape(self) -> tuple[int, int]:
        return self.p_init.shape[:2]

    def without(self, drop: np.ndarray) -> Setup:
        """The same with the observations where ``drop`` (C, F, M) made unseen."""
        return replace(self, ideal=without(self.ideal, drop))

    def problem(self, markers: np.ndarray, name: str, level: np.ndarray) -> Problem:
        """The problem of ``markers`` (int indices) with model ``name`` at levels (len(markers),)."""
        F = self.p_init.shape[0]
        return Problem(Rows.of(self.ideal, markers), self.cams, self.fps, F, name, level, self.loss,
                       self.p_init[0, markers])


@dataclass
class Fit:
    """A solve: xyz (F, M, 3) [m], cov (F, M, 3, 3) [m^2] or None, velocity and acceleration (F, M, 3) [m/s, m/s^2]
    (NaN where the marker's model has none); state (F, M, 9) each marker's scaled state (its model's d first, NaN
    after) and models (M,) their names (None: not solved); per marker cost, logdet (physical units; a group's on
    its first member), iterations, converged, at_camera; per segment used: pairs (S', 2), length_m, length_sd_m."""

    state: np.ndarray
    models: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray | None
    velocity: np.ndarray
    acceleration: np.ndarray
    cost: np.ndarray
    logdet: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    at_camera: np.ndarray
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    length_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    length_sd_m: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def empty(cls, F: int, M: int, covariances: bool) -> Fit:
        nan3 = np.full((F, M, 3), np.nan)
        return cls(np.full((F, M, 9), np.nan), np.full(M, None, object), nan3,
                   np.full((F, M, 3, 3), np.nan) if covariances else None, nan3.copy(), nan3.copy(), np.zeros(M),
                   np.zeros(M), np.zeros(M, int), np.zeros(M, bool), np.zeros(M, bool))

    def merge(self, other: Fit, markers: np.ndarray) -> Fit:
        """This fit with ``markers`` (M,) bool, and their segments, taken from ``other``, in place."""
        for name in ("state", "xyz", "velocity", "acceleration"):
            getattr(self, name)[:, markers] = getattr(other, name)[:, markers]
        if self.cov is not None and other.cov is not None:
            self.cov[:, markers] = other.cov[:, markers]
        for name in ("models", "cost", "logdet", "iterations", "converged", "at_camera"):
            getattr(self, name)[markers] = getattr(other, name)[markers]
        mine = ~markers[self.pairs].all(axis=1) if len(self.pairs) else np.zeros(0, bool)
        self.pairs = np.concatenate([self.pairs[mine], other.pairs])
        self.length_m = np.concatenate([self.length_m[mine], other.length_m])
        self.length_sd_m = np.concatenate([self.length_sd_m[mine], other.length_sd_m])
        return self


def solve(setup: Setup, models: np.ndarray, levels: np.ndarray, start: tuple, settings: lm.Settings = lm.TIGHT,
          covariances: bool = True, with_segments: bool = True) -> Fit:
    """Minimise the cost of the markers with a model (models (M,) names, None for the others; levels (M,)) from
    start = (p, v, a) (F, M, 3) [m, m/s, m/s^2] (v, a may be None: np.gradient), with the session's segments
    between solved markers unless ``with_segments`` is False (the members of a group must share one model)."""
    with one_blas_thread():
        return _solve(setup, models, levels, start, settings, covariances, with_segments)


def _solve(setup, models, levels, start, settings, covariances, with_segments) -> Fit:
    F, M = setup.shape
    out = Fit.empty(F, M, covariances)
    solved = np.array([m is not None for m in models])
    found = segments.groups(setup.pairs, solved) if with_segments else []
    grouped = np.zeros(M, bool)
    for members, _ in found:
        grouped[members] = True
    for name in dict.fromkeys(m for m in models[solved & ~grouped]):
        ms = np.flatnonzero((models == name) & ~grouped)
        prob = setup.problem(ms, name, levels[ms])
        sol = chains.solve(prob, _start(name, setup.fps, start, ms), settings, covariances=covariances)
        _put(out, ms, sol.x, None if sol.Sigma is None else sol.Sigma[..., :3, :3], setup.fps, name)
        out.cost[ms], out.logdet[ms] = sol.cost, sol.logdet
        out.iterations[ms], out.converged[ms], out.at_camera[ms] = sol.iterations, sol.converged, sol.at_camera
    pairs, lengths, sds = [], [], []
    for members, seg_ids in found:
        names = set(models[members])
        if len(names) != 1:
            raise ValueError(f"markers {members.tolist()} are joined by segments but have models {sorted(names)}")
        name = names.pop()
        x, L, cov_L, ld, res, cov = _solve_group(setup, members, seg_ids, name, levels, start, settings,
                                                 covariances)
        _put(out, members, x, cov, setup.fps, name)
        out.cost[members] = res.cost[0] / len(members)
        out.logdet[members] = 0.0
        out.logdet[members[0]] = ld + log_det_units(name, setup.fps, F) * len(members)
        out.iterations[members], out.converged[members] = res.iterations[0], res.converged[0]
        out.at_camera[members] = res.at_camera[0]
        pairs.append(setup.pairs[seg_ids])
        lengths.append(L)
        sds.append(np.sqrt(np.diag(cov_L)))
    if pairs:
        out.pairs, out.length_m, out.length_sd_m = np.concatenate(pairs), np.concatenate(lengths), np.concatenate(sds)
    return out


def _solve_group(setup, members, seg_ids, name, levels, start, settings, covariances):
    prob = setup.problem(members, name, levels[members])
    seg = segments.Segments(np.searchsorted(members, setup.pairs[seg_ids]), setup.rigid_sigma_m)
    x = _start(name, setup.fps, start, members)
    group = segments.Group(prob, seg)
    state = (x, segments.initial_lengths(x[..., :3], seg.local, setup.ideal.seen.any(axis=0)[:, members]))
    res = lm.minimise(group, state, settings)
    cov_x, cov_L, ld = segments.marginals(group, state, covariances)
    return state[0], state[1], cov_L, ld, res, None if cov_x is None else cov_x[..., :3, :3]


def _start(name: str, fps: float, start: tuple, ms: np.ndarray) -> np.ndarray:
    p, v, a = start
    return start_state(name, fps, p[:, ms], None if v is None else v[:, ms], None if a is None else a[:, ms])


def _put(out: Fit, ms: np.ndarray, x: np.ndarray, cov: np.ndarray | None, fps: float, name: str) -> None:
    out.state[:, ms, :x.shape[-1]] = x
    out.models[ms] = name
    out.xyz[:, ms] = x[..., :3]
    if out.cov is not None and cov is not None:
        out.cov[:, ms] = cov
    v, a = derivatives(x, fps)
    if v is not None:
        out.velocity[:, ms] = v
    if a is not None:
        out.acceleration[:, ms] = a


def log_evidence(fit: Fit, models: np.ndarray, levels: np.ndarray, fps: float) -> np.ndarray:
    """Each chain's Laplace log marginal likelihood (M,) (NaN for markers without a model)."""
    F = fit.xyz.shape[0]
    out = np.full(len(models), np.nan)
    for name in dict.fromkeys(m for m in models if m is not None):
        ms = models == name
        out[ms] = mm.log_evidence(fit.cost[ms], fit.logdet[ms], levels[ms], name, 1.0 / fps, F - 1)
    return out


def sq_residuals(setup: Setup, fit: Fit) -> np.ndarray:
    """|r|^2 = |L^-1 (pi(p(t)) - uv)|^2 of every observation of ``setup`` at ``fit``'s states (plain Gaussian
    whitening), (C, F, M); NaN where unseen, not solved, or behind the camera."""
    C, F, M = setup.ideal.seen.shape
    out = np.full((C, F, M), np.nan)
    for name in dict.fromkeys(m for m in fit.models if m is not None):
        ms = np.flatnonzero(fit.models == name)
        prob = setup.problem(ms, name, np.ones(len(ms)))
        x = np.ascontiguousarray(fit.state[:, ms, :prob.d])
        terms = kernels.row_terms(x, prob.rows, prob.cams, PLAIN)
        rows = prob.rows
        out[rows.cam, rows.frame, ms[rows.marker]] = np.where(terms["inv"] > 0, (terms["r"] ** 2).sum(axis=1), np.nan)
    return out

