"""Session folders: every bad input is one InputError naming file, line/key and problem; good input round-trips."""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomli_w

from batgraph.errors import InputError
from batgraph.session import dense_observations, read_session, write_session


# ----------------------------------------------------------------------------------------------
# helpers: edit one file of a valid session
# ----------------------------------------------------------------------------------------------
def _edit_obs_line(folder: Path, line_no: int, new_line: str) -> None:
    """Replace line ``line_no`` (1-based, header = 1) of observations.csv."""
    path = folder / "observations.csv"
    lines = path.read_text().splitlines()
    lines[line_no - 1] = new_line
    path.write_text("\n".join(lines) + "\n")


def _obs_line(folder: Path, line_no: int) -> list[str]:
    return (folder / "observations.csv").read_text().splitlines()[line_no - 1].split(",")


def _edit_toml(path: Path, edit) -> None:
    with open(path, "rb") as f:
        doc = tomllib.load(f)
    edit(doc)
    path.write_text(tomli_w.dumps(doc))


def _error(folder: Path) -> str:
    with pytest.raises(InputError) as e:
        read_session(folder)
    msg = str(e.value)
    assert "\n" not in msg, "messages are one line"
    return msg


# ----------------------------------------------------------------------------------------------
# missing files and bad tables
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["session.toml", "calibration.toml", "observations.csv"])
def test_missing_file(session_folder, name):
    (session_folder / name).unlink()
    msg = _error(session_folder)
    assert name in msg and "not found" in msg


def test_missing_folder(tmp_path):
    msg = _error(tmp_path / "nope")
    assert "nope" in msg and "not found" in msg


@pytest.mark.parametrize("wrong, right", [("markr", "marker"), ("camera_name", "camera"), ("frames", "frame")])
def test_misspelt_column_suggests_the_right_one(session_folder, wrong, right):
    header = ",".join(wrong if c == right else c for c in _obs_line(session_folder, 1))
    _edit_obs_line(session_folder, 1, header)
    msg = _error(session_folder)
    assert "observations.csv" in msg and f"missing column '{right}'" in msg and f"did you mean '{wrong}'" in msg


def test_missing_column(session_folder):
    df = pd.read_csv(session_folder / "observations.csv").drop(columns="v")
    df.to_csv(session_folder / "observations.csv", index=False)
    msg = _error(session_folder)
    assert "observations.csv" in msg and "missing column 'v'" in msg


@pytest.mark.parametrize(
    "column, value, expect",
    [
        ("u", "12;5", "u '12;5' is not a number"),
        ("u", "abc", "u 'abc' is not a number"),
        ("v", "inf", "v is infinite"),
        ("v", "-inf", "v is infinite"),
        ("frame", "-1", "frame '-1' is not an integer >= 0"),
        ("frame", "1.5", "frame '1.5' is not an integer >= 0"),
        ("frame", "", "frame is empty"),
        ("camera", "cam9", "camera 'cam9' is not in calibration.toml"),
        ("marker", "", "marker is empty"),
    ],
)
def test_bad_cell_names_file_line_and_column(session_folder, column, value, expect):
    line_no = 5
    cells = _obs_line(session_folder, line_no)
    cols = _obs_line(session_folder, 1)
    cells[cols.index(column)] = value
    _edit_obs_line(session_folder, line_no, ",".join(cells))
    msg = _error(session_folder)
    assert f"observations.csv line {line_no}" in msg and expect in msg


def test_row_with_an_extra_field(session_folder):
    _edit_obs_line(session_folder, 5, ",".join(_obs_line(session_folder, 5) + ["7"]))
    msg = _error(session_folder)
    assert "observations.csv" in msg and "line 5" in msg


def test_bad_weight(session_folder):
    df = pd.read_csv(session_folder / "observations.csv").assign(weight=1.0)
    df.loc[3, "weight"] = 1.5
    df.to_csv(session_folder / "observations.csv", index=False)
    msg = _error(session_folder)
    assert "observations.csv line 5" in msg and "weight" in msg and "(0, 1]" in msg


def test_only_one_of_u_v(session_folder):
    cells = _obs_line(session_folder, 3)
    cells[4] = ""
    _edit_obs_line(session_folder, 3, ",".join(cells))
    msg = _error(session_folder)
    assert "observations.csv line 3" in msg and "only one of u, v" in msg


def test_duplicate_rows(session_folder):
    lines = (session_folder / "observations.csv").read_text().splitlines()
    dup = lines[3].split(",")
    dup[3] = "100.0"  # same frame, camera, marker; other pixel
    lines.append(",".join(dup))
    (session_folder / "observations.csv").write_text("\n".join(lines) + "\n")
    msg = _error(session_folder)
    assert "observations.csv line 4 and line" in msg and "duplicate" in msg
    assert f"line {len(lines)}" in msg and f"camera '{dup[1]}'" in msg and f"marker '{dup[2]}'" in msg


