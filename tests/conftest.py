"""Shared test helpers: a tiny rig, a moving point set and a valid session folder, built from camera.py.

Use the fixtures (``session_folder``, ``make_session_folder``) or import the functions
(``from conftest import tiny_rig, look_at, ...``); pytest puts this folder on sys.path.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from batgraph.camera import Camera, Rig
from batgraph.measurement import ideal_observations
from batgraph.motion import constant_velocity_F, constant_velocity_Q
from batgraph.session import PAPER_PHYSICS, MotionConfig, Session, dense_observations, write_session


def look_at(name: str, centre_world_m, target_world_m, K, size_wh=(640, 480), dist=None,
            up_world=(0.0, 0.0, 1.0)) -> Camera:
    """A camera at ``centre_world_m`` (3,) [m] whose optical axis points at ``target_world_m`` (3,) [m].

    World z is up; the image's v axis points along -up_world (camera axes: x right, y down, z forward).
    K: (3, 3) [px]; dist: (5,) OpenCV coefficients or None for none.
    """
    c = np.asarray(centre_world_m, float)
    z = np.asarray(target_world_m, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, up_world)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates -> cam_from_world
    rvec = cv2.Rodrigues(R)[0].ravel()
    return Camera(name, size_wh, K, np.zeros(5) if dist is None else dist, rvec, -R @ c)


def tiny_rig(n_cams: int = 3, size_wh=(640, 480), focal_px: float = 600.0, radius_m: float = 3.0,
             dist=None, skew: float = 0.0) -> Rig:
    """n_cams cameras on a circle of ``radius_m`` around the origin at heights 0.4-1.0 m, all aimed at it.

    Focal lengths differ slightly per camera (so a mixed-up camera order is detectable); the principal
    point sits near the image centre.
    """
    w, h = size_wh
    cams = []
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams + 0.3
        f = focal_px * (1 + 0.05 * i)
        K = np.array([[f, skew, (w - 1) / 2 + 3 * i], [0, f * 1.01, (h - 1) / 2 - 2 * i], [0, 0, 1]])
        centre = [radius_m * np.cos(a), radius_m * np.sin(a), 0.4 + 0.6 * i / max(n_cams - 1, 1)]
        cams.append(look_at(f"cam{i + 1}", centre, [0.0, 0.0, 0.1], K, size_wh, dist))
    return Rig(cams)


def tiny_scene(n_frames: int = 6, n_markers: int = 2, seed: int = 0) -> np.ndarray:
    """A smoothly moving marker set near the origin: xyz_world_m, shape (n_frames, n_markers, 3) [m]."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)[:, None, None] / max(n_frames, 1)
    base = rng.uniform(-0.2, 0.2, size=(1, n_markers, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(1, n_markers, 3))
    return base + 0.1 * np.sin(2 * np.pi * t + phase)


def observations_table(rig: Rig, xyz_world_m: np.ndarray, markers: list[str] | None = None) -> pd.DataFrame:
    """Project ``xyz_world_m`` (F, M, 3) into every camera: long table frame, camera, marker, u, v, weight.

    Only points that project inside the image are kept (raw pixels, with the rig's distortion).
    """
    F, M = xyz_world_m.shape[:2]
    markers = markers or [f"m{j}" for j in range(M)]
    uv = rig.project(xyz_world_m)  # (C, F, M, 2)
    rows = []
    for c, cam in enumerate(rig):
        ok = np.isfinite(uv[c, ..., 0]) & cam.in_image(uv[c])
        f, m = np.nonzero(ok)
        rows.append(pd.DataFrame({"frame": f, "camera": cam.name, "marker": np.array(markers)[m],
                                  "u": uv[c, f, m, 0], "v": uv[c, f, m, 1], "weight": 1.0}))
    return pd.concat(rows).sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True)


def write_tiny_session(folder: Path, n_cams: int = 3, n_frames: int = 6, n_markers: int = 2, seed: int = 0,
                       fps: float = 100.0, dist=None, with_truth: bool = True) -> Path:
    """Write a small valid session folder (session.toml, calibration.toml, observations.csv, truth.csv).

    Returns the folder. Every marker is seen by every camera on every frame (the scene is small and
    central), so tests can delete rows to make gaps.
    """
    rig = tiny_rig(n_cams, dist=dist)
    xyz = tiny_scene(n_frames, n_markers, seed)
    markers = [f"m{j}" for j in range(n_markers)]
    truth = pd.DataFrame({
        "frame": np.repeat(np.arange(n_frames), n_markers), "marker": markers * n_frames,
        "x": xyz[..., 0].ravel(), "y": xyz[..., 1].ravel(), "z": xyz[..., 2].ravel(),
    })
    session = Session(name=Path(folder).name, fps=fps, rig=rig, observations=observations_table(rig, xyz, markers),
                      motion=MotionConfig(model="random_walk", **PAPER_PHYSICS), marker_names=markers,
                      truth=truth if with_truth else None)
    return write_session(session, folder)


@pytest.fixture
def session_folder(tmp_path: Path) -> Path:
    """A valid tiny session folder (3 cameras, 6 frames, 2 markers) in tmp_path/session."""
    return write_tiny_session(tmp_path / "session")


@pytest.fixture
def make_session_folder(tmp_path: Path):
    """Factory: ``make_session_folder(name="s", **kwargs)`` -> folder written by :func:`write_tiny_session`."""
    def make(name: str = "session", **kwargs) -> Path:
        return write_tiny_session(tmp_path / name, **kwargs)
    return make


def cv_scene(q_per_marker, n_frames: int, seed: int = 0, fps: float = 100.0, v0_sigma_mps: float = 0.3):
    """Session, dense, ideal and truth (F, M, 3) [m] of tracks drawn from the constant-velocity model with
    one q [m^2/s^3] per marker, seen by 4 cameras with 0.5 px noise."""
    rng = np.random.default_rng(seed)
    q = np.asarray(q_per_marker, float)
    M, dt = len(q), 1 / fps
    Fm = constant_velocity_F(dt)
    x = np.zeros((n_frames, M, 6))
    x[0, :, :3] = rng.uniform(-0.1, 0.1, (M, 3))
    x[0, :, 3:] = rng.normal(0, v0_sigma_mps, (M, 3))
    L = np.linalg.cholesky(constant_velocity_Q(1.0, dt))
    for k in range(1, n_frames):
        x[k] = x[k - 1] @ Fm.T + np.sqrt(q)[:, None] * (rng.normal(size=(M, 6)) @ L.T)
    truth = x[..., :3]
    rig = tiny_rig(4, size_wh=(1280, 720), focal_px=900.0)
    obs = observations_table(rig, truth)
    obs[["u", "v"]] += rng.normal(0, 0.5, (len(obs), 2))
    session = Session("q", fps, rig, obs, MotionConfig(model="constant_velocity", **PAPER_PHYSICS), pixel_sigma_px=0.5)
    dense = dense_observations(session)
    return session, dense, ideal_observations(rig, dense, 0.5), truth
