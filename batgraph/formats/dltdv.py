"""DLTdv8 / DLTdv7 (and Argus) files <-> batgraph: 2D clicks, 11-parameter DLT coefficients, 3D points.

* ``*xypts.csv``: one row per frame, columns ``pt{p}_cam{c}_X, pt{p}_cam{c}_Y`` (p, c from 1; DLTdv 8.4 writes
  ``_U, _V``), ``NaN`` = not digitised. **Row k (0-based, after the header) is batgraph frame k**; DLTdv's
  GUI counts frames from 1, so DLTdv frame n is batgraph frame n - 1.
* ``*dltCoefs.csv``: 11 rows (L1..L11) x one column per camera, no header;
  ``u = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)``, v likewise with L5..L8.
* ``*xyzpts.csv``: ``pt{p}_X, pt{p}_Y, pt{p}_Z`` per frame; ``*xyzres.csv``: ``pt{p}_dltres``.

Pixel origin, handedness and units are read from the coefficients, not from a version number (every DLTdv
version, Argus and easyWand put the origin at the lower left, y up, 1-based; a DLT world may be mirrored or in
millimetres): the arithmetic is in :mod:`batgraph.geometry.dlt`, :func:`resolve_conventions` applies it.
Camera offsets (``*offsets.csv``) are read by :mod:`batgraph.formats.offsets`: the clicks keep each camera's
own video frame and calibration.toml gets its ``time_offset_s``. DLTdv8's "sparse" xypts layout is not read.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .. import atomic
from ..camera import Camera, Rig
from ..errors import InputError
from ..geometry import dlt
from ..geometry.triangulation import linear_points
from ..inputs import read_csv
from ..session import Session, read_session, write_session
from .c3d_trc import keep_range
from .offsets import read_offsets

_MISSING = {"", "nan", "na", "none"}  # DLTdv writes NaN; tolerate what spreadsheets write
_XYPTS = (re.compile(r"^pt(\d+)_cam(\d+)_([XYUV])$", re.IGNORECASE), "pt{p}_cam{c}_X / pt{p}_cam{c}_Y")
_XYZPTS = (re.compile(r"^pt(\d+)_([XYZ])$", re.IGNORECASE), "pt{p}_X / pt{p}_Y / pt{p}_Z")
_XYZRES = (re.compile(r"^pt(\d+)_(dltres)$", re.IGNORECASE), "pt{p}_dltres")


# ----------------------------------------------------------------------------------------------
# pixel conventions (the arithmetic is batgraph.geometry.dlt's)
# ----------------------------------------------------------------------------------------------
def to_opencv_px(uv_px: np.ndarray, origin: str, height_px: float | None = None) -> np.ndarray:
    """File pixels (..., 2) with ``origin`` ("lower-left" / "upper-left") -> OpenCV pixels; NaN stays NaN."""
    return dlt.apply_affine(np.linalg.inv(dlt.pixel_affine(origin, height_px)), uv_px)


def from_opencv_px(uv_px: np.ndarray, origin: str, height_px: float | None = None) -> np.ndarray:
    """OpenCV pixels (..., 2) -> file pixels with ``origin``; NaN stays NaN."""
    return dlt.apply_affine(dlt.pixel_affine(origin, height_px), uv_px)


def coefs_to_opencv(coefs: np.ndarray, origin: str, height_px: float | None = None) -> np.ndarray:
    """DLT coefficients (n_cams, 11) for ``origin`` pixels -> the same cameras' coefficients in OpenCV pixels."""
    A = np.linalg.inv(dlt.pixel_affine(origin, height_px))
    return dlt.dlt_coefs(dlt.transform_dlt(dlt.dlt_matrix(coefs), pixel_from=A)).reshape(-1, 11)


def coefs_from_opencv(coefs: np.ndarray, origin: str, height_px: float | None = None) -> np.ndarray:
    """DLT coefficients (n_cams, 11) in OpenCV pixels -> ``origin`` pixels."""
    A = dlt.pixel_affine(origin, height_px)
    return dlt.dlt_coefs(dlt.transform_dlt(dlt.dlt_matrix(coefs), pixel_from=A)).reshape(-1, 11)


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------
def _read_text_table(path: Path, header: bool, what: str) -> pd.DataFrame:
    return read_csv(path, header=header, what=what)


