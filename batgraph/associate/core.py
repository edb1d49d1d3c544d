"""Association end to end on arrays: detections -> 3D points per frame (batgraph.associate.views) -> the seeded
markers tracked away from the seed (batgraph.associate.tracks) -> every detection named by where its marker is
(batgraph.associate.refine) -> the gaps between named stretches tracked again from every named position
(batgraph.associate.gaps), each step's names checked (batgraph.associate.verify); last, a named detection that
another marker could as well have made is unnamed (refine.shared_views). Where some cameras are out of step or
shaken on some frames, their detections are moved there by what the names tell (batgraph.associate.jitter), and the
naming runs again from the names it gave (the tracking does not). Before that, where the rig's stated clocks put a
camera's captures within a frame of the session's instants, the detections are moved to those instants along the
named markers' motion and the whole association runs again, round after round (:func:`_on_the_clock`). No files
(batgraph.associate.session).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from ..camera import Rig
from . import affine, gaps, jitter, refine, segments, tracks, verify, views
from .detections import Detections

PAIRS_UP_TO_CAMERAS = 8  # larger rigs find points from the markers' predictions (views.projected_points)
SIGMA_SAMPLE_FRAMES = 40  # frames whose points measure the pixel noise
SIGMA_START_PX = 2.0  # the noise assumed while measuring it
SIGMA_SETTLED = 0.01  # the measurement is repeated until it moves by less than this fraction...
SIGMA_ROUNDS = 20  # ...or this many times
HOW = ("", "seed", "tracked", "ray", "reprojection")
"""How a detection got its name: not named, the user's seed, a point the tracker assigned to its marker, a lone
detection the tracker joined along its marker's predicted ray, or matched to where its marker is (refine)."""


@dataclass
class AssociateOptions:
    """pixel_sigma_px: the detections' noise [px] (None: measured from points seen by 4 cameras or more, or 3);
    margin: the least extra cost (chi-square units) for a detection's name to be kept (4.6: confidence 0.9);
    rounds: matching rounds (batgraph.associate.refine); track: the tracker's options; progress: a bar over the
    rounds of step 7 (each a whole association: minutes on a long session)."""

    pixel_sigma_px: float | None = None
    margin: float = 4.6
    rounds: int = 2
    track: tracks.TrackOptions = field(default_factory=tracks.TrackOptions)
    progress: bool = False


@dataclass
class Association:
    """Per detection (in the order of ``Detections``): label (N,) marker index (-1: unnamed), confidence (N,),
    candidate (N,) the best marker of an unnamed one (-1: none near), track (N,) its track id (-1: none), how (N,)
    an index into HOW. pixel_sigma_px: the noise used [px], sigma_source how it was had ("stated", "measured", or
    "assumed": SIGMA_START_PX where no point had views enough to measure it); sweep: what the tracker found per
    frame and marker; moved (F, C) bool: the camera-frames found out of step or shaken and moved
    (batgraph.associate.jitter; None: none), moved_px (N,) how far each detection was moved there [raw px];
    clock_rounds: how many times the detections were moved to their frames' instants and named again
    (:func:`_on_the_clock`; 0: on the clock)."""

    label: np.ndarray
    confidence: np.ndarray
    candidate: np.ndarray
    track: np.ndarray
    how: np.ndarray
    pixel_sigma_px: float
    sweep: tracks.Sweep
    sigma_source: str = "stated"
    moved: np.ndarray | None = None
    moved_px: np.ndarray | None = None
    clock_rounds: int = 0


def frame_index(dets: Detections, ideal: np.ndarray, sig: np.ndarray) -> tracks.FrameDetections:
    """The detections by frame, over every frame from the first to the last."""
    first, last = int(dets.frame[0]), int(dets.frame[-1])
    start = np.searchsorted(dets.frame, np.arange(first, last + 2))
    return tracks.FrameDetections(dets.frame, dets.camera, ideal, sig, first, start)


def frame_points(geom: views.Geometry, fi: tracks.FrameDetections, f: int) -> views.FramePoints:
    """One frame's points: those of three views or more chosen, then every two-view candidate on the detections
    they left (batgraph.associate.views), views as global detection indices."""
    rows = fi.rows(f)
    uv, sig, cam = fi.uv[rows], fi.sig[rows], fi.camera[rows]
    cands, llr = views.candidates(geom, uv, sig, cam)
    chosen = views.select(geom, uv, sig, llr, cands)
    used = np.zeros(len(rows), bool)
    used[chosen.views[chosen.views >= 0]] = True
    pairs = views.free_pairs(cands, used)
    v = np.concatenate([chosen.views, pairs.views])
    return views.FramePoints(np.where(v >= 0, rows[np.maximum(v, 0)], -1), np.concatenate([chosen.xyz, pairs.xyz]),
                             np.concatenate([chosen.score, pairs.score]))


