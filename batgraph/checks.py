"""Self-checks on every reconstruct, before any estimator runs; and the noise they measure.

:func:`preflight` triangulates what two cameras see, measures each camera's pixel noise
(:mod:`batgraph.pixel_noise`), and checks that the geometry can be right:

* **points behind a camera**: more than half of the triangulated points a camera sees behind it is an
  input error (exit 2) naming the camera and the likely causes (pixel origin, mirrored world, poses
  written world_from_camera); more than 5 % is a warning.
* **scale**: a camera whose median distance to its points is > 50 m or < 5 cm (animals are filmed from
  0.1-30 m): units? (a calibration in millimetres read as metres).
* **residuals**: a camera whose measured noise is > 5x the stated ``pixel_sigma_px``, or > 5x the median of
  the other cameras' when measured: a wrong calibration or mislabels. **guessed image size** (an import).
It also measures the motion noise from the triangulated track when session.toml states no physics
(batgraph.motion.noise_from_track). Warnings go to the terminal, summary.json and the report.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .measurement import IdealObservations, ideal_observations
from .motion import noise_from_track
from .pixel_noise import estimate_pixel_sigma
from .session import DenseObservations, Session
from .triangulate import dlt_points

BEHIND_ERROR = 0.5  # fraction of a camera's points behind it that makes the geometry impossible
BEHIND_WARN = 0.05
SCALE_RANGE_M = (0.05, 50.0)  # plausible camera-to-subject distances [m]
NOISE_RATIO_WARN = 5.0
LOOSE_MOTION = (0.1, 1e3)  # (sigma_m [m], q [m^2/s^3]) when the track cannot say: next to no motion prior


@dataclass
class Preflight:
    """What the checks found and measured.

    sigma_px: the pixel noise every estimator uses, (C,) [px]. noise: per camera name the measured
    figures (sigma_px, n_used, n_rejected, pooled) and "source" ("estimated" or "session.toml").
    session: the session with its motion noise filled in when it had no physics.
    warnings: one line each. figures: per camera distance [m] and fraction behind, for summary.json.
    ideal: the observations undistorted, with the noise ``sigma_px`` (batgraph.measurement).
    """

    sigma_px: np.ndarray
    noise: dict
    session: Session
    warnings: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    ideal: IdealObservations | None = None


def _given_sigma(session: Session) -> np.ndarray | None:
    """The session's own pixel noise per camera (C,), or None when it is to be measured."""
    given = session.pixel_sigma_px
    if given is None:
        return None
    if isinstance(given, dict):
        return np.array([float(given[name]) for name in session.rig.names])
    return np.full(len(session.rig), float(given))


def _where(session: Session) -> str:
    return str(session.path / "calibration.toml") if session.path is not None else f"session {session.name}"


def _geometry(session: Session, xyz: np.ndarray, seen: np.ndarray) -> tuple[dict, list[str]]:
    """Points behind each camera and camera-to-points distances; raises InputError when impossible."""
    figures, warnings = {}, []
    valid = np.isfinite(xyz).all(axis=-1)
    for c, cam in enumerate(session.rig):
        s = seen[c] & valid
        n = int(s.sum())
        if n == 0:
            figures[cam.name] = {"n_points": 0}
            continue
        pts = xyz[s]
        behind = float(np.mean(cam.to_cam(pts)[:, 2] <= 0))
        dist = float(np.median(np.linalg.norm(pts - cam.center_world, axis=-1)))
        figures[cam.name] = {"n_points": n, "behind_fraction": behind, "median_distance_m": dist}
        if behind > BEHIND_ERROR and n >= 5:
            raise InputError(f"{_where(session)}: camera {cam.name}: {100 * behind:.0f} % of the {n} points it "
                             f"sees triangulate behind it, so the geometry cannot be right (pixel origin flipped? "
                             f"a mirrored world? poses written world_from_camera?)")
        if behind > BEHIND_WARN:
            warnings.append(f"camera {cam.name}: {100 * behind:.0f} % of the {n} points it sees triangulate "
                            f"behind it (mislabels, or a calibration problem)")
        lo, hi = SCALE_RANGE_M
        if dist > hi:
            warnings.append(f"camera {cam.name} is {dist:.4g} m from the points it sees: a calibration in "
                            f"millimetres read as metres? (units: calibration.toml [metadata] units = \"mm\", "
                            f"or import with --units mm)")
        elif dist < lo:
            warnings.append(f"camera {cam.name} is {dist:.3g} m from the points it sees: a calibration in metres "
                            f"read as millimetres or centimetres? (units: calibration.toml [metadata] units)")
    return figures, warnings


