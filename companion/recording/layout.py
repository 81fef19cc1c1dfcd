"""The recording's on-disk layout, shared by the writer and the reader: the format version, the
video containers, the frame thumbnails that catch half-written frames, the pose as JSON, and the
order of a stream's files (see :mod:`companion.recording` for the folder's layout)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.geometry.camera import Pose

FORMAT_VERSION = 2  # 2: frame index and events in numbered chunks; 1: frames.jsonl, events.jsonl
SUFFIX = {"MJPG": ".avi", "mp4v": ".mp4"}
THUMB = 8
# Grey levels an 8x8-grid block mean may move through lossy compression; a half-decoded frame moves
# whole blocks to flat grey, far more than this.
THUMB_TOLERANCE = 24.0


class RecordingError(RuntimeError):
    """A recording that cannot be read (missing or corrupt file); the message names the file."""


def pose_to_dict(pose: Pose | None) -> dict[str, Any] | None:
    if pose is None:
        return None
    d: dict[str, Any] = {k: float(getattr(pose, k)) for k in ("t", "north", "east", "down", "roll", "pitch", "yaw")}
    d["gimbal"] = None if pose.gimbal is None else np.asarray(pose.gimbal, float).tolist()
    return d


def pose_from_dict(d: dict[str, Any] | None) -> Pose | None:
    if d is None:
        return None
    g = d.get("gimbal")
    return Pose(float(d["t"]), float(d["north"]), float(d["east"]), float(d["down"]),
                float(d["roll"]), float(d["pitch"]), float(d["yaw"]),
                None if g is None else np.asarray(g, float))


def thumbnail(image: np.ndarray) -> list[int]:
    """8x8 block means of the grey image: lets the reader tell a frame it decoded from a
    half-written one (a truncated segment decodes its last JPEG as partly flat grey)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return [int(v) for v in cv2.resize(grey, (THUMB, THUMB), interpolation=cv2.INTER_AREA).ravel()]


def _thumb_matches(image: np.ndarray, thumb: Any) -> bool:
    if not isinstance(thumb, list) or len(thumb) != THUMB * THUMB:
        return True  # older or hand-made recordings carry none: nothing to check against
    diff = np.abs(np.asarray(thumbnail(image), float) - np.asarray(thumb, float))
    return float(diff.max()) <= THUMB_TOLERANCE


def stream_files(folder: Path, stem: str) -> list[Path]:
    """The files of one stream (``frames`` or ``events``) of a recording, in order: format 1's
    single ``<stem>.jsonl``, then the chunks ``<stem>-NNNNN.jsonl`` by number."""
    single = folder / f"{stem}.jsonl"
    numbered: list[tuple[int, Path]] = []
    for p in folder.glob(f"{stem}-*.jsonl"):
        m = re.fullmatch(rf"{stem}-(\d+)\.jsonl", p.name)
        if m is not None:
            numbered.append((int(m.group(1)), p))
    return ([single] if single.is_file() else []) + [p for _, p in sorted(numbered)]
