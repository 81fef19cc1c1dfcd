"""Camera sources with real files, a real MJPEG-over-HTTP server on loopback and real OpenCV."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.service.camera import (
    CameraError,
    CameraSource,
    Kind,
    classify,
    gstreamer_available,
    plausible_capture_time,
)


def _frame(i: int, w: int = 64, h: int = 48) -> np.ndarray:
    """A frame whose content encodes ``i`` (a bright square moving across a gradient), with read
    noise of its own as a live sensor gives (without it, frames of a scene that changes only in a
    small region are a frozen camera's: ``companion.service.freshness``)."""
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 1] = np.linspace(0, 200, w, dtype=np.uint8)[None, :]
    noise = np.random.default_rng(1000 + i).integers(0, 8, (h, w, 3), dtype=np.uint8)
    img = cv2.add(img, noise)
    x = (i * 5) % (w - 8)
    img[10:18, x:x + 8] = 255
    img[0, 0] = (i, i, i)
    return img


def _collect(cam: CameraSource) -> list:
    got: list = []
    cam.add_listener(got.append)
    return got


def _wait_until(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def test_folder_source_plays_every_frame_in_order(tmp_path: Path) -> None:
    for i in range(6):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), _frame(i))
    cam = CameraSource(str(tmp_path), fps=100)
    assert cam.kind is Kind.FOLDER
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert [f.index for f in got] == list(range(6))
    for i, f in enumerate(got):
        assert np.array_equal(f.image, _frame(i))  # PNG is lossless
    ts = [f.t for f in got]
    assert all(b > a for a, b in zip(ts, ts[1:]))
    # Played at ~100 fps, not as fast as the disk allows: 6 frames take >= 50 ms.
    assert ts[-1] - ts[0] >= 0.045
    assert cam.stats.corrupt == 0


def test_corrupt_frame_is_counted_and_dropped(tmp_path: Path) -> None:
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.jpg"), _frame(i))
    (tmp_path / "f001b.jpg").write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg" + bytes(200))
    (tmp_path / "f002b.png").write_bytes(b"")
    cam = CameraSource(str(tmp_path), fps=200)
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert cam.stats.corrupt == 2
    assert cam.stats.frames == 4
    assert len(got) == 4 and all(f.image.shape == (48, 64, 3) for f in got)


def test_video_file_source(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    assert vw.isOpened()
    for i in range(12):
        vw.write(_frame(i))
    vw.release()
    cam = CameraSource(str(path), fps=200)
    assert cam.kind is Kind.FILE
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert len(got) == 12
    for i, f in enumerate(got):
        # MJPG is lossy: compare loosely, but a wrong frame order would differ a lot.
        assert np.abs(f.image.astype(int) - _frame(i).astype(int)).mean() < 6


def test_newest_frame_only_and_dropped_count(tmp_path: Path) -> None:
    for i in range(10):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), _frame(i))
    cam = CameraSource(str(tmp_path), fps=200).start()
    assert _wait_until(lambda: cam.ended, 5)
    f = cam.take()
    assert f is not None and f.index == 9  # the newest, not the oldest
    assert cam.take() is None  # taken once
    assert cam.stats.dropped == 9
    cam.stop()


async def test_async_next_frame(tmp_path: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), _frame(i))
    cam = CameraSource(str(tmp_path), fps=5).start()
    try:
        f = await cam.next_frame(timeout=2.0)
        assert f is not None and f.image.shape == (48, 64, 3)
        g = await cam.next_frame(timeout=2.0)
        assert g is not None and g.index > f.index
    finally:
        cam.stop()


def test_bad_sources_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="no such file or folder"):
        classify(str(tmp_path / "missing.mp4"))
    with pytest.raises(CameraError, match="empty"):
        classify("  ")
    with pytest.raises(CameraError, match="holds no image files"):
        CameraSource(str(tmp_path))
    if not gstreamer_available():
        with pytest.raises(CameraError, match="built without GStreamer"):
            classify("gst:videotestsrc ! appsink")
    assert classify("/dev/video0") is Kind.V4L2
    assert classify("0") is Kind.V4L2
    assert classify("rtsp://127.0.0.1/x") is Kind.RTSP


