"""Marker names for anonymous tracks: from the user's seed clicks, propagated along tracks and across their splits
by segment lengths and motion, each with a confidence.

A track holding a seeded detection takes that marker. Every other track is scored against every marker it could
be (one not held by another track on any of its frames), as a log likelihood ratio against "none of them" (a ghost
or a spurious track):

* segments: on each of its frames, its distance to the track holding each of the marker's segment partners,
  against that segment's length (Gaussian, its std from the labelled frames; capped at 5 std, so one bad frame
  cannot sink a long track), against a distance drawn uniformly from 0 to SEGMENT_RANGE_M;
* motion: its first position against the constant-velocity prediction (batgraph.motion) from the marker's
  previous track, and its last position against the backward prediction from the marker's next one, against a
  position drawn uniformly from a MOTION_VOLUME_M3.

The confidence of the best marker is its posterior probability among all markers and "none" (equal priors).
Tracks are named best first, re-scored as their neighbours in time and space get names (a wavefront from the
seed); one whose best confidence stays below ``min_confidence`` is left unnamed: low-confidence stretches are
flagged, not guessed. Segments are the session's ``[markers] rigid`` and ``skeleton`` pairs, plus pairs whose
distance the labelled tracks show to be as steady as a rigid one (learned, for marker sets that declare none).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from .tracks import Tracklets

SEGMENT_RANGE_M = 0.3  # "none": a distance uniform on [0, this]
MOTION_VOLUME_M3 = 0.3 ** 3  # "none": a position uniform in this volume
CAP_SIGMA = 5.0  # a segment residual counts at most this many std
MIN_SIGMA_M = 0.0015  # a segment's std is at least the triangulation's noise on two points
MAX_GAP = 30  # frames: the motion term reaches this far to the marker's previous / next track
LEARN_MIN_FRAMES = 10  # frames two labelled markers share before their distance may become a segment
LEARN_MAX_STD_M = 0.003  # ... and its std (robust) at most this
LEARN_MAX_LENGTH_M = 0.12  # ... and its length at most this
LEARN_MAX_PARTNERS = 6  # learned segments per marker (the steadiest)
NEAR_M = 0.2  # a new name re-scores the tracks within this distance of it


@dataclass
class LabelOptions:
    """min_confidence: the least posterior probability for a track to be named; accel_psd_m2_s3: the motion
    term's acceleration noise q [m^2/s^3]; learn: also use steady distances as segments."""

    min_confidence: float = 0.99
    accel_psd_m2_s3: float = 200.0
    learn: bool = True


@dataclass
class TrackLabels:
    """label (n_tracks,) marker index per track id (-1: unnamed); confidence (n_tracks,); how (n_tracks,) 0 none,
    1 seed, 2 segments, 3 motion (the term that gave most of the evidence)."""

    label: np.ndarray
    confidence: np.ndarray
    how: np.ndarray


HOW = ("", "seed", "segments", "motion")


class _Index:
    """Tracklets as per-track slices and a dense (frame, marker) map of who holds each name."""

    def __init__(self, tl: Tracklets, n_labels: int):
        self.tl = tl
        self.n_tracks = int(tl.track.max()) + 1 if len(tl.track) else 0
        starts = np.searchsorted(tl.track, np.arange(self.n_tracks + 1))
        self.start, self.stop = starts[:-1], starts[1:]
        self.f0 = int(tl.frame.min()) if len(tl.frame) else 0
        F = int(tl.frame.max()) - self.f0 + 1 if len(tl.frame) else 0
        self.holder = np.full((F, n_labels), -1, np.int64)  # entry index of the named track's row
        self.X = np.full((F, n_labels, 3), np.nan)  # positions of named points (rows with a point)
        self.first = tl.frame[self.start] if self.n_tracks else np.zeros(0, np.int64)
        self.last = tl.frame[self.stop - 1] if self.n_tracks else np.zeros(0, np.int64)

    def rows(self, t: int) -> np.ndarray:
        return np.arange(self.start[t], self.stop[t])

    def name(self, t: int, label: int) -> None:
        r = self.rows(t)
        k = self.tl.frame[r] - self.f0
        self.holder[k, label] = r
        pt = self.tl.kind[r] == 0
        self.X[k[pt], label] = self.tl.state[r[pt], :3]


