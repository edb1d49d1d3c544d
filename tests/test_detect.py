"""batgraph detect: blobs found in rendered footage (batgraph.render) where the scene put them, and named by
associate from there."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import write_tiny_session
from scipy.spatial import cKDTree

from batgraph.cli import main
from batgraph.detect import BlobOptions, blobs, detect
from batgraph.formats.csv_text import write_csv
from batgraph.render import Look, render_session
from batgraph.session import read_session


def _footage(tmp: Path, frames: int = 20, look: Look | None = None, video: str | None = None, seed: int = 0):
    """The tiny scene (4 cameras, 6 markers) rendered: (session, the cameras' footage paths)."""
    src = write_tiny_session(tmp / "labelled", n_cams=4, n_frames=frames, n_markers=6, seed=seed)
    session = read_session(src)
    paths = render_session(session.rig, session.observations, frames, tmp / "footage", np.random.default_rng(seed),
                           look, video)
    return session, paths


def _isolated(obs: pd.DataFrame, px: float = 8.0) -> pd.DataFrame:
    """The observations with no other marker within px in their camera and frame (their blobs are alone)."""
    keep = []
    for _, g in obs.groupby(["frame", "camera"]):
        uv = g[["u", "v"]].to_numpy()
        d = np.hypot(*(uv[:, None] - uv[None]).transpose(2, 0, 1))
        np.fill_diagonal(d, np.inf)
        keep += list(g.index[d.min(axis=1) > px])
    return obs.loc[keep]


def _errors(obs: pd.DataFrame, table: pd.DataFrame) -> np.ndarray:
    """Each observation's distance to the nearest detection of its camera and frame [px] (inf: none)."""
    out = np.full(len(obs), np.inf)
    for (f, c), g in obs.groupby(["frame", "camera"]):
        d = table[(table["frame"] == f) & (table["camera"] == c)]
        if len(d):
            out[obs.index.get_indexer(g.index)] = cKDTree(d[["u", "v"]].to_numpy()).query(g[["u", "v"]].to_numpy())[0]
    return out


def test_blob_centres_are_found_to_a_tenth_of_a_pixel(tmp_path):
    """Gaussian blobs (1.2 px std, 120 levels) on a textured background with static lamps and 2 levels of noise:
    every lone blob found within 0.2 px (a half-pixel convention slip would be 0.7 px off), nothing at a lamp."""
    session, paths = _footage(tmp_path)
    table, per_camera = detect(paths, session.rig.names)
    alone = _isolated(session.observations)
    err = _errors(alone, table)
    assert len(alone) > 300 and np.isfinite(err).all()
    assert np.max(err) < 0.2 and np.median(err) < 0.06, (np.median(err), np.max(err))
    off = _errors(table.reset_index(drop=True), session.observations)  # each detection to its nearest marker
    assert np.max(off) < 8.0  # two markers' merged blob lies between them; a lamp or a noise speck anywhere
    assert all(abs(p.noise - 2.0) < 0.3 for p in per_camera)  # the measured noise is the rendered one
    assert list(table.columns) == ["frame", "camera", "u", "v", "size"]
    assert (np.diff(table["frame"].to_numpy()) >= 0).all()


def test_dark_markers_on_a_plain_backdrop(tmp_path):
    """Dark blobs (-40 levels) on a uniform 60-level backdrop, found with --polarity dark, on the per-pixel median
    and on the flat background alike (within 0.4 px: a third of the contrast, three times the noise in u, v)."""
    session, paths = _footage(tmp_path, look=Look(contrast=-40.0, lamps=0, textured=False))
    alone = _isolated(session.observations)
    for background in ("median", "flat"):
        table, _ = detect(paths, session.rig.names, BlobOptions(polarity="dark", background=background))
        err = _errors(alone, table)
        assert np.max(err) < 0.4, (background, np.max(err))
    bright, _ = detect(paths, session.rig.names, BlobOptions(polarity="bright"))
    assert len(bright) == 0


def test_blob_weighting_and_area_bounds():
    """A lone 3x3 blob's centre is its contrast-weighted mean; blobs outside the area bounds are dropped."""
    c = np.zeros((20, 30), np.float32)
    c[4:7, 10:13] = [[10, 20, 10], [20, 40, 20], [10, 20, 50]]
    c[15, 2] = 100  # a one-pixel speck
    uv, area = blobs(c, 5.0, 2, 400)
    w = c[4:7, 10:13].astype(float)
    rows, cols = np.mgrid[4:7, 10:13]
    assert area.tolist() == [9]
    assert np.allclose(uv[0], [(w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()])
    assert len(blobs(c, 5.0, 1, 8)[1]) == 1  # now the speck, not the 9-pixel blob


@pytest.mark.parametrize("apart_px, found", [(6.0, 2), (2.0, 1)])
def test_touching_blobs_are_split_where_their_peaks_stand_apart(apart_px, found):
    """Two Gaussian blobs (1.2 px std, 100 levels) whose thresholded areas touch: 6 px apart the saddle between
    them is far below both peaks, and each is found within 0.3 px of its centre (the other's tail pulls it a
    little); 2 px apart there is one peak, and one blob at their mean."""
    rows, cols = np.mgrid[0:30, 0:40].astype(float)
    centres = np.array([[15.3, 14.6], [15.3 + apart_px, 15.1]])
    c = sum(100 * np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 1.2 ** 2)) for u, v in centres)
    c = c.astype(np.float32)
    uv, area = blobs(c, 5.0, 4, 400)
    assert len(uv) == found
    if found == 2:
        uv = uv[np.argsort(uv[:, 0])]
        assert np.abs(uv - centres).max() < 0.3, uv
    else:
        assert np.abs(uv[0] - centres.mean(axis=0)).max() < 0.05


