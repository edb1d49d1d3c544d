"""DeepLabCut 2D output (one .h5 or .csv per camera) + an aniposelib calibration.toml -> a batgraph session.

DeepLabCut's ``analyze_videos`` writes a pandas table with one row per video frame (the index is the
0-based frame number) and three column levels ``scorer / bodyparts / coords`` (``coords`` = x, y,
likelihood); the CSV export spells these levels as three header rows whose first cell is the level
name, the .h5 stores the same table under the key ``df_with_missing``. Multi-animal DeepLabCut adds
a level ``individuals`` between scorer and bodyparts: one individual is imported (``individual=``),
because DeepLabCut does not match identities across cameras. Labelled-data files
(``CollectedData_*``, x and y without likelihood, image paths as index) are refused.

Pixels: DeepLabCut's x, y are image coordinates with the origin at the top-left pixel, as OpenCV's, and
are not undistorted: they go to observations.csv unchanged. Frame i of every file is taken to be the
same instant (synchronised cameras). The likelihood becomes the observation ``weight``; detections
below ``threshold`` are dropped. Reading .h5 needs the ``tables`` package; CSV needs nothing extra.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputError
from ..inputs import MAX_FRAME, check_file, check_frame_gaps, check_readable, read_text
from ..session import Session
from .keypoints2d import check_fps, load_rig, make_session, match_cameras, observations_from_arrays

LEVELS_SINGLE = ["scorer", "bodyparts", "coords"]
LEVELS_MULTI = ["scorer", "individuals", "bodyparts", "coords"]


def _read_csv(path: Path) -> tuple[pd.DataFrame, int]:
    """The table and its number of header rows; header layout checked row by row."""
    text = read_text(path)
    head = [row for _, row in zip(range(4), csv.reader(io.StringIO(text, newline="")), strict=False)]
    firsts = [r[0].strip().lower() if r else "" for r in head]
    levels = LEVELS_MULTI if len(firsts) > 1 and firsts[1] == "individuals" else LEVELS_SINGLE
    for i, want in enumerate(levels):
        got = firsts[i] if i < len(firsts) else "<end of file>"
        if got != want:
            raise InputError(f"{path} line {i + 1}: expected DeepLabCut header row '{want}', found {got!r} "
                             f"(rows must be {' / '.join(levels)})")
    try:
        df = pd.read_csv(io.StringIO(text), header=list(range(len(levels))), index_col=0, dtype=str,
                         keep_default_na=False)
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError) as e:
        raise InputError(f"{path}: cannot be read as DeepLabCut CSV ({str(e).strip().splitlines()[-1]})") from None
    return df, len(levels)


def _read_h5(path: Path) -> pd.DataFrame:
    try:
        import tables  # noqa: F401  (pandas needs it for HDF5)
    except ImportError:
        raise InputError(f"{path}: reading .h5 needs the 'tables' package (pip install tables), "
                         f"or export CSV from DeepLabCut") from None
    check_readable(path)
    try:
        with pd.HDFStore(path, mode="r") as store:
            keys = store.keys()
            key = "/df_with_missing" if "/df_with_missing" in keys else (keys[0] if len(keys) == 1 else None)
            if key is None:
                raise InputError(f"{path}: no 'df_with_missing' table among keys {keys}")
            df = store[key]
    except InputError:
        raise
    except Exception as e:  # not HDF5, or not a pandas table
        raise InputError(f"{path}: cannot be read as DeepLabCut .h5 ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(df, pd.DataFrame) or df.columns.nlevels not in (3, 4):
        raise InputError(f"{path}: expected a table with column levels {' / '.join(LEVELS_SINGLE)} "
                         f"(or with 'individuals'), found {getattr(df.columns, 'nlevels', '?')} level(s)")
    return df


def read_deeplabcut(path: str | Path, individual: str | None = None,
                    ) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Read one DeepLabCut 2D file.

    Returns frames (F,), bodypart names (M,), uv_px (F, M, 2) [raw px, NaN = missing] and
    likelihood (F, M). ``individual`` picks one animal of a multi-animal file (required when it has
    several).
    """
    path = check_file(path)
    if path.suffix.lower() in (".h5", ".hdf5"):
        df, n_header = _read_h5(path), 0
    elif path.suffix.lower() == ".csv":
        df, n_header = _read_csv(path)
    else:
        raise InputError(f"{path}: expected a DeepLabCut .h5 or .csv file")

    def where(row: int) -> str:  # a data row -> "file line N" (CSV) or "file row N" (h5)
        return f"{path} line {row + n_header + 1}" if n_header else f"{path} row {row}"

    cols = df.columns
    if cols.nlevels == 4:
        individuals = list(dict.fromkeys(cols.get_level_values(1)))
        if individual is None and len(individuals) > 1:
            raise InputError(f"{path}: multi-animal file with individuals {individuals}; pass individual= to "
                             f"import one (identities are not matched across cameras)")
        pick = individual if individual is not None else individuals[0]
        if pick not in individuals:
            raise InputError(f"{path}: individual {pick!r} not in the file (individuals: {individuals})")
        df = df.loc[:, cols.get_level_values(1) == pick]
    elif individual is not None:
        raise InputError(f"{path}: individual={individual!r} given but the file is single-animal")
    part = df.columns.get_level_values(-2).astype(str).to_numpy()
    coord = df.columns.get_level_values(-1).astype(str).str.strip().str.lower().to_numpy()
    if "likelihood" not in coord:
        raise InputError(f"{path}: no 'likelihood' coordinate; expected x, y, likelihood per bodypart "
                         f"(DeepLabCut's analyze_videos output, not a labelled-data file)")
    bodyparts = list(dict.fromkeys(part))
    index = {(p, c): i for i, (p, c) in enumerate(zip(part, coord, strict=True))}
    if len(index) != len(part):
        raise InputError(f"{path}: a bodypart/coordinate column appears more than once")
    order = []
    for p in bodyparts:
        for c in ("x", "y", "likelihood"):
            if (p, c) not in index:
                raise InputError(f"{path}: bodypart {p!r} has no {c!r} column")
            order.append(index[(p, c)])
    raw = df.iloc[:, order]
    num = raw.apply(lambda s: pd.to_numeric(s, errors="coerce"))
    text = raw.astype(str).apply(lambda s: s.str.strip())
    bad = num.isna().to_numpy() & ~(raw.isna() | text.isin(["", "nan", "NaN"])).to_numpy()
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"{where(int(r))}: {bodyparts[c // 3]} {('x', 'y', 'likelihood')[c % 3]} "
                         f"{raw.iat[r, c]!r} is not a number")
    frame = pd.to_numeric(pd.Series(df.index, dtype=object).astype(str).str.strip(), errors="coerce").to_numpy()
    bad = ~np.isfinite(frame) | (frame < 0) | (frame != np.round(frame)) | (frame > MAX_FRAME)
    if bad.any():
        r = int(np.argmax(bad))
        raise InputError(f"{where(r)}: index {df.index[r]!r} is not a frame number (an integer from 0 to "
                         f"{MAX_FRAME:,})")
    if len(set(frame)) != len(frame):
        r = int(np.argmax(pd.Series(frame).duplicated().to_numpy()))
        raise InputError(f"{where(r)}: frame {int(frame[r])} appears twice")
    if n_header:
        check_frame_gaps(frame.astype(np.int64), path, True, rows=np.arange(len(frame)) + n_header - 1)
    else:
        check_frame_gaps(frame.astype(np.int64), path, False)
    vals = num.to_numpy(float).reshape(len(df), len(bodyparts), 3)
    return frame.astype(np.int64), bodyparts, vals[..., :2], vals[..., 2]


