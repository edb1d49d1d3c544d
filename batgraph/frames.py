"""One camera's recording read frame by frame: a video file (what OpenCV's FFmpeg reads) or a folder of images
(one per frame, in name order, as high-speed cameras export them), as grayscale arrays.

Frame k is the recording's k-th frame counted from 0. Images keep their depth (8 or 16 bits); a video's frames
are 8-bit. This module reads; it finds nothing in the frames.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError

VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".m4v", ".mts", ".wmv"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm"}


def gray(image: np.ndarray) -> np.ndarray:
    """A colour frame (BGR, as OpenCV decodes it) as grayscale; a grayscale one as it is."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def read_image(path: Path) -> np.ndarray:
    """An image file as grayscale at its own depth; InputError when OpenCV cannot read it."""
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None:
        raise InputError(f"{path}: not an image OpenCV can read")
    return gray(img[..., :3] if img.ndim == 3 else img)


@dataclass
class Recording:
    """path: the video file or the image folder; images: the folder's image files in name order (None: a video)."""

    path: Path
    images: list[Path] | None = None

    @classmethod
    def open(cls, source: str | Path) -> Recording:
        """The recording at ``source``; InputError when it is missing, empty or not a video or image folder."""
        path = Path(source)
        if path.is_dir():
            images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not images:
                raise InputError(f"{path}: a folder with no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
            return cls(path, images)
        if not path.is_file():
            raise InputError(f"{path}: file not found")
        rec = cls(path)
        cap = rec._capture()
        ok, _ = cap.read()
        cap.release()
        if not ok:
            raise InputError(f"{path}: a video with no frame OpenCV can decode")
        return rec

    def _capture(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise InputError(f"{self.path}: cannot open the video (not a video OpenCV's FFmpeg reads)")
        return cap

    def count(self) -> int:
        """How many frames: exact for a folder; the container's figure for a video (may be off by a few)."""
        if self.images is not None:
            return len(self.images)
        cap = self._capture()
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        return max(n, 0)

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        """(k, grayscale frame) for every frame in order; a folder's images must all have one size."""
        if self.images is not None:
            shape = None
            for k, p in enumerate(self.images):
                img = read_image(p)
                if shape is not None and img.shape != shape:
                    raise InputError(f"{p}: {img.shape[1]}x{img.shape[0]} px, but {self.images[0].name} is "
                                     f"{shape[1]}x{shape[0]} px (one camera's frames have one size)")
                shape = img.shape
                yield k, img
            return
        cap = self._capture()
        try:
            k = 0
            while True:
                ok, frame = cap.read()
                if not ok:
                    return
                yield k, gray(frame)
                k += 1
        finally:
            cap.release()

    def sample(self, n: int) -> list[np.ndarray]:
        """About ``n`` frames spread evenly over the recording (all of them when it has fewer; a video that states
        no length: its first n). A video is read through to them (seeking costs more than decoding in some
        containers: 0.3 s a seek in an FFV1 AVI of 720p frames, against 10 ms a frame decoded)."""
        if self.images is not None:
            picks = np.unique(np.linspace(0, len(self.images) - 1, min(n, len(self.images))).round().astype(int))
            return [read_image(self.images[k]) for k in picks]
        total = self.count()
        picks = set(np.linspace(0, total - 1, min(n, total)).round().astype(int).tolist()) if total > 0 \
            else set(range(n))
        cap = self._capture()
        out = []
        try:
            k = 0
            while len(out) < len(picks) and k <= max(picks) and cap.grab():
                if k in picks:
                    ok, frame = cap.retrieve()
                    if ok:
                        out.append(gray(frame))
                k += 1
        finally:
            cap.release()
        return out
