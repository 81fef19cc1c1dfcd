"""The service's small HTTP server: the status page, its JSON and the annotated live view.

- ``GET /``: a page (plain HTML and a few lines of JavaScript, no framework) showing the live view,
  the phase, the health, the zones and the last decisions; it polls ``/status.json`` once a second;
- ``GET /status.json``: the same as JSON (:meth:`Service.status_json`);
- ``GET /stream.mjpg``: the live view, ``multipart/x-mixed-replace`` JPEG frames (HTTP MJPEG, which
  browsers, VLC, ffmpeg and MAVProxy open): the paper's figure of each frame the pipeline
  processed (``companion.replay.live_figure``); a frame the pipeline cannot use (on the ground,
  under the head plane, no pose) as the camera gave it, with the reason; with no frame at all for
  ``IDLE_S``, a placeholder saying why, once per ``IDLE_S``: a client never waits on a silent stream.

Standard library asyncio only. Off by default (``live.enabled``) and on loopback by default
(``live.address``). The figure is drawn only while a stream client is connected, at most
``LIVE_MAX_FPS`` times a second, in a worker thread; with nobody watching a frame costs one
comparison. Each client has a queue of ``CLIENT_QUEUE`` frames: a client that reads slowly loses
frames (counted), one that stops reading for ``SEND_TIMEOUT_S`` is dropped, and neither ever
holds up the pipeline or another client.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.config import LiveSettings
from companion.mavlink.gcs_commands import VideoStream
from companion.pipeline.slz import FrameResult
from companion.replay.live_figure import encode_jpeg, live_figure, placeholder_figure, raw_figure
from companion.service.page import PAGE

log = logging.getLogger(__name__)

CLIENT_QUEUE = 2
MAX_STREAM_CLIENTS = 4
SEND_TIMEOUT_S = 5.0
REQUEST_TIMEOUT_S = 5.0
MAX_REQUEST_BYTES = 8192
BOUNDARY = "slzframe"
STREAM_PATH = "/stream.mjpg"


@dataclass(frozen=True)
class Snapshot:
    """What one live frame shows: the image the pipeline saw, its result, the target, a caption;
    ``result`` None and ``reason`` set for a frame the pipeline could not use (drawn raw)."""

    image: np.ndarray
    result: FrameResult | None
    target_id: int | None
    caption: str
    reason: str | None = None


#: Most frames a second drawn for the live view (drawn only while a client watches): enough to
#: follow the decision, at one JPEG encode each on the CPU the pipeline needs.
LIVE_MAX_FPS = 5.0
#: With no frame for this long (s), a stream client gets a placeholder saying why, and again at
#: this period: a browser waiting for a first or next part never finishes loading the page.
IDLE_S = 1.0
#: The placeholder's size before any frame was drawn (px): the figure of a 640 x 480 camera.
DEFAULT_FIGURE = (640 + 4 + 480, 480 + 28)


@dataclass
class LiveStats:
    drawn: int = 0  # frames drawn and encoded
    dropped: int = 0  # frames a slow client did not take in time
    clients_dropped: int = 0  # clients that stopped reading
    errors: int = 0  # frames that could not be drawn


class LiveView:
    """Draws the newest offered frame for the connected stream clients (see the module docstring)."""

    def __init__(self, max_fps: float = LIVE_MAX_FPS, jpeg_quality: int = 80) -> None:
        self.period_s = 1.0 / max_fps
        self.quality = jpeg_quality
        self.stats = LiveStats()
        self.draw_ms: list[float] = []  # the last frames' draw + encode time (ms)
        self._clients: set[asyncio.Queue[bytes]] = set()
        self._latest: Snapshot | None = None
        self._new = asyncio.Event()
        self._last_offer = -math.inf
        self.size = DEFAULT_FIGURE  # (width, height) of the last figure drawn (px)
        self.drawing = False  # a frame is being drawn: a placeholder would only overtake it

    @property
    def clients(self) -> int:
        return len(self._clients)

    def wants(self, now: float) -> bool:
        """Whether a frame offered at ``now`` (monotonic s) would be drawn: somebody watches and
        the rate allows it. The frame loop asks before building a snapshot."""
        return bool(self._clients) and now - self._last_offer >= self.period_s

    @property
    def pending(self) -> bool:
        """A frame is waiting to be drawn or being drawn: a placeholder would only overtake it."""
        return self.drawing or self._latest is not None

    def offer(self, snapshot: Snapshot, now: float) -> None:
        """The newest frame; drawn later, unless a newer one replaces it first."""
        if not self.wants(now):
            return
        self._last_offer = now
        self._latest = snapshot
        self._new.set()

    def add_client(self) -> asyncio.Queue[bytes]:
        q: asyncio.Queue[bytes] = asyncio.Queue(maxsize=CLIENT_QUEUE)
        self._clients.add(q)
        return q

    def remove_client(self, q: asyncio.Queue[bytes]) -> None:
        self._clients.discard(q)

    def publish(self, jpeg: bytes) -> None:
        """Hand one encoded frame to every client; a full queue loses its oldest frame."""
        for q in list(self._clients):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
                self.stats.dropped += 1
            q.put_nowait(jpeg)

    async def run(self) -> None:
        """Draw offered frames until cancelled."""
        while True:
            await self._new.wait()
            self._new.clear()
            snap, self._latest = self._latest, None
            if snap is None or not self._clients:
                continue
            t0 = time.perf_counter()
            self.drawing = True
            try:
                if snap.result is None:
                    fig = await asyncio.to_thread(raw_figure, snap.image, snap.caption, snap.reason or "unknown")
                else:
                    fig = await asyncio.to_thread(live_figure, snap.image, snap.result, snap.target_id, snap.caption)
                self.size = (fig.shape[1], fig.shape[0])
                jpeg = await asyncio.to_thread(encode_jpeg, fig, self.quality)
            except Exception as exc:  # a drawing bug must cost the live view a frame, nothing more
                self.stats.errors += 1
                if self.stats.errors <= 3:
                    log.warning("live view: frame not drawn: %r", exc)
                continue
            finally:
                self.drawing = False
            self.draw_ms = (self.draw_ms + [(time.perf_counter() - t0) * 1000.0])[-50:]
            self.stats.drawn += 1
            self.publish(jpeg)

    async def placeholder(self, reason: str) -> bytes:
        """A frame of the last figure's size saying ``reason`` (JPEG)."""
        img = await asyncio.to_thread(placeholder_figure, *self.size, reason)
        return await asyncio.to_thread(encode_jpeg, img, self.quality)


