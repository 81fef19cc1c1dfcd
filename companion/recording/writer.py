"""The flight recorder's writing side: :class:`FlightRecorder` queues frames for a background thread
that writes the video segments and the frame index, writes event lines (downsampled per kind), and
keeps everything recorded under its folder within the disk budget by deleting the oldest finished
files (see :mod:`companion.recording` for the budget's rules)."""

from __future__ import annotations

import collections
import json
import logging
import math
import queue
import re
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.avi import AVI_BUFFER, MjpegAviWriter, encode_jpeg, is_jpeg
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.logs import RateLimitedLog
from companion.recording.chunks import _Chunks, _dumps, _json_default
from companion.recording.layout import FORMAT_VERSION, SUFFIX, pose_to_dict, thumbnail

#: The package's one logger, named as the single module was, so that log lines and filters on
#: ``companion.recording`` read the same whichever part of the recorder speaks.
log = logging.getLogger("companion.recording")

#: JPEG quality of frames the recorder encodes itself (those that did not come as JPEGs): the
#: quality OpenCV's own MJPG writer used before ``companion.avi``.
JPEG_QUALITY = 95
MiB = 1024 * 1024
PIECE_MIN = 4096
PIECE_MAX = 64 * MiB
#: Bytes the video encoder holds before they reach the disk (OpenCV's FFmpeg backend: 256 KiB,
#: measured), so a segment's size on disk lags what it will be by up to this much.
ENCODER_BUFFER = 256 * 1024
#: Default event downsampling: events per second per (kind, message type), sustained.
DEFAULT_EVENT_RATES_HZ: Mapping[str, float] = {"telemetry": 5.0}
#: Kinds that are never downsampled: what the flight's judge and an investigation rely on.
NEVER_DOWNSAMPLED = frozenset({"trigger", "phase", "controller", "zones"})
BURST_S = 2.0  # a downsampled stream may burst this many seconds' worth of events
LOG_EVERY_S = 10.0  # at most one log line per kind of write failure per this many seconds

_RECORDED = re.compile(r"seg_\d+\.(avi|mp4)|(frames|events)(-\d+)?\.jsonl")


