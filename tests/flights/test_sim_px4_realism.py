"""The simulated PX4 against what the real PX4 v1.15 (SIH) does, over real MAVLink on loopback.

Each test pins one behaviour measured on the real firmware: the EKF origin below/above home and
PX4's wrong MAV_FRAME_GLOBAL_RELATIVE_ALT_INT conversion (the fly-away it caused), no
POSITION_TARGET_GLOBAL_INT in OFFBOARD, HOME_POSITION wandering before arming, the failsafe
framework's hold before acting (COM_FAIL_ACT_T), and the land detector disarming in OFFBOARD.
Frames: world NED metres from home (``sim.truth``), MAVLink fields in their own units.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.faults import Failsafe
from sim.vehicle.px4 import AUTO_LAND, AUTO_LOITER, MAIN_OFFBOARD, MAIN_POSCTL, OFFBOARD, POSCTL, HomeWander
from tests.flights.test_sim_vehicle_mavlink import HOME, MavClient, fly

pytestmark = pytest.mark.sitl

POS_ONLY = 0b110111111000  # SET_POSITION_TARGET_* type_mask: position only
OFFSET = -1.5              # home_alt - EKF origin alt (m): home 1.5 m below the origin, as SIH


def local_target(north: float, east: float, z_local: float):
    """SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED (the EKF-origin frame), metres."""
    return mav.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mav.MAV_FRAME_LOCAL_NED, POS_ONLY, north, east, z_local, 0, 0, 0, 0, 0, 0, 0, 0)


def global_target(frame: int, alt: float, lat: float = HOME[0], lon: float = HOME[1]):
    """SET_POSITION_TARGET_GLOBAL_INT at (lat, lon) degrees, ``alt`` metres in ``frame``."""
    return mav.MAVLink_set_position_target_global_int_message(
        0, 1, 1, frame, POS_ONLY, int(round(lat * 1e7)), int(round(lon * 1e7)), alt,
        0, 0, 0, 0, 0, 0, 0, 0)


class Streamer:
    """Sends ``current`` at ``hz`` until cancelled, as a companion keeps OFFBOARD alive."""

    def __init__(self, client: MavClient, first, hz: float = 10.0) -> None:
        self.client, self.current, self.hz = client, first, hz
        self.task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        while True:
            self.client.send(self.current)
            await asyncio.sleep(1.0 / self.hz)

    def cancel(self) -> None:
        self.task.cancel()


async def enter_offboard(c: MavClient, streamer: Streamer) -> None:
    """Let the stream warm up past PX4's 1 s, then switch to OFFBOARD."""
    await asyncio.sleep(1.2)
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == mav.MAV_RESULT_ACCEPTED
    await c.heartbeat(lambda m: m.custom_mode == OFFBOARD, timeout=2.0)


async def settles_at(sim, altitude: float, timeout: float) -> None:
    await sim.wait_for(lambda t: abs(t.altitude - altitude) < 0.1
                       and abs(float(t.velocity[2])) < 0.05, timeout)


# ----- 1. EKF origin vs home altitude -----

async def test_px4_converts_frame_6_with_its_wrong_formula_and_5_11_local_correctly() -> None:
    home_alt = HOME[2]
    sim, c = await fly("px4", start=(0.0, 0.0, -20.0),
                       autopilot=AutopilotConfig(origin_alt_offset_m=OFFSET))
    # 20 m above home in the EKF-origin frame: z_local = world_down - offset.
    hold_20 = local_target(0.0, 0.0, -20.0 - OFFSET)
    stream = Streamer(c, hold_20)
    try:
        await enter_offboard(c, stream)
        # What the vehicle reports: LOCAL_POSITION_NED from the origin, home in that frame,
        # GLOBAL_POSITION_INT against home and AMSL as always.
        lpn = await c.wait("LOCAL_POSITION_NED", since=c.mark())
        assert lpn.z == pytest.approx(-20.0 - OFFSET, abs=0.05)
        home = await c.wait("HOME_POSITION", since=c.mark(), timeout=3.0)
        assert (home.x, home.y, home.z) == pytest.approx((0.0, 0.0, -OFFSET), abs=1e-3)
        assert home.altitude == round(home_alt * 1000)
        gpi = await c.wait("GLOBAL_POSITION_INT", since=c.mark())
        assert gpi.relative_alt == pytest.approx(20_000, abs=50)
        assert gpi.alt == pytest.approx((home_alt + 20.0) * 1000, abs=50)

        # Frame 6, "20 m above home": PX4 puts it 2 * (home_alt - ref_alt) = 3 m higher.
        stream.current = global_target(mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 20.0)
        await settles_at(sim, 20.0 - 2 * OFFSET, 8.0)
        # Frame 5 (AMSL) is right: back to 20 m.
        stream.current = global_target(mav.MAV_FRAME_GLOBAL_INT, home_alt + 20.0)
        await settles_at(sim, 20.0, 8.0)
        # Frame 11 (above terrain; flat at home's height) is right too.
        stream.current = global_target(mav.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, 21.0)
        await settles_at(sim, 21.0, 8.0)
        # The local equivalent of 20 m above home is 20 m: off by the offset it would not be.
        stream.current = hold_20
        await settles_at(sim, 20.0, 8.0)
        await asyncio.sleep(1.5)
        assert sim.truth.altitude == pytest.approx(20.0, abs=0.1)

        # Any other frame of SET_POSITION_TARGET_GLOBAL_INT is discarded.
        invalid = sim.autopilot.counters["setpoints_invalid"]
        for frame in (mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                      mav.MAV_FRAME_GLOBAL_TERRAIN_ALT, mav.MAV_FRAME_LOCAL_NED):
            c.send(global_target(frame, 30.0))
        await asyncio.sleep(1.0)
        assert sim.autopilot.counters["setpoints_invalid"] == invalid + 4
        assert sim.truth.altitude == pytest.approx(20.0, abs=0.1)
    finally:
        stream.cancel()
        await sim.stop()
        c.close()


