"""Every command a ground station addresses to the companion gets an answer (issue 18, item 2).

Real MAVLink on loopback: the companion's link with its ``CommandServer`` and failsafe monitor
(and, at the end, the whole ``Service`` as ``companion run`` builds it), a pymavlink peer standing
in for the flight controller, and ground-station packets sent from that peer's socket as a real
autopilot would forward them.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config
from companion.control.trigger import TriggerSource
from companion.mavlink.failsafe import FailsafeConfig, FailsafeMonitor
from companion.mavlink.gcs_commands import NO_LIVE_VIEW_TEXT, CameraInfo, CommandServer, VideoStream
from companion.mavlink.link import LinkConfig, MavLink
from companion.service.app import Service
from companion.service.parts import load_model
from tests.mavpeer import MavPeer

pytestmark = pytest.mark.timeout(60)

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.5, command_timeout_s=0.2, command_retries=1)
STREAM = VideoStream("http://192.168.1.20:8090/live.mjpg", 640, 480, 10.0, hfov_deg=70.0)


class Gcs:
    """A ground station (``system_id``/190) talking through the autopilot peer's socket."""

    def __init__(self, peer: MavPeer, system_id: int = 255) -> None:
        self.peer = peer
        self.mav = m.MAVLink(peer, srcSystem=system_id, srcComponent=190)
        self.system_id = system_id

    async def command(self, command: int, *params: float, target=(1, 191), use_int: bool = False,
                      timeout: float = 1.0):
        """Send a command; the ack addressed back to us (TimeoutError if none)."""
        start = len(self.peer.received)
        p = list(params) + [0.0] * (7 - len(params))
        if use_int:
            self.mav.command_int_send(*target, 0, command, 0, 0, *p[:4], int(p[4]), int(p[5]), p[6])
        else:
            self.mav.command_long_send(*target, command, 0, *p)
        ack = await self.peer.wait_for(
            "COMMAND_ACK", lambda a: a.command == command and a.target_system == self.system_id,
            timeout=timeout, start=start)
        return ack, start

    def after(self, start: int, msg_type: str) -> list:
        return [msg for msg, _ in self.peer.received[start:] if msg.get_type() == msg_type]


@pytest.fixture
async def rig():
    made = []

    async def make(video=lambda: None, camera: CameraInfo | None = CameraInfo(640, 480)):
        link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
        await link.start()
        peer = MavPeer()
        await peer.connect_udp(link.local_address)
        peer.heartbeat()
        await link.wait_connected(2.0)
        server = CommandServer(link, camera=camera, video=video)
        server.attach()
        monitor = FailsafeMonitor(FailsafeConfig(gcs_system_ids=(255,)), link)
        monitor.attach(server)
        fired: list = []
        monitor.subscribe(fired.append)
        made.append((link, peer))
        return server, peer, fired

    yield make
    for link, peer in made:
        await peer.close()
        await link.close()


async def test_camera_information_on_request_message_and_the_legacy_command(rig):
    server, peer, _ = await rig(camera=CameraInfo(1280, 720, focal_length_mm=4.0, sensor_width_mm=6.4,
                                                  sensor_height_mm=3.6, vendor="Arducam", model="IMX477"))
    gcs = Gcs(peer)
    for command, params in ((m.MAV_CMD_REQUEST_MESSAGE, (m.MAVLINK_MSG_ID_CAMERA_INFORMATION,)),
                            (m.MAV_CMD_REQUEST_CAMERA_INFORMATION, (1,))):
        ack, start = await gcs.command(command, *params)
        assert ack.result == m.MAV_RESULT_ACCEPTED and ack.get_srcComponent() == 191
        info = await peer.wait_for("CAMERA_INFORMATION", timeout=1.0, start=start)
        assert (info.resolution_h, info.resolution_v) == (1280, 720)
        assert info.focal_length == pytest.approx(4.0) and info.sensor_size_h == pytest.approx(6.4)
        assert bytes(info.vendor_name).rstrip(b"\0") == b"Arducam" and bytes(info.model_name).rstrip(b"\0") == b"IMX477"
        assert info.flags == 0  # no live view: no HAS_VIDEO_STREAM


