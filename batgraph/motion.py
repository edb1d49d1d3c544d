"""Motion models: the paper's random walk (eq. 3-5), a constant-velocity (white-noise acceleration) and a
constant-acceleration (white-noise jerk) prior, as noise matrices in physical units. Choosing a noise
level from data lives with the estimators.
"""

from __future__ import annotations

import math

import numpy as np

from .session import MotionConfig

CHI2_3DOF_95 = 7.814727903251178  # 95 % quantile of chi-square, 3 DOF (the paper rounds it to 7.8147, eq. 5)
CHI2_3DOF_MEDIAN = 2.3659738843753377  # its median (scipy.stats.chi2.ppf(0.5, 3))
CHI2_1DOF_95 = 3.841458820694124  # 95 % quantile of chi-square, 1 DOF (scipy.stats.chi2.ppf(0.95, 1))
G_MPS2 = 9.81  # standard gravity [m/s^2]


def max_motion_per_frame_m(motion: MotionConfig, fps: float) -> float:
    """Paper eq. 4: d_m = sqrt((v_f / f_c)^2 + (alpha_f l_w f_f / f_c)^2) [m]. Needs the physics."""
    if not motion.has_physics:
        raise ValueError("[motion] has no physics (flight_speed_mps, span_m, flap_hz, flap_angle_deg) and no sigma_m: "
                         "reconstruct measures sigma_m from the triangulated track (noise_from_track)")
    alpha = math.radians(motion.flap_angle_deg)
    return math.hypot(motion.flight_speed_mps / fps, alpha * motion.span_m * motion.flap_hz / fps)


def random_walk_sigma_m(motion: MotionConfig, fps: float) -> float:
    """Per-axis std of the random walk per frame [m]: ``sigma_m`` if set, else sqrt(d_m^2 / 7.8147) (eq. 5)."""
    if motion.sigma_m is not None:
        return float(motion.sigma_m)
    return max_motion_per_frame_m(motion, fps) / math.sqrt(CHI2_3DOF_95)


CAUSAL_Q_FLOOR = 1.0  # [m^2/s^3] the causal q without a flap: a filter that sees no data should not assume rigidity


def causal_accel_psd(motion: MotionConfig, fps: float) -> float:
    """Constant-velocity q [m^2/s^3] from the motion config alone (the filter's default: it sees no data).

    The paper's eq. 4 bounds a wing's speed by the flap's peak speed alpha_f l_w f_f; a sinusoidal flap with that
    peak speed has peak acceleration a = 2 pi f_f alpha_f l_w f_f, and its velocity changes per frame by
    a sin(.) dt, of mean square a^2 dt^2 / 2 (3-D); white-noise acceleration of PSD q changes it by 3 q dt per frame,
    so q = a^2 dt / 6 (8.7 m^2/s^3 for the paper's flight), at least CAUSAL_Q_FLOOR. Without physics:
    ``causal_accel_psd_m2_s3``, measured by reconstruct from the triangulated track (:func:`noise_from_track`).
    """
    if not motion.has_physics:
        if motion.causal_accel_psd_m2_s3 is None:
            raise ValueError("[motion] has no physics and no measured q (batgraph.motion.noise_from_track)")
        return float(motion.causal_accel_psd_m2_s3)
    a = 2 * math.pi * motion.flap_hz * math.radians(motion.flap_angle_deg) * motion.span_m * motion.flap_hz
    return max(a * a / fps / 6.0, CAUSAL_Q_FLOOR)


def constant_velocity_Q(accel_psd_m2_s3: float, dt_s: float) -> np.ndarray:
    """Process covariance of one step of the constant-velocity model, shape (6, 6).

    State [p (3) m, v (3) m/s]; continuous white-noise acceleration of PSD q [m^2/s^3]:
    ``Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]``; transition ``F = [[I, dt I], [0, I]]``.
    """
    q, dt = accel_psd_m2_s3, dt_s
    I = np.eye(3)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def constant_velocity_F(dt_s: float) -> np.ndarray:
    """Transition matrix of the constant-velocity model, shape (6, 6)."""
    return np.block([[np.eye(3), dt_s * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])


def constant_acceleration_Q(jerk_psd_m2_s5: float, dt_s: float) -> np.ndarray:
    """Process covariance of one step of the constant-acceleration model, shape (9, 9).

    State [p (3) m, v (3) m/s, a (3) m/s^2]; continuous white-noise jerk of PSD j [m^2/s^5]:
    ``Q = j [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]] (x) I3``;
    transition :func:`constant_acceleration_F`. Per axis det = j^3 dt^9 / 8640.
    """
    j, dt = jerk_psd_m2_s5, dt_s
    blocks = [[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2], [dt**3 / 6, dt**2 / 2, dt]]
    return j * np.kron(np.array(blocks), np.eye(3))


def constant_acceleration_F(dt_s: float) -> np.ndarray:
    """Transition matrix of the constant-acceleration model, shape (9, 9): p' = p + v dt + a dt^2 / 2, v' = v + a dt."""
    dt = dt_s
    return np.kron(np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]]), np.eye(3))