def import_deeplabcut(files: list[str | Path], calibration: str | Path, fps: float, out: str | Path | None,
                      camera_names: list[str] | None = None, threshold: float = 0.6,
                      individual: str | None = None, name: str | None = None, units: str | None = None,
                      skeleton: list[tuple[str, str]] | None = None) -> Session:
    """Import one DeepLabCut 2D file per camera into a session (written to ``out`` unless None).

    files: one .h5/.csv per camera. calibration: aniposelib calibration.toml.
    camera_names: the calibration camera of each file, in order; None = matched from the file names
        (rule in :mod:`batgraph.formats.keypoints2d`).
    fps: frame rate [Hz]. threshold: minimum likelihood kept (DeepLabCut's pcutoff is 0.6).
    individual: for multi-animal files, which individual to import. name: session name (default:
        the ``out`` folder's name). units: the calibration's translation units (see keypoints2d.load_rig).
    skeleton: pairs of body parts for session.toml's [markers] skeleton (Anipose's scheme).
    """
    fps = check_fps(fps)
    calib, rig = load_rig(calibration, units)
    paths = [Path(f) for f in files]
    for p in paths:
        check_file(p)
    cams = match_cameras(paths, rig, camera_names, calib)
    tables, markers = [], []
    for p, cam in zip(paths, cams, strict=True):
        frames, parts, uv, lik = read_deeplabcut(p, individual)
        tables.append(observations_from_arrays(cam, frames, parts, uv, lik, threshold))
        markers += [m for m in parts if m not in markers]
    label = name or (Path(out).name if out is not None else paths[0].stem)
    return make_session(label, fps, rig, tables, markers, out, f"{', '.join(map(str, paths))}", skeleton=skeleton)