def _size_on_disk(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


@dataclass
class RecorderStats:
    """frames: written; dropped: not recorded because the writer was behind; segments: opened;
    deleted: files (segments, chunks, emptied runs' meta.json) removed to stay within max_mb;
    errors: write failures (frames and events; ENOSPC and the like), each not recorded;
    events: event lines written; downsampled: events not written by the rate limit;
    jpeg_as_sent: frames (of ``frames``) stored as the camera's own JPEG bytes, not encoded again
    (MJPG segments of an MJPEG camera's frames)."""

    frames: int = 0
    dropped: int = 0
    segments: int = 0
    deleted: int = 0
    errors: int = 0
    events: int = 0
    downsampled: int = 0
    jpeg_as_sent: int = 0


@dataclass
class _Item:
    index: int
    t: float
    image: np.ndarray
    pose: Pose | None
    jpeg: bytes | None = None


class FlightRecorder:
    """Records one run into a new folder under ``root``.

    segment_s: seconds of capture time per video segment (shorter when a segment reaches a
    piece of the budget). max_mb: budget in MiB for everything recorded under ``root`` (see
    :mod:`companion.recording`). codec: ``MJPG`` (.avi) or ``mp4v`` (.mp4). fps: nominal frame rate
    written in the container (timing truth is ``t`` in the frame index). meta: extra fields for
    meta.json (config, model); intrinsics and mount are stored so replay can rebuild geometry.
    event_rates_hz: events per second kept per kind and message type (None: the default,
    telemetry at 5 Hz; ``{}``: keep every event); kinds in NEVER_DOWNSAMPLED are refused.
    """

    def __init__(self, root: str | Path, *, segment_s: float = 60.0, max_mb: float = 2048.0,
                 codec: str = "MJPG", fps: float = 10.0, intrinsics: Intrinsics | None = None,
                 mount: Mount | None = None, meta: dict[str, Any] | None = None,
                 queue_size: int = 8, event_rates_hz: Mapping[str, float] | None = None) -> None:
        if codec not in SUFFIX:
            raise ValueError(f"recorder codec must be one of {', '.join(SUFFIX)}, got {codec!r}")
        rates = dict(DEFAULT_EVENT_RATES_HZ if event_rates_hz is None else event_rates_hz)
        for kind, hz in rates.items():
            if kind in NEVER_DOWNSAMPLED:
                raise ValueError(f"recorder: {kind!r} events are never downsampled")
            if not (math.isfinite(hz) and hz > 0):
                raise ValueError(f"recorder: event rate for {kind!r} must be > 0 Hz, got {hz!r}")
        self.root = Path(root)
        self.segment_s = float(segment_s)
        self.max_bytes = int(max_mb * MiB)
        self.piece_bytes = max(PIECE_MIN, min(self.max_bytes // 16, PIECE_MAX))
        self.codec = codec
        self.fps = float(fps) if fps > 0 else 10.0
        self.event_rates_hz = rates
        self.stats = RecorderStats()
        self._meta = {
            "format": "companion-recording",
            "version": FORMAT_VERSION,
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "monotonic_at_start": time.monotonic(),
            "codec": codec,
            "segment_s": self.segment_s,
            "fps": self.fps,
            "intrinsics": None if intrinsics is None else asdict(intrinsics),
            "mount": None if mount is None else asdict(mount),
            **(meta or {}),
        }
        self._queue: queue.Queue[_Item | None] = queue.Queue(maxsize=queue_size)
        self._events_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.path: Path | None = None
        self._writer: cv2.VideoWriter | MjpegAviWriter | None = None
        self._seg_name: str | None = None
        self._seg_start_t = 0.0
        self._seg_k = 0
        self._seg_size: tuple[int, int] | None = None
        self._seg_no = 0
        self._frames: _Chunks | None = None
        self._events: _Chunks | None = None
        self._buckets: dict[tuple[str, Any], tuple[float, float]] = {}  # key -> (tokens, last t)
        self._rl = RateLimitedLog(log, LOG_EVERY_S)
        # The budget's inventory: finished files oldest first (deleted in that order), and what
        # stays: every run's meta.json (keyed by its run folder), files that could not be deleted.
        self._disk_lock = threading.RLock()
        self._finished: collections.deque[tuple[Path, int]] = collections.deque()
        self._finished_bytes = 0
        self._kept: dict[Path, int] = {}
        self._video_done = False  # the writer thread has finished its last segment

    def start(self) -> Path:
        """Make room within the budget, create the run folder, write meta.json and start the
        writer thread. Raises OSError (naming the folder) when the folder cannot be created or
        written."""
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        self.root.mkdir(parents=True, exist_ok=True)
        self._scan()
        self._enforce_budget()
        path = self.root / stamp
        n = 1
        while path.exists():
            path = self.root / f"{stamp}-{n}"
            n += 1
        path.mkdir()
        self.path = path
        meta = json.dumps(self._meta, indent=2, default=_json_default)
        (path / "meta.json").write_text(meta)
        with self._disk_lock:
            self._kept[path] = len(meta.encode("utf-8"))
        self._frames = _Chunks(path, "frames", self.piece_bytes, self._file_finished)
        self._events = _Chunks(path, "events", self.piece_bytes, self._file_finished)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        log.info("recording to %s (budget %.0f MiB, pieces of %.2f MiB)", path, self.max_bytes / MiB,
                 self.piece_bytes / MiB)
        return path

    # ---- producer side (event loop) ----------------------------------------------------------
    def add_frame(self, index: int, t: float, image: np.ndarray, pose: Pose | None,
                  jpeg: bytes | None = None) -> bool:
        """Queue a frame (BGR uint8) with its capture time and pose; False when dropped.
        jpeg: the bytes ``image`` was decoded from, when it came as a JPEG: MJPG segments store
        them as they are (no second encoding; they must decode to ``image``)."""
        if self._thread is None:
            return False
        try:
            self._queue.put_nowait(_Item(index, t, image, pose, jpeg))
            return True
        except queue.Full:
            self.stats.dropped += 1
            return False

    def add_event(self, kind: str, t: float, **data: Any) -> bool:
        """One events line: ``kind`` (telemetry, trigger, state, decision, ...) at ``t`` monotonic
        seconds, plus any JSON-able fields (dataclasses and arrays are converted). Downsampled
        per kind and ``msg`` field (see :mod:`companion.recording`). True when written; never raises."""
        if self._events is None or self._events.closed:
            return False
        try:
            if kind in self.event_rates_hz and not self._take_token(kind, data.get("msg"), t):
                self.stats.downsampled += 1
                return False
            line = _dumps({"t": t, "kind": kind, **data})
            with self._events_lock:
                self._events.write(line)
            self.stats.events += 1
            return True
        except Exception as exc:  # OSError (disk full), a closed stream, anything: never raise
            self.stats.errors += 1
            self._rl.warning("event", "recorder: cannot write event (%d write errors so far): %s",
                             self.stats.errors, exc)
            return False

    def _take_token(self, kind: str, msg: Any, t: float) -> bool:
        rate = self.event_rates_hz[kind]
        burst = max(1.0, rate * BURST_S)
        key = (kind, msg if isinstance(msg, (str, int, type(None))) else str(msg))
        tokens, last = self._buckets.get(key, (burst, t))
        dt = t - last
        if dt > 0:  # false for NaN or a clock that went back: no refill
            tokens = min(burst, tokens + dt * rate)
            last = t
        if tokens < 1.0:
            self._buckets[key] = (tokens, last)
            return False
        self._buckets[key] = (tokens - 1.0, last)
        return True

    def close(self, timeout: float = 5.0) -> None:
        """Flush queued frames, close the segment and files. Never raises: a failure (a full disk,
        a stuck writer) is logged and the rest is still closed."""
        try:
            if self._thread is not None:
                try:
                    self._queue.put(None, timeout=timeout)
                except queue.Full:
                    pass
                self._thread.join(timeout)
                if self._thread.is_alive():
                    log.warning("recorder: writer still busy after %.1f s; its segment is left open", timeout)
                self._thread = None
            with self._events_lock:
                for stream in (self._frames, self._events):
                    if stream is not None:
                        stream.close()
            self._rl.flush()
        except Exception as exc:
            log.error("recorder: close: %r", exc)

    # ---- writer thread -----------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                break
            try:
                self._write(item)
            except Exception as exc:  # the recorder must never take the service down
                self.stats.errors += 1
                self._rl.warning("frame", "recorder: frame %d not recorded (%d write errors so far): %s",
                                 item.index, self.stats.errors, exc)
        self._video_done = True  # no more video: no more room kept for it
        try:
            self._close_segment()
        except Exception as exc:
            log.warning("recorder: closing the last segment: %r", exc)

    def _write(self, item: _Item) -> None:
        img = item.image
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"not a BGR uint8 frame: shape {img.shape}, {img.dtype}")
        size = (img.shape[1], img.shape[0])
        if (self._writer is None or size != self._seg_size
                or item.t - self._seg_start_t >= self.segment_s):
            self._open_segment(size, item.t)
        assert self._writer is not None and self.path is not None and self._frames is not None
        if isinstance(self._writer, MjpegAviWriter):
            sent = item.jpeg if item.jpeg is not None and is_jpeg(item.jpeg) else None
            try:
                self._writer.write(sent if sent is not None else encode_jpeg(img, JPEG_QUALITY))
            except OSError:
                # A part of the chunk may be on disk: end the segment here (its index lists the
                # whole frames) and start the next frame in a new one.
                self._close_segment()
                raise
            self.stats.jpeg_as_sent += sent is not None
        else:
            self._writer.write(img)
        k = self._seg_k
        self._seg_k += 1  # the image is in the segment even if its index line fails below
        try:
            self._frames.write(_dumps({"i": item.index, "t": item.t, "seg": self._seg_name, "k": k,
                                       "pose": pose_to_dict(item.pose), "thumb": thumbnail(img)}))
            self.stats.frames += 1
        finally:
            if _size_on_disk(self.path / str(self._seg_name)) >= self.piece_bytes:
                self._close_segment()

    def _open_segment(self, size: tuple[int, int], t: float) -> None:
        self._close_segment()
        assert self.path is not None
        name = f"seg_{self._seg_no:05d}{SUFFIX[self.codec]}"
        self._seg_no += 1
        writer: cv2.VideoWriter | MjpegAviWriter
        if self.codec == "MJPG":
            # JPEG bytes into the file (``companion.avi``): the camera's own where it sent JPEGs.
            writer = MjpegAviWriter(self.path / name, size, self.fps)
        else:
            fourcc = cv2.VideoWriter_fourcc(*self.codec)  # type: ignore[attr-defined]  # missing from the cv2 stubs
            writer = cv2.VideoWriter(str(self.path / name), fourcc, self.fps, size)
            if not writer.isOpened():
                raise OSError(f"cannot open video segment {self.path / name} ({self.codec})")
        self._writer, self._seg_name, self._seg_size, self._seg_start_t, self._seg_k = writer, name, size, t, 0
        self.stats.segments += 1

    def _close_segment(self) -> None:
        writer, self._writer = self._writer, None
        if writer is None or self.path is None:
            return
        if isinstance(writer, MjpegAviWriter):
            writer.close()
        else:
            writer.release()
        seg = self.path / str(self._seg_name)
        try:
            size = seg.stat().st_size
        except OSError:
            return
        self._file_finished(seg, size)

    # ---- the disk budget ---------------------------------------------------------------------
    def _scan(self) -> None:
        """Inventory of what earlier runs left under root: their files oldest first."""
        found: list[tuple[float, str, Path, int]] = []
        metas: dict[Path, int] = {}  # run folder -> its meta.json's size
        try:
            runs = [p for p in self.root.iterdir() if p.is_dir()]
        except OSError as exc:
            log.warning("recorder: cannot list %s: %s", self.root, exc)
            return
        for run in runs:
            try:
                for p in run.iterdir():
                    if p.name == "meta.json":
                        metas[run] = p.stat().st_size
                    elif _RECORDED.fullmatch(p.name):
                        st = p.stat()
                        found.append((st.st_mtime, str(p), p, st.st_size))
            except OSError:
                continue  # raced with a deletion, or unreadable: not ours to count
        with self._disk_lock:
            self._kept.update(metas)
            for *_, p, size in sorted(found):
                self._finished.append((p, size))
                self._finished_bytes += size

    def _file_finished(self, path: Path, size: int) -> None:
        with self._disk_lock:
            self._finished.append((path, size))
            self._finished_bytes += size
        self._enforce_budget()

    def _enforce_budget(self) -> None:
        """Delete the oldest finished files (all runs) until they, with every meta.json, fit in
        max_bytes less the room of the files still being written."""
        with self._disk_lock:
            buffer = AVI_BUFFER if self.codec == "MJPG" else ENCODER_BUFFER
            room = 0 if self._video_done else self.piece_bytes + 2 * buffer
            room += sum(self.piece_bytes for c in (self._frames, self._events) if c is None or not c.closed)
            limit = max(0, self.max_bytes - room)
            while self._finished and self._finished_bytes + sum(self._kept.values()) > limit:
                p, size = self._finished.popleft()
                self._finished_bytes -= size
                try:
                    p.unlink()
                except FileNotFoundError:
                    continue
                except OSError as exc:
                    self._kept[p] = size  # stays on disk: counted, never retried
                    self._rl.warning("delete", "recorder: cannot delete %s: %s", p, exc)
                    continue
                self.stats.deleted += 1
                self._rl.info("deleted", "recorder: deleted %s to stay within %.1f MiB", p, self.max_bytes / MiB)
                self._remove_if_emptied(p.parent)

    def _remove_if_emptied(self, run: Path) -> None:
        """A finished run left with nothing but its meta.json goes whole."""
        if run == self.path or run not in self._kept:
            return
        try:
            if {p.name for p in run.iterdir()} != {"meta.json"}:
                return
            (run / "meta.json").unlink()
            run.rmdir()
        except OSError:
            return
        del self._kept[run]
        self.stats.deleted += 1
