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
"""

from __future__ import annotations

import numpy as np
import pandas as pd

_NEEDS_QUOTES = (",", '"', "\n", "\r")
CHUNK_ROWS = 100_000


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


def write_csv(path, table: pd.DataFrame, float_format: str, chunk_rows: int = CHUNK_ROWS) -> None:
    """Write :func:`csv_text` of ``table`` to ``path`` atomically, ``chunk_rows`` rows at a time (the text of
    a million-row table held at once is ~100 MB more peak memory than pandas' own chunked writer)."""
    from ..atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as out:
        for start in range(0, max(len(table), 1), chunk_rows):
            text = csv_text(table.iloc[start:start + chunk_rows], float_format)
            out.write(text if start == 0 else text.split("\n", 1)[1])