class _MjpegServer:
    """A loopback MJPEG server. The first connection sends ``stall_after`` parts (one corrupt)
    and then goes silent with the socket open (a stalled camera); later connections stream."""

    def __init__(self) -> None:
        self.connections = 0
        self.sent = 0  # frames sent over all connections: a live camera's next one is new
        self.stop = threading.Event()
        self.stall_after = 5
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a: object) -> None:
                pass

            def do_GET(self) -> None:
                outer.connections += 1
                first = outer.connections == 1
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                i = 0
                try:
                    while not outer.stop.is_set():
                        if first and i >= outer.stall_after:
                            outer.stop.wait(10)  # silent, connection open
                            return
                        data = b"garbage, not a JPEG" if (first and i == 2) else \
                            cv2.imencode(".jpg", _frame(outer.sent))[1].tobytes()
                        outer.sent += 1
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\n"
                                         + f"Content-Length: {len(data)}\r\n\r\n".encode() + data + b"\r\n")
                        self.wfile.flush()
                        i += 1
                        time.sleep(0.02)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def test_mjpeg_stall_detected_and_reopened() -> None:
    server = _MjpegServer()
    cam = CameraSource(f"http://127.0.0.1:{server.port}/stream.mjpg", stall_timeout_s=0.5, max_backoff_s=0.5)
    assert cam.kind is Kind.MJPEG
    try:
        cam.start()
        assert _wait_until(lambda: cam.stats.frames >= 4, 5)
        assert cam.stats.corrupt == 1  # the garbage part was counted and dropped
        # The server goes silent: the source stops delivering, notices, and reconnects.
        assert _wait_until(lambda: not cam.delivering(), 3)
        assert _wait_until(lambda: cam.stats.reopens >= 1, 5)
        assert cam.stats.stalls >= 1
        n = cam.stats.frames
        assert _wait_until(lambda: cam.stats.frames >= n + 5 and cam.delivering(), 5)
        assert server.connections >= 2
    finally:
        cam.stop()
        server.close()


def test_lost_camera_retries_with_backoff() -> None:
    # A port nobody listens on: open fails, is retried, the thread never crashes.
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    cam = CameraSource(f"http://127.0.0.1:{port}/stream.mjpg", stall_timeout_s=0.3, max_backoff_s=0.2).start()
    try:
        assert _wait_until(lambda: cam.stats.open_failures >= 3, 5)
        assert not cam.delivering() and cam._thread is not None and cam._thread.is_alive()
    finally:
        cam.stop()


# ---- freshness: a repeated frame is never fresh (issue 12, item 7) ----------------------------


def test_repeated_frames_are_counted_not_delivered(tmp_path: Path) -> None:
    one_pixel = _frame(2).copy()
    one_pixel[3, 5] = (7, 7, 7)  # off the digest's subsample grid: the full check decides
    # frame 1 repeated twice, frame 2 once (a frozen encoder repeating its buffer), then a frame
    # that differs from frame 2 by a single pixel (no live sensor gives that: the history's
    # verdict, stale), then frame 3.
    images = [_frame(0), _frame(1), _frame(1), _frame(1), _frame(2), _frame(2), one_pixel, _frame(3)]
    for i, img in enumerate(images):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), img)
    cam = CameraSource(str(tmp_path), fps=200)
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert [f.index for f in got] == [0, 1, 2, 3]
    for f, img in zip(got, [_frame(0), _frame(1), _frame(2), _frame(3)]):
        assert np.array_equal(f.image, img)
    assert cam.stats.frames == 4
    assert cam.stats.repeated == 4 and cam.stats.stale == 1
    last = cam.take()
    assert last is not None and np.array_equal(last.image, _frame(3))


