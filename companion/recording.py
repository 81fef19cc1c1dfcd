"""Flight recorder: frames as video segments plus JSON Lines of poses, telemetry and decisions.

One folder per run under the recorder's ``dir``::

    20261121T130000Z/
        meta.json        format version, intrinsics, mount, model, config, codec, start times
        frames.jsonl     one line per recorded frame: {"i", "t", "seg", "k", "pose"}
        events.jsonl     telemetry, triggers, state changes, decisions: {"t", "kind", ...}
        seg_00000.avi    video segments of ``segment_s`` seconds (MJPG .avi or mp4v .mp4)

``i`` is the camera's frame index, ``t`` its capture time (monotonic seconds, the clock of the
vehicle state), ``seg``/``k`` the segment file and the frame's position in it, ``pose`` the vehicle
pose paired with the frame (world NED metres, radians) or null. A frame line is written only
after its image is in the segment, so every line points at a frame that was handed to the encoder.

Disk use is bounded: when all segments under ``dir`` (every run) pass ``max_mb``, the oldest
segments are deleted first; their frame lines stay and :class:`RecordingReader` skips them.

Writing happens in one background thread behind a short queue: the service never waits for the
disk, and a frame that finds the queue full is counted in ``stats.dropped`` and not recorded.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from companion.geometry.camera import Intrinsics, Mount, Pose

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
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
    deleted: segments removed to stay under max_mb; errors: write failures."""

    frames: int = 0
    dropped: int = 0
    segments: int = 0
    deleted: int = 0
    errors: int = 0


@dataclass
class _Item:
    index: int
    t: float
    image: np.ndarray
    pose: Pose | None


