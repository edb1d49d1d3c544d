"""Gaps in the named paths tracked again, forward and backward over every frame, from every named position.

The first sweeps (batgraph.associate.tracks) start from the seed frame only: a marker they lose stays unnamed until
its segments place it again, and a stretch the checks drop (batgraph.associate.verify) stays unnamed. Here every
named position is an anchor (a sure link, batgraph.associate.tracks.Anchors), and the tracker names what lies
between them, from both sides. A detection takes the name one sweep gives it where the other gives it no other
name and the marker has no other detection in that camera and frame. A new name is kept where its point is the
marker's alone: within the gate of no other marker unnamed on that frame, where the names (the new ones included:
they place the neighbours a lost marker moves with) carry that one (batgraph.associate.refine.carry). The caller's
checks then judge every path again, with the new links whose confidence is below DOUBT_BELOW in doubt.
"""

from __future__ import annotations

import numpy as np

from . import refine, tracks
from .tracks import CHI2_3DOF_GATE
from .views import Geometry


def fill(geom: Geometry, fi: tracks.FrameDetections, points_at, label: np.ndarray, n_labels: int,
         pairs: list[tuple[int, int]], fps: float, opt: tracks.TrackOptions, noise_m: float
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Names (N,) with the gaps filled (see module docstring); how each new name was found (N,) (the sweep's kind:
    1 a point, 2 a ray join; 0 elsewhere) and its confidence (N,) (the sweep's); the links in doubt (F, L) bool
    (tracks.doubtful of both sweeps). points_at as for tracks.sweep; noise_m [m] the points' noise."""
    xyz, std, label = refine.positions(geom, fi, label, n_labels)
    F, C, N = fi.n_frames, len(geom.rig), len(fi.frame)
    views = np.full((F, n_labels, C), -1, np.int64)
    named = np.flatnonzero(label >= 0)
    views[fi.frame[named] - fi.first, label[named], fi.camera[named]] = named
    anchors = tracks.Anchors(np.where(np.isfinite(std)[..., None], xyz, np.nan), views)
    frames = np.arange(fi.first, fi.first + F)
    got, kinds, confs, doubt = [], [], [], np.zeros((F, n_labels), bool)
    k = fi.frame - fi.first
    for order, dt, k0 in ((frames, 1.0 / fps, -1), (frames[::-1], -1.0 / fps, F - 1)):
        sw = tracks.Sweep.empty(F, n_labels, C)
        tracks.sweep(geom, points_at, fi, order, dt, {}, pairs, sw, opt, None, anchors)
        lab, kind, _ = tracks.per_detection(sw, N)
        got.append(lab)
        kinds.append(kind)
        confs.append(sw.conf[k, np.maximum(lab, 0)])
        doubt |= tracks.doubtful(sw, k0)
    a, b = got
    new = (label < 0) & (np.maximum(a, b) >= 0) & ((a == b) | (a < 0) | (b < 0))
    out = np.where(new, np.maximum(a, b), label)
    on = np.flatnonzero(out >= 0)
    key = (fi.frame[on].astype(np.int64) * C + fi.camera[on]) * n_labels + out[on]
    _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    twice = on[count[inv] > 1]
    out[twice[new[twice]]] = -1  # a marker with two detections in one camera keeps its named one, else none
    new &= out >= 0
    now, now_std, _ = refine.positions(geom, fi, out, n_labels)
    xc, sc = refine.carry(now, now_std, fps, noise_m)  # the new names place the neighbours a lost marker moves with
    alone = exclusive(now, np.isfinite(now_std), xc, sc, now_std, noise_m, np.unique(np.stack(
        [k[new], out[new]], axis=1), axis=0))
    out = np.where(new & ~alone[k, np.maximum(out, 0)], -1, out)
    first = a == out
    new = out != label
    return (out, np.where(new, np.where(first, kinds[0], kinds[1]), 0),
            np.where(new, np.where(first, confs[0], confs[1]), 0.0), doubt)


def exclusive(xyz: np.ndarray, have: np.ndarray, carried: np.ndarray, carried_std: np.ndarray,
              std: np.ndarray, noise_m: float, cells: np.ndarray) -> np.ndarray:
    """Whether each new name's point is its marker's alone (F, L) bool, for cells (n, 2) of (frame, marker): its
    position xyz[k, m] (F, L, 3) [m] (std (F, L) [m], where ``have``) within the 3-DOF gate of no other marker
    unnamed on that frame, where the names carry that one (carried (F, L, 3), carried_std (F, L) [m], NaN where
    nowhere). A cell without a position is kept."""
    ok = np.ones(have.shape, bool)
    k, m = cells.reshape(-1, 2).T
    on = have[k, m]
    k, m = k[on], m[on]
    s2 = carried_std[k] ** 2 + std[k, m][:, None] ** 2 + noise_m ** 2  # (n, L)
    d2 = np.sum((carried[k] - xyz[k, m][:, None]) ** 2, axis=-1) / s2
    rival = np.isfinite(d2) & (d2 < CHI2_3DOF_GATE) & ~have[k]
    rival[np.arange(len(m)), m] = False
    ok[k, m] = ~rival.any(axis=1)
    return ok