TRACK_LAGS = (1, 2, 4, 8, 16)  # frames: second differences at the shortest lag that clears the noise
TRACK_SNR = 4.0
TRACK_MARKER_PERCENTILE = 90  # the filter's one q must cover the fast markers (the paper's physics: the wing tip)


def noise_from_track(xyz_m: np.ndarray, cov_m2: np.ndarray, fps: float) -> tuple[float, float]:
    """(random-walk sigma_m [m], constant-velocity q [m^2/s^3]) measured from a triangulated track.

    For sessions whose session.toml states no physics (imported humans, mice, insects): the paper's
    eq. 4-5 take d_m as the largest motion per frame and sigma_m = d_m / sqrt(7.8147); here d_m is the
    95th percentile of the observed per-frame 3D displacements. q follows the physics rule of
    causal_accel_psd, q = a_rms^2 dt / 3 (a sinusoid's mean square is half its
    peak squared), with a_rms^2 each marker's mean square 3D acceleration from second differences
    ``x[k+L] - 2 x[k] + x[k-L] ~ a (L dt)^2`` at the shortest lag L in TRACK_LAGS whose mean square is
    TRACK_SNR times the triangulation noise ``tr(S[k+L]) + 4 tr(S[k]) + tr(S[k-L])`` (subtracted), and
    the 90th percentile over markers (the physics rule is the wing tip's); the largest 0.5 % of second
    differences are dropped (mislabels). Floored at 0.01 (the smoother's search floor).

    xyz_m: (F, M, 3) [m], NaN where not triangulated; cov_m2: (F, M, 3, 3) [m^2]. fps [Hz].
    Raises ValueError when fewer than 10 consecutive pairs are triangulated.
    """
    dt = 1.0 / fps
    step = np.linalg.norm(np.diff(xyz_m, axis=0), axis=-1)
    step = step[np.isfinite(step)]
    if len(step) < 10:
        raise ValueError("too few consecutive triangulated frames to measure the motion noise")
    sigma_m = float(np.percentile(step, 95)) / math.sqrt(CHI2_3DOF_95)
    tr = np.trace(cov_m2, axis1=-2, axis2=-1)
    a2 = 0.0
    for L in TRACK_LAGS:
        if len(xyz_m) <= 2 * L:
            break
        d2 = xyz_m[2 * L:] - 2 * xyz_m[L:-L] + xyz_m[:-2 * L]
        e = np.sum(d2 * d2, axis=-1)  # (F - 2L, M)
        noise = tr[2 * L:] + 4 * tr[L:-L] + tr[:-2 * L]
        ok = np.isfinite(e) & np.isfinite(noise)
        if ok.sum() < 10:
            break
        e, noise = np.where(ok, e, np.nan), np.where(ok, noise, np.nan)
        cut = np.nanpercentile(e, 99.5)
        e, noise = np.where(e <= cut, e, np.nan), np.where(e <= cut, noise, np.nan)
        enough = np.sum(np.isfinite(e), axis=0) >= 10
        per_marker = ((np.nanmean(e[:, enough], axis=0) - np.nanmean(noise[:, enough], axis=0))
                      / (L * dt) ** 4)  # (M',) markers with >= 10 samples
        if enough.any():
            a2 = max(float(np.percentile(per_marker, TRACK_MARKER_PERCENTILE)), 0.0)
        if np.nanmean(e) >= TRACK_SNR * np.nanmean(noise):
            break
    return max(sigma_m, 1e-6), max(a2 * dt / 3.0, 0.01)


WINGBEAT_BAND_HZ = (2.0, 40.0)  # the bats' (and birds') wingbeat frequencies batgraph looks for [Hz]
WINGBEAT_MIN_CYCLES = 2.0  # a frequency is measured only if the take holds this many of its cycles
WINGBEAT_OVERSAMPLE = 16  # the spectrum is sampled this many times finer than 1 / (take length)
WINGBEAT_MIN_FRAMES = 8  # a track with fewer triangulated frames is left out
# a periodogram peak this many times its median is a periodic motion (wingbeat_peak): the prominence is 23-2000
# on every flapping simulated scene (both generators, 4-15 Hz, 60-1000 fps, 1-8 px), 1.8 on a glide with an
# interior maximum, 69 on a real LED wand waved at 3.1 Hz
WINGBEAT_PROMINENCE = 10.0


def wingbeat_frequency(xyz_m: np.ndarray, fps: float) -> float | None:
    """The wingbeat frequency [Hz] measured from tracks: the peak of their summed periodogram
    (:func:`wingbeat_peak`'s frequency), or None."""
    peak = wingbeat_peak(xyz_m, fps)
    return None if peak is None else peak[0]


