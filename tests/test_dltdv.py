"""DLTdv8/DLTdv7 import and export: a trial written in DLTdv's own files, imported, triangulated by
batgraph, and compared with DLTdv's own reconstruction (plain 11-parameter DLT) of the same clicks.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from conftest import look_at, tiny_scene

from batgraph.camera import Camera, Rig
from batgraph.errors import InputError
from batgraph.formats import dltdv
from batgraph.geometry import dlt
from batgraph.session import dense_observations, read_session
from batgraph.triangulate import triangulate

SIZE = (1280, 720)


def dlt_reconstruct(coefs: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """DLTdv's reconstruction, the reference: linear least squares on the 11 DLT coefficients.

    coefs: (C, 11) in the clicks' pixel convention; uv_px: (C, N, 2), NaN where not digitised.
    Each camera that sees a point adds ``(L1 - u L9) X + (L2 - u L10) Y + (L3 - u L11) Z = u - L4`` and
    the same for v with L5..L8; solved per point with >= 2 cameras. Returns xyz (N, 3), NaN otherwise.
    """
    L = np.asarray(coefs, float)
    seen = np.isfinite(uv_px[..., 0])  # (C, N)
    u = np.where(seen, uv_px[..., 0], 0.0)[..., None]
    v = np.where(seen, uv_px[..., 1], 0.0)[..., None]
    rows_u = L[:, None, 0:3] - u * L[:, None, 8:11]  # (C, N, 3)
    rows_v = L[:, None, 4:7] - v * L[:, None, 8:11]
    A = np.concatenate([rows_u, rows_v], axis=0) * np.concatenate([seen, seen])[..., None]  # (2C, N, 3)
    b = np.concatenate([u[..., 0] - L[:, None, 3], v[..., 0] - L[:, None, 7]]) * np.concatenate([seen, seen])
    A, b = np.moveaxis(A, 1, 0), np.moveaxis(b, 1, 0)  # (N, 2C, 3), (N, 2C)
    ok = seen.sum(axis=0) >= 2
    xyz = np.full((uv_px.shape[1], 3), np.nan)
    xyz[ok] = (np.linalg.pinv(A[ok]) @ b[ok][..., None])[..., 0]
    return xyz


def _rig() -> Rig:
    """Four zero-distortion cameras (a DLT has none) around a 1 m volume; one with skew."""
    Ks = [np.array([[1100.0 + 80 * i, 3.0 if i == 2 else 0.0, 640.0 - 7 * i], [0, 1105.0 + 80 * i, 355.0 + 5 * i],
                    [0, 0, 1]]) for i in range(4)]
    centres = [[3.0, 0.5, 1.0], [-0.4, 3.2, 1.4], [-2.8, -1.0, 0.6], [0.6, -3.0, 2.0]]
    return Rig([look_at(f"cam{i + 1}", c, [0.0, 0.0, 0.2], K, SIZE) for i, (c, K) in enumerate(zip(centres, Ks,
                                                                                                  strict=True))])


def _trial(tmp_path, origin: str, noise_px: float = 0.0, seed: int = 0, units: str = "m", mirror: bool = False):
    """Write a DLTdv trial (xypts, dltCoefs, xyzpts) with ``origin`` pixels; returns what a test needs.

    units: the files' world units; mirror: the files' world is the rig's with z negated (left-handed).

    40 frames of 5 moving markers; 35 % of the clicks are dropped, and those outside the image, so
    points have 0..4 views.
    The xyzpts file holds DLTdv's own reconstruction (:func:`dlt_reconstruct` of the written clicks).
    """
    rng = np.random.default_rng(seed)
    rig = _rig()
    F, M = 40, 5
    xyz = 3 * tiny_scene(F, M, seed)
    uv_cv = rig.project(xyz)  # (C, F, M, 2)
    uv_cv = uv_cv + noise_px * rng.normal(size=uv_cv.shape)
    uv_cv[rng.random(uv_cv.shape[:3]) < 0.35] = np.nan
    uv_cv[~np.stack([cam.in_image(uv_cv[c]) for c, cam in enumerate(rig)])] = np.nan  # a camera sees its image
    assert np.isfinite(uv_cv).all(axis=-1).sum() > 0
    uv = dltdv.from_opencv_px(uv_cv, origin, SIZE[1])
    c, f, m = np.nonzero(np.isfinite(uv[..., 0]))
    table = pd.DataFrame({"frame": f, "camera_index": c, "point_index": m, "u": uv[c, f, m, 0],
                          "v": uv[c, f, m, 1]})
    paths = {k: tmp_path / f"trial_{origin}_{k}.csv" for k in ("xypts", "dltCoefs", "xyzpts")}
    dltdv.write_xypts(paths["xypts"], table, n_cams=len(rig), n_points=M, n_frames=F)
    file_rig = Rig(rig.cameras, world_mirror=[1, 1, -1] if mirror else [1, 1, 1])
    dltdv.write_dlt_coefs(paths["dltCoefs"], file_rig, origin, SIZE, units)
    # DLTdv's own 3D, from its own files (no pixel conversion at all)
    L = dltdv.read_dlt_coefs(paths["dltCoefs"])
    clicks = dltdv.read_xypts(paths["xypts"], n_cams=len(rig))
    uv_file = np.full((len(rig), F * M, 2), np.nan)
    uv_file[clicks["camera_index"], clicks["frame"] * M + clicks["point_index"]] = clicks[["u", "v"]].to_numpy()
    ref = dlt_reconstruct(L, uv_file).reshape(F, M, 3)
    ff, mm = np.meshgrid(np.arange(F), np.arange(M), indexing="ij")
    dltdv.write_xyzpts(paths["xyzpts"], pd.DataFrame({"frame": ff.ravel(), "point_index": mm.ravel(),
                                                      "x": ref[..., 0].ravel(), "y": ref[..., 1].ravel(),
                                                      "z": ref[..., 2].ravel()}), n_points=M, n_frames=F)
    return rig, xyz, ref, paths


def _batgraph_xyz(session, n_frames: int) -> np.ndarray:
    """batgraph.triangulate on the imported session, as (n_frames, M, 3) indexed by frame from 0."""
    dense = dense_observations(session)
    xyz, cov = triangulate(session.rig, dense, 1.0)  # positions do not depend on the noise
    out = np.full((n_frames, len(dense.markers), 3), np.nan)
    out[dense.frames] = xyz
    assert dense.markers == [f"pt{j + 1}" for j in range(len(dense.markers))]
    return out


@pytest.mark.parametrize("origin", ["lower-left", "upper-left"])
def test_import_then_triangulate_equals_dltdv_reconstruction(tmp_path, origin):
    """Noise-free clicks: batgraph (OpenCV pixels, K R t, homogeneous DLT) equals DLTdv's own
    reconstruction (its pixels, its coefficients, inhomogeneous DLT) and the truth.

    A pixel-convention slip of 1 px would move points by ~2 mm here. Clicks are stored with 6
    decimals (5e-7 px rounding ~ 1e-8 m). Measured max difference to DLTdv 2.0e-10 m (v8 and v7),
    to the truth 5.6e-9 m; bound 1e-6 m for both. The pixel origin is detected from the coefficients.
    """
    rig, truth, ref, paths = _trial(tmp_path, origin)
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 120.0, tmp_path / "session",
                                 image_size=SIZE, xyzpts=paths["xyzpts"])
    imp = session.extra_toml["import"]
    assert (imp["pixel_origin"], imp["pixel_origin_source"], imp["world"]) == (origin, "detected", "right-handed")
    assert session.warnings == []  # every click inside its image, so in the right convention
    ours = _batgraph_xyz(session, len(truth))
    both = np.isfinite(ref).all(-1)
    np.testing.assert_array_equal(np.isfinite(ours).all(-1), both)  # NaN where < 2 views, in both
    assert 0.3 < both.mean() < 0.95, "the trial has points with and without 2 views"
    assert np.abs(ours[both] - ref[both]).max() < 1e-6
    assert np.abs(ours[both] - truth[both]).max() < 1e-6
    # the cameras are the ones that were written, whatever the file convention
    for a, b in zip(rig, session.rig, strict=True):
        np.testing.assert_allclose(b.K, a.K, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.tvec, a.tvec, rtol=0, atol=1e-9)
    # and the clicks are now OpenCV raw pixels: they reproject onto the cameras' own projection
    obs = session.observations
    for cam in session.rig:
        o = obs[obs.camera == cam.name]
        pred = cam.project(truth[o.frame.to_numpy(), [int(m[2:]) - 1 for m in o.marker]])
        assert np.abs(pred - o[["u", "v"]].to_numpy()).max() < 1e-5  # 6-decimal storage


def test_noisy_clicks_agree_with_dltdv_to_noise_level(tmp_path):
    """With 0.5 px click noise both linear methods see the same clicks but weight cameras differently
    (batgraph: rows scaled to depth x pixel error, homogeneous SVD; DLTdv: rows in units of the DLT's
    own scale, inhomogeneous), so they differ by a small fraction of the noise-induced error itself.
    Measured over seeds 0-5: RMS difference 0.15-0.17 mm (max 0.38-0.58 mm) vs RMS error to truth
    2.0-2.3 mm for both methods (ratio 0.065-0.084); bounds: ratio 0.15, max difference 1 mm, and
    batgraph's RMS error within 5 % of DLTdv's.
    """
    _, truth, ref, paths = _trial(tmp_path, "lower-left", noise_px=0.5, seed=3)
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 120.0, tmp_path / "session")
    ours = _batgraph_xyz(session, len(truth))
    both = np.isfinite(ref).all(-1)

    def rms(a):
        return np.sqrt((np.linalg.norm(a, axis=-1) ** 2).mean())

    diff = ours[both] - ref[both]
    err_ref, err_ours = rms(ref[both] - truth[both]), rms(ours[both] - truth[both])
    assert rms(diff) < 0.15 * err_ref and np.linalg.norm(diff, axis=-1).max() < 1e-3
    assert err_ours < 1.05 * err_ref


def test_xyzpts_kept_as_reference_and_files_written(tmp_path):
    _, _, ref, paths = _trial(tmp_path, "lower-left")
    out = tmp_path / "session"
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 250.0, out, xyzpts=paths["xyzpts"],
                                 marker_names=[f"m{j}" for j in range(5)], camera_names=list("ABCD"))
    for name in ("session.toml", "calibration.toml", "observations.csv", "reference_xyz.csv"):
        assert (out / name).is_file()
    assert session.fps == 250.0 and session.rig.names == list("ABCD") and session.marker_names[:1] == ["m0"]
    r = session.reference
    ok = np.isfinite(ref).all(-1)
    assert len(r) == ok.sum()
    got = r[["x", "y", "z"]].to_numpy()
    want = ref[r.frame.to_numpy(), [int(m[1:]) for m in r.marker]]
    assert np.abs(got - want).max() < 1e-8  # written with 9 decimals
    assert session.extra_toml["import"]["format"] == "dltdv"
    assert read_session(out).reference.equals(r)


@pytest.mark.parametrize("origin", ["lower-left", "upper-left"])
def test_inferred_image_size(tmp_path, origin):
    """Without --image-size: the file's principal point (cx, cy) is the centre, W = round(2 cx - 1),
    H = round(2 cy - 1) in the file's 1-based pixels whatever the origin, enlarged to hold every click;
    the session records that it was guessed (reconstruct warns)."""
    _, _, _, paths = _trial(tmp_path, origin)
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 100.0, tmp_path / "s")
    P = dlt.dlt_matrix(dltdv.read_dlt_coefs(paths["dltCoefs"]))
    clicks = dltdv.read_xypts(paths["xypts"])
    for c, cam in enumerate(session.rig):
        want = np.round(2 * dlt.principal_point(P[c]) - 1)
        uv = clicks.loc[clicks.camera_index == c, ["u", "v"]].to_numpy()
        want = np.maximum(want, np.ceil(uv.max(axis=0) - 0.5))
        assert cam.size_wh == tuple(int(x) for x in want)
        assert abs(cam.size_wh[1] - SIZE[1]) < 60  # principal points 10-25 px off centre
    assert session.warnings == []
    assert session.extra_toml["import"]["image_size"] == "inferred"


def test_pixel_conventions_by_hand():
    """OpenCV's top-left pixel centre is (1, 1) upper-left and (1, H) lower-left (DLTdv); the bottom-right
    is (W, H) / (W, 1)."""
    W, H = SIZE
    cv = np.array([[0.0, 0.0], [W - 1, H - 1], [np.nan, np.nan]])
    np.testing.assert_array_equal(dltdv.from_opencv_px(cv, "upper-left")[:2], [[1, 1], [W, H]])
    np.testing.assert_array_equal(dltdv.from_opencv_px(cv, "lower-left", H)[:2], [[1, H], [W, 1]])
    assert np.isnan(dltdv.from_opencv_px(cv, "lower-left", H)[2]).all()
    for origin in dlt.PIXEL_ORIGINS:
        np.testing.assert_allclose(dltdv.to_opencv_px(dltdv.from_opencv_px(cv, origin, H), origin, H), cv)
    with pytest.raises(ValueError):
        dlt.pixel_affine("lower-left")


@pytest.mark.parametrize("origin", ["lower-left", "upper-left"])
def test_coefficient_file_round_trip(tmp_path, origin):
    """Camera -> DLTdv coefficient file -> Camera, skew included. Measured 6.3e-13 px on K, 3.5e-15 on R,
    1.9e-15 m on t (v8 and v7); bound 1e-9."""
    rig = _rig()
    path = tmp_path / "c.csv"
    dltdv.write_dlt_coefs(path, rig, origin, SIZE)
    L = dltdv.read_dlt_coefs(path)
    assert L.shape == (4, 11) and len(path.read_text().splitlines()) == 11
    L_cv = dltdv.coefs_to_opencv(L, origin, SIZE[1])
    for cam, l_cv in zip(rig, L_cv, strict=True):
        back = Camera.from_dlt(cam.name, l_cv, SIZE)
        np.testing.assert_allclose(back.K, cam.K, rtol=0, atol=1e-9)
        np.testing.assert_allclose(back.R, cam.R, rtol=0, atol=1e-9)
        np.testing.assert_allclose(back.tvec, cam.tvec, rtol=0, atol=1e-9)
    # the file's coefficients project into the file's pixel convention
    xyz = np.array([[0.1, -0.2, 0.3]])
    for cam, l in zip(rig, L, strict=True):
        den = xyz @ l[8:11] + 1
        uv = np.stack([(xyz @ l[0:3] + l[3]) / den, (xyz @ l[4:7] + l[7]) / den], axis=1)
        np.testing.assert_allclose(uv, dltdv.from_opencv_px(cam.project(xyz), origin, SIZE[1]), atol=1e-9)


def test_wide_file_round_trips(tmp_path):
    """read_xypts(write_xypts(t)) == t; the same for xyzpts and xyzres; NaN written as NaN."""
    rng = np.random.default_rng(7)
    t = pd.DataFrame({"frame": [0, 0, 3, 5], "camera_index": [0, 1, 1, 0], "point_index": [0, 2, 1, 2],
                      "u": rng.uniform(0, 100, 4).round(6), "v": rng.uniform(0, 100, 4).round(6)})
    dltdv.write_xypts(tmp_path / "xy.csv", t, n_cams=3, n_points=3, n_frames=8)
    text = (tmp_path / "xy.csv").read_text().splitlines()
    assert text[0].startswith("pt1_cam1_X,pt1_cam1_Y,pt1_cam2_X,") and len(text) == 9 and "NaN" in text[1]
    back = dltdv.read_xypts(tmp_path / "xy.csv")
    pd.testing.assert_frame_equal(back, t.astype({c: np.int64 for c in ("frame", "camera_index", "point_index")}))
    assert back.attrs == {"n_frames": 8, "n_points": 3, "n_cams": 3}

    x = pd.DataFrame({"frame": [1, 2], "point_index": [0, 1], "x": [0.1, 0.2], "y": [1.0, 2.0], "z": [-1.0, 3.0]})
    dltdv.write_xyzpts(tmp_path / "xyz.csv", x, n_frames=4)
    assert (tmp_path / "xyz.csv").read_text().startswith("pt1_X,pt1_Y,pt1_Z,pt2_X")
    pd.testing.assert_frame_equal(dltdv.read_xyzpts(tmp_path / "xyz.csv"), x)
    r = pd.DataFrame({"frame": [0, 3], "point_index": [1, 0], "residual": [0.5, 1.25]})
    dltdv.write_xyzres(tmp_path / "res.csv", r, n_points=2)
    assert (tmp_path / "res.csv").read_text().startswith("pt1_dltres,pt2_dltres\n")
    pd.testing.assert_frame_equal(dltdv.read_xyzres(tmp_path / "res.csv"), r.sort_values("frame", ignore_index=True))


# ----------------------------------------------------------------------------------------------
# user errors: one line, naming the file and the row/column
# ----------------------------------------------------------------------------------------------
@pytest.fixture
def trial(tmp_path):
    return _trial(tmp_path, "lower-left")[3]


def _import_error(paths, tmp_path, **kwargs) -> str:
    args = dict(xypts=paths["xypts"], coefs=paths["dltCoefs"], fps=100.0, out=tmp_path / "out")
    args.update(kwargs)
    with pytest.raises(InputError) as e:
        dltdv.import_dltdv(**args)
    msg = str(e.value)
    assert "\n" not in msg
    assert not (tmp_path / "out").exists(), "nothing is written for bad input"
    return msg


def _set_cell(path, line_no: int, col: int, value: str) -> None:
    lines = path.read_text().splitlines()
    cells = lines[line_no - 1].split(",")
    cells[col] = value
    lines[line_no - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("arg", ["xypts", "coefs", "xyzpts"])
def test_missing_files(trial, tmp_path, arg):
    msg = _import_error(trial, tmp_path, **{arg: tmp_path / "nope.csv"})
    assert f"{tmp_path / 'nope.csv'}: file not found" in msg


def test_wrong_column_pattern(trial, tmp_path):
    _set_cell(trial["xypts"], 1, 3, "pt1_camera2_Y")
    msg = _import_error(trial, tmp_path)
    assert "xypts.csv line 1" in msg and "'pt1_camera2_Y'" in msg and "pt{p}_cam{c}_X" in msg


def test_missing_column(trial, tmp_path):
    df = pd.read_csv(trial["xypts"]).drop(columns="pt3_cam2_Y")
    df.to_csv(trial["xypts"], index=False, na_rep="NaN")
    msg = _import_error(trial, tmp_path)
    assert "xypts.csv line 1" in msg and "missing column pt3_cam2_Y" in msg


def test_non_numeric_click(trial, tmp_path):
    _set_cell(trial["xypts"], 7, 4, "12.5px")
    msg = _import_error(trial, tmp_path)
    assert "xypts.csv line 7, column pt1_cam3_X: '12.5px' is not a number" in msg


def test_half_digitised_click(trial, tmp_path):
    df = pd.read_csv(trial["xypts"])
    i = int(np.argmax(df["pt2_cam1_X"].notna()))
    df.loc[i, "pt2_cam1_Y"] = np.nan
    df.to_csv(trial["xypts"], index=False, na_rep="NaN")
    msg = _import_error(trial, tmp_path)
    assert f"xypts.csv line {i + 2}, pt2_cam1: only one of X, Y" in msg


def test_coefficients_not_11_rows(trial, tmp_path):
    lines = trial["dltCoefs"].read_text().splitlines()
    trial["dltCoefs"].write_text("\n".join(lines[:10]) + "\n")
    msg = _import_error(trial, tmp_path)
    assert "dltCoefs.csv" in msg and "expected 11 rows" in msg and "found 10" in msg


def test_non_numeric_coefficient(trial, tmp_path):
    _set_cell(trial["dltCoefs"], 4, 2, "abc")
    msg = _import_error(trial, tmp_path)
    assert "dltCoefs.csv line 4, column 3 (camera 3): 'abc' is not a number" in msg


def test_empty_coefficient(trial, tmp_path):
    _set_cell(trial["dltCoefs"], 9, 1, "NaN")
    msg = _import_error(trial, tmp_path)
    assert "dltCoefs.csv line 9, column 2" in msg and "L9 of camera 2 is empty" in msg


def test_camera_count_mismatch(trial, tmp_path):
    lines = trial["dltCoefs"].read_text().splitlines()
    trial["dltCoefs"].write_text("\n".join(line.rsplit(",", 1)[0] for line in lines) + "\n")
    msg = _import_error(trial, tmp_path)
    assert "xypts.csv line 1" in msg and "4 camera(s)" in msg and "dltCoefs.csv has 3 column(s)" in msg


def test_a_camera_from_another_convention_is_named(tmp_path):
    """Camera 3's coefficients written for upper-left pixels in a lower-left trial: exit 2 naming it."""
    rig, _, _, paths = _trial(tmp_path, "lower-left")
    L = dltdv.read_dlt_coefs(paths["dltCoefs"]).copy()
    L[2] = dltdv.rig_to_dlt_coefs(Rig([rig[2]]), "upper-left", SIZE)[0]
    paths["dltCoefs"].write_text("".join(",".join(f"{x:.17g}" for x in row) + "\n" for row in L.T))
    msg = _import_error(paths, tmp_path)
    assert "dltCoefs.csv column 3 (camera cam3)" in msg and "behind it" in msg and "pixel origin?" in msg


