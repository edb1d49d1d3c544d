"""One method's trajectories table -> C3D (biomechanics readers), TRC (OpenSim) and analysis tables; a TRC reader.

Input: a table with trajectories.csv's columns (metres, world frame, NaN xyz where the method has no estimate),
written as it is (no axis swap, no filling: a missing point stays missing). Session frame ``k`` is at time
``k / fps`` and is file frame ``k + 1`` (C3D and TRC count from 1); both hold one take (:func:`one_take`, the
longest by default). :func:`keep_range` applies the range to every writer: "span" (default: each marker's
first to last frame with >= 2 views; the extrapolated track ends are missing), "observed" (>= 2 views that
frame) or "all"; a table without ``span`` or ``status`` gets them from n_views.
C3D: float format in millimetres; a point's 4th word holds its residual (the RMS of its three standard
deviations, in steps of |POINT:SCALE|, :func:`c3d_point_scale_mm`) and its camera mask, written by ezc3d and
rewritten here because ezc3d swaps the two bytes (pyomeca/ezc3d#386). TRC: metres by default, ``NaN`` for a
missing point (OpenSim drops a row's trailing empty cells). Analysis table (:func:`analysis_table`): long
format, one row per method, frame and marker, with per-axis standard deviations ``sd_*`` and correlations
``r_*`` (NaN where a standard deviation is 0). docs/formats.md describes every field of each format.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import ezc3d
import numpy as np
import pandas as pd

from ..atomic import atomic_path, write_text
from ..errors import InputError
from ..evaluate import add_span, dense_from_table, status_of, take_of
from .csv_text import write_csv

RANGES = ("span", "observed", "all")
"""Values of ``keep`` / ``--range``; the first is the default."""

C3D_RESIDUAL_STEP_MM = 0.1
"""The smallest |POINT:SCALE| [mm], the finest residual step; see :func:`c3d_point_scale_mm`."""

C3D_MAX_CAMERAS = 7
"""Cameras a C3D camera mask can name (the high byte's 8th bit is the sign of "invalid")."""

_UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}
_COV_COLS = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]


def keep_range(trajectories: pd.DataFrame, keep: str = "span") -> pd.DataFrame:
    """The table with positions and covariances outside the range set to NaN (see the module docstring).

    keep: "span" (span == inside), "observed" (status == observed) or "all" (unchanged).
    Adds ``status`` / ``span`` from n_views where the table lacks them. Rows are kept, in order.
    """
    if keep not in RANGES:
        raise ValueError(f"keep must be one of {', '.join(RANGES)}; got {keep!r}")
    t = trajectories.copy()
    if keep == "all":
        return t
    if "status" not in t.columns or "span" not in t.columns:
        if "n_views" not in t.columns:
            raise ValueError(f"range {keep!r} needs the table's n_views (or its status and span columns)")
        if "status" not in t.columns:
            t["status"] = status_of(t["n_views"].to_numpy())
        if "span" not in t.columns:
            t = add_span(t) if "method" in t.columns else add_span(t.assign(method="")).drop(columns="method")
    inside = (t["span"] == "inside") if keep == "span" else (t["status"] == "observed")
    cols = ["x", "y", "z"] + [c for c in _COV_COLS if c in t.columns]
    t.loc[~inside.to_numpy(), cols] = np.nan
    return t


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


def one_take(trajectories: pd.DataFrame, take: int | None = None) -> tuple[pd.DataFrame, int, int]:
    """The rows of one take of a result table: (rows, take index, number of takes).

    A result table holds every frame of its takes and none between (batgraph.session.frame_axis); C3D and
    TRC files are one contiguous run of frames, so they hold one take. take: 0-based index; None = the
    longest (the first of equally long ones). InputError when ``take`` is out of range.
    """
    frames = trajectories["frame"].to_numpy(np.int64)
    tk = take_of(frames) if len(frames) else np.zeros(0, int)
    n = int(tk.max()) + 1 if len(tk) else 1
    if take is None:  # frames per take: the table's distinct frames counted by take
        take = int(np.argmax(np.bincount(take_of(np.unique(frames))))) if n > 1 else 0
    if not 0 <= take < n:
        raise InputError(f"take {take + 1}: the result has {n} take{'s' if n > 1 else ''} (1..{n})")
    return (trajectories if n == 1 else trajectories[tk == take]), take, n


