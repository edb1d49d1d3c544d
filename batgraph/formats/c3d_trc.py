"""One method's trajectories table -> C3D (biomechanics readers) and TRC (OpenSim) files, and a TRC reader.

Input is the ``trajectories`` table of CONTRACT.md section 3 (metres, world frame, NaN xyz where a
method has no estimate). The world frame is written as it is: no axis swap (OpenSim's Y-up is the
user's business, as it is for Pose2Sim's files, see :func:`read_trc`). Frame ``k`` of a session is at
time ``k / fps``; C3D and TRC count frames from 1, so session frame ``k`` is file frame ``k + 1``.
This module does not estimate, filter or fill anything: a missing point stays missing.

C3D (written with ezc3d, 32-bit float data):

* ``POINT:UNITS = "mm"``: C3D readers (Mokka, Visual3D, OpenSim's C3D adapter) assume millimetres,
  so coordinates are metres x 1000.
* ``POINT:LABELS`` = marker names; ``POINT:RATE`` = fps; header first frame = first session frame.
* Residual of a point = ``sqrt(trace(cov) / 3)`` in mm, the RMS of the three per-axis standard
  deviations. C3D stores it as an 8-bit count of ``|POINT:SCALE|`` mm (the spec's float format:
  low byte of the 4th word), so it is quantised to :data:`C3D_RESIDUAL_STEP_MM` and saturates at
  255 steps (25.5 mm): a quality flag for C3D tools. The full covariance is in trajectories.csv.
  A point with an estimate but no covariance gets residual 0 (C3D: "computed, no residual").
* A missing point has coordinates 0 and residual -1, the C3D convention for "invalid"; ezc3d and
  other readers give NaN for it.

TRC (tab-separated text, the OpenSim marker format): header ``PathFileType 4 (X/Y/Z)``, then
DataRate, CameraRate, NumFrames, NumMarkers, Units, OrigDataRate, OrigDataStartFrame, OrigNumFrames,
then ``Frame#  Time  name1 . .  name2 ...`` and ``X1 Y1 Z1 X2 ...``. Units are metres by default
(``units="mm"`` writes millimetres); a missing point is three empty cells.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import ezc3d
import numpy as np
import pandas as pd

from ..atomic import atomic_path, write_text
from ..errors import InputError

C3D_RESIDUAL_STEP_MM = 0.1
"""Resolution of the C3D residual [mm] (|POINT:SCALE|); the largest storable residual is 255 steps."""

_UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass
class DenseTrajectories:
    """One method's trajectories as arrays.

    frames: session frame indices, contiguous, shape (F,).
    markers: names along M.
    xyz_m: positions, shape (F, M, 3) [m, world]; NaN where no estimate.
    cov_m2: covariances, shape (F, M, 3, 3) [m^2]; NaN where none.
    """

    frames: np.ndarray
    markers: list[str]
    xyz_m: np.ndarray
    cov_m2: np.ndarray


def dense_trajectories(trajectories: pd.DataFrame, markers: list[str] | None = None,
                       method: str | None = None) -> DenseTrajectories:
    """Scatter one method's rows of a trajectories table into (F, M) arrays.

    trajectories: CONTRACT.md section 3 columns (``method`` optional; ``cov_*`` optional).
    markers: output order; None = order of first appearance. Markers not in the table stay NaN.
    method: which method to keep; None requires the table to hold a single method.
    The frame axis runs contiguously from the first to the last frame of the table.
    """
    t = trajectories
    if "method" in t.columns:
        methods = list(dict.fromkeys(t["method"]))
        if method is None and len(methods) > 1:
            raise ValueError(f"trajectories hold several methods {methods}; pass method=")
        if method is not None:
            t = t[t["method"] == method]
    if len(t) == 0:
        raise ValueError(f"no trajectories{f' for method {method!r}' if method else ''}")
    names = list(markers) if markers is not None else list(dict.fromkeys(t["marker"].astype(str)))
    t = t[t["marker"].astype(str).isin(names)]
    frame = t["frame"].to_numpy(np.int64)
    frames = np.arange(frame.min(), frame.max() + 1)
    fi = frame - frames[0]
    mi = t["marker"].astype(str).map({n: i for i, n in enumerate(names)}).to_numpy()
    F, M = len(frames), len(names)
    xyz = np.full((F, M, 3), np.nan)
    xyz[fi, mi] = t[["x", "y", "z"]].to_numpy(float)
    cov = np.full((F, M, 3, 3), np.nan)
    cols = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]
    if all(c in t.columns for c in cols):
        c6 = t[cols].to_numpy(float)
        iu = np.triu_indices(3)
        block = np.empty((len(t), 3, 3))
        block[:, iu[0], iu[1]] = c6
        block[:, iu[1], iu[0]] = c6
        cov[fi, mi] = block
    return DenseTrajectories(frames, names, xyz, cov)


def c3d_residual_mm(cov_m2: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The C3D residual written for each point, shape (...) [mm].

    cov_m2: covariances (..., 3, 3) [m^2]; valid: bool (...), True where the point has an estimate.
    Returns ``sqrt(trace / 3)`` in mm, quantised to :data:`C3D_RESIDUAL_STEP_MM`, at least one step
    and at most 255 steps; 0 where valid without a finite covariance; -1 where not valid.
    """
    rms_mm = np.sqrt(np.trace(cov_m2, axis1=-2, axis2=-1) / 3.0) * 1e3
    step = C3D_RESIDUAL_STEP_MM
    q = np.clip(np.round(rms_mm / step), 1, 255) * step
    return np.where(valid, np.where(np.isfinite(rms_mm), q, 0.0), -1.0)


