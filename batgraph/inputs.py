"""The input boundary: every file a command reads, every option it parses and every place it writes to is
checked here first, and every problem becomes one :class:`batgraph.errors.InputError` naming the file,
the line or key, and the problem. This module knows no file layout (session.py and formats/* do).

* Text files (TOML, CSV, JSON) are UTF-8, a byte-order mark accepted; UTF-16, Latin-1 / Windows-1252 and
  binary files are refused with a hint.
* CSV is comma-separated with a header row (unless a reader says otherwise); semicolons or tabs (a
  spreadsheet's locale export) and a header naming a column twice are refused. Line numbers are the file's.
* Frames: integers ``0 <= frame <= MAX_FRAME``. Estimators hold every frame from the first to the last
  observed one in memory (:class:`batgraph.session.DenseObservations`), so a jump of more than
  ``MAX_FRAME_GAP`` frames (a typo such as one row at frame 2,000,000) is refused, and so is a session
  whose dense arrays would not fit in memory (:func:`check_dense_memory`).
* Output places are checked before any work starts (:func:`check_output_dir`, :func:`check_output_file`);
  nothing is created here. Command-line option types (:func:`positive_float` ...): one set for every command.
"""

from __future__ import annotations

import argparse
import codecs
import csv
import difflib
import io
import json
import math
import os
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import InputError
from .labels import Labels, factorize

MAX_FRAME = 10_000_000
"""Largest frame number accepted (a day at 115 Hz); larger is a typo or an overflowed counter."""

MAX_FRAME_GAP = 100_000
"""Largest jump between consecutive observed frames (14 minutes at 120 Hz): every frame in between is
allocated (and estimated unless a gap longer than [session] take_gap_s splits the takes), so a larger gap is
refused; split such a recording into sessions."""

MISSING = ("", "nan", "NaN", "NA", "None")
"""Cell texts that mean "no value" in a numeric column."""


# ----------------------------------------------------------------------------------------------
# files -> bytes -> text
# ----------------------------------------------------------------------------------------------
def _read_raw(path: Path) -> bytes:
    """The one place that opens an input file for reading (tests replace it to simulate OS errors)."""
    with open(path, "rb") as f:
        return f.read()


def _os_problem(e: OSError) -> str:
    if isinstance(e, PermissionError):
        return "permission denied (cannot read it; check the file's permissions)"
    if isinstance(e, IsADirectoryError):
        return "is a folder, expected a file"
    return f"cannot be read ({e.strerror or type(e).__name__})"


def check_file(path: str | os.PathLike, what: str = "file") -> Path:
    """``path`` as a Path if it is an existing file, else InputError ("not found", "is a folder")."""
    path = Path(path)
    try:
        if path.is_dir():
            raise InputError(f"{path}: is a folder, expected a {what}")
        if not path.is_file():
            raise InputError(f"{path}: {what} not found" if what != "file" else f"{path}: file not found")
    except OSError as e:  # e.g. a parent folder without search permission
        raise InputError(f"{path}: {_os_problem(e)}") from None
    return path


def check_readable(path: str | os.PathLike, what: str = "file") -> Path:
    """As :func:`check_file`, and the file can be opened for reading (for binary formats read elsewhere)."""
    path = check_file(path, what)
    try:
        with open(path, "rb") as f:
            f.read(1)
    except OSError as e:
        raise InputError(f"{path}: {_os_problem(e)}") from None
    return path


def read_bytes(path: str | os.PathLike, what: str = "file") -> bytes:
    """The content of an existing, readable file; InputError otherwise."""
    path = check_file(path, what)
    try:
        return _read_raw(path)
    except OSError as e:
        raise InputError(f"{path}: {_os_problem(e)}") from None


def _looks_utf16(data: bytes) -> bool:
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return True
    head = data[:200]
    # ASCII text in UTF-16 without a BOM: every other byte is NUL
    return len(head) >= 4 and any(half.count(0) > 0.8 * len(half) for half in (head[0::2], head[1::2]))


