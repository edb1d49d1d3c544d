"""Checks of named 3D paths: a marker's name is kept only on the stretches of its path that its segments or its
continuity with the seed vouch for. A swap shows as a jump in the path (its ends) or as segment lengths gone
wrong (its middle); where the evidence cannot tell, the name is dropped (flagged, not guessed).

Per marker: frames whose position leaves the local quadratic through its neighbours on both sides (up to
JUMP_WINDOW named frames a side, within 2 JUMP_WINDOW frames) by more than JUMP_SIGMA times the path's own scatter
(a robust scale, at least JUMP_FLOOR_M) are jumps; they and gaps of more than MAX_GAP frames cut the path into
stretches. A stretch is vouched for when it holds a seed frame, or when at least MIN_CHECKS of its distances to
segment partners were checked and at most MAX_FAIL of them were off by more than SEGMENT_SIGMA stds
(batgraph.associate.segments; a marker without a declared segment is also checked against its learned affine
relation, batgraph.associate.affine), or when it meets a vouched stretch across a gap without a jump (its end,
extrapolated linearly, lands within the jump bound of the other's start): a name carried by continuity from the
seed. A link the tracker doubted (placed with a confidence below batgraph.associate.tracks.DOUBT_BELOW) cuts the
path too, and continuity does not carry a name across it: the stretch beyond keeps its name only where its segments
vouch for it. A frame where the marker is named in one camera only has no position to check: its name is kept where
continuity carries a vouched name to it over such frames (:func:`carried`).
"""

from __future__ import annotations

import numpy as np

from . import affine
from . import segments as seg_mod

JUMP_WINDOW = 5
JUMP_SIGMA = 3.5
JUMP_FLOOR_M = 0.006
MAX_GAP = 8
MIN_CHECKS = 4
MAX_FAIL = 0.15
SEGMENT_SIGMA = 4.0


def _jumps(x: np.ndarray, have: np.ndarray, floor_m: float) -> tuple[np.ndarray, float]:
    """Breaks (F,) bool of one marker's path x (F, 3) (where ``have``): frame k breaks from the frame before where
    the quadratics fitted to up to JUMP_WINDOW named frames on each side within 2 JUMP_WINDOW frames of k (at least
    3 a side; the path bends as a wing flaps) disagree, half a frame before k, by more than the bound [m], and more
    than at the neighbouring frames. A swap shows so at both ends. The bound is JUMP_SIGMA times the robust
    disagreement where both sides have their JUMP_WINDOW nearest frames in reach (fits over sparser frames
    extrapolate further and would loosen it for every frame), at least floor_m."""
    F = len(x)
    idx = np.flatnonzero(have)
    gap = np.full(F, np.nan)
    whole = np.zeros(F, bool)  # both sides' nearest frames in reach: these set the bound
    ks, sides = [], ([], [])
    for j in range(1, len(idx)):
        k = idx[j]
        left = idx[max(0, j - JUMP_WINDOW):j]
        right = idx[j:j + JUMP_WINDOW]
        whole[k] = k - left[0] <= 2 * JUMP_WINDOW and right[-1] - k <= 2 * JUMP_WINDOW
        left, right = left[k - left <= 2 * JUMP_WINDOW], right[right - k <= 2 * JUMP_WINDOW]
        if len(left) < 3 or len(right) < 3:
            continue
        ks.append(k)
        sides[0].append(left)
        sides[1].append(right)
    if ks:
        ks = np.array(ks)
        a, b = (_fit_at(x, frames, ks - 0.5) for frames in sides)
        gap[ks] = np.linalg.norm(a - b, axis=1)
    ok = np.isfinite(gap) & whole
    scale = 1.4826 * float(np.median(gap[ok])) if ok.sum() >= 5 else floor_m
    bound = max(JUMP_SIGMA * scale, floor_m)
    g = np.nan_to_num(gap, nan=0.0)
    peak = (g >= np.r_[0.0, g[:-1]]) & (g >= np.r_[g[1:], 0.0])
    return (g > bound) & peak, bound


def _fit_at(x: np.ndarray, frames: list[np.ndarray], at: np.ndarray) -> np.ndarray:
    """Per window i the least-squares polynomial through x[frames[i]] (x (F, 3) [m], NaN allowed off the windows),
    a quadratic where the window holds 4 frames or more, else a line, evaluated at ``at[i]``: (n, 3). All windows
    in one batched solve (a polyfit per window cost a third of the checks' time)."""
    n, W = len(frames), max(len(f) for f in frames)
    idx = np.zeros((n, W), np.int64)
    on = np.zeros((n, W), bool)
    for i, f in enumerate(frames):
        idx[i, :len(f)], on[i, :len(f)] = f, True
    t = np.where(on, idx - at[:, None], 0.0)
    quad = on.sum(axis=1) >= 4
    V = np.stack([on * 1.0, t, np.where(quad[:, None], t * t, 0.0)], axis=2)  # (n, W, 3), rows off the window 0
    A = np.einsum("nwi,nwj->nij", V, V)
    A[~quad, 2, 2] = 1.0  # a line: the quadratic's coefficient solved as 0
    coef = np.linalg.solve(A, np.einsum("nwi,nwd->nid", V, np.where(on[..., None], x[idx], 0.0)))
    return coef[:, 0]