async def test_ardupilot_converts_frame_6_correctly_whatever_the_offset() -> None:
    from sim.vehicle.ardupilot import GUIDED
    sim, c = await fly("ardupilot", start=(0.0, 0.0, -10.0),
                       autopilot=AutopilotConfig(origin_alt_offset_m=OFFSET))
    try:
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
        c.send(global_target(mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 12.0))
        await settles_at(sim, 12.0, 6.0)
        lpn = await c.wait("LOCAL_POSITION_NED", since=c.mark())
        assert lpn.z == pytest.approx(-12.0, abs=0.05)  # ArduPilot's local frame: home
    finally:
        await sim.stop()
        c.close()


@pytest.mark.parametrize("offset,climbs", [(OFFSET, True), (0.0, False)])
async def test_old_companion_descent_in_frame_6_climbs_away_when_home_is_below_origin(
        offset: float, climbs: bool) -> None:
    # The old companion descended by asking, every 0.5 s, for "0.5 m below where I am now"
    # in frame 6 (relative_alt from GLOBAL_POSITION_INT). With home 1.5 m below the EKF origin
    # each such target is 2.5 m ABOVE the vehicle on the real PX4: it climbed away.
    start_alt = 20.0
    sim, c = await fly("px4", start=(0.0, 0.0, -start_alt),
                       autopilot=AutopilotConfig(origin_alt_offset_m=offset))

    def below_me() -> mav.MAVLink_message:
        rel = c.latest("GLOBAL_POSITION_INT").relative_alt / 1000.0
        return global_target(mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, rel - 0.5)

    await c.wait("GLOBAL_POSITION_INT", timeout=1.0)
    stream = Streamer(c, below_me())
    try:
        await enter_offboard(c, stream)
        loop = asyncio.get_running_loop()
        end = loop.time() + 15.0
        peak, low = start_alt, start_alt
        while loop.time() < end:
            stream.current = below_me()
            await asyncio.sleep(0.5)
            alt = sim.truth.altitude
            peak, low = max(peak, alt), min(low, alt)
            if (climbs and alt > start_alt + 5.0) or (not climbs and alt < start_alt - 5.0):
                break
        assert sim.truth.mode == "OFFBOARD"
        if climbs:
            assert peak > start_alt + 5.0, f"only reached {peak:.1f} m"
            assert low > start_alt - 0.5  # never went down
        else:
            assert low < start_alt - 5.0, f"only got down to {low:.1f} m"
            assert peak < start_alt + 0.3  # never went up
    finally:
        stream.cancel()
        await sim.stop()
        c.close()


# ----- 2. no POSITION_TARGET_GLOBAL_INT in OFFBOARD -----

async def test_px4_sends_no_position_target_global_int_in_offboard() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -6.0))
    stream = Streamer(c, local_target(2.0, 0.0, -6.0))
    try:
        # In AUTO.LOITER the navigator has a target: 1 Hz, AMSL in MAV_FRAME_GLOBAL_INT.
        pt = await c.wait("POSITION_TARGET_GLOBAL_INT", timeout=2.5)
        assert pt.coordinate_frame == mav.MAV_FRAME_GLOBAL_INT
        assert pt.alt == pytest.approx(HOME[2] + 6.0, abs=0.2)
        await enter_offboard(c, stream)
        since = c.mark()
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        await asyncio.sleep(2.2)
        assert sim.truth.mode == "OFFBOARD"
        assert c.count("POSITION_TARGET_GLOBAL_INT", t0, loop.time()) == 0
        assert not any(m.get_type() == "POSITION_TARGET_GLOBAL_INT" for _, m in c.log[since:])
        assert c.count("GLOBAL_POSITION_INT", t0, loop.time()) >= 8  # telemetry kept coming
    finally:
        stream.cancel()
        await sim.stop()
        c.close()


