"""Imports of DeepLabCut, Anipose and Pose2Sim (OpenPose JSON) 2D keypoints into sessions.

Synthetic files are written exactly as the tools write them (DeepLabCut: pandas MultiIndex table
``scorer / bodyparts / coords`` -> to_csv / to_hdf key ``df_with_missing``); the real Pose2Sim demo
(../shared/data/real/pose2sim_demo_4cam_human) is imported and triangulated against Pose2Sim's own 3D.
"""

import dataclasses
import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from batgraph.camera import Camera, Rig
from batgraph.errors import InputError
from batgraph.formats.anipose import import_anipose
from batgraph.formats.c3d_trc import read_trc
from batgraph.formats.deeplabcut import import_deeplabcut
from batgraph.formats.pose2sim import KEYPOINT_SKELETONS, import_pose2sim
from batgraph.result import Options
from batgraph.session import DenseObservations, calibration_toml, dense_observations, read_session
from batgraph.triangulate import triangulate

CAMS = ["A", "B", "C"]
PARTS = ["snout", "wrist_r", "digit3_r", "tail"]
N_FRAMES = 30
SCORER = "DLC_resnet50_batflightOct1shuffle1_100000"

REAL = Path(__file__).parents[2] / "shared/data/real/pose2sim_demo_4cam_human"
REAL_TRIAL = REAL / "S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial"

try:
    import tables  # noqa: F401
    HAVE_TABLES = True
except ImportError:
    HAVE_TABLES = False


