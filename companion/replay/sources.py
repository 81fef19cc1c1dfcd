"""Where replayed frames come from: a folder of images, a video file, or a flight recording.

Every source yields :class:`ReplayFrame` in order. A frame that cannot be decoded is yielded with
``image=None`` and a ``problem`` text, so the replay counts and skips it instead of stopping.
Problems that make the whole input unusable raise :class:`ReplayInputError` naming the path.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.frames import IMAGE_SUFFIXES, as_bgr, image_files, read_image, read_video_frame
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.mavlink.state import DOWNWARD_ORIENTATION, RANGEFINDER_MAX_AGE_S, downward_range_m
from companion.recording import RecordingError, RecordingReader

KINDS = ("auto", "frames", "video", "recording")


class ReplayInputError(ValueError):
    """An input that cannot be replayed at all (missing, empty, unreadable container)."""


@dataclass(frozen=True)
class ReplayFrame:
    """index: position in the input (0-based, counting skipped frames too). t: capture time in
    seconds (recorded time, or index / fps). image: BGR uint8 (H, W, 3), or None when the frame
    could not be read (``problem`` says why). pose: the vehicle pose at capture, when recorded."""

    index: int
    t: float
    image: np.ndarray | None
    pose: Pose | None = None
    problem: str | None = None
    name: str = ""
    #: Metres above the ground by a fresh downward rangefinder at capture (a recording's
    #: DISTANCE_SENSOR telemetry at most ``RANGEFINDER_MAX_AGE_S`` old), else None.
    agl: float | None = None


@dataclass
class ReplaySource:
    """An opened input. ``frames`` yields its frames; ``total`` is the frame count and ``fps`` the
    frame rate in Hz when known;
    ``intrinsics`` / ``mount`` come with recordings (None otherwise)."""

    kind: str
    path: Path
    frames: Iterator[ReplayFrame]
    total: int | None = None
    fps: float | None = None
    intrinsics: Intrinsics | None = None
    mount: Mount | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    # Frames the input itself dropped without yielding them (a recording's deleted or truncated
    # segments): reason -> count, read once the frames are exhausted.
    skipped_upstream: Callable[[], dict[str, int]] | None = None
    # Telemetry lines of the input that could not be used (a recording's malformed rangefinder
    # lines): reason -> count. Not frames: the summary reports them apart.
    telemetry_dropped: dict[str, int] = field(default_factory=dict)


def _check_fps(fps: float) -> float:
    if not (math.isfinite(fps) and fps > 0):
        raise ReplayInputError(f"--fps must be a number > 0, got {fps!r}")
    return float(fps)


def open_folder(folder: Path, fps: float) -> ReplaySource:
    """A folder of image frames, sorted by name, frame ``i`` at ``t = i / fps`` seconds."""
    fps = _check_fps(fps)
    if not folder.exists():
        raise ReplayInputError(f"frame folder {folder} does not exist")
    if not folder.is_dir():
        raise ReplayInputError(f"{folder} is not a folder of frames")
    files = image_files(folder)
    if not files:
        raise ReplayInputError(
            f"frame folder {folder} is empty: no image files ({', '.join(IMAGE_SUFFIXES)})")

    def frames() -> Iterator[ReplayFrame]:
        for i, p in enumerate(files):
            image = read_image(p)
            problem = None if image is not None else f"{p}: not a readable image"
            yield ReplayFrame(i, i / fps, image, None, problem, p.name)

    return ReplaySource("frames", folder, frames(), total=len(files), fps=fps)


def open_video(path: Path, fps: float | None) -> ReplaySource:
    """A video file; frame ``i`` at ``i / fps`` with the container's rate unless ``fps`` is given."""
    if not path.exists():
        raise ReplayInputError(f"video file {path} does not exist")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ReplayInputError(f"{path} is not a video that OpenCV can open")
    rate = fps if fps is not None else float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    if not (math.isfinite(rate) and rate > 0):
        cap.release()
        raise ReplayInputError(f"{path}: the video does not give its frame rate; pass --fps")
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)

    def frames() -> Iterator[ReplayFrame]:
        try:
            i = 0
            while True:
                ok, img = read_video_frame(cap)
                if not ok:
                    # A decoder failure and the end of the file look alike to OpenCV; past the
                    # announced length it is the end, before it the rest of the file is lost.
                    if count and i < count:
                        yield ReplayFrame(i, i / rate, None, None,
                                          f"{path}: frame {i} could not be decoded; "
                                          f"the remaining {count - i - 1} frame(s) are lost")
                    return
                yield ReplayFrame(i, i / rate, img, None,
                                  None if img is not None else f"{path}: frame {i} is not an image")
                i += 1
        finally:
            cap.release()

    return ReplaySource("video", path, frames(), total=count or None, fps=rate)