@pytest.mark.parametrize("given", [None, "upper-left"])
def test_mirrored_world_comes_back_in_the_files_frame(tmp_path, given):
    """A left-handed DLT world (z negated) with lower-left pixels: detected as upper-left (the same
    coefficients), or read as mirrored when the user says lower-left... here said upper-left on a
    lower-left trial whose world is right-handed gives the mirrored reading. Either way the 3D equals
    DLTdv's own reconstruction in the file's frame, every point in front of every camera (1e-6 m)."""
    _, truth, ref, paths = _trial(tmp_path, "lower-left", mirror=given is None)
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 120.0, tmp_path / "s", image_size=SIZE,
                                 pixel_origin=given)
    imp = session.extra_toml["import"]
    assert imp["pixel_origin"] == "upper-left"
    assert imp["world"] == ("right-handed" if given is None else "mirrored")
    assert read_session(tmp_path / "s").rig.mirrored == (given is not None)
    ours = session.rig.to_user(_batgraph_xyz(session, len(truth)))
    both = np.isfinite(ref).all(-1)
    assert np.abs(ours[both] - ref[both]).max() < 1e-6
    internal = _batgraph_xyz(session, len(truth))
    for cam in session.rig:
        assert (cam.to_cam(internal[both])[:, 2] > 0).all()