def measure_sigma(geom: views.Geometry, fi: tracks.FrameDetections, scale: np.ndarray,
                  start: float = SIGMA_START_PX) -> float | None:
    """The detections' noise [px] from the reprojection errors of points seen by 4 cameras or more (by 3 where none is
    seen by 4: a rig of 3 cameras) on up to SIGMA_SAMPLE_FRAMES frames; None where none is seen by 3 (two views'
    errors are what pairs them: they cannot measure it). A view's squared error is sigma^2 (1 - 3 / (2 n))
    chi-square(2) for n views, so sigma^2 = median(e^2 / (1 - 3 / (2 n))) / (2 ln 2). The points are found with the
    gates of the noise assumed (``start`` [px] at first), which leave out the views beyond them, so the measurement
    is repeated with the gates of the last until it settles (SIGMA_SETTLED, at most SIGMA_ROUNDS times): the noise of
    the views within the gates it sets. Gaussian noise small against the markers' spacing settles in 2-3 rounds next
    to the truth; large noise still reads low, for views with another detection near them are left out (a wingbeat's
    7 px read 2.3 px); markerless keypoints, whose errors have long tails, climb for longer (the Pose2Sim demo: 2.0,
    4.0, 5.3, ... 14.1 px)."""
    frames = fi.first + np.unique(np.linspace(0, fi.n_frames - 1, min(fi.n_frames, SIGMA_SAMPLE_FRAMES)).astype(int))
    sigma, measured = start, False
    for _ in range(SIGMA_ROUNDS):
        fi.sig = sigma * scale
        pts = [frame_points(geom, fi, int(f)) for f in frames]
        least = 4 if any((p.n_views >= 4).any() for p in pts) else 3
        e2 = []
        for p in pts:
            n = p.n_views
            enough = n >= least
            if enough.any():
                r2 = views.residuals(geom, fi.uv, scale, p.views[enough], p.xyz[enough])
                e2.append((r2 / (1 - 3 / (2 * n[enough]))[:, None])[p.views[enough] >= 0])
        if not e2:
            return sigma if measured else None
        last, measured = sigma, True
        sigma = float(np.sqrt(np.median(np.concatenate(e2)) / (2 * np.log(2))))
        if abs(sigma - last) <= SIGMA_SETTLED * last:
            break
    return sigma


SUBSET_CAMERAS = 4  # a large rig's cameras matched pair by pair on the frames next to a seed


def _subset_points(rig: Rig, fi: tracks.FrameDetections, seed_det: np.ndarray):
    """For a large rig: frame -> its points from the SUBSET_CAMERAS cameras that saw the most seeded detections,
    matched pair by pair (frame_points): where the seeded markers went on the frame next to the seed, before
    their velocities are known (the predictions that find points in a large rig need them)."""
    counts = np.bincount(fi.camera[seed_det], minlength=len(rig))
    cams = np.sort(np.argsort(-counts, kind="stable")[:SUBSET_CAMERAS])
    sub = views.geometry(Rig([rig[int(c)] for c in cams], world_mirror=rig.world_mirror))
    where = np.full(len(rig), -1, np.int64)
    where[cams] = np.arange(len(cams))

    def at(f: int) -> views.FramePoints:
        rows = fi.rows(f)
        rows = rows[where[fi.camera[rows]] >= 0]
        part = tracks.FrameDetections(fi.frame[rows], where[fi.camera[rows]], fi.uv[rows], fi.sig[rows], f,
                                      np.array([0, len(rows)]))
        p = frame_points(sub, part, f)
        v = np.full((len(p.views), len(rig)), -1, np.int64)
        v[:, cams] = np.where(p.views >= 0, rows[np.maximum(p.views, 0)], -1)
        return views.FramePoints(v, p.xyz, p.score)
    return at