def test_saturated_blobs_are_not_split(tmp_path):
    """Blobs clipped at 255 (2 px std, 600 levels) on the textured background: each flat top is many small peaks
    of 255 - background, none rising the threshold above the pass to the highest, so no marker gets two
    detections (a test of the straight line between two peaks split 19 of 240 on 40 frames: the line cuts
    through the blob's rim)."""
    session, paths = _footage(tmp_path, frames=20, look=Look(contrast=600.0, blob_sigma_px=2.0))
    table, _ = detect(paths[:2], session.rig.names[:2])
    obs = session.observations
    for (f, c), g in table.groupby(["frame", "camera"]):
        o = obs[(obs["frame"] == f) & (obs["camera"] == c)][["u", "v"]].to_numpy()
        d, j = cKDTree(o).query(g[["u", "v"]].to_numpy())
        assert len(set(j[d < 3])) == len(j[d < 3]), (f, c)


def test_a_video_file_is_read_like_its_frames(tmp_path):
    """The footage as MPEG-4 videos (lossy): lone blobs still within 0.3 px; the camera named by the file."""
    session, paths = _footage(tmp_path, video=".mp4")
    assert paths[0].name == "cam1.mp4"
    table, per_camera = detect(paths, [p.stem for p in paths])
    assert [p.frames for p in per_camera] == [20] * 4
    err = _errors(_isolated(session.observations), table)
    assert np.max(err) < 0.3, np.max(err)