class FlightRecorder:
    """Records one run into a new folder under ``root``.

    segment_s: seconds of capture time per video segment. max_mb: budget in MiB for all
    segments under ``root``. codec: ``MJPG`` (.avi) or ``mp4v`` (.mp4). fps: nominal frame rate
    written in the container (timing truth is ``t`` in frames.jsonl). meta: extra fields for
    meta.json (config, model); intrinsics and mount are stored so replay can rebuild geometry.
    """

    def __init__(self, root: str | Path, *, segment_s: float = 60.0, max_mb: float = 2048.0,
                 codec: str = "MJPG", fps: float = 10.0, intrinsics: Intrinsics | None = None,
                 mount: Mount | None = None, meta: dict[str, Any] | None = None,
                 queue_size: int = 8) -> None:
        if codec not in SUFFIX:
            raise ValueError(f"recorder codec must be one of {', '.join(SUFFIX)}, got {codec!r}")
        self.root = Path(root)
        self.segment_s = float(segment_s)
        self.max_bytes = int(max_mb * 1024 * 1024)
        self.codec = codec
        self.fps = float(fps) if fps > 0 else 10.0
        self.stats = RecorderStats()
        self._meta = {
            "format": "companion-recording",
            "version": FORMAT_VERSION,
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
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
        self._writer: cv2.VideoWriter | None = None
        self._seg_name: str | None = None
        self._seg_start_t = 0.0
        self._seg_k = 0
        self._seg_size: tuple[int, int] | None = None
        self._seg_no = 0
        self._frames_fh: Any = None
        self._events_fh: Any = None

    def start(self) -> Path:
        """Create the run folder, write meta.json and start the writer thread. Raises OSError
        (naming the folder) when the folder cannot be created or written."""
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / stamp
        n = 1
        while path.exists():
            path = self.root / f"{stamp}-{n}"
            n += 1
        path.mkdir()
        self.path = path
        (path / "meta.json").write_text(json.dumps(self._meta, indent=2, default=_json_default))
        self._frames_fh = open(path / "frames.jsonl", "a", buffering=1)
        self._events_fh = open(path / "events.jsonl", "a", buffering=1)
        self._enforce_budget()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        log.info("recording to %s", path)
        return path

    # ---- producer side (event loop) ----------------------------------------------------------
    def add_frame(self, index: int, t: float, image: np.ndarray, pose: Pose | None) -> bool:
        """Queue a frame (BGR uint8) with its capture time and pose; False when dropped."""
        if self._thread is None:
            return False
        try:
            self._queue.put_nowait(_Item(index, t, image, pose))
            return True
        except queue.Full:
            self.stats.dropped += 1
            return False

    def add_event(self, kind: str, t: float, **data: Any) -> None:
        """One line in events.jsonl: ``kind`` (telemetry, trigger, state, decision, ...) at ``t``
        monotonic seconds, plus any JSON-able fields (dataclasses and arrays are converted)."""
        if self._events_fh is None:
            return
        line = _dumps({"t": t, "kind": kind, **data})
        with self._events_lock:
            try:
                self._events_fh.write(line + "\n")
            except (OSError, ValueError) as exc:
                self.stats.errors += 1
                log.warning("recorder: cannot write event: %s", exc)

    def close(self, timeout: float = 5.0) -> None:
        """Flush queued frames, close the segment and files."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout)
            self._thread = None
        with self._events_lock:
            for fh in (self._frames_fh, self._events_fh):
                if fh is not None:
                    fh.close()
            self._frames_fh = self._events_fh = None

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
                log.warning("recorder: frame %d not recorded: %s", item.index, exc)
        self._close_segment()

    def _write(self, item: _Item) -> None:
        img = item.image
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"not a BGR uint8 frame: shape {img.shape}, {img.dtype}")
        size = (img.shape[1], img.shape[0])
        if (self._writer is None or size != self._seg_size
                or item.t - self._seg_start_t >= self.segment_s):
            self._open_segment(size, item.t)
        assert self._writer is not None and self.path is not None
        self._writer.write(img)
        self._frames_fh.write(_dumps({"i": item.index, "t": item.t, "seg": self._seg_name,
                                      "k": self._seg_k, "pose": pose_to_dict(item.pose),
                                      "thumb": thumbnail(img)}) + "\n")
        self._seg_k += 1
        self.stats.frames += 1
        if self._seg_k % 50 == 0:
            self._enforce_budget()

    def _open_segment(self, size: tuple[int, int], t: float) -> None:
        self._close_segment()
        assert self.path is not None
        name = f"seg_{self._seg_no:05d}{SUFFIX[self.codec]}"
        self._seg_no += 1
        fourcc = cv2.VideoWriter_fourcc(*self.codec)  # type: ignore[attr-defined]  # missing from the cv2 stubs
        writer = cv2.VideoWriter(str(self.path / name), fourcc, self.fps, size)
        if not writer.isOpened():
            raise OSError(f"cannot open video segment {self.path / name} ({self.codec})")
        self._writer, self._seg_name, self._seg_size, self._seg_start_t, self._seg_k = writer, name, size, t, 0
        self.stats.segments += 1
        self._enforce_budget()

    def _close_segment(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            self._enforce_budget()

    def _enforce_budget(self) -> None:
        """Delete the oldest segments under root (all runs) until they fit in max_bytes."""
        current = self.path / self._seg_name if (self.path and self._seg_name and self._writer) else None
        segs = []
        for suffix in set(SUFFIX.values()):
            segs += [p for p in self.root.glob(f"*/seg_*{suffix}")]
        try:
            sized = [(p.stat().st_mtime, str(p), p, p.stat().st_size) for p in segs]
        except FileNotFoundError:
            return  # raced with another deletion; next check catches up
        total = sum(s for *_, s in sized)
        for _mtime, _name, p, size in sorted(sized):
            if total <= self.max_bytes:
                break
            if current is not None and p == current:
                continue
            try:
                p.unlink()
            except OSError as exc:
                log.warning("recorder: cannot delete %s: %s", p, exc)
                continue
            total -= size
            self.stats.deleted += 1
            log.info("recorder: deleted %s to stay under %.0f MiB", p, self.max_bytes / 2**20)


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

    ``path`` is the run folder (the one holding meta.json). Raises RecordingError naming the
    file when meta.json or frames.jsonl is missing or meta.json is corrupt. Deleted segments and a
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
        if not (self.path / "frames.jsonl").is_file():
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
        """The frame lines of frames.jsonl (bad lines skipped)."""
        return list(_read_jsonl(self.path / "frames.jsonl", self.stats))

    def __len__(self) -> int:
        return len(self.rows())

    def events(self, kind: str | None = None) -> Iterator[dict[str, Any]]:
        """Lines of events.jsonl, optionally only one ``kind``."""
        p = self.path / "events.jsonl"
        if not p.exists():
            return
        for row in _read_jsonl(p, self.stats):
            if kind is None or row.get("kind") == kind:
                yield row

    def frames(self) -> Iterator[RecordedFrame]:
        """Every readable frame in recording order, paired with its recorded pose."""
        self.stats = ReadStats()
        cap: cv2.VideoCapture | None = None
        seg: str | None = None
        pos = 0  # next frame position in the open segment
        dead = False  # the open segment is missing or ended early: skip its remaining rows
        truncated = False
        try:
            for row in _read_jsonl(self.path / "frames.jsonl", self.stats):
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
                        cap = cv2.VideoCapture(str(seg_path))
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
                while pos <= k:
                    ok, img = cap.read()
                    if not ok:
                        break
                    pos += 1
                    if pos - 1 == k:
                        image = img
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


__all__ = ["FlightRecorder", "RecordingReader", "RecordedFrame", "RecordingError", "RecorderStats",
           "pose_to_dict", "pose_from_dict"]
