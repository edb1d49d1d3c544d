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


def test_fixed_point_bytes_are_pythons_text_at_ties_and_edges():
    """fixed_csv_bytes (numpy-built fields) gives pandas' characters, also where rounding is delicate: exact
    ties (odd multiples of 1/128 at "%.6f"), the nearest floats either side of them, -0.0 and negatives
    that round to zero, carries into the integer part, values too large for its integer path, inf, NaN."""
    from batgraph.formats.csv_text import fixed_csv_bytes

    rng = np.random.default_rng(7)
    ties = (2 * rng.integers(0, 2**20, 300) + 1) / 128.0
    edges = np.array([0.0, -0.0, -1e-9, 1e-9, 0.9999996, 0.9999995, -0.9999996, 2.5e-7, 5e-7, 1.5e-6, 4e9,
                      9.2e12, -3.3e15, 1e300, -1e300, np.inf, -np.inf, np.nan, 123456.0000005])
    x = np.concatenate([ties, np.nextafter(ties, 0), np.nextafter(ties, 1e9), edges,
                        rng.normal(size=3000) * 10.0 ** rng.integers(-8, 11, 3000)])
    x = np.concatenate([x, -x])
    table = pd.DataFrame({
        "marker": rng.choice(["wrist_r", "élbow", "digit 3"], len(x)),
        "frame": rng.integers(-5, 10**12, len(x)),
        "u": x,
        "v": rng.permutation(x),
        "outlier": rng.random(len(x)) < 0.5,
        "status": pd.Categorical(rng.choice(["observed", "single_view"], len(x))),
    })
    for fmt in ("%.6f", "%.0f", "%.3f", "%.9f"):
        assert fixed_csv_bytes(table, fmt).decode() == table.to_csv(index=False, float_format=fmt), fmt
    assert fixed_csv_bytes(table, "%.9e") is None  # neither "%.Nf" nor "%.Ng": csv_text's path
    quoted = table.assign(marker="a, b")
    assert fixed_csv_bytes(quoted, "%.6f") is None


def test_general_format_bytes_are_pythons_text_at_ties_and_edges():
    """"%.Ng" fields built by numpy (the 9-digit text of trajectories.csv) are pandas' characters: ties at N
    significant digits and the floats either side of them, powers of ten and their neighbours (where the
    exponent from log10 could be one off, and a rounding carries into a new digit), both notations and the
    switch between them (exponent -5 / -4 and N - 1 / N), trailing zeros, -0.0, subnormals, huge values, inf,
    NaN, and values of 45 decades."""
    from batgraph.formats.csv_text import fixed_csv_bytes

    rng = np.random.default_rng(11)
    ties = (2 * rng.integers(10**8, 10**9, 300) + 1) / 2 * 10.0 ** rng.integers(-12, 4, 300)
    powers = 10.0 ** np.arange(-20, 25)
    edges = np.array([0.0, -0.0, 5e-324, 1e-310, 1.7976931348623157e308, np.inf, -np.inf, np.nan, 0.5, 2.5,
                      123456789.5, 1234567895.0, 99999999.95, 999999999.5, 9.9999999995e-5, 1e-5, 1e-4, 1.25e-4,
                      123456789.0, 1234567890.0, 100.0, 120.5, 7.0])
    x = np.concatenate([ties, np.nextafter(ties, 0), np.nextafter(ties, np.inf), powers, np.nextafter(powers, 0),
                        np.nextafter(powers, np.inf), edges, np.round(rng.normal(size=2000), 3),
                        rng.normal(size=3000) * 10.0 ** rng.integers(-20, 25, 3000)])
    x = np.concatenate([x, -x])
    table = pd.DataFrame({"method": rng.choice(["smoother", "filter"], len(x)), "frame": rng.integers(0, 999, len(x)),
                          "x": x, "y": rng.permutation(x), "n_views": rng.integers(0, 30, len(x))})
    for fmt in ("%.9g", "%.1g", "%.6g", "%.15g"):
        assert fixed_csv_bytes(table, fmt).decode() == table.to_csv(index=False, float_format=fmt), fmt
    assert fixed_csv_bytes(table, "%.17g") is None  # more digits than the integer path holds: csv_text's path


def test_fixed_point_file_in_chunks_is_pandas_text(tmp_path):
    from batgraph.formats.csv_text import write_csv

    table = _table(250)
    write_csv(tmp_path / "t.csv", table, "%.6f", chunk_rows=37)
    assert (tmp_path / "t.csv").read_text() == table.to_csv(index=False, float_format="%.6f")