@dataclass
class _Segments:
    """Per marker its partners (L, K) (-1: none), their lengths (L, K) [m] and stds (L, K) [m] (NaN: unknown)."""

    partner: np.ndarray
    length: np.ndarray
    sigma: np.ndarray


def _segments(idx: _Index, pairs: list[tuple[int, int]], learn: bool) -> _Segments:
    """Lengths and stds of the declared pairs (and, with ``learn``, of up to LEARN_MAX_PARTNERS steady undeclared
    pairs per marker) measured on the named points so far: the median distance and 1.4826 MAD (at least
    MIN_SIGMA_M; twice that from fewer than 3 frames)."""
    L = idx.X.shape[1]
    declared = {tuple(sorted(p)) for p in pairs}
    cand = set(declared)
    if learn:
        have = np.isfinite(idx.X[..., 0]).astype(np.int32)
        a, b = np.nonzero(np.triu(have.T @ have >= LEARN_MIN_FRAMES, 1))  # pairs named together often enough
        cand |= set(zip(a.tolist(), b.tolist(), strict=True))
    per: list[list[tuple]] = [[] for _ in range(L)]
    for a, b in cand:
        d = np.linalg.norm(idx.X[:, a] - idx.X[:, b], axis=1)
        d = d[np.isfinite(d)]
        if not len(d):
            continue
        med = float(np.median(d))
        std = 1.4826 * float(np.median(np.abs(d - med))) if len(d) >= 3 else 2 * MIN_SIGMA_M
        std = max(std, MIN_SIGMA_M)
        is_declared = (a, b) in declared
        if is_declared or (std <= LEARN_MAX_STD_M and med <= LEARN_MAX_LENGTH_M):
            per[a].append((not is_declared, std, b, med))
            per[b].append((not is_declared, std, a, med))
    keep = [[x for x in sorted(p) if not x[0]] + [x for x in sorted(p) if x[0]][:LEARN_MAX_PARTNERS] for p in per]
    K = max([len(p) for p in keep] + [1])
    partner = np.full((L, K), -1, np.int64)
    length = np.full((L, K), np.nan)
    sigma = np.full((L, K), np.nan)
    for i, p in enumerate(keep):
        for j, (_, std, other, med) in enumerate(p):
            partner[i, j], length[i, j], sigma[i, j] = other, med, std
    return _Segments(partner, length, sigma)


def _segment_llr(idx: _Index, seg: _Segments, rows: np.ndarray) -> np.ndarray:
    """(L,) the segment evidence for each marker of a track's rows with a point (see module docstring)."""
    tl = idx.tl
    pts = rows[tl.kind[rows] == 0]
    L = idx.X.shape[1]
    if not len(pts):
        return np.zeros(L)
    x = tl.state[pts, :3]
    k = tl.frame[pts] - idx.f0
    D = np.linalg.norm(idx.X[k] - x[:, None], axis=-1)  # (n, L) distance to each named marker
    valid = seg.partner >= 0
    d = D[:, np.maximum(seg.partner, 0)]  # (n, L, K)
    z = (d - seg.length) / seg.sigma
    term = (-0.5 * np.minimum(z * z, CAP_SIGMA ** 2) - np.log(seg.sigma * math.sqrt(2 * math.pi))
            + math.log(SEGMENT_RANGE_M))
    ok = valid[None] & np.isfinite(term)
    return np.where(ok, term, 0.0).sum(axis=(0, 2))


