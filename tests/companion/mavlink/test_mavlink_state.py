"""Vehicle state: every telemetry message parsed over a real link; pose interpolation; staleness."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.landing import LandingConfig, LandingController, Phase, VehicleStatus
from companion.control.planner import PlannerConfig
from companion.control.trigger import Trigger, TriggerSource
from companion.geometry.geodesy import GeoPoint, geo_from_ned
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.state import VehicleState
from companion.pipeline.tracker import Track
from tests.mavpeer import MavPeer

HOME = GeoPoint(47.397742, 8.545594, 488.0)
ENC = m.MAVLink(None, 1, 1)


def gpi(t_ms: int, north: float, east: float, up: float):
    p = geo_from_ned(HOME, north, east, -up)
    return m.MAVLink_global_position_int_message(
        t_ms, round(p.lat_deg * 1e7), round(p.lon_deg * 1e7), round(p.alt_m * 1e3), round(up * 1e3), 100, -50, 0, 9000
    )


def home_msg():
    return m.MAVLink_home_position_message(
        round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7), round(HOME.alt_m * 1e3), 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
    )


def att(t_ms: int, roll: float, pitch: float, yaw: float):
    return m.MAVLink_attitude_message(t_ms, roll, pitch, yaw, 0, 0, 0)


def with_header(msg):
    """Give a locally built message the source ids a received one has."""
    msg.pack(ENC)
    return msg


async def test_every_message_type_is_parsed_into_the_state_over_the_link():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, heartbeat_period_s=0.1))
    await link.start()
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode=4)
    state = VehicleState()
    state.attach(link)
    try:
        await peer.connect_udp(link.local_address)
        peer.heartbeat()
        await link.wait_connected(2.0)
        peer.mav.send(home_msg())
        peer.mav.send(att(1000, 0.1, -0.05, 1.5))
        peer.mav.send(gpi(1000, 12.0, -7.0, 25.0))
        peer.mav.extended_sys_state_send(m.MAV_VTOL_STATE_UNDEFINED, m.MAV_LANDED_STATE_IN_AIR)
        peer.mav.sys_status_send(0, 0, 0, 500, 15800, 1200, 63, 0, 0, 0, 0, 0, 0)
        peer.mav.battery_status_send(
            0, 0, 0, 2500, [4000, 4000, 3900] + [65535] * 7, 1200, 100, 100, 40, 600, m.MAV_BATTERY_CHARGE_STATE_LOW
        )
        peer.mav.distance_sensor_send(1000, 20, 4000, 2480, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0)
        q = [math.cos(-math.pi / 4), 0.0, math.sin(-math.pi / 4), 0.0]  # pitched 90 deg down
        peer.mav.gimbal_device_attitude_status_send(1, 191, 1000, m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, q, 0, 0, 0, 0)
        for _ in range(200):
            if state.gimbal is not None:
                break
            await asyncio.sleep(0.01)
        assert state.heartbeat.custom_mode == 4 and state.armed is True
        assert state.heartbeat.system_status == m.MAV_STATE_ACTIVE
        assert state.home.point.lat_deg == pytest.approx(HOME.lat_deg, abs=1e-7)
        assert state.attitude.yaw == pytest.approx(1.5)
        assert state.position.relative_alt_m == pytest.approx(25.0)
        n, e, d = state.local_ned()
        assert (n, e, d) == pytest.approx((12.0, -7.0, -25.0), abs=0.02)
        assert state.altitude_above_home() == pytest.approx(25.0)
        assert state.landed.landed_state == m.MAV_LANDED_STATE_IN_AIR and not state.landed.on_ground
        assert state.sys_status_battery.remaining_pct == 63 and state.sys_status_battery.voltage_v == pytest.approx(15.8)
        assert state.battery_status.charge_state == m.MAV_BATTERY_CHARGE_STATE_LOW
        assert state.battery_status.remaining_pct == 40 and state.battery_status.voltage_v == pytest.approx(11.9)
        assert state.altitude_above_ground(state.rangefinder.t) == pytest.approx(24.8)
        assert state.gimbal.q == pytest.approx(tuple(q))
        for part in (state.heartbeat, state.home, state.attitude, state.position, state.landed, state.battery, state.gimbal):
            assert part.t > 0  # each has its monotonic receive time
    finally:
        await peer.close()
        await link.close()


def test_heartbeats_of_other_components_do_not_set_the_mode():
    state = VehicleState()
    cam = m.MAVLink(None, 1, 100)
    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_CAMERA, m.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    hb.pack(cam)
    state.update(hb, 1.0)
    assert state.heartbeat is None


def test_pose_interpolates_between_samples_and_wraps_yaw():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.0, 0.0, math.radians(170)), 10.0)
    s.update(att(100, 0.2, -0.1, math.radians(-170)), 10.1)
    s.update(gpi(0, 0.0, 0.0, 20.0), 10.0)
    s.update(gpi(100, 10.0, 4.0, 30.0), 10.1)
    pose = s.pose_at(10.05)
    assert pose is not None and pose.t == 10.05
    assert abs(abs(pose.yaw) - math.pi) < 0.01  # slerp: halfway from 170 to -170 deg is 180, not 0
    assert pose.roll == pytest.approx(0.1, abs=0.01) and pose.pitch == pytest.approx(-0.05, abs=0.01)
    assert (pose.north, pose.east, pose.down) == pytest.approx((5.0, 2.0, -25.0), abs=0.02)


def test_pose_is_none_outside_the_samples_across_gaps_and_without_home():
    s = VehicleState(max_gap_s=0.5, max_extrapolation_s=0.1)
    s.update(att(0, 0, 0, 0), 10.0)
    s.update(gpi(0, 0, 0, 20), 10.0)
    assert s.pose_at(10.0) is None  # no home yet: no world frame
    s.update(home_msg(), 10.0)
    assert s.pose_at(10.0) is not None
    assert s.pose_at(10.05) is not None  # small extrapolation allowance
    assert s.pose_at(10.2) is None  # too far past the newest sample
    assert s.pose_at(9.9) is None  # before the history
    s.update(att(2000, 0, 0, 0), 12.0)
    s.update(gpi(2000, 0, 0, 20), 12.0)
    assert s.pose_at(11.0) is None  # 2 s telemetry gap around t
    assert s.pose_at(float("nan")) is None


def test_fresh_only_with_recent_attitude_position_and_home():
    s = VehicleState()
    assert not s.is_fresh(10.0, 0.5)
    s.update(home_msg(), 9.0)
    s.update(att(0, 0, 0, 0), 10.0)
    s.update(gpi(0, 0, 0, 20), 10.0)
    assert s.is_fresh(10.3, 0.5)
    assert not s.is_fresh(10.6, 0.5)


def test_nan_and_out_of_range_values_are_counted_and_dropped():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0, 0, 0), 1.0)
    s.update(att(10, float("nan"), 0, 0), 1.01)
    assert s.attitude.t == 1.0 and s.rejected == 1
    bad = m.MAVLink_global_position_int_message(0, 95 * 10**7, 0, 0, 0, 0, 0, 0, 0)
    s.update(bad, 1.0)
    no_fix = m.MAVLink_global_position_int_message(0, 0, 0, 0, 0, 0, 0, 0, 0)
    s.update(no_fix, 1.0)
    s.update(m.MAVLink_home_position_message(0, 0, 0, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0), 1.0)
    q_bad = m.MAVLink_gimbal_device_attitude_status_message(1, 191, 0, 0, [float("nan"), 0, 0, 0], 0, 0, 0, 0)
    s.update(q_bad, 1.0)
    assert s.position is None and s.gimbal is None and s.home.point.lat_deg == pytest.approx(HOME.lat_deg)
    assert s.rejected == 5


def test_rangefinder_out_of_range_or_not_downward_gives_no_height():
    s = VehicleState()
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 5000, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0), 1.0)
    assert s.altitude_above_ground(1.0) is None
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 300, 0, 0, m.MAV_SENSOR_ROTATION_NONE, 0), 1.0)
    assert s.altitude_above_ground(1.0) is None
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 300, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0), 1.0)
    assert s.altitude_above_ground(1.2) == pytest.approx(3.0)
    assert s.altitude_above_ground(2.0) is None  # stale


def test_gimbal_pointing_down_gives_the_camera_rotation_in_the_body_frame():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.0, 0.0, 1.0), 1.0)
    s.update(gpi(0, 0, 0, 20), 1.0)
    half = -math.pi / 4  # pitch -90 deg about the camera's right axis
    for flags in (m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME):
        yaw_half = 0.0 if flags == m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME else 0.5  # earth: yaw 1 rad too
        qz = [math.cos(yaw_half), 0, 0, math.sin(yaw_half)]
        qy = [math.cos(half), 0, math.sin(half), 0]
        w1, x1, y1, z1 = qz
        w2, x2, y2, z2 = qy
        q = [w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
             w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]
        s.update(m.MAVLink_gimbal_device_attitude_status_message(1, 191, 0, flags, q, 0, 0, 0, 0), 1.0)
        pose = s.pose_at(1.0)
        # The camera's forward axis points straight down in the body frame of a level vehicle.
        assert pose.gimbal @ np.array([1.0, 0, 0]) == pytest.approx([0, 0, 1], abs=1e-9)


def test_finite_but_absurd_telemetry_is_counted_and_dropped():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.1, -0.2, 3.0), 1.0)
    s.update(gpi(0, 5.0, 5.0, 20.0), 1.0)
    good_att, good_pos = s.attitude, s.position
    s.update(att(10, 1e30, 0, 0), 1.01)           # roll 1e30 rad
    s.update(att(20, 0, 2.0, 0), 1.02)            # pitch past the vertical
    huge = m.MAVLink_global_position_int_message(0, 473977420, 85455940, 488000, 2_147_000_000, 0, 0, 0, 0)
    s.update(huge, 1.03)                          # 2,147 km above home
    fast = m.MAVLink_global_position_int_message(0, 473977420, 85455940, 508000, 20000, 32000, 0, 0, 0)
    s.update(fast, 1.04)                          # 320 m/s
    assert s.rejected == 4
    assert s.attitude is good_att and s.position is good_pos
    pose = s.pose_at(1.0)
    assert pose is not None and pose.roll == pytest.approx(0.1) and -pose.down == pytest.approx(20.0, abs=0.01)


async def test_a_late_time_boot_ms_sample_is_rejected_over_a_real_link():
    """Issue 12, item 1: a packet held 3 s (a stalled link, a buffer) must not become the pose."""
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, heartbeat_period_s=0.1))
    await link.start()
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode=4)
    state = VehicleState()
    state.attach(link)
    boot0 = time.monotonic()

    def boot_ms() -> int:
        return int((time.monotonic() - boot0) * 1000) + 1000

    async def until(pred) -> None:
        for _ in range(200):
            if pred():
                return
            await asyncio.sleep(0.01)
        raise AssertionError("condition not reached")

    try:
        await peer.connect_udp(link.local_address)
        peer.heartbeat()
        await link.wait_connected(2.0)
        peer.mav.send(home_msg())
        for _ in range(10):  # live telemetry at 25 Hz: the clock learns the offset
            peer.mav.send(gpi(boot_ms(), 0.0, 0.0, 20.0))
            peer.mav.send(att(boot_ms(), 0.0, 0.0, 0.0))
            await asyncio.sleep(0.04)
        await until(lambda: state.clock.stats.stamped >= 20)
        good = state.position
        sampled = boot_ms()
        await asyncio.sleep(1.5)  # the sample waits in a buffer
        peer.mav.send(gpi(sampled, 50.0, 0.0, 20.0))  # where the vehicle was 1.5 s ago, 50 m off
        peer.mav.send(gpi(sampled - 500, 50.0, 0.0, 20.0))  # and one older than the last: backwards
        await until(lambda: state.rejected >= 2)
        assert state.position is good
        assert state.clock.stats.late == 1 and state.clock.stats.backwards == 1
        now_ms = boot_ms()
        peer.mav.send(gpi(now_ms, 1.0, 0.0, 20.0))  # the live stream goes on and is taken
        await until(lambda: state.position is not good)
        assert state.position.time_boot_ms == now_ms
    finally:
        await peer.close()
        await link.close()


def test_a_held_pose_reports_its_true_age_and_the_controller_refuses_it():
    """pose_at used to hold the last sample and label it with the time asked for, so the
    controller's pose-age check could never reject anything (1.26 m off at 5 m/s)."""
    s = VehicleState(max_extrapolation_s=0.5)
    s.update(home_msg(), 0.0)
    for k in range(5):  # telemetry up to t = 10.4, moving north at 5 m/s
        s.update(att(10_000 + 100 * k, 0, 0, 0), 10.0 + 0.1 * k)
        s.update(gpi(10_000 + 100 * k, 0.5 * k, 0.0, 20.0), 10.0 + 0.1 * k)
    fresh = s.pose_at(10.35)
    held = s.pose_at(10.7)  # 0.3 s past the newest sample: held, not invented
    assert fresh.t == pytest.approx(10.35) and fresh.north == pytest.approx(1.75, abs=0.01)
    assert held.t == pytest.approx(10.4) and held.north == pytest.approx(2.0, abs=0.01)
    assert s.covers(10.35) and not s.covers(10.7)
    ctl = LandingController(LandingConfig(max_pose_age_s=0.25, planner=PlannerConfig(
        min_track_age_s=1.0, min_track_hits=3, zone_max_age_s=1.0)))
    ctl.on_state(VehicleStatus(10.4, 2.0, 0.0, -20.0, HOME, mode="LOITER"))
    ctl.on_trigger(Trigger("battery critical", TriggerSource.BATTERY, 10.7))
    zone = Track(id=3, x=12.0, y=1.0, r=5.0, r_filtered=5.0, age=30, hits=30, misses=0, born_t=5.0, last_t=10.7)
    assert ctl.on_frame(10.7, [zone], held) == []  # 0.3 s old: no decision on it
    assert ctl.phase is Phase.SELECT
    fresh_now = dataclasses.replace(held, t=10.7)
    assert [type(c).__name__ for c in ctl.on_frame(10.7, [zone], fresh_now)] == ["Goto"]


