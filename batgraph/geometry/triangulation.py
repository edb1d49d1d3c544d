"""Linear (homogeneous DLT) triangulation: the one implementation, for any projection matrices.

Each view of a point gives Hartley & Zisserman's two rows ``x P3 - P1`` and ``y P3 - P2`` (P (3, 4), x, y the
point's coordinates in P's image); the point is the homogeneous least-squares solution of the stacked rows.
"""

from __future__ import annotations

import numpy as np

_IU4 = np.triu_indices(4)  # the 10 distinct entries of a symmetric 4x4 matrix


def linear_points(P: np.ndarray, xy: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """Homogeneous least-squares triangulation of N points seen by C cameras.

    P: (C, 3, 4) projection matrices; xy: (C, N, 2) image coordinates in P's convention, NaN where a camera
    does not see a point. weight: None scales every row to unit norm (each view weighs the same whatever P's
    units, for a file's raw DLT matrices), or (C,): camera c's rows count ``weight[c]`` times in the sum of
    squares (e.g. fx fy, so a row in normalised coordinates is ``depth * pixel residual``).
    Returns xyz (N, 3) in P's world; NaN where fewer than 2 cameras see the point.
    Solved as the eigenvector of the smallest eigenvalue of the 4x4 normal matrix, accumulated per camera: the
    SVD of the stacked (2C, 4) rows has the same null vector but costs 2-3x in time and 2C x 4 memory per point.
    """
    P = np.asarray(P, dtype=float)
    seen = np.isfinite(xy[..., 0])  # (C, N)
    i, j = _IU4
    normal = np.zeros((seen.shape[1], len(i)))  # upper triangle of each point's normal matrix
    for c in range(len(P)):
        s = seen[c]
        if not s.any():
            continue
        a = xy[c, s, 0:1] * P[c, 2] - P[c, 0]  # (n, 4)
        b = xy[c, s, 1:2] * P[c, 2] - P[c, 1]
        if weight is None:
            normal[s] += (a[:, i] * a[:, j]) / _squared_norm(a) + (b[:, i] * b[:, j]) / _squared_norm(b)
        else:
            normal[s] += weight[c] * (a[:, i] * a[:, j] + b[:, i] * b[:, j])
    ok = seen.sum(axis=0) >= 2
    xyz = np.full((seen.shape[1], 3), np.nan)
    if ok.any():
        A = np.zeros((int(ok.sum()), 4, 4))
        A[:, i, j] = A[:, j, i] = normal[ok]
        X = np.linalg.eigh(A)[1][:, :, 0]  # eigenvalues ascending: the first eigenvector
        with np.errstate(divide="ignore", invalid="ignore"):
            xyz[ok] = X[:, :3] / X[:, 3:4]
    return xyz


def _squared_norm(rows: np.ndarray) -> np.ndarray:
    """|row|^2 (n, 1) of rows (n, 4), 1 for a zero row (it adds nothing either way)."""
    n2 = np.einsum("ni,ni->n", rows, rows)[:, None]
    return np.where(n2 > 0, n2, 1.0)
