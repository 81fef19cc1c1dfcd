"""MAVSDK (the real library, 4.x asyncio API) against the simulator over loopback UDP.

MAVSDK is the PX4-side reference client: if it reads the simulator's telemetry and its action
plugin's ``land()`` is obeyed, the simulator speaks MAVLink the way MAVSDK expects an autopilot to
(heartbeat identity, command protocol with acks, position and attitude streams, landed state).
"""

from __future__ import annotations

import asyncio
import math
import socket

import pytest

from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.kinematics import VehicleParams
from sim.vehicle.simulator import SimConfig, Simulator

mavsdk_asyncio = pytest.importorskip("mavsdk.asyncio", reason="mavsdk 4.x is not installed")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.telemetry import FlightMode, LandedState  # noqa: E402

pytestmark = pytest.mark.sitl

FAST = VehicleParams(land_speed_high=2.5, land_speed=1.5, land_alt_low=1.0, land_detect_s=0.5)
HOME = AutopilotConfig()


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _first(gen, timeout: float = 5.0):
    async def take():
        async for item in gen:
            return item
    try:
        return await asyncio.wait_for(take(), timeout)
    finally:
        await gen.aclose()


async def _until(gen, cond, timeout: float):
    async def take():
        async for item in gen:
            if cond(item):
                return item
    try:
        return await asyncio.wait_for(take(), timeout)
    finally:
        await gen.aclose()


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
async def test_mavsdk_reads_telemetry_and_its_land_is_obeyed(flavour: str) -> None:
    port = _free_udp_port()
    sim = Simulator(SimConfig(flavour=flavour, outputs=[f"udpout:127.0.0.1:{port}"],
                              start_position=(3.0, -2.0, -5.0), start_yaw=math.radians(30),
                              vehicle=FAST))
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        async with sim:
            system = await mavsdk.first_autopilot(timeout_s=5.0)
            assert system is not None, "MAVSDK did not discover the simulated autopilot"
            assert await system.get_system_id() == 1
            telemetry, action = TelemetryAsync(system), ActionAsync(system)

            pos = await _first(telemetry.subscribe_position())
            assert pos.relative_altitude_m == pytest.approx(5.0, abs=0.05)
            assert pos.absolute_altitude_m == pytest.approx(HOME.home_alt + 5.0, abs=0.05)
            # 3 m north, 2 m west of home, as geodesy puts it (1e-7 deg is ~1 cm).
            assert pos.latitude_deg > HOME.home_lat and pos.longitude_deg < HOME.home_lon
            att = await _first(telemetry.subscribe_attitude_euler())
            assert att.yaw_deg == pytest.approx(30.0, abs=0.5)
            assert abs(att.roll_deg) < 1 and abs(att.pitch_deg) < 1
            mode = await _first(telemetry.subscribe_flight_mode())
            assert mode == FlightMode.HOLD  # LOITER / AUTO.LOITER
            assert await _first(telemetry.subscribe_armed()) is True

            await action.land()  # raises ActionError unless the autopilot acks ACCEPTED
            await _until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.LAND, 3.0)
            await _until(telemetry.subscribe_landed_state(),
                         lambda s: s == LandedState.ON_GROUND, 10.0)
            truth = sim.truth
            assert truth.landed and truth.position[2] == 0.0
            assert math.dist(truth.position[:2], (3.0, -2.0)) < 0.05  # landed where it was
            await _until(telemetry.subscribe_armed(), lambda a: a is False, 5.0)
