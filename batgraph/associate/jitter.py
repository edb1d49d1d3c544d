"""Cameras out of step or shaken, frame by frame: per camera and frame, the image shift and time offset that move
its detections onto where the other cameras put the markers; measured on a first association and taken out of the
detections before steps 3-6 run again (batgraph.associate.core; docs/associate.md, step 8).

Free-running cameras paired by the nearest frame (webcams by sync index) see a moving marker up to half a frame
early or late, by an amount that changes from frame to frame, and a camera on a light mount shakes. Either puts a
camera's detections several pixels off the points the other cameras triangulate, on some frames (Caliscope's cam1:
5-14 px on a third of its frames, against 0.85 px of noise), and the gates leave them unnamed there. The model, per
camera and frame: a detection of a marker is off its projection by ``shift + dt * g`` (g the marker's image velocity
[px/s], from its path's frames either side). Markers triangulated on the frame are paired with detections
(:func:`_pairs`), the fit is weighted least squares (pairs beyond the 99.9 % gate dropped and fitted again), and it
is kept where it lowers chi-square by more than 3 DOF's chance at a false-alarm rate of FALSE_ALARM over all the
session's cameras and frames: a synchronised, steady rig keeps its detections as they are. Every detection of a
kept camera-frame is moved back by the fit, its g that of the marker projected nearest it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import refine
from .tracks import CHI2_2DOF_GATE, FrameDetections, jacobian
from .views import Geometry, project

RATIO = 2.0  # a pair's distance against the next nearest, both ways
CANDIDATES = 3  # per projection, its nearest detections whose shifts are tried
FALSE_ALARM = 0.01  # the chance that a synchronised, steady rig has any camera and frame moved
LEAST_PAIRS = 4  # more than the fit's 3 unknowns


@dataclass
class Jitter:
    """Per frame k and camera: shift (F, C, 2) [ideal px] and dt (F, C) [s], zero where nothing significant; the
    markers' positions xyz (F, L, 3) [m] and velocities vel (F, L, 3) [m/s] they were measured with (NaN where
    unknown)."""

    shift: np.ndarray
    dt: np.ndarray
    xyz: np.ndarray
    vel: np.ndarray

    @property
    def moved(self) -> np.ndarray:
        """(F, C) bool: the camera-frames whose detections are moved."""
        return (self.dt != 0) | self.shift.any(axis=-1)


def measure(geom: Geometry, fi: FrameDetections, label: np.ndarray, n_labels: int, fps: float,
            noise_m: float) -> Jitter:
    """Fit every camera and frame against the markers' paths from the named detections label (N,) (see module
    docstring); noise_m [m]: the seeded points' noise (refine.carry's floor)."""
    xyz, std, triangulated, vel = paths(geom, fi, label, n_labels, fps, noise_m)
    F, C = fi.n_frames, len(geom.rig)
    out = Jitter(np.zeros((F, C, 2)), np.zeros((F, C)), xyz, vel)
    focal = np.array([c.K[0, 0] for c in geom.rig])
    from scipy.stats import chi2  # 0.9 s to import: not at batgraph's start-up

    threshold = float(chi2.isf(FALSE_ALARM / (F * C), 3))
    for k in range(F):
        rows = fi.rows(fi.first + k)
        have = np.flatnonzero(triangulated[k] & np.isfinite(vel[k]).all(axis=1))
        if len(have) < LEAST_PAIRS or not len(rows):
            continue
        proj, depth = project(geom, xyz[k, have])
        for c in np.unique(fi.camera[rows]):
            rc = rows[fi.camera[rows] == c]
            front = np.flatnonzero(depth[c] > 0)
            p, d = _pairs(proj[c, front], fi.uv[rc], np.sqrt(CHI2_2DOF_GATE) * float(np.median(fi.sig[rc])))
            if len(p) < LEAST_PAIRS:
                continue
            m = have[front[p]]
            g = np.einsum("pij,pj->pi", jacobian(geom.P[c], xyz[k, m]), vel[k, m])
            r = fi.uv[rc[d]] - proj[c, front[p]]
            s2 = fi.sig[rc[d]] ** 2 + (std[k, m] * focal[c] / depth[c, front[p]]) ** 2
            fit = _fit(r, g, s2, threshold)
            if fit is not None:
                out.shift[k, c], out.dt[k, c] = fit
    return out


def paths(geom: Geometry, fi: FrameDetections, label: np.ndarray, n_labels: int, fps: float, noise_m: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The markers' paths from the named detections label (N,): positions xyz (F, L, 3) [m] and their std (F, L)
    [m] (triangulated, or carried across short gaps: refine.carry), where triangulated (F, L) bool, and velocities
    vel (F, L, 3) [m/s] from the frames either side (NaN where unknown)."""
    xyz, std, _ = refine.positions(geom, fi, label, n_labels)
    triangulated = np.isfinite(std)
    xyz, std = refine.carry(xyz, std, fps, noise_m)
    vel = np.full_like(xyz, np.nan)
    vel[1:-1] = (xyz[2:] - xyz[:-2]) * fps / 2
    return xyz, std, triangulated, vel


