"""Text labels (camera and marker names) as integer codes into their distinct names.

A label column of N rows holds a few dozen distinct names: factorized once (``pd.factorize``), every
per-row question (is it empty, is it a known camera, which position on an axis, which rows repeat a key,
how do rows sort by it) is answered on the K distinct names and then looked up by code, instead of a
string operation over all N rows. Knows nothing of files or of which columns are labels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class Labels:
    """A label column as codes: ``names[codes]`` is its text.

    codes: (N,) int64 into ``names``, -1 where the cell is missing (NaN / None).
    names: (K,) object array of str, distinct, in the order of their first row.
    """

    codes: np.ndarray
    names: np.ndarray

    def __len__(self) -> int:
        return len(self.codes)

    def text(self) -> np.ndarray:
        """(N,) object array of str, the label of each row (None where missing)."""
        return np.append(self.names, None)[self.codes]

    def column(self) -> pd.api.extensions.ExtensionArray | np.ndarray:
        """The text of each row as a pandas str column (:func:`text_column`); missing rows as missing values."""
        return text_column(self.names, self.codes)

    def rows_where(self, name_mask: np.ndarray) -> np.ndarray:
        """(N,) bool: the rows whose name satisfies ``name_mask`` ((K,) bool over ``names``); missing rows False."""
        return np.append(np.asarray(name_mask, bool), False)[self.codes]

    def positions(self, order: Sequence[str]) -> np.ndarray:
        """(N,) int64: each row's position in ``order`` (e.g. the rig's camera names), -1 where its name is not
        in ``order`` or the row is missing."""
        at = pd.Index(list(order)).get_indexer(self.names) if len(self.names) else np.zeros(0, np.int64)
        return np.append(at, -1).astype(np.int64)[self.codes]

    def sort_keys(self) -> np.ndarray:
        """(N,) int64 that orders rows as their labels sort as strings (Python's str order, as pandas sorts
        a str column); missing rows last."""
        rank = np.empty(len(self.names) + 1, np.int64)
        rank[np.argsort(self.names.astype(str), kind="stable")] = np.arange(len(self.names))
        rank[-1] = len(self.names)
        return rank[self.codes]


def factorize(values: pd.Series | np.ndarray | Sequence, strip: bool = False) -> Labels:
    """The :class:`Labels` of a column, each cell's text as ``str(cell)`` (``.strip()``-ed with ``strip``).

    A str column is factorized as is and only its distinct names are converted and stripped (two cells that
    differ by surrounding spaces get one code with ``strip``); any other column (numbers, mixed objects from
    Parquet) is converted cell by cell first (``astype(str)``), so its text is exactly pandas'. Missing cells
    (NaN / None) get code -1.
    """
    s = values if isinstance(values, pd.Series) else pd.Series(values, dtype=object if not len(values) else None)
    if not (pd.api.types.is_string_dtype(s.dtype) and (s.dtype != object or pd.api.types.infer_dtype(
            s, skipna=True) in ("string", "empty"))):
        s = s.where(s.isna(), s.astype(str))
    codes, uniques = pd.factorize(s)
    names = np.asarray(pd.Index(uniques).astype(str), dtype=object)
    if strip:
        names = np.asarray([n.strip() for n in names], dtype=object)
        merged, names = pd.factorize(names)  # " a" and "a" are one label now
        codes = np.append(merged, -1)[codes]
        names = np.asarray(names, dtype=object)
    return Labels(np.asarray(codes, np.int64), names)



def text_column(names: Sequence[str], codes: np.ndarray) -> pd.api.extensions.ExtensionArray | np.ndarray:
    """``names[codes]`` (-1: missing) as the column pandas makes of that many Python str: its pyarrow-backed str
    array gathered by pyarrow's take, without a Python object per row (1M rows: 0.09 -> 0.02 s); an object array
    where pandas' default text dtype is not pyarrow's."""
    names = np.asarray(names, dtype=object)
    if not _TEXT_IS_ARROW:
        return np.append(names, None)[codes]
    import pyarrow as pa

    codes = np.asarray(codes, np.int64)
    return pd.array(pa.array(names, pa.large_string()).take(pa.array(codes, mask=codes < 0)), dtype=_TEXT_DTYPE)


_TEXT_DTYPE = pd.Series(np.array(["a"], dtype=object)).dtype  # pandas' dtype for a column of str
_TEXT_IS_ARROW = isinstance(_TEXT_DTYPE, pd.StringDtype) and _TEXT_DTYPE.storage == "pyarrow"
