"""The service's HTTP server over real sockets: the MJPEG live view of real pipeline results (the
shipped model on a rendered crowd), the status JSON and page, bad requests, slow and broken
clients, a port in use, and the live.* settings."""

from __future__ import annotations

import asyncio
import json
import math
import socket
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import config, synthetic
from companion.config import ConfigError, LiveSettings
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from companion.replay.live_figure import CAPTION_PX
from companion.service import web
from companion.service.web import LiveView, Snapshot, WebServer, live_video_stream, stream_uri
from tests import early


@pytest.fixture(scope="module")
def results(model_path):
    """Real pipeline results: the shipped model over a rendered crowd seen from 20 m."""
    scene = synthetic.crowd_scene(640, 480, n_people=120, free=((200, 240, 90),), seed=3)
    frame = synthetic.render(scene, seed=3)
    pipe = SLZPipeline(DensityModel(model_path, threads=1), PipelineConfig(),
                       intrinsics=Intrinsics.from_fov(640, 480, 70.0), mount=Mount())
    out = []
    for k in range(6):
        t = k / 10.0
        out.append(pipe.process(frame, t, Pose(t, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)))
    assert out[-1].tracks, "the rendered free area should be tracked"
    return frame, out


def status() -> dict:
    return {"phase": "MONITOR", "zones": [{"id": 1}], "decisions": []}


async def serve(live: LiveView, settings: LiveSettings | None = None) -> WebServer:
    server = WebServer(settings or LiveSettings(enabled=True, port=0), live, status)
    await server.start()
    return server


async def get(port: int, request: bytes) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request)
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), 5.0)
    writer.close()
    return data


async def test_the_live_view_streams_the_figure_of_real_results_only_while_watched(results):
    frame, res = results
    live = LiveView(max_fps=100.0)
    server = await serve(live)
    drawer = asyncio.create_task(live.run())
    try:
        snap = Snapshot(frame, res[-1], res[-1].tracks[0].id, "MONITOR  zones 1")
        for k in range(5):  # nobody watches: nothing is drawn
            assert not live.wants(k)
            live.offer(snap, float(k))
        await asyncio.sleep(0.2)
        assert live.stats.drawn == 0
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 2.0)
        assert b"multipart/x-mixed-replace; boundary=slzframe" in head
        while not live.clients:
            await asyncio.sleep(0.01)
        live.offer(snap, 10.0)
        part = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10.0)
        assert part.startswith(b"--slzframe\r\nContent-Type: image/jpeg")
        size = int(part.split(b"Content-Length: ")[1].split(b"\r\n")[0])
        img = cv2.imdecode(np.frombuffer(await reader.readexactly(size), np.uint8), cv2.IMREAD_COLOR)
        # The figure: caption band over the frame and its head-plane view, side by side.
        assert img.shape == (480 + CAPTION_PX, 640 + 4 + 480, 3)
        assert live.stats.drawn == 1 and live.draw_ms[0] > 0
        live.offer(snap, 10.001)  # faster than max_fps: not drawn
        assert live.stats.drawn == 1
        writer.close()
    finally:
        drawer.cancel()
        await server.close()


async def test_a_slow_client_loses_frames_a_stalled_one_is_dropped_and_nobody_waits(results, monkeypatch):
    frame, res = results
    monkeypatch.setattr(web, "SEND_TIMEOUT_S", 0.5)
    live = LiveView(max_fps=1000.0)
    server = await serve(live)
    try:
        # A client that connects and never reads.
        stalled = socket.create_connection(("127.0.0.1", server.port))
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.sendall(b"GET /stream.mjpg HTTP/1.1\r\n\r\n")
        while not live.clients:
            await asyncio.sleep(0.01)
        big = bytes(np.random.default_rng(0).integers(0, 255, 200_000, dtype=np.uint8))
        worst = 0.0
        for _ in range(100):
            t0 = time.perf_counter()
            live.publish(big)  # what the drawer does with each frame
            worst = max(worst, time.perf_counter() - t0)
            await asyncio.sleep(0.01)
        assert worst < 0.05, f"publishing waited {worst:.3f} s on a client"
        assert live.stats.dropped > 10
        deadline = time.monotonic() + 5
        while live.clients and time.monotonic() < deadline:
            live.publish(big)
            await asyncio.sleep(0.05)
        assert live.clients == 0 and live.stats.clients_dropped == 1
        stalled.close()
        # The server still answers.
        assert b"200 OK" in await get(server.port, b"GET /status.json HTTP/1.1\r\n\r\n")
    finally:
        await server.close()


async def test_the_page_the_json_and_bad_requests(monkeypatch):
    monkeypatch.setattr(web, "REQUEST_TIMEOUT_S", 0.3)
    live = LiveView(max_fps=5.0)
    server = await serve(live)
    try:
        page = await get(server.port, b"GET / HTTP/1.1\r\n\r\n")
        assert page.startswith(b"HTTP/1.1 200 OK") and b'<img id="live" src="/stream.mjpg"' in page
        js = await get(server.port, b"GET /status.json HTTP/1.1\r\n\r\n")
        assert json.loads(js.split(b"\r\n\r\n", 1)[1]) == status()
        assert (await get(server.port, b"GET /nope HTTP/1.1\r\n\r\n")).startswith(b"HTTP/1.1 404")
        assert (await get(server.port, b"POST / HTTP/1.1\r\n\r\n")).startswith(b"HTTP/1.1 405")
        assert (await get(server.port, b"\x00\xff garbage\r\n\r\n")).startswith(b"HTTP/1.1 400")
        assert await get(server.port, b"GET / HTTP/1.1\r\n") == b""  # never finished: closed
        assert await get(server.port, b"GET /" + b"a" * 20000 + b" HTTP/1.1\r\n\r\n") == b""  # too long
        assert server.bad_requests >= 3
        assert (await get(server.port, b"GET / HTTP/1.1\r\n\r\n")).startswith(b"HTTP/1.1 200")
    finally:
        await server.close()


