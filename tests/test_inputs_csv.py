"""batgraph.inputs.read_csv: pyarrow's reading (where it applies) gives exactly the table pandas' reading gives."""

from __future__ import annotations

import io

import numpy as np
import pandas as pd
import pytest

from batgraph import inputs

SAME = {
    "plain": "frame,camera,marker,u,v\n0,cam1,a,1.5,2.25\n1,cam2,b,-3,4e-3\n",
    "crlf and a BOM": "\ufeffframe,camera,marker,u,v\r\n0,cam1,a,1.5,2.25\r\n1,cam2,b,-3,4e-3\r\n",
    "no final line break": "frame,camera,marker,u,v\n0,cam1,a,1.5,2.25",
    "blank lines": "\n\nframe,camera,marker,u,v\n0,cam1,a,1.5,2.25\n\n1,cam2,b,,\n\n",
    "empty cells and missing words": "frame,camera,marker,u,v\n0,cam1,a,,\n1,cam2,b,nan,NA\n2,cam2,c,None,NaN\n",
    "trailing spaces, tabs and unicode": "frame,camera,marker,u,v\n0,cam 1 ,flügel\t,1.5 ,2\n1,c,b,3,4\n",
    "numbers as text": "frame,camera,marker,u,v\n007,01,1,1.50,2.0000\n1e2,2,3,inf,-0\n",
    "one column": "frame\n0\n1\n",
    "spaced header": "frame ,camera,marker,u,v\n0,cam1,a,1,2\n",
}
PANDAS_ONLY = {
    "quotes": 'frame,camera,marker,u,v\n0,"cam,1",a,1,2\n',
    "space after a comma": "frame,camera,marker,u,v\n0, cam1,a,1,2\n",
    "space at a line start": "frame,camera,marker,u,v\n 0,cam1,a,1,2\n",
    "space before a header name": "frame, camera,marker,u,v\n0,cam1,a,1,2\n",
    "an extra field": "frame,camera,marker,u,v\n0,cam1,a,1,2,3\n",
    "a missing field": "frame,camera,marker,u,v\n0,cam1,a,1\n",
    "header only": "frame,camera,marker,u,v\n",
    "an empty column name": "frame,camera,,u,v\n0,cam1,a,1,2\n",
}


def _pandas(text: str) -> pd.DataFrame:
    df = pd.read_csv(io.StringIO(text.removeprefix("\ufeff")), dtype=str, keep_default_na=False,
                     skipinitialspace=True)
    df.columns = [str(c).strip() for c in df.columns]
    return df


@pytest.mark.parametrize("name", list(SAME))
def test_pyarrow_reads_what_pandas_reads(name, tmp_path):
    text = SAME[name]
    assert inputs._arrow_cells(text.encode()) is not None  # the fast path applies
    path = tmp_path / "t.csv"
    path.write_bytes(text.encode())
    got = inputs.read_csv(path)
    pd.testing.assert_frame_equal(got, _pandas(text), check_exact=True)
    assert type(got.index) is pd.RangeIndex
    assert [type(got[c].array) for c in got] == [type(_pandas(text)[c].array) for c in got]


@pytest.mark.parametrize("name", list(PANDAS_ONLY))
def test_where_the_readers_differ_pandas_reads(name):
    assert inputs._arrow_cells(PANDAS_ONLY[name].encode()) is None


def test_first_line_of_a_long_text():
    assert inputs._first_line("\r\n\n" + "x" * 100_000 + "\r\nrest") == "x" * 100_000
    assert inputs._first_line("a,b\r\nc") == "a,b"
    assert inputs._first_line("\na\x0bb\n") == "a"  # splitlines' other breaks, as before


def test_pyarrow_numbers_are_python_floats():
    """The cast takes a subset of the texts float() takes, with the same value (else the caller's parse runs)."""
    texts = ["1.5", "-0", "+.5", "5.", "1e-400", "1.5e+308", "1e309", "-inf", "nan", "0.1", "123456789.123456789",
             "4.9406564584124654e-324", "2.2250738585072011e-308", "%.17g" % (2 / 3)]
    got = inputs._arrow_floats(pd.Series(texts, dtype="str"))
    want = np.array([float(t) for t in texts])
    assert got.tobytes() == want.tobytes()  # bit for bit, signed zeros and NaN included
    for refused in (["1_000"], [" 1"], ["1 "], ["infinity "], [""]):
        assert inputs._arrow_floats(pd.Series(refused, dtype="str")) is None
    assert inputs._arrow_floats(pd.Series([1.5])) is None  # not text: the caller's parse


def test_numbers_with_python_only_spellings_still_parse(tmp_path):
    df = pd.DataFrame({"u": pd.Series(["1_000", " 2 ", "Infinity"], dtype="str")})
    with pytest.raises(inputs.InputError, match="infinite"):
        inputs.numeric_column(df, "u", tmp_path / "t.csv", True, allow_missing=False)
    np.testing.assert_array_equal(inputs.numeric_column(df.iloc[:2], "u", "t.csv", True, allow_missing=False),
                                  [1000.0, 2.0])