def _numbers(df: pd.DataFrame, path: Path, first_line: int, col_label) -> np.ndarray:
    """All cells as floats (R, K), NaN where empty/NaN; InputError naming line and column otherwise.

    first_line: file line number of df's row 0 (1-based); col_label(j) names column j in messages.
    """
    shape = df.shape
    # one flat pass over every cell: vectorised, and the same rules for every column
    text = pd.Series(df.to_numpy(dtype=object).ravel(), dtype=str).str.strip()
    missing = text.str.lower().isin(_MISSING).to_numpy()
    values = pd.to_numeric(text.mask(missing), errors="coerce").to_numpy(dtype=float)
    for bad, problem in ((~missing & np.isnan(values), "is not a number"), (np.isinf(values), "is infinite")):
        if bad.any():
            k = int(np.argmax(bad))
            i, j = divmod(k, shape[1])
            raise InputError(f"{path} line {first_line + i}, {col_label(j)}: {text.iat[k]!r} {problem}")
    return values.reshape(shape)


def _read_wide(path: Path, pattern: tuple[re.Pattern, str], what: str) -> tuple[np.ndarray, list[tuple]]:
    """A headed DLTdv table: (values (n_frames, n_cols) with NaN, parsed column keys)."""
    path = Path(path)
    df = _read_text_table(path, header=True, what=what)
    regex, form = pattern
    keys = []
    for name in df.columns:
        m = regex.match(name)
        if m is None:
            raise InputError(f"{path} line 1: column {name!r} is not of the form {form}")
        keys.append(m.groups())
    if len(df) == 0:
        raise InputError(f"{path}: no rows (the file has a header only)")
    values = _numbers(df, path, 2, lambda j: f"column {df.columns[j]}")
    return values, keys


def _check_complete(path: Path, keys: list[tuple], expected: list[tuple], fmt: str) -> None:
    def norm(key):  # "pt01" is pt1; "x" is X
        return tuple(int(k) if str(k).isdigit() else str(k).upper() for k in key)

    have = {norm(key) for key in keys}
    for key in expected:
        if norm(key) not in have:
            raise InputError(f"{path} line 1: missing column {fmt.format(*key)}")


def read_xypts(path: str | Path, n_cams: int | None = None) -> pd.DataFrame:
    """Read a DLTdv ``*xypts.csv`` into a long table, in the file's own pixel convention.

    Returns columns frame (= row index, from 0), camera_index, point_index (0-based: ``cam1`` is 0,
    ``pt1`` is 0), u, v [px, DLTdv convention]; only digitised cells. ``attrs`` holds n_frames,
    n_points, n_cams (from the header, so never-digitised points and cameras still count).
    n_cams: expected camera count (e.g. columns of the coefficient file); None accepts the header's.
    """
    path = Path(path)
    values, keys = _read_wide(path, _XYPTS, "DLTdv xypts: pt{p}_cam{c}_X, pt{p}_cam{c}_Y columns")
    keys = [(p, c, {"U": "X", "V": "Y"}.get(a.upper(), a)) for p, c, a in keys]  # DLTdv 8.4 writes _U, _V
    pts = np.array([int(k[0]) for k in keys])
    cams = np.array([int(k[1]) for k in keys])
    axis = np.array([0 if k[2].upper() == "X" else 1 for k in keys])
    if pts.min() < 1 or cams.min() < 1:
        raise InputError(f"{path} line 1: point and camera numbers start at 1 (pt1, cam1)")
    P, C = int(pts.max()), int(cams.max())
    if n_cams is not None and C != n_cams:
        raise InputError(f"{path} line 1: the header has cameras cam1..cam{C} but {n_cams} were expected")
    _check_complete(path, keys, [(p, c, a) for p in range(1, P + 1) for c in range(1, C + 1) for a in "XY"],
                    "pt{}_cam{}_{}")
    n_frames = len(values)
    uv = np.full((n_frames, P, C, 2), np.nan)
    uv[:, pts - 1, cams - 1, axis] = values
    half = np.isnan(uv[..., 0]) != np.isnan(uv[..., 1])
    if half.any():
        f, p, c = np.argwhere(half)[0]
        raise InputError(f"{path} line {f + 2}, pt{p + 1}_cam{c + 1}: only one of X, Y is given")
    f, p, c = np.nonzero(np.isfinite(uv[..., 0]))
    out = pd.DataFrame({"frame": f.astype(np.int64), "camera_index": c.astype(np.int64),
                        "point_index": p.astype(np.int64), "u": uv[f, p, c, 0], "v": uv[f, p, c, 1]})
    out = out.sort_values(["frame", "camera_index", "point_index"], kind="stable").reset_index(drop=True)
    out.attrs.update(n_frames=n_frames, n_points=P, n_cams=C)
    return out


