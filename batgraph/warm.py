"""Compile every numba loop, the solver's (batgraph.solver.kernels) and association's (batgraph.associate.kernels),
ahead of the first reconstruct or associate: ``make install`` runs ``python -m batgraph.warm``; numba caches the
compiled loops on disk."""

from __future__ import annotations

import numpy as np

from .associate import kernels as associate_kernels
from .camera import Camera, Rig
from .measurement import IdealObservations
from .solver import chains, kernels, lm
from .solver.problem import Cameras, Loss, Problem, Rows


def compile_all() -> None:
    """Compile every loop for the argument types the solver and association pass (tiny inputs), so that the first
    reconstruct or associate does not wait for it: ``python -m batgraph.warm`` (run by ``make install``)."""
    rig = Rig([Camera("a", (100, 100), [[100, 0, 50], [0, 100, 50], [0, 0, 1]], tvec=[0.0, 0.0, 1.0]),
               Camera("b", (100, 100), [[100, 0, 50], [0, 100, 50], [0, 0, 1]], tvec=[0.1, 0.0, 1.0])])
    uv = np.full((2, 3, 1, 2), 50.0)
    ideal = IdealObservations(uv, np.broadcast_to(np.eye(2), (2, 3, 1, 2, 2)).copy())
    for name in ("random_walk", "constant_velocity", "constant_acceleration"):
        prob = Problem(Rows.of(ideal), Cameras.of(rig), 100.0, 3, name, np.ones(1), Loss("huber"), np.zeros((1, 3)))
        chains.solve(prob, np.zeros((3, 1, prob.d)), lm.LOOSE, covariances=True, slope=True)
        kernels.row_terms(np.zeros((3, 1, prob.d)), prob.rows, prob.cams, Loss("huber"))
    z1, z2 = np.zeros(1, np.int64), np.zeros((1, 2))
    for exact in (False, True):
        kernels.shared_terms(z1, z1, np.zeros((1, 2, 3)), z2, np.zeros((1, 2, 3)), np.ones(1), np.ones(1),
                             np.zeros((1, 2, 1)), np.zeros((1, 1), np.int64), exact, 1, 1, 3, 1)
    kernels.mirror_lower(np.eye(3))
    kernels.mirror_lower(np.asfortranarray(np.eye(3)))  # LAPACK's output (segments)
    kernels.robust_loss(np.ones(2), 1, 2.0)
    associate_kernels.pair_distance_medians(np.zeros((2, 1, 3)))


if __name__ == "__main__":
    compile_all()
