"""Camera sources for the service: a reader thread that keeps only the newest frame.

Sources (``camera.source`` in the config):

* V4L2 device: ``/dev/video0`` or a device index ``0``;
* a video file, played at ``fps`` as if it were live;
* a folder of frames (``.jpg``, ``.png``, ... sorted by name), played at ``fps``;
* ``http://`` / ``https://`` MJPEG stream (``multipart/x-mixed-replace``), read by a small parser
  here rather than through FFmpeg, whose buffering adds latency and hides stalls; other HTTP
  content and ``rtsp://`` go through OpenCV's FFmpeg backend with open/read timeouts;
* a GStreamer pipeline, ``gst:v4l2src ! ... ! appsink`` (or any text with `` ! ``), when OpenCV was
  built with GStreamer; otherwise a clear :class:`CameraError` at start.

Capture time. ``Frame.t`` is the capture time on ``time.monotonic()`` (CLOCK_MONOTONIC), the clock
of the vehicle state, so ``state.pose_at(frame.t)`` pairs the frame with the pose at capture;
``Frame.t_source`` says where it came from:

* ``"device"``: a V4L2 device's buffer timestamp, which OpenCV's V4L2 backend gives as
  ``CAP_PROP_POS_MSEC`` (the driver's ``v4l2_buffer.timestamp``; CLOCK_MONOTONIC for drivers that
  set ``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``, i.e. nearly all of them in recent kernels; OpenCV does
  not expose the flag, hence the plausibility check below);
* ``"header"``: an MJPEG part's ``X-Timestamp`` header (seconds), which mjpg-streamer-like servers
  and the simulator's camera (``sim.world.camera_server``) send; it is on our clock only when the server
  runs on this machine and stamps with CLOCK_MONOTONIC;
* ``"grab"``: ``time.monotonic()`` right after the grab returned, for every other source (files,
  folders, RTSP/FFmpeg and GStreamer, whose positions are media time) and as the fallback.

A source timestamp is used only when it is plausibly on our clock: not in the future, at most
``MAX_SOURCE_AGE_S`` old, and after the previous frame's time; otherwise the frame gets its grab
time and the first such fallback is logged once (a camera stamping wall-clock time or another
machine's clock ends up there).

Freshness. A frame a live sensor could not have given is not fresh (``companion.service.freshness``):
one identical to the previous delivered frame (a camera re-serving its last frame after a reconnect,
a frozen driver or encoder repeating a buffer), or the same as one of the last few delivered frames
but for a small region (a driver cycling through its buffers, a frozen image with a live clock
drawn on it). It is counted in ``repeated`` (the history's verdicts also in ``stale``) and dropped:
not delivered, not recorded, and it does not count as a frame for ``delivering()`` or the stall
timeout (only stale frames for ``stall_timeout_s`` = a frozen camera, reopened, and ``frozen()``
says so). The history is kept across reconnects, so the last frame before a stall served again
after it is caught too. A real sensor never gives such frames (read noise changes every part of
the image); a looped folder of a few images or a renderer over a static scene without noise does,
and is treated as frozen (the simulator's camera adds sensor noise for that reason).

A frame that cannot be decoded or is not an HxWx3 uint8 image is counted in ``corrupt`` and
dropped. No new frame for ``stall_timeout_s`` means the camera stalled or was lost: it is closed and
reopened with exponential back-off (0.5 s doubling up to ``max_backoff_s``). A frame replaced by a
newer one before anyone took it is counted in ``dropped``: the consumer always gets the newest
frame and nothing queues up behind a slow pipeline.
"""

from __future__ import annotations

import asyncio
import http.client
import logging
import math
import threading
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from companion.frames import IMAGE_SUFFIXES, decode_image, image_files, read_image, read_video_frame
from companion.service.freshness import Freshness

log = logging.getLogger(__name__)

#: Oldest source timestamp taken as a capture time (s before the grab returned); older, or in the
#: future, means the source stamps on another clock (or is badly late): the grab time is used.
MAX_SOURCE_AGE_S = 1.0
TimeSource = Literal["grab", "device", "header"]