def test_an_implausible_home_altitude_or_rangefinder_is_counted_and_dropped():
    """Issue 61, item 10: HOME_POSITION's altitude and DISTANCE_SENSOR were not range-checked."""
    s = VehicleState()
    s.update(home_msg(), 0.0)
    good_home = s.home
    high = m.MAVLink_home_position_message(round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7),
                                           2_000_000_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)  # 2,000 km
    s.update(with_header(high), 1.0)
    assert s.rejected == 1 and s.home is good_home
    down = m.MAV_SENSOR_ROTATION_PITCH_270
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 300, 0, 0, down, 0), 1.0)
    for bad in (m.MAVLink_distance_sensor_message(0, 20, 65535, 60000, 0, 0, down, 0),  # 600 m
                m.MAVLink_distance_sensor_message(0, 4000, 20, 300, 0, 0, down, 0),     # min above max
                m.MAVLink_distance_sensor_message(0, 20, 20, 20, 0, 0, down, 0)):       # an empty range
        s.update(bad, 1.1)
    assert s.rejected == 4
    assert s.altitude_above_ground(1.2) == pytest.approx(3.0)  # the last plausible reading, aged as before


def test_replays_rangefinder_rule_refuses_what_the_live_state_refuses() -> None:
    """``downward_range_m`` is the rule replay reads recorded DISTANCE_SENSORs with: a range that is
    empty or beyond any rangefinder's gives no height, as the live state drops such a message."""
    from companion.mavlink.state import MAX_RANGEFINDER_CM, downward_range_m
    assert downward_range_m(350, 20, 4000) == 3.5
    assert downward_range_m(10, 20, 4000) is None  # below the sensor's own minimum
    assert downward_range_m(350, 4000, 4000) is None  # an empty range
    assert downward_range_m(350, 20, MAX_RANGEFINDER_CM + 1) is None  # no rangefinder's range
    assert downward_range_m(MAX_RANGEFINDER_CM + 1, 0, MAX_RANGEFINDER_CM + 1) is None
