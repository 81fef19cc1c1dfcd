"""The flight recorder's reading side, used by replay and the simulator's judge:
:class:`RecordingReader` gives a recording's meta.json, its frame index, its events and its frames
(paired with their poses) in recording order, from either layout, skipping and counting what the
disk budget deleted or a power cut left half-written."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from companion.avi import jpeg_frames
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.recording.layout import FORMAT_VERSION, RecordingError, _thumb_matches, pose_from_dict, stream_files

#: The package's one logger, named as the single module was, so that log lines and filters on
#: ``companion.recording`` read the same whichever part of the recorder speaks.
log = logging.getLogger("companion.recording")


@dataclass(frozen=True)
class RecordedFrame:
    """A frame read back: camera index, capture time (monotonic s), BGR image, pose or None."""

    index: int
    t: float
    frame_bgr: np.ndarray
    pose: Pose | None


@dataclass
class ReadStats:
    """What a pass over a recording skipped: bad_lines (unparsable JSON lines), missing
    (frames whose segment was deleted or is absent), truncated (frames listed past the end of a
    segment that could not be decoded), corrupt (frames that decoded but do not match the
    recorded thumbnail, e.g. the half-written last frame of a truncated segment)."""

    bad_lines: int = 0
    missing: int = 0
    truncated: int = 0
    corrupt: int = 0


def _read_stream(folder: Path, stem: str, stats: ReadStats) -> Iterator[dict[str, Any]]:
    """The lines of every file of a stream; a chunk deleted meanwhile (the budget, while the
    recording is still being written) is skipped."""
    for path in stream_files(folder, stem):
        try:
            yield from _read_jsonl(path, stats)
        except RecordingError:
            continue


def _read_jsonl(path: Path, stats: ReadStats) -> Iterator[dict[str, Any]]:
    try:
        fh = open(path, encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise RecordingError(f"{path} is missing: not a complete recording") from None
    with fh:
        for n, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                if not isinstance(row, dict):
                    raise ValueError("not an object")
            except ValueError:
                # A power cut leaves a half-written last line; skip it, and any other bad one.
                stats.bad_lines += 1
                log.warning("%s:%d: unreadable line skipped", path, n)
                continue
            yield row


class RecordingReader:
    """Reads a recording folder made by :class:`FlightRecorder`.

    ``path`` is the run folder (the one holding meta.json). Reads both layouts (see
    :mod:`companion.recording`). Raises RecordingError naming the file when meta.json is missing
    or corrupt, or a format 1 recording has no frames.jsonl. Deleted segments and chunks (the disk
    budget) and a truncated last segment are tolerated: their frames are skipped and counted in
    ``stats``.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(f"recording {self.path} does not exist or is not a folder")
        meta_path = self.path / "meta.json"
        if not meta_path.is_file():
            runs = sorted(p.name for p in self.path.iterdir() if (p / "meta.json").is_file())
            hint = f"; it holds the runs {', '.join(runs)}" if runs else ""
            raise RecordingError(f"{meta_path} is missing: not a recording folder{hint}")
        try:
            self.meta: dict[str, Any] = json.loads(meta_path.read_text())
        except (ValueError, OSError) as exc:
            raise RecordingError(f"{meta_path} is not valid JSON: {exc}") from None
        if not isinstance(self.meta, dict) or self.meta.get("format") != "companion-recording":
            raise RecordingError(f"{meta_path} is not a companion recording's meta.json")
        if int(self.meta.get("version", 0)) > FORMAT_VERSION:
            raise RecordingError(f"{meta_path}: format version {self.meta.get('version')} is newer than "
                                 f"this reader ({FORMAT_VERSION})")
        self.version = int(self.meta.get("version", 0))
        if self.version < 2 and not (self.path / "frames.jsonl").is_file():
            raise RecordingError(f"{self.path / 'frames.jsonl'} is missing: not a complete recording")
        try:
            k = self.meta.get("intrinsics")
            self.intrinsics: Intrinsics | None = None if k is None else Intrinsics(
                float(k["fx"]), float(k["fy"]), float(k["cx"]), float(k["cy"]), int(k["width"]),
                int(k["height"]), tuple(float(v) for v in k.get("dist", ())), str(k.get("model", "pinhole")))
            m = self.meta.get("mount")
            self.mount: Mount | None = None if m is None else Mount(
                float(m["roll"]), float(m["pitch"]), float(m["yaw"]),
                cast("tuple[float, float, float]", tuple(float(v) for v in m["offset"])))
        except (KeyError, TypeError, ValueError) as exc:  # GeometryError is a ValueError
            raise RecordingError(f"{meta_path}: bad intrinsics or mount: {exc}") from None
        self.stats = ReadStats()

    def rows(self) -> list[dict[str, Any]]:
        """The lines of the frame index (bad lines skipped)."""
        return list(_read_stream(self.path, "frames", self.stats))

    def __len__(self) -> int:
        return len(self.rows())

    def events(self, kind: str | None = None) -> Iterator[dict[str, Any]]:
        """The events lines in order (either layout), optionally only one ``kind``."""
        for row in _read_stream(self.path, "events", self.stats):
            if kind is None or row.get("kind") == kind:
                yield row

    def frames(self) -> Iterator[RecordedFrame]:
        """Every readable frame in recording order, paired with its recorded pose."""
        self.stats = ReadStats()
        cap: _JpegSegment | cv2.VideoCapture | None = None
        seg: str | None = None
        pos = 0  # next frame position in the open segment
        dead = False  # the open segment is missing or ended early: skip its remaining rows
        truncated = False
        try:
            for row in _read_stream(self.path, "frames", self.stats):
                try:
                    name, k = str(row["seg"]), int(row["k"])
                    index, t = int(row["i"]), float(row["t"])
                    pose = pose_from_dict(row.get("pose"))
                except (KeyError, TypeError, ValueError):
                    self.stats.bad_lines += 1
                    continue
                if name != seg:
                    if cap is not None:
                        cap.release()
                    cap, seg, pos, dead, truncated = None, name, 0, False, False
                    seg_path = self.path / name
                    if "/" in name or "\\" in name or not seg_path.is_file():
                        dead = True
                        log.warning("%s: segment %s is missing (deleted to save space?); its frames "
                                    "are skipped", self.path, name)
                    else:
                        cap = _segment_reader(seg_path)
                        if not cap.isOpened():
                            dead = True
                            log.warning("%s: segment %s cannot be opened; its frames are skipped",
                                        self.path, name)
                if dead or cap is None:
                    if truncated:
                        self.stats.truncated += 1
                    else:
                        self.stats.missing += 1
                    continue
                image = None
                ended = False
                while pos <= k:
                    ok, img = cap.read()
                    if not ok:
                        ended = True
                        break
                    pos += 1
                    if pos - 1 == k:
                        image = img
                if image is None and not ended:
                    self.stats.corrupt += 1  # a whole JPEG that does not decode
                    log.warning("%s: frame %d in %s cannot be decoded; skipped", self.path, index, name)
                    continue
                if image is None:
                    dead = truncated = True
                    self.stats.truncated += 1
                    log.warning("%s: segment %s ends before frame %d (truncated); the rest of it "
                                "is skipped", self.path, name, k)
                    continue
                if not _thumb_matches(image, row.get("thumb")):
                    self.stats.corrupt += 1
                    log.warning("%s: frame %d in %s does not match its thumbnail (half-written?); "
                                "skipped", self.path, index, name)
                    continue
                yield RecordedFrame(index, t, image, pose)
        finally:
            if cap is not None:
                cap.release()