def _stretches(have: np.ndarray, jump: np.ndarray, doubt: np.ndarray) -> list[np.ndarray]:
    """Runs of frames with a position, cut before each break, at gaps of more than MAX_GAP frames and where a
    doubtful link lies between two frames (``doubt`` (F,) the count of doubtful links up to each frame)."""
    idx = np.flatnonzero(have)
    out, cur = [], []
    for k in idx:
        if cur and (k - cur[-1] > MAX_GAP or jump[k] or doubt[k] > doubt[cur[-1]]):
            out.append(np.array(cur))
            cur = []
        cur.append(k)
    if cur:
        out.append(np.array(cur))
    return out


def _segment_counts(X: np.ndarray, have: np.ndarray, seg: seg_mod.Segments, m: int,
                    relations: affine.Relations | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (F,) how many of marker m's segment distances (and its affine relation's prediction,
    batgraph.associate.affine) were checked and how many failed."""
    checks, fails = np.zeros(len(X), int), np.zeros(len(X), int)
    if relations is not None and relations.refs[m, 0] >= 0:
        r = relations.residual(X, have, m)
        on = np.isfinite(r)
        checks += on
        fails += on & (r > SEGMENT_SIGMA * relations.sigma[m])
    part = seg.partner[m]
    ok = part >= 0
    part, length, sigma = part[ok], seg.length[m][ok], seg.sigma[m][ok]
    if not len(part):
        return checks, fails
    d = np.linalg.norm(X[:, part] - X[:, m, None], axis=-1)  # (F, K)
    both = have[:, part] & have[:, m, None]
    bad = both & (np.abs(d - length) > SEGMENT_SIGMA * sigma)
    return checks + both.sum(axis=1), fails + bad.sum(axis=1)


def vouched(X: np.ndarray, have: np.ndarray, seed: np.ndarray, seg: seg_mod.Segments,
            noise_m: float = 0.0, doubt: np.ndarray | None = None,
            relations: affine.Relations | None = None) -> np.ndarray:
    """Which named positions keep their name (F, L) bool. X (F, L, 3) [m] positions, have (F, L) where named,
    seed (F, L) where the user named the marker, seg: segments with lengths, noise_m [m] the positions' noise (the
    jump bound's floor is at least 3 times it; see module docstring), relations: the markers' learned affine
    relations (batgraph.associate.affine; None: none)."""
    F, L = have.shape
    keep = np.zeros((F, L), bool)
    for m in range(L):
        if not have[:, m].any():
            continue
        jump, bound = _jumps(X[:, m], have[:, m], max(JUMP_FLOOR_M, 3 * noise_m))
        doubts = np.cumsum(doubt[:, m]) if doubt is not None else np.zeros(F, np.int64)
        parts = _stretches(have[:, m], jump, doubts)
        checks, fails = _segment_counts(X, have, seg, m, relations)
        good = []
        for p in parts:
            n, bad = int(checks[p].sum()), int(fails[p].sum())
            good.append(bool(seed[p, m].any()) or (n >= MIN_CHECKS and bad <= MAX_FAIL * n))
        changed = True
        while changed:  # continuity carries a name from a vouched stretch to its neighbours
            changed = False
            for i, p in enumerate(parts):
                if good[i]:
                    continue
                for j in (i - 1, i + 1):
                    if not 0 <= j < len(parts) or not good[j]:
                        continue
                    earlier, later = parts[min(i, j)], parts[max(i, j)]
                    sure = not jump[later[0]] and doubts[later[0]] == doubts[earlier[-1]]
                    if sure and _continues(X[:, m], parts[j], p, bound):
                        good[i] = changed = True
                        break
        for p, g in zip(parts, good, strict=True):
            keep[p, m] = g
    return keep


def _continues(x: np.ndarray, a: np.ndarray, b: np.ndarray, bound: float) -> bool:
    """Whether stretch b follows stretch a (or precedes it) without a jump: a's nearest end extrapolated linearly
    over the gap lands within bound (plus 2 mm per frame of gap) of b's nearest end."""
    if a[-1] < b[0]:
        end, start, gap = a[-2:] if len(a) >= 2 else a[-1:], b[0], b[0] - a[-1]
    else:
        end, start, gap = a[:2][::-1] if len(a) >= 2 else a[:1], b[-1], a[0] - b[-1]
    if len(end) == 2:
        v = (x[end[1]] - x[end[0]]) / (end[1] - end[0])
        guess = x[end[1]] + v * (start - end[1])
    else:
        guess = x[end[0]]
    return float(np.linalg.norm(x[start] - guess)) <= bound + 0.002 * gap


def carried(keep: np.ndarray, single: np.ndarray, doubt: np.ndarray) -> np.ndarray:
    """Where a name is kept (F, L): the vouched positions ``keep`` and the frames continuity carries them to over
    frames where the marker is named in one camera only (``single``: no position to check; the tracker followed it
    along its predicted ray), forwards and backwards, up to a link in doubt (``doubt`` (F, L), marked on the later
    frame of a link) or a frame without the name."""
    out = keep.copy()
    for k in range(1, len(out)):
        out[k] |= out[k - 1] & single[k] & ~doubt[k]
    for k in range(len(out) - 2, -1, -1):
        out[k] |= out[k + 1] & single[k] & ~doubt[k + 1]
    return out