def decode_text(data: bytes, path: str | os.PathLike) -> str:
    """UTF-8 bytes (a BOM is dropped) -> str; InputError with a hint for UTF-16, Latin-1 and binary files."""
    if data.startswith((codecs.BOM_UTF32_LE, codecs.BOM_UTF32_BE)):
        raise InputError(f"{path}: saved as UTF-32 text; save it as UTF-8")
    if _looks_utf16(data):
        raise InputError(f"{path}: saved as UTF-16 text (a Windows editor's 'Unicode')? save it as UTF-8")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        if b"\x00" in data[:8192]:
            raise InputError(f"{path}: a binary file, not text (line {line}: byte 0x{data[e.start]:02x} "
                             f"is not UTF-8)") from None
        raise InputError(f"{path} line {line}: byte 0x{data[e.start]:02x} is not UTF-8 (saved as Latin-1 / "
                         f"Windows-1252? save it as UTF-8)") from None
    if "\x00" in text:
        line = text[:text.index("\x00")].count("\n") + 1
        raise InputError(f"{path} line {line}: contains a NUL byte (a binary file, not text)")
    return text


def read_text(path: str | os.PathLike, what: str = "file") -> str:
    """A UTF-8 text file (BOM accepted) as str; InputError naming the file and problem otherwise."""
    return decode_text(read_bytes(path, what), path)


# ----------------------------------------------------------------------------------------------
# TOML, JSON
# ----------------------------------------------------------------------------------------------
def read_toml(path: str | os.PathLike, what: str = "file") -> dict:
    """A TOML file as a dict; InputError naming the file, line and problem."""
    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML ({e})") from None


def read_json(path: str | os.PathLike, what: str = "file") -> object:
    """A JSON file; InputError naming the file, line and problem."""
    text = read_text(path, what)
    if not text.strip():
        raise InputError(f"{path}: empty file (expected JSON)")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (nested too deeply)") from None


def read_json_object(path: str | os.PathLike, what: str = "file") -> dict:
    """A JSON file whose top level is an object {...}."""
    doc = read_json(path, what)
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a JSON object {{...}} at the top level, got {type(doc).__name__}")
    return doc