def dense_trajectories(trajectories: pd.DataFrame, markers: list[str] | None = None,
                       method: str | None = None, take: int | None = None) -> DenseTrajectories:
    """Scatter one method's rows of a trajectories table into (F, M) arrays.

    trajectories: trajectories.csv columns (``method`` optional; ``cov_*`` optional).
    markers: output order; None = order of first appearance. Markers not in the table stay NaN.
    method: which method to keep; None requires the table to hold a single method.
    take: which take of a table with several (:func:`one_take`; None = the longest).
    The frame axis runs contiguously from the first to the last frame of that take.
    """
    t = trajectories
    if "method" in t.columns and method is None and t["method"].nunique() > 1:
        raise ValueError(f"trajectories hold several methods {list(dict.fromkeys(t['method']))}; pass method=")
    if "method" in t.columns and method is not None:
        t = t[t["method"] == method]
    if len(t) == 0:
        raise ValueError(f"no trajectories{f' for method {method!r}' if method else ''}")
    t = one_take(t, take)[0]
    xyz, cov, frames, names = dense_from_table(t, markers=markers)
    return DenseTrajectories(frames, names, xyz, cov)


def c3d_point_scale_mm(max_abs_mm: float) -> float:
    """|POINT:SCALE| [mm] for float data whose largest |coordinate| is ``max_abs_mm``: the smallest of
    0.1, 0.2, 0.5, 1, 2, 5, ... mm with ``32000 x scale >= max_abs_mm`` (the spec derives the scale from
    the largest coordinate, so that an integer conversion fits), never below :data:`C3D_RESIDUAL_STEP_MM`."""
    need = max_abs_mm / 32000.0 if np.isfinite(max_abs_mm) else 0.0
    scale = C3D_RESIDUAL_STEP_MM
    decade = C3D_RESIDUAL_STEP_MM
    while scale < need * (1 - 1e-12):
        for m in (1.0, 2.0, 5.0):
            scale = round(decade * m, 10)
            if scale >= need * (1 - 1e-12):
                break
        decade *= 10
    return scale


def c3d_residual_counts(cov_m2: np.ndarray, valid: np.ndarray, scale_mm: float = C3D_RESIDUAL_STEP_MM) -> np.ndarray:
    """The C3D residual byte of each point (integer, shape (...)): residual / |POINT:SCALE|.

    cov_m2: covariances (..., 3, 3) [m^2]; valid: bool (...), True where the point is written.
    ``round(sqrt(trace / 3) [mm] / scale_mm)`` clipped to 1..255; 0 where valid without a finite
    covariance; -1 where not valid. Times ``scale_mm`` it is the residual in mm a reader gets.
    """
    rms_mm = np.sqrt(np.trace(cov_m2, axis1=-2, axis2=-1) / 3.0) * 1e3
    with np.errstate(invalid="ignore"):
        q = np.clip(np.round(rms_mm / scale_mm), 1, 255)
    return np.where(valid, np.where(np.isfinite(rms_mm), q, 0), -1).astype(np.int32)


def c3d_residual_mm(cov_m2: np.ndarray, valid: np.ndarray, scale_mm: float = C3D_RESIDUAL_STEP_MM) -> np.ndarray:
    """The residual [mm] a C3D reader gets for each point: :func:`c3d_residual_counts` x ``scale_mm``, -1 if invalid."""
    n = c3d_residual_counts(cov_m2, valid, scale_mm)
    return np.where(n >= 0, n * scale_mm, -1.0)


def c3d_camera_masks(reprojection: pd.DataFrame | None, d: DenseTrajectories, method: str | None,
                     cameras: list[str] | None) -> tuple[np.ndarray, list[str]]:
    """Camera mask (F, M) int for :func:`write_c3d` and the cameras its bits name (bit k = cameras[k]).

    A camera contributes to a point when the reprojection table has its observation of that marker in that
    frame, for this method, not flagged as an outlier. ``cameras``: bit order (the rig's); None = order of
    first appearance in the table. More than :data:`C3D_MAX_CAMERAS` cameras, or no table: all 0, no names.
    """
    F, M = d.xyz_m.shape[:2]
    mask = np.zeros((F, M), np.int32)
    if reprojection is None or len(reprojection) == 0:
        return mask, []
    r = reprojection
    if method is not None and "method" in r.columns:
        r = r[r["method"] == method]
    names = list(cameras) if cameras is not None else list(dict.fromkeys(r["camera"].astype(str)))
    if not names or len(names) > C3D_MAX_CAMERAS:
        return mask, []
    if "outlier" in r.columns:
        r = r[~r["outlier"].astype(bool)]
    fi = r["frame"].to_numpy(np.int64) - int(d.frames[0])
    mi = r["marker"].astype(str).map({n: i for i, n in enumerate(d.markers)}).to_numpy(float)
    bit = r["camera"].astype(str).map({n: k for k, n in enumerate(names)}).to_numpy(float)
    ok = (fi >= 0) & (fi < F) & np.isfinite(mi) & np.isfinite(bit)
    np.bitwise_or.at(mask, (fi[ok], mi[ok].astype(np.int64)), (1 << bit[ok].astype(np.int32)).astype(np.int32))
    return mask, names