def write_c3d(path: str | Path, trajectories: pd.DataFrame, fps: float, markers: list[str] | None = None,
              method: str | None = None) -> Path:
    """Write one method's trajectories to a C3D file (mm, see the module docstring). Atomic.

    path: output ``.c3d``; trajectories: CONTRACT.md section 3 table [m]; fps: frame rate [Hz];
    markers: label order (None = order in the table); method: see :func:`dense_trajectories`.
    """
    d = dense_trajectories(trajectories, markers, method)
    valid = np.isfinite(d.xyz_m).all(axis=-1)  # (F, M)
    F, M = valid.shape
    pts = np.zeros((4, M, F))
    pts[:3] = np.where(valid[..., None], d.xyz_m * 1e3, 0.0).transpose(2, 1, 0)
    pts[3] = 1.0
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(d.markers)
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = tuple(
        "batgraph; residual = RMS of per-axis std [mm]" for _ in d.markers)
    # negative scale = float data; its magnitude is the residual's unit (C3D spec)
    c["parameters"]["POINT"]["SCALE"]["value"] = [-C3D_RESIDUAL_STEP_MM]
    c.add_parameter("POINT", "UNITS", "mm")
    c["header"]["points"]["first_frame"] = int(d.frames[0])
    c["data"]["points"] = pts
    res = c3d_residual_mm(d.cov_m2, valid)
    # the file holds residual / |scale| as an integer and ezc3d truncates: a quarter step up makes
    # truncation and rounding both land on the intended count
    res = np.where(res > 0, res + C3D_RESIDUAL_STEP_MM / 4, res)
    c["data"]["meta_points"]["residuals"] = res.T[None]
    path = Path(path)
    with atomic_path(path) as tmp:
        c.write(str(tmp))
    return path


def _fmt(values: np.ndarray, fmt: str) -> np.ndarray:
    """Numbers -> strings, NaN -> '' (TRC's missing cell)."""
    out = np.char.mod(fmt, np.nan_to_num(values))
    return np.where(np.isfinite(values), out, "")


