"""C3D, TRC and analysis-table exports, read back by readers batgraph does not write with.

* C3D: py-c3d (``pip install c3d``, follows C3D.org's spec byte for byte and refuses inconsistent headers),
  the raw bytes, and ezc3d (coordinates only: it swaps the residual and camera-mask bytes of float data,
  pyomeca/ezc3d#386).
* TRC: a strict re-implementation of OpenSim 4.6's TRCFileAdapter row rule (always), and OpenSim's own
  reader when the ``opensim`` wheel is installed.
"""

import struct
import warnings
from pathlib import Path

import ezc3d
import numpy as np
import pandas as pd
import pytest
from conftest import observations_table, tiny_rig, tiny_scene

from batgraph.cli import main
from batgraph.errors import InputError
from batgraph.evaluate import cov_matrices
from batgraph.formats.c3d_trc import (
    C3D_RESIDUAL_STEP_MM,
    analysis_table,
    c3d_point_scale_mm,
    keep_range,
    read_trc,
    write_c3d,
    write_trc,
)
from batgraph.methods import ALL_METHODS
from batgraph.session import PAPER_PHYSICS, MotionConfig, Session, write_session

c3d = pytest.importorskip("c3d")  # py-c3d, in the test extras

FPS = 120.0
MARKERS = ["body1", "body2", "wrist_r", "digit3_r"]
FIRST, N_FRAMES = 3, 40
COV_COLS = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]

REAL_TRC = (Path(__file__).parents[2] / "shared/data/real/pose2sim_demo_4cam_human/S00_P00_SingleParticipant"
            / "S00_P00_T01_BalancingTrial/pose-3d/S00_P00_T01_BalancingTrial_0-100.trc")


def _table(seed: int = 0, extent_m: float = 8.0) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """A two-method trajectories table (CONTRACT.md section 3, no span column) with missing points.

    Returns the table and the smoother's truth: xyz (F, M, 3) [m] with NaN where missing, and
    covariances (F, M, 3, 3) [m^2]. Positions span +-extent_m so float32 rounding is exercised.
    """
    rng = np.random.default_rng(seed)
    F, M = N_FRAMES, len(MARKERS)
    xyz = rng.uniform(-extent_m, extent_m, (F, M, 3))
    A = rng.normal(0, 2e-3, (F, M, 3, 3))  # std of a few mm
    cov = A @ np.swapaxes(A, -1, -2) + np.eye(3) * 1e-8
    cov[30, 1] = np.eye(3)  # std 1 m: the C3D residual saturates
    cov[31, 1] = np.eye(3) * 1e-12  # std 1 um: rounds up to one residual step, never 0
    cov[32, 1] = np.nan  # an estimate without covariance: residual 0
    xyz[5:9, 2] = np.nan  # a gap of one marker
    xyz[0, :] = np.nan  # a whole frame missing
    xyz[20, 3, :] = np.nan  # the last marker missing: the TRC row must still have every cell
    frames = np.arange(FIRST, FIRST + F)
    rows = []
    for method, offset in (("smoother", 0.0), ("filter", 0.5)):
        fi, mi = np.meshgrid(np.arange(F), np.arange(M), indexing="ij")
        fi, mi = fi.ravel(), mi.ravel()
        iu = np.triu_indices(3)
        c6 = cov[fi, mi][:, iu[0], iu[1]]
        df = pd.DataFrame({"method": method, "frame": frames[fi], "time_s": frames[fi] / FPS,
                           "marker": np.array(MARKERS)[mi]})
        df[["x", "y", "z"]] = xyz[fi, mi] + offset
        df[COV_COLS] = c6
        df["n_views"] = 2
        df["status"] = "observed"
        rows.append(df)
    table = pd.concat(rows, ignore_index=True).sample(frac=1.0, random_state=1)  # order must not matter
    return table, xyz, cov


def read_py_c3d(path: Path):
    """py-c3d's reading: (reader, points (F, M, 5) = x, y, z [mm], residual [mm] or -1, camera byte).

    Any warning other than "no analog data" fails the test (e.g. a data block left over)."""
    with open(path, "rb") as h, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = c3d.Reader(h)  # asserts header == parameters (scale factor, rate, point count)
        pts = np.stack([p.copy() for _, p, _ in r.read_frames()])
    other = [str(w.message) for w in caught if "No analog data" not in str(w.message)]
    assert not other, other
    return r, pts