def number(value, where: str, positive: bool = False, allow_zero: bool = False) -> float:
    """A finite TOML/JSON number (not a bool) as float; ``positive``: > 0 (>= 0 with ``allow_zero``)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{where}: expected a number, got {value!r}")
    try:
        x = float(value)
    except OverflowError:
        raise InputError(f"{where}: {value!r} is too large") from None
    if not math.isfinite(x):
        raise InputError(f"{where}: must be finite, got {value!r}")
    if positive and not (x > 0 or (allow_zero and x == 0)):
        raise InputError(f"{where}: must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return x


def array(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    """Finite numbers of exactly ``shape`` (a TOML/JSON nested list) as a float array."""
    if _has_bool(value):
        raise InputError(f"{where}: expected numbers of shape {shape}, got {value!r}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{where}: expected numbers of shape {shape}, got {value!r}") from None
    if arr.shape != shape:
        raise InputError(f"{where}: expected shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{where}: contains a non-finite value")
    return arr


def _has_bool(value) -> bool:
    if isinstance(value, bool):
        return True
    return isinstance(value, list | tuple) and any(_has_bool(v) for v in value)


def unique_names(values, where: str, what: str = "name") -> list[str]:
    """A list of non-empty strings with no repeats, else InputError naming the first repeated one."""
    if not (isinstance(values, list) and all(isinstance(v, str) for v in values)):
        raise InputError(f"{where}: expected a list of {what}s, got {values!r}")
    seen: set[str] = set()
    for i, v in enumerate(values):
        if not v.strip():
            raise InputError(f"{where}[{i}]: empty {what}")
        if v in seen:
            raise InputError(f"{where}: {what} {v!r} appears more than once (at [{values.index(v)}] and [{i}])")
        seen.add(v)
    return list(values)


# ----------------------------------------------------------------------------------------------
# CSV and Parquet tables
# ----------------------------------------------------------------------------------------------
def _check_separator(first_line: str, path) -> None:
    fields = [f.strip() for f in next(csv.reader([first_line]), [])]
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if any(sep in f for f in fields):  # "frame;camera;..." or decimal commas "1,5;2,3"
            raise InputError(f"{path} line 1: columns are separated by {name}, not commas (a spreadsheet's "
                             f"regional CSV?); save it as comma-separated CSV")


def _first_line(text: str) -> str:
    """``text.lstrip("\\r\\n").splitlines()[0]`` without splitting all of a long text (``text`` not blank)."""
    start = 0
    while text[start] in "\r\n":
        start += 1
    n = 4096
    while True:
        lines = text[start:start + n].splitlines()
        if len(lines) > 1 or start + n >= len(text):
            return lines[0]
        n *= 16


def _arrow_cells(data: bytes) -> pd.DataFrame | None:
    """The str cells of the CSV bytes ``data`` (UTF-8, header on line 1) as pyarrow's reader reads them, or None
    where it might read them otherwise than :func:`read_csv`'s pandas call, which then does.

    The same table as pandas' (``dtype=str, keep_default_na=False, skipinitialspace=True``) where the text has
    no quote character and no field starts with a space (the two places where their rules differ), no column
    name is empty (pandas names it "Unnamed: i") and every row has the header's number of fields (pyarrow
    refuses the others; pandas reads or words them), ~10x
    faster: observations.csv of the 30 x 180 x 160 scene (530k rows) 0.33 -> 0.03 s. tests/test_inputs_csv.py
    compares the two.
    """
    import pyarrow as pa
    import pyarrow.compute as pc
    from pyarrow import csv as pa_csv

    if b'"' in data:
        return None
    try:
        table = pa_csv.read_csv(  # a quoted line break cannot occur (no quotes); newlines_in_values is faster here
            pa.py_buffer(data[len(codecs.BOM_UTF8):] if data.startswith(codecs.BOM_UTF8) else data),
            parse_options=pa_csv.ParseOptions(newlines_in_values=True),
            convert_options=pa_csv.ConvertOptions(default_column_type=pa.string(), strings_can_be_null=False))
    except (pa.ArrowException, ValueError):
        return None
    if table.num_rows == 0 or any(not name or name.startswith(" ") for name in table.column_names) or any(
            pc.any(pc.starts_with(column, " ")).as_py() for column in table.columns):
        return None
    return table.to_pandas()


def _is_number_text(text: str) -> bool:
    if text.lower() in {m.lower() for m in MISSING}:
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_header_names(names: list[str], path, what: str) -> None:
    """InputError when line 1 holds numbers (or NaN) only: a file saved without its header line, whose first data
    row would otherwise be read as column names (and be refused for a name it repeats, such as NaN)."""
    if names and all(_is_number_text(n) for n in names):
        shown = ",".join(names[:4]) + (",..." if len(names) > 4 else "")
        raise InputError(f"{path} line 1: {shown!r} holds numbers, not column names: the header line is missing "
                         f"(expected: {what}; the file has {len(names)} columns)")


def read_csv(path: str | os.PathLike, header: bool = True, what: str = "a table") -> pd.DataFrame:
    """A comma-separated UTF-8 file as a DataFrame of str cells (header = line 1 unless ``header`` is False).

    Column names are stripped. InputError for an empty file, a ragged row (naming its line), other
    separators, and a column named twice. Read by pyarrow where that gives pandas' table (:func:`_arrow_cells`).
    """
    path = Path(path)
    data = read_bytes(path)
    text = decode_text(data, path)
    if not text or text.isspace():
        raise InputError(f"{path}: empty file (expected {what})")
    first = _first_line(text)
    _check_separator(first, path)
    if header:
        names = [c.strip() for c in next(csv.reader([first]))]
        _check_header_names(names, path, what)
        dup = sorted({c for c in names if names.count(c) > 1})
        if dup:
            raise InputError(f"{path} line 1: column {dup[0]!r} appears more than once")
    df = _arrow_cells(data) if header else None
    try:
        if df is None:
            df = pd.read_csv(io.StringIO(text), header=0 if header else None, dtype=str, keep_default_na=False,
                             skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise InputError(f"{path}: empty file (expected {what})") from None
    except (pd.errors.ParserError, ValueError, csv.Error) as e:  # a ragged or corrupt file: say where
        raise InputError(f"{path}: cannot be read as CSV ({str(e).strip().splitlines()[-1]})") from None
    df.columns = [str(c).strip() for c in df.columns]
    return df


def read_parquet(path: str | os.PathLike) -> pd.DataFrame:
    """A Parquet file as a DataFrame; InputError naming the file for anything unreadable."""
    path = check_readable(path)
    try:
        return pd.read_parquet(path)
    except Exception as e:  # pyarrow raises many types for a corrupt file: one line naming it
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise InputError(f"{path}: cannot be read as Parquet ({type(e).__name__}: {msg})") from None


def read_table(path: str | os.PathLike, required: list[str], what: str,
               allow_empty: bool = False) -> tuple[pd.DataFrame, bool]:
    """A CSV (str cells) or .parquet table with the ``required`` columns; returns (table, is_csv).

    what: what the rows are, for messages ("observations"). allow_empty: a header-only file is fine.
    """
    path = Path(path)
    is_csv = path.suffix.lower() != ".parquet"
    df = read_csv(path, what=f"a header and {what}") if is_csv else read_parquet(path)
    df.columns = [str(c).strip() for c in df.columns]
    for col in required:
        if col not in df.columns:
            close = difflib.get_close_matches(col, df.columns, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise InputError(f"{path}: missing column '{col}'{hint}; found {', '.join(df.columns)}")
    if len(df) == 0 and not allow_empty:
        raise InputError(f"{path}: no {what} (the file has a header only)")
    return df, is_csv


def cell(value) -> str:
    """A table cell as messages quote it (numpy scalars from Parquet as plain Python values)."""
    return repr(value.item() if isinstance(value, np.generic) else value)


def row_name(i: int, is_csv: bool) -> str:
    """Row ``i`` (0-based, of the data) as a message names it: the CSV line (header = line 1), or the row."""
    return f"line {i + 2}" if is_csv else f"row {i}"


def numeric_column(df: pd.DataFrame, col: str, path, is_csv: bool, allow_missing: bool) -> np.ndarray:
    """Column ``col`` as float (NaN where missing if ``allow_missing``); InputError naming the bad row."""
    raw = df[col]
    values = _arrow_floats(raw)
    if values is None:
        try:  # the common case, every cell a number: one vectorised parse
            values = raw.astype("float64").to_numpy(dtype=float)
        except (ValueError, TypeError):
            values = None
    if values is not None and not np.isnan(values).any():
        return _finite(values, raw, col, path, is_csv)
    text = raw.astype(str).str.strip()
    missing = (raw.isna() | text.isin(MISSING)).to_numpy()
    values = pd.to_numeric(raw.where(~missing), errors="coerce").to_numpy(dtype=float)
    bad = ~missing & np.isnan(values)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} {cell(raw.iloc[i])} is not a number")
    if not allow_missing and missing.any():
        i = int(np.argmax(missing))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} is empty")
    return _finite(values, raw, col, path, is_csv)


def _arrow_floats(raw: pd.Series) -> np.ndarray | None:
    """A pyarrow-backed text column as float64 by pyarrow's cast (one pass in C; pandas' astype converts every
    cell to a Python str and float: 0.14 -> 0.02 s for the four columns of a 530k-row observations.csv), or None
    for another column or a cell the cast refuses (the caller parses those as before). The cast accepts a
    subset of the texts Python's float() does, with the same correctly rounded values (tests/test_inputs_csv.py)."""
    if not (isinstance(raw.dtype, pd.StringDtype) and raw.dtype.storage == "pyarrow"):
        return None
    import pyarrow as pa
    import pyarrow.compute as pc

    try:
        return np.array(pc.cast(pa.array(raw), pa.float64()).to_numpy(zero_copy_only=False), dtype=float)
    except pa.ArrowException:
        return None