class _ScriptedMjpegServer:
    """A loopback MJPEG server whose ``script(connection)`` gives the parts of each connection
    (1-based): JPEG bytes, or None to go silent with the socket open (a stalled camera).
    ``stamp(part_bytes)`` may give an ``X-Timestamp`` header value for a part."""

    def __init__(self, script, period: float = 0.02, stamp=None) -> None:
        self.connections = 0
        self.parts_sent = 0
        self.stop = threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a: object) -> None:
                pass

            def do_GET(self) -> None:
                outer.connections += 1
                parts = script(outer.connections)
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for data in parts:
                        if outer.stop.is_set():
                            return
                        if data is None:
                            outer.stop.wait(10)  # silent, connection open
                            return
                        extra = "" if stamp is None else f"X-Timestamp: {stamp(data)}\r\n"
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\n"
                                         + f"Content-Length: {len(data)}\r\n{extra}\r\n".encode()
                                         + data + b"\r\n")
                        self.wfile.flush()
                        outer.parts_sent += 1
                        time.sleep(period)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()


@contextmanager
def scripted_camera(script, stamp=None, **camera) -> Iterator[tuple[_ScriptedMjpegServer, CameraSource, list]]:
    """A ``_ScriptedMjpegServer`` playing ``script`` (``stamp`` its X-Timestamp), a camera on it
    (``CameraSource(url, **camera)``, not started) and the list of the frames it delivers; the
    camera stopped and the server closed afterwards, whatever happened."""
    server = _ScriptedMjpegServer(script, stamp=stamp)
    cam = CameraSource(server.url, **camera)
    got = _collect(cam)
    try:
        yield server, cam, got
    finally:
        _stop_both(cam, server)


def _stop_both(cam: CameraSource, server: _ScriptedMjpegServer) -> None:
    """Stop the camera, then close the server: told to stop first (``stop(0)`` does not wait for
    its thread), a reader blocked on a silent part reads the end of the closed connection and
    ends, rather than ``stop()`` waiting its 2 s for a read timed out only after
    ``stall_timeout_s``; nothing is reopened once it is told to stop."""
    cam.stop(0.0)
    server.close()
    cam.stop()


def _jpeg(i: int) -> bytes:
    return cv2.imencode(".jpg", _frame(i))[1].tobytes()


def _decoded(data: bytes) -> bytes:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).tobytes()


_WHICH = {_decoded(_jpeg(i)): i for i in range(64)}


def _which(image: np.ndarray) -> int:
    """The i of the ``_jpeg(i)`` a delivered image was decoded from."""
    return _WHICH[image.tobytes()]


def test_a_camera_repeating_one_frame_is_not_delivering() -> None:
    # Three fresh frames, then the encoder freezes and repeats its last buffer at 50 fps, also
    # after a reconnect.
    def script(conn: int):
        if conn == 1:
            yield from (_jpeg(i) for i in range(3))
        while True:
            yield _jpeg(2)

    with scripted_camera(script, stall_timeout_s=0.5, max_backoff_s=0.2) as (_, cam, got):
        cam.start()
        assert _wait_until(lambda: cam.stats.frames >= 3, 5)
        # Frames keep arriving, all repeats: the camera is not delivering, and it is treated as
        # stalled (closed and reopened) rather than as a healthy camera.
        assert _wait_until(lambda: not cam.delivering(), 3)
        assert cam.stats.frames == 3 and len(got) == 3
        assert cam.stats.repeated >= 10
        assert _wait_until(lambda: cam.stats.stalls >= 1, 3)
        assert _wait_until(lambda: cam.stats.reopens >= 1, 3)
        n = cam.stats.repeated
        assert _wait_until(lambda: cam.stats.repeated > n, 3)  # the reopened camera: repeats too
        assert not cam.delivering()
        assert cam.stats.frames == 3 and len(got) == 3
        f = cam.take()
        assert f is not None and f.index == 2 and cam.take() is None


def test_frozen_camera_reserving_its_last_frame_after_reconnect_is_not_fresh() -> None:
    # The audit's frozen camera: five frames, a stall, then on every reconnect it serves the last
    # frame again and goes silent. Old behaviour: one stale frame per reconnect, health ok.
    def script(conn: int):
        if conn == 1:
            yield from (_jpeg(i) for i in range(5))
        else:
            yield _jpeg(4)
        yield None

    with scripted_camera(script, stall_timeout_s=0.4, max_backoff_s=0.2) as (_, cam, got):
        cam.start()
        assert _wait_until(lambda: cam.stats.frames >= 5, 5)
        # The served repeats are counted by the reader thread a moment after they are sent.
        assert _wait_until(lambda: cam.stats.reopens >= 2 and cam.stats.repeated >= 2, 6)
        assert [_which(f.image) for f in got] == list(range(5))  # no stale frame after a reconnect
        assert cam.stats.frames == 5
        assert not cam.delivering()