def c3d_words(path: Path) -> tuple[float, np.ndarray]:
    """The raw bytes: the header's scale factor and the float data (F, M, 4) of a points-only Intel C3D."""
    b = Path(path).read_bytes()
    assert b[1] == 0x50 and b[(b[0] - 1) * 512 + 3] == 84  # C3D key, Intel processor
    n_points, _, first, last = struct.unpack_from("<HHHH", b, 2)
    scale = struct.unpack_from("<f", b, 12)[0]
    start = (struct.unpack_from("<H", b, 16)[0] - 1) * 512
    F = last - first + 1
    return scale, np.frombuffer(b, "<f4", count=F * n_points * 4, offset=start).reshape(F, n_points, 4)


def expected_counts(cov: np.ndarray, valid: np.ndarray, scale_mm: float) -> np.ndarray:
    """Residual bytes from the covariances, computed here independently of the writer."""
    rms_mm = np.sqrt(np.trace(cov, axis1=-2, axis2=-1) / 3) * 1e3
    n = np.full(valid.shape, -1)
    finite = valid & np.isfinite(rms_mm)
    n[finite] = np.clip(np.floor(rms_mm[finite] / scale_mm + 0.5), 1, 255)
    n[valid & ~np.isfinite(rms_mm)] = 0
    return n


# ----- C3D -------------------------------------------------------------------------------------------
def test_c3d_bytes_follow_the_spec(tmp_path):
    """One frame, hand-made: header scale == POINT:SCALE (negative: float); the 4th word is the float of
    camera mask x 256 + residual / |scale|; -1 for a missing point. Residual 0.6 mm (1.2 mm) with scale
    0.1 mm is byte 6 (12); cameras cam1+cam3 (cam2) are mask 0b101 (0b010). The old layout (6 << 8 =
    1536.0) would fail here and be read as residual 0 by py-c3d."""
    sd = np.array([0.6e-3, 1.2e-3])
    table = pd.DataFrame({"method": "m", "frame": [0, 0, 0], "marker": ["a", "b", "c"],
                          "x": [0.1, 0.2, np.nan], "y": [0.0, 0.0, np.nan], "z": [0.0, 0.0, np.nan],
                          "cov_xx": [sd[0] ** 2, sd[1] ** 2, np.nan], "cov_xy": 0.0, "cov_xz": 0.0,
                          "cov_yy": [sd[0] ** 2, sd[1] ** 2, np.nan], "cov_yz": 0.0,
                          "cov_zz": [sd[0] ** 2, sd[1] ** 2, np.nan], "n_views": [2, 1, 0]})
    reproj = pd.DataFrame({"method": "m", "frame": 0, "camera": ["cam1", "cam3", "cam2", "cam3", "cam1"],
                           "marker": ["a", "a", "b", "b", "c"], "outlier": [False, False, False, True, False]})
    path = write_c3d(tmp_path / "s.c3d", table, 100.0, keep="all", reprojection=reproj,
                     cameras=["cam1", "cam2", "cam3"])
    scale, data = c3d_words(path)
    r, pts = read_py_c3d(path)
    assert scale == np.float32(-0.1) == np.float32(r.get_float("POINT:SCALE"))
    assert data[0, :, 3].tolist() == [0b101 * 256 + 6, 0b010 * 256 + 12, -1.0]  # cam3's b is an outlier
    assert data[0, 2, :3].tolist() == [0, 0, 0]
    assert pts[0, :, 3] == pytest.approx([0.6, 1.2, -1], abs=1e-6)
    assert pts[0, :2, 4].tolist() == [0b101, 0b010]  # (py-c3d gives 127 for an invalid point)
    assert [s.strip() for s in r.get("BATGRAPH:CAMERAS").string_array] == ["cam1", "cam2", "cam3"]
    assert r.get("BATGRAPH:RANGE").string_value.strip() == "all"


def test_c3d_point_scale_follows_the_largest_coordinate():
    """|POINT:SCALE| = the smallest 1-2-5 step >= max|coordinate| / 32000, at least 0.1 mm."""
    assert c3d_point_scale_mm(0.0) == C3D_RESIDUAL_STEP_MM == c3d_point_scale_mm(3200.0)
    assert c3d_point_scale_mm(3201.0) == 0.2 and c3d_point_scale_mm(8000.0) == 0.5
    assert c3d_point_scale_mm(16001.0) == 1.0 and c3d_point_scale_mm(1e6) == 50.0


