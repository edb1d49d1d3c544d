"""Rerun recordings written by batgraph.viewer, read back with the Rerun SDK's own .rrd reader."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict

import cv2
import numpy as np
import pandas as pd
import pytest
import scipy.stats
from scipy.spatial.transform import Rotation

from batgraph import viewer
from batgraph.camera import Camera, Rig
from batgraph.errors import InputError
from batgraph.session import Session, dense_observations

FPS = 100.0
N_FRAMES = 10
MARKERS = ["head", "body", "wrist", "tip"]
SKELETON = [("head", "body"), ("body", "wrist"), ("wrist", "tip")]
METHODS = ["smoother", "triangulate"]
COV_COLS = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]


def _look_at(name: str, center: np.ndarray) -> Camera:
    """Zero-distortion 640x480 camera at ``center`` looking at the origin (z forward, y down)."""
    z = -center / np.linalg.norm(center)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world -> cam_from_world
    K = [[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]
    return Camera(name, (640, 480), K, np.zeros(5), cv2.Rodrigues(R)[0].ravel(), -R @ center)


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def make_scene():
    """3 cameras, 4 markers, 10 frames; 'triangulate' misses 'tip' on frames 3-4 (empty x, y, z)."""
    rng = np.random.default_rng(7)
    centers = ([3.0, 0.0, 1.0], [0.0, 3.0, 1.2], [-2.5, -1.5, 0.8])
    cams = [_look_at(f"cam{i + 1}", np.array(c)) for i, c in enumerate(centers)]
    rig = Rig(cams)
    frames = np.arange(N_FRAMES)
    truth = (rng.normal(0, 0.2, (1, len(MARKERS), 3)) + 0.01 * frames[:, None, None] * np.array([1.0, 0.5, 0.0]))
    uv = rig.project(truth)  # (C, F, M, 2)
    c_i, f_i, m_i = np.meshgrid(range(len(cams)), frames, range(len(MARKERS)), indexing="ij")
    obs = pd.DataFrame({"frame": f_i.ravel(), "camera": np.array(rig.names)[c_i.ravel()],
                        "marker": np.array(MARKERS)[m_i.ravel()], "u": uv[..., 0].ravel(), "v": uv[..., 1].ravel(),
                        "weight": 1.0})
    obs = obs.drop(index=obs.index[(obs.camera == "cam3") & (obs.frame == 5)])  # cam3 blind on frame 5
    session = Session(name="tiny", fps=FPS, rig=rig, observations=obs.reset_index(drop=True),
                      marker_names=MARKERS, skeleton=SKELETON)
    dense = dense_observations(session)

    rows, reproj = [], []
    for method in METHODS:
        xyz = truth + rng.normal(0, 0.002, truth.shape)
        A = rng.normal(0, 0.01, (N_FRAMES, len(MARKERS), 3, 3))
        cov = A @ A.transpose(0, 1, 3, 2) + 1e-6 * np.eye(3)  # random SPD, ~1e-4 m^2
        if method == "triangulate":
            xyz[3:5, 3] = np.nan
            cov[3:5, 3] = np.nan
        for f in frames:
            for m, name in enumerate(MARKERS):
                c = cov[f, m]
                rows.append(dict(method=method, frame=f, time_s=f / FPS, marker=name, x=xyz[f, m, 0],
                                 y=xyz[f, m, 1], z=xyz[f, m, 2], cov_xx=c[0, 0], cov_xy=c[0, 1], cov_xz=c[0, 2],
                                 cov_yy=c[1, 1], cov_yz=c[1, 2], cov_zz=c[2, 2], n_views=3, status="observed"))
        uv_hat = rig.project(xyz)
        for o in session.observations.itertuples():
            c, m = rig.index(o.camera), MARKERS.index(o.marker)
            uh = uv_hat[c, o.frame, m]
            reproj.append(dict(method=method, frame=o.frame, camera=o.camera, marker=o.marker, u=o.u, v=o.v,
                               u_hat=uh[0], v_hat=uh[1], err_px=float(np.hypot(*(uh - [o.u, o.v]))),
                               outlier=bool(o.frame == 7 and m == 0)))
    return session, dense, pd.DataFrame(rows), pd.DataFrame(reproj)


def _read(path) -> dict[str, list[dict]]:
    """Entity path -> rows (dicts of column name -> python value) of every chunk in the .rrd."""
    from rerun.chunk import RrdReader

    out = defaultdict(list)
    for chunk in RrdReader(path).stream():
        out[chunk.entity_path].extend(chunk.to_record_batch().to_pylist())
    return out


@pytest.fixture(scope="module")
def written(scene, tmp_path_factory):
    session, dense, traj, reproj = scene
    out = tmp_path_factory.mktemp("out")
    path = viewer.write_recording(out / "recording.rrd", session, dense, traj, reproj, trail_frames=4)
    return out, path, _read(path)


def _by_frame(rows: list[dict], column: str) -> dict[int, list]:
    """Temporal rows of one entity -> {frame: the component's instances}; asserts one row per frame."""
    frames = [r["frame"] for r in rows if r.get("frame") is not None and r.get(column) is not None]
    assert len(frames) == len(set(frames)), f"{column}: more than one row on a frame"
    return {r["frame"]: r[column] for r in rows if r.get("frame") is not None and r.get(column) is not None}


def test_entities_frames_and_atomic_write(written, scene):
    """Every documented entity is present; each per-frame entity has one row on each of the 10 frames."""
    out, path, ents = written
    session = scene[0]
    assert sorted(p.name for p in out.iterdir()) == ["recording.rrd"]  # no temporary left beside it
    static = {"/world"} | {f"/world/cameras/{c}{s}" for c in session.rig.names for s in ("", "/image")}
    expected = set(static)
    for cam in session.rig.names:
        expected.add(f"/world/cameras/{cam}/image/detections")
        expected |= {f"/world/cameras/{cam}/image/reproj/{m}{s}" for m in METHODS for s in ("", "/residuals")}
    for m in METHODS:
        expected |= {f"/world/{m}/{e}" for e in ("markers", "ellipsoids", "skeleton", "trails")}
    assert expected <= set(ents)

    for p in expected - static:
        frames = sorted(r["frame"] for r in ents[p] if r.get("frame") is not None)
        assert frames == list(range(N_FRAMES)), p
    all_frames = {r["frame"] for rows in ents.values() for r in rows if r.get("frame") is not None}
    assert all_frames == set(range(N_FRAMES))
    # the "time" timeline is frame / fps seconds (stored as a duration in ns)
    for r in ents["/world/smoother/markers"]:
        if r.get("frame") is not None:
            t = r["time"]
            t_s = t.total_seconds() if hasattr(t, "total_seconds") else t / 1e9
            assert t_s == pytest.approx(r["frame"] / FPS, abs=1e-6)


def test_rerun_cli_verifies_the_file(written):
    """``rerun rrd verify`` (the CLI the viewer is built on) loads and interprets every archetype."""
    _, path, _ = written
    run = subprocess.run([viewer._rerun_executable(), "rrd", "verify", str(path)], capture_output=True, text=True,
                         env={**os.environ, "RERUN_APP_ONLY": "true"}, timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "verified without error" in run.stdout + run.stderr


def test_cameras_are_logged_static_with_pose_and_intrinsics(written, scene):
    """Transform3D = world_from_cam and Pinhole = K with the image size (float32: 1e-5 relative)."""
    _, _, ents = written
    for cam in scene[0].rig:
        (tf,) = [r for r in ents[f"/world/cameras/{cam.name}"] if r.get("Transform3D:translation") is not None]
        R_wc, t_wc = cam.world_from_cam()
        np.testing.assert_allclose(tf["Transform3D:translation"][0], t_wc, rtol=1e-6, atol=1e-6)
        # Rerun stores Mat3x3 column-major
        np.testing.assert_allclose(np.array(tf["Transform3D:mat3x3"][0]).reshape(3, 3).T, R_wc, atol=1e-6)
        (ph,) = [r for r in ents[f"/world/cameras/{cam.name}/image"] if r.get("Pinhole:image_from_camera") is not None]
        np.testing.assert_allclose(np.array(ph["Pinhole:image_from_camera"][0]).reshape(3, 3).T, cam.K, rtol=1e-6)
        assert ph["Pinhole:resolution"][0] == [640.0, 480.0]


def test_points_detections_and_reprojections(written, scene):
    """3D markers and 2D points are the tables' values (float32: |err| < 1e-6 m and < 1e-3 px at 640 px)."""
    session, dense, traj, reproj = scene
    _, _, ents = written
    for method in METHODS:
        pos = _by_frame(ents[f"/world/{method}/markers"], "Points3D:positions")
        ids = _by_frame(ents[f"/world/{method}/markers"], "Points3D:class_ids")
        t = traj[traj.method == method]
        for f in range(N_FRAMES):
            rows = t[(t.frame == f) & t.x.notna()]
            assert [MARKERS[i] for i in ids[f]] == list(rows.marker)
            np.testing.assert_allclose(pos[f], rows[["x", "y", "z"]].to_numpy(), atol=1e-6)
        # the empty x, y, z of triangulate (tip, frames 3-4) are left out, not drawn at the origin
        assert len(pos[3]) == (3 if method == "triangulate" else 4)
        skel = _by_frame(ents[f"/world/{method}/skeleton"], "LineStrips3D:strips")
        assert len(skel[3]) == (2 if method == "triangulate" else 3)
        trails = _by_frame(ents[f"/world/{method}/trails"], "LineStrips3D:strips")
        assert all(len(s) == 4 for s in trails[9])
        tip = t[t.marker == "tip"].set_index("frame")[["x", "y", "z"]].to_numpy()
        # trail of the last marker at frame 9 = its positions on frames 6..9 (oldest first)
        np.testing.assert_allclose(trails[9][-1], tip[6:10], atol=1e-6)
        if method == "triangulate":
            # no trail while the marker is missing; afterwards the trail bridges the gap (frames 3-4)
            assert len(trails[3]) == 3
            np.testing.assert_allclose(trails[5][-1], tip[[2, 2, 2, 5]], atol=1e-6)

    for cam in session.rig.names:
        det = _by_frame(ents[f"/world/cameras/{cam}/image/detections"], "Points2D:positions")
        obs = session.observations[session.observations.camera == cam]
        for f in range(N_FRAMES):
            np.testing.assert_allclose(np.reshape(det[f], (-1, 2)), obs[obs.frame == f][["u", "v"]].to_numpy(),
                                       atol=1e-3)
        assert (len(det[5]) == 0) == (cam == "cam3")  # an empty row clears the previous frame
        rp = _by_frame(ents[f"/world/cameras/{cam}/image/reproj/smoother"], "Points2D:positions")
        r = reproj[(reproj.method == "smoother") & (reproj.camera == cam) & (reproj.frame == 7)]
        np.testing.assert_allclose(rp[7], r[["u_hat", "v_hat"]].to_numpy(), atol=1e-3)
        col = _by_frame(ents[f"/world/cameras/{cam}/image/reproj/smoother"], "Points2D:colors")
        red = (viewer.OUTLIER_COLOR[0] << 24) | (viewer.OUTLIER_COLOR[1] << 16) | (viewer.OUTLIER_COLOR[2] << 8) | 255
        assert [c == red for c in col[7]] == list(r.outlier)


def test_ellipsoid_half_axes_match_covariance(written, scene):
    """R diag(h^2 / chi2) R^T rebuilt from the file equals the table's covariance.

    Half-sizes and quaternions are float32 in the file: relative error ~1e-7 per number, so the
    rebuilt covariance matches to 1e-5 of its largest entry (measured 1.0e-7).
    """
    _, _, traj, _ = scene
    _, _, ents = written
    assert viewer.CHI2_3D_95 == pytest.approx(scipy.stats.chi2.ppf(0.95, 3), rel=1e-12)
    for method in METHODS:
        rows = ents[f"/world/{method}/ellipsoids"]
        half = _by_frame(rows, "Ellipsoids3D:half_sizes")
        quat = _by_frame(rows, "Ellipsoids3D:quaternions")
        center = _by_frame(rows, "Ellipsoids3D:centers")
        t = traj[(traj.method == method)]
        for f in range(N_FRAMES):
            tf = t[(t.frame == f) & t.x.notna()]
            c = tf[COV_COLS].to_numpy()[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
            R = Rotation.from_quat(np.array(quat[f])).as_matrix()
            h2 = np.array(half[f], dtype=float) ** 2 / viewer.CHI2_3D_95
            rebuilt = R @ (h2[:, :, None] * R.transpose(0, 2, 1))
            np.testing.assert_allclose(rebuilt, c, atol=1e-5 * np.abs(c).max())
            np.testing.assert_allclose(center[f], tf[["x", "y", "z"]].to_numpy(), atol=1e-6)


def test_quaternions_are_scipys_rotations():
    """viewer.quaternions_xyzw (numpy, no scipy.spatial at run time) gives the rotations scipy gives, for random
    rotations and the awkward ones: identity, half turns about each axis and about a diagonal (w = 0)."""
    rots = Rotation.random(500, random_state=np.random.default_rng(0)).as_matrix()
    half_turns = Rotation.from_rotvec(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0] / np.sqrt(2)]))
    rots = np.concatenate([rots, np.eye(3)[None], half_turns.as_matrix()])
    quat = viewer.quaternions_xyzw(rots)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), rots, atol=1e-12)