def test_millimetre_world_is_imported_in_metres(tmp_path):
    """Coefficients and xyzpts in millimetres + units="mm": the session is in metres (1e-6 m)."""
    _, truth, ref, paths = _trial(tmp_path, "lower-left", units="mm")
    session = dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], 120.0, tmp_path / "s", units="mm",
                                 xyzpts=paths["xyzpts"])
    both = np.isfinite(ref).all(-1)
    assert np.abs(ref[both] / 1000 - truth[both]).max() < 1e-6  # the files really are in mm
    assert np.abs(_batgraph_xyz(session, len(truth))[both] - truth[both]).max() < 1e-6
    r = session.reference
    assert np.abs(r[["x", "y", "z"]].to_numpy() - truth[r.frame.to_numpy(), [int(m[2:]) - 1 for m in r.marker]]
                  ).max() < 1e-6


@pytest.mark.parametrize(
    "kwargs, expect",
    [
        ({"fps": 0.0}, "fps must be a number > 0"),
        ({"pixel_origin": "bottom"}, "pixel origin must be one of"),
        ({"units": "inch"}, "units must be one of"),
        ({"image_size": (1280,)}, "image size must be two positive integers"),
        ({"marker_names": ["a", "b"]}, "5 points in the file but 2 point names"),
        ({"camera_names": ["a", "a", "b", "c"]}, "camera names must be non-empty and distinct"),
    ],
)
def test_bad_arguments(trial, tmp_path, kwargs, expect):
    assert expect in _import_error(trial, tmp_path, **kwargs)


