"""The landing runner end to end: link, state, flavour and controller against a pymavlink peer.

The peer plays the flight controller: it streams HOME_POSITION, ATTITUDE and GLOBAL_POSITION_INT
of a position the test moves, answers commands, and follows DO_SET_MODE. Frames are fed with the
pose the real ``VehicleState`` interpolates at the frame's time.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time

import pytest
from geographiclib.geodesic import Geodesic
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.landing import Goto, Handback, LandingConfig, LandingController, Phase
from companion.control.planner import PlannerConfig
from companion.control.trigger import Trigger, TriggerSource
from companion.geometry.geodesy import GeoPoint, geo_from_ned
from companion.mavlink.flavours import select_flavour
from companion.mavlink.link import CommandRefused, CommandTimeout, LinkConfig, MavLink
from companion.mavlink.px4 import px4_custom_mode
from companion.mavlink.state import VehicleState
from companion.pipeline.tracker import Track
from companion.service.landing_runner import LandingRunner
from tests.mavpeer import MavPeer

HOME = GeoPoint(47.397742, 8.545594, 488.0)
FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.5, command_timeout_s=0.1, command_retries=1)
CFG = LandingConfig(
    planner=PlannerConfig(min_track_age_s=0.5, min_track_hits=3, zone_max_age_s=0.5),
    select_timeout_s=0.6,
    hold_timeout_s=0.6,
    descend_alt_m=10.0,
    descend_step_m=3.0,
    max_pose_age_s=0.15,
    search_s=0.0,
)


class Vehicle:
    """The peer plus a position it streams (NED metres from HOME)."""

    def __init__(self, peer: MavPeer) -> None:
        self.peer = peer
        self.north, self.east, self.alt = 0.0, 0.0, 30.0
        self.on_ground = False
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        async def loop() -> None:
            k = 0
            while True:
                ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
                p = geo_from_ned(HOME, self.north, self.east, -self.alt)
                self.peer.mav.attitude_send(ms, 0.0, 0.0, 0.3, 0, 0, 0)
                self.peer.mav.global_position_int_send(
                    ms, round(p.lat_deg * 1e7), round(p.lon_deg * 1e7), round(p.alt_m * 1e3), round(self.alt * 1e3),
                    0, 0, 0, 1700,
                )
                if k % 5 == 0:
                    self.peer.mav.home_position_send(
                        round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7), round(HOME.alt_m * 1e3),
                        0, 0, 0, [1, 0, 0, 0], 0, 0, 0,
                    )
                    landed = m.MAV_LANDED_STATE_ON_GROUND if self.on_ground else m.MAV_LANDED_STATE_IN_AIR
                    self.peer.mav.extended_sys_state_send(0, landed)
                k += 1
                await asyncio.sleep(0.05)

        self._task = asyncio.get_running_loop().create_task(loop())

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()


@contextlib.asynccontextmanager
async def rig(autopilot: int = m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode: int = 5, config: LandingConfig = CFG,
              shadow: bool = False):
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    await link.start()
    peer = MavPeer(autopilot=autopilot, custom_mode=custom_mode)
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    await link.wait_connected(2.0)
    state = VehicleState()
    state.attach(link)
    flavour = select_flavour(link)
    if hasattr(flavour, "warmup_s"):
        flavour.warmup_s = 0.2
    vehicle = Vehicle(peer)
    vehicle.start()
    runner = LandingRunner(LandingController(config), flavour, state, link, tick_hz=20, shadow=shadow)
    task = asyncio.create_task(runner.run())
    for _ in range(100):
        if state.is_fresh(time.monotonic(), 0.2):
            break
        await asyncio.sleep(0.02)
    try:
        yield runner, vehicle, peer, state
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        vehicle.stop()
        await peer.close()
        await link.close()


def zone(id: int, north: float, east: float, t: float, r: float = 5.0) -> Track:
    return Track(id=id, x=north, y=east, r=r, r_filtered=r, age=50, hits=50, misses=0, born_t=t - 5.0, last_t=t)


async def feed(runner: LandingRunner, state: VehicleState, zones_at, until, timeout: float = 3.0) -> None:
    """Feed frames at 20 Hz (tracks from ``zones_at(t)``) until ``until()`` is true."""
    deadline = time.monotonic() + timeout
    while not until():
        assert time.monotonic() < deadline, f"timed out in phase {runner.controller.phase}"
        t = time.monotonic() - 0.02  # captured a moment ago
        runner.on_frame(t, zones_at(t), state.pose_at(t))
        await asyncio.sleep(0.05)


def mode_changes(peer: MavPeer) -> list[tuple[int, int]]:
    return [(int(c.param2), int(c.param3)) for c in peer.commands_of(m.MAV_CMD_DO_SET_MODE)]


async def test_ardupilot_trigger_guided_target_over_zone_then_land():
    async with rig() as (runner, vehicle, peer, state):
        runner.on_trigger(Trigger("ground station asked to land", TriggerSource.GCS_COMMAND, time.monotonic()))
        await feed(runner, state, lambda t: [zone(3, 12.0, -5.0, t)], lambda: peer.of_type("SET_POSITION_TARGET_GLOBAL_INT"))
        assert mode_changes(peer)[0] == (4, 0)  # GUIDED
        sp = peer.of_type("SET_POSITION_TARGET_GLOBAL_INT")[0]
        g = Geodesic.WGS84.Direct(HOME.lat_deg, HOME.lon_deg, math.degrees(math.atan2(-5.0, 12.0)), math.hypot(12, 5))
        # lat/lon on the wire are 1e-7 degrees: about 1 cm.
        assert sp.lat_int == round(g["lat2"] * 1e7) and sp.lon_int == round(g["lon2"] * 1e7)
        assert sp.alt == pytest.approx(30.0, abs=0.01) and sp.type_mask == 3576 and sp.coordinate_frame == 6
        _, text = await peer.wait_for_text("landing at zone 3")
        assert text == "SLZ: landing at zone 3, 13.0 m away, radius 5.0 m"
        # The vehicle arrives, then follows each descent target down.
        vehicle.north, vehicle.east = 12.0, -5.0

        def follow() -> bool:
            sps = peer.of_type("SET_POSITION_TARGET_GLOBAL_INT")
            vehicle.alt = sps[-1].alt
            return runner.controller.phase == Phase.LAND

        await feed(runner, state, lambda t: [zone(3, 12.0, -5.0, t)], follow, timeout=5.0)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE and c.param2 == 9)
        alts = [s.alt for s in peer.of_type("SET_POSITION_TARGET_GLOBAL_INT")]
        assert min(alts) == pytest.approx(10.0) and all(a - b <= 3.0 + 1e-3 for a, b in zip(alts, alts[1:]))
        vehicle.alt, vehicle.on_ground = 0.0, True
        for _ in range(100):
            if runner.controller.phase == Phase.LANDED:
                break
            await asyncio.sleep(0.02)
        assert runner.controller.phase == Phase.LANDED
        assert all(e is None for _, e in runner.executed)


async def test_px4_offboard_stream_then_auto_land():
    async with rig(m.MAV_AUTOPILOT_PX4, custom_mode=px4_custom_mode(4, 4)) as (runner, vehicle, peer, state):
        vehicle.alt = 10.2
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [zone(1, 8.0, 8.0, t)], lambda: runner.autopilot.mode == "OFFBOARD")
        assert mode_changes(peer)[0] == (6, 0)
        vehicle.north, vehicle.east = 8.0, 8.0
        await feed(runner, state, lambda t: [zone(1, 8.0, 8.0, t)], lambda: runner.controller.phase == Phase.LAND)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE and c.param3 == 6)
        assert mode_changes(peer)[-1] == (4, 6)  # AUTO.LAND
        await asyncio.sleep(0.1)
        assert not runner.autopilot.streaming


async def test_no_zone_hands_back_with_the_autopilots_land():
    async with rig() as (runner, vehicle, peer, state):
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [zone(1, 5, 5, t, r=2.2)], lambda: runner.controller.phase == Phase.HANDBACK)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE)
        assert mode_changes(peer) == [(9, 0)]  # LAND, and nothing else was ever commanded
        assert peer.of_type("SET_POSITION_TARGET_GLOBAL_INT") == []
        severity, text = await peer.wait_for_text("handing back")
        # CRITICAL: the companion gave up and the autopilot's own failsafe lands where it is.
        assert severity == m.MAV_SEVERITY_CRITICAL
        assert text == "SLZ: no safe zone confirmed within 0.6 s: handing back to the autopilot (LAND)"


async def test_no_zone_hands_back_with_rtl_when_configured():
    cfg = LandingConfig(planner=CFG.planner, select_timeout_s=0.4, handback_action="RTL", search_s=0.0)
    async with rig(config=cfg) as (runner, vehicle, peer, state):
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [], lambda: runner.controller.phase == Phase.HANDBACK)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE)
        assert mode_changes(peer) == [(6, 0)]


async def test_refused_guided_is_retried_then_handed_back():
    async with rig() as (runner, vehicle, peer, state):
        peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = lambda c: m.MAV_RESULT_DENIED if c.param2 == 4 else m.MAV_RESULT_ACCEPTED
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [zone(1, 5, 5, t)], lambda: runner.controller.phase == Phase.HANDBACK)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE and c.param2 == 9)
        errors = [e for _, e in runner.executed if e is not None]
        assert len(errors) == 3 and all(isinstance(e, CommandRefused) for e in errors)
        assert isinstance(runner.executed[-1][0], Handback) and runner.executed[-1][1] is None
        assert peer.of_type("SET_POSITION_TARGET_GLOBAL_INT") == []  # never a target without GUIDED


async def test_zone_lost_during_descent_holds_over_the_vehicle():
    async with rig() as (runner, vehicle, peer, state):
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        vehicle.north, vehicle.east = 6.0, 6.0
        await feed(runner, state, lambda t: [zone(1, 6, 6, t)], lambda: runner.controller.phase == Phase.DESCEND)
        await feed(runner, state, lambda t: [], lambda: runner.controller.phase == Phase.HOLD)
        _, text = await peer.wait_for_text("holding")
        assert "zone 1 lost (no longer tracked)" in text
        await asyncio.sleep(0.1)
        last = peer.of_type("SET_POSITION_TARGET_GLOBAL_INT")[-1]
        here = geo_from_ned(HOME, 6.0, 6.0)
        assert last.lat_int == pytest.approx(here.lat_deg * 1e7, abs=2)
        # At the plan's level: the 27 m step it was already told to descend to from 30 m, never an
        # altitude derived from where the vehicle is now (issue 19).
        assert last.alt == pytest.approx(27.0, abs=0.1)
        goto_zone_ids = [c.zone_id for c, _ in runner.executed if isinstance(c, Goto)]
        assert goto_zone_ids[-1] is None


async def test_stale_pose_no_command_at_all():
    async with rig() as (runner, vehicle, peer, state):
        vehicle.stop()  # telemetry stops: every pose goes stale
        await asyncio.sleep(0.3)
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        for _ in range(8):
            t = time.monotonic()
            assert state.pose_at(t) is None
            runner.on_frame(t, [zone(1, 5, 5, t)], state.pose_at(t))
            await asyncio.sleep(0.05)
        assert runner.controller.phase == Phase.SELECT
        assert peer.of_type("SET_POSITION_TARGET_GLOBAL_INT") == [] and mode_changes(peer) == []


async def test_unanswered_guided_times_out_then_hands_back():
    async with rig() as (runner, vehicle, peer, state):
        peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = lambda c: None if c.param2 == 4 else m.MAV_RESULT_ACCEPTED
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [zone(1, 5, 5, t)], lambda: runner.controller.phase == Phase.HANDBACK)
        await peer.wait_for("COMMAND_LONG", lambda c: c.command == m.MAV_CMD_DO_SET_MODE and c.param2 == 9)
        errors = [e for _, e in runner.executed if e is not None]
        assert len(errors) == 3 and all(isinstance(e, CommandTimeout) for e in errors)
        # Each attempt was retried with the confirmation field counting up.
        assert [c.confirmation for c in peer.commands_of(m.MAV_CMD_DO_SET_MODE)[:2]] == [0, 1]
        _, text = await peer.wait_for_text("handing back")
        assert "3 commands failed in a row" in text


#: What shadow mode must never send: anything that changes the vehicle's mode, position or arming.
VEHICLE_COMMANDS = {m.MAV_CMD_DO_SET_MODE, m.MAV_CMD_NAV_LAND, m.MAV_CMD_NAV_RETURN_TO_LAUNCH,
                    m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_CMD_DO_REPOSITION, m.MAV_CMD_NAV_TAKEOFF,
                    m.MAV_CMD_NAV_LOITER_UNLIM, m.MAV_CMD_DO_CHANGE_SPEED}


@pytest.mark.parametrize("autopilot", [m.MAV_AUTOPILOT_ARDUPILOTMEGA, m.MAV_AUTOPILOT_PX4])
async def test_shadow_mode_decides_the_whole_landing_but_sends_nothing(autopilot):
    custom_mode = 5 if autopilot == m.MAV_AUTOPILOT_ARDUPILOTMEGA else px4_custom_mode(4, 3)
    async with rig(autopilot, custom_mode, shadow=True) as (runner, vehicle, peer, state):
        withheld = []
        runner.on_withheld(withheld.append)
        vehicle.alt = 10.2
        runner.on_trigger(Trigger("battery", TriggerSource.BATTERY, time.monotonic()))
        await feed(runner, state, lambda t: [zone(1, 8.0, 8.0, t)], lambda: runner.controller.phase == Phase.APPROACH)
        # The vehicle goes there by itself (as if it had been told): the controller commits to LAND.
        vehicle.north, vehicle.east = 8.0, 8.0
        await feed(runner, state, lambda t: [zone(1, 8.0, 8.0, t)], lambda: runner.controller.phase == Phase.LAND)
        await asyncio.sleep(0.3)
        assert [type(c).__name__ for c in withheld][:1] == ["Goto"] and type(withheld[-1]).__name__ == "Land"
        assert runner.withheld == withheld and runner.executed == []
        sent = [c.command for c in peer.commands]
        assert not VEHICLE_COMMANDS & set(sent), sent
        for kind in ("SET_MODE", "SET_POSITION_TARGET_GLOBAL_INT", "SET_POSITION_TARGET_LOCAL_NED"):
            assert peer.of_type(kind) == [], kind
        texts = peer.statustexts()
        assert texts and all(t.startswith("SHADOW: ") for _, t in texts), texts
        assert (m.MAV_SEVERITY_WARNING, "SHADOW: trigger: battery; looking for a landing zone") in texts
        assert any(sev == m.MAV_SEVERITY_NOTICE and "landing at zone 1" in t for sev, t in texts), texts
        assert any(sev == m.MAV_SEVERITY_NOTICE and t.startswith("SHADOW: LAND over zone 1") for sev, t in texts)
        assert not runner.autopilot.streaming if hasattr(runner.autopilot, "streaming") else True
