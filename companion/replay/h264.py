"""H.264 in MP4 through PyAV: the video web browsers play (yuv420p, ``+faststart``).

OpenCV's pip wheels cannot encode H.264 (their FFmpeg has no H.264 encoder: ``avc1`` does not
open, ``mp4v`` writes MPEG-4 Part 2, which browsers do not play); PyAV's wheels bundle libx264.
PyAV is in the ``tools`` extra and imported only when a writer opens.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def available() -> bool:
    """Whether PyAV (the ``tools`` extra) is installed, so that :class:`H264Writer` can write."""
    try:
        import av  # noqa: F401  (the tools extra)
    except ImportError:
        return False
    return True


class H264Writer:
    """Writes BGR frames as H.264 (yuv420p) into an MP4 at a constant ``fps`` (frames/s). The
    first frame fixes the size (cut to even width and height, which yuv420p needs); later frames
    of another size are resized to it. Raises ModuleNotFoundError (name ``av``) without PyAV."""

    def __init__(self, path: Path, fps: float, crf: int = 23) -> None:
        import av  # the tools extra

        self.path, self.fps, self.frames = path, fps, 0
        path.parent.mkdir(parents=True, exist_ok=True)
        self._av = av
        self._container: Any = av.open(str(path), "w", options={"movflags": "+faststart"})
        self._stream: Any = None
        self._crf = crf

    def write(self, image_bgr: np.ndarray) -> None:
        if self._stream is None:
            stream = self._container.add_stream("libx264", rate=max(1, round(self.fps)))
            stream.width, stream.height = image_bgr.shape[1] // 2 * 2, image_bgr.shape[0] // 2 * 2
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": str(self._crf), "preset": "veryfast"}
            self._stream = stream
        w, h = self._stream.width, self._stream.height
        if image_bgr.shape[1] // 2 * 2 != w or image_bgr.shape[0] // 2 * 2 != h:
            import cv2

            image_bgr = cv2.resize(image_bgr, (w, h), interpolation=cv2.INTER_AREA)
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(image_bgr[:h, :w]), format="bgr24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        if self._container is None:
            return
        try:
            if self._stream is not None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
        finally:
            self._container.close()
            self._container = None

    def __enter__(self) -> H264Writer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