def test_empty_and_header_only_xypts(trial, tmp_path):
    header = trial["xypts"].read_text().splitlines()[0]
    trial["xypts"].write_text(header + "\n")
    assert "header only" in _import_error(trial, tmp_path)
    trial["xypts"].write_bytes(b"")
    assert "empty file" in _import_error(trial, tmp_path)
    trial["xypts"].write_text(header + "\n" + ",".join(["NaN"] * len(header.split(","))) + "\n")
    assert "no digitised points" in _import_error(trial, tmp_path)



@pytest.mark.parametrize("first_row", ["NaN", "number"])
def test_xypts_without_its_header_line_says_so(trial, tmp_path, first_row):
    """An xypts file saved without its header line (its first row NaN everywhere, as DLTdv writes an undigitised
    frame, or clicks): one line saying the header is missing and what it should be, not a complaint about a
    column named NaN twice."""
    lines = trial["xypts"].read_text().splitlines()
    rows = lines[1:]
    if first_row == "NaN":
        rows[0] = ",".join(["NaN"] * len(lines[0].split(",")))
    else:  # a digitised frame: numbers (and NaN)
        rows[0] = ",".join("12.5" if c == "NaN" else c for c in rows[0].split(","))
    trial["xypts"].write_text("\n".join(rows) + "\n")
    msg = _import_error(trial, tmp_path)
    assert "xypts.csv line 1" in msg and "header line is missing" in msg and "pt{p}_cam{c}_X" in msg, msg
    assert "more than once" not in msg

