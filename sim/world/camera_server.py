"""The simulated camera as a real camera source: MJPEG over HTTP on loopback.

``CameraServer`` renders the world from the vehicle's pose at a fixed frame rate and serves the
frames like many IP cameras do: ``GET /stream.mjpg`` answers ``multipart/x-mixed-replace`` with one
JPEG part per frame; ``GET /snapshot.jpg`` answers the latest frame. Each part carries
``X-Frame-Index``, ``X-Render-Time`` (``time.time()`` seconds when the frame was rendered) and
``X-Timestamp`` (the capture time: ``time.monotonic()`` seconds when the pose and the world were
sampled for the frame, the header mjpg-streamer sends with the V4L2 buffer time; the service's
camera uses it as the capture time, since the two run on the same machine and clock) headers.
A slow client is never queued frames: it always gets the newest one.

Sensor noise. The renderer is deterministic: a static scene from a hovering (or landed) vehicle
renders bit-identical frames, which a real sensor never gives and which the service rightly takes
for a frozen camera. Each served frame gets Gaussian read noise (``noise_sigma`` DN, default 1.5,
seeded by the world's seed) before JPEG encoding. The noise is a window at a random offset into a
pre-drawn bank of ``2 x H x W x 3`` samples (an independent realisation per pixel and frame for
~0.3 ms at 640x480, against ~9 ms to draw fresh normals); consecutive offsets always differ.
``render_now`` stays noise-free.

The server does not step the world (the simulator does, with its clock) unless
``advance_world=True``, for a stand-alone camera.

:func:`read_mjpeg` is a small dependency-free reader of such a stream (used by the tests, usable by
the service), and :meth:`CameraServer.render_now` renders in-process without HTTP.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import math
import socket
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.world.render import render_world

BOUNDARY = "simcamframe"
SEND_BUFFER = 32 * 1024  # bytes; about half a 640x480 JPEG
RECV_BUFFER = 64 * 1024  # bytes


@dataclass(frozen=True)
class Frame:
    """One rendered frame: BGR image (with sensor noise), its index, the pose it was rendered from
    and when."""

    image: np.ndarray
    index: int
    pose: Pose
    render_time: float  # time.time() seconds
    jpeg: bytes = b""
    capture_time: float = 0.0  # time.monotonic() seconds when pose and world were sampled


class SensorNoise:
    """Gaussian read noise of ``sigma`` DN added to uint8 images, seeded: each call adds a window
    at a new random offset of a pre-drawn bank of int8 samples (saturating at 0 and 255)."""

    def __init__(self, sigma: float, seed: int = 0) -> None:
        self.sigma = float(sigma)
        self.rng = np.random.default_rng([seed & 0xFFFFFFFF, 0x5E45])
        self._bank: np.ndarray | None = None
        self._last_offset = -1

    def prepare(self, size: int) -> None:
        """Draw the bank for images of ``size`` values (~60 ms at 640x480x3; done at start)."""
        if self.sigma > 0 and (self._bank is None or self._bank.size < 2 * size):
            draw = np.rint(self.rng.standard_normal(2 * size, dtype=np.float32) * self.sigma)
            self._bank = np.clip(draw, -127, 127).astype(np.int8)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self.sigma <= 0:
            return image
        n = image.size
        self.prepare(n)
        assert self._bank is not None
        offset = int(self.rng.integers(0, self._bank.size - n + 1))
        if offset == self._last_offset:
            offset = (offset + 1) % (self._bank.size - n + 1)
        self._last_offset = offset
        noise = self._bank[offset:offset + n].reshape(image.shape)
        return cv2.add(image, noise, dtype=cv2.CV_8U)


def stamp_index(img: np.ndarray, index: int, bits: int = 16, cell: int = 8) -> None:
    """Write ``index`` as black/white ``cell``-pixel squares along the top-left edge (for
    measuring end-to-end latency through a reader that only gives pixels, like OpenCV)."""
    for b in range(bits):
        img[0:cell, b * cell:(b + 1) * cell] = 255 if (index >> b) & 1 else 0


def read_stamp(img: np.ndarray, bits: int = 16, cell: int = 8) -> int:
    """The index written by :func:`stamp_index` (robust to JPEG: reads each square's centre)."""
    c = cell // 2
    grey = img if img.ndim == 2 else img.mean(axis=2)
    return sum(1 << b for b in range(bits) if grey[c, b * cell + c] > 127)


class CameraServer:
    """Simulated camera rendering ``world`` from ``pose_provider()`` at ``fps`` frames per second.

    pose_provider: returns the vehicle pose now (world NED metres, radians).
    world: a :class:`sim.world.crowd.World` (positions/headings/moving/t/seed).
    intrinsics, mount: the camera model (``companion.geometry.camera``); frames are
        ``intrinsics.width x intrinsics.height``.
    fps: render rate, frames per second. port: TCP port on 127.0.0.1 (0 = any free port; see
        ``url`` after ``start``). ground: a :class:`sim.world.ground.ProceduralGround` or alike.
    jpeg_quality: 0-100. stamp: write the frame index into the top-left pixels (latency tests).
    advance_world: step the world by the wall-clock time between frames (stand-alone use).
    noise_sigma: sensor read noise in DN (0 = none: identical frames of a static scene).
    noise_seed: its seed (default: the world's ``seed``).
    """

    def __init__(self, pose_provider: Callable[[], Pose], world: object, intrinsics: Intrinsics,
                 mount: Mount, fps: float = 12.0, port: int = 0, ground: object | None = None,
                 jpeg_quality: int = 85, stamp: bool = False, advance_world: bool = False,
                 host: str = "127.0.0.1", noise_sigma: float = 1.5,
                 noise_seed: int | None = None) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps!r}")
        if ground is None:
            from sim.world.ground import ProceduralGround
            ground = ProceduralGround(getattr(world, "seed", 0))
        self.pose_provider = pose_provider
        self.world = world
        self.intrinsics = intrinsics
        self.mount = mount
        self.fps = float(fps)
        self.port = int(port)
        self.host = host
        self.ground = ground
        self.jpeg_quality = int(jpeg_quality)
        self.stamp = stamp
        self.advance_world = advance_world
        self.noise = SensorNoise(noise_sigma, getattr(world, "seed", 0) if noise_seed is None else noise_seed)
        self.latest: Frame | None = None
        self.render_times: dict[int, float] = {}  # frame index -> time.time() at render end
        self.capture_times: dict[int, float] = {}  # frame index -> its X-Timestamp (monotonic)
        self.frames_rendered = 0
        self.errors = 0
        self._index = 0
        self._cond: asyncio.Condition | None = None
        self._server: asyncio.base_events.Server | None = None
        self._task: asyncio.Task | None = None
        self._clients: set[asyncio.Task] = set()

    @property
    def url(self) -> str:
        """The stream URL, ``http://127.0.0.1:PORT/stream.mjpg``."""
        return f"http://{self.host}:{self.port}/stream.mjpg"

    def render_now(self, pose: Pose | None = None) -> np.ndarray:
        """Render a BGR frame of the world now from ``pose`` (default: the provider's), in-process."""
        p = self.pose_provider() if pose is None else pose
        return render_world(self.world, p, self.intrinsics, self.mount, self.ground)  # type: ignore[arg-type]

    async def start(self) -> None:
        """Render a first frame (generating the ground tiles in view), bind the port, start."""
        with contextlib.suppress(Exception):  # a bad first pose is the render loop's to count
            await asyncio.to_thread(self.render_now)
        await asyncio.to_thread(self.noise.prepare, self.intrinsics.width * self.intrinsics.height * 3)
        self._cond = asyncio.Condition()
        self._server = await asyncio.start_server(self._handle, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._task = asyncio.create_task(self._render_loop(), name="sim-camera-render")

    async def stop(self) -> None:
        """Stop rendering, close client connections and the port."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for c in list(self._clients):
            c.cancel()
        if self._clients:
            await asyncio.gather(*self._clients, return_exceptions=True)
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None

    async def __aenter__(self) -> CameraServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def _render_encode(self, pose: Pose, positions: tuple, index: int, capture_time: float = 0.0) -> Frame:
        from sim.world.render import looks_for, render
        pos, hd, mv, t, seed, ids = positions
        img = render(pos, pose, self.intrinsics, self.mount, self.ground,  # type: ignore[arg-type]
                     headings=hd, moving=mv, t=t, seed=seed,
                     looks=looks_for(ids, seed) if ids is not None else None, ids=ids)
        img = self.noise(img)  # the sensor: read noise before the encoder
        if self.stamp:
            stamp_index(img, index)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return Frame(img, index, pose, time.time(), buf.tobytes(), capture_time)

    async def _render_loop(self) -> None:
        period = 1.0 / self.fps
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        last_wall = time.monotonic()
        while True:
            now_wall = time.monotonic()
            if self.advance_world:
                self.world.step(now_wall - last_wall)  # type: ignore[attr-defined]
            last_wall = now_wall
            try:
                pose = self.pose_provider()
                # The exposure: the time of the state the pose describes (the simulator's last
                # physics step, the clock of the autopilot's telemetry), when the provider gives a
                # recent one; a fixed test pose gives none, and then it is now.
                now = time.monotonic()
                capture_time = pose.t if math.isfinite(pose.t) and 0.0 <= now - pose.t <= 1.0 else now
                w = self.world
                # Snapshot the world on the loop thread; render and encode off it (both release
                # the GIL in OpenCV) so the simulator's MAVLink tasks keep their timing.
                snap = (w.positions(), w.headings(), w.moving(), w.t, getattr(w, "seed", 0),  # type: ignore[attr-defined]
                        w.ids() if hasattr(w, "ids") else None)
                frame = await asyncio.to_thread(self._render_encode, pose, snap, self._index, capture_time)
            except asyncio.CancelledError:
                raise
            except Exception:  # a bad pose (NaN, underground) must not kill the camera
                self.errors += 1
            else:
                self.render_times[frame.index] = frame.render_time
                self.capture_times[frame.index] = frame.capture_time
                if len(self.render_times) > 1000:
                    self.render_times.pop(next(iter(self.render_times)))
                    self.capture_times.pop(next(iter(self.capture_times)))
                self.latest = frame
                self.frames_rendered += 1
                self._index += 1
                assert self._cond is not None
                async with self._cond:
                    self._cond.notify_all()
            next_t += period
            delay = next_t - loop.time()
            if delay < 0:  # fell behind: drop the backlog, keep the rate from now
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(delay)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._clients.add(task)
        try:
            request = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5.0)
            line = request.split(b"\r\n", 1)[0].decode("latin-1").split()
            path = urllib.parse.urlsplit(line[1]).path if len(line) >= 2 else ""
            if len(line) < 2 or line[0] != "GET":
                writer.write(b"HTTP/1.0 405 Method Not Allowed\r\nContent-Length: 0\r\n\r\n")
            elif path == "/stream.mjpg":
                await self._stream(writer)
            elif path == "/snapshot.jpg":
                frame = await self.next_frame(None)
                writer.write(b"HTTP/1.0 200 OK\r\nContent-Type: image/jpeg\r\n"
                             + f"Content-Length: {len(frame.jpeg)}\r\n\r\n".encode() + frame.jpeg)
            else:
                writer.write(b"HTTP/1.0 404 Not Found\r\nContent-Length: 0\r\n\r\n")
            await writer.drain()
        except (TimeoutError, asyncio.TimeoutError, asyncio.CancelledError, ConnectionError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass
        finally:
            if task is not None:
                self._clients.discard(task)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def next_frame(self, after: int | None) -> Frame:
        """The newest frame rendered after frame ``after`` (any frame when None), waiting for it:
        what the stream and the snapshot send, and a consumer in this process (``sim.flights.lockstep``)."""
        assert self._cond is not None
        async with self._cond:
            await self._cond.wait_for(
                lambda: self.latest is not None and (after is None or self.latest.index > after))
        assert self.latest is not None
        return self.latest

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        # Small send buffers: a frame that waits in a kernel or asyncio buffer is a stale frame.
        # With them, a reader slower than ``fps`` gets newer frames instead of a growing backlog.
        sock = writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        writer.transport.set_write_buffer_limits(high=SEND_BUFFER)
        writer.write(b"HTTP/1.0 200 OK\r\nCache-Control: no-cache\r\nPragma: no-cache\r\n"
                     b"Connection: close\r\n"
                     + f"Content-Type: multipart/x-mixed-replace; boundary={BOUNDARY}\r\n\r\n".encode())
        last: int | None = None
        while True:
            frame = await self.next_frame(last)
            last = frame.index
            writer.write(
                f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(frame.jpeg)}\r\n"
                f"X-Frame-Index: {frame.index}\r\nX-Render-Time: {frame.render_time:.6f}\r\n"
                f"X-Timestamp: {frame.capture_time:.6f}\r\n\r\n".encode()
                + frame.jpeg + b"\r\n")
            # Waiting for the socket to drain is what keeps a slow client from queueing frames:
            # while it waits, newer frames replace older ones in ``latest``.
            await writer.drain()


@dataclass(frozen=True)
class MjpegFrame:
    """A frame read by :func:`read_mjpeg`: BGR image and the part's headers (lower-case keys)."""

    image: np.ndarray
    headers: dict[str, str]
    received: float  # time.time() seconds when the last byte arrived


def _read_headers(fp: io.IOBase) -> tuple[dict[str, str], bool]:
    """HTTP header lines up to the blank line (keys lower case), and whether the stream ended
    before it (the headers read until then are kept)."""
    headers: dict[str, str] = {}
    while True:
        h = fp.readline()
        if not h or h in (b"\r\n", b"\n"):
            return headers, not h
        k, _, v = h.decode("latin-1").partition(":")
        headers[k.strip().lower()] = v.strip()


def read_mjpeg(url: str, timeout: float = 5.0, recv_buffer: int = RECV_BUFFER) -> Iterator[MjpegFrame]:
    """Frames of an MJPEG-over-HTTP stream (``multipart/x-mixed-replace``), as they arrive.

    Blocking (run it in a thread); stops when the server closes the stream. Parts that are not
    decodable JPEG are skipped. Raises ``ConnectionError`` when the server does not answer 200
    with a multipart stream. The socket's receive buffer is kept small (``recv_buffer`` bytes)
    so that a consumer slower than the camera reads recent frames rather than a growing backlog
    (the server sees the full window and drops frames instead).
    """
    u = urllib.parse.urlsplit(url)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, recv_buffer)  # before connect
        sock.settimeout(timeout)
        sock.connect((u.hostname or "127.0.0.1", u.port or 80))
        path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        sock.sendall(f"GET {path} HTTP/1.0\r\nHost: {u.netloc}\r\n\r\n".encode())
        fp = sock.makefile("rb", buffering=16 * 1024)
        status = fp.readline().decode("latin-1").split()
        head, _ = _read_headers(fp)
        ctype = head.get("content-type", "")
        if len(status) < 2 or status[1] != "200" or "boundary=" not in ctype:
            raise ConnectionError(f"{url}: {' '.join(status)!r} {ctype!r}, not an MJPEG stream")
        boundary = b"--" + ctype.split("boundary=", 1)[1].strip().strip('"').lstrip("-").encode()
        while True:
            line = fp.readline()
            if not line:
                return
            if not line.strip().startswith(boundary):
                continue
            headers, ended = _read_headers(fp)
            if ended:
                return
            n = int(headers.get("content-length", "-1"))
            if n < 0:
                continue  # this reader needs Content-Length (all IP cameras we target send it)
            data = fp.read(n)
            if len(data) < n:
                return
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if img is not None:
                yield MjpegFrame(img, headers, time.time())
    finally:
        sock.close()