@pytest.mark.parametrize("extent_m", [2.0, 8.0])
def test_c3d_read_by_py_c3d(tmp_path, extent_m):
    """py-c3d reads positions back to 1e-6 m (float32 mm: |x| <= 8000 mm has spacing 2^-11 mm, so rounding
    <= 0.24 um), labels, rate, first frame, missing points (residual -1) and residuals equal to
    sqrt(trace(cov) / 3) in mm quantised to |POINT:SCALE| (0.1 mm within 3.2 m, 0.5 mm within 8 m):
    within half a step, at least one step, saturating at 255 steps, 0 without covariance."""
    table, xyz, cov = _table(extent_m=extent_m)
    path = write_c3d(tmp_path / "t.c3d", table, FPS, markers=MARKERS, method="smoother")
    assert [p.name for p in tmp_path.iterdir()] == ["t.c3d"]  # atomic: no temporary left behind
    r, pts = read_py_c3d(path)
    scale = abs(float(r.point_scale))
    assert scale == pytest.approx(0.1 if extent_m == 2.0 else 0.5)
    assert [s.strip() for s in r.point_labels] == MARKERS
    assert r.point_rate == FPS and r.first_frame == FIRST + 1 and len(pts) == N_FRAMES
    assert r.get("POINT:UNITS").string_value.strip() == "mm"
    missing = np.isnan(xyz).any(axis=-1)
    res = pts[..., 3]
    assert np.array_equal(res == -1, missing)
    err = np.abs(pts[~missing][:, :3] / 1e3 - xyz[~missing]).max()
    print(f"C3D (py-c3d) max position error {err * 1e6:.3f} um")
    assert err < 1e-6
    counts = expected_counts(cov, ~missing, scale)
    assert np.allclose(res, np.where(counts >= 0, counts * np.float32(scale), -1), rtol=1e-6, atol=0)
    rms_mm = np.sqrt(np.trace(cov, axis1=-2, axis2=-1) / 3) * 1e3
    inner = ~missing & np.isfinite(rms_mm) & (rms_mm < 255 * scale) & (rms_mm > scale)
    assert np.all(np.abs(res[inner] - rms_mm[inner]) <= scale / 2 + 1e-5)
    assert res[30, 1] == pytest.approx(255 * scale) and res[31, 1] == pytest.approx(scale) and res[32, 1] == 0
    assert np.all(pts[..., 4][~missing] == 0)  # no reprojection table: no camera mask
    # the other method is written on request, and is different
    write_c3d(tmp_path / "f.c3d", table, FPS, markers=MARKERS, method="filter")
    _, f = read_py_c3d(tmp_path / "f.c3d")
    assert np.abs(f[~missing][:, :3] / 1e3 - xyz[~missing] - 0.5).max() < 1e-6


def test_c3d_read_by_ezc3d_coordinates_and_missing(tmp_path):
    """ezc3d reads the coordinates and the missing points (NaN); its residuals of float data are the high
    byte (pyomeca/ezc3d#386): here the camera mask, 0. If ezc3d follows the spec one day this fails and the
    module docstring's note goes."""
    table, xyz, _ = _table()
    path = write_c3d(tmp_path / "t.c3d", table, FPS, markers=MARKERS, method="smoother")
    c = ezc3d.c3d(str(path))
    assert c["parameters"]["POINT"]["LABELS"]["value"] == MARKERS
    assert c["header"]["points"]["first_frame"] == FIRST
    back = c["data"]["points"][:3].transpose(2, 1, 0) / 1e3
    missing = np.isnan(xyz).any(axis=-1)
    assert np.array_equal(np.isnan(back).any(axis=-1), missing)
    assert np.nanmax(np.abs(back - xyz)) < 1e-6
    res = c["data"]["meta_points"]["residuals"][0].T
    assert np.all(res[~missing] == 0) and np.all(res[missing] < 0)


def test_c3d_marker_order_and_method_required(tmp_path):
    """``markers`` sets the label order (a marker absent from the table is all missing); a table with
    two methods needs ``method=``."""
    table, xyz, _ = _table()
    with pytest.raises(ValueError, match="several methods"):
        write_c3d(tmp_path / "x.c3d", table, FPS)
    order = ["digit3_r", "body1", "ghost"]
    write_c3d(tmp_path / "o.c3d", table, FPS, markers=order, method="smoother")
    r, pts = read_py_c3d(tmp_path / "o.c3d")
    assert [s.strip() for s in r.point_labels] == order
    ok = pts[..., 3] >= 0
    assert np.array_equal(ok[:, :2], ~np.isnan(xyz[:, [3, 0]]).any(axis=-1))
    assert np.abs(pts[:, :2, :3][ok[:, :2]] / 1e3 - xyz[:, [3, 0]][ok[:, :2]]).max() < 1e-6
    assert not ok[:, 2].any()