def _motion_llr(idx: _Index, t: int, q: float, dt: float) -> np.ndarray:
    """(L,) the motion evidence for each marker: the track's first position against the forward prediction from
    the marker's previous holder, its last against the backward one from its next (within MAX_GAP frames)."""
    tl = idx.tl
    L = idx.X.shape[1]
    out = np.zeros(L)
    a, b = int(idx.first[t]) - idx.f0, int(idx.last[t]) - idx.f0
    for sign, edge, window in ((1, idx.start[t], idx.holder[max(a - MAX_GAP, 0):a][::-1]),
                               (-1, idx.stop[t] - 1, idx.holder[b + 1:b + 1 + MAX_GAP])):
        if not len(window):
            continue
        has = window >= 0
        lab = np.flatnonzero(has.any(axis=0))
        if not len(lab):
            continue
        g = np.argmax(has[:, lab], axis=0) + 1  # frames from the holder's row to the track's edge
        e = window[g - 1, lab]
        s_, P = tl.state[e], tl.cov[e]
        tau = (sign * g * dt)[:, None]
        pred = s_[:, :3] + s_[:, 3:] * tau
        Ppos = (P[:, :3, :3] + tau[:, :, None] * (P[:, :3, 3:] + P[:, 3:, :3])
                + tau[:, :, None] ** 2 * P[:, 3:, 3:])
        Qg = q * (g * dt) ** 3 / 3  # the position block of constant_velocity_Q(q, g dt): q tau^3 / 3 I
        S = Ppos + Qg[:, None, None] * np.eye(3) + tl.cov[edge, :3, :3]
        r = tl.state[edge, :3] - pred
        m = np.einsum("ni,ni->n", r, np.linalg.solve(S, r[..., None])[..., 0])
        logdet = np.linalg.slogdet(S)[1]
        out[lab] += -0.5 * (np.minimum(m, CAP_SIGMA ** 2) + logdet + 3 * math.log(2 * math.pi)) + math.log(
            MOTION_VOLUME_M3)
    return out


def _score(idx: _Index, seg: _Segments, t: int, q: float, dt: float) -> tuple[int, float, float, int]:
    """(best marker, its log likelihood ratio, its confidence, how) of an unnamed track t; marker -1 when none is
    possible."""
    rows = idx.rows(t)
    k = idx.tl.frame[rows] - idx.f0
    feasible = (idx.holder[k] < 0).all(axis=0)
    if not feasible.any():
        return -1, 0.0, 0.0, 0
    s_llr = _segment_llr(idx, seg, rows)
    m_llr = _motion_llr(idx, t, q, dt)
    llr = np.where(feasible, s_llr + m_llr, -np.inf)
    best = int(np.argmax(llr))
    top = llr[best]
    conf = 1.0 / (np.exp(-top) + np.sum(np.exp(llr[feasible] - top)))  # among the feasible markers and "none"
    how = 2 if s_llr[best] >= m_llr[best] else 3
    return best, float(top), float(conf), how


def label_tracks(tl: Tracklets, seed: dict[int, int], pairs: list[tuple[int, int]], n_labels: int, fps: float,
                 opt: LabelOptions) -> TrackLabels:
    """Name the tracks (see module docstring). seed: track id -> marker index from the user's clicks; pairs:
    declared segments as marker index pairs."""
    idx = _Index(tl, n_labels)
    n = idx.n_tracks
    label, conf, how = np.full(n, -1, np.int64), np.zeros(n), np.zeros(n, np.int64)
    for t, lab in seed.items():
        idx.name(t, lab)
        label[t], conf[t], how[t] = lab, 1.0, 1
    seg = _segments(idx, pairs, opt.learn)
    named_points = int(np.isfinite(idx.X[..., 0]).sum())
    dt = 1.0 / fps
    version = np.zeros(n, np.int64)
    heap = []

    def push(t):
        version[t] += 1
        best, llr, c, h = _score(idx, seg, t, opt.accel_psd_m2_s3, dt)
        if best >= 0:
            heapq.heappush(heap, (-c, -llr, int(t), int(version[t]), best, h))

    for t in range(n):
        if label[t] < 0:
            push(t)
    while heap:
        neg_c, _, t, ver, best, h = heapq.heappop(heap)
        if ver != version[t] or label[t] >= 0:
            continue
        if -neg_c < opt.min_confidence:
            break
        idx.name(t, best)
        label[t], conf[t], how[t] = best, -neg_c, h
        points = int(np.isfinite(idx.X[..., 0]).sum())
        if points > 1.5 * named_points:  # segment lengths measured again as the named points grow
            seg, named_points = _segments(idx, pairs, opt.learn), points
        near = (idx.first <= idx.last[t] + MAX_GAP) & (idx.last >= idx.first[t] - MAX_GAP) & (label < 0)
        for u in np.flatnonzero(near):
            push(u)
    for t in range(n):  # the unnamed tracks keep their best confidence, for the record
        if label[t] < 0:
            conf[t] = _score(idx, seg, t, opt.accel_psd_m2_s3, dt)[2]
    return TrackLabels(label, conf, how)