class LatestFrameReader:
    """Reads an MJPEG stream in a background thread and keeps only the newest frame: the way to
    consume a live camera when processing is slower than the camera (drop, never queue).

    ``get(timeout)`` returns the newest frame not returned before (waits for one), or None on
    timeout. ``close()`` stops the thread.
    """

    def __init__(self, url: str, timeout: float = 5.0) -> None:
        self.url = url
        self.timeout = timeout
        self.error: BaseException | None = None
        self.frames_read = 0
        self._latest: MjpegFrame | None = None
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mjpeg-reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for f in read_mjpeg(self.url, self.timeout):
                with self._cv:
                    self._latest = f
                    self.frames_read += 1
                    self._cv.notify_all()
                if self._stop.is_set():
                    return
        except BaseException as exc:  # reported to the consumer through ``error``
            self.error = exc
        finally:
            with self._cv:
                self._cv.notify_all()

    def get(self, timeout: float = 5.0) -> MjpegFrame | None:
        with self._cv:
            self._cv.wait_for(lambda: self._latest is not None or not self._thread.is_alive(), timeout)
            f, self._latest = self._latest, None
            return f

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=self.timeout + 1.0)

    def __enter__(self) -> LatestFrameReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


async def _serve_forever(seconds: float | None, port: int, altitude: float) -> None:
    from sim.world.crowd import default_world

    world = default_world(seed=0)
    K = Intrinsics.from_fov(640, 480, 70.0)
    srv = CameraServer(lambda: Pose(time.monotonic(), 0.0, 0.0, -altitude, 0.0, 0.0, 0.0), world, K,
                       Mount(), port=port, advance_world=True)
    async with srv:
        print(f"simulated camera at {srv.url} ({altitude:g} m, straight down); Ctrl-C stops", flush=True)
        await asyncio.sleep(seconds if seconds is not None else 1e9)


if __name__ == "__main__":  # python -m sim.world.camera_server [--port 8080] [--altitude 30]
    import argparse

    ap = argparse.ArgumentParser(description="Serve the default simulated world as an MJPEG camera")
    ap.add_argument("--port", type=int, default=8080)
    ap.add_argument("--altitude", type=float, default=30.0, help="metres above the ground")
    ap.add_argument("--seconds", type=float, default=None, help="stop after this long")
    a = ap.parse_args()
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_serve_forever(a.seconds, a.port, a.altitude))