def seed_sigma(geom: views.Geometry, fi: tracks.FrameDetections, scale: np.ndarray, seed_det: np.ndarray,
               seed_lab: np.ndarray) -> float | None:
    """The detections' noise [px] from the seed: the reprojection errors of the seeded markers clicked in 4
    cameras or more, as :func:`measure_sigma` reads them (None where there are none)."""
    e2 = []
    C = len(geom.rig)
    for f in np.unique(fi.frame[seed_det]):
        on = fi.frame[seed_det] == f
        labs = np.unique(seed_lab[on])
        v = np.full((len(labs), C), -1, np.int64)
        for i, lab in enumerate(labs):
            ds = seed_det[on & (seed_lab == lab)]
            v[i, fi.camera[ds]] = ds
        n = (v >= 0).sum(axis=1)
        v = v[n >= 4]
        if len(v):
            r2 = views.residuals(geom, fi.uv, scale, v, views.triangulate(geom, fi.uv, v))
            e2.append((r2 / (1 - 3 / (2 * (v >= 0).sum(axis=1)))[:, None])[v >= 0])
    if not e2:
        return None
    return float(np.sqrt(np.median(np.concatenate(e2)) / (2 * np.log(2))))


def seeds(geom: views.Geometry, fi: tracks.FrameDetections, points: dict[int, views.FramePoints],
          seed_det: np.ndarray, seed_lab: np.ndarray) -> dict[int, tracks.Seed]:
    """The user's clicks as 3D placements per frame: a marker clicked in two cameras or more is triangulated from
    its clicks; one clicked in one camera takes the point that holds that detection, if any and if none of its
    other views is clicked (as another marker: the point pairs two markers' views)."""
    out = {}
    C = len(geom.rig)
    for f in np.unique(fi.frame[seed_det]):
        on = fi.frame[seed_det] == f
        labs, v, xyz = [], [], []
        for lab in np.unique(seed_lab[on]):
            ds = seed_det[on & (seed_lab == lab)]
            row = np.full(C, -1, np.int64)
            row[fi.camera[ds]] = ds
            if len(ds) >= 2:
                x = views.triangulate(geom, fi.uv, row[None])[0]
            else:
                pts = points.get(int(f))
                hit = np.flatnonzero((pts.views == ds[0]).any(axis=1)) if pts is not None else []
                if not len(hit):
                    continue
                x, row = pts.xyz[hit[0]], pts.views[hit[0]]
                if np.isin(row[row >= 0], seed_det[on]).sum() > 1:
                    continue
            if np.isfinite(x).all():
                labs.append(lab)
                v.append(row)
                xyz.append(x)
        if labs:
            out[int(f)] = tracks.Seed(np.array(labs), np.array(xyz), np.array(v))
    return out


def associate(rig: Rig, dets: Detections, seed_det: np.ndarray, seed_lab: np.ndarray, n_labels: int,
              pairs: list[tuple[int, int]], fps: float, opt: AssociateOptions | None = None) -> Association:
    """Name every detection (see module docstring). seed_det (S,) detection indices the user named, seed_lab (S,)
    their marker indices; pairs: declared segments as marker index pairs; fps [Hz]."""
    opt = opt or AssociateOptions()
    geom = views.geometry(rig)
    ideal, scale = views.undistort(rig, dets.camera, dets.uv_px)
    fi = frame_index(dets, ideal, scale)
    t = _track(geom, fi, scale, seed_det, seed_lab, n_labels, pairs, fps, opt)
    label = _name(geom, fi, t, t.swept, n_labels, pairs, fps, opt)
    if len(rig) > PAIRS_UP_TO_CAMERAS:  # a large rig's points come from the markers' predictions, not t.points
        return t.association(*label)
    clock = 0
    if dets.time_frac.any():
        t, label, clock = _on_the_clock(geom, fi, ideal, scale, dets.time_frac / fps, t, label, seed_det, seed_lab,
                                        n_labels, pairs, fps, opt)
    jit = jitter.measure(geom, fi, label[0], n_labels, fps, t.noise_m)
    if not jit.moved.any():
        return dataclasses.replace(t.association(*label), clock_rounds=clock)
    before = fi.uv
    fi.uv = jitter.moved_back(geom, fi, jit)
    for k in np.flatnonzero(jit.moved.any(axis=1)):
        t.points[fi.first + int(k)] = frame_points(geom, fi, fi.first + int(k))
    label = _name(geom, fi, t, label[0], n_labels, pairs, fps, opt)
    return dataclasses.replace(t.association(*label), moved=jit.moved,
                               moved_px=np.linalg.norm(fi.uv - before, axis=1) / scale, clock_rounds=clock)