# ----- TRC -------------------------------------------------------------------------------------------
class OpenSimTrcError(ValueError):
    pass


def opensim_trc_rule(path: Path) -> tuple[list[str], np.ndarray]:
    """A strict re-implementation of OpenSim 4.6's TRCFileAdapter::extendRead (what it accepts):

    line 1 starts with PathFileType; lines 2-3 are tab-separated keys and values with NumMarkers; line 4
    is ``Frame#  Time`` and exactly NumMarkers names; line 5 the X1 Y1 Z1 ... labels; data rows follow
    (blank lines before them skipped, a blank line after them ends the data). A row is split at tabs the
    way std::getline splits it: an empty cell after the last tab is not a cell. Every row must have exactly
    2 + 3 x NumMarkers cells ("Unexpected number of columns in line N. Expected = E. Received = R.").
    Cells are numbers, NaN/nan, or empty inside a row (read as NaN). Stricter than OpenSim: a cell that is
    not a number is an error. Returns the marker names and the values (rows, 2 + 3 x NumMarkers)."""
    lines = Path(path).read_text().split("\n")
    if not lines[0].startswith("PathFileType"):
        raise OpenSimTrcError("line 1: no PathFileType")
    head = dict(zip(lines[1].rstrip("\t").split("\t"), lines[2].rstrip("\t").split("\t"), strict=True))
    n = int(head["NumMarkers"])
    labels = [c for c in lines[3].split("\t")[2:] if c]
    if lines[3].split("\t")[:2] != ["Frame#", "Time"] or len(labels) != n:
        raise OpenSimTrcError(f"Unexpected number of column labels. Expected = {n}. Received = {len(labels)}.")
    expected = 2 + 3 * n
    rows, i = [], 5
    while i < len(lines) and not lines[i].strip():
        i += 1
    for line_no in range(i + 1, len(lines) + 1):
        line = lines[line_no - 1]
        if not line.strip():
            break
        cells = line.split("\t")
        if cells[-1] == "":
            cells = cells[:-1]  # std::getline: nothing after the last delimiter is no cell
        if len(cells) != expected:
            raise OpenSimTrcError(f"Unexpected number of columns in line {line_no}. Expected = {expected}. "
                                  f"Received = {len(cells)}.")
        rows.append([float(c) if c.strip() else np.nan for c in cells])
    return labels, np.array(rows)


def _old_style(path: Path, dest: Path) -> Path:
    """The file as batgraph wrote it before: missing cells empty (a missing last marker ends the row in tabs)."""
    dest.write_text("\n".join(line.replace("NaN", "") for line in path.read_text().split("\n")))
    return dest


def test_trc_every_row_has_every_cell_and_passes_the_opensim_rule(tmp_path):
    """A missing point is NaN NaN NaN, so every row has 2 + 3 x 4 = 14 cells, also when the last marker is
    missing (frame 20); the old empty cells fail the rule exactly as OpenSim 4.6 failed for the user."""
    table, xyz, _ = _table()
    path = write_trc(tmp_path / "t.trc", table[table["method"] == "smoother"], FPS, markers=MARKERS)
    data = path.read_text().split("\n")[6:-1]
    assert len(data) == N_FRAMES and all(len(row.split("\t")) == 14 for row in data)
    assert data[20].split("\t")[-3:] == ["NaN", "NaN", "NaN"] and not data[20].endswith("\t")
    labels, values = opensim_trc_rule(path)
    assert labels == MARKERS and values.shape == (N_FRAMES, 14)
    assert np.array_equal(np.isnan(values[:, 2:]).reshape(N_FRAMES, 4, 3), np.isnan(xyz))
    with pytest.raises(OpenSimTrcError, match=r"line 7\. Expected = 14\. Received = 13"):  # frame FIRST: all missing
        opensim_trc_rule(_old_style(path, tmp_path / "old.trc"))


def test_trc_read_by_opensim(tmp_path):
    """OpenSim's own TRCFileAdapter (when the opensim wheel is installed) reads our file, values and NaN
    intact; it rejects the old empty-cell file and the rule above agrees with it on both."""
    osim = pytest.importorskip("opensim")
    table, xyz, _ = _table()
    path = write_trc(tmp_path / "t.trc", table[table["method"] == "smoother"], FPS, markers=MARKERS, units="mm")
    t = osim.TimeSeriesTableVec3(str(path))
    assert list(t.getColumnLabels()) == MARKERS and t.getNumRows() == N_FRAMES
    assert t.getTableMetaDataAsString("Units") == "mm"
    flat = t.flatten()  # keep the table alive while numpy reads its matrix (a temporary segfaults)
    back = flat.getMatrix().to_numpy().reshape(N_FRAMES, 4, 3) / 1e3
    assert np.array_equal(np.isnan(back), np.isnan(xyz)) and np.nanmax(np.abs(back - xyz)) < 1e-8
    assert np.allclose(np.array(t.getIndependentColumn()), np.arange(FIRST, FIRST + N_FRAMES) / FPS)
    old = _old_style(path, tmp_path / "old.trc")
    with pytest.raises(RuntimeError, match=r"Unexpected number of columns in line 7\. Expected = 14\. Received = 13"):
        osim.TimeSeriesTableVec3(str(old))


