"""batgraph.labels: a label column as codes gives the same answers as the per-row string operations."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from batgraph.labels import factorize, text_column

ROWS = ["cam2", " cam1", "cam10", "cam1 ", "cam2", "Cam1", "é", "cam1", "", "nan"]


@pytest.mark.parametrize("dtype", ["str", object])
def test_codes_give_the_stripped_text(dtype):
    col = pd.Series(ROWS, dtype=dtype)
    labels = factorize(col, strip=True)
    assert labels.text().tolist() == col.astype(str).str.strip().tolist()
    assert len(labels.names) == len(set(labels.names))  # " cam1", "cam1 " and "cam1": one name
    assert factorize(col).text().tolist() == ROWS  # without strip: the text as is


def test_missing_cells_get_minus_one():
    labels = factorize(pd.Series(["a", None, "b", np.nan], dtype=object))
    assert labels.codes.tolist()[1::2] == [-1, -1]
    assert labels.text().tolist() == ["a", None, "b", None]
    assert labels.rows_where(np.ones(len(labels.names), bool)).tolist() == [True, False, True, False]


def test_numbers_and_mixed_objects_as_pandas_writes_them():
    for values in ([1, 2, 1], [1.0, 2.5, 1.0], [1, "1", 1.0, True]):  # mixed: 1, 1.0 and True stay apart
        col = pd.Series(values, dtype=object if isinstance(values[1], str) else None)
        assert factorize(col).text().tolist() == col.astype(str).tolist()


def test_positions_on_an_axis():
    labels = factorize(pd.Series(["b", "x", "a", "b"], dtype="str"))
    assert labels.positions(["a", "b", "c"]).tolist() == [1, -1, 0, 1]
    assert labels.positions([]).tolist() == [-1] * 4
    assert factorize(pd.Series([], dtype="str")).positions(["a"]).tolist() == []


def test_sort_keys_order_rows_as_pandas_sorts_their_text():
    rng = np.random.default_rng(0)
    col = pd.Series(rng.choice(["m10", "m2", "M1", "m1", "ä", "z", "m1 "], size=200), dtype="str")
    labels = factorize(col)
    order = np.argsort(labels.sort_keys(), kind="stable")
    assert order.tolist() == col.sort_values(kind="stable").index.tolist()


def test_text_column_is_the_column_pandas_makes_of_str():
    names, codes = ["cam1", "flügel", "x"], np.array([2, 0, 0, 1, -1, 2])
    got = pd.Series(text_column(names, codes))
    want = pd.Series(np.array(["x", "cam1", "cam1", "flügel", None, "x"], dtype=object))
    pd.testing.assert_series_equal(got, want, check_exact=True)
    assert got.dtype == want.dtype and type(got.array) is type(want.array)
    assert pd.Series(text_column(names, np.zeros(0, np.int64))).dtype == want.dtype