def stream_uri(settings: LiveSettings) -> str:
    """The live view's URL as a client elsewhere would open it (a wildcard address gives the
    host's name: which interface a client reaches is not known here)."""
    host = settings.address
    if host in ("0.0.0.0", "::", ""):
        host = socket.gethostname()
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{settings.port}{STREAM_PATH}"


def live_video_stream(settings: LiveSettings, width: int, height: int) -> VideoStream:
    """The live view as VIDEO_STREAM_INFORMATION announces it (for the ground station's camera
    protocol, ``companion.mavlink.gcs_commands``). MAVLink has no stream type for HTTP MJPEG;
    ``TCP_MPEG`` with an ``http://`` URI is the nearest (QGroundControl does not play it from the
    announcement; a browser, VLC or MAVProxy opens the URI). ``width`` x ``height``: the figure's
    size (the frame and its head-plane view side by side, under the caption)."""
    return VideoStream(uri=stream_uri(settings)[:160], width=width, height=height,
                       framerate_hz=LIVE_MAX_FPS, stream_type=m.VIDEO_STREAM_TYPE_TCP_MPEG,
                       encoding=m.VIDEO_STREAM_ENCODING_UNKNOWN)


class WebServer:
    """The HTTP server (see the module docstring). ``status`` gives the JSON of ``/status.json``."""

    def __init__(self, settings: LiveSettings, live: LiveView, status: Callable[[], dict[str, Any]]) -> None:
        self.settings = settings
        self.live = live
        self.status = status
        self._server: asyncio.Server | None = None
        self._streams: set[asyncio.Task[Any]] = set()
        self.requests = 0
        self.bad_requests = 0

    async def start(self) -> None:
        """Listen; raises OSError (a port in use, an address not on this host)."""
        self._server = await asyncio.start_server(self._serve, self.settings.address, self.settings.port,
                                                  limit=MAX_REQUEST_BYTES)

    @property
    def port(self) -> int:
        """The port listened on (the configured one, or the one chosen for port 0)."""
        assert self._server is not None and self._server.sockets
        return int(self._server.sockets[0].getsockname()[1])

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._streams):
            task.cancel()
        for task in list(self._streams):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 0.5)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._streams.add(task)
        try:
            await self._handle(reader, writer)
        except asyncio.CancelledError:
            writer.close()  # the server is closing: end quietly (a cancelled handler is logged as an error)
            return
        except (ConnectionError, TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError):
            self.bad_requests += 1
        except Exception:  # a bug in one request must not take the server down
            log.exception("web: request failed")
        finally:
            if task is not None:
                self._streams.discard(task)
        writer.close()
        with contextlib.suppress(Exception, asyncio.CancelledError):
            await asyncio.wait_for(writer.wait_closed(), 0.5)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
        parts = head.split(b"\r\n", 1)[0].decode("latin-1").split()
        self.requests += 1
        if len(parts) != 3 or not parts[2].startswith("HTTP/"):
            self.bad_requests += 1
            await self._reply(writer, 400, "text/plain", b"bad request\n")
            return
        method, path = parts[0], parts[1].split("?", 1)[0]
        if method not in ("GET", "HEAD"):
            await self._reply(writer, 405, "text/plain", b"only GET\n", extra="Allow: GET, HEAD\r\n")
            return
        if path == "/":
            await self._reply(writer, 200, "text/html; charset=utf-8", PAGE.encode(), head_only=method == "HEAD")
        elif path == "/status.json":
            body = json.dumps(self.status(), allow_nan=False, default=str).encode()
            await self._reply(writer, 200, "application/json", body, head_only=method == "HEAD")
        elif path == STREAM_PATH:
            await self._stream(writer)
        else:
            await self._reply(writer, 404, "text/plain", b"not found\n")

    @staticmethod
    async def _reply(writer: asyncio.StreamWriter, code: int, ctype: str, body: bytes, *, extra: str = "",
                     head_only: bool = False) -> None:
        reason = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed",
                  503: "Service Unavailable"}[code]
        writer.write(f"HTTP/1.1 {code} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                     f"Cache-Control: no-store\r\nConnection: close\r\n{extra}\r\n".encode())
        if not head_only:
            writer.write(body)
        await asyncio.wait_for(writer.drain(), SEND_TIMEOUT_S)

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        if self.live.clients >= MAX_STREAM_CLIENTS:
            await self._reply(writer, 503, "text/plain", b"too many live-view clients\n")
            return
        q = self.live.add_client()
        try:
            writer.write(b"HTTP/1.1 200 OK\r\nCache-Control: no-store\r\nConnection: close\r\n"
                         b"Content-Type: multipart/x-mixed-replace; boundary=" + BOUNDARY.encode() + b"\r\n\r\n")
            await asyncio.wait_for(writer.drain(), SEND_TIMEOUT_S)
            while True:
                try:
                    jpeg = await asyncio.wait_for(q.get(), IDLE_S)
                except (TimeoutError, asyncio.TimeoutError):  # no frame: say why rather than go silent
                    if self.live.pending:
                        continue  # one is on its way
                    jpeg = await self.live.placeholder(self._idle_reason())
                writer.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                             .encode() + jpeg + b"\r\n")
                try:
                    await asyncio.wait_for(writer.drain(), SEND_TIMEOUT_S)
                except (TimeoutError, asyncio.TimeoutError):  # one class from 3.11 on
                    self.live.stats.clients_dropped += 1
                    log.info("live view: a client stopped reading for %.0f s: dropped", SEND_TIMEOUT_S)
                    return
        finally:
            self.live.remove_client(q)

    def _idle_reason(self) -> str:
        """Why no frame comes: the service's health, as the page shows it."""
        try:
            health = self.status().get("health", {})
        except Exception:  # the status is the page's; the stream goes on without it
            health = {}
        return f"no camera frame: {health.get('reason', 'unknown')}"