def test_trc_round_trip(tmp_path):
    """TRC is text with 10 significant digits: |x| <= 8 m gives <= 8e-10 m rounding; bound 1e-8 m.
    Header keys, frame numbers (session frame + 1), times (frame / fps), missing cells and the three unit
    choices are checked with batgraph's reader."""
    table, xyz, _ = _table()
    smoother = table[table["method"] == "smoother"]
    for units, scale in (("m", 1.0), ("cm", 1e2), ("mm", 1e3)):
        path = write_trc(tmp_path / f"t_{units}.trc", smoother, FPS, markers=MARKERS, units=units)
        lines = path.read_text().splitlines()
        assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
        head = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
        assert head == {"DataRate": "120", "CameraRate": "120", "NumFrames": str(N_FRAMES),
                        "NumMarkers": str(len(MARKERS)), "Units": units, "OrigDataRate": "120",
                        "OrigDataStartFrame": str(FIRST + 1), "OrigNumFrames": str(N_FRAMES)}
        assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"]
        first = lines[6].split("\t")  # frame FIRST is fully missing
        assert first[0] == str(FIRST + 1) and first[2:] == ["NaN"] * 12
        assert float(lines[7].split("\t")[2]) == pytest.approx(xyz[1, 0, 0] * scale, abs=1e-8 * scale)
        trc = read_trc(path)
        assert trc.markers == MARKERS and trc.units == units and trc.rate_hz == FPS
        assert np.array_equal(trc.frame, np.arange(FIRST, FIRST + N_FRAMES) + 1)
        assert np.allclose(trc.time_s, np.arange(FIRST, FIRST + N_FRAMES) / FPS, atol=1e-12)
        assert np.array_equal(np.isnan(trc.xyz_m), np.isnan(xyz))
        assert np.nanmax(np.abs(trc.xyz_m - xyz)) < 1e-8


def test_read_trc_errors(tmp_path):
    """Bad TRC files give one-line InputErrors that name the file and line."""
    with pytest.raises(InputError, match="file not found"):
        read_trc(tmp_path / "none.trc")
    bad = tmp_path / "bad.trc"
    bad.write_text("hello\n" * 6)
    with pytest.raises(InputError, match="line 1"):
        read_trc(bad)
    table, _, _ = _table()
    path = write_trc(tmp_path / "ok.trc", table[table["method"] == "smoother"], FPS)
    lines = path.read_text().splitlines()
    lines[8] = lines[8].replace(lines[8].split("\t")[3], "abc", 1)
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"line 9, column 4: 'abc'"):
        read_trc(path)


def test_read_real_pose2sim_trc():
    """Pose2Sim's own TRC (real data): 21 markers, 100 frames at 60 Hz, metres, Frame# from 1."""
    if not REAL_TRC.is_file():
        pytest.skip(f"real data absent: {REAL_TRC}")
    trc = read_trc(REAL_TRC)
    assert len(trc.markers) == 21 and trc.markers[0] == "RHip" and trc.markers[-1] == "LWrist"
    assert trc.xyz_m.shape == (100, 21, 3) and trc.rate_hz == 60 and trc.units == "m"
    assert trc.frame[0] == 1 and trc.time_s[0] == pytest.approx(1 / 60)
    assert np.isfinite(trc.xyz_m).all()
    # Y-up: the standing person's height is along the file's Y (head above ankles by > 1 m)
    y = trc.xyz_m[..., 1]
    assert np.all(y[:, trc.markers.index("Head")] - y[:, trc.markers.index("RAnkle")] > 1.0)
    assert opensim_trc_rule(REAL_TRC)[1].shape == (100, 2 + 63)  # the rule accepts OpenSim-world files