def _pairs(proj: np.ndarray, uv: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Projections (P, 2) and detections (n, 2) paired (projection indices, detection indices): each projection
    with the detection nearest it where each is the other's nearest and RATIO times nearer than the next, both
    ways, after the shift that brings the most projections within tol [px] of a detection (the least among equals;
    tried: none, and from each projection to its CANDIDATES nearest detections): a camera whose detections are all
    off by more than their spacing's half-ratio is still paired. A shift of half the projections' spacing or more
    (the median distance to the nearest other) is not tried: it cannot be told from naming every marker as its
    neighbour (a board's corners lie on a grid)."""
    from scipy.spatial import cKDTree  # 50 ms to import: only associate needs it

    if len(proj) < 2 or len(uv) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    tree = cKDTree(uv)
    _, near = tree.query(proj, k=min(CANDIDATES, len(uv)))
    shifts = np.concatenate([np.zeros((1, 2)), (uv[near.reshape(len(proj), -1)] - proj[:, None]).reshape(-1, 2)])
    spacing = float(np.median(cKDTree(proj).query(proj, k=2)[0][:, 1]))
    shifts = shifts[(np.linalg.norm(shifts, axis=1) < 0.5 * spacing) | (np.arange(len(shifts)) == 0)]
    dist, _ = tree.query((proj[None] + shifts[:, None]).reshape(-1, 2), k=1)
    count = (dist.reshape(len(shifts), len(proj)) <= tol).sum(axis=1)
    best = np.lexsort((np.linalg.norm(shifts, axis=1), -count))[0]
    d = np.linalg.norm(proj[:, None] + shifts[best] - uv[None], axis=-1)
    i, j = np.argmin(d, axis=1), np.argmin(d, axis=0)
    p = np.flatnonzero(j[i] == np.arange(len(proj)))
    dp, dd = np.sort(d, axis=1)[:, :2], np.sort(d, axis=0)[:2]
    ok = (RATIO * dp[p, 0] <= dp[p, 1]) & (RATIO * dd[0, i[p]] <= dd[1, i[p]])
    return p[ok], i[p[ok]]


def _fit(r: np.ndarray, g: np.ndarray, s2: np.ndarray, threshold: float) -> tuple[np.ndarray, float] | None:
    """The shift (2,) [px] and time offset [s] that best explain distances r (n, 2) [px] of markers moving at
    g (n, 2) [px/s], weights 1 / s2 (n,) [px^2]; None unless chi-square drops by more than ``threshold``. Where
    every g is alike, shift and offset cannot be told apart: the least-norm solution, whose sum is what counts."""
    keep = np.ones(len(r), bool)
    for refit in (False, True):
        if keep.sum() < LEAST_PAIRS:
            return None
        w = np.repeat(1.0 / np.sqrt(s2[keep]), 2)
        A = np.zeros((2 * keep.sum(), 3))
        A[0::2, 0] = A[1::2, 1] = 1.0
        A[:, 2] = g[keep].ravel()
        A, b = A * w[:, None], r[keep].ravel() * w
        x = np.linalg.lstsq(A, b, rcond=1e-9)[0]
        if not refit:
            e = r - x[:2] - x[2] * g
            keep = np.sum(e * e, axis=1) / s2 < CHI2_2DOF_GATE
    gain = float(b @ b - np.sum((A @ x - b) ** 2))
    return (x[:2], float(x[2])) if gain > threshold else None


def moved_back(geom: Geometry, fi: FrameDetections, jit: Jitter) -> np.ndarray:
    """The detections' ideal pixels (N, 2) with each moved camera-frame's fit taken out: moved back by the shift
    and dt times the image velocity of the marker projected nearest the detection."""
    k = fi.frame - fi.first
    return along_motion(geom, fi, fi.uv, jit.xyz, jit.vel, jit.shift[k, fi.camera], jit.dt[k, fi.camera])


def along_motion(geom: Geometry, fi: FrameDetections, uv: np.ndarray, xyz: np.ndarray, vel: np.ndarray,
                 shift: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Ideal pixels uv (N, 2) less shift (N, 2) [px] and dt (N,) [s] times the image velocity of the marker
    projected nearest each detection (positions xyz and velocities vel (F, L, 3) [m, m/s], NaN where unknown).
    Detections with neither, or with no marker known on their frame, stay where they are."""
    out = uv.copy()
    move = shift.any(axis=1) | (dt != 0)
    for k, c in np.unique(np.stack([fi.frame[move] - fi.first, fi.camera[move]], axis=1), axis=0):
        rows = fi.rows(fi.first + int(k))
        rc = rows[(fi.camera[rows] == c) & move[rows]]
        known = np.isfinite(xyz[k]).all(axis=1) & np.isfinite(vel[k]).all(axis=1)
        x, v = xyz[k, known], vel[k, known]
        h = x @ geom.P[c][:, :3].T + geom.P[c][:, 3]
        front = h[:, 2] > 0
        if not front.any():
            continue
        proj = h[front, :2] / h[front, 2:3]
        g = np.einsum("pij,pj->pi", jacobian(geom.P[c], x[front]), v[front])
        near = np.argmin(np.linalg.norm(uv[rc][:, None] - proj[None], axis=-1), axis=1)
        out[rc] = uv[rc] - shift[rc] - dt[rc, None] * g[near]
    return out