def test_duplicate_rows_named_in_pairs(session_folder):
    """Two keys each given twice, interleaved (A, B, A, B): the message names A's two rows, not A's and B's."""
    path = session_folder / "observations.csv"
    lines = path.read_text().splitlines()
    lines += [lines[3], lines[5]]  # line 4 again (A), then line 6 again (B)
    path.write_text("\n".join(lines) + "\n")
    a = lines[3].split(",")
    msg = _error(session_folder)
    assert f"line 4 and line {len(lines) - 1}: duplicate" in msg
    assert f"frame {a[0]}, camera '{a[1]}', marker '{a[2]}'" in msg


def test_empty_observation_file(session_folder):
    (session_folder / "observations.csv").write_bytes(b"")
    msg = _error(session_folder)
    assert "observations.csv" in msg and "empty file" in msg


def test_header_only_observation_file(session_folder):
    (session_folder / "observations.csv").write_text("frame,camera,marker,u,v\n")
    msg = _error(session_folder)
    assert "observations.csv" in msg and "header only" in msg


def test_all_pixels_empty(session_folder):
    df = pd.read_csv(session_folder / "observations.csv")
    df[["u", "v"]] = np.nan
    df.to_csv(session_folder / "observations.csv", index=False)
    msg = _error(session_folder)
    assert "observations.csv" in msg and "no observations" in msg


# ----------------------------------------------------------------------------------------------
# calibration.toml
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "key, value, expect",
    [
        ("matrix", [[600.0, 0.0, 320.0], [0.0, 600.0, 240.0]], "matrix: expected shape (3, 3), got (2, 3)"),
        ("matrix", [[600.0, 0.0], [0.0, 600.0]], "matrix: expected shape (3, 3), got (2, 2)"),
        ("matrix", [[600.0, 0.0, 320.0], [0.0, 600.0], [0.0, 0.0, 1.0]], "matrix: expected numbers of shape (3, 3)"),
        ("matrix", [[-600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]], "matrix: expected [[fx, s, cx]"),
        ("rotation", [0.1, 0.2], "rotation: expected shape (3,), got (2,)"),
        ("rotation", [0.1, 0.2, 0.3, 0.4], "rotation: expected shape (3,), got (4,)"),
        ("translation", [0.0, math.nan, 1.0], "translation: contains a non-finite value"),
        ("translation", [0.0, math.inf, 1.0], "translation: contains a non-finite value"),
        ("size", [640, 0], "size: expected two positive integers"),
        ("distortions", [0.1, 0.0, 0.0, 0.0, 0.0, 0.0], "distortions: expected up to 5 values"),
    ],
)
def test_bad_calibration_value(session_folder, key, value, expect):
    def edit(doc):
        doc["cam_1"][key] = value
    _edit_toml(session_folder / "calibration.toml", edit)
    msg = _error(session_folder)
    assert "calibration.toml [cam_1]" in msg and expect in msg


def test_calibration_missing_key(session_folder):
    _edit_toml(session_folder / "calibration.toml", lambda doc: doc["cam_2"].pop("translation"))
    msg = _error(session_folder)
    assert "calibration.toml [cam_2]" in msg and "missing key 'translation'" in msg


def test_calibration_not_toml(session_folder):
    (session_folder / "calibration.toml").write_text("[cam_0\nname = 'x'\n")
    msg = _error(session_folder)
    assert "calibration.toml" in msg and "not valid TOML" in msg


# ----------------------------------------------------------------------------------------------
# session.toml
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "edit, expect",
    [
        (lambda d: d["session"].update(fps=0.0), "[session] fps: must be > 0"),
        (lambda d: d["session"].update(fps=-120.0), "[session] fps: must be > 0"),
        (lambda d: d["session"].update(fps="120"), "[session] fps: expected a number"),
        (lambda d: d["session"].update(fps=math.nan), "[session] fps: must be finite"),
        (lambda d: d["session"].pop("fps"), "[session]: missing key 'fps'"),
        (lambda d: d.pop("session"), "missing table [session]"),
        (lambda d: d["motion"].update(model="brownian"), "[motion] model: 'brownian' is not one of"),
        (lambda d: d["motion"].update(span_m=-0.5), "[motion] span_m: must be > 0"),
        (lambda d: d["noise"].update(pixel_sigma_px=0), "[noise] pixel_sigma_px: must be > 0"),
        (lambda d: d["markers"].update(skeleton=[["m0"]]), "[markers] skeleton[0]: expected a pair"),
    ],
)
def test_bad_session_toml(session_folder, edit, expect):
    _edit_toml(session_folder / "session.toml", edit)
    msg = _error(session_folder)
    assert "session.toml" in msg and expect in msg