# ----- ranges ----------------------------------------------------------------------------------------
def test_keep_range_masks_outside_points():
    """span keeps span == inside, observed keeps status == observed, all keeps everything; a table without
    span gets it from n_views (first..last frame with >= 2 views, per method and marker)."""
    n = np.array([0, 1, 2, 1, 0, 2, 1])
    t = pd.DataFrame({"method": "m", "frame": np.arange(7), "marker": "a", "x": 1.0, "y": 2.0, "z": 3.0,
                      "cov_xx": 1e-6, "n_views": n})
    assert np.isfinite(keep_range(t, "all")["x"]).all()
    assert np.isfinite(keep_range(t, "span")["x"]).tolist() == [False, False, True, True, True, True, False]
    obs = keep_range(t, "observed")
    assert np.isfinite(obs["x"]).tolist() == (n >= 2).tolist()
    assert np.isnan(obs.loc[n < 2, "cov_xx"]).all() and list(obs["status"])[:3] == ["unobserved", "single_view",
                                                                                      "observed"]
    with pytest.raises(ValueError, match="keep must be one of"):
        keep_range(t, "inside")
    with pytest.raises(ValueError, match="needs the table's n_views"):
        keep_range(t.drop(columns="n_views"), "span")


# ----- end to end: every method of a reconstruct, the files it writes, and `export` ----------------------
CAMS = ["cam1", "cam2", "cam3"]
SESSION_MARKERS = ["m0", "m1", "m2"]


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    """A reconstruct of a tiny session (3 cameras, 30 frames, 3 markers) with every method, where m2 is
    unseen in frames 0-3 and 26-29 (outside its span; triangulate has no estimate there: the last marker's
    cells of a TRC row), m1 is seen by cam1 alone in frames 10-12 (single_view), m0 by nobody in frame 15
    and by cam1 + cam3 in frames 20-22."""
    from batgraph.pipeline import reconstruct

    tmp = tmp_path_factory.mktemp("recon")
    rig = tiny_rig(3)
    xyz = tiny_scene(30, 3, seed=2)
    obs = observations_table(rig, xyz, SESSION_MARKERS)
    f, c, m = obs["frame"], obs["camera"], obs["marker"]
    drop = (((m == "m2") & ((f <= 3) | (f >= 26))) | ((m == "m1") & f.between(10, 12) & (c != "cam1"))
            | ((m == "m0") & (f == 15)) | ((m == "m0") & f.between(20, 22) & (c == "cam2")))
    session = Session(name="s", fps=100.0, rig=rig, observations=obs[~drop].reset_index(drop=True),
                      motion=MotionConfig(model="random_walk", **PAPER_PHYSICS), marker_names=SESSION_MARKERS)
    folder = write_session(session, tmp / "s")
    out = tmp / "out"
    result = reconstruct(folder, out, methods=list(ALL_METHODS), viewer="none")
    return out, result.trajectories, result.reprojection


def test_every_methods_c3d_read_by_py_c3d(recon, tmp_path):
    """For each of the five methods, written with every estimate (--range all): py-c3d reads each position
    back to 1e-6 m, a residual of sqrt(trace(cov) / 3) quantised to 0.1 mm, -1 exactly where the method has
    no estimate (triangulate's missing points included), and the camera byte = the cameras of the
    reprojection table's non-outlier observations (frames 20-22 of m0: cam1 + cam3 = 0b101)."""
    _, traj, reproj = recon
    tri = traj[traj["method"] == "triangulate"]
    assert tri["x"].isna().sum() == (tri["n_views"] < 2).sum() == 8 + 3 + 1  # m2's ends, m1's single
    # views, m0's frame 15: triangulate estimates a point from >= 2 views only
    for method in ALL_METHODS:
        one = traj[traj["method"] == method].sort_values(["frame", "marker"])
        path = write_c3d(tmp_path / f"{method}.c3d", one, 100.0, SESSION_MARKERS, keep="all",
                         reprojection=reproj, cameras=CAMS)
        r, pts = read_py_c3d(path)
        F = 30
        xyz = one[["x", "y", "z"]].to_numpy(float).reshape(F, 3, 3)
        missing = np.isnan(xyz).any(axis=-1)
        assert np.array_equal(pts[..., 3] == -1, missing), method
        assert np.abs(pts[..., :3][~missing] / 1e3 - xyz[~missing]).max() < 1e-6, method
        cov = cov_matrices(one).reshape(F, 3, 3, 3)
        counts = expected_counts(cov, ~missing, 0.1)
        assert np.allclose(pts[..., 3], np.where(counts >= 0, counts * np.float32(0.1), -1), rtol=1e-6), method
        mask = np.zeros((F, 3), int)
        ok = reproj[(reproj["method"] == method) & ~reproj["outlier"].astype(bool)]
        for fr, cam, mk in ok[["frame", "camera", "marker"]].itertuples(index=False):
            mask[fr, SESSION_MARKERS.index(mk)] |= 1 << CAMS.index(cam)
        assert np.array_equal(pts[..., 4][~missing], mask[~missing]), method
        assert np.all(pts[20:23, 0, 4][~missing[20:23, 0]] == 0b101), method


