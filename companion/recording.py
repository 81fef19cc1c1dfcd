"""Flight recorder: frames as video segments plus JSON Lines of poses, telemetry and decisions.

One folder per run under the recorder's ``dir``::

    20261121T130000Z/
        meta.json             format version, intrinsics, mount, model, config, codec, start times
        frames-00000.jsonl    the frame index, one line per recorded frame: {"i", "t", "seg", "k", "pose"}
        events-00000.jsonl    telemetry, triggers, state changes, decisions: {"t", "kind", ...}
        seg_00000.avi         video segments (MJPG .avi or mp4v .mp4)

``i`` is the camera's frame index, ``t`` its capture time (monotonic seconds, the clock of the
vehicle state), ``seg``/``k`` the segment file and the frame's position in it, ``pose`` the vehicle
pose paired with the frame (world NED metres, radians) or null. A frame line is written only
after its image is in the segment, so every line points at a frame that was handed to the encoder.
The frame index and the events are each a stream of numbered *chunks*, read in number order.
Format 1 (recordings made before chunks) had one ``frames.jsonl`` and one ``events.jsonl``;
:class:`RecordingReader` reads both layouts.

Disk budget (``max_mb``, MiB): everything the recorder writes under ``dir``, every run, counts:
video, frame index, events and meta.json. Every file is written in pieces of ``piece`` =
``max_mb``/16 (at least 4 KiB, at most 64 MiB): a video segment ends after ``segment_s`` or when
its size on disk reaches a piece, a chunk when it reaches a piece. When a file is finished, the
oldest finished files (any kind, any run; a run left with only its meta.json is removed whole)
are deleted until the finished files fit in ``max_mb`` less the room of the files still to be
written (a video segment, a frame chunk, an events chunk; none once ``close()`` has finished
them): a piece each, and for the segment twice its writer's buffer too (the size on disk lags by
up to one buffer, and the rest reaches the disk when the segment ends): 8 KiB for MJPG, whose
JPEG bytes go straight to the file (``companion.avi``, ``AVI_BUFFER``), 256 KiB for OpenCV's
mp4v encoder (``ENCODER_BUFFER``). So the total never passes ``max_mb`` by more than the item
that completes a piece in each stream (one frame, one index line, one event line) and the
container index written when a segment ends -- the slack the tests allow. After ``close()`` the
total is within ``max_mb``. A frame whose segment or index chunk was deleted is skipped by the
reader.

Events are downsampled per kind and message type (``event_rates_hz``, default telemetry at
5 Hz): a token bucket on the events' own time ``t`` keeps at most that rate sustained, with
bursts of up to two seconds' worth (a burst of STATUSTEXT lines passes whole), and counts the
rest in ``stats.downsampled``. Trigger, phase, controller and zones events are never dropped.

Writing happens in one background thread behind a short queue: the service never waits for the
disk, and a frame that finds the queue full is counted in ``stats.dropped`` and not recorded.
Events are written by the caller (one ``write`` of a line). No write raises: a failure (ENOSPC
on a full disk, EIO, anything) is counted in ``stats.errors``, logged at most once per
10 s per kind of failure (:mod:`companion.logs`), a partly written line is cut off again, and
recording goes on with the next frame or event. ``close()`` never raises.
"""

from __future__ import annotations

import collections
import io
import json
import logging
import math
import os
import queue
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from companion.avi import AVI_BUFFER, MjpegAviWriter, encode_jpeg, is_jpeg, jpeg_frames
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.logs import RateLimitedLog

log = logging.getLogger(__name__)

FORMAT_VERSION = 2  # 2: frame index and events in numbered chunks; 1: frames.jsonl, events.jsonl
SUFFIX = {"MJPG": ".avi", "mp4v": ".mp4"}
#: JPEG quality of frames the recorder encodes itself (those that did not come as JPEGs): the
#: quality OpenCV's own MJPG writer used before ``companion.avi``.
JPEG_QUALITY = 95
THUMB = 8
# Grey levels an 8x8-grid block mean may move through lossy compression; a half-decoded frame moves
# whole blocks to flat grey, far more than this.
THUMB_TOLERANCE = 24.0
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


