"""A Motion-JPEG AVI file written from JPEG bytes: the recorder's video segments without
decoding and encoding the frames again.

``cv2.VideoWriter`` takes decoded images only, so a frame that came from the camera as a JPEG
(an MJPEG stream) was encoded a second time to be recorded: 2.2 ms of CPU a 640x480 frame on the
development machine, for a copy one generation further from what the pipeline saw. Here the
camera's own bytes go into the file, and replay decodes exactly the pixels the service decoded.
Frames that come decoded (V4L2, GStreamer, files) are encoded once with libjpeg
(``encode_jpeg``), 0.9 ms a 640x480 frame at quality 95.

The file is AVI 1.0 (RIFF ``AVI ``, one ``vids``/``MJPG`` stream, a ``movi`` list of ``00dc``
chunks and an ``idx1`` index), what OpenCV's own MJPG writer makes and what FFmpeg, OpenCV and
players read. The header is written first with the sizes and the frame count of an empty file
and patched by ``close``; a file cut off before that (a power cut) still reads up to its last
whole frame, as FFmpeg reads the ``movi`` list without the index. Segments stay far below the 1
GiB where AVI 1.0 ends (the recorder cuts them at 64 MiB at most).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

_AVIF_HASINDEX = 0x10
_AVIIF_KEYFRAME = 0x10
#: The rate is stored as rate / scale frames a second: a thousandth of a frame per second.
_SCALE = 1000
#: From the file's start: where avih's total frames, strh's length and the movi list's size sit.
_AVIH_FRAMES = 48
_STRH_LENGTH = 140
_MOVI_SIZE = 216
_HEADER_BYTES = 224
#: The file's write buffer (bytes): what its size on disk may lag behind what was written (a
#: frame larger than this goes to the file at once). The recorder's disk budget counts it.
AVI_BUFFER = 8192


def encode_jpeg(image: np.ndarray, quality: int = 95) -> bytes:
    """A BGR (or grey) uint8 image as JPEG bytes; ValueError when OpenCV cannot encode it."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} {image.dtype} image as JPEG")
    return buf.tobytes()


def is_jpeg(data: bytes) -> bool:
    """The bytes start like a JPEG (start-of-image marker, then another marker)."""
    return len(data) > 4 and data[:3] == b"\xff\xd8\xff"


class MjpegAviWriter:
    """Writes one AVI file of JPEG frames of one size. ``write`` each frame's bytes, then
    ``close`` (idempotent). OSError from the file system is the caller's (the recorder counts it).

    path: the file (overwritten). size: (width, height) in pixels, as stored in the headers.
    fps: nominal frame rate (> 0)."""

    def __init__(self, path: str | Path, size: tuple[int, int], fps: float) -> None:
        w, h = (int(v) for v in size)
        if w <= 0 or h <= 0 or not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"AVI needs a positive size and frame rate, got {size!r} at {fps!r}")
        self.path = Path(path)
        self.size = (w, h)
        self.frames = 0
        self._index: list[tuple[int, int]] = []  # (offset from the movi list's fourcc, size)
        self._pos = 4  # next chunk's offset from the movi fourcc
        self._max_chunk = 0
        self._fh: BinaryIO | None = open(self.path, "wb", buffering=AVI_BUFFER)  # noqa: SIM115 (closed by close())
        rate = max(1, round(fps * _SCALE))
        self._fh.write(self._header(w, h, rate))

    @staticmethod
    def _header(w: int, h: int, rate: int) -> bytes:
        avih = struct.pack("<10I4I", round(1e6 * _SCALE / rate), 0, 0, _AVIF_HASINDEX, 0, 0, 1, 0, w, h,
                           0, 0, 0, 0)
        strh = struct.pack("<4s4sIHHIIIIIIII4h", b"vids", b"MJPG", 0, 0, 0, 0, _SCALE, rate, 0, 0, 0,
                           0xFFFFFFFF, 0, 0, 0, w, h)
        strf = struct.pack("<IiiHH4sIiiII", 40, w, h, 1, 24, b"MJPG", w * h * 3, 0, 0, 0, 0)
        strl = b"strl" + _chunk(b"strh", strh) + _chunk(b"strf", strf)
        hdrl = b"hdrl" + _chunk(b"avih", avih) + b"LIST" + struct.pack("<I", len(strl)) + strl
        head = b"RIFF" + struct.pack("<I", 0) + b"AVI " + b"LIST" + struct.pack("<I", len(hdrl)) + hdrl
        head += b"LIST" + struct.pack("<I", 4) + b"movi"
        assert len(head) == _HEADER_BYTES
        return head

    def write(self, jpeg: bytes) -> None:
        """Append one frame's JPEG bytes (not checked beyond their first bytes)."""
        if self._fh is None:
            raise ValueError(f"{self.path} is closed")
        if not is_jpeg(jpeg):
            raise ValueError("not JPEG bytes")
        chunk = _chunk(b"00dc", jpeg)
        self._fh.write(chunk)
        self._index.append((self._pos, len(jpeg)))
        self._pos += len(chunk)
        self._max_chunk = max(self._max_chunk, len(jpeg))
        self.frames += 1

    def close(self) -> None:
        """Write the index and the sizes and frame count into the headers."""
        fh, self._fh = self._fh, None
        if fh is None:
            return
        try:
            idx = b"".join(struct.pack("<4sIII", b"00dc", _AVIIF_KEYFRAME, off, n) for off, n in self._index)
            fh.write(_chunk(b"idx1", idx))
            end = fh.tell()
            for at, value in ((4, end - 8), (_AVIH_FRAMES, self.frames), (_STRH_LENGTH, self.frames),
                              (_MOVI_SIZE, self._pos)):
                fh.seek(at)
                fh.write(struct.pack("<I", value))
            # Suggested buffer sizes: the largest frame (readers allocate from them).
            for at in (_AVIH_FRAMES + 12, _STRH_LENGTH + 4):
                fh.seek(at)
                fh.write(struct.pack("<I", self._max_chunk))
        finally:
            fh.close()


