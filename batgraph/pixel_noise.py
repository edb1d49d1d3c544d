"""Pixel noise per camera, measured from the session's own observations (no ground truth needed).

Every (frame, marker) seen by >= 2 cameras is triangulated by weighted least squares (linear DLT, then
Gauss-Newton on the ideal-pixel reprojection error with each camera's current noise). At that
solution an observation's unit-noise squared residual ``e = r^T S1^-1 r`` (S1 its 2x2 ideal-pixel
covariance for a 1 px raw-pixel noise, batgraph.measurement) has expectation ``sigma_c^2 (2 - h)``,
h the trace of its 2x2 block of the weighted hat matrix (its leverage: the degrees of freedom the 3D
point took from it). Per camera, ``sigma_c^2 = sum e / sum (2 - h)`` over its inliers
(``e / sigma_c^2 < 13.82``, chi-square 2 DOF 99.9 %: mislabels do not inflate it), iterated from a
median start, then the triangulation is re-weighted with the new sigmas and the whole repeated until
the sigmas change by < 1 %. A camera with fewer than MIN_OBSERVATIONS inliers gets the pooled value.

A large session is measured on a sample of its markers (:func:`sample_markers`: at most MAX_POINTS
(frame, marker) points, markers spread over the list, topped up until every camera keeps
MIN_SAMPLED_OBSERVATIONS of its observations): at 30 x 180 x 160 it measures 50 of 180 markers, 3,800-5,000
observations a camera, whose statistical error in sigma is ~1 % (1 / sqrt(2 nu), nu = sum (2 - h) their degrees
of freedom), the iteration's own tolerance; measured, the sampled sigmas are the whole session's within 1.5 %,
in 0.18 s instead of 0.54 s.

Why not a library: aniposelib and OpenCV report reprojection errors, which understate the noise by the
leverage (with 2 cameras by half) and mix cameras; this is the unbiased per-camera figure.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Rig
from .measurement import IdealObservations
from .triangulate import dlt_points

CHI2_2DOF_999 = 13.815510557964274
MIN_OBSERVATIONS = 20
MAX_POINTS = 8000  # (frame, marker) points measured; more are sampled by marker (sample_markers)
MIN_SAMPLED_OBSERVATIONS = 2000  # each camera keeps this many of its observations in the sample (or all it has)
MEDIAN_CHI2_2DOF = 2 * math.log(2)  # median of chi-square with 2 DOF


def _gauss_newton(P: np.ndarray, uv: np.ndarray, Wu: np.ndarray, w_scale: np.ndarray, xyz: np.ndarray,
                  use: np.ndarray, iters: int = 3):
    """Refine xyz (F, M, 3) by weighted Gauss-Newton, a step kept per point only where it lowers its cost.

    P (C, 3, 4) projection matrices to ideal pixels; uv (C, F, M, 2) ideal pixels (0 where unseen); Wu
    (C, F, M, 2, 2) each observation's unit information S1^-1 (zero where not used); w_scale: (C,) 1 / sigma_c^2
    multiplying it; use: bool (C, F, M), the observations that take part (points with >= 2 of them are refined,
    the others are NaN). Returns xyz, residuals r (C, F, M, 2) [ideal px], each observation's leverage h
    (C, F, M) (zero where not used) and the posterior covariance Sigma (F, M, 3, 3) for the weights w_scale
    (NaN where not triangulated). The per-point loop is compiled (batgraph.graph.kernels.weighted_triangulation:
    2.5 -> 0.57 s at 30 x 180 x 160).
    """
    from .graph import kernels  # numba: imported when the pixel noise is measured

    W = Wu * w_scale[:, None, None, None, None]
    ok = np.isfinite(xyz).all(axis=-1) & (use.sum(axis=0) >= 2)
    xyz = np.ascontiguousarray(np.where(ok[..., None], xyz, np.nan))
    r = np.zeros(use.shape + (2,))
    h = np.zeros(use.shape)
    Sigma = np.full(xyz.shape + (3,), np.nan)
    kernels.weighted_triangulation(P, uv, W, use & ok[None], xyz, iters, r, h, Sigma)
    return xyz, r, h, Sigma


def sample_markers(seen: np.ndarray, max_points: int = MAX_POINTS,
                   min_observations: int = MIN_SAMPLED_OBSERVATIONS) -> np.ndarray:
    """The markers (sorted indices into M) whose points the pixel noise is measured on, for observations
    ``seen`` (C, F, M) bool: all when F x M <= max_points; else max(1, max_points // F) markers spread evenly
    over the list, then, for each camera with fewer than min(min_observations, all it has) observations of
    points seen twice among them, its own most observed markers added until it has that many."""
    C, F, M = seen.shape
    if F * M <= max_points:
        return np.arange(M)
    keep = np.zeros(M, bool)
    keep[np.unique(np.linspace(0, M - 1, max(1, max_points // F)).round().astype(int))] = True
    per = (seen & (seen.sum(axis=0) >= 2)[None]).sum(axis=1)  # (C, M) observations usable for the noise
    for c in range(C):
        need, have = min(min_observations, int(per[c].sum())), int(per[c][keep].sum())
        for m in np.argsort(-per[c], kind="stable"):
            if have >= need:
                break
            if not keep[m]:
                keep[m], have = True, have + int(per[c, m])
    return np.flatnonzero(keep)


def estimate_pixel_sigma(rig: Rig, ideal_unit: IdealObservations, xyz_start: np.ndarray | None = None,
                         max_rounds: int = 6, max_points: int = MAX_POINTS,
                         min_observations: int = MIN_SAMPLED_OBSERVATIONS) -> tuple[np.ndarray, dict]:
    """Per-camera raw-pixel noise std [px] (module docstring).

    ideal_unit: ideal observations with a 1 px raw-pixel noise (``ideal_observations(rig, dense, 1.0)``),
    uv_px (C, F, M, 2), cov_px2 (C, F, M, 2, 2). xyz_start: the linear triangulation (F, M, 3) if the
    caller has it. Observations of points behind their camera at the start take no part (the geometry
    checks report them). Measured on the markers :func:`sample_markers` picks (``max_points``,
    ``min_observations``). Returns sigma (C,) [px] and info: "cameras", per camera name {"sigma_px", "n_used",
    "n_rejected", "pooled"}; "markers", the sampled markers' indices (K,); "xyz_m" (F, K, 3) and "cov_m2"
    (F, K, 3, 3), their weighted triangulation at the final sigmas (world frame, NaN where < 2 views).
    Cameras with no usable observation get the pooled value; NaN everywhere if no point has 2 views.
    """
    C = len(rig)
    xyz0 = dlt_points(rig, ideal_unit) if xyz_start is None else xyz_start
    markers = sample_markers(ideal_unit.seen, max_points, min_observations)
    if len(markers) < xyz0.shape[1]:
        ideal_unit = IdealObservations(ideal_unit.uv_px[:, :, markers], ideal_unit.cov_px2[:, :, markers])
        xyz0 = xyz0[:, markers]
    seen = ideal_unit.seen & np.isfinite(xyz0).all(axis=-1)[None]
    for c, cam in enumerate(rig):
        seen[c][seen[c]] = cam.to_cam(xyz0[seen[c]])[:, 2] > 0
    # what every round shares: the cameras, the pixels and each observation's unit information
    P = np.stack([cam.P for cam in rig])
    uv = np.ascontiguousarray(np.nan_to_num(ideal_unit.uv_px))
    Wu = np.zeros(seen.shape + (2, 2))
    cov = ideal_unit.cov_px2[seen]  # 2x2 inverses in closed form: 0.03-0.07 s vs np.linalg.inv 0.12 s on 5e5
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    Wu[seen] = np.stack([np.stack([c, -b], axis=-1), np.stack([-b, a], axis=-1)], axis=-2) / det[:, None, None]
    sigma2 = np.ones(C)
    for _ in range(max_rounds):
        # leverage h = tr(W J Sigma J^T) = sum(J^T W J * Sigma) (Sigma symmetric), W = Wu / sigma_c^2
        xyz, r, h, Sigma = _gauss_newton(P, uv, Wu, 1.0 / sigma2, xyz0, seen)
        seen_now = seen & np.isfinite(xyz).all(axis=-1)[None]
        e = np.einsum("...i,...ij,...j->...", r, Wu, r)  # (C, F, M) unit-noise squared residuals
        dof = np.clip(2.0 - h, 1e-6, 2.0)
        new = np.full(C, np.nan)
        used, rejected = np.zeros(C, int), np.zeros(C, int)
        for c in range(C):
            ec, dc = e[c][seen_now[c]], dof[c][seen_now[c]]
            if len(ec) == 0:
                continue
            s2 = float(np.median(ec / (dc / 2))) / MEDIAN_CHI2_2DOF
            for _ in range(10):
                inl = ec < CHI2_2DOF_999 * max(s2, 1e-30)
                s2_new = float(ec[inl].sum() / dc[inl].sum()) if inl.any() else s2
                if abs(s2_new - s2) <= 1e-4 * s2:
                    s2 = s2_new
                    break
                s2 = s2_new
            new[c], used[c], rejected[c] = s2, int(inl.sum()), int((~inl).sum())
        enough = used >= MIN_OBSERVATIONS
        pooled = (float(np.sum(new[enough] * used[enough]) / used[enough].sum()) if enough.any()
                  else float(np.nanmean(new)) if np.isfinite(new).any() else np.nan)
        new = np.maximum(np.where(enough, new, pooled), 1e-12)
        done = np.all(np.abs(new - sigma2) <= 0.01 * sigma2)
        sigma2 = new
        if done or not np.isfinite(sigma2).all():
            break
    sigma = np.sqrt(sigma2)
    info = {cam.name: {"sigma_px": float(sigma[c]), "n_used": int(used[c]), "n_rejected": int(rejected[c]),
                       "pooled": bool(not enough[c])} for c, cam in enumerate(rig)}
    return sigma, {"cameras": info, "markers": markers, "xyz_m": xyz, "cov_m2": Sigma}