def _size_on_disk(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "__dataclass_fields__"):
        return asdict(o)
    return str(o)


def _dumps(obj: Any) -> str:
    def clean(v: Any) -> Any:  # JSON has no NaN/inf: write null rather than an unreadable file
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return json.dumps(clean(json.loads(json.dumps(obj, default=_json_default))), separators=(",", ":"))


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


class _Chunks:
    """One JSON Lines stream written as ``<stem>-00000.jsonl``, ``-00001``, ...: a chunk is
    finished once it holds ``piece`` bytes, and handed to ``finished(path, size)``. Unbuffered:
    one write per line, nothing held back to fail later in close(). A failed or short write
    raises OSError after cutting the chunk back to its last whole line."""

    def __init__(self, folder: Path, stem: str, piece: int,
                 finished: Callable[[Path, int], None]) -> None:
        self.folder, self.stem, self.piece, self._finished = folder, stem, piece, finished
        self._fh: io.FileIO | None = None
        self._path: Path | None = None
        self._size = 0
        self._no = 0
        self._closed = False
        self._lock = threading.Lock()

    def write(self, line: str) -> None:
        data = (line + "\n").encode("utf-8")
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.stem} stream is closed")
            fh = self._fh
            if fh is None:
                path = self.folder / f"{self.stem}-{self._no:05d}.jsonl"
                fh = self._fh = open(path, "ab", buffering=0)
                self._path, self._size = path, fh.tell()
                self._no += 1
            try:
                n = fh.write(data)
                if n != len(data):
                    raise OSError(f"short write to {self._path} ({n} of {len(data)} bytes): disk full?")
            except OSError:
                try:
                    os.ftruncate(fh.fileno(), self._size)  # no half line left behind
                except OSError:
                    pass
                raise
            self._size += len(data)
            if self._size >= self.piece:
                self._finish()

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Finish the open chunk; never raises."""
        with self._lock:
            self._closed = True
            self._finish()

    def _finish(self) -> None:
        fh, path, size = self._fh, self._path, self._size
        self._fh, self._path, self._size = None, None, 0
        if fh is None or path is None:
            return
        try:
            fh.close()
        except OSError as exc:
            log.warning("recorder: closing %s: %s", path, exc)
        self._finished(path, size)


class FlightRecorder:
    """Records one run into a new folder under ``root``.

    segment_s: seconds of capture time per video segment (shorter when a segment reaches a
    piece of the budget). max_mb: budget in MiB for everything recorded under ``root`` (see the
    module docstring). codec: ``MJPG`` (.avi) or ``mp4v`` (.mp4). fps: nominal frame rate
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
        per kind and ``msg`` field (see the module docstring). True when written; never raises."""
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


# ---- reading ------------------------------------------------------------------------------------

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

    ``path`` is the run folder (the one holding meta.json). Reads both layouts (see the module
    docstring). Raises RecordingError naming the file when meta.json is missing or corrupt, or a
    format 1 recording has no frames.jsonl. Deleted segments and chunks (the disk budget) and a
    truncated last segment are tolerated: their frames are skipped and counted in ``stats``.
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
                int(k["height"]), tuple(float(v) for v in k.get("dist", ())))
            m = self.meta.get("mount")
            self.mount: Mount | None = None if m is None else Mount(
                float(m["roll"]), float(m["pitch"]), float(m["yaw"]),
                cast("tuple[float, float, float]", tuple(float(v) for v in m["offset"])))
        except (KeyError, TypeError, ValueError) as exc:
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


__all__ = ["FlightRecorder", "RecordingReader", "RecordedFrame", "RecordingError", "RecorderStats",
           "pose_to_dict", "pose_from_dict", "stream_files"]