def _finite(values: np.ndarray, raw: pd.Series, col: str, path, is_csv: bool) -> np.ndarray:
    """values, unless one is infinite: then InputError naming its row."""
    if np.isinf(values).any():
        i = int(np.argmax(np.isinf(values)))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} is infinite ({cell(raw.iloc[i])})")
    return values


def frame_column(df: pd.DataFrame, path, is_csv: bool, col: str = "frame") -> np.ndarray:
    """Column ``col`` as int64 frame numbers, each an integer in [0, MAX_FRAME]; InputError naming the row."""
    f = numeric_column(df, col, path, is_csv, allow_missing=False)
    bad = (f < 0) | (f != np.round(f))
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} {cell(df[col].iloc[i])} is not an integer >= 0")
    big = f > MAX_FRAME
    if big.any():
        i = int(np.argmax(big))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} {cell(df[col].iloc[i])} is larger than {MAX_FRAME:,} "
                         f"(the most batgraph accepts; a typo?)")
    return f.astype(np.int64)


def check_frame_gaps(frames: np.ndarray, path, is_csv: bool, rows: np.ndarray | None = None,
                     max_gap: int = MAX_FRAME_GAP, where=None) -> None:
    """InputError naming the row when consecutive observed frames (sorted) are more than ``max_gap`` apart.

    frames: frame numbers in file order, shape (N,); rows: their 0-based data rows in the file (default
    0..N-1), for the message; where: optional function row -> location text (default "PATH line N").
    """
    if len(frames) < 2:
        return
    uniq = np.unique(frames)
    gaps = np.diff(uniq)
    if (gaps > max_gap).any():
        k = int(np.argmax(gaps > max_gap))
        after, before = int(uniq[k + 1]), int(uniq[k])
        i = int(np.argmax(frames == after))
        i = int(rows[i]) if rows is not None else i
        place = where(i) if where is not None else f"{path} {row_name(i, is_csv)}"
        raise InputError(f"{place}: frame {after} follows frame {before} after a gap of "
                         f"{after - before:,} frames (at most {max_gap:,}: every frame in between is held in memory); "
                         f"a typo? else split the recording into sessions")


