"""Pixel noise per camera, measured from the session's own observations (no ground truth needed).

Every (frame, marker) seen by >= 2 cameras is triangulated by weighted least squares (linear DLT, then
Gauss-Newton on the ideal-pixel reprojection error with each camera's current noise). There an observation's
unit-noise squared residual ``e = r^T S1^-1 r`` (S1 its ideal-pixel covariance for 1 px of raw-pixel noise,
batgraph.measurement) has expectation ``sigma_c^2 (2 - h)``, h the trace of its 2x2 block of the weighted hat
matrix (the degrees of freedom the point took from it). Per camera ``sigma_c^2 = sum e / sum (2 - h)`` over its
inliers (``e / sigma_c^2 < 13.82``, chi-square 2 DOF 99.9 %: mislabels do not inflate it), from a median start;
the points are re-weighted with the new sigmas until they change by < 1 %. A camera with fewer than
MIN_OBSERVATIONS inliers gets the pooled value. A large session is measured on a sample of its markers
(:func:`sample_markers`: at most MAX_POINTS points, every camera keeping MIN_SAMPLED_OBSERVATIONS), whose
statistical error, 1 / sqrt(2 sum (2 - h)), is ~1 % at 30 x 180 x 160, the iteration's own tolerance.
Why not a library: aniposelib and OpenCV report reprojection errors, which understate the noise by the
leverage (with 2 cameras by half) and mix cameras; this is the unbiased per-camera figure.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Rig
from .measurement import IdealObservations
from .solver import chains, kernels, lm
from .solver.problem import Cameras, Loss, Problem, Rows
from .triangulate import dlt_points

CHI2_2DOF_999 = 13.815510557964274
MIN_OBSERVATIONS = 20
MAX_POINTS = 8000  # (frame, marker) points measured; more are sampled by marker (sample_markers)
MIN_SAMPLED_OBSERVATIONS = 2000  # each camera keeps this many of its observations in the sample (or all it has)
MEDIAN_CHI2_2DOF = 2 * math.log(2)  # median of chi-square with 2 DOF


def _gauss_newton(rig: Rig, ideal_unit: IdealObservations, w_scale: np.ndarray, xyz: np.ndarray, use: np.ndarray):
    """Weighted least-squares triangulation of every point with >= 2 observations in ``use`` (C, F, M), from xyz
    (F, M, 3): each point a one-frame problem of the solver (batgraph.solver: its row kernel and Levenberg-Marquardt,
    plain loss, a negligible prior), each observation's noise its unit covariance / w_scale[c]. Returns xyz (F, M, 3),
    residuals r (C, F, M, 2) [ideal px, pi(p) - uv], leverages h (C, F, M) (0 where not used) and the posterior
    covariances Sigma (F, M, 3, 3) (NaN where not triangulated)."""
    C, F, M = use.shape
    ok = np.isfinite(xyz).all(axis=-1) & (use.sum(axis=0) >= 2)
    f, m = np.nonzero(ok)
    r, h = np.zeros((C, F, M, 2)), np.zeros((C, F, M))
    out, Sigma = np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan)
    if not len(f):
        return out, r, h, Sigma
    sel = use[:, f, m]  # (C, P): the points as markers of a one-frame problem
    uv = np.where(sel[..., None], ideal_unit.uv_px[:, f, m], np.nan)[:, None]
    cov = ideal_unit.cov_px2[:, f, m] / w_scale[:, None, None, None]
    prob = weighted_points(rig, IdealObservations(uv, cov[:, None]), xyz[f, m])
    res = lm.minimise(chains.Chains(prob), xyz[f, m][None].copy(), lm.TIGHT)
    _, _, D, _, _ = prob.system(res.state, False)
    with np.errstate(all="ignore"):
        S = np.linalg.inv(D[0])
    t = kernels.row_terms(res.state, prob.rows, prob.cams, Loss("none"))
    rows = prob.rows
    Linv = rows.Linv
    L = np.stack([np.stack([1 / Linv[0], np.zeros_like(Linv[0])], -1),
                  np.stack([-Linv[1] / (Linv[0] * Linv[2]), 1 / Linv[2]], -1)], -2)  # L = (L^-1)^-1
    c, p = rows.cam, rows.marker
    r[c, f[p], m[p]] = np.einsum("nij,nj->ni", L, t["r"])
    h[c, f[p], m[p]] = np.einsum("nij,njk,nik->n", t["J"], S[p], t["J"])
    out[f, m], Sigma[f, m] = res.state[0], 0.5 * (S + np.swapaxes(S, -1, -2))
    return out, r, h, Sigma


def weighted_points(rig: Rig, ideal: IdealObservations, xyz: np.ndarray) -> Problem:
    """The weighted triangulation of P points as a one-frame solver problem: ideal (C, 1, P) their observations,
    xyz (P, 3) the start and the mean of a negligible prior (1e-12 / m^2: only keeps a degenerate point finite)."""
    P = len(xyz)
    return Problem(Rows.of(ideal), Cameras.of(rig), 1.0, 1, "random_walk", np.ones(P), Loss("none"), xyz,
                   prior=(xyz, np.broadcast_to(1e-12 * np.eye(3), (P, 3, 3))))


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
    # each observation's unit information
    Wu = np.zeros(seen.shape + (2, 2))
    cov = ideal_unit.cov_px2[seen]  # 2x2 inverses in closed form: 0.03-0.07 s vs np.linalg.inv 0.12 s on 5e5
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    Wu[seen] = np.stack([np.stack([c, -b], axis=-1), np.stack([-b, a], axis=-1)], axis=-2) / det[:, None, None]
    sigma2, start = np.ones(C), xyz0
    for _ in range(max_rounds):
        # leverage h = tr(W J Sigma J^T) = sum(J^T W J * Sigma) (Sigma symmetric), W = Wu / sigma_c^2
        xyz, r, h, Sigma = _gauss_newton(rig, ideal_unit, 1.0 / sigma2, start, seen)
        start = np.where(np.isfinite(xyz), xyz, xyz0)  # the next round's weights move the points little
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
