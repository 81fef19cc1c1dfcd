"""One frame of the live view: the paper's figure (``draw.figure``: people red, proposals green,
tracks blue, target yellow, the north-up head-plane view) under a caption band with the phase and
the zones, JPEG-encoded. The service's live view (``companion.service.web``) and ``companion
bench`` (its cost per frame) use it; the drawing itself is ``draw``'s, not repeated here.
"""

from __future__ import annotations

import cv2
import numpy as np

from companion.pipeline.slz import FrameResult
from companion.replay import draw

#: Height of the caption band above the figure (px).
CAPTION_PX = 28


def live_figure(image: np.ndarray, result: FrameResult, target_id: int | None, caption: str) -> np.ndarray:
    """The figure of ``image`` (BGR, the frame the pipeline saw) and its ``result``, with
    ``caption`` (one line: phase, zones, time) in a dark band on top."""
    fig = draw.figure(image, result.occupancy, result.projection, result.proposals, result.tracks, target_id,
                      result.free_grid, result.grid, result.surface, result.people_free,
                      looked_at=result.looked_at)
    band = np.full((CAPTION_PX, fig.shape[1], 3), 32, np.uint8)
    cv2.putText(band, caption, (8, CAPTION_PX - 9), cv2.FONT_HERSHEY_SIMPLEX, 0.55, draw.WHITE, 1, cv2.LINE_AA)
    return np.vstack([band, fig])


def encode_jpeg(image: np.ndarray, quality: int = 80) -> bytes:
    """``image`` (BGR) as JPEG bytes; ValueError when OpenCV cannot encode it."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def live_jpeg(image: np.ndarray, result: FrameResult, target_id: int | None, caption: str,
              quality: int = 80) -> bytes:
    """``live_figure`` encoded as JPEG: one part of the MJPEG stream."""
    return encode_jpeg(live_figure(image, result, target_id, caption), quality)


def raw_figure(image: np.ndarray, caption: str, reason: str) -> np.ndarray:
    """The live view of a frame the pipeline cannot use (on the ground, under the head plane, no
    pose): ``image`` (BGR) as the camera gave it, a dark square where the head-plane view goes,
    with ``reason`` written on it, under ``caption``: the same size as ``live_figure``'s."""
    h, w = image.shape[:2]
    panel = np.full((h, 4 + h, 3), 24, np.uint8)
    for i, line in enumerate(("not processed:", reason)):
        cv2.putText(panel, line, (14, h // 2 - 10 + 26 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.6, draw.WHITE, 1,
                    cv2.LINE_AA)
    band = np.full((CAPTION_PX, w + 4 + h, 3), 32, np.uint8)
    cv2.putText(band, f"{caption}  NOT PROCESSED: {reason}", (8, CAPTION_PX - 9), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                draw.MAGENTA, 1, cv2.LINE_AA)
    return np.vstack([band, np.hstack([image, panel])])


def placeholder_figure(width: int, height: int, reason: str) -> np.ndarray:
    """A dark ``width`` x ``height`` frame saying ``reason``: what the live view sends while no
    camera frame comes, so that a client is never left waiting for a first or next frame."""
    img = np.full((height, width, 3), 24, np.uint8)
    cv2.putText(img, reason, (16, height // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.7, draw.WHITE, 1, cv2.LINE_AA)
    return img