async def test_unknown_commands_get_unsupported_and_broadcasts_only_what_we_handle(rig):
    server, peer, fired = await rig()
    gcs = Gcs(peer)
    ack, _ = await gcs.command(m.MAV_CMD_DO_SET_SERVO, 9, 1500)
    assert ack.result == m.MAV_RESULT_UNSUPPORTED
    ack, _ = await gcs.command(m.MAV_CMD_DO_SET_SERVO, 9, 1500, use_int=True)
    assert ack.result == m.MAV_RESULT_UNSUPPORTED
    ack, _ = await gcs.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == m.MAV_RESULT_UNSUPPORTED  # a message the companion does not provide
    # Broadcast to every component: answered for what the companion handles, silent otherwise.
    ack, start = await gcs.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_CAMERA_INFORMATION, target=(1, 0))
    assert ack.result == m.MAV_RESULT_ACCEPTED and gcs.after(start, "CAMERA_INFORMATION")
    for command in (m.MAV_CMD_DO_SET_SERVO, m.MAV_CMD_USER_1, m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION):
        with pytest.raises(TimeoutError):
            await gcs.command(command, target=(1, 0), timeout=0.3)
    # For another component or system: not ours.
    with pytest.raises(TimeoutError):
        await gcs.command(m.MAV_CMD_DO_SET_SERVO, target=(1, 1), timeout=0.3)
    with pytest.raises(TimeoutError):
        await gcs.command(m.MAV_CMD_DO_SET_SERVO, target=(2, 191), timeout=0.3)
    assert fired == [] and server.stats.not_ours == 2 and server.stats.silent == 3
    assert peer.commands == []  # nothing a ground station asked became a command to the vehicle


async def test_a_refused_trigger_gets_denied_and_the_reason(rig):
    server, peer, fired = await rig()
    ack, start = await Gcs(peer, system_id=42).command(m.MAV_CMD_USER_1)
    assert ack.result == m.MAV_RESULT_DENIED and fired == []
    text = await peer.wait_for("STATUSTEXT", lambda s: "refused" in s.text, timeout=1.0, start=start)
    assert text.text == "SLZ: trigger refused: system 42 not a GCS" and len(text.text) <= 50
    assert text.get_srcComponent() == 191
    # The same refusal again at once: acked again, the text not repeated (no flood on the radio).
    ack, start = await Gcs(peer, system_id=42).command(m.MAV_CMD_USER_1)
    assert ack.result == m.MAV_RESULT_DENIED
    await asyncio.sleep(0.2)
    assert not Gcs(peer).after(start, "STATUSTEXT")
    # From the ground station: accepted, the ack before the trigger fires, once.
    ack, _ = await Gcs(peer).command(m.MAV_CMD_USER_1)
    assert ack.result == m.MAV_RESULT_ACCEPTED and [t.source for t in fired] == [TriggerSource.GCS_COMMAND]


async def test_video_stream_information_without_and_with_a_live_view(rig):
    server, peer, _ = await rig()
    gcs = Gcs(peer)
    for command, params in ((m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, (0,)),
                            (m.MAV_CMD_REQUEST_MESSAGE, (m.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,))):
        ack, start = await gcs.command(command, *params)
        assert ack.result == m.MAV_RESULT_UNSUPPORTED
    text = await peer.wait_for("STATUSTEXT", lambda s: s.text == NO_LIVE_VIEW_TEXT, timeout=1.0)
    assert text.severity == m.MAV_SEVERITY_WARNING

    live = {"stream": None}
    server, peer, _ = await rig(video=lambda: live["stream"])
    gcs = Gcs(peer)
    ack, _ = await gcs.command(m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 1)
    assert ack.result == m.MAV_RESULT_UNSUPPORTED
    live["stream"] = STREAM  # the live view starts
    for command, params in ((m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, (1,)),
                            (m.MAV_CMD_REQUEST_MESSAGE, (m.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION, 1))):
        ack, start = await gcs.command(command, *params)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        info = await peer.wait_for("VIDEO_STREAM_INFORMATION", timeout=1.0, start=start)
        assert info.uri == STREAM.uri and (info.resolution_h, info.resolution_v) == (640, 480)
        assert info.framerate == pytest.approx(10.0) and info.hfov == 70 and info.stream_id == 1
        assert info.flags & m.VIDEO_STREAM_STATUS_FLAGS_RUNNING
    ack, start = await gcs.command(m.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1)
    info = await peer.wait_for("CAMERA_INFORMATION", timeout=1.0, start=start)
    assert info.flags & m.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    ack, _ = await gcs.command(m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 2)
    assert ack.result == m.MAV_RESULT_DENIED  # we have one stream


def test_a_video_stream_must_fit_mavlink():
    with pytest.raises(ValueError, match="uri"):
        VideoStream("http://x/" + "a" * 200, 640, 480, 10.0)
    with pytest.raises(ValueError, match="framerate"):
        VideoStream("http://x/live", 640, 480, math.nan)