def label_codes(df: pd.DataFrame, col: str, path, is_csv: bool) -> Labels:
    """Column ``col`` as stripped, non-empty labels (batgraph.labels: codes into the distinct names);
    InputError naming the first empty row (a missing cell, or text that is blank or "nan")."""
    labels = factorize(df[col], strip=True)
    empty = labels.rows_where(np.isin(labels.names, ["", "nan"])) | (labels.codes < 0)
    if empty.any():
        i = int(np.argmax(empty))
        raise InputError(f"{path} {row_name(i, is_csv)}: {col} is empty")
    return labels


def label_column(df: pd.DataFrame, col: str, path, is_csv: bool) -> pd.Series:
    """Column ``col`` as stripped, non-empty str (:func:`label_codes`); InputError naming the first empty row."""
    return pd.Series(label_codes(df, col, path, is_csv).column(), index=df.index)


# ----------------------------------------------------------------------------------------------
# memory
# ----------------------------------------------------------------------------------------------
def physical_memory_bytes() -> int | None:
    """The machine's physical memory [bytes], or None where the OS does not say."""
    try:
        n = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    return int(n) if n > 0 else None


def dense_bytes(n_cams: int, n_frames: int, n_markers: int) -> int:
    """Estimated bytes of the dense layout of one session: the (C, F, M) observation arrays (u, v, weight:
    24 bytes per cell) plus one method's state and covariance per (frame, marker) (6 + 36 floats)."""
    return int(n_frames) * int(n_markers) * (24 * int(n_cams) + 8 * (6 + 36))


def check_dense_memory(n_cams: int, n_frames: int, n_markers: int, where: str) -> None:
    """InputError when the dense arrays of a session (:func:`dense_bytes`) exceed the physical memory."""
    need = dense_bytes(n_cams, n_frames, n_markers)
    have = physical_memory_bytes()
    if have is not None and need > have:
        raise InputError(f"{where}: {n_frames:,} frames x {n_markers} markers x {n_cams} cameras need about "
                         f"{need / 2**30:.1f} GiB in memory but this machine has {have / 2**30:.1f} GiB; "
                         f"split the recording into shorter sessions")


# ----------------------------------------------------------------------------------------------
# output places (checked before any work; nothing is created here)
# ----------------------------------------------------------------------------------------------
def _can_write(folder: Path) -> bool:
    """Whether new files can be created in the existing ``folder`` (tests replace it: root may write anywhere)."""
    return os.access(folder, os.W_OK | os.X_OK)


