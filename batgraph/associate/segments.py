"""Segments: marker pairs whose distance stays nearly constant (a bone, the body), their lengths measured on the
named points, and the evidence a candidate point's distances to named partners give for a marker.

A segment is a declared pair (session.toml ``[markers] rigid`` and ``skeleton``) or, for marker sets that declare
none, a pair the named points show to be as steady as a bone (learned: LEARN_MIN_FRAMES frames together, a robust
std of at most LEARN_MAX_STD_M, a length of at most LEARN_MAX_LENGTH_M; its std then at least LEARN_MIN_SIGMA_M).
Its length is the median distance, its
std 1.4826 MAD (at least MIN_SIGMA_M, the triangulation's noise on two points; twice that from fewer than three
frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import kernels

CAP_SIGMA = 5.0  # a residual counts at most this many std (one bad point cannot sink a marker)
MIN_SIGMA_M = 0.0015
LEARN_MIN_FRAMES = 40  # more than a wingbeat at 120 fps: a pair steady only over part of a stroke is not a bone
LEARN_MAX_STD_M = 0.002
LEARN_MIN_SIGMA_M = 0.003  # a learned segment is trusted less than a declared one
LEARN_MAX_LENGTH_M = 0.12
LEARN_MAX_PARTNERS = 6  # learned segments kept per marker (the steadiest)


@dataclass
class Segments:
    """Per marker its partners (L, K) (-1: none), the lengths (L, K) [m] and stds (L, K) [m] (NaN: none)."""

    partner: np.ndarray
    length: np.ndarray
    sigma: np.ndarray

    @classmethod
    def none(cls, n_labels: int) -> Segments:
        return cls(np.full((n_labels, 1), -1, np.int64), np.full((n_labels, 1), np.nan), np.full((n_labels, 1), np.nan))


def pair_stats(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per marker pair (L, L): the frames both are named on, the median and the MAD of their distance [m], from
    named positions X (F, L, 3) (NaN where unnamed)."""
    return kernels.pair_distance_medians(np.ascontiguousarray(X.transpose(1, 0, 2), dtype=np.float64))


def measure(X: np.ndarray, pairs: list[tuple[int, int]], learn: bool, noise_m: float = 0.0,
            reference: dict | None = None, stats: tuple | None = None) -> Segments:
    """Segments measured on named positions X (F, L, 3) [m] (NaN where unnamed): the declared ``pairs`` (marker
    index pairs) and, with ``learn``, the steady undeclared ones (see module docstring). noise_m [m]: the points'
    position noise; the stds' floors are at least it (twice it for a learned segment, which may be 1.5 times it).
    reference: {(a, b): length [m]} measured where the user placed both markers: a declared segment's length is
    that, not the named frames' (names carried wrongly all along would otherwise vouch for themselves).
    stats: :func:`pair_stats` of X where the caller has it."""
    min_sigma, learn_sigma = max(MIN_SIGMA_M, noise_m), max(LEARN_MIN_SIGMA_M, 2 * noise_m)
    learn_std = max(LEARN_MAX_STD_M, 1.5 * noise_m)
    reference = reference or {}
    L = X.shape[1]
    declared = {tuple(sorted(p)) for p in pairs}
    n, med, mad = stats if stats is not None else pair_stats(X)
    mad = 1.4826 * mad
    std = np.where(n >= 3, np.maximum(mad, min_sigma), 2 * min_sigma)
    cand = set(declared)
    if learn:
        a, b = np.nonzero(np.triu((n >= LEARN_MIN_FRAMES) & (std <= learn_std) & (med <= LEARN_MAX_LENGTH_M), 1))
        cand |= set(zip(a.tolist(), b.tolist(), strict=True))
    per: list[list[tuple]] = [[] for _ in range(L)]
    for a, b in cand:
        is_declared = (a, b) in declared
        if n[a, b] == 0 and (a, b) not in reference:
            continue
        length = reference.get((a, b), float(med[a, b]) if n[a, b] else np.nan)
        sd = float(std[a, b]) if n[a, b] else 2 * min_sigma
        if not is_declared:
            sd = max(sd, learn_sigma)
        per[a].append((not is_declared, sd, b, length))
        per[b].append((not is_declared, sd, a, length))
    keep = [[x for x in sorted(p) if not x[0]] + [x for x in sorted(p) if x[0]][:LEARN_MAX_PARTNERS] for p in per]
    K = max([len(p) for p in keep] + [1])
    seg = Segments(np.full((L, K), -1, np.int64), np.full((L, K), np.nan), np.full((L, K), np.nan))
    for i, p in enumerate(keep):
        for j, (_, std, other, med) in enumerate(p):
            seg.partner[i, j], seg.length[i, j], seg.sigma[i, j] = other, med, std
    return seg


def evidence(seg: Segments, targets: np.ndarray, points: np.ndarray, placed: np.ndarray, range_m: float) -> np.ndarray:
    """Log likelihood ratios (T, n) that each point (n, 3) [m] is each target marker (T,), from its distances to
    the target's partners placed on this frame (placed: (L, 3) positions, NaN where not placed), against
    "another point": per partner ln N(d; length, std) (residual capped at CAP_SIGMA) - ln(1 / range_m), range_m [m]
    the size of the marker set (a distance uniform on [0, range_m])."""
    part = seg.partner[targets]  # (T, K)
    where = placed[np.maximum(part, 0)]  # (T, K, 3)
    d = np.linalg.norm(points[None, :, None] - where[:, None], axis=-1)  # (T, n, K)
    sigma, length = seg.sigma[targets][:, None], seg.length[targets][:, None]
    z = (d - length) / sigma
    term = (-0.5 * np.minimum(z * z, CAP_SIGMA ** 2) - np.log(sigma * math.sqrt(2 * math.pi)) + math.log(range_m))
    ok = (part >= 0)[:, None] & np.isfinite(term)
    return np.where(ok, term, 0.0).sum(axis=2)