class RangefinderHeights:
    """A recording's downward rangefinder over time, from its DISTANCE_SENSOR telemetry lines:
    the height above the ground the live service had at any moment (``at``), by the service's
    own rule (``companion.mavlink.state``). A reading out of the sensor's range ends the last one,
    as it does live; a malformed line (no finite time, or a field missing or not an integer) is
    skipped and counted in ``malformed``, which the replay's summary reports."""

    def __init__(self, telemetry: Iterable[dict[str, Any]]) -> None:
        readings: list[tuple[float, float | None]] = []
        self.malformed = 0
        for e in telemetry:
            if e.get("msg") != "DISTANCE_SENSOR":
                continue
            t = e.get("t")
            fields = [v for v in (e.get(k) for k in ("orientation", "current_distance", "min_distance",
                                                      "max_distance")) if isinstance(v, int) and not isinstance(v, bool)]
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or len(fields) != 4:
                self.malformed += 1
                continue
            if fields[0] != DOWNWARD_ORIENTATION:
                continue  # another sensor's reading leaves the downward one as it was, as live
            readings.append((float(t), downward_range_m(*fields[1:])))
        readings.sort(key=lambda r: r[0])
        self._t = [r[0] for r in readings]
        self._m = [r[1] for r in readings]

    def at(self, t: float) -> float | None:
        """Metres above the ground at ``t`` (s, the recording's clock): the latest reading at or
        before ``t``, at most ``RANGEFINDER_MAX_AGE_S`` old and within range; else None."""
        i = bisect.bisect_right(self._t, t)
        if i == 0 or t - self._t[i - 1] > RANGEFINDER_MAX_AGE_S:
            return None
        return self._m[i - 1]


def open_recording(path: Path) -> ReplaySource:
    """A flight recording made by the service (``companion.recording``)."""
    if not path.exists():
        raise ReplayInputError(f"recording {path} does not exist")
    try:
        reader = RecordingReader(path)
    except RecordingError as exc:
        raise ReplayInputError(str(exc)) from None

    heights = RangefinderHeights(reader.events("telemetry"))

    def frames() -> Iterator[ReplayFrame]:
        for rec in reader.frames():
            img = as_bgr(rec.frame_bgr)
            problem = None if img is not None else f"{path}: recorded frame {rec.index} is not an image"
            yield ReplayFrame(int(rec.index), float(rec.t), img, rec.pose, problem, agl=heights.at(float(rec.t)))

    def upstream() -> dict[str, int]:
        st = reader.stats
        return {"recorded line unreadable": st.bad_lines,
                "recorded frame missing (segment deleted)": st.missing,
                "recorded frame lost (segment truncated)": st.truncated,
                "recorded frame corrupt (thumbnail mismatch)": st.corrupt}

    rate = reader.meta.get("fps")
    return ReplaySource("recording", path, frames(), total=len(reader),
                        fps=float(rate) if isinstance(rate, (int, float)) and rate > 0 else None,
                        intrinsics=reader.intrinsics, mount=reader.mount, meta=dict(reader.meta),
                        skipped_upstream=upstream,
                        telemetry_dropped={"DISTANCE_SENSOR line malformed": heights.malformed}
                        if heights.malformed else {})


def guess_kind(path: Path) -> str:
    """``frames`` for a folder of images, ``recording`` for another folder (recordings are
    folders), ``video`` for a file (OpenCV decides whether it can play it)."""
    if not path.exists():
        raise ReplayInputError(f"input {path} does not exist")
    if path.is_dir():
        return "frames" if image_files(path) else "recording"
    return "video"


def open_input(path: str | Path, kind: str = "auto", fps: float | None = None) -> ReplaySource:
    """Open ``path`` as ``kind`` (see :data:`KINDS`). Folder frames default to 10 fps."""
    path = Path(path)
    if kind not in KINDS:
        raise ReplayInputError(f"input kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "auto":
        kind = guess_kind(path)
        # A folder without images is more likely a mistake than a recording when the recorder
        # cannot read it; say so in the terms of a folder.
        if kind == "recording" and path.is_dir() and not (path / "meta.json").exists():
            try:
                return open_recording(path)
            except ReplayInputError:
                raise ReplayInputError(
                    f"frame folder {path} is empty: no image files ({', '.join(IMAGE_SUFFIXES)}) "
                    "and not a flight recording") from None
    if kind == "frames":
        return open_folder(path, 10.0 if fps is None else fps)
    if kind == "video":
        return open_video(path, fps)
    return open_recording(path)