# ----- 3. HOME_POSITION while disarmed -----

def test_home_wander_is_deterministic_per_seed_and_small() -> None:
    a, b, other = HomeWander(3), HomeWander(3), HomeWander(4)
    times = [0.5 * i for i in range(200)]
    wa = np.array([a.at(t) for t in times])
    wb = np.array([b.at(t) for t in times[::3]])  # read less often: the same walk
    assert np.array_equal(wa[::3], wb)
    assert not np.array_equal(wa, np.array([other.at(t) for t in times]))
    assert np.abs(wa[:, :2]).max() < 0.5 and np.abs(wa[:, 2]).max() < 1.0
    assert np.abs(wa[:, :2]).max() > 0.01 and np.abs(wa[:, 2]).max() > 0.05


async def test_px4_home_position_wanders_while_disarmed_and_is_fixed_once_armed() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, 0.0))
    try:
        await asyncio.sleep(5.2)
        disarmed = [m for _, m in c.log if m.get_type() == "HOME_POSITION"]
        assert len(disarmed) >= 3  # 0.5 Hz
        values = {(m.latitude, m.longitude, m.altitude) for m in disarmed}
        assert len(values) >= 2, values
        for m in disarmed:
            dlat_m = (m.latitude / 1e7 - HOME[0]) * 111_000
            dlon_m = (m.longitude / 1e7 - HOME[1]) * 111_000 * math.cos(math.radians(HOME[0]))
            assert math.hypot(dlat_m, dlon_m) < 0.6 and abs(m.altitude / 1000 - HOME[2]) < 1.0
            assert m.z == pytest.approx(-(m.altitude / 1000 - HOME[2]), abs=2e-3)

        assert await c.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, float("nan"), float("nan"),
                               float("nan"), HOME[2] + 4.0) == mav.MAV_RESULT_ACCEPTED
        assert await c.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
        await sim.wait_for(lambda t: t.altitude > 1.0, 5.0)
        since = c.mark()
        await asyncio.sleep(4.5)
        armed = [m for _, m in c.log[since:] if m.get_type() == "HOME_POSITION"]
        assert len(armed) >= 2
        assert {(m.latitude, m.longitude, m.altitude, m.x, m.y, m.z) for m in armed} == {
            (round(HOME[0] * 1e7), round(HOME[1] * 1e7), round(HOME[2] * 1000), 0.0, 0.0, 0.0)}
        # Nothing else moved with the wander: relative_alt is against the configured home.
        gpi = c.latest("GLOBAL_POSITION_INT")
        assert gpi.relative_alt / 1000 == pytest.approx(sim.truth.altitude, abs=0.3)
    finally:
        await sim.stop()
        c.close()


# ----- 4. failsafes through PX4's failsafe framework -----

async def _in_posctl(c: MavClient) -> None:
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_POSCTL) == mav.MAV_RESULT_ACCEPTED
    await c.heartbeat(lambda m: m.custom_mode == POSCTL, timeout=2.0)


async def test_px4_battery_low_only_warns() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -10.0))
    try:
        await _in_posctl(c)
        since = c.mark()
        sim.inject_failsafe(Failsafe.BATTERY_LOW)
        text = await c.wait("STATUSTEXT", lambda m: "battery" in m.text.lower(), 1.0, since)
        assert text.severity == mav.MAV_SEVERITY_WARNING
        bat = await c.wait("BATTERY_STATUS", since=since, timeout=3.0)
        assert bat.charge_state == mav.MAV_BATTERY_CHARGE_STATE_LOW
        # Two heartbeats after the warning (1 Hz: a fixed sleep raced their phase, and CI once
        # saw only one), each still POSCTL.
        first = await c.wait("HEARTBEAT", since=since, timeout=3.0)
        await c.wait("HEARTBEAT", lambda m: m is not first, since=since, timeout=3.0)
        hbs = [m for _, m in c.log[since:] if m.get_type() == "HEARTBEAT"]
        assert len(hbs) >= 2 and all(m.custom_mode == POSCTL for m in hbs)
        assert all(m.system_status == mav.MAV_STATE_ACTIVE for m in hbs[1:])  # a warning, no failsafe
        assert sim.truth.mode == "POSCTL"
    finally:
        await sim.stop()
        c.close()