def test_reconstruct_writes_span_limited_c3d_and_trc(recon):
    """reconstruct's trajectories.c3d / .trc hold the smoother's points inside each marker's span only:
    m2's frames 0-3 and 26-29 are missing although the smoother estimated them; inside, every estimate
    (single_view, unobserved) is kept. Both files pass py-c3d and the OpenSim rule."""
    out, traj, _ = recon
    sm = traj[traj["method"] == "smoother"].sort_values(["frame", "marker"])
    assert np.isfinite(sm["x"]).all()
    inside = (sm["span"] == "inside").to_numpy().reshape(30, 3)
    assert not inside[:4, 2].any() and not inside[26:, 2].any() and inside.sum() == 90 - 8
    r, pts = read_py_c3d(out / "trajectories.c3d")
    assert np.array_equal(pts[..., 3] >= 0, inside)
    assert r.get("BATGRAPH:RANGE").string_value.strip() == "span"
    assert [s.strip() for s in r.get("BATGRAPH:CAMERAS").string_array] == CAMS
    seen = (sm["n_views"] >= 1).to_numpy().reshape(30, 3)
    assert np.all(pts[..., 4][inside & seen] > 0)  # a kept point seen by a camera has its camera bits
    assert np.all(pts[..., 4][inside & ~seen] == 0)  # m0 in frame 15: seen by none
    labels, values = opensim_trc_rule(out / "trajectories.trc")
    assert labels == SESSION_MARKERS
    assert np.array_equal(np.isfinite(values[:, 2:]).reshape(30, 3, 3).all(axis=-1), inside)


def test_export_ranges_and_tables(recon, tmp_path, capsys):
    """`export c3d|trc --range` and `export csv|parquet`: observed <= span <= all point counts; the analysis
    table's sd * sd * r gives back trajectories.csv's covariance, in mm with --units mm; csv == parquet."""
    out, traj, _ = recon
    counts = {}
    for rng in ("observed", "span", "all"):
        assert main(["export", "trc", str(out), "--method", "triangulate", "--range", rng,
                     "--to", str(tmp_path / f"{rng}.trc")]) == 0
        _, v = opensim_trc_rule(tmp_path / f"{rng}.trc")
        assert v.shape == (30, 2 + 9)  # every row every cell, also where the last marker m2 is missing
        assert main(["export", "c3d", str(out), "--range", rng, "--to", str(tmp_path / f"{rng}.c3d")]) == 0
        r, pts = read_py_c3d(tmp_path / f"{rng}.c3d")
        assert [s.strip() for s in r.get("BATGRAPH:CAMERAS").string_array] == CAMS  # rig order, from summary.json
        counts[rng] = int((pts[..., 3] >= 0).sum())
    sm = traj[traj["method"] == "smoother"]
    assert counts == {"observed": int((sm["status"] == "observed").sum()),
                      "span": int((sm["span"] == "inside").sum()), "all": 90}
    assert counts["observed"] < counts["span"] < counts["all"]
    assert main(["export", "c3d", str(out), "--units", "m"]) == 2
    assert "always written in mm" in capsys.readouterr().err

    assert main(["export", "csv", str(out), "--method", "all", "--units", "mm", "--range", "all",
                 "--to", str(tmp_path / "t.csv")]) == 0
    assert main(["export", "parquet", str(out), "--method", "all", "--units", "mm", "--range", "all",
                 "--to", str(tmp_path / "t.parquet")]) == 0
    csv, pq = pd.read_csv(tmp_path / "t.csv"), pd.read_parquet(tmp_path / "t.parquet")
    assert list(csv.columns) == ["method", "frame", "time_s", "marker", "x_mm", "y_mm", "z_mm", "sd_x_mm",
                                 "sd_y_mm", "sd_z_mm", "r_xy", "r_xz", "r_yz", "n_views", "status", "span"]
    assert len(csv) == len(traj) and set(csv["method"]) == set(ALL_METHODS)
    pd.testing.assert_frame_equal(csv, pq, check_dtype=False, rtol=1e-8)
    back = pd.read_csv(out / "trajectories.csv")
    assert np.allclose(csv["x_mm"], back["x"] * 1e3, rtol=1e-8, equal_nan=True)
    sd = csv[["sd_x_mm", "sd_y_mm", "sd_z_mm"]].to_numpy() / 1e3
    ok = np.isfinite(sd).all(axis=1) & (sd > 0).all(axis=1)
    assert ok.sum() > 300
    assert np.allclose(sd[ok] ** 2, back.loc[ok, ["cov_xx", "cov_yy", "cov_zz"]], rtol=1e-7)
    assert np.allclose(csv.loc[ok, "r_xy"] * sd[ok, 0] * sd[ok, 1], back.loc[ok, "cov_xy"], rtol=1e-6, atol=1e-18)
    assert np.allclose(csv.loc[ok, "r_yz"] * sd[ok, 1] * sd[ok, 2], back.loc[ok, "cov_yz"], rtol=1e-6, atol=1e-18)
    assert (np.abs(csv.loc[ok, ["r_xy", "r_xz", "r_yz"]]) <= 1 + 1e-9).all().all()
    assert (csv[["status", "span", "n_views"]] == back[["status", "span", "n_views"]]).all().all()
    # the default range: only the span, and a table from the function equals the CLI's
    span = analysis_table(traj, units="m", method="smoother")
    assert span["x_m"].notna().sum() == (traj.loc[traj["method"] == "smoother", "span"] == "inside").sum()