class _JpegSegment:
    """A Motion-JPEG AVI segment read like a ``cv2.VideoCapture``, its frames' JPEG bytes
    decoded by ``cv2.imdecode`` (``companion.avi.jpeg_frames``): the pixels the service decoded
    from an MJPEG camera, where FFmpeg's decoder would differ slightly. ``read`` gives (True,
    None) for a whole chunk that does not decode, (False, None) at the end."""

    def __init__(self, frames: Iterator[bytes], first: bytes | None) -> None:
        self._frames = frames
        self._next = first

    def isOpened(self) -> bool:  # noqa: N802 (cv2.VideoCapture's name)
        return True

    def read(self) -> tuple[bool, np.ndarray | None]:
        data, self._next = self._next, None
        if data is None:
            try:
                data = next(self._frames)
            except (StopIteration, OSError):
                return False, None
        return True, cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def release(self) -> None:
        close = getattr(self._frames, "close", None)
        if close is not None:
            close()


def _segment_reader(path: Path) -> _JpegSegment | cv2.VideoCapture:
    """A segment to read frame by frame: MJPG AVIs by their JPEG bytes, anything else (mp4v,
    an AVI of another codec) through OpenCV."""
    if path.suffix.lower() == ".avi":
        frames = jpeg_frames(path)
        try:
            return _JpegSegment(frames, next(frames))
        except StopIteration:
            return _JpegSegment(iter(()), None)  # no whole frame: every row reads as truncated
        except (ValueError, OSError):
            pass
    return cv2.VideoCapture(str(path))