CLOCK_ROUNDS = 8  # at most: each round is a whole association
CLOCK_GROWTH = 0.005  # another round while the names grow by more than this fraction of the detections


def _on_the_clock(geom: views.Geometry, fi: tracks.FrameDetections, ideal: np.ndarray, scale: np.ndarray,
                  dt: np.ndarray, t: _Tracked, label: tuple, seed_det: np.ndarray, seed_lab: np.ndarray,
                  n_labels: int, pairs: list[tuple[int, int]], fps: float, opt: AssociateOptions
                  ) -> tuple[_Tracked, tuple, int]:
    """Detections captured dt (N,) [s] after their session frame's instant (what a stated time offset leaves within
    a frame, a rolling shutter's readout) moved back to it along their marker's image motion, from the paths of
    the names so far (batgraph.associate.jitter.along_motion), and steps 1-6 run again from the seed; repeated while
    the names grow by more than CLOCK_GROWTH of the detections (each round's paths reach further), at most
    CLOCK_ROUNDS times. Returns the last round's tracking and names, and the number of rounds."""
    named, rounds, grown = int((label[0] >= 0).sum()), 0, len(ideal)
    bar = tqdm(total=CLOCK_ROUNDS, desc="naming on the stated clocks: rounds", disable=not opt.progress, leave=False)
    while rounds < CLOCK_ROUNDS and grown > CLOCK_GROWTH * len(ideal):
        rounds += 1
        bar.set_postfix_str(f"{100 * named / len(ideal):.0f} % named")
        xyz, _, _, vel = jitter.paths(geom, fi, label[0], n_labels, fps, t.noise_m)
        fi.uv = jitter.along_motion(geom, fi, ideal, xyz, vel, np.zeros_like(ideal), dt)
        t = _track(geom, fi, scale, seed_det, seed_lab, n_labels, pairs, fps, opt, t.sigma)
        label = _name(geom, fi, t, t.swept, n_labels, pairs, fps, opt)
        grown = int((label[0] >= 0).sum()) - named
        named += grown
        bar.update()
    bar.close()
    return t, label, rounds


@dataclass
class _Tracked:
    """What the tracking from the seed left for the naming (:func:`_track`)."""

    sigma: float
    sigma_source: str  # Association.sigma_source
    noise_m: float
    track_options: tracks.TrackOptions
    sweep: tracks.Sweep
    swept: np.ndarray  # (N,) the tracker's names, checked
    how: np.ndarray  # (N,) HOW index of the tracker's names
    track: np.ndarray  # (N,) track id
    fixed: np.ndarray  # (N,) the seed's names (-1 elsewhere)
    seeded: np.ndarray  # (F, L) bool
    doubt: np.ndarray  # (F, L) bool: the tracker's links in doubt
    points: dict  # frame -> views.FramePoints (small rigs; empty for a large one)
    points_at: object  # (frame, xyz, std) -> views.FramePoints

    def association(self, label, conf, cand, filled) -> Association:
        """The names (N,) with their confidence, candidates and gap fills as an Association."""
        how = np.where(filled > 0, filled + 1, self.how)
        how = np.where(self.fixed >= 0, 1, np.where(label < 0, 0, np.where((label == self.swept) | (filled > 0),
                                                                            how, 4)))
        track = np.where((label >= 0) & (label == self.swept), self.track, -1)
        return Association(label, conf, cand, track, how, self.sigma, self.sweep, self.sigma_source)