def jpeg_frames(path: str | Path) -> Iterator[bytes]:
    """The frames of a Motion-JPEG AVI file as their JPEG bytes, in file order: what
    ``MjpegAviWriter`` wrote, and what OpenCV's MJPG writer wrote (older recordings). Decoding
    them with ``cv2.imdecode`` gives the very pixels the service decoded from the same bytes
    (FFmpeg's decoder, behind ``cv2.VideoCapture``, differs by up to a few tens of levels at
    colour edges). The ``movi`` list is walked chunk by chunk, index or not, so a file cut off
    (by a power cut, before its sizes were written) yields its whole frames and stops at the
    first incomplete one.

    ValueError before the first frame when the file is not an AVI of one MJPG video stream
    (the caller then reads it some other way); OSError when it cannot be read."""
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"AVI ":
            raise ValueError(f"{path} is not an AVI file")
        codec: bytes | None = None
        while True:
            top = fh.read(8)
            if len(top) < 8:
                return
            fourcc, size = top[:4], struct.unpack("<I", top[4:])[0]
            if fourcc == b"LIST":
                kind = fh.read(4)
                if kind == b"hdrl":
                    codec = _hdrl_codec(fh.read(max(0, size - 4)))
                    if codec != b"MJPG":
                        raise ValueError(f"{path}: video stream is {codec!r}, not MJPG")
                    continue
                if kind == b"movi":
                    if codec is None:
                        raise ValueError(f"{path}: no stream header before the frames")
                    yield from _movi_frames(fh)
                    return
                fh.seek(max(0, size - 4) + size % 2, 1)  # another list (INFO, ...)
                continue
            fh.seek(size + size % 2, 1)


def _hdrl_codec(hdrl: bytes) -> bytes | None:
    """The compression field of the first stream's format (``strf``) in a ``hdrl`` list (an
    audio stream first gives something that is not MJPG: the file is then read another way)."""
    at = 0
    while at + 8 <= len(hdrl):
        fourcc, size = hdrl[at:at + 4], struct.unpack("<I", hdrl[at + 4:at + 8])[0]
        if fourcc == b"LIST":
            found = _hdrl_codec(hdrl[at + 12:at + 8 + size])
            if found is not None:
                return found
        elif fourcc == b"strf" and size >= 20:
            return hdrl[at + 8 + 16:at + 8 + 20]
        at += 8 + size + size % 2
    return None


def _movi_frames(fh: BinaryIO) -> Iterator[bytes]:
    """The video chunks (``##dc``/``##db``) from here to the end of the file or the first
    incomplete chunk; lists (``rec ``, and the ``movi`` of an OpenDML ``RIFF AVIX``
    continuation) are walked into, anything else (JUNK, ``ix##``, ``idx1``) skipped. The lists'
    own sizes are not trusted: ``movi`` says 4 in a file that was never closed."""
    while True:
        top = fh.read(8)
        if len(top) < 8:
            return
        fourcc, size = top[:4], struct.unpack("<I", top[4:])[0]
        if fourcc in (b"LIST", b"RIFF"):
            fh.read(4)  # its type ('rec ', 'AVIX', 'movi'): its chunks follow
            continue
        if fourcc[2:] in (b"dc", b"db"):
            data = fh.read(size)
            if len(data) < size:
                return
            yield data
            if size % 2:
                fh.read(1)
        else:
            fh.seek(size + size % 2, 1)


def _chunk(fourcc: bytes, data: bytes) -> bytes:
    """A RIFF chunk: fourcc, little-endian size, the data, a pad byte to an even length."""
    return fourcc + struct.pack("<I", len(data)) + data + (b"\0" if len(data) % 2 else b"")