def test_camera_that_resumes_after_reserving_its_last_frame_delivers_only_new_frames() -> None:
    # Reconnect: the stale last frame first (not fresh), then live frames again (fresh).
    def script(conn: int):
        if conn == 1:
            yield from (_jpeg(i) for i in range(4))
            yield None
        else:
            yield _jpeg(3)
            yield from (_jpeg(i) for i in range(10, 40))
            yield None

    with scripted_camera(script, stall_timeout_s=0.4, max_backoff_s=0.2) as (_, cam, got):
        cam.start()
        assert _wait_until(lambda: cam.stats.frames >= 10, 6)
        which = [_which(f.image) for f in got]
        assert which[:4] == [0, 1, 2, 3] and which[4] >= 10
        assert all(i >= 10 for i in which[4:])
        assert cam.stats.repeated == 1 and cam.stats.reopens >= 1
        assert cam.delivering()


# ---- capture timestamps ----------------------------------------------------------------------


def test_mjpeg_x_timestamp_on_our_clock_is_the_capture_time() -> None:
    sent: dict[bytes, float] = {}

    def stamp(data: bytes) -> str:
        t = time.monotonic() - 0.05  # captured 50 ms before it was sent
        sent[data] = t
        return f"{t:.6f}"

    with scripted_camera(lambda conn: (_jpeg(i) for i in range(8)), stamp=stamp,
                         stall_timeout_s=2.0) as (_, cam, got):
        cam.start()
        assert _wait_until(lambda: len(got) >= 8, 5)
    for f in got:
        assert f.t_source == "header"
        assert f.t == pytest.approx(sent[_jpeg(_which(f.image))], abs=2e-6)
        # The recorder stores an MJPEG camera's own bytes (no second encoding): each frame
        # carries exactly the part it was decoded from.
        assert f.jpeg == _jpeg(_which(f.image))
        assert np.array_equal(cv2.imdecode(np.frombuffer(f.jpeg, np.uint8), cv2.IMREAD_COLOR), f.image)
    assert cam.stats.last_frame_t == got[-1].t


def test_mjpeg_timestamp_on_another_clock_falls_back_to_grab_time(caplog: pytest.LogCaptureFixture) -> None:
    # mjpg-streamer-like servers may stamp wall-clock time (or another machine's clock): unusable.
    with scripted_camera(lambda conn: (_jpeg(i) for i in range(6)), stamp=lambda data: f"{time.time():.6f}",
                         stall_timeout_s=2.0) as (_, cam, got):
        with caplog.at_level("WARNING", logger="companion.service.camera"):
            before = time.monotonic()
            cam.start()
            assert _wait_until(lambda: len(got) >= 6, 5)
    assert all(f.t_source == "grab" and before <= f.t <= time.monotonic() for f in got)
    warned = [r for r in caplog.records if "not on this machine's monotonic clock" in r.getMessage()]
    assert len(warned) == 1  # said once, not per frame


def test_sources_without_timestamps_use_grab_time(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(4):
        vw.write(_frame(i))
    vw.release()
    cam = CameraSource(str(path), fps=100)  # a file's position is media time, never a capture time
    got = _collect(cam)
    before = time.monotonic()
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert len(got) == 4 and all(f.t_source == "grab" and f.t >= before for f in got)
    assert all(f.jpeg is None for f in got)  # decoded by OpenCV: no bytes to store as they came


def test_plausible_capture_time() -> None:
    now = 1000.0
    assert plausible_capture_time(now - 0.02, now, None)
    assert plausible_capture_time(now - 0.02, now, now - 0.1)
    assert not plausible_capture_time(now + 0.5, now, None)  # in the future
    assert not plausible_capture_time(now - 1.5, now, None)  # too old (or another clock)
    assert not plausible_capture_time(1.7e9, now, None)  # wall-clock time
    assert not plausible_capture_time(now - 0.02, now, now - 0.01)  # not after the previous frame

