"""Is a camera out of step? Two checks on the markers that need no estimate of the timing.

* :func:`timing_check`: a time offset shows in a camera's residuals as a displacement along each marker's
  image velocity; a rolling shutter, as the same growing with the image row. Each camera's residuals against
  a given track (positions and velocities per frame) are regressed on both, every point re-triangulated from
  its own frame's observations so that a camera cannot hide its offset by pulling the point toward itself
  (exact for any estimate the triangulation is the start of). Offsets are only relative (a common shift moves
  the points and nothing else): they are stated against the reference camera, the one with the most
  observations used; warnings compare each camera with the median camera ("the others").
* :func:`scan_lags`: whole-frame lags, from the epipolar (Sampson) distance between two cameras' observations
  of a marker at frames shifted against each other, every pair, solved jointly for one lag per camera.

Results are corrections to the rig's known timing (calibration.toml), in seconds and frames of the session
clock. docs/timing.md gives the figures behind the thresholds (scripts/timing_check.py measures them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .camera import Rig, distort_normalized
from .geometry import pinhole
from .measurement import IdealObservations

SIGNIFICANT_Z = 5.0  # |offset| / sd above which an offset is significant
MATERIAL_PX = 0.5  # ... and material when it moves the camera's faster markers by more than this [px]
SPEED_PERCENTILE = 90  # the faster markers: this percentile of a camera's image speeds
MATERIAL_SIGMA = 0.25  # ... and by more than this fraction of the camera's pixel noise
AMBIGUOUS_RATIO = 1.5  # a lag is ambiguous when one 2+ frames away costs less than this times the best
HUBER_K = 3.0  # robust weight of a residual above this many sigmas: k / |r| (mislabels, occlusion swaps)
BLOCK_S = 0.1  # a marker's residuals within this time [s] count as one cluster (_cluster_cov)


@dataclass
class TimingCheck:
    """What :func:`timing_check` found.

    table: per camera: camera, n_obs (observations used), offset_s, offset_sd_s (relative to the reference camera,
        beyond the rig's known offset), readout_s, readout_sd_s (beyond its known readout), step_s, step_sd_s (its
        offset relative to the median camera), image_speed_px_s (|image velocity| of its faster markers: the
        SPEED_PERCENTILE-th percentile), flagged
        (out of step), rolling (reads its rows over a time the rig does not state), sigma_px (its pixel noise,
        from the observations' covariance).
    reference: the camera offsets are stated against. warnings: one line per camera out of step, one for the
        rolling shutters.
    """

    table: pd.DataFrame
    reference: str
    warnings: list[str] = field(default_factory=list)


def _raw_rows(rig: Rig, ideal: IdealObservations) -> np.ndarray:
    """raw row / image height (C, F, M) of ideal pixels (distorted back), for observations without row_frac."""
    out = np.zeros(ideal.uv_px.shape[:3])
    for c, cam in enumerate(rig):
        xy = pinhole.normalized_from_pixels(ideal.uv_px[c], np.linalg.inv(cam.K))
        raw = pinhole.pixels_from_normalized(distort_normalized(xy, cam.dist), cam.K)
        out[c] = np.nan_to_num(raw[..., 1]) / cam.size_wh[1]
    return out


def _linearise(rig: Rig, ideal: IdealObservations, xyz_m: np.ndarray, vel_mps: np.ndarray, fps: float):
    """Per observation (C, F, M): residual r (.., 2) [px] at the known capture time, Jacobian J (.., 2, 3) [px/m],
    inverse covariance Sinv (.., 2, 2), image velocity w (.., 2) [px/s], row / height, usable (C, F, M)."""
    C, F, M = ideal.uv_px.shape[:3]
    dt = np.zeros((C, F, M)) if ideal.time_frac is None else ideal.time_frac / fps
    rows = _raw_rows(rig, ideal) if ideal.row_frac is None else ideal.row_frac
    X = xyz_m[None] + vel_mps[None] * dt[..., None]
    P = np.stack([cam.P for cam in rig])[:, None, None]
    ok = ideal.seen & np.isfinite(X).all(-1) & np.isfinite(vel_mps).all(-1)[None]
    X = np.where(ok[..., None], X, 0.0)
    J = pinhole.point_jacobian(P, X)
    r = np.where(ok[..., None], ideal.uv_px - pinhole.project_ideal(P, X), 0.0)
    w = np.einsum("cfmij,fmj->cfmi", J, np.nan_to_num(vel_mps))
    cov = np.where(ok[..., None, None], ideal.cov_px2, np.eye(2))
    Sinv = np.linalg.inv(cov)
    ok &= np.isfinite(r).all(-1) & np.isfinite(J).all((-1, -2)) & np.isfinite(w).all(-1)
    return np.nan_to_num(r), np.nan_to_num(J), Sinv, np.nan_to_num(w), rows, ok


def _solve(r, J, Sinv, x, wgt, ref: int, block: int):
    """Weighted least squares of the residuals on the regressors, the points re-triangulated (see module docstring).

    wgt (C, F, M): robust weights (0 = unused). block: frames per cluster of :func:`_cluster_cov`. Returns (params
    (C, 2) with the reference offset fixed at 0, their covariance (2C, 2C), whitened residual norms (C, F, M), used
    (C, F, M))."""
    C = r.shape[0]
    WS = wgt[..., None, None] * Sinv
    used = (wgt > 0) & ((wgt > 0).sum(0) >= 2)[None]  # a point one camera sees says nothing
    WS = np.where(used[..., None, None], WS, 0.0)
    JtWS = np.swapaxes(J, -1, -2) @ WS  # (C, F, M, 3, 2); batched matmul: einsum of three operands is slow here
    XtWS = np.swapaxes(x, -1, -2) @ WS  # (C, F, M, 2, 2)
    A = (JtWS @ J).sum(axis=0)  # (F, M, 3, 3)
    pts = used.any(0)
    Ainv = np.zeros_like(A)
    Ainv[pts] = np.linalg.inv(A[pts])
    U = np.moveaxis(JtWS @ x, 0, 3).reshape(*A.shape[:2], 3, 2 * C)  # (F, M, 3, 2C)
    g = (JtWS @ r[..., None])[..., 0].sum(axis=0)  # (F, M, 3)
    D = (XtWS @ x).sum(axis=(1, 2))  # (C, 2, 2)
    N = np.zeros((2 * C, 2 * C))
    for c in range(C):
        N[2 * c:2 * c + 2, 2 * c:2 * c + 2] = D[c]
    Z = Ainv @ U
    N -= U.reshape(-1, 2 * C).T @ Z.reshape(-1, 2 * C)
    b = (XtWS @ r[..., None])[..., 0].sum(axis=(1, 2)).reshape(-1) - U.reshape(-1, 2 * C).T @ (
        (Ainv @ g[..., None]).reshape(-1))
    free = np.ones(2 * C, bool)
    free[2 * ref] = False
    free &= np.diag(N) > 1e-9 * max(np.diag(N).max(), 1e-300)
    theta = np.zeros(2 * C)
    Ninv = np.linalg.pinv(N[np.ix_(free, free)], rcond=1e-12)
    theta[free] = Ninv @ b[free]
    delta = (Ainv @ (g - U @ theta)[..., None])[..., 0]  # point corrections with the timing removed
    res = r - (J @ delta[None, ..., None])[..., 0] - (x @ theta.reshape(C, 1, 1, 2, 1))[..., 0]
    e2 = (res[..., None, :] @ np.where(used[..., None, None], Sinv, 0.0) @ res[..., None])[..., 0, 0]
    n_pts, n_obs = int(pts.sum()), int(used.sum())
    dof = max(2 * n_obs - 3 * n_pts - int(free.sum()), 1)
    s2 = float((wgt * e2)[used].sum()) / dof
    cov = np.full((2 * C, 2 * C), np.nan)
    scores = np.moveaxis((XtWS @ res[..., None])[..., 0], 0, 2).reshape(*res.shape[1:3], 2 * C)[..., free]
    cov[np.ix_(free, free)] = _cluster_cov(scores, Ninv, block, s2)
    cov[2 * ref, :] = cov[:, 2 * ref] = 0.0
    return theta.reshape(C, 2), cov, np.sqrt(e2 / max(s2, 1e-300)), used


MIN_CLUSTERS = 20


def _cluster_cov(scores: np.ndarray, Ninv: np.ndarray, block: int, s2: float) -> np.ndarray:
    """The parameters' covariance, robust to errors correlated along a marker's track (a detector's bias persists
    over frames; pixels are not independent): the sandwich ``N^-1 (sum_g s_g s_g^T) N^-1`` over clusters g of
    ``block`` frames of one marker, seen by every camera (a point's re-triangulation couples its cameras), scaled
    by G / (G - 1); never below the independent-errors covariance ``s2 N^-1``, the one used with fewer than
    MIN_CLUSTERS clusters. scores (F, M, P): each point's score per parameter, x^T W r."""
    F, M, P = scores.shape
    edges = np.arange(0, F, block)
    per = np.add.reduceat(scores, edges, axis=0).reshape(-1, P) if F and P else np.zeros((0, P))
    per = per[np.abs(per).sum(axis=1) > 0]
    model = s2 * Ninv
    G = len(per)
    if G < MIN_CLUSTERS:
        return model
    sandwich = Ninv @ (per.T @ per) @ Ninv * G / (G - 1)
    scale = max(1.0, float(np.max(np.diag(sandwich) / np.maximum(np.diag(model), 1e-300))))
    return model * scale


def timing_check(rig: Rig, ideal: IdealObservations, xyz_m: np.ndarray, vel_mps: np.ndarray,
                 fps: float) -> TimingCheck:
    """Each camera's time offset and readout as the markers' residuals show them (module docstring).

    ideal: the session's observations (batgraph.measurement; time_frac, row_frac used when present, else no known
    timing and rows from the pixels); xyz_m, vel_mps: an estimate of every marker's position [m] and velocity
    [m/s] per frame, (F, M, 3), NaN where unknown (e.g. the smoother's, or a triangulation and its np.gradient
    times fps); fps: the session's frame rate [Hz]. Huber weights (HUBER_K) keep mislabels out.
    """
    r, J, Sinv, w, rows, ok = _linearise(rig, ideal, xyz_m, vel_mps, fps)
    C = len(rig)
    # the readout about each camera's median row: the offset is then that of the rows its markers are on, and
    # hardly correlated with the readout (a camera that sees the animal in a band of rows cannot tell them apart)
    mid = np.array([np.median(rows[c][ok[c]]) if ok[c].any() else 0.0 for c in range(C)])
    x = np.stack([w, w * (rows - mid[:, None, None])[..., None]], axis=-1)
    ref = int(np.argmax(ok.sum(axis=(1, 2))))
    wgt = ok.astype(float)
    block = max(1, round(BLOCK_S * fps))
    for _ in range(4):
        theta, cov, e, used = _solve(r, J, Sinv, x, wgt, ref, block)
        wgt = np.where(ok, np.minimum(1.0, HUBER_K / np.maximum(e, 1e-12)), 0.0)
    speed = np.linalg.norm(w, axis=-1)
    sigma = np.sqrt(0.5 * np.trace(ideal.cov_px2, axis1=-2, axis2=-1))
    noise = np.array([np.median(sigma[c][used[c]]) if used[c].any() else np.nan for c in range(C)])
    step, step_sd = _steps(theta[:, 0], cov[0::2, 0::2])
    at_row0, cov0 = _at_row_zero(theta, cov, mid, ref)
    med_speed = np.array([np.percentile(speed[c][used[c]], SPEED_PERCENTILE) if used[c].any() else np.nan
                          for c in range(C)])
    table = pd.DataFrame({
        "camera": rig.names, "n_obs": used.sum(axis=(1, 2)), "offset_s": at_row0,
        "offset_sd_s": np.sqrt(np.diag(cov0)), "readout_s": theta[:, 1],
        "readout_sd_s": np.sqrt(np.diag(cov)[1::2]), "step_s": step, "step_sd_s": step_sd,
        "image_speed_px_s": med_speed, "sigma_px": noise})
    table["flagged"] = _material(table["step_s"], table["step_sd_s"], table["image_speed_px_s"], noise)
    table["rolling"] = _material(table["readout_s"], table["readout_sd_s"], 0.5 * table["image_speed_px_s"], noise)
    return TimingCheck(table, rig.names[ref], _warnings(table, fps))


def _at_row_zero(theta: np.ndarray, cov: np.ndarray, mid: np.ndarray, ref: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets at row 0 (calibration.toml's meaning) relative to the reference camera's, and their covariance (C, C),
    from offsets at each camera's median row ``mid`` (C,) and readouts: theta (C, 2), cov (2C, 2C)."""
    C = len(theta)
    L = np.zeros((C, 2 * C))
    for c in range(C):
        L[c, 2 * c], L[c, 2 * c + 1] = 1.0, -mid[c]
    L -= L[ref]
    cov0 = L @ np.nan_to_num(cov) @ L.T
    unknown = (L[:, ~np.isfinite(np.diag(cov))] != 0).any(axis=1)
    cov0[unknown, :] = cov0[:, unknown] = np.nan
    return L @ theta.reshape(-1), cov0


def _steps(offset_s: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's offset against the median camera's (the others'), and its sd, (C,) [s]; with two cameras,
    against the other one. Cameras with no estimate (NaN sd) are left out of the median."""
    C = len(offset_s)
    known = np.flatnonzero(np.isfinite(np.diag(cov)))
    if len(known) < 2:
        return np.full(C, np.nan), np.full(C, np.nan)
    order = known[np.argsort(offset_s[known], kind="stable")]
    mid = order[(len(order) - 1) // 2]
    step = offset_s - offset_s[mid]
    var = np.diag(cov) + cov[mid, mid] - 2 * cov[:, mid]
    if len(known) == 2:  # the pair: each against the other
        other = np.where(np.arange(C) == known[0], known[1], known[0])
        step = offset_s - offset_s[other]
        var = np.diag(cov) + cov[other, other] - 2 * cov[np.arange(C), other]
    return step, np.sqrt(np.maximum(var, 0.0))


def _material(value_s: pd.Series, sd_s: pd.Series, speed_px_s: pd.Series, sigma_px: np.ndarray) -> np.ndarray:
    """Significant (SIGNIFICANT_Z sds) and material timing errors (C,) bool: they move the camera's faster markers
    (at ``speed_px_s``) by MATERIAL_PX or more, and by MATERIAL_SIGMA of its pixel noise ``sigma_px`` or more."""
    value, sd = np.abs(value_s.to_numpy(float)), sd_s.to_numpy(float)
    shift = value * speed_px_s.to_numpy(float)
    material = (shift > MATERIAL_PX) & (shift > MATERIAL_SIGMA * np.asarray(sigma_px, float))
    return np.nan_to_num((value > SIGNIFICANT_Z * sd) & material, nan=False).astype(bool)


def _warnings(table: pd.DataFrame, fps: float) -> list[str]:
    flagged = table[table["flagged"]]
    out = []
    if len(table) == 2 and len(flagged):  # a pair: one line for both
        a, b = table["camera"].tolist()
        step = float(table["step_s"].iloc[1])
        out.append(f"{b} looks ~{1e3 * abs(step):.1f} ms {'behind' if step > 0 else 'ahead of'} {a} "
                   f"({abs(step) * fps:.2f} frame): run with --sync estimate")
    elif len(flagged):
        out += [f"{row.camera} looks ~{1e3 * abs(row.step_s):.1f} ms out of step with the others "
                f"({abs(row.step_s) * fps:.2f} frame): run with --sync estimate" for row in flagged.itertuples()]
    rolling = table[table["rolling"]]
    if len(rolling):
        each = ", ".join(f"{r.camera} ~{1e3 * r.readout_s:.1f} ms" for r in rolling.itertuples())
        out.append(f"rolling shutter: {each} from the top row to the bottom beyond what calibration.toml states "
                   f"(readout_s): run with --sync estimate")
    return out


# ----------------------------------------------------------------------------------------------
# whole-frame lags
# ----------------------------------------------------------------------------------------------
@dataclass
class LagScan:
    """What :func:`scan_lags` found.

    table: per camera: camera, lag_frames (its frame labelled k shows the session's instant k + lag, relative to
        the reference camera; NaN when it cannot be told), offset_frames (the same to a rough fraction of a frame,
        a start for an estimator), time_offset_s (the rig's known offset plus lag / fps),
        cost_px (median Sampson distance at that lag over its pairs), cost_at_zero_px, ambiguous (bool), note.
    reference: the camera the lags are relative to (the one with the most observations).
    """

    table: pd.DataFrame
    reference: str
    warnings: list[str] = field(default_factory=list)


def _sampson(Fm: np.ndarray, ha: np.ndarray, hb: np.ndarray) -> np.ndarray:
    """Sampson distances [px] of ideal pixel pairs, homogeneous (N, 3), (N, 3), under F."""
    Fa, Fb = ha @ Fm.T, hb @ Fm
    num = np.einsum("ni,ni->n", hb, Fa)
    return np.abs(num) / np.sqrt(Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2)


def pair_costs(rig: Rig, uv: np.ndarray, frames: np.ndarray, span: int, min_points: int, max_points: int = 4000):
    """Median Sampson distance D[a, b, s + span] [px] between camera a at frame k and camera b at frame k + s, s in
    [-span, span]; NaN where fewer than ``min_points`` such pairs (at most ``max_points``, evenly spaced, are used).
    D[b, a, span - s] = D[a, b, span + s]: the same pairs of points, and the distance is symmetric.

    uv: ideal pixels (C, F, M, 2), NaN where unseen; frames (F,): their frame numbers, sorted (gaps allowed: only
    pairs exactly s frames apart count)."""
    C, F, M = uv.shape[:3]
    D = np.full((C, C, 2 * span + 1), np.nan)
    flat = np.concatenate([uv.reshape(C, F * M, 2), np.ones((C, F * M, 1))], axis=-1)  # homogeneous
    seen = np.isfinite(flat[..., 0])
    fundamental = {(a, b): rig.fundamental(a, b) for a in range(C) for b in range(a + 1, C)}
    for s in range(-span, span + 1):
        lo, hi = max(0, -s), min(F, F - s)
        if hi <= lo:
            continue
        f = np.arange(lo, hi)
        f = f[frames[f + s] == frames[f] + s]
        at = (f[:, None] * M + np.arange(M)).ravel()  # camera a's points; camera b's are s * M further
        seen_a, seen_b = seen[:, at], seen[:, at + s * M]
        for a in range(C):
            for b in range(a + 1, C):
                ok = np.flatnonzero(seen_a[a] & seen_b[b])
                if len(ok) < min_points:
                    continue
                ok = at[ok[np.linspace(0, len(ok) - 1, min(len(ok), max_points)).astype(int)]]
                d = float(np.median(_sampson(fundamental[a, b], flat[a, ok], flat[b, ok + s * M])))
                D[a, b, span + s] = D[b, a, span - s] = d
    return D


def _profile(D: np.ndarray, lags: np.ndarray, c: int, max_lag: int) -> np.ndarray:
    """Camera c's cost (2 max_lag + 1,) [px] over its lag, the others' held: the mean over its pairs of D at the
    lag difference; a shift with too few points costs the pair's worst (no evidence is no alibi)."""
    span = (D.shape[2] - 1) // 2
    out = np.zeros(2 * max_lag + 1)
    n = 0
    for b in range(D.shape[0]):
        row = D[c, b]
        if b == c or not np.isfinite(row).any():
            continue
        worst = np.nanmax(row)
        L = np.arange(-max_lag, max_lag + 1)
        out += np.nan_to_num(row[span + L - int(lags[b])], nan=worst)
        n += 1
    return out / n if n else np.full(2 * max_lag + 1, np.nan)


def _pair_offsets(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's offset d[a, b] ~ tau_a - tau_b [frames] at the minimum of its cost over the shift, refined to a
    fraction of a frame by a V through the minimum and its neighbours (the cost grows as |shift - d| times the
    markers' image speed), and the pair's weight (0 where unknown). D: :func:`pair_costs`."""
    C, _, S = D.shape
    span = (S - 1) // 2
    d, w = np.zeros((C, C)), np.zeros((C, C))
    for a in range(C):
        for b in range(C):
            row = D[a, b]
            if a == b or not np.isfinite(row).any():
                continue
            i = int(np.nanargmin(row))
            frac = 0.0
            if 0 < i < S - 1 and np.isfinite(row[i - 1]) and np.isfinite(row[i + 1]):
                slope = max(row[i - 1], row[i + 1]) - row[i]
                frac = float(np.clip((row[i - 1] - row[i + 1]) / (2 * slope), -0.5, 0.5)) if slope > 0 else 0.0
            d[a, b], w[a, b] = i - span + frac, 1.0
    return d, w


def _relative_offsets(d: np.ndarray, w: np.ndarray, ref: int) -> np.ndarray:
    """tau (C,) [frames], tau_ref = 0, from pairwise tau_a - tau_b = d[a, b] by weighted least squares; pairs more
    than a frame from the fit are dropped and the fit repeated (a pair's cost can have its minimum at a wrong lag)."""
    C = len(d)
    a, b = np.nonzero(np.triu(w, 1) > 0)
    keep = np.ones(len(a), bool)
    tau = np.zeros(C)
    for _ in range(5):
        A = np.zeros((keep.sum(), C))
        A[np.arange(keep.sum()), a[keep]], A[np.arange(keep.sum()), b[keep]] = 1.0, -1.0
        free = np.arange(C) != ref
        if not keep.any():
            break
        tau[free] = np.linalg.lstsq(A[:, free], d[a[keep], b[keep]], rcond=None)[0]
        bad = np.abs(tau[a] - tau[b] - d[a, b]) > 1.0
        if np.array_equal(bad, ~keep) or not (keep & ~bad).any():
            break
        keep = ~bad
    return tau


def scan_lags(rig: Rig, ideal: IdealObservations, frames: np.ndarray, fps: float, max_lag: int = 5,
              min_points: int = 20) -> LagScan:
    """Each camera's whole-frame lag relative to the reference camera, from the markers (module docstring).

    ideal: the observations (ideal pixels, C, F, M); frames (F,): their session frame numbers; fps [Hz]; lags are
    searched in [-max_lag, max_lag]. Every pair's cost over the shift (:func:`pair_costs`) gives its offset to a
    fraction of a frame (:func:`_pair_offsets`); one offset per camera is fitted to all pairs and rounded to the
    nearest frame. A lag is ambiguous when a lag two or more frames away costs less than AMBIGUOUS_RATIO times as
    much (the camera's cost: the mean over its pairs at the others' lags); an offset near half a frame is noted.
    """
    seen = ideal.seen
    ref = int(np.argmax(seen.sum(axis=(1, 2))))
    D = pair_costs(rig, ideal.uv_px, np.asarray(frames, np.int64), 2 * max_lag, min_points)
    tau = _relative_offsets(*_pair_offsets(D), ref)  # on the frames as they are, the known timing included
    known = np.zeros(len(rig))
    if ideal.time_frac is not None:
        known = np.array([np.median(ideal.time_frac[c][seen[c]]) if seen[c].any() else 0.0 for c in range(len(rig))])
    extra = tau - (known - known[ref])
    return _lag_table(rig, D, _nearest(tau, max_lag), _nearest(extra, max_lag), extra, ref, fps, max_lag)


def _nearest(x: np.ndarray, max_lag: int) -> np.ndarray:
    return np.clip(np.ceil(x - 0.5), -max_lag, max_lag).astype(int)


def _lag_table(rig: Rig, D: np.ndarray, on_frames: np.ndarray, lags: np.ndarray, tau: np.ndarray, ref: int,
               fps: float, max_lag: int) -> LagScan:
    """The table of :class:`LagScan`: on_frames (C,) the lags between the frames as they are (the costs' shifts);
    lags (C,) and tau (C,) [frames] beyond the rig's known timing."""
    rows, warnings = [], []
    for c, cam in enumerate(rig):
        prof = _profile(D, on_frames, c, max_lag)
        if not np.isfinite(prof).any():
            rows.append((cam.name, np.nan, np.nan, np.nan, np.nan, np.nan, True,
                         "too few markers seen with another camera"))
            warnings.append(f"{cam.name}: its lag cannot be told (too few markers seen with another camera)")
            continue
        best, i = int(lags[c]), int(on_frames[c]) + max_lag
        far = np.abs(np.arange(-max_lag, max_lag + 1) - on_frames[c]) >= 2
        ambiguous = bool(far.any() and np.nanmin(prof[far]) < AMBIGUOUS_RATIO * prof[i])
        notes = []
        if ambiguous:
            alt = int(np.arange(-max_lag, max_lag + 1)[far][np.nanargmin(prof[far])])
            notes.append(f"ambiguous: a shift of {alt} frames costs {np.nanmin(prof[far]):.2g} px against "
                         f"{prof[i]:.2g} px")
        if abs(tau[c]) > max_lag + 0.5:
            notes.append(f"beyond the scan (+-{max_lag} frames): about {tau[c]:+.1f} frames")
        elif abs(tau[c] - best) > 0.35:
            notes.append(f"about {tau[c]:+.2f} frames: between {best} and {best + int(np.sign(tau[c] - best))}")
        rows.append((cam.name, float(best), float(tau[c]), cam.time_offset_s + best / fps, float(prof[i]),
                     float(prof[max_lag]), ambiguous, "; ".join(notes)))
        if c != ref and (best != 0 or ambiguous):
            warnings.append(f"{cam.name} runs ~{abs(best)} frame(s) {'late' if best > 0 else 'early'} against "
                            f"{rig.names[ref]}: time_offset_s ~{cam.time_offset_s + best / fps:.4g} s"
                            + (f" ({'; '.join(notes)})" if notes else ""))
    table = pd.DataFrame(rows, columns=["camera", "lag_frames", "offset_frames", "time_offset_s", "cost_px",
                                        "cost_at_zero_px", "ambiguous", "note"])
    return LagScan(table, rig.names[ref], warnings)
