"""batgraph.formats.csv_text writes the characters pandas' to_csv writes (the contract's CSV text)."""

import numpy as np
import pandas as pd
import pytest

from batgraph.formats.csv_text import csv_text


def _table(n=500, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n) * 10.0 ** rng.integers(-9, 6, n)
    x[::37] = np.nan
    return pd.DataFrame({
        "method": pd.Categorical(rng.choice(["smoother", "filter"], n)),
        "frame": rng.integers(0, 60000, n),
        "camera": rng.choice(["cam1", "cam 2", "Cam_3"], n),
        "x": x,
        "time_s": np.arange(n) / 120.0,
        "whole": np.arange(n, dtype=float),  # integral floats: "%.9g" writes them without a decimal point
        "tiny": np.full(n, -1e-300),
        "outlier": rng.random(n) < 0.1,
        "n_views": rng.integers(0, 30, n).astype(np.int32),
    })


@pytest.mark.parametrize("fmt", ["%.9g", "%.6f", "%.4f"])
def test_same_text_as_pandas(fmt):
    table = _table()
    assert csv_text(table, fmt) == table.to_csv(index=False, float_format=fmt)


def test_fields_that_need_quoting_and_empty_tables_go_to_pandas():
    table = _table(20)
    table.loc[3, "camera"] = 'cam "4", left'
    assert csv_text(table, "%.6f") == table.to_csv(index=False, float_format="%.6f")
    assert '"cam ""4"", left"' in csv_text(table, "%.6f")
    empty = table.iloc[:0]
    assert csv_text(empty, "%.6f") == empty.to_csv(index=False, float_format="%.6f")
    with_none = table.astype({"camera": object})
    with_none.loc[2, "camera"] = None
    assert csv_text(with_none, "%.6f") == with_none.to_csv(index=False, float_format="%.6f")


def test_the_pipeline_tables_write_as_pandas_would(session_folder, tmp_path):
    """The real result tables (categoricals, NaN covariances of unestimated cells, booleans) of a reconstruct."""
    from batgraph.pipeline import reconstruct

    result = reconstruct(session_folder, tmp_path / "out", methods=["smoother", "triangulate"], viewer="none")
    for table, fmt in ((result.trajectories, "%.9g"), (result.reprojection, "%.6f")):
        assert csv_text(table, fmt) == table.to_csv(index=False, float_format=fmt)
    assert (tmp_path / "out" / "trajectories.csv").read_text() == result.trajectories.to_csv(index=False,
                                                                                             float_format="%.9g")


def test_chunked_file_is_the_same_text(tmp_path):
    """write_csv in chunks (one with NaN, one without) gives one header and pandas' text."""
    from batgraph.formats.csv_text import write_csv

    table = _table(250)
    write_csv(tmp_path / "t.csv", table, "%.9g", chunk_rows=37)
    assert (tmp_path / "t.csv").read_text() == table.to_csv(index=False, float_format="%.9g")
    write_csv(tmp_path / "e.csv", table.iloc[:0], "%.9g")
    assert (tmp_path / "e.csv").read_text() == table.iloc[:0].to_csv(index=False, float_format="%.9g")
