"""Camera intrinsics (K and OpenCV distortion) from checkerboard or ChArUco images or video frames.

Detects the board with OpenCV (sub-pixel refined chessboard corners, or ChArUco corners), then
runs ``cv2.calibrateCamera`` with the 5-parameter model (k1, k2, p1, p2, k3) that GoPro-like
lenses need, or the 4-parameter model (k3 = 0) for mild lenses. Returns a
:class:`batgraph.camera.Camera` with an identity pose, ready for calibration.toml (see
:func:`batgraph.calibrate.write_calibration`). It does not estimate extrinsics between cameras
(that is :mod:`batgraph.calibrate`) and does not model fisheye lenses.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .camera import Camera
from .errors import InputError
from .frames import VIDEO_SUFFIXES, Recording

DIST_MODELS = {"k1k2p1p2k3": 0, "k1k2p1p2": cv2.CALIB_FIX_K3}


@dataclass
class Board:
    """A calibration board.

    kind: "checkerboard" or "charuco".
    cols, rows: checkerboard: inner corners along x and y; ChArUco: squares along x and y.
    square_m: side of one square [m].
    marker_m: ChArUco marker side [m] (ignored for checkerboards).
    dictionary: ChArUco dictionary name, e.g. "DICT_4X4_1000".
    legacy: ChArUco boards made by OpenCV < 4.6 (and Caliscope's "inverted" boards) use the
        legacy pattern.
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"
    legacy: bool = False

    def __post_init__(self):
        if self.kind not in ("checkerboard", "charuco"):
            raise InputError(f"board kind must be 'checkerboard' or 'charuco', got {self.kind!r}")
        if self.cols < 2 or self.rows < 2 or not self.square_m > 0:
            raise InputError(f"board: need cols, rows >= 2 and square_m > 0, got {self.cols}, {self.rows}, "
                             f"{self.square_m}")
        if self.kind == "charuco":
            if not 0 < self.marker_m < self.square_m:
                raise InputError(f"board: ChArUco marker_m must be in (0, square_m), got {self.marker_m}")
            if not hasattr(cv2.aruco, self.dictionary):
                raise InputError(f"board: unknown ArUco dictionary {self.dictionary!r}")

    def object_points(self) -> np.ndarray:
        """Corner positions on the board plane (z = 0), shape (n, 3) [m], in detection id order."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), dtype=float).reshape(-1, 3)
        gx, gy = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1) * self.square_m

    def charuco_board(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        b = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)
        b.setLegacyPattern(self.legacy)
        return b


def detect_board(gray: np.ndarray, board: Board, detector=None) -> tuple[np.ndarray, np.ndarray] | None:
    """Board corners in one grayscale image (H, W) uint8.

    Returns (object points (n, 3) [m], image points (n, 2) [px, OpenCV convention]) or None when
    the board is not found (checkerboards must be found whole; ChArUco needs >= 6 corners).
    """
    if board.kind == "checkerboard":
        size = (board.cols, board.rows)
        ok, corners = cv2.findChessboardCorners(
            gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (7, 7), (-1, -1), crit)
        return board.object_points(), corners.reshape(-1, 2).astype(float)
    detector = detector or cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    return board.object_points()[ids.ravel()], corners.reshape(-1, 2).astype(float)


def iter_frames(sources: Iterable[str | Path], every_nth: int = 1) -> Iterator[tuple[str, np.ndarray]]:
    """(label, grayscale image) from image files and/or videos (every ``every_nth`` video frame)."""
    for src in sources:
        path = Path(src)
        if not path.is_file():
            raise InputError(f"{path}: file not found")
        if path.suffix.lower() in VIDEO_SUFFIXES:
            for k, frame in Recording.open(path).frames():
                if k % every_nth == 0:
                    yield f"{path.name}#{k}", frame
        else:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f"{path}: not an image OpenCV can read")
            yield path.name, img


def calibrate_intrinsics(
    sources: Iterable[str | Path] | Iterable[np.ndarray], board: Board, *, name: str = "cam1",
    dist_model: str = "k1k2p1p2k3", every_nth: int = 1, min_views: int = 3,
) -> tuple[Camera, dict]:
    """Intrinsics of one camera from board images.

    sources: image / video paths, or grayscale images (H, W) uint8 already in memory.
    dist_model: "k1k2p1p2k3" (5 parameters, e.g. GoPro) or "k1k2p1p2" (k3 = 0).
    Returns (Camera with identity pose, report): report has rms_px (OpenCV's overall RMS),
    per_view_rms_px, n_views, n_corners, used (labels of the views with a detected board),
    skipped (labels without), std_fx_fy_cx_cy_px and std_dist (OpenCV's parameter std devs).
    """
    if dist_model not in DIST_MODELS:
        raise InputError(f"dist_model must be one of {', '.join(DIST_MODELS)}, got {dist_model!r}")
    detector = cv2.aruco.CharucoDetector(board.charuco_board()) if board.kind == "charuco" else None
    items = list(sources)
    frames = (((f"image{i}", im) for i, im in enumerate(items)) if items and isinstance(items[0], np.ndarray)
              else iter_frames(items, every_nth))
    obj, img, used, skipped, size = [], [], [], [], None
    for label, gray in frames:
        wh = (gray.shape[1], gray.shape[0])
        if size is not None and wh != size:
            raise InputError(f"{label}: image size {wh} differs from the first image's {size}")
        size = wh
        det = detect_board(gray, board, detector)
        if det is None:
            skipped.append(label)
            continue
        obj.append(det[0].astype(np.float32))
        img.append(det[1].astype(np.float32).reshape(-1, 1, 2))
        used.append(label)
    if len(used) < min_views:
        more = "..." if len(skipped) > 5 else ""
        raise InputError(f"calibrate-intrinsics: the board was found in {len(used)} view(s); at least "
                         f"{min_views} are needed (skipped: {', '.join(skipped[:5])}{more})")
    flags = DIST_MODELS[dist_model]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, _, _, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj, img, size, None, None, flags=flags, criteria=crit)
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    dist = np.concatenate([dist, np.zeros(5 - len(dist))])
    std_in = np.asarray(std_in, dtype=float).ravel()
    cam = Camera(name, size, np.asarray(K, dtype=float), dist)
    report = {"rms_px": float(rms), "per_view_rms_px": np.asarray(per_view, dtype=float).ravel().tolist(),
              "n_views": len(used), "n_corners": int(sum(len(o) for o in obj)), "used": used, "skipped": skipped,
              "std_fx_fy_cx_cy_px": std_in[:4].tolist(), "std_dist": std_in[4:9].tolist(),
              "dist_model": dist_model, "image_size_wh": list(size)}
    return cam, report