def read_dlt_coefs(path: str | Path) -> np.ndarray:
    """Read a DLTdv ``*dltCoefs.csv`` (11 rows x one column per camera, no header).

    Returns coefficients L1..L11 per camera, shape (n_cams, 11), in the file's pixel convention.
    """
    path = Path(path)
    df = _read_text_table(path, header=False, what="11 rows of DLT coefficients, one column per camera")
    if len(df) != 11:
        raise InputError(f"{path}: expected 11 rows (DLT coefficients L1..L11, one column per camera), "
                         f"found {len(df)}")
    L = _numbers(df, path, 1, lambda j: f"column {j + 1} (camera {j + 1})").T
    if np.isnan(L).any():
        c, i = np.argwhere(np.isnan(L))[0]
        raise InputError(f"{path} line {i + 1}, column {c + 1}: "
                         f"coefficient L{i + 1} of camera {c + 1} is empty")
    M = np.concatenate([L, np.ones((len(L), 1))], axis=1).reshape(-1, 3, 4)[:, :, :3]
    sing = np.abs(np.linalg.det(M)) <= 1e-12 * np.linalg.norm(M, axis=(1, 2)) ** 3
    if sing.any():
        c = int(np.argmax(sing))
        raise InputError(f"{path} column {c + 1}: the DLT coefficients of camera {c + 1} are degenerate "
                         f"(L1-L3, L5-L7, L9-L11 are not independent)")
    return L


def read_xyzpts(path: str | Path) -> pd.DataFrame:
    """Read a DLTdv ``*xyzpts.csv``: columns frame (= row index), point_index (0-based), x, y, z.

    Rows with NaN are dropped; ``attrs`` holds n_frames and n_points. Units are those of the
    calibration (metres if the wand was given in metres).
    """
    path = Path(path)
    values, keys = _read_wide(path, _XYZPTS, "DLTdv xyzpts: pt{p}_X, pt{p}_Y, pt{p}_Z columns")
    pts = np.array([int(k[0]) for k in keys])
    axis = np.array(["XYZ".index(k[1].upper()) for k in keys])
    P = int(pts.max())
    _check_complete(path, keys, [(p, a) for p in range(1, P + 1) for a in "XYZ"], "pt{}_{}")
    xyz = np.full((len(values), P, 3), np.nan)
    xyz[:, pts - 1, axis] = values
    f, p = np.nonzero(np.isfinite(xyz).all(axis=-1))
    out = pd.DataFrame({"frame": f.astype(np.int64), "point_index": p.astype(np.int64),
                        "x": xyz[f, p, 0], "y": xyz[f, p, 1], "z": xyz[f, p, 2]})
    out.attrs.update(n_frames=len(values), n_points=P)
    return out


def read_xyzres(path: str | Path) -> pd.DataFrame:
    """Read a DLTdv ``*xyzres.csv``: columns frame, point_index (0-based), residual; NaN rows dropped."""
    path = Path(path)
    values, keys = _read_wide(path, _XYZRES, "DLTdv xyzres: pt{p}_dltres columns")
    pts = np.array([int(k[0]) for k in keys])
    res = np.full((len(values), int(pts.max())), np.nan)
    res[:, pts - 1] = values
    f, p = np.nonzero(np.isfinite(res))
    out = pd.DataFrame({"frame": f.astype(np.int64), "point_index": p.astype(np.int64),
                        "residual": res[f, p]})
    out.attrs.update(n_frames=len(values), n_points=res.shape[1])
    return out


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------
def _scatter(table: pd.DataFrame, index_cols: list[str], value_cols: list[str],
             shape: tuple[int, ...]) -> np.ndarray:
    """Long table -> dense array of ``shape + (len(value_cols),)`` with NaN where no row."""
    out = np.full(shape + (len(value_cols),), np.nan)
    idx = tuple(table[c].to_numpy(dtype=np.int64) for c in index_cols)
    out[idx] = table[value_cols].to_numpy(dtype=float)
    return out


def _size(table: pd.DataFrame, col: str, given: int | None) -> int:
    n = int(table[col].max()) + 1 if len(table) else 0
    return n if given is None else int(given)


def _write_wide(path: str | Path, columns: list[str], values: np.ndarray, float_format: str) -> None:
    text = pd.DataFrame(values, columns=columns).to_csv(index=False, na_rep="NaN", float_format=float_format)
    atomic.write_text(path, text)


def write_xypts(path: str | Path, table: pd.DataFrame, n_cams: int | None = None, n_points: int | None = None,
                n_frames: int | None = None) -> None:
    """Write a DLTdv ``*xypts.csv`` (the inverse of :func:`read_xypts`).

    table: columns frame (>= 0; row k of the file is frame k), camera_index, point_index (0-based),
        u, v [px, already in the target DLTdv convention: see :func:`from_opencv_px`].
    n_cams, n_points, n_frames: file dimensions; default one past the table's largest index.
    """
    C, P = _size(table, "camera_index", n_cams), _size(table, "point_index", n_points)
    F = _size(table, "frame", n_frames)
    uv = _scatter(table, ["frame", "point_index", "camera_index"], ["u", "v"], (F, P, C))
    cols = [f"pt{p}_cam{c}_{a}" for p in range(1, P + 1) for c in range(1, C + 1) for a in "XY"]
    _write_wide(path, cols, uv.reshape(F, -1), "%.6f")


