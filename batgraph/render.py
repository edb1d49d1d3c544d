"""A session's observations drawn as marker blobs into each camera's frames: the footage a blob detector
(batgraph.detect) is tested on, with the centre of every blob known.

Each blob is a 2D Gaussian of ``blob_sigma_px`` whose centre is the observation's u, v (the OpenCV pixel
convention: pixel (row r, column c) covers c - 0.5 .. c + 0.5), added to a static background (a smooth random
texture, 40-120 gray levels, and a few bright static lamps the detector must subtract); then Gaussian pixel noise,
rounded to 8 bits. Blobs closer than a few sigma overlap into one, as real ones do. Frames are written as PNG
folders (lossless) or a video. Randomness comes from the ``np.random.Generator`` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from .camera import Rig

CODECS = {".avi": "FFV1", ".mp4": "mp4v"}
"""Video suffix -> FourCC: FFV1 is lossless; mp4v (MPEG-4 part 2) is lossy, as a camera's own encoder is."""


@dataclass
class Look:
    """blob_sigma_px: a blob's Gaussian std [px]; contrast: its peak above the background [gray levels];
    noise: pixel noise std [gray levels]; lamps: bright static spots in the background; textured: False for a
    uniform background of 60 gray levels (a plain backdrop)."""

    blob_sigma_px: float = 1.2
    contrast: float = 120.0
    noise: float = 2.0
    lamps: int = 3
    textured: bool = True


def background(size_wh: tuple[int, int], rng: np.random.Generator, look: Look) -> np.ndarray:
    """(H, W) float32: a smooth random texture of 40-120 gray levels (or 60 flat) with ``look.lamps`` bright
    discs (static lamps along the top of the image, where the test scenes put no marker: a marker in front of
    a saturated lamp is lost to any detector)."""
    w, h = size_wh
    if look.textured:
        coarse = rng.uniform(40.0, 120.0, (max(h // 40, 2), max(w // 40, 2))).astype(np.float32)
        bg = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    else:
        bg = np.full((h, w), 60.0, np.float32)
    for _ in range(look.lamps):
        cv2.circle(bg, (int(rng.integers(0, w)), int(rng.integers(8, 30))), int(rng.integers(3, 8)), 250.0, -1)
    return np.clip(bg, 0, 255)


def draw_blobs(image: np.ndarray, uv_px: np.ndarray, look: Look) -> None:
    """Add a Gaussian blob (peak ``look.contrast``) at each (u, v) of ``uv_px`` (n, 2) to ``image`` in place."""
    h, w = image.shape
    r = int(np.ceil(4 * look.blob_sigma_px))
    for u, v in uv_px:
        c0, r0 = int(round(u)) - r, int(round(v)) - r
        cols = np.arange(max(c0, 0), min(c0 + 2 * r + 1, w))
        rows = np.arange(max(r0, 0), min(r0 + 2 * r + 1, h))
        if len(cols) == 0 or len(rows) == 0:
            continue
        g = np.exp(-((cols[None, :] - u) ** 2 + (rows[:, None] - v) ** 2) / (2 * look.blob_sigma_px ** 2))
        image[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1] += look.contrast * g


def render_camera(obs: pd.DataFrame, size_wh: tuple[int, int], frames: int, rng: np.random.Generator,
                  look: Look | None = None):
    """Yield (frame, uint8 (H, W) image) for frames 0..frames-1 of one camera's observations (frame, u, v)."""
    look = look or Look()
    bg = background(size_wh, rng, look)
    by_frame = {int(f): g[["u", "v"]].to_numpy() for f, g in obs.groupby("frame")}
    for k in range(frames):
        img = bg.copy()
        draw_blobs(img, by_frame.get(k, np.zeros((0, 2))), look)
        img += rng.normal(0.0, look.noise, img.shape).astype(np.float32)
        yield k, np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_session(rig: Rig, obs: pd.DataFrame, frames: int, folder, rng: np.random.Generator,
                   look: Look | None = None, video: str | None = None) -> list[Path]:
    """Every camera's footage in ``folder``: a PNG folder per camera (``video`` None) or a video file with that
    suffix (a key of CODECS), named as the camera. Returns the paths, in the rig's order."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for cam in rig:
        mine = obs[obs["camera"] == cam.name]
        size = (int(cam.size_wh[0]), int(cam.size_wh[1]))
        if video is None:
            out = folder / cam.name
            out.mkdir(exist_ok=True)
            for k, img in render_camera(mine, size, frames, rng, look):
                cv2.imwrite(str(out / f"{k:06d}.png"), img)
        else:
            out = folder / f"{cam.name}{video}"
            writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*CODECS[video]), 30.0, size, isColor=False)
            for _, img in render_camera(mine, size, frames, rng, look):
                writer.write(img)
            writer.release()
        paths.append(out)
    return paths