def _patch_c3d(path: Path, word4: np.ndarray, scale: float) -> None:
    """Set the header scale factor to ``scale`` and every point's 4th word to ``word4`` (F, M) in the
    float C3D ezc3d wrote at ``path`` (Intel byte order, points only, frames in order)."""
    b = bytearray(path.read_bytes())
    F, M = word4.shape
    param_start = (b[0] - 1) * 512
    n_points, n_analog = struct.unpack_from("<HH", b, 2)
    data_start = (struct.unpack_from("<H", b, 16)[0] - 1) * 512
    if (b[1] != 0x50 or b[param_start + 3] != 84 or n_points != M or n_analog != 0
            or struct.unpack_from("<f", b, 12)[0] >= 0 or len(b) < data_start + F * M * 16):
        raise RuntimeError(f"{path}: ezc3d wrote an unexpected C3D layout; cannot set residuals and camera masks")
    struct.pack_into("<f", b, 12, -scale)
    data = np.frombuffer(b, dtype="<f4", count=F * M * 4, offset=data_start).reshape(F, M, 4).copy()
    data[..., 3] = word4.astype(np.float32)
    b[data_start:data_start + data.nbytes] = data.tobytes()
    end = data_start + -(-data.nbytes // 512) * 512  # the data's last 512-byte block
    if not any(b[end:]):  # ezc3d appends a whole zero block after block-aligned data; readers warn about it
        del b[end:]
    path.write_bytes(bytes(b))


def write_c3d(path: str | Path, trajectories: pd.DataFrame, fps: float, markers: list[str] | None = None,
              method: str | None = None, keep: str = "span", reprojection: pd.DataFrame | None = None,
              cameras: list[str] | None = None, take: int | None = None) -> Path:
    """Write one method's trajectories to a C3D file (mm, see the module docstring). Atomic.

    path: output ``.c3d``; trajectories: a trajectories.csv table [m]; fps: frame rate [Hz];
    markers: label order (None = order in the table); method: see :func:`dense_trajectories`;
    keep: range, see :func:`keep_range`; reprojection: the reprojection table, for the camera masks;
    cameras: the rig's camera order (bit k of the mask = cameras[k]); see :func:`c3d_camera_masks`.
    take: which take of a result with several (:func:`one_take`; None = the longest).
    """
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: frame rate must be a positive number of Hz, got {fps}")
    d = dense_trajectories(keep_range(trajectories, keep), markers, method, take)
    valid = np.isfinite(d.xyz_m).all(axis=-1)  # (F, M)
    F, M = valid.shape
    xyz_mm = np.where(valid[..., None], d.xyz_m * 1e3, 0.0)
    scale = c3d_point_scale_mm(float(np.abs(xyz_mm).max(initial=0.0)))
    pts = np.zeros((4, M, F))
    pts[:3] = xyz_mm.transpose(2, 1, 0)
    pts[3] = 1.0
    if method is None and "method" in trajectories.columns and len(trajectories):
        method = str(trajectories["method"].iloc[0])
    mask, cam_names = c3d_camera_masks(reprojection, d, method, cameras)
    counts = c3d_residual_counts(d.cov_m2, valid, scale)
    word4 = np.where(valid, mask * 256 + counts, -1)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(d.markers)
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = tuple(
        "batgraph; residual = RMS of per-axis std [mm]" for _ in d.markers)
    c["parameters"]["POINT"]["SCALE"]["value"] = [-scale]
    c.add_parameter("POINT", "UNITS", "mm")
    c.add_parameter("BATGRAPH", "RANGE", keep)
    if cam_names:
        c.add_parameter("BATGRAPH", "CAMERAS", tuple(cam_names))
    c["header"]["points"]["first_frame"] = int(d.frames[0])
    c["data"]["points"] = pts
    path = Path(path)
    with atomic_path(path) as tmp:
        c.write(str(tmp))
        _patch_c3d(Path(tmp), word4, scale)
    return path


TRC_MISSING = "NaN"
"""A missing coordinate in a TRC file (OpenSim reads it as NaN; an empty last cell would be dropped)."""


def _fmt(values: np.ndarray, fmt: str) -> np.ndarray:
    """Numbers -> strings, NaN -> :data:`TRC_MISSING`."""
    out = np.char.mod(fmt, np.nan_to_num(values))
    return np.where(np.isfinite(values), out, TRC_MISSING)


def write_trc(path: str | Path, trajectories: pd.DataFrame, fps: float, markers: list[str] | None = None,
              method: str | None = None, units: str = "m", keep: str = "span", take: int | None = None) -> Path:
    """Write one method's trajectories to an OpenSim TRC file (see the module docstring). Atomic.

    units: "m" (default, the table's own unit), "cm" or "mm". Frame# = session frame + 1, Time = frame / fps.
    keep: range, see :func:`keep_range`. Every data row has 2 + 3 x NumMarkers cells; missing = NaN.
    take: which take of a result with several (:func:`one_take`; None = the longest).
    """
    if units not in _UNIT_TO_M:
        raise ValueError(f"units must be one of {', '.join(_UNIT_TO_M)}; got {units!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: frame rate must be a positive number of Hz, got {fps}")
    d = dense_trajectories(keep_range(trajectories, keep), markers, method, take)
    F, M = d.xyz_m.shape[:2]
    scale = 1.0 / _UNIT_TO_M[units]
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


def analysis_table(trajectories: pd.DataFrame, units: str = "m", keep: str = "span",
                   method: str | None = None) -> pd.DataFrame:
    """The long analysis table of the module docstring from a trajectories table (no recomputation).

    units: "m", "cm" or "mm" for positions and standard deviations (in the column names);
    keep: range (:func:`keep_range`); method: keep only this method (None = every method in the table).
    """
    if units not in _UNIT_TO_M:
        raise ValueError(f"units must be one of {', '.join(_UNIT_TO_M)}; got {units!r}")
    t = trajectories if method is None else trajectories[trajectories["method"] == method]
    t = keep_range(t, keep).reset_index(drop=True)
    s = 1.0 / _UNIT_TO_M[units]
    out = t[[c for c in ("method", "frame", "time_s", "marker") if c in t.columns]].copy()
    for a in "xyz":
        out[f"{a}_{units}"] = t[a].to_numpy(float) * s
    var = {a: t[f"cov_{a}{a}"].to_numpy(float) if f"cov_{a}{a}" in t.columns else np.full(len(t), np.nan)
           for a in "xyz"}
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = {a: np.sqrt(v) for a, v in var.items()}
        for a in "xyz":
            out[f"sd_{a}_{units}"] = sd[a] * s
        for a, b in (("x", "y"), ("x", "z"), ("y", "z")):
            cov = t[f"cov_{a}{b}"].to_numpy(float) if f"cov_{a}{b}" in t.columns else np.full(len(t), np.nan)
            den = sd[a] * sd[b]
            out[f"r_{a}{b}"] = np.where(den > 0, cov / np.where(den > 0, den, 1.0), np.nan)
    for c in ("n_views", "status", "span"):
        if c in t.columns:
            out[c] = t[c].to_numpy()
    return out


def write_table(path: str | Path, trajectories: pd.DataFrame, units: str = "m", keep: str = "span",
                method: str | None = None) -> Path:
    """Write :func:`analysis_table` as CSV or Parquet (by the suffix: ``.csv`` or ``.parquet``). Atomic."""
    path = Path(path)
    table = analysis_table(trajectories, units, keep, method)
    if path.suffix == ".parquet":
        with atomic_path(path) as tmp:
            table.to_parquet(tmp, index=False)
    elif path.suffix == ".csv":
        write_csv(path, table, "%.9g")
    else:
        raise ValueError(f"{path}: the suffix must be .csv or .parquet")
    return path


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
    text = table.apply(lambda col: col.str.strip().str.lower())
    bad = num.isna().to_numpy() & ~text.isin(["", "nan"]).to_numpy()  # empty and NaN cells are missing
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
