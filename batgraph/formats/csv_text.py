"""CSV text of a table, the same characters ``DataFrame.to_csv(index=False, float_format=...)`` writes, ~3x faster.

Why not pandas itself: its float formatting runs per value through several layers (NaN masks, object
arrays); on the 30 x 180 x 160 scene reprojection.csv (1.06 M rows, 10 columns) took 5.2 s in
``to_csv`` and 1.6 s here (issue "Speed a user feels"). Here every row is one ``%`` format of a
template over Python lists. pyarrow's CSV writer is faster still but writes other text (shortest
round-trip floats, ``true`` for ``True``), which would change the contract's files.

Same text as pandas: floats by ``float_format`` with NaN as an empty field, integers ``%d``, booleans
``True``/``False``, anything else ``str``; "\\n" line ends. A table whose text fields would need CSV
quoting (a comma, quote or line break) or whose columns are not plain numbers, booleans and strings is
handed to pandas unchanged. tests/test_csv_text.py compares with ``to_csv``.

Fixed-point formats (``"%.6f"``: reprojection.csv, observations.csv) take a faster path still,
:func:`fixed_csv_bytes`: every field of every row is built as bytes by numpy at once, no Python object per
value (reprojection.csv of the 30 x 180 x 160 scene: ~1.5 s of CPU per-row, ~0.2 s this way). A float's
digits come from rounding x * 10^N to the nearest integer, which is Python's correctly rounded ``%`` text
except where x * 10^N lies within a few units in the last place of a tie (.5): those few values, and any
too large for the integer path or not finite, are formatted by ``%`` itself.
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

_NEEDS_QUOTES = (",", '"', "\n", "\r")
CHUNK_ROWS = 100_000
_FIXED = re.compile(r"%\.(\d)f")  # "%.Nf", N = 0..9: the formats fixed_csv_bytes writes itself
_EXACT_BELOW = 2.0**50  # |x| * 10^N below this: the integer path (int64, and room for the tie test)
_PAIRS = np.array([[48 + i // 10, 48 + i % 10] for i in range(100)], np.uint8)  # "00" .. "99"


def csv_text(table: pd.DataFrame, float_format: str) -> str:
    """The CSV text of ``table`` (header, no index), as ``table.to_csv(index=False, float_format=float_format)``."""
    fields, columns = [], []
    for name in table.columns:
        col = table[name]
        kind = col.dtype.kind if isinstance(col.dtype, np.dtype) else None
        if kind == "f":
            values = col.to_numpy()
            if np.isnan(values).any():  # pandas writes NaN as an empty field
                columns.append([float_format % v if v == v else "" for v in values.tolist()])
                fields.append("%s")
            else:
                columns.append(values.tolist())
                fields.append(float_format)
        elif kind in ("i", "u", "b"):
            columns.append(col.to_numpy().tolist())
            fields.append("%d" if kind != "b" else "%s")
        elif kind == "O" or isinstance(col.dtype, pd.CategoricalDtype | pd.StringDtype):
            values = col.astype(str).tolist()
            if col.isna().any() or any(c in v for v in set(values) for c in _NEEDS_QUOTES):
                return table.to_csv(index=False, float_format=float_format)
            columns.append(values)
            fields.append("%s")
        else:
            return table.to_csv(index=False, float_format=float_format)
    if any(c in str(name) for name in table.columns for c in _NEEDS_QUOTES):
        return table.to_csv(index=False, float_format=float_format)
    if not columns or len(table) == 0:
        return table.to_csv(index=False, float_format=float_format)
    template = ",".join(fields) + "\n"
    return ",".join(str(name) for name in table.columns) + "\n" + "".join(
        [template % row for row in zip(*columns, strict=True)])


def _digits(n: np.ndarray) -> np.ndarray:
    """(rows, width) uint8: the decimal digits of the non-negative int64 ``n``, right-aligned, with 0 bytes
    (dropped later) in place of leading zeros."""
    width = len(str(int(n.max()))) if len(n) else 1
    out = np.empty((len(n), width), np.uint8)
    rest = n.copy()
    for k in range(width):  # k-th digit from the right
        out[:, width - 1 - k] = np.where((n >= 10**k) | (k == 0), rest % 10 + 48, 0)
        rest //= 10
    return out


def _right_aligned(texts: list[bytes], width: int) -> np.ndarray:
    """(len(texts), width) uint8: each text at the right end, 0 bytes before it."""
    out = np.zeros((len(texts), width), np.uint8)
    for i, t in enumerate(texts):
        if t:
            out[i, width - len(t):] = np.frombuffer(t, np.uint8)
    return out


def _fixed_field(x: np.ndarray, decimals: int, float_format: str) -> np.ndarray:
    """(rows, width) uint8 of ``float_format % x`` ("%.{decimals}f"), NaN as an empty field (pandas)."""
    scale = 10**decimals
    nan = np.isnan(x)
    with np.errstate(over="ignore", invalid="ignore"):  # inf, NaN and huge values go to the slow path
        y = np.abs(x) * scale
        near_tie = np.abs(y - np.floor(y) - 0.5) <= 4 * np.spacing(y)
        fast = (y < _EXACT_BELOW) & ~near_tie
    n = np.where(fast, np.rint(np.where(fast, y, 0)), 0).astype(np.int64)
    whole, part = np.divmod(n, scale)
    sign = np.where(np.signbit(x) & fast, ord("-"), 0).astype(np.uint8)[:, None]
    pieces = [sign, _digits(whole)]
    if decimals:
        frac = np.empty((len(x), decimals), np.uint8)
        for k in range(decimals - 2, -1, -2):  # two digits per step, from the right, by table
            frac[:, k:k + 2] = _PAIRS[part % 100]
            part //= 100
        if decimals % 2:
            frac[:, 0] = part + 48
        pieces += [np.full((len(x), 1), ord("."), np.uint8), frac]
    field = np.concatenate(pieces, axis=1)
    field[~fast] = 0  # NaN: empty; the rest below
    slow = np.flatnonzero(~fast & ~nan)
    if len(slow):
        texts = [(float_format % v).encode() for v in x[slow].tolist()]
        width = max(field.shape[1], max(map(len, texts)))
        field = np.concatenate([np.zeros((len(x), width - field.shape[1]), np.uint8), field], axis=1)
        field[slow] = _right_aligned(texts, width)
    return field


def _label_field(col: pd.Series) -> np.ndarray | None:
    """(rows, width) uint8 of the text of each cell of a string/categorical/bool column; None when a cell is
    missing or its text would need CSV quoting (or holds a NUL byte)."""
    if col.isna().any():
        return None
    codes, uniques = pd.factorize(col)
    texts = [str(u).encode("utf-8") for u in uniques]
    if any(c.encode() in t for t in texts for c in (*_NEEDS_QUOTES, "\0")):
        return None
    table = _right_aligned(texts, max(map(len, texts), default=1))
    return table[codes]


def fixed_csv_bytes(table: pd.DataFrame, float_format: str, header: bool = True) -> bytes | None:
    """The UTF-8 bytes of ``csv_text(table, float_format)`` for a fixed-point ``float_format`` ("%.Nf"), built by
    numpy (module docstring); None where this path does not apply (another format, a column type or text
    that :func:`csv_text` hands to pandas), for the caller to use csv_text."""
    found = _FIXED.fullmatch(float_format)
    if found is None or len(table) == 0 or len(table.columns) == 0:
        return None
    names = [str(name) for name in table.columns]
    if any(c in name or "\0" in name for name in names for c in _NEEDS_QUOTES):
        return None
    comma = np.full((len(table), 1), ord(","), np.uint8)
    fields = []
    for name in table.columns:
        col = table[name]
        kind = col.dtype.kind if isinstance(col.dtype, np.dtype) else None
        if kind == "f":
            field = _fixed_field(col.to_numpy(np.float64), int(found.group(1)), float_format)
        elif kind in ("i", "u"):
            v = col.to_numpy()
            if len(v) and (v.min() < -(2**62) or v.max() > 2**62):
                return None
            v = v.astype(np.int64)
            field = np.concatenate([np.where(v < 0, ord("-"), 0).astype(np.uint8)[:, None], _digits(np.abs(v))],
                                   axis=1)
        elif kind == "b" or kind == "O" or isinstance(col.dtype, pd.CategoricalDtype | pd.StringDtype):
            field = _label_field(col)
            if field is None:
                return None
        else:
            return None
        fields += [field, comma]
    fields[-1] = np.full((len(table), 1), ord("\n"), np.uint8)
    rows = np.concatenate(fields, axis=1).ravel()
    body = rows[rows != 0].tobytes()
    return (",".join(names) + "\n").encode("utf-8") + body if header else body


def write_csv(path, table: pd.DataFrame, float_format: str, chunk_rows: int = CHUNK_ROWS) -> None:
    """Write :func:`csv_text` of ``table`` to ``path`` atomically, ``chunk_rows`` rows at a time (the text of
    a million-row table held at once is ~100 MB more peak memory than pandas' own chunked writer); a
    fixed-point format through :func:`fixed_csv_bytes` where it applies."""
    from ..atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as out:
        for start in range(0, max(len(table), 1), chunk_rows):
            chunk = table.iloc[start:start + chunk_rows]
            data = fixed_csv_bytes(chunk, float_format, header=start == 0)
            if data is None:
                text = csv_text(chunk, float_format)
                data = (text if start == 0 else text.split("\n", 1)[1]).encode("utf-8")
            out.write(data)