@pytest.mark.parametrize(
    "text, expect",
    [
        ('motion = "random_walk"\n[session]\nfps = 100.0\n', "'motion' must be a table [motion]"),
        ("noise = 1.0\n[session]\nfps = 100.0\n", "'noise' must be a table [noise]"),
        ('[session]\nfps = 100.0\n[markers]\nnames = "m0"\n', "[markers] names: expected a list"),
    ],
)
def test_session_toml_tables_of_the_wrong_kind(session_folder, text, expect):
    (session_folder / "session.toml").write_text(text)
    msg = _error(session_folder)
    assert "session.toml" in msg and expect in msg


# ----------------------------------------------------------------------------------------------
# accepted input
# ----------------------------------------------------------------------------------------------
def test_point_outside_image_is_kept_and_counted(session_folder):
    cells = _obs_line(session_folder, 2)
    cells[3] = "-5.0"
    _edit_obs_line(session_folder, 2, ",".join(cells))
    cells = _obs_line(session_folder, 6)
    cells[4] = "1e5"
    _edit_obs_line(session_folder, 6, ",".join(cells))
    s = read_session(session_folder)
    assert len(s.observations) == 36
    assert (s.observations["u"] == -5.0).sum() == 1 and (s.observations["v"] == 1e5).sum() == 1
    assert len(s.warnings) == 1 and "2 observation(s) lie outside" in s.warnings[0]
    assert "observations.csv" in s.warnings[0]


def test_empty_pixels_mean_unseen(session_folder):
    lines = (session_folder / "observations.csv").read_text().splitlines()
    for i in (2, 7):
        cells = lines[i - 1].split(",")
        cells[3:5] = ["", "NaN"] if i == 2 else [" ", " "]
        lines[i - 1] = ",".join(cells)
    (session_folder / "observations.csv").write_text("\n".join(lines) + "\n")
    s = read_session(session_folder)
    assert len(s.observations) == 34
    dense = dense_observations(s)
    assert dense.seen.sum() == 34 and dense.uv_px.shape == (3, 6, 2, 2)


def test_round_trip(session_folder, tmp_path):
    a = read_session(session_folder)
    write_session(a, tmp_path / "copy")
    b = read_session(tmp_path / "copy")
    pd.testing.assert_frame_equal(a.observations, b.observations)
    pd.testing.assert_frame_equal(a.truth, b.truth)
    assert (a.name, a.fps, a.pixel_sigma_px, a.marker_names, a.skeleton) == (
        session_folder.name, b.fps, b.pixel_sigma_px, b.marker_names, b.skeleton)
    assert a.motion == b.motion
    assert a.rig.names == b.rig.names
    for ca, cb in zip(a.rig, b.rig, strict=True):
        assert ca.size_wh == cb.size_wh
        for attr in ("K", "dist", "rvec", "tvec"):
            np.testing.assert_array_equal(getattr(ca, attr), getattr(cb, attr))
    # the files themselves are a fixed point of read -> write
    write_session(b, tmp_path / "copy2")
    for name in ("session.toml", "calibration.toml", "observations.csv", "truth.csv"):
        assert (tmp_path / "copy" / name).read_bytes() == (tmp_path / "copy2" / name).read_bytes()


def test_parquet_observations(session_folder):
    csv = read_session(session_folder).observations
    df = pd.read_csv(session_folder / "observations.csv")
    df.to_parquet(session_folder / "observations.parquet", index=False)
    (session_folder / "observations.csv").unlink()
    s = read_session(session_folder)
    pd.testing.assert_frame_equal(s.observations, csv)
    # rows of a parquet file are reported by 0-based row index
    df.loc[4, "u"] = np.inf
    df.to_parquet(session_folder / "observations.parquet", index=False)
    msg = _error(session_folder)
    assert "observations.parquet row 4" in msg and "u is infinite" in msg


def test_read_session_never_modifies_its_inputs(make_session_folder):
    folder = make_session_folder("s", n_frames=4)
    stamp = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir()}
    old = {p.name: os.stat(p).st_mtime_ns - 10_000_000_000 for p in folder.iterdir()}
    for p in folder.iterdir():  # push mtimes into the past so a rewrite within the same tick shows
        os.utime(p, ns=(old[p.name], old[p.name]))
    read_session(folder)
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir()}
    assert set(after) == set(stamp), "no file created or removed"
    for name, (data, mtime) in after.items():
        assert data == stamp[name][0] and mtime == old[name], name