def test_export_writes_the_projects_own_units(tmp_path):
    """A millimetre project imported with --units mm, reconstructed and exported: the exported xyzpts are
    in millimetres again and equal DLTdv's own reconstruction of the same clicks (measured 2e-7 mm, from
    9-decimal metre storage; bound 1e-4 mm), read back as plain CSV."""
    from batgraph.cli import main

    _, truth, ref, paths = _trial(tmp_path, "lower-left", units="mm")
    assert main(["import", "dltdv", "--xypts", str(paths["xypts"]), "--coefs", str(paths["dltCoefs"]), "--fps",
                 "120", "--units", "mm", "--image-size", *map(str, SIZE), "--out", str(tmp_path / "s")]) == 0
    assert main(["reconstruct", str(tmp_path / "s"), "--methods", "triangulate", "--viewer", "none", "--quiet",
                 "--out", str(tmp_path / "o")]) == 0
    assert main(["export", "dltdv", str(tmp_path / "o")]) == 0
    got = pd.read_csv(tmp_path / "o" / "triangulate_xyzpts.csv").to_numpy().reshape(len(ref), -1, 3)
    both = np.isfinite(ref).all(-1)
    assert np.isfinite(ref[both]).all() and np.abs(ref[both]).max() > 100  # the reference is in mm
    assert np.abs(got[both] - ref[both]).max() < 1e-4


def test_import_does_not_overwrite_a_session_without_force(tmp_path, capsys):
    """An import into a folder that holds a session exits 2 with one line naming it and leaves every file
    as it was; --force replaces it."""
    from batgraph.cli import main

    _, _, _, paths = _trial(tmp_path, "lower-left")
    argv = ["import", "dltdv", "--xypts", str(paths["xypts"]), "--coefs", str(paths["dltCoefs"]), "--fps", "120",
            "--image-size", *map(str, SIZE), "--out", str(tmp_path / "s")]
    assert main(argv) == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "s").iterdir()}
    (tmp_path / "s" / "session.toml").write_text((tmp_path / "s" / "session.toml").read_text() + "# edited\n")
    before["session.toml"] = (tmp_path / "s" / "session.toml").read_bytes()
    capsys.readouterr()
    assert main(argv) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and str(tmp_path / "s") in err[0] and "--force" in err[0], err
    assert {p.name: p.read_bytes() for p in (tmp_path / "s").iterdir()} == before
    assert main([*argv, "--force"]) == 0
    assert "# edited" not in (tmp_path / "s" / "session.toml").read_text()