class CameraError(RuntimeError):
    """A camera source that can never work as configured (bad kind, missing file, no GStreamer)."""


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    index: sequence number of the frame among those the source delivered (0-based, counts only
        good fresh frames, so gaps mean frames the consumer never saw).
    t: capture time, ``time.monotonic()`` seconds (for pose pairing).
    image: BGR uint8 array (H, W, 3).
    t_source: where ``t`` came from: ``"device"`` (V4L2 buffer timestamp), ``"header"`` (the MJPEG
        part's ``X-Timestamp``) or ``"grab"`` (when the grab returned); see the module docstring.
    jpeg: the JPEG bytes ``image`` was decoded from (an MJPEG stream's part), or None: the
        recorder stores them as they came instead of encoding the image again.
    """

    index: int
    t: float
    image: np.ndarray
    t_source: TimeSource = "grab"
    jpeg: bytes | None = field(default=None, repr=False)


@dataclass
class CameraStats:
    """Counters since start. frames: good fresh frames delivered by the device; corrupt: frames
    counted and dropped as undecodable/malformed; repeated: frames not fresh (a frozen camera:
    see the module docstring), counted and dropped; stale: those of them judged by the history
    (the same as a recent frame but for a small region), not identical to the previous one;
    dropped: good frames replaced by a newer one before the consumer took them; stalls: times no
    new frame came for ``stall_timeout_s``; reopens: successful opens after the first;
    last_frame_t: capture time (monotonic) of the newest fresh frame; last_stale_t: when the
    newest frame that was not fresh arrived (monotonic)."""

    frames: int = 0
    corrupt: int = 0
    repeated: int = 0
    stale: int = 0
    dropped: int = 0
    stalls: int = 0
    reopens: int = 0
    open_failures: int = 0
    last_frame_t: float | None = None
    last_stale_t: float | None = None


class Kind(str, Enum):
    V4L2 = "v4l2"
    FILE = "file"
    FOLDER = "folder"
    MJPEG = "http"
    RTSP = "rtsp"
    GSTREAMER = "gstreamer"


def gstreamer_available() -> bool:
    info = cv2.getBuildInformation()
    return any("GStreamer" in line and "YES" in line for line in info.splitlines())


def classify(source: str) -> Kind:
    """The kind of ``source``; raises CameraError when it can never be opened."""
    s = source.strip()
    if not s:
        raise CameraError("camera.source is empty")
    if s.startswith("gst:") or " ! " in s:
        if not gstreamer_available():
            raise CameraError(
                f"camera.source {source!r} is a GStreamer pipeline, but this OpenCV was built without "
                "GStreamer (cv2.getBuildInformation()); use a device, file or URL, or install an "
                "OpenCV built with GStreamer"
            )
        return Kind.GSTREAMER
    low = s.lower()
    if low.startswith(("http://", "https://")):
        return Kind.MJPEG
    if low.startswith(("rtsp://", "rtsps://", "rtmp://", "udp://", "tcp://")):
        return Kind.RTSP
    if s.isdigit() or s.startswith("/dev/"):
        return Kind.V4L2  # a device may appear later (USB replug): keep trying, don't fail
    p = Path(s)
    if p.is_dir():
        return Kind.FOLDER
    if p.is_file():
        return Kind.FILE
    raise CameraError(f"camera.source {source!r}: no such file or folder (and not a device or URL)")


class _Status(Enum):
    OK = 1
    CORRUPT = 2
    FAIL = 3
    END = 4
    LOST = 5  # the connection closed: reopen now rather than wait for the stall timeout


class _Reader:
    """One open camera; ``read`` returns a status and the image (only with OK). ``stamp``: the
    source's capture timestamp of the frame ``read`` last returned (seconds, on the source's
    clock), or None when it gives none; ``stamp_source`` names it for ``Frame.t_source``."""

    stamp: float | None = None
    stamp_source: TimeSource = "grab"
    #: The JPEG bytes of the image ``read`` last returned, when the source sends JPEGs.
    jpeg: bytes | None = None

    def read(self) -> tuple[_Status, np.ndarray | None]:
        raise NotImplementedError

    def close(self) -> None:
        pass


class _Pacer:
    """Plays stored media at ``fps`` so a file behaves like a live camera."""

    def __init__(self, fps: float, stop: threading.Event) -> None:
        self.period = 1.0 / fps if fps > 0 else 0.0
        self.next_t = time.monotonic()
        self.stop = stop

    def wait(self) -> None:
        if self.period <= 0:
            return
        delay = self.next_t - time.monotonic()
        if delay > 0:
            self.stop.wait(delay)
        self.next_t = max(self.next_t + self.period, time.monotonic() - self.period)


class _CvReader(_Reader):
    """An OpenCV capture. device_stamps: read ``CAP_PROP_POS_MSEC`` as the capture timestamp
    (only for V4L2, where it is the driver's buffer timestamp; elsewhere it is media time)."""

    stamp_source: TimeSource = "device"

    def __init__(self, cap: cv2.VideoCapture, live: bool, pacer: _Pacer | None,
                 device_stamps: bool = False) -> None:
        self.cap, self.live, self.pacer = cap, live, pacer
        self.device_stamps = device_stamps

    def read(self) -> tuple[_Status, np.ndarray | None]:
        if self.pacer is not None:
            self.pacer.wait()
        self.stamp = None
        ok, bgr = read_video_frame(self.cap)
        if not ok:
            return (_Status.FAIL if self.live else _Status.END), None
        if self.device_stamps:
            ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
            self.stamp = ms / 1000.0 if ms > 0 else None  # 0 = none yet (OpenCV's first capture)
        return (_Status.OK, bgr) if bgr is not None else (_Status.CORRUPT, None)

    def close(self) -> None:
        self.cap.release()


def folder_images(folder: Path) -> list[Path]:
    """The image files of a folder source, sorted; CameraError when it holds none."""
    files = image_files(folder)
    if not files:
        raise CameraError(f"camera.source {str(folder)!r}: folder holds no image files "
                          f"({', '.join(IMAGE_SUFFIXES)})")
    return files


def check_source(source: str) -> Kind:
    """``classify``, and for a folder, that it holds images and that at least one of them decodes
    (one truncated or foreign file among good ones is counted and dropped as it plays, but a
    folder of nothing but those would run without a single frame): what start-up can know is
    wrong."""
    kind = classify(source)
    if kind is Kind.FOLDER:
        folder = Path(source.strip())
        files = folder_images(folder)
        if not any(read_image(p) is not None for p in files):
            raise CameraError(f"camera.source {str(folder)!r}: none of the folder's {len(files)} image "
                              f"file(s) decodes as a whole image (truncated or not images), e.g. {files[0].name}")
    return kind


class _FolderReader(_Reader):
    def __init__(self, folder: Path, pacer: _Pacer) -> None:
        self.files = folder_images(folder)
        self.i = 0
        self.pacer = pacer

    def read(self) -> tuple[_Status, np.ndarray | None]:
        if self.i >= len(self.files):
            return _Status.END, None
        self.pacer.wait()
        path = self.files[self.i]
        self.i += 1
        image = read_image(path)
        if image is None:
            log.debug("cannot decode %s", path)
            return _Status.CORRUPT, None
        return _Status.OK, image


class _MjpegReader(_Reader):
    """``multipart/x-mixed-replace`` JPEG parts over HTTP, with a socket timeout so a silent
    server is noticed as a stall rather than blocking the reader thread forever. A part's
    ``X-Timestamp`` header (seconds) is its capture timestamp."""

    stamp_source: TimeSource = "header"

    def __init__(self, url: str, timeout: float) -> None:
        u = urllib.parse.urlsplit(url)
        conn_cls = http.client.HTTPSConnection if u.scheme == "https" else http.client.HTTPConnection
        self.conn = conn_cls(u.hostname or "127.0.0.1", u.port, timeout=timeout)
        path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        self.conn.request("GET", path)
        self.resp = self.conn.getresponse()
        if self.resp.status != 200:
            raise OSError(f"HTTP {self.resp.status} {self.resp.reason} from {url}")
        ctype = self.resp.getheader("Content-Type", "")
        if "multipart" not in ctype or "boundary=" not in ctype:
            raise _NotMjpeg(ctype)
        boundary = ctype.split("boundary=", 1)[1].split(";")[0].strip().strip('"')
        self.boundary = b"--" + boundary.removeprefix("--").encode()

    def _readline(self) -> bytes:
        line = self.resp.readline(65536)
        if not line:
            raise EOFError("MJPEG stream closed")
        return line

    def read(self) -> tuple[_Status, np.ndarray | None]:
        self.stamp = self.jpeg = None
        try:
            line = self._readline()
            skipped = 0
            while not line.startswith(self.boundary):
                skipped += 1
                if skipped > 10000:
                    return _Status.FAIL, None
                line = self._readline()
            headers: dict[str, str] = {}
            while True:
                line = self._readline().strip()
                if not line:
                    break
                k, _, v = line.decode("latin-1").partition(":")
                headers[k.strip().lower()] = v.strip()
            length = int(headers.get("content-length", "-1"))
            if length < 0:
                data = self._read_to_boundary()
            else:
                data = self.resp.read(length)
                if len(data) < length:
                    raise EOFError("MJPEG part truncated")
        except TimeoutError as exc:
            log.debug("MJPEG read timed out: %s", exc)
            return _Status.FAIL, None
        except (OSError, EOFError, ValueError, http.client.HTTPException) as exc:
            log.debug("MJPEG read failed: %s", exc)
            return _Status.LOST, None
        image = decode_image(data, cv2.IMREAD_COLOR)  # a part cut short is refused, not decoded
        if image is None:
            return _Status.CORRUPT, None
        self.stamp = _parse_stamp(headers.get("x-timestamp"))
        self.jpeg = data
        return _Status.OK, image

    def _read_to_boundary(self) -> bytes:
        chunks = []
        while True:
            line = self.resp.peek(len(self.boundary))[: len(self.boundary)]
            if line.startswith(self.boundary):
                break
            chunks.append(self.resp.readline(65536))
        return b"".join(chunks).rstrip(b"\r\n")

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass


class _NotMjpeg(Exception):
    pass


def _parse_stamp(text: str | None) -> float | None:
    """A header's timestamp in seconds, or None when absent or not a finite number."""
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def plausible_capture_time(stamp: float, now: float, previous: float | None) -> bool:
    """A source timestamp can be taken as the capture time on ``time.monotonic()`` taken at
    ``now`` (just after the grab): not in the future (1 ms for rounding), at most
    ``MAX_SOURCE_AGE_S`` old, and after the ``previous`` frame's capture time."""
    return (now - MAX_SOURCE_AGE_S <= stamp <= now + 1e-3
            and (previous is None or stamp > previous))


FrameCallback = Callable[[Frame], None]


@dataclass
class CameraSource:
    """Reads ``source`` in a daemon thread and keeps the newest frame.

    width/height/fps: asked of devices (0 = the device's default); fps also paces files and
    folders. stall_timeout_s: no good frame for this long = stalled, reopen. max_backoff_s:
    longest wait between open attempts. loop: restart files and folders at their end.
    """

    source: str
    width: int = 0
    height: int = 0
    fps: float = 0.0
    stall_timeout_s: float = 2.0
    max_backoff_s: float = 10.0
    loop: bool = False
    stats: CameraStats = field(default_factory=CameraStats)

    def __post_init__(self) -> None:
        self.kind = classify(self.source)
        self._lock = threading.Lock()
        self._latest: Frame | None = None
        self._taken_index = -1
        self._new = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ended = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._anew: asyncio.Event | None = None
        self._next_index = 0
        self._listeners: list[FrameCallback] = []
        # The recent delivered frames, kept across reopens: a repeat of them is not fresh.
        self._freshness = Freshness()
        self._prev_t: float | None = None
        self._warned_stamp = False
        if self.kind is Kind.FOLDER:
            # Fail at start on an empty folder rather than retrying forever.
            _FolderReader(Path(self.source), _Pacer(0, self._stop))

    # ---- lifecycle ---------------------------------------------------------------------------
    def start(self) -> CameraSource:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="camera", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._new.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def add_listener(self, callback: FrameCallback) -> None:
        """Called in the reader thread with every good frame (the recorder); must be quick."""
        self._listeners.append(callback)

    # ---- consumer side -----------------------------------------------------------------------
    @property
    def ended(self) -> bool:
        """A file or folder (without ``loop``) reached its end; no more frames will come."""
        return self._ended

    def delivering(self, now: float | None = None) -> bool:
        """A fresh frame (not a repeat) was captured within ``stall_timeout_s``."""
        last = self.stats.last_frame_t
        now = time.monotonic() if now is None else now
        return last is not None and now - last < self.stall_timeout_s

    def frozen(self, now: float | None = None) -> bool:
        """Not delivering, but frames keep coming that are not fresh (a frozen camera)."""
        now = time.monotonic() if now is None else now
        stale = self.stats.last_stale_t
        return not self.delivering(now) and stale is not None and now - stale < self.stall_timeout_s

    def take(self) -> Frame | None:
        """The newest frame not yet taken, or None."""
        with self._lock:
            f = self._latest
            if f is None or f.index <= self._taken_index:
                self._new.clear()
                return None
            self._taken_index = f.index
            self._new.clear()
            return f

    def wait(self, timeout: float) -> Frame | None:
        """Blocking: the newest new frame, waiting up to ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            f = self.take()
            if f is not None or self._stop.is_set():
                return f
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._new.wait(remaining)

    async def next_frame(self, timeout: float) -> Frame | None:
        """Async: the newest new frame, waiting up to ``timeout`` seconds (None on timeout)."""
        loop = asyncio.get_running_loop()
        if self._loop is not loop:
            self._loop, self._anew = loop, asyncio.Event()
        assert self._anew is not None
        f = self.take()
        if f is not None:
            return f
        self._anew.clear()
        f = self.take()  # a frame may have landed between the take and the clear
        if f is not None:
            return f
        try:
            await asyncio.wait_for(self._anew.wait(), timeout)
        except (TimeoutError, asyncio.TimeoutError):
            return None
        return self.take()

    # ---- reader thread -----------------------------------------------------------------------
    def _open(self) -> _Reader:
        pacer = _Pacer(self.fps, self._stop)
        timeout_ms = int(self.stall_timeout_s * 1000)
        if self.kind is Kind.FOLDER:
            return _FolderReader(Path(self.source), pacer)
        if self.kind is Kind.MJPEG:
            try:
                return _MjpegReader(self.source, timeout=self.stall_timeout_s)
            except _NotMjpeg:
                pass  # not multipart: let FFmpeg handle whatever it is (HLS, a file over HTTP)
        if self.kind is Kind.GSTREAMER:
            pipeline = self.source.removeprefix("gst:").strip()
            cap = cv2.VideoCapture(pipeline, cv2.CAP_GSTREAMER)
        elif self.kind is Kind.V4L2:
            dev: int | str = int(self.source) if self.source.isdigit() else self.source
            cap = cv2.VideoCapture(dev, cv2.CAP_V4L2)
            if self.width and self.height:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            if self.fps:
                cap.set(cv2.CAP_PROP_FPS, self.fps)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not one from a driver queue
        elif self.kind is Kind.FILE:
            cap = cv2.VideoCapture(self.source)
        else:
            cap = cv2.VideoCapture(self.source, cv2.CAP_FFMPEG, [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms])
        if not cap.isOpened():
            cap.release()
            raise OSError(f"OpenCV cannot open {self.source!r}")
        live = self.kind is not Kind.FILE
        return _CvReader(cap, live=live, pacer=None if live else pacer,
                         device_stamps=self.kind is Kind.V4L2)

    def _is_repeat(self, image: np.ndarray) -> bool:
        """``image`` is not fresh (see the module docstring; the caller counts it in ``repeated``);
        a fresh one is remembered."""
        verdict = self._freshness.judge(image)
        if verdict == "fresh":
            return False
        self.stats.last_stale_t = time.monotonic()
        if verdict == "stale":
            self.stats.stale += 1
        return True

    def _capture_time(self, stamp: float | None, source: TimeSource, now: float) -> tuple[float, TimeSource]:
        """The frame's capture time and its source: the source's timestamp ``stamp`` when
        plausible, else ``now`` (the grab time)."""
        if stamp is None:
            return now, "grab"
        if plausible_capture_time(stamp, now, self._prev_t):
            return min(stamp, now), source
        if not self._warned_stamp:
            self._warned_stamp = True
            log.warning("camera %s: %s timestamp %.6f is not on this machine's monotonic clock "
                        "(now %.6f, previous frame %s); using grab time for such frames (logged once)",
                        self.source, source, stamp, now,
                        "none" if self._prev_t is None else f"{self._prev_t:.6f}")
        return now, "grab"

    def _publish(self, image: np.ndarray, t: float, t_source: TimeSource = "grab",
                 jpeg: bytes | None = None) -> None:
        frame = Frame(self._next_index, t, image, t_source, jpeg)
        self._prev_t = t
        self._next_index += 1
        with self._lock:
            if self._latest is not None and self._latest.index > self._taken_index:
                self.stats.dropped += 1
            self._latest = frame
            self.stats.frames += 1
            self.stats.last_frame_t = t
        self._new.set()
        for cb in self._listeners:
            try:
                cb(frame)
            except Exception:  # a listener must never stop the camera
                log.exception("camera frame listener failed")
        if self._loop is not None and self._anew is not None:
            try:
                self._loop.call_soon_threadsafe(self._anew.set)
            except RuntimeError:
                pass  # event loop closed during shutdown

    def _run(self) -> None:
        backoff = 0.5
        reader: _Reader | None = None
        opened_once = False
        last_good = time.monotonic()
        while not self._stop.is_set():
            if reader is None:
                try:
                    reader = self._open()
                except (OSError, CameraError, http.client.HTTPException) as exc:
                    self.stats.open_failures += 1
                    log.warning("camera %s: cannot open (%s); retrying in %.1f s", self.source, exc, backoff)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.max_backoff_s)
                    continue
                if opened_once:
                    self.stats.reopens += 1
                    log.info("camera %s: reopened", self.source)
                opened_once = True
                last_good = time.monotonic()
            status, image = reader.read()
            now = time.monotonic()
            if status is _Status.OK:
                assert image is not None
                if not self._is_repeat(image):
                    self._publish(image, *self._capture_time(reader.stamp, reader.stamp_source, now), jpeg=reader.jpeg)
                    last_good = now
                    backoff = 0.5
                    continue
                # Not fresh: a frozen source, or one re-serving its last frame after a reconnect.
                self.stats.repeated += 1
                if self.stats.repeated <= 3 or self.stats.repeated % 100 == 0:
                    log.warning("camera %s: stale frame ignored (%d so far, %d the same as a recent one "
                                "but for a small region)", self.source, self.stats.repeated, self.stats.stale)
            elif status is _Status.CORRUPT:
                self.stats.corrupt += 1
                if self.stats.corrupt <= 10 or self.stats.corrupt % 100 == 0:
                    log.warning("camera %s: corrupt frame dropped (%d so far)", self.source, self.stats.corrupt)
            elif status is _Status.END:
                reader.close()
                reader = None
                if not self.loop:
                    log.info("camera %s: end of stream", self.source)
                    self._ended = True
                    break
                opened_once = False  # a loop restart is not a reopen
                continue
            elif status is _Status.LOST:
                log.warning("camera %s: connection lost; reopening", self.source)
                reader.close()
                reader = None
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.max_backoff_s)
                continue
            else:
                self._stop.wait(0.01)  # a failing device returns at once: don't spin
            if now - last_good > self.stall_timeout_s:
                self.stats.stalls += 1
                log.warning("camera %s: no new frame for %.1f s (%d repeated so far); reopening",
                            self.source, now - last_good, self.stats.repeated)
                reader.close()
                reader = None
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.max_backoff_s)
        if reader is not None:
            reader.close()
        self._new.set()