def test_ellipsoid_axes_of_a_known_covariance():
    """A covariance built from a rotation and standard deviations (1, 2, 3) cm gives them back exactly."""
    R = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    sd = np.array([0.01, 0.02, 0.03])
    cov = R @ np.diag(sd**2) @ R.T
    half, quat = viewer.ellipsoid_axes(cov[None])
    np.testing.assert_allclose(half[0], np.sqrt(viewer.CHI2_3D_95) * sd, rtol=1e-12)
    Rq = Rotation.from_quat(quat[0]).as_matrix()
    assert np.linalg.det(Rq) == pytest.approx(1.0)
    np.testing.assert_allclose(np.abs(Rq.T @ R), np.eye(3), atol=1e-12)  # same axes up to sign


def test_failed_write_leaves_no_file(scene, tmp_path):
    """A crash while logging (a table without x) leaves neither recording.rrd nor a temporary."""
    session, dense, traj, reproj = scene
    with pytest.raises(KeyError):
        viewer.write_recording(tmp_path / "recording.rrd", session, dense, traj.drop(columns="x"), reproj)
    assert list(tmp_path.iterdir()) == []


def test_live_viewer_streams_frame_by_frame(scene, tmp_path):
    """LiveViewer (to a file, the same code path as spawn/connect) logs one row per update."""
    session, dense, traj, _ = scene
    t = traj[traj.method == "smoother"]
    path = tmp_path / "live.rrd"
    with viewer.LiveViewer(session, dense, method="filter", mode="save", path=path, trail_frames=3) as live:
        for f in range(N_FRAMES):
            tf = t[t.frame == f]
            cov = tf[COV_COLS].to_numpy()[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
            live.update(f, tf[["x", "y", "z"]].to_numpy(), cov)
    ents = _read(path)
    pos = _by_frame(ents["/world/filter/markers"], "Points3D:positions")
    assert sorted(pos) == list(range(N_FRAMES))
    np.testing.assert_allclose(pos[6], t[t.frame == 6][["x", "y", "z"]].to_numpy(), atol=1e-6)
    assert len(_by_frame(ents["/world/filter/ellipsoids"], "Ellipsoids3D:half_sizes")[0]) == len(MARKERS)
    trails = _by_frame(ents["/world/filter/trails"], "LineStrips3D:strips")
    body = t[t.marker == "body"].set_index("frame")[["x", "y", "z"]].to_numpy()
    np.testing.assert_allclose(trails[5][1], body[3:6], atol=1e-6)
    assert "/world/cameras/cam1/image/detections" in ents


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_live_viewer_connects_to_a_running_rerun(scene, tmp_path):
    """Live streaming over gRPC, as --viewer spawn does once the viewer runs: a real ``rerun --save``
    server (no window) receives every frame as it is logged."""
    session, dense, traj, _ = scene
    t = traj[traj.method == "smoother"]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = tmp_path / "received.rrd"
    server = subprocess.Popen([viewer._rerun_executable(), "--port", str(port), "--save", str(path)],
                              env={**os.environ, "RERUN_APP_ONLY": "true"},
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not viewer._port_open(port):
            assert time.monotonic() < deadline and server.poll() is None, "rerun server did not start"
            time.sleep(0.1)
        with viewer.LiveViewer(session, dense, mode="connect", url=f"rerun+http://127.0.0.1:{port}/proxy") as live:
            for f in range(N_FRAMES):
                live.update(f, t[t.frame == f][["x", "y", "z"]].to_numpy())
        # the client's flush means sent, not saved: the server gives no acknowledgement to wait for, and an
        # immediate SIGINT once lost the last frame (1 fresh-clone run of 3, on a loaded 2-core machine)
        time.sleep(1.0)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
    pos = _by_frame(_read(path)["/world/filter/markers"], "Points3D:positions")
    assert sorted(pos) == list(range(N_FRAMES))
    np.testing.assert_allclose(pos[9], t[t.frame == 9][["x", "y", "z"]].to_numpy(), atol=1e-6)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display detection is X11/Wayland specific")
def test_no_display_gives_a_clear_error(scene, tmp_path, monkeypatch):
    """Without DISPLAY/WAYLAND_DISPLAY, spawning or opening says so in one line instead of hanging."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(viewer.ViewerUnavailable, match="no display"):
        viewer.LiveViewer(scene[0], scene[1], mode="spawn")
    with pytest.raises(InputError, match="no recording.rrd"):
        viewer.open_recording(tmp_path)
    with pytest.raises(InputError, match="file not found"):
        viewer.open_recording(tmp_path / "elsewhere.rrd")
    (tmp_path / "recording.rrd").write_bytes(b"")
    with pytest.raises(viewer.ViewerUnavailable, match="no display"):
        viewer.open_recording(tmp_path)


# ----- how a recording opens ------------------------------------------------------------------------
def _blueprint_rows(path) -> dict[str, list[dict]]:
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    out = defaultdict(list)
    for store in reader.blueprints():
        for chunk in reader.stream(store=store):
            out[chunk.entity_path].extend(chunk.to_record_batch().to_pylist())
    return out


def test_recording_opens_on_the_smoother_with_the_others_hidden(written, scene):
    """Blueprint: every method but the smoother hidden (3D and each camera's reprojections), and the smoother's
    track ends; the frame timeline paused; the 3D eye aimed at the animal on the opening frame; marker names on
    hover only, but for a few markers of one method; an image border in every camera's view."""
    from rerun.blueprint.components import PlayState

    _, path, ents = written
    session, _, traj, _ = scene
    bp = _blueprint_rows(path)
    hidden = {p.split("/ViewContents/overrides", 1)[1].removesuffix("/visualizers")
              for p, rows in bp.items() if "/ViewContents/overrides/" in p
              and any(r.get("EntityBehavior:visible") == [False] for r in rows)}
    cams = session.rig.names
    assert hidden == ({"/world/triangulate", "/world/smoother/track_ends"}
                      | {f"/world/cameras/{c}/image/reproj/triangulate" for c in cams})
    panel = {k: v for r in bp["/time_panel"] for k, v in r.items() if v is not None}
    assert panel["TimePanelBlueprint:timeline"] == ["frame"]
    assert panel["TimePanelBlueprint:play_state"] == [PlayState.Paused.value]
    assert panel["TimePanelBlueprint:fps"] == [FPS]
    views = [p for p in bp if p.startswith("/view/") and p.count("/") == 2]
    assert len(views) == 1 + len(cams)  # 3D and one 2D view per camera (detections + reprojections)
    eye = {k: v for p, rows in bp.items() if p.endswith("/EyeControls3D") for r in rows for k, v in r.items()
           if v is not None}
    f = viewer.focus(session, traj)
    np.testing.assert_allclose(eye["EyeControls3D:look_target"][0], f.centre, atol=1e-5)

    def labels(entity):
        return [r["Points3D:show_labels"] for r in ents[entity] if r.get("Points3D:show_labels")]
    assert labels("/world/smoother/markers") == [[False]] and labels("/world/triangulate/markers") == [[False]]
    assert labels("/world/smoother/names") == [[True]] and "/world/triangulate/names" not in ents
    named = _by_frame(ents["/world/smoother/names"], "Points3D:class_ids")
    assert all(1 <= len(ids) <= viewer.NAMED_MARKERS for ids in named.values())
    for cam in cams:
        (border,) = [r for r in ents[f"/world/cameras/{cam}/image/border"] if r.get("LineStrips2D:strips")]
        w, h = session.rig[cam].size_wh
        assert border["LineStrips2D:strips"][0][2] == [w - 0.5, h - 0.5]


def test_track_ends_are_logged_apart_and_the_recording_names_its_opening_frame(scene, tmp_path):
    """Points outside a marker's span (here 'tip' on frames 0-2, seen by one camera: extrapolated) go to
    world/{method}/track_ends, not to the markers, skeleton or trails; the recording's properties and its eye
    name the opening frame: the first where nearly every marker is seen by >= 2 cameras."""
    session, dense, traj, reproj = scene
    traj = traj.copy()
    early_tip = (traj["marker"] == "tip") & (traj["frame"] <= 2)
    traj.loc[early_tip, "n_views"] = 1
    traj.loc[(traj["frame"] == 0), "n_views"] = 1  # frame 0: no marker seen twice
    path = viewer.write_recording(tmp_path / "recording.rrd", session, dense, traj, reproj, trail_frames=3)
    ents = _read(path)
    tip = MARKERS.index("tip")
    markers = _by_frame(ents["/world/smoother/markers"], "Points3D:class_ids")
    ends = _by_frame(ents["/world/smoother/track_ends/markers"], "Points3D:class_ids")
    assert all(tip not in markers.get(f, []) for f in range(3)) and all(tip in markers[f] for f in range(3, 10))
    assert sorted(ends[0]) == list(range(len(MARKERS))) and [ends[f] for f in (1, 2)] == [[tip], [tip]]
    assert not any(ends.get(f) for f in range(3, 10))
    props = [r for p, rows in ents.items() if p.startswith("/__properties") for r in rows]
    # frames 1-2 have 3 of the 4 markers seen twice, under 90 % of the most on any frame (4, from frame 3 on)
    assert any(r.get("opening_frame") == [3] for r in props), props
    assert viewer.focus(session, traj).frame == 3


@pytest.mark.slow
def test_a_headless_viewer_opens_the_recording_on_its_opening_frame(tmp_path):
    """A real Rerun viewer (headless: a software rasterizer such as Mesa's lavapipe is enough) shown the bundled
    sample's recording, its cursor moved as `batgraph view` moves it: it stands on summary.json's opening frame,
    and its screenshot of the 3D view is not blank. Skipped where no viewer can start or render (no graphics driver:
    the viewer then starts, panics "Failed to get render context" and drops the connection)."""
    from pathlib import Path

    from batgraph.pipeline import reconstruct
    from batgraph.result import Options

    try:
        from rerun.experimental import ViewerClient
    except ImportError:
        pytest.skip("this rerun-sdk has no viewer control API")
    sample = Path(__file__).parents[1] / "data" / "samples" / "flight_5cam"
    result = reconstruct(sample, tmp_path / "out", ["smoother"], Options(progress=False), viewer="save")
    frame = result.summary["opening_frame"]
    assert frame is not None and frame > 0  # the sample's first frames are seen by one camera only
    port = viewer._free_port()
    try:
        client = ViewerClient.spawn(headless=True, port=port, executable_path=viewer._rerun_executable(),
                                    hide_welcome_screen=True)
    except Exception as e:  # noqa: BLE001 - no graphics adapter here
        pytest.skip(f"no headless Rerun viewer here: {e}")
    try:
        try:
            client.open(str(tmp_path / "out" / "recording.rrd"))
        except ConnectionError as e:  # started, then died: no render context (no Vulkan or GL driver here)
            pytest.skip(f"the headless Rerun viewer cannot render here: {e}")
        assert viewer.move_cursor(port, frame, timeout_s=60)
        (rec,) = client.get_state().recordings
        assert rec.current_timeline == "frame" and rec.current_time == frame
        time.sleep(1.0)
        client.save_screenshot(str(tmp_path / "viewer.png"))
    finally:
        client.quit()
    image = cv2.imread(str(tmp_path / "viewer.png"))
    assert image is not None and image.shape[1] >= 1000
    assert float(image.std()) > 10.0


# ----- `batgraph view`: the rerun child process -------------------------------------------------------
VIEW_SCRIPT = """
import sys
from batgraph import viewer
from batgraph.cli import main
viewer._rerun_executable = lambda: sys.argv[2]
sys.exit(main(["view", sys.argv[1]]))
"""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals and a shell script as the viewer")
@pytest.mark.parametrize("sig, stubborn, code", [(signal.SIGTERM, False, 143), (signal.SIGINT, False, 130),
                                                 (signal.SIGTERM, True, 143)])
def test_view_passes_signals_on_and_never_leaves_the_viewer_running(tmp_path, sig, stubborn, code):
    """A fake rerun (a shell script that records its pid and sleeps; 'stubborn' ignores the signal): the
    signal to `batgraph view` reaches it, `view` exits 128 + signal, and the child is gone (killed after 5 s
    when it ignores the signal)."""
    (tmp_path / "recording.rrd").write_bytes(b"")
    pidfile = tmp_path / "pid"
    fake = tmp_path / "rerun"
    trap = "trap '' TERM INT\n" if stubborn else ""
    fake.write_text(f"#!/bin/sh\n{trap}echo $$ > {pidfile}\nwhile true; do sleep 0.05; done\n")
    fake.chmod(0o755)
    script = tmp_path / "view.py"
    script.write_text(VIEW_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path), str(fake)],
                            env={**os.environ, "DISPLAY": ":99"}, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not (pidfile.exists() and pidfile.read_text().strip()):
        assert time.time() - t0 < 60 and proc.poll() is None, proc.stderr.read() if proc.poll() is not None else ""
        time.sleep(0.05)
    child = int(pidfile.read_text())
    proc.send_signal(sig)
    assert proc.wait(timeout=30) == code
    assert not _pid_alive(child)
    assert "Traceback" not in proc.stderr.read()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals")
def test_a_signal_while_the_viewer_starts_still_reaches_it(monkeypatch):
    """Ctrl-C in the instant after the child is spawned, before its wait begins: the child is still stopped, not
    orphaned (on a loaded machine the test above once sent its signal in that instant)."""
    spawned = []
    popen = subprocess.Popen

    def spawn_then_interrupt(*args, **kwargs):
        spawned.append(popen(*args, **kwargs))
        os.kill(os.getpid(), signal.SIGINT)
        return spawned[-1]

    monkeypatch.setattr(subprocess, "Popen", spawn_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        viewer.run_child([sys.executable, "-c", "import time; time.sleep(60)"], grace_s=5.0)
    alive = spawned and spawned[0].poll() is None
    if alive:
        spawned[0].kill()
    assert spawned and not alive


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display detection is X11/Wayland specific")
def test_view_without_display_names_no_option_it_does_not_have(tmp_path, monkeypatch, capsys):
    """`batgraph view` has no --viewer option: its message must not suggest one; it says how to use Rerun's web
    viewer instead, with a flag the installed rerun has."""
    from batgraph.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    (tmp_path / "recording.rrd").write_bytes(b"")
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no display" in err and "--viewer" not in err and len(err.strip().splitlines()) == 1
    assert f"rerun --web-viewer {tmp_path / 'recording.rrd'}" in err
    helped = subprocess.run([viewer._rerun_executable(), "--help"], capture_output=True, text=True, timeout=60,
                            env={**os.environ, "RERUN_APP_ONLY": "true"})
    assert "--web-viewer" in helped.stdout
