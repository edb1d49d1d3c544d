"""Non-rigid Coherent Point Drift (Myronenko and Song, IEEE TPAMI 32(12), 2010): where each marker of a predicted
configuration went among a frame's points, when the markers move together but not rigidly (a flapping wing).

The predicted positions Y (M, 3) are Gaussian-mixture centroids moved by a smooth displacement field G W (G the
Gaussian kernel of width ``beta`` between the centroids); the points X (N, 3) are drawn from them, or from a
uniform outlier component of weight ``outlier``. EM alternates the posterior P of each point's centroid with the
field and the common variance sigma^2 (held at or above ``min_sigma2``: the points' own noise). Centroids without
a point are carried by the field, as their neighbours move. Nothing here names anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Registration:
    """moved (M, 3) [m]: the centroids after the field; P (M, N): each point's posterior over the centroids (its
    columns sum to 1 less the outlier share); sigma2 [m^2] the final variance."""

    moved: np.ndarray
    P: np.ndarray
    sigma2: float


def register(Y: np.ndarray, X: np.ndarray, beta: float, lam: float = 2.0, outlier: float = 0.1,
             min_sigma2: float = 1e-6, iters: int = 40, weight: np.ndarray | None = None) -> Registration:
    """Register centroids Y (M, 3) [m] to points X (N, 3) [m] (see module docstring). weight (N,): how much each
    point counts (a two-view candidate is a marker less often than a point of three views)."""
    M, N = len(Y), len(X)
    if M == 0 or N == 0:
        return Registration(Y.copy(), np.zeros((M, N)), float("nan"))
    w = np.ones(N) if weight is None else weight
    G = np.exp(-np.sum((Y[:, None] - Y[None]) ** 2, axis=-1) / (2 * beta * beta))
    W = np.zeros((M, 3))
    TY = Y.copy()
    sigma2 = max(float(np.sum((X[None] - Y[:, None]) ** 2)) / (3 * M * N), min_sigma2)
    P = np.zeros((M, N))
    for _ in range(iters):
        d2 = np.sum((X[None] - TY[:, None]) ** 2, axis=-1)  # (M, N)
        P = np.exp(-d2 / (2 * sigma2))
        c = (2 * math.pi * sigma2) ** 1.5 * outlier / (1 - outlier) * M / N
        P = P / (P.sum(axis=0, keepdims=True) + c) * w[None]
        P1, Np = P.sum(axis=1), P.sum()
        if Np < 1e-9:
            break
        PX = P @ X
        W = np.linalg.solve(P1[:, None] * G + lam * sigma2 * np.eye(M), PX - P1[:, None] * Y)
        TY = Y + G @ W
        new = (np.sum(P.sum(axis=0) * np.sum(X * X, axis=1)) - 2 * np.sum(PX * TY)
               + np.sum(P1 * np.sum(TY * TY, axis=1))) / (3 * Np)
        new = max(float(new), min_sigma2)
        if abs(new - sigma2) < 1e-3 * sigma2:
            sigma2 = new
            break
        sigma2 = new
    return Registration(TY, P, sigma2)
