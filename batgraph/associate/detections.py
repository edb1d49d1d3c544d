"""Unlabelled detections, seed labels and the parts of a session folder that association needs, read and checked.

``detections.csv`` (or ``.parquet``): one row per blob, ``frame, camera, u, v`` and optionally ``size`` (area,
px^2) and ``score`` (a detector's confidence); u, v are raw (distorted) pixels in the OpenCV convention, as in
observations.csv. ``seed_labels.csv``: ``frame, camera, marker, u, v``, the user's clicks naming markers.
``frame`` is each camera's own frame number, as in observations.csv; a rig whose calibration.toml gives a camera
its own ``fps`` or a ``time_offset_s`` has its detections put on the session clock (batgraph.session.session_frames):
association pairs the cameras' detections by session frame.
Every problem is one :class:`batgraph.errors.InputError` naming the file, the row and the problem. This module
matches nothing and estimates nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .. import inputs
from ..camera import Rig
from ..errors import InputError
from ..session import capture_fractions, check_clock, read_calibration, session_frames

DETECTION_COLUMNS = ["frame", "camera", "u", "v"]
OPTIONAL_COLUMNS = ["size", "score"]
SEED_COLUMNS = ["frame", "camera", "marker", "u", "v"]
SNAP_PX = 5.0
"""A seed click names the detection nearest to it in its camera and frame, if that is within this many pixels
(a click lands on a blob's centre to within a few pixels; DLTdv snaps a click to its blob the same way)."""


@dataclass
class Detections:
    """Detections sorted by session frame then camera (file order within), as arrays.

    frame: (N,) int64 session frame; camera: (N,) int64 index into the rig; uv_px: (N, 2) raw pixels; size, score:
    (N,) float or None when the file has no such column; row: (N,) each detection's 0-based data row in the file;
    own_frame: (N,) int64 the file's frame (the camera's own; the same as frame for a rig on the session clock);
    time_frac: (N,) when the detection was captured, less its session frame [session frames]: what a stated
    time_offset_s leaves within a frame, plus readout_s * v / height (0 on the session clock).
    """

    frame: np.ndarray
    camera: np.ndarray
    uv_px: np.ndarray
    size: np.ndarray | None
    score: np.ndarray | None
    row: np.ndarray
    own_frame: np.ndarray
    time_frac: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def weight(self) -> np.ndarray:
        """(N,) each detection's weight in observations.csv: the score where it is in (0, 1], else 1."""
        if self.score is None:
            return np.ones(len(self.frame))
        return np.where((self.score > 0) & (self.score <= 1), self.score, 1.0)


@dataclass
class SessionSetup:
    """What association reads from session.toml: fps [Hz], [markers] names / rigid / skeleton, and
    [noise] pixel_sigma_px [px] (None: measured from the detections)."""

    fps: float
    marker_names: list[str] = field(default_factory=list)
    rigid: list[tuple[str, str]] = field(default_factory=list)
    skeleton: list[tuple[str, str]] = field(default_factory=list)
    pixel_sigma_px: float | None = None


def find_detections(folder: Path) -> Path:
    """The session's detections.csv, else detections.parquet; InputError when it has neither."""
    for name in ("detections.csv", "detections.parquet"):
        if (folder / name).exists():
            return folder / name
    raise InputError(f"{folder / 'detections.csv'}: file not found (nor detections.parquet); association needs "
                     "the unlabelled detections: frame, camera, u, v")


def read_setup(path: Path) -> SessionSetup:
    """session.toml's [session] fps, [markers] and [noise] pixel_sigma_px (the rest is the estimators' business:
    ``reconstruct`` checks it when it reads the associated session)."""
    data = inputs.read_toml(path)
    sess = data.get("session")
    if not isinstance(sess, dict) or "fps" not in sess:
        raise InputError(f"{path} [session]: missing key 'fps'")
    fps = inputs.number(sess["fps"], f"{path} [session] fps", positive=True)
    markers = data.get("markers", {})
    if not isinstance(markers, dict):
        raise InputError(f"{path}: 'markers' must be a table [markers], got {markers!r}")
    names = inputs.unique_names(markers.get("names", []), f"{path} [markers] names", "marker name")
    pairs = {}
    for key in ("rigid", "skeleton"):
        value = markers.get(key, [])
        if not isinstance(value, list) or not all(
                isinstance(e, list) and len(e) == 2 and all(isinstance(m, str) for m in e) for e in value):
            raise InputError(f"{path} [markers] {key}: expected a list of [marker, marker] pairs, got {value!r}")
        for i, (a, b) in enumerate(value):
            for m in (a, b):
                if names and m not in names:
                    raise InputError(f"{path} [markers] {key}[{i}]: marker {m!r} is not in [markers] names")
        pairs[key] = [(a, b) for a, b in value if a != b]
    noise = data.get("noise", {})
    sigma = None
    if isinstance(noise, dict) and "pixel_sigma_px" in noise:
        sigma = inputs.number(noise["pixel_sigma_px"], f"{path} [noise] pixel_sigma_px", positive=True)
    return SessionSetup(fps, list(names), pairs["rigid"], pairs["skeleton"], sigma)


def read_detections(path: Path, rig: Rig, fps: float, calibration_name: str = "calibration.toml") -> Detections:
    """Read and check detections.csv / .parquet against the rig (see module docstring); fps: the session's [Hz].

    Refused: a ``marker`` column (labelled observations belong in observations.csv), frames out of order (a
    detector writes them in order; a shuffled file is a sign of a merge gone wrong), a camera not in the rig,
    an empty or non-numeric u, v, size or score, a negative size, and the same blob listed twice.
    """
    df, is_csv = inputs.read_table(path, DETECTION_COLUMNS, "detections")
    if "marker" in df.columns:
        raise InputError(f"{path}: has a 'marker' column: these are labelled observations, not unlabelled "
                         "detections (name the file observations.csv, which reconstruct takes as it is, or drop "
                         "the column)")
    frame = inputs.frame_column(df, path, is_csv)
    back = np.flatnonzero(np.diff(frame) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise InputError(f"{path} {inputs.row_name(i, is_csv)}: frame {frame[i]} comes after frame {frame[i - 1]}; "
                         "detections must be in frame order (sort the file by frame)")
    cam = _camera_positions(df, rig, path, is_csv, calibration_name)
    u = inputs.numeric_column(df, "u", path, is_csv, allow_missing=False)
    v = inputs.numeric_column(df, "v", path, is_csv, allow_missing=False)
    extra = {}
    for col in OPTIONAL_COLUMNS:
        if col in df.columns:
            x = inputs.numeric_column(df, col, path, is_csv, allow_missing=False)
            if (x < 0).any():
                i = int(np.argmax(x < 0))
                raise InputError(f"{path} {inputs.row_name(i, is_csv)}: {col} {inputs.cell(df[col].iloc[i])} is "
                                 "negative")
            extra[col] = x
    inputs.check_frame_gaps(frame, path, is_csv)
    check_clock(rig, fps, calibration_name)
    own = frame
    frame = own if rig.on_session_clock(fps) else session_frames(own, np.asarray(rig.names)[cam], rig, fps)
    frac, _ = capture_fractions(rig, pd.DataFrame({"frame": frame, "camera_frame": own, "v": v}), cam, fps)
    order = np.lexsort((cam, frame))  # stable: file order within a frame and camera
    key = np.stack([frame, cam, u, v], axis=1)[order]
    dup = np.flatnonzero((key[1:] == key[:-1]).all(axis=1))
    if len(dup):
        a, b = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
        raise InputError(f"{path} {inputs.row_name(a, is_csv)} and {inputs.row_name(b, is_csv)}: the same detection "
                         f"twice (frame {frame[a]}, camera {rig.names[cam[a]]!r}, u {u[a]!r}, v {v[a]!r})")
    return Detections(frame[order], cam[order], np.stack([u, v], axis=1)[order],
                      extra["size"][order] if "size" in extra else None,
                      extra["score"][order] if "score" in extra else None, order, own[order],
                      frac[order])


def read_seed(path: Path, rig: Rig, fps: float, detections: Detections, marker_names: list[str]) -> pd.DataFrame:
    """Read seed_labels.csv (frames: the cameras' own) and snap every click to its detection: a table ``detection,
    marker, row``.

    detection: index into ``detections``; marker: the name clicked; row: the click's 0-based data row.
    Refused: a marker not in ``marker_names`` (when session.toml names its markers), a camera not in the rig,
    a click with no detection within :data:`SNAP_PX` in its camera and frame, a marker clicked twice in one
    camera and frame, and two markers on one detection.
    """
    df, is_csv = inputs.read_table(path, SEED_COLUMNS, "seed labels")
    frame = inputs.frame_column(df, path, is_csv)
    cam = _camera_positions(df, rig, path, is_csv, "the rig")
    marker = inputs.label_codes(df, "marker", path, is_csv)
    k = frame if rig.on_session_clock(fps) else session_frames(frame, np.asarray(rig.names)[cam], rig, fps)
    names = marker.names[marker.codes]
    if marker_names:
        unknown = ~np.isin(names, marker_names)
        if unknown.any():
            i = int(np.argmax(unknown))
            raise InputError(f"{path} {inputs.row_name(i, is_csv)}: marker {names[i]!r} is not in session.toml "
                             f"[markers] names ({', '.join(marker_names)})")
    u = inputs.numeric_column(df, "u", path, is_csv, allow_missing=False)
    v = inputs.numeric_column(df, "v", path, is_csv, allow_missing=False)
    det = np.full(len(df), -1, np.int64)
    for i in range(len(df)):
        lo, hi = np.searchsorted(detections.frame, [k[i], k[i] + 1])
        pool = lo + np.flatnonzero(detections.camera[lo:hi] == cam[i])
        if len(pool):
            d = np.hypot(*(detections.uv_px[pool] - [u[i], v[i]]).T)
            if d.min() <= SNAP_PX:
                det[i] = pool[int(np.argmin(d))]
        if det[i] < 0:
            raise InputError(f"{path} {inputs.row_name(i, is_csv)}: no detection within {SNAP_PX:g} px of ({u[i]:g}, "
                             f"{v[i]:g}) in camera {rig.names[cam[i]]!r} on frame {frame[i]}")
    _check_unique(path, is_csv, det, names, frame, cam, rig)
    return pd.DataFrame({"detection": det, "marker": names.astype(str), "row": np.arange(len(df))})


def _check_unique(path, is_csv, det, names, frame, cam, rig) -> None:
    """InputError for two markers on one detection, or one marker on two detections of a camera and frame."""
    by_det: dict[int, int] = {}
    by_key: dict[tuple, int] = {}
    for i in range(len(det)):
        a = by_det.setdefault(int(det[i]), i)
        if names[a] != names[i]:
            raise InputError(f"{path} {inputs.row_name(a, is_csv)} and {inputs.row_name(i, is_csv)}: markers "
                             f"{names[a]!r} and {names[i]!r} snap to the same detection (camera "
                             f"{rig.names[cam[i]]!r}, frame {frame[i]})")
        a = by_key.setdefault((names[i], int(frame[i]), int(cam[i])), i)
        if det[a] != det[i]:
            raise InputError(f"{path} {inputs.row_name(a, is_csv)} and {inputs.row_name(i, is_csv)}: marker "
                             f"{names[i]!r} is clicked twice in camera {rig.names[cam[i]]!r} on frame {frame[i]}")


def read_inputs(folder: Path, calibration: Path | None = None) -> tuple[SessionSetup, Rig, Detections, Path]:
    """session.toml, calibration.toml (or ``calibration``) and the detections of a session folder."""
    if not folder.is_dir():
        raise InputError(f"{folder}: session folder not found" if not folder.exists() else
                         f"{folder}: not a folder (a session is a folder holding session.toml, ...)")
    setup = read_setup(folder / "session.toml")
    cal = calibration if calibration is not None else folder / "calibration.toml"
    rig = read_calibration(cal)
    path = find_detections(folder)
    return setup, rig, read_detections(path, rig, setup.fps, cal.name), path


def _camera_positions(df, rig, path, is_csv: bool, rig_name: str) -> np.ndarray:
    """Each row's camera as its position in ``rig`` (n,); InputError naming the first row whose camera the rig
    (called ``rig_name`` in the message) does not have."""
    camera = inputs.label_codes(df, "camera", path, is_csv)
    cam = camera.positions(rig.names)
    if (cam < 0).any():
        i = int(np.argmax(cam < 0))
        raise InputError(f"{path} {inputs.row_name(i, is_csv)}: camera {camera.names[camera.codes[i]]!r} is not in "
                         f"{rig_name} (cameras: {', '.join(rig.names)})")
    return cam
