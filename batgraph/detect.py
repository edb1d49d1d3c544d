"""Marker blobs in each camera's video: the unlabelled detections (``frame, camera, u, v, size``) that
``batgraph associate`` names.

Per camera: the background is the per-pixel median of frames spread over the recording (a bat flying through
covers a pixel on few of them); each frame's contrast is its difference from the background (``bright``
markers: frame - background; ``dark``: background - frame); pixels whose contrast exceeds the threshold are
grouped into 8-connected blobs (OpenCV's connected components), a blob split where it holds separate peaks (two
markers' blobs touching); a blob's position is its contrast-weighted centroid, as DLTdv snaps a click to its blob's
weighted centre. u, v are in the OpenCV pixel convention (the centre of the top-left pixel is 0, 0), raw
(distorted), as observations.csv. The threshold defaults to NOISE_SIGMAS times the image noise, measured as the
robust std of the sampled frames' contrast. Blobs smaller or larger than the area bounds are dropped (a noise
speck; the bat's body). Names nothing (batgraph.associate).

OpenCV's SimpleBlobDetector is not used: it takes a blob's centre from the binarised shape, unweighted, and has
no background to subtract (a bat's silhouette and a lamp would be blobs as much as the markers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd

from .errors import InputError
from .forked import can_fork, map_jobs, usable_cores
from .frames import Recording

NOISE_SIGMAS = 6.0
"""Default threshold in stds of the image noise: a pure-noise pixel exceeds it with probability 1e-9, so a
1920 x 1080 frame holds a false speck about once in 500 frames (a speck must also reach the smallest area)."""
MIN_THRESHOLD = 5.0
"""Gray levels: the default threshold's floor, for footage whose measured noise is nearly zero (a static
background identical on every frame, as rendered or losslessly compressed frames are)."""
TRIMMED_RMS = 0.8705
"""The RMS of a standard normal within its central 95 % (|x| < 1.96)."""
CROWDED = 500
"""Blobs per frame (median) beyond which a camera is warned about: more than any marker set holds, so the
threshold lies in the image noise or the background moves."""


@dataclass
class BlobOptions:
    """polarity: 'bright' markers on a darker surround, or 'dark'; threshold: contrast [gray levels] a marker's
    pixels exceed (None: NOISE_SIGMAS x the measured noise, at least MIN_THRESHOLD); min_area_px, max_area_px:
    a blob's pixel count bounds; background: 'median' (per-pixel, of background_frames frames spread over the
    recording) or 'flat' (each frame's own median gray level: markers on a plain backdrop, as with infrared
    light and retroreflective markers)."""

    polarity: str = "bright"
    threshold: float | None = None
    min_area_px: int = 4
    max_area_px: int = 400
    background: str = "median"
    background_frames: int = 25

    def __post_init__(self):
        if self.polarity not in ("bright", "dark"):
            raise InputError(f"polarity must be 'bright' or 'dark', not {self.polarity!r}")
        if self.background not in ("median", "flat"):
            raise InputError(f"background must be 'median' or 'flat', not {self.background!r}")
        if self.min_area_px > self.max_area_px:
            raise InputError(f"the smallest blob area ({self.min_area_px} px) exceeds the largest "
                             f"({self.max_area_px} px)")


@dataclass
class CameraBlobs:
    """One camera's result: table (frame, camera, u, v, size), frames read, the measured noise [gray levels]
    and the threshold used [gray levels]."""

    camera: str
    table: pd.DataFrame
    frames: int
    noise: float
    threshold: float

    def median_per_frame(self) -> float:
        counts = np.bincount(self.table["frame"].to_numpy(), minlength=self.frames) if len(self.table) else [0]
        return float(np.median(counts))


def contrast(frame: np.ndarray, background: np.ndarray | None, polarity: str) -> np.ndarray:
    """(H, W) float32 contrast: frame - background for bright markers, background - frame for dark ones. A
    background of None is the frame's own median gray level ('flat')."""
    f = frame.astype(np.float32)
    bg = np.float32(np.median(f[::4, ::4])) if background is None else background
    return f - bg if polarity == "bright" else bg - f