def test_cli_detect_then_associate_names_the_markers(tmp_path, capsys):
    """Footage -> batgraph detect -> batgraph associate (one seed frame clicked on the lone blobs): 90 % or more of
    the markers' views named correctly, none wrongly."""
    frames = 40
    session, paths = _footage(tmp_path, frames=frames)
    sess = tmp_path / "session"
    shutil.copytree(tmp_path / "labelled", sess)
    (sess / "observations.csv").unlink()
    assert main(["detect", *map(str, paths), "--out", str(sess / "detections.csv"), "--quiet"]) == 0
    assert "wrote" in capsys.readouterr().out
    obs = session.observations
    seed = _isolated(obs[obs["frame"] == frames // 2])[["frame", "camera", "marker", "u", "v"]]
    write_csv(sess / "seed_labels.csv", seed, "%.6f")
    assert main(["associate", str(sess), "--out", str(tmp_path / "named")]) == 0
    named = pd.read_csv(tmp_path / "named" / "observations.csv")
    key = ["frame", "camera", "marker"]
    both = named.merge(obs, on=key, suffixes=("", "_true"))
    right = np.hypot(both["u"] - both["u_true"], both["v"] - both["v_true"]) < 1.0
    assert right.sum() >= 0.9 * len(obs), (right.sum(), len(obs))
    assert right.all() and len(both) == len(named)  # no name on another marker's blob


def test_no_blob_is_warned(tmp_path, capsys):
    _, paths = _footage(tmp_path, frames=6)
    out = tmp_path / "det.csv"
    assert main(["detect", *map(str, paths), "--out", str(out), "--threshold", "250"]) == 0
    err = capsys.readouterr().err
    assert "cam1: no blob on any of its 6 frames" in err
    assert pd.read_csv(out).empty


def _fails(args: list[str], capsys) -> str:
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("batgraph: error:"), err
    return err


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    _, paths = _footage(tmp_path, frames=3)
    out = str(tmp_path / "det.csv")
    cams = list(map(str, paths))
    assert "file not found" in _fails(["detect", str(tmp_path / "nope.mp4"), "--out", out], capsys)
    (tmp_path / "empty").mkdir()
    assert "no image files" in _fails(["detect", str(tmp_path / "empty"), "--out", out], capsys)
    assert "2 names for 4 recordings" in _fails(["detect", *cams, "--out", out, "--cameras", "a,b"], capsys)
    assert "named twice" in _fails(["detect", *cams, "--out", out, "--cameras", "a,b,a,c"], capsys)
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    assert "junk.mp4" in _fails(["detect", str(tmp_path / "junk.mp4"), "--out", out], capsys)
    odd = tmp_path / "odd"
    shutil.copytree(paths[0], odd)
    cv2.imwrite(str(odd / "000009.png"), np.zeros((10, 10), np.uint8))
    assert "000009.png" in _fails(["detect", str(odd), "--out", out, "--background", "flat"], capsys)
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(paths[0] / "000000.png", one)
    assert "--background flat" in _fails(["detect", str(one), "--out", out], capsys)
    assert "must be a .csv" in _fails(["detect", *cams, "--out", str(tmp_path / "det.txt")], capsys)
    msg = _fails(["detect", *cams, "--out", str(tmp_path / "labelled" / "detections.csv"), "--cameras",
                  "cam1,cam2,cam3,cam9"], capsys)
    assert "calibration.toml: no camera 'cam9'" in msg and not (tmp_path / "labelled" / "detections.csv").exists()
    assert not Path(out).exists()


def test_a_file_that_is_no_video_is_one_line_in_a_real_process(tmp_path):
    """FFmpeg's own log lines (written by C code, past Python's stderr) are off: the one line is batgraph's."""
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    r = subprocess.run([sys.executable, str(Path(__file__).resolve().parents[1] / "scripts" / "detect.py"),
                        str(tmp_path / "junk.mp4"), "--out", str(tmp_path / "d.csv")], capture_output=True, text=True,
                       timeout=300, env={k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"})
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"batgraph: error: {tmp_path / 'junk.mp4'}: cannot open the video (not a "
                                             "video OpenCV's FFmpeg reads)"], r.stderr


@pytest.mark.parametrize("bad", [dict(polarity="up"), dict(background="mean"), dict(min_area_px=9, max_area_px=4)])
def test_blob_options_are_checked(bad):
    from batgraph.errors import InputError
    with pytest.raises(InputError):
        BlobOptions(**bad)