def point_names(markers: list[str]) -> tuple[list[str], str | None]:
    """Column-name stems of DLTdv 3D files for ``markers``: the marker names themselves where DLTdv can read
    them, else pt1..ptN; returns (stems, why the names were not kept, or None).

    DLTdv (8.4 and later) names its columns after its points (``{name}_X``, ``{name}_dltres``) and reads the
    names back through MATLAB's table variable names, so a name is kept when every marker's is a MATLAB
    identifier (a letter, then letters, digits, _) whose longest column (``{name}_dltres``) fits MATLAB's 63
    characters, the names differ regardless of case, and none is ``pt{k}`` for another point than the k-th
    (older DLTdv versions and Argus number the points by those columns).
    """
    bad = [m for m in markers if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", m) or len(m) + len("_dltres") > 63]
    if bad:
        return [f"pt{p}" for p in range(1, len(markers) + 1)], (
            f"marker name {bad[0]!r} is not a MATLAB identifier of at most 56 characters")
    lower = [m.lower() for m in markers]
    twice = sorted({m for m in lower if lower.count(m) > 1})
    if twice:
        return [f"pt{p}" for p in range(1, len(markers) + 1)], f"marker names differ only by case ({twice[0]!r})"
    for k, m in enumerate(lower, start=1):
        if re.fullmatch(r"pt\d+", m) and m != f"pt{k}":
            return [f"pt{p}" for p in range(1, len(markers) + 1)], (
                f"marker {markers[k - 1]!r} is point {k}: its name would read as another point's number")
    return list(markers), None


def write_xyzpts(path: str | Path, table: pd.DataFrame, n_points: int | None = None,
                 n_frames: int | None = None, names: list[str] | None = None) -> None:
    """Write a DLTdv ``*xyzpts.csv``. table: frame, point_index (0-based), x, y, z; NaN where missing.

    names: the column stems of the points (:func:`point_names`); None numbers them pt1..ptN.
    """
    P, F = _size(table, "point_index", n_points if names is None else len(names)), _size(table, "frame", n_frames)
    stems = names or [f"pt{p}" for p in range(1, P + 1)]
    xyz = _scatter(table, ["frame", "point_index"], ["x", "y", "z"], (F, P))
    _write_wide(path, [f"{n}_{a}" for n in stems for a in "XYZ"], xyz.reshape(F, -1), "%.9f")


def write_xyzres(path: str | Path, table: pd.DataFrame, n_points: int | None = None,
                 n_frames: int | None = None, names: list[str] | None = None) -> None:
    """Write a DLTdv ``*xyzres.csv``. table: frame, point_index (0-based), residual [px]; NaN = missing.

    names: as for :func:`write_xyzpts`.
    """
    P, F = _size(table, "point_index", n_points if names is None else len(names)), _size(table, "frame", n_frames)
    stems = names or [f"pt{p}" for p in range(1, P + 1)]
    res = _scatter(table, ["frame", "point_index"], ["residual"], (F, P))
    _write_wide(path, [f"{n}_dltres" for n in stems], res.reshape(F, -1), "%.6f")


def rig_to_dlt_coefs(rig: Rig, origin: str = "lower-left", image_size: tuple[int, int] | None = None,
                     units: str = "m") -> np.ndarray:
    """DLT coefficients (n_cams, 11) of a rig's pinholes (distortion ignored) in a file's conventions.

    origin: the file's pixel origin ("lower-left", DLTdv's, or "upper-left"). image_size: (W, H) [px] for
    the lower-left y flip; None uses each camera's own height. units: the file's world units ("m", "cm",
    "mm"). The world is the user's frame (``rig.world_mirror`` applied), as the rig's session came in.
    """
    T = np.linalg.inv(dlt.world_scale_mirror(dlt.UNITS_M[units], rig.world_mirror))  # X_int = T @ X_file
    out = []
    for cam in rig:
        h = image_size[1] if image_size is not None else cam.size_wh[1]
        P = dlt.transform_dlt(dlt.dlt_matrix(cam.to_dlt()), pixel_from=dlt.pixel_affine(origin, h), world_to=T)
        out.append(dlt.dlt_coefs(P))
    return np.array(out).reshape(-1, 11)


def write_dlt_coefs(path: str | Path, rig: Rig, origin: str = "lower-left",
                    image_size: tuple[int, int] | None = None, units: str = "m") -> None:
    """Write a DLTdv ``*dltCoefs.csv`` (11 rows x one column per camera, no header) for ``rig``.

    Distortion is not representable in a DLT and is ignored; see :func:`rig_to_dlt_coefs`.
    """
    L = rig_to_dlt_coefs(rig, origin, image_size, units)
    # %.17g: every float64 round-trips exactly, so Camera -> file -> Camera loses nothing
    text = "".join(",".join(f"{x:.17g}" for x in row) + "\n" for row in L.T)
    atomic.write_text(path, text)


# ----------------------------------------------------------------------------------------------
# import
# ----------------------------------------------------------------------------------------------
def _names(given, n: int, default: str, what: str, where: str) -> list[str]:
    names = [default.format(i + 1) for i in range(n)] if given is None else [str(s).strip() for s in given]
    if len(names) != n:
        raise InputError(f"{where}: {n} {what}s in the file but {len(names)} {what} names were given")
    if any(not s for s in names) or len(set(names)) != len(names):
        raise InputError(f"{where}: {what} names must be non-empty and distinct, got {names}")
    return names


def infer_image_size(P_file: np.ndarray, uv_file_px: np.ndarray) -> tuple[int, int]:
    """Image size (W, H) [px] when none is given: the principal point taken as the image centre.

    P_file: one camera's DLT matrix (3, 4) and uv_file_px (n, 2) its clicks, both in the file's own
    1-based pixels, whatever their origin: the centre of a W x H image is ((W + 1) / 2, (H + 1) / 2) in
    either, so ``W = round(2 cx - 1)``, enlarged so that every click lies inside (``u <= W + 0.5``).
    Only batgraph's "outside the image" checks and plots depend on it (a DLT has no distortion to centre).
    """
    size = np.round(2 * dlt.principal_point(P_file) - 1)
    if len(uv_file_px):
        size = np.maximum(size, np.ceil(np.nanmax(uv_file_px, axis=0) - 0.5))
    w, h = np.maximum(size, 1).astype(int)
    return int(w), int(h)


def resolve_conventions(P_file: np.ndarray, uv_file_px: np.ndarray, pixel_origin: str | None, *,
                        xyz_file: np.ndarray | None = None, camera_names: list[str], coefs_path: Path,
                        ) -> tuple[str, np.ndarray, str]:
    """The pixel origin and world mirror of a DLT trial, from its coefficients and clicks.

    P_file: (C, 3, 4) as in the file; uv_file_px: (C, N, 2) clicks, NaN where missing; xyz_file:
    optional (N, 3) 3D in the file's world (DLTdv's xyzpts) for points no two cameras see.
    pixel_origin: None to detect, or "lower-left" / "upper-left" as the user says.
    Each camera votes with :func:`batgraph.geometry.dlt.orientation_sign` on the points it sees
    (triangulated by the file's own linear DLT); one rig must agree. Detected: -1 -> lower-left (DLTdv's
    convention, right-handed world), +1 -> upper-left (or lower-left with a mirrored world: the same 3D).
    A given origin that disagrees with the sign means a mirrored world: z is negated internally.
    Returns (origin, world_mirror (3,), note). Raises InputError naming the camera that disagrees.
    """
    xyz = linear_points(P_file, uv_file_px)  # each view's rows at unit norm: the file's own 3D
    if xyz_file is not None:
        xyz = np.where(np.isfinite(xyz), xyz, xyz_file)
    seen = np.isfinite(uv_file_px[..., 0])
    frac = dlt.orientation_sign(P_file, xyz, seen)
    known = np.isfinite(frac)
    if not known.any():
        raise InputError(f"{coefs_path}: no point is digitised in two cameras, so the pixel origin cannot be "
                         f"checked against the coefficients; digitise some points in two cameras")
    votes = np.where(frac[known] > 0.5, 1, -1)
    if votes.sum() == 0:
        raise InputError(f"{coefs_path}: half of the cameras put the points behind them: the coefficient "
                         f"columns mix pixel origins or handedness (cameras {', '.join(camera_names)})")
    sign = 1 if votes.sum() > 0 else -1
    for c in np.flatnonzero(known):
        if (frac[c] > 0.5) != (sign > 0):
            behind = 100 * (frac[c] if sign < 0 else 1 - frac[c])
            raise InputError(f"{coefs_path} column {c + 1} (camera {camera_names[c]}): {behind:.0f} % of the points "
                             f"it sees lie behind it under the pixel origin and handedness the other cameras share: "
                             f"its coefficients come from another convention (pixel origin? mirrored world?)")
    if pixel_origin is None:
        origin = "upper-left" if sign > 0 else "lower-left"
        note = ("detected from the coefficients" + (" (upper-left pixels with a right-handed world, or lower-left "
                "with a mirrored one: the coefficients cannot tell them apart and both give the same 3D)"
                if sign > 0 else ""))
        return origin, np.ones(3), note
    mirrored = (pixel_origin == "upper-left") != (sign > 0)
    note = "given" + (" (the coefficients then describe a mirrored world: z is negated internally, results come "
                      "back in the file's frame)" if mirrored else "")
    return pixel_origin, np.array([1.0, 1.0, -1.0 if mirrored else 1.0]), note


def import_dltdv(xypts: str | Path, coefs: str | Path, fps: float, out: str | Path, *,
                 pixel_origin: str | None = None, units: str = "m", image_size: tuple[int, int] | None = None,
                 xyzpts: str | Path | None = None, camera_names: list[str] | None = None,
                 marker_names: list[str] | None = None, pixel_sigma_px: float | None = None,
                 offsets: list[str | Path] = ()) -> Session:
    """Convert a DLTdv / Argus / easyWand trial into a session folder ``out`` and return it as read back.

    xypts, coefs: ``*xypts.csv`` and ``*dltCoefs.csv`` (same pixel convention); fps [Hz]: row k is at k / fps.
    pixel_origin: "lower-left" (DLTdv's), "upper-left", or None to detect it (:func:`resolve_conventions`); a
        given origin the coefficients contradict means a mirrored world (``[metadata] world_mirror``).
    units: the world units of the coefficients and xyzpts ("m", "cm", "mm"); the session is in metres.
    image_size: (W, H) [px] of every camera; None infers it per camera (:func:`infer_image_size`; reconstruct warns).
    xyzpts: optional ``*xyzpts.csv``, kept as the session's reference (reference_xyz.csv, metres).
    camera_names, marker_names: default cam1.. (coefficient columns) and pt1.. (xypts points).
    pixel_sigma_px: click noise [px]; None (default) lets reconstruct estimate it per camera.
    offsets: up to two offsets files (:func:`_apply_offsets`: per-row video frames and/or Argus's sync table).
    The imported pinholes reproduce each camera's own DLT projection exactly, with the points in front.
    Raises InputError naming the file (and camera) for bad input.
    """
    xypts, coefs, out = Path(xypts), Path(coefs), Path(out)
    image_size = _check_import_options(pixel_origin, units, fps, pixel_sigma_px, image_size)
    trial = _read_trial(xypts, coefs, xyzpts, camera_names, marker_names)
    uv_file, xyz_file = dense_clicks(trial)
    P_file = dlt.dlt_matrix(trial.coefs)
    origin, mirror, note = resolve_conventions(P_file, uv_file, pixel_origin, xyz_file=xyz_file,
                                               camera_names=trial.cameras, coefs_path=coefs)
    sizes = ([image_size] * len(P_file) if image_size is not None
             else [infer_image_size(P, uv[np.isfinite(uv[:, 0])]) for P, uv in zip(P_file, uv_file, strict=True)])
    clicks = trial.clicks
    ci, pi = clicks["camera_index"].to_numpy(), clicks["point_index"].to_numpy()
    own, time_offsets, timing_note = _apply_offsets(offsets, clicks["frame"].to_numpy(), ci, len(P_file),
                                                    clicks.attrs["n_frames"], fps, xypts)
    rig, uv_cv = _opencv_rig(P_file, clicks, trial.cameras, sizes, origin, mirror, units, time_offsets)
    observations = pd.DataFrame({
        "frame": own, "camera": np.array(trial.cameras)[ci], "marker": np.array(trial.markers)[pi],
        "u": uv_cv[:, 0], "v": uv_cv[:, 1], "weight": 1.0,
    })[own >= 0]
    provenance = {"format": "dltdv", "xypts": xypts.name, "dlt_coefs": coefs.name, "pixel_origin": origin,
                  "pixel_origin_source": "detected" if pixel_origin is None else "given",
                  "pixel_origin_note": note, "world": "mirrored" if rig.mirrored else "right-handed",
                  "units": units, "image_size": "given" if image_size is not None else "inferred"}
    if xyzpts is not None:
        provenance["xyzpts"] = Path(xyzpts).name
    provenance.update(timing_note)
    session = Session(name=out.name, fps=float(fps), rig=rig, observations=observations,
                      pixel_sigma_px=pixel_sigma_px, marker_names=trial.markers,
                      reference=_reference_table(trial, units), extra_toml={"import": provenance})
    write_session(session, out)
    return read_session(out)


def _check_import_options(pixel_origin, units, fps, pixel_sigma_px, image_size) -> tuple[int, int] | None:
    """InputError for an option of :func:`import_dltdv` out of its range; the image size as (W, H) ints."""
    if pixel_origin is not None and pixel_origin not in dlt.PIXEL_ORIGINS:
        raise InputError(f"pixel origin must be one of {', '.join(dlt.PIXEL_ORIGINS)}, got {pixel_origin!r}")
    if units not in dlt.UNITS_M:
        raise InputError(f"units must be one of {', '.join(dlt.UNITS_M)}, got {units!r}")
    if not (isinstance(fps, int | float) and math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a number > 0, got {fps!r}")
    if pixel_sigma_px is not None and not (isinstance(pixel_sigma_px, int | float) and math.isfinite(pixel_sigma_px)
                                           and pixel_sigma_px > 0):
        raise InputError(f"pixel_sigma_px must be a number > 0, got {pixel_sigma_px!r}")
    if image_size is None:
        return None
    size = np.asarray(image_size, dtype=object)
    if size.shape != (2,) or not all(isinstance(s, int | float) and s > 0 and s == int(s) for s in size):
        raise InputError(f"image size must be two positive integers W H, got {image_size!r}")
    return int(size[0]), int(size[1])


@dataclass
class Trial:
    """A DLTdv trial as read: coefs (C, 11); clicks (:func:`read_xypts`); the camera and marker names;
    reference: the xyzpts table (:func:`read_xyzpts`) or None."""

    coefs: np.ndarray
    clicks: pd.DataFrame
    cameras: list[str]
    markers: list[str]
    reference: pd.DataFrame | None


def _read_trial(xypts: Path, coefs: Path, xyzpts, camera_names, marker_names) -> Trial:
    """Read a trial's files and check that they agree with each other and with the names given."""
    L = read_dlt_coefs(coefs)
    clicks = read_xypts(xypts)
    if clicks.attrs["n_cams"] != len(L):
        raise InputError(f"{xypts} line 1: the header has {clicks.attrs['n_cams']} camera(s) "
                         f"but {coefs} has {len(L)} column(s) of coefficients")
    cams = _names(camera_names, len(L), "cam{}", "camera", str(coefs))
    markers = _names(marker_names, clicks.attrs["n_points"], "pt{}", "point", str(xypts))
    if len(clicks) == 0:
        raise InputError(f"{xypts}: no digitised points (every cell is NaN)")
    ref = None
    if xyzpts is not None:
        ref = read_xyzpts(xyzpts)
        if ref.attrs["n_points"] != len(markers):
            raise InputError(f"{xyzpts} line 1: {ref.attrs['n_points']} point(s) but {xypts} has {len(markers)}")
    return Trial(L, clicks, cams, markers, ref)


def dense_clicks(trial: Trial) -> tuple[np.ndarray, np.ndarray | None]:
    """The clicks in the file's pixels as (C, N, 2), N = (row, point) pairs, NaN where missing; and the
    xyzpts positions (N, 3) in the file's world (None without xyzpts): the convention check's input."""
    clicks, n_points = trial.clicks, trial.clicks.attrs["n_points"]
    n = clicks["frame"].to_numpy() * n_points + clicks["point_index"].to_numpy()
    uv_file = np.full((len(trial.coefs), clicks.attrs["n_frames"] * n_points, 2), np.nan)
    uv_file[clicks["camera_index"].to_numpy(), n] = clicks[["u", "v"]].to_numpy()
    if trial.reference is None:
        return uv_file, None
    ref = trial.reference
    xyz_file = np.full((uv_file.shape[1], 3), np.nan)
    k = ref["frame"].to_numpy() * n_points + ref["point_index"].to_numpy()
    inside = k < len(xyz_file)
    xyz_file[k[inside]] = ref[["x", "y", "z"]].to_numpy()[inside]
    return uv_file, xyz_file


def _opencv_rig(P_file: np.ndarray, clicks: pd.DataFrame, cameras: list[str], sizes: list, origin: str,
                mirror: np.ndarray, units: str, time_offsets: np.ndarray) -> tuple[Rig, np.ndarray]:
    """The trial's cameras in batgraph's conventions (OpenCV pixels, metres, right-handed) and every click
    (N, 2) in OpenCV pixels: each camera's DLT with its pixel origin and the world's scale and mirror undone."""
    T = dlt.world_scale_mirror(dlt.UNITS_M[units], mirror)  # X_file = T @ X_internal
    ci = clicks["camera_index"].to_numpy()
    out, uv_cv = [], np.empty((len(clicks), 2))
    for c, name in enumerate(cameras):
        A_inv = np.linalg.inv(dlt.pixel_affine(origin, sizes[c][1]))
        P_cv = dlt.transform_dlt(P_file[c], pixel_from=A_inv, world_to=T)
        cam = Camera.from_dlt(name, dlt.dlt_coefs(P_cv), sizes[c])
        cam.time_offset_s = float(time_offsets[c])
        out.append(cam)
        uv_cv[ci == c] = dlt.apply_affine(A_inv, clicks.loc[ci == c, ["u", "v"]].to_numpy())
    return Rig(out, world_mirror=mirror), uv_cv


def _reference_table(trial: Trial, units: str) -> pd.DataFrame | None:
    """The xyzpts points as a session's reference table (frame, marker, x, y, z) in the user's frame, metres."""
    if trial.reference is None:
        return None
    ref = trial.reference
    reference = ref.assign(marker=np.array(trial.markers)[ref["point_index"].to_numpy()])
    reference[["x", "y", "z"]] = reference[["x", "y", "z"]].to_numpy() * dlt.UNITS_M[units]
    return reference[["frame", "marker", "x", "y", "z"]]


def _apply_offsets(paths, row: np.ndarray, cam: np.ndarray, n_cams: int, n_rows: int, fps: float, xypts: Path):
    """(each click's video frame (N,), time_offset_s per camera (C,), provenance) from offsets files: DLTdv's or
    the Argus clicker's per-row offsets (which video frame each row shows; clicks before a video's first frame
    get a negative frame and are dropped) and/or Argus's sync table (time offsets to a fraction of a frame,
    taking precedence). Without any, the rows are the cameras' own frames and the offsets 0."""
    files = [read_offsets(p, n_cams) for p in paths]
    per_row = [f for f in files if f.per_row]
    sync = [f for f in files if not f.per_row]
    if len(paths) > 2 or len(per_row) > 1 or len(sync) > 1:
        raise InputError(f"offsets: give at most one per-row file (DLTdv8 / Argus clicker) and one Argus sync table, "
                         f"got {', '.join(map(str, paths))}")
    own, offsets, note = row.copy(), np.zeros(n_cams), {}
    if per_row:
        f = per_row[0]
        if f.n_rows != n_rows:
            raise InputError(f"{paths[files.index(f)]}: {f.n_rows} row(s) but {xypts} has {n_rows} (one per frame)")
        own, offsets = f.video_frames(row, cam), f.time_offsets_s(fps)
        note.update(offsets=Path(paths[files.index(f)]).name, offsets_format=f.kind,
                    clicks_before_first_video_frame=int((own < 0).sum()))
    if sync:
        offsets = sync[0].time_offsets_s(fps)
        note.update(sync_offsets=Path(paths[files.index(sync[0])]).name)
    return own, offsets, note


def export_dltdv(prefix: str | Path, trajectories: pd.DataFrame, reprojection: pd.DataFrame,
                 method: str, units: str = "m", keep: str = "span") -> list[Path]:
    """Write one method's result as DLTdv ``{prefix}xyzpts.csv`` and ``{prefix}xyzres.csv``.

    Points are in the table's marker order, their columns named after the markers where DLTdv can read
    the names (:func:`point_names`), else pt1..ptN; file row k is frame k (rows before the first frame
    are NaN). keep: which estimates to write, the others NaN (batgraph.formats.c3d_trc.keep_range):
    "span" (default) leaves out the track ends, where every method extrapolates. The residual of a point
    is the RMS over cameras of its reprojection error [px] (DLTdv's xyzres is its DLT residual, also in
    pixels), NaN where its position is. trajectories are in metres in the user's frame
    (trajectories.csv); units: those the xyzpts file is written in, the imported project's own ("m",
    "cm", "mm").
    """
    traj = trajectories[trajectories["method"] == method]
    if traj.empty:
        raise InputError(f"trajectories.csv: no rows for method {method!r} "
                         f"(methods: {', '.join(dict.fromkeys(trajectories['method']))})")
    markers = list(dict.fromkeys(traj["marker"]))
    index = {m: i for i, m in enumerate(markers)}
    n_frames = int(traj["frame"].max()) + 1
    traj = keep_range(traj, keep)
    xyz = traj.assign(point_index=traj["marker"].map(index))
    xyz[["x", "y", "z"]] = xyz[["x", "y", "z"]].to_numpy(float) / dlt.UNITS_M[units]  # back to the project's units
    rep = reprojection[reprojection["method"] == method]
    written = xyz.loc[np.isfinite(xyz["x"].to_numpy(float)), ["frame", "marker"]]
    rep = rep.merge(written, on=["frame", "marker"])  # a residual only where a position is written
    res = (rep.assign(e2=rep["err_px"] ** 2).groupby(["frame", "marker"], as_index=False)["e2"].mean()
           .assign(residual=lambda d: np.sqrt(d["e2"]), point_index=lambda d: d["marker"].map(index)))
    names = point_names(markers)[0]
    paths = [Path(f"{prefix}xyzpts.csv"), Path(f"{prefix}xyzres.csv")]
    write_xyzpts(paths[0], xyz, n_frames=n_frames, names=names)
    write_xyzres(paths[1], res, n_frames=n_frames, names=names)
    return paths