def _check_ancestors(path: Path, target: Path) -> None:
    """The nearest existing ancestor of ``target`` (itself included) must be a writable folder."""
    a = target
    try:
        while not a.exists() and a != a.parent:
            a = a.parent
        if not a.is_dir():
            raise InputError(f"{path}: {a} is a file, not a folder")
    except OSError as e:
        raise InputError(f"{path}: cannot be checked ({e.strerror or type(e).__name__})") from None
    if not _can_write(a):
        raise InputError(f"{path}: cannot write in {a} (permission denied or a read-only file system)")


def check_output_dir(path: str | os.PathLike, what: str = "output folder") -> Path:
    """``path`` as a Path if it is, or can become, a folder batgraph can write into; InputError otherwise."""
    path = Path(path)
    try:
        if path.exists() and not path.is_dir():
            raise InputError(f"{path}: exists and is a file; the {what} must be a folder")
    except OSError as e:
        raise InputError(f"{path}: cannot be checked ({e.strerror or type(e).__name__})") from None
    _check_ancestors(path, path)
    return path


def check_output_file(path: str | os.PathLike, what: str = "output file") -> Path:
    """``path`` as a Path if a file can be written there (it may exist and is then replaced)."""
    path = Path(path)
    try:
        if path.is_dir():
            raise InputError(f"{path}: is a folder; the {what} must be a file path")
    except OSError as e:
        raise InputError(f"{path}: cannot be checked ({e.strerror or type(e).__name__})") from None
    _check_ancestors(path, path.parent)
    return path


def os_error_message(e: OSError) -> str:
    """One line for an OS error while reading or writing: the path, and what to do."""
    hints = {28: "no space left on the device", 30: "read-only file system", 13: "permission denied",
             122: "disk quota exceeded", 36: "file name too long"}
    problem = hints.get(e.errno or -1, e.strerror or str(e) or type(e).__name__)
    where = e.filename if e.filename is not None else "writing"
    if e.filename2 is not None:
        where = f"{e.filename} -> {e.filename2}"
    unchanged = getattr(e, "unchanged", None)  # (folder, existed): set by batgraph.atomic.result_folder
    if unchanged is not None:
        folder, existed = unchanged
        problem += (f"; {folder} still holds the previous result, unchanged" if existed else
                    f"; nothing was written to {folder}")
        if e.errno in (28, 122):
            problem += " (free some space and run again)"
    return f"{where}: {problem}"


# ----------------------------------------------------------------------------------------------
# command-line option types (argparse ``type=``): one set for every command
# ----------------------------------------------------------------------------------------------
def _float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return x


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def finite_float(text: str) -> float:
    """A finite number (angles, offsets)."""
    return _float(text)


def positive_float(text: str) -> float:
    """A finite number > 0 (rates, lengths, noise levels, thresholds in sigmas)."""
    x = _float(text)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return x


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    x = _float(text)
    if not x >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return x


def fraction(text: str) -> float:
    """A finite number in [0, 1) (a rate of events)."""
    x = _float(text)
    if not 0 <= x < 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return x


def probability(text: str) -> float:
    """A finite number in [0, 1] (a likelihood threshold)."""
    x = _float(text)
    if not 0 <= x <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text!r}")
    return x


def angle_deg(text: str) -> float:
    """A finite angle in [-360, 360] degrees."""
    x = _float(text)
    if not -360 <= x <= 360:
        raise argparse.ArgumentTypeError(f"must be an angle in [-360, 360] degrees, got {text!r}")
    return x


def positive_int(text: str) -> int:
    """An integer >= 1 (counts, workers)."""
    v = _int(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return v


def nonnegative_int(text: str) -> int:
    """An integer >= 0 (indices, seeds)."""
    v = _int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return v


def frame_count(text: str) -> int:
    """A number of frames, 1 .. MAX_FRAME."""
    v = positive_int(text)
    if v > MAX_FRAME:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_FRAME:,}, got {text!r}")
    return v


def image_side(text: str) -> int:
    """An image width or height [px], 1 .. 100000."""
    v = positive_int(text)
    if v > 100_000:
        raise argparse.ArgumentTypeError(f"must be at most 100000 px, got {text!r}")
    return v