def test_export_dltdv_range_names_and_residuals(recon, tmp_path, capsys):
    """`export dltdv`: by default m2's extrapolated track ends (frames 0-3, 26-29, estimated by the smoother) are
    NaN and the terminal says how to include them; --range observed / all as for C3D; positions equal
    trajectories.csv's where written, residuals only there; columns named after the markers (m0_X, m0_dltres)."""
    out, traj, reproj = recon
    sm = traj[traj["method"] == "smoother"].sort_values(["frame", "marker"])
    got = {}
    for rng in ("span", "observed", "all"):
        argv = ["export", "dltdv", str(out), "--to", str(tmp_path / f"{rng}_")]
        assert main(argv + ([] if rng == "span" else ["--range", rng])) == 0
        said = capsys.readouterr()
        if rng == "span":
            assert "--range all" in said.out and "track ends" in said.out
        xyz = pd.read_csv(tmp_path / f"{rng}_xyzpts.csv")
        res = pd.read_csv(tmp_path / f"{rng}_xyzres.csv")
        assert list(xyz.columns) == [f"{m}_{a}" for m in SESSION_MARKERS for a in "XYZ"]
        assert list(res.columns) == [f"{m}_dltres" for m in SESSION_MARKERS]
        assert len(xyz) == len(res) == 30
        got[rng] = xyz.to_numpy().reshape(30, 3, 3)
        written = np.isfinite(got[rng]).all(axis=-1)
        assert np.array_equal(np.isfinite(got[rng]).any(axis=-1), written)
        assert not (np.isfinite(res.to_numpy()) & ~written).any()  # no residual without its position
        assert np.isfinite(res.to_numpy()[written & (sm["n_views"] >= 1).to_numpy().reshape(30, 3)]).all()
        want = {"span": sm["span"] == "inside", "observed": sm["status"] == "observed",
                "all": sm["x"].notna()}[rng].to_numpy().reshape(30, 3)
        assert np.array_equal(written, want), rng
        assert np.allclose(got[rng][written], sm[["x", "y", "z"]].to_numpy().reshape(30, 3, 3)[written], atol=1e-9)
    assert not np.isfinite(got["span"][:4, 2]).any() and np.isfinite(got["all"][:4, 2]).all()


def test_dltdv_point_names_where_dltdv_can_read_them():
    """Marker names become DLTdv column stems when every one is a MATLAB identifier that fits, they differ
    regardless of case and none is another point's ptK; otherwise every point is numbered, with the reason."""
    from batgraph.formats.dltdv import point_names

    assert point_names(["body1", "wrist_r", "Digit3"]) == (["body1", "wrist_r", "Digit3"], None)
    assert point_names(["pt1", "pt2"]) == (["pt1", "pt2"], None)  # a DLTdv project's own points
    for markers, why in ((["body 1", "b"], "MATLAB identifier"), (["1st", "b"], "MATLAB identifier"),
                         (["a" * 57, "b"], "at most 56"), (["wing", "Wing"], "case"), (["pt2", "pt1"], "point 1")):
        stems, reason = point_names(markers)
        assert stems == ["pt1", "pt2"] and why in reason, (markers, reason)
    assert point_names(["a" * 56])[1] is None