def write_trc(path: str | Path, trajectories: pd.DataFrame, fps: float, markers: list[str] | None = None,
              method: str | None = None, units: str = "m") -> Path:
    """Write one method's trajectories to an OpenSim TRC file (see the module docstring). Atomic.

    units: "m" (default, the table's own unit) or "mm". Frame# = session frame + 1, Time = frame / fps.
    """
    if units not in ("m", "mm"):
        raise ValueError(f"units must be 'm' or 'mm', got {units!r}")
    d = dense_trajectories(trajectories, markers, method)
    F, M = d.xyz_m.shape[:2]
    scale = 1.0 if units == "m" else 1e3
    first = int(d.frames[0]) + 1
    rate = f"{float(fps):g}"
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{F}\t{M}\t{units}\t{rate}\t{first}\t{F}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in d.markers),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)),
        "",  # OpenSim's own TRC files have a blank line before the data
    ]
    cells = np.concatenate([
        np.char.mod("%d", d.frames[:, None] + 1),
        np.char.mod("%.10g", d.frames[:, None] / float(fps)),
        _fmt(d.xyz_m.reshape(F, 3 * M) * scale, "%.10g"),
    ], axis=1)
    body = "\n".join("\t".join(row) for row in cells)
    write_text(path, "\n".join(lines) + "\n" + body + "\n")
    return Path(path)


@dataclass
class Trc:
    """A TRC file's content, in metres.

    markers: names along M; frame: the file's Frame# column, shape (F,); time_s: Time, shape (F,).
    xyz_m: positions in the file's own axes, shape (F, M, 3) [m]; NaN where a cell is empty.
    rate_hz: DataRate; units: the file's Units ("m", "mm" or "cm").
    """

    markers: list[str]
    frame: np.ndarray
    time_s: np.ndarray
    xyz_m: np.ndarray
    rate_hz: float
    units: str


def read_trc(path: str | Path) -> Trc:
    """Read a TRC file (ours, Pose2Sim's, OpenSim's); coordinates are converted to metres.

    Axes are kept as in the file. Pose2Sim writes Y-up files: its world (Z-up, the calibration's
    frame) is ``xyz_world = xyz_trc[..., [2, 0, 1]]``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise InputError(f"{path} line 1: not a TRC file (expected 'PathFileType')")
    keys = [k.strip() for k in lines[1].split("\t")]
    vals = [v.strip() for v in lines[2].split("\t")]
    head = dict(zip(keys, vals, strict=False))
    for k in ("DataRate", "NumMarkers", "Units"):
        if k not in head:
            raise InputError(f"{path} line 2: missing header key '{k}'")
    units = head["Units"].lower()
    if units not in _UNIT_TO_M:
        raise InputError(f"{path} line 3: Units {head['Units']!r} is not one of m, mm, cm")
    try:
        rate, n_markers = float(head["DataRate"]), int(head["NumMarkers"])
    except ValueError:
        raise InputError(f"{path} line 3: DataRate or NumMarkers is not a number") from None
    names_row = lines[3].split("\t")
    if names_row[:2] != ["Frame#", "Time"]:
        raise InputError(f"{path} line 4: expected 'Frame#<TAB>Time<TAB>marker names'")
    markers = [n.strip() for n in names_row[2:] if n.strip()]
    if len(markers) != n_markers:
        raise InputError(f"{path} line 4: {len(markers)} marker names but NumMarkers = {n_markers}")
    rows, line_no = [], []
    for i, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        cells = line.split("\t")
        if len(cells) > 2 + 3 * n_markers:
            raise InputError(f"{path} line {i}: {len(cells)} cells, more than 2 + 3 x {n_markers}")
        rows.append(cells + [""] * (2 + 3 * n_markers - len(cells)))
        line_no.append(i)
    if not rows:
        raise InputError(f"{path}: no data rows")
    table = pd.DataFrame(rows)
    num = table.apply(lambda col: pd.to_numeric(col.str.strip().replace("", np.nan), errors="coerce"))
    bad = num.isna().to_numpy() & (table.apply(lambda col: col.str.strip()) != "").to_numpy()
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"{path} line {line_no[r]}, column {c + 1}: {table.iat[r, c]!r} is not a number")
    arr = num.to_numpy(float)
    if np.isnan(arr[:, :2]).any():
        r = int(np.argmax(np.isnan(arr[:, :2]).any(axis=1)))
        raise InputError(f"{path} line {line_no[r]}: Frame# or Time is empty")
    F = len(arr)
    xyz = arr[:, 2:].reshape(F, n_markers, 3) * _UNIT_TO_M[units]
    return Trc(markers, arr[:, 0].astype(np.int64), arr[:, 1], xyz, rate, units)