def _noise_warnings(session: Session, measured: np.ndarray, given: np.ndarray | None) -> list[str]:
    names = session.rig.names
    out = []
    for c, name in enumerate(names):
        if not np.isfinite(measured[c]):
            continue
        if given is not None:
            ratio = measured[c] / given[c]
            if ratio > NOISE_RATIO_WARN:
                out.append(f"camera {name}: triangulation residuals say {measured[c]:.3g} px noise, {ratio:.0f}x the "
                           f"session's pixel_sigma_px {given[c]:g} px (a wrong calibration of this camera, or "
                           f"remove [noise] pixel_sigma_px to have it measured)")
            continue
        others = np.delete(measured, c)
        others = others[np.isfinite(others)]
        if len(others) and measured[c] > NOISE_RATIO_WARN * np.median(others):
            out.append(f"camera {name}: its measured pixel noise {measured[c]:.3g} px is "
                       f"{measured[c] / np.median(others):.0f}x the other cameras' median "
                       f"({np.median(others):.3g} px): a wrong calibration or mislabels in this camera?")
    return out


def preflight(session: Session, dense: DenseObservations) -> Preflight:
    """Measure the pixel noise, check the geometry, fill motion noise without physics (module docstring).

    Raises InputError when the geometry cannot be right. dense: the session's observations (C, F, M).
    """
    ideal_unit = ideal_observations(session.rig, dense, 1.0)
    xyz_linear = dlt_points(session.rig, ideal_unit)  # needs no noise, no sign: the geometry checks' points
    figures, warnings = _geometry(session, xyz_linear, dense.seen)
    measured, info = estimate_pixel_sigma(session.rig, ideal_unit, xyz_start=xyz_linear)
    given = _given_sigma(session)
    sigma = given if given is not None else measured
    if not np.isfinite(sigma).all():
        raise InputError(f"{_where(session)}: no point is seen by two cameras, so the pixel noise cannot be measured; "
                         f"set [noise] pixel_sigma_px in session.toml")
    noise = dict(info["cameras"])
    for c, name in enumerate(session.rig.names):
        noise[name] = dict(noise[name], used_px=float(sigma[c]))
    noise = {"source": "session.toml" if given is not None else "estimated", "cameras": noise,
             "measured_on_markers": int(len(info["markers"]))}  # of dense.markers (pixel_noise.sample_markers)
    warnings += _noise_warnings(session, measured, given)
    if session.extra_toml.get("import", {}).get("image_size") == "inferred":
        warnings.append("image sizes were guessed at import (principal point = image centre): 'outside the "
                        "image' checks and plots assume them (re-import with --image-size W H)")
    motion = session.motion
    if not motion.has_physics and (motion.sigma_m is None or motion.causal_accel_psd_m2_s3 is None):
        try:  # info's covariances are those of the measured noise: what the track really carries (sampled markers')
            sigma_m, q = noise_from_track(info["xyz_m"], info["cov_m2"], session.fps)
        except ValueError as e:  # e.g. labelled frames far apart: nothing to measure, so stay loose
            sigma_m, q = LOOSE_MOTION
            warnings.append(f"{e}: the filter and the random walk use loose motion noise (q = {q:g} m^2/s^3, "
                            f"sigma_m = {sigma_m:g} m); set [motion] sigma_m / accel_psd_m2_s3 in session.toml")
        motion = dataclasses.replace(motion, sigma_m=motion.sigma_m if motion.sigma_m is not None else sigma_m,
                                     causal_accel_psd_m2_s3=q)
        figures["motion_from_track"] = {"sigma_m": motion.sigma_m, "causal_accel_psd_m2_s3": q}
    return Preflight(sigma, noise, dataclasses.replace(session, motion=motion), warnings, figures,
                     ideal_unit.with_sigma(sigma))
