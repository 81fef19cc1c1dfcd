"""The replay loop: frames from a source through the pipeline into the requested outputs.

Outputs are optional and independent: JSON Lines (one record per processed frame), occupancy masks
(PNG per frame, 255 = occupied), the annotated video. Frames that cannot be read or processed are
counted and skipped; the summary says how many and why.
"""

from __future__ import annotations

import itertools
import json
import logging
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from companion.control.planner import PlannerConfig, ZonePlanner
from companion.control.touchdown import DescentProfile, touchdown_basis
from companion.geometry.camera import GeometryError
from companion.pipeline.density import DensityModelError
from companion.pipeline.slz import FrameResult, SLZPipeline
from companion.pipeline.tracker import Track
from companion.replay import draw, h264
from companion.replay.records import frame_record, frame_target
from companion.replay.sources import ReplayFrame, ReplaySource
from companion.replay.summary import SummaryBuilder

log = logging.getLogger(__name__)

SKIP_UNREADABLE = "unreadable frame"
SKIP_MODEL = "the density model rejected the frame"
SKIP_GEOMETRY = "no valid head-plane projection for the frame"


class ReplayOutputError(ValueError):
    """An output that cannot be written (folder not creatable, video codec missing)."""


def mask_name(index: int) -> str:
    """File name of frame ``index``'s occupancy mask."""
    return f"{index:06d}.png"


def occupied_mask_image(occupancy_free: np.ndarray) -> np.ndarray:
    """The mask written by ``--masks``: 255 where occupied (people), 0 where free; the inverse of
    the pipeline's free map."""
    return cv2.bitwise_not(occupancy_free)


def dumps_record(record: dict[str, Any]) -> str:
    # allow_nan=False turns any NaN that slipped past the record builder into an error here
    # rather than invalid JSON in the file.
    return json.dumps(record, allow_nan=False, separators=(",", ":"))