def _track(geom: views.Geometry, fi: tracks.FrameDetections, scale: np.ndarray, seed_det: np.ndarray,
           seed_lab: np.ndarray, n_labels: int, pairs: list[tuple[int, int]], fps: float, opt: AssociateOptions,
           sigma_start: float = SIGMA_START_PX) -> _Tracked:
    """The noise measured (sets fi.sig; from sigma_start [px]: a round of step 7 starts from the last round's),
    each frame's points found, the markers tracked forwards and backwards from the seed frame with the most clicks
    (other seed frames placed where the sweeps reach them), and the tracker's names checked (steps 1-2 and 4 of
    docs/associate.md)."""
    rig = geom.rig
    large = len(rig) > PAIRS_UP_TO_CAMERAS
    sigma, source = opt.pixel_sigma_px, "stated"
    if sigma is None:
        sigma = seed_sigma(geom, fi, scale, seed_det, seed_lab) if large else measure_sigma(geom, fi, scale,
                                                                                              sigma_start)
        sigma, source = (SIGMA_START_PX, "assumed") if sigma is None else (sigma, "measured")
    fi.sig = sigma * scale
    frames = np.arange(fi.first, fi.first + fi.n_frames)
    if large:  # points from the markers' predictions: matching every camera pair would cost too much
        points = {}

        def points_at(f, xyz, std):
            rows = fi.rows(f)
            p = views.projected_points(geom, fi.uv[rows], fi.sig[rows], fi.camera[rows], xyz, std)
            return views.FramePoints(np.where(p.views >= 0, rows[np.maximum(p.views, 0)], -1), p.xyz, p.score,
                                     p.source)
    else:
        points = {int(f): frame_points(geom, fi, int(f)) for f in frames}
        empty = views.FramePoints(np.zeros((0, len(rig)), np.int64), np.zeros((0, 3)), np.zeros(0))

        def points_at(f, xyz, std):
            return points.get(int(f), empty)
    placed = seeds(geom, fi, points, seed_det, seed_lab)
    noise_m = 0.0
    if placed:
        volume, size = tracks.extent(np.concatenate([sd.xyz for sd in placed.values()]))
        noise_m = float(np.median(np.concatenate([np.sqrt(np.linalg.eigvalsh(tracks.point_covariance(
            geom, sd.xyz, sd.views, fi.sig))[:, -1]) for sd in placed.values()])))
        opt = dataclasses.replace(opt, track=dataclasses.replace(opt.track, volume_m3=volume, range_m=size,
                                                                 noise_m=noise_m,
                                                                 segment_lengths=_seed_lengths(placed, pairs)))
    sw = tracks.Sweep.empty(fi.n_frames, n_labels, len(rig))
    # from the frame with the most clicks (of equals, the earliest); the other seed frames are placed when reached
    start = max(placed, key=lambda f: (int(np.sum(fi.frame[seed_det] == f)), -f)) if placed else int(frames[0])
    first = functools.lru_cache(_subset_points(rig, fi, seed_det)) if large else None  # start_noise, then sweep
    if placed:
        near = first or (lambda f: points.get(int(f), empty))
        opt = dataclasses.replace(opt, track=tracks.start_noise(placed[start], near(start - 1).xyz,
                                                                near(start + 1).xyz, 1.0 / fps, noise_m, opt.track))
    ahead = {f: sd for f, sd in placed.items() if f >= start}
    behind = {f: sd for f, sd in placed.items() if f <= start}
    tracks.sweep(geom, points_at, fi, frames[frames >= start], 1.0 / fps, ahead, pairs, sw, opt.track, first)
    tracks.sweep(geom, points_at, fi, frames[frames <= start][::-1], -1.0 / fps, behind, pairs, sw, opt.track, first)
    N = len(fi.frame)
    label, kind, track = tracks.per_detection(sw, N)
    how = np.where(kind > 0, kind + 1, 0)
    fixed = np.full(N, -1, np.int64)
    fixed[seed_det] = seed_lab
    label = np.where(fixed >= 0, fixed, label)
    seeded = np.zeros((fi.n_frames, n_labels), bool)
    seeded[fi.frame[seed_det] - fi.first, seed_lab] = True
    ref = opt.track.segment_lengths
    doubt = tracks.doubtful(sw, start - fi.first)
    label = _vouched(geom, fi, label, fixed, seeded, pairs, n_labels, noise_m, ref, doubt)
    return _Tracked(sigma, source, noise_m, opt.track, sw, label, how, track, fixed, seeded, doubt, points, points_at)


