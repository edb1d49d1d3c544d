"""Association end to end on arrays: detections -> 3D points per frame -> tracks -> named tracks -> every detection
named (batgraph.associate.views, .tracks, .labelling, .refine). No files (batgraph.associate.session).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Rig
from . import labelling, refine, tracks, views
from .detections import Detections

SIGMA_SAMPLE_FRAMES = 40  # frames whose points measure the pixel noise
SIGMA_START_PX = 2.0  # the noise assumed while measuring it


@dataclass
class AssociateOptions:
    """pixel_sigma_px: the detections' noise [px] (None: measured from points seen by 4 cameras or more);
    margin: the least extra cost (chi-square units) for a detection's name to be kept (4.6: confidence 0.9);
    rounds: matching rounds (batgraph.associate.refine); track, label: the tracker's and the namer's options."""

    pixel_sigma_px: float | None = None
    margin: float = 4.6
    rounds: int = 2
    track: tracks.TrackOptions = field(default_factory=tracks.TrackOptions)
    label: labelling.LabelOptions = field(default_factory=labelling.LabelOptions)


@dataclass
class Association:
    """Per detection (in the order of ``Detections``): label (N,) marker index (-1: unnamed), confidence (N,),
    candidate (N,) the best marker of an unnamed one (-1: none near), track (N,) its track id (-1: none), how
    (N,) 0 none, 1 seed, 2 segments, 3 motion (how its track was named), 4 reprojection (named by where its
    marker is, outside a named track). pixel_sigma_px: the noise used [px]; tracks: the tracks; track_labels:
    their names."""

    label: np.ndarray
    confidence: np.ndarray
    candidate: np.ndarray
    track: np.ndarray
    how: np.ndarray
    pixel_sigma_px: float
    tracks: tracks.Tracklets
    track_labels: labelling.TrackLabels


def frame_index(dets: Detections, ideal: np.ndarray, sig: np.ndarray) -> refine.FrameIndex:
    """The detections by frame, over every frame from the first to the last."""
    first, last = int(dets.frame[0]), int(dets.frame[-1])
    start = np.searchsorted(dets.frame, np.arange(first, last + 2))
    return refine.FrameIndex(dets.frame, dets.camera, ideal, sig, first, start)


def frame_points(geom: views.Geometry, fi: refine.FrameIndex, f: int) -> views.FramePoints:
    """One frame's chosen points (three views or more, then unambiguous pairs), views as global indices."""
    rows = fi.rows(f)
    uv, sig, cam = fi.uv[rows], fi.sig[rows], fi.camera[rows]
    cands, llr = views.candidates(geom, uv, sig, cam)
    chosen = views.select(geom, uv, sig, llr, cands)
    used = np.zeros(len(rows), bool)
    used[chosen.views[chosen.views >= 0]] = True
    pairs = views.unambiguous_pairs(cands, used)
    v = np.concatenate([chosen.views, pairs.views])
    return views.FramePoints(np.where(v >= 0, rows[np.maximum(v, 0)], -1), np.concatenate([chosen.xyz, pairs.xyz]),
                             np.concatenate([chosen.score, pairs.score]))


def measure_sigma(geom: views.Geometry, fi: refine.FrameIndex, scale: np.ndarray) -> float:
    """The detections' noise [px] from the reprojection errors of points seen by 4 cameras or more on up to
    SIGMA_SAMPLE_FRAMES frames: a view's squared error is sigma^2 (1 - 3 / (2 n)) chi-square(2) for n views, so
    sigma^2 = median(e^2 / (1 - 3 / (2 n))) / (2 ln 2). Measured twice, the second time with the first's gates."""
    F = len(fi.start) - 1
    frames = fi.first + np.unique(np.linspace(0, F - 1, min(F, SIGMA_SAMPLE_FRAMES)).astype(int))
    sigma = SIGMA_START_PX
    for _ in range(2):
        fi.sig = sigma * scale
        e2 = []
        for f in frames:
            p = frame_points(geom, fi, int(f))
            n = p.n_views
            four = n >= 4
            if not four.any():
                continue
            rows = p.views[four]
            r2 = views.residuals(geom, fi.uv, np.ones(len(fi.uv)) * scale, rows, p.xyz[four])
            e2.append((r2 / (1 - 3 / (2 * n[four]))[:, None])[rows >= 0])
        if not e2:
            return sigma
        sigma = float(np.sqrt(np.median(np.concatenate(e2)) / (2 * np.log(2))))
    return sigma