async def test_px4_battery_critical_holds_then_lands_after_com_fail_act_t() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -10.0))
    try:
        await _in_posctl(c)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        sim.inject_failsafe(Failsafe.BATTERY_CRITICAL)
        assert sim.truth.mode == "AUTO.LOITER"  # hold at once
        hb = await c.heartbeat(lambda m: m.custom_mode == AUTO_LOITER, timeout=1.5)
        assert hb.system_status == mav.MAV_STATE_EMERGENCY
        truth = await sim.wait_for(lambda t: t.mode != "AUTO.LOITER", 8.0)
        acted_after = loop.time() - t0
        assert truth.mode == "AUTO.LAND"
        assert 4.0 <= acted_after <= 6.0, acted_after  # COM_FAIL_ACT_T = 5 s
        assert truth.altitude > 9.0  # it held its height during the wait
        await c.heartbeat(lambda m: m.custom_mode == AUTO_LAND, timeout=2.0)
    finally:
        await sim.stop()
        c.close()


async def test_px4_takeover_during_the_hold_cancels_the_failsafe_action() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -10.0))
    stream = Streamer(c, local_target(0.0, 0.0, -10.0))
    try:
        await _in_posctl(c)
        await asyncio.sleep(1.2)  # the setpoint stream is warm
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        since = c.mark()
        sim.inject_failsafe(Failsafe.BATTERY_CRITICAL)
        await c.heartbeat(lambda m: m.custom_mode == AUTO_LOITER, timeout=1.5)
        await asyncio.sleep(1.0)
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == \
            mav.MAV_RESULT_ACCEPTED
        await asyncio.sleep(max(0.0, t0 + 7.0 - loop.time()))  # well past the 5 s
        hbs = [m for _, m in c.log[since:] if m.get_type() == "HEARTBEAT"]
        assert all(m.custom_mode != AUTO_LAND for m in hbs)
        assert hbs[-1].custom_mode == OFFBOARD
        assert hbs[-1].system_status == mav.MAV_STATE_EMERGENCY  # still latched
        assert sim.truth.mode == "OFFBOARD" and sim.truth.altitude > 9.0
    finally:
        stream.cancel()
        await sim.stop()
        c.close()


async def test_px4_com_fail_act_t_is_a_parameter_and_delays_rc_loss_too() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -10.0))
    try:
        since = c.mark()
        c.send(mav.MAVLink_param_request_read_message(1, 1, b"COM_FAIL_ACT_T", -1))
        pv = await c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_FAIL_ACT_T", 2.0, since)
        assert pv.param_value == pytest.approx(5.0)
        since = c.mark()
        c.send(mav.MAVLink_param_set_message(1, 1, b"COM_FAIL_ACT_T", 1.0,
                                             mav.MAV_PARAM_TYPE_REAL32))
        pv = await c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_FAIL_ACT_T", 2.0, since)
        assert pv.param_value == pytest.approx(1.0)
        await _in_posctl(c)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        sim.inject_failsafe(Failsafe.RC_LOSS)
        assert sim.truth.mode == "AUTO.LOITER"
        truth = await sim.wait_for(lambda t: t.mode != "AUTO.LOITER", 3.0)
        assert truth.mode == "AUTO.LAND"
        assert 0.8 <= loop.time() - t0 <= 1.6
    finally:
        await sim.stop()
        c.close()


# ----- 5. disarmed by landing in any mode -----

async def test_px4_lands_in_offboard_disarms_and_the_heartbeat_stays_offboard() -> None:
    sim, c = await fly("px4", start=(0.0, 0.0, -4.0))
    stream = Streamer(c, local_target(0.0, 0.0, -4.0))
    try:
        await enter_offboard(c, stream)
        since = c.mark()
        stream.current = local_target(0.0, 0.0, 0.0)  # down to the ground
        landed = await sim.wait_for(lambda t: t.landed, 10.0)
        assert landed.armed and landed.mode == "OFFBOARD"
        loop = asyncio.get_running_loop()
        t_landed = loop.time()
        await sim.wait_for(lambda t: not t.armed, 3.5)
        assert 1.7 <= loop.time() - t_landed <= 2.6  # COM_DISARM_LAND = 2 s
        await c.wait("STATUSTEXT", lambda m: "Disarmed by landing" in m.text, 1.0, since)
        hb = await c.heartbeat(timeout=2.0)
        assert hb.custom_mode == OFFBOARD and not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        # The stream stops: disarmed, no offboard-loss failsafe, the mode stays OFFBOARD.
        stream.cancel()
        await asyncio.sleep(2.0)
        hb = await c.heartbeat(timeout=2.0)
        assert hb.custom_mode == OFFBOARD and not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status == mav.MAV_STATE_STANDBY
    finally:
        stream.cancel()
        await sim.stop()
        c.close()
