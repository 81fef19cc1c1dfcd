"""``companion sim --camera-only --pose-from URL``: the simulated camera rides on an external
vehicle (a real SITL in use; here a pymavlink peer on loopback UDP sending what a SITL sends), and
the frame it serves over HTTP is the crowd seen from that vehicle's pose."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.geometry.geodesy import GeoPoint, geo_from_ned
from sim.flights.flight import free_port
from sim.flights.standalone import run as sim_run
from sim.world.camera_server import CameraServer, read_mjpeg
from sim.world.crowd import default_world
from sim.world.ground import ProceduralGround
from sim.world.pose_follow import ExternalPose, NoPose
from sim.world.render import render_world
from tests.mavpeer import MavPeer

HOME = GeoPoint(47.397742, 8.545594, 488.0)  # PX4's SITL home
K = Intrinsics.from_fov(320, 240, 70.0)


class Vehicle:
    """Streams HOME_POSITION, GLOBAL_POSITION_INT and ATTITUDE of a pose that the test moves."""

    def __init__(self, peer: MavPeer) -> None:
        self.peer, self.north, self.east, self.alt, self.yaw = peer, 0.0, 0.0, 20.0, 0.0
        self.boot_ms = 1000

    async def stream(self) -> None:
        mav: Any = self.peer.mav
        while True:
            self.boot_ms += 50
            p = geo_from_ned(HOME, self.north, self.east, -self.alt)
            mav.home_position_send(int(HOME.lat_deg * 1e7), int(HOME.lon_deg * 1e7), int(HOME.alt_m * 1000),
                                   0, 0, 0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0)
            mav.global_position_int_send(self.boot_ms, int(round(p.lat_deg * 1e7)), int(round(p.lon_deg * 1e7)),
                                         int(round(p.alt_m * 1000)), int(round(self.alt * 1000)), 0, 0, 0, 65535)
            mav.attitude_send(self.boot_ms, 0.0, 0.0, self.yaw, 0.0, 0.0, 0.0)
            await asyncio.sleep(0.05)


async def _frame(url: str, after_index: int) -> tuple[int, np.ndarray]:
    def read() -> tuple[int, np.ndarray]:
        for f in read_mjpeg(url):
            i = int(f.headers["x-frame-index"])
            if i > after_index:
                return i, f.image
        raise AssertionError("the stream ended")

    return await asyncio.wait_for(asyncio.to_thread(read), 10.0)


async def _pose_near(vehicle: ExternalPose, north: float, east: float, alt: float, yaw: float) -> Pose:
    # Position and yaw arrive in two messages (GLOBAL_POSITION_INT, then ATTITUDE): wait for both,
    # or a pose polled between them pairs the new position with the old yaw.
    for _ in range(100):
        try:
            p = vehicle.pose()
            if (abs(p.north - north) < 0.05 and abs(p.east - east) < 0.05 and abs(-p.down - alt) < 0.05
                    and abs(math.remainder(p.yaw - yaw, 2 * math.pi)) < 1e-3):
                return p
        except NoPose:
            pass
        await asyncio.sleep(0.05)
    raise AssertionError(f"no pose near N {north} E {east} alt {alt} yaw {yaw}: {vehicle.state.position}")


async def test_the_served_frame_follows_the_external_vehicles_pose() -> None:
    port = free_port()
    vehicle = ExternalPose(f"udpin:127.0.0.1:{port}")
    await vehicle.start()
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_PX4)
    await peer.connect_udp(("127.0.0.1", port))
    peer.start_heartbeats()
    with pytest.raises(NoPose):
        vehicle.pose()  # nothing heard yet: no frame rather than a wrong one
    sim = Vehicle(peer)
    streamer = asyncio.create_task(sim.stream())
    world = default_world(seed=3)
    camera = CameraServer(vehicle.pose, world, K, Mount(), fps=10, ground=ProceduralGround(3), noise_sigma=0.0)
    try:
        first_pose = await _pose_near(vehicle, 0.0, 0.0, 20.0, 0.0)
        async with camera:
            i1, img1 = await _frame(camera.url, -1)
            sim.north, sim.east, sim.alt, sim.yaw = 25.0, -30.0, 35.0, math.radians(90)
            moved_pose = await _pose_near(vehicle, 25.0, -30.0, 35.0, math.radians(90))
            _, img2 = await _frame(camera.url, i1 + 1)
    finally:
        streamer.cancel()
        await peer.close()
        await vehicle.close()

    def like(img: np.ndarray, pose: Pose) -> float:
        ref = render_world(world, pose, K, Mount(), camera.ground)
        return float(np.median(np.abs(img.astype(int) - ref.astype(int))))

    assert like(img1, first_pose) <= 4  # the crowd seen from the first pose (up to JPEG) ...
    assert like(img2, moved_pose) <= 4  # ... and from the moved one
    assert like(img2, first_pose) > 10 and np.abs(img1.astype(int) - img2.astype(int)).mean() > 10
    assert abs(moved_pose.yaw - math.radians(90)) < 1e-3
    # It commands nothing: the only commands it sent ask for the pose messages' rates.
    assert peer.commands and {c.command for c in peer.commands} == {m.MAV_CMD_SET_MESSAGE_INTERVAL}


def test_camera_only_needs_pose_from(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.cli import build_parser

    parser, _ = build_parser("sim")
    assert sim_run(parser.parse_args(["sim", "--camera-only"])) == 2
    assert "--pose-from" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        parser.parse_args(["sim", "--camera-only", "--pose-from", "carrier-pigeon:1"])
