"""The autopilot's own descent speeds, read from its parameters (issue 11, item 3): the time to
touchdown is the autopilot's, not a guess in the settings.

Against the simulated ArduPilot and PX4 over loopback UDP (they answer PARAM_REQUEST_READ as the
real ones do), through the real flavours; and against a pymavlink peer that does not answer, or
answers garbage, where the configured speeds must stay.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.landing import LandingConfig, LandingController
from companion.control.touchdown import DescentProfile
from companion.mavlink.flavours import select_flavour
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.params import read_params
from companion.mavlink.state import VehicleState
from companion.service.landing_runner import LandingRunner
from sim.flights.flight import free_port
from sim.vehicle.kinematics import VehicleParams
from sim.vehicle.simulator import SimConfig, Simulator
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.5, command_timeout_s=0.1, command_retries=1)


@contextlib.asynccontextmanager
async def simulated(flavour: str, params: VehicleParams) -> AsyncIterator[tuple[Simulator, MavLink]]:
    port = free_port()
    sim = Simulator(SimConfig(flavour=flavour, outputs=[f"udpout:127.0.0.1:{port}"],
                              start_position=(0.0, 0.0, -20.0), vehicle=params, seed=1))
    link = MavLink(LinkConfig(f"udpin:127.0.0.1:{port}", message_rates_hz={}))
    await link.start()
    await sim.start()
    try:
        await link.wait_connected(5.0)
        yield sim, link
    finally:
        await sim.stop()
        await link.close()


@pytest.mark.sitl
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
async def test_the_simulated_autopilots_descent_speeds_are_read_through_the_real_flavour(flavour):
    params = VehicleParams(max_speed_down=1.2, land_speed=0.3)
    async with simulated(flavour, params) as (_sim, link):
        speeds = await select_flavour(link).descent_speeds(timeout_s=0.5)
    assert speeds == pytest.approx({"descend_speed_mps": 1.2, "land_speed_mps": 0.3})


@pytest.mark.sitl
async def test_the_runner_gives_the_controller_the_autopilots_speeds_and_says_so():
    async with simulated("ardupilot", VehicleParams(land_speed=0.3)) as (_sim, link):
        state = VehicleState()
        state.attach(link)
        controller = LandingController(LandingConfig(descent=DescentProfile(land_speed_mps=0.9)))
        runner = LandingRunner(controller, select_flavour(link), state, link)
        heard: list[str] = []
        runner.subscribe(lambda event: heard.append(event.text))
        await runner.read_autopilot_speeds()
    assert controller.descent.land_speed_mps == pytest.approx(0.3)
    assert controller.descent.descend_speed_mps == pytest.approx(1.5)  # WPNAV_SPEED_DN 150 cm/s
    assert heard == ["SLZ: descent 1.5 m/s, LAND 0.3 m/s (ardupilot parameters)"]  # recorded, and sent
    # 0.3 m/s from 10 m is 33 s of LAND: the prediction follows the autopilot, not the setting.
    assert controller.descent.time_to_touchdown(10.0) == pytest.approx(10.0 / 0.3)


async def peer_link() -> tuple[MavLink, MavPeer]:
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    await link.start()
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode=5)
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    await link.wait_connected(2.0)
    return link, peer


async def test_an_autopilot_that_does_not_answer_leaves_the_configured_speeds_within_the_timeout():
    link, peer = await peer_link()
    try:
        flavour = select_flavour(link)
        t0 = time.monotonic()
        speeds = await flavour.descent_speeds(timeout_s=0.1, retries=2)
        assert speeds == {}
        assert time.monotonic() - t0 < 1.0
        # It asked three times for each, by name.
        asked = [msg.param_id for msg in peer.of_type("PARAM_REQUEST_READ")]
        assert sorted(set(asked)) == ["LAND_SPEED", "WPNAV_SPEED_DN"] and len(asked) == 6
        ctl = LandingController(LandingConfig())
        ctl.use_autopilot_speeds(speeds, "ardupilot parameters")
        assert ctl.descent == DescentProfile() and ctl.pop_events() == []
    finally:
        await peer.close()
        await link.close()


async def test_garbage_and_implausible_parameter_values_are_not_believed():
    link, peer = await peer_link()
    try:
        async def answer() -> None:
            await asyncio.sleep(0.05)
            # NaN for one, 5,000 cm/s (50 m/s, no multicopter lands at that) for the other.
            peer.mav.send(peer.mav.param_value_encode(b"LAND_SPEED", math.nan, m.MAV_PARAM_TYPE_REAL32, 2, 0))
            peer.mav.send(peer.mav.param_value_encode(b"WPNAV_SPEED_DN", 5000.0, m.MAV_PARAM_TYPE_REAL32, 2, 1))
            # An answer for a parameter nobody asked for changes nothing.
            peer.mav.send(peer.mav.param_value_encode(b"LAND_SPEED_HIGH", 10.0, m.MAV_PARAM_TYPE_REAL32, 3, 2))

        task = asyncio.create_task(answer())
        speeds = await select_flavour(link).descent_speeds(timeout_s=0.2, retries=0)
        await task
        assert speeds == {}
        with pytest.raises(ValueError, match="param_id"):
            await read_params(link, ["A_NAME_LONGER_THAN_16"])
    finally:
        await peer.close()
        await link.close()


def test_the_controller_ignores_speeds_that_are_not_positive_numbers():
    ctl = LandingController(LandingConfig())
    ctl.use_autopilot_speeds({"land_speed_mps": -1.0, "descend_speed_mps": math.inf, "other": 3.0}, "test")
    assert ctl.descent == DescentProfile() and ctl.pop_events() == []
    ctl.use_autopilot_speeds({"land_speed_mps": 0.7}, "px4 parameters")
    assert ctl.descent.land_speed_mps == 0.7
    assert [e.text for e in ctl.pop_events()] == ["SLZ: descent 1.5 m/s, LAND 0.7 m/s (px4 parameters)"]