async def test_forged_and_malformed_commands_are_counted_and_refused_never_raised(rig):
    server, peer, fired = await rig()
    gcs = Gcs(peer)
    ack, _ = await gcs.command(m.MAV_CMD_REQUEST_MESSAGE, math.nan)
    assert ack.result == m.MAV_RESULT_DENIED
    ack, _ = await gcs.command(m.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1e30)
    assert ack.result == m.MAV_RESULT_DENIED
    assert server.stats.malformed == 2
    peer.send_raw(bytes(range(200)))  # noise
    # Still answering, nothing fired, nothing sent to the vehicle.
    ack, _ = await gcs.command(m.MAV_CMD_DO_SET_SERVO)
    assert ack.result == m.MAV_RESULT_UNSUPPORTED and fired == [] and peer.commands == []
    assert server.link.stats.handler_errors == 0


# ----- the service as companion run builds it ------------------------------------------------------


async def test_the_service_answers_camera_and_video_requests(tmp_path: Path, model_path: Path):
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "0000.png"), np.full((480, 640, 3), 90, np.uint8))
    peer = MavPeer()
    port = (await peer.listen_udp())[1]  # the companion's link sends to the "autopilot"
    cfg = config.load(None, {"link.url": f"udpout:127.0.0.1:{port}", "model.path": str(model_path),
                             "camera.source": str(frames), "camera.loop": True, "camera.width": 640,
                             "camera.height": 480, "camera.hfov_deg": 70.0, "camera.sensor_width_mm": 6.17})
    svc = Service(cfg, load_model(cfg), video_stream=lambda: STREAM)
    task = asyncio.create_task(svc.run())
    try:
        await peer.wait_for("HEARTBEAT", lambda h: h.get_srcComponent() == 191, timeout=5.0)
        gcs = Gcs(peer)
        # Before the autopilot is heard: camera answered, the trigger refused with its reason.
        ack, start = await gcs.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_CAMERA_INFORMATION)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        info = await peer.wait_for("CAMERA_INFORMATION", timeout=1.0, start=start)
        fx = config.intrinsics(cfg).fx
        assert (info.resolution_h, info.resolution_v) == (640, 480)
        assert info.focal_length == pytest.approx(fx * 6.17 / 640, rel=1e-5)
        assert info.sensor_size_v == pytest.approx(6.17 * 480 / 640, rel=1e-5)
        assert bytes(info.model_name).rstrip(b"\0") == b"SLZ downward camera"
        ack, start = await gcs.command(m.MAV_CMD_USER_1)
        assert ack.result == m.MAV_RESULT_DENIED
        await peer.wait_for("STATUSTEXT", lambda s: s.text == "SLZ: trigger refused: no autopilot yet",
                            timeout=1.0, start=start)
        ack, start = await gcs.command(m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 0)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        assert (await peer.wait_for("VIDEO_STREAM_INFORMATION", timeout=1.0, start=start)).uri == STREAM.uri
        # Once wired to the autopilot, the trigger from a stranger is refused by the monitor.
        peer.start_heartbeats(0.1)
        for _ in range(100):
            if svc.monitor is not None:
                break
            await asyncio.sleep(0.05)
        assert svc.monitor is not None
        ack, _ = await Gcs(peer, system_id=42).command(m.MAV_CMD_USER_1)
        assert ack.result == m.MAV_RESULT_DENIED and svc.monitor.triggered is None
        ack, _ = await gcs.command(m.MAV_CMD_DO_SET_SERVO)
        assert ack.result == m.MAV_RESULT_UNSUPPORTED
        assert not [c for c in peer.commands if c.command != m.MAV_CMD_SET_MESSAGE_INTERVAL]
    finally:
        svc.request_stop("test over")
        assert await asyncio.wait_for(task, 10.0) == 0
        await peer.close()


def test_camera_information_settings_are_checked_and_unknowns_stay_nan():
    with pytest.raises(config.ConfigError, match="camera.vendor_name was removed"):
        config.load(None, {"camera.vendor_name": "bench"})
    with pytest.raises(config.ConfigError, match="camera.sensor_width_mm"):
        config.load(None, {"camera.sensor_width_mm": -1.0})
    info = config.camera_info(config.load(None, {}))
    assert (info.width, info.height) == (640, 480)
    assert math.isnan(info.focal_length_mm) and math.isnan(info.sensor_width_mm)
    # Non-square pixels: the vertical pitch follows fy (f_mm = fx * pitch_x = fy * pitch_y).
    cfg = config.load(None, {"camera.fx": 500.0, "camera.fy": 400.0, "camera.sensor_width_mm": 6.4})
    info = config.camera_info(cfg)
    assert info.focal_length_mm == pytest.approx(5.0)
    assert info.sensor_height_mm == pytest.approx(480 * 5.0 / 400.0)
