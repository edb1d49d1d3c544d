"""C3D and TRC exports of a trajectories table, read back with ezc3d and batgraph's TRC reader."""

from pathlib import Path

import ezc3d
import numpy as np
import pandas as pd
import pytest

from batgraph.errors import InputError
from batgraph.formats.c3d_trc import C3D_RESIDUAL_STEP_MM, read_trc, write_c3d, write_trc

FPS = 120.0
MARKERS = ["body1", "body2", "wrist_r", "digit3_r"]
FIRST, N_FRAMES = 3, 40
COV_COLS = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]

REAL_TRC = (Path(__file__).parents[2] / "shared/data/real/pose2sim_demo_4cam_human/S00_P00_SingleParticipant"
            / "S00_P00_T01_BalancingTrial/pose-3d/S00_P00_T01_BalancingTrial_0-100.trc")


def _table(seed: int = 0) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """A two-method trajectories table (CONTRACT.md section 3) with missing points.

    Returns the table and the smoother's truth: xyz (F, M, 3) [m] with NaN where missing, and
    covariances (F, M, 3, 3) [m^2]. Positions span +-8 m so float32 rounding is exercised.
    """
    rng = np.random.default_rng(seed)
    F, M = N_FRAMES, len(MARKERS)
    xyz = rng.uniform(-8.0, 8.0, (F, M, 3))
    A = rng.normal(0, 2e-3, (F, M, 3, 3))  # std of a few mm
    cov = A @ np.swapaxes(A, -1, -2) + np.eye(3) * 1e-8
    cov[30, 1] = np.eye(3)  # std 1 m: the C3D residual saturates
    cov[31, 1] = np.eye(3) * 1e-12  # std 1 um: rounds up to one residual step, never 0
    cov[32, 1] = np.nan  # an estimate without covariance: residual 0
    xyz[5:9, 2] = np.nan  # a gap of one marker
    xyz[0, :] = np.nan  # a whole frame missing
    xyz[20, 3, :] = np.nan
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


def test_c3d_round_trip(tmp_path):
    """Positions back to 1e-6 m: C3D holds float32 mm; |x| <= 8 m = 8000 mm < 8192 mm, where the float32
    spacing is 2^-11 mm, so rounding is <= 2^-12 mm = 0.24 um (measured 0.242 um); bound 1 um.
    Labels, rate, units, first frame, frame count, missing points (NaN, residual -1) and residuals
    (RMS per-axis std in mm, quantised to 0.1 mm: bound half a step + float32 noise) are checked."""
    table, xyz, cov = _table()
    path = write_c3d(tmp_path / "t.c3d", table, FPS, markers=MARKERS, method="smoother")
    assert [p.name for p in tmp_path.iterdir()] == ["t.c3d"]  # atomic: no temporary left behind
    c = ezc3d.c3d(str(path), extract_forceplat_data=False)
    point = c["parameters"]["POINT"]
    assert point["LABELS"]["value"] == MARKERS
    assert point["RATE"]["value"][0] == FPS
    assert point["UNITS"]["value"] == ["mm"]
    assert c["header"]["points"]["first_frame"] == FIRST
    pts = c["data"]["points"]  # (4, M, F) [mm]
    assert pts.shape == (4, len(MARKERS), N_FRAMES)
    back = pts[:3].transpose(2, 1, 0) / 1e3
    missing = np.isnan(xyz).any(axis=-1)
    assert np.array_equal(np.isnan(back).any(axis=-1), missing)
    err = np.nanmax(np.abs(back - xyz))
    print(f"C3D max position error {err * 1e6:.3f} um")
    assert err < 1e-6, err
    res = c["data"]["meta_points"]["residuals"][0].T  # (F, M) [mm]
    assert np.all(res[missing] == -1)
    rms_mm = np.sqrt(np.trace(cov, axis1=-2, axis2=-1) / 3) * 1e3
    expected = np.where(np.isfinite(rms_mm), np.clip(rms_mm, C3D_RESIDUAL_STEP_MM, 255 * C3D_RESIDUAL_STEP_MM), 0)
    assert res[30, 1] == pytest.approx(25.5) and res[31, 1] == pytest.approx(0.1) and res[32, 1] == 0
    assert np.all(np.abs(res[~missing] - expected[~missing]) <= C3D_RESIDUAL_STEP_MM / 2 + 1e-5)
    # the other method is written on request, and is different
    write_c3d(tmp_path / "f.c3d", table, FPS, markers=MARKERS, method="filter")
    f = ezc3d.c3d(str(tmp_path / "f.c3d"))["data"]["points"][:3].transpose(2, 1, 0) / 1e3
    assert np.nanmax(np.abs(f - xyz - 0.5)) < 1e-6


def test_c3d_marker_order_and_method_required(tmp_path):
    """``markers`` sets the label order (a marker absent from the table is all missing); a table with
    two methods needs ``method=``."""
    table, xyz, _ = _table()
    with pytest.raises(ValueError, match="several methods"):
        write_c3d(tmp_path / "x.c3d", table, FPS)
    order = ["digit3_r", "body1", "ghost"]
    write_c3d(tmp_path / "o.c3d", table, FPS, markers=order, method="smoother")
    c = ezc3d.c3d(str(tmp_path / "o.c3d"))
    assert c["parameters"]["POINT"]["LABELS"]["value"] == order
    pts = c["data"]["points"][:3].transpose(2, 1, 0) / 1e3
    assert np.nanmax(np.abs(pts[:, :2] - xyz[:, [3, 0]])) < 1e-6
    assert np.isnan(pts[:, 2]).all()


def test_trc_round_trip(tmp_path):
    """TRC is text with 10 significant digits: |x| <= 8 m gives <= 8e-10 m rounding; bound 1e-8 m
    (tighter than the 1e-6 m asked). Header keys, frame numbers (session frame + 1), times (frame / fps),
    missing cells and both unit choices are checked."""
    table, xyz, _ = _table()
    smoother = table[table["method"] == "smoother"]
    for units, scale in (("m", 1.0), ("mm", 1e3)):
        path = write_trc(tmp_path / f"t_{units}.trc", smoother, FPS, markers=MARKERS, units=units)
        lines = path.read_text().splitlines()
        assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
        head = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
        assert head == {"DataRate": "120", "CameraRate": "120", "NumFrames": str(N_FRAMES),
                        "NumMarkers": str(len(MARKERS)), "Units": units, "OrigDataRate": "120",
                        "OrigDataStartFrame": str(FIRST + 1), "OrigNumFrames": str(N_FRAMES)}
        assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"]
        first = lines[6].split("\t")  # frame FIRST is fully missing: empty cells
        assert first[0] == str(FIRST + 1) and all(c == "" for c in first[2:])
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
