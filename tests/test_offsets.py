"""Camera offsets from DLTdv8 and Argus into calibration.toml's time_offset_s, sign and frames checked against the
physics: a trial built with known offsets (each camera's frame j shows the instant j - O on the first camera's
clock, the tools' convention) must come back with every click at its exact capture time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import tiny_rig

from batgraph.cli import main
from batgraph.errors import InputError
from batgraph.formats import dltdv
from batgraph.formats.offsets import read_offsets
from batgraph.session import dense_observations

FPS = 100.0
N_ROWS = 40
COLS = ["cam1_offset", "cam2_offset", "cam3_offset"]  # DLTdv8's header


def _xyz(t_s: np.ndarray) -> np.ndarray:
    """Two markers moving fast and smoothly, (N, 2, 3) [m] at times (N,) [s]."""
    t = np.asarray(t_s, float)[:, None]
    a = np.stack([0.3 * np.sin(7 * t), 0.2 * np.cos(5 * t), 0.1 * np.sin(3 * t + 1)], -1)
    return np.concatenate([a, a * 0.5 + 0.05], axis=1)


def _trial(folder: Path, offsets_frames, video_frame) -> dict:
    """A DLTdv trial of tiny_rig(3): camera c's video frame j shows the instant (j - O_c) / FPS; xypts row r holds
    its video frame video_frame(r, O_c). Returns the paths (xypts, coefs)."""
    rig = tiny_rig(3)
    rows = []
    for c, cam in enumerate(rig):
        r = np.arange(N_ROWS)
        j = video_frame(r, offsets_frames[c])
        uv = cam.project(_xyz((j - offsets_frames[c]) / FPS))  # (N, 2 markers, 2)
        for p in range(2):
            uv_file = dltdv.from_opencv_px(uv[:, p], "lower-left", cam.size_wh[1])
            rows.append(pd.DataFrame({"frame": r, "camera_index": c, "point_index": p,
                                      "u": uv_file[:, 0], "v": uv_file[:, 1]}))
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"xypts": folder / "t_xypts.csv", "coefs": folder / "t_dltCoefs.csv"}
    dltdv.write_xypts(paths["xypts"], pd.concat(rows, ignore_index=True), n_cams=3, n_points=2, n_frames=N_ROWS)
    dltdv.write_dlt_coefs(paths["coefs"], rig)
    return paths


def _matlab_round(x):
    x = np.asarray(x, float)
    return (np.sign(x) * np.floor(np.abs(x) + 0.5)).astype(int)


def _import(tmp_path: Path, paths: dict, offsets: list[Path]):
    return dltdv.import_dltdv(paths["xypts"], paths["coefs"], FPS, tmp_path / "session", pixel_origin="lower-left",
                              image_size=(640, 480), offsets=offsets)


def _capture_residual_px(session) -> float:
    """Largest distance [px] between each click and the true marker at the capture time the session states."""
    dense = dense_observations(session)
    worst = 0.0
    for c, cam in enumerate(session.rig):
        seen = dense.seen[c]
        f, m = np.nonzero(seen)
        t = (dense.frames[f] + dense.time_frac[c][f, m]) / session.fps
        truth = cam.project(_xyz(t)[np.arange(len(t)), [int(session.markers[k][2:]) - 1 for k in m]])
        worst = max(worst, float(np.abs(truth - dense.uv_px[c][f, m]).max()))
    return worst


def test_dltdv_offsets_non_integer(tmp_path):
    """DLTdv8: row r of camera c holds its video frame round(r + O) (MATLAB round), O non-integer allowed."""
    O = [0.0, 2.3, -1.7]
    paths = _trial(tmp_path / "trial", O, lambda r, o: _matlab_round(r + o))
    table = np.zeros((N_ROWS, 3))
    table[5:, 1], table[::3, 2] = O[1], O[2]  # DLTdv writes 0 where an offset was never set (rows not shown)
    off = tmp_path / "trial" / "t_offsets.csv"
    pd.DataFrame(table, columns=COLS).to_csv(off, index=False, float_format="%.6f")
    session = _import(tmp_path, paths, [off])
    assert np.allclose([c.time_offset_s for c in session.rig], [0.0, -0.023, 0.017])
    assert _capture_residual_px(session) < 1e-3
    obs = session.observations
    assert np.array_equal(obs[obs["camera"] == "cam2"]["camera_frame"], obs[obs["camera"] == "cam2"]["frame"] + 2)
    cam3 = obs[obs["camera"] == "cam3"]
    assert np.array_equal(cam3["frame"], cam3["camera_frame"] + 2)  # rows are the session frames
    assert session.extra_toml["import"]["offsets_format"] == "dltdv"
    assert session.extra_toml["import"]["clicks_before_first_video_frame"] == 2 * 2  # rows 0, 1 of cam3: frame < 0


def test_the_opposite_sign_would_be_wrong(tmp_path):
    """The same trial read with the offsets negated puts the clicks at the wrong instants (the test can fail)."""
    O = [0.0, 2.3, -1.7]
    paths = _trial(tmp_path / "trial", O, lambda r, o: _matlab_round(r + o))
    off = tmp_path / "trial" / "t_offsets.csv"
    pd.DataFrame(np.tile(-np.array(O), (N_ROWS, 1)), columns=COLS).to_csv(off, index=False)
    assert _capture_residual_px(_import(tmp_path, paths, [off])) > 1.0  # the right sign: < 1e-3 px


def test_argus_clicker_and_sync(tmp_path):
    """Argus: the clicker shows video frame r + integer offset; the sync table gives the offset to a fraction of a
    frame (frames_offset d: the sound comes d frames later in that camera), which wins for the time."""
    O = [0.0, 3.4, -2.2]  # the truth; the user typed the sync table's rounded values into the clicker
    paths = _trial(tmp_path / "trial", O, lambda r, o: r + int(np.round(o)))
    clicker = tmp_path / "trial" / "t-offsets.csv"
    pd.DataFrame(np.tile(np.round(O), (N_ROWS, 1)), columns=["camera_1", "camera_2", "camera_3"]).to_csv(
        clicker, index=False, na_rep="NaN")
    sync = tmp_path / "trial" / "movie_offsets.csv"
    sync.write_text("Filename,seconds_offset,frames_offset,max_correlation\n"
                    + "".join(f"cam{c + 1}.mp4,{o / FPS},{o},0.9\n" for c, o in enumerate(O)))
    session = _import(tmp_path, paths, [clicker, sync])
    assert np.allclose([c.time_offset_s for c in session.rig], -np.array(O) / FPS)
    assert _capture_residual_px(session) < 1e-3
    only_clicker = _import(tmp_path, paths, [clicker])  # whole frames only: the sub-frame part is left out
    assert 0.05 < _capture_residual_px(only_clicker)
    s = read_offsets(sync, 3)
    assert s.kind == "argus-sync" and not s.per_row and np.allclose(s.time_offsets_s(FPS), -np.array(O) / FPS)


def test_no_offsets_keeps_the_rows(tmp_path):
    paths = _trial(tmp_path / "trial", [0.0, 0.0, 0.0], lambda r, o: r)
    session = _import(tmp_path, paths, [])
    assert "camera_frame" not in session.observations and all(c.time_offset_s == 0 for c in session.rig)
    assert not any(k.startswith("offsets") for k in session.extra_toml["import"])


@pytest.mark.parametrize("text, words", [
    ("a,b,c\n0,0,0\n", "expected the columns"),
    ("cam1_offset,cam2_offset\n0,0\n", "2 camera(s) but 3 expected"),
    ("cam1_offset,cam2_offset,cam3_offset\n0,1,0\n0,2,0\n", "lines 2 and 3, cam2_offset: the offset changes"),
    ("cam1_offset,cam2_offset,cam3_offset\n0,x,0\n", "line 2, cam2_offset: 'x' is not a finite number"),
    ("Filename,seconds_offset,frames_offset,max_correlation\na,0,0,1\nb,0.01,1,0.5\n", "2 camera row(s) but 3"),
])
def test_bad_offsets_files(tmp_path, text, words):
    path = tmp_path / "o.csv"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        read_offsets(path, 3)
    assert words in str(e.value) and str(path) in str(e.value)


def test_offsets_rows_must_match_the_clicks(tmp_path):
    paths = _trial(tmp_path / "trial", [0.0, 1.0, 0.0], lambda r, o: _matlab_round(r + o))
    off = tmp_path / "o.csv"
    pd.DataFrame(np.zeros((N_ROWS - 1, 3)), columns=COLS).to_csv(off, index=False)
    with pytest.raises(InputError, match="39 row"):
        _import(tmp_path, paths, [off])


def test_cli_import_with_offsets(tmp_path, capsys):
    O = [0.0, 2.3, -1.7]
    paths = _trial(tmp_path / "trial", O, lambda r, o: _matlab_round(r + o))
    off = tmp_path / "trial" / "t_offsets.csv"
    pd.DataFrame(np.tile(O, (N_ROWS, 1)), columns=COLS).to_csv(off, index=False)
    rc = main(["import", "dltdv", "--xypts", str(paths["xypts"]), "--coefs", str(paths["coefs"]), "--fps", str(FPS),
               "--image-size", "640", "480", "--offsets", str(off), "--out", str(tmp_path / "s")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "cam2 -23.000" in out and "cam3 +17.000" in out and "before a video's first frame dropped" in out
    cal = (tmp_path / "s" / "calibration.toml").read_text()
    assert "time_offset_s = -0.023" in cal


def test_dltdv_8_4_headers(tmp_path):
    """DLTdv 8.4 names the xypts columns pt1_cam1_U, pt1_cam1_V: the same clicks as _X, _Y."""
    paths = _trial(tmp_path / "trial", [0.0, 0.0, 0.0], lambda r, o: r)
    text = paths["xypts"].read_text().splitlines()
    header = text[0].replace("_X", "_U").replace("_Y", "_V")
    assert "_U" in header and "_X" not in header
    renamed = tmp_path / "trial" / "u_xypts.csv"
    renamed.write_text("\n".join([header] + text[1:]) + "\n")
    a = dltdv.read_xypts(paths["xypts"])
    b = dltdv.read_xypts(renamed)
    pd.testing.assert_frame_equal(a, b)
