"""Camera time offsets written by DLTdv and Argus, as batgraph's timing (``time_offset_s`` in calibration.toml).

Three files, told apart by their header:

* DLTdv8 ``*offsets.csv``: ``cam1_offset, ..., camN_offset``, one row per xypts row: row r's clicks of camera c
  are of its video frame ``round(r + offset)`` (0-based, MATLAB's round; may be non-integer; 0 = not set).
* Argus clicker ``*-offsets.csv``: ``camera_1, ..., camera_N``, one row per frame: row r shows the camera's
  video frame ``r + offset`` (integers; NaN allowed).
* Argus sync ``*_offsets.csv``: ``Filename, seconds_offset, frames_offset, max_correlation``, one row per camera
  (the first 0): ``frames_offset`` d > 0 means the same sound comes d frames later in this camera's video.

All three mean: camera c's video frame ``r + offset`` shows the instant of the first camera's frame r, so its
frame j is exposed at ``(j - offset) / fps``: ``time_offset_s = -offset / fps`` (``-seconds_offset`` for the
sync file). docs/timing.md gives the sources; tests/test_offsets.py checks a synthetic audio delay.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputError
from ..inputs import read_csv

SAME_OFFSET = 1e-6  # [frames]: a camera's offsets in a per-row file that differ by more are different offsets


@dataclass
class Offsets:
    """A file's offsets per camera.

    kind: "dltdv", "argus-clicker" or "argus-sync". frames: (C,) offset [frames] of each camera (the sign above).
    seconds: (C,) [s] (the sync file's own seconds), or None. per_row: whether the file says which video frame each
    row of the clicks shows (the DLTdv and Argus clicker files; the sync file does not).
    """

    kind: str
    frames: np.ndarray
    seconds: np.ndarray | None
    per_row: bool
    n_rows: int

    def video_frames(self, row: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """The 0-based video frame (N,) int64 that row ``row`` (N,) of the clicks shows in camera ``camera`` (N,)."""
        x = np.asarray(row, float) + self.frames[np.asarray(camera)]
        if self.kind == "dltdv":  # MATLAB round: a half away from zero
            return (np.sign(x) * np.floor(np.abs(x) + 0.5)).astype(np.int64)
        return np.round(x).astype(np.int64)

    def time_offsets_s(self, fps: float) -> np.ndarray:
        """batgraph's time_offset_s (C,) [s]: -offset / fps (the sync file: -seconds_offset)."""
        return -self.seconds if self.seconds is not None else -self.frames / float(fps)


def read_offsets(path: str | Path, n_cams: int | None = None) -> Offsets:
    """Read a DLTdv8, Argus clicker or Argus sync offsets file (module docstring); InputError naming the file,
    line and column for bad input. n_cams: the cameras expected (None: any)."""
    path = Path(path)
    df = read_csv(path, header=True, what="camera offsets (DLTdv8 *offsets.csv, Argus *-offsets.csv or *_offsets.csv)")
    cols = [str(c).strip() for c in df.columns]
    if [c.lower() for c in cols[:3]] == ["filename", "seconds_offset", "frames_offset"]:
        return _sync(path, df, n_cams)
    lower = [c.lower() for c in cols]
    if all(c == f"cam{i + 1}_offset" for i, c in enumerate(lower)):
        kind = "dltdv"
    elif all(c == f"camera_{i + 1}" for i, c in enumerate(lower)):
        kind = "argus-clicker"
    else:
        raise InputError(f"{path} line 1: expected the columns cam1_offset, cam2_offset, ... (DLTdv8), camera_1, "
                         f"camera_2, ... (Argus clicker) or Filename, seconds_offset, frames_offset, max_correlation "
                         f"(Argus sync), got {', '.join(cols)}")
    if n_cams is not None and len(cols) != n_cams:
        raise InputError(f"{path} line 1: {len(cols)} camera(s) but {n_cams} expected")
    values = _numbers(path, df)
    frames = np.zeros(len(cols))
    for c in range(len(cols)):
        v = values[:, c]
        set_ = np.isfinite(v) & (v != 0)  # 0 = not set (DLTdv's sparse convention): the offset is the rest
        if set_.any():
            first = int(np.argmax(set_))
            other = set_ & (np.abs(v - v[first]) > SAME_OFFSET)
            if other.any():
                k = int(np.argmax(other))
                raise InputError(f"{path} lines {first + 2} and {k + 2}, {cols[c]}: the offset changes from "
                                 f"{v[first]:g} to {v[k]:g}; batgraph takes one offset per camera (set the one that "
                                 f"holds in every row)")
            frames[c] = v[first]
    return Offsets(kind, frames, None, True, len(values))


def _numbers(path: Path, df) -> np.ndarray:
    """Every cell as a float (R, C); NaN / empty allowed; InputError naming line and column otherwise."""
    text = pd.DataFrame(df).astype(str).apply(lambda col: col.str.strip())
    missing = text.apply(lambda col: col.str.lower().isin(["", "nan", "na"])).to_numpy()
    values = text.mask(missing).apply(pd.to_numeric, errors="coerce").to_numpy(float)
    bad = (~missing & ~np.isfinite(values))
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(f"{path} line {i + 2}, {df.columns[j]}: {text.iat[i, j]!r} is not a finite number")
    return values


def _sync(path: Path, df, n_cams: int | None) -> Offsets:
    """Argus's sync table: one row per camera (module docstring)."""
    if n_cams is not None and len(df) != n_cams:
        raise InputError(f"{path}: {len(df)} camera row(s) but {n_cams} expected (one per camera, in the clicks' "
                         f"camera order)")
    values = _numbers(path, df[df.columns[1:3]])
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(f"{path} line {i + 2}, {df.columns[1 + j]}: an offset is required")
    return Offsets("argus-sync", values[:, 1], values[:, 0], False, len(values))
