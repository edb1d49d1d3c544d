"""The backends the schedule runs on: what it asks of a solver (fit, choose) and the two that answer it.

- :data:`FAST`: batgraph's own (chains and segment groups, batgraph.solver.fit; the search of batgraph.solver.search).
- GTSAM's factor graph (batgraph.solver.reference): the same cost as a graph of Point3 / vector variables and
  GTSAM's Levenberg-Marquardt and marginals; the reference the fast backend is tested against, and ``--solver
  gtsam``. Its noise search is the fast one (an evidence is the same number on either backend, tested).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from tqdm.auto import tqdm

from . import fit as fit_mod
from . import lm, search


class Backend(Protocol):
    name: str

    def fit(self, setup: fit_mod.Setup, models: np.ndarray, levels: np.ndarray, start: tuple,
            settings: lm.Settings = lm.TIGHT, covariances: bool = True, with_segments: bool = True) -> fit_mod.Fit: ...

    def choose(self, setup: fit_mod.Setup, start: tuple, candidates: tuple[str, ...], groups: list[np.ndarray],
               progress: bool) -> search.Choice: ...


def choose_fast(setup: fit_mod.Setup, start: tuple, candidates: tuple[str, ...], groups: list[np.ndarray],
                progress: bool) -> search.Choice:
    """batgraph.solver.search.choose over the estimated markers of ``setup``, as full-width (M,) arrays."""
    ms = np.flatnonzero(setup.estimated)
    M = setup.shape[1]
    template = setup.problem(ms, candidates[0], np.ones(len(ms)))
    cut = tuple(None if a is None else a[:, ms] for a in start)
    column = np.full(M, -1)
    column[ms] = np.arange(len(ms))
    local = [column[g] for g in groups]
    with tqdm(desc="choosing each marker's motion noise", disable=not progress, leave=False) as bar:
        ch = search.choose(template, cut, candidates, local, bar)
    model = np.full(M, None, object)
    level, ev = np.full(M, np.nan), np.full(M, np.nan)
    model[ms], level[ms], ev[ms] = ch.model, ch.level, ch.log_evidence
    by_model = {n: _widen(v, ms, M) for n, v in ch.evidence_by_model.items()}
    solution = {n: _widen(v, ms, M) for n, v in ch.solution.items()}
    return search.Choice(model, level, ev, by_model, solution, ch.n_solves)


def _widen(a: np.ndarray, ms: np.ndarray, M: int) -> np.ndarray:
    """(..., M', ...) arrays of the markers ms as (..., M, ...), NaN elsewhere (markers on axis 0 or 1)."""
    axis = 0 if a.ndim == 1 else 1
    shape = list(a.shape)
    shape[axis] = M
    out = np.full(shape, np.nan)
    (out.__setitem__((ms,) if axis == 0 else (slice(None), ms), a))
    return out


@dataclass(frozen=True)
class Fast:
    name: str = "fast"

    def fit(self, setup, models, levels, start, settings=lm.TIGHT, covariances=True, with_segments=True):
        return fit_mod.solve(setup, models, levels, start, settings, covariances, with_segments)

    def choose(self, setup, start, candidates, groups, progress):
        return choose_fast(setup, start, candidates, groups, progress)


FAST = Fast()