def _seed_tracks(tl: tracks.Tracklets, geom: views.Geometry, fi: refine.FrameIndex, seed_det: np.ndarray,
                 seed_lab: np.ndarray) -> tuple[tracks.Tracklets, dict[int, int]]:
    """The seed as names of tracks: a track holding seeded detections takes the marker most of them name; a
    seeded marker none of whose detections is in a track gets a one-frame track of its own where two of its
    clicks or more triangulate."""
    det_track = np.full(len(fi.frame), -1, np.int64)
    has = tl.views >= 0
    det_track[tl.views[has]] = np.broadcast_to(tl.track[:, None], tl.views.shape)[has]
    votes: dict[int, dict[int, int]] = {}
    for d, lab in zip(seed_det, seed_lab, strict=True):
        if det_track[d] >= 0:
            v = votes.setdefault(int(det_track[d]), {})
            v[lab] = v.get(lab, 0) + 1
    named = {t: max(v, key=v.get) for t, v in votes.items()}
    taken = {(int(fi.frame[d]), lab) for d, lab in zip(seed_det, seed_lab, strict=True) if det_track[d] >= 0}
    extra = []
    next_id = int(tl.track.max()) + 1 if len(tl.track) else 0
    C = len(geom.rig)
    for (f, lab) in sorted({(int(fi.frame[d]), int(lab)) for d, lab in zip(seed_det, seed_lab, strict=True)}):
        if (f, lab) in taken:
            continue
        ds = seed_det[(seed_lab == lab) & (fi.frame[seed_det] == f)]
        v = np.full((1, C), -1, np.int64)
        v[0, fi.camera[ds]] = ds
        if (v >= 0).sum() < 2:
            continue
        xyz = views.triangulate(geom, fi.uv, v)
        if not np.isfinite(xyz).all():
            continue
        cov = np.zeros((1, 6, 6))
        cov[0, :3, :3] = tracks.point_covariance(geom, xyz, v, fi.sig)
        cov[0, 3:, 3:] = np.eye(3) * 9.0  # velocity unknown: 3 m/s
        extra.append((next_id, f, np.concatenate([xyz[0], np.zeros(3)]), cov[0], v[0]))
        named[next_id] = lab
        next_id += 1
    if extra:
        tl = tracks.Tracklets(
            np.r_[tl.track, [e[0] for e in extra]], np.r_[tl.frame, [e[1] for e in extra]],
            np.concatenate([tl.state, [e[2] for e in extra]]), np.concatenate([tl.cov, [e[3] for e in extra]]),
            np.concatenate([tl.views, [e[4] for e in extra]]), np.r_[tl.kind, np.zeros(len(extra), np.int64)])
    return tl, named


def associate(rig: Rig, dets: Detections, seed_det: np.ndarray, seed_lab: np.ndarray, n_labels: int,
              pairs: list[tuple[int, int]], fps: float, opt: AssociateOptions | None = None) -> Association:
    """Name every detection (see module docstring). seed_det (S,) detection indices the user named, seed_lab (S,)
    their marker indices; pairs: declared segments as marker index pairs; fps [Hz]."""
    opt = opt or AssociateOptions()
    geom = views.geometry(rig)
    ideal, scale = views.undistort(rig, dets.camera, dets.uv_px)
    fi = frame_index(dets, ideal, scale)
    sigma = opt.pixel_sigma_px if opt.pixel_sigma_px is not None else measure_sigma(geom, fi, scale)
    fi.sig = sigma * scale
    frames = np.arange(fi.first, fi.first + len(fi.start) - 1)
    points = {int(f): frame_points(geom, fi, int(f)) for f in frames}
    dets_t = tracks.FrameDetections(fi.uv, fi.sig, fi.camera, fi.first, fi.start)
    tl = tracks.track(geom, points, dets_t, frames, fps, opt.track)
    tl, seeded = _seed_tracks(tl, geom, fi, seed_det, seed_lab)
    tlab = labelling.label_tracks(tl, seeded, pairs, n_labels, fps, opt.label)
    N = len(dets.frame)
    track_of = np.full(N, -1, np.int64)
    has = tl.views >= 0
    track_of[tl.views[has]] = np.broadcast_to(tl.track[:, None], tl.views.shape)[has]
    label = np.where(track_of >= 0, tlab.label[np.maximum(track_of, 0)], -1)
    fixed = np.full(N, -1, np.int64)
    fixed[seed_det] = seed_lab
    label = np.where(fixed >= 0, fixed, label)
    conf, cand = np.where(label >= 0, 1.0, 0.0), np.full(N, -1, np.int64)
    for _ in range(opt.rounds):
        xyz, std = refine.positions(geom, fi, label, n_labels)
        xyz, std = refine.carry(xyz, std, fps)
        label, conf, cand = refine.match(geom, fi, xyz, std, opt.margin, fixed)
    how = np.where(track_of >= 0, tlab.how[np.maximum(track_of, 0)], 0)
    in_named_track = (track_of >= 0) & (tlab.label[np.maximum(track_of, 0)] == label)
    how = np.where(fixed >= 0, 1, np.where(label < 0, 0, np.where(in_named_track, how, 4)))
    return Association(label, conf, cand, track_of, how, sigma, tl, tlab)