class VideoOut:
    """An annotated video file; the first frame fixes the size, later frames are fitted to it.

    ``.mp4`` is H.264 through PyAV (``companion.replay.h264``: browsers play it) when the tools
    extra is installed, else OpenCV's MPEG-4 Part 2 (said once in the log: browsers do not play
    it); ``.avi`` is OpenCV's Motion JPEG."""

    def __init__(self, path: Path, fps: float):
        self.path = path
        self.fps = fps
        self._writer: cv2.VideoWriter | None = None
        self._h264: h264.H264Writer | None = None
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def _open(self, w: int, h: int) -> None:
        # Codecs want even sizes.
        self._size = (w + (w & 1), h + (h & 1))
        if self.path.suffix.lower() == ".mp4" and h264.available():
            try:
                self._h264 = h264.H264Writer(self.path, self.fps)
            except (OSError, ValueError) as exc:  # PyAV's errors are OSErrors and ValueErrors
                raise ReplayOutputError(f"cannot write the video {self.path}: {exc}") from None
            return
        if self.path.suffix.lower() == ".mp4":
            log.warning("PyAV (the tools extra) is not installed: %s is MPEG-4 Part 2, which browsers do not "
                        "play; pip install 'companion-slz[tools]' for H.264", self.path)
        codec = "MJPG" if self.path.suffix.lower() == ".avi" else "mp4v"
        fourcc = cv2.VideoWriter_fourcc(*codec)  # type: ignore[attr-defined]  # missing from the cv2 stubs
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = cv2.VideoWriter(str(self.path), fourcc, self.fps, self._size)
        if not self._writer.isOpened():
            raise ReplayOutputError(f"cannot write the video {self.path} (no encoder for "
                                    f"{self.path.suffix or 'this file type'}; try .mp4 or .avi)")

    def write(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        if self._size is None:
            self._open(w, h)
        assert self._size is not None
        if (w, h) != self._size:
            image = cv2.resize(image, self._size, interpolation=cv2.INTER_AREA)
        if self._h264 is not None:
            self._h264.write(image)
        elif self._writer is not None:
            self._writer.write(image)
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._h264 is not None:
            self._h264.close()
            self._h264 = None


@dataclass
class ReplayOutputs:
    """Where results go; each is optional."""

    jsonl: IO[str] | None = None
    masks: Path | None = None
    video: VideoOut | None = None


def _process(pipe: SLZPipeline, frame: ReplayFrame, use_pose: bool
             ) -> tuple[FrameResult | None, str | None, str]:
    """The frame's result, or (None, skip reason, why)."""
    assert frame.image is not None
    try:
        return pipe.process(frame.image, frame.t, frame.pose if use_pose else None), None, ""
    except GeometryError as exc:
        return None, SKIP_GEOMETRY, str(exc)
    except DensityModelError as exc:
        return None, SKIP_MODEL, str(exc)


#: Skipped frames logged one by one per reason; the rest are only counted (a recording that ends
#: on the ground would otherwise log every grounded frame).
LOGGED_SKIPS = 5
#: Skips every recording of a flight has, said once at INFO and counted, not warned about (what
#: the pipeline says of the frame -> why it is expected): frames from below the head plane (the
#: vehicle on the ground, before its take-off or after its landing), frames from about the head
#: plane's height (the last metres before touchdown: the plane then passes through the camera, or
#: within millimetres of it, so the recorded pose gives a homography that cannot be inverted; a
#: user's fixed homography is checked at start-up instead, so per frame this comes from poses
#: alone) and frames recorded before the first pose arrived (the service did not use them either).
EXPECTED_SKIPS = {"not above the head plane": "on the ground",
                  "homography is not invertible": "camera at about head-plane height (take-off, or the last metres "
                                                  "before touchdown): the head plane passes through it",
                  "no pose and no fixed projection": "recorded without a pose: the flight did not use it either"}


def _log_skip(counts: dict[str, int], reason: str, index: int, why: str) -> None:
    for words, expected in EXPECTED_SKIPS.items():
        if words in why:
            counts[expected] = counts.get(expected, 0) + 1
            if counts[expected] == 1:
                log.info("frame %d skipped: %s (%s); such frames are counted in the summary only", index, why, expected)
            return
    counts[reason] = counts.get(reason, 0) + 1
    if counts[reason] <= LOGGED_SKIPS:
        log.warning("frame %d skipped: %s", index, why)
        if counts[reason] == LOGGED_SKIPS:
            log.warning("further frames skipped for the same reason are counted in the summary only")


class _NoBar:
    """Stands in for a tqdm bar when no progress is shown."""

    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _progress_bar(total: int | None, progress: bool, desc: str) -> Any:
    """A tqdm bar on stderr when ``progress``; tqdm (the tools extra) is imported only then, so a
    replay without progress runs where only the daemon's dependencies are installed (the image)."""
    if not progress:
        return _NoBar()
    from tqdm import tqdm
    return tqdm(total=total, unit="frame", file=sys.stderr, desc=desc)


def replay(source: ReplaySource, pipe: SLZPipeline, outputs: ReplayOutputs, use_pose: bool,
           max_frames: int | None = None, progress: bool | None = None,
           on_result: Callable[[ReplayFrame, FrameResult], None] | None = None,
           planner: ZonePlanner | None = None, descent: DescentProfile | None = None,
           land_agl_m: float = 0.0,
           flight_zones: Mapping[int, tuple[list[Track], int | None]] | None = None) -> dict[str, Any]:
    """Run ``pipe`` over ``source``; returns the summary (see summary.SummaryBuilder.build).

    descent: the time to touchdown from a frame's height, for each track's ``clearance_m`` in the
    JSONL (frames with a pose only); default ``DescentProfile()``. land_agl_m: the flight's
    ``controller.land_agl_m``: where a recording's downward rangefinder was fresh at a frame
    (``ReplayFrame.agl``), the height is the rangefinder's and the descent goes on down to it
    before the LAND, as the live controller figured it (``touchdown_basis``).

    planner: picks the target of each frame (the JSONL ``target``, the video's highlighted zone,
    the summary's switches) by the landing controller's rule; default: the default settings with
    the pipeline's ``r0_m``.
    use_pose: project with each frame's recorded pose (else the pipeline's fixed projection).
    flight_zones: what the flight decided, by frame index (``records.flight_zones`` of its
    recording): the video draws these zones and target over the replay's maps instead of the
    replay's own, so its ids and target are the flight's; the summary's ``flight_zones`` counts
    the frames whose replayed zone ids differ from the flight's.
    progress: show a tqdm bar; default only when stderr is a terminal.
    """
    if progress is None:
        progress = sys.stderr.isatty()
    if planner is None:
        planner = ZonePlanner(PlannerConfig(r0_m=pipe.config.r0_m))
    total = source.total if max_frames is None else min(source.total or max_frames, max_frames)
    summary = SummaryBuilder()
    skip_logs: dict[str, int] = {}
    compared = {"frames": 0, "ids_differ": 0}
    if outputs.masks is not None:
        outputs.masks.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    bar = _progress_bar(total, progress, f"replay {source.path.name}")
    try:
        for frame in itertools.islice(source.frames, max_frames):
            bar.update(1)
            if frame.image is None:
                _log_skip(skip_logs, SKIP_UNREADABLE, frame.index, str(frame.problem))
                summary.add_skip(SKIP_UNREADABLE)
                continue
            result, skip, why = _process(pipe, frame, use_pose)
            if result is None:
                _log_skip(skip_logs, skip or "unknown", frame.index, why)
                summary.add_skip(skip or "unknown")
                continue
            target = frame_target(result, planner)
            target_id = None if target is None else target.id
            summary.add_frame(frame.t, result.timings_ms, target_id)
            posed = use_pose and frame.pose is not None
            height, profile = touchdown_basis(-frame.pose.down if posed and frame.pose is not None else None,
                                              frame.agl if posed else None, descent or DescentProfile(), land_agl_m)
            if outputs.jsonl is not None:
                outputs.jsonl.write(dumps_record(frame_record(frame.index, result, planner, height, profile)) + "\n")
            if outputs.masks is not None:
                path = outputs.masks / mask_name(frame.index)
                if not cv2.imwrite(str(path), occupied_mask_image(result.occupancy)):
                    raise ReplayOutputError(f"cannot write the mask {path}")
            shown, shown_target = result.tracks, target_id
            if flight_zones is not None:
                shown, shown_target = flight_zones.get(frame.index, ([], None))
                compared["frames"] += 1
                if sorted(t.id for t in shown) != sorted(t.id for t in result.tracks):
                    compared["ids_differ"] += 1
            if outputs.video is not None:
                clearances = None if height is None else draw.touchdown_clearances(shown, profile, height)
                outputs.video.write(draw.figure(
                    frame.image, result.occupancy, result.projection, result.proposals,
                    shown, shown_target,
                    result.free_grid if posed else None, result.grid if posed else None,
                    result.surface, result.people_free, clearances, result.looked_at))
            if on_result is not None:
                on_result(frame, result)
        if source.skipped_upstream is not None:
            for reason, count in source.skipped_upstream().items():
                for _ in range(count):
                    summary.add_skip(reason)
        summary.telemetry_dropped.update(source.telemetry_dropped)
    finally:
        bar.close()
        close = getattr(source.frames, "close", None)
        if close is not None:
            close()  # releases a video capture left open by --max-frames or an error
        if outputs.video is not None:
            outputs.video.close()
    wall = time.perf_counter() - start
    built = summary.build(wall, pipe.tracker.born, pipe.tracker.ended)
    if flight_zones is not None:
        built["flight_zones"] = compared
    return built
