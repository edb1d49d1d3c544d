"""The 11-parameter DLT: pixel origins, units and handedness, and DLT <-> K, R, t.

A DLT coefficient set depends on three conventions its file does not state: the **pixel origin** (OpenCV,
batgraph's: (0, 0) the centre of the top-left pixel, v down; ``upper-left`` files, 1-based: ``u_cv + 1,
v_cv + 1``; ``lower-left`` files, every DLTdv version, Argus, easyWand: ``u_cv + 1, H - v_cv``), the
**handedness** of the world (it may be mirrored) and its **units**.
For a right-handed world and OpenCV pixels, P = lambda K [R | t] with det R = +1 and K's diagonal positive,
so sign(det P[:, :3]) = sign(lambda), and a point in front of the camera has ``w = P[2] @ [X, 1]`` of that
sign. A lower-left origin or a mirrored world each flip sign(det P[:, :3]) and leave w alone, so
:func:`orientation_sign`, sign(det P[:, :3] * w) over the points a camera sees, is +1 for upper-left pixels
with a right-handed world (or lower-left with a mirrored one) and -1 for lower-left with a right-handed world
(or upper-left with a mirrored one): the coefficients cannot tell the two readings of one sign apart, and
both give the same 3D in the file's own world frame. This module converts; it reads no files
(:mod:`batgraph.formats.dltdv` does).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

PIXEL_ORIGINS = ("lower-left", "upper-left")
UNITS_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per unit of a world given in these units


def pixel_affine(origin: str, height_px: float | None = None) -> np.ndarray:
    """Affine map A (3, 3) from OpenCV homogeneous pixels to ``origin`` pixels: ``uv_file = A @ uv_cv``.

    A DLT matrix converts as ``P_file ~ A @ P_cv``. height_px: image height H [px], needed for
    ``lower-left`` (the y axis flips about it).
    """
    if origin == "upper-left":
        return np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 1]])
    if origin == "lower-left":
        if height_px is None:
            raise ValueError("lower-left pixels: the image height is needed")
        return np.array([[1.0, 0, 1], [0, -1, float(height_px)], [0, 0, 1]])
    raise ValueError(f"pixel origin must be one of {PIXEL_ORIGINS}, got {origin!r}")


def apply_affine(A: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) through the affine A (3, 3) (last row 0 0 1); NaN stays NaN."""
    uv = np.asarray(uv_px, dtype=float)
    return uv @ A[:2, :2].T + A[:2, 2]


def dlt_matrix(coefs: np.ndarray) -> np.ndarray:
    """Coefficients L1..L11 (..., 11) -> projection matrices (..., 3, 4) with P[2, 3] = 1."""
    L = np.asarray(coefs, dtype=float)
    return np.concatenate([L, np.ones(L.shape[:-1] + (1,))], axis=-1).reshape(L.shape[:-1] + (3, 4))


def dlt_coefs(P: np.ndarray) -> np.ndarray:
    """Projection matrices (..., 3, 4) -> coefficients L1..L11 (..., 11) (scaled so P[2, 3] = 1)."""
    P = np.asarray(P, dtype=float)
    return (P / P[..., 2:3, 3:4]).reshape(P.shape[:-2] + (12,))[..., :11]


def transform_dlt(P: np.ndarray, pixel_from: np.ndarray | None = None,
                  world_to: np.ndarray | None = None) -> np.ndarray:
    """The same cameras in other pixel and world coordinates, shape (..., 3, 4).

    pixel_from: A (3, 3) with ``uv_new = A @ uv_old``. world_to: T (4, 4) with ``X_old = T @ X_new``
    (homogeneous): ``P_new = A @ P_old @ T``.
    """
    P = np.asarray(P, dtype=float)
    if pixel_from is not None:
        P = pixel_from @ P
    if world_to is not None:
        P = P @ world_to
    return P


def world_scale_mirror(metres_per_unit: float, mirror: np.ndarray | None = None) -> np.ndarray:
    """T (4, 4) with ``X_file = T @ X_internal``: X_internal in metres, optionally mirrored.

    mirror: (3,) of +-1 with ``x_user = mirror * x_internal`` (x_user in metres, the file's frame).
    """
    m = np.ones(3) if mirror is None else np.asarray(mirror, dtype=float)
    return np.diag(np.append(m / metres_per_unit, 1.0))


def principal_point(P: np.ndarray) -> np.ndarray:
    """Principal point (..., 2) [px] of projection matrices (..., 3, 4), in their own pixel convention.

    The image of the optical axis: ``(m1 . m3, m2 . m3) / |m3|^2`` with m_i the rows of P[:, :3]; it
    needs no decomposition and no convention.
    """
    M = np.asarray(P, dtype=float)[..., :3]
    m3 = M[..., 2, :]
    return np.einsum("...ij,...j->...i", M[..., :2, :], m3) / np.sum(m3 * m3, axis=-1)[..., None]


def orientation_sign(P: np.ndarray, xyz: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Per camera, the fraction of the points it sees with det(P[:, :3]) * w > 0 (module docstring).

    P: (C, 3, 4); xyz: (N, 3) in P's world (NaN rows ignored); seen: bool (C, N).
    Returns (C,): 1.0 = all consistent with upper-left pixels and a right-handed world, 0.0 = all with
    lower-left pixels (or a mirrored world); NaN for a camera that sees no finite point.
    """
    P = np.asarray(P, dtype=float)
    w = np.einsum("cj,nj->cn", P[:, 2, :3], np.nan_to_num(xyz)) + P[:, 2, 3:4]  # (C, N)
    s = np.sign(np.linalg.det(P[:, :, :3]))[:, None] * w > 0
    use = seen & np.isfinite(xyz).all(axis=1)[None]
    n = use.sum(axis=1)
    with np.errstate(invalid="ignore"):
        return np.where(n > 0, (s & use).sum(axis=1) / np.maximum(n, 1), np.nan)


def krt_from_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3, 3), R (3, 3), t (3,) of a projection matrix (3, 4) for OpenCV pixels and a right-handed world.

    P's overall sign is chosen so that det(P[:, :3]) > 0; K comes from an RQ decomposition with a
    positive diagonal and K[2, 2] = 1 (skew kept), det(R) = +1. Points in front of the camera are those
    with ``P[2] @ [X, 1]`` of the sign det(P[:, :3]) had: callers check that (:func:`orientation_sign`).
    """
    P = np.asarray(P, dtype=float)
    if np.linalg.det(P[:, :3]) < 0:  # the DLT's overall scale is negative: flip it
        P = -P
    K, R = scipy.linalg.rq(P[:, :3])
    S = np.diag(np.sign(np.diag(K)))  # make K's diagonal positive (S @ S = I)
    K, R = K @ S, S @ R
    t = np.linalg.solve(K, P[:, 3])
    return K / K[2, 2], R, t
