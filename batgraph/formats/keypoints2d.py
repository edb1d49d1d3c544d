"""Shared by the 2D keypoint importers (DeepLabCut, Anipose, Pose2Sim): files -> calibration cameras, and
per-camera keypoint arrays -> a validated :class:`batgraph.session.Session`; no file format is read here.

Camera matching rule (used when the caller gives no camera names): a file or folder name matches the
calibration camera ``name`` when, after splitting the name (without extension) into alphanumeric
tokens (separators: anything else, e.g. ``-``, ``_``, ``.``, space) and lower-casing, a run of
consecutive tokens joined together equals ``name`` with its separators removed, or equals ``"cam"``
followed by it. So ``cam01_json`` matches ``cam_01``, ``trial3-camA.h5`` matches ``A`` and ``camA``,
``left_video.csv`` matches ``left``. DeepLabCut's scorer suffix (``DLC_`` and what follows, written right
after the video's name: ``cam1DLC_resnet50_....h5``) is left out first. Exactly one camera must match each
file, and each camera at most one file.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from ..camera import Rig
from ..errors import InputError
from ..geometry.dlt import UNITS_M
from ..session import Session, read_calibration, write_session


def _norm(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def _matches(label: str, camera: str) -> bool:
    tokens = [t for t in re.split(r"[^0-9a-z]+", label.lower()) if t]
    target = _norm(camera)
    runs = {"".join(tokens[i:j]) for i in range(len(tokens)) for j in range(i + 1, len(tokens) + 1)}
    return bool(target) and (target in runs or "cam" + target in runs)


def match_cameras(paths: list[Path], rig: Rig, camera_names: list[str] | None, calibration: Path) -> list[str]:
    """The calibration camera of each input file or folder (module docstring's rule, or ``camera_names``).

    paths: one file/folder per camera; camera_names: explicit names in the same order, or None.
    Raises InputError on a count mismatch, an unknown, unmatched, ambiguous or repeated camera.
    """
    if len(paths) != len(rig):
        raise InputError(f"{calibration}: {len(rig)} cameras ({', '.join(rig.names)}) but {len(paths)} "
                         f"input files/folders were given; give one per camera")
    if camera_names is not None:
        names = [str(n) for n in camera_names]
        if len(names) != len(paths):
            raise InputError(f"camera_names: {len(names)} names for {len(paths)} input files")
        for p, n in zip(paths, names, strict=True):
            if n not in rig.names:
                raise InputError(f"{p}: camera {n!r} is not in {calibration} (cameras: {', '.join(rig.names)})")
    else:
        names = []
        for p in paths:
            label = p.name if p.is_dir() else p.stem
            label = label.split("DLC_")[0] or label  # DeepLabCut appends its scorer: cam1DLC_resnet50_...
            hits = [c for c in rig.names if _matches(label, c)]
            if len(hits) != 1:
                why = "matches no" if not hits else f"matches several ({', '.join(hits)}) of the"
                raise InputError(f"{p}: the name {why} calibration cameras in {calibration} "
                                 f"({', '.join(rig.names)}); pass camera_names")
            names.append(hits[0])
    seen: dict[str, Path] = {}
    for p, n in zip(paths, names, strict=True):
        if n in seen:
            raise InputError(f"{p}: camera {n!r} is already given by {seen[n]}")
        seen[n] = p
    return names


def check_fps(fps: float) -> float:
    """fps as a float > 0, or InputError."""
    try:
        x = float(fps)
    except (TypeError, ValueError):
        raise InputError(f"fps: expected a number, got {fps!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise InputError(f"fps: must be > 0, got {fps!r}")
    return x


def load_rig(calibration: str | Path, units: str | None = None) -> tuple[Path, Rig]:
    """Read an aniposelib-format calibration.toml (Anipose's, Pose2Sim's Calib_*.toml), in metres.

    units: the calibration's translation units ("m", "cm", "mm"); None = its ``[metadata] units`` or metres.
    """
    path = Path(calibration)
    if units is not None and units not in UNITS_M:
        raise InputError(f"units must be one of {', '.join(UNITS_M)}, got {units!r}")
    return path, read_calibration(path, units)


def observations_from_arrays(camera: str, frames: np.ndarray, markers: list[str], uv_px: np.ndarray,
                             confidence: np.ndarray, threshold: float) -> pd.DataFrame:
    """One camera's keypoints -> long observation rows (the columns of observations.csv).

    frames: frame indices, shape (F,); markers: names along M.
    uv_px: raw pixels (OpenCV convention), shape (F, M, 2), NaN where not detected.
    confidence: detector score, shape (F, M). A point is kept when its score is >= ``threshold``
    and > 0 (a zero score is "not detected" in OpenPose and DeepLabCut); weight = min(score, 1).
    """
    F, M = confidence.shape
    keep = np.isfinite(uv_px).all(axis=-1) & np.isfinite(confidence) & (confidence >= threshold) & (confidence > 0)
    fi, mi = np.nonzero(keep)
    return pd.DataFrame({
        "frame": np.asarray(frames, np.int64)[fi], "camera": camera, "marker": np.asarray(markers, object)[mi],
        "u": uv_px[fi, mi, 0], "v": uv_px[fi, mi, 1], "weight": np.minimum(confidence[fi, mi], 1.0),
    })


def make_session(name: str, fps: float, rig: Rig, tables: list[pd.DataFrame], markers: list[str],
                 out: str | Path | None, source: str, reference: pd.DataFrame | None = None,
                 pixel_sigma_px: float | None = None, skeleton: list[tuple[str, str]] | None = None) -> Session:
    """Assemble and (if ``out``) write a session from per-camera observation tables.

    reference: another tool's 3D (frame, marker, x, y, z [m]) to keep as reference_xyz.csv.
    skeleton: bones (marker name pairs) for session.toml; those with a marker never observed are left out.

    markers: the source's keypoint order (becomes session.toml [markers] names).
    source: what was imported (for the error message when nothing is left).
    pixel_sigma_px: detection noise [px]; None (default): reconstruct measures it per camera.
    """
    obs = pd.concat(tables, ignore_index=True)
    if len(obs) == 0:
        raise InputError(f"{source}: no detection at or above the likelihood threshold")
    obs = obs.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True)
    n_out = 0
    for cam in rig:
        sel = (obs["camera"] == cam.name).to_numpy()
        n_out += int((~cam.in_image(obs.loc[sel, ["u", "v"]].to_numpy(float))).sum())
    warnings = [f"{source}: {n_out} detection(s) lie outside their camera's image; kept"] if n_out else []
    seen = set(obs["marker"])
    session = Session(name=name, fps=fps, rig=rig, observations=obs,
                      marker_names=[m for m in markers if m in seen], warnings=warnings, reference=reference,
                      pixel_sigma_px=pixel_sigma_px,
                      skeleton=[(a, b) for a, b in skeleton or [] if a in seen and b in seen])
    if out is not None:
        session.path = write_session(session, out)
    return session