def blobs(c: np.ndarray, threshold: float, min_area_px: int, max_area_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Blobs of the contrast image ``c`` (H, W) above ``threshold``: (n, 2) contrast-weighted centroids (u, v)
    [px, OpenCV convention] and (n,) areas [px], of the blobs whose area lies within the bounds.

    A blob holding two peaks that each rise above the highest pass between them to a higher peak by the threshold
    (two markers' blobs touching) is split: each pixel goes to its nearest such peak. Peaks closer than that stay
    one blob, at their weighted mean (two markers a few pixels apart: no image tells them apart)."""
    mask = (c > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    rows, cols = np.nonzero(mask)
    lab = labels[rows, cols]
    area = stats[:, cv2.CC_STAT_AREA].astype(np.int64)
    keep = (area >= min_area_px) & (area <= max_area_px)
    keep[0] = False  # label 0: the pixels below the threshold
    lab = _split(c, labels, stats, rows, cols, lab, keep, threshold)
    m = int(lab.max()) + 1
    part_area = np.bincount(lab, minlength=m)
    w = c[rows, cols].astype(np.float64)
    total = np.bincount(lab, weights=w, minlength=m)
    total[total == 0] = 1.0  # label 0 (below the threshold) holds no pixel of the mask
    u = np.bincount(lab, weights=w * cols, minlength=m) / total
    v = np.bincount(lab, weights=w * rows, minlength=m) / total
    keep = np.concatenate([keep, np.ones(m - n, bool)])  # the parts split off a kept blob are kept
    return np.column_stack([u[keep], v[keep]]), part_area[keep]


def _split(c, labels, stats, rows, cols, lab, keep, threshold) -> np.ndarray:
    """Mask pixels' labels (like ``lab``) with every kept blob that holds separate peaks (see :func:`blobs`) cut
    into one part per peak: the first keeps the blob's label, the others get new ones from len(keep)."""
    peak = (c >= cv2.dilate(c, np.ones((3, 3), np.uint8))) & (labels > 0)
    pr, pc = np.nonzero(peak)
    pl = labels[pr, pc]
    counts = np.bincount(pl, minlength=len(keep))
    lab = lab.copy()
    next_label = len(keep)
    for b in np.flatnonzero((counts >= 2) & keep):
        x, y, w, h = stats[b, :4]
        patch = np.where(labels[y:y + h, x:x + w] == b, c[y:y + h, x:x + w], -np.inf).astype(np.float32)
        mine = pl == b
        order = np.argsort(-c[pr[mine], pc[mine]], kind="stable")
        pts = np.column_stack([pr[mine][order] - y, pc[mine][order] - x])
        chosen = [pts[0]]
        for p in pts[1:]:
            # p stands apart where, cut at the threshold below it, no higher peak chosen is joined to it
            _, cut = cv2.connectedComponents((patch > patch[p[0], p[1]] - threshold).astype(np.uint8), connectivity=8)
            if cut[p[0], p[1]] not in {cut[q[0], q[1]] for q in chosen}:
                chosen.append(p)
        if len(chosen) < 2:
            continue
        inside = np.flatnonzero(lab == b)
        centres = np.array(chosen, float) + [y, x]
        d = (rows[inside, None] - centres[:, 0]) ** 2 + (cols[inside, None] - centres[:, 1]) ** 2
        new = np.concatenate([[b], np.arange(next_label, next_label + len(chosen) - 1)])
        lab[inside] = new[np.argmin(d, axis=1)]
        next_label += len(chosen) - 1
    return lab


def background_of(rec: Recording, options: BlobOptions) -> tuple[np.ndarray | None, float]:
    """The background (H, W) float32 (None: 'flat') and the image noise [gray levels]: the RMS of the sampled
    frames' contrast within its 95th percentile, over that of a Gaussian (robust to the markers and the bat
    passing, and unlike the median absolute deviation not rounded to whole gray levels)."""
    sample = rec.sample(options.background_frames)
    if options.background == "median":
        if len(sample) < 3:
            raise InputError(f"{rec.path}: {len(sample)} frame(s); a median background needs 3 or more "
                             "(use --background flat)")
        if len({f.shape for f in sample}) > 1:
            raise InputError(f"{rec.path}: frames of different sizes")
        background = np.median(np.stack(sample), axis=0).astype(np.float32)
    else:
        background = None
    devs = np.abs(np.concatenate([contrast(f, background, "bright")[::2, ::2].ravel() for f in sample]))
    inner = devs[devs <= np.quantile(devs, 0.95)]
    noise = float(np.sqrt(np.mean(inner ** 2))) / TRIMMED_RMS if len(inner) else 0.0
    return background, noise


def detect_camera(source, camera: str, options: BlobOptions, progress: bool = False) -> CameraBlobs:
    """Every frame of the recording at ``source`` (video file or image folder) searched for blobs."""
    rec = Recording.open(source)
    background, noise = background_of(rec, options)
    threshold = options.threshold if options.threshold is not None else max(NOISE_SIGMAS * noise, MIN_THRESHOLD)
    frames, uv, area = [], [], []
    n = 0
    it = rec.frames()
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=rec.count() or None, desc=camera, unit="frame", leave=False)
    for k, frame in it:
        if background is not None and frame.shape != background.shape:
            raise InputError(f"{rec.path}: frame {k} is {frame.shape[1]}x{frame.shape[0]} px, the others "
                             f"{background.shape[1]}x{background.shape[0]} px")
        xy, a = blobs(contrast(frame, background, options.polarity), threshold, options.min_area_px,
                      options.max_area_px)
        frames.append(np.full(len(a), k, np.int64))
        uv.append(xy)
        area.append(a)
        n = k + 1
    xy = np.concatenate(uv) if uv else np.zeros((0, 2))
    table = pd.DataFrame({"frame": np.concatenate(frames) if frames else np.zeros(0, np.int64),
                          "camera": camera, "u": xy[:, 0], "v": xy[:, 1],
                          "size": (np.concatenate(area) if area else np.zeros(0)).astype(float)})
    return CameraBlobs(camera, table, n, noise, threshold)


def detect(sources: list, cameras: list[str], options: BlobOptions | None = None,
           progress: bool = False) -> tuple[pd.DataFrame, list[CameraBlobs]]:
    """Blobs of every camera's recording: (detections table in frame then camera order, per-camera results).
    ``cameras[i]`` names ``sources[i]`` (as calibration.toml names the camera). The cameras are shared over the
    cores (batgraph.forked; a progress bar only where they run in this process)."""
    if len(cameras) != len(sources):
        raise InputError(f"--cameras: {len(cameras)} names for {len(sources)} recordings")
    dup = sorted({c for c in cameras if cameras.count(c) > 1})
    if dup:
        raise InputError(f"--cameras: {', '.join(dup)} named twice (one recording per camera)")
    options = options or BlobOptions()
    parallel = len(sources) > 1 and can_fork() and usable_cores() > 1
    per_camera = map_jobs(lambda i: detect_camera(sources[i], cameras[i], options, progress and not parallel),
                          len(sources))
    table = pd.concat([p.table for p in per_camera], ignore_index=True)
    order = np.lexsort((np.repeat(np.arange(len(per_camera)), [len(p.table) for p in per_camera]),
                       table["frame"].to_numpy()))
    return table.iloc[order].reset_index(drop=True), per_camera


def report_lines(per_camera: list[CameraBlobs]) -> tuple[list[str], list[str]]:
    """(one summary line per camera, warnings): a camera with no blob, or more per frame than any marker set."""
    lines, warnings = [], []
    for p in per_camera:
        per = p.median_per_frame()
        lines.append(f"{p.camera}: {p.frames} frames, {len(p.table)} blobs ({per:g} per frame, median), "
                     f"noise {p.noise:.2f} gray levels, threshold {p.threshold:.1f}")
        if len(p.table) == 0:
            warnings.append(f"{p.camera}: no blob on any of its {p.frames} frames (lower --threshold, or check "
                            "--polarity and --max-area)")
        elif per > CROWDED:
            warnings.append(f"{p.camera}: {per:g} blobs per frame (median), more than a marker set holds: the "
                            "threshold lies in the image noise or the background moves (raise --threshold or "
                            "--min-area)")
    return lines, warnings