def _look_at(name: str, centre: np.ndarray) -> Camera:
    """A 1280x1024 camera at ``centre`` [m] looking at the origin, with mild distortion."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world
    K = [[1400.0, 0.0, 640.0], [0.0, 1400.0, 512.0], [0.0, 0.0, 1.0]]
    rvec = cv2.Rodrigues(R)[0].ravel()
    return Camera(name, (1280, 1024), K, [-0.08, 0.02, 0.0005, -0.0003, 0.0], rvec, -R @ centre)


def _scene(seed: int = 0):
    """Rig of 3 cameras, truth (F, M, 3) [m] and per-camera pixels (C, F, M, 2) and likelihoods (C, F, M)."""
    rng = np.random.default_rng(seed)
    rig = Rig([_look_at(n, c) for n, c in zip(CAMS, [np.array([3.0, 0.0, 0.5]), np.array([0.0, 3.2, 0.8]),
                                                     np.array([-2.5, -2.0, 1.0])], strict=True)])
    t = np.arange(N_FRAMES)[:, None, None]
    xyz = rng.uniform(-0.3, 0.3, (1, len(PARTS), 3)) + 0.01 * t * np.array([1.0, -0.5, 0.2])
    uv = rig.project(xyz)
    lik = rng.uniform(0.7, 1.0, uv.shape[:3])
    lik[0, 3:6, 1] = 0.2  # below the threshold: dropped
    lik[1, 10, 2] = 0.0
    uv[2, 12:15, 0] = np.nan  # not detected (DLC writes NaN when it has no estimate)
    return rig, xyz, uv, lik


def _dlc_frame(uv: np.ndarray, lik: np.ndarray, individuals: list[str] | None = None) -> pd.DataFrame:
    """One camera's table as DeepLabCut's analyze_videos builds it (uv (F, M, 2), lik (F, M))."""
    def block(shift_px):
        return np.concatenate([uv + shift_px, lik[..., None]], axis=-1).reshape(len(uv), -1)

    data = block(0.0)
    if individuals is None:
        cols = pd.MultiIndex.from_product([[SCORER], PARTS, ["x", "y", "likelihood"]],
                                          names=["scorer", "bodyparts", "coords"])
    else:
        data = np.concatenate([block(7.0 * i) for i in range(len(individuals))], axis=1)  # bat2: +7 px
        cols = pd.MultiIndex.from_product([[SCORER], individuals, PARTS, ["x", "y", "likelihood"]],
                                          names=["scorer", "individuals", "bodyparts", "coords"])
    return pd.DataFrame(data, columns=cols, index=np.arange(len(uv)))


def _write_calibration(path: Path, rig: Rig) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(calibration_toml(rig))
    return path


def _write_dlc(folder: Path, uv, lik, stem: str = "{cam}-trial1" + SCORER, ext: str = "csv",
               individuals=None) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for c, cam in enumerate(CAMS):
        p = folder / (stem.format(cam="cam" + cam) + "." + ext)
        df = _dlc_frame(uv[c], lik[c], individuals)
        if ext == "csv":
            df.to_csv(p)
        else:
            df.to_hdf(p, key="df_with_missing", format="table", mode="w")
        paths.append(p)
    return paths


def _expected(uv, lik, threshold):
    keep = np.isfinite(uv).all(-1) & (lik >= threshold) & (lik > 0)
    return keep


def _check_session(session, rig, xyz, uv, lik, threshold):
    """Observations equal the files' kept points; noise-free triangulation recovers the truth.

    Pixels go through CSV at full repr precision, so triangulation of the imported session returns
    the truth to round-off (measured ~1e-12 m); bound 1e-6 m."""
    keep = _expected(uv, lik, threshold)
    obs = session.observations
    assert len(obs) == keep.sum()
    d = dense_observations(session)
    assert d.cameras == CAMS and d.markers == PARTS and len(d.frames) == N_FRAMES
    assert np.array_equal(d.seen, keep)
    assert np.allclose(d.uv_px[keep], uv[keep], atol=1e-9)
    assert np.allclose(d.weight[keep], lik[keep], atol=1e-12)
    est, _ = triangulate(session.rig, d, 1.0)
    ok = d.n_views >= 2
    assert ok.sum() > 0.9 * ok.size
    assert np.max(np.abs(est[ok] - np.broadcast_to(xyz, est.shape)[ok])) < 1e-6


def test_deeplabcut_csv(tmp_path):
    """DLC CSV with its 3 header rows: import, written session reads back identically, truth recovered."""
    rig, xyz, uv, lik = _scene()
    calib = _write_calibration(tmp_path / "calibration.toml", rig)
    files = _write_dlc(tmp_path / "dlc", uv, lik)
    head = files[0].read_text().splitlines()[:4]
    assert [h.split(",")[0] for h in head] == ["scorer", "bodyparts", "coords", "0"]
    assert head[2].split(",")[1:4] == ["x", "y", "likelihood"]
    s = import_deeplabcut(files[::-1], calib, fps=200, out=tmp_path / "sess", threshold=0.6)
    _check_session(s, rig, xyz, uv, lik, 0.6)
    back = read_session(tmp_path / "sess")
    assert back.fps == 200 and back.rig.names == CAMS and back.markers == PARTS
    cols = ["frame", "camera", "marker"]
    assert back.observations[cols].equals(s.observations[cols])
    assert np.allclose(back.observations[["u", "v", "weight"]], s.observations[["u", "v", "weight"]], atol=1e-6)



def test_deeplabcut_files_named_as_deeplabcut_names_them(tmp_path):
    """analyze_videos names its output after the video with the scorer right behind it (cam_01.mp4 ->
    cam_01DLC_resnet50_...csv): matched to calibration camera cam_01 without --camera-names."""
    rig, xyz, uv, lik = _scene()
    named = Rig([dataclasses.replace(c, name=f"cam_0{i + 1}") for i, c in enumerate(rig)])
    calib = _write_calibration(tmp_path / "calibration.toml", named)
    files = _write_dlc(tmp_path / "dlc", uv, lik, stem="{cam}" + SCORER)
    for i, f in enumerate(files):
        f.rename(f.with_name(f"cam_0{i + 1}{SCORER}.csv"))
    files = sorted((tmp_path / "dlc").iterdir())
    s = import_deeplabcut(files[::-1], calib, fps=200, out=tmp_path / "sess", threshold=0.6)
    assert s.rig.names == ["cam_01", "cam_02", "cam_03"]
    assert (s.observations.groupby("camera").size() == [int(_expected(uv[c], lik[c], 0.6).sum()) for c in
                                                       range(3)]).all()

@pytest.mark.skipif(not HAVE_TABLES, reason="reading DeepLabCut .h5 needs the 'tables' package")
def test_deeplabcut_h5_equals_csv(tmp_path):
    """The .h5 (key df_with_missing) and the CSV of the same data import to the same observations."""
    rig, xyz, uv, lik = _scene(1)
    calib = _write_calibration(tmp_path / "calibration.toml", rig)
    s_h5 = import_deeplabcut(_write_dlc(tmp_path / "h5", uv, lik, ext="h5"), calib, 100, None)
    s_csv = import_deeplabcut(_write_dlc(tmp_path / "csv", uv, lik), calib, 100, None)
    _check_session(s_h5, rig, xyz, uv, lik, 0.6)
    pd.testing.assert_frame_equal(s_h5.observations, s_csv.observations, check_exact=False, atol=1e-9)


def test_deeplabcut_multi_animal(tmp_path):
    """Multi-animal files (4 header rows with 'individuals') need individual= when there are several."""
    rig, xyz, uv, lik = _scene(2)
    calib = _write_calibration(tmp_path / "calibration.toml", rig)
    files = _write_dlc(tmp_path / "ma", uv, lik, individuals=["bat1", "bat2"])
    assert files[0].read_text().splitlines()[1].startswith("individuals,")
    with pytest.raises(InputError, match="individuals.*individual="):
        import_deeplabcut(files, calib, 100, None)
    s = import_deeplabcut(files, calib, 100, None, individual="bat1")
    _check_session(s, rig, xyz, uv, lik, 0.6)
    s2 = import_deeplabcut(files, calib, 100, None, individual="bat2")  # shifted by 7 px in the file
    assert np.allclose(s2.observations["u"], s.observations["u"] + 7.0)
    with pytest.raises(InputError, match="'bat3' not in"):
        import_deeplabcut(files, calib, 100, None, individual="bat3")


def test_deeplabcut_errors(tmp_path):
    """Each user error is an InputError naming the file and the row or key."""
    rig, _, uv, lik = _scene()
    calib = _write_calibration(tmp_path / "calibration.toml", rig)
    files = _write_dlc(tmp_path / "dlc", uv, lik)
    with pytest.raises(InputError, match="missing.csv: file not found"):
        import_deeplabcut(files[:2] + [tmp_path / "missing.csv"], calib, 100, None)
    with pytest.raises(InputError, match="3 cameras .* but 2 input files"):
        import_deeplabcut(files[:2], calib, 100, None)
    with pytest.raises(InputError, match="camera 'D' is not in"):
        import_deeplabcut(files, calib, 100, None, camera_names=["A", "B", "D"])
    with pytest.raises(InputError, match="camera 'A' is already given"):
        import_deeplabcut(files, calib, 100, None, camera_names=["A", "B", "A"])
    odd = tmp_path / "odd" / "left.csv"
    odd.parent.mkdir()
    odd.write_text(files[2].read_text())
    with pytest.raises(InputError, match="left.csv: the name matches no calibration cameras"):
        import_deeplabcut(files[:2] + [odd], calib, 100, None)
    # wrong header layout: rows swapped
    lines = files[0].read_text().splitlines()
    swapped = tmp_path / "bad" / "camA.csv"
    swapped.parent.mkdir()
    swapped.write_text("\n".join([lines[0], lines[2], lines[1]] + lines[3:]))
    with pytest.raises(InputError, match="camA.csv line 2: expected DeepLabCut header row 'bodyparts'"):
        import_deeplabcut([swapped] + files[1:], calib, 100, None)
    # a non-number in a data row: the CSV line is named
    lines[7] = lines[7].replace(lines[7].split(",")[2], "oops", 1)
    bad = tmp_path / "bad2" / "camA.csv"
    bad.parent.mkdir()
    bad.write_text("\n".join(lines))
    with pytest.raises(InputError, match="camA.csv line 8: snout y 'oops' is not a number"):
        import_deeplabcut([bad] + files[1:], calib, 100, None)
    # labelled-data file: x, y only
    lab = tmp_path / "lab" / "camA.csv"
    lab.parent.mkdir()
    df = _dlc_frame(uv[0], lik[0]).drop(columns="likelihood", level="coords")
    df.to_csv(lab)
    with pytest.raises(InputError, match="no 'likelihood'"):
        import_deeplabcut([lab] + files[1:], calib, 100, None)
    with pytest.raises(InputError, match="fps: must be > 0"):
        import_deeplabcut(files, calib, 0, None)


@pytest.mark.skipif(not HAVE_TABLES, reason="Anipose's pose-2d files are .h5 (needs 'tables')")
def test_anipose_project(tmp_path):
    """An Anipose project: config.toml at the root, session/pose-2d/<trial>-cam<X>.h5, session/calibration/
    calibration.toml. cam_regex and score_threshold come from config.toml; two trials need trial=. The scheme's
    chains become the skeleton, written to session.toml; a scheme that is not lists of names is one line."""
    rig, xyz, uv, lik = _scene(3)
    root = tmp_path / "bat-project"
    root.mkdir()
    config = ("nesting = 1\n\n[triangulation]\ncam_regex = '-cam([A-Z])$'\nscore_threshold = 0.75\n\n[labeling]\n"
              "scheme = [['snout', 'wrist_r', 'digit3_r'], ['snout', 'tail']]\n")
    (root / "config.toml").write_text(config)
    session_dir = root / "2024-05-01"
    _write_calibration(session_dir / "calibration" / "calibration.toml", rig)
    _write_dlc(session_dir / "pose-2d", uv, lik, stem="flight1-{cam}", ext="h5")
    _write_dlc(session_dir / "pose-2d", uv[:, :5], lik[:, :5], stem="flight2-{cam}", ext="h5")
    with pytest.raises(InputError, match="several trials \\(flight1, flight2\\); pass trial="):
        import_anipose(session_dir, 100, None)
    s = import_anipose(session_dir, 100, tmp_path / "out", trial="flight1")
    assert s.name == "flight1"
    _check_session(s, rig, xyz, uv, lik, 0.75)
    bones = [("snout", "wrist_r"), ("wrist_r", "digit3_r"), ("snout", "tail")]
    assert s.skeleton == bones and read_session(tmp_path / "out").skeleton == bones
    s2 = import_anipose(session_dir / "pose-2d", 100, None, trial="flight2", threshold=0.0)
    assert s2.observations["frame"].max() == 4
    with pytest.raises(InputError, match="cam_regex .* finds no camera name"):
        import_anipose(session_dir, 100, None, trial="flight1", cam_regex="_view([0-9])$")
    (root / "config.toml").write_text(config.replace("['snout', 'tail']", "'tail'"))
    with pytest.raises(InputError, match=r"config.toml \[labeling\] scheme: expected lists of body part names"):
        import_anipose(session_dir, 100, None, trial="flight1")
    (root / "config.toml").write_text("nesting = 1\nlabeling = 3\n")
    with pytest.raises(InputError, match=r"config.toml: 'labeling' must be a table \[labeling\]"):
        import_anipose(session_dir, 100, None, trial="flight1")


def test_pose2sim_json_errors(tmp_path):
    """OpenPose JSON problems name the file: wrong keypoint count (model), not JSON, missing 'people'. The model's
    bones become the skeleton, less those of a keypoint never detected (RHeel here); a custom list has none."""
    rig, _, _, _ = _scene()
    calib = _write_calibration(tmp_path / "calibration.toml", rig)
    dirs = []
    for cam in CAMS:
        d = tmp_path / f"cam{cam}_json"
        d.mkdir()
        for f in range(3):
            kp = np.tile([100.0, 200.0, 0.9], 25)
            kp[-1] = 0.0  # RHeel (BODY_25B's last keypoint) not detected
            (d / f"trial_{f:012d}_keypoints.json").write_text(
                json.dumps({"people": [{"pose_keypoints_2d": kp.tolist()}]}))
        dirs.append(d)
    s = import_pose2sim(dirs, calib, 60, None)
    assert len(s.observations) == 3 * 3 * 24 and sorted(set(s.observations["frame"])) == [0, 1, 2]
    bones = KEYPOINT_SKELETONS["BODY_25B"]
    assert set(s.skeleton) == {b for b in bones if "RHeel" not in b} and len(s.skeleton) == len(bones) - 1
    assert ("LKnee", "LAnkle") in s.skeleton
    custom = import_pose2sim(dirs, calib, 60, None, keypoints=[f"k{j}" for j in range(25)])
    assert custom.skeleton == []
    with pytest.raises(InputError, match=r"trial_000000000000_keypoints.json: people\[0\].* 75 numbers, "
                                          r"expected 3 x 26"):
        import_pose2sim(dirs, calib, 60, None, keypoints="HALPE_26")
    with pytest.raises(InputError, match="unknown model 'BODY_99'"):
        import_pose2sim(dirs, calib, 60, None, keypoints="BODY_99")
    (dirs[1] / "trial_000000000001_keypoints.json").write_text("{not json")
    with pytest.raises(InputError, match="camB_json/trial_000000000001_keypoints.json: not valid JSON"):
        import_pose2sim(dirs, calib, 60, None)
    (dirs[1] / "trial_000000000001_keypoints.json").write_text("{}")
    with pytest.raises(InputError, match="missing key 'people'"):
        import_pose2sim(dirs, calib, 60, None)


def _pose2sim_like(rig, d: DenseObservations, obs_cols, pixel_sigma_px, max_err_px=15.0):
    """Per point, drop up to 2 cameras while the mean reprojection error exceeds 15 px (what Pose2Sim's
    triangulation does with reproj_error_threshold_triangulation = 15); returns xyz (F, K, 3)."""

    def mean_err(X, use):
        e = np.linalg.norm(rig.project(X) - d.uv_px[:, :, obs_cols], axis=-1)
        ok = use[:, None, None] & np.isfinite(e)
        n = ok.sum(axis=0)
        return np.where(n > 0, np.where(ok, e, 0.0).sum(axis=0) / np.maximum(n, 1), np.nan)

    C = len(rig)
    xyz = triangulate(rig, d, pixel_sigma_px)[0][:, obs_cols]
    err = mean_err(xyz, np.ones(C, bool))
    for n_drop in (1, 2):  # Pose2Sim: the best subset with n_drop cameras fewer, for points still above 15 px
        bad = err > max_err_px
        best_X, best_e = np.full_like(xyz, np.nan), np.full_like(err, np.inf)
        for keep in itertools.combinations(range(C), C - n_drop):
            use = np.isin(np.arange(C), keep)
            sub = DenseObservations(d.cameras, d.frames, d.markers, np.where(use[:, None, None, None], d.uv_px, np.nan),
                                    np.where(use[:, None, None], d.weight, 0.0))
            X = triangulate(rig, sub, pixel_sigma_px)[0][:, obs_cols]
            e = np.nan_to_num(mean_err(X, use), nan=np.inf)
            better = e < best_e
            best_X[better], best_e[better] = X[better], e[better]
        take = bad & (best_e < err)
        xyz[take], err[take] = best_X[take], best_e[take]
    return xyz


def test_pose2sim_real_demo(tmp_path):
    """Real Pose2Sim demo: 4 cameras x 100 frames of OpenPose BODY_25B JSON + Calib_qualisys.toml.

    Triangulated with batgraph's per-frame DLT and compared with Pose2Sim's own TRC (Y-up: world =
    trc[..., [2, 0, 1]]; TRC Frame# n is JSON frame n - 1). Plain DLT on every camera: measured
    median 7.6 mm over all points, per keypoint 0.8 mm (Nose) to 64 mm (RHip); Pose2Sim drops
    cameras whose reprojection error exceeds 15 px, and with that emulated: median 2.7 mm, worst
    keypoint median 8.5 mm (RBigToe). Bounds: 10 mm and 4 mm overall, 12 mm per keypoint (emulated),
    i.e. the import (keypoint ids, frame numbering, calibration, axes) is right to a few mm;
    the JSON keypoints are markerless detections with ~10 px noise in 1088x1920 images.
    """
    calib = REAL / "S00_Calibration" / "Calib_qualisys.toml"
    ref_path = REAL_TRIAL / "pose-3d" / "S00_P00_T01_BalancingTrial_0-100.trc"
    if not (calib.is_file() and ref_path.is_file()):
        pytest.skip(f"real data absent: {REAL}")
    s = import_pose2sim(REAL_TRIAL / "pose-associated", calib, 60, tmp_path / "p2s", keypoints="BODY_25B")
    written = read_session(tmp_path / "p2s")
    assert written.skeleton == s.skeleton and len(s.skeleton) == 25  # BODY_25B's bones, every keypoint seen
    d = dense_observations(written)
    assert d.cameras == ["cam_01", "cam_02", "cam_03", "cam_04"]
    assert len(d.frames) == 100 and d.frames[0] == 0 and len(d.markers) == 25
    assert (d.weight[d.seen] >= 0.3).all()
    ref = read_trc(ref_path)
    assert ref.frame[0] == 1 and len(ref.frame) == 100
    ref_world = ref.xyz_m[..., [2, 0, 1]]  # undo Pose2Sim's zup2yup
    cols = [d.markers.index(m) for m in ref.markers]
    xyz, _ = triangulate(s.rig, d, 5.0)
    diff_mm = np.linalg.norm(xyz[:, cols] - ref_world, axis=-1) * 1e3
    per_kp = np.nanmedian(diff_mm, axis=0)
    like = np.linalg.norm(_pose2sim_like(s.rig, d, cols, 5.0) - ref_world, axis=-1) * 1e3
    per_kp_like = np.nanmedian(like, axis=0)
    print("\nmedian |batgraph DLT - Pose2Sim| per keypoint [mm]:")
    for m, a, b in zip(ref.markers, per_kp, per_kp_like, strict=True):
        print(f"  {m:10s} all cameras {a:6.1f}   with Pose2Sim's camera exclusion {b:5.1f}")
    print(f"  overall median {np.nanmedian(diff_mm):.1f} mm; with exclusion {np.nanmedian(like):.1f} mm")
    assert np.nanmedian(diff_mm) < 10.0
    assert np.nanmedian(like) < 4.0
    assert per_kp_like.max() < 12.0


def test_pose2sim_import_keeps_its_trc_as_reference_and_reconstruct_compares(tmp_path):
    """The real Pose2Sim demo imported with its own TRC as the reference: `reconstruct` compares the two
    in summary.json and the report. Triangulation vs Pose2Sim's 3D: measured median 7.6 mm over 2100
    points (see test_pose2sim_real_demo for why it is not 0); bound 10 mm. The report has the section."""
    from batgraph.pipeline import reconstruct

    calib = REAL / "S00_Calibration" / "Calib_qualisys.toml"
    ref_path = REAL_TRIAL / "pose-3d" / "S00_P00_T01_BalancingTrial_0-100.trc"
    if not (calib.is_file() and ref_path.is_file()):
        pytest.skip(f"real data absent: {REAL}")
    import_pose2sim(REAL_TRIAL / "pose-associated", calib, 60, tmp_path / "p2s", reference_trc=ref_path)
    assert (tmp_path / "p2s" / "reference_xyz.csv").is_file()
    result = reconstruct(tmp_path / "p2s", tmp_path / "out", ["triangulate"], Options(progress=False), viewer="none")
    ref = result.summary["methods"]["triangulate"]["reference"]
    assert ref["n"] == 2100
    assert ref["median_m"] < 0.010
    assert "reference" in (tmp_path / "out" / "report.html").read_text().lower()
