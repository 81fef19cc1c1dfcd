"""Health tells when frames cannot be decided with (issue 61 item 6, issue 62 item 2): with no
pose, a stale pose, the vehicle on the ground or a frozen camera, health is never "ok"; the state's
name reaches the ground station (HEARTBEAT system_status, one STATUSTEXT per change) and systemd's
status line; the status page's numbers and the live view on the ground. The service runs in-process with the real model and pipeline against a pymavlink peer
on loopback that streams a vehicle's telemetry the test controls."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config
from companion.mavlink.link import MavLink
from companion.mavlink.statustext import TextPacer
from companion.replay.live_figure import CAPTION_PX
from companion.service.app import Service
from companion.service.freshness import HISTORY
from companion.service.parts import load_model
from sim.flights.flight import PortClaim, reserve_port
from tests.companion.service.test_freshness import _clock_frames
from tests.companion.service.test_landing_runner import Vehicle
from tests.mavpeer import MavPeer


def _live_frames(folder: Path) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(HISTORY + 4):  # more than the freshness history: the loop plays as live
        cv2.imwrite(str(folder / f"{i:04d}.png"), rng.integers(80, 120, (480, 640, 3), dtype=np.uint8))
    return folder


class Rig:
    """The service and its autopilot peer."""

    def __init__(self, svc: Service, peer: MavPeer, vehicle: Vehicle) -> None:
        self.svc, self.peer, self.vehicle = svc, peer, vehicle

    def system_status(self) -> int:
        """The system_status of the companion's latest HEARTBEAT, as the peer heard it."""
        return int([h for h in self.peer.of_type("HEARTBEAT") if h.type == m.MAV_TYPE_ONBOARD_CONTROLLER][-1]
                   .system_status)

    def texts(self) -> list[str]:
        return [t for _, t in self.peer.statustexts()]

    async def until(self, pred: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            assert time.monotonic() < deadline, (f"timed out waiting for {what}: health "
                                                 f"{self.svc.health(time.monotonic()).reason!r}, "
                                                 f"texts {self.texts()}, counters {self.svc.counters}")
            await asyncio.sleep(0.05)


async def _first_part(port: int) -> np.ndarray:
    """The first image of the live view's MJPEG stream, decoded (BGR)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
    try:
        await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5.0)
        part = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5.0)
        size = int(part.split(b"Content-Length: ")[1].split(b"\r\n")[0])
        data = await asyncio.wait_for(reader.readexactly(size), 5.0)
    finally:
        writer.close()
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


async def _run(tmp_path: Path, frames: Path, body, telemetry: bool = True) -> None:
    with reserve_port(socket.SOCK_STREAM) as page:  # the status page's port, claimed meanwhile
        await _run_on(page, frames, body, telemetry)


async def _run_on(page: PortClaim, frames: Path, body, telemetry: bool) -> None:
    peer = MavPeer(custom_mode=5)
    host, port = await peer.listen_udp()
    cfg = config.load(None, {"link.url": f"udpout:{host}:{port}", "link.flavour": "ardupilot",
                             "camera.source": str(frames), "camera.loop": True, "camera.fps": 5.0,
                             "camera.stall_timeout_s": 1.0, "live.enabled": True, "live.port": page.port})
    svc = Service(cfg, load_model(cfg), link=MavLink(config.link_config(cfg)))
    # The ground station's texts are paced (companion.mavlink.statustext: at most 4 in 10 s, 1 s
    # apart, a condition's next text 5 s after its last; test_statustext_pacing tests that). Here
    # 4 in 2 s, 0.2 s apart and 1 s, given as the service's GroundStation takes a pace, so the
    # test waits for the texts, not for the pace: each change is still told once, as asserted.
    svc.gcs.outbox.pacer = TextPacer(window_s=2.0, min_gap_s=0.2, repeat_s=1.0)
    svc.gcs.conditions.min_gap_s = 1.0
    task = asyncio.create_task(svc.run())
    vehicle = Vehicle(peer)
    rig = Rig(svc, peer, vehicle)
    try:
        deadline = time.monotonic() + 20.0
        while svc.monitor is None or not svc.gcs.ready:  # the peer answers once the link has written
            assert time.monotonic() < deadline, "the service never got ready"
            if peer._udp_peer is not None and peer._hb_task is None:
                peer.start_heartbeats(0.1)
                if telemetry:
                    vehicle.start()
            await asyncio.sleep(0.05)
        await body(rig)
    finally:
        vehicle.stop()
        svc.request_stop("test")
        assert await asyncio.wait_for(task, 10.0) == 0
        await peer.close()


@pytest.mark.timeout(120)
async def test_health_names_why_frames_cannot_be_used_and_tells_the_pilot(tmp_path: Path, model_path: Path) -> None:
    async def body(rig: Rig) -> None:
        svc = rig.svc
        # Airborne with a pose: frames are used, health ok, ACTIVE.
        await rig.until(lambda: svc.counters.processed >= 3 and svc.health(time.monotonic()).ok, "frames in use")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_ACTIVE, "ACTIVE")

        # The telemetry stops (heartbeats go on): every frame lacks a pose. Not "ok" any more.
        rig.vehicle.stop()
        await rig.until(lambda: svc.health(time.monotonic()).reason == "stale pose", "stale pose")
        await rig.until(lambda: "SLZ: frames not used: stale pose" in rig.texts(), "its STATUSTEXT")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_CRITICAL, "CRITICAL")
        await rig.until(lambda: svc.notifier.last_status.startswith("degraded: stale pose; MONITOR"), "STATUS=")
        assert svc.link.connected  # the link is up: it is the pose that is missing

        # The vehicle is back, on the ground: frames from below the head plane cannot be used.
        rig.vehicle.alt, rig.vehicle.on_ground = 0.0, True
        rig.vehicle._task = None
        rig.vehicle.start()
        await rig.until(lambda: svc.health(time.monotonic()).reason == "on the ground", "on the ground", 15)
        await rig.until(lambda: "SLZ: standby, on the ground" in rig.texts(), "its STATUSTEXT")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_STANDBY, "STANDBY")
        await rig.until(lambda: svc.notifier.last_status.startswith("standby: on the ground; MONITOR"), "STATUS=")
        s = svc.status_json()
        assert s["health"]["reason"] == "on the ground" and s["health"]["standby"] and not s["health"]["ok"]
        # The page's numbers on the ground: height, the autopilot's mode, armed, no trigger, no
        # handback, and no clearance figure from 0 m (the judging height is 10 m: shown below it).
        v = s["vehicle"]
        assert abs(v["height_m"]) < 0.5 and v["mode"] == "LOITER" and v["armed"] is True, v
        assert v["trigger"] is None and v["handback"] is None and v["height_agl_m"] is None, v
        assert s["clearance_note"] is None
        # The live view on the ground: the raw camera frame with the reason, not a blank stream.
        image = await _first_part(svc.web.port)
        assert image.shape == (480 + CAPTION_PX, 640 + 4 + 480, 3)
        # The left part is the camera's frame (80..120 grey noise), not a placeholder's dark fill.
        assert 80 <= float(image[CAPTION_PX:, :640].mean()) <= 120
        assert svc.live is not None and svc.live.stats.drawn >= 1

        # Airborne again: frames used, ok, ACTIVE, and the pilot is told.
        rig.vehicle.alt, rig.vehicle.on_ground = 30.0, False
        await rig.until(lambda: svc.health(time.monotonic()).ok, "ok again", 15)
        s = svc.status_json()
        assert abs(s["vehicle"]["height_m"] - 30.0) < 1.0 and s["clearance_note"] == "n/a above 10 m (judged there)"
        await rig.until(lambda: "SLZ: airborne, frames used" in rig.texts(), "its STATUSTEXT")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_ACTIVE, "ACTIVE again")
        # One text per change, not one per frame.
        texts = rig.texts()
        assert texts.count("SLZ: frames not used: stale pose") == 1, texts
        assert texts.count("SLZ: standby, on the ground") == 1, texts

    await _run(tmp_path, _live_frames(tmp_path / "frames"), body)


@pytest.mark.timeout(90)
async def test_no_pose_at_all_is_told(tmp_path: Path, model_path: Path) -> None:
    """Heartbeats but never any telemetry: "no pose", not "ok"."""
    async def body(rig: Rig) -> None:
        await rig.until(lambda: rig.svc.health(time.monotonic()).reason == "no pose", "no pose")
        await rig.until(lambda: "SLZ: frames not used: no pose" in rig.texts(), "its STATUSTEXT")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_CRITICAL, "CRITICAL")
        assert rig.svc.counters.processed == 0 and rig.svc.counters.no_pose > 5

    await _run(tmp_path, _live_frames(tmp_path / "frames"), body, telemetry=False)


@pytest.mark.timeout(90)
async def test_a_frozen_camera_is_told_as_frozen(tmp_path: Path, model_path: Path) -> None:
    """A frozen image with a live clock drawn on it: its frames are stale, none is used after the
    first, and health says "camera frozen", not "camera not delivering" and never "ok"."""
    folder = tmp_path / "clock"
    folder.mkdir()
    for i, data in enumerate(_clock_frames(40)):
        (folder / f"f{i:04d}.jpg").write_bytes(data)

    async def body(rig: Rig) -> None:
        await rig.until(lambda: rig.svc.health(time.monotonic()).reason == "camera frozen", "camera frozen")
        await rig.until(lambda: "SLZ: camera frozen: no landing zones" in rig.texts(), "its STATUSTEXT")
        await rig.until(lambda: rig.system_status() == m.MAV_STATE_CRITICAL, "CRITICAL")
        assert rig.svc.camera.stats.stale >= 5 and rig.svc.camera.stats.frames == 1
        assert rig.svc.counters.processed <= 1

    await _run(tmp_path, folder, body)