async def test_a_port_in_use_leaves_the_service_running_without_the_page(model_path):
    from companion.service.app import Service
    from companion.service.parts import load_model

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        cfg = config.load(None, {"live.enabled": True, "live.port": port})
        svc = Service(cfg, load_model(cfg))
        await svc._start_web()
        assert svc.web is None and svc.web_error is not None and str(port) in svc.web_error
        texts = svc._ready_texts()
        assert texts[-1].startswith("SLZ: status page off: 127.0.0.1:") and len(texts[-1]) <= 50


async def test_the_stream_is_announced_only_while_served(model_path):
    from companion.service.app import Service
    from companion.service.parts import load_model

    on = LiveSettings(enabled=True, address="127.0.0.1", port=8090)
    stream = live_video_stream(on, 1124, 508)
    assert stream.uri == "http://127.0.0.1:8090/stream.mjpg" and (stream.width, stream.height) == (1124, 508)
    assert math.isclose(stream.framerate_hz, 5.0)
    assert stream_uri(LiveSettings(address="0.0.0.0", port=9000)).endswith(":9000/stream.mjpg")
    # The service's provider for the camera protocol: None until the page is served.
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = config.load(None, {"live.enabled": True, "live.port": port})
    svc = Service(cfg, load_model(cfg))
    assert svc.commands.video() is None
    await svc._start_web()
    try:
        got = svc.commands.video()
        assert got is not None and got.uri == f"http://127.0.0.1:{port}/stream.mjpg"
        assert (got.width, got.height) == (640 + 4 + 480, 480 + CAPTION_PX)
    finally:
        assert svc.web is not None
        await svc.web.close()
    off = Service(config.load(None, {}), svc.model)
    assert off.commands.video() is None


@pytest.mark.parametrize("key, value, says", [
    ("live.port", 70000, "live.port must be >= 1 and <= 65535"),
    ("live.enabled", "maybe", "live.enabled must be true or false"),
    ("live.max_fps", 5, "live.max_fps was removed"),
    ("live.address", "", "live.address must be"),
    ("live.colour", 1, "unknown key 'live.colour'"),
    ("gcs.values_hz", 50, "gcs.values_hz must be >= 0.0 and <= 10.0"),
])
def test_a_wrong_live_or_gcs_setting_names_the_key(key, value, says):
    with pytest.raises(ConfigError, match=says.replace(".", r"\.")):
        config.load(None, {key: value})


@early.batch("run-wrong-live-port")
def _run_wrong_live_port(folder: Path) -> list[early.Run]:
    return [early.Run([sys.executable, "-m", "companion", "run", "--set", "live.port=99999"])]


@pytest.mark.started_early("run-wrong-live-port")  # a Python started beside the tests before it (tests/early.py)
def test_companion_run_exits_2_on_a_wrong_live_setting():
    (proc,) = early.result("run-wrong-live-port")[1]
    assert proc.returncode == 2 and "live.port" in proc.stderr, proc.stderr


async def _parts(reader: asyncio.StreamReader, n: int, timeout: float) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        part = (await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), timeout)).lstrip(b"\r\n")
        assert part.startswith(b"--slzframe\r\nContent-Type: image/jpeg")
        size = int(part.split(b"Content-Length: ")[1].split(b"\r\n")[0])
        out.append(cv2.imdecode(np.frombuffer(await reader.readexactly(size), np.uint8), cv2.IMREAD_COLOR))
    return out


async def test_a_frame_the_pipeline_cannot_use_is_shown_raw_and_no_frame_at_all_gives_a_placeholder(results):
    """On the ground the pipeline refuses every frame: the stream shows the camera's frame with
    the reason; with no frame at all a placeholder comes every IDLE_S, so a browser never waits on
    a silent stream (a headless Chromium screenshot after landing never finished before)."""
    frame, _ = results
    live = LiveView(max_fps=100.0)
    server = WebServer(LiveSettings(enabled=True, port=0), live,
                       lambda: {"health": {"ok": False, "reason": "camera not delivering"}})
    await server.start()
    drawer = asyncio.create_task(live.run())
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
        await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 2.0)
        t0 = time.monotonic()
        placeholders = await _parts(reader, 2, 5.0)  # nothing offered: placeholders, at IDLE_S
        assert time.monotonic() - t0 < 2 * web.IDLE_S + 2.0
        assert all(p.shape == (480 + CAPTION_PX, 640 + 4 + 480, 3) for p in placeholders)
        assert all(p.mean() < 40 for p in placeholders) and live.stats.drawn == 0
        live.offer(Snapshot(frame, None, None, "MONITOR  no target", "on the ground"), 100.0)
        (raw,) = await _parts(reader, 1, 10.0)
        assert live.stats.drawn == 1 and raw.shape == placeholders[0].shape
        # The camera's frame as it came, beside a dark panel with the reason.
        diff = np.abs(raw[CAPTION_PX:, :640].astype(int) - frame.astype(int)).mean()
        assert diff < 8, diff
        assert raw[CAPTION_PX:, 644:].mean() < 40
        writer.close()
    finally:
        drawer.cancel()
        await server.close()
