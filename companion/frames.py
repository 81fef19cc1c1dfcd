"""Reading frames from stored media, written once for the service's camera and for replay.

A folder of images is played in file-name order; an image is BGR ``uint8`` (H, W, 3) or, when it
cannot be decoded, ``None`` (the caller counts it as corrupt, it never stops a stream).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: What a folder source plays (lower-case suffixes).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")


def as_bgr(image: object) -> np.ndarray | None:
    """The frame as BGR uint8 (H, W, 3), or None when it is not a usable image."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.size == 0:
        return None
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return None


def image_files(folder: Path) -> list[Path]:
    """The image files of ``folder`` sorted by name (the frame order); empty when it holds none."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: p.name)


def read_image(path: Path) -> np.ndarray | None:
    """One image file as BGR uint8, or None when it cannot be decoded as one."""
    return as_bgr(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))


def read_video_frame(cap: cv2.VideoCapture) -> tuple[bool, np.ndarray | None]:
    """The next frame of an open capture: (False, None) when it gives none (the end of a file, a
    failed device or decoder), else (True, the frame as BGR uint8, or None when it is not an
    image)."""
    ok, image = cap.read()
    if not ok:
        return False, None
    return True, as_bgr(image)
