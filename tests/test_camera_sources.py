"""Camera sources with real files, a real MJPEG-over-HTTP server on loopback and real OpenCV."""

from __future__ import annotations

import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.service.camera import CameraError, CameraSource, Kind, classify, gstreamer_available


def _frame(i: int, w: int = 64, h: int = 48) -> np.ndarray:
    """A frame whose content encodes ``i`` (a bright square moving across a gradient)."""
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 1] = np.linspace(0, 200, w, dtype=np.uint8)[None, :]
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
                            cv2.imencode(".jpg", _frame(i))[1].tobytes()
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