def _name(geom: views.Geometry, fi: tracks.FrameDetections, t: _Tracked, label: np.ndarray, n_labels: int,
          pairs: list[tuple[int, int]], fps: float, opt: AssociateOptions) -> tuple[np.ndarray, ...]:
    """Every detection named from the names ``label`` (N,) by where the markers are, the gaps tracked again and the
    names checked (steps 3-6 of docs/associate.md): (label, confidence, candidate, filled) (N,) each."""
    large = len(geom.rig) > PAIRS_UP_TO_CAMERAS
    N = len(fi.frame)
    fixed, seeded, doubt, noise_m = t.fixed, t.seeded, t.doubt, t.noise_m
    ref = t.track_options.segment_lengths
    conf, cand = np.where(label >= 0, 1.0, 0.0), np.full(N, -1, np.int64)
    det_xyz, det_std = _detection_points(geom, fi, t.points)
    for _ in range(1 if large else opt.rounds):  # one round in a large rig: each costs as much as the tracking
        xyz, std, label = refine.positions(geom, fi, label, n_labels)
        xyz, std = refine.carry(xyz, std, fps, noise_m, patch=not large)
        others = refine.leave_one_out(geom, fi, label, n_labels)
        label, conf, cand = refine.match(geom, fi, xyz, std, opt.margin, fixed, det_xyz, det_std, noise_m, others)
        label = _vouched(geom, fi, label, fixed, seeded, pairs, n_labels, noise_m, ref, doubt)
    filled = np.zeros(N, np.int64)
    if not large:  # two more sweeps: in a large rig they would cost as much as the first two
        label, filled, gap_conf, gap_doubt = gaps.fill(geom, fi, t.points_at, label, n_labels, pairs, fps,
                                                       t.track_options, noise_m)
        label = _vouched(geom, fi, label, fixed, seeded, pairs, n_labels, noise_m, ref, doubt | gap_doubt)
        conf = np.where(filled > 0, gap_conf, conf)
    shared = refine.shared_views(geom, fi, label, fixed, n_labels)
    cand, label = np.where(shared, label, cand), np.where(shared, -1, label)
    return label, conf, cand, filled


def _detection_points(geom: views.Geometry, fi: tracks.FrameDetections, points: dict[int, views.FramePoints]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per detection the point of three views or more it is in (N, 3) [m] and that point's std (N,) [m] (the
    largest axis of its first-order covariance); NaN where none."""
    N = len(fi.frame)
    xyz, std = np.full((N, 3), np.nan), np.full(N, np.nan)
    for p in points.values():
        three = p.n_views >= 3
        if not three.any():
            continue
        v, x = p.views[three], p.xyz[three]
        s = np.sqrt(np.linalg.eigvalsh(tracks.point_covariance(geom, x, v, fi.sig))[:, -1])
        has = v >= 0
        xyz[v[has]] = np.broadcast_to(x[:, None], v.shape + (3,))[has]
        std[v[has]] = np.broadcast_to(s[:, None], v.shape)[has]
    return xyz, std


def _seed_lengths(placed: dict[int, tracks.Seed], pairs: list[tuple[int, int]]) -> dict:
    """{(a, b): median length [m]} of the declared segments (a < b) over the seed frames that place both markers."""
    lengths: dict = {}
    for sd in placed.values():
        at = {int(m): i for i, m in enumerate(sd.label)}
        for a, b in pairs:
            if a in at and b in at:
                lengths.setdefault(tuple(sorted((a, b))), []).append(
                    float(np.linalg.norm(sd.xyz[at[a]] - sd.xyz[at[b]])))
    return {k: float(np.median(v)) for k, v in lengths.items()}


def _vouched(geom: views.Geometry, fi: tracks.FrameDetections, label: np.ndarray, fixed: np.ndarray,
             seeded: np.ndarray, pairs: list[tuple[int, int]], n_labels: int, noise_m: float,
             reference: dict | None, doubt: np.ndarray | None = None) -> np.ndarray:
    """The names (N,) left where batgraph.associate.verify vouches for the marker's path (doubt (F, L): where
    the tracker's link is in doubt, tracks.doubtful); a name on a frame where its marker has no triangulated
    position (one view) stays where verify.carried carries a vouched name to it."""
    xyz, std, label = refine.positions(geom, fi, label, n_labels)
    have = np.isfinite(std)
    X = np.where(have[..., None], xyz, np.nan)
    stats = segments.pair_stats(X)
    seg = segments.measure(X, pairs, True, noise_m, reference, stats)
    relations = affine.learn(X, {m for pair in pairs for m in pair}, noise_m, stats)
    keep = verify.vouched(xyz, have, seeded, seg, noise_m, doubt, relations)
    k = fi.frame - fi.first
    lab = np.maximum(label, 0)
    single = np.zeros_like(have)
    single[k[label >= 0], label[label >= 0]] = True
    single &= ~have
    carried = verify.carried(keep, single, np.zeros_like(keep) if doubt is None else doubt)
    ok = np.where(have[k, lab], keep[k, lab], carried[k, lab])
    return np.where(fixed >= 0, fixed, np.where((label >= 0) & ok, label, -1))
