"""An Anipose session folder (pose-2d/<trial>-cam<X>.h5 from DeepLabCut + calibration/calibration.toml)
-> a batgraph session; the 2D files are read by :mod:`batgraph.formats.deeplabcut`.

Anipose lays a session out as ``<session>/pose-2d/*.h5`` (one DeepLabCut file per camera and trial)
and ``<session>/calibration/calibration.toml``, with its ``config.toml`` in the session folder or a
parent (the ``nesting`` levels). As Anipose does, the camera name is the first group of
``cam_regex`` searched in a file's name without extension, and the trial name is the file name with
that match removed. ``cam_regex`` and the likelihood threshold come from config.toml
(``[triangulation] cam_regex``, ``score_threshold``) when not given, else Anipose's tutorial
defaults ``-cam([A-Z])$`` and 0.8. The folder names ``pose-2d`` and ``calibration`` follow
``[pipeline] pose_2d`` and ``calibration_results`` when config.toml sets them. The lines Anipose draws between
body parts (``[labeling] scheme``: lists of body parts, each drawn as a chain) become the session's skeleton.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import InputError
from ..inputs import number, read_toml
from ..session import Session
from .deeplabcut import import_deeplabcut

DEFAULT_CAM_REGEX = "-cam([A-Z])$"
DEFAULT_SCORE_THRESHOLD = 0.8


def _find_config(folder: Path, levels: int = 4) -> dict:
    """Anipose's config.toml in ``folder`` or up to ``levels`` parents; {} when there is none."""
    for d in [folder, *list(folder.parents)[:levels]]:
        path = d / "config.toml"
        if path.is_file():
            cfg = read_toml(path)
            for table in ("pipeline", "triangulation", "labeling"):
                if not isinstance(cfg.get(table, {}), dict):
                    raise InputError(f"{path}: '{table}' must be a table [{table}]")
            if "score_threshold" in cfg.get("triangulation", {}):
                x = number(cfg["triangulation"]["score_threshold"], f"{path} [triangulation] score_threshold")
                if not 0 <= x <= 1:
                    raise InputError(f"{path} [triangulation] score_threshold: must be in [0, 1], got {x!r}")
            if not isinstance(cfg.get("triangulation", {}).get("cam_regex", ""), str):
                raise InputError(f"{path} [triangulation] cam_regex: expected a string")
            _scheme(cfg, path)
            return cfg
    return {}


def _scheme(cfg: dict, path: Path | None = None) -> list[tuple[str, str]]:
    """Anipose's ``[labeling] scheme`` (lists of body parts, each a chain) as pairs of neighbours in a chain."""
    scheme = cfg.get("labeling", {}).get("scheme", [])
    if not isinstance(scheme, list) or not all(isinstance(c, list) and all(isinstance(b, str) for b in c)
                                               for c in scheme):
        raise InputError(f"{path} [labeling] scheme: expected lists of body part names, got {scheme!r}")
    return list(dict.fromkeys((a, b) for chain in scheme for a, b in zip(chain[:-1], chain[1:], strict=True)
                              if a != b))


def anipose_trials(pose_dir: Path, cam_regex: str) -> dict[str, dict[str, Path]]:
    """{trial: {camera: file}} for the .h5/.csv files of an Anipose pose-2d folder."""
    try:
        rx = re.compile(cam_regex)
    except re.error as e:
        raise InputError(f"cam_regex {cam_regex!r}: not a regular expression ({e})") from None
    files = sorted(p for p in pose_dir.iterdir() if p.suffix.lower() in (".h5", ".csv"))
    if not files:
        raise InputError(f"{pose_dir}: no .h5 or .csv files")
    trials: dict[str, dict[str, Path]] = {}
    for p in files:
        m = rx.search(p.stem)
        if not m or not m.groups():
            raise InputError(f"{p}: cam_regex {cam_regex!r} finds no camera name in the file name")
        cam, trial = m.groups()[0].strip(), rx.sub("", p.stem).strip()
        if cam in trials.setdefault(trial, {}):
            raise InputError(f"{p}: camera {cam!r} of trial {trial!r} already given by {trials[trial][cam]}")
        trials[trial][cam] = p
    return trials


def import_anipose(project: str | Path, fps: float, out: str | Path | None, calibration: str | Path | None = None,
                   threshold: float | None = None, trial: str | None = None,
                   cam_regex: str | None = None, units: str | None = None) -> Session:
    """Import one trial of an Anipose session folder (or of a pose-2d folder) into a session.

    project: the session folder holding pose-2d/ (and calibration/calibration.toml), or the pose-2d
        folder itself. calibration: calibration.toml; None = <session>/calibration/calibration.toml.
    fps: frame rate [Hz]. threshold: minimum likelihood kept (None = config or 0.8).
    trial: which trial when pose-2d holds several. cam_regex: None = config or ``-cam([A-Z])$``.
    units: the calibration's translation units (Anipose calibrates in the board's units, often mm).
    """
    folder = Path(project)
    if not folder.is_dir():
        raise InputError(f"{folder}: folder not found")
    cfg = _find_config(folder)
    pipeline, tri = cfg.get("pipeline", {}), cfg.get("triangulation", {})
    pose_name = str(pipeline.get("pose_2d", "pose-2d"))
    if (folder / pose_name).is_dir():
        session_dir, pose_dir = folder, folder / pose_name
    else:
        session_dir, pose_dir = folder.parent, folder
    cam_regex = cam_regex if cam_regex is not None else str(tri.get("cam_regex", DEFAULT_CAM_REGEX))
    if threshold is None:
        threshold = float(tri.get("score_threshold", DEFAULT_SCORE_THRESHOLD))
    trials = anipose_trials(pose_dir, cam_regex)
    if trial is None:
        if len(trials) > 1:
            raise InputError(f"{pose_dir}: several trials ({', '.join(sorted(trials))}); pass trial=")
        trial = next(iter(trials))
    if trial not in trials:
        raise InputError(f"{pose_dir}: trial {trial!r} not found (trials: {', '.join(sorted(trials))})")
    if calibration is None:
        calibration = session_dir / str(pipeline.get("calibration_results", "calibration")) / "calibration.toml"
        if not Path(calibration).is_file():
            raise InputError(f"{calibration}: file not found (Anipose's calibration; pass calibration=)")
    cams = trials[trial]
    return import_deeplabcut(list(cams.values()), calibration, fps, out, camera_names=list(cams),
                             threshold=threshold, name=trial or session_dir.name, units=units, skeleton=_scheme(cfg))
