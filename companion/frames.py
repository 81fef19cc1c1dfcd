"""Reading frames from stored media, written once for the service's camera and for replay.

A folder of images is played in file-name order; an image is BGR ``uint8`` (H, W, 3) or, when it
cannot be decoded, ``None`` (the caller counts it as corrupt, it never stops a stream).

A JPEG cut short (a file still being written, a copy interrupted, a stream part lost on the way) is
not decoded at all: OpenCV's ``imread`` decodes what is there and fills the rest with flat grey
(128), and one cut at 3 % of its bytes came out 97.5 % grey, an image of nothing that the pipeline
would have taken for empty ground. A JPEG must end with its end-of-image marker (``FF D9``; zero,
``FF`` or white-space padding after it is allowed); one that does not is refused before decoding.
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


#: A JPEG stream's first two bytes (start of image) and last two (end of image).
JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"


def truncated_jpeg(data: bytes) -> bool:
    """``data`` is a JPEG (starts with SOI) that does not end with its EOI marker, padding aside:
    cut short, so part of the image would be made up by the decoder."""
    return data[:2] == JPEG_SOI and not data.rstrip(b"\x00\xff \t\r\n").endswith(JPEG_EOI)


def decode_image(data: bytes, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """Encoded image bytes as BGR uint8, or None when they are not a whole, decodable image (a
    truncated JPEG among them, see the module docstring)."""
    if not data or truncated_jpeg(data):
        return None
    return as_bgr(cv2.imdecode(np.frombuffer(data, np.uint8), flags))


def read_image(path: Path) -> np.ndarray | None:
    """One image file as BGR uint8, or None when it cannot be read or decoded as a whole image."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    return decode_image(data)


def read_video_frame(cap: cv2.VideoCapture) -> tuple[bool, np.ndarray | None]:
    """The next frame of an open capture: (False, None) when it gives none (the end of a file, a
    failed device or decoder), else (True, the frame as BGR uint8, or None when it is not an
    image)."""
    ok, image = cap.read()
    if not ok:
        return False, None
    return True, as_bgr(image)