def wingbeat_peak(xyz_m: np.ndarray, fps: float) -> tuple[float, float] | None:
    """The peak of the tracks' summed periodogram: (frequency [Hz], prominence = its power / the band's median
    power), or None when the band is empty, no track is long enough, or the maximum is at an end of the band.

    xyz_m: positions (F, M, 3) [m], NaN where not triangulated. A marker hidden behind a wing for half of every
    stroke leaves gaps, so the spectrum is the Lomb-Scargle periodogram of the triangulated frames as they are
    (interpolating across the gaps put the peak at the band's edge on a hold-out scene): scipy.signal.lombscargle's,
    written as four matrix products over every track at once (scipy's takes one track at a time: 2.1 s at
    30 x 180 x 160). Each marker's axis with >= WINGBEAT_MIN_FRAMES frames is detrended by a quadratic in time (a
    flight's path is not the wingbeat); the periodograms, summed over markers and axes, are maximised over
    WINGBEAT_BAND_HZ below fps / 4 and of >= WINGBEAT_MIN_CYCLES cycles in the take, sampled WINGBEAT_OVERSAMPLE
    times finer than 1 / (take length). It is the largest periodic motion, flapping or not: the smoother's
    per-marker model choice decides whether an oscillation at it helps. A maximum at an end of the band is the
    spectrum still rising toward a slower or faster motion (e.g. a walking human's stride), not a peak.
    """
    spectrum = periodogram(xyz_m, fps)
    if spectrum is None:
        return None
    hz, power = spectrum
    peak = int(np.argmax(power))
    if not 0 < peak < len(hz) - 1:
        return None
    median = float(np.median(power))
    return float(hz[peak]), float(power[peak] / median) if median > 0 else float("inf")


def periodogram(xyz_m: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`wingbeat_peak`'s spectrum: the frequencies (K,) [Hz] and the Lomb-Scargle power (K,) summed over
    the tracks (scipy.signal.lombscargle's scale, [m^2]); None when the band is empty or no track is long
    enough."""
    F = len(xyz_m)
    lo = max(WINGBEAT_BAND_HZ[0], WINGBEAT_MIN_CYCLES * fps / max(F, 1))
    hi = min(WINGBEAT_BAND_HZ[1], fps / 4.0)
    if lo >= hi:
        return None
    hz = np.arange(lo, hi, fps / F / WINGBEAT_OVERSAMPLE)
    y = np.moveaxis(np.asarray(xyz_m, float), 0, -1).reshape(-1, F)  # (M * 3, F), one track per row
    ok = np.isfinite(y)
    keep = ok.sum(axis=1) >= WINGBEAT_MIN_FRAMES
    if not keep.any():
        return None
    y, w = np.where(ok, y, 0.0)[keep], ok[keep].astype(float)  # w: 1 on a triangulated frame
    t = np.arange(F) / fps
    t = t - t.mean()
    # each track less its least-squares quadratic in time over its own frames
    V = np.stack([np.ones(F), t, t * t], axis=1)  # (F, 3)
    coef = np.linalg.solve(np.einsum("nf,fi,fj->nij", w, V, V), np.einsum("nf,fi->ni", w * y, V)[..., None])[..., 0]
    y = w * (y - coef @ V.T)
    n = w.sum(axis=1)[:, None]
    power = np.empty(len(hz))
    for k0 in range(0, len(hz), PERIODOGRAM_CHUNK):  # the frequencies in chunks: memory ~ (F + tracks) x chunk
        chunk = hz[k0:k0 + PERIODOGRAM_CHUNK]
        power[k0:k0 + len(chunk)] = _lomb_scargle(y, w, n, 2 * np.pi * t[:, None] * chunk[None, :])
    return hz, power


PERIODOGRAM_CHUNK = 256  # frequencies per chunk of :func:`periodogram` (180 markers x 1200 frames: 325 -> 29 MB peak)


def _lomb_scargle(y: np.ndarray, w: np.ndarray, n: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """Lomb-Scargle power summed over tracks (K,): y (tracks, F) detrended and 0 off a track's frames, w (tracks,
    F) 1 on them, n (tracks, 1) their number, wt (F, K) the angle omega t of each frame and frequency. Per
    (track, frequency) from the sums over its frames of y cos wt, y sin wt, cos 2wt and sin 2wt."""
    yc, ys = y @ np.cos(wt), y @ np.sin(wt)
    c2, s2 = w @ np.cos(2 * wt), w @ np.sin(2 * wt)
    two_tau = np.arctan2(s2, c2)  # 2 w tau: the time shift that makes the sine and cosine terms orthogonal
    c, s = np.cos(two_tau / 2), np.sin(two_tau / 2)
    cc = 0.5 * (n + c2)  # sum cos^2 wt, sum sin^2 wt, sum sin wt cos wt
    ss, cs = 0.5 * (n - c2), 0.5 * s2
    power = 0.5 * (_ratio((c * yc + s * ys) ** 2, c * c * cc + 2 * c * s * cs + s * s * ss, n)
                   + _ratio((c * ys - s * yc) ** 2, c * c * ss - 2 * c * s * cs + s * s * cc, n))
    return power.sum(axis=0)


def _ratio(num: np.ndarray, den: np.ndarray, n: np.ndarray) -> np.ndarray:
    """num / den, 0 where den is a rounding error of n (tracks, 1) frames: frames every k-th fall on the zeros of
    that term's sine or cosine at multiples of fps / (2 k), where it has no power to give."""
    ok = den > 1e-9 * n
    return np.divide(num, den, out=np.zeros_like(num), where=ok)
